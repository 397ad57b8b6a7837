"""Simulated calibration sets: checkerboard and laser-stripe images with their ground truth.

Images are rendered with the cell's own camera model: every pixel centre is undistorted
(OpenCV's model, iterated to float precision), its ray cut with the board plane, and the
board's reflectance box-filtered over the pixel's footprint on the board (square edges as
ramps as wide as the footprint: anti-aliased and unbiased at the corners); then lens blur, a
lamp with vignetting, and read noise. Laser images draw the cut of
the cell's laser plane with the board exactly as the seam sensor draws its stripe
(:meth:`LaserSensor.stripe_layer`: Gaussian cross-section, speckle), scaled by the board's
reflectance under it, in a dimmed lamp.

Four sets, one per procedure of :mod:`torchseam.geometry.calibrate`:

* camera: the board at varied poses in front of the camera;
* laser: per pose a checkerboard image (laser off) and a stripe image (laser on);
* hand-eye: a board fixed in the robot base seen from recorded flange poses
  ``T_B_F`` (camera at ``T_B_F @ hand_eye``), with robot pose noise on the record;
* TCP: flange poses that touch one fixed point with the torch tip, with touch and robot noise.

Everything is deterministic for a seed; every set carries its truth.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from torchseam.core.calibration import BoardSpec, CalibrationConfig, RenderSettings
from torchseam.core.config import CameraConfig, CellConfig, LaserPlane, Pose, to_dict
from torchseam.core.poses_csv import write_pose_csv
from torchseam.core.transforms import invert, matrix_to_quat, rotation_about
from torchseam.sim.noise import STRIPE_BGR
from torchseam.sim.sensor import LaserSensor, StripeView

#: Kinds of calibration set :func:`write_set` writes.
SET_KINDS = ("camera", "laser", "handeye", "tcp")

_FIT_MARGIN_PX = 8.0     # the squares' outline must lie this far inside the image
_STRIPE_STEP_MM = 0.02   # spacing of the 3D samples along the stripe


class BoardRenderer:
    """Renders a checkerboard seen by ``camera`` at any pose ``T_C_O``.

    The undistorted ray of every pixel is computed once, so each image costs a plane cut and
    an anti-aliased look-up over the board's image box.

    Example:
        >>> from torchseam.core.config import load_cell
        >>> from torchseam.core.calibration import load_calibration
        >>> cfg = load_calibration()
        >>> r = BoardRenderer(load_cell().camera, cfg.board, cfg.simulate.render)
        >>> T = np.eye(4); T[:3, 3] = [-12.0, -7.5, 130.0]
        >>> r.board_image(T, np.random.default_rng(0)).shape
        (492, 656, 3)
    """

    def __init__(self, camera: CameraConfig, board: BoardSpec, render: RenderSettings) -> None:
        self.camera, self.board, self.render = camera, board, render
        w, h = camera.width, camera.height
        self.size = (w, h)
        # Undistorted ray (x/z, y/z) of every pixel centre, exact (OpenCV iterated to 1e-15).
        vv, uu = np.mgrid[0:h, 0:w].astype(np.float64)
        pts = np.stack([uu, vv], -1).reshape(-1, 1, 2)
        crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 40, 1e-15)
        xy = cv2.undistortPoints(pts, camera.K, np.asarray(camera.dist, float), criteria=crit)
        xy = xy.reshape(h, w, 2)
        self._x, self._y = xy[..., 0].copy(), xy[..., 1].copy()
        r2 = ((uu - w / 2) ** 2 + (vv - h / 2) ** 2) / ((w / 2) ** 2 + (h / 2) ** 2)
        self._lamp = (render.light_grey * (1.0 - render.vignetting * r2)).astype(np.float32)

    def reflectance(self, T_C_O: np.ndarray) -> np.ndarray:
        """(H, W) float32 reflectance per pixel of the board at pose ``T_C_O``, box-filtered
        over each pixel's footprint on the board.

        Each pixel centre is cut with the board plane; the pixel's footprint there spans
        ``+-h`` along the board axes (``h`` from the local Jacobian). Every square edge is a
        linear ramp over ``+-h``, and the checker is ``0.5 + 0.5 Sx Sy`` with ``S`` the ramped
        square wave: point-symmetric about each inner corner, so corners are unbiased.
        """
        rs, bd = self.render, self.board
        w, h = self.size
        out = np.full((h, w), rs.background, np.float32)
        box = self._board_box(T_C_O)
        if box is None:
            return out
        u0, v0, u1, v1 = box
        x, y = self._x[v0:v1, u0:u1], self._y[v0:v1, u0:u1]
        R, c = T_C_O[:3, :3], T_C_O[:3, 3]
        n = R[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            t = float(n @ c) / (n[0] * x + n[1] * y + n[2])
        bx = t * (R[0, 0] * x + R[1, 0] * y + R[2, 0]) - float(R[:, 0] @ c)
        by = t * (R[0, 1] * x + R[1, 1] * y + R[2, 1]) - float(R[:, 1] @ c)
        front = t > 0
        bx, by = np.where(front, bx, 1e6), np.where(front, by, 1e6)
        hx = 0.5 * (np.abs(np.gradient(bx, axis=1)) + np.abs(np.gradient(bx, axis=0)))
        hy = 0.5 * (np.abs(np.gradient(by, axis=1)) + np.abs(np.gradient(by, axis=0)))
        hx, hy = np.maximum(hx, 1e-6), np.maximum(hy, 1e-6)
        s = bd.square_mm

        def wave(q: np.ndarray, hq: np.ndarray) -> np.ndarray:
            k = q / s
            dist = np.abs(k - np.round(k)) * s  # to the nearest grid line (mm)
            sign = 1.0 - 2.0 * (np.floor(k) % 2)
            return sign * np.clip(dist / hq, 0.0, 1.0)

        def ramp(d: np.ndarray, hq: np.ndarray) -> np.ndarray:
            return np.clip(0.5 + d / (2 * hq), 0.0, 1.0)

        black = 0.5 + 0.5 * wave(bx, hx) * wave(by, hy)
        black *= (ramp(bx + s, hx) * ramp(bd.cols * s - bx, hx)
                  * ramp(by + s, hy) * ramp(bd.rows * s - by, hy))
        x0, y0, x1, y1 = bd.outline()
        on = ramp(bx - x0, hx) * ramp(x1 - bx, hx) * ramp(by - y0, hy) * ramp(y1 - by, hy)
        refl = rs.background + on * (rs.white - rs.background) + black * (rs.black - rs.white)
        out[v0:v1, u0:u1] = np.where(np.isfinite(refl), refl, rs.background)
        return out

    def _board_box(self, T_C_O: np.ndarray) -> tuple[int, int, int, int] | None:
        """Pixel box ``(u0, v0, u1, v1)`` (end exclusive) holding the board's image."""
        x0, y0, x1, y1 = self.board.outline()
        e = np.linspace(0.0, 1.0, 33)
        xs = np.concatenate([x0 + (x1 - x0) * e, np.full(33, x1), x1 - (x1 - x0) * e,
                             np.full(33, x0)])
        ys = np.concatenate([np.full(33, y0), y0 + (y1 - y0) * e, np.full(33, y1),
                             y1 - (y1 - y0) * e])
        P = np.stack([xs, ys, np.zeros_like(xs)], 1) @ T_C_O[:3, :3].T + T_C_O[:3, 3]
        if np.any(P[:, 2] <= 1.0):  # the board reaches behind the camera: render it all
            return 0, 0, *self.size
        uv, _ = cv2.projectPoints(P, np.zeros(3), np.zeros(3), self.camera.K,
                                  np.asarray(self.camera.dist, float))
        uv = uv.reshape(-1, 2)
        w, h = self.size
        u0, v0 = np.clip(np.floor(uv.min(axis=0)) - 3, 0, [w, h]).astype(int)
        u1, v1 = np.clip(np.ceil(uv.max(axis=0)) + 4, 0, [w, h]).astype(int)
        if u1 <= u0 or v1 <= v0:
            return None
        return int(u0), int(v0), int(u1), int(v1)

    def _finish(self, img: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        rs = self.render
        if rs.blur_px > 0:
            img = cv2.GaussianBlur(img, (0, 0), rs.blur_px)
        img = img + rs.noise_grey * rng.standard_normal(img.shape).astype(np.float32)
        return np.clip(np.rint(img), 0, 255).astype(np.uint8)

    def board_image(self, T_C_O: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """(H, W, 3) uint8 BGR image of the board lit by the calibration lamp."""
        grey = self.reflectance(T_C_O) * self._lamp
        return self._finish(cv2.merge([grey, grey, grey]), rng)

    def laser_image(self, T_C_O: np.ndarray, sensor: LaserSensor, rng: np.random.Generator
                    ) -> np.ndarray:
        """(H, W, 3) uint8 BGR image of the laser stripe on the board, lamp dimmed.

        The stripe is the cut of ``sensor``'s laser plane with the board, drawn by
        :meth:`LaserSensor.stripe_layer` with incidence brightness, times the reflectance
        under it relative to white.
        """
        rs = self.render
        refl = self.reflectance(T_C_O)
        stripe = sensor.stripe_layer(self.stripe_view(T_C_O, sensor), rng)
        stripe = stripe * (refl / rs.white)
        ambient = rs.laser_ambient * refl * self._lamp
        img = ambient[..., None] + stripe[..., None] * STRIPE_BGR[None, None, :]
        return self._finish(img.astype(np.float32), rng)

    def stripe_points(self, T_C_O: np.ndarray, plane: LaserPlane) -> np.ndarray:
        """(M, 3) points of the laser plane's cut with the board (with border), in {C} (mm)."""
        nL, dL = np.asarray(plane.normal), plane.distance_mm
        R, c = T_C_O[:3, :3], T_C_O[:3, 3]
        nB = R[:, 2]
        dB = float(nB @ c)
        u = np.cross(nL, nB)
        if np.linalg.norm(u) < 1e-9:
            return np.zeros((0, 3))
        u /= np.linalg.norm(u)
        X0 = np.linalg.lstsq(np.stack([nL, nB]), np.array([dL, dB]), rcond=None)[0]
        # the board-frame line X0_O + s u_O clipped to the board's outline (slab method)
        p, q = R.T @ (X0 - c), R.T @ u
        x0, y0, x1, y1 = self.board.outline()
        lo, hi = -np.inf, np.inf
        for a, b, pa, qa in ((x0, x1, p[0], q[0]), (y0, y1, p[1], q[1])):
            if abs(qa) < 1e-12:
                if not a <= pa <= b:
                    return np.zeros((0, 3))
                continue
            s0, s1 = sorted(((a - pa) / qa, (b - pa) / qa))
            lo, hi = max(lo, s0), min(hi, s1)
        if hi <= lo:
            return np.zeros((0, 3))
        s = np.arange(lo + 1e-6, hi, _STRIPE_STEP_MM)
        return X0 + s[:, None] * u

    def stripe_view(self, T_C_O: np.ndarray, sensor: LaserSensor) -> StripeView:
        """The stripe on the board as a :class:`StripeView` for the sensor's renderer."""
        X = self.stripe_points(T_C_O, sensor.cell.laser_plane)
        if len(X) < 2:
            z2, z3 = np.zeros((0, 2)), np.zeros(3)
            return StripeView(z2, np.zeros(0), np.zeros(0, int), np.zeros(2), z3,
                              np.full((2, 3), np.nan), np.full((2, 2), np.nan), False)
        uv = sensor.project(X)
        ray = X - sensor.src_C
        inc = np.abs(ray @ T_C_O[:3, 2]) / np.linalg.norm(ray, axis=1)
        mid = len(X) // 2
        return StripeView(uv, 0.35 + 0.65 * inc, np.ones(len(X), int), uv[mid], X[mid],
                          np.full((2, 3), np.nan), np.full((2, 2), np.nan), True)


# --------------------------------------------------------------------------- poses

def _pose_facing(R_tilt: np.ndarray, spin_rad: float, board: BoardSpec, centre_C: np.ndarray
                 ) -> np.ndarray:
    """T_C_O with the board turned by ``R_tilt @ Rz(spin)`` and its grid centre at centre_C."""
    R = R_tilt @ rotation_about(np.array([0.0, 0.0, 1.0]), spin_rad)
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = centre_C - R @ board.centre()
    return T


def _random_tilt(rng: np.random.Generator, tilt_deg: tuple[float, ...]) -> np.ndarray:
    phi = rng.uniform(0.0, 2 * np.pi)
    theta = np.radians(rng.uniform(tilt_deg[0], tilt_deg[1]))
    return rotation_about(np.array([np.cos(phi), np.sin(phi), 0.0]), theta)


def board_fits(T_C_O: np.ndarray, camera: CameraConfig, board: BoardSpec,
               margin_px: float = _FIT_MARGIN_PX) -> bool:
    """Whether the board's squares lie in front of the camera and inside the image."""
    P = board.outer_corners() @ T_C_O[:3, :3].T + T_C_O[:3, 3]
    if np.any(P[:, 2] < 10.0):
        return False
    uv, _ = cv2.projectPoints(P, np.zeros(3), np.zeros(3), camera.K, np.asarray(camera.dist))
    uv = uv.reshape(-1, 2)
    return bool(np.all((uv >= margin_px) & (uv <= [camera.width - 1 - margin_px,
                                                     camera.height - 1 - margin_px])))


def sample_board_poses(rng: np.random.Generator, n: int, camera: CameraConfig, board: BoardSpec,
                       distance_mm: tuple[float, ...], tilt_deg: tuple[float, ...],
                       spin_deg: float) -> np.ndarray:
    """(n, 4, 4) board poses T_C_O in view: random depth, tilt about a random in-plane axis,
    spin about the normal, position anywhere the whole board fits (rejection sampling)."""
    out: list[np.ndarray] = []
    for _ in range(2000 * n):
        if len(out) == n:
            break
        z = rng.uniform(distance_mm[0], distance_mm[1])
        u, v = rng.uniform(0, camera.width), rng.uniform(0, camera.height)
        centre = z * np.array([(u - camera.cx) / camera.fx, (v - camera.cy) / camera.fy, 1.0])
        T = _pose_facing(_random_tilt(rng, tilt_deg), np.radians(rng.uniform(-spin_deg, spin_deg)),
                         board, centre)
        if board_fits(T, camera, board):
            out.append(T)
    if len(out) < n:
        raise ValueError(f"cannot place the {board.cols}x{board.rows} board in view at "
                         f"{distance_mm} mm; use a smaller board or a larger distance")
    return np.stack(out)


def sample_laser_poses(rng: np.random.Generator, n: int, cell: CellConfig, board: BoardSpec,
                       stripe_rows: tuple[float, ...], tilt_deg: tuple[float, ...],
                       spin_deg: float, shift_mm: float) -> np.ndarray:
    """(n, 4, 4) board poses whose squares are in view and cut by the laser plane: the
    board's centre lies on the plane (where a chosen image row sees it) moved by up to
    ``shift_mm`` in the board; the laser source lies on the board's lit side."""
    cam, lp = cell.camera, cell.laser_plane
    nL, dL, src = np.asarray(lp.normal), lp.distance_mm, np.asarray(lp.source_mm)
    out: list[np.ndarray] = []
    for _ in range(2000 * n):
        if len(out) == n:
            break
        u = rng.uniform(0.35, 0.65) * cam.width
        v = rng.uniform(stripe_rows[0], stripe_rows[1]) * cam.height
        ray = np.array([(u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy, 1.0])
        on_plane = ray * dL / (nL @ ray)
        T = _pose_facing(_random_tilt(rng, tilt_deg), np.radians(rng.uniform(-spin_deg, spin_deg)),
                         board, on_plane)
        T[:3, 3] += T[:3, :3] @ np.array([*rng.uniform(-shift_mm, shift_mm, 2), 0.0])
        lit = T[:3, 2] @ (src - T[:3, 3]) < 0  # source on the camera's side of the board
        if lit and board_fits(T, cam, board):
            out.append(T)
    if len(out) < n:
        raise ValueError("cannot place the board in view across the laser plane")
    return np.stack(out)


def _perturb(rng: np.random.Generator, T: np.ndarray, sigma_mm: float, sigma_deg: float
             ) -> np.ndarray:
    """A recorded robot pose: the true one with position and orientation noise."""
    out = T.copy()
    out[:3, 3] += rng.normal(0.0, sigma_mm, 3)
    if sigma_deg > 0:
        out[:3, :3] = cv2.Rodrigues(np.radians(rng.normal(0.0, sigma_deg, 3)))[0] @ T[:3, :3]
    return out


# --------------------------------------------------------------------------- sets

@dataclass
class CameraSet:
    """Checkerboard views with truth: the camera that took them and each board pose."""

    images: list[np.ndarray]
    names: list[str]
    T_C_O: np.ndarray       # (N, 4, 4) board poses in the camera (mm)
    camera: CameraConfig


@dataclass
class LaserSet:
    """Per pose a checkerboard image (laser off) and a stripe image (laser on), with truth."""

    board_images: list[np.ndarray]
    board_names: list[str]
    laser_images: list[np.ndarray]
    laser_names: list[str]
    T_C_O: np.ndarray       # (N, 4, 4)
    plane: LaserPlane


@dataclass
class HandEyeSet:
    """Board images from recorded robot poses, with the truth behind them."""

    images: list[np.ndarray]
    names: list[str]
    T_B_F: np.ndarray       # (N, 4, 4) recorded flange poses (with robot noise)
    T_B_F_true: np.ndarray  # (N, 4, 4) where the flange really was
    T_B_O: np.ndarray       # (4, 4) the board in the base
    hand_eye: Pose


@dataclass
class TcpSet:
    """Recorded flange poses touching one point with the torch tip, with truth."""

    names: list[str]
    T_B_F: np.ndarray       # (N, 4, 4) recorded
    T_B_F_true: np.ndarray
    point_B: np.ndarray     # (3,) the touched point
    tool: Pose


def _rng(cfg: CalibrationConfig, seed: int | None, salt: int) -> np.random.Generator:
    return np.random.default_rng([cfg.simulate.seed if seed is None else seed, salt])


def simulate_camera_set(cell: CellConfig, cfg: CalibrationConfig, seed: int | None = None,
                        views: int | None = None) -> CameraSet:
    """Checkerboard images at ``simulate.camera`` poses (``views`` overrides the count)."""
    rng = _rng(cfg, seed, 1)
    sc = cfg.simulate.camera
    n = sc.views if views is None else views
    T = sample_board_poses(rng, n, cell.camera, cfg.board, sc.distance_mm, sc.tilt_deg,
                           sc.spin_deg)
    r = BoardRenderer(cell.camera, cfg.board, cfg.simulate.render)
    return CameraSet([r.board_image(t, rng) for t in T], [f"{k:02d}.png" for k in range(n)], T,
                     cell.camera)


def simulate_laser_set(cell: CellConfig, cfg: CalibrationConfig, seed: int | None = None,
                       views: int | None = None) -> LaserSet:
    """Board + stripe image pairs at ``simulate.laser`` poses across the cell's laser plane."""
    rng = _rng(cfg, seed, 2)
    sl = cfg.simulate.laser
    n = sl.views if views is None else views
    T = sample_laser_poses(rng, n, cell, cfg.board, sl.stripe_rows, sl.tilt_deg, sl.spin_deg,
                           sl.shift_mm)
    r = BoardRenderer(cell.camera, cfg.board, cfg.simulate.render)
    sensor = LaserSensor(cell)
    boards = [r.board_image(t, rng) for t in T]
    lasers = [r.laser_image(t, sensor, rng) for t in T]
    return LaserSet(boards, [f"{k:02d}_board.png" for k in range(n)], lasers,
                    [f"{k:02d}_laser.png" for k in range(n)], T, cell.laser_plane)


def simulate_handeye_set(cell: CellConfig, cfg: CalibrationConfig, seed: int | None = None,
                         views: int | None = None) -> HandEyeSet:
    """A board fixed in the base, seen from ``simulate.handeye`` flange poses.

    Camera poses are drawn around the board; the flange is ``T_B_C @ inv(hand_eye)``; the
    recorded flange poses carry ``robot_noise_mm`` / ``robot_noise_deg``.
    """
    rng = _rng(cfg, seed, 3)
    sh = cfg.simulate.handeye
    n = sh.views if views is None else views
    T_C_O = sample_board_poses(rng, n, cell.camera, cfg.board, sh.distance_mm, sh.tilt_deg,
                               sh.spin_deg)
    T_B_O = sh.board_in_base.matrix()
    X = cell.hand_eye.matrix()
    T_B_F = T_B_O @ invert(T_C_O) @ invert(X)
    rec = np.stack([_perturb(rng, T, sh.robot_noise_mm, sh.robot_noise_deg) for T in T_B_F])
    r = BoardRenderer(cell.camera, cfg.board, cfg.simulate.render)
    return HandEyeSet([r.board_image(t, rng) for t in T_C_O], [f"{k:02d}.png" for k in range(n)],
                      rec, T_B_F, T_B_O, cell.hand_eye)


def simulate_tcp_set(cell: CellConfig, cfg: CalibrationConfig, seed: int | None = None,
                     poses: int | None = None) -> TcpSet:
    """Flange poses with the torch tip on ``simulate.tcp.point_mm``, tilted 15-35 degrees
    about random horizontal axes and spun about the torch, with touch and robot noise."""
    rng = _rng(cfg, seed, 4)
    st = cfg.simulate.tcp
    n = st.poses if poses is None else poses
    P = np.asarray(st.point_mm)
    T_F_W = cell.tool.matrix()
    down = np.diag([1.0, -1.0, -1.0])  # torch z pointing down
    true = []
    for _ in range(n):
        T_B_W = np.eye(4)
        T_B_W[:3, :3] = (_random_tilt(rng, st.tilt_deg) @ down
                         @ rotation_about(np.array([0.0, 0.0, 1.0]), rng.uniform(-np.pi, np.pi)))
        T_B_W[:3, 3] = P + rng.normal(0.0, st.touch_noise_mm, 3)
        true.append(T_B_W @ invert(T_F_W))
    true_arr = np.stack(true)
    rec = np.stack([_perturb(rng, T, st.robot_noise_mm, st.robot_noise_deg) for T in true_arr])
    return TcpSet([f"p{k:02d}" for k in range(n)], rec, true_arr, P, cell.tool)


# --------------------------------------------------------------------------- writing

def _pose_json(T: np.ndarray) -> dict[str, list[float]]:
    return {"position_mm": [round(float(x), 6) for x in T[:3, 3]],
            "quaternion": [round(float(x), 9) for x in matrix_to_quat(T[:3, :3])]}


def write_set(kind: str, out: str | os.PathLike[str], cell: CellConfig, cfg: CalibrationConfig,
              seed: int | None = None, views: int | None = None, overwrite: bool = False
              ) -> dict[str, Any]:
    """Simulate a calibration set of ``kind`` and write it in the layout ``torchseam
    calibrate KIND DIR`` reads, with ``truth.json`` (the true values, board poses).

    Layouts: camera ``NN.png``; laser ``NN_board.png`` + ``NN_laser.png``; handeye
    ``NN.png`` + ``poses.csv`` (``image,x,y,z,q1,q2,q3,q4``: the recorded flange pose in the
    base per image); tcp ``poses.csv`` (``pose,x,y,z,q1,q2,q3,q4``). The pose files are the
    project's pose CSV (:mod:`torchseam.core.poses_csv`), as a user writes them for a real set.

    Returns:
        The truth written to ``truth.json``.
    """
    if kind not in SET_KINDS:
        raise ValueError(f"calibration set kind {kind!r}: use one of {', '.join(SET_KINDS)}")
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise FileExistsError(f"{out}: exists and is not a folder")
    out.mkdir(parents=True, exist_ok=True)
    old = [p for p in out.iterdir() if p.suffix in (".png", ".csv", ".json")]
    if old and not overwrite:
        raise FileExistsError(f"{out}: already holds {len(old)} files (use --overwrite)")
    for p in old:
        p.unlink()
    truth: dict[str, Any] = {"kind": kind, "seed": cfg.simulate.seed if seed is None else seed}

    def save(name: str, img: np.ndarray) -> None:
        cv2.imwrite(str(out / name), img, [cv2.IMWRITE_PNG_COMPRESSION, 3])

    if kind == "camera":
        cam = simulate_camera_set(cell, cfg, seed, views)
        for name, img in zip(cam.names, cam.images, strict=True):
            save(name, img)
        truth["camera"] = to_dict(cam.camera)
        truth["board_poses"] = {n: _pose_json(T) for n, T in zip(cam.names, cam.T_C_O, strict=True)}
    elif kind == "laser":
        las = simulate_laser_set(cell, cfg, seed, views)
        for name, img in zip(las.board_names + las.laser_names, las.board_images + las.laser_images,
                             strict=True):
            save(name, img)
        truth["laser_plane"] = to_dict(las.plane)
        truth["camera"] = to_dict(cell.camera)
        truth["board_poses"] = {n: _pose_json(T) for n, T in zip(las.laser_names, las.T_C_O,
                                                                 strict=True)}
    elif kind == "handeye":
        he = simulate_handeye_set(cell, cfg, seed, views)
        for name, img in zip(he.names, he.images, strict=True):
            save(name, img)
        _write_flange_poses(out / "poses.csv", "image", he.names, he.T_B_F)
        truth["hand_eye"] = to_dict(he.hand_eye)
        truth["board_in_base"] = _pose_json(he.T_B_O)
        truth["camera"] = to_dict(cell.camera)
        truth["flange_true"] = {n: _pose_json(T) for n, T in zip(he.names, he.T_B_F_true,
                                                                 strict=True)}
    else:
        tcp = simulate_tcp_set(cell, cfg, seed, views)
        _write_flange_poses(out / "poses.csv", "pose", tcp.names, tcp.T_B_F)
        truth["tool"] = to_dict(tcp.tool)
        truth["point_mm"] = [float(x) for x in tcp.point_B]
    (out / "truth.json").write_text(json.dumps(truth, indent=1))
    return truth


def _write_flange_poses(path: Path, label: str, names: list[str], T_B_F: np.ndarray) -> None:
    """A set's ``poses.csv``: per view its name and the recorded flange pose in the base."""
    T = np.asarray(T_B_F)
    write_pose_csv(path, T[:, :3, 3], matrix_to_quat(T[:, :3, :3]), label=label, labels=names)
