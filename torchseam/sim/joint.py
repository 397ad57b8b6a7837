"""The part's geometry, as the simulator sees it: :mod:`torchseam.core.part`, re-exported.

The joint kinds (pipe, offset, plate, sphere), their seam and ray casting are the part's, not
the simulator's: the planner and the reachability gate take them from :mod:`torchseam.core.part`
too. This module keeps the old import path for the simulator's callers.
"""

from __future__ import annotations

from torchseam.core.part import (
    BRANCH_LENGTH_MM,
    NOZZLE_ABOVE_SEAM_MM,
    PLATE_HALF_MM,
    PLATE_THICKNESS_MM,
    Joint,
    PipeJoint,
    PlateJoint,
    SeamSample,
    SphereJoint,
    closed_form_orthogonal_seam,
    make_joint,
)

__all__ = ["BRANCH_LENGTH_MM", "NOZZLE_ABOVE_SEAM_MM", "PLATE_HALF_MM", "PLATE_THICKNESS_MM",
           "Joint", "PipeJoint", "PlateJoint", "SeamSample", "SphereJoint",
           "closed_form_orthogonal_seam", "make_joint"]
