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
for every ``u_c`` on a grid (coarse, then ``step_px`` around the best; compiled, each arm's
sums about ``u_c`` from prefix sums of the points sorted by u), the best
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
    if np.any(np.diff(pts[:, 0]) < 0):  # the compiled search takes the points sorted by u
        pts = pts[np.argsort(pts[:, 0], kind="stable")]
    u, v = pts[:, 0], pts[:, 1]
    m, vm = float(u.mean()), float(v.mean())
    t, y = (u - m) / _SCALE, v - vm
    prior = np.zeros(4)
    if curvature is not None and curvature_weight > 0:
        s2 = _SCALE * _SCALE
        w = curvature_weight / s2 ** 2  # w (c - c0)^2 in px -> in the scaled units
        prior[:] = (float(curvature[0]) * s2, w, float(curvature[1]) * s2, w)
    out = np.empty(10)
    n = int(load_kernels(__package__).shallow_search(
        np.ascontiguousarray(t), np.ascontiguousarray(y), min_points, step_px / _SCALE, prior,
        COARSE, out))
    if n == 0:
        return None
    tc, J, curv, a00, width = (float(x) for x in out[:5])
    th = out[5:]
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
