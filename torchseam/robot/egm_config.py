"""Typed configuration of the EGM link and the simulated controller (``configs/egm.yaml``).

The numeric sections load with core's :func:`~torchseam.core.config.from_dict` (same checks and
messages as every other config). Core's loader reads numbers only, so the few text fields
(addresses and the mode) are checked here, with errors in the same ``<file>: <field>: <problem>``
form.
"""

from __future__ import annotations

import ipaddress
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from torchseam.core.config import CONFIG_DIR, ConfigError, _f, from_dict

#: EGM modes: position guidance (``EgmSensor``) or path correction (``EgmSensorPathCorr``).
MODES = ("pose", "pathcorr")


@dataclass(frozen=True)
class EgmNetwork:
    """Where the sensor listens and whom it accepts datagrams from."""

    host: str = "127.0.0.1"
    port: int = 6510
    controller_host: str = "127.0.0.1"
    controller_port: int = 6511  # 0: lock onto the first valid sender's port

    @property
    def is_loopback(self) -> bool:
        return ipaddress.ip_address(self.host).is_loopback


@dataclass(frozen=True)
class EgmLinkConfig:
    """Datagram handling of the sensor side."""

    max_datagram_bytes: int = _f(lo=64, hi=65507)
    late_reply_ms: float = _f(lo=0.0, lo_open=True)
    reorder_window: int = _f(lo=1)
    latency_samples: int = _f(lo=1)
    rt_priority: int = _f(lo=0, hi=99)  # SCHED_FIFO priority of the link thread; 0: normal


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
    mode: str
    link: EgmLinkConfig
    safety: EgmSafety
    sim_controller: SimControllerConfig


def _ip(value: Any, where: str) -> str:
    if not isinstance(value, str):
        raise ConfigError(f"{where}: expected an IP address, got {value!r}")
    try:
        return str(ipaddress.ip_address(value))
    except ValueError:
        raise ConfigError(f"{where}: not an IP address: {value!r} (use e.g. 127.0.0.1)") from None


def _port(value: Any, where: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value <= 65535:
        raise ConfigError(f"{where}: expected a port number 0..65535, got {value!r}")
    return value


def _network(data: Any) -> EgmNetwork:
    if not isinstance(data, dict):
        raise ConfigError(f"network: expected a mapping, got {data!r}")
    known = ("host", "port", "controller_host", "controller_port")
    unknown = sorted(set(data) - set(known))
    if unknown:
        raise ConfigError(f"network.{unknown[0]}: unknown field (expected one of "
                          f"{', '.join(known)})")
    for name in known:
        if name not in data:
            raise ConfigError(f"network.{name}: missing")
    return EgmNetwork(host=_ip(data["host"], "network.host"),
                      port=_port(data["port"], "network.port"),
                      controller_host=_ip(data["controller_host"], "network.controller_host"),
                      controller_port=_port(data["controller_port"], "network.controller_port"))


def _section(cls: type[Any], data: dict[str, Any], name: str) -> Any:
    if name not in data:
        raise ConfigError(f"{name}: missing")
    try:
        return from_dict(cls, data[name], source=name)
    except ConfigError as e:
        # from_dict writes "<source>: <field>: ..."; make it "<section>.<field>: ..."
        msg = str(e)
        prefix = f"{name}: "
        if msg.startswith(prefix) and ":" in msg[len(prefix):]:
            msg = f"{name}.{msg[len(prefix):]}"
        raise ConfigError(msg) from None


def egm_config_from_dict(data: Any) -> EgmConfig:
    """Validate a parsed ``egm.yaml`` mapping (raises :class:`ConfigError` naming the field)."""
    if not isinstance(data, dict):
        raise ConfigError(f"top level: expected a mapping, got {data!r}")
    known = [f for f in EgmConfig.__dataclass_fields__]
    unknown = sorted(set(data) - set(known))
    if unknown:
        raise ConfigError(f"{unknown[0]}: unknown field (expected one of {', '.join(known)})")
    if "network" not in data:
        raise ConfigError("network: missing")
    mode = data.get("mode")
    if mode not in MODES:
        raise ConfigError(f"mode: expected one of {', '.join(MODES)}, got {mode!r}")
    return EgmConfig(network=_network(data["network"]), mode=mode,
                     link=_section(EgmLinkConfig, data, "link"),
                     safety=_section(EgmSafety, data, "safety"),
                     sim_controller=_section(SimControllerConfig, data, "sim_controller"))


def load_egm_config(path: str | os.PathLike[str] | None = None) -> EgmConfig:
    """Load ``configs/egm.yaml`` (or ``path``).

    Raises:
        ConfigError: ``"<file>: <field>: <problem>"``.
    """
    p = Path(path) if path is not None else CONFIG_DIR / "egm.yaml"
    try:
        text = p.read_text()
    except OSError as e:
        raise ConfigError(f"{p}: cannot read config ({e.strerror or e})") from None
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as e:
        raise ConfigError(f"{p}: not valid YAML ({e})") from None
    try:
        return egm_config_from_dict(data)
    except ConfigError as e:
        raise ConfigError(f"{p}: {e}") from None
