"""Synthetic V-stripe sequences for the tracker tests and benchmarks (private fixture).

Not the simulator (that is :mod:`torchseam.sim`): a cheap, fully controlled image model of the
one thing the trackers see, a bright laser stripe of two straight arms meeting at the seam
corner (a roof, like the simulator's stripe), Gaussian profile, moving smoothly over a dark
background, with optional arc-like clutter (bright blobs and streaks near the corner) and frames
where the stripe vanishes. Lines are drawn anti-aliased with sub-pixel end points (OpenCV,
8 fractional bits) and blurred; the corner truth is exact to ~0.1 px.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
import torch
from torch import Tensor

SHIFT = 8  # fractional bits of the OpenCV drawing calls
ONE = 1 << SHIFT


@dataclass
class VStripeSequence:
    """frames (B, T, H, W) float32 grey in [0, 255]; uv (B, T, 2) true corner; visible (B, T)."""

    frames: Tensor
    uv: Tensor
    visible: Tensor


def _pt(x: float, y: float) -> tuple[int, int]:
    return int(round(x * ONE)), int(round(y * ONE))


def v_stripe_sequence(batch: int = 4, n_frames: int = 120, size: tuple[int, int] = (120, 160),
                      *, seed: int = 0, noise_sigma: float = 6.0, stripe: float = 200.0,
                      width_px: float = 1.0, blob_prob: float = 0.0, blobs: int = 2,
                      streak_prob: float = 0.0, streaks: int = 3, clutter_radius: float = 18.0,
                      vanish: tuple[tuple[int, int], ...] = (), amplitude: float = 20.0,
                      period: float = 90.0) -> VStripeSequence:
    """Render B sequences of a moving V stripe with clutter.

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
    sig = math.sqrt(width_px**2 + 1.0 / 6.0)   # AA line (triangle, var 1/6) then blur
    gain = math.sqrt(2 * math.pi) * sig        # line integral -> peak value
    blur = math.sqrt(max(width_px**2 - 1.0 / 6.0, 0.05))
    reach = 2.0 * (H + W)
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float32)
    frames = np.empty((B, T, H, W), dtype=np.float32)
    for bi in range(B):
        for k in range(T):
            cx, cy = u[bi, k], v[bi, k]
            lines = np.zeros((H, W), dtype=np.float32)
            if visible[bi, k]:
                for ang in (ang_l[bi, k], ang_r[bi, k]):
                    end = (cx + reach * math.cos(ang), cy + reach * math.sin(ang))
                    cv2.line(lines, _pt(cx, cy), _pt(*end), stripe * gain, 1, cv2.LINE_AA, SHIFT)
            if rng.random() < streak_prob:
                for _ in range(1 + int(rng.random() * streaks)):
                    r, th = clutter_radius * math.sqrt(rng.random()), 2 * math.pi * rng.random()
                    bx, by = cx + r * math.cos(th), cy + r * math.sin(th)
                    phi, ln = 2 * math.pi * rng.random(), 8.0 + 22.0 * rng.random()
                    end = (bx + ln * math.cos(phi), by + ln * math.sin(phi))
                    cv2.line(lines, _pt(bx, by), _pt(*end), (120 + 135 * rng.random()) * gain, 1,
                             cv2.LINE_AA, SHIFT)
            img = cv2.GaussianBlur(lines, (0, 0), blur) + 15.0
            if rng.random() < blob_prob:
                for _ in range(1 + int(rng.random() * blobs)):
                    r, th = clutter_radius * math.sqrt(rng.random()), 2 * math.pi * rng.random()
                    bx, by = cx + r * math.cos(th), cy + r * math.sin(th)
                    s = 2.0 + 2.0 * rng.random()
                    img += (120 + 135 * rng.random()) * np.exp(
                        -((xx - bx) ** 2 + (yy - by) ** 2) / (2 * s * s))
            frames[bi, k] = img
    frames += rng.normal(0.0, noise_sigma, frames.shape).astype(np.float32)
    np.clip(frames, 0.0, 255.0, out=frames)
    uv = np.stack([u, v], axis=-1)
    return VStripeSequence(frames=torch.from_numpy(frames),
                           uv=torch.tensor(uv, dtype=torch.float32),
                           visible=torch.from_numpy(visible))
