"""Calibration of the laser-vision sensor (METHOD.md section 7).

Four procedures, each from a set of views, each returning a typed result with its residuals:

* :func:`calibrate_camera`: intrinsics and OpenCV distortion from checkerboard images
  (``findChessboardCorners`` + ``cornerSubPix`` + ``calibrateCameraExtended``).
* :func:`calibrate_laser_plane`: the laser light plane in {C} from stripe images on the flat
  board at several poses. The board pose comes from a checkerboard image taken at the same pose
  (``solvePnP``) or is given; the stripe centre line is found per column by sub-pixel grey
  gravity; the undistorted rays are cut with the board plane and a plane is fitted by SVD.
* :func:`calibrate_hand_eye`: the camera pose in the flange {F} from recorded flange poses
  ``T_B_F`` and images of a board fixed in the robot base (``AX = XB``, Park & Martin, with
  ``cv2.calibrateHandEye`` where the installed OpenCV has it), refined by bundle adjustment of
  the corner reprojection error.
* :func:`calibrate_tcp`: the torch tool centre point in {F} by pivoting: the torch tip touches
  one fixed point from several orientations; linear least squares.

Settings live in ``configs/calibration.yaml`` (:class:`CalibrationConfig`). Every error names
what to fix: the image that failed, the view that is short, the set that is degenerate.

Frames: {B} robot base, {F} flange, {C} camera, {O} board (origin at the first inner corner,
x along the board's ``cols`` corners, y along its ``rows``, z into the board, away from the
camera that sees its face). Units: mm, degrees, pixels; quaternions (w, x, y, z).
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from torchseam.core.calibration import (
    POSE_COLUMNS,
    BoardSpec,
    CalibrationConfig,
    CalibrationError,
    CameraSetSim,
    CameraSettings,
    DetectSettings,
    HandEyeSetSim,
    HandEyeSettings,
    LaserSetSim,
    LaserSettings,
    RenderSettings,
    SimulationSettings,
    TcpSetSim,
    TcpSettings,
    load_calibration,
    read_pose_csv,
    write_pose_csv,
)
from torchseam.core.camera import undistort_points
from torchseam.core.config import CameraConfig, LaserPlane, Pose
from torchseam.core.transforms import invert, matrix_to_quat

#: the settings and the pose file live in :mod:`torchseam.core.calibration` (the simulator
#: reads them too); re-exported here with the procedures
__all__ = ["HAND_EYE_METHODS", "IMAGE_SUFFIXES", "POSE_COLUMNS", "BoardSpec", "CalibrationConfig",
           "CalibrationError", "CameraCalibration", "CameraSetSim", "CameraSettings",
           "DetectSettings", "HandEyeCalibration", "HandEyeSetSim", "HandEyeSettings",
           "LaserCalibration", "LaserSetSim", "LaserSettings", "RenderSettings",
           "SimulationSettings", "TcpCalibration", "TcpSetSim", "TcpSettings", "board_pose",
           "calibrate_camera", "calibrate_hand_eye", "calibrate_laser_plane", "calibrate_tcp",
           "detect_board", "extract_stripe", "fit_plane", "hand_eye_linear", "list_images",
           "load_calibration", "load_camera_set", "load_handeye_set", "load_laser_set",
           "load_tcp_set", "read_image", "read_pose_csv", "stripe_on_board", "to_grey",
           "write_pose_csv"]

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")


# --------------------------------------------------------------------------- results

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
    """

    camera: CameraConfig
    rms_px: float
    view_rms_px: np.ndarray
    std: dict[str, float]
    board_poses: np.ndarray
    tilt_spread_deg: float
    names: list[str]

    def summary(self) -> list[str]:
        c, s = self.camera, self.std
        worst = int(np.argmax(self.view_rms_px))
        return [
            f"views               {len(self.names)} (board normals spread over "
            f"{self.tilt_spread_deg:.1f} deg)",
            f"fx, fy              {c.fx:.3f} +- {s['fx']:.3f}, {c.fy:.3f} +- {s['fy']:.3f} px",
            f"cx, cy              {c.cx:.3f} +- {s['cx']:.3f}, {c.cy:.3f} +- {s['cy']:.3f} px",
            "dist (k1 k2 p1 p2 k3)  " + " ".join(f"{d:.6f}" for d in c.dist),
            f"reprojection RMS    {self.rms_px:.4f} px (worst view {self.names[worst]}: "
            f"{self.view_rms_px[worst]:.4f} px)",
        ]


@dataclass
class LaserCalibration:
    """Result of :func:`calibrate_laser_plane`.

    Attributes:
        plane: the fitted plane ``normal . X = distance_mm`` in {C}; ``source_mm`` is the
            previous source projected onto it (stripe images cannot see the source).
        rms_mm: RMS distance of the stripe points to the plane (mm).
        max_mm: largest distance of a kept point (mm).
        view_rms_mm: (N,) RMS per view (mm).
        view_points: (N,) stripe points kept per view.
        rejected: points dropped as outliers.
        points: (M, 3) the stripe points in {C} (mm).
        board_poses: (N, 4, 4) ``T_C_O`` used per view.
        names: the N views (laser image names).
    """

    plane: LaserPlane
    rms_mm: float
    max_mm: float
    view_rms_mm: np.ndarray
    view_points: np.ndarray
    rejected: int
    points: np.ndarray
    board_poses: np.ndarray
    names: list[str]

    def summary(self) -> list[str]:
        p = self.plane
        worst = int(np.argmax(self.view_rms_mm))
        return [
            f"views               {len(self.names)} ({int(self.view_points.sum())} stripe points, "
            f"{self.rejected} rejected)",
            "normal              " + " ".join(f"{x:.9f}" for x in p.normal),
            f"distance            {p.distance_mm:.6f} mm",
            f"plane fit RMS       {self.rms_mm:.4f} mm (max {self.max_mm:.4f} mm; worst view "
            f"{self.names[worst]}: {self.view_rms_mm[worst]:.4f} mm)",
        ]


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
            f"board in base       RMS {_rms(self.view_pos_mm):.4f} mm, max "
            f"{self.view_pos_mm[wp]:.4f} mm ({self.names[wp]}); RMS "
            f"{_rms(self.view_rot_deg):.4f} deg, max {self.view_rot_deg[wr]:.4f} deg "
            f"({self.names[wr]})",
        ]


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


def _rms(x: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(x)))) if len(x) else float("nan")


# --------------------------------------------------------------------------- board detection

def to_grey(image: np.ndarray) -> np.ndarray:
    """(H, W) or (H, W, 3) BGR uint8 -> (H, W) uint8 grey."""
    if image.ndim == 3:
        return cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    return image


def detect_board(image: np.ndarray, board: BoardSpec, detect: DetectSettings, name: str
                 ) -> np.ndarray:
    """Inner corners of the checkerboard, sub-pixel, in the board's own order.

    The order is made canonical: right-handed as seen from the board's face, and the square
    between the first four corners black (``cols + rows`` odd makes this unique).

    Args:
        image: (H, W) grey or (H, W, 3) BGR uint8.
        board: the board.
        detect: ``cornerSubPix`` settings.
        name: the image's name, for errors.

    Returns:
        (rows * cols, 2) float64 pixels (u, v), in :meth:`BoardSpec.object_points` order.

    Raises:
        CalibrationError: ``"<name>: no 9x6 checkerboard found ..."``.
    """
    grey = to_grey(image)
    flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
    found, corners = cv2.findChessboardCorners(grey, board.pattern_size, flags=flags)
    if not found:
        raise CalibrationError(
            f"{name}: no {board.cols}x{board.rows} checkerboard found (the whole board with its "
            "outer squares must be in view, lit and sharp; board size in configs/calibration.yaml)")
    n = detect.subpix_half_window_px
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, detect.subpix_iterations,
            detect.subpix_epsilon_px)
    corners = cv2.cornerSubPix(grey, corners.astype(np.float32), (n, n), (-1, -1), crit)
    grid = corners.reshape(board.rows, board.cols, 2).astype(np.float64)
    # Right-handed as seen from the face: image x-axis then y-axis turn clockwise (v down).
    ex, ey = grid[0, 1] - grid[0, 0], grid[1, 0] - grid[0, 0]
    if ex[0] * ey[1] - ex[1] * ey[0] < 0:
        grid = grid[::-1]
    first, second = _square_grey(grey, grid, 0, 0), _square_grey(grey, grid, 1, 0)
    if abs(first - second) < 10.0:
        raise CalibrationError(f"{name}: cannot tell black from white squares on the board "
                               f"(grey {first:.0f} vs {second:.0f}); too little contrast")
    if first > second:  # the first square must be black: the order is turned by half a turn
        grid = grid[::-1, ::-1]
    return grid.reshape(-1, 2)


def _square_grey(grey: np.ndarray, grid: np.ndarray, i: int, j: int) -> float:
    """Mean grey of the square whose top-left inner corner is grid[j, i]."""
    c = grid[j:j + 2, i:i + 2].reshape(-1, 2).mean(axis=0)
    patch = cv2.getRectSubPix(grey, (5, 5), (float(c[0]), float(c[1])))
    return float(patch.mean())


def board_pose(corners: np.ndarray, board: BoardSpec, camera: CameraConfig
               ) -> tuple[np.ndarray, float]:
    """Board pose in the camera from its corners (IPPE, then Levenberg-Marquardt).

    Args:
        corners: (N, 2) pixels in :meth:`BoardSpec.object_points` order.
        board: the board; camera: the camera model.

    Returns:
        ``(T_C_O (4, 4) mm, reprojection RMS px)``.
    """
    obj = board.object_points()
    K, dist = camera.K, np.asarray(camera.dist, float)
    img = corners.reshape(-1, 1, 2).astype(np.float64)
    ok, rvec, tvec = cv2.solvePnP(obj, img, K, dist, flags=cv2.SOLVEPNP_IPPE)
    if not ok:  # pragma: no cover - IPPE succeeds on any non-degenerate planar set
        raise CalibrationError("solvePnP failed on a detected board")
    rvec, tvec = cv2.solvePnPRefineLM(obj, img, K, dist, rvec, tvec)
    proj, _ = cv2.projectPoints(obj, rvec, tvec, K, dist)
    rms = float(np.sqrt(np.mean(np.sum((proj.reshape(-1, 2) - corners) ** 2, axis=1))))
    return _rt_matrix(rvec, tvec), rms


def _rt_matrix(rvec: np.ndarray, tvec: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(np.asarray(rvec, float).reshape(3, 1))[0]
    T[:3, 3] = np.asarray(tvec, float).ravel()
    return T


def _detect_all(images: Sequence[np.ndarray], names: Sequence[str], cfg: CalibrationConfig,
                skip_failed: bool, what: str) -> tuple[list[np.ndarray], list[int]]:
    """Detect the board in every image; name every failure (or skip them)."""
    found, keep, failed = [], [], []
    for k, (img, name) in enumerate(zip(images, names, strict=True)):
        try:
            found.append(detect_board(img, cfg.board, cfg.detect, name))
            keep.append(k)
        except CalibrationError as e:
            failed.append(str(e))
    if failed and not skip_failed:
        more = f" (and {len(failed) - 3} more)" if len(failed) > 3 else ""
        raise CalibrationError(f"{what}: board not found in {len(failed)} of {len(images)} "
                               f"images: " + "; ".join(failed[:3]) + more)
    return found, keep


def _check_count(n: int, need: int, what: str, field_name: str, unit: str = "views") -> None:
    if n < need:
        raise CalibrationError(
            f"{what}: {n} usable {unit}, need at least {need} "
            f"(configs/calibration.yaml: {field_name}); add {unit} at other poses")


def _check_sizes(images: Sequence[np.ndarray], names: Sequence[str]) -> tuple[int, int]:
    h, w = images[0].shape[:2]
    for img, name in zip(images, names, strict=True):
        if img.shape[:2] != (h, w):
            raise CalibrationError(f"{name}: image is {img.shape[1]}x{img.shape[0]}, the first "
                                   f"({names[0]}) is {w}x{h}; one camera, one size")
    return w, h


# --------------------------------------------------------------------------- camera

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
    _check_count(len(images), cfg.camera.min_views, what, "camera.min_views")
    w, h = _check_sizes(images, names)
    corners, keep = _detect_all(images, names, cfg, skip_failed, what)
    names = [names[k] for k in keep]
    _check_count(len(corners), cfg.camera.min_views, what, "camera.min_views")
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
    poses = np.stack([_rt_matrix(r, t) for r, t in zip(rvecs, tvecs, strict=True)])
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
                             spread, list(names))


def _cv_msg(e: cv2.error) -> str:
    return str(e).strip().splitlines()[-1] if str(e).strip() else "cv2.error"


# --------------------------------------------------------------------------- laser plane

def extract_stripe(image: np.ndarray, min_peak: float, half_window: int) -> np.ndarray:
    """Stripe centre line: one sub-pixel row per column by grey gravity.

    The stripe is the red channel of a BGR image (or the grey image). Per column: the peak row
    of the lightly smoothed column; the floor is the mean of the two pixels just outside the
    window on each side; the centre is the centroid of ``I - floor`` (clipped at 0) over
    ``peak +- half_window`` rows.

    Args:
        image: (H, W, 3) BGR or (H, W) uint8.
        min_peak: the peak must stand this many grey levels above the floor.
        half_window: centroid half window (rows); about 3 sigma of the stripe profile.

    Returns:
        (M, 2) float64 ``(u, v)`` pixels of the columns that hold a stripe.
    """
    red = (image[..., 2] if image.ndim == 3 else image).astype(np.float32)
    h, w = red.shape
    smooth = cv2.GaussianBlur(red, (1, 5), 0, sigmaY=1.0)
    v0 = np.argmax(smooth, axis=0)
    hw = half_window
    cols = np.arange(w)
    ok = (v0 >= hw + 2) & (v0 < h - hw - 2)
    cols, v0 = cols[ok], v0[ok]
    rows = v0[:, None] + np.arange(-hw - 2, hw + 3)[None, :]
    prof = red[rows, cols[:, None]]
    floor = 0.25 * (prof[:, 0] + prof[:, 1] + prof[:, -2] + prof[:, -1])
    win = np.clip(prof[:, 2:-2] - floor[:, None], 0.0, None)
    peak = win.max(axis=1)
    good = peak >= min_peak
    off = np.arange(-hw, hw + 1, dtype=np.float64)
    mass = win.sum(axis=1)
    centre = v0 + (win * off).sum(axis=1) / np.maximum(mass, 1e-9)
    return np.stack([cols[good].astype(np.float64), centre[good]], axis=1)


def _rays(uv: np.ndarray, camera: CameraConfig) -> np.ndarray:
    """(..., 2) distorted pixels -> (..., 3) rays (x, y, 1) in {C} (core's undistortion)."""
    K = torch.as_tensor(camera.K, dtype=torch.float64)
    dist = torch.as_tensor(camera.dist, dtype=torch.float64)
    xy = undistort_points(torch.as_tensor(uv, dtype=torch.float64), K, dist).numpy()
    return np.concatenate([xy, np.ones_like(xy[..., :1])], axis=-1)


def _cut_board(rays: np.ndarray, T_C_O: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rays from the camera centre cut with the board plane: (points in {C}, points in {O})."""
    n, c = T_C_O[:3, 2], T_C_O[:3, 3]
    t = (n @ c) / (rays @ n)
    X = rays * t[..., None]
    return X, (X - c) @ T_C_O[:3, :3]


def fit_plane(points: np.ndarray) -> tuple[np.ndarray, float, np.ndarray]:
    """Least-squares plane through (M, 3) points by SVD.

    Returns:
        ``(normal (3,), distance, singular values (3,))`` with ``normal . X = distance`` and
        ``distance >= 0``.
    """
    mean = points.mean(axis=0)
    _, s, vt = np.linalg.svd(points - mean, full_matrices=False)
    n = vt[2]
    d = float(n @ mean)
    if d < 0:
        n, d = -n, -d
    return n, d, s


def stripe_on_board(image: np.ndarray, T_C_O: np.ndarray, camera: CameraConfig,
                    cfg: CalibrationConfig, name: str) -> tuple[np.ndarray, np.ndarray]:
    """Stripe samples of one laser image that lie on white squares, and their 3D points.

    :func:`extract_stripe`, then each sample's ray (and the rays of its window's ends) cut
    with the board plane; a sample is kept when its whole centroid window lies inside one
    white area, ``laser.edge_margin_mm`` from its edges (black squares and square edges would
    bias the grey gravity).

    Args:
        image: (H, W, 3) BGR stripe image; T_C_O: (4, 4) the board's pose (mm).
        camera: the camera; cfg: settings (board, ``laser``); name: for errors.

    Returns:
        ``(uv (M, 2) px, X (M, 3) points in {C}, mm)``.

    Raises:
        CalibrationError: no stripe, or too few samples on white squares (naming ``name``).
    """
    ls = cfg.laser
    uv = extract_stripe(image, ls.min_peak_grey, ls.half_window_px)
    if len(uv) < ls.min_points_per_view:
        raise CalibrationError(
            f"{name}: no laser stripe found ({len(uv)} columns with a peak "
            f"{ls.min_peak_grey:g} grey levels above the floor; laser.min_peak_grey)")
    hw = float(ls.half_window_px)
    ends = np.stack([uv, uv - [0.0, hw], uv + [0.0, hw]])
    X, XO = _cut_board(_rays(ends, camera), T_C_O)
    cell = cfg.board.white_cell(XO[..., 0], XO[..., 1], ls.edge_margin_mm)
    keep = (cell[0] >= 0) & (cell[0] == cell[1]) & (cell[0] == cell[2])
    if keep.sum() < ls.min_points_per_view:
        raise CalibrationError(
            f"{name}: only {int(keep.sum())} stripe points fall on white squares of the board "
            f"(of {len(uv)} found; need {ls.min_points_per_view}, laser.min_points_per_view): "
            "the stripe must cross the board")
    return uv[keep], X[0][keep]


def calibrate_laser_plane(laser_images: Sequence[np.ndarray], names: Sequence[str],
                          camera: CameraConfig, cfg: CalibrationConfig,
                          board_images: Sequence[np.ndarray] | None = None,
                          board_names: Sequence[str] | None = None,
                          board_poses: Sequence[np.ndarray] | None = None,
                          source_mm: Sequence[float] | None = None) -> LaserCalibration:
    """Laser plane in {C} from stripe images on the flat board at several poses.

    Each view is a laser image (stripe on the board, lamp dimmed) and the board's pose: from a
    checkerboard image at the same pose (``board_images``, laser off) or given
    (``board_poses``). Stripe samples are used only where their centroid window lies inside a
    white square (black squares and square edges bias the grey gravity).

    Args:
        laser_images: N (H, W, 3) BGR uint8 stripe images.
        names: their names, for errors.
        camera: the (calibrated) camera.
        cfg: calibration settings (board, ``detect``, ``laser``).
        board_images: N checkerboard images at the same poses, or None with ``board_poses``.
        board_names: their names (default: ``names``).
        board_poses: N (4, 4) ``T_C_O`` (mm) instead of ``board_images``.
        source_mm: (3,) the laser source in {C} to keep (projected onto the fitted plane);
            default: the foot of the perpendicular from the camera centre.

    Returns:
        :class:`LaserCalibration`.

    Raises:
        CalibrationError: fewer than ``laser.min_views`` views, a board or stripe not found
            (naming the image), or stripe points of all views on one line (degenerate).
    """
    what = "laser-plane calibration"
    n_views = len(laser_images)
    if len(names) != n_views:
        raise ValueError(f"{n_views} laser images but {len(names)} names")
    _check_count(n_views, cfg.laser.min_views, what, "laser.min_views")
    if board_poses is None:
        if board_images is None:
            raise ValueError("give board_images or board_poses")
        bnames = list(board_names) if board_names is not None else list(names)
        if len(board_images) != n_views or len(bnames) != n_views:
            raise ValueError(f"{n_views} laser images but {len(board_images)} board images")
        corners, _ = _detect_all(board_images, bnames, cfg, False, what)
        poses = np.stack([board_pose(c, cfg.board, camera)[0] for c in corners])
    else:
        poses = np.asarray(board_poses, float).reshape(-1, 4, 4)
        if len(poses) != n_views:
            raise ValueError(f"{n_views} laser images but {len(poses)} board poses")
    ls = cfg.laser
    pts, view_of = [], []
    for k, (img, name) in enumerate(zip(laser_images, names, strict=True)):
        _, X = stripe_on_board(img, poses[k], camera, cfg, name)
        pts.append(X)
        view_of.append(np.full(len(X), k))
    P, V = np.concatenate(pts), np.concatenate(view_of)
    _, _, s = fit_plane(P)
    spread = float(s[1] / s[0])
    if spread < ls.min_line_spread:
        raise CalibrationError(
            f"{what}: the stripe points of all {n_views} views lie on one line (spread "
            f"{spread:.4f} < laser.min_line_spread {ls.min_line_spread:g}): the board poses cut "
            "the laser plane in the same line; move the board in depth and tilt it between views")
    keep = np.ones(len(P), bool)
    for _ in range(3):  # fit, drop outliers, refit
        normal, dist, _ = fit_plane(P[keep])
        r = np.abs(P @ normal - dist)
        new = r <= ls.reject_sigma * max(_rms(r[keep]), 1e-6)
        if np.array_equal(new, keep) or new.sum() < len(P) // 2:
            break
        keep = new
    normal, dist, _ = fit_plane(P[keep])
    r = P @ normal - dist
    view_rms = np.array([_rms(r[keep & (V == k)]) for k in range(n_views)])
    view_pts = np.array([int(np.sum(keep & (V == k))) for k in range(n_views)])
    src = np.asarray(source_mm, float) if source_mm is not None else np.zeros(3)
    src = src - (normal @ src - dist) * normal
    plane = LaserPlane(normal=tuple(float(x) for x in normal), distance_mm=float(dist),
                       source_mm=tuple(float(x) for x in src))
    return LaserCalibration(plane, _rms(r[keep]), float(np.abs(r[keep]).max()), view_rms,
                            view_pts, int((~keep).sum()), P[keep], poses, list(names))


# --------------------------------------------------------------------------- hand-eye

def _motion_checks(T_B_F: np.ndarray, min_rot_deg: float, min_axis_deg: float, what: str,
                   unit: str) -> None:
    """Refuse pure translations and rotations about a single axis."""
    R = T_B_F[:, :3, :3]
    # the turns between all pairs of poses, each in the first pose's flange frame
    rv = np.array([Rotation.from_matrix(R[i].T @ R[j]).as_rotvec()
                   for i, j in itertools.combinations(range(len(R)), 2)]).reshape(-1, 3)
    ang = np.degrees(np.linalg.norm(rv, axis=1)) if len(rv) else np.zeros(0)
    if not len(ang) or ang.max() < min_rot_deg:
        top = float(ang.max()) if len(ang) else 0.0
        raise CalibrationError(
            f"{what}: the flange only translates between the {len(R)} {unit} (largest turn "
            f"{top:.2f} deg < {min_rot_deg:g}): the rotation part is not observable; turn the "
            "flange between poses, about at least two different axes")
    axes = rv[ang >= min_rot_deg] / np.radians(ang[ang >= min_rot_deg])[:, None]
    cosang = np.abs(np.clip(axes @ axes.T, -1.0, 1.0))
    spread = float(np.degrees(np.arccos(cosang.min())))
    if spread < min_axis_deg:
        raise CalibrationError(
            f"{what}: every flange turn between the {len(R)} {unit} is about one axis (axes within "
            f"{spread:.2f} deg < {min_axis_deg:g}): the offset along that axis is not "
            "observable; add poses turned about a second axis")


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


_CV_METHODS = {"tsai": "CALIB_HAND_EYE_TSAI", "park": "CALIB_HAND_EYE_PARK",
               "horaud": "CALIB_HAND_EYE_HORAUD", "andreff": "CALIB_HAND_EYE_ANDREFF",
               "daniilidis": "CALIB_HAND_EYE_DANIILIDIS"}
HAND_EYE_METHODS = tuple(_CV_METHODS)


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
    if method not in _CV_METHODS:
        raise ValueError(f"hand-eye method {method!r}: use one of {', '.join(_CV_METHODS)}")
    fn = getattr(cv2, "calibrateHandEye", None)
    if fn is None:
        return _hand_eye_park(T_B_F, T_C_O), "park (numpy; no cv2.calibrateHandEye)"
    R, t = fn(list(T_B_F[:, :3, :3]), list(T_B_F[:, :3, 3:]), list(T_C_O[:, :3, :3]),
              list(T_C_O[:, :3, 3:]), method=getattr(cv2, _CV_METHODS[method]))
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
    _check_count(len(T_B_F), hs.min_views, what, "handeye.min_views", "robot poses")
    _motion_checks(T_B_F, hs.min_rotation_deg, hs.min_axis_spread_deg, what, "robot poses")
    corners, _ = _detect_all(images, names, cfg, False, what)
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
    return HandEyeCalibration(pose, T_B_O, used, refine, _rms(err.ravel()), view_reproj, pos, rot,
                              list(names))


# --------------------------------------------------------------------------- TCP

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
    _check_count(len(T_B_F), ts.min_poses, what, "tcp.min_poses", "poses")
    _motion_checks(T_B_F, ts.min_rotation_deg, ts.min_axis_spread_deg, what, "poses")
    R, p = T_B_F[:, :3, :3], T_B_F[:, :3, 3]
    A = np.concatenate([R, -np.broadcast_to(np.eye(3), R.shape)], axis=2).reshape(-1, 6)
    sol, *_ = np.linalg.lstsq(A, -p.reshape(-1), rcond=None)
    t, P = sol[:3], sol[3:]
    err = np.linalg.norm(np.einsum("nij,j->ni", R, t) + p - P, axis=1)
    tool = Pose(position_mm=tuple(float(v) for v in t),
                quaternion=tuple(float(v) for v in orientation))
    return TcpCalibration(tool, P, _rms(err), err, list(names))


# --------------------------------------------------------------------------- folders

def read_image(path: Path) -> np.ndarray:
    """An image file as uint8 BGR; an unreadable one is a :class:`CalibrationError` naming it."""
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if img is None:
        raise CalibrationError(f"{path}: cannot be read as an image")
    return img


def list_images(folder: Path, what: str) -> list[Path]:
    folder = Path(folder)
    if not folder.is_dir():
        raise CalibrationError(f"{folder}: no such folder ({what})")
    files = sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
    if not files:
        raise CalibrationError(f"{folder}: holds no images ({', '.join(IMAGE_SUFFIXES)})")
    return files


def load_camera_set(folder: Path) -> tuple[list[np.ndarray], list[str]]:
    """Every image in ``folder`` (sorted by name): the checkerboard views."""
    files = list_images(folder, "camera calibration set")
    return [read_image(p) for p in files], [p.name for p in files]


def load_laser_set(folder: Path) -> tuple[list[np.ndarray], list[str], list[np.ndarray],
                                          list[str]]:
    """Pairs ``NAME_board.png`` (checkerboard, laser off) + ``NAME_laser.png`` (stripe).

    Returns:
        ``(laser images, laser names, board images, board names)``, sorted by NAME.
    """
    files = list_images(folder, "laser calibration set")
    by = {p.name: p for p in files}
    stems = sorted({p.stem[:-6] for p in files if p.stem.endswith("_laser")}
                   | {p.stem[:-6] for p in files if p.stem.endswith("_board")})
    if not stems:
        raise CalibrationError(f"{folder}: no NAME_board.png / NAME_laser.png pairs")
    lasers, boards = [], []
    for s in stems:
        pair = []
        for kind in ("laser", "board"):
            hit = [p for p in files if p.stem == f"{s}_{kind}"]
            if not hit:
                other = "board" if kind == "laser" else "laser"
                have = next(n for n in by if n.startswith(f"{s}_{other}"))
                raise CalibrationError(f"{folder / have}: has no {s}_{kind} image beside it "
                                       "(each pose needs NAME_board and NAME_laser)")
            pair.append(hit[0])
        lasers.append(pair[0])
        boards.append(pair[1])
    return ([read_image(p) for p in lasers], [p.name for p in lasers],
            [read_image(p) for p in boards], [p.name for p in boards])


def load_handeye_set(folder: Path) -> tuple[list[np.ndarray], list[str], np.ndarray]:
    """``poses.csv`` (``image,x_mm,...,qz``: flange pose per image) and the images it names."""
    folder = Path(folder)
    if not folder.is_dir():
        raise CalibrationError(f"{folder}: no such folder (hand-eye calibration set)")
    keys, T = read_pose_csv(folder / "poses.csv", "image")
    images = []
    for k in keys:
        if not (folder / k).is_file():
            raise CalibrationError(f"{folder / 'poses.csv'}: image {k} is not in {folder}")
        images.append(read_image(folder / k))
    return images, keys, T


def load_tcp_set(folder: Path) -> tuple[list[str], np.ndarray]:
    """``poses.csv`` (``pose,x_mm,...,qz``): flange poses with the tip on the fixed point."""
    folder = Path(folder)
    if not folder.is_dir():
        raise CalibrationError(f"{folder}: no such folder (TCP calibration set)")
    return read_pose_csv(folder / "poses.csv", "pose")
