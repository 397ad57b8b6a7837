"""Typed configuration of the EGM link and the simulated controller (``configs/egm.yaml``).

Loads through :func:`torchseam.core.config.load_config` (same checks and
``<file>: <field>: <problem>`` messages as every other config).
"""

from __future__ import annotations

import ipaddress
import os
from dataclasses import dataclass
from typing import Any

from torchseam.core.config import config_field as _f
from torchseam.core.config import config_path, from_dict, load_config

#: EGM modes: position guidance (``EgmSensor``) or path correction (``EgmSensorPathCorr``).
MODES = ("pose", "pathcorr")


@dataclass(frozen=True)
class EgmNetwork:
    """Where the sensor listens and whom it accepts datagrams from."""

    host: str = _f(ip=True)
    port: int = _f(lo=0, hi=65535)
    controller_host: str = _f(ip=True)
    controller_port: int = _f(lo=0, hi=65535)  # 0: lock onto the first valid sender's port

    @property
    def is_loopback(self) -> bool:
        return ipaddress.ip_address(self.host).is_loopback


@dataclass(frozen=True)
class EgmLinkConfig:
    """Datagram handling of the sensor side."""

    max_datagram_bytes: int = _f(lo=64, hi=65507)
    late_reply_ms: float = _f(lo=0.0, lo_open=True)
    reorder_window: int = _f(lo=1)
    # the sequence policy of issue 25 (torchseam/robot/egm/policy.py, SequenceTracker)
    max_gap: int = _f(lo=1)                 # seqnos ahead of the newest taken without time evidence
    min_period_ms: float = _f(lo=0.0, lo_open=True)  # the controller's shortest cycle
    session_confirm: int = _f(lo=2)         # consistent datagrams a restart / far jump needs
    session_silence_ms: float = _f(lo=0.0)  # the session silent this long before one is believed
    latency_samples: int = _f(lo=1)
    rt_priority: int = _f(lo=0, hi=99)  # SCHED_FIFO priority of the link thread; 0: normal
    # the serving process's GIL switch interval while the link serves (0: Python's own)
    switch_interval_ms: float = _f(lo=0.0)


@dataclass(frozen=True)
class EgmSafety:
    """What the link refuses to send (part 5 of issue 6)."""

    max_step_mm: float = _f(lo=0.0, lo_open=True)
    max_step_deg: float = _f(lo=0.0, lo_open=True)
    max_lead_mm: float = _f(lo=0.0, lo_open=True)
    max_correction_mm: float = _f(lo=0.0, lo_open=True)
    max_age_ms: float = _f(lo=0.0, lo_open=True)
    watchdog_ms: float = _f(lo=0.0, lo_open=True)


@dataclass(frozen=True)
class SimControllerConfig:
    """The simulated IRC5: cycle rate, start joints, speed limits and the programmed path."""

    rate_hz: float = _f(lo=1.0, hi=1000.0)
    home_joints_deg: tuple[float, ...] = _f(6)
    joint_speed_deg_s: tuple[float, ...] = _f(6, lo=0.0, lo_open=True)
    tcp_speed_mm_s: float = _f(lo=0.0, lo_open=True)
    tcp_rot_speed_deg_s: float = _f(lo=0.0, lo_open=True)
    path_direction: tuple[float, ...] = _f(3, unit=True)
    path_length_mm: float = _f(lo=0.0)
    path_speed_mm_s: float = _f(lo=0.0, lo_open=True)
    correction_speed_mm_s: float = _f(lo=0.0, lo_open=True)
    rt_priority: int = _f(lo=0, hi=99)  # SCHED_FIFO priority of the cycle thread; 0: normal

    @property
    def period_s(self) -> float:
        return 1.0 / self.rate_hz


@dataclass(frozen=True)
class EgmConfig:
    """The whole ``configs/egm.yaml``."""

    network: EgmNetwork
    mode: str = _f(choices=MODES)
    link: EgmLinkConfig = _f()
    safety: EgmSafety = _f()
    sim_controller: SimControllerConfig = _f()


def egm_config_from_dict(data: Any, source: str = "<dict>") -> EgmConfig:
    """Validate a parsed ``egm.yaml`` mapping (raises :class:`ConfigError` naming the field)."""
    return from_dict(EgmConfig, data, source)


def load_egm_config(path: str | os.PathLike[str] | None = None) -> EgmConfig:
    """Load ``configs/egm.yaml`` (or ``path``).

    Raises:
        ConfigError: ``"<file>: <field>: <problem>"``.
    """
    return load_config(EgmConfig, path if path is not None else config_path("egm.yaml"))
