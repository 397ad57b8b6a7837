"""The camera pose in the flange {F} (eye in hand) from robot poses and board images
(:func:`calibrate_hand_eye`).

Needs the calibrated camera. The board is fixed in the robot base; ``AX = XB`` in closed form
(:func:`hand_eye_linear`: ``cv2.calibrateHandEye`` where the installed OpenCV has it, Park &
Martin otherwise), optionally refined by bundle adjustment of the corner reprojection error.
The set's flange poses come from its ``poses.csv``
(:func:`torchseam.core.poses_csv.read_pose_csv`, label column ``image``).
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from torchseam.core.calibration import CalibrationConfig, CalibrationError
from torchseam.core.config import CameraConfig, Pose
from torchseam.core.poses_csv import read_pose_csv
from torchseam.core.transforms import invert, matrix_to_quat
from torchseam.geometry.calibrate.sets import (
    board_pose,
    check_count,
    check_motion,
    detect_all,
    read_image,
    rms,
)
from torchseam.geometry.names import HAND_EYE_CV_FLAGS, HAND_EYE_METHODS

__all__ = ["HAND_EYE_METHODS", "HandEyeCalibration", "calibrate_hand_eye", "hand_eye_linear",
           "load_handeye_set"]


@dataclass
class HandEyeCalibration:
    """Result of :func:`calibrate_hand_eye`.

    Attributes:
        hand_eye: camera pose in the flange ``T_F_C`` (mm, w x y z).
        T_B_O: (4, 4) board pose in the robot base, fitted with it (mm).
        method: the linear solver that gave the start (``park``, ``tsai``, ...).
        refined: whether bundle adjustment refined it.
        reproj_rms_px: RMS corner reprojection error with the fitted transforms (px).
        view_reproj_px: (N,) per view (px).
        view_pos_mm: (N,) distance between the board pose seen in view i
            (``T_B_F_i @ X @ T_C_O_i``, ``T_C_O_i`` by solvePnP) and the fitted ``T_B_O`` (mm).
        view_rot_deg: (N,) the rotation between them (deg).
        names: the N views.
    """

    hand_eye: Pose
    T_B_O: np.ndarray
    method: str
    refined: bool
    reproj_rms_px: float
    view_reproj_px: np.ndarray
    view_pos_mm: np.ndarray
    view_rot_deg: np.ndarray
    names: list[str]

    def summary(self) -> list[str]:
        h = self.hand_eye
        wp, wr = int(np.argmax(self.view_pos_mm)), int(np.argmax(self.view_rot_deg))
        return [
            f"views               {len(self.names)} (start: {self.method}"
            f"{', bundle-adjusted' if self.refined else ''})",
            "position            " + " ".join(f"{x:.4f}" for x in h.position_mm) + " mm",
            "quaternion          " + " ".join(f"{x:.9f}" for x in h.quaternion),
            f"reprojection RMS    {self.reproj_rms_px:.4f} px",
            f"board in base       RMS {rms(self.view_pos_mm):.4f} mm, max "
            f"{self.view_pos_mm[wp]:.4f} mm ({self.names[wp]}); RMS "
            f"{rms(self.view_rot_deg):.4f} deg, max {self.view_rot_deg[wr]:.4f} deg "
            f"({self.names[wr]})",
        ]


def _hand_eye_park(T_B_F: np.ndarray, T_C_O: np.ndarray) -> np.ndarray:
    """``AX = XB`` by Park & Martin (1994) over all pairs of views: X = T_F_C (4, 4)."""
    alphas, betas, As, Bs = [], [], [], []
    for i, j in itertools.combinations(range(len(T_B_F)), 2):
        A = invert(T_B_F[i]) @ T_B_F[j]
        B = T_C_O[i] @ invert(T_C_O[j])
        alphas.append(Rotation.from_matrix(A[:3, :3]).as_rotvec())
        betas.append(Rotation.from_matrix(B[:3, :3]).as_rotvec())
        As.append(A)
        Bs.append(B)
    a, b = np.array(alphas), np.array(betas)
    # alpha = R_X beta: orthogonal Procrustes (Kabsch)
    U, _, Vt = np.linalg.svd(b.T @ a)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    R_X = Vt.T @ D @ U.T
    # (R_A - I) t_X = R_X t_B - t_A
    M = np.concatenate([A[:3, :3] - np.eye(3) for A in As])
    rhs = np.concatenate([R_X @ B[:3, 3] - A[:3, 3] for A, B in zip(As, Bs, strict=True)])
    t_X = np.linalg.lstsq(M, rhs, rcond=None)[0]
    X = np.eye(4)
    X[:3, :3], X[:3, 3] = R_X, t_X
    return X


def hand_eye_linear(T_B_F: np.ndarray, T_C_O: np.ndarray, method: str = "park"
                    ) -> tuple[np.ndarray, str]:
    """Closed-form eye-in-hand ``AX = XB``: camera pose in the flange.

    Uses ``cv2.calibrateHandEye`` with ``method`` when the installed OpenCV exposes it (its
    Python binding is missing in 5.0.0, opencv/opencv#29565); otherwise Park & Martin here.

    Args:
        T_B_F: (N, 4, 4) flange poses in the base (mm).
        T_C_O: (N, 4, 4) board poses in the camera (mm).
        method: one of :data:`HAND_EYE_METHODS`.

    Returns:
        ``(T_F_C (4, 4), the method that ran)``.
    """
    if method not in HAND_EYE_CV_FLAGS:
        raise ValueError(f"hand-eye method {method!r}: use one of {', '.join(HAND_EYE_CV_FLAGS)}")
    fn = getattr(cv2, "calibrateHandEye", None)
    if fn is None:
        return _hand_eye_park(T_B_F, T_C_O), "park (numpy; no cv2.calibrateHandEye)"
    R, t = fn(list(T_B_F[:, :3, :3]), list(T_B_F[:, :3, 3:]), list(T_C_O[:, :3, :3]),
              list(T_C_O[:, :3, 3:]), method=getattr(cv2, HAND_EYE_CV_FLAGS[method]))
    X = np.eye(4)
    X[:3, :3], X[:3, 3] = R, np.asarray(t).ravel()
    return X, f"{method} (cv2.calibrateHandEye)"


def _vec(T: np.ndarray) -> np.ndarray:
    return np.concatenate([Rotation.from_matrix(T[:3, :3]).as_rotvec(), T[:3, 3]])


def _mat(v: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(v[:3]).as_matrix()
    T[:3, 3] = v[3:]
    return T


def _mean_pose(Ts: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_matrix(Ts[:, :3, :3]).mean().as_matrix()
    T[:3, 3] = Ts[:, :3, 3].mean(axis=0)
    return T


def _pose_gap(Ta: np.ndarray, Tb: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(N,) position distance (mm) and rotation angle (deg) between pose stacks."""
    d = np.linalg.norm(Ta[..., :3, 3] - Tb[..., :3, 3], axis=-1)
    rel = np.einsum("...ji,...jk->...ik", Ta[..., :3, :3], Tb[..., :3, :3])
    ang = np.degrees(np.linalg.norm(Rotation.from_matrix(rel.reshape(-1, 3, 3)).as_rotvec(),
                                    axis=-1))
    return d, ang.reshape(d.shape)


def calibrate_hand_eye(images: Sequence[np.ndarray], names: Sequence[str], T_B_F: np.ndarray,
                       camera: CameraConfig, cfg: CalibrationConfig, method: str = "park",
                       refine: bool = False) -> HandEyeCalibration:
    """Camera pose in the flange (eye in hand) from robot poses and board images.

    The board is fixed in the robot base; at each recorded flange pose ``T_B_F[i]`` the camera
    sees it, giving ``T_C_O[i]`` by solvePnP, and ``AX = XB`` is solved in closed form
    (:func:`hand_eye_linear`). ``refine`` adds a bundle adjustment of ``X = T_F_C`` and
    ``T_B_O`` on the corner reprojection error of all views, which trusts the flange poses
    exactly: use it only when they are far better than the camera's view of the board. This
    lens sees 23 degrees, so a camera turned about a point near the board hardly changes its
    image; the adjustment then slides along that direction to absorb robot error: better with
    exact poses, several times worse with a real robot's pose noise (simulated figures:
    docs/benchmarks.md, "Calibration").

    Args:
        images: N board images; names: their names.
        T_B_F: (N, 4, 4) recorded flange poses in the base (mm).
        camera: the (calibrated) camera.
        cfg: calibration settings (board, ``detect``, ``handeye``).
        method: closed-form solver, one of :data:`HAND_EYE_METHODS`.
        refine: run the bundle adjustment (only for near-exact flange poses, see above).

    Returns:
        :class:`HandEyeCalibration`.

    Raises:
        CalibrationError: fewer than ``handeye.min_views`` poses, a board not found (naming
            the image), pure translations, or all turns about one axis.
    """
    what = "hand-eye calibration"
    T_B_F = np.asarray(T_B_F, float).reshape(-1, 4, 4)
    if not len(images) == len(names) == len(T_B_F):
        raise ValueError(f"{len(images)} images, {len(names)} names, {len(T_B_F)} robot poses")
    hs = cfg.handeye
    check_count(len(T_B_F), hs.min_views, what, "handeye.min_views", "robot poses")
    check_motion(T_B_F, hs.min_rotation_deg, hs.min_axis_spread_deg, what, "robot poses")
    corners, _, _ = detect_all(images, names, cfg, False, what)
    T_C_O = np.stack([board_pose(c, cfg.board, camera)[0] for c in corners])
    X, used = hand_eye_linear(T_B_F, T_C_O, method)
    T_B_O = _mean_pose(T_B_F @ X @ T_C_O)
    obj = cfg.board.object_points()
    K, dist = camera.K, np.asarray(camera.dist, float)
    uv = np.stack(corners)

    def reproject(x: np.ndarray) -> np.ndarray:
        Xm, Bm = _mat(x[:6]), _mat(x[6:])
        out = np.empty_like(uv)
        for k in range(len(uv)):
            T = invert(T_B_F[k] @ Xm) @ Bm  # T_C_O of view k
            rvec = cv2.Rodrigues(T[:3, :3])[0]
            out[k] = cv2.projectPoints(obj, rvec, T[:3, 3], K, dist)[0].reshape(-1, 2)
        return out

    x0 = np.concatenate([_vec(X), _vec(T_B_O)])
    if refine:
        sol = least_squares(lambda x: (reproject(x) - uv).ravel(), x0, method="lm",
                            x_scale=np.tile([1e-3] * 3 + [1.0] * 3, 2), xtol=1e-12, ftol=1e-12)
        x0 = sol.x
    X, T_B_O = _mat(x0[:6]), _mat(x0[6:])
    err = np.linalg.norm(reproject(x0) - uv, axis=-1)
    view_reproj = np.sqrt(np.mean(err**2, axis=1))
    pos, rot = _pose_gap(T_B_F @ X @ T_C_O, np.broadcast_to(T_B_O, T_C_O.shape))
    pose = Pose(position_mm=tuple(float(v) for v in X[:3, 3]),
                quaternion=tuple(float(v) for v in matrix_to_quat(X[:3, :3])))
    return HandEyeCalibration(pose, T_B_O, used, refine, rms(err.ravel()), view_reproj, pos, rot,
                              list(names))


def load_handeye_set(folder: Path) -> tuple[list[np.ndarray], list[str], np.ndarray]:
    """``poses.csv`` (``image,x,y,z,q1,q2,q3,q4``: the flange pose in the base per image; a pose
    CSV, :mod:`torchseam.core.poses_csv`) and the images it names.

    Raises:
        CalibrationError: no folder, an image the file names is missing or unreadable.
        PoseFileError: ``poses.csv`` cannot be read (naming its line and field).
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise CalibrationError(f"{folder}: no such folder (hand-eye calibration set)")
    poses = read_pose_csv(folder / "poses.csv", label="image")
    keys, T = poses.labels or [], poses.T
    images = []
    for k in keys:
        if not (folder / k).is_file():
            raise CalibrationError(f"{folder / 'poses.csv'}: image {k} is not in {folder}")
        images.append(read_image(folder / k))
    return images, keys, T
