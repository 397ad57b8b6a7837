"""The torch tool centre point in the flange {F} by pivoting (:func:`calibrate_tcp`).

The torch tip touches one fixed point from several orientations; linear least squares. Needs no
camera: only the flange poses of the set's ``poses.csv``
(:func:`torchseam.core.poses_csv.read_pose_csv`, label column ``pose``).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from torchseam.core.calibration import CalibrationConfig, CalibrationError
from torchseam.core.config import Pose
from torchseam.core.poses_csv import read_pose_csv
from torchseam.geometry.calibrate.sets import check_count, check_motion, rms

__all__ = ["TcpCalibration", "calibrate_tcp", "load_tcp_set"]


@dataclass
class TcpCalibration:
    """Result of :func:`calibrate_tcp`.

    Attributes:
        tool: TCP pose in the flange (position fitted, mm; orientation kept from the input).
        point_B: (3,) the touched point in the robot base (mm).
        rms_mm: RMS of ``|R_i t + p_i - point|`` over the poses (mm).
        pose_err_mm: (N,) per pose (mm).
        names: the N poses.
    """

    tool: Pose
    point_B: np.ndarray
    rms_mm: float
    pose_err_mm: np.ndarray
    names: list[str]

    def summary(self) -> list[str]:
        worst = int(np.argmax(self.pose_err_mm))
        return [
            f"poses               {len(self.names)}",
            "TCP in flange       " + " ".join(f"{x:.4f}" for x in self.tool.position_mm) + " mm",
            "touched point       " + " ".join(f"{x:.4f}" for x in self.point_B) + " mm (base)",
            f"pivot residual      RMS {self.rms_mm:.4f} mm, max {self.pose_err_mm[worst]:.4f} mm "
            f"({self.names[worst]})",
        ]


def calibrate_tcp(T_B_F: np.ndarray, names: Sequence[str], cfg: CalibrationConfig,
                  orientation: Sequence[float] = (1.0, 0.0, 0.0, 0.0)) -> TcpCalibration:
    """Torch TCP in the flange by pivoting about one fixed point.

    At each pose the torch tip touches the same point ``P`` of the base:
    ``R_i t + p_i = P``; ``[R_i, -I] [t; P] = -p_i`` stacked and solved by least squares.

    Args:
        T_B_F: (N, 4, 4) recorded flange poses (mm).
        names: their names (e.g. the CSV's pose column).
        cfg: calibration settings (``tcp``).
        orientation: (4,) TCP orientation in the flange to keep (pivoting cannot see it).

    Returns:
        :class:`TcpCalibration`.

    Raises:
        CalibrationError: fewer than ``tcp.min_poses`` poses, one orientation for all, or all
            turns about one axis.
    """
    what = "TCP calibration"
    T_B_F = np.asarray(T_B_F, float).reshape(-1, 4, 4)
    if len(names) != len(T_B_F):
        raise ValueError(f"{len(T_B_F)} poses but {len(names)} names")
    ts = cfg.tcp
    check_count(len(T_B_F), ts.min_poses, what, "tcp.min_poses", "poses")
    check_motion(T_B_F, ts.min_rotation_deg, ts.min_axis_spread_deg, what, "poses")
    R, p = T_B_F[:, :3, :3], T_B_F[:, :3, 3]
    A = np.concatenate([R, -np.broadcast_to(np.eye(3), R.shape)], axis=2).reshape(-1, 6)
    sol, *_ = np.linalg.lstsq(A, -p.reshape(-1), rcond=None)
    t, P = sol[:3], sol[3:]
    err = np.linalg.norm(np.einsum("nij,j->ni", R, t) + p - P, axis=1)
    tool = Pose(position_mm=tuple(float(v) for v in t),
                quaternion=tuple(float(v) for v in orientation))
    return TcpCalibration(tool, P, rms(err), err, list(names))


def load_tcp_set(folder: Path) -> tuple[list[str], np.ndarray]:
    """``poses.csv`` (``pose,x,y,z,q1,q2,q3,q4``; a pose CSV, :mod:`torchseam.core.poses_csv`):
    the touches' names and flange poses in the base, the torch tip on the fixed point.

    Raises:
        CalibrationError: no folder.
        PoseFileError: ``poses.csv`` cannot be read (naming its line and field).
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise CalibrationError(f"{folder}: no such folder (TCP calibration set)")
    poses = read_pose_csv(folder / "poses.csv", label="pose")
    return poses.labels or [], poses.T
