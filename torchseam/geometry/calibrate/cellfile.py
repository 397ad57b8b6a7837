"""A calibration's result written into a cell config: only the calibrated section changes.

``torchseam calibrate`` writes each procedure's result (a camera, a laser plane, a hand-eye or a
tool pose) into a copy of the cell config. The file is a person's: its comments and the other
sections are kept, values are rounded far below their uncertainty, and the new config must load
back through core's parser before it counts as written (:func:`update_cell`).
"""

from __future__ import annotations

import math
import re
from pathlib import Path
from typing import Any

from torchseam.core.config import (
    CellConfig,
    ConfigError,
    from_dict,
    load_cell,
    save_config,
    to_dict,
)

__all__ = ["splice_section", "update_cell"]

#: Digits kept when a calibrated value is written (far below each one's uncertainty).
_DIGITS = {"fx": 4, "fy": 4, "cx": 4, "cy": 4, "dist": 8, "normal": 9, "distance_mm": 6,
           "source_mm": 6, "position_mm": 4, "quaternion": 9}


def _round(section: str, data: dict[str, Any]) -> dict[str, Any]:
    out = {}
    for k, v in data.items():
        nd = _DIGITS.get(k)
        if nd is None:
            out[k] = v
        elif isinstance(v, list):
            out[k] = [round(float(x), nd) + 0.0 for x in v]
        else:
            out[k] = round(float(v), nd) + 0.0
    return out


def _yaml_value(v: Any) -> str:
    if isinstance(v, list):
        return "[" + ", ".join(_yaml_value(x) for x in v) + "]"
    if isinstance(v, str) and re.fullmatch(r"[A-Za-z_][A-Za-z0-9_-]*", v):
        return v  # a setting's name (camera.stripe_axis: auto)
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise TypeError(f"cannot write {v!r}")  # programming error: sections hold numbers
    text = repr(v)
    if "e" in text and "." not in text:  # YAML 1.1 reads 1e-06 as a string, 1.0e-06 as a float
        text = text.replace("e", ".0e")
    return text


def splice_section(text: str, section: str, data: dict[str, Any], note: str) -> str | None:
    """Replace the values of a top-level section of a YAML file in place.

    Keeps every comment and every other line; a ``# calibrated: ...`` line right under the
    section's key is replaced by ``note``. Returns None when a field is not a one-line value
    in ``text`` (the caller then writes the whole file anew).
    """
    lines = text.splitlines(keepends=True)
    head = next((i for i, ln in enumerate(lines) if re.match(rf"{section}\s*:\s*(#.*)?$", ln)),
                None)
    if head is None:
        return None
    end = next((i for i in range(head + 1, len(lines)) if re.match(r"[A-Za-z_]", lines[i])),
               len(lines))
    for key, val in data.items():
        pat = re.compile(rf"^(\s+){re.escape(key)}\s*:\s*([^#\s][^#]*?)\s*(#.*)?$")
        hit = [i for i in range(head + 1, end) if pat.match(lines[i].rstrip("\n"))]
        if len(hit) != 1:
            return None
        m = pat.match(lines[hit[0]].rstrip("\n"))
        assert m is not None
        comment = f"  {m.group(3)}" if m.group(3) else ""
        lines[hit[0]] = f"{m.group(1)}{key}: {_yaml_value(val)}{comment}\n"
    body = [re.match(r"(\s+)\S", lines[i]) for i in range(head + 1, end)]
    indent = next((m.group(1) for m in body if m), "  ")
    if head + 1 < len(lines) and lines[head + 1].strip().startswith("# calibrated:"):
        lines[head + 1] = f"{indent}# {note}\n"
    else:
        lines.insert(head + 1, f"{indent}# {note}\n")
    return "".join(lines)


def _same(a: Any, b: Any) -> bool:
    """Two configs' trees (:func:`to_dict`) equal, floats to 1e-12 relative: a unit vector is
    normalised again when its file is read, which may move its last bits."""
    if isinstance(a, dict) and isinstance(b, dict):
        return a.keys() == b.keys() and all(_same(a[k], b[k]) for k in a)
    if isinstance(a, (list, tuple)) and isinstance(b, (list, tuple)):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b, strict=True))
    if isinstance(a, float) or isinstance(b, float):
        return (not isinstance(a, bool) and not isinstance(b, bool)
                and isinstance(a, (int, float)) and isinstance(b, (int, float))
                and math.isclose(a, b, rel_tol=1e-12, abs_tol=1e-12))
    return bool(a == b)


def update_cell(cell_path: Path, out: Path, section: str, value: Any, note: str
                ) -> tuple[CellConfig, bool]:
    """Write ``cell_path``'s config with ``section`` replaced by ``value`` to ``out``.

    The new config is validated by core's parser first (an invalid result is a
    :class:`ConfigError` naming the field). The file's text is kept, comments included, with
    only the section's values changed; if the file's layout does not allow that, the whole
    config is written with :func:`save_config`.

    Returns:
        ``(the written CellConfig, whether the file's text and comments were kept)``; the
        config loads back equal with ``load_cell(out)``.
    """
    base = load_cell(cell_path)
    data = to_dict(base)
    data[section] = _round(section, to_dict(value))
    new = from_dict(CellConfig, data, source=f"{out} (calibrated {section})")
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    text = splice_section(Path(cell_path).read_text(), section, data[section], note)
    if text is not None:
        out.write_text(text)
        try:
            back = load_cell(out)
            if _same(to_dict(back), to_dict(new)):
                return back, True
        except ConfigError:
            pass
    save_config(new, out)
    return new, False
