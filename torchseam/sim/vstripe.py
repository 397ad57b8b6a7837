"""Synthetic V-stripe frames: the one cheap image model of a laser stripe with a known corner.

Not the cell simulator (:mod:`torchseam.sim.sequence` renders the pipes, the camera and the arc):
a fully controlled picture of the one thing the trackers see, a bright laser stripe of two
straight arms meeting at the seam corner, with a Gaussian profile across the arms, over a dark
background. The corner is exact, so a test or a benchmark knows the truth to a fraction of a
pixel without a scene. Two users, one drawing function (:func:`draw_v_stripes`):

- the tracker tests and benchmarks: :func:`v_stripe_sequence`, a roof-shaped stripe moving
  smoothly, with optional arc-like clutter (bright blobs and spatter streaks near the corner)
  and frames where the stripe vanishes;
- the fit's synthetic sequences (:mod:`torchseam.fit.synthetic`): frames whose corners follow
  a known motion model, drawn at the points that model gives.

The profile is evaluated exactly at every pixel centre (distance to each arm), so the corner is
where the numbers say to any fraction of a pixel. (The tracker fixture this replaces drew the
arms with OpenCV's ``LINE_AA``, which on float images quietly draws plain pixel-quantised lines:
its arms sat up to ~0.6 px off the corner it reported.)

>>> import math
>>> img = draw_v_stripes([(40.0, 20.0)], (60, 80), (math.pi - 0.5, 0.5), peak=200.0)
>>> img.shape, img.dtype.name
((1, 60, 80), 'float32')
>>> bool(img[0, 20, 40] > 150.0), bool(img[0, 5, 40] < 1.0)   # on the corner; above it, dark
(True, True)
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

__all__ = ["Segment", "VStripeSequence", "draw_v_stripes", "v_stripe_sequence"]

Segment = tuple[float, float, float, float, float]
"""A straight extra line ``(x0, y0, x1, y1, peak)`` in pixels and grey, e.g. a spatter streak."""


def _dist2(px: np.ndarray, py: np.ndarray, x0: float, y0: float, ex: float, ey: float,
             length: float) -> np.ndarray:
    """Squared distance of every pixel to the segment from (x0, y0) along unit (ex, ey)."""
    dx, dy = px - x0, py - y0
    t = np.clip(dx * ex + dy * ey, 0.0, length)
    return (dx - t * ex) ** 2 + (dy - t * ey) ** 2


def draw_v_stripes(corners: np.ndarray | Sequence[tuple[float, float]], size: tuple[int, int],
                   angles: np.ndarray | Sequence[float], *, peak: float = 200.0,
                   width_px: float = 1.0, background: float = 0.0,
                   visible: np.ndarray | Sequence[bool] | None = None,
                   segments: Sequence[Sequence[Segment]] | None = None) -> np.ndarray:
    """(T, H, W) float32 frames of a V stripe with its corner at each of ``corners`` (T, 2) (u, v).

    Each frame: the two arms leave the corner at ``angles`` (radians, image axes: 0 along +u,
    pi/2 along +v, i.e. down) and run out of the frame, with a Gaussian profile of sigma
    ``width_px`` (~2.8 px FWHM at 1.2) and peak ``peak`` grey across them, evaluated exactly
    at every pixel centre (pixel (i, j) at u = j, v = i), so the arms and the corner are where
    the numbers say, to any fraction of a pixel; ``background`` added. Where lines cross, the
    brighter wins (no doubled corner). No noise: the callers add their own (and their clutter)
    in their own order.

    Args:
        corners: (T, 2) corner points, u (column) and v (row), sub-pixel.
        size: (H, W).
        angles: the two arms' directions, (2,) for every frame or (T, 2) per frame. A roof
            (arms down-left and down-right) is ``(pi - a, a)``; a V opening upwards
            ``(pi + a, -a)``.
        visible: (T,) where False the frame has no stripe (only ``segments`` and background).
        segments: per frame, extra straight lines with the same profile and their own peak
            (spatter streaks), ``segments[k]`` for frame k.

    Example: a V opening upwards, arms 35 degrees above the horizontal, corner at (48.5, 60.25)::

        a = math.radians(35)
        frames = draw_v_stripes([(48.5, 60.25)], (96, 96), (math.pi + a, -a), peak=220.0)
    """
    pts = np.asarray(corners, dtype=np.float64).reshape(-1, 2)
    T = len(pts)
    H, W = size
    arms = np.broadcast_to(np.asarray(angles, dtype=np.float64), (T, 2))
    py, px = np.mgrid[0:H, 0:W].astype(np.float32)
    two_var = 2 * width_px**2
    out = np.empty((T, H, W), dtype=np.float32)
    for k in range(T):
        cu, cv = pts[k]
        img = np.zeros((H, W), dtype=np.float32)
        if visible is None or visible[k]:
            d2 = np.full((H, W), np.inf, dtype=np.float32)
            for ang in arms[k]:
                ex, ey = math.cos(ang), math.sin(ang)
                d2 = np.minimum(d2, _dist2(px, py, cu, cv, ex, ey, math.inf))
            img = peak * np.exp(-d2 / two_var)
        for x0, y0, x1, y1, level in segments[k] if segments is not None else ():
            length = math.hypot(x1 - x0, y1 - y0)
            ex, ey = ((x1 - x0) / length, (y1 - y0) / length) if length > 0 else (1.0, 0.0)
            line = level * np.exp(-_dist2(px, py, x0, y0, ex, ey, length) / two_var)
            img = np.maximum(img, line)
        out[k] = background + img
    return out


@dataclass
class VStripeSequence:
    """frames (B, T, H, W) float32 grey in [0, 255]; uv (B, T, 2) true corner; visible (B, T)."""

    frames: Tensor
    uv: Tensor
    visible: Tensor


Blob = tuple[float, float, float, float]  # u, v, sigma (px), peak grey


def _clutter(rng: np.random.Generator, cx: float, cy: float, radius: float,
             streak_prob: float, streaks: int, blob_prob: float,
             blobs: int) -> tuple[list[Segment], list[Blob]]:
    """One frame's spatter streaks and blobs within ``radius`` of the corner (random draws)."""
    lines: list[Segment] = []
    spots: list[Blob] = []
    if rng.random() < streak_prob:
        for _ in range(1 + int(rng.random() * streaks)):
            r, th = radius * math.sqrt(rng.random()), 2 * math.pi * rng.random()
            bx, by = cx + r * math.cos(th), cy + r * math.sin(th)
            phi, ln = 2 * math.pi * rng.random(), 8.0 + 22.0 * rng.random()
            lines.append((bx, by, bx + ln * math.cos(phi), by + ln * math.sin(phi),
                          120 + 135 * rng.random()))
    if rng.random() < blob_prob:
        for _ in range(1 + int(rng.random() * blobs)):
            r, th = radius * math.sqrt(rng.random()), 2 * math.pi * rng.random()
            bx, by = cx + r * math.cos(th), cy + r * math.sin(th)
            s = 2.0 + 2.0 * rng.random()
            spots.append((bx, by, s, 120 + 135 * rng.random()))
    return lines, spots


def v_stripe_sequence(batch: int = 4, n_frames: int = 120, size: tuple[int, int] = (120, 160),
                      *, seed: int = 0, noise_sigma: float = 6.0, stripe: float = 200.0,
                      width_px: float = 1.0, blob_prob: float = 0.0, blobs: int = 2,
                      streak_prob: float = 0.0, streaks: int = 3, clutter_radius: float = 18.0,
                      vanish: tuple[tuple[int, int], ...] = (), amplitude: float = 20.0,
                      period: float = 90.0) -> VStripeSequence:
    """Render B sequences of a moving roof-shaped V stripe with clutter, for the trackers.

    The corner moves along smooth sinusoids (random phases and periods near ``period``) about
    the frame centre; the arms leave it down-left and down-right (a roof, as in the simulator)
    and sway a little. Deterministic for a ``seed``.

    Args:
        batch, n_frames, size: B, T and (H, W).
        seed: RNG seed.
        noise_sigma: grey-level Gaussian noise.
        stripe: stripe peak grey level; ``width_px`` its Gaussian sigma (~2.4 px FWHM at 1).
        blob_prob, blobs: chance per frame of 1..``blobs`` bright Gaussian spots (sigma 2-4 px,
            120-255 grey) within ``clutter_radius`` of the corner.
        streak_prob, streaks: same for straight spatter streaks (8-30 px long, 120-255 grey).
        vanish: (start, stop) frame ranges where the stripe is gone (clutter stays).
        amplitude, period: corner motion (px, frames), smooth sinusoids with random phases.

    Returns:
        :class:`VStripeSequence`.

    >>> seq = v_stripe_sequence(2, 5, (48, 64), seed=1, vanish=((3, 5),))
    >>> tuple(seq.frames.shape), tuple(seq.uv.shape), seq.visible[0].tolist()
    ((2, 5, 48, 64), (2, 5, 2), [True, True, True, False, False])
    """
    rng = np.random.default_rng(seed)
    H, W = size
    B, T = batch, n_frames
    t = np.arange(T, dtype=np.float64)
    ph = rng.random((B, 4)) * 2 * math.pi
    fu = 2 * math.pi / (period * (0.8 + 0.4 * rng.random((B, 1))))
    fv = 2 * math.pi / (period * (0.8 + 0.4 * rng.random((B, 1))))
    u = W / 2 + amplitude * np.sin(fu * t + ph[:, :1]) + 0.3 * amplitude * np.sin(
        2.3 * fu * t + ph[:, 1:2])
    v = H / 2 + 0.6 * amplitude * np.sin(fv * t + ph[:, 2:3]) + 0.2 * amplitude * np.sin(
        1.7 * fv * t + ph[:, 3:4])
    # arms leave the corner down-left and down-right (a roof, as in the simulator)
    ang_l = math.pi - (0.35 + 0.25 * rng.random((B, 1))) + 0.05 * np.sin(fu * t)
    ang_r = (0.35 + 0.25 * rng.random((B, 1))) + 0.05 * np.sin(fv * t)
    visible = np.ones((B, T), dtype=bool)
    for a, b in vanish:
        visible[:, a:b] = False
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float32)
    frames = np.empty((B, T, H, W), dtype=np.float32)
    for bi in range(B):
        clutter = [_clutter(rng, u[bi, k], v[bi, k], clutter_radius, streak_prob, streaks,
                            blob_prob, blobs) for k in range(T)]
        frames[bi] = draw_v_stripes(np.stack([u[bi], v[bi]], axis=-1), size,
                                    np.stack([ang_l[bi], ang_r[bi]], axis=-1), peak=stripe,
                                    width_px=width_px, background=15.0, visible=visible[bi],
                                    segments=[lines for lines, _ in clutter])
        for k, (_, spots) in enumerate(clutter):
            for bx, by, s, level in spots:
                frames[bi, k] += level * np.exp(-((xx - bx) ** 2 + (yy - by) ** 2) / (2 * s * s))
    frames += rng.normal(0.0, noise_sigma, frames.shape).astype(np.float32)
    np.clip(frames, 0.0, 255.0, out=frames)
    uv = np.stack([u, v], axis=-1)
    return VStripeSequence(frames=torch.from_numpy(frames),
                           uv=torch.tensor(uv, dtype=torch.float32),
                           visible=torch.from_numpy(visible))
