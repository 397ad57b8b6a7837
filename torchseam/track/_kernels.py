"""The live tracker's compiled kernels (numba): the STC confidence map's peak and its quality,
and the glare level's median.

The peak, its sub-pixel offset, the peak-to-sidelobe ratio and the competing peaks of a
(64, 64) confidence map are a few thousand comparisons: as ~30 numpy calls they cost ~0.15 ms
of interpreter overhead a frame, compiled ~0.01 ms. The glare level (the median red response
of a 61 x 61 box) is counted in a 256-bin histogram instead of cutting, converting and
partitioning the box. The signatures are given, so the kernels are compiled (or loaded from
numba's on-disk cache) when this module is imported, which
:class:`~torchseam.track.fusion.LiteEAKFSTC` does when it is built, never in the middle of the
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


@numba.njit("void(u1[:, :, ::1], i8, i8, f8[:, ::1])", cache=True, nogil=True)
def red_window(frame, r0, c0, out):  # pragma: no cover - compiled
    """``out`` (H, W) = the red response ``R - max(G, B)`` (saturating) of the BGR frame's
    (H, W) window whose top-left pixel is ``(r0, c0)``, rows and columns outside the frame
    replicated from its border, as float64: EAKF-STC's context window
    (``LiteEAKFSTC._window``: the crop, ``red_response`` and the conversion, ~20 us as numpy
    and OpenCV calls, twice a frame)."""
    hi, wi = frame.shape[0], frame.shape[1]
    h, w = out.shape
    for i in range(h):
        px = frame[min(max(r0 + i, 0), hi - 1)]
        o = out[i]
        for j in range(w):
            c = min(max(c0 + j, 0), wi - 1)
            x = px[c, 2]
            m = max(px[c, 1], px[c, 0])
            o[j] = np.float64(x - m) if x > m else 0.0


@numba.njit(cache=True, nogil=True, inline="always")
def _arm_normal(n, s1, s2, s3, s4, t0, t1, t2, c0, w):  # pragma: no cover - compiled
    """One arm of :func:`two_arm_fit`: from its sums (n, S1..S4, T0..T2) and curvature prior
    (c0, w), its Schur term, its right-hand side term, A^-1 s, A^-1 r and r."""
    b00, b01, b11 = s2, s3, s4 + w
    det = b00 * b11 - b01 * b01
    if abs(det) < 1e-300:
        det = 1e-300
    i00, i01, i11 = b11 / det, -b01 / det, b00 / det
    r0, r1 = t1, t2 + w * c0
    bs0, bs1 = i00 * s1 + i01 * s2, i01 * s1 + i11 * s2
    br0, br1 = i00 * r0 + i01 * r1, i01 * r0 + i11 * r1
    return n - (s1 * bs0 + s2 * bs1), t0 - (s1 * br0 + s2 * br1), bs0, bs1, br0, br1, r0, r1


@numba.njit("void(f8[::1], f8[::1], f8[::1], f8[::1], f8[:, ::1], f8[::1], f8[::1])",
            cache=True, nogil=True)
def two_arm_fit(t, y, grid, prior, theta, J, var_a):  # pragma: no cover - compiled
    """The shallow corner's two-arm fit (:mod:`torchseam.track.shallow`) at every corner
    column of ``grid`` (K,): points ``t``, ``y`` (N,) sorted by t; ``prior`` (c0_L, w_L, c0_R,
    w_R). Writes theta (K, 5) = (a, b_L, c_L, b_R, c_R), the sum of squares J (K,) and var(a)
    per unit noise (K,). Each arm's (b, c) for a given a from its 2x2 normal matrix, a from
    the Schur complement (closed form). The sums taken directly, O(K N): the reference the
    search's prefix-sum form (:func:`_fit_prefix`) is held to by the tests."""
    n = t.shape[0]
    yy = 0.0
    for i in range(n):
        yy += y[i] * y[i]
    for k in range(grid.shape[0]):
        tc = grid[k]
        # per side: n, S1..S4, T0..T2 (scalars: the sums stay in registers)
        l0 = l1 = l2 = l3 = l4 = l5 = l6 = l7 = 0.0
        r0 = r1 = r2 = r3 = r4 = r5 = r6 = r7 = 0.0
        for i in range(n):
            x = t[i] - tc
            yi = y[i]
            x2 = x * x
            if x < 0:
                l0 += 1.0
                l1 += x
                l2 += x2
                l3 += x2 * x
                l4 += x2 * x2
                l5 += yi
                l6 += x * yi
                l7 += x2 * yi
            else:
                r0 += 1.0
                r1 += x
                r2 += x2
                r3 += x2 * x
                r4 += x2 * x2
                r5 += yi
                r6 += x * yi
                r7 += x2 * yi
        sl, ql, bsl0, bsl1, brl0, brl1, rl0, rl1 = _arm_normal(
            l0, l1, l2, l3, l4, l5, l6, l7, prior[0], prior[1])
        sr, qr, bsr0, bsr1, brr0, brr1, rr0, rr1 = _arm_normal(
            r0, r1, r2, r3, r4, r5, r6, r7, prior[2], prior[3])
        schur = 1e-12
        schur += sl
        schur += sr
        rhs = 0.0
        rhs += ql
        rhs += qr
        a = rhs / schur
        theta[k, 0] = a
        Jk = yy + prior[1] * prior[0] ** 2 + prior[3] * prior[2] ** 2 - a * (l5 + r5)
        b = brl0 - a * bsl0
        c = brl1 - a * bsl1
        theta[k, 1], theta[k, 2] = b, c
        Jk -= b * rl0 + c * rl1
        b = brr0 - a * bsr0
        c = brr1 - a * bsr1
        theta[k, 3], theta[k, 4] = b, c
        Jk -= b * rr0 + c * rr1
        J[k] = Jk
        var_a[k] = 1.0 / schur


@numba.njit(cache=True, nogil=True)
def _arange(lo, hi, step):  # pragma: no cover - compiled
    """``np.arange(lo, hi, step)`` as numpy fills it (``lo + i * ((lo + step) - lo)``), so
    the compiled search visits the very columns the numpy one did."""
    n = max(int(np.ceil((hi - lo) / step)), 0)
    out = np.empty(n)
    if n > 0:
        out[0] = lo
    if n > 1:
        delta = (lo + step) - lo
        out[1] = lo + delta
        for i in range(2, n):
            out[i] = lo + i * delta
    return out


@numba.njit(cache=True, nogil=True)
def _prefix(t, y):  # pragma: no cover - compiled
    """Prefix sums (N + 1, 8) of 1, t, t^2, t^3, t^4, y, t y, t^2 y, and sum y^2."""
    n = t.shape[0]
    P = np.zeros((n + 1, 8))
    yy = 0.0
    for i in range(n):
        ti, yi = t[i], y[i]
        t2 = ti * ti
        yy += yi * yi
        P[i + 1, 0] = P[i, 0] + 1.0
        P[i + 1, 1] = P[i, 1] + ti
        P[i + 1, 2] = P[i, 2] + t2
        P[i + 1, 3] = P[i, 3] + t2 * ti
        P[i + 1, 4] = P[i, 4] + t2 * t2
        P[i + 1, 5] = P[i, 5] + yi
        P[i + 1, 6] = P[i, 6] + ti * yi
        P[i + 1, 7] = P[i, 7] + t2 * yi
    return P, yy


@numba.njit(cache=True, nogil=True)
def _centred(P, m, side, c):  # pragma: no cover - compiled
    """One arm's sums about the corner column ``c`` (n, S1..S4, T0..T2: powers of t - c)
    from the prefix sums: the left arm the first ``m`` points, the right arm the rest."""
    n = P.shape[0] - 1
    q = np.empty(8)
    for j in range(8):
        q[j] = P[m, j] if side == 0 else P[n, j] - P[m, j]
    c2 = c * c
    c3 = c2 * c
    return (q[0], q[1] - c * q[0], q[2] - 2.0 * c * q[1] + c2 * q[0],
            q[3] - 3.0 * c * q[2] + 3.0 * c2 * q[1] - c3 * q[0],
            q[4] - 4.0 * c * q[3] + 6.0 * c2 * q[2] - 4.0 * c3 * q[1] + c2 * c2 * q[0],
            q[5], q[6] - c * q[5], q[7] - 2.0 * c * q[6] + c2 * q[5])


@numba.njit(cache=True, nogil=True)
def _fit_prefix(t, P, yy, grid, prior):  # pragma: no cover - compiled
    """:func:`two_arm_fit` for points sorted by t, from their prefix sums (:func:`_prefix`):
    O(K log N) instead of O(K N). t is centred and scaled (|t| ~ 1), so the binomial
    expansion about each corner column loses a few of the 16 digits at most (the corner
    moves by < 1e-9 px against the direct sums)."""
    K = grid.shape[0]
    theta, J, var_a = np.empty((K, 5)), np.empty(K), np.empty(K)
    for k in range(K):
        c = grid[k]
        m = np.searchsorted(t, c)  # t[i] < c for i < m: the left arm
        l0, l1, l2, l3, l4, l5, l6, l7 = _centred(P, m, 0, c)
        r0, r1, r2, r3, r4, r5, r6, r7 = _centred(P, m, 1, c)
        sl, ql, bsl0, bsl1, brl0, brl1, rl0, rl1 = _arm_normal(
            l0, l1, l2, l3, l4, l5, l6, l7, prior[0], prior[1])
        sr, qr, bsr0, bsr1, brr0, brr1, rr0, rr1 = _arm_normal(
            r0, r1, r2, r3, r4, r5, r6, r7, prior[2], prior[3])
        schur = 1e-12 + sl + sr
        a = (ql + qr) / schur
        theta[k, 0] = a
        Jk = yy + prior[1] * prior[0] ** 2 + prior[3] * prior[2] ** 2 - a * (l5 + r5)
        b = brl0 - a * bsl0
        cc = brl1 - a * bsl1
        theta[k, 1], theta[k, 2] = b, cc
        Jk -= b * rl0 + cc * rl1
        b = brr0 - a * bsr0
        cc = brr1 - a * bsr1
        theta[k, 3], theta[k, 4] = b, cc
        Jk -= b * rr0 + cc * rr1
        J[k] = Jk
        var_a[k] = 1.0 / schur
    return theta, J, var_a


@numba.njit(cache=True, nogil=True)
def _grid_search(t, y, lo, hi, step, prior, coarse, out):  # pragma: no cover - compiled
    """The best corner column over ``lo..hi`` (coarse grid, then ``step`` around its best,
    parabola-refined): out = (tc, J, J'', A^-1[0, 0], width, theta (5)); False without a
    grid."""
    if hi - lo < 3 * step:
        return False
    P, yy = _prefix(t, y)
    cgrid = _arange(lo, hi + 0.5 * step, coarse * step)
    _, Jc0, _ = _fit_prefix(t, P, yy, cgrid, prior)
    i0 = int(np.argmin(Jc0))
    k0 = cgrid[i0]
    jmin = Jc0[i0]
    s2 = max(jmin, 0.0) / max(t.shape[0] - 5, 1)
    width = 0.0
    for i in range(cgrid.shape[0]):
        if Jc0[i] <= jmin + s2:
            width = max(width, abs(cgrid[i] - k0))
    grid = _arange(max(lo, k0 - coarse * step), min(hi, k0 + coarse * step) + 0.5 * step,
                   step)
    m = grid.shape[0]
    if m < 3:
        return False
    _, J, _ = _fit_prefix(t, P, yy, grid, prior)
    k = int(np.argmin(J))
    curv = 0.0
    tc = grid[k]
    if 0 < k < m - 1:
        j0, j1, j2 = J[k - 1], J[k], J[k + 1]
        curv = (j0 - 2 * j1 + j2) / step ** 2
        if curv > 0:
            tc = min(max(grid[k] + 0.5 * step * (j0 - j2) / (j0 - 2 * j1 + j2),
                         grid[k] - step), grid[k] + step)
    one = np.empty(1)
    one[0] = tc
    theta, Jc, a00 = _fit_prefix(t, P, yy, one, prior)
    out[0], out[1], out[2], out[3], out[4] = tc, Jc[0], curv, a00[0], width
    out[5:10] = theta[0]
    return True


@numba.njit(cache=True, nogil=True)
def _two_arm_residuals(t, y, tc, th):  # pragma: no cover - compiled
    e = np.empty(t.shape[0])
    for i in range(t.shape[0]):
        x = t[i] - tc
        if x < 0:
            e[i] = y[i] - (th[0] + th[1] * x + th[2] * x * x)
        else:
            e[i] = y[i] - (th[0] + th[3] * x + th[4] * x * x)
    return e


@numba.njit("i8(f8[::1], f8[::1], i8, f8, f8[::1], i8, f8[::1])", cache=True, nogil=True)
def shallow_search(t, y, min_points, step, prior, coarse, out):  # pragma: no cover - compiled
    """The shallow corner's whole search (:func:`torchseam.track.shallow.shallow_corner`):
    the grid search over the corner columns of points ``t``, ``y`` (N,) sorted by t (from
    the ``min_points``-th point to the ``min_points``-th from the end), a robust pass (points
    within max(3 MAD, 0.5) of the fit kept) and a second search on the kept points. Writes
    out (10,) = (tc, J, J'', A^-1[0, 0], width, theta (5)) and returns the points kept, or
    0 (too few points, no grid)."""
    n = t.shape[0]
    keep = np.ones(n, np.bool_)
    nk = n
    for _ in range(2):  # a search, then one on the points the robust pass kept
        if nk < 2 * min_points + 5:
            return 0
        tk, yk = np.empty(nk), np.empty(nk)
        j = 0
        for i in range(n):
            if keep[i]:
                tk[j], yk[j] = t[i], y[i]
                j += 1
        if not _grid_search(tk, yk, tk[min_points - 1], tk[nk - min_points], step, prior,
                            coarse, out):
            return 0
        tc, th = out[0], out[5:10]
        e = _two_arm_residuals(tk, yk, tc, th)
        mad = 1.4826 * np.median(np.abs(e - np.median(e)))
        e_all = _two_arm_residuals(t, y, tc, th)
        lim = max(3.0 * mad, 0.5)
        same = True
        new_n = 0
        new = np.empty(n, np.bool_)
        for i in range(n):
            new[i] = abs(e_all[i]) < lim
            new_n += new[i]
            same = same and new[i] == keep[i]
        if same:
            break
        keep, nk = new, new_n
    return nk

