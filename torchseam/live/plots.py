"""Figures like the paper's: quaternions along each segment, errors, the 3D seam."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")  # files only: no display in a weld cell's cabinet PC service
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402


def quaternion_plot(segments: list[tuple[str, np.ndarray]], path: Path) -> Path:
    """q1..q4 (w, x, y, z) along each segment, one panel per segment (paper Fig. 24)."""
    n = max(1, len(segments))
    fig, axes = plt.subplots(1, n, figsize=(3.2 * n, 3.0), sharey=True, squeeze=False)
    for ax, (name, q) in zip(axes[0], segments, strict=True):
        q = np.asarray(q, dtype=float).reshape(-1, 4)  # a segment with no pose welded: (0, 4)
        for i, lab in enumerate(("q1 (w)", "q2 (x)", "q3 (y)", "q4 (z)")):
            ax.plot(np.arange(len(q)) * 2.0, q[:, i], label=lab, lw=1.2)
        if not len(q):
            ax.text(0.5, 0.5, "no pose welded", ha="center", va="center",
                    transform=ax.transAxes)
        ax.set_title(f"segment {name}")
        ax.set_xlabel("path (mm)")
        ax.grid(alpha=0.3)
    axes[0][0].set_ylabel("quaternion")
    axes[0][-1].legend(fontsize=7, loc="best")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def series_plot(series: dict[str, np.ndarray], ylabel: str, path: Path, xlabel: str = "frame"
                ) -> Path:
    """Several 1-D series on one axis (errors along the weld)."""
    fig, ax = plt.subplots(figsize=(8, 3))
    for name, y in series.items():
        ax.plot(y, lw=0.9, label=name)
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def seam_3d_plot(paths: dict[str, list[np.ndarray]], path: Path) -> Path:
    """3D polylines (true seam, nominal path, tracked path), mm; each a list of (N, 3) pieces
    (one per segment: drawn apart, the part turns between segments)."""
    fig = plt.figure(figsize=(6, 5))
    ax = fig.add_subplot(projection="3d")
    for k, (name, pieces) in enumerate(paths.items()):
        for i, P in enumerate(p for p in pieces if len(p)):
            ax.plot(P[:, 0], P[:, 1], P[:, 2], lw=1.0, color=f"C{k}",
                    label=name if i == 0 else None)
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("y (mm)")
    ax.set_zlabel("z (mm)")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
