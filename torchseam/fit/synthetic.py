"""Synthetic labelled sequences with a *known* motion model, for tests and timing.

The feature point follows the EAKF's own model (METHOD.md section 3, eq. 12 and 16) with a
chosen acceleration colour ``lam``: ``w(k) = lam w(k-1) + n(k)``, ``n ~ N(0, q)``. Each frame
draws a V-shaped laser stripe (two arms meeting at the corner, Gaussian profile; the drawing is
:mod:`torchseam.sim.vstripe`'s, shared with the tracker tests) with its corner at the true point
plus white measurement jitter (``jitter_px``), over a dim noisy background.
Because the data obey the model, the EAKF's best ``lam`` is known: fitting should move towards it.
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import cv2
import numpy as np

from torchseam.core.dataset import frame_name, write_labels
from torchseam.sim.vstripe import draw_v_stripes

__all__ = ["coloured_track", "render_v_stripes", "write_synthetic_sequences"]


def coloured_track(n: int, T: int, lam: float, q: float, frame_rate: float = 25.0,
                   centre: tuple[float, float] = (48.0, 48.0), seed: int = 0,
                   max_extent: float | None = None) -> np.ndarray:
    """(n, T, 2) trajectories of eq. 12/16 started at rest at ``centre``.

    Args:
        lam: acceleration colour in (-1, 1).
        q: white-acceleration variance (px^2/s^4).
        max_extent: redraw a trajectory whose u or v range exceeds this (px); keeps the
            corner inside small frames.
    """
    rng = np.random.default_rng(seed)
    dt = 1.0 / frame_rate
    out = np.empty((n, T, 2))
    i = 0
    tries = 0
    while i < n:
        tries += 1
        if tries > 1000 * n:
            raise ValueError("coloured_track: max_extent too small for q and lam")
        x = np.zeros(2)
        v = np.zeros(2)
        w = np.zeros(2)
        for k in range(T):
            out[i, k] = x
            x = x + v * dt + 0.5 * w * dt * dt
            v = v + w * dt
            w = lam * w + math.sqrt(q) * rng.standard_normal(2)
        ext = np.ptp(out[i], axis=0).max()
        if max_extent is None or ext <= max_extent:
            out[i] += np.asarray(centre) - 0.5 * (out[i].max(0) + out[i].min(0))
            i += 1
    return out


def render_v_stripes(corners: np.ndarray, size: tuple[int, int] = (96, 96), *,
                     width_px: float = 1.2, peak: float = 220.0, arm_deg: float = 35.0,
                     noise: float = 4.0, seed: int = 0) -> np.ndarray:
    """(T, H, W) uint8 grey frames of a V stripe with its corner at ``corners`` (T, 2) (u, v).

    The fit's frame convention on the shared drawing (:func:`torchseam.sim.vstripe.draw_v_stripes`):
    the arms rise from the corner at ``arm_deg`` above the horizontal to the left and right, a
    dim background (12 grey) and Gaussian read noise of sigma ``noise`` (seeded), as a camera
    gives uint8 frames.

    >>> render_v_stripes(np.array([[48.0, 60.0], [49.5, 60.5]])).shape
    (2, 96, 96)
    """
    rng = np.random.default_rng(seed)
    a = math.radians(arm_deg)
    img = draw_v_stripes(corners, size, (math.pi + a, -a), peak=peak, width_px=width_px,
                         background=12.0)
    img += noise * rng.standard_normal(img.shape)
    return np.clip(img, 0, 255).astype(np.uint8)


def write_synthetic_sequences(root: str | os.PathLike[str], n: int = 4, T: int = 24, *,
                              lam: float = 0.8, q: float = 400.0, jitter_px: float = 0.5,
                              size: tuple[int, int] = (96, 96), seed: int = 0) -> list[Path]:
    """Write ``n`` labelled sequences ``root/seq-NN`` in the dataset format (BGR frames whose
    red channel holds the stripe, so ``red_response`` gives it back; labels are the true
    corners)."""
    root = Path(root)
    H, W = size
    truth = coloured_track(n, T, lam, q, centre=(W / 2, H / 2), seed=seed,
                           max_extent=min(H, W) / 3)
    rng = np.random.default_rng(seed + 1)
    dirs = []
    for i in range(n):
        d = root / f"seq-{i:02d}"
        d.mkdir(parents=True, exist_ok=True)
        meas = truth[i] + jitter_px * rng.standard_normal(truth[i].shape)
        grey = render_v_stripes(meas, size, seed=seed * 1000 + i)
        for k, g in enumerate(grey):
            bgr = np.stack([np.zeros_like(g), np.zeros_like(g), g], axis=-1)
            cv2.imwrite(str(d / frame_name(k)), bgr)
        write_labels(d / "labels.csv", np.arange(T), truth[i])
        dirs.append(d)
    return dirs
