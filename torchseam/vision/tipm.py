"""TIPM: the weld feature point in a clean laser-stripe frame (METHOD.md section 1).

Pipeline: red-stripe recognition (``R - max(G, B)``: the 650 nm stripe is red, arc light that
saturates all channels is not; minus its local vertical mean, so broad glare drops out) ->
threshold -> connected-area filtering (drop small blobs) -> dilation (close breaks) -> centre
line -> feature point.

Centre line: the paper thins the mask to a one-pixel skeleton (``centre_line="thinning"``, kept
for comparison and for the overlay); the default is a sub-pixel grey-gravity centre per column
(the accepted improvement of METHOD.md), weighed by the ridge response rather than the raw red
one, so that glare under the stripe does not pull it, and refined over the response within a few
rows of it, so that a stripe saturated on glare (its response split into two ridges) does not
leave it on one of them.

Feature point: the stripe is split into its two arms at the column that best explains it as two
lines (an exhaustive two-line least-squares search, O(N) with cumulative sums); each arm is then
fitted with a quadratic ``v = a + b u + c u^2`` over a window next to the corner (skipping the
few columns at the corner where the two arms blur together), and the feature point is where the
two quadratics meet (the windows move there and the arms are refitted, up to three times; fits
that still meet inside one arm's window give no point). A frame without a usable stripe gives
``ok=False`` and a reason, never a garbage point.

Arm prior (optional, for a tracker that has seen the previous frames): each arm's slope at the
corner and its curvature change little from frame to frame, while an arm with a gap next to the
corner or spatter on it lets a free quadratic bend and slide the corner several px along the
stripe. ``prior`` (see :func:`arm_shape`) adds ridge terms pulling slope and curvature toward the
previous frame's (a MAP fit); without it the fit is the plain least squares.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from torchseam.core.config import CONFIG_DIR, config_field, load_config
from torchseam.core.dataset import check_frame


@dataclass(frozen=True)
class TipmConfig:
    """Parameters of TIPM (``configs/tipm.yaml``)."""

    min_red: float = config_field(lo=0.0)
    rel_threshold: float = config_field(lo=0.0, hi=1.0)
    ridge_px: int = config_field(lo=3)
    min_area: int = config_field(lo=0)
    dilate_px: int = config_field(lo=0)
    centre_half_px: float = config_field(lo=0.0, lo_open=True)
    centre_passes: int = config_field(lo=0)
    corner_gap_px: float = config_field(lo=0.0)
    fit_window_px: float = config_field(lo=0.0, lo_open=True)
    min_points_per_arm: int = config_field(lo=3)
    max_rms_px: float = config_field(lo=0.0, lo_open=True)
    min_corner_deg: float = config_field(lo=0.0, hi=180.0)
    max_saturated_fraction: float = config_field(lo=0.0, hi=1.0)


def red_response(frame: np.ndarray, with_green: bool = False,
                 out: list[np.ndarray] | None = None):
    """Red-stripe response ``R - max(G, B)`` (H, W) uint8 of a BGR frame.

    The 650 nm stripe is red; arc light bright enough to saturate the sensor is white. This is
    also the grey image the trackers work on. With ``with_green`` also returns the G channel.
    ``out``: three (H, W) uint8 buffers to reuse (B, G, R planes; the response goes into the
    first), because allocating fresh frame-sized planes costs more than the arithmetic.
    """
    if out is None:
        b, g, r = cv2.split(frame)
        red = cv2.subtract(r, cv2.max(g, b))
    else:
        b, g, r = cv2.split(frame, out)
        red = cv2.subtract(r, cv2.max(g, b, dst=b), dst=b)
    return (red, g) if with_green else red


def load_tipm_config(path: str | Path | None = None) -> TipmConfig:
    return load_config(TipmConfig, path or CONFIG_DIR / "tipm.yaml")


@dataclass
class TipmResult:
    """Outcome of TIPM on one frame.

    Attributes:
        ok: a feature point was found.
        uv: (2,) feature pixel (u, v), NaN when not ``ok``.
        reason: why not, when not ``ok`` (e.g. ``"no stripe found"``).
        centre: (N, 2) centre-line points (u, v) used.
        arms: ((3,), (3,)) quadratic coefficients (a, b, c) of each arm in ``u - u0``, or None.
        u0: the column the arm fits are centred on.
        corner_deg: angle between the two arms' directions at the corner (180 = straight).
        rms_px: RMS residual of the arm fits.
        mask: (H, W) uint8 stripe mask after filtering (for the overlay).
    """

    ok: bool
    uv: np.ndarray
    reason: str = ""
    centre: np.ndarray | None = None
    arms: tuple[np.ndarray, np.ndarray] | None = None
    u0: float = 0.0
    corner_deg: float = float("nan")
    rms_px: float = float("nan")
    mask: np.ndarray | None = None


def _fail(reason: str, mask: np.ndarray | None = None, centre: np.ndarray | None = None
          ) -> TipmResult:
    return TipmResult(False, np.full(2, np.nan), reason, centre=centre, mask=mask)


class Tipm:
    """Classic stripe image processing for the weld feature point.

    Example:
        >>> tipm = Tipm()
        >>> res = tipm(np.zeros((492, 656, 3), np.uint8))
        >>> res.ok, res.reason
        (False, 'no stripe found (no red pixels above threshold)')
    """

    def __init__(self, cfg: TipmConfig | None = None, centre_line: str = "subpixel") -> None:
        if centre_line not in ("subpixel", "thinning"):
            raise ValueError(f"centre_line must be 'subpixel' or 'thinning', got {centre_line!r}")
        self.cfg = cfg or load_tipm_config()
        self.centre_line = centre_line
        k = 2 * self.cfg.dilate_px + 1
        self._kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k))
        self._ws: dict[tuple, np.ndarray] = {}  # reused frame-sized planes (see _plane)

    def _plane(self, name: str, shape: tuple[int, int]) -> np.ndarray:
        """A reused uint8 work plane: fresh frame-sized arrays cost page faults on every frame,
        more than TIPM's arithmetic."""
        key = (name, shape)
        buf = self._ws.get(key)
        if buf is None:
            if len(self._ws) > 64:  # ROI sizes vary at the image border: keep the cache small
                self._ws.clear()
            buf = self._ws[key] = np.empty(shape, np.uint8)
        return buf

    # ------------------------------------------------------------------ stages
    def stripe_mask(self, frame: np.ndarray) -> tuple[np.ndarray, np.ndarray, str]:
        """Stripe response (H, W) uint8, filtered + dilated mask (H, W) uint8, failure reason.

        The stripe response is the ridge: the red response minus its local vertical mean, i.e.
        the stripe with the glare under it taken away. The centre line and ECAL weigh pixels
        by it: weighed by the raw red response, a glare halo's slope across the stripe pulls
        each column's centre toward the glare (a red glare blob 25-40 px below the corner moved
        the corner 0.1 px, on heavy-arc frames up to 0.5 px); a frame refused as saturated
        gives the raw red response (and an empty mask). It lives in a work plane of this
        ``Tipm``: valid until its next call.
        """
        cfg = self.cfg
        hw = frame.shape[:2]
        planes = [self._plane(c, hw) for c in "bgr"]
        red, g = red_response(frame, with_green=True, out=planes)
        # the stripe saturates R only; white arc light saturates G as well
        sat = cv2.compare(g, 250, cv2.CMP_GE, dst=planes[2])
        if cv2.countNonZero(sat) > cfg.max_saturated_fraction * red.size:
            return red, np.zeros_like(red), "frame saturated by arc light"
        # ridge: red minus its local vertical mean, so broad red glare does not pass as stripe
        # (a 3-column box runs 3x faster but lets more spatter through under heavy arc)
        ridge = cv2.blur(red, (1, cfg.ridge_px), dst=planes[1])
        ridge = cv2.subtract(red, ridge, dst=ridge)
        # relative to the strongest ridge: a brighter spatter streak only raises the threshold
        # to rel_threshold * 255, still well below a lit stripe
        peak = cv2.minMaxLoc(ridge)[1]
        thr = max(cfg.min_red, cfg.rel_threshold * peak)
        _, binary = cv2.threshold(ridge, thr, 255, cv2.THRESH_BINARY, dst=planes[2])
        bx, by, bw, bh = cv2.boundingRect(binary)
        if bw == 0:
            return ridge, np.zeros_like(red), "no stripe found (no red pixels above threshold)"
        # label and dilate only the box that holds anything (the stripe is a thin band), with a
        # margin for the dilation
        d = cfg.dilate_px
        h, w = binary.shape
        roi = (slice(max(by - d, 0), min(by + bh + d, h)),
               slice(max(bx - d, 0), min(bx + bw + d, w)))
        n, lab, stats, _ = cv2.connectedComponentsWithStats(binary[roi], connectivity=8,
                                                            ltype=cv2.CV_16U)
        keep = np.nonzero(stats[1:, cv2.CC_STAT_AREA] >= cfg.min_area)[0] + 1
        mask = np.zeros_like(binary)
        if len(keep) == 0:
            return ridge, mask, "no stripe found (only small blobs)"
        if len(keep) == n - 1:
            box = binary[roi]  # every blob is large enough: nothing to filter
        else:
            lut = np.zeros(max(n, 256), np.uint8)
            lut[keep] = 255
            # cv2.LUT needs 8-bit labels; with <= 256 labels (nearly always) it is 5x np.take
            box = cv2.LUT(lab.astype(np.uint8), lut[:256]) if n <= 256 else np.take(lut, lab)
        mask[roi] = cv2.dilate(box, self._kernel)
        return ridge, mask, ""

    def mask_around(self, frame: np.ndarray, uv: np.ndarray, radius: int
                    ) -> tuple[np.ndarray, np.ndarray, tuple[int, int]]:
        """Stripe response and mask (see :meth:`stripe_mask`) in the square ROI of ``radius``
        around ``uv``.

        What ECAL needs in the live loop, at a fraction of the full-frame cost. Returns
        ``(response, mask, (x0, y0))`` with the ROI's top-left corner.
        """
        h, w = frame.shape[:2]
        x0, y0 = max(0, int(uv[0]) - radius), max(0, int(uv[1]) - radius)
        x1, y1 = min(w, int(uv[0]) + radius + 1), min(h, int(uv[1]) + radius + 1)
        if x1 <= x0 or y1 <= y0:
            z = np.zeros((1, 1), np.uint8)
            return z, z, (x0, y0)
        red, mask, _ = self.stripe_mask(np.ascontiguousarray(frame[y0:y1, x0:x1]))
        return red, mask, (x0, y0)

    def centre(self, response: np.ndarray, mask: np.ndarray) -> np.ndarray:
        """(N, 2) centre-line points (u, v) of the masked stripe: per column the centroid of
        ``response`` (the stripe response of :meth:`stripe_mask`) within the mask.

        Columns where the stripe comes within the ridge filter's reach of the top or bottom
        row of the image (or of the window the tracker cut) are left out: the border skews the
        filter's vertical mean there, the mask ends short of the stripe's cross-section, so
        its centre leans inward, and those are the arm ends that bend a quadratic fit most (at
        a deep V in a +-110 px window the corner moved 0.3-0.4 px in v on clean frames)."""
        if self.centre_line == "thinning":
            skel = cv2.ximgproc.thinning(mask)
            v, u = np.nonzero(skel)
            order = np.argsort(u, kind="stable")
            pts = np.stack([u[order], v[order]], axis=1)
        else:
            x0, y0, bw, bh = cv2.boundingRect(mask)
            r, m = response[y0:y0 + bh, x0:x0 + bw], mask[y0:y0 + bh, x0:x0 + bw]
            w = cv2.bitwise_and(r, r, mask=m).astype(np.float32)
            # column sums of w and of row * w in one small matrix product
            rows = np.stack([np.ones(bh, np.float32), np.arange(y0, y0 + bh, dtype=np.float32)])
            s0, s1 = rows @ w
            cols = np.nonzero(s0 > 0)[0]
            v = self._recentre(response, cols + x0, s1[cols] / s0[cols])
            pts = np.stack([cols + x0, v], axis=1)
        k = self.cfg.ridge_px // 2 + 1  # the ridge filter's reach: its mean is skewed there
        cut = (mask[:k] > 0).any(axis=0) | (mask[-k:] > 0).any(axis=0)
        if len(pts) and cut.any():
            pts = pts[~cut[pts[:, 0].astype(np.intp)]]
        return pts.astype(float)

    def _recentre(self, response: np.ndarray, cols: np.ndarray, v: np.ndarray) -> np.ndarray:
        """Each column's centre ``v`` (N,) at columns ``cols`` (N,) moved to the centroid of the
        stripe response within ``centre_half_px`` rows of it, mask or not (``centre_passes``
        times).

        Why: where the stripe runs over arc glare its red channel saturates while green rises
        with the glare, so ``R - max(G, B)`` dips at the stripe's middle and its cross-section
        splits into two ridges 4-8 px apart, each near the threshold. The mask then holds one of
        them in some columns and the masked centroid sits on it, 1.3-2.4 px off the stripe;
        next to the corner those columns slid the corner 2-4.6 px along the stripe with tight
        arm fits (heavy-arc T ring seed 5: 15 frames in a row). The window takes both ridges.
        """
        cfg = self.cfg
        if cfg.centre_passes == 0 or len(cols) == 0:
            return v
        # a band of rows around each column's first centre, wide enough for the window to move
        # a few px (gathered: the whole stripe's row span costs ~1 ms per full frame)
        reach = int(np.ceil(cfg.centre_half_px)) + 3
        rows = np.rint(v).astype(np.intp)[None, :] + np.arange(-reach, reach + 1)[:, None]
        np.clip(rows, 0, response.shape[0] - 1, out=rows)
        r = response[rows, cols[None, :]].astype(np.float32)      # (2 reach + 1, N)
        y = rows.astype(np.float32)
        for _ in range(cfg.centre_passes):
            w = r * (np.abs(y - v.astype(np.float32)) <= cfg.centre_half_px)
            s0 = w.sum(axis=0)
            v = np.where(s0 > 0, (w * y).sum(axis=0) / np.maximum(s0, 1e-6), v)  # empty: keep
        return v.astype(float)

    # ------------------------------------------------------------------ main
    def __call__(self, frame: np.ndarray, prior: np.ndarray | None = None) -> TipmResult:
        """Find the feature point in one BGR (H, W, 3) uint8 frame (``prior``: see
        :meth:`corner`)."""
        check_frame(frame)
        red, mask, why = self.stripe_mask(frame)
        if why:
            return _fail(why, mask)
        pts = self.centre(red, mask)
        return self.corner(pts, mask, prior)

    def corner(self, pts: np.ndarray, mask: np.ndarray | None = None,
               prior: np.ndarray | None = None) -> TipmResult:
        """Feature point from centre-line points (N, 2), sorted by u.

        ``prior``: (2, 4) rows (slope at the corner, curvature, weight of the slope, weight of
        the curvature) for the left and right arm; a weight is the squared point noise over the
        prior's variance (px^2 per slope^2, resp. per curvature^2). None: plain fit."""
        cfg = self.cfg
        if len(pts) < 2 * cfg.min_points_per_arm:
            return _fail(f"no stripe found ({len(pts)} centre-line points)", mask, pts)
        split = _best_split(pts[:, 0], pts[:, 1], cfg.min_points_per_arm)
        if split is None:
            return _fail("no corner: the stripe cannot be split into two arms", mask, pts)
        # The two-line split is only roughly at the corner (the arms are curved): fit the arms
        # next to it, move to where they meet, and refit there until the corner stays put.
        u0 = split
        for it in range(3):
            fit = self._fit_arms(pts, u0, prior)
            if isinstance(fit, str):
                return _fail(fit, mask, pts)
            arms, rms, x = fit  # arms are centred on u0; they meet at u0 + x
            if abs(x) < 0.05 or it == 2:
                break
            u0 += x
        if abs(x) > cfg.corner_gap_px:
            # the arms meet inside one arm's fitted span: that fit ran over the corner (glare
            # hid or bent the stripe next to it) and the refits did not settle
            return _fail(f"no corner: the arm fits do not settle ({abs(x):.1f} px apart)",
                         mask, pts)
        if rms > cfg.max_rms_px:
            return _fail(f"no clean stripe: arm fit residual {rms:.2f} px", mask, pts)
        v = float(np.polynomial.polynomial.polyval(x, arms[0]))
        # angle between the arms at the corner (slopes b + 2 c x)
        s1 = arms[0][1] + 2 * arms[0][2] * x
        s2 = arms[1][1] + 2 * arms[1][2] * x
        d1, d2 = np.array([-1.0, -s1]), np.array([1.0, s2])
        cosang = d1 @ d2 / (np.linalg.norm(d1) * np.linalg.norm(d2))
        corner = float(np.degrees(np.arccos(np.clip(cosang, -1, 1))))
        if 180.0 - corner < cfg.min_corner_deg:
            return _fail(f"no corner: the stripe is straight ({corner:.1f} deg)", mask, pts)
        return TipmResult(True, np.array([u0 + x, v]), "", pts, (arms[0], arms[1]), u0, corner,
                          rms, mask)

    def _fit_arms(self, pts: np.ndarray, u0: float, prior: np.ndarray | None = None
                  ) -> tuple[list[np.ndarray], float, float] | str:
        """Quadratic fit of each arm beside column ``u0``; returns (arms, rms, x of the meeting
        point relative to ``u0``) or the reason it fails. ``pts`` is sorted by u, so each arm's
        window is a slice (this runs up to three times per frame: keep it lean). ``prior``: see
        :meth:`corner` (the slope is taken at ``u0``, which converges onto the corner)."""
        cfg = self.cfg
        u = pts[:, 0]
        windows = ((u0 - cfg.fit_window_px, u0 - cfg.corner_gap_px),
                   (u0 + cfg.corner_gap_px, u0 + cfg.fit_window_px))
        arms, rms_all = [], []
        for name, (lo, hi) in zip(("left", "right"), windows, strict=True):
            i0, i1 = np.searchsorted(u, (lo, hi + 1e-9))
            if i1 - i0 < cfg.min_points_per_arm:
                return f"no corner: the {name} arm has only {int(i1 - i0)} points"
            x, y = u[i0:i1] - u0, pts[i0:i1, 1]
            arm_prior = None if prior is None else prior[len(arms)]
            coef, res = _quadfit(x, y, arm_prior)
            # one robust pass: drop points far off the fit (spatter touching the stripe); the
            # residuals of a fit with an intercept have zero mean, so their std is their RMS
            good = np.abs(res) < max(3 * np.sqrt(res @ res / len(res)), 0.5)
            n_good = np.count_nonzero(good)
            if cfg.min_points_per_arm <= n_good < len(x):
                coef, res = _quadfit(x[good], y[good], arm_prior)
            arms.append(coef)
            rms_all.append(float(np.sqrt(res @ res / len(res))))
        c0, c1, c2 = arms[0] - arms[1]
        if abs(c2) > 1e-12:
            disc = c1 * c1 - 4 * c2 * c0
            if disc < 0:
                return "no corner: the arms do not meet"
            sq = np.sqrt(disc)
            roots = ((-c1 - sq) / (2 * c2), (-c1 + sq) / (2 * c2))
            x = float(min(roots, key=abs))
        elif abs(c1) > 1e-12:
            x = float(-c0 / c1)
        else:
            return "no corner: the arms are parallel"
        if abs(x) > cfg.fit_window_px:
            return "no corner: the arms meet far from the stripe"
        return arms, max(rms_all), x


def power_sums(x: np.ndarray) -> tuple[float, float, float, float, float]:
    """(n, sum x, sum x^2, sum x^3, sum x^4) of ``x`` (N,): what a quadratic fit's 3x3 normal
    matrix is made of.

    Example:
        >>> power_sums(np.array([1.0, 2.0]))
        (2.0, 3.0, 5.0, 9.0, 17.0)
    """
    x2 = x * x
    return float(len(x)), float(x.sum()), float(x2.sum()), float(x2 @ x), float(x2 @ x2)


def quad_normal_adjugate(sums: tuple[float, ...], w: tuple[float, float] = (0.0, 0.0)
                         ) -> tuple[tuple[float, ...], float]:
    """Adjugate (A00, A01, A02, A11, A12, A22) and determinant of the normal matrix
    ``A = [[n, s1, s2], [s1, s2 + w_b, s3], [s2, s3, s4 + w_c]]`` of a quadratic fit with power
    sums ``sums`` (:func:`power_sums`) and ridge weights ``w`` on slope and curvature.

    In closed form: ``np.linalg.solve`` costs ~15 us a call on a 3x3, this a handful of float
    operations. ``A^-1 = adj / det``.

    Example:
        >>> adj, det = quad_normal_adjugate(power_sums(np.arange(3.0)))  # x = 0, 1, 2
        >>> det
        4.0
    """
    a, b, c, f, g = sums
    d, g = c + w[0], g + w[1]
    A00, A01, A02 = d * g - f * f, c * f - b * g, b * f - c * d
    A11, A12, A22 = a * g - c * c, b * c - a * f, a * d - b * b
    return (A00, A01, A02, A11, A12, A22), a * A00 + b * A01 + c * A02


def _quadfit(x: np.ndarray, y: np.ndarray, prior: np.ndarray | None = None
             ) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares (a, b, c) of y = a + b x + c x^2 (x is centred on the corner already) and
    the residuals, from the 3x3 normal equations in closed form (a Vandermonde matrix and
    ``np.linalg.solve`` cost twice as much per arm, up to six times a frame). ``prior``
    (b0, c0, w_b, w_c) adds w_b (b - b0)^2 + w_c (c - c0)^2 to the squared error."""
    x2 = x * x
    r0, r1, r2 = float(y.sum()), float(x @ y), float(x2 @ y)
    w = (0.0, 0.0)
    if prior is not None:
        b0, c0, wb, wc = (float(p) for p in prior)
        w = (wb, wc)
        r1, r2 = r1 + wb * b0, r2 + wc * c0
    (A00, A01, A02, A11, A12, A22), det = quad_normal_adjugate(power_sums(x), w)
    k0 = (A00 * r0 + A01 * r1 + A02 * r2) / det
    k1 = (A01 * r0 + A11 * r1 + A12 * r2) / det
    k2 = (A02 * r0 + A12 * r1 + A22 * r2) / det
    return np.array([k0, k1, k2]), y - (k0 + k1 * x + k2 * x2)


def arm_shape(res: TipmResult) -> np.ndarray:
    """(2, 2) slope at the corner and curvature of the left and right arm of a found corner
    (what :meth:`Tipm.corner` takes as a prior)."""
    assert res.arms is not None
    x = res.uv[0] - res.u0
    return np.array([[a[1] + 2 * a[2] * x, a[2]] for a in res.arms])


def _best_split(u: np.ndarray, v: np.ndarray, min_pts: int) -> float | None:
    """Column that best splits (u, v) into two straight lines (least squares, O(N))."""
    n = len(u)
    if n < 2 * min_pts:
        return None
    M = np.empty((5, n))  # moments of the centred points, then their running sums
    np.subtract(u, u.mean(), out=M[0])
    np.subtract(v, v.mean(), out=M[1])
    np.multiply(M[0], M[0], out=M[2])
    np.multiply(M[0], M[1], out=M[3])
    np.multiply(M[1], M[1], out=M[4])
    np.cumsum(M, axis=1, out=M)
    i = np.arange(min_pts - 1, n - min_pts)
    left = M[:, i]                   # points 0..i
    right = M[:, -1:] - left         # points i+1..n-1: the totals less the left's
    k_left = i + 1.0
    total = _line_sse(left, k_left) + _line_sse(right, n - k_left)
    best = i[np.argmin(total)]
    return float(0.5 * (u[best] + u[best + 1]))


def _line_sse(S: np.ndarray, k: np.ndarray) -> np.ndarray:
    """Squared error of a least-squares line through each of the point sets whose count is
    ``k`` (M,) and sums of x, y, x^2, xy, y^2 are the columns of ``S`` (5, M)."""
    sx, sy, sxx, sxy, syy = S
    vx = sxx - sx * sx / k
    cxy = sxy - sx * sy / k
    return syy - sy * sy / k - np.where(vx > 1e-9, cxy * cxy / np.maximum(vx, 1e-9), 0.0)


def draw_overlay(frame: np.ndarray, res: TipmResult, truth: np.ndarray | None = None
                 ) -> np.ndarray:
    """Frame with the stripe centre line (green), arm fits (blue) and feature point (yellow)."""
    out = frame.copy()
    if res.centre is not None and len(res.centre):
        for u, v in res.centre[:: max(1, len(res.centre) // 400)].astype(int):
            cv2.circle(out, (int(u), int(v)), 0, (0, 255, 0), -1)
    if res.ok and res.arms is not None:
        for side, coef in zip((-1, 1), res.arms, strict=True):
            x = np.linspace(0, 150, 40) * side + (res.uv[0] - res.u0)
            y = np.polynomial.polynomial.polyval(x, coef)
            poly = np.stack([x + res.u0, y], axis=1)
            cv2.polylines(out, [np.round(poly * 16).astype(np.int32)], False, (255, 128, 0), 1,
                          cv2.LINE_AA, 4)
        c = tuple(int(round(x * 16)) for x in res.uv)
        cv2.circle(out, c, 8 * 16, (0, 255, 255), 1, cv2.LINE_AA, 4)
        cv2.drawMarker(out, tuple(int(round(x)) for x in res.uv), (0, 255, 255),
                       cv2.MARKER_CROSS, 18, 1, cv2.LINE_AA)
    label = f"TIPM ({res.uv[0]:.1f}, {res.uv[1]:.1f})" if res.ok else f"TIPM: {res.reason}"
    cv2.putText(out, label, (8, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 1,
                cv2.LINE_AA)
    if truth is not None:
        cv2.drawMarker(out, tuple(int(round(x)) for x in truth), (0, 255, 0),
                       cv2.MARKER_TILTED_CROSS, 12, 1, cv2.LINE_AA)
    return out
