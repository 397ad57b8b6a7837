"""Pixels -> 3D seam points in the robot base (METHOD.md section 7), batched in torch.

pixel -> undistorted ray -> cut with the laser plane -> camera frame {C} -> flange {F} (hand-eye)
-> robot base {B} (the flange pose the robot reports for the frame's time stamp).
"""

from __future__ import annotations

import cv2
import numpy as np
import torch
from torch import Tensor, nn

from torchseam.core.camera import intrinsics, laser_plane_tensor, pixels_to_plane
from torchseam.core.checks import check_shape
from torchseam.core.config import CellConfig

# iterate OpenCV's undistortion to convergence (its default stops after 5 iterations)
_UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 20, 1e-12)


def transform_points(T: Tensor, X: Tensor) -> Tensor:
    """Apply (..., 4, 4) rigid transforms to (..., 3) points (broadcasting)."""
    return (T[..., :3, :3] @ X.unsqueeze(-1)).squeeze(-1) + T[..., :3, 3]


def triangulate(uv: Tensor, K: Tensor, dist: Tensor, plane: Tensor, T_F_C: Tensor,
                T_B_F: Tensor) -> Tensor:
    """Seam pixels to 3D points in the robot base.

    Args:
        uv: (..., 2) pixels (u, v) on the laser stripe.
        K: (3, 3) intrinsics; dist: (5,) OpenCV distortion.
        plane: (4,) laser plane (n, d) in {C}: n . X = d (mm).
        T_F_C: (4, 4) hand-eye, camera pose in the flange frame (mm).
        T_B_F: (..., 4, 4) flange pose in the base at each frame (mm).

    Returns:
        (..., 3) points in {B} (mm); NaN where a pixel's ray misses the plane.

    Example:
        >>> from torchseam.core.config import load_cell
        >>> tri = Triangulator(load_cell())
        >>> tri(torch.tensor([[331.5, 243.2]]), torch.eye(4, dtype=torch.float64)).shape
        torch.Size([1, 3])
    """
    check_shape(uv, "... 2", "uv")
    check_shape(T_F_C, "... 4 4", "T_F_C")
    check_shape(T_B_F, "... 4 4", "T_B_F")
    X_C = pixels_to_plane(uv, K, dist, plane)
    return transform_points(T_B_F @ T_F_C, X_C)


class Triangulator(nn.Module):
    """:func:`triangulate` with the cell's calibration held as buffers (device/dtype follow)."""

    K: Tensor
    dist: Tensor
    plane: Tensor
    T_F_C: Tensor

    def __init__(self, cell: CellConfig, dtype: torch.dtype = torch.float64) -> None:
        super().__init__()
        K, dist = intrinsics(cell.camera, dtype)
        self.register_buffer("K", K)
        self.register_buffer("dist", dist)
        self.register_buffer("plane", laser_plane_tensor(cell.laser_plane, dtype))
        self.register_buffer("T_F_C", torch.tensor(cell.hand_eye.matrix(), dtype=dtype))

    def forward(self, uv: Tensor, T_B_F: Tensor) -> Tensor:
        """(..., 2) pixels + (..., 4, 4) flange poses -> (..., 3) base points (mm)."""
        uv = uv.to(self.K)
        return triangulate(uv, self.K, self.dist, self.plane, self.T_F_C, T_B_F.to(self.K))


class FastTriangulator:
    """:func:`triangulate` for a few pixels at a time on the CPU, through OpenCV.

    The torch version pays a per-op overhead that dominates for the three points of one frame,
    too much for the live loop's 4 ms EGM cycle; this one is a few OpenCV and numpy calls.
    Tests hold the two to the same numbers.
    """

    def __init__(self, cell: CellConfig) -> None:
        self.K = cell.camera.K
        self.dist = np.asarray(cell.camera.dist, float)
        self.n = np.asarray(cell.laser_plane.normal, float)
        self.d = float(cell.laser_plane.distance_mm)
        self.T_F_C = cell.hand_eye.matrix()

    def __call__(self, uv: np.ndarray, T_B_F: np.ndarray) -> np.ndarray:
        """(N, 2) pixels + (4, 4) flange pose -> (N, 3) base points (mm), NaN off-plane."""
        uv = np.asarray(uv, float).reshape(-1, 1, 2)
        xy = cv2.undistortPoints(uv, self.K, self.dist, criteria=_UNDISTORT_CRITERIA)
        ray = np.concatenate([xy.reshape(-1, 2), np.ones((len(xy), 1))], axis=1)
        denom = ray @ self.n
        # d / denom where the ray meets the plane, NaN where it runs along it (np.divide's
        # where: no warning to silence, which np.errstate did at ~10 us a call)
        scale = np.divide(self.d, denom, out=np.full(len(denom), np.nan),
                          where=np.abs(denom) > 1e-9)
        X = ray * scale[:, None]
        T = np.asarray(T_B_F, float) @ self.T_F_C
        return X @ T[:3, :3].T + T[:3, 3]

    def expect(self, p_a: np.ndarray, p_b: np.ndarray, T_B_F: np.ndarray) -> np.ndarray | None:
        """Where the stripe should cross the seam in a frame taken with the flange at ``T_B_F``:
        the seam taken as the line through the base points ``p_a`` -> ``p_b`` (mm), cut with
        the laser plane there and projected (2,) px; None when the line runs in the plane.

        In closed loop the image jumps when the torch turns to a new target; the robot's own
        pose says by how much, before the frame is even looked at.
        """
        T = np.asarray(T_B_F, float) @ self.T_F_C
        R, t = T[:3, :3], T[:3, 3]
        A = (np.asarray(p_a, float) - t) @ R   # camera frame (R^T (p - t))
        D = (np.asarray(p_b, float) - t) @ R - A
        den = float(self.n @ D)
        if abs(den) < 1e-9:
            return None
        X = A + (self.d - float(self.n @ A)) / den * D
        if X[2] <= 0:
            return None  # behind the camera
        uv, _ = cv2.projectPoints(X.reshape(1, 1, 3), np.zeros(3), np.zeros(3), self.K,
                                  self.dist)
        return uv.reshape(2)
