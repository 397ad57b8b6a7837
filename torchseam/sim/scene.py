"""The simulated cell over time: the true part (with deviations), the nominal part, the torch path.

* The **nominal** part is the design: the kind of part (:mod:`torchseam.core.part`), its
  diameters, intersection angle and designed offset at the nominal placement, no unwanted
  offset, ovality or drift. A robot programmed from the design follows it.
* The **true** part adds the branch offset, ovality (main pipe and branch), clamping error and
  a slow thermal drift.
* The part sits on a positioner that turns it about the branch axis by ``rotation_deg`` (the
  six-segment welding of METHOD.md section 6).
"""

from __future__ import annotations

import numpy as np

from torchseam.core.config import PartConfig
from torchseam.core.part import SegmentGeometry, make_joint, nominal_part, torch_frames

__all__ = ["DRIFT_DIRECTION", "Scene", "nominal_part", "torch_frames"]  # the last two: core.part

# Direction of the thermal drift in {T} (fixed: the part warps one way as it heats).
DRIFT_DIRECTION = np.array([0.6, -0.55, 0.58]) / np.linalg.norm([0.6, -0.55, 0.58])


class Scene(SegmentGeometry):
    """True and nominal part in the robot base frame {B}.

    Example:
        >>> from torchseam.core.config import load_part
        >>> scene = Scene(load_part())
        >>> scene.nominal_tcp(np.array([0.0, 10.0])).shape
        (2, 4, 4)
    """

    def __init__(self, part: PartConfig, rotation_deg: float = 0.0) -> None:
        super().__init__(part, rotation_deg)  # the nominal part, as the planner has it
        self.true_joint = make_joint(part)
        self._T_B_Ttrue0 = self.T_B_Tnom @ part.placement_error.matrix()

    def part_pose(self, t_s: float) -> np.ndarray:
        """True pose of the part {T} in {B} at weld time ``t_s``, (4, 4)."""
        p = self.part
        drift = np.eye(4)
        grow = 0.5 * (1.0 - np.cos(2 * np.pi * t_s / p.distortion_period_s))
        drift[:3, 3] = p.distortion_mm * grow * DRIFT_DIRECTION
        return self._T_B_Ttrue0 @ drift

    def true_seam_base(self, phi: np.ndarray, t_s: float) -> np.ndarray:
        """True seam points (N, 3) in {B} at angles ``phi`` and time ``t_s``."""
        T = self.part_pose(t_s)
        return self.true_joint.seam(phi).point @ T[:3, :3].T + T[:3, 3]
