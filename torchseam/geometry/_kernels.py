"""ECAL's compiled kernel (numba): the arm crossings on every circle of one frame.

Finding the runs of stripe along ~8 circles of ~380 samples, their grey-weighted mean angle and
their connection to the feature point is a few thousand comparisons: as some 40 numpy calls
(cumulative sums over the doubled rings, sorts, searches) the interpreter overhead would be
most of ECAL's time (figures: docs/benchmarks.md, "Figures behind design choices"). The
signature is given, so the kernel is compiled (or loaded from
numba's on-disk cache) when this module is imported, which :class:`~torchseam.geometry.ecal.Ecal`
does when it is built, never in the middle of the live loop.
"""

from __future__ import annotations

import numba
import numpy as np


@numba.njit("void(u1[:, :], u1[:, :], b1, f8[:, ::1], f8[:, ::1], f8, f8, b1[:, ::1], "
            "f8[:, ::1])", cache=True, nogil=True)
def polar(mask, intensity, has_val, ru, rv, u, v, on, val):  # pragma: no cover - compiled
    """:meth:`Ecal.polar` of a feature point ``(u, v)`` whose rings lie inside the image: the
    sample ``(i, j)`` is the pixel ``(rint(u + ru[i, j]), rint(v + rv[i, j]))``; ``on`` is
    whether ``mask`` is non-zero there, ``val`` the ``intensity`` there (``has_val``), as
    float64. The numpy version's arithmetic (the same additions, the same rounding) without
    its ~10 passes over the (R, N) rings."""
    for i in range(ru.shape[0]):
        for j in range(ru.shape[1]):
            c = int(np.rint(ru[i, j] + u))
            r = int(np.rint(rv[i, j] + v))
            on[i, j] = mask[r, c] > 0
            if has_val:
                val[i, j] = np.float64(intensity[r, c])


@numba.njit("Tuple((i8[::1], f8[::1], i8[::1]))(b1[:, ::1], f8[:, ::1], i8[::1], f8[::1], "
            "f8[::1], f8[::1], f8, f8, f8)", cache=True, nogil=True)
def crossings(on, val, rows, radii, cos_t, sin_t, min_width, max_width, min_connected
              ):  # pragma: no cover - compiled
    """Arm crossings on the circles ``rows`` of a polar sampling ``on`` (R, N) (ring r at radius
    ``radii[r]``, sample j at angle ``theta_j`` with ``cos_t``, ``sin_t`` (N,)); ``val`` (R, N)
    grey levels, or (0, 0) for none.

    A crossing is a run of stripe along a circle (background before and after it, going round)
    whose arc length is within [min_width, max_width] px and which is joined to the feature
    point: stripe on at least ``min_connected`` of the rings from 0.15 of its ring index out to
    its own, at the run's mean angle (grey-weighted where the run has grey levels).

    Returns (circle index (M,), angle (M,) rad, rejected runs per circle (C,)) for the M
    accepted crossings, by circle then by where their run starts (angle 0 upwards).
    """
    n = on.shape[1]
    weighted = val.shape[0] > 0
    c_out = np.empty(64, np.int64)
    a_out = np.empty(64)
    m = 0
    rejected = np.zeros(rows.size, np.int64)
    for c in range(rows.size):
        row = rows[c]
        r = radii[row]
        lo = int(0.15 * row)
        for s in range(n):
            if not on[row, s] or on[row, s - 1]:  # s - 1 = -1 wraps: circular
                continue
            # a rise at s: the run goes on to the first background sample going round
            length = 1
            while length < n and on[row, (s + length) % n]:
                length += 1
            zc = zs = 0.0
            wc = ws = wsum = 0.0
            for t in range(s, s + length):
                j = t % n
                zc += cos_t[j]
                zs += sin_t[j]
                if weighted:
                    x = val[row, j]
                    wsum += x
                    wc += x * cos_t[j]
                    ws += x * sin_t[j]
            if weighted and wsum > 0:
                zc, zs = wc, ws
            ang = np.arctan2(zs, zc)
            width = length * (2.0 * np.pi / n) * r
            good = min_width <= width <= max_width
            if good:
                k = int(np.rint(ang * n / (2.0 * np.pi))) % n
                count = 0
                for i in range(lo, row + 1):
                    count += on[i, k]
                good = count >= min_connected * (row + 1 - lo)
            if not good:
                rejected[c] += 1
                continue
            if m == c_out.size:
                c_out = np.concatenate((c_out, np.empty(m, np.int64)))
                a_out = np.concatenate((a_out, np.empty(m)))
            c_out[m], a_out[m] = c, ang
            m += 1
    return c_out[:m].copy(), a_out[:m].copy(), rejected
