"""The part's compiled kernels (numba): the joints' ray casts.

The simulated sensor casts a few thousand rays a frame at a joint, in some seven calls (thirty
for a bevelled branch, whose groove's edges it bisects), most of them a handful of rays: as
numpy calls over all rays at once, their interpreter overhead was most of the cast's time. A
bevelled branch's wall (:class:`~torchseam.core.part.BevelledJoint`) is worse: a ray's first
entry into it is marched along its path through the wall's shell and bisected, up to some
eighty evaluations of the wall's material per ray, each a few dozen float operations; in numpy
every ray was marched to the end of its path. Here each ray is cast on its own: its march stops
at its first sample in the material, or past the main body's hit (which hides the branch beyond
it), and the crossing is refined by regula falsi (a handful of evaluations, not thirty
halvings). The entry points carry their signatures, so they are compiled (or loaded from numba's
on-disk cache) when this module is imported, which a joint does on its first ray cast (the
simulator's sensor, which alone casts rays, has loaded its own kernels by then, so this costs
milliseconds). ``nogil`` lets the caller's other threads run meanwhile.

The geometry ``g`` of a joint, (:data:`GEOMETRY_SIZE`,) float64: the branch axis's point ``o``
(3), its direction ``d`` (3), the directions ``e1``, ``e2`` (3 each) across it, the oval's
semi-axes' directions ``k1 e1``, ``k2 e2`` (3 each); ``k1``, ``k2`` (the ovality factors),
``r``, ``r_in`` (outer and inner radius of the round branch), the root gap, tan of the bevel
angle, the branch's bottom and top (along the axis from ``o``); the main body's four parameters
(``base_kind``: :data:`PIPE`, :data:`PLATE` or :data:`SPHERE`).
"""

from __future__ import annotations

import math

import numba
import numpy as np
from numba import types

#: the main body (``base_kind``) and its four parameters at the end of the geometry (unused 0)
PIPE = 0     # (a, b, s, 0): semi-axes along y and z, the main axis at y = -s
PLATE = 1    # (half, 0, 0, 0): the plate's top face z = 0, |x|, |y| <= half
SPHERE = 2   # (R, m_x, m_y, m_z): radius and centre
#: the length of a joint's geometry ``g``
GEOMETRY_SIZE = 30

_RAYS = types.Array(types.float64, 2, "C", readonly=True)  # the caller's arrays, read only
_ROW = types.Array(types.float64, 1, "C", readonly=True)
_CAST = types.Tuple((types.float64[::1], types.int8[::1]))   # (t, surface)


@numba.njit(cache=True, nogil=True, inline="always")
def _material(p0, p1, p2, g, base_kind):  # pragma: no cover - compiled
    """> 0 where the point ``(p0, p1, p2)`` of the wall's shell lies in the wall's material:
    above the bevel face and below the branch's top (``BevelledJoint``'s polar coordinates
    and root height)."""
    q0, q1, q2 = p0 - g[0], p1 - g[1], p2 - g[2]
    a = q0 * g[3] + q1 * g[4] + q2 * g[5]            # along the axis
    u = (q0 * g[6] + q1 * g[7] + q2 * g[8]) / g[18]  # the round branch's cross-section
    v = (q0 * g[9] + q1 * g[10] + q2 * g[11]) / g[19]
    rho = math.hypot(u, v)
    cos, sin = (u / rho, v / rho) if rho > 0.0 else (1.0, 0.0)   # of the angle phi
    # the inner generator at phi, where it meets the main body: the root edge's height
    r_in = g[21]
    c0 = g[0] + r_in * (cos * g[12] + sin * g[15])
    c1 = g[1] + r_in * (cos * g[13] + sin * g[16])
    c2 = g[2] + r_in * (cos * g[14] + sin * g[17])
    if base_kind == PIPE:
        y = c1 + g[28]
        s = math.sqrt(max(1.0 - (y / g[26]) ** 2, 1e-12))
        h = (g[27] * s - c2) / g[5]
    elif base_kind == PLATE:
        h = -c2 / g[5]
    else:
        w0, w1, w2 = c0 - g[27], c1 - g[28], c2 - g[29]
        gd = w0 * g[3] + w1 * g[4] + w2 * g[5]
        h = -gd + math.sqrt(max(gd * gd + g[26] ** 2 - (w0 * w0 + w1 * w1 + w2 * w2), 1e-12))
    face = (h + g[22]) + (rho - r_in) * g[23]
    return min(a - face, g[25] - a)


@numba.njit(cache=True, nogil=True, inline="always")
def _roots(A, B, C):  # pragma: no cover - compiled
    """Both roots (smaller, larger) of A t^2 + B t + C = 0, ``inf`` where there are none."""
    disc = B * B - 4 * A * C
    if not (disc >= 0 and A > 1e-12):
        return np.inf, np.inf
    sq = math.sqrt(disc)
    return (-B - sq) / (2 * A), (-B + sq) / (2 * A)


@numba.njit(cache=True, nogil=True, inline="always")
def _entry_root(A, B, C):  # pragma: no cover - compiled
    """Smallest positive root of A t^2 + B t + C = 0 for a ray starting outside (C > 0), else
    ``inf``."""
    disc = B * B - 4 * A * C
    if not (disc >= 0 and A > 1e-12 and C > 0):
        return np.inf
    t = (-B - math.sqrt(disc)) / (2 * A)
    return t if t > 0 else np.inf


@numba.njit(cache=True, nogil=True, inline="always")
def _main_hit(p0, p1, p2, v0, v1, v2, g, base_kind):  # pragma: no cover - compiled
    """The ray ``p + t v``'s entry into the main body, ``inf`` for none."""
    if base_kind == PIPE:   # ((y + s) / a)^2 + (z / b)^2 = 1
        a, b = g[26], g[27]
        y = p1 + g[28]
        return _entry_root((v1 / a) ** 2 + (v2 / b) ** 2,
                           2 * (y * v1 / a**2 + p2 * v2 / b**2),
                           (y / a) ** 2 + (p2 / b) ** 2 - 1.0)
    if base_kind == PLATE:   # the top face only: rays come from above the plate
        if not (p2 > 0.0 and v2 < -1e-12):
            return np.inf
        t = -p2 / v2
        half = g[26]
        if abs(p0 + t * v0) <= half and abs(p1 + t * v1) <= half and t > 0:
            return t
        return np.inf
    w0, w1, w2 = p0 - g[27], p1 - g[28], p2 - g[29]
    return _entry_root(v0 * v0 + v1 * v1 + v2 * v2, 2 * (w0 * v0 + w1 * v1 + w2 * v2),
                       (w0 * w0 + w1 * w1 + w2 * w2) - g[26] ** 2)


@numba.njit(cache=True, nogil=True, inline="always")
def _quadric(p0, p1, p2, v0, v1, v2, g):  # pragma: no cover - compiled
    """The ray ``p + t v`` against the branch's axis: ``(qa, da, A, B, qq)``, the origin's and
    the direction's parts along the axis and the quadratic ``A t^2 + B t + qq`` of the squared
    distance from the axis in the round branch's cross-section (``Joint._branch_quadric``)."""
    d0, d1, d2 = g[3], g[4], g[5]
    q0, q1, q2 = p0 - g[0], p1 - g[1], p2 - g[2]
    qa, da = q0 * d0 + q1 * d1 + q2 * d2, v0 * d0 + v1 * d1 + v2 * d2
    x0, x1, x2 = q0 - qa * d0, q1 - qa * d1, q2 - qa * d2
    y0, y1, y2 = v0 - da * d0, v1 - da * d1, v2 - da * d2
    un1, un2 = 1.0 / g[18] - 1.0, 1.0 / g[19] - 1.0
    if un1 != 0.0 or un2 != 0.0:   # an oval: its e1 and e2 parts scaled to the round one's
        a0, a1, a2, b0, b1, b2 = g[6], g[7], g[8], g[9], g[10], g[11]
        xa, xb = x0 * a0 + x1 * a1 + x2 * a2, x0 * b0 + x1 * b1 + x2 * b2
        ya, yb = y0 * a0 + y1 * a1 + y2 * a2, y0 * b0 + y1 * b1 + y2 * b2
        x0, x1, x2 = (x0 + un1 * xa * a0 + un2 * xb * b0, x1 + un1 * xa * a1 + un2 * xb * b1,
                      x2 + un1 * xa * a2 + un2 * xb * b2)
        y0, y1, y2 = (y0 + un1 * ya * a0 + un2 * yb * b0, y1 + un1 * ya * a1 + un2 * yb * b1,
                      y2 + un1 * ya * a2 + un2 * yb * b2)
    A = y0 * y0 + y1 * y1 + y2 * y2
    B = 2 * (x0 * y0 + x1 * y1 + x2 * y2)
    return qa, da, A, B, x0 * x0 + x1 * x1 + x2 * x2


@numba.njit(cache=True, nogil=True, inline="always")
def _wall_hit(p0, p1, p2, v0, v1, v2, t_max, g, base_kind, frac, steps,
              tol):  # pragma: no cover - compiled
    """The ray ``p + t v``'s first entry into a bevelled branch's wall, ``inf`` for none:
    where it crosses the outer cylinder above the shoulder, or first meets the material on its
    path through the wall's shell (outer cylinder to bore), tried at the fractions ``frac``
    (M,) of that stretch in order; the bracket before the first sample inside is narrowed to
    ``tol`` (mm along the ray) by at most ``steps`` steps of regula falsi (the Illinois
    variant, which halves the value kept at an end that stays, so both ends close in; a
    halving where a step would leave the bracket), and its end in the material answered. The
    march stops after its first sample beyond ``t_max``: an entry there lies beyond it."""
    r, r_in, top = g[20], g[21], g[25]
    qa, _, A, B, qq = _quadric(p0, p1, p2, v0, v1, v2, g)
    if A <= 1e-12:
        # a ray along the axis crosses no cylinder: in the shell from its origin, if at all
        if not (qq <= r * r and qq >= r_in * r_in):
            return np.inf
        s0, s1 = 0.0, 2.0 * (abs(top) + abs(qa)) + 1.0
    else:
        out0, out1 = _roots(A, B, qq - r * r)
        in0, _ = _roots(A, B, qq - r_in * r_in)
        s0 = max(out0, 0.0)
        # the shell's first stretch ends where the ray enters the bore, else where it leaves
        s1 = in0 if (in0 < np.inf and in0 > s0) else out1
        if not (out0 < np.inf and out1 > 0.0 and s1 > s0):
            return np.inf
    first = -1
    hi = s0
    f_lo = f_hi = 0.0
    for j in range(frac.shape[0]):
        hi = s0 + (s1 - s0) * frac[j]
        f_hi = _material(p0 + hi * v0, p1 + hi * v1, p2 + hi * v2, g, base_kind)
        if f_hi >= 0.0:
            first = j
            break
        f_lo = f_hi
        if hi > t_max:
            break
    if first < 0:
        return np.inf
    if first == 0:
        return s0   # the outer wall (or the origin is in the wall)
    lo = s0 + (s1 - s0) * frac[first - 1]
    side = 0   # which end the last step moved: +1 the one in the material, -1 the other
    for _ in range(steps):
        if hi - lo <= tol:
            break
        mid = (lo * f_hi - hi * f_lo) / (f_hi - f_lo)
        if not (lo < mid and mid < hi):
            mid = 0.5 * (lo + hi)
        f = _material(p0 + mid * v0, p1 + mid * v1, p2 + mid * v2, g, base_kind)
        if f >= 0.0:
            hi, f_hi = mid, f
            if side == 1:
                f_lo *= 0.5
            side = 1
        else:
            lo, f_lo = mid, f
            if side == -1:
                f_hi *= 0.5
            side = -1
    return hi


@numba.njit(_CAST(_RAYS, _RAYS, _ROW, types.int64), cache=True, nogil=True)
def raycast(origin, direction, g, base_kind):  # pragma: no cover - compiled
    """First hit of rays with a branch pipe set on its main body: ``(t, surface)``, (N,)
    distance along each ray (``inf`` for a miss) and (N,) surface id (0 none, 1 the main body,
    2 the branch), as :meth:`~torchseam.core.part.Joint.raycast`. ``origin`` (N, 3) or (1, 3),
    one for all rays; ``direction`` (N, 3) unit; ``g`` and ``base_kind`` the joint's (module
    docstring). The branch is its outer cylinder between its bottom and top."""
    n = direction.shape[0]
    t = np.empty(n)
    surface = np.zeros(n, np.int8)
    one = origin.shape[0] == 1
    r2, bottom, top = g[20] ** 2, g[24], g[25]
    for i in range(n):
        k = 0 if one else i
        p0, p1, p2 = origin[k, 0], origin[k, 1], origin[k, 2]
        v0, v1, v2 = direction[i, 0], direction[i, 1], direction[i, 2]
        t_main = _main_hit(p0, p1, p2, v0, v1, v2, g, base_kind)
        qa, da, A, B, qq = _quadric(p0, p1, p2, v0, v1, v2, g)
        t_branch = _entry_root(A, B, qq - r2)
        h = qa + t_branch * da   # the hit's height along the branch axis: the branch there?
        if not (h > bottom and h < top):
            t_branch = np.inf
        t[i] = min(t_main, t_branch)
        if t[i] < np.inf:
            surface[i] = 1 if t_main <= t_branch else 2
    return t, surface


@numba.njit(_CAST(_RAYS, _RAYS, _ROW, types.int64, _ROW, types.int64, types.float64),
            cache=True, nogil=True)
def bevel_raycast(origin, direction, g, base_kind, frac, steps,
                  tol):  # pragma: no cover - compiled
    """:func:`raycast` of a bevelled branch set on its main body with a root gap: the main
    body is cut to the branch's bore (a set-on branch), and the branch is its wall, cast by
    :func:`_wall_hit` with the march's fractions ``frac`` (M,), ``steps`` and ``tol``, its
    march stopping past the main body's hit."""
    n = direction.shape[0]
    t = np.empty(n)
    surface = np.zeros(n, np.int8)
    one = origin.shape[0] == 1
    for i in range(n):
        k = 0 if one else i
        p0, p1, p2 = origin[k, 0], origin[k, 1], origin[k, 2]
        v0, v1, v2 = direction[i, 0], direction[i, 1], direction[i, 2]
        t_main = _main_hit(p0, p1, p2, v0, v1, v2, g, base_kind)
        if t_main < np.inf:   # in the bore: cut out
            q0 = p0 + t_main * v0 - g[0]
            q1 = p1 + t_main * v1 - g[1]
            q2 = p2 + t_main * v2 - g[2]
            u = (q0 * g[6] + q1 * g[7] + q2 * g[8]) / g[18]
            v = (q0 * g[9] + q1 * g[10] + q2 * g[11]) / g[19]
            if math.hypot(u, v) < g[21]:
                t_main = np.inf
        t_branch = _wall_hit(p0, p1, p2, v0, v1, v2, t_main, g, base_kind, frac, steps,
                             tol)
        t[i] = min(t_main, t_branch)
        if t[i] < np.inf:
            surface[i] = 1 if t_main <= t_branch else 2
    return t, surface
