"""Plain-text tables and summary statistics for the CLI and the benchmarks."""

from __future__ import annotations

import contextlib
import json
import math
import os
import sys
import time
from collections.abc import Iterator, Sequence
from pathlib import Path

import numpy as np

from torchseam.core.errors import TorchseamError


class ReportError(TorchseamError):
    """A report cannot be written (its folder, a full disk, a permission)."""


#: the file that says a report folder's run has not finished: written when the run starts,
#: removed once its summary.json is written (a folder holding it and no summary.json is a run
#: that was killed, or whose report could not be written)
RUN_MARKER = "RUNNING"


@contextlib.contextmanager
def report_file(path: Path) -> Iterator[Path]:
    """Write ``path`` in the block: an :class:`OSError` there (a full disk, a permission)
    becomes a :class:`ReportError` naming ``path`` and the error, one line."""
    try:
        yield Path(path)
    except OSError as e:
        raise ReportError(f"{path}: cannot write the report ({e.strerror or e})") from None


def write_run_marker(out: Path, command: str) -> Path:
    """The :data:`RUN_MARKER` of a run that starts writing into ``out``: when, which process,
    and that summary.json comes at the end. A :class:`ReportError` when it cannot be written."""
    path = Path(out) / RUN_MARKER
    with report_file(path):
        path.write_text(
            f"{command}: running since {time.strftime('%Y-%m-%d %H:%M:%S %z')}, pid "
            f"{os.getpid()}. summary.json is written when the run ends and this file is then "
            "removed; a folder with this file and no summary.json holds a run that did not "
            "finish (killed, or its report could not be written).\n")
    return path


def format_table(headers: Sequence[str], rows: Sequence[Sequence[object]]) -> str:
    """Align ``rows`` under ``headers``; floats get 3 significant decimals."""
    def cell(x: object) -> str:
        if isinstance(x, float | np.floating):
            v = float(x)
            return "nan" if not np.isfinite(v) else f"{v:.3f}" if abs(v) < 1000 else f"{v:.0f}"
        return str(x)

    body = [[cell(x) for x in r] for r in rows]
    widths = [max(len(h), *(len(r[i]) for r in body)) if body else len(h)
              for i, h in enumerate(headers)]
    line = "  ".join(h.ljust(w) for h, w in zip(headers, widths, strict=True))
    out = [line, "  ".join("-" * w for w in widths)]
    out += ["  ".join(c.rjust(w) for c, w in zip(r, widths, strict=True)) for r in body]
    return "\n".join(out)


def error_stats(err_px: np.ndarray, lost_px: float = 15.0) -> dict[str, float]:
    """RMSE, max, % > 5 px and % lost (> ``lost_px``) of per-frame errors (NaN = no output)."""
    err = np.asarray(err_px, dtype=float)
    ok = np.isfinite(err)
    e = err[ok]
    return {
        "n": int(len(err)),
        "rmse": float(np.sqrt(np.mean(e**2))) if len(e) else float("nan"),
        "max": float(e.max()) if len(e) else float("nan"),
        "pct_gt5": float(100.0 * np.mean(e > 5.0)) if len(e) else float("nan"),
        "pct_lost": float(100.0 * (np.sum(e > lost_px) + np.sum(~ok)) / max(len(err), 1)),
        "pct_none": float(100.0 * np.mean(~ok)) if len(err) else float("nan"),
    }


def percentiles_ms(seconds: Sequence[float]) -> tuple[float, float]:
    """(p50, p99) in milliseconds."""
    t = np.asarray(seconds) * 1000.0
    return float(np.percentile(t, 50)), float(np.percentile(t, 99))


def write_json_atomic(path: Path, data: object) -> Path:
    """Write ``data`` as JSON to ``path`` atomically (a temporary file in the same folder, then
    a rename): a reader sees the old file or the whole new one, never half of it. NaN becomes
    null (JSON has no NaN)."""
    def clean(x: object) -> object:
        if isinstance(x, float) and not math.isfinite(x):
            return None
        if isinstance(x, dict):
            return {k: clean(v) for k, v in x.items()}
        if isinstance(x, (list, tuple)):
            return [clean(v) for v in x]
        return x

    tmp = path.with_name(f".{path.name}.tmp")
    try:
        tmp.write_text(json.dumps(clean(data), indent=1))
        os.replace(tmp, path)
    except OSError as e:
        with contextlib.suppress(OSError):
            tmp.unlink(missing_ok=True)  # no half-written file left behind
        raise ReportError(f"{path}: cannot write the report ({e.strerror or e})") from None
    return path


def prepare_out_dir(out: Path, command: str) -> Path:
    """The run's report folder, never mixing two runs: created when missing; a folder that
    holds an earlier run's files is moved aside to ``OUT.previous-N`` (said on stderr) and a
    new empty one made. An ``out`` that is a file, or cannot be made, is a :class:`ReportError`
    naming it."""
    out = Path(out)
    try:
        if out.exists() and not out.is_dir():
            raise ReportError(f"{out}: --out is a file, not a folder")
        if out.is_dir() and any(out.iterdir()):
            n = 1
            while out.with_name(f"{out.name}.previous-{n}").exists():
                n += 1
            aside = out.with_name(f"{out.name}.previous-{n}")
            out.rename(aside)
            print(f"{command}: {out} held an earlier run's report: moved to {aside}",
                  file=sys.stderr)
        out.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise ReportError(f"{out}: cannot make the report folder ({e.strerror or e})") from None
    return out
