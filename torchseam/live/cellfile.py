"""The cell file ``torchseam weld`` reads: how to reach the cell's camera and controller, and the
cell's calibration.

A cell file is YAML with three sections (``torchseam virtual-cell --write-cell FILE`` writes
one for the virtual cell; for a real cell copy it and edit it)::

    calibration:          # the cell config (configs/cell.yaml's fields): camera intrinsics,
      camera: {...}       # laser plane, hand-eye, tool (the torch's TCP), process
      ...
    camera:
      source: tcp://127.0.0.1:7000   # the frame stream (torchseam.live.framestream), or
                                     # aravis://DEVICE (GenICam), camera:N or a stream URL
                                     # (OpenCV): torchseam.live.cameras
      latency_ms: 20.0               # exposure -> arrival at the PC (torchseam calibrate latency)
      stall_frames: 2.0              # no frame for this many periods: hold, arc off
      exposure_us: 2000.0            # optional: the exposure time set on a GenICam camera (us;
                                     # left out: as the camera is set). Short enough that the
                                     # arc does not clip the stripe's band (a mono band-pass
                                     # camera has one band: docs/benchmarks.md, "Exposure")
      auto_exposure: false           # optional: the weld sets the exposure frame by frame from
                                     # the window round the tracked point (configs/exposure.yaml;
                                     # a tcp:// frame stream or an aravis:// camera only)
    controller:           # the EGM link (configs/egm.yaml's network section)
      host: 127.0.0.1                # where the weld listens (the UdpUc device's remote address)
      port: 6510
      controller_host: 127.0.0.1     # datagrams from any other address are dropped
      controller_port: 6511
      cycle_ms: 4.0                  # the EGM cycle
      feedback_delay_ms: 4.0         # the least age of a fed-back pose on arrival
      rapid_data: true               # RobotWare >= 6.10: arc and segment state over EGM

:func:`load_weld_cell` validates it (one line naming the file and the field on a bad value).
"""

from __future__ import annotations

import dataclasses
import os
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import yaml

from torchseam.core.config import CellConfig, ConfigError, load_config, to_dict
from torchseam.core.config import config_field as _f
from torchseam.robot.egm.config import EgmNetwork


def _camera_url(v: object) -> object:
    """``camera.source``: a ``tcp://HOST:PORT`` frame stream, an ``aravis://DEVICE`` GenICam
    camera, or ``camera:N`` / a stream URL for OpenCV (:mod:`torchseam.live.cameras`)."""
    from torchseam.live.cameras import is_camera_source
    from torchseam.live.framestream import FrameStreamError, parse_url

    what = "tcp://HOST:PORT, aravis://DEVICE, camera:N or a stream URL"
    if not isinstance(v, str) or not is_camera_source(v):
        raise ValueError(f"expected {what}, got {v!r}")
    if v.startswith("tcp://"):
        try:
            parse_url(v)
        except FrameStreamError:
            raise ValueError(f"expected {what}, got {v!r}") from None
    return v


@dataclass(frozen=True)
class CameraLink:
    """How the weld reads the camera (``camera:`` of a cell file)."""

    source: str = _f(convert=_camera_url)
    latency_ms: float = _f(lo=0.0, hi=1000.0)
    stall_frames: float = _f(default=2.0, lo=1.0, hi=50.0)
    #: the exposure time (microseconds) the weld sets on a GenICam camera when it opens it
    #: (None: as the camera is set); a frame stream or an OpenCV camera takes none from the weld
    exposure_us: float | None = _f(default=None, lo=1.0, hi=1e7)
    #: the weld's automatic exposure (torchseam.vision.exposure): after each frame it asks the
    #: camera for the next frames' exposure, a share of the configured one; a frame stream
    #: or a GenICam camera takes the request, an OpenCV camera does not
    auto_exposure: bool = _f(default=False)

    def _check(self) -> None:
        if self.auto_exposure and not self.source.startswith(("tcp://", "aravis://")):
            raise ValueError(f"auto_exposure: set, but {self.source} takes no exposure request "
                             "from the weld (a tcp:// frame stream or an aravis:// GenICam "
                             "camera does): use the camera's own automatic exposure and leave "
                             "auto_exposure out")
        if self.exposure_us is not None and not self.source.startswith("aravis://"):
            raise ValueError(f"exposure_us: set, but {self.source} takes no exposure time from "
                             "the weld (only an aravis:// GenICam camera does): set it on the "
                             "camera's side and leave exposure_us out")


@dataclass(frozen=True)
class ControllerLink(EgmNetwork):
    """Where the weld listens for the controller's EGM datagrams and whom it accepts them from
    (``controller:`` of a cell file)."""

    cycle_ms: float = _f(default=4.0, lo=1.0, hi=100.0)
    # the least time from a pose's measurement (feedBack.time) to its datagram's arrival
    feedback_delay_ms: float = _f(default=4.0, lo=0.0, hi=100.0)
    rapid_data: bool = _f(default=True)


@dataclass(frozen=True)
class WeldCell:
    """A cell file: calibration, camera link, controller link."""

    calibration: CellConfig
    camera: CameraLink
    controller: ControllerLink


def wait_for_cell(path: Path, seconds: float, command: str) -> None:
    """Wait up to ``seconds`` for the cell file ``path`` (a virtual cell started just before
    writes it once it is ready), saying so on stderr; ``TorchseamError`` when it never comes."""
    from torchseam.core.errors import TorchseamError

    if path.exists():
        return
    print(f"torchseam {command}: {path} is not there yet: waiting up to {seconds:g} s (a "
          "virtual cell writes it when it is ready)", file=sys.stderr, flush=True)
    end = time.monotonic() + seconds
    while not path.exists():
        if time.monotonic() > end:
            raise TorchseamError(f"{path}: no cell file after {seconds:g} s")
        time.sleep(0.1)


#: top-level fields of the sensor's calibration (configs/cell.yaml) that a cell file holds
#: under ``calibration:`` only
_CALIBRATION_ONLY = ("laser_plane", "hand_eye", "tool", "process")


def load_weld_cell(path: str | os.PathLike[str]) -> WeldCell:
    """Read and validate a cell file (:class:`ConfigError` naming the file and the field).

    The sensor's calibration file (``configs/cell.yaml``, what ``calibrate`` writes) given
    instead is named as such, with how to make a cell file, rather than as an unknown field.
    """
    try:
        return load_config(WeldCell, path)
    except ConfigError:
        try:
            raw = yaml.safe_load(Path(path).read_text())
        except (OSError, yaml.YAMLError):
            raw = None
        if (isinstance(raw, dict) and "calibration" not in raw
                and any(k in raw for k in _CALIBRATION_ONLY)):
            raise ConfigError(
                f"{path}: this is a sensor calibration (the fields of configs/cell.yaml), not "
                "a cell file: a cell file holds it under calibration:, with camera: (source, "
                "latency_ms) and controller: (the EGM addresses); `torchseam virtual-cell "
                "--write-cell FILE` writes one to start from (README, section 4)") from None
        raise


def save_weld_cell(cell: WeldCell, path: str | os.PathLike[str], header: str = "") -> None:
    """Write a cell file atomically (a reader never sees half of it), its folder made when it
    is not there yet (``--write-cell V/cell.yaml`` from an empty folder)."""
    # lists of numbers on one line ([k1, k2, ...]): `calibrate KIND --cell` then rewrites a
    # calibrated section in place, keeping the file's comments
    from torchseam.geometry.calibrate.cellfile import dump_config_yaml

    write_cell_text(path, header + dump_config_yaml(to_dict(cell)))


def write_cell_text(path: str | os.PathLike[str], text: str) -> None:
    """Write a cell file's text atomically, its folder made when it is not there yet."""
    p = Path(path)
    tmp = p.with_name(f".{p.name}.tmp")
    try:
        p.parent.mkdir(parents=True, exist_ok=True)
        tmp.write_text(text)
        os.replace(tmp, p)
    except OSError as e:
        raise ConfigError(f"{p}: cannot write the cell file ({e.strerror or e})") from None


def write_latency(path: str | os.PathLike[str], cell: WeldCell, latency_ms: float,
                  note: str) -> bool:
    """Write ``camera.latency_ms`` (rounded to 0.01 ms) into the cell file ``path`` that
    ``cell`` was read from: in place, the file's comments and other lines kept (``note`` under
    ``camera:``), else the whole file anew. Returns whether the text was kept."""
    from torchseam.geometry.calibrate.cellfile import splice_section

    new = dataclasses.replace(cell, camera=dataclasses.replace(
        cell.camera, latency_ms=round(float(latency_ms), 2)))
    text = splice_section(Path(path).read_text(), "camera",
                          {"latency_ms": new.camera.latency_ms}, note)
    if text is not None:
        write_cell_text(path, text)
        try:
            if load_weld_cell(path) == new:
                return True
        except ConfigError:
            pass
    save_weld_cell(new, path, header=f"# {note}\n")
    return False
