"""Plain-text tables and summary statistics for the CLI and the benchmarks."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np


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
