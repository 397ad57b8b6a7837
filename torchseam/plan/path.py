"""Weld planning (METHOD.md section 6): six segments, look-ahead buffer, IPI step control.

* The closed seam is welded in six segments of 60 degrees of branch angle. The torch welds one
  segment while the part is still, then the positioner turns the part 60 degrees about the
  branch axis, so every segment is welded in the same, comfortable, part of the workspace.
* The stripe runs ``look_ahead_mm`` ahead of the torch: located seam points wait in a bounded
  buffer until the torch gets there.
* IPI (eq. 30): from the current point cp towards the located point np the next commanded point
  is ip = cp + d' l, l = (np - cp) / |np - cp|, with d' the step (2 mm).
"""

from __future__ import annotations

import functools
from collections import deque
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from torchseam.core.config import config_field, config_path, load_config

SEGMENTS = 6
SEGMENT_NAMES = "abcdef"
MERGE_MM = 0.1  # located points closer than this to the newest one are merged into it
MIN_MEASURED_ARMS = 3  # measured arms needed to outvote ECAL's guessed (fallback) ones
MSAC_HYPOTHESES = 200  # point triples tried per robust fit
WINDOW_MARGIN_MM = 1.0  # fit candidates reach this much past smooth_mm (outliers sit aside)
#: where the located points round a point cover less than ``LOPSIDED`` smooth_mm of the seam
#: on one side of it (the edge of a hole a blind stretch left), its tangent's fit reaches across
#: the hole to the points beyond, within ``TANGENT_REACH`` smooth_mm of it
#: (:meth:`LookAheadBuffer._wide_fit`)
LOPSIDED = 0.5
TANGENT_REACH = 3.0


@dataclass(frozen=True)
class PlanSearch:
    """What the weld planner may change when the configured plan fails the reachability gate
    (``search`` in ``configs/plan.yaml``; see :mod:`torchseam.plan.weld`). Ranges are
    ``[min, max]``; every range includes the configured value (0 for the placement)."""

    min_joint_margin_deg: float = config_field(default=10.0, lo=0.0)
    segment_start_step_deg: float = config_field(default=15.0, lo=1.0, hi=60.0)
    yaw_deg: tuple[float, ...] = config_field(2, default=(-90.0, 90.0), lo=-180.0, hi=180.0)
    yaw_step_deg: float = config_field(default=30.0, lo=0.0, lo_open=True)
    tilt_deg: tuple[float, ...] = config_field(2, default=(-30.0, 30.0), lo=-90.0, hi=90.0)
    tilt_step_deg: float = config_field(default=15.0, lo=0.0, lo_open=True)
    shift_mm: tuple[float, ...] = config_field(2, default=(-100.0, 100.0))
    shift_step_mm: float = config_field(default=50.0, lo=0.0, lo_open=True)
    work_angle_deg: tuple[float, ...] = config_field(2, default=(-10.0, 10.0), lo=-45.0, hi=45.0)
    travel_angle_deg: tuple[float, ...] = config_field(2, default=(-15.0, 15.0), lo=-45.0,
                                                       hi=45.0)
    roll_deg: tuple[float, ...] = config_field(2, default=(0.0, 0.0), lo=-180.0, hi=180.0)
    angle_step_deg: float = config_field(default=5.0, lo=0.0, lo_open=True)
    roll_step_deg: float = config_field(default=15.0, lo=0.0, lo_open=True)
    screen_stride: int = config_field(default=3, lo=1)

    def _check(self) -> None:
        for name in ("yaw_deg", "tilt_deg", "shift_mm", "work_angle_deg", "travel_angle_deg",
                     "roll_deg"):
            lo, hi = getattr(self, name)
            if not lo <= 0.0 <= hi and name in ("yaw_deg", "tilt_deg", "shift_mm", "roll_deg"):
                raise ValueError(f"{name}: [{lo:g}, {hi:g}] must include 0 (the configured "
                                 "placement / no roll)")
            if lo > hi:
                raise ValueError(f"{name}: [{lo:g}, {hi:g}] is empty (min > max)")


@dataclass(frozen=True)
class PlanConfig:
    """Planning settings (``configs/plan.yaml``)."""

    segment_start_deg: float
    approach_mm: float
    smooth_mm: float
    outlier_mm: float
    buffer_points: int
    work_angle_deg: float
    travel_angle_deg: float
    search: PlanSearch = PlanSearch()

    def _check(self) -> None:
        for name in ("work_angle_deg", "travel_angle_deg"):
            lo, hi = getattr(self.search, name)
            v = getattr(self, name)
            if not lo <= v <= hi:
                raise ValueError(f"{name}: {v:g} lies outside search.{name} [{lo:g}, {hi:g}]")


def load_plan_config(path: str | Path | None = None) -> PlanConfig:
    return load_config(PlanConfig, path or config_path("plan.yaml"))


@dataclass(frozen=True)
class Segment:
    """One welding segment: branch angles [phi_start, phi_end) and the positioner turn."""

    name: str
    index: int
    phi_start: float
    phi_end: float
    rotation_deg: float


def six_segments(start_phi: float, closed: bool = True) -> list[Segment]:
    """The six segments a..f of the ring, starting at branch angle ``start_phi`` (rad; the
    configured one is ``radians(PlanConfig.segment_start_deg)``).

    Segment k is welded with the part turned by ``-60 k`` degrees, which brings it to where
    segment a was. An open seam (``closed`` False: a coupon) is cut into six equal lengths from
    its start (``start_phi`` 0) and not turned: the robot follows it along.
    """
    step = 2 * np.pi / SEGMENTS
    turn = -60.0 if closed else 0.0
    return [Segment(SEGMENT_NAMES[k], k, start_phi + k * step, start_phi + (k + 1) * step,
                    turn * k) for k in range(SEGMENTS)]


def ipi_step(cp: np.ndarray, np_: np.ndarray, step_mm: float) -> np.ndarray:
    """eq. 30: the next commanded point from cp (3,) towards np (3,), ``step_mm`` away.

    If np is closer than the step, np itself (never overshoot a located point).
    """
    d = np_ - cp
    dist = float(np.linalg.norm(d))
    if dist <= step_mm or dist == 0.0:
        return np_.copy()
    return cp + step_mm * d / dist


@dataclass
class Located:
    """A located seam point waiting in the buffer (robot base, mm)."""

    s_mm: float          # arc length along the located path
    p: np.ndarray        # (3,) weld point
    q: np.ndarray        # (2, 3) points on the two stripe arms (NaN when ECAL found none)
    t_s: float           # time of the frame that saw it
    n: int = 1           # measurements averaged into it
    flagged: bool = False  # off the smooth seam through its neighbours: spatter, not seam
    residual_mm: float = float("nan")  # distance from that smooth seam (NaN: never fitted)
    judged_mm: float = float("inf")  # how far from the centre of the fit that judged it
    guessed: bool = False  # one arm point was ECAL's fallback (the previous frame's direction)


@dataclass
class SeamFit:
    """The local seam fit at one buffered point (see :meth:`LookAheadBuffer.fit`).

    Attributes:
        p: (3,) smoothed point; tangent: (3,) unit seam tangent, or None (too few points);
        arms: (2, 3) median unit arm directions over the inliers (NaN if none had arms);
        used: number of inliers fitted; rejected: points of the window flagged as off-seam.
        coef: (3, 3) the fitted quadratic, rows c0, c1, c2: point(x) = c0 + c1 x + c2 x^2 at
            x = (point - origin) . d; origin (3,), d (3,) unit; span: the fitted points' x
            range. None when there was no fit (tangent None).

    Example:
        >>> buf = LookAheadBuffer(maxlen=100, outlier_mm=0.2)
        >>> for x in range(0, 12):
        ...     _ = buf.push(np.array([float(x), 0.05 * x * x, 0]), np.full((2, 3), np.nan), x)
        >>> f = buf.seam_fit(5)
        >>> f.tangent_at(np.array([4.0, 0.8, 0])).round(2).tolist()   # slope 0.1 x at x = 4
        [0.93, 0.37, 0.0]
    """

    p: np.ndarray
    tangent: np.ndarray | None
    arms: np.ndarray
    used: int
    rejected: int
    coef: np.ndarray | None = None
    origin: np.ndarray | None = None
    d: np.ndarray | None = None
    span: tuple[float, float] = (0.0, 0.0)
    #: the quadratic the tangent is the derivative of and its points' x range, where it is
    #: not ``coef``: the wider fit of a lopsided window (see :meth:`LookAheadBuffer.seam_fit`)
    tcoef: np.ndarray | None = None
    tspan: tuple[float, float] = (0.0, 0.0)
    #: how far from the fitted point the points it rests on may lie (``smooth_mm``; a lopsided
    #: window's ``TANGENT_REACH smooth_mm``): a point pushed farther away changes nothing
    reach_mm: float = 0.0

    def tangent_at(self, p: np.ndarray) -> np.ndarray | None:
        """Unit tangent of the fit at the position of ``p`` (3,) along it (None: no fit)."""
        coef, span = (self.coef, self.span) if self.tcoef is None else (self.tcoef, self.tspan)
        if coef is None:
            return self.tangent
        x = float(np.clip((p - self.origin) @ self.d, *span))
        t = coef[1] + 2 * coef[2] * x
        return t / np.linalg.norm(t)


class LookAheadBuffer:
    """Bounded FIFO of located seam points between the stripe and the torch.

    The stripe runs ahead of the torch, so when the torch reaches a located point the buffer
    holds located points on both sides of it (points are kept until they are ``2 smooth_mm``
    behind the torch). That is used for the commanded point, a local quadratic fit of the
    located points within ``smooth_mm`` of it along the seam, which averages the measurement
    noise without lag; for the seam tangent of the torch frame
    (:func:`~torchseam.geometry.torch_frame.torch_frame`), that fit's derivative at the commanded
    point, centred on it instead of trailing it; and for the arm directions, the median over the
    same points.

    The fit is robust: a located point farther than ``outlier_mm`` from the smooth seam through
    its neighbours (a feature point the tracker put on a spatter streak or up an arm) is
    *flagged* (``Located.flagged``) and used for nothing, neither the path, the tangent nor the
    arms. The fit's parameter is the position along the local seam direction (a robust chord),
    not the cumulative arc length, which outliers inflate, nor frame time, which stops when the
    robot holds.

    Example:
        >>> buf = LookAheadBuffer(maxlen=100, outlier_mm=0.2)
        >>> for x in range(0, 30):
        ...     _ = buf.push(np.array([float(x), 0, 0]), np.full((2, 3), np.nan), t_s=x / 25)
        >>> ip, tangent, q = buf.next_command(np.array([0.0, 0, 0]), step_mm=2.0)
        >>> ip.round(6).tolist(), tangent.round(6).tolist()
        ([2.0, 0.0, 0.0], [1.0, 0.0, 0.0])
    """

    def __init__(self, maxlen: int = 2048, smooth_mm: float = 3.0, *, outlier_mm: float
                 ) -> None:
        self.points: deque[Located] = deque(maxlen=maxlen)
        self.smooth_mm = smooth_mm
        self.outlier_mm = outlier_mm  # PlanConfig.outlier_mm in the live loop and the ring run
        self.dropped = 0  # points pushed out by a full buffer (reported, never silent)
        # changes with every point pushed, merged or dropped and every flag a fit turns: an
        # answer read off the points (where they are, which are flagged, when they were seen)
        # that was worked out at one version holds at the same version (LiveLoop caches its
        # hole bridging and seen times by it). Edit ``points`` directly only between uses.
        self.version = 0
        self.flagged = 0  # points flagged as off the seam so far (reported, never silent)
        # next_command worked out ahead by prepare(): (cp, step, result, fitted points (n, 3),
        # distance from cp to the nearest point then, how far from each fitted point its fit
        # reached (n,): SeamFit.reach_mm)
        self._ready: tuple[np.ndarray, float, tuple, np.ndarray, float, np.ndarray] | None = None

    def __len__(self) -> int:
        return len(self.points)

    def push(self, p: np.ndarray, q: np.ndarray, t_s: float, guessed: bool = False) -> Located:
        """Add a located point (``q``: (2, 3) arm points; ``guessed``: one of them is ECAL's
        occluded-arm fallback); returns its buffer entry. A point within ``MERGE_MM`` of the
        newest one (the sensor standing still) is averaged into it instead of appended."""
        p = np.asarray(p, float)
        r = self._ready
        if r is not None and (
                len(self.points) == self.points.maxlen
                or np.any(np.linalg.norm(r[3] - p, axis=1)
                          <= r[5] + WINDOW_MARGIN_MM + MERGE_MM)
                or np.linalg.norm(p - r[0]) <= r[4] + MERGE_MM):
            # the point may enter a fit the prepared command rests on, or become the point
            # nearest cp (which decides where the search starts)
            self._ready = None
        self.version += 1
        if self.points and np.linalg.norm(p - self.points[-1].p) < MERGE_MM:
            last = self.points[-1]
            n = last.n + 1
            last.p = last.p + (p - last.p) / n
            q = np.asarray(q, float)
            if np.all(np.isfinite(q)):
                last.q = q if not np.all(np.isfinite(last.q)) else last.q + (q - last.q) / n
            last.n, last.t_s = n, t_s
            return last
        s = 0.0 if not self.points else self.points[-1].s_mm + float(
            np.linalg.norm(p - self.points[-1].p))
        if len(self.points) == self.points.maxlen:
            self.dropped += 1
        self.points.append(Located(s, p, np.asarray(q, float), t_s, guessed=guessed))
        return self.points[-1]

    def ahead_mm(self, cp: np.ndarray) -> float:
        """Distance from cp to the newest located point (what the stripe has seen ahead)."""
        return float(np.linalg.norm(self.points[-1].p - cp)) if self.points else 0.0

    def fit(self, k: int) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
        """``(point (3,), unit tangent (3,) or None, arm directions (2, 3))`` of
        :meth:`seam_fit` at buffered point ``k``."""
        self._ready = None  # judging points may change a prepared answer
        f = self.seam_fit(k)
        return f.p, f.tangent, f.arms

    def seam_fit(self, k: int) -> SeamFit:
        """Robust local fit of the seam at buffered point ``k``.

        The points within ``smooth_mm`` of point ``k`` along the local seam direction are
        fitted with a quadratic in that position by MSAC (every triple of points proposes a
        quadratic; the one the most points agree with to ``outlier_mm`` wins, and is refitted
        by least squares on the points that agree). A plain least-squares start would let a
        few consecutive spatter hits at the window's edge bend the quadratic towards them.
        Points farther than ``outlier_mm`` from the fit are flagged (each point is judged by
        the fit centred nearest to it) and not used. The smoothed point is the fit at point
        ``k``'s position along the seam (smoothed over the inliers' order of arrival), the
        tangent its derivative there (where the window's points lie to one side of point
        ``k``, at the edge of a hole, that of a fit reaching across the hole:
        :meth:`_wide_fit`), the arm directions the median over the inliers' unit arm
        vectors. The tangent is None when fewer than
        4 points agree (the seam seen at one spot only, e.g. before the robot moves); the
        point is then point ``k`` itself.
        """
        pts = list(self.points)
        P = np.stack([loc.p for loc in pts])                                   # (N, 3)
        pk = P[k]
        # candidates by distance, with a margin for points pushed off sideways by outliers
        cand = np.flatnonzero(np.linalg.norm(P - pk, axis=1)
                              <= self.smooth_mm + WINDOW_MARGIN_MM)
        d = np.zeros(3)
        if len(cand) >= 2:
            # local seam direction: the chord between the medians of the older and the newer
            # half of the candidates (robust to outliers, unlike cumulative arc length)
            h = len(cand) // 2
            d = np.median(P[cand[h:]], axis=0) - np.median(P[cand[:h]], axis=0)
        if len(cand) < 4 or np.linalg.norm(d) < 1e-9:
            return SeamFit(pk, None, self._arms(pts, cand), len(cand), 0)
        d /= np.linalg.norm(d)
        x = (P[cand] - pk) @ d
        win = np.abs(x) <= self.smooth_mm
        idx, x = cand[win], x[win]
        if len(idx) < 4:
            return SeamFit(pk, None, self._arms(pts, idx), len(idx), 0)
        coef, r = _msac_quadratic(x, P[idx], self.outlier_mm)
        inl = r <= self.outlier_mm
        if inl.sum() < 4:
            # no smooth seam through enough of these points: judge nothing, fit nothing
            return SeamFit(pk, None, self._arms(pts, idx), len(idx), 0)
        for i, xi, ri in zip(idx, np.abs(x), r, strict=True):
            loc = pts[i]
            if xi <= loc.judged_mm:  # the fit centred nearest the point judges it
                loc.judged_mm, loc.residual_mm = float(xi), float(ri)
                if (ri > self.outlier_mm) != loc.flagged:
                    loc.flagged = not loc.flagged
                    self.version += 1
                    self.flagged += 1 if loc.flagged else -1
        # where along the seam point k is: its own position, smoothed by the inliers' order
        # of arrival (noise along the seam moves a point along the curve, not off it; the
        # arrival order, unlike time, does not jump when the robot holds)
        n_k = idx - k
        B = np.stack([np.ones(len(idx)), n_k, n_k * n_k], axis=1)[inl]
        xk = float(np.clip(np.linalg.lstsq(B, x[inl], rcond=None)[0][0], x.min(), x.max()))
        p = coef[0] + coef[1] * xk + coef[2] * xk * xk
        span = (float(x.min()), float(x.max()))
        if float(x[inl].max() - x[inl].min()) < LOPSIDED * self.smooth_mm:
            # the seam seen over less than half a window (the first points after the robot
            # starts where it stood, e.g. after a seam search): a quadratic's slope over 1-2 mm
            # of points 0.03 mm apart across the seam swings by degrees; no tangent (the torch
            # keeps its travel direction) rather than a guess
            return SeamFit(p, None, self._arms(pts, idx[inl]), int(inl.sum()),
                           int((~inl).sum()))
        tcoef, tspan, reach = None, (0.0, 0.0), self.smooth_mm
        cover = (xk - float(x[inl].min()), float(x[inl].max()) - xk)
        if min(cover) < LOPSIDED * self.smooth_mm:
            reach = TANGENT_REACH * self.smooth_mm
            wide = self._wide_fit(P, pk, d, xk, cover)
            if wide is not None:
                tcoef, tspan = wide
        c = coef if tcoef is None else tcoef
        tangent = c[1] + 2 * c[2] * xk
        tangent = tangent / np.linalg.norm(tangent)
        return SeamFit(p, tangent, self._arms(pts, idx[inl]), int(inl.sum()),
                       int((~inl).sum()), coef, pk, d, span, tcoef, tspan, reach)

    def _wide_fit(self, P: np.ndarray, pk: np.ndarray, d: np.ndarray, xk: float,
                  cover: tuple[float, float]) -> tuple[np.ndarray, tuple[float, float]] | None:
        """The quadratic (and its inliers' x range) for the tangent at ``xk`` (along ``d`` from
        ``pk``) where the window's points cover less than ``LOPSIDED smooth_mm`` of the seam
        on a side of it (``cover``: how far they reach behind and ahead): that side reaches on
        across the hole, to ``smooth_mm`` past the first point seen beyond it, within
        ``TANGENT_REACH smooth_mm``. None where nothing was seen beyond (the stripe's first or
        newest points: the seam there is not known to bend as a quadratic over a longer
        stretch) or too little fits.

        A quadratic's slope at the end of the points it was fitted to has sixteen times the
        variance of its slope at their middle: at the edges of a hole in the look-ahead buffer
        (the arc's glare hid the bevel's root for ~20 frames after the arc struck) the located
        points' scatter (~0.05 mm) pitched the tangent, and with it the torch frame's axis
        (the arms are projected across the tangent), by up to 2.8 degrees. With the points
        beyond the hole the tangent there is interpolated, not extrapolated. It judges no
        point."""
        reach = TANGENT_REACH * self.smooth_mm
        cand = np.flatnonzero(np.linalg.norm(P - pk, axis=1) <= reach + WINDOW_MARGIN_MM)
        x = (P[cand] - pk) @ d - xk
        lo, hi = -self.smooth_mm, self.smooth_mm
        wider = False
        for sign, covered in ((-1.0, cover[0]), (1.0, cover[1])):
            if covered >= LOPSIDED * self.smooth_mm:
                continue
            beyond = sign * x[(sign * x > self.smooth_mm) & (sign * x <= reach)]
            if not len(beyond):
                continue
            edge = min(float(beyond.min()) + self.smooth_mm, reach)
            lo, hi = (-edge, hi) if sign < 0 else (lo, edge)
            wider = True
        win = (x >= lo) & (x <= hi)
        if not wider or win.sum() < 4:
            return None
        xw = x[win] + xk
        coef, r = _msac_quadratic(xw, P[cand[win]], self.outlier_mm)
        inl = r <= self.outlier_mm
        if inl.sum() < 4:
            return None
        return coef, (float(xw[inl].min()), float(xw[inl].max()))

    @staticmethod
    def _arms(pts: list[Located], idx: np.ndarray) -> np.ndarray:
        """Median unit arm directions (2, 3) of points ``idx`` (NaN if none had arms). The
        median, not the mean: one ECAL crossing taken on a spatter streak must not tilt the
        torch. Arms ECAL measured on both sides win over guessed ones (its occluded-arm
        fallback extrapolates the hidden arm from an older direction: on a heavy-arc ring,
        when it still held that direction, those were 4-7 degrees off while the measured ones
        were within about 1) when there are enough of them.

        Each arm votes with the weight of its length ``|q - p|`` (a weighted median): ECAL
        places the arm point at the radius of the circle it measured on, and a crossing's
        pixel error turns the arm by about error / radius, so a vote taken on the innermost
        circle only is several times less precise than one from circles out to ``r_max``
        (the weighted median is the maximum-likelihood centre of Laplace errors whose scale
        falls as 1 / radius). On the 60-degree joint the branch hid the main arm beyond the
        first one or two circles for ~40 frames; those short arms were 2-8 degrees off, all
        one way, and as equal votes tilted the torch 1.8 degrees."""
        if len(idx) == 0:
            return np.full((2, 3), np.nan)
        arms = np.stack([pts[i].q - pts[i].p for i in idx])                    # (n, 2, 3)
        length = np.linalg.norm(arms, axis=2, keepdims=True)                   # (n, 2, 1)
        arms = arms / length
        good = np.all(np.isfinite(arms), axis=(1, 2))
        if not good.any():
            return np.full((2, 3), np.nan)
        measured = good & ~np.array([pts[i].guessed for i in idx])
        if measured.sum() >= max(MIN_MEASURED_ARMS, good.sum() // 3):
            good = measured  # (a few measured among many guessed: spatter may have made them)
        med = _weighted_median(arms[good], np.broadcast_to(length[good], arms[good].shape))
        return med / np.linalg.norm(med, axis=1, keepdims=True)

    def screen(self) -> int:
        """Fit around every point no fit has judged yet (flagging outliers); returns how many
        points are flagged. For reports: the live loop judges the points as it plans."""
        self._ready = None  # judging points may change a prepared answer
        k = 0
        while k < len(self.points):
            if np.isnan(self.points[k].residual_mm):
                self.seam_fit(k)
                if np.isnan(self.points[k].residual_mm):
                    self.points[k].residual_mm = np.inf  # too few neighbours to judge
            k += 1
        return sum(loc.flagged for loc in self.points)

    def next_command(self, cp: np.ndarray, step_mm: float
                     ) -> tuple[np.ndarray, np.ndarray | None, np.ndarray] | None:
        """IPI step from cp: ``(ip (3,), tangent (3,) or None, arm_dirs (2, 3))`` or None when
        nothing is located a step ahead yet (tangent None: too few points around np to fit).

        np is the robust fit (:meth:`seam_fit`) at the first buffered point, from the one
        nearest cp on, that is at least one step from cp and not flagged as off the seam. Points
        more than ``2 smooth_mm`` behind cp are dropped (nearer ones are kept: the fit around
        np needs points on both sides). ``tangent`` is the fit's at ip, not at np: np lies up
        to one point spacing beyond ip, and the saddle turns fast (0.3 mm further on turned the
        torch axis by up to 0.5 degree on the 60-degree joint). ``arm_dirs`` are the smoothed
        unit arm directions at np, for the torch frame:
        ``torch_frame(ip, ip + arm_dirs[0], ip + arm_dirs[1], tangent=tangent)``.
        """
        r = self._ready
        if r is not None and r[1] == step_mm and np.array_equal(r[0], cp):
            return r[2]
        self._ready = None  # this search may drop points and judge others
        return self._next_command(cp, step_mm)[0]

    def prepare(self, cp: np.ndarray, step_mm: float) -> None:
        """Work out :meth:`next_command` ``(cp, step_mm)`` now and keep it (the live loop does
        this between camera frames, so the frame that finds the torch at cp only sends).
        The kept answer is dropped as soon as a point is pushed within reach of a fit it
        rests on (``smooth_mm`` and margins around each fitted point; ``TANGENT_REACH
        smooth_mm`` round one whose window was lopsided) or nearer cp than any
        point was, when the full buffer drops its oldest, and when anything else searches or
        fits (:meth:`next_command` elsewhere, :meth:`fit`, :meth:`screen`), so
        :meth:`next_command` returns what it would compute itself. (One difference remains
        after a drop: the fit it ran has judged its window's points, as a fit run then would
        have; the fresh search starts from those judgements.) The stripe sees the seam ~20 mm
        ahead of the torch, so in steady tracking the new points land far from the fits at cp
        and the answer stands until the torch gets there. Edit ``points`` directly only
        without a prepared answer."""
        r = self._ready
        if r is not None and r[1] == step_mm and np.array_equal(r[0], cp):
            return
        self._ready = None
        out, fitted = self._next_command(cp, step_mm)
        if out is not None:
            near = float(np.min(np.linalg.norm(np.stack([loc.p for loc in self.points]) - cp,
                                               axis=1)))
            self._ready = (np.array(cp, float), step_mm, out,
                           np.array([f[0] for f in fitted]).reshape(-1, 3), near,
                           np.array([f[1] for f in fitted]))

    def _next_command(self, cp: np.ndarray, step_mm: float
                      ) -> tuple[tuple[np.ndarray, np.ndarray | None, np.ndarray] | None,
                                 list[tuple[np.ndarray, float]]]:
        """next_command's answer and the points whose fits it ran, each with its fit's reach
        (see prepare)."""
        fitted: list[tuple[np.ndarray, float]] = []
        if not self.points:
            return None, fitted
        P = np.stack([loc.p for loc in self.points])
        j = int(np.argmin(np.linalg.norm(P - cp, axis=1)))
        behind = 0
        while behind < j and np.linalg.norm(P[behind] - cp) > 2 * self.smooth_mm:
            behind += 1
        for _ in range(behind):
            self.points.popleft()
        self.version += behind
        P, j = P[behind:], j - behind
        dist = np.linalg.norm(P - cp, axis=1)
        # from the point nearest cp on (it is itself a target when cp is a step or more away,
        # off the located path: the torch's start, the sensor having seen one spot only)
        for k in np.flatnonzero(dist >= step_mm):
            if k < j or self.points[k].flagged:
                continue
            f = self.seam_fit(int(k))
            fitted.append((P[k], max(f.reach_mm, self.smooth_mm)))
            if self.points[k].flagged:
                continue  # the candidate itself was off the seam: take the next one
            ip = ipi_step(cp, f.p, step_mm)
            return (ip, f.tangent_at(ip), f.arms), fitted
        return None, fitted


def _weighted_median(x: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Weighted median along axis 0 of ``x`` (n, ...) with positive weights ``w`` (same
    shape): the value where the cumulative weight of the sorted values reaches half the
    total (the mean of the two values around it when it lands on half exactly, as
    ``np.median`` does with equal weights)."""
    order = np.argsort(x, axis=0)
    xs, ws = np.take_along_axis(x, order, 0), np.take_along_axis(w, order, 0)
    cum = np.cumsum(ws, axis=0)
    half = cum[-1] / 2
    i = np.sum(cum < half * (1 - 1e-12), axis=0)[None]                        # (1, ...)
    lo = np.take_along_axis(xs, i, 0)[0]
    hi = np.take_along_axis(xs, np.minimum(i + 1, len(x) - 1), 0)[0]
    on_half = np.abs(np.take_along_axis(cum, i, 0)[0] - half) <= 1e-9 * cum[-1]
    return np.where(on_half, (lo + hi) / 2, lo)


@functools.lru_cache(maxsize=256)
def _triples(n: int) -> np.ndarray:
    """Index triples (m, 3) proposing quadratics among n >= 3 points ordered along the seam:
    one point from each third of the window (well-spread triples give well-conditioned
    quadratics), all of them up to ``MSAC_HYPOTHESES``, else that many drawn with a fixed seed
    (repeatable plans)."""
    cuts = [0, max(1, n // 3), max(2, (2 * n) // 3), n]
    t = np.stack(np.meshgrid(*[np.arange(cuts[i], cuts[i + 1]) for i in range(3)],
                             indexing="ij"), axis=-1).reshape(-1, 3)
    if len(t) > MSAC_HYPOTHESES:
        t = t[np.random.default_rng(0).choice(len(t), MSAC_HYPOTHESES, replace=False)]
    t.flags.writeable = False  # cached (drawing them cost up to 0.5 ms per fit)
    return t


def _msac_quadratic(x: np.ndarray, P: np.ndarray, thr: float) -> tuple[np.ndarray, np.ndarray]:
    """Robust quadratic P(x) = c0 + c1 x + c2 x^2 through points ``P`` (n, 3) at ``x`` (n,).

    Returns ``(coef (3, 3) rows c0, c1, c2, residuals (n,))``: MSAC over point triples (cost
    sum(min(r^2, thr^2))), then least squares on the points within ``thr`` of the winner, twice.
    """
    order = np.argsort(x)
    x, P = x[order], P[order]
    A = np.stack([np.ones_like(x), x, x * x], axis=1)                         # (n, 3)
    t = _triples(len(x))
    At = A[t]                                                                 # (m, 3, 3)
    ok = np.abs(np.linalg.det(At)) > 1e-9
    if ok.any():
        C = np.linalg.solve(At[ok], P[t[ok]])                                 # (m, 3, 3)
        r2 = ((P[None] - A[None] @ C) ** 2).sum(-1)                           # (m, n)
        best = C[int(np.argmin(np.minimum(r2, thr * thr).sum(1)))]
    else:  # points bunched at one place along the seam: no triple spans a quadratic
        best = np.linalg.lstsq(A, P, rcond=None)[0]
    r = np.linalg.norm(P - A @ best, axis=1)
    for _ in range(2):
        inl = r <= thr
        if inl.sum() < 4:
            break
        best = np.linalg.lstsq(A[inl], P[inl], rcond=None)[0]
        r = np.linalg.norm(P - A @ best, axis=1)
    out = np.empty_like(r)
    out[order] = r
    return best, out

