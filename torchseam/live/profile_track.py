"""The live loop's tracker for joints other than the fillet: :mod:`torchseam.track.profile`
(there, below the live loop, so ``torchseam track`` and ``eval`` follow a profile too); kept
here under its first name."""

from torchseam.track.profile import (
    MAX_GATE_GROWTH,
    SIDES,
    ProfileTrackConfig,
    ProfileTracker,
    load_profile_track_config,
    make_joint_tracker,
)

__all__ = ["MAX_GATE_GROWTH", "SIDES", "ProfileTrackConfig", "ProfileTracker",
           "load_profile_track_config", "make_joint_tracker"]
