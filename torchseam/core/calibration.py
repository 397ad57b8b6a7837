"""The calibration settings (``configs/calibration.yaml``).

:class:`CalibrationConfig` holds the checkerboard (:class:`BoardSpec`), each procedure's settings
(:mod:`torchseam.geometry.calibrate` runs them) and the simulated sets' settings
(:mod:`torchseam.sim.board` renders them): one config, read by both, so it lives in core. The
robot pose file of a hand-eye or TCP set (the flange pose ``T_B_F`` per image or touch) is the
project's one pose CSV (:mod:`torchseam.core.poses_csv`) with a label column.

Frames: {B} robot base, {F} flange, {O} board (origin at the first inner corner, x along the
board's ``cols`` corners, y along its ``rows``, z into the board). Units: mm, degrees, pixels.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np

from torchseam.core.config import Pose, config_path, load_config
from torchseam.core.config import config_field as _m
from torchseam.core.errors import TorchseamError


class CalibrationError(TorchseamError):
    """A calibration set cannot give a trustworthy result: the message says which view or file
    and what to change."""


# --------------------------------------------------------------------------- settings

@dataclass(frozen=True)
class BoardSpec:
    """Checkerboard with ``cols`` x ``rows`` inner corners of ``square_mm`` squares.

    The squares span ``[-square, cols * square] x [-square, rows * square]`` in board
    coordinates (mm); square ``(a, b) = floor((x, y) / square)`` is black when ``a + b`` is even,
    so the square between the first four inner corners is black. A white border of
    ``margin_mm`` runs round the squares. ``cols + rows`` must be odd (one corner order).
    """

    cols: int = _m(lo=3)
    rows: int = _m(lo=3)
    square_mm: float = _m(lo=0.0, lo_open=True)
    margin_mm: float = _m(lo=0.0)

    def _check(self) -> None:
        if (self.cols + self.rows) % 2 == 0:
            raise ValueError(f"cols: cols + rows must be odd (got {self.cols} + {self.rows}): "
                             "otherwise the board's corner order is ambiguous under a half turn")

    @property
    def pattern_size(self) -> tuple[int, int]:
        """``(cols, rows)`` as OpenCV's ``patternSize``."""
        return (self.cols, self.rows)

    def object_points(self) -> np.ndarray:
        """(rows * cols, 3) inner corners in {O} (mm), row by row, as OpenCV orders them."""
        j, i = np.mgrid[0:self.rows, 0:self.cols]
        pts = np.stack([i.ravel(), j.ravel(), np.zeros(i.size)], axis=1)
        return pts * self.square_mm

    def outline(self, margin: bool = True) -> tuple[float, float, float, float]:
        """``(x0, y0, x1, y1)`` of the board (with its white border) or of the squares (mm)."""
        s, m = self.square_mm, self.margin_mm if margin else 0.0
        return (-s - m, -s - m, self.cols * s + m, self.rows * s + m)

    def outer_corners(self) -> np.ndarray:
        """(4, 3) corners of the squares' outline in {O}: what must be in view for detection."""
        x0, y0, x1, y1 = self.outline(margin=False)
        return np.array([[x0, y0, 0], [x1, y0, 0], [x1, y1, 0], [x0, y1, 0]], float)

    def centre(self) -> np.ndarray:
        """(3,) centre of the inner-corner grid in {O} (mm)."""
        return np.array([(self.cols - 1) / 2, (self.rows - 1) / 2, 0.0]) * self.square_mm

    def reflectance(self, x: np.ndarray, y: np.ndarray, white: float, black_r: float,
                    background: float) -> np.ndarray:
        """Reflectance at board points ``(x, y)`` (mm, any shape): squares, border, or what
        lies behind the board (``background``)."""
        x0, y0, x1, y1 = self.outline()
        inv = 1.0 / self.square_mm
        a = np.floor(x * inv).astype(np.int32)
        b = np.floor(y * inv).astype(np.int32)
        # 0 background, 1 white (border or square), 2 black square
        idx = ((x >= x0) & (x < x1) & (y >= y0) & (y < y1)).astype(np.int8)
        black = ((a + b) & 1) == 0
        black &= (a >= -1) & (a < self.cols) & (b >= -1) & (b < self.rows)
        idx += black
        return np.array([background, white, black_r], np.float32)[idx]

    def white_cell(self, x: np.ndarray, y: np.ndarray, margin_mm: float) -> np.ndarray:
        """Id of the white area holding each point at least ``margin_mm`` from its edges.

        White squares get ids ``>= 0``, the white border one id of its own; -1 for points on
        black squares, off the board, or within ``margin_mm`` of an edge. Two points with the
        same id >= 0 see the same uniform white between them.
        """
        s, m = self.square_mm, margin_mm
        x0, y0, x1, y1 = self.outline()
        on_board = (x >= x0 + m) & (x < x1 - m) & (y >= y0 + m) & (y < y1 - m)
        sx0, sy0, sx1, sy1 = -s, -s, self.cols * s, self.rows * s
        in_border = on_board & ((x < sx0 - m) | (x >= sx1 + m) | (y < sy0 - m) | (y >= sy1 + m))
        a, b = np.floor(x / s), np.floor(y / s)
        fx, fy = x - a * s, y - b * s
        in_squares = (x >= sx0) & (x < sx1) & (y >= sy0) & (y < sy1)
        inner = (fx >= m) & (fx < s - m) & (fy >= m) & (fy < s - m)
        white_sq = in_squares & inner & ((a + b) % 2 == 1)
        cell = ((b + 1) * (self.cols + 1) + (a + 1)).astype(np.int64)
        border_id = (self.cols + 1) * (self.rows + 1)
        return np.where(white_sq, cell, np.where(in_border, border_id, -1))


@dataclass(frozen=True)
class DetectSettings:
    subpix_half_window_px: int = _m(lo=1)
    subpix_iterations: int = _m(lo=1)
    subpix_epsilon_px: float = _m(lo=0.0, lo_open=True)


@dataclass(frozen=True)
class CameraSettings:
    min_views: int = _m(lo=3)
    radial_terms: int = _m(lo=2, hi=3)
    min_tilt_spread_deg: float = _m(lo=0.0)
    max_focal_std_rel: float = _m(lo=0.0, lo_open=True)


@dataclass(frozen=True)
class LaserSettings:
    min_views: int = _m(lo=2)
    min_peak_grey: float = _m(lo=0.0, lo_open=True)
    half_window_px: int = _m(lo=2)
    edge_margin_mm: float = _m(lo=0.0)
    min_points_per_view: int = _m(lo=2)
    min_line_spread: float = _m(lo=0.0, hi=1.0)
    reject_sigma: float = _m(lo=1.0)


@dataclass(frozen=True)
class HandEyeSettings:
    min_views: int = _m(lo=3)
    min_rotation_deg: float = _m(lo=0.0)
    min_axis_spread_deg: float = _m(lo=0.0, hi=90.0)


@dataclass(frozen=True)
class TcpSettings:
    min_poses: int = _m(lo=3)
    min_rotation_deg: float = _m(lo=0.0)
    min_axis_spread_deg: float = _m(lo=0.0, hi=90.0)


@dataclass(frozen=True)
class RenderSettings:
    """How the simulator draws calibration images (see :mod:`torchseam.sim.board`)."""

    blur_px: float = _m(lo=0.0)
    noise_grey: float = _m(lo=0.0)
    light_grey: float = _m(lo=0.0, hi=255.0)
    vignetting: float = _m(lo=0.0, hi=1.0)
    white: float = _m(lo=0.0, hi=1.0)
    black: float = _m(lo=0.0, hi=1.0)
    background: float = _m(lo=0.0, hi=1.0)
    laser_ambient: float = _m(lo=0.0, hi=1.0)


@dataclass(frozen=True)
class CameraSetSim:
    views: int = _m(lo=1)
    distance_mm: tuple[float, ...] = _m(2, lo=1.0)
    tilt_deg: tuple[float, ...] = _m(2, lo=0.0, hi=70.0)
    spin_deg: float = _m(lo=0.0, hi=180.0)


@dataclass(frozen=True)
class LaserSetSim:
    views: int = _m(lo=1)
    tilt_deg: tuple[float, ...] = _m(2, lo=0.0, hi=70.0)
    spin_deg: float = _m(lo=0.0, hi=180.0)
    stripe_rows: tuple[float, ...] = _m(2, lo=0.0, hi=1.0)
    shift_mm: float = _m(lo=0.0)


@dataclass(frozen=True)
class HandEyeSetSim:
    views: int = _m(lo=1)
    distance_mm: tuple[float, ...] = _m(2, lo=1.0)
    tilt_deg: tuple[float, ...] = _m(2, lo=0.0, hi=70.0)
    spin_deg: float = _m(lo=0.0, hi=180.0)
    board_in_base: Pose = _m()
    robot_noise_mm: float = _m(lo=0.0)
    robot_noise_deg: float = _m(lo=0.0)


@dataclass(frozen=True)
class TcpSetSim:
    poses: int = _m(lo=1)
    tilt_deg: tuple[float, ...] = _m(2, lo=0.0, hi=80.0)
    point_mm: tuple[float, ...] = _m(3)
    touch_noise_mm: float = _m(lo=0.0)
    robot_noise_mm: float = _m(lo=0.0)
    robot_noise_deg: float = _m(lo=0.0)


@dataclass(frozen=True)
class SimulationSettings:
    seed: int = _m(lo=0)
    render: RenderSettings = _m()
    camera: CameraSetSim = _m()
    laser: LaserSetSim = _m()
    handeye: HandEyeSetSim = _m()
    tcp: TcpSetSim = _m()


@dataclass(frozen=True)
class CalibrationConfig:
    """``configs/calibration.yaml``: the board, each procedure's settings, the simulated sets."""

    board: BoardSpec
    detect: DetectSettings
    camera: CameraSettings
    laser: LaserSettings
    handeye: HandEyeSettings
    tcp: TcpSettings
    simulate: SimulationSettings


def load_calibration(path: str | os.PathLike[str] | None = None) -> CalibrationConfig:
    """The calibration settings (default ``configs/calibration.yaml``).

    Raises:
        ConfigError: naming the file and the field, like every config of the project.
    """
    return load_config(CalibrationConfig, path or config_path("calibration.yaml"))
