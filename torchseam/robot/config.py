"""Typed configuration of the robot model and the reachability gate (``configs/robot.yaml``).

Loads through :func:`torchseam.core.config.load_config` (same validation and
``"<file>: <field>: <problem>"`` messages as every other config).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Any

from torchseam.core.config import ConfigError, config_path, from_dict, load_config
from torchseam.core.config import config_field as _f

#: Allowed values of the string fields.
CHOICES: dict[str, tuple[str, ...]] = {
    "axis3_range_applies_to": ("controller", "difference"),
    "ik_method": ("analytic", "numeric"),
}


@dataclass(frozen=True)
class AxesConfig:
    """Controller axis ranges and speeds, axes 1..6 (degrees, deg/s)."""

    min_deg: tuple[float, ...] = _f(6)
    max_deg: tuple[float, ...] = _f(6)
    max_speed_deg_s: tuple[float, ...] = _f(6, lo=0.0, lo_open=True)
    speed_safety_factor: float = _f(lo=0.0, hi=1.0, lo_open=True)

    def _check(self) -> None:
        for i, (lo, hi) in enumerate(zip(self.min_deg, self.max_deg, strict=True)):
            if lo >= hi:
                raise ValueError(f"min_deg: axis {i + 1}: min {lo} must be below max {hi}")


@dataclass(frozen=True)
class SingularityConfig:
    """Refuse poses whose flange Jacobian's smallest singular value is below ``min_sigma``."""

    min_sigma: float = _f(lo=0.0)
    length_mm: float = _f(lo=0.0, lo_open=True)


@dataclass(frozen=True)
class TorchShape:
    """The torch body along the TCP z axis (see ``configs/robot.yaml``): from
    ``tip_exclusion_mm`` behind the TCP back to ``length_mm`` behind it. With a nozzle
    (``nozzle_length_mm`` > 0) the front is the gas nozzle, a cone of radius
    ``nozzle_radius_mm`` at ``tip_exclusion_mm`` widening to ``radius_mm`` at
    ``nozzle_length_mm`` behind the TCP, and the body behind it a cylinder of ``radius_mm``;
    without one, the whole torch is that cylinder."""

    radius_mm: float = _f(lo=0.0)
    length_mm: float = _f(lo=0.0, lo_open=True)
    tip_exclusion_mm: float = _f(lo=0.0)
    nozzle_radius_mm: float = _f(lo=0.0, default=0.0)
    nozzle_length_mm: float = _f(lo=0.0, default=0.0)   # 0: no nozzle (a plain cylinder)

    def _check(self) -> None:
        if self.tip_exclusion_mm >= self.length_mm:
            raise ValueError(f"tip_exclusion_mm: {self.tip_exclusion_mm} must be shorter than "
                             f"length_mm {self.length_mm}")
        if self.nozzle_length_mm:
            if not self.tip_exclusion_mm < self.nozzle_length_mm <= self.length_mm:
                raise ValueError(f"nozzle_length_mm: {self.nozzle_length_mm} must lie between "
                                 f"tip_exclusion_mm {self.tip_exclusion_mm} and length_mm "
                                 f"{self.length_mm}")
            if not 0.0 < self.nozzle_radius_mm <= self.radius_mm:
                raise ValueError(f"nozzle_radius_mm: {self.nozzle_radius_mm} must be above 0 "
                                 f"and at most radius_mm {self.radius_mm} (the nozzle widens "
                                 "towards the body)")

    def pieces(self) -> tuple[tuple[float, float, float, float], ...]:
        """The checked body as pieces ``(d0, d1, r0, r1)``: from ``d0`` to ``d1`` mm behind the
        TCP, the radius growing linearly from ``r0`` to ``r1`` mm."""
        r, d0 = self.radius_mm, self.tip_exclusion_mm
        if not self.nozzle_length_mm:
            return ((d0, self.length_mm, r, r),)
        out = [(d0, self.nozzle_length_mm, self.nozzle_radius_mm, r)]
        if self.nozzle_length_mm < self.length_mm:
            out.append((self.nozzle_length_mm, self.length_mm, r, r))
        return tuple(out)

    def radius_at(self, d_mm: float) -> float:
        """The torch's radius ``d_mm`` behind the TCP (0 in front of the checked body)."""
        for d0, d1, r0, r1 in self.pieces():
            if d0 <= d_mm <= d1:
                return r0 + (r1 - r0) * (d_mm - d0) / (d1 - d0)
        return 0.0


@dataclass(frozen=True)
class ClearanceConfig:
    margin_mm: float = _f(lo=0.0)
    main_pipe_length_mm: float = _f(lo=0.0, lo_open=True)


@dataclass(frozen=True)
class IKConfig:
    position_tol_mm: float = _f(lo=0.0, lo_open=True)
    orientation_tol_deg: float = _f(lo=0.0, lo_open=True)
    restarts: int = _f(lo=1)
    max_iterations: int = _f(lo=1)


@dataclass(frozen=True)
class RobotConfig:
    """The whole ``configs/robot.yaml``.

    Example:
        >>> cfg = load_robot_config()
        >>> cfg.axes.max_deg[4], cfg.axis3_range_applies_to
        (115.0, 'controller')
    """

    axes: AxesConfig
    home_deg: tuple[float, ...] = _f(6)
    singularity: SingularityConfig = _f()
    torch: TorchShape = _f()
    clearance: ClearanceConfig = _f()
    ik: IKConfig = _f()
    axis3_range_applies_to: str = _f(choices=CHOICES["axis3_range_applies_to"])
    ik_method: str = _f(choices=CHOICES["ik_method"])

    def _check(self) -> None:
        lo, hi = self.axes.min_deg, self.axes.max_deg
        bad = [i for i in range(6) if not lo[i] <= self.home_deg[i] <= hi[i]]
        if bad:
            raise ValueError(f"home_deg: axis {bad[0] + 1} ({self.home_deg[bad[0]]}) lies outside "
                             f"its range {lo[bad[0]]}..{hi[bad[0]]}")

    def __post_init__(self) -> None:
        # also for objects made in code (dataclasses.replace): a choice field must be valid
        for name, choices in CHOICES.items():
            if getattr(self, name) not in choices:
                raise ConfigError(f"{name}: expected one of {', '.join(choices)}, "
                                  f"got {getattr(self, name)!r}")


def robot_config_from_dict(data: Any, source: str = "<dict>") -> RobotConfig:
    """Validate a parsed ``robot.yaml`` mapping (raises :class:`ConfigError` naming the field)."""
    return from_dict(RobotConfig, data, source)


def load_robot_config(path: str | os.PathLike[str] | None = None) -> RobotConfig:
    """Load ``configs/robot.yaml`` (or ``path``).

    Raises:
        ConfigError: ``"<file>: <field>: <problem>"`` for a missing file, bad YAML or bad field.
    """
    return load_config(RobotConfig, path if path is not None else config_path("robot.yaml"))
