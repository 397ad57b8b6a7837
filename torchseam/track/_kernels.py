"""The live tracker's compiled kernels (numba): the STC confidence map's peak and its quality,
and the glare level's median.

The peak, its sub-pixel offset, the peak-to-sidelobe ratio and the competing peaks of a
(64, 64) confidence map are a few thousand comparisons: as ~30 numpy calls they cost ~0.15 ms
of interpreter overhead a frame, compiled ~0.01 ms. The glare level (the median red response
of a 61 x 61 box) is counted in a 256-bin histogram instead of cutting, converting and
partitioning the box. The signatures are given, so the kernels are compiled (or loaded from
numba's on-disk cache) when this module is imported, which
:class:`~torchseam.track.lite.LiteEAKFSTC` does when it is built, never in the middle of the
live loop.
"""

from __future__ import annotations

import numba
import numpy as np

_TINY = float(np.finfo(np.float64).tiny)


@numba.njit("Tuple((f8, f8, f8, f8, f8, i8))(f8[:, ::1], i8, b1, i8)", cache=True, nogil=True)
def peak_quality(resp, e, even, eb):  # pragma: no cover - compiled
    """Of a confidence map ``resp`` (H, W), circular: (offset of the sub-pixel peak from the
    window centre along u, along v, peak value, peak-to-sidelobe ratio outside the
    (2 e + 1)^2 area around the peak, second-peak ratio, number of peaks).

    The sub-pixel peak is a parabola through the peak and its neighbours per axis (wrapping).
    Competing peaks are the interior local maxima (3 x 3) of the 2 x 2-block maxima when
    ``even`` (else of the map), off the peak's own (2 eb + 1)^2 blocks; the second-peak ratio
    is the highest one's height over the peak's, both above the sidelobe mean, in [0, 1];
    ``n_peaks`` counts the peak and those above half its height.
    """
    h, w = resp.shape
    i = j = 0
    peak = resp[0, 0]
    s = ss = 0.0
    for r in range(h):
        for c in range(w):
            x = resp[r, c]
            s += x
            ss += x * x
            if x > peak:
                peak, i, j = x, r, c
    off_u, off_v = float(j - w // 2), float(i - h // 2)
    lo, hi = resp[i, (j - 1) % w], resp[i, (j + 1) % w]
    den = lo + hi - 2.0 * peak
    if den < 0:
        off_u += min(max(0.5 * (lo - hi) / den, -0.5), 0.5)
    lo, hi = resp[(i - 1) % h, j], resp[(i + 1) % h, j]
    den = lo + hi - 2.0 * peak
    if den < 0:
        off_v += min(max(0.5 * (lo - hi) / den, -0.5), 0.5)
    # peak-to-sidelobe ratio: mean and variance of the map less the peak's area
    a = aa = 0.0
    for dr in range(-e, e + 1):
        for dc in range(-e, e + 1):
            x = resp[(i + dr) % h, (j + dc) % w]
            a += x
            aa += x * x
    n, p = h * w, (2 * e + 1) ** 2
    mean_all = s / n
    var_all = ss / n - mean_all * mean_all
    mean_s = (mean_all * n - a) / (n - p)
    var_s = ((var_all + mean_all * mean_all) * n - aa) / (n - p) - mean_s * mean_s
    height = peak - mean_s
    psr = height / np.sqrt(max(var_s, _TINY))
    # competing peaks
    if even:
        bh, bw = h // 2, w // 2
        blocks = np.empty((bh, bw))
        for r in range(bh):
            for c in range(bw):
                blocks[r, c] = max(max(resp[2 * r, 2 * c], resp[2 * r, 2 * c + 1]),
                                   max(resp[2 * r + 1, 2 * c], resp[2 * r + 1, 2 * c + 1]))
        bi, bj = i // 2, j // 2
    else:
        bh, bw = h, w
        blocks = resp
        bi, bj = i, j
    height = max(height, _TINY)
    second = mean_s
    n_peaks = 1
    for r in range(1, bh - 1):
        # the peak's own blocks (circular distance) are not competitors
        dr = (r - bi) % bh
        near_r = dr <= eb or dr >= bh - eb
        for c in range(1, bw - 1):
            dc = (c - bj) % bw
            if near_r and (dc <= eb or dc >= bw - eb):
                continue
            x = blocks[r, c]
            if (x >= blocks[r - 1, c - 1] and x >= blocks[r - 1, c] and x >= blocks[r - 1, c + 1]
                    and x >= blocks[r, c - 1] and x >= blocks[r, c + 1]
                    and x >= blocks[r + 1, c - 1] and x >= blocks[r + 1, c]
                    and x >= blocks[r + 1, c + 1]):
                second = max(second, x)
                n_peaks += x > mean_s + 0.5 * height
    second_ratio = min(max((second - mean_s) / height, 0.0), 1.0)
    return off_u, off_v, peak, psr, second_ratio, n_peaks


@numba.njit(cache=True, nogil=True)
def _rank_value(hist, rank):  # pragma: no cover - compiled
    """The value of rank ``rank`` of the values counted in ``hist`` (256,)."""
    seen = 0
    for v in range(256):
        seen += hist[v]
        if seen > rank:
            return v
    return 255


@numba.njit("i8(u1[:, :, :], i8)", cache=True, nogil=True)
def colour_median_red(box, rank):  # pragma: no cover - compiled
    """The value of rank ``rank`` (0: the smallest) among the red responses
    ``R - max(G, B)`` (saturating) of a BGR box (h, w, 3) uint8: ``np.partition`` of the
    response, by counting (a 256-bin histogram) instead of copying and selecting."""
    hist = np.zeros(256, np.int64)
    h, w, _ = box.shape
    for r in range(h):
        for c in range(w):
            m = max(box[r, c, 1], box[r, c, 0])
            hist[max(box[r, c, 2], m) - m] += 1
    return _rank_value(hist, rank)


@numba.njit("i8(u1[:, :], i8)", cache=True, nogil=True)
def mono_median(box, rank):  # pragma: no cover - compiled
    """:func:`colour_median_red` of a mono box (h, w) uint8 (the response is the value)."""
    hist = np.zeros(256, np.int64)
    h, w = box.shape
    for r in range(h):
        for c in range(w):
            hist[box[r, c]] += 1
    return _rank_value(hist, rank)


@numba.njit("void(f8[::1], f8[::1], f8[::1], f8[::1], f8[:, ::1], f8[::1], f8[::1])",
            cache=True, nogil=True)
def two_arm_fit(t, y, grid, prior, theta, J, var_a):  # pragma: no cover - compiled
    """The shallow corner's two-arm fit (:mod:`torchseam.track.shallow`) at every corner
    column of ``grid`` (K,): points ``t``, ``y`` (N,) sorted by t; ``prior`` (c0_L, w_L, c0_R,
    w_R). Writes theta (K, 5) = (a, b_L, c_L, b_R, c_R), the sum of squares J (K,) and var(a)
    per unit noise (K,). Each arm's (b, c) for a given a from its 2x2 normal matrix, a from
    the Schur complement (closed form)."""
    n = t.shape[0]
    yy = 0.0
    for i in range(n):
        yy += y[i] * y[i]
    for k in range(grid.shape[0]):
        tc = grid[k]
        # per side: n, S1..S4, T0..T2
        S = np.zeros((2, 8))
        for i in range(n):
            x = t[i] - tc
            side = 0 if x < 0 else 1
            x2 = x * x
            S[side, 0] += 1.0
            S[side, 1] += x
            S[side, 2] += x2
            S[side, 3] += x2 * x
            S[side, 4] += x2 * x2
            S[side, 5] += y[i]
            S[side, 6] += x * y[i]
            S[side, 7] += x2 * y[i]
        schur = 1e-12
        rhs = 0.0
        keep = np.zeros((2, 6))
        for side in range(2):
            c0, w = prior[2 * side], prior[2 * side + 1]
            b00, b01, b11 = S[side, 2], S[side, 3], S[side, 4] + w
            det = b00 * b11 - b01 * b01
            if abs(det) < 1e-300:
                det = 1e-300
            i00, i01, i11 = b11 / det, -b01 / det, b00 / det
            r0, r1 = S[side, 6], S[side, 7] + w * c0
            s0, s1 = S[side, 1], S[side, 2]
            bs0, bs1 = i00 * s0 + i01 * s1, i01 * s0 + i11 * s1
            br0, br1 = i00 * r0 + i01 * r1, i01 * r0 + i11 * r1
            schur += S[side, 0] - (s0 * bs0 + s1 * bs1)
            rhs += S[side, 5] - (s0 * br0 + s1 * br1)
            keep[side, 0], keep[side, 1], keep[side, 2] = bs0, bs1, br0
            keep[side, 3], keep[side, 4], keep[side, 5] = br1, r0, r1
        a = rhs / schur
        theta[k, 0] = a
        Jk = yy + prior[1] * prior[0] ** 2 + prior[3] * prior[2] ** 2 - a * (S[0, 5] + S[1, 5])
        for side in range(2):
            b = keep[side, 2] - a * keep[side, 0]
            c = keep[side, 3] - a * keep[side, 1]
            theta[k, 1 + 2 * side], theta[k, 2 + 2 * side] = b, c
            Jk -= b * keep[side, 4] + c * keep[side, 5]
        J[k] = Jk
        var_a[k] = 1.0 / schur
