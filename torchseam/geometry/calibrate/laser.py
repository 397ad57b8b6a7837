"""The laser light plane in {C} from stripe images on the flat board
(:func:`calibrate_laser_plane`).

Needs the calibrated camera. The board pose per view comes from a checkerboard image taken at
the same pose (``solvePnP``) or is given; the stripe centre line is found per column by sub-pixel
grey gravity (:func:`extract_stripe`), kept only on white squares (:func:`stripe_on_board`); the
undistorted rays are cut with the board plane and a plane is fitted by SVD (:func:`fit_plane`)
with outliers dropped. A two-lobed stripe is centred between its lobes by TIPM's rule
(:func:`~torchseam.vision.tipm.two_lobe_centres`): the plane is where TIPM will read the stripe.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch

from torchseam.core.calibration import CalibrationConfig, CalibrationError
from torchseam.core.camera import undistort_points
from torchseam.core.config import CameraConfig, LaserPlane
from torchseam.geometry.calibrate.sets import (
    board_pose,
    check_count,
    detect_all,
    list_images,
    read_image,
    rms,
)
from torchseam.vision.tipm import LobeRule, load_tipm_config, two_lobe_centres

__all__ = ["LaserCalibration", "calibrate_laser_plane", "extract_stripe", "fit_plane",
           "load_laser_set", "stripe_on_board"]


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


def extract_stripe(image: np.ndarray, min_peak: float, half_window: int,
                   lobes: LobeRule) -> np.ndarray:
    """Stripe centre line: one sub-pixel row per column by grey gravity.

    The stripe is the red channel of a BGR image (or the grey image). Per column: the peak row
    of the lightly smoothed column; the floor is the mean of the two pixels just outside the
    window on each side; the centre is the centroid of ``I - floor`` (clipped at 0) over
    ``peak +- half_window`` rows, or the middle between the lobes of a two-lobed stripe
    (``lobes``, TIPM's rule).

    Args:
        image: (H, W, 3) BGR or (H, W) uint8.
        min_peak: the peak must stand this many grey levels above the floor.
        half_window: centroid half window (rows); about 3 sigma of the stripe profile.
        lobes: when the stripe is two-lobed (:func:`~torchseam.vision.tipm.two_lobe_centres`).

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
    mid = two_lobe_centres(win[good], (v0 - hw)[good].astype(float), lobes)
    centre[good] = np.where(np.isfinite(mid), mid, centre[good])
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
                    cfg: CalibrationConfig, name: str, lobes: LobeRule | None = None
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Stripe samples of one laser image that lie on white squares, and their 3D points.

    :func:`extract_stripe`, then each sample's ray (and the rays of its window's ends) cut
    with the board plane; a sample is kept when its whole centroid window lies inside one
    white area, ``laser.edge_margin_mm`` from its edges (black squares and square edges would
    bias the grey gravity).

    Args:
        image: (H, W, 3) BGR stripe image; T_C_O: (4, 4) the board's pose (mm).
        camera: the camera; cfg: settings (board, ``laser``); name: for errors.
        lobes: TIPM's two-lobed stripe rule (default: ``configs/tipm.yaml``'s).

    Returns:
        ``(uv (M, 2) px, X (M, 3) points in {C}, mm)``.

    Raises:
        CalibrationError: no stripe, or too few samples on white squares (naming ``name``).
    """
    ls = cfg.laser
    lobes = load_tipm_config().lobes if lobes is None else lobes
    uv = extract_stripe(image, ls.min_peak_grey, ls.half_window_px, lobes)
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
                          source_mm: Sequence[float] | None = None,
                          lobes: LobeRule | None = None) -> LaserCalibration:
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
        lobes: the two-lobed stripe rule of the TIPM that will read the stripe (default:
            ``configs/tipm.yaml``'s), so that the plane and the tracked points agree.

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
    check_count(n_views, cfg.laser.min_views, what, "laser.min_views")
    if board_poses is None:
        if board_images is None:
            raise ValueError("give board_images or board_poses")
        bnames = list(board_names) if board_names is not None else list(names)
        if len(board_images) != n_views or len(bnames) != n_views:
            raise ValueError(f"{n_views} laser images but {len(board_images)} board images")
        corners, _, _ = detect_all(board_images, bnames, cfg, False, what)
        poses = np.stack([board_pose(c, cfg.board, camera)[0] for c in corners])
    else:
        poses = np.asarray(board_poses, float).reshape(-1, 4, 4)
        if len(poses) != n_views:
            raise ValueError(f"{n_views} laser images but {len(poses)} board poses")
    ls = cfg.laser
    lobes = load_tipm_config().lobes if lobes is None else lobes
    pts, view_of = [], []
    for k, (img, name) in enumerate(zip(laser_images, names, strict=True)):
        _, X = stripe_on_board(img, poses[k], camera, cfg, name, lobes)
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
        new = r <= ls.reject_sigma * max(rms(r[keep]), 1e-6)
        if np.array_equal(new, keep) or new.sum() < len(P) // 2:
            break
        keep = new
    normal, dist, _ = fit_plane(P[keep])
    r = P @ normal - dist
    view_rms = np.array([rms(r[keep & (V == k)]) for k in range(n_views)])
    view_pts = np.array([int(np.sum(keep & (V == k))) for k in range(n_views)])
    src = np.asarray(source_mm, float) if source_mm is not None else np.zeros(3)
    src = src - (normal @ src - dist) * normal
    plane = LaserPlane(normal=tuple(float(x) for x in normal), distance_mm=float(dist),
                       source_mm=tuple(float(x) for x in src))
    return LaserCalibration(plane, rms(r[keep]), float(np.abs(r[keep]).max()), view_rms,
                            view_pts, int((~keep).sum()), P[keep], poses, list(names))


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
