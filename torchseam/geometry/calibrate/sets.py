"""What the four calibration procedures share: a set's image files, the board in its images,
and the checks that a set can give a result at all.

A calibration set is a folder of views (:mod:`torchseam.geometry.calib_cli` names the layouts).
Every procedure that sees the checkerboard finds its corners here (:func:`detect_board`, in one
canonical order so that the board frame {O} is the same in every view) and takes the board's pose
from them (:func:`board_pose`); the count, size and motion checks raise the same
:class:`CalibrationError` wording for each procedure, naming the setting that sets the bound.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from torchseam.core.calibration import (
    BoardSpec,
    CalibrationConfig,
    CalibrationError,
    DetectSettings,
)
from torchseam.core.config import CameraConfig
from torchseam.core.errors import FrameError
from torchseam.core.imageio import read_image as read_image_file

__all__ = ["IMAGE_SUFFIXES", "board_pose", "check_count", "check_motion", "check_sizes",
           "detect_all", "detect_board", "list_images", "read_image", "rms", "rt_matrix",
           "to_grey"]

#: the image files a set's folder may hold (case-insensitive suffix)
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")


def rms(x: np.ndarray) -> float:
    """Root mean square of ``x``; NaN for an empty array (a view with no points kept)."""
    return float(np.sqrt(np.mean(np.square(x)))) if len(x) else float("nan")


def read_image(path: Path) -> np.ndarray:
    """An image file as uint8 BGR; an unreadable one is a :class:`CalibrationError` naming it:
    not a regular file (a FIFO, refused without being opened), a header that declares more
    pixels than :func:`~torchseam.core.imageio.max_frame_pixels` (refused before decoding),
    or a file OpenCV cannot decode (:func:`torchseam.core.imageio.read_image`)."""
    try:
        img = read_image_file(path, cv2.IMREAD_COLOR)
    except FrameError as e:
        raise CalibrationError(str(e)) from None
    return img


def list_images(folder: Path, what: str) -> list[Path]:
    folder = Path(folder)
    if not folder.is_dir():
        raise CalibrationError(f"{folder}: no such folder ({what})")
    files = sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
    if not files:
        raise CalibrationError(f"{folder}: holds no images ({', '.join(IMAGE_SUFFIXES)})")
    return files


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
    return rt_matrix(rvec, tvec), rms


def rt_matrix(rvec: np.ndarray, tvec: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(np.asarray(rvec, float).reshape(3, 1))[0]
    T[:3, 3] = np.asarray(tvec, float).ravel()
    return T


def detect_all(images: Sequence[np.ndarray], names: Sequence[str], cfg: CalibrationConfig,
                skip_failed: bool, what: str,
                hint: str = "") -> tuple[list[np.ndarray], list[int], list[str]]:
    """Detect the board in every image; name every failure (or skip them).

    Returns the boards found, their indices in ``images`` and, for each image skipped, its
    reason (``skip_failed``; otherwise a failure raises, ending with ``hint``).
    """
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
                               f"images: " + "; ".join(failed[:3]) + more + hint)
    return found, keep, failed


def check_count(n: int, need: int, what: str, field_name: str, unit: str = "views") -> None:
    if n < need:
        raise CalibrationError(
            f"{what}: {n} usable {unit}, need at least {need} "
            f"(configs/calibration.yaml: {field_name}); add {unit} at other poses")


def check_sizes(images: Sequence[np.ndarray], names: Sequence[str]) -> tuple[int, int]:
    h, w = images[0].shape[:2]
    for img, name in zip(images, names, strict=True):
        if img.shape[:2] != (h, w):
            raise CalibrationError(f"{name}: image is {img.shape[1]}x{img.shape[0]}, the first "
                                   f"({names[0]}) is {w}x{h}; one camera, one size")
    return w, h


def check_motion(T_B_F: np.ndarray, min_rot_deg: float, min_axis_deg: float, what: str,
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
