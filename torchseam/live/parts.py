"""What the live stack runs with besides the cell, the part and the noise: the planning, loop,
search and EGM settings, the arm model, TIPM and ECAL.

:class:`LiveParts` is handed to :func:`~torchseam.live.demo.run_demo`,
:func:`~torchseam.live.ring.run_ring` and :func:`~torchseam.live.replay.run_replay` (and
through them to every :class:`~torchseam.live.loop.LiveLoop` and
:class:`~torchseam.live.locate.SeamLocator` they build), so that no file is read below the
command line: a caller with other settings replaces a field
(``dataclasses.replace(parts, live=...)``). :func:`load_live_parts` reads the shipped ones.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from torchseam.geometry.ecal import Ecal, load_ecal
from torchseam.live.loop import LiveConfig, load_live_config
from torchseam.live.profile_track import (
    ProfileTrackConfig,
    load_profile_track_config,
    make_joint_tracker,
)
from torchseam.live.search import SearchConfig, load_search_config
from torchseam.plan.path import PlanConfig, load_plan_config
from torchseam.robot.egm import EgmConfig, load_egm_config
from torchseam.robot.kinematics import IRB1410, load_irb1410
from torchseam.track.peers import FrameTracker
from torchseam.vision.exposure import ExposureConfig, load_exposure_config
from torchseam.vision.profiles import ProfileConfig, load_profile_config
from torchseam.vision.tipm import Tipm, load_tipm

__all__ = ["LiveParts", "load_live_parts"]


@dataclass(frozen=True)
class LiveParts:
    """The settings and parts of a live run (each read once, at the command line or by the
    caller).

    Attributes:
        plan: planning settings (``configs/plan.yaml``): the weld plan, the look-ahead buffer.
        live: the loop's settings (``configs/live.yaml``).
        search: the seam search's settings (``configs/search.yaml``; the demo's off-seam start).
        egm: the EGM link's settings (``configs/egm.yaml``; the demo's link and controller).
        robot: the arm model; its config holds the reachability gate's limits
            (``configs/robot.yaml``).
        tipm: the stripe image processing (``configs/tipm.yaml``): start frames, the search's
            corner, the locator's arm directions.
        ecal: the arm finder (``configs/ecal.yaml``).
        profiles: the joint profiles (``configs/profiles.yaml``): a part whose ``joint`` is
            not a fillet is followed by its profile's aim point.
        profile_track: how that is followed (``configs/profile_track.yaml``;
            :class:`~torchseam.live.profile_track.ProfileTracker`).
        exposure: the automatic exposure's settings (``configs/exposure.yaml``; used where a
            cell file turns it on, ``camera.auto_exposure``); None: not read.
    """

    plan: PlanConfig
    live: LiveConfig
    search: SearchConfig
    egm: EgmConfig
    robot: IRB1410
    tipm: Tipm
    ecal: Ecal
    profiles: ProfileConfig
    profile_track: ProfileTrackConfig
    exposure: ExposureConfig | None = None

    def tracker(self, name: str, joint: str, model_path: str | Path | None = None
                ) -> FrameTracker:
        """The live loop's tracker ``name`` for a part's ``joint``
        (:func:`~torchseam.live.profile_track.make_joint_tracker`)."""
        return make_joint_tracker(name, joint, self.tipm, self.profiles, self.profile_track,
                                  model_path)


def load_live_parts() -> LiveParts:
    """The shipped :class:`LiveParts`: ``configs/plan.yaml``, ``live.yaml``, ``search.yaml``,
    ``egm.yaml``, ``robot.yaml``, ``tipm.yaml``, ``ecal.yaml``, ``profiles.yaml``,
    ``profile_track.yaml`` and ``exposure.yaml``, each read by its own loader (a bad file
    raises ``ConfigError`` naming it and the field)."""
    return LiveParts(plan=load_plan_config(), live=load_live_config(),
                     search=load_search_config(), egm=load_egm_config(), robot=load_irb1410(),
                     tipm=load_tipm(), ecal=load_ecal(), profiles=load_profile_config(),
                     profile_track=load_profile_track_config(),
                     exposure=load_exposure_config())
