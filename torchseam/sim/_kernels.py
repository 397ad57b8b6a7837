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
from llvmlite import ir
from numba.core import types
from numba.core.extending import intrinsic


@intrinsic
def _fma32(typingctx, a, b, c):  # pragma: no cover - compiled
    """``a * b + c`` in float32 rounded once (LLVM's ``llvm.fma.f32``: the CPU's fused
    multiply-add where it has one, a correctly rounded emulation where not)."""
    sig = types.float32(types.float32, types.float32, types.float32)

    def codegen(context, builder, signature, args):
        f = ir.FloatType()
        fn = builder.module.declare_intrinsic("llvm.fma", [f], ir.FunctionType(f, [f, f, f]))
        return builder.call(fn, args)

    return sig, codegen


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


@numba.njit("void(f4[:, ::1], f4[:, ::1], f4[:, ::1], f4[:, ::1], i8, i8, f4[::1])", cache=True,
            nogil=True)
def _mix_row(stripe, glare, spatter, mix, y, tail_from, out):  # pragma: no cover - compiled
    """Row ``y`` of the light, interleaved (W * 3): ``cv2.transform``'s arithmetic (see
    :func:`mix_finish`); from flat pixel ``tail_from`` on, its scalar tail's."""
    w = stripe.shape[1]
    s_row, g_row, p_row = stripe[y], glare[y], spatter[y]
    xs = min(w, max(0, tail_from - y * w))
    for c in range(3):
        m0, m1, m2 = mix[c, 0], mix[c, 1], mix[c, 2]
        for x in range(xs):
            out[3 * x + c] = _fma32(s_row[x], m0, _fma32(g_row[x], m1, p_row[x] * m2))  # type: ignore[call-arg]
        for x in range(xs, w):
            out[3 * x + c] = _fma32(p_row[x], m2, _fma32(s_row[x], m0, g_row[x] * m1))  # type: ignore[call-arg]


@numba.njit("void(f4[:, ::1], f4[:, ::1], f4[:, ::1], f4[:, ::1], i8, f4[:, ::1], f4[:, ::1], "
            "i8, i8, f4, u1[:, ::1])", cache=True, nogil=True)
def mix_finish(stripe, glare, spatter, mix, tail_from, background, noise, row, col, sigma,
               out):  # pragma: no cover - compiled
    """The colour mix and :func:`finish_frame` in one pass: the light of pixel ``(y, x)``,
    channel ``c``, is ``cv2.transform``'s of the three grey layers merged (``stripe``,
    ``glare``, ``spatter``, each (H, W)) by the (3, 3) matrix ``mix``, then
    ``out = uint8(clip((light + background) + noise_window * sigma, 0, 255))`` as
    :func:`finish_frame` (``background``, ``noise`` and ``out`` as there, rows of interleaved
    channels), without the merged and the mixed planes.

    ``cv2.transform`` of a float32 3-channel image by a 3 x 3 matrix, on a CPU with AVX2,
    computes ``fma(s, m0, fma(g, m1, p * m2))`` (its SIMD loop's ``v_matmuladd``) and, on its
    last pixels (from flat pixel ``tail_from``: ``sequence._mix_tail_from``), its scalar
    loop's ``fma(p, m2, fma(s, m0, g * m1))``: this is that arithmetic, so the frame is the two
    calls' to the bit where ``sequence._fused_mix_agrees`` finds it so (else the renderer
    makes the calls; tests/test_sim_sensor.py)."""
    h, w = stripe.shape
    lo, hi = np.float32(0.0), np.float32(255.0)
    light = np.empty(3 * w, np.float32)
    for y in range(h):
        _mix_row(stripe, glare, spatter, mix, y, tail_from, light)
        b_row, o_row = background[y], out[y]
        n_row = noise[row + y]
        for j in range(3 * w):
            v = (light[j] + b_row[j]) + n_row[col + j] * sigma
            o_row[j] = np.uint8(min(max(v, lo), hi))


@numba.njit("void(f4[:, ::1], f4[:, ::1], f4[:, ::1], f4[:, ::1], i8, f4[:, ::1])", cache=True,
            nogil=True)
def mix_light(stripe, glare, spatter, mix, tail_from, out):  # pragma: no cover - compiled
    """The light :func:`mix_finish` computes, (H, W * 3) interleaved: what it is checked
    against ``cv2.transform`` with (``sequence._fused_mix_agrees``)."""
    for y in range(stripe.shape[0]):
        _mix_row(stripe, glare, spatter, mix, y, tail_from, out[y])
