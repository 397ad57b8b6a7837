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

import yaml

from torchseam.core.config import (
    CellConfig,
    ConfigError,
    from_dict,
    read_yaml,
    save_config,
    to_dict,
)

__all__ = ["dump_config_yaml", "load_calibrated_cell", "splice_section", "update_cell"]

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


def _block(lines: list[str], key: str, lo: int, hi: int, indent: str) -> tuple[int, int] | None:
    """The lines ``[head, end)`` of the mapping ``key`` written at ``indent`` within
    ``lines[lo:hi]`` (its head line and everything indented deeper after it)."""
    head = next((i for i in range(lo, hi)
                 if re.match(rf"{indent}{key}\s*:\s*(#.*)?$", lines[i].rstrip("\n"))), None)
    if head is None:
        return None
    deeper = re.compile(rf"{indent}\s+\S|\s*(#.*)?$")  # an indented line, a blank or a comment
    end = next((i for i in range(head + 1, hi) if not deeper.match(lines[i].rstrip("\n"))), hi)
    return head, end


def splice_section(text: str, section: str, data: dict[str, Any], note: str,
                   parent: str | None = None) -> str | None:
    """Replace the values of a top-level section of a YAML file in place (or of a section
    of the top-level mapping ``parent``: a cell file's ``calibration``).

    Keeps every comment and every other line; a ``# calibrated: ...`` line right under the
    section's key is replaced by ``note``. Returns None when a field is not a one-line value
    in ``text`` (the caller then writes the whole file anew).
    """
    lines = text.splitlines(keepends=True)
    found = _block(lines, section, 0, len(lines), "")
    if parent is not None:
        outer = _block(lines, parent, 0, len(lines), "")
        inner = None
        if outer is not None:
            m = next((re.match(r"(\s+)\S", lines[i]) for i in range(outer[0] + 1, outer[1])
                      if re.match(r"\s+[^#\s]", lines[i])), None)
            inner = _block(lines, section, outer[0] + 1, outer[1], m.group(1)) if m else None
        found = inner
    if found is None:
        return None
    head, end = found
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


class _ListsOnOneLine(yaml.SafeDumper):
    """YAML with mappings as blocks and lists on one line (``dist: [k1, k2, ...]``): the
    layout :func:`splice_section` rewrites in place."""


_ListsOnOneLine.add_representer(
    list, lambda d, v: d.represent_sequence("tag:yaml.org,2002:seq", v, flow_style=True))


def dump_config_yaml(data: Any) -> str:
    """``data`` (a config's :func:`to_dict`) as YAML: mappings as blocks, lists on one line,
    keys in their order."""
    return yaml.dump(data, Dumper=_ListsOnOneLine, sort_keys=False)


#: the key under which a cell file (``torchseam weld --cell``) holds the sensor's calibration
CELL_FILE_KEY = "calibration"


def _is_cell_file(raw: Any) -> bool:
    return isinstance(raw, dict) and isinstance(raw.get(CELL_FILE_KEY), dict)


def load_calibrated_cell(path: str | Path) -> CellConfig:
    """The sensor's calibration from ``path``: a calibration file (the fields of
    ``configs/cell.yaml``) or a cell file (``weld --cell``), which holds them under
    ``calibration:``. A bad field is a :class:`ConfigError` naming the file and the field."""
    raw = read_yaml(Path(path))
    if _is_cell_file(raw):
        return from_dict(CellConfig, raw[CELL_FILE_KEY], source=f"{path}: {CELL_FILE_KEY}")
    return from_dict(CellConfig, raw, source=str(path))


def update_cell(cell_path: Path, out: Path, section: str, value: Any, note: str
                ) -> tuple[CellConfig, bool]:
    """Write ``cell_path``'s config with ``section`` replaced by ``value`` to ``out``.

    ``cell_path`` is a calibration file (the fields of ``configs/cell.yaml``) or a cell file
    (``weld --cell``: the calibration under ``calibration:``, whose other sections, the camera
    and the controller links, are kept as they are). The new config is validated by core's
    parser first (an invalid result is a :class:`ConfigError` naming the field). The file's
    text is kept, comments included, with only the section's values changed; if the file's
    layout does not allow that, the whole file is written anew.

    Returns:
        ``(the written CellConfig, whether the file's text and comments were kept)``; the
        config loads back equal with :func:`load_calibrated_cell`.
    """
    raw = read_yaml(Path(cell_path))
    nested = _is_cell_file(raw)
    base = load_calibrated_cell(cell_path)
    data = to_dict(base)
    data[section] = _round(section, to_dict(value))
    new = from_dict(CellConfig, data, source=f"{out} (calibrated {section})")
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    text = splice_section(Path(cell_path).read_text(), section, data[section], note,
                          parent=CELL_FILE_KEY if nested else None)
    if text is not None:
        out.write_text(text)
        try:
            back = load_calibrated_cell(out)
            if _same(to_dict(back), to_dict(new)):
                return back, True
        except ConfigError:
            pass
    if nested:
        raw[CELL_FILE_KEY] = to_dict(new)
        out.write_text(dump_config_yaml(raw))
    else:
        save_config(new, out)
    return new, False
