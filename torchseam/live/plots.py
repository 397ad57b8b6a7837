"""Figures like the paper's: quaternions along each segment, errors, the 3D seam.

Every per-frame figure can mark where one segment ends and the next begins and where the arc
is off (the approach to each segment's start, and any interruption). The arc-off frames are
not welding: the torch moves towards the seam from its stand-off, so its error there is the
remaining approach distance, not a tracking error, and the summary leaves them out. Given
which frames those are, :func:`series_plot` draws the welding frames on a scale of their own
and the whole run, approach included, below, so the plot and the summary agree.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import matplotlib

matplotlib.use("Agg")  # files only: no display in a weld cell's cabinet PC service
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

ARC_OFF_COLOUR = "0.85"   # shading of arc-off spans
BOUNDARY_COLOUR = "0.35"  # segment boundaries


def _spans(mask: np.ndarray) -> list[tuple[int, int]]:
    """[start, stop) index ranges where the boolean ``mask`` is True."""
    m = np.concatenate([[False], np.asarray(mask, dtype=bool), [False]])
    edges = np.flatnonzero(np.diff(m.astype(np.int8)))
    return list(zip(edges[::2].tolist(), edges[1::2].tolist(), strict=True))


def _mark_frames(ax, n: int, segments: Sequence[str] | None, arc_on: np.ndarray | None,
                 x: np.ndarray | None = None, names: bool = True) -> None:
    """Shade arc-off spans and draw a line at each change of segment (labelled at the top)."""
    xs = np.arange(n, dtype=float) if x is None else np.asarray(x, dtype=float)
    step = float(np.median(np.diff(xs))) if n > 1 else 1.0
    if arc_on is not None and n:
        for k, (a, b) in enumerate(_spans(~np.asarray(arc_on, dtype=bool)[:n])):
            ax.axvspan(xs[a] - step / 2, xs[b - 1] + step / 2, color=ARC_OFF_COLOUR, lw=0,
                       zorder=0, label="arc off (approach)" if k == 0 else None)
    if segments is not None and n:
        seg = list(segments)[:n]
        starts = [0] + [i for i in range(1, len(seg)) if seg[i] != seg[i - 1]]
        for k, i in enumerate(starts):
            if i:
                ax.axvline(xs[i] - step / 2, color=BOUNDARY_COLOUR, lw=0.8, ls="--",
                           label="segment start" if k == 1 else None)
            if names:
                ax.text(xs[i], 0.97, f" {seg[i]}", transform=ax.get_xaxis_transform(),
                        va="top", ha="left", fontsize=8, fontweight="bold",
                        color=BOUNDARY_COLOUR)


def quaternion_plot(segments: list[tuple[str, np.ndarray]], path: Path,
                    approach: dict[str, np.ndarray] | None = None,
                    step_mm: float = 2.0) -> Path:
    """q1..q4 (w, x, y, z) along each segment, one panel per segment (paper Fig. 24), each
    with its legend. ``approach``: per segment name, a boolean per pose, True where the pose
    was sent with the arc off (shaded); ``step_mm``: path length between poses."""
    n = max(1, len(segments))
    fig, axes = plt.subplots(1, n, figsize=(3.2 * n, 3.2), sharey=True, squeeze=False)
    for ax, (name, q) in zip(axes[0], segments, strict=False):
        q = np.asarray(q, dtype=float).reshape(-1, 4)  # a segment with no pose welded: (0, 4)
        x = np.arange(len(q)) * step_mm
        mask = None if approach is None else approach.get(name)
        if mask is not None and len(q):
            _mark_frames(ax, len(q), None, ~np.asarray(mask, dtype=bool)[:len(q)], x=x)
        for i, lab in enumerate(("q1 (w)", "q2 (x)", "q3 (y)", "q4 (z)")):
            ax.plot(x, q[:, i], label=lab, lw=1.2)
        if not len(q):
            ax.text(0.5, 0.5, "no pose welded", ha="center", va="center",
                    transform=ax.transAxes)
        ax.set_title(f"segment {name}")
        ax.set_xlabel("path (mm)")
        ax.grid(alpha=0.3)
        if len(q):
            ax.legend(fontsize=6, loc="best")
    axes[0][0].set_ylabel("quaternion")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def _robust_limits(values: list[np.ndarray]) -> tuple[float, float] | None:
    y = (np.concatenate([np.asarray(v, dtype=float).ravel() for v in values]) if values
         else np.zeros(0))
    y = y[np.isfinite(y)]
    if not len(y):
        return None
    lo, hi = float(y.min()), float(y.max())
    pad = 0.08 * (hi - lo) if hi > lo else max(abs(hi), 1e-3) * 0.5
    return lo - pad, hi + pad


def series_plot(series: dict[str, np.ndarray], ylabel: str, path: Path, xlabel: str = "frame",
                segments: Sequence[str] | None = None, arc_on: Sequence[bool] | None = None
                ) -> Path:
    """Several 1-D series on one axis (errors along the weld).

    ``segments``: the segment name per sample (a dashed line where it changes, the name at
    the top); ``arc_on``: True per sample while welding. With ``arc_on`` holding any False,
    two panels: the welding samples on their own scale (what the summary figures count), and
    every sample with the arc-off spans shaded (the approach's error is the distance still to
    go). Without either, one panel as before."""
    n = max((len(np.asarray(y)) for y in series.values()), default=0)
    on = None if arc_on is None else np.asarray(arc_on, dtype=bool)[:n]
    split = on is not None and len(on) == n and n > 0 and not on.all() and on.any()
    fig, axes = plt.subplots(2 if split else 1, 1, figsize=(8, 5.2 if split else 3),
                             sharex=True, squeeze=False,
                             gridspec_kw={"height_ratios": [3, 2]} if split else None)
    # each panel with the arc-on mask it keeps to (None: every sample)
    panels = [(axes[0][0], on), (axes[1][0], None)] if split else [(axes[0][0], None)]
    for ax, welding in panels:
        _mark_frames(ax, n, segments, on, names=ax is axes[0][0])
        for name, y in series.items():
            y = np.asarray(y, dtype=float)
            if welding is not None:
                y = np.where(welding[:len(y)], y, np.nan)
            ax.plot(y, lw=0.9, label=name)
        if welding is not None:
            lim = _robust_limits([np.asarray(y, dtype=float)[welding[:len(y)]]
                                  for y in series.values()])
            if lim is not None:
                ax.set_ylim(*lim)
            ax.set_title("arc on (welding): the frames the summary counts", fontsize=8,
                         loc="left")
        elif split:
            ax.set_title("every frame, the approach (arc off) included", fontsize=8, loc="left")
        ax.set_ylabel(ylabel)
        ax.grid(alpha=0.3)
        # above the axes, right of the title: the data and the segment names stay clear
        ax.legend(fontsize=7, loc="lower right", bbox_to_anchor=(1.0, 1.0), ncol=4,
                  frameon=False, borderaxespad=0.2)
    axes[-1][0].set_xlabel(xlabel)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def _equal_axes(ax, pts: np.ndarray) -> None:
    """One mm the same length along x, y and z: a cube around the points."""
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    c, r = (lo + hi) / 2, max(float((hi - lo).max()) / 2, 1.0) * 1.05
    ax.set_xlim(c[0] - r, c[0] + r)
    ax.set_ylim(c[1] - r, c[1] + r)
    ax.set_zlim(c[2] - r, c[2] + r)
    ax.set_box_aspect((1, 1, 1))


def seam_3d_plot(paths: dict[str, list[np.ndarray]], path: Path,
                 segment_names: Sequence[str] | None = None,
                 approach: dict[str, list[np.ndarray]] | None = None) -> Path:
    """3D polylines (true seam, nominal path, tracked path), mm; each a list of (N, 3) pieces,
    one per segment. One view per segment (the part turns between segments), with equal axis
    scales and its own legend. ``segment_names``: the name of each piece's segment (default
    1, 2, ...); ``approach``: per path, per piece, a boolean per point, True where it was sent
    with the arc off: drawn dotted in grey apart from the welded line."""
    n = max((len(v) for v in paths.values()), default=0)
    names = list(segment_names) if segment_names is not None else [str(i + 1) for i in range(n)]
    cols = min(3, max(1, n))
    rows = max(1, -(-n // cols))
    fig = plt.figure(figsize=(4.2 * cols, 4.0 * rows))
    for s in range(max(1, n)):
        ax = fig.add_subplot(rows, cols, s + 1, projection="3d")
        pts, handles = [], {}
        # drawn last to first, so the first path (the tracked one, within hundredths of a mm of
        # the true seam) lies on top, thinner than the ones under it; legend in the given order
        items = list(enumerate(paths.items()))
        for k, (name, pieces) in reversed(items):
            P = np.asarray(pieces[s], dtype=float).reshape(-1, 3) if s < len(pieces) else None
            if P is None or not len(P):
                continue
            lw = 1.0 + 1.2 * k / max(1, len(items) - 1)
            mask = None
            if approach is not None and name in approach and s < len(approach[name]):
                mask = np.asarray(approach[name][s], dtype=bool)[:len(P)]
            if mask is not None and mask.any():
                W = np.where(mask[:, None], np.nan, P)
                A = np.where(mask[:, None], P, np.nan)
                handles[(k, 1)] = ax.plot(A[:, 0], A[:, 1], A[:, 2], lw=0.8, ls=":", color="0.4",
                                          label=f"{name}: approach (arc off)")[0]
                P_weld = W
            else:
                P_weld = P
            handles[(k, 0)] = ax.plot(P_weld[:, 0], P_weld[:, 1], P_weld[:, 2], lw=lw,
                                      color=f"C{k}", label=name)[0]
            pts.append(P)
        if pts:
            _equal_axes(ax, np.concatenate(pts))
            ax.legend(handles=[handles[key] for key in sorted(handles)], fontsize=6,
                      loc="upper left")
        else:
            ax.text2D(0.5, 0.5, "nothing welded", ha="center", transform=ax.transAxes)
        ax.set_title(f"segment {names[s]}" if s < len(names) else "", fontsize=9)
        ax.set_xlabel("x (mm)", fontsize=7)
        ax.set_ylabel("y (mm)", fontsize=7)
        ax.set_zlabel("z (mm)", fontsize=7)
        ax.tick_params(labelsize=6)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
