"""Batched, differentiable trackers: STC, the coloured-noise EAKF and their fusion EAKF-STC.

METHOD.md sections 2-4. Images are (B, H, W) grey, pixel coordinates (u, v) = (column, row).
:class:`LiteEAKFSTC` runs a fitted EAKF-STC module's equations in numpy for one live stream.

The names below are imported on first use (``from torchseam.track import EAKFSTC``), so that
importing a light module of the package (:mod:`torchseam.track.names`, the command line's
parser) does not import torch.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from torchseam.core.lazy import lazy_exports

if TYPE_CHECKING:
    from torchseam.core.checks import InputError as TrackInputError  # the tracker's name for it
    from torchseam.track.base import TrackResult
    from torchseam.track.config import TrackerConfig
    from torchseam.track.eakf import EAKF, EAKFState, eakf_filter
    from torchseam.track.fusion import EAKFSTC, DriftGuard, LiteEAKFSTC, SequenceResult, TrackStatus
    from torchseam.track.stc import STC, STCState, extract_windows, locate_peak, peak_quality

#: each exported name: (module, name there)
_LAZY = {
    "TrackInputError": ("torchseam.core.checks", "InputError"),
    "TrackerConfig": ("torchseam.track.config", "TrackerConfig"),
    **{n: ("torchseam.track.eakf", n) for n in ("EAKF", "EAKFState", "eakf_filter")},
    **{n: ("torchseam.track.fusion", n)
       for n in ("EAKFSTC", "DriftGuard", "SequenceResult", "TrackStatus")},
    "TrackResult": ("torchseam.track.base", "TrackResult"),
    "LiteEAKFSTC": ("torchseam.track.fusion", "LiteEAKFSTC"),
    **{n: ("torchseam.track.stc", n)
       for n in ("STC", "STCState", "extract_windows", "locate_peak", "peak_quality")},
}

__all__ = ["EAKF", "EAKFSTC", "STC", "DriftGuard", "EAKFState", "LiteEAKFSTC", "STCState",
           "SequenceResult", "TrackInputError",
           "TrackResult", "TrackStatus", "TrackerConfig", "eakf_filter", "extract_windows",
           "locate_peak", "peak_quality"]

__getattr__ = lazy_exports(__name__, _LAZY)
