"""Camera intrinsics and OpenCV distortion from checkerboard images (:func:`calibrate_camera`).

The first procedure: the others take the camera it gives. ``findChessboardCorners`` +
``cornerSubPix`` (:func:`~torchseam.geometry.calibrate.sets.detect_board`), then OpenCV's
``calibrateCameraExtended``; refused when the board views are all parallel or the focal length
is not determined.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from torchseam.core.calibration import CalibrationConfig, CalibrationError
from torchseam.core.config import CameraConfig
from torchseam.geometry.calibrate.sets import (
    check_count,
    check_sizes,
    detect_all,
    list_images,
    read_image,
    rt_matrix,
)

__all__ = ["CameraCalibration", "calibrate_camera", "load_camera_set"]


@dataclass
class CameraCalibration:
    """Result of :func:`calibrate_camera`.

    Attributes:
        camera: the fitted camera (size, fx, fy, cx, cy in px; dist k1 k2 p1 p2 k3).
        rms_px: RMS corner reprojection error over all views (px).
        view_rms_px: (N,) RMS per view (px).
        std: one-sigma uncertainty of fx, fy, cx, cy (px) and k1, k2, p1, p2, k3.
        board_poses: (N, 4, 4) board pose in the camera ``T_C_O`` per view (mm).
        tilt_spread_deg: largest angle between two views' board normals.
        names: the N views used.
        skipped: the images left out (``skip_failed``), each with why: "NAME: reason".
    """

    camera: CameraConfig
    rms_px: float
    view_rms_px: np.ndarray
    std: dict[str, float]
    board_poses: np.ndarray
    tilt_spread_deg: float
    names: list[str]
    skipped: list[str]

    def summary(self) -> list[str]:
        c, s = self.camera, self.std
        worst = int(np.argmax(self.view_rms_px))
        lines = [
            f"views               {len(self.names)} (board normals spread over "
            f"{self.tilt_spread_deg:.1f} deg)",
            f"fx, fy              {c.fx:.3f} +- {s['fx']:.3f}, {c.fy:.3f} +- {s['fy']:.3f} px",
            f"cx, cy              {c.cx:.3f} +- {s['cx']:.3f}, {c.cy:.3f} +- {s['cy']:.3f} px",
            "dist (k1 k2 p1 p2 k3)  " + " ".join(f"{d:.6f}" for d in c.dist),
            f"reprojection RMS    {self.rms_px:.4f} px (worst view {self.names[worst]}: "
            f"{self.view_rms_px[worst]:.4f} px)",
        ]
        if self.skipped:
            n = len(self.skipped) + len(self.names)
            lines.insert(1, f"skipped             {len(self.skipped)} of {n} images, board not "
                            "found: " + ", ".join(e.split(":", 1)[0] for e in self.skipped))
        return lines


def calibrate_camera(images: Sequence[np.ndarray], names: Sequence[str], cfg: CalibrationConfig,
                     skip_failed: bool = False) -> CameraCalibration:
    """Camera intrinsics and distortion from checkerboard images.

    Args:
        images: N (H, W) or (H, W, 3) uint8 images of the board at varied poses.
        names: their names (file names), for errors and the report.
        cfg: calibration settings (board, ``detect``, ``camera``).
        skip_failed: leave out images where the board is not found instead of failing.

    Returns:
        :class:`CameraCalibration` with the fitted :class:`CameraConfig` and its residuals.

    Raises:
        CalibrationError: a board not found (naming the images), fewer than
            ``camera.min_views`` views, all boards parallel, or a focal length not determined.

    Example:
        >>> from torchseam.sim.board import simulate_camera_set
        >>> from torchseam.core.calibration import load_calibration
        >>> from torchseam.core.config import load_cell
        >>> cfg = load_calibration()
        >>> s = simulate_camera_set(load_cell(), cfg, views=6)
        >>> res = calibrate_camera(s.images, s.names, cfg)
        >>> bool(abs(res.camera.fx / 1600.0 - 1) < 0.01)
        True
    """
    what = "camera calibration"
    if len(images) != len(names):
        raise ValueError(f"{len(images)} images but {len(names)} names")
    check_count(len(images), cfg.camera.min_views, what, "camera.min_views")
    w, h = check_sizes(images, names)
    corners, keep, skipped = detect_all(
        images, names, cfg, skip_failed, what,
        hint=" (--skip-failed leaves out the images where it is not found)")
    names = [names[k] for k in keep]
    check_count(len(corners), cfg.camera.min_views, what, "camera.min_views")
    obj = [cfg.board.object_points().astype(np.float32)] * len(corners)
    img = [c.reshape(-1, 1, 2).astype(np.float32) for c in corners]
    flags = cv2.CALIB_FIX_K3 if cfg.camera.radial_terms == 2 else 0
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 200, 1e-12)
    try:
        # None: OpenCV computes the camera matrix and distortion (its stubs want arrays)
        rms, K, dist, rvecs, tvecs, std_int, _, per_view = cv2.calibrateCameraExtended(
            obj, img, (w, h), None, None, flags=flags,  # type: ignore[call-overload]
            criteria=crit)
    except cv2.error as e:
        raise CalibrationError(f"{what}: OpenCV could not solve this set ({_cv_msg(e)}); "
                               "the views are probably too alike: tilt the board more") from None
    poses = np.stack([rt_matrix(r, t) for r, t in zip(rvecs, tvecs, strict=True)])
    normals = poses[:, :3, 2]
    cosang = np.clip(normals @ normals.T, -1.0, 1.0)
    spread = float(np.degrees(np.arccos(cosang.min())))
    if spread < cfg.camera.min_tilt_spread_deg:
        raise CalibrationError(
            f"{what}: all {len(names)} board views are parallel (normals within {spread:.2f} "
            f"deg, need {cfg.camera.min_tilt_spread_deg:g}; camera.min_tilt_spread_deg): the "
            "focal length is not observable; tilt the board 10-40 degrees about different axes")
    std_int = np.asarray(std_int, float).ravel()
    keys = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3")
    std = {k: float(std_int[i]) for i, k in enumerate(keys)}
    if not np.all(np.isfinite(K)) or not std["fx"] < cfg.camera.max_focal_std_rel * K[0, 0]:
        raise CalibrationError(
            f"{what}: the focal length is not determined by these {len(names)} views (fx "
            f"{K[0, 0]:.1f} +- {std['fx']:.1f} px; camera.max_focal_std_rel "
            f"{cfg.camera.max_focal_std_rel:g}): add views with more tilt and over the whole image")
    d = np.zeros(5)
    d[:min(5, dist.size)] = dist.ravel()[:5]
    camera = CameraConfig(width=w, height=h, fx=float(K[0, 0]), fy=float(K[1, 1]),
                          cx=float(K[0, 2]), cy=float(K[1, 2]), dist=tuple(float(x) for x in d))
    return CameraCalibration(camera, float(rms), np.asarray(per_view, float).ravel(), std, poses,
                             spread, list(names), skipped)


def _cv_msg(e: cv2.error) -> str:
    return str(e).strip().splitlines()[-1] if str(e).strip() else "cv2.error"


def load_camera_set(folder: Path) -> tuple[list[np.ndarray], list[str]]:
    """Every image in ``folder`` (sorted by name): the checkerboard views."""
    files = list_images(folder, "camera calibration set")
    return [read_image(p) for p in files], [p.name for p in files]
