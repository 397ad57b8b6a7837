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

import math

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


@numba.njit("i8[::1](f8[:, ::1], f8[::1], f4[:, ::1])", cache=True, nogil=True)
def splat(pts, weight, img):  # pragma: no cover - compiled
    """Bilinear splat of weighted points (N, 2) into the all-zero float32 (H, W) ``img``;
    returns the box ``(x0, y0, x1, y1)`` (end-exclusive, inside the image) that holds every
    pixel it wrote, or ``(-1, -1, -1, -1)`` when no point lies in the image.

    The numbers of the numpy statement: the points with ``-1 < u < W`` and ``-1 < v < H``,
    each at pixel ``(floor u, floor v)`` plus ``(fx, fy)``, add ``weight`` times their four
    bilinear weights to that pixel and its right, lower and lower-right neighbours, in a box
    from the smallest pixel to one past the largest; the sums are ``np.bincount``'s with
    weights, one corner after the other (each corner's sums in the points' order, added to
    the box in the order (0, 0), (1, 0), (0, 1), (1, 1)), and the box, less what lies outside
    the image, is cast to float32 into the image. A corner's sums are added where that corner
    touched the box only (elsewhere they are +0.0, which changes no sum: a sum here never is
    -0.0), so the work follows the points, not the box."""
    h, w = img.shape
    n_in = 0
    bx, by, mx, my = 0, 0, 0, 0
    for i in range(len(pts)):
        u, v = pts[i, 0], pts[i, 1]
        if u > -1 and u < w and v > -1 and v < h:
            xi, yi = int(math.floor(u)), int(math.floor(v))
            if n_in == 0:
                bx, by, mx, my = xi, yi, xi, yi
            else:
                bx, by, mx, my = min(bx, xi), min(by, yi), max(mx, xi), max(my, yi)
            n_in += 1
    box = np.full(4, -1, np.int64)
    if n_in == 0:
        return box
    bw, bh = mx - bx + 2, my - by + 2
    n = bw * bh
    acc = np.zeros(n)
    part = np.zeros(n)
    seen = np.zeros(n, np.bool_)
    touched = np.empty(n_in, np.int64)
    for k in range(4):
        dx, dy = k % 2, k // 2
        m = 0
        for i in range(len(pts)):
            u, v = pts[i, 0], pts[i, 1]
            if not (u > -1 and u < w and v > -1 and v < h):
                continue
            xf, yf = math.floor(u), math.floor(v)
            fx, fy = u - xf, v - yf
            wx = fx if dx else 1 - fx
            wy = fy if dy else 1 - fy
            j = (int(yf) - by + dy) * bw + int(xf) - bx + dx
            part[j] += weight[i] * (wx * wy)
            if not seen[j]:
                seen[j] = True
                touched[m] = j
                m += 1
        for t in range(m):
            j = touched[t]
            acc[j] += part[j]
            part[j] = 0.0
            seen[j] = False
            y, x = by + j // bw, bx + j % bw
            if 0 <= y < h and 0 <= x < w:
                img[y, x] = np.float32(acc[j])
    box[0], box[1] = max(0, bx), max(0, by)
    box[2], box[3] = bx + min(bw, w - bx), by + min(bh, h - by)
    return box


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


@numba.njit("void(f4[:, ::1], f4[:, ::1], i8, i8, i8, i8, f8)", cache=True, nogil=True)
def paste_scaled(img, template, y0, x0, ty0, tx0, peak):  # pragma: no cover - compiled
    """``img[y0:, x0:] = float32(peak * template[ty0:, tx0:])`` over the overlap (the
    arithmetic of ``np.multiply(template, peak, out=img, casting="same_kind")`` with a float64
    ``peak``: each product in float64, rounded once to float32), ``img``'s box being the
    part of the template's box that lies inside the image (given by the caller)."""
    h = min(img.shape[0] - y0, template.shape[0] - ty0)
    w = min(img.shape[1] - x0, template.shape[1] - tx0)
    for y in range(h):
        i_row, t_row = img[y0 + y], template[ty0 + y]
        for x in range(w):
            i_row[x0 + x] = np.float32(np.float64(t_row[tx0 + x]) * peak)


@numba.njit("void(f4[::1], f4[::1], f8, f8, f8, f8, f8, f8, f8[:, ::1])", cache=True,
            nogil=True)
def blob_arg(xs, ys, cx, cy, ca, sa, ra, rb, out):  # pragma: no cover - compiled
    """The exponent of a reflection blob on the box of pixel columns ``xs`` and rows ``ys``
    (float32 coordinates): ``-0.5 * (p^2 + q^2)`` with ``p = (ca dx + sa dy) / ra``,
    ``q = (-sa dx + ca dy) / rb``, ``dx = x - cx``, ``dy = y - cy``, each operation in float64
    in ``ArcNoise._blob``'s order (its numpy passes' numbers)."""
    msa = -sa
    for i in range(len(ys)):
        dy = np.float64(ys[i]) - cy
        sdy, cdy = sa * dy, ca * dy
        o_row = out[i]
        for j in range(len(xs)):
            dx = np.float64(xs[j]) - cx
            p = (ca * dx + sdy) / ra
            q = (msa * dx + cdy) / rb
            o_row[j] = (p * p + q * q) * -0.5


@numba.njit("void(f4[:, ::1], i8, i8, f8[:, ::1], f8)", cache=True, nogil=True)
def add_scaled(img, y0, x0, vals, amp):  # pragma: no cover - compiled
    """``img[y0:, x0:][:h, :w] += vals * amp`` for the (h, w) float64 ``vals``: the product in
    float64, the sum of the float32 pixel and it in float64, rounded once to float32 (numpy's
    ``img[box] += p`` of a float64 ``p``)."""
    for i in range(vals.shape[0]):
        i_row, v_row = img[y0 + i], vals[i]
        for j in range(vals.shape[1]):
            i_row[x0 + j] = np.float32(np.float64(i_row[x0 + j]) + v_row[j] * amp)


@numba.njit("void(f4[::1], f4[::1], f8, f8, f8, f8, f8, f8, f8[:, ::1])", cache=True,
            nogil=True)
def band_arg(xs, ys, x0, y0, d0, d1, len2, two_w2, out):  # pragma: no cover - compiled
    """The exponent of the groove's band (``ArcNoise._band``) on the box of pixel columns
    ``xs`` and rows ``ys``: ``-(ex^2 + ey^2) / two_w2`` with ``(ex, ey)`` the pixel's offset
    from its nearest point ``t`` (clipped to [0, 1]) along the segment from ``(x0, y0)`` by
    ``(d0, d1)``; float64, in the numpy passes' order."""
    for i in range(len(ys)):
        dy = np.float64(ys[i]) - y0
        dyd = dy * d1
        o_row = out[i]
        for j in range(len(xs)):
            dx = np.float64(xs[j]) - x0
            t = min(max((dx * d0 + dyd) / len2, 0.0), 1.0)
            ex = dx - t * d0
            ey = dy - t * d1
            o_row[j] = -(ex * ex + ey * ey) / two_w2


@numba.njit("void(f4[:, ::1], i8, i8, f4[::1], f4[::1], f8, f8, f8, f8, f8, f8, f8[:, ::1])",
            cache=True, nogil=True)
def band_add(img, r0, c0, xs, ys, x0, y0, d0, d1, len2, amp, e):  # pragma: no cover
    """``img`` += the groove's band on its box (rows from ``r0``, columns from ``c0``):
    ``((1 - 0.6 t) * amp) * e`` with ``t`` as in :func:`band_arg` and ``e`` the exponential
    of its exponent, added as :func:`add_scaled` adds (float64, rounded once to float32)."""
    for i in range(len(ys)):
        dy = np.float64(ys[i]) - y0
        dyd = dy * d1
        i_row, e_row = img[r0 + i], e[i]
        for j in range(len(xs)):
            dx = np.float64(xs[j]) - x0
            t = min(max((dx * d0 + dyd) / len2, 0.0), 1.0)
            v = ((1.0 - t * 0.6) * amp) * e_row[j]
            i_row[c0 + j] = np.float32(np.float64(i_row[c0 + j]) + v)


@numba.njit("Tuple((f8[:, ::1], f8[::1], f8[::1], i8[::1]))(f8[:, ::1], f8[::1], f8, f8)",
            cache=True, nogil=True)
def stripe_samples(uv, brightness, step_px, max_gap_px):  # pragma: no cover - compiled
    """The stripe's splat samples along its polyline ``uv`` (N, 2): each segment shorter than
    ``max_gap_px`` cut into ``max(1, ceil(length / step_px))`` samples at fractions ``j / n``
    (longer ones, real gaps, into none). Returns the samples (M, 2), the arc length per sample,
    the brightness interpolated along the segment times that length, and each sample's segment.
    ``LaserSensor.stripe_layer``'s numpy statement (np.diff, the row norms, np.repeat,
    np.cumsum), element by element in its order: the same numbers."""
    n_seg = max(len(uv) - 1, 0)
    seg_len = np.empty(n_seg)
    n_sub = np.empty(n_seg, np.int64)
    total = 0
    for i in range(n_seg):
        d0, d1 = uv[i + 1, 0] - uv[i, 0], uv[i + 1, 1] - uv[i, 1]
        seg_len[i] = math.sqrt(d0 * d0 + d1 * d1)
        n_sub[i] = max(1, int(math.ceil(seg_len[i] / step_px))) if seg_len[i] < max_gap_px \
            else 0
        total += n_sub[i]
    pts = np.empty((total, 2))
    step = np.empty(total)
    weight = np.empty(total)
    starts = np.empty(total, np.int64)
    k = 0
    for i in range(n_seg):
        n = n_sub[i]
        d0, d1 = uv[i + 1, 0] - uv[i, 0], uv[i + 1, 1] - uv[i, 1]
        st = seg_len[i] / max(n, 1)
        for j in range(n):
            f = np.float64(j) / np.float64(max(n, 1))
            pts[k, 0] = uv[i, 0] + f * d0
            pts[k, 1] = uv[i, 1] + f * d1
            step[k] = st
            weight[k] = (brightness[i] * (1 - f) + brightness[i + 1] * f) * st
            starts[k] = i
            k += 1
    return pts, step, weight, starts


@numba.njit("void(f8[:, ::1], f8[:, ::1], f8[::1], f8[:, ::1])", cache=True, nogil=True)
def project_points(X, K, k, out):  # pragma: no cover - compiled
    """``cv2.projectPoints(X, zeros(3), zeros(3), K, dist)`` of the (N, 3) points ``X`` into
    ``out`` (N, 2): OpenCV's arithmetic (its ``cvProjectPoints2Internal``), operation by
    operation in its order, with the rotation of a zero vector (the identity), a zero
    translation and no tilt; ``k`` the distortion coefficients padded with zeros to 14.
    OpenCV computes the projection's Jacobian too, which the Python call cannot decline and
    which costs most of the call; ``LaserSensor`` uses this where a probe finds it OpenCV's
    to the bit (``sensor._projection_agrees``)."""
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    for i in range(X.shape[0]):
        xw, yw, zw = X[i, 0], X[i, 1], X[i, 2]
        x = 1.0 * xw + 0.0 * yw + 0.0 * zw + 0.0
        y = 0.0 * xw + 1.0 * yw + 0.0 * zw + 0.0
        z = 0.0 * xw + 0.0 * yw + 1.0 * zw + 0.0
        z = 1.0 / z if z != 0.0 else 1.0
        x *= z
        y *= z
        r2 = x * x + y * y
        r4 = r2 * r2
        r6 = r4 * r2
        a1 = 2 * x * y
        a2 = r2 + 2 * x * x
        a3 = r2 + 2 * y * y
        cdist = 1 + k[0] * r2 + k[1] * r4 + k[4] * r6
        icdist2 = 1.0 / (1 + k[5] * r2 + k[6] * r4 + k[7] * r6)
        xd0 = x * cdist * icdist2 + k[2] * a1 + k[3] * a2 + k[8] * r2 + k[9] * r4
        yd0 = y * cdist * icdist2 + k[2] * a3 + k[3] * a1 + k[10] * r2 + k[11] * r4
        # the tilt: the identity matrix times (xd0, yd0, 1)
        t0 = 1.0 * xd0 + 0.0 * yd0 + 0.0 * 1.0
        t1 = 0.0 * xd0 + 1.0 * yd0 + 0.0 * 1.0
        t2 = 0.0 * xd0 + 0.0 * yd0 + 1.0 * 1.0
        inv = 1.0 / t2 if t2 != 0.0 else 1.0
        out[i, 0] = (inv * t0) * fx + cx
        out[i, 1] = (inv * t1) * fy + cy
