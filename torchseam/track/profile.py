"""The tracker for joints other than the fillet: the joint profile's aim point.

TIPM's corner and the anchored EAKF-STC tracker (:mod:`torchseam.track.anchored`) follow a
fillet: two arms meeting at a corner. A V-groove's aim point is the root centre, the middle of
a gap in the stripe, where there is no corner and nothing to learn an appearance from.
:class:`ProfileTracker` reads the part's joint profile (:class:`~torchseam.vision.profiles.
ProfileFinder`) in a window round the point it predicts: the expected pixel the locator hands
it from the robot's motion (:meth:`~torchseam.track.base.Tracker.expect`), else its last point
moved as it last moved (held where it was after a frame without evidence). A profile found
there, its aim point within ``gate_px`` of the prediction, is the frame's evidence: status
``tracked``, the point the aim point (the tracker's own prediction, its point held while blind,
goes stale as the joint moves on: ``(1 + n) gate_px`` after n frames without evidence, at most
:data:`MAX_GATE_GROWTH` times; the locator's is made afresh on every frame from the robot's
pose and does not, so its gate does not grow; a butt's gap centre is held tighter round the
locator's prediction, :meth:`ProfileTracker._centre_tol`). Otherwise the
point is the prediction, ``coasting``, and after ``lost_frames`` such frames ``lost``. The
profile itself (feature points and the pieces leaving the root edges) stays on the tracker
(:attr:`ProfileTracker.result`) for the locator, which locates the faces' directions from it.

:func:`make_joint_tracker` gives the tracker for a part's joint: the named tracker
(:func:`~torchseam.track.peers.make_tracker`) for a fillet, as before; this one otherwise.
"""

from __future__ import annotations

import dataclasses
from collections import deque
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from torchseam.core.config import config_field, config_path, load_config
from torchseam.core.dataset import check_frame
from torchseam.core.errors import TorchseamError
from torchseam.core.orient import FrameView
from torchseam.track.base import Tracker, TrackResult
from torchseam.track.fusion import TrackStatus
from torchseam.track.peers import FrameTracker, make_tracker
from torchseam.vision.axis import stripe_axis
from torchseam.vision.profiles import (
    JOINTS,
    LAP_DARK_FACE,
    ProfileConfig,
    ProfileFinder,
    ProfileResult,
    load_profile_config,
)
from torchseam.vision.tipm import Tipm

#: the evidence gate round the tracker's own prediction (its point held while blind) after n
#: frames without evidence: ``gate_px (1 + n)``, at most this many times ``gate_px`` (round the
#: locator's prediction, :meth:`ProfileTracker.expect`, ``gate_px`` on every frame)
MAX_GATE_GROWTH = 4.0
#: a profile found again after the track was lost keeps its width and root gap within this
#: share of the last tracked frame's (:meth:`ProfileTracker._same_shape`)
REFIND_SHARE = 0.5
#: the sides of a groove, in the order of :meth:`ProfileTracker._root_edges`' arrays
SIDES = ("left", "right")

__all__ = ["ProfileTrackConfig", "ProfileTracker", "load_profile_track_config",
           "make_joint_tracker", "profile_start"]


@dataclass(frozen=True)
class ProfileTrackConfig:
    """Settings of :class:`ProfileTracker` (``configs/profile_track.yaml``, px)."""

    window_px: int = config_field(lo=16)
    gate_px: float = config_field(lo=0.0, lo_open=True)
    lost_frames: int = config_field(lo=1)
    smooth: float = config_field(lo=0.0, hi=1.0, hi_open=True)
    edge_history: int = config_field(lo=1)
    edge_min: int = config_field(lo=1)
    edge_tol_px: float = config_field(lo=0.0, lo_open=True)
    edge_max_frames: int = config_field(lo=0)
    line_tol_deg: float = config_field(lo=0.0)
    centre_tol_px: float = config_field(lo=0.0, lo_open=True)
    centre_tol_growth_px: float = config_field(lo=0.0)


def load_profile_track_config(path: str | Path | None = None) -> ProfileTrackConfig:
    """:class:`ProfileTrackConfig` from ``path`` (default ``configs/profile_track.yaml``)."""
    return load_config(ProfileTrackConfig, path or config_path("profile_track.yaml"))


class ProfileTracker(Tracker):
    """A joint profile's aim point, read in a window round the predicted point per frame.

    Args:
        finder: the joint's profile (not ``fillet``: TIPM's trackers follow a fillet).
        cfg: :class:`ProfileTrackConfig`.

    Example:
        >>> from torchseam.vision.profiles import load_profile_config
        >>> from torchseam.vision.tipm import load_tipm
        >>> t = ProfileTracker(ProfileFinder(load_tipm(), load_profile_config(), "v_groove"),
        ...                    load_profile_track_config())
        >>> t.init(np.zeros((64, 64), np.uint8), np.array([30.0, 30.0]))
        >>> TrackStatus(t.track(np.zeros((64, 64), np.uint8)).status).name
        'COASTING'
    """

    name = "profile"

    def __init__(self, finder: ProfileFinder, cfg: ProfileTrackConfig) -> None:
        if finder.joint == "fillet":
            raise ValueError("ProfileTracker follows a joint other than the fillet (TIPM's "
                             "trackers follow fillets)")
        self.finder, self.cfg = finder, cfg
        self.uv = np.full(2, np.nan)
        self.velocity = np.zeros(2)
        self.expected: np.ndarray | None = None
        self.misses = 0
        #: the profile found on the last frame (frame pixels), None when none was taken
        self.result: ProfileResult | None = None
        #: v_groove: each root edge's place along its face's line from where the two lines
        #: meet, (2,) px, on the recent frames with a profile
        self._edges = (deque[float](maxlen=cfg.edge_history),
                       deque[float](maxlen=cfg.edge_history))
        self._stale = [0, 0]  # frames in a row each side's edge was taken from its history
        #: each side's face line's direction (degrees, image) on the recent frames with both
        #: edges in their places
        self._dirs = (deque[float](maxlen=cfg.edge_history),
                      deque[float](maxlen=cfg.edge_history))
        #: butt, lap: the vector from one end to the other (px) on the recent frames that
        #: were evidence with their ends as read (:meth:`_ends`)
        self._pair = deque[np.ndarray](maxlen=cfg.edge_history)
        self._stale_pair = 0
        #: the span of the frame in hand where its ends were taken as read: it joins the
        #: history only if the frame is evidence (:meth:`_learn`)
        self._span: np.ndarray | None = None
        #: butt: how far from the locator's prediction the frame in hand's aim may lie
        #: (:meth:`_centre_tol`; infinite round the tracker's own prediction)
        self._tol = float("inf")
        #: (width, root gap) px of the last frame tracked (the start frame's at first)
        self._shape = (float("nan"), float("nan"))

    def find(self, frame: np.ndarray) -> ProfileResult:
        """The profile on a whole frame (the start: no prediction yet)."""
        return self.finder(frame)

    def init(self, frame: np.ndarray, uv: np.ndarray) -> None:
        self.uv = np.asarray(uv, float).copy()
        self.velocity = np.zeros(2)
        self.expected, self.misses, self.result = None, 0, None
        for hist in (*self._edges, *self._dirs):
            hist.clear()
        self._stale = [0, 0]
        self._pair.clear()
        self._stale_pair = 0
        self._shape = (float("nan"), float("nan"))
        self._tol = float("inf")   # the start frame: no prediction but the start point
        # the profile's shape (and a butt's or a lap's span) from the start frame (clean: the
        # arc is not lit yet), so the first frames under the arc are checked too
        if np.all(np.isfinite(self.uv)):
            res = self._window(check_frame(frame), self.uv)
            if res.ok and float(np.linalg.norm(res.aim - self.uv)) <= self.cfg.gate_px:
                self._shape = (res.width_px, res.gap_px)
                if res.joint != "v_groove":
                    self._ends(res, self.uv)
                    self._learn()

    def expect(self, uv: np.ndarray | None) -> None:
        self.expected = None if uv is None else np.asarray(uv, float).copy()

    def _window(self, frame: np.ndarray, centre: np.ndarray) -> ProfileResult:
        """The profile in the window round ``centre``, in frame pixels."""
        h, w = frame.shape[:2]
        r = self.cfg.window_px
        u0 = int(np.clip(round(float(centre[0])) - r, 0, max(w - 1, 0)))
        v0 = int(np.clip(round(float(centre[1])) - r, 0, max(h - 1, 0)))
        crop = np.ascontiguousarray(frame[v0:v0 + 2 * r + 1, u0:u0 + 2 * r + 1])
        res = self.finder(crop)
        if not res.ok:
            return res
        off = np.array([u0, v0], float)
        return ProfileResult(
            res.joint, True, res.aim + off, {k: p + off for k, p in res.points.items()},
            res.reason, res.width_px, res.gap_px, res.area_px2,
            None if res.centre is None else res.centre + off, None,
            None if res.arm_points is None else res.arm_points + off)

    def track(self, frame: np.ndarray) -> TrackResult:
        frame = check_frame(frame)
        pred = self.expected if self.expected is not None else self.uv + self.velocity
        handed = self.expected is not None
        self.expected = None
        self.result = None
        self._span = None
        if not np.all(np.isfinite(pred)):
            return TrackResult(np.full(2, np.nan), int(TrackStatus.LOST))
        res = self._window(frame, pred)
        # the tracker's own prediction (its point, held while blind) grows less certain with
        # each frame without evidence; the locator's (the seam seen so far, cut with the laser
        # plane at the camera's pose now) is made afresh from the robot's motion on every
        # frame: the joint does not move away from it while the tracker is blind, and a
        # reading farther off than gate_px is as far off the joint (grown, it took other
        # breaks whose span agreed by chance, 12-17 px off: the bench's butt `wide` extreme)
        grow = 1.0 if handed else min(1.0 + self.misses, MAX_GATE_GROWTH)
        gate = self.cfg.gate_px * grow
        self._tol = self._centre_tol() if handed else float("inf")
        if res.ok:
            res = self._root_edges(res) if res.joint == "v_groove" else self._ends(res, pred)
        if res.ok and res.joint == "v_groove" and self.misses > self.cfg.lost_frames:
            res = self._same_shape(res)
        if res.ok and float(np.linalg.norm(res.aim - pred)) <= gate:
            uv = self.cfg.smooth * pred + (1.0 - self.cfg.smooth) * res.aim
            self.velocity = uv - self.uv if np.all(np.isfinite(self.uv)) else np.zeros(2)
            self.uv, self.misses, self.result = uv, 0, res
            self._shape = (res.width_px, res.gap_px)
            self._learn()
            return TrackResult(uv.copy(), int(TrackStatus.TRACKED))
        self.misses += 1
        self.uv, self.velocity = pred, np.zeros(2)  # held, not extrapolated, while blind
        status = TrackStatus.LOST if self.misses > self.cfg.lost_frames else TrackStatus.COASTING
        return TrackResult(pred.copy(), int(status))

    def _centre_tol(self) -> float:
        """How far from the locator's prediction a butt's aim may lie to be evidence:
        ``centre_tol_px`` after a frame with evidence, ``centre_tol_growth_px`` more for each
        frame without since (the prediction is drawn from the seam seen, which ages while the
        tracker is blind: on the butt's closed loop its error against the truth, p90, grew
        0.66, 0.85, 0.95, 1.04, 1.38 px after 0-4 frames without evidence).

        The arc's glare stands on the seam and moves a butt's two gap edges alike as often as
        it eats one: a span "in its place" whose two ends moved the same way moves the gap's
        centre with them, and the span check cannot see it (the bench's butt rows at extreme:
        both edges 3-6 px to one side, tracked 3.1-5.7 px off within the 6 px gate); a way
        read off a span off its history (:meth:`_ends`) is off by its kept edge's own loss.
        The prediction is the one thing such a reading is checked against: the gap moves by a
        fraction of a pixel a frame between the prediction and the frame (the locator's
        prediction on the closed loop, p99 1.5 px after a frame with evidence). Held to
        ``gate_px`` at every age (the gate's own bound), and not used round the tracker's own
        prediction (its point held while blind: the gate grows round it instead)."""
        return min(self.cfg.centre_tol_px + self.cfg.centre_tol_growth_px * self.misses,
                   self.cfg.gate_px)

    def _same_shape(self, res: ProfileResult) -> ProfileResult:
        """After the track was lost (its gate grown :data:`MAX_GATE_GROWTH` times), a groove
        found again is taken only with the shape it last had: its width and its root gap each
        within :data:`REFIND_SHARE` of the last tracked frame's (the joint's cross-section
        changes slowly along the seam; a structure the arc's glare and spatter make near the
        prediction does not keep it), or no evidence. (A butt's and a lap's span is checked on
        every frame, :meth:`_ends`; the glare eats a butt's two edges alike, and its centre
        holds while its width does not.)"""
        for name, now, then in (("width", res.width_px, self._shape[0]),
                                ("root gap", res.gap_px, self._shape[1])):
            if np.isfinite(now) and np.isfinite(then) and abs(now - then) > REFIND_SHARE * then:
                return dataclasses.replace(
                    res, ok=False, aim=np.full(2, np.nan),
                    reason=f"found again with its {name} {now:.1f} px (last tracked "
                           f"{then:.1f})")
        return res

    def _root_edges(self, res: ProfileResult) -> ProfileResult:
        """A v_groove's root edges checked against the recent frames'. The stripe's end at a
        root edge is the profile's weakest reading: the arc's glare and its reflection up the
        groove wash out (or saturate) the stripe's last pixels there, a spatter streak carries
        it on into the gap; the faces' lines, fitted to tens of points, are its strongest.
        Each edge's place along its face's line, measured from where the two lines meet, is
        stable from frame to frame (the groove's shape changes slowly round the saddle).

        Per side, with ``edge_min`` of its places known (the last ``edge_history`` that
        agreed), an edge more than ``edge_tol_px`` off their median is taken at the median, on
        its line as this frame shows it; only places that agree join the history (an edge
        washed out for a second does not become the groove's shape). A side taken from its
        history on more than ``edge_max_frames`` frames in a row is no longer known: its
        history starts again from what the frames show (the gate on the prediction still
        holds). No evidence (``ok`` False): a frame with both edges off (a glare band over the
        root: the lines are no better there; a spatter streak bridging the gap), with an edge
        off and a face's line turned by more than ``line_tol_deg`` from its direction on the
        recent frames with both edges in place (the glare that took the edge bent the line
        the edge is put back on, and the face's direction the torch bisects), or with the
        edge of a side no longer known."""
        if res.joint != "v_groove" or res.arm_points is None:
            return res
        roots = np.stack([res.points["left_root"], res.points["right_root"]])
        d = res.arm_points - roots
        n = np.linalg.norm(d, axis=1)
        if np.any(n < 1e-9):
            return res
        d /= n[:, None]
        m = np.stack([d[0], -d[1]], axis=1)
        if abs(float(np.linalg.det(m))) < 1e-6:  # parallel faces: no place to measure from
            return res
        x = roots[0] + float(np.linalg.solve(m, roots[1] - roots[0])[0]) * d[0]
        place = np.einsum("ij,ij->i", roots - x, d)                            # (2,)
        off = np.zeros(2, bool)
        ref = place.copy()
        for i, hist in enumerate(self._edges):
            if len(hist) >= self.cfg.edge_min:
                ref[i] = float(np.median(hist))
                off[i] = abs(place[i] - ref[i]) > self.cfg.edge_tol_px
            if off[i]:
                self._stale[i] += 1
                if self._stale[i] > self.cfg.edge_max_frames:  # no longer known: start again
                    hist.clear()
                    self._stale[i] = 0
                    return dataclasses.replace(
                        res, ok=False, aim=np.full(2, np.nan),
                        reason=f"the {SIDES[i]} root edge off its recent place for "
                               f"{self.cfg.edge_max_frames} frames")
            else:
                hist.append(place[i])
                self._stale[i] = 0
        ang = np.degrees(np.arctan2(d[:, 1], d[:, 0]))
        turn = np.zeros(2)
        for i, hist in enumerate(self._dirs):
            if len(hist) >= self.cfg.edge_min:
                turn[i] = abs((ang[i] - float(np.median(hist)) + 180.0) % 360.0 - 180.0)
            if not off.any():
                hist.append(float(ang[i]))
        if not off.any():
            return res
        if off.all():  # a glare band over the root, a spatter streak across the gap
            return dataclasses.replace(
                res, ok=False, aim=np.full(2, np.nan),
                reason=f"both root edges off their recent places (by "
                       f"{np.abs(place - ref).max():.1f} px)")
        if turn.max() > self.cfg.line_tol_deg:  # the glare that took an edge bent a line
            return dataclasses.replace(
                res, ok=False, aim=np.full(2, np.nan),
                reason=f"a root edge off its recent place and a face's line turned by "
                       f"{turn.max():.1f} deg")
        new = roots.copy()
        new[off] = x + ref[off, None] * d[off]
        pts = dict(res.points, left_root=new[0], right_root=new[1])
        which = SIDES[int(np.flatnonzero(off)[0])]
        return dataclasses.replace(
            res, aim=new.mean(axis=0), points=pts,
            reason=(res.reason + "; " if res.reason else "") + f"{which} root edge at its "
            "recent place",
            gap_px=float(np.linalg.norm(new[1] - new[0])))

    def _ends(self, res: ProfileResult, pred: np.ndarray) -> ProfileResult:
        """A butt's two gap edges, a lap's root and edge, checked against the recent frames'.
        The vector from one end to the other (the gap across, the step) changes slowly along
        the seam; an end is where the stripe stops, the profile's weakest reading: the arc's
        glare eats the stripe's end (the gap reads wider), a spatter streak carries it on.

        The history: the start frame's vector (:meth:`init`) and those of the recent frames
        that were evidence with their ends as read (the last ``edge_history``): agreeing with
        the history's median, or both off alike (below). A frame whose vector is more than
        ``edge_tol_px`` off that median is read three ways: its first end as read and the
        second put back at the median from it, the second as read and the first put back, or
        (ends in their order) both off alike, the aim as read: the arc's glare stands on the
        seam, where the torch is, and eats the two edges alike as often as one (an end "in
        its place" beside one eaten as far carried half the excess into the seam); and the
        gap under the arc need not read as it did on the clean start frame (a wide stripe's
        bleed narrows it there). A lap is read the first two ways only: its aim is one of its
        ends (the root, the corner the torch stands on), and the glare round it eats the root
        and the edge, the face's length away, unlike each other: the root moved by half the
        span's excess is no reading of it (a dark face read with its root 15.6 px and its edge
        9.1 px short was taken so, 3.17 px off). The way whose aim lies nearest the prediction
        is taken, within ``edge_tol_px`` of it (a butt's: within :meth:`_centre_tol` too, as
        a butt's span in place or started again is); none there: no evidence (``ok`` False).
        A frame the gate refuses (some other structure, whose span may agree by chance)
        neither joins the history nor counts as a span in place (:meth:`_learn`). A vector off
        its history on more than ``edge_max_frames`` frames in a row is no longer known (its
        history starts again from what the frames show; the gate on the prediction still
        holds; a butt's from a gap within :data:`REFIND_SHARE` of the width last tracked,
        else no evidence).

        A lap whose edge face is lit (not noted :data:`~torchseam.vision.profiles.LAP_DARK_FACE`)
        has no end to keep: both are where the face's line meets the plates', and a span off
        is that line off; no evidence. (The arc's glare bends the face's centre line, which
        moves both ends the same way frame after frame: an end put back from the other
        carried that into the seam, and a run of them turned the look-ahead's tangent, and
        the torch axis with it.)"""
        names = ("left_edge", "right_edge") if res.joint == "butt" else ("root", "edge")
        if not all(n in res.points for n in names):
            return res
        a, b = res.points[names[0]], res.points[names[1]]
        d = b - a
        hist = self._pair
        if not hist:   # the first span (the start frame's, or after the history ran stale)
            then = self._shape[0] if res.joint == "butt" else float("nan")
            now = float(np.linalg.norm(d))
            if np.isfinite(then) and abs(now - then) > REFIND_SHARE * then:
                # a history started again is started from a gap as wide as the one last
                # tracked (as a groove found again keeps its shape, _same_shape): a break the
                # glare blew to 90 px is not the 22 px gap
                return dataclasses.replace(
                    res, ok=False, aim=np.full(2, np.nan),
                    reason=f"the butt's span started again at {now:.1f} px (last tracked "
                           f"{then:.1f})")
            if res.joint == "butt" and self._centre_off(res, pred):
                return self._far_centre(res, pred, "a span started again")
            self._span = d
            return res
        ref = np.median(np.array(hist), axis=0)
        if float(np.linalg.norm(d - ref)) <= self.cfg.edge_tol_px:
            if res.joint == "butt" and self._centre_off(res, pred):
                # both ends moved the same way (the glare beside the gap): the span agrees,
                # the centre moved with them
                return self._far_centre(res, pred, "its span in place")
            self._span = d   # joins the history if the frame is evidence (_learn)
            return res
        self._stale_pair += 1
        if self._stale_pair > self.cfg.edge_max_frames:
            hist.clear()
            self._stale_pair = 0
            return dataclasses.replace(
                res, ok=False, aim=np.full(2, np.nan),
                reason=f"the {res.joint}'s ends off their recent span for "
                       f"{self.cfg.edge_max_frames} frames")
        if res.joint == "lap" and res.reason != LAP_DARK_FACE:
            # a lit edge face: root and edge are where the face's one line meets the plates'
            # lines, not two readings; a span off is that line off (the arc's glare bends the
            # face's centre line), which moves both ends, each along its plate: an end "in its
            # place" is off too, and the other put back from it carried that into the seam
            return dataclasses.replace(
                res, ok=False, aim=np.full(2, np.nan),
                reason=f"the lap's edge face off its recent span (span {np.linalg.norm(d):.1f} "
                       f"px, recently {np.linalg.norm(ref):.1f}): both ends are on its line")
        share = 0.5 if res.joint == "butt" else 0.0   # the aim's place between the ends
        # where the ends truly are, read three ways: end a as read and b off (eaten by glare,
        # carried on by spatter), b as read and a off, or, where the ends are in their order,
        # both off alike (the arc's glare stands on the seam, where the torch is, and eats the
        # two edges alike as often as one: an end "in its place" beside an end eaten as far
        # carried half the excess into the seam; and the span read under the arc need not be
        # the one read before it, which a wide stripe's bleed narrows): the span's centre as
        # read, the span kept. Not a lap's: its aim is an end, and the glare round the root
        # eats its two ends unlike each other (the edge lies the face's length away)
        norm = max(float(np.linalg.norm(ref)), 1e-9)
        ways = [(a, a + ref, names[1]), (b - ref, b, names[0])]
        if res.joint == "butt" and float(d @ ref) > 0.0:
            ways.append((a + 0.5 * (d - ref), b - 0.5 * (d - ref), "both ends"))
        off = [float(np.linalg.norm(w[0] + share * ref - pred)) for w in ways]
        k = int(np.argmin(off))
        tol = min(self.cfg.edge_tol_px, self._tol) if res.joint == "butt" else self.cfg.edge_tol_px
        if off[k] > tol:
            return dataclasses.replace(
                res, ok=False, aim=np.full(2, np.nan),
                reason=f"both ends off their expected places (span {np.linalg.norm(d):.1f} px, "
                       f"recently {norm:.1f})")
        a_new, b_new, moved = ways[k]
        if k == 2:   # the span as read, both ends off alike: it joins the history (_learn)
            self._span = d
        aim = a_new + share * ref
        arms = res.arm_points
        if arms is not None and res.joint == "butt":   # each plate's piece moves with its end
            arms = arms + np.stack([a_new - a, b_new - b])
        elif arms is not None:   # a lap: the plate's with the root, the face root to edge
            face = b_new - a_new
            reach = float(np.linalg.norm(arms[1] - a))
            arms = np.stack([arms[0] + a_new - a,
                             a_new + reach * face / max(float(np.linalg.norm(face)), 1e-9)])
        note = (f"{moved} at its recent span" if k < 2
                else "both ends off alike: the span's centre as read")
        return dataclasses.replace(
            res, aim=aim, points=dict(res.points, **{names[0]: a_new, names[1]: b_new}),
            arm_points=arms, reason=(res.reason + "; " if res.reason else "") + note,
            width_px=norm if res.joint == "butt" else res.width_px)

    def _centre_off(self, res: ProfileResult, pred: np.ndarray) -> bool:
        """A butt's gap centre as read farther from the prediction than :meth:`_centre_tol`."""
        return float(np.linalg.norm(res.aim - pred)) > self._tol

    def _far_centre(self, res: ProfileResult, pred: np.ndarray, how: str) -> ProfileResult:
        """No evidence: the gap's centre read too far from the prediction."""
        return dataclasses.replace(
            res, ok=False, aim=np.full(2, np.nan),
            reason=f"the gap's centre {np.linalg.norm(res.aim - pred):.1f} px from the "
                   f"prediction with {how} (at most {self._tol:.2f})")

    def _learn(self) -> None:
        """The span of the frame in hand (:meth:`_ends`) joins the history: the frame is
        evidence. (A frame whose aim the gate refuses is some other structure, whose span
        may agree by chance: it neither joins the history nor counts as a span in place.)"""
        if self._span is not None:
            self._pair.append(self._span)
            self._stale_pair = 0
            self._span = None

    def update(self, frame: np.ndarray) -> tuple[np.ndarray, int]:
        r = self.track(frame)
        return r.uv, r.status


def make_joint_tracker(name: str, joint: str, tipm: Tipm, profiles: ProfileConfig,
                       track: ProfileTrackConfig, model_path: str | Path | None = None
                       ) -> FrameTracker:
    """The live loop's tracker for a part's ``joint``: the tracker ``name``
    (:func:`~torchseam.track.peers.make_tracker`, ``model_path`` its model) for a fillet; a
    :class:`ProfileTracker` of that profile otherwise, which only ``anchored`` (the default)
    names: another tracker asked for a joint it cannot follow is an error."""
    if joint not in JOINTS:
        raise TorchseamError(f"joint {joint!r}: use one of {', '.join(JOINTS)}")
    if joint == "fillet":
        return make_tracker(name, tipm, model_path=model_path)
    if name != "anchored" or model_path is not None:
        raise TorchseamError(f"tracker {name}{' --model' if model_path else ''}: a {joint} joint "
                             "is followed by its profile's aim point (the default tracker, "
                             "anchored, without a model)")
    return ProfileTracker(ProfileFinder(tipm, profiles, joint), track)


def profile_start(img: np.ndarray, tipm: Tipm, joint: str, uv0: np.ndarray | None, axis: str,
                  response: str, name: str, number: int) -> tuple[FrameView, np.ndarray, str]:
    """How to view a stream of a ``joint`` other than the fillet and where to start, from its
    first readable frame ``img`` (``torchseam track`` and ``eval``, as the live locator
    starts): the stripe's own axis with ``auto`` (:func:`~torchseam.vision.axis.stripe_axis`:
    a groove need not show TIPM a corner), the red response unless ``response`` names one,
    and the profile's aim point there unless ``uv0`` (camera pixels) is given. Returns
    ``(view, start pixel (camera), note)``; :class:`TorchseamError` naming ``name`` where the
    frame shows no stripe or not the profile."""
    response = "red" if response == "auto" else response
    if axis == "auto":
        found = stripe_axis(img, tipm, response)
        if found is None:
            raise TorchseamError(f"{name}: no stripe on the first frame to find its axis; give "
                                 "--stripe-axis")
        axis = found
    view = FrameView(axis, img.shape[0], response)
    if uv0 is not None:
        return view, np.asarray(uv0, float), "given"
    res = ProfileFinder(tipm, load_profile_config(), joint)(view.frame(img))
    if not res.ok:
        raise TorchseamError(f"{name}: the {joint} profile cannot start the tracker on the "
                             f"first frame ({res.reason}); give the start point with --init U,V")
    return view, view.to_camera(res.aim), f"{joint} profile on frame {number}"
