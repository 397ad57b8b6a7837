"""The simulator's compiled kernels (numba): the last pass of a rendered frame.

Adding the background and the read noise, clipping and casting a (492, 656, 3) float32 frame
to uint8 were four full-frame numpy passes with their temporaries (~1.5 ms a frame, most of it
memory traffic); one compiled pass reads each input once and writes the uint8 frame. Every
operation is the numpy pass's, in float32 and in the same order (the tests hold the kernel to
the numpy arithmetic bit for bit). The signature is given, so the kernel is compiled (or
loaded from numba's on-disk cache) when this module is imported, which
:class:`~torchseam.sim.sequence.SensorRenderer` does when it is built.
"""

from __future__ import annotations

import numba
import numpy as np


@numba.njit("void(f4[:, ::1], f4[:, ::1], f4[:, ::1], i8, i8, f4, u1[:, ::1])", cache=True,
            nogil=True)
def finish_frame(light, background, noise, row, col, sigma, out):  # pragma: no cover
    """``out = uint8(clip((light + background) + noise_window * sigma, 0, 255))``,
    element-wise in float32 (each operation rounded to float32, as numpy's ``+=``,
    ``multiply`` and ``clip`` of float32 arrays; the cast truncates, as ``astype``).

    Frames are given as rows of interleaved channels: ``light``, ``background`` and ``out``
    (H, W * C); ``noise`` is a larger field (H', W' * C) whose window starts at ``row`` and
    element ``col`` of the row (pixel ``dx``: ``col = dx * C``). Each row is one contiguous
    run, which the compiler vectorises."""
    h, n = light.shape
    lo, hi = np.float32(0.0), np.float32(255.0)
    for y in range(h):
        a_row, b_row, o_row = light[y], background[y], out[y]
        n_row = noise[row + y]
        for j in range(n):
            v = (a_row[j] + b_row[j]) + n_row[col + j] * sigma
            o_row[j] = np.uint8(min(max(v, lo), hi))


@numba.njit("f8[::1](i8[::1], i8[::1], f8[::1], f8[::1], f8[::1], i8, i8)", cache=True,
            nogil=True)
def splat_box(x0, y0, fx, fy, weight, bw, bh):  # pragma: no cover - compiled
    """Bilinear splat of points into a (bh, bw) box, flat: the point at pixel ``(x0, y0)``
    (box coordinates) plus ``(fx, fy)`` adds ``weight`` times its four bilinear weights to
    that pixel and its right, lower and lower-right neighbours. The sums of ``np.bincount``
    with weights, one corner after the other (each corner's sums in the points' order, then
    added to the box in the order (0, 0), (1, 0), (0, 1), (1, 1)): the same numbers."""
    n = bw * bh
    acc = np.zeros(n)
    part = np.empty(n)
    for k in range(4):
        dx, dy = k % 2, k // 2
        part[:] = 0.0
        for i in range(len(x0)):
            wx = fx[i] if dx else 1 - fx[i]
            wy = fy[i] if dy else 1 - fy[i]
            part[(y0[i] + dy) * bw + x0[i] + dx] += weight[i] * (wx * wy)
        for j in range(n):
            acc[j] += part[j]
    return acc
