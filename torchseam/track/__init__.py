"""Batched, differentiable trackers: STC, the coloured-noise EAKF and their fusion EAKF-STC.

METHOD.md sections 2-4. Images are (B, H, W) grey, pixel coordinates (u, v) = (column, row).
:class:`LiteEAKFSTC` runs a fitted EAKF-STC module's equations in numpy for one live stream.
"""

from torchseam.core.checks import InputError as TrackInputError  # the tracker's name for it
from torchseam.track.config import TrackerConfig
from torchseam.track.eakf import EAKF, EAKFState, eakf_filter
from torchseam.track.fusion import EAKFSTC, DriftGuard, TrackResult, TrackStatus
from torchseam.track.lite import LiteEAKFSTC
from torchseam.track.stc import STC, STCState, extract_windows, locate_peak, peak_quality

__all__ = ["EAKF", "EAKFSTC", "STC", "DriftGuard", "EAKFState", "LiteEAKFSTC", "STCState",
           "TrackInputError",
           "TrackResult", "TrackStatus", "TrackerConfig", "eakf_filter", "extract_windows",
           "locate_peak", "peak_quality"]
