"""Joint profiles: the feature points of fillets, V-grooves, butt gaps and laps in one frame.

TIPM (:mod:`torchseam.vision.tipm`) finds one profile, the corner where the stripe's two arms
meet (a fillet). A laser-stripe sensor over other joints shows other shapes, each with its own
feature points and its own aim point (where the torch goes):

=========  ==========================================  ==================================
joint      what the stripe shows                       feature points (aim)
=========  ==========================================  ==================================
fillet     two arms meeting at a corner                ``corner`` (the corner)
v_groove   two plate lines, two flanks going down to   ``left_shoulder``, ``left_root``,
           a root, broken by the root gap (a closed    ``right_root``, ``right_shoulder``
           root: the flanks meet; a single bevel: one  (the root centre); the groove's
           side has no flank, its shoulder is its      width (shoulder to shoulder) and
           root edge)                                  cross-section area
butt       a straight stripe broken by the gap: a      ``left_edge``, ``right_edge`` (the
           break, a dip in its brightness (a gap       gap's centre); the gap's width
           closed flush) or a step in depth (hi-lo)
lap        a step: the upper plate's line ends at its  ``edge`` (the upper plate's corner),
           edge, the lower plate's line starts there   ``root`` (the root)
=========  ==========================================  ==================================

Every profile but the fillet is read off the stripe's centre line (:meth:`Tipm.centre`, in the
view TIPM works in: the stripe along the rows) as straight pieces fitted by total least squares
(a flank at 45 degrees or steeper is no function ``v(u)``), split where two lines explain a
piece best (an exhaustive search over the split, O(N) with cumulative sums). The stripe is
thresholded lower than TIPM's and its pieces are judged by their size grown over small
breaks (``stripe:`` in ``configs/profiles.yaml``): the flanks of a groove face away from the camera
and their stripe is thin, dim and speckled. A pixel is stripe only where it stands above the
light ``side_px`` rows above it and below it (a line, not an edge): a bright plate or table
edge beside the stripe passes TIPM's ridge filter as a band, but its bright side stays bright,
so it is not read as a piece of the stripe; a column's run taller than a stripe (a blob) is
dropped too.
A frame without the profile gives ``ok=False`` and a reason, never a guess.

Pixels are (u, v) = (column, row) of the view; :meth:`ProfileResult.to_camera` maps a result
to the camera's pixels.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from torchseam.core.config import JOINT_PROFILES, config_field, config_path, load_config
from torchseam.core.dataset import check_frame
from torchseam.core.kernels import load_kernels
from torchseam.core.orient import BRIGHTNESS, FrameView
from torchseam.core.overlay import put_label
from torchseam.vision.tipm import SATURATED, Tipm, TipmResult, red_response

#: the joint profiles (``joint:`` of a part, ``--joint`` of the commands)
JOINTS = JOINT_PROFILES


@dataclass(frozen=True)
class StripeSettings:
    """How the profiles read the stripe (``stripe:`` in ``configs/profiles.yaml``)."""

    rel_threshold: float = config_field(lo=0.0, hi=1.0)
    close_px: int = config_field(lo=0)
    min_area: int = config_field(lo=0)
    max_run_px: int = config_field(lo=3)
    side_px: int = config_field(lo=1)


@dataclass(frozen=True)
class ProfileConfig:
    """Parameters of the joint profiles (``configs/profiles.yaml``)."""

    stripe: StripeSettings
    min_points: int = config_field(lo=3)
    max_rms_px: float = config_field(lo=0.0, lo_open=True)
    min_bend_deg: float = config_field(lo=0.0, hi=90.0)
    min_gap_px: float = config_field(lo=1.0)
    end_fraction: float = config_field(lo=0.0, hi=1.0)
    dip_fraction: float = config_field(lo=0.0, hi=1.0)
    min_step_px: float = config_field(lo=0.0, lo_open=True)
    min_depth_px: float = config_field(lo=0.0)
    fit_px: float = config_field(lo=2.0)
    shoulder_ratio: float = config_field(lo=1.0)
    arm_px: float = config_field(lo=2.0)
    far_side: str = config_field(choices=("up", "down"))
    lit_face_share: float = config_field(lo=0.0, hi=1.0, lo_open=True)
    soft_sigma_px: float = config_field(lo=0.0)


def load_profile_config(path: str | Path | None = None) -> ProfileConfig:
    """Read ``configs/profiles.yaml`` (or ``path``)."""
    return load_config(ProfileConfig, path or config_path("profiles.yaml"))


#: the feature points each piece of :attr:`ProfileResult.arm_points` leaves, by profile
ARM_ROOTS = {"v_groove": ("left_root", "right_root"), "butt": ("left_edge", "right_edge"),
             "lap": ("root", "root")}
#: a lap's note (:attr:`ProfileResult.reason`) where its edge face is dark: its root and edge
#: are then the plates' own ends, two readings; where the face is lit both are where the face's
#: one line meets the plates' (the profile tracker's span check tells the two apart)
LAP_DARK_FACE = "dark edge face"


@dataclass
class ProfileResult:
    """Outcome of a joint profile on one frame.

    Attributes:
        joint: the profile (one of :data:`JOINTS`).
        ok: the profile was found.
        aim: (2,) where the torch aims (u, v), NaN when not ``ok``.
        points: the feature points by name, each (2,) (u, v) (see the module's table).
        reason: why not, when not ``ok``; a note (e.g. ``"single bevel"``) when ``ok``.
        width_px: the groove's width (v_groove: shoulder to shoulder) or the gap's (butt).
        gap_px: the root gap (v_groove), NaN where none.
        area_px2: the groove's cross-section area (v_groove), px^2 in the image.
        centre: (N, 2) centre-line points used.
        tipm: the corner TIPM found (fillet).
        arm_points: (2, 2) v_groove: a point on the stripe's piece that leaves each root
            edge (left, right), up to ``fit_px`` along it (the flank, or a side's plate where
            it has no flank), along its tangent at the edge (a quadratic over ``arm_px`` of
            it: a bevel is a cone and a pipe a cylinder, and their laser cuts curve): with
            the root edges, the two faces' directions at the root (what the torch bisects);
            butt: ``fit_px`` out along each plate from its gap edge (one line across the gap:
            the torch stands across it); lap: along the far plate and along the edge face
            from the root (:attr:`arm_roots`). None where not found.
    """

    joint: str
    ok: bool
    aim: np.ndarray
    points: dict[str, np.ndarray] = field(default_factory=dict)
    reason: str = ""
    width_px: float = float("nan")
    gap_px: float = float("nan")
    area_px2: float = float("nan")
    centre: np.ndarray | None = None
    tipm: TipmResult | None = None
    arm_points: np.ndarray | None = None

    @property
    def arm_roots(self) -> np.ndarray | None:
        """(2, 2) where each of :attr:`arm_points`' pieces leaves the joint (a groove's root
        edges, a butt's gap edges, a lap's root twice: its far plate and its edge face leave
        it); None without arm points."""
        names = ARM_ROOTS.get(self.joint)
        if names is None or self.arm_points is None:
            return None
        return np.stack([self.points[n] for n in names])

    @property
    def status(self) -> str:
        """``ok`` or ``none: <reason>``: what a per-frame log shows."""
        return "ok" + (f" ({self.reason})" if self.reason else "") if self.ok else (
            f"none: {self.reason}")

    def to_camera(self, view: FrameView) -> ProfileResult:
        """The result with its pixels in the camera image of ``view``."""
        return dataclasses.replace(
            self, aim=view.to_camera(self.aim),
            points={k: view.to_camera(p) for k, p in self.points.items()},
            centre=None if self.centre is None else view.to_camera(self.centre),
            arm_points=None if self.arm_points is None else view.to_camera(self.arm_points))


def _fail(joint: str, reason: str, centre: np.ndarray | None = None) -> ProfileResult:
    return ProfileResult(joint, False, np.full(2, np.nan), reason=reason, centre=centre)


# ---------------------------------------------------------------------- straight pieces
@dataclass(frozen=True)
class Line:
    """A straight piece of the stripe: a point ``c`` (2,), a unit direction ``d`` (2,) and the
    RMS of the points' distances to it."""

    c: np.ndarray
    d: np.ndarray
    rms: float

    def project(self, p: np.ndarray) -> np.ndarray:
        """(2,) the foot of ``p`` (2,) on the line."""
        return self.c + float((p - self.c) @ self.d) * self.d

    def v_at(self, u: float) -> float:
        """The line's row at column ``u`` (NaN for a vertical line)."""
        if abs(self.d[0]) < 1e-9:
            return float("nan")
        return float(self.c[1] + (u - self.c[0]) * self.d[1] / self.d[0])


def fit_line(p: np.ndarray, robust: bool = True) -> Line:
    """Total-least-squares line through points (N, 2), N >= 2; ``robust``: refitted once on
    the points within 3 sigma (MAD) of the first fit, so a spatter dot on a piece does not
    tilt it (compiled: ``_kernels.fit_line``)."""
    # the kernels are loaded (compiled) when the finder's Tipm is built: the same package's
    cx, cy, dx, dy, rms = load_kernels(__package__).fit_line(np.asarray(p, np.float64), robust)
    return Line(np.array([cx, cy]), np.array([dx, dy]), rms)


def split_two_lines(p: np.ndarray, min_points: int) -> int:
    """Where points (N, 2), ordered along the stripe, are best explained as two straight
    pieces: the index ``k`` of the first point of the second piece (each piece at least
    ``min_points``), or -1 when N is too small. The total-least-squares error of every split is
    read off cumulative sums (the smaller eigenvalue of each piece's scatter matrix)."""
    n = len(p)
    if n < 2 * min_points:
        return -1
    q = p - p.mean(axis=0)
    u, v = q[:, 0], q[:, 1]
    sums = np.cumsum(np.stack([np.ones(n), u, v, u * u, v * v, u * v]), axis=1)
    total = sums[:, -1:]
    k = np.arange(min_points, n - min_points + 1)
    return int(k[np.argmin(_tls_error(sums[:, k - 1]) + _tls_error(total - sums[:, k - 1]))])


def split_three_lines(p: np.ndarray, min_points: int, near: int, reach: int
                      ) -> tuple[int, int]:
    """Where points (N, 2), ordered along the stripe, are best explained as three straight
    pieces, the middle one short (a lap's edge face; empty where it is dark) and holding the
    point ``near``: ``(i0, i1)``, the middle piece ``p[i0:i1]``, ``i0 <= near <= i1``, each
    within ``reach`` points of ``near``, the outer pieces at least ``min_points`` each
    (total-least-squares errors from cumulative sums, as :func:`split_two_lines`)."""
    n = len(p)
    q = p - p.mean(axis=0)
    u, v = q[:, 0], q[:, 1]
    sums = np.concatenate([np.zeros((6, 1)), np.cumsum(
        np.stack([np.ones(n), u, v, u * u, v * v, u * v]), axis=1)], axis=1)  # (6, N + 1)

    def err(s: np.ndarray) -> np.ndarray:
        """The TLS error of pieces from their sums (6, ...); 0 for fewer than two points."""
        many = s[0] >= 2
        return np.where(many, _tls_error(np.where(many, s, 1.0)), 0.0)

    near = min(max(near, min_points), n - min_points)
    a = np.arange(max(min_points, near - reach), near + 1)            # first of the middle
    b = np.arange(near, min(n - min_points, near + reach) + 1)       # first after it
    outer = err(sums[:, a])[:, None] + err(sums[:, -1:] - sums[:, b])[None, :]
    middle = err(sums[:, None, b] - sums[:, a, None])                 # (len a, len b)
    i, k = np.unravel_index(int(np.argmin(outer + middle)), middle.shape)
    return int(a[i]), int(b[k])


def _tls_error(s: np.ndarray) -> np.ndarray:
    """(K,) the total-least-squares squared error of pieces from their sums (6, K) of 1, u, v,
    u^2, v^2, uv."""
    n = s[0]
    sxx = s[3] - s[1] ** 2 / n
    syy = s[4] - s[2] ** 2 / n
    sxy = s[5] - s[1] * s[2] / n
    return (sxx + syy) / 2 - np.sqrt(((sxx - syy) / 2) ** 2 + sxy**2)


def meet(a: Line, b: Line) -> np.ndarray | None:
    """(2,) where two lines cross; None when they are parallel."""
    m = np.stack([a.d, -b.d], axis=1)
    if abs(np.linalg.det(m)) < 1e-9:
        return None
    s = np.linalg.solve(m, b.c - a.c)
    return a.c + s[0] * a.d


def bend_deg(a: Line, b: Line) -> float:
    """How much the stripe turns from one line to the other, degrees in [0, 90]."""
    return float(np.degrees(np.arccos(min(1.0, abs(float(a.d @ b.d))))))


def groove_area(poly: np.ndarray) -> float:
    """The area (px^2) of a polygon (N, 2) (the shoelace formula)."""
    x, y = poly[:, 0], poly[:, 1]
    return float(abs(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1))) / 2)


# ---------------------------------------------------------------------- the finder
class ProfileFinder:
    """The feature points of one joint profile in a frame (:data:`JOINTS`).

    Args:
        tipm: TIPM, whose stripe response, centre line and (fillet) corner are used.
        cfg: :class:`ProfileConfig`.
        joint: the profile.

    Example:
        >>> from torchseam.vision.tipm import load_tipm
        >>> find = ProfileFinder(load_tipm(), load_profile_config(), "butt")
        >>> find(np.zeros((64, 64), np.uint8)).status
        'none: no stripe found (no red pixels above threshold)'
    """

    def __init__(self, tipm: Tipm, cfg: ProfileConfig, joint: str = "fillet") -> None:
        if joint not in JOINTS:
            raise ValueError(f"joint {joint!r}: use one of {', '.join(JOINTS)}")
        self.tipm, self.cfg, self.joint = tipm, cfg, joint
        s = cfg.stripe
        # TIPM's stripe response and centre line with the profiles' threshold; no area filter
        # and no dilation there: the profiles judge pieces grown over breaks (stripe())
        self._low = Tipm(dataclasses.replace(tipm.cfg, rel_threshold=s.rel_threshold,
                                             min_area=0, dilate_px=0), tipm.centre_line)
        self._close = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * s.close_px + 1,) * 2)
        self._tall = np.ones((s.max_run_px + 1, 1), np.uint8)
        self._across = np.ones((2 * s.side_px + 1, 1), np.uint8)
        self._dilate = tipm._kernel
        self._ridge = np.zeros((1, 1), np.uint8)  # the frame's stripe response (see _end)
        #: the most stripe response the intensity frame last read has room for at each pixel
        #: (headroom; _end); None for a colour frame's red excess
        self._room: np.ndarray | None = None
        #: the stripe's whole width (rows) on the frame last read: side_px, or its mask's
        #: median height + 1 where taller (stripe(); glare_white)
        self._width = cfg.stripe.side_px

    def __call__(self, frame: np.ndarray) -> ProfileResult:
        """The profile in one frame (H, W[, 3]), 8 or 16 bit, the stripe along the rows."""
        frame = check_frame(frame)
        if self.joint == "fillet":
            res = self.tipm(frame)
            if not res.ok:
                return _fail("fillet", res.reason, res.centre)
            return ProfileResult("fillet", True, res.uv.copy(), {"corner": res.uv.copy()},
                                 centre=res.centre, tipm=res)
        if frame.ndim != 3:
            found = self._profile(frame)
            return found if found.ok else self._soft(frame, found, found)
        # a colour frame is also looked at by its brightness, as a mono frame: where the red
        # excess gives no profile (Tipm.find says why: red glare clipped round the stripe,
        # red-tinted fume), and where glare clips R round the stripe at the joint on more
        # than white_core_fraction of its centre line within fit_px of the aim (the stretch
        # the feature points are read from; glare_white). There the red excess no longer
        # tells the stripe: clipped R carries nothing, and R - max(G, B) dips where the
        # stripe raises G and B; its centre line runs where R drops out of clipping beside
        # the stripe (3-5 px off) or stops, and its feature points move with it. The share
        # is taken on the brightness's centre line (the red excess's is off the white or
        # missing there), and the brightness's profile is taken only where the red excess
        # gives none or reads the same joint, its aim within the stripe's width of the
        # brightness's (moved by the light clipped beside the stripe; max_run_px + 1 at
        # most). Farther apart they read different things, and glare at one says not which
        # is right: the brightness also shows the arc's white light, which the red excess
        # tells from the stripe (a groove under the arc: its brightness put the root 33-39 px
        # off, the red excess within 1 px; a lap's red excess 9-10 px off with the glow on
        # its face stays)
        found = self._profile(frame)
        if not found.ok:
            bright = cv2.transform(frame, BRIGHTNESS)
            grey = self._profile(bright)
            return grey if grey.ok else self._soft(bright, grey, found)
        # the brightness is read beside a found profile only where white light lies within
        # fit_px of an aim it could be taken at as the same joint (a stripe's width of this
        # one's; a stripe is no wider than max_run_px + 1: a taller run is a blob, stripe())
        # or in a break of the red excess's centre line (where it is blind); elsewhere the red
        # excess's profile stands, and most frames under the arc cost one reading (a
        # brightness joint beside a red centre line that runs elsewhere, with no break, is
        # not looked for)
        reach = self.cfg.stripe.max_run_px + 1
        if frame.dtype != np.uint8 or not (
                _any_white(_around(frame, found.aim, int(self.cfg.fit_px) + reach + 2))
                or self._white_break(frame, found.centre)):
            return found
        grey = self._profile(cv2.transform(frame, BRIGHTNESS))
        width = self._width   # the stripe's, in the brightness
        if not grey.ok or (self._white_at_joint(frame, grey, width)
                           <= self.tipm.cfg.white_core_fraction):
            return found
        # the two read the same joint; or the red excess is blind at the brightness's (its
        # centre line has no point within fit_px of its aim, where glare clips R round the
        # stripe): it cannot read that joint, and what it read elsewhere says not that the
        # joint is not there (a lap's white step under the arc: the red excess's step 30-230
        # px off, on a break beside it; the brightness's within 1 px)
        if float(np.linalg.norm(found.aim - grey.aim)) <= min(width, reach) or (
                found.centre is not None and len(found.centre) and float(np.min(
                    np.linalg.norm(found.centre - grey.aim, axis=1))) > self.cfg.fit_px):
            return grey
        return found

    def _soft(self, bright: np.ndarray, grey: ProfileResult, found: ProfileResult
              ) -> ProfileResult:
        """A groove's last look, where neither the red excess nor the brightness gives one:
        the brightness ``bright`` (H, W) blurred by a Gaussian of ``soft_sigma_px``; the
        profile found there, else ``found`` (the first look's failure: its reason stands).
        ``grey``: the brightness's own failure (a frame saturated by arc light is not looked
        at again).

        Why: fume veils the stripe, blurred to 8-10 px on a bright veil, and the read noise
        on the veil sets the threshold (TIPM's noise term, ``noise_k`` times the ridge's 90th
        percentile: 18-33, median 21, above the stripe's median ridge on half the bench's
        `smoke` extreme frames; docs/benchmarks.md, issue 37 h33): the flanks' mask breaks
        into pieces smaller than ``min_area``,
        or misses a flank, and no groove is read (or one on spatter streaks). The read noise
        is the pixels' own; the fumed stripe is wider than the blur: blurred, the noise and
        the threshold with it fall several times while the stripe keeps most of its ridge,
        and its centre line and ends (where it has half its light) stay where they were.
        Only a groove (the tracker checks its root edges against their recent places, and
        a frame it reads off is no evidence); a frame with a groove at the first looks
        keeps it."""
        sigma = self.cfg.soft_sigma_px
        if self.joint != "v_groove" or sigma <= 0 or grey.reason == SATURATED:
            return found
        soft = self._profile(cv2.GaussianBlur(bright, (0, 0), sigma))
        return soft if soft.ok else found

    def _white_break(self, frame: np.ndarray, pts: np.ndarray | None) -> bool:
        """Whether glare whitens the stripe in a break of a centre line (N, 2) (ordered along
        the rows): a white pixel (:func:`_any_white`) in the box over a break at least
        ``min_gap_px`` wide, a stripe's reach (``max_run_px + 1``) above and below the
        line's ends there. The red excess sees nothing where glare clips R round the stripe:
        its centre line breaks there, and the joint may lie in the break."""
        if pts is None or len(pts) < 2:
            return False
        r = self.cfg.stripe.max_run_px + 1
        h, w = frame.shape[:2]
        for i in np.flatnonzero(np.diff(pts[:, 0]) >= self.cfg.min_gap_px):
            (u0, v0), (u1, v1) = pts[i], pts[i + 1]
            box = frame[max(int(min(v0, v1)) - r, 0):min(int(max(v0, v1)) + r + 1, h),
                        max(int(u0), 0):min(int(u1) + 1, w)]
            if _any_white(np.ascontiguousarray(box)):
                return True
        return False

    def _white_at_joint(self, frame: np.ndarray, res: ProfileResult, width: int) -> float:
        """The share of a found profile's centre-line points within ``fit_px`` of its aim
        where glare clips R round the stripe (``width`` rows wide) in the BGR ``frame``
        (:func:`glare_white`)."""
        if res.centre is None or not len(res.centre):
            return 0.0
        near = res.centre[np.linalg.norm(res.centre - res.aim, axis=1) <= self.cfg.fit_px]
        return float(np.mean(glare_white(frame, near, width))) if len(near) else 0.0

    def _profile(self, frame: np.ndarray) -> ProfileResult:
        """:meth:`__call__`'s profile of a checked frame read by one response: a colour
        frame's red excess, a mono frame's intensity."""
        ridge, mask, why = self.stripe(frame)
        if why:
            return _fail(self.joint, why)
        pts = saturated_centre(frame, self._low.centre(ridge, mask), self.cfg.stripe.max_run_px)
        if len(pts) < 2 * self.cfg.min_points:
            return _fail(self.joint, f"no stripe found ({len(pts)} centre-line points)", pts)
        resp = response_at(ridge, pts)
        if (self.joint == "v_groove" and frame.ndim == 3
                and np.median(resp) < self._low.cfg.min_red):
            # a stripe saturated in R and G has no red excess in its core, where its centre
            # line runs (saturated_centre): no level to tell where it ends by. A groove's root
            # edges are its stripe's ends: each was followed on over the root gap or into the
            # glare beside it (where both were, they crossed; where one side's line started
            # late under the glare, the root read off by tens of px). Its brightness reads it
            # (__call__). (A butt's ends cross there, and a lap's are checked against its span.)
            return _fail(self.joint, "no stripe found (white along its centre line: no red "
                         "excess to end it by)", pts)
        self._ridge = ridge
        # the red excess has no room to speak of where R clips (it dips at the stripe there:
        # glare_white; the brightness reads such frames, __call__): only an intensity's room
        self._room = headroom(frame, self.tipm.cfg.ridge_px) if frame.ndim == 2 else None
        finder = {"v_groove": self._v_groove, "butt": self._butt, "lap": self._lap}[self.joint]
        return finder(pts, resp)

    def stripe(self, frame: np.ndarray) -> tuple[np.ndarray, np.ndarray, str]:
        """The stripe response (H, W) uint8 (a copy), the profiles' mask (H, W) uint8 and a
        failure reason: TIPM's ridge thresholded at the profiles' level, pieces under
        ``min_area`` (grown by ``close_px``) dropped, runs taller than ``max_run_px``
        dropped, dilated as TIPM's."""
        s = self.cfg.stripe
        ridge, binary, why = self._low.stripe_mask(frame)
        ridge = ridge.copy()
        if why:
            return ridge, np.zeros_like(ridge), why
        # a line is brighter than the light side_px rows above AND below it; a bright part or
        # table edge is not (its bright side stays bright), though its ridge is a band
        red = red_response(frame)
        # beyond the stripe's whole width at least: a wide stripe saturated in R and G has a
        # red excess of two ridges, its edges, side_px apart or less; each would fail the test
        # on the other (its width: the median of the columns of its mask closed across)
        cols = np.count_nonzero(cv2.morphologyEx(binary, cv2.MORPH_CLOSE, self._across),
                                axis=0)
        k = max(s.side_px, int(np.median(cols[cols > 0])) + 1 if cols.any() else 0)
        self._width = k
        side = np.zeros_like(red)
        side[k:] = red[:-k]
        side[:-k] = np.maximum(side[:-k], red[k:])
        line = cv2.subtract(red, side)
        binary = cv2.bitwise_and(binary, cv2.compare(
            2 * line.astype(np.uint16), ridge.astype(np.uint16), cv2.CMP_GE))
        # a tall run is a bright blob, not the stripe
        binary = cv2.subtract(binary, cv2.morphologyEx(binary, cv2.MORPH_OPEN, self._tall))
        # pieces are measured grown by close_px (a speckled flank breaks into short dashes)
        grown = cv2.dilate(binary, self._close)
        # labelled in the box that holds anything (the stripe is a thin band)
        bx, by, bw, bh = cv2.boundingRect(grown)
        if bw == 0:
            return ridge, np.zeros_like(ridge), "no stripe found (only small blobs)"
        box = (slice(by, by + bh), slice(bx, bx + bw))
        n, lab, st, _ = cv2.connectedComponentsWithStats(grown[box], connectivity=8,
                                                         ltype=cv2.CV_16U)
        keep = np.zeros(max(n, 256), np.uint8)
        keep[1:n][st[1:, cv2.CC_STAT_AREA] >= s.min_area] = 255
        if not keep.any():
            return ridge, np.zeros_like(ridge), "no stripe found (only small blobs)"
        kept = np.zeros_like(binary)
        # cv2.LUT takes 8-bit labels; with <= 256 labels (nearly always) it is 5x np.take
        kept[box] = (cv2.LUT(lab.astype(np.uint8), keep[:256]) if n <= 256
                     else np.take(keep, lab))  # type: ignore[arg-type]  # CV_16U labels
        return ridge, cv2.dilate(cv2.bitwise_and(kept, binary), self._dilate), ""

    # ------------------------------------------------------------------ pieces
    def _end(self, piece: np.ndarray, resp: np.ndarray, line: Line) -> np.ndarray:
        """(2,) where a piece (N, 2), ordered from its free end (a gap) inward, ends: the first
        point whose response reaches ``end_fraction`` of the piece's median, on ``line``, then
        followed along the line as far as the stripe stays that bright (the centre line's
        path may stop short of an end where the stripe jumps: a lap's step), to the sub-pixel
        point where the response (bilinear, the brightest of the line and a pixel either side
        of it) falls through that level: a blurred line's end is where it has half its
        brightness, and whole-pixel steps stopped ~1 px short of it."""
        median = float(np.median(resp))
        lit = resp >= self._level(piece, median)
        k = int(np.argmax(lit)) if lit.any() else 0
        end = line.project(piece[k])
        if len(piece) < 2:
            return end
        out = piece[0] - piece[-1]
        step = line.d if float(out @ line.d) > 0 else -line.d
        normal = np.array([-step[1], step[0]])
        ds = END_STEP_PX
        n = int(4 * self.cfg.min_gap_px / ds)
        along = end + (ds * np.arange(n + 1))[:, None] * step                  # (n + 1, 2)
        val = _bilinear(self._ridge, (along[None] + np.array([-1.0, 0.0, 1.0])[:, None, None]
                                      * normal).reshape(-1, 2)).reshape(3, -1).max(axis=0)
        level = self._level(along, median)
        below = np.flatnonzero(val < level)
        if not len(below) or below[0] == 0:  # bright throughout, or dim where it starts
            return along[-1] if not len(below) else end
        i = int(below[0])
        frac = (val[i - 1] - level[i - 1]) / max(val[i - 1] - val[i], 1e-9)
        return along[i - 1] + frac * ds * step

    def _level(self, p: np.ndarray, median: float) -> np.ndarray:
        """(N,) the response at points (N, 2) below which the stripe has ended there:
        ``end_fraction`` of the piece's ``median`` response, or of the room the frame leaves
        the response there where that is less (:func:`headroom`: glare that lifts the light
        towards clipping leaves a stripe on it less to rise by, and the stripe's last lit
        pixels under the glare at the root read dim though lit), there never below TIPM's
        floor ``min_red`` (where glare clips the plane there is no room, and nothing is
        lit)."""
        level = np.full(len(p), self.cfg.end_fraction * median)
        if self._room is not None:
            room = _bilinear(self._room, p)
            low = room < median
            level[low] = np.maximum(self.cfg.end_fraction * room[low], self._low.cfg.min_red)
        return level

    def _near(self, piece: np.ndarray, reach: float | None = None) -> int:
        """How many points of a piece (N, 2), from its first, lie within ``fit_px`` (or
        ``reach``) of it (at least ``min_points``): the stretch a line is fitted to next to an
        edge, where a curved surface (a pipe cut by the laser plane) is still straight."""
        d = np.linalg.norm(piece - piece[0], axis=1)
        return max(self.cfg.min_points, int(np.searchsorted(
            np.maximum.accumulate(d), self.cfg.fit_px if reach is None else reach,
            side="right")))

    def _side(self, side: np.ndarray, resp: np.ndarray
              ) -> tuple[Line, Line | None, np.ndarray, np.ndarray, np.ndarray] | str:
        """One side of a groove, its points (N, 2) ordered from the root outward: the line at
        the root (the flank; the plate where the side has no bevel), the plate's line (None:
        no bevel), the shoulder, the root edge and a point up the root's piece (``fit_px``
        along it at most); or why not.

        A side has a shoulder where two straight pieces explain it (each within
        ``max_rms_px``), bending by ``min_bend_deg`` at least, ``shoulder_ratio`` times better
        than one smooth curve (a quadratic): a curved plate (a pipe cut by the laser plane)
        split in two bends too, but a quadratic follows it as well as two lines. Lines next to
        an edge are fitted to the ``fit_px`` of the piece there."""
        cfg = self.cfg
        m = cfg.min_points
        if len(side) < m:
            return f"only {len(side)} points"
        k = split_two_lines(side, m)
        if k > 0:
            flank, plate = fit_line(side[:k]), fit_line(side[k:])
            shoulder = meet(flank, plate)
            two = max(flank.rms, plate.rms)
            if (bend_deg(flank, plate) >= cfg.min_bend_deg and shoulder is not None
                    and _curve_rms(side) > cfg.shoulder_ratio * max(two, 0.25)):
                if two > cfg.max_rms_px:
                    return f"fit residual {two:.2f} px"
                near = fit_line(side[k:k + self._near(side[k:])])
                shoulder = meet(flank, near)
                if shoulder is None:
                    shoulder = flank.project(side[k])
                root = self._end(side[:k], resp[:k], flank)
                reach = min(cfg.fit_px, float(np.linalg.norm(shoulder - root)))
                along = _tangent_at(side[:min(k, self._near(side, cfg.arm_px))], flank, root)
                return flank, plate, shoulder, root, root + reach * along
        n = self._near(side)
        line = fit_line(side[:n])
        if line.rms > cfg.max_rms_px:
            return f"fit residual {line.rms:.2f} px"
        root = self._end(side, resp, line)
        along = _tangent_at(side[:self._near(side, cfg.arm_px)], line, root)
        return line, None, root, root, root + cfg.fit_px * along

    def _v_groove(self, pts: np.ndarray, resp: np.ndarray) -> ProfileResult:
        cfg = self.cfg
        du = np.diff(pts[:, 0])
        j = int(np.argmax(du))
        closed = bool(du[j] < cfg.min_gap_px)
        breaks = np.flatnonzero(du >= cfg.min_gap_px)
        if len(breaks) > 1:
            # the root gap is the deepest break (farthest from the chord of the stripe's
            # ends), not the widest: a wide, blurred stripe narrows the root gap below a
            # dropout on a plate
            a, b = pts[0], pts[-1]
            n = np.array([a[1] - b[1], b[0] - a[0]])
            mid = 0.5 * (pts[breaks] + pts[breaks + 1])
            j = int(breaks[np.argmax(np.abs((mid - a) @ n))])
        if not closed:  # the root gap
            left, right = pts[j::-1], pts[j + 1:]
            lresp, rresp = resp[j::-1], resp[j + 1:]
        else:  # a closed root: the flanks meet at the point farthest from the chord
            a, b = pts[0], pts[-1]
            n = np.array([a[1] - b[1], b[0] - a[0]])
            j = int(np.argmax(np.abs((pts - a) @ n)))
            left, right, lresp, rresp = pts[j::-1], pts[j:], resp[j::-1], resp[j:]
        found = []
        for name, side, sresp in (("left", left, lresp), ("right", right, rresp)):
            got = self._side(side, sresp)
            if isinstance(got, str):
                return _fail("v_groove", f"no groove: its {name} side: {got}", pts)
            found.append(got)
        (lf, lp, ls, lr, la), (rf, rp, rs, rr, ra) = found
        if lp is None and rp is None:
            return _fail("v_groove", "no groove: no shoulder on either side (a square butt "
                         "gap? try the butt profile)", pts)
        if closed:  # both root edges where the flanks meet
            x = meet(lf, rf)
            if x is None:
                return _fail("v_groove", "no groove: the flanks are parallel", pts)
            lr = rr = x
        along = pts[-1] - pts[0]
        if float((rr - lr) @ along) < -float(np.linalg.norm(along)):   # over 1 px the wrong way
            return _fail("v_groove", "no groove: its root edges cross", pts)
        aim = (lr + rr) / 2
        top = rs - ls
        down = aim - ls
        depth = abs(float(top[0] * down[1] - top[1] * down[0])) / max(
            float(np.linalg.norm(top)), 1e-9)
        if depth < cfg.min_depth_px:
            return _fail("v_groove", f"no groove: the root is {depth:.1f} px below the "
                         "shoulders", pts)
        note = "single bevel" if lp is None or rp is None else ""
        poly = np.stack([ls, lr, rr, rs])
        return ProfileResult(
            "v_groove", True, aim,
            {"left_shoulder": ls, "left_root": lr, "right_root": rr, "right_shoulder": rs},
            note, float(np.linalg.norm(top)), float(np.linalg.norm(rr - lr)), groove_area(poly),
            pts, arm_points=np.stack([la, ra]))

    def _two_plates(self, pts: np.ndarray, resp: np.ndarray, j: int
                    ) -> tuple[Line, Line, np.ndarray, np.ndarray] | str:
        """The lines of the plates left and right of a joint between centre points ``j`` and
        ``j + 1`` and the ends of the stripe at it; or why not."""
        cfg = self.cfg
        left, right = pts[j::-1], pts[j + 1:]
        if min(len(left), len(right)) < cfg.min_points:
            return f"a plate has only {min(len(left), len(right))} points"
        a, b = fit_line(left), fit_line(right)
        if max(a.rms, b.rms) > cfg.max_rms_px:
            return f"plate fit residual {max(a.rms, b.rms):.2f} px"
        if bend_deg(a, b) >= cfg.min_bend_deg:
            return f"the stripe bends by {bend_deg(a, b):.1f} deg at the joint"
        return a, b, self._end(left, resp[j::-1], a), self._end(right, resp[j + 1:], b)

    def _butt(self, pts: np.ndarray, resp: np.ndarray) -> ProfileResult:
        cfg = self.cfg
        du = np.diff(pts[:, 0])
        dv = np.abs(np.diff(pts[:, 1]))
        j = int(np.argmax(du))
        how = "break"
        if du[j] < cfg.min_gap_px:
            j = int(np.argmax(dv))
            how = "step"
            if dv[j] < cfg.min_step_px:
                dip = _dip(resp, cfg.dip_fraction)
                if dip is None:
                    return _fail("butt", "no gap: the stripe is unbroken, even and straight",
                                 pts)
                i0, i1 = dip
                sides = self._two_plates(pts, resp, i0 - 1)
                if isinstance(sides, str):
                    return _fail("butt", f"no gap: {sides}", pts)
                a, b = sides[0], sides[1]
                le, re = a.project(pts[i0 - 1]), b.project(pts[i1])
                arms = np.stack([le + self.cfg.fit_px * _outward(a, pts[i0 - 1::-1]),
                                 re + self.cfg.fit_px * _outward(b, pts[i1:])])
                return ProfileResult("butt", True, (le + re) / 2,
                                     {"left_edge": le, "right_edge": re}, "dip",
                                     float(np.linalg.norm(re - le)), centre=pts,
                                     arm_points=arms)
        along = pts[-1] - pts[0]
        along = along / max(float(np.linalg.norm(along)), 1e-9)
        if how == "break":
            # the gap is the widest break as the stripe's ends read it, not as the centre line
            # breaks: a glint streak over the stripe makes its columns' runs tall and drops
            # them from the centre line, though the stripe is lit there (its ends, followed
            # along the line, meet across such a break)
            best: tuple[float, int, tuple[Line, Line, np.ndarray, np.ndarray]] | None = None
            why = ""
            for i in np.flatnonzero(du >= cfg.min_gap_px):
                got = self._two_plates(pts, resp, int(i))
                if isinstance(got, str):
                    why = why or got
                    continue
                width = float((got[3] - got[2]) @ along)
                if best is None or width > best[0]:
                    best = (width, int(i), got)
            if best is None:
                return _fail("butt", f"no gap: {why}", pts)
            width, j, sides = best
        else:
            got = self._two_plates(pts, resp, j)
            if isinstance(got, str):
                return _fail("butt", f"no gap: {got}", pts)
            sides = got
            width = float((sides[3] - sides[2]) @ along)
        a, b, le, re = sides
        if width < -1.0:   # over 1 px the wrong way
            # each end followed on along the stripe past the other: no gap read (a stripe
            # overexposed into white has no red excess in its core, two ridges at its edges:
            # its response along the centre line is no brightness to find an end by)
            return _fail("butt", "no gap: its edges cross", pts)
        arms = np.stack([le + self.cfg.fit_px * _outward(a, pts[j::-1]),
                         re + self.cfg.fit_px * _outward(b, pts[j + 1:])])
        return ProfileResult("butt", True, (le + re) / 2, {"left_edge": le, "right_edge": re},
                             how, float(abs(re[0] - le[0])), centre=pts, arm_points=arms)

    def _plates(self, left: np.ndarray, right: np.ndarray) -> tuple[Line, Line] | str:
        """A lap's two plates, their points (N, 2) from the joint outward: their lines next
        to the joint (``fit_px``), straight and parallel; or why not."""
        cfg = self.cfg
        m = cfg.min_points
        if min(len(left), len(right)) < m:
            return f"a plate has only {min(len(left), len(right))} points"
        for side in (left, right):   # a plate is one smooth curve all along (no shoulder)
            curve = _curve_rms(side)
            if curve > cfg.max_rms_px:
                return f"a plate is no smooth curve (residual {curve:.2f} px)"
            k = split_two_lines(side, m)
            if k > 0:
                p, q = fit_line(side[:k]), fit_line(side[k:])
                if (bend_deg(p, q) >= cfg.min_bend_deg
                        and curve > cfg.shoulder_ratio * max(p.rms, q.rms, 0.25)):
                    return f"a plate bends by {bend_deg(p, q):.1f} deg (a groove's shoulder?)"
        a = fit_line(left[:self._near(left)])
        b = fit_line(right[:self._near(right)])
        if max(a.rms, b.rms) > cfg.max_rms_px:
            return f"plate fit residual {max(a.rms, b.rms):.2f} px"
        if bend_deg(a, b) >= cfg.min_bend_deg:
            return f"the plates are {bend_deg(a, b):.1f} deg apart (not parallel)"
        return a, b

    def _lap(self, pts: np.ndarray, resp: np.ndarray) -> ProfileResult:
        """Two parallel plates, one nearer the sensor, the step between them: the near plate's
        edge face lit (the stripe runs down it: a Z) or dark (a break). Read along the
        stripe's own direction, so a stripe across the view at any slope is read as one along
        the rows: the offset across it jumps (or ramps, over the lit face) by the step. The
        root, where the fillet goes, is the far plate's end (``far_side``); the edge the near
        plate's. A dark face is noted (:data:`LAP_DARK_FACE`): its two ends are read apart."""
        cfg = self.cfg
        m = cfg.min_points
        # the stripe's direction: the median of its local directions (the plates' own, the
        # face being short beside them); the offsets across it
        w = min(5, len(pts) - 1)
        step_d = pts[w:] - pts[:-w]
        ang = float(np.median(np.arctan2(step_d[:, 1], step_d[:, 0])))
        across = np.array([-np.sin(ang), np.cos(ang)])   # the down side of the stripe
        n = (pts - pts[0]) @ across
        # where the offset jumps: the split into a before and an after that explains the
        # offsets best (each side at least min_points)
        k = np.arange(m, len(pts) - m + 1)
        c1 = np.concatenate([[0.0], np.cumsum(n)])
        c2 = np.concatenate([[0.0], np.cumsum(n * n)])
        sse = ((c2[k] - c1[k] ** 2 / k)
               + (c2[-1] - c2[k] - (c1[-1] - c1[k]) ** 2 / (len(pts) - k)))
        j = int(k[np.argmin(sse)])
        offset = float(np.median(n[j:]) - np.median(n[:j]))   # the after plate's, down
        jump = abs(offset)
        if jump < cfg.min_step_px:
            return _fail("lap", f"no step: the plates are {jump:.1f} px apart", pts)
        # the plates and the edge face between them: three straight pieces round the jump
        i0, i1 = split_three_lines(pts, m, j, int(2 * cfg.fit_px))
        lit = self._plates(pts[:i0][::-1], pts[i1:])
        face = pts[i0:i1]
        f = fit_line(face) if len(face) >= 3 else None
        if (not isinstance(lit, str) and f is not None
                and float(np.linalg.norm(face[-1] - face[0])) >= cfg.min_step_px
                and min(bend_deg(lit[0], f), bend_deg(lit[1], f)) >= cfg.min_bend_deg):
            a, b = lit   # the lit edge face: the corners where its line meets the plates'
            le, re = meet(a, f), meet(b, f)
            assert le is not None and re is not None   # not parallel: they bend
            note = ""
        else:            # a dark face (no third piece across the plates): their ends
            left, right = pts[:j][::-1], pts[j:]
            dark = self._plates(left, right)
            if isinstance(dark, str):
                return _fail("lap", f"no step: {dark}", pts)
            a, b = dark
            le = self._end(left, response_at(self._ridge, left), a)
            re = self._end(right, response_at(self._ridge, right), b)
            # a dark face is dark between the plates' ends; where the stripe is lit there, the
            # face is lit and its centre line was lost (its speckled pixels dropped as small
            # pieces, fume over it): the ends read are where that line stopped, not where the
            # plates end, and each is carried on into the face's light at its corner
            lit_share = self._lit_between(le, re, resp)
            if lit_share > cfg.lit_face_share:
                return _fail("lap", f"a lit edge face without its centre line (lit on "
                             f"{100 * lit_share:.0f} % between the plates' ends)", pts)
            note = LAP_DARK_FACE
        # the far plate shows on the far side of the other: its end is the root
        before_far = (offset > 0.0) == (cfg.far_side == "up")
        root, edge, plate, piece = ((le, re, a, pts[:j][::-1]) if before_far
                                    else (re, le, b, pts[j:]))
        face = edge - root
        face_d = face / max(float(np.linalg.norm(face)), 1e-9)
        arms = np.stack([root + cfg.fit_px * _outward(plate, piece), root + cfg.fit_px * face_d])
        return ProfileResult("lap", True, root.copy(), {"edge": edge, "root": root}, note,
                             width_px=jump, centre=pts, arm_points=arms)

    def _lit_between(self, a: np.ndarray, b: np.ndarray, resp: np.ndarray) -> float:
        """The share of the segment from ``a`` to ``b`` (a lap's two plates' ends as read
        apart), farther than the stripe's width from either, where the stripe's response
        (:meth:`_end`'s: the frame's ridge, at ``end_fraction`` of the centre line's median
        response ``resp``) is lit within half the stripe's width across the segment (a lit
        face's stripe runs from corner to corner; the ends read off its corners put the
        segment up to a few pixels beside it). 0 where the segment is no longer than two
        stripe widths (too short to tell)."""
        w = float(self._width)
        d = b - a
        length = float(np.linalg.norm(d))
        if length <= 2.0 * w:
            return 0.0
        d = d / length
        normal = np.array([-d[1], d[0]])
        level = self.cfg.end_fraction * float(np.median(resp))
        along = a + (w + END_STEP_PX * np.arange(int((length - 2.0 * w) / END_STEP_PX) + 1)
                     )[:, None] * d                                              # (n, 2)
        across = np.arange(-0.5 * w, 0.5 * w + 1e-9, 1.0)                        # (m,)
        val = _bilinear(self._ridge, (along[None] + across[:, None, None] * normal)
                        .reshape(-1, 2)).reshape(len(across), -1).max(axis=0)
        return float(np.mean(val >= level))


#: :meth:`ProfileFinder._end`'s step along a line when it follows the stripe to its end (px)
END_STEP_PX = 0.25


def _bilinear(img: np.ndarray, p: np.ndarray) -> np.ndarray:
    """(N,) ``img`` (H, W) sampled bilinearly at points (N, 2) (u, v); 0 outside it."""
    h, w = img.shape
    u, v = p[:, 0], p[:, 1]
    inside = (u >= 0) & (u <= w - 1) & (v >= 0) & (v <= h - 1)
    u0 = np.clip(np.floor(u).astype(int), 0, w - 2)
    v0 = np.clip(np.floor(v).astype(int), 0, h - 2)
    fu, fv = np.clip(u - u0, 0, 1), np.clip(v - v0, 0, 1)
    f00, f01 = img[v0, u0].astype(float), img[v0, u0 + 1].astype(float)
    f10, f11 = img[v0 + 1, u0].astype(float), img[v0 + 1, u0 + 1].astype(float)
    val = (1 - fu) * (1 - fv) * f00 + fu * (1 - fv) * f01 + (1 - fu) * fv * f10 + fu * fv * f11
    return np.where(inside, val, 0.0)


def _outward(line: Line, piece: np.ndarray) -> np.ndarray:
    """(2,) the unit direction of ``line`` from a piece's first point (N, 2) towards its
    last."""
    return line.d if float((piece[-1] - piece[0]) @ line.d) >= 0 else -line.d


def _tangent_at(piece: np.ndarray, line: Line, at: np.ndarray) -> np.ndarray:
    """(2,) the unit direction of a piece (N, 2), ordered from ``at`` (its end, on ``line``)
    outward, at ``at``: the tangent there of the quadratic fitted to it across ``line`` (a
    plate that is a pipe cut by the laser plane curves; a line fitted along it gives the
    direction at the middle of the stretch, off the one at its end by half the turn over
    it). The line's own direction where there are too few points for a quadratic."""
    out = _outward(line, piece)
    if len(piece) < 6:
        return out
    nrm = np.array([-out[1], out[0]])
    x, y = (piece - at) @ out, (piece - at) @ nrm
    if float(np.ptp(x)) < 1e-6:
        return out
    slope = float(np.polyfit(x, y, 2)[1])
    d = out + slope * nrm
    return d / float(np.linalg.norm(d))


def _curve_rms(p: np.ndarray) -> float:
    """RMS distance of points (N, 2) from the quadratic fitted to them across their chord
    (least squares in the chord's frame): how well one smooth curve explains them."""
    chord = p[-1] - p[0]
    n = float(np.linalg.norm(chord))
    if n < 1e-9 or len(p) < 4:
        return 0.0
    t = chord / n
    x, y = (p - p[0]) @ t, (p - p[0]) @ np.array([-t[1], t[0]])
    r = y - np.polyval(np.polyfit(x, y, 2), x)
    return float(np.sqrt(np.mean(r * r)))


def _dip(resp: np.ndarray, fraction: float) -> tuple[int, int] | None:
    """The longest run ``[i0, i1)`` of centre points (not at the stripe's ends) whose response
    is below ``fraction`` of the median: a gap closed flush, lit but darker; None if none."""
    low = resp < fraction * np.median(resp)
    if not low.any():
        return None
    d = np.diff(np.concatenate([[0], low.astype(np.int8), [0]]))
    starts, ends = np.nonzero(d == 1)[0], np.nonzero(d == -1)[0]
    inner = (starts > 0) & (ends < len(resp))
    if not inner.any():
        return None
    k = int(np.argmax(np.where(inner, ends - starts, -1)))
    return int(starts[k]), int(ends[k])


#: :func:`saturated_centre`: a point's saturated run starts at most this many rows from it (it
#: sits on one of the run's edges)
SATURATED_NEAR_PX = 3
#: an 8-bit pixel at or above this is saturated
SATURATED_LEVEL = 250


def saturated_centre(frame: np.ndarray, pts: np.ndarray, max_run: int) -> np.ndarray:
    """Centre points (N, 2) of a stripe moved to the middle of its saturated run where it has
    one. A stripe bright enough to saturate R (and G with it, over arc light or a wide
    stripe's bleed) has no red excess in its core: its response is two ridges, its edges, and
    a centre line weighed on them sits on the stronger one when glare dims the other (3-6 px
    off on a wide stripe). The run of pixels saturated in R nearest each point, starting
    within ``SATURATED_NEAR_PX`` rows of it (the point is on its edge), at most ``max_run``
    rows tall (a taller saturated blob of glare is no stripe: the profiles' ``max_run_px``)
    and saturated in G too somewhere (where the red excess splits; a stripe saturated in R
    alone keeps its excess and its centre), gives the point its middle; other points stay.
    Mono frames are left as they are (their response is the intensity: no split)."""
    if not len(pts) or frame.ndim != 3:   # mono: the response is the intensity, no split
        return pts
    plane, green = frame[..., 2], frame[..., 1]
    h = plane.shape[0]
    u = np.clip(np.rint(pts[:, 0]).astype(int), 0, plane.shape[1] - 1)
    v0 = np.rint(pts[:, 1]).astype(int)
    reach = max_run + SATURATED_NEAR_PX
    rows = v0[:, None] + np.arange(-reach, reach + 1)[None, :]            # (N, M)
    inside = (rows >= 0) & (rows < h)
    at = (np.clip(rows, 0, h - 1), u[:, None])
    sat = inside & (plane[at] >= SATURATED_LEVEL)
    split = inside & sat & (green[at] >= SATURATED_LEVEL)   # no red excess there
    has = sat.any(axis=1)
    if not has.any():
        return pts
    starts = sat & ~np.concatenate([np.zeros((len(pts), 1), bool), sat[:, :-1]], axis=1)
    run = np.cumsum(starts, axis=1) * sat                                  # run ids, 0 off
    dist = np.abs(np.arange(rows.shape[1]) - reach)[None, :] + np.where(sat, 0, 10 * reach)
    pick = np.argmin(dist, axis=1)
    has &= dist[np.arange(len(pts)), pick] <= SATURATED_NEAR_PX
    near = run[np.arange(len(pts)), pick]
    mine = (run == near[:, None]) & sat
    first = np.argmax(mine, axis=1)
    last = rows.shape[1] - 1 - np.argmax(mine[:, ::-1], axis=1)
    ok = (has & (last > first) & (first > 0) & (last < rows.shape[1] - 1)
          & (last - first < max_run) & (mine & split).any(axis=1))
    out = pts.copy()
    out[ok, 1] = v0[ok] - reach + 0.5 * (first[ok] + last[ok])
    return out


def _any_white(frame: np.ndarray) -> bool:
    """Whether a BGR uint8 frame has a pixel overexposed into white as
    :func:`~torchseam.vision.tipm.white_core` counts one: R clipped, G or B above half."""
    if not frame.size:
        return False
    b, g, r = cv2.split(frame)
    clip = cv2.compare(r, SATURATED_LEVEL, cv2.CMP_GE)  # type: ignore[call-overload]
    lit = cv2.compare(cv2.max(g, b), SATURATED_LEVEL // 2, cv2.CMP_GT)  # type: ignore[call-overload]
    return cv2.countNonZero(cv2.bitwise_and(clip, lit)) > 0


def _around(frame: np.ndarray, at: np.ndarray, r: int) -> np.ndarray:
    """The square of half side ``r`` of ``frame`` round the point ``at`` (2,) (u, v), cut at
    the frame's edges (a contiguous copy)."""
    h, w = frame.shape[:2]
    u, v = int(round(float(at[0]))), int(round(float(at[1])))
    return np.ascontiguousarray(frame[max(v - r, 0):max(min(v + r + 1, h), 0),
                                      max(u - r, 0):max(min(u + r + 1, w), 0)])


def glare_white(frame: np.ndarray, pts: np.ndarray, width: int) -> np.ndarray:
    """(N,) bool: at which centre points (N, 2) of a BGR uint8 ``frame`` glare clips R round
    the stripe, so that its red excess no longer tells it: the stripe is white there
    (:func:`~torchseam.vision.tipm.white_core`'s test: R clipped, G or B above half) and R
    stays clipped beyond the stripe's own core, more than ``width / 2`` rows from the point
    on one side at least (``width``: the stripe's whole width, as :meth:`ProfileFinder.stripe`
    measures it, side_px at least: a stripe saturated in R and G has its red excess, two
    ridges at its edges, within it, and :func:`saturated_centre` centres between them). A
    stripe white in its own core keeps its excess at its edges; glare that clips R beside it
    leaves the excess a ridge where R drops out of clipping, off the stripe by the clipped
    light's reach, or none."""
    if not len(pts):
        return np.zeros(0, bool)
    h, w = frame.shape[:2]
    u = np.clip(np.rint(pts[:, 0]).astype(int), 0, w - 1)
    v = np.clip(np.rint(pts[:, 1]).astype(int), 0, h - 1)
    px = frame[v, u].astype(int)
    white = (px[:, 2] >= SATURATED_LEVEL) & (px[:, :2].max(axis=1) > SATURATED_LEVEL // 2)
    reach = int(width) // 2 + 1
    rows = v[:, None] + np.arange(-reach, reach + 1)[None, :]                # (N, 2 reach + 1)
    clip = ((rows >= 0) & (rows < h)
            & (frame[np.clip(rows, 0, h - 1), u[:, None], 2] >= SATURATED_LEVEL))
    return white & (clip[:, :reach + 1].all(axis=1) | clip[:, reach:].all(axis=1))


def headroom(plane: np.ndarray, ridge_px: int) -> np.ndarray:
    """(H, W) uint8: the most stripe response (ridge) each pixel of an 8-bit intensity
    ``plane`` (H, W) has room for: full scale less the plane's local vertical mean over
    ``ridge_px`` rows (the ridge's own: the ridge is the plane less that mean, so it cannot
    exceed this). On glare near clipping a lit stripe's ridge is small."""
    return cv2.bitwise_not(cv2.blur(plane, (1, ridge_px)))   # 255 less the mean


def response_at(ridge: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """(N,) the stripe response (H, W) at centre points (N, 2): the brightest of the pixel
    and its neighbours across the stripe (a centre between two rows)."""
    h, w = ridge.shape
    u = np.clip(np.rint(pts[:, 0]).astype(int), 0, w - 1)
    v = np.rint(pts[:, 1]).astype(int)
    return np.max([ridge[np.clip(v + dv, 0, h - 1), u] for dv in (-1, 0, 1)], axis=0).astype(
        float)


def draw_profile(frame: np.ndarray, res: ProfileResult) -> np.ndarray:
    """Frame with the centre line (green), the profile's polyline and points (cyan) and the
    aim point (yellow); a mono frame is drawn on in colour."""
    out = cv2.cvtColor(frame, cv2.COLOR_GRAY2BGR) if frame.ndim == 2 else frame.copy()
    if res.centre is not None and len(res.centre):
        for u, v in res.centre[:: max(1, len(res.centre) // 400)].astype(int):
            cv2.circle(out, (int(u), int(v)), 0, (0, 255, 0), -1)
    if res.ok:
        pts = list(res.points.values())
        poly = np.round(np.array(pts) * 16).astype(np.int32)
        cv2.polylines(out, [poly], False, (255, 255, 0), 1, cv2.LINE_AA, 4)
        for p in pts:
            cv2.circle(out, tuple(int(round(x * 16)) for x in p), 4 * 16, (255, 255, 0), 1,
                       cv2.LINE_AA, 4)
        cv2.drawMarker(out, tuple(int(round(x)) for x in res.aim), (0, 255, 255),
                       cv2.MARKER_CROSS, 18, 1, cv2.LINE_AA)
    label = (f"{res.joint} aim ({res.aim[0]:.1f}, {res.aim[1]:.1f})" if res.ok
             else f"{res.joint}: {res.reason}")
    put_label(out, label, (8, 20), 0.5)
    return out
