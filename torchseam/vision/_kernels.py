"""TIPM's compiled kernels (numba): the centre line and the corner search of
:class:`~torchseam.vision.tipm.Tipm`.

They are a few hundred float operations per column or per arm fit, run up to six arm fits a
frame: as numpy calls their interpreter overhead would be most of TIPM's time per frame
(figures: docs/benchmarks.md, "Figures behind design choices"). The entry points carry their
signatures, so they are compiled (or loaded from numba's on-disk cache) when this module is
imported, which :class:`Tipm` does when it is built, never in the middle of the live loop; a
call with other types raises instead of compiling.
``nogil`` lets the loop's other threads run meanwhile.
"""

from __future__ import annotations

import numba
import numpy as np

from torchseam.vision.quadfit import quad_normal_adjugate

# every kernel: cache=True (compiled once per install), nogil=True (the loop's threads run on)
NO_PRIOR = np.zeros((2, 4))  # prior rows (b0, c0, w_b, w_c) = 0: the plain least squares
CORNER_FAILS = {
    1: "no corner: the stripe cannot be split into two arms",
    2: "no corner: the left arm has only {count} points",
    3: "no corner: the right arm has only {count} points",
    4: "no corner: the arms do not meet",
    5: "no corner: the arms are parallel",
    6: "no corner: the arms meet far from the stripe",
}
adjugate = numba.njit(cache=True, nogil=True)(quad_normal_adjugate)


@numba.njit("b1[::1](u1[:, ::1], i8)", cache=True, nogil=True)
def border_columns(mask, reach):  # pragma: no cover - compiled
    """(W,) columns where the mask comes within ``reach`` rows of the top or bottom row."""
    h, w = mask.shape
    cut = np.zeros(w, np.bool_)
    for r in range(h):
        if min(r, h - 1 - r) < reach:
            for c in range(w):
                if mask[r, c]:
                    cut[c] = True
    return cut


@numba.njit("i8(i8, i8)", cache=True, nogil=True)
def reflect101(p, n):  # pragma: no cover - compiled
    """OpenCV's BORDER_REFLECT_101 index of row ``p`` in ``n`` rows (cv2.borderInterpolate)."""
    if n == 1:
        return 0
    while p < 0 or p >= n:
        p = -p if p < 0 else 2 * n - 2 - p
    return p


@numba.njit("void(u1[:, ::1], i8[::1], u1[::1])", cache=True, nogil=True)
def ridge_stats(ridge, hist, colmax):  # pragma: no cover - compiled
    """The statistics :meth:`Tipm._threshold` reads off a ridge (H, W) uint8, in one pass:
    the histogram of its values (``hist`` (256,), what ``cv2.calcHist`` counts) and each
    column's maximum (``colmax`` (W,), ``cv2.reduce(..., REDUCE_MAX)``)."""
    h, w = ridge.shape
    part = np.zeros((4, 256), np.int64)  # four partial histograms: no chain of increments
    colmax[:] = 0
    for r in range(h):
        row = ridge[r]
        for c in range(w):
            colmax[c] = max(colmax[c], row[c])
        c = 0
        while c + 4 <= w:
            part[0, row[c]] += 1
            part[1, row[c + 1]] += 1
            part[2, row[c + 2]] += 1
            part[3, row[c + 3]] += 1
            c += 4
        while c < w:
            part[0, row[c]] += 1
            c += 1
    for v in range(256):
        hist[v] = part[0, v] + part[1, v] + part[2, v] + part[3, v]


@numba.njit(cache=True, nogil=True)
def _root(parent, a):  # pragma: no cover - compiled
    while parent[a] != a:
        a = parent[a]
    return a


@numba.njit(cache=True, nogil=True)
def _row_runs(row, x0, w, r, rs, re, rr, parent, n, prev0, prev1, level
              ):  # pragma: no cover - compiled
    """The runs of pixels above ``level`` of ``row[x0:x0 + w]`` (row ``r`` of the box) from
    run ``n`` on, each joined to the runs ``[prev0, prev1)`` of the row above that touch it (a
    column apart at most: 8-connected); returns the run count after them."""
    c = 0
    j = prev0
    while c < w:
        while c < w and row[x0 + c] <= level:
            c += 1
        if c >= w:
            break
        s = c
        while c < w and row[x0 + c] > level:
            c += 1
        rs[n], re[n], rr[n] = s, c, r
        parent[n] = n
        best = n
        while j < prev1 and re[j] < s:  # ends left of column s - 1
            j += 1
        k = j
        while k < prev1 and rs[k] <= c:  # starts by column c (this run ends at c - 1)
            a = _root(parent, k)
            b = _root(parent, best)
            if a < b:
                parent[b] = a
            elif b < a:
                parent[a] = b
            best = min(a, b)
            k += 1
        if k > j:
            j = k - 1  # the last one touched may reach the next run too
        n += 1
    return n


@numba.njit("i8(i8, i8)", cache=True, nogil=True)
def runs_cap(h, w):  # pragma: no cover - compiled
    """The most runs an (h, w) box holds: every other pixel of every row."""
    return h * ((w + 1) // 2) + 1


@numba.njit(cache=True, nogil=True)
def _blobs(binary, y0, y1, x0, x1, min_area, work, level=0):  # pragma: no cover - compiled
    """The runs of the box ``[y0, y1) x [x0, x1)`` of ``binary`` (pixels above ``level``:
    :func:`_row_runs`) and
    their blobs: ``(runs, first columns, ends, rows (in the box), whether each run's blob has
    min_area px at least, blobs, blobs kept)``. ``work``: (4, runs_cap(box)) int64."""
    h, w = y1 - y0, x1 - x0
    rs = work[0]      # a run's first column (in the box) ...
    re = work[1]      # ... one past its last
    rr = work[2]      # ... its row
    parent = work[3]  # union-find over the runs
    n = 0
    prev0 = 0  # the runs of the row above: [prev0, n)
    for r in range(h):
        first = n
        n = _row_runs(binary[y0 + r], x0, w, r, rs, re, rr, parent, n, prev0, n, level)
        prev0 = first
    area = np.zeros(max(n, 1), np.int64)
    for i in range(n):
        a = _root(parent, i)
        parent[i] = a
        area[a] += re[i] - rs[i]
    blobs = kept = 0
    for i in range(n):
        if parent[i] == i:
            blobs += 1
            kept += area[i] >= min_area
    large = np.empty(max(n, 1), np.bool_)
    for i in range(n):
        large[i] = area[parent[i]] >= min_area
    return n, rs, re, rr, large, blobs, kept


@numba.njit("f8(i8[::1], u1[::1], f8, f8, f8)", cache=True, nogil=True)
def stripe_threshold(hist, colmax, noise_k, min_red, rel):  # pragma: no cover - compiled
    """:meth:`Tipm._threshold` of a ridge's histogram ``hist`` (256,) and column maxima
    ``colmax`` (W,) (fewer than 2^24 pixels: the float32 cumulative counts are whole numbers,
    exact), in numpy's arithmetic: the 90th percentile is the first level whose float32
    cumulative count reaches ``float32(0.9) * float32(total)`` (numpy 2 multiplies a float32
    by a Python float in float32), ``noise = noise_k * max(that, 1)``, the stripe's level
    the median of the column maxima above the noise (the middle one, or the mean of the
    middle two in float64), counted instead of sorted; returns ``max(min_red, noise,
    rel * level)``."""
    total = 0
    for v in range(256):
        total += hist[v]
    target = np.float32(0.9) * np.float32(total)
    cum = 0
    p90 = 256  # (np.searchsorted past the end: only an empty histogram)
    for v in range(256):
        cum += hist[v]
        if np.float32(cum) >= target:
            p90 = v
            break
    noise = noise_k * max(float(p90), 1.0)
    above = np.zeros(256, np.int64)
    n = 0
    for c in range(len(colmax)):
        if colmax[c] > noise:
            above[colmax[c]] += 1
            n += 1
    level = 0.0
    if n:
        lo = -1  # the values of rank (n - 1) // 2 and n // 2
        hi = -1
        seen = 0
        for v in range(256):
            seen += above[v]
            if lo < 0 and seen > (n - 1) // 2:
                lo = v
            if seen > n // 2:
                hi = v
                break
        level = float(hi) if n % 2 else (float(lo) + float(hi)) / 2.0
    return max(min_red, noise, rel * level)


@numba.njit(cache=True, nogil=True)
def _dilate_large(n, rs, re, rr, large, reach, mask, y0, x0, h, w):  # pragma: no cover
    """The runs of :func:`_blobs`' large blobs dilated into ``mask``'s box at ``(y0, x0)`` of
    ``h`` x ``w`` (a row ``k`` of the structuring element the centred run ``+-reach[k]``,
    clipped to the box); returns the box-relative ``(top, left, bottom, right)`` written
    (``bottom`` -1: nothing)."""
    d = len(reach) // 2
    top, left, bottom, right = h, w, -1, -1
    for i in range(n):
        if not large[i]:
            continue
        for k in range(len(reach)):
            r = rr[i] + k - d
            if r < 0 or r >= h:
                continue
            c0 = max(rs[i] - reach[k], 0)
            c1 = min(re[i] + reach[k], w)
            if c1 <= c0:
                continue
            mask[y0 + r, x0 + c0:x0 + c1] = 255
            top, bottom = min(top, r), max(bottom, r)
            left, right = min(left, c0), max(right, c1)
    return top, left, bottom, right


@numba.njit("UniTuple(i8, 6)(u1[:, ::1], i8, i8, i8[::1], i8[:, ::1], u1[:, ::1])",
            cache=True, nogil=True)
def stripe_blobs(ridge, level, min_area, reach, work, mask):  # pragma: no cover - compiled
    """:meth:`Tipm._mask` from the threshold on: the pixels of ``ridge`` (H, W) above
    ``level`` (an integer: ``cv2.threshold``'s binary image at a threshold in
    ``[level, level + 1)``), their blobs of ``min_area`` px at least, dilated into ``mask``
    (zeros on entry) as :func:`large_blobs_dilated` does in the box round the binary image
    (a blob's dilation reaches ``len(reach) // 2`` px at most: the box's margin; the image's
    edge clips both alike). Returns ``(pixels above, blobs kept, x, y, width, height)``, the
    last four ``cv2.boundingRect`` of ``mask``. ``work``: (4, :func:`runs_cap` (H, W)) int64
    at least."""
    h, w = ridge.shape
    if work.shape[0] < 4 or work.shape[1] < runs_cap(h, w):
        raise ValueError("stripe_blobs: work too small")
    n, rs, re, rr, large, blobs, kept = _blobs(ridge, 0, h, 0, w, min_area, work, level)
    above = 0
    for i in range(n):
        above += re[i] - rs[i]
    top, left, bottom, right = _dilate_large(n, rs, re, rr, large, reach, mask, 0, 0, h, w)
    if bottom < 0:
        return above, kept, 0, 0, 0, 0
    return above, kept, left, top, right - left, bottom - top + 1


@numba.njit("UniTuple(i8, 2)(u1[:, ::1], i8, i8, i8, i8, i8, u1[:, ::1])", cache=True,
            nogil=True)
def large_blobs(binary, y0, y1, x0, x1, min_area, out):  # pragma: no cover - compiled
    """The blobs of ``min_area`` px at least in the box ``[y0, y1) x [x0, x1)`` of ``binary``
    (H, W) uint8 (zero or not): ``out`` (y1 - y0, x1 - x0) is 255 on their pixels and 0
    elsewhere; returns ``(blobs, blobs kept)``. A blob is an 8-connected area of non-zero
    pixels, what ``cv2.connectedComponentsWithStats(..., connectivity=8)`` labels (the mask
    is the same to the bit; its labels and statistics, then a lookup table, took ~60 us of
    the tracker's ~0.3 ms TIPM window): here labelled by runs along the rows
    (:func:`_row_runs`), a union-find over the runs."""
    work = np.empty((4, runs_cap(y1 - y0, x1 - x0)), np.int64)
    n, rs, re, rr, large, blobs, kept = _blobs(binary, y0, y1, x0, x1, min_area, work)
    out[:, :] = 0
    for i in range(n):
        if large[i]:
            out[rr[i], rs[i]:re[i]] = 255
    return blobs, kept


@numba.njit("UniTuple(i8, 5)(u1[:, ::1], i8, i8, i8, i8, i8, i8[::1], i8[:, ::1], "
            "u1[:, ::1])", cache=True, nogil=True)
def large_blobs_dilated(binary, y0, y1, x0, x1, min_area, reach, work, mask
                        ):  # pragma: no cover - compiled
    """:func:`large_blobs` dilated, into ``mask`` (H, W), zeros on entry: its box
    ``[y0, y1) x [x0, x1)`` gets ``cv2.dilate`` of the blobs' image by a structuring element
    whose row ``k`` (of ``len(reach)``, centred) is the centred run ``+-reach[k]`` columns
    (an ellipse's), the box's outside not read nor written (what ``cv2.dilate`` of the box
    alone does). Returns ``(blobs kept, x, y, width, height)``: the bounding box of what it
    wrote, ``cv2.boundingRect`` of ``mask`` (all 0 when nothing was). ``work``: (4, at
    least :func:`runs_cap` of the box) int64, the caller's (reused: a fresh one for a whole
    window is ~0.8 MB, fresh pages on every call)."""
    if work.shape[0] < 4 or work.shape[1] < runs_cap(y1 - y0, x1 - x0):
        raise ValueError("large_blobs_dilated: work too small")
    n, rs, re, rr, large, blobs, kept = _blobs(binary, y0, y1, x0, x1, min_area, work)
    h, w = y1 - y0, x1 - x0
    top, left, bottom, right = _dilate_large(n, rs, re, rr, large, reach, mask, y0, x0, h, w)
    if bottom < 0:
        return kept, 0, 0, 0, 0
    return kept, x0 + left, y0 + top, right - left, bottom - top + 1


@numba.njit(cache=True, nogil=True)
def _box_ridge(red, ksize, mean_of, ridge):  # pragma: no cover - compiled
    """``ridge = red - mean_of[sum of red over ksize rows]``, saturating, the rows outside the
    image reflected (reflect-101): ``cv2.subtract(red, cv2.blur(red, (1, ksize)))`` with
    ``mean_of`` its rounding of a sum to the mean (a table: no division per pixel). The
    running column sums are uint16 (``ksize`` <= 257) and every step is unsigned, which
    lets the compiler vectorise the rows (signed index arithmetic made this 10x slower)."""
    h, w = red.shape
    half = ksize // 2
    acc = np.zeros(w, np.uint16)
    for j in range(-half, half + 1):
        row = red[reflect101(j, h)]
        for c in range(w):
            acc[c] += row[c]
    for r in range(h):
        row = red[r]
        out = ridge[r]
        for c in range(w):
            m = mean_of[np.uint64(acc[c])]
            out[c] = max(row[c], m) - m
        if r + 1 < h:
            add = red[reflect101(r + 1 + half, h)]
            sub = red[reflect101(r - half, h)]
            for c in range(w):
                acc[c] = acc[c] + add[c] - sub[c]


@numba.njit("void(u1[:, ::1], i8, u1[::1], u1[:, ::1])", cache=True, nogil=True)
def row_box(src, ksize, mean_of, out):  # pragma: no cover - compiled
    """``out = cv2.blur(src, (ksize, 1))`` of an (H, W) uint8 plane: the mean over ``ksize``
    columns (odd), the columns outside the image reflected (reflect-101), ``mean_of`` the
    rounding of a sum to the mean (see :func:`_box_ridge`). TIPM's second look (~35 us as
    the OpenCV call on the tracker's window)."""
    h, w = src.shape
    half = ksize // 2
    for r in range(h):
        row = src[r]
        o = out[r]
        acc = np.int64(0)
        for j in range(-half, half + 1):
            acc += row[reflect101(j, w)]
        for c in range(w):
            o[c] = mean_of[acc]
            if c + 1 < w:
                acc += np.int64(row[reflect101(c + 1 + half, w)]) - np.int64(
                    row[reflect101(c - half, w)])


@numba.njit("Tuple((i8, i8))(u1[:, :, ::1], i8, u1[::1], u1[:, ::1], u1[:, ::1], i8[::1], "
            "u1[::1])", cache=True, nogil=True)
def colour_ridge(frame, ksize, mean_of, red, ridge, hist, colmax):  # pragma: no cover
    """:meth:`Tipm.stripe_mask`'s planes of a BGR frame (H, W, 3) uint8 in one pass:
    ``red = R - max(G, B)`` (saturating), ``ridge = red - box(red)`` (saturating; ``box`` the
    mean over ``ksize`` rows, odd, OpenCV's ``blur`` with its reflect-101 border:
    :func:`_box_ridge`), the ridge's histogram and column maxima (:func:`ridge_stats`).
    Returns the pixels with R >= 250 (an arc flash that clips red) and with G >= 250 (white
    arc light)."""
    h, w = red.shape
    clip = np.zeros(w, np.int32)  # per-column counts (summed at the end: the loop vectorises)
    sat = np.zeros(w, np.int32)
    for r in range(h):
        px = frame[r].ravel()  # B, G, R interleaved
        out = red[r]
        for c in range(w):
            x, g = px[3 * c + 2], px[3 * c + 1]
            m = max(g, px[3 * c])
            out[c] = max(x, m) - m
            clip[c] += x >= 250
            sat[c] += g >= 250
    n_clip = 0
    n_sat = 0
    for c in range(w):
        n_clip += clip[c]
        n_sat += sat[c]
    _box_ridge(red, ksize, mean_of, ridge)
    ridge_stats(ridge, hist, colmax)
    return n_clip, n_sat


@numba.njit("void(u1[:, :, ::1], i8, u1[::1], u1[:, ::1], u1[:, ::1])", cache=True,
            nogil=True)
def brightness_line(frame, ksize, mean_of, grey, out):  # pragma: no cover - compiled
    """The plane :meth:`Tipm.find`'s brightness look reads a BGR frame (H, W, 3) uint8 by, in
    one pass instead of eight OpenCV calls (~0.2 ms on the tracker's window): ``grey`` the
    brightness, ``cv2.transform(frame, BRIGHTNESS)``, which is ``(B + G + R + 1) // 3``
    (the float sum is within ~1e-4 of ``(B + G + R) / 3``, whose fraction is 0, 1/3 or 2/3:
    never near a rounding tie); ``ridge = grey - box(grey)`` (:func:`_box_ridge`); ``line =
    grey - max(grey ksize // 2 rows above, ... below)`` (``cv2.dilate`` by ``Tipm._sides``:
    rows outside the image count as 0), all saturating; ``out = min(ridge, line + line)``."""
    h, w = grey.shape
    for r in range(h):
        px = frame[r].ravel()  # B, G, R interleaved
        g = grey[r]
        for c in range(w):
            g[c] = (np.uint32(px[3 * c]) + np.uint32(px[3 * c + 1]) + np.uint32(px[3 * c + 2])
                    + np.uint32(1)) // np.uint32(3)
    _box_ridge(grey, ksize, mean_of, out)
    half = ksize // 2
    zero = np.zeros(w, np.uint8)
    for r in range(h):
        g = grey[r]
        o = out[r]
        up = grey[r - half] if r - half >= 0 else zero
        dn = grey[r + half] if r + half < h else zero
        for c in range(w):
            m = max(up[c], dn[c])
            line = np.uint32(max(g[c], m) - m)
            o[c] = min(np.uint32(o[c]), min(line + line, np.uint32(255)))


@numba.njit("i8(u1[:, ::1], i8, u1[::1], u1[:, ::1], u1[:, ::1], i8[::1], u1[::1])",
            cache=True, nogil=True)
def mono_ridge(frame, ksize, mean_of, red, ridge, hist, colmax):  # pragma: no cover
    """:func:`colour_ridge` of a mono frame (H, W) uint8: its response is the intensity
    itself (copied into ``red``); returns the pixels >= 250."""
    h, w = red.shape
    n_sat = 0
    for r in range(h):
        px = frame[r]
        out = red[r]
        for c in range(w):
            out[c] = px[c]
        for c in range(w):
            n_sat += px[c] >= 250
    _box_ridge(red, ksize, mean_of, ridge)
    ridge_stats(ridge, hist, colmax)
    return n_sat


MAD_SIGMA = 1.4826  # sigma of a normal distribution per unit of its median absolute deviation
MAX_RUNS = 8  # runs of masked rows kept per column (more join the last one)


#: a tie-break between paths equal in length and smoothness: the brighter run, by at most
#: this share of one column's worth (a reflection beside the whole stripe is dimmer)
PATH_TIE = 0.01


@numba.njit("i8[::1](f8[:, ::1], f8[:, ::1], i8[::1], b1[::1], f8, f8)", cache=True,
            nogil=True)
def stripe_path(cen, weight, n_run, usable, step, step_cost):  # pragma: no cover
    """Which run of mask each column's stripe is: the longest smooth path across the columns.

    ``cen`` / ``weight`` (W, R): each column's runs (centroid row, summed response; weight 0:
    none), ``n_run`` (W,) how many, ``usable`` (W,) columns that may hold a point. A path
    steps from a run to one in a later column (over a dropout, any number of columns) at most
    ``step`` rows per column away; it scores one per column it holds, less ``step_cost`` per
    row it steps (the smoother of two ways wins) plus :data:`PATH_TIE` times the run's share
    of its column's strongest. The best path is found by dynamic programming; the search
    back over the columns stops where no path could do better (about O(W R^2) on a stripe).
    Returns (W,) the run index per column on it, -1 off it (a spatter streak in the same
    columns as the stripe, or alone in a dropout of it: in a mono frame only where it lies
    tells it from the stripe)."""
    w, r = cen.shape
    score = np.full((w, r), -np.inf)
    upto = np.full(w, -np.inf)  # the best score of a path ending in column c or before
    back = np.full((w, r, 2), -1, np.int64)
    best, end_c, end_k = -np.inf, -1, -1
    for c in range(w):
        if c > 0:
            upto[c] = upto[c - 1]
        if not usable[c]:
            continue
        top = 0.0
        for k in range(n_run[c]):
            top = max(top, weight[c, k])
        for k in range(n_run[c]):
            if weight[c, k] <= 0:
                continue
            y = cen[c, k]
            base, pc, pk = 0.0, -1, -1  # or the path starts here
            for c2 in range(c - 1, -1, -1):
                if upto[c2] <= base:
                    break  # no path ending there or before can do better (steps cost >= 0)
                g = c - c2
                for k2 in range(n_run[c2]):
                    if score[c2, k2] == -np.inf:
                        continue
                    dy = abs(y - cen[c2, k2])
                    if dy > step * g:
                        continue
                    sc = score[c2, k2] - step_cost * dy
                    if sc > base:
                        base, pc, pk = sc, c2, k2
            score[c, k] = base + 1.0 + PATH_TIE * weight[c, k] / top
            back[c, k, 0], back[c, k, 1] = pc, pk
            upto[c] = max(upto[c], score[c, k])
            if score[c, k] > best:
                best, end_c, end_k = score[c, k], c, k
    choice = np.full(w, -1, np.int64)
    c, k = end_c, end_k
    while c >= 0:
        choice[c] = k
        c, k = back[c, k, 0], back[c, k, 1]
    return choice


@numba.njit(cache=True, nogil=True)
def column_runs(response, mask, reach, box):  # pragma: no cover - compiled
    """Each column's runs of masked rows: ``(cen (W, R), weight (W, R), n_run (W,), usable
    (W,))``, their ``response``-weighed centroid row and summed response (up to
    :data:`MAX_RUNS` a column, more join the last), and the columns that hold a run with
    response and do not come within ``reach`` of the top or bottom row. ``box`` (x0, y0, x1,
    y1), end-exclusive, holds every masked pixel (outside it nothing is counted: the same
    runs as a walk over the whole mask, without the empty rows and columns)."""
    h, w = mask.shape
    n_run = np.zeros(w, np.int64)
    s0 = np.zeros((w, MAX_RUNS))
    s1 = np.zeros((w, MAX_RUNS))
    inside = np.zeros(w, np.bool_)
    for r in range(box[1], box[3]):
        for c in range(box[0], box[2]):
            if mask[r, c]:
                if not inside[c]:
                    inside[c] = True
                    if n_run[c] < MAX_RUNS:
                        n_run[c] += 1
                k = n_run[c] - 1
                x = float(response[r, c])
                s0[c, k] += x
                s1[c, k] += r * x
            else:
                inside[c] = False
    cut = border_columns(mask, reach)
    cen = np.zeros((w, MAX_RUNS))
    usable = np.zeros(w, np.bool_)
    for c in range(w):
        for k in range(n_run[c]):
            if s0[c, k] > 0:
                cen[c, k] = s1[c, k] / s0[c, k]
                usable[c] = not cut[c]
    return cen, s0, n_run, usable


@numba.njit("f8[:, ::1](u1[:, ::1], u1[:, ::1], f8, i8, i8, f8, f8, i8[::1])", cache=True,
            nogil=True)
def centre_line(response, mask, half, passes, reach, step, step_cost, box):  # pragma: no cover
    """Sub-pixel centre line (N, 2) (u, v) of :meth:`Tipm.centre` (``box`` (x0, y0, x1, y1),
    end-exclusive: where the mask has pixels, :func:`column_runs`).

    Per column the runs of masked rows (:func:`column_runs`); the stripe is the run on the
    :func:`stripe_path` (``step``, ``step_cost``), columns off it give no point. That centre
    is then moved ``passes`` times to the centroid of the response within ``half`` rows of
    it over a band of rows around it (mask or not)."""
    h, w = mask.shape
    cen, s0, n_run, usable = column_runs(response, mask, reach, box)
    choice = stripe_path(cen, s0, n_run, usable, step, step_cost)
    n = 0
    for c in range(w):
        n += choice[c] >= 0
    pts = np.empty((n, 2))
    band = int(np.ceil(half)) + 3  # wide enough for the window to move a few px
    i = 0
    for c in range(w):
        if choice[c] < 0:
            continue
        v = cen[c, choice[c]]
        r0 = int(np.rint(v))
        for _ in range(passes):
            a = b = 0.0
            for j in range(-band, band + 1):
                r = min(max(r0 + j, 0), h - 1)  # at the border a row counts again
                if abs(r - v) <= half:
                    x = float(response[r, c])
                    a += x
                    b += x * r
            if a > 0:  # nothing there: keep
                v = b / a
        pts[i, 0], pts[i, 1] = c, v
        i += 1
    return pts


@numba.njit(cache=True, nogil=True)
def quad_fit(x, y, keep, prior):  # pragma: no cover - compiled
    """(a, b, c) of the least-squares y = a + b x + c x^2 over the points where ``keep``, plus
    the ridge terms of ``prior`` (b0, c0, w_b, w_c): the 3x3 normal equations in closed form."""
    n = s1 = s2 = s3 = s4 = r0 = r1 = r2 = 0.0
    for i in range(x.size):
        if keep[i]:
            xi, yi = x[i], y[i]
            xx = xi * xi
            n += 1.0
            s1 += xi
            s2 += xx
            s3 += xx * xi
            s4 += xx * xx
            r0 += yi
            r1 += xi * yi
            r2 += xx * yi
    b0, c0, wb, wc = prior[0], prior[1], prior[2], prior[3]
    r1 += wb * b0
    r2 += wc * c0
    (A00, A01, A02, A11, A12, A22), det = adjugate((n, s1, s2, s3, s4), (wb, wc))
    return ((A00 * r0 + A01 * r1 + A02 * r2) / det, (A01 * r0 + A11 * r1 + A12 * r2) / det,
            (A02 * r0 + A12 * r1 + A22 * r2) / det)


@numba.njit(cache=True, nogil=True)
def line_sse(k, sx, sy, sxx, sxy, syy):  # pragma: no cover - compiled
    """Squared error of the least-squares line through ``k`` points with these sums."""
    vx = sxx - sx * sx / k
    cxy = sxy - sx * sy / k
    return syy - sy * sy / k - (cxy * cxy / vx if vx > 1e-9 else 0.0)


@numba.njit(cache=True, nogil=True)
def best_split(pts, min_pts):  # pragma: no cover - compiled
    """Column that best splits the points (N, 2) (u, v), sorted by u, into two straight lines
    (least squares over every split with running sums, O(N)); NaN with too few points."""
    n = pts.shape[0]
    if n < 2 * min_pts:
        return np.nan
    mu, mv = pts[:, 0].mean(), pts[:, 1].mean()  # centred: the sums stay well conditioned
    tx = ty = txx = txy = tyy = 0.0
    for i in range(n):
        du, dv = pts[i, 0] - mu, pts[i, 1] - mv
        tx += du
        ty += dv
        txx += du * du
        txy += du * dv
        tyy += dv * dv
    sx = sy = sxx = sxy = syy = 0.0
    best, best_sse = -1, np.inf
    for i in range(n - min_pts):
        du, dv = pts[i, 0] - mu, pts[i, 1] - mv
        sx += du
        sy += dv
        sxx += du * du
        sxy += du * dv
        syy += dv * dv
        if i < min_pts - 1:
            continue
        k = i + 1.0  # points 0..i on the left, i+1..n-1 on the right
        sse = (line_sse(k, sx, sy, sxx, sxy, syy)
               + line_sse(n - k, tx - sx, ty - sy, txx - sxx, txy - sxy, tyy - syy))
        if sse < best_sse:
            best, best_sse = i, sse
    if best < 0:
        return np.nan
    return 0.5 * (pts[best, 0] + pts[best + 1, 0])


@numba.njit(cache=True, nogil=True)
def fit_arms(pts, u0, gap, window, min_pts, prior, arms):  # pragma: no cover - compiled
    """Quadratic fit of each arm beside column ``u0`` into ``arms`` (2, 3), centred on ``u0``;
    returns (fail code, its count, rms over all points, rms over the kept points, x of the
    meeting point relative to ``u0``), each rms the worse arm's. ``pts`` is
    sorted by u, so each arm's window is a slice."""
    u = pts[:, 0]
    rms = rms_in = 0.0
    for side in range(2):
        lo, hi = (u0 - window, u0 - gap) if side == 0 else (u0 + gap, u0 + window)
        i0 = np.searchsorted(u, lo)
        i1 = np.searchsorted(u, hi + 1e-9)
        m = i1 - i0
        if m < min_pts:
            return 2.0 + side, float(m), 0.0, 0.0, 0.0
        x = u[i0:i1] - u0
        y = np.ascontiguousarray(pts[i0:i1, 1])
        keep = np.ones(m, np.bool_)
        k0, k1, k2 = quad_fit(x, y, keep, prior[side])
        res = y - (k0 + k1 * x + k2 * x * x)
        ss = (res * res).sum()
        # one robust pass: refit without the points far off the fit (spatter touching the
        # stripe), more than 3 sigma, the sigma taken from the residuals' median absolute
        # deviation: their RMS grows with the very outliers it is to reject (a streak along an
        # arm, in a mono frame where no colour tells it from the stripe, hid in its own
        # spread). Two RMS about the refit arm: over every point (how clean the stripe is:
        # dropped points count against it, TIPM refuses a dirty one) and over the kept ones
        # (how well the line is placed: the corner's noise as a measurement).
        lim = max(3.0 * MAD_SIGMA * np.median(np.abs(res - np.median(res))), 0.5)
        n_good = 0
        for j in range(m):
            keep[j] = abs(res[j]) < lim
            n_good += keep[j]
        ss_in, n_in = ss, m
        if min_pts <= n_good < m:
            k0, k1, k2 = quad_fit(x, y, keep, prior[side])
            ss = ss_in = 0.0
            for j in range(m):
                r = y[j] - (k0 + k1 * x[j] + k2 * x[j] * x[j])
                ss += r * r
                if keep[j]:
                    ss_in += r * r
            n_in = n_good
        arms[side, 0], arms[side, 1], arms[side, 2] = k0, k1, k2
        rms = max(rms, np.sqrt(ss / m))
        rms_in = max(rms_in, np.sqrt(ss_in / n_in))
    c0, c1, c2 = arms[0, 0] - arms[1, 0], arms[0, 1] - arms[1, 1], arms[0, 2] - arms[1, 2]
    if abs(c2) > 1e-12:
        disc = c1 * c1 - 4.0 * c2 * c0
        if disc < 0:
            return 4.0, 0.0, rms, rms_in, 0.0
        sq = np.sqrt(disc)
        xa, xb = (-c1 - sq) / (2.0 * c2), (-c1 + sq) / (2.0 * c2)
        x_meet = xa if abs(xa) <= abs(xb) else xb
    elif abs(c1) > 1e-12:
        x_meet = -c0 / c1
    else:
        return 5.0, 0.0, rms, rms_in, 0.0
    if abs(x_meet) > window:
        return 6.0, 0.0, rms, rms_in, 0.0
    return 0.0, 0.0, rms, rms_in, x_meet


@numba.njit("Tuple((i8, i8, f8, f8, f8, f8, f8, f8))(f8[:, ::1], f8, f8, i8, f8[:, ::1], "
            "f8[:, ::1])",
            cache=True, nogil=True)
def corner(pts, gap, window, min_pts, prior, arms):  # pragma: no cover - compiled
    """The corner search of :meth:`Tipm.corner` on centre-line points (N, 2) sorted by u:
    (fail code (0: found, see ``CORNER_FAILS``), its count, u0, x, rms, inlier rms, v, corner
    angle in degrees); the arms (2, 3), centred on u0, go into ``arms``."""
    u0 = best_split(pts, min_pts)
    if np.isnan(u0):
        return 1, 0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
    # The two-line split is only roughly at the corner (the arms are curved): fit the arms
    # next to it, move to where they meet, and refit there until the corner stays put.
    x = rms = rms_in = 0.0
    for it in range(3):
        code, count, rms, rms_in, x = fit_arms(pts, u0, gap, window, min_pts, prior, arms)
        if code:
            return int(code), int(count), u0, 0.0, rms, rms_in, 0.0, 0.0
        if abs(x) < 0.05 or it == 2:
            break
        u0 += x
    v = arms[0, 0] + x * (arms[0, 1] + x * arms[0, 2])
    # angle between the arms at the corner (slopes b + 2 c x)
    s1 = arms[0, 1] + 2.0 * arms[0, 2] * x
    s2 = arms[1, 1] + 2.0 * arms[1, 2] * x
    cosang = (1.0 + s1 * s2) / (np.sqrt(1.0 + s1 * s1) * np.sqrt(1.0 + s2 * s2))
    corner = np.degrees(np.arccos(min(max(-cosang, -1.0), 1.0)))
    return 0, 0, u0, x, rms, rms_in, v, corner


@numba.njit("f8[:, ::1](u1[:, ::1], f8[:, ::1], i8)", cache=True, nogil=True)
def cross_sections(response, pts, half):  # pragma: no cover - compiled
    """(N, 2 half + 1) the response down each centre-line point's column (``pts`` (N, 2) (u,
    v)), rows ``round(v) - half`` to ``round(v) + half``, clamped to the image."""
    h = response.shape[0]
    out = np.empty((pts.shape[0], 2 * half + 1))
    for i in range(pts.shape[0]):
        c, r0 = int(pts[i, 0]), int(np.rint(pts[i, 1])) - half
        for j in range(2 * half + 1):
            out[i, j] = response[min(max(r0 + j, 0), h - 1), c]
    return out


@numba.njit(cache=True, nogil=True)
def _vertex(prof, i, j):  # pragma: no cover - compiled
    """Sub-pixel position of the local maximum at sample ``j`` of cross-section ``i``: the
    vertex of the parabola through it and its two neighbours."""
    d = prof[i, j - 1] - 2.0 * prof[i, j] + prof[i, j + 1]
    return j + (0.5 * (prof[i, j - 1] - prof[i, j + 1]) / d if d < 0.0 else 0.0)


@numba.njit("f8[:, ::1](f8[:, ::1], f8, f8)", cache=True, nogil=True)
def two_ridges(prof, ridge, dip):  # pragma: no cover - compiled
    """Per stripe cross-section (a row of ``prof`` (N, K)): ``(distance, middle)`` of its two
    strongest local maxima (samples from its first; sub-pixel), NaN where it does not hold two
    ridges: each at least ``ridge`` times the cross-section's peak, the profile between them
    falling to ``dip`` times the weaker or below."""
    n, k = prof.shape
    out = np.full((n, 2), np.nan)
    for i in range(n):
        a = b = -1  # the strongest local maximum and the next
        for j in range(1, k - 1):
            x = prof[i, j]
            if x > 0.0 and x >= prof[i, j - 1] and x > prof[i, j + 1]:
                if a < 0 or x > prof[i, a]:
                    a, b = j, a
                elif b < 0 or x > prof[i, b]:
                    b = j
        if b < 0:
            continue
        peak = 0.0
        for j in range(k):
            peak = max(peak, prof[i, j])
        lo, hi = min(a, b), max(a, b)
        weak = min(prof[i, a], prof[i, b])
        if weak < ridge * peak:
            continue
        low = weak
        for j in range(lo, hi + 1):
            low = min(low, prof[i, j])
        if low > dip * weak:
            continue
        va, vb = _vertex(prof, i, lo), _vertex(prof, i, hi)
        out[i, 0], out[i, 1] = vb - va, 0.5 * (va + vb)
    return out


@numba.njit(cache=True, nogil=True)
def _tls(p, keep):  # pragma: no cover - compiled
    """The total-least-squares line through the kept points of ``p`` (N, 2): its centre, its
    unit direction (the scatter matrix's major axis, in closed form: tan 2 theta =
    2 sxy / (sxx - syy)) and every point's signed distance to it (N,)."""
    n = 0
    cx = cy = 0.0
    for i in range(p.shape[0]):
        if keep[i]:
            cx += p[i, 0]
            cy += p[i, 1]
            n += 1
    cx /= n
    cy /= n
    sxx = syy = sxy = 0.0
    for i in range(p.shape[0]):
        if keep[i]:
            du, dv = p[i, 0] - cx, p[i, 1] - cy
            sxx += du * du
            syy += dv * dv
            sxy += du * dv
    theta = 0.5 * np.arctan2(2.0 * sxy, sxx - syy)
    dx, dy = np.cos(theta), np.sin(theta)
    r = np.empty(p.shape[0])
    for i in range(p.shape[0]):
        r[i] = -(p[i, 0] - cx) * dy + (p[i, 1] - cy) * dx
    return cx, cy, dx, dy, r


@numba.njit("UniTuple(f8, 5)(f8[:, :], b1)", cache=True, nogil=True)
def fit_line(p, robust):  # pragma: no cover - compiled
    """:func:`torchseam.vision.profiles.fit_line`'s line through points (N, 2), N >= 2:
    ``(cx, cy, dx, dy, rms)``, the direction pointing to +u (the profiles read dozens of short
    pieces a frame: as numpy calls each took ~0.15 ms, mostly two medians' overhead)."""
    n = p.shape[0]
    keep = np.ones(n, np.bool_)
    cx, cy, dx, dy, r = _tls(p, keep)
    if robust and n >= 6:
        dev = np.abs(r - np.median(r))
        lim = max(3 * 1.4826 * np.median(dev), 1.0)
        kept = 0
        for i in range(n):
            keep[i] = dev[i] <= lim
            kept += keep[i]
        if 2 <= kept < n:
            cx, cy, dx, dy, r = _tls(p, keep)
    else:
        kept = n
    ss = 0.0
    for i in range(n):
        if keep[i]:
            ss += r[i] * r[i]
    if dx < 0.0:
        dx, dy = -dx, -dy
    return cx, cy, dx, dy, np.sqrt(ss / kept)


@numba.njit("i8(u1[:, ::1], i8, i8, i8, u1[:, ::1])", cache=True, nogil=True)
def thin_clipped_runs(plane, level, max_rows, min_area, out):  # pragma: no cover - compiled
    """:func:`torchseam.vision.tipm.thin_clipped_runs` into ``out`` (H, W) uint8, zeros on
    entry: 255 on each column's one run of pixels ``>= level`` at most ``max_rows`` tall and
    bounded by lower pixels above and below (a column with two such runs or more keeps none),
    in 8-connected areas of ``min_area`` px at least; returns the columns kept. With one run
    a column at most, an area is a chain of runs in consecutive columns, each touching the
    next (a row apart at most), so it is summed along the columns, not labelled (the numpy
    and ``cv2.connectedComponentsWithStats`` version took ~1 ms on the tracker's window)."""
    h, w = plane.shape
    runs = np.zeros(w, np.int64)  # thin bounded runs found in the column
    top = np.zeros(w, np.int64)
    end = np.zeros(w, np.int64)   # the last one's rows [top, end)
    for c in range(w):  # column by column (a window is in cache: 2x faster than by rows)
        start = -1  # the open run's first row; -1: none, or one from the top row
        prev = plane[0, c] >= level
        n = 0
        t = 0
        e = 0
        for r in range(1, h):
            cur = plane[r, c] >= level
            if cur != prev:
                if cur:
                    start = r
                else:
                    if start >= 0 and r - start <= max_rows:
                        n += 1
                        t = start
                        e = r
                    start = -1
                prev = cur
        runs[c] = n
        top[c] = t
        end[c] = e
    # (a run still open at the bottom row has no end: it is not counted)
    kept = 0
    c = 0
    while c < w:
        if runs[c] != 1:
            c += 1
            continue
        c1 = c + 1  # the chain of touching runs from column c: columns [c, c1)
        area = end[c] - top[c]
        while (c1 < w and runs[c1] == 1 and top[c1] <= end[c1 - 1]
               and top[c1 - 1] <= end[c1]):
            area += end[c1] - top[c1]
            c1 += 1
        if area >= min_area:
            for k in range(c, c1):
                for r in range(top[k], end[k]):
                    out[r, k] = 255
            kept += c1 - c
        c = c1
    return kept
