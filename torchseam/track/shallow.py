"""The corner of a nearly straight stripe: both arms' whole length, the kink's uncertainty.

TIPM (:meth:`~torchseam.vision.tipm.Tipm.corner`) fits each arm over the columns next to the
corner and refuses a stripe that bends by less than ``min_corner_deg``: there the two fits
trade the corner's place along the stripe against their slopes and curvatures, and the answer
is a guess. Where the saddle's dihedral angle makes the stripe almost straight (arms within a
few degrees of collinear), or glare over the corner leaves only the arms, the place along the
stripe is still weakly in the image: in where the slope breaks. :func:`shallow_corner` reads
it from every centre-line point of both arms and says how weakly.

The model: the centre line ``v(u)`` is two quadratics that meet at the corner column ``u_c``,

    v = a + b_L x + c_L x^2   (x = u - u_c < 0),     v = a + b_R x + c_R x^2   (x >= 0),

fitted by least squares (5 unknowns, a curvature prior ``w_c (c - c0)^2`` per arm when given)
for every ``u_c`` on a grid (coarse, then ``step_px`` around the best; compiled), the best
``u_c`` refined by a parabola through the sum of squares ``J(u_c)``, a robust pass (MAD) and
a second search. The uncertainty: with the residual variance ``s^2 = J_min / (n - 5)``,

    var(u_c) = max(2 s^2 / J''(u_c), w^2)   (J rises by s^2 one sigma away: Delta chi^2 = 1;
                                             w: the farthest coarse-grid column within s^2
                                             of J_min, where J has other low minima)
    cov(uv)  = var(u_c) t t^T + var(a) e_v e_v^T,   t = (1, (b_L + b_R) / 2),  e_v = (0, 1)

``J''`` scales as the square of the slope break, so the sigma along the stripe grows as
``1 / kink`` as the kink flattens, and it stays small across the stripe (``var(a)``, the
fitted ``a``'s variance at the best ``u_c``): a straight stripe still says where the line is.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from torchseam.core.kernels import load_kernels

__all__ = ["ShallowFix", "shallow_corner"]

#: the sums of squares are taken over a centred, scaled column (conditioning): u = m + S t
_SCALE = 100.0
#: the grid is searched at COARSE steps first, then at single steps around the best
COARSE = 4


@dataclass
class ShallowFix:
    """A corner read from the slope break of a nearly straight stripe.

    Attributes:
        uv: (2,) the corner (px, the points' frame).
        cov: (2, 2) its covariance per unit point noise factor (px^2): ``s^2``-scaled, along
            the stripe ``var(u_c)``, across it ``var(a)``.
        kink_deg: how far from collinear the two arms' tangents are at the corner (degrees).
        sigma_px: the residual std ``s`` of the kept points.
        slope: the mean of the two arms' slopes at the corner (dv/du).
        n: the points kept.
    """

    uv: np.ndarray
    cov: np.ndarray
    kink_deg: float
    sigma_px: float
    slope: float
    n: int

    @property
    def along_px(self) -> float:
        """The corner's std along the stripe (the larger axis of ``cov``), px."""
        return float(np.sqrt(max(np.linalg.eigvalsh(self.cov)[-1], 0.0)))


def _solve(t: np.ndarray, y: np.ndarray, tc: np.ndarray, prior: np.ndarray
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The two-arm fit at every corner column ``tc`` (K,): (theta (K, 5) = (a, b_L, c_L, b_R,
    c_R), J (K,), var(a) per unit noise (K,)); compiled (``_kernels.two_arm_fit``: each
    arm's (b, c) for a given ``a`` from its 2x2 normal matrix, ``a`` from the Schur
    complement)."""
    K = len(tc)
    theta, J, var_a = np.empty((K, 5)), np.empty(K), np.empty(K)
    load_kernels(__package__).two_arm_fit(t, y, np.ascontiguousarray(tc, dtype=np.float64),
                                          prior, theta, J, var_a)
    return theta, J, var_a


def _search(t: np.ndarray, y: np.ndarray, lo: float, hi: float, step: float,
            prior: np.ndarray
            ) -> tuple[float, np.ndarray, float, float, float, float] | None:
    """Best corner column over the grid ``lo..hi`` (scaled units), parabola-refined: (tc,
    theta (5,), J at tc, J'' at tc, A^-1[0, 0] at tc, the half-width of the coarse grid's
    columns whose J lies within s^2 of the least); None without a grid."""
    if hi - lo < 3 * step:
        return None
    coarse = np.arange(lo, hi + 0.5 * step, COARSE * step)
    _, Jc0, _ = _solve(t, y, coarse, prior)
    k0 = float(coarse[int(np.argmin(Jc0))])
    s2 = max(float(Jc0.min()), 0.0) / max(len(t) - 5, 1)
    width = float(np.max(np.abs(coarse[Jc0 <= Jc0.min() + s2] - k0)))
    grid = np.arange(max(lo, k0 - COARSE * step), min(hi, k0 + COARSE * step) + 0.5 * step,
                     step)
    if len(grid) < 3:
        return None
    _, J, _ = _solve(t, y, grid, prior)
    k = int(np.argmin(J))
    curv = 0.0
    tc = float(grid[k])
    if 0 < k < len(grid) - 1:
        j0, j1, j2 = J[k - 1], J[k], J[k + 1]
        curv = (j0 - 2 * j1 + j2) / step ** 2
        if curv > 0:
            tc = float(np.clip(grid[k] + 0.5 * step * (j0 - j2) / (j0 - 2 * j1 + j2),
                               grid[k] - step, grid[k] + step))
    theta, Jc, a00 = _solve(t, y, np.array([tc]), prior)
    return tc, theta[0], float(Jc[0]), curv, float(a00[0]), width


def _residuals(t: np.ndarray, y: np.ndarray, tc: float, th: np.ndarray) -> np.ndarray:
    x = t - tc
    left = x < 0
    return y - np.where(left, th[0] + th[1] * x + th[2] * x * x,
                        th[0] + th[3] * x + th[4] * x * x)


def shallow_corner(pts: np.ndarray, min_points: int = 15, step_px: float = 1.0,
                   curvature: np.ndarray | None = None, curvature_weight: float = 0.0,
                   max_along_px: float = 1e4) -> ShallowFix | None:
    """The corner of centre-line points ``pts`` (N, 2) (u, v), sorted by u, read from the
    slope break between two quadratic arms over the whole length of both (see the module
    docstring), with its covariance.

    Args:
        min_points: each arm has at least this many points.
        step_px: the grid of corner columns searched (px).
        curvature: (2,) the arms' curvature (1/px) to pull toward (the live tracker's arm
            prior: the curvature does not change as the kink flattens, the slopes do), with
            ``curvature_weight`` (squared point noise over its variance, px^2 / (1/px)^2);
            None: no prior.
        max_along_px: the std along the stripe is capped here (a straight stripe: no place).

    Returns:
        the fix, or None (too few points).

    Example:
        >>> u = np.arange(0.0, 200.0)
        >>> v = 100 + np.where(u < 120, 0.0, np.tan(np.radians(3.0)) * (u - 120))
        >>> v = v + np.random.default_rng(0).normal(0, 0.2, u.size)
        >>> f = shallow_corner(np.stack([u, v], 1))
        >>> bool(abs(f.uv[0] - 120) < 3 * f.along_px), round(f.kink_deg)
        (True, 3)
    """
    pts = np.asarray(pts, dtype=np.float64)
    if pts.ndim != 2 or len(pts) < 2 * min_points + 5:
        return None
    u, v = pts[:, 0], pts[:, 1]
    m, vm = float(u.mean()), float(v.mean())
    t, y = (u - m) / _SCALE, v - vm
    prior = np.zeros(4)
    if curvature is not None and curvature_weight > 0:
        s2 = _SCALE * _SCALE
        w = curvature_weight / s2 ** 2  # w (c - c0)^2 in px -> in the scaled units
        prior[:] = (float(curvature[0]) * s2, w, float(curvature[1]) * s2, w)
    step = step_px / _SCALE
    keep = np.ones(len(t), bool)
    best = None
    for _ in range(2):  # a search, then one on the points the robust pass kept
        tk, yk = np.ascontiguousarray(t[keep]), np.ascontiguousarray(y[keep])
        if len(tk) < 2 * min_points + 5:
            return None
        best = _search(tk, yk, float(tk[min_points - 1]), float(tk[-min_points]), step, prior)
        if best is None:
            return None
        e = _residuals(tk, yk, best[0], best[1])
        mad = 1.4826 * float(np.median(np.abs(e - np.median(e))))
        e_all = _residuals(t, y, best[0], best[1])
        new = np.abs(e_all) < max(3.0 * mad, 0.5)
        if np.array_equal(new, keep):
            break
        keep = new
    assert best is not None
    tc, th, J, curv, a00, width = best
    n = int(keep.sum())
    s2 = max(J, 0.0) / max(n - 5, 1)
    # the local curvature's sigma, or, where J has other minima about as low (a spatter
    # streak, glare bending an arm), the reach of those (Delta chi^2 = 1 over the whole grid)
    var_u = min(max(2.0 * s2 / curv if curv > 0 else np.inf, width ** 2) * _SCALE ** 2,
                max_along_px ** 2)
    b_left, b_right = th[1] / _SCALE, th[3] / _SCALE  # dv/du at the corner, px
    slope = 0.5 * (b_left + b_right)
    tvec = np.array([1.0, slope])
    cov = var_u * np.outer(tvec, tvec) + np.diag([0.0, s2 * a00])
    kink = abs(float(np.degrees(np.arctan(b_right) - np.arctan(b_left))))
    uv = np.array([m + _SCALE * tc, vm + th[0]])
    return ShallowFix(uv, cov, kink, float(np.sqrt(s2)), float(slope), n)
