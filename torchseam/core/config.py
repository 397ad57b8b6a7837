"""Typed, validated configuration of the weld cell, the part and the arc-noise model.

Every file in ``configs/`` loads into a frozen dataclass. A missing, unknown or wrong field
raises :class:`ConfigError` naming the file and the dotted field, e.g.
``configs/cell.yaml: camera.fx: expected a number > 0, got -3``.

Units are the cell's: mm, degrees, pixels; quaternions in ABB order (w, x, y, z).
"""

from __future__ import annotations

import dataclasses
import ipaddress
import math
import os
import re
import types
import typing
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

import numpy as np
import yaml

from torchseam import config_dir
from torchseam.core.errors import TorchseamError

T = TypeVar("T")

#: Folder of the configs when this module was imported (tests and bench scripts reading the
#: shipped files): the package's loaders use :func:`config_path`, resolved when called, which
#: follows a later ``--config-dir``.
CONFIG_DIR = config_dir()


def config_path(*parts: str) -> Path:
    """A path in the config folder in use, resolved when called: ``$TORCHSEAM_CONFIGS``
    (``torchseam --config-dir DIR`` sets it for the command), else the configs shipped in the
    package (the repository's ``configs/`` in a checkout)."""
    return config_dir().joinpath(*parts)


class ConfigError(TorchseamError, ValueError):
    """A configuration file is missing, unreadable, or has a bad field."""


def _spec(n: int | None = None, lo: float | None = None, hi: float | None = None,
          lo_open: bool = False, hi_open: bool = False, unit: bool = False,
          choices: tuple[str, ...] | None = None, ip: bool = False,
          convert: Callable[[Any], Any] | None = None) -> dict[str, Any]:
    """Field constraints: fixed length ``n``, bounds ``lo``/``hi`` (open with ``lo_open`` /
    ``hi_open``), unit-norm vector; for ``str`` fields the allowed ``choices`` or an IP address
    (``ip``). ``convert`` turns the raw value into the form the field's type reads (e.g.
    comma-separated text into a list) before the checks; it raises ValueError('problem')."""
    return {"n": n, "lo": lo, "hi": hi, "lo_open": lo_open, "hi_open": hi_open, "unit": unit,
            "choices": choices, "ip": ip, "convert": convert}


def config_field(n: int | None = None, default: Any = dataclasses.MISSING,
                 default_factory: Callable[[], Any] | Any = dataclasses.MISSING,
                 **kw: Any) -> Any:
    """A dataclass field with the constraints :func:`load_config` checks (see ``_spec``):
    ``config_field(3, unit=True)``, ``config_field(lo=0.0, lo_open=True)``,
    ``config_field(choices=("pose", "pathcorr"))``, ``config_field(ip=True)``. A field with a
    ``default`` (or ``default_factory``) may be left out of the file (for settings added after
    files were written, and options files that give only what they change)."""
    return field(default=default, default_factory=default_factory, metadata=_spec(n, **kw))


_f = config_field  # the short name used inside this module

#: Camera image sides a config may give (px): a larger one is a typo, not a sensor (and would
#: allocate gigabytes per frame).
MIN_IMAGE_PX, MAX_IMAGE_PX = 32, 16384
#: Pipe outer diameters a part may give (mm): what a welding cell can hold and the sensor see.
MIN_PIPE_OD_MM, MAX_PIPE_OD_MM = 10.0, 3000.0
#: No number in a config is larger in magnitude (the rest of the code can square it safely).
MAX_CONFIG_NUMBER = 1e12
#: the settings a cell config's ``camera.stripe_axis`` takes (the views of
#: :class:`torchseam.core.orient.FrameView`, or ``auto``)
STRIPE_AXES = ("auto", "rows", "columns")
#: the settings of ``camera.stripe_response``
STRIPE_RESPONSES = ("auto", "red", "intensity")


@dataclass(frozen=True)
class Pose:
    """Rigid pose: position (mm) and unit quaternion (w, x, y, z) of a child frame in a parent."""

    position_mm: tuple[float, ...] = _f(3)
    quaternion: tuple[float, ...] = _f(4, unit=True)

    def matrix(self) -> np.ndarray:
        """4x4 homogeneous transform parent <- child (mm)."""
        from torchseam.core.transforms import pose_matrix

        return pose_matrix(np.asarray(self.position_mm), np.asarray(self.quaternion))


@dataclass(frozen=True)
class CameraConfig:
    """Pinhole camera with OpenCV distortion (k1, k2, p1, p2, k3)."""

    width: int = _f(lo=MIN_IMAGE_PX, hi=MAX_IMAGE_PX)
    height: int = _f(lo=MIN_IMAGE_PX, hi=MAX_IMAGE_PX)
    fx: float = _f(lo=0.0, lo_open=True, hi=1e6)
    fy: float = _f(lo=0.0, lo_open=True, hi=1e6)
    cx: float = _f(lo=-MAX_IMAGE_PX, hi=2 * MAX_IMAGE_PX)
    cy: float = _f(lo=-MAX_IMAGE_PX, hi=2 * MAX_IMAGE_PX)
    dist: tuple[float, ...] = _f(5)
    #: how the laser stripe runs in the image (see torchseam.core.orient): along the rows,
    #: along the columns (sensor mounted at 90 degrees), or auto: found on the first clean frame
    stripe_axis: str = _f(default="auto", choices=STRIPE_AXES)
    #: the stripe response of a colour camera: red excess, its brightness (the channels' mean:
    #: a stripe overexposed into white), or auto: chosen on the first clean frame
    stripe_response: str = _f(default="auto", choices=STRIPE_RESPONSES)

    @property
    def K(self) -> np.ndarray:  # noqa: N802 - the math's name
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])


@dataclass(frozen=True)
class LaserPlane:
    """Laser light plane in the camera frame: ``normal . X = distance_mm``."""

    normal: tuple[float, ...] = _f(3, unit=True)
    distance_mm: float = _f()
    source_mm: tuple[float, ...] = _f(3)

    def _check(self) -> None:
        off = float(np.dot(self.normal, self.source_mm) - self.distance_mm)
        if abs(off) > 0.01:
            raise ValueError(f"source_mm: lies {off:.3f} mm off the plane (must be on it)")


@dataclass(frozen=True)
class ProcessConfig:
    look_ahead_mm: float = _f(lo=0.0, lo_open=True)
    step_mm: float = _f(lo=0.0, lo_open=True)
    weld_speed_mm_s: float = _f(lo=0.0, lo_open=True)
    frame_rate_hz: float = _f(lo=0.0, lo_open=True)


@dataclass(frozen=True)
class CellConfig:
    """The whole sensor/robot cell (``configs/cell.yaml``)."""

    camera: CameraConfig
    laser_plane: LaserPlane
    hand_eye: Pose
    tool: Pose
    process: ProcessConfig


#: The kinds of part (``kind:`` in ``configs/parts/*.yaml``): what the branch pipe is set on,
#: or (``coupon``) two flat plates butted along a straight, open seam (see
#: :mod:`torchseam.core.part`).
PART_KINDS = ("pipe", "offset", "plate", "sphere", "inline", "coupon")
#: the joint profiles a part's ``joint:`` names (:mod:`torchseam.vision.profiles`): what the
#: stripe shows at its seam and where the torch aims
JOINT_PROFILES = ("fillet", "v_groove", "butt", "lap")


def _positive(name: str, value: float, what: str, least: float | None = None) -> str:
    """The message for a size that must be > 0."""
    bound = "> 0" + (f" (at least {least:g} mm)" if least is not None else "")
    return f"{name}: {what} must be {bound}, got {value!r}"


@dataclass(frozen=True, kw_only=True)
class PartConfig:
    """The joint's geometry and its real-part deviations (``configs/parts/*.yaml``).

    ``kind`` says what the branch pipe is set on (:mod:`torchseam.core.part`): ``pipe`` (the
    default: a main pipe, METHOD.md section 0), ``offset`` (a main pipe with the branch axis
    ``design_offset_mm`` off its axis by design), ``plate`` (a flat plate), ``sphere`` (a
    spherical head of ``sphere_radius_mm``; ``design_offset_mm`` there puts a hillside nozzle
    off the centre) or ``inline`` (a pipe of its own size on its own axis: a girth butt with
    ``root_gap_mm`` between ends of wall ``branch_wall_mm``, or a lap under a sleeve of
    ``sleeve_wall_mm``). ``main_od_mm`` and ``main_ovality`` belong to the pipe kinds only;
    ``branch_ovality``, ``branch_offset_mm``, the clamping error and the thermal drift apply
    to every kind. ``joint`` names the joint profile the seam shows the sensor
    (:data:`JOINT_PROFILES`; default ``fillet``, the corner of a set-on branch).

    ``coupon`` is no pipe: two flat plates ``plate_thickness_mm`` thick, square edges
    ``root_gap_mm`` apart, butted along a straight seam welded over ``seam_length_mm`` (an open
    seam: it has two ends, the positioner does not turn the part); ``branch_offset_mm`` is the
    second plate off its design place, across the seam (a wider gap where > 0) and up (the
    hi-lo). It has no branch pipe: ``branch_od_mm`` and ``intersection_angle_deg`` are left
    out (the other kinds must give them).
    """

    kind: str = _f(default="pipe", choices=PART_KINDS)
    joint: str = _f(default="fillet", choices=JOINT_PROFILES)
    # 0 (the default): none (plate, sphere); a pipe kind's must be > 0 (_check says so)
    main_od_mm: float = _f(hi=MAX_PIPE_OD_MM, default=0.0)
    # 0 / 90 (the defaults) only for a coupon, which has no branch pipe; the other kinds must
    # give both (_check_given says so)
    branch_od_mm: float = _f(lo=MIN_PIPE_OD_MM, hi=MAX_PIPE_OD_MM, default=0.0)
    intersection_angle_deg: float = _f(lo=60.0, hi=90.0, default=90.0)
    design_offset_mm: float = _f(lo=-MAX_PIPE_OD_MM, hi=MAX_PIPE_OD_MM, default=0.0)
    sphere_radius_mm: float = _f(hi=MAX_PIPE_OD_MM, default=0.0)  # 0: no sphere (as main_od_mm)
    branch_offset_mm: tuple[float, ...] = _f(2, lo=-100.0, hi=100.0)
    main_ovality: float = _f(lo=0.0, hi=0.1, default=0.0)
    branch_ovality: float = _f(lo=0.0, hi=0.1, default=0.0)
    distortion_mm: float = _f(lo=0.0, hi=10.0)
    distortion_period_s: float = _f(lo=1.0, hi=86400.0)
    # a bevelled branch (torchseam.core.part.BevelledJoint): its end cut at bevel_deg from the
    # square end across the wall of branch_wall_mm, set root_gap_mm off the main body
    # (measured along the branch axis); 0 (the default): a square-cut branch sitting on it
    bevel_deg: float = _f(lo=0.0, hi=60.0, default=0.0)
    branch_wall_mm: float = _f(lo=0.0, hi=100.0, default=0.0)
    root_gap_mm: float = _f(lo=0.0, hi=6.0, default=0.0)
    # the inline kind's lap: the wall of the sleeve slipped over the pipe (the step's height)
    sleeve_wall_mm: float = _f(lo=0.0, hi=50.0, default=0.0)
    # the coupon kind: the welded length of its straight seam and its plates' thickness
    seam_length_mm: float = _f(lo=0.0, hi=2000.0, default=0.0)
    plate_thickness_mm: float = _f(lo=0.0, hi=100.0, default=0.0)
    placement: Pose = field(default_factory=lambda: Pose((0.0, 0.0, 0.0), (1.0, 0.0, 0.0, 0.0)))
    placement_error: Pose = field(
        default_factory=lambda: Pose((0.0, 0.0, 0.0), (1.0, 0.0, 0.0, 0.0)))

    def file_dict(self) -> dict[str, Any]:
        """The part as its YAML file holds it (:func:`save_config`): every field, less those
        its kind must leave out (a coupon's branch pipe), so that the file loads back."""
        data = to_dict(self)
        if self.kind == "coupon":
            del data["branch_od_mm"], data["intersection_angle_deg"]
        return data

    def _check_given(self, given: frozenset[str]) -> None:
        """A size the kind needs, left out of the file (its default 0 means none)."""
        if self.kind in ("pipe", "offset") and "main_od_mm" not in given:
            raise ValueError("main_od_mm: missing (the main pipe's outer diameter)")
        if self.kind != "coupon":
            for name in ("branch_od_mm", "intersection_angle_deg"):
                if name not in given:
                    raise ValueError(f"{name}: missing")
        elif "branch_od_mm" in given or "intersection_angle_deg" in given:
            name = "branch_od_mm" if "branch_od_mm" in given else "intersection_angle_deg"
            raise ValueError(f"{name}: a part of kind coupon has no branch pipe (leave it out)")
        if self.kind == "sphere" and "sphere_radius_mm" not in given:
            raise ValueError("sphere_radius_mm: missing (the sphere's radius)")

    def _check_fields(self) -> None:
        """A size given to a kind that has none."""
        kind = self.kind
        pipe = kind in ("pipe", "offset")
        for name, applies in (("main_od_mm", pipe), ("main_ovality", pipe),
                              ("sphere_radius_mm", kind == "sphere"),
                              ("design_offset_mm", kind in ("offset", "sphere"))):
            if not applies and getattr(self, name) != 0.0:
                raise ValueError(f"{name}: a part of kind {kind} has none (leave it out)")
        for name in ("seam_length_mm", "plate_thickness_mm"):
            if kind != "coupon" and getattr(self, name) != 0.0:
                raise ValueError(f"{name}: a part of kind {kind} has none (a coupon has)")

    def _check(self) -> None:
        kind = self.kind
        pipe = kind in ("pipe", "offset")
        self._check_fields()
        if kind == "coupon":
            self._check_coupon()
            return
        if self.branch_od_mm < MIN_PIPE_OD_MM:
            raise ValueError(f"branch_od_mm: expected a number >= {MIN_PIPE_OD_MM}, got "
                             f"{self.branch_od_mm!r}")
        r = self.branch_od_mm / 2 * (1 + self.branch_ovality)
        y = self.design_offset_mm + self.branch_offset_mm[1]
        if kind == "inline":
            self._check_inline()
            return
        if self.joint in ("butt", "lap"):
            raise ValueError(f"joint: a {self.joint} joint is a part of kind inline (a pipe on "
                             f"its own axis); a branch set on a {kind} is a fillet or a v_groove")
        if self.sleeve_wall_mm != 0.0:
            raise ValueError(f"sleeve_wall_mm: a part of kind {kind} has none (a lap of kind "
                             "inline has)")
        self._check_bevel()
        if pipe:
            if self.main_od_mm <= 0.0:
                raise ValueError(_positive("main_od_mm", self.main_od_mm,
                                           "the main pipe's outer diameter", MIN_PIPE_OD_MM))
            if self.main_od_mm < MIN_PIPE_OD_MM:
                raise ValueError(f"main_od_mm: expected a number >= {MIN_PIPE_OD_MM}, got "
                                 f"{self.main_od_mm!r}")
            R = self.main_od_mm / 2 * (1 - self.main_ovality)
            if r + abs(y) >= R:
                what = "its y offset" if kind == "pipe" else "its y offset (design and error)"
                raise ValueError(
                    f"branch_od_mm: branch radius plus {what} must stay inside the main pipe "
                    f"({r + abs(y):.1f} mm >= {R:.1f} mm)")
        if kind == "sphere":
            if self.sphere_radius_mm <= 0.0:
                raise ValueError(_positive("sphere_radius_mm", self.sphere_radius_mm,
                                           "the sphere's radius"))
            off = math.hypot(self.branch_offset_mm[0], y)
            if r + off >= self.sphere_radius_mm:
                raise ValueError(
                    "branch_od_mm: branch radius plus its offset from the sphere's centre must "
                    f"stay inside the sphere ({r + off:.1f} mm >= {self.sphere_radius_mm:.1f} mm)")


    def _check_inline(self) -> None:
        """A girth joint: the pipe on its own axis, a butt with a root gap between two square
        ends of a given wall, or a lap under a sleeve."""
        if self.intersection_angle_deg != 90.0:
            raise ValueError("intersection_angle_deg: a part of kind inline continues the pipe "
                             f"along its own axis: 90, got {self.intersection_angle_deg!r}")
        if self.joint not in ("butt", "lap"):
            raise ValueError(f"joint: a part of kind inline is a butt or a lap, got "
                             f"{self.joint!r}")
        if self.bevel_deg != 0.0:
            raise ValueError("bevel_deg: a part of kind inline has square-cut ends (leave it out)")
        r_min = self.branch_od_mm / 2 * (1 - self.branch_ovality)
        if self.joint == "butt":
            if self.root_gap_mm <= 0.0:
                raise ValueError(_positive("root_gap_mm", self.root_gap_mm,
                                           "a butt's gap between the pipes' ends"))
            if not 0.0 < self.branch_wall_mm < r_min:
                raise ValueError(f"branch_wall_mm: a butt's pipe wall must be > 0 and thinner "
                                 f"than its radius ({r_min:.1f} mm), got {self.branch_wall_mm!r}")
            if self.sleeve_wall_mm != 0.0:
                raise ValueError("sleeve_wall_mm: a butt has no sleeve (leave it out)")
            hilo = math.hypot(*self.branch_offset_mm)
            if hilo >= self.branch_wall_mm:
                raise ValueError(f"branch_offset_mm: the pipes' ends must overlap: their offset "
                                 f"(hi-lo, {hilo:.1f} mm) must stay under the wall "
                                 f"({self.branch_wall_mm!r} mm)")
        else:
            if self.sleeve_wall_mm <= 0.0:
                raise ValueError(_positive("sleeve_wall_mm", self.sleeve_wall_mm,
                                           "a lap's sleeve wall (the step)"))
            if self.root_gap_mm != 0.0 or self.branch_wall_mm != 0.0:
                name = "root_gap_mm" if self.root_gap_mm != 0.0 else "branch_wall_mm"
                raise ValueError(f"{name}: a lap has none (leave it out)")

    def _check_coupon(self) -> None:
        """Two flat plates butted with a root gap along a straight seam."""
        if self.joint != "butt":
            raise ValueError(f"joint: a part of kind coupon is a butt (two plates edge to edge), "
                             f"got {self.joint!r}")
        for name, what in (("seam_length_mm", "the welded length of the seam"),
                           ("plate_thickness_mm", "the plates' thickness"),
                           ("root_gap_mm", "a butt's gap between the plates' edges")):
            if getattr(self, name) <= 0.0:
                raise ValueError(_positive(name, getattr(self, name), what))
        for name in ("branch_ovality", "bevel_deg", "branch_wall_mm", "sleeve_wall_mm"):
            if getattr(self, name) != 0.0:
                raise ValueError(f"{name}: a part of kind coupon has none (leave it out)")
        across, up = self.branch_offset_mm
        if self.root_gap_mm + across <= 0.0:
            raise ValueError(f"branch_offset_mm: the second plate {-across:g} mm towards the "
                             f"first closes the {self.root_gap_mm:g} mm gap (the plates would "
                             "overlap)")
        if abs(up) >= self.plate_thickness_mm:
            raise ValueError(f"branch_offset_mm: the plates' faces must overlap: their hi-lo "
                             f"({abs(up):g} mm) must stay under their thickness "
                             f"({self.plate_thickness_mm:g} mm)")

    def _check_bevel(self) -> None:
        """A bevel needs the wall it is cut across, and a root gap needs a bevel (a square
        branch lifted off the main body has no groove for the torch to bisect)."""
        r_min = self.branch_od_mm / 2 * (1 - self.branch_ovality)
        if self.bevel_deg > 0.0 and self.branch_wall_mm <= 0.0:
            raise ValueError(_positive("branch_wall_mm", self.branch_wall_mm,
                                       "the branch's wall thickness (a bevel is cut across it)"))
        if self.branch_wall_mm >= r_min:
            raise ValueError(f"branch_wall_mm: the wall must be thinner than the branch's radius "
                             f"({self.branch_wall_mm!r} >= {r_min:.1f} mm)")
        if self.root_gap_mm > 0.0 and self.bevel_deg <= 0.0:
            raise ValueError("root_gap_mm: a root gap needs a bevelled branch (bevel_deg > 0)")
        if self.bevel_deg > 0.0 and self.bevel_deg < 15.0:
            raise ValueError(f"bevel_deg: expected 0 (none) or 15..60, got {self.bevel_deg!r}")


@dataclass(frozen=True)
class GlareNoise:
    peak: float = _f(lo=0.0, hi=255.0)
    radius_px: float = _f(lo=0.0, lo_open=True)
    flicker: float = _f(lo=0.0)


@dataclass(frozen=True)
class GrooveNoise:
    brightness: tuple[float, ...] = _f(2, lo=0.0, hi=255.0)
    reach: tuple[float, ...] = _f(2, lo=0.0, hi=1.5)
    width_px: float = _f(lo=0.0, lo_open=True)


@dataclass(frozen=True)
class SpatterNoise:
    rate: float = _f(lo=0.0)
    burst_rate: float = _f(lo=0.0)
    burst_prob: float = _f(lo=0.0, hi=1.0)
    burst_frames: float = _f(lo=1.0)
    length_px: tuple[float, ...] = _f(2, lo=0.0)
    brightness: tuple[float, ...] = _f(2, lo=0.0, hi=255.0)


@dataclass(frozen=True)
class ReflectionNoise:
    count: int = _f(lo=0)
    radius_px: tuple[float, ...] = _f(2, lo=0.0)
    brightness: tuple[float, ...] = _f(2, lo=0.0, hi=255.0)


@dataclass(frozen=True)
class FlashNoise:
    prob: float = _f(lo=0.0, hi=1.0)
    brightness: tuple[float, ...] = _f(2, lo=0.0, hi=255.0)


@dataclass(frozen=True)
class DropoutNoise:
    prob: float = _f(lo=0.0, hi=1.0)
    gaps: tuple[int, ...] = _f(2, lo=0)
    length_px: tuple[float, ...] = _f(2, lo=0.0)


@dataclass(frozen=True)
class SensorNoise:
    sigma_clean: float = _f(lo=0.0)
    sigma_arc: float = _f(lo=0.0)


#: The appearance families of the simulated sensor (``families:`` in ``configs/noise.yaml``).
FAMILY_NAMES = ("sim", "wide", "thin", "smoke", "glint")
#: the heaviest arc-noise level a config or command may ask for: 1 is the amplitudes of
#: configs/noise.yaml, the benchmarks go to 1.5 x that (`extreme`)
MAX_NOISE_LEVEL = 2.0


@dataclass(frozen=True)
class StripeLook:
    """How the laser stripe is imaged: cross-section, brightness, colour and speckle."""

    sigma_px: float = _f(lo=0.0, lo_open=True, hi=8.0)  # width scale of the cross-section
    order: float = _f(lo=1.0, hi=8.0)      # super-Gaussian order: 1 Gaussian, > 1 flat top
    peak: float = _f(lo=0.0, lo_open=True, hi=2000.0)  # grey level head-on, at exposure gain 1
    bgr: tuple[float, ...] = _f(3, lo=0.0, hi=2.0)     # colour through the Bayer filter
    speckle: float = _f(lo=0.0, hi=2.0)    # log-normal speckle depth along the stripe
    speckle_px: float = _f(lo=0.25, hi=64.0)  # speckle correlation length along the stripe
    grain: float = _f(lo=0.0, hi=0.9)      # depth of the fixed surface grain
    #: two parallel lobes this far apart across the stripe (a diode lasing in two modes; the
    #: second weaker); 0: one line
    split_px: float = _f(lo=0.0, hi=8.0, default=0.0)


@dataclass(frozen=True)
class GlareLook:
    """Shape, placement and colour of the arc glare."""

    core: float = _f(lo=0.0)               # weight of the saturated core
    halo: float = _f(lo=0.0)               # weight of the long exponential halo
    size: float = _f(lo=0.0, lo_open=True, hi=4.0)  # scale of ``glare.radius_px``
    aspect: float = _f(lo=0.2, hi=5.0)     # along-seam (image vertical) / across-seam extent
    tilt_deg: float = _f(lo=-90.0, hi=90.0)  # rotation of the long axis from the vertical
    offset_px: tuple[float, ...] = _f(2)   # arc light centre relative to the torch tip pixel
    bgr: tuple[float, ...] = _f(3, lo=0.0, hi=2.0)
    #: specular glint of the arc on the main pipe, relative to ``glare.peak``; 0: none
    glint: float = _f(lo=0.0, hi=4.0, default=0.0)


@dataclass(frozen=True)
class SpatterLook:
    """How spatter droplets are imaged."""

    style: str = _f(choices=("streaks", "dots"))
    length_scale: float = _f(lo=0.0, lo_open=True, hi=10.0)  # scale of ``spatter.length_px``
    size_px: tuple[int, ...] = _f(2, lo=1, hi=12)  # streak thickness or dot radius range
    head: float = _f(lo=0.0, hi=4.0)       # extra brightness of a streak's leading droplet
    bgr: tuple[float, ...] = _f(3, lo=0.0, hi=2.0)

    def _check(self) -> None:
        if self.size_px[0] > self.size_px[1]:
            raise ValueError(f"size_px: expected [min, max], got {list(self.size_px)}")


@dataclass(frozen=True)
class ExposureLook:
    """The camera's exposure and response."""

    gain: float = _f(lo=0.0, lo_open=True, hi=10.0)  # scales all light before the response
    gamma: float = _f(lo=0.2, hi=5.0)      # response curve 255 (x / 255) ** gamma
    bleed: tuple[float, ...] = _f(2, lo=0.0, hi=1.0)  # red above full well into (blue, green)
    band_prob: float = _f(lo=0.0, hi=1.0)  # chance per frame (level 1) of a saturated row band
    band_gain: float = _f(lo=1.0, hi=20.0)  # exposure gain inside that band


@dataclass(frozen=True)
class HazeLook:
    """Welding fume: a grey, drifting, low-frequency veil."""

    amount: float = _f(lo=0.0, hi=255.0)   # grey level of the densest fume at level 1
    absorb: float = _f(lo=0.0, hi=1.0)     # share of the stripe light the densest fume hides
    scale_px: float = _f(lo=8.0, hi=2000.0)  # size of the fume patches
    drift_px: float = _f(lo=0.0, hi=100.0)   # fume drift per frame


@dataclass(frozen=True)
class AppearanceFamily:
    """One structurally distinct look of the sensor images (see ``configs/noise.yaml``)."""

    stripe: StripeLook
    glare: GlareLook
    spatter: SpatterLook
    exposure: ExposureLook
    haze: HazeLook
    reflections_gain: float = _f(lo=0.0, hi=10.0)  # scales ``reflections.brightness``
    dropout_gain: float = _f(lo=0.0, hi=10.0)      # scales ``dropout.prob``
    motion_blur_px: int = _f(lo=0, hi=31)           # horizontal motion blur length
    read_noise: float = _f(lo=0.0, hi=50.0)         # extra read noise std (in quadrature)


@dataclass(frozen=True)
class AppearanceFamilies:
    """The appearance families, one field per name of :data:`FAMILY_NAMES`."""

    sim: AppearanceFamily
    wide: AppearanceFamily
    thin: AppearanceFamily
    smoke: AppearanceFamily
    glint: AppearanceFamily


@dataclass(frozen=True)
class NoiseConfig:
    """Arc-noise model (``configs/noise.yaml``); amplitudes are those at level 1.0.

    ``family`` names the default appearance family; ``families`` holds each family's look
    (:meth:`appearance`).
    """

    levels: dict[str, float]
    clean_lead_frames: int = _f(lo=0)
    family: str = _f(choices=FAMILY_NAMES)
    families: AppearanceFamilies = _f()
    glare: GlareNoise = field(default_factory=GlareNoise)
    groove: GrooveNoise = field(default_factory=GrooveNoise)
    spatter: SpatterNoise = field(default_factory=SpatterNoise)
    reflections: ReflectionNoise = field(default_factory=ReflectionNoise)
    flash: FlashNoise = field(default_factory=FlashNoise)
    dropout: DropoutNoise = field(default_factory=DropoutNoise)
    sensor: SensorNoise = field(default_factory=SensorNoise)

    def appearance(self, family: str | None = None) -> AppearanceFamily:
        """The look of ``family`` (None: the default ``family``); ValueError naming an unknown
        one."""
        name = self.family if family is None else family
        if name not in FAMILY_NAMES:
            raise ValueError(f"appearance family {name!r}: expected one of "
                             f"{', '.join(FAMILY_NAMES)}")
        return getattr(self.families, name)

    def level(self, name_or_value: str | float) -> float:
        """Resolve ``'heavy'`` or ``'0.4'`` or ``0.4`` to a level in [0, MAX_NOISE_LEVEL]
        (1: the amplitudes of ``configs/noise.yaml``; above 1: heavier arc than that)."""
        if isinstance(name_or_value, str) and name_or_value in self.levels:
            return float(self.levels[name_or_value])
        try:
            value = float(name_or_value)
        except (TypeError, ValueError):
            raise ValueError(
                f"noise level {name_or_value!r}: use a number in [0, {MAX_NOISE_LEVEL:g}] or "
                f"one of {', '.join(self.levels)}") from None
        if not 0.0 <= value <= MAX_NOISE_LEVEL or math.isnan(value):
            raise ValueError(f"noise level {value}: must lie in [0, {MAX_NOISE_LEVEL:g}]")
        return value


# --------------------------------------------------------------------------- parsing

_FLOAT_TEXT = re.compile(r"^[-+]?(\d+\.?\d*|\.\d+)([eE][-+]?\d+)?$")


def _shown(v: Any) -> str:
    """``v`` for a message: a value too long to print whole is described instead."""
    text = repr(v)
    if len(text) <= 40:
        return text
    if isinstance(v, int):
        return f"a {len(text.lstrip('-'))}-digit number"
    return f"{text[:30]}... ({len(text)} characters)"


def _check_number(v: Any, meta: dict[str, Any], want_int: bool) -> float | int:
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        hint = ""
        if isinstance(v, str) and _FLOAT_TEXT.match(v.strip()):
            # YAML 1.1 reads 1e3 (no point, no exponent sign) as text
            hint = " (YAML reads this as text: write the number with a point and an " \
                   "exponent sign, e.g. 1.0e+3)"
        raise ValueError(f"expected a {'whole number' if want_int else 'number'}, "
                         f"got {_shown(v)}{hint}")
    # (a Python int may be too large for a float: no float() or math.* on it before the bounds)
    if isinstance(v, float):
        if not math.isfinite(v):
            raise ValueError(f"expected a finite number, got {v!r}")
        if want_int and not v.is_integer():
            raise ValueError(f"expected a whole number, got {v!r}")
    lo, hi = meta.get("lo"), meta.get("hi")
    kind = "whole number" if want_int else "number"
    if lo is not None and (v <= lo if meta.get("lo_open") else v < lo):
        op = ">" if meta.get("lo_open") else ">="
        raise ValueError(f"expected a {kind} {op} {lo}, got {_shown(v)}")
    if hi is not None and (v >= hi if meta.get("hi_open") else v > hi):
        op = "<" if meta.get("hi_open") else "<="
        raise ValueError(f"expected a {kind} {op} {hi}, got {_shown(v)}")
    if abs(v) > MAX_CONFIG_NUMBER:
        raise ValueError(f"expected a number of magnitude <= {MAX_CONFIG_NUMBER:g}, "
                         f"got {_shown(v)}")
    return int(v) if want_int else float(v)


def _check_str(v: Any, meta: dict[str, Any]) -> str:
    choices = meta.get("choices")
    if choices is not None:
        if v not in choices:
            raise ValueError(f"expected one of {', '.join(choices)}, got {v!r}")
        return str(v)
    if meta.get("ip"):
        try:
            return str(ipaddress.ip_address(v if isinstance(v, str) else ""))
        except ValueError:
            raise ValueError(f"not an IP address: {v!r} (use e.g. 127.0.0.1)") from None
    if not isinstance(v, str):
        raise ValueError(f"expected a string, got {v!r}")
    return v


def _parse_union(arms: tuple[Any, ...], v: Any, meta: dict[str, Any], path: str) -> Any:
    """``A | B`` (e.g. ``float | None``, ``float | tuple[float, float]``): None where allowed,
    else the first arm that reads ``v``, a tuple arm first for a list; the error is that arm's."""
    if v is None and type(None) in arms:
        return None
    seq = isinstance(v, (list, tuple))
    tried = sorted((a for a in arms if a is not type(None)),
                   key=lambda a: (typing.get_origin(a) is tuple) != seq)
    first: ValueError | None = None
    for arm in tried:
        try:
            return _parse_value(arm, v, meta, path)
        except ValueError as e:
            first = first or e
    assert first is not None
    raise first


def _parse_tuple(args: tuple[Any, ...], v: Any, meta: dict[str, Any]) -> tuple[Any, ...]:
    """``tuple[X, ...]`` (length ``meta["n"]`` when given) or ``tuple[X, Y]`` (that length) of
    strings or of numbers."""
    if not isinstance(v, (list, tuple)):
        raise ValueError(f"expected a list, got {v!r}")
    n = meta.get("n") if Ellipsis in args else len(args)
    if n is not None and len(v) != n:
        raise ValueError(f"expected {n} values, got {len(v)}")
    item_tps = [args[0]] * len(v) if Ellipsis in args else list(args)
    if args[0] is str:
        return tuple(_check_str(x, meta) for x in v)
    out = tuple(_check_number(x, meta, tp is int) for x, tp in zip(v, item_tps, strict=True))
    if meta.get("unit"):
        norm = math.sqrt(sum(x * x for x in out))
        if abs(norm - 1.0) > 1e-4:
            raise ValueError(f"expected a unit vector, norm is {norm:.6f}")
        out = tuple(x / norm for x in out)
    return out


def _parse_mapping(value_tp: Any, v: Any) -> dict[str, Any]:
    """``dict[str, Any]``: any mapping (its user checks it); ``dict[str, float]``: a non-empty
    mapping of numbers in [0, MAX_NOISE_LEVEL] (the noise levels)."""
    if value_tp is Any:
        if not isinstance(v, dict):
            raise ValueError(f"expected a mapping, got {v!r}")
        return dict(v)
    if not isinstance(v, dict) or not v:
        raise ValueError(f"expected a non-empty mapping, got {v!r}")
    return {str(k): _check_number(x, {"lo": 0.0, "hi": MAX_NOISE_LEVEL}, False)
            for k, x in v.items()}


def _parse_value(tp: Any, v: Any, meta: dict[str, Any], path: str) -> Any:
    convert = meta.get("convert")
    if convert is not None:
        v = convert(v)
    origin = typing.get_origin(tp)
    if isinstance(tp, type) and dataclasses.is_dataclass(tp):
        return _parse_dataclass(tp, v, path)
    if origin in (typing.Union, types.UnionType):
        return _parse_union(typing.get_args(tp), v, {**meta, "convert": None}, path)
    if origin is tuple:
        return _parse_tuple(typing.get_args(tp), v, meta)
    if origin is dict:
        return _parse_mapping(typing.get_args(tp)[1], v)
    if tp in (int, float):
        return _check_number(v, meta, tp is int)
    if tp is bool:
        if not isinstance(v, bool):
            raise ValueError(f"expected true or false, got {v!r}")
        return v
    if tp is str:
        return _check_str(v, meta)
    raise TypeError(f"unsupported config type {tp!r} at {path}")  # programming error


def _parse_dataclass(cls: type[T], data: Any, path: str) -> T:
    if not isinstance(data, dict):
        raise ConfigError(f"{path or 'top level'}: expected a mapping, got {data!r}")
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls)}  # type: ignore[arg-type]
    unknown = sorted(set(data) - set(fields))
    if unknown:
        raise ConfigError(f"{path + '.' if path else ''}{unknown[0]}: unknown field "
                          f"(expected one of {', '.join(fields)})")
    kwargs = {}
    for name, f in fields.items():
        where = f"{path}.{name}" if path else name
        if name not in data:
            if f.default is not dataclasses.MISSING:
                kwargs[name] = f.default
                continue
            if f.default_factory is not dataclasses.MISSING:
                kwargs[name] = f.default_factory()
                continue
            raise ConfigError(f"{where}: missing")
        try:
            kwargs[name] = _parse_value(hints[name], data[name], dict(f.metadata), where)
        except ConfigError:
            raise
        except ValueError as e:
            raise ConfigError(f"{where}: {e}") from None
    obj = cls(**kwargs)
    check = getattr(obj, "_check", None)
    given = getattr(obj, "_check_given", None)  # checks that need to know what the file gave
    if check is not None or given is not None:
        try:
            if given is not None:
                given(frozenset(data))
            if check is not None:
                check()
        except ValueError as e:
            raise ConfigError(f"{path + '.' if path else ''}{e}") from None
    return obj


def load_config(cls: type[T], path: str | os.PathLike[str]) -> T:
    """Load and validate a YAML file into the dataclass ``cls``.

    Raises:
        ConfigError: ``"<file>: <field>: <problem>"`` for a missing file, bad YAML or bad field.
    """
    p = Path(path)
    return from_dict(cls, read_yaml(p), str(p))


class DuplicateKeyError(yaml.YAMLError):
    """A YAML mapping gives the same key twice (PyYAML keeps the last silently).

    Attributes:
        key: the dotted path of the key (``camera.fx``, ``frames[2].t_s``).
        line: 1-based line of the second one; first: 1-based line of the first one.
    """

    def __init__(self, key: str, line: int, first: int) -> None:
        super().__init__(f"{key} given twice (first on line {first})")
        self.key, self.line, self.first = key, line, first


#: PyYAML's tag of a merge key (``<<: *base``): it may be followed by keys that override the
#: merged ones, which is what merging is for, not a duplicate.
_MERGE_TAG = "tag:yaml.org,2002:merge"


def _key_text(text: str) -> str:
    """A mapping key as written, as it is shown in a path (clipped: a message is one line)."""
    text = " ".join(text.split())
    return text if len(text) <= 60 else text[:52] + "..."


class UniqueKeyLoader(yaml.SafeLoader):
    """:class:`yaml.SafeLoader` that refuses a key given twice in one mapping
    (:class:`DuplicateKeyError` naming the key's dotted path and both lines).

    Keys are compared as the values they load as (``1`` and ``1.0``, ``yes`` and ``true`` are
    the same key, as in the dict they would make); keys brought in by a merge (``<<: *base``)
    may be overridden. The nodes are checked as the parser wrote them, before anything is
    constructed, so anchors and merges cannot hide a duplicate or fake one."""

    def construct_document(self, node: yaml.Node) -> Any:
        self._check_unique_keys(node)
        return super().construct_document(node)

    def _check_unique_keys(self, root: yaml.Node) -> None:
        seen: set[int] = set()
        todo: list[tuple[yaml.Node, str]] = [(root, "")]
        while todo:
            node, path = todo.pop()
            if id(node) in seen:   # an alias: checked where it was anchored (cycles end here)
                continue
            seen.add(id(node))
            if isinstance(node, yaml.SequenceNode):
                todo.extend((v, f"{path}[{i}]") for i, v in reversed(list(enumerate(node.value))))
            elif isinstance(node, yaml.MappingNode):
                first: dict[Any, int] = {}
                children = []
                for key_node, value_node in node.value:
                    if key_node.tag == _MERGE_TAG:   # an inline merged mapping is checked too
                        children.append((value_node, path))
                        continue
                    name = path
                    if isinstance(key_node, yaml.ScalarNode):
                        key = self.construct_object(key_node, deep=True)
                        shown = _key_text(key_node.value)
                        name = f"{path}.{shown}" if path else shown
                        try:
                            line = first.get(key)
                        except TypeError:  # unhashable: PyYAML's own error names it
                            line = None
                        else:
                            if line is not None:
                                raise DuplicateKeyError(name, key_node.start_mark.line + 1,
                                                        line)
                            first[key] = key_node.start_mark.line + 1
                    children.append((value_node, name))
                todo.extend(reversed(children))


def load_yaml(text: str, name: str = "<yaml>") -> Any:
    """``text`` parsed as YAML with :class:`UniqueKeyLoader` (what ``yaml.safe_load`` gives,
    but a key given twice is refused). Raises :class:`ConfigError`: ``NAME:L: KEY given twice
    (first on line F)``, or ``NAME: not valid YAML: PROBLEM (line L, column C)``."""
    try:
        return yaml.load(text, Loader=UniqueKeyLoader)  # a SafeLoader: no Python objects
    except DuplicateKeyError as e:
        raise ConfigError(f"{name}:{e.line}: {e}") from None
    except yaml.YAMLError as e:
        raise ConfigError(f"{name}: not valid YAML: {yaml_problem(e)}") from None


def read_yaml(path: str | os.PathLike[str]) -> Any:
    """The parsed YAML of ``path``; :class:`ConfigError` naming the file when it cannot be read
    or parsed, or gives a key twice (``configs/cell.yaml:12: camera.fx given twice (first on
    line 5)``: see :func:`load_yaml`)."""
    p = Path(path)
    try:
        text = p.read_text()
    except OSError as e:
        raise ConfigError(f"{p}: cannot read config ({e.strerror or e})") from None
    return load_yaml(text, str(p))


def yaml_problem(e: yaml.YAMLError) -> str:
    """PyYAML's multi-line error as one line: ``PROBLEM (line L, column C)`` (1-based), from
    a :class:`yaml.MarkedYAMLError`'s ``problem`` and ``problem_mark``; its context when it has
    no problem text."""
    if isinstance(e, yaml.MarkedYAMLError):
        what = e.problem or e.context or "cannot parse"
        mark = e.problem_mark or e.context_mark
        where = f" (line {mark.line + 1}, column {mark.column + 1})" if mark is not None else ""
        return " ".join(f"{what}{where}".split())
    return " ".join(str(e).split()) or type(e).__name__


def load_cell(path: str | os.PathLike[str] | None = None) -> CellConfig:
    """The cell configuration (default ``configs/cell.yaml``)."""
    return load_config(CellConfig, path or config_path("cell.yaml"))


def load_part(path: str | os.PathLike[str] | None = None) -> PartConfig:
    """A part configuration (default ``configs/parts/t_joint.yaml``, the deviated T joint).

    A relative ``configs/...`` path that is not there (a command run outside the checkout, as
    the manual writes it: ``--part configs/parts/y_joint_75.yaml``) is the config folder in
    use's file of that name (the shipped configs, or ``--config-dir``)."""
    if path is None:
        return load_config(PartConfig, config_path("parts", "t_joint.yaml"))
    return load_config(PartConfig, shipped_config(path))


def shipped_config(path: str | os.PathLike[str]) -> Path:
    """``path``, or, when it is a relative ``configs/...`` path that does not exist here, the
    config folder in use's file of that name (when that exists)."""
    p = Path(path)
    if p.exists() or p.is_absolute() or not p.parts or p.parts[0] != "configs":
        return p
    alt = config_path(*p.parts[1:])
    return alt if alt.exists() else p


def load_noise(path: str | os.PathLike[str] | None = None) -> NoiseConfig:
    """The arc-noise model (default ``configs/noise.yaml``)."""
    return load_config(NoiseConfig, path or config_path("noise.yaml"))


def to_dict(obj: Any) -> Any:
    """A config object as plain lists/dicts (for ``meta.json`` and writing YAML back)."""
    if dataclasses.is_dataclass(obj):
        return {f.name: to_dict(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
    if isinstance(obj, (tuple, list)):
        return [to_dict(x) for x in obj]
    if isinstance(obj, dict):
        return {k: to_dict(v) for k, v in obj.items()}
    return obj


def from_dict(cls: type[T], data: Any, source: str = "<dict>") -> T:
    """Inverse of :func:`to_dict`, with the same validation as :func:`load_config`."""
    try:
        return _parse_dataclass(cls, data, "")
    except ConfigError as e:
        raise ConfigError(f"{source}: {e}") from None


def save_config(obj: Any, path: str | os.PathLike[str]) -> None:
    """Write a config object back to YAML (``torchseam calibrate``; a part as turned for a
    segment, ``plan --out`` and the demo's report: :meth:`PartConfig.file_dict`)."""
    data = obj.file_dict() if isinstance(obj, PartConfig) else to_dict(obj)
    Path(path).write_text(yaml.safe_dump(data, sort_keys=False))

