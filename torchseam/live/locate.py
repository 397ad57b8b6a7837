"""Per-frame seam location: feature point -> 3D weld point -> ECAL arm points (robot base).

:class:`SeamLocator` is the seeing half of the live loop; the planning half is
:class:`~torchseam.plan.path.LookAheadBuffer`. It is used by the open-loop ring run
(:mod:`torchseam.live.ring`) and the closed-loop demo.
"""

from __future__ import annotations

import time
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from torchseam.core.config import CellConfig
from torchseam.core.errors import TorchseamError
from torchseam.core.orient import FrameView
from torchseam.geometry.ecal import Ecal, EcalResult
from torchseam.geometry.triangulate import FastTriangulator
from torchseam.live.profile_track import ProfileTracker
from torchseam.track.fusion import TrackStatus
from torchseam.track.peers import FrameTracker
from torchseam.vision.axis import stripe_axis
from torchseam.vision.tipm import Tipm, find_view

EXPECT_POINTS = 40     # recent located points kept for the expected pixel (~1.5 s at 25 Hz)
EXPECT_SPAN_MM = 4.0   # the seam's local direction from two of them at least this far apart
                       # (over 1 mm the chord carried the newest point's error into the next
                       # expected pixel x1.15-1.35 per frame: biased runs of fixes fed
                       # themselves on heavy-arc rings)


@dataclass
class Location:
    """What one frame says about the seam (robot base, mm)."""

    uv: np.ndarray            # (2,) feature pixel from the tracker
    status: int               # TrackStatus
    p: np.ndarray             # (3,) weld point, NaN when the status is LOST
    q: np.ndarray             # (2, 3) arm points, NaN when ECAL found none
    arms_ok: bool
    arms_fallback: bool
    timings_ms: dict[str, float] = field(default_factory=dict)


class SeamLocator:
    """Tracker + triangulation + ECAL for one camera stream.

    Frames may be colour or mono (8 bit; see :func:`~torchseam.core.dataset.check_frame`),
    with the stripe along the rows or the columns (``cell.camera.stripe_axis``) and, in
    colour, read by its red excess or its brightness (``stripe_response``); ``auto``: found
    on the start frame. The tracker and ECAL see the frame in that view
    (:class:`~torchseam.core.orient.FrameView`); pixels go back to the camera's own before
    triangulation, and :class:`Location` holds camera pixels.

    Args:
        cell: calibration (camera, laser plane, hand-eye).
        tracker: any :class:`~torchseam.track.peers.FrameTracker` (EAKF-STC in the live loop);
            a :class:`~torchseam.live.profile_track.ProfileTracker` (a joint other than the
            fillet) is started on its profile's aim point, and its profile's faces at the root
            are the arms (no ECAL: the aim point lies in the root gap, on no face).
        tipm: TIPM: the start frame's pixel, the stripe's view with ``auto``, and the stripe
            mask around the feature point that ECAL searches.
        ecal: ECAL, the arm points (its ``r_max_px`` sizes the region around the feature
            point; ``tipm_agreement_deg`` says when TIPM's arm directions are used).
    """

    def __init__(self, cell: CellConfig, tracker: FrameTracker, tipm: Tipm, ecal: Ecal
                 ) -> None:
        self.cell = cell
        self.tracker = tracker
        cam = cell.camera
        self._view_setting = (cam.stripe_axis, cam.stripe_response)
        self.axis: FrameView | None = (
            None if "auto" in self._view_setting
            else FrameView(cam.stripe_axis, cam.height, cam.stripe_response))
        self.tipm = tipm
        self.ecal = ecal
        self._agree_cos = float(np.cos(np.radians(self.ecal.cfg.tipm_agreement_deg)))
        self.tri = FastTriangulator(cell)
        self.prev_angles: np.ndarray | None = None
        self._roi = int(self.ecal.cfg.r_max_px) + 8
        self._seen: deque[np.ndarray] = deque(maxlen=EXPECT_POINTS)  # recent located points

    def start(self, frame: np.ndarray, uv0: np.ndarray | None = None) -> np.ndarray:
        """Initialise on a clean frame (TIPM when ``uv0``, camera pixels, is None). Returns the
        start pixel (camera pixels). With ``stripe_axis: auto`` the frame also tells which
        way the stripe runs."""
        if self.axis is None and isinstance(self.tracker, ProfileTracker):
            self.axis = self._profile_view(frame)
        if self.axis is None:
            self.axis = find_view(frame, self.tipm, *self._view_setting)
            if self.axis is None:
                raise TorchseamError("cannot start tracking: no stripe corner in the start "
                                     "frame (camera.stripe_axis "
                                     f"{self._view_setting[0]}, stripe_response "
                                     f"{self._view_setting[1]}; a joint that is not a "
                                     "fillet: give its profile, --joint)")
        view = self.axis.frame(frame)
        if uv0 is None and isinstance(self.tracker, ProfileTracker):
            prof = self.tracker.find(view)
            if not prof.ok:
                raise TorchseamError(f"cannot start tracking: {prof.joint}: {prof.reason}")
            uv0 = self.axis.to_camera(prof.aim)
        if uv0 is None:
            res = self.tipm(view)
            if not res.ok:
                raise TorchseamError(f"cannot start tracking: {res.reason}")
            uv0 = self.axis.to_camera(res.uv)
        self.tracker.init(view, self.axis.to_canonical(np.asarray(uv0, float)))
        self.prev_angles = None
        self._seen.clear()
        return np.asarray(uv0, float)

    def _profile_view(self, frame: np.ndarray) -> FrameView | None:
        """The view of a joint other than the fillet: the stripe's own axis (a groove need
        not show TIPM a corner), red response unless the cell file says otherwise."""
        axis, response = self._view_setting
        response = "red" if response == "auto" else response
        if axis == "auto":
            found = stripe_axis(frame, self.tipm, response)
            if found is None:
                return None
            axis = found
        return FrameView(axis, frame.shape[0], response)

    def _profile_location(self, axis: FrameView, uv: np.ndarray, status: int,
                          T_B_F: np.ndarray, times: dict[str, float]) -> Location:
        """A profile joint's location: the aim point triangulated, and where the tracker took
        a profile on the frame, the two faces at the root (each root edge and a point up its
        piece, triangulated: their 3D direction, placed at the aim point, is the arm the
        torch frame bisects; the aim point itself lies on no face)."""
        assert isinstance(self.tracker, ProfileTracker)
        t1 = time.perf_counter()
        prof = self.tracker.result
        pix = [uv]
        roots = None if prof is None else prof.arm_roots
        if status == TrackStatus.TRACKED and prof is not None and roots is not None:
            assert prof.arm_points is not None   # (arm_roots is None without them)
            pix += [roots[0], prof.arm_points[0], roots[1], prof.arm_points[1]]
        X = self.tri(axis.to_camera(np.stack(pix)), T_B_F)
        if status == TrackStatus.TRACKED and np.all(np.isfinite(X[0])):
            self._seen.append(X[0])
        q, arms_ok = np.full((2, 3), np.nan), False
        if len(X) == 5 and np.all(np.isfinite(X)):
            q, arms_ok = np.stack([X[0] + X[2] - X[1], X[0] + X[4] - X[3]]), True
        times["triangulate"] = (time.perf_counter() - t1) * 1e3
        return Location(axis.to_camera(uv), status, X[0], q, arms_ok, False, times)

    def _expect(self, T_B_F: np.ndarray) -> np.ndarray | None:
        """The feature pixel this frame should show, from the seam seen so far and the camera's
        pose now (:meth:`FastTriangulator.expect`), or None (too little seam seen)."""
        if len(self._seen) < 2:
            return None
        p_b = self._seen[-1]
        # the newest point at least EXPECT_SPAN_MM from p_b: the distances to all of them at
        # once, then the exact test (a norm each, as it always was) on those that may pass,
        # newest first (one or two; a norm per point back cost ~0.04 ms a frame at 25 Hz)
        seen = np.array(self._seen)
        d = seen - p_b
        # (a squared distance to a few ulps: the margin of 1e-9 keeps every point whose norm
        # may reach EXPECT_SPAN_MM for the exact test)
        near = np.sqrt((d * d).sum(axis=1)) < EXPECT_SPAN_MM * (1.0 - 1e-9)
        for i in np.flatnonzero(~near)[::-1]:
            p_a = self._seen[int(i)]
            if np.linalg.norm(p_b - p_a) >= EXPECT_SPAN_MM:
                return self.tri.expect(p_a, p_b, T_B_F)
        return None

    def _stripe(self, frame: np.ndarray, uv: np.ndarray,
                lent: tuple[np.ndarray, np.ndarray, tuple[int, int]] | None
                ) -> tuple[np.ndarray, np.ndarray, tuple[int, int]]:
        """Stripe response (TIPM's ridge), mask and ROI corner around ``uv`` for ECAL. What
        the tracker made for this frame (:attr:`TrackResult.stripe`: its TIPM window) is
        ``lent`` and used when its window holds ECAL's whole ROI; else they are made here
        (computing them twice cost ~0.4 ms a frame)."""
        if lent is not None:
            red, mask, (x0, y0) = lent
            h, w = frame.shape[:2]
            r = self._roi
            u0, v0 = max(0, int(uv[0]) - r), max(0, int(uv[1]) - r)
            u1, v1 = min(w, int(uv[0]) + r + 1), min(h, int(uv[1]) + r + 1)
            if x0 <= u0 and y0 <= v0 and u1 <= x0 + mask.shape[1] and v1 <= y0 + mask.shape[0]:
                win = (slice(v0 - y0, v1 - y0), slice(u0 - x0, u1 - x0))
                return red[win], mask[win], (u0, v0)
        return self.tipm.mask_around(frame, uv, self._roi)

    def _tangent_points(self, arms: EcalResult, local: np.ndarray, lent: np.ndarray | None
                        ) -> np.ndarray:
        """(2, 2) points on the left and right arm's tangent at the corner (window pixels).

        ECAL finds and checks the arms (both seen, spurious crossings rejected). A tracker that
        fitted the arms on this frame (the anchored tracker's clean TIPM fix:
        :attr:`TrackResult.arm_dirs`, (2, 2) unit image directions or None) lends their
        directions, which are 2-3x tighter
        than ECAL's circle crossings and not biased by a feature point off an arm (per frame
        against the true surfaces on heavy-arc rings: main-pipe arm std 0.3-0.5 against
        0.8-1.2 degrees): they are taken when both agree with ECAL's arms within
        ``tipm_agreement_deg`` (never for ECAL's occluded-arm fallback), placed ``r_max_px``
        out so that they vote as full-length arms in the look-ahead buffer."""
        if lent is None or arms.fallback:
            return self._ecal_tangents(arms, local)
        ecal = np.stack([np.cos(arms.angles), np.sin(arms.angles)], axis=1)
        if np.min(np.sum(ecal * lent, axis=1)) < self._agree_cos:
            return self._ecal_tangents(arms, local)
        return local + self.ecal.cfg.r_max_px * lent

    def _ecal_tangents(self, arms: EcalResult, local: np.ndarray) -> np.ndarray:
        """ECAL's own tangent points (made only now: most frames take the tracker's)."""
        p_tangent = self.ecal.tangents(arms, local)
        assert p_tangent is not None  # called for a found pair of arms (arms.ok)
        return p_tangent

    def step(self, frame: np.ndarray, T_B_F: np.ndarray) -> Location:
        """Locate the seam in ``frame`` taken with the flange at ``T_B_F`` (4, 4) mm."""
        t0 = time.perf_counter()
        if self.axis is None and isinstance(self.tracker, ProfileTracker):
            self.axis = self._profile_view(frame)
        if self.axis is None:  # a tracker started by the caller, not by start(): find it here
            self.axis = find_view(frame, self.tipm, *self._view_setting) or FrameView(
                "rows", frame.shape[0])
        axis = self.axis
        frame = axis.frame(frame)  # the stripe along the rows (the same array if it is)
        seen = self._expect(T_B_F)  # where the robot's motion puts the point
        self.tracker.expect(None if seen is None else axis.to_canonical(seen))
        res = self.tracker.track(frame)
        uv, status = res.uv, res.status
        t1 = time.perf_counter()
        nan3, q = np.full(3, np.nan), np.full((2, 3), np.nan)
        arms_ok = fallback = False
        if status == TrackStatus.LOST or not np.isfinite(uv).all():
            return Location(axis.to_camera(uv), status, nan3, q, False, False,
                            {"track": (t1 - t0) * 1e3})
        if isinstance(self.tracker, ProfileTracker):
            return self._profile_location(axis, uv, status, T_B_F, {"track": (t1 - t0) * 1e3})
        red, mask, (x0, y0) = self._stripe(frame, uv, res.stripe)
        local = uv - (x0, y0)
        arms = self.ecal(mask, local, red, self.prev_angles, tangents=False)
        t2 = time.perf_counter()
        pix = [uv]
        if arms.ok:
            arms_ok, fallback = True, arms.fallback
            self.prev_angles = arms.angles
            pix += list(self._tangent_points(arms, local, res.arm_dirs) + (x0, y0))
        X = self.tri(axis.to_camera(np.stack(pix)), T_B_F)
        # the points the expected pixel is drawn from: those resting on a TIPM corner taken
        # this frame (seen, or extrapolated over a short gap: accurate either way) or a firm
        # shallow one (Fix.firm; docs/benchmarks.md), not predictions
        if np.isfinite(X[0]).all() and (status == TrackStatus.TRACKED or (
                res.fix is not None and res.fix.taken and res.fix.firm)):
            self._seen.append(X[0])
        if arms_ok:
            q = X[1:3]
        t3 = time.perf_counter()
        return Location(axis.to_camera(uv), status, X[0], q, arms_ok, fallback,
                        {"track": (t1 - t0) * 1e3, "ecal": (t2 - t1) * 1e3,
                         "triangulate": (t3 - t2) * 1e3})
