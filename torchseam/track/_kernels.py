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
