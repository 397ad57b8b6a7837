"""Console settings (``configs/console.yaml``) and the operator's weld parameters.

:class:`ConsoleConfig` is loaded and validated like every other config. :class:`WeldParams` is
what the page's parameter form sends; :func:`parse_params` checks it against
``ConsoleConfig.limits`` and raises :class:`ParamError` with a message the page shows as it is
(``step_mm must be in 0.5..5 mm, got 9``).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from torchseam.core.config import CellConfig, NoiseConfig, config_path, load_config
from torchseam.core.config import config_field as _f
from torchseam.core.errors import TorchseamError

#: Address the console binds to unless ``--host`` says otherwise: this machine only.
DEFAULT_HOST = "127.0.0.1"
#: Segment letters of the ring (see :func:`torchseam.plan.path.six_segments`).
SEGMENT_LETTERS = "abcdef"


@dataclass(frozen=True)
class ServerSettings:
    """The web server (``server:``). The connection settings keep a path open for the
    operator whatever else connects (see ``torchseam.console.server.ConnectionGuard``); they
    have defaults, so a console.yaml written before them still loads."""

    port: int = _f(lo=0, hi=65535)
    max_clients: int = _f(lo=1)
    send_timeout_s: float = _f(lo=0.0, lo_open=True)
    heartbeat_s: float = _f(lo=0.0, lo_open=True)
    #: connections open at once, all clients together (fewer when the descriptor limit
    #: leaves less room: see ``fd_reserve``)
    max_connections: int = _f(lo=8, hi=1_000_000, default=256)
    #: connections open at once from one address (loopback is one address for every program
    #: on the PC, the operator's browser included)
    max_connections_per_client: int = _f(lo=2, hi=1_000_000, default=64)
    #: a connection with no request being answered for this long is closed: one that sends
    #: nothing, sends its request's header too slowly, or sits idle between requests
    idle_timeout_s: float = _f(lo=0.0, lo_open=True, hi=3600.0, default=10.0)
    #: longest a request may take to be answered once its header is in (its body included);
    #: the WebSocket stream is not bounded by it
    request_timeout_s: float = _f(lo=0.0, lo_open=True, hi=3600.0, default=10.0)
    #: pending connections the kernel queues for the server (listen backlog)
    backlog: int = _f(lo=1, hi=65535, default=512)
    #: file descriptors kept free for the rest of the process (the weld, its files, OpenCV)
    fd_reserve: int = _f(lo=0, hi=1_000_000, default=64)
    #: longest request line / header line accepted (aiohttp); longer is a 400
    max_line_size: int = _f(lo=256, hi=1 << 20, default=8190)
    max_field_size: int = _f(lo=256, hi=1 << 20, default=8190)
    #: malformed requests logged per minute (one line each); the rest are counted, and the
    #: count is given in the next line logged
    bad_requests_logged_per_min: int = _f(lo=0, hi=1_000_000, default=10)
    #: the page's CSP allows ``eval`` ('unsafe-eval'): the page needs none, but browser
    #: automation (Playwright's ``wait_for_function``, the console's browser test) evaluates
    #: its predicates inside the page; injected scripts and handlers are refused either way
    page_allows_eval: bool = _f(default=False)

    def _check(self) -> None:
        if self.max_connections_per_client > self.max_connections:
            raise ValueError(f"max_connections_per_client ({self.max_connections_per_client}) "
                             f"above max_connections ({self.max_connections})")
        if self.max_clients >= self.max_connections_per_client:
            raise ValueError(f"max_clients ({self.max_clients}) must be below "
                             f"max_connections_per_client ({self.max_connections_per_client}): "
                             "each page's stream holds a connection, and a page needs more")


@dataclass(frozen=True)
class PublishSettings:
    rate_hz: float = _f(lo=0.0, lo_open=True, hi=60.0)
    jpeg_rate_hz: float = _f(lo=0.0, lo_open=True, hi=60.0)
    jpeg_quality: int = _f(lo=1, hi=100)
    jpeg_scale: float = _f(lo=0.0, lo_open=True, hi=1.0)
    link_stats_hz: float = _f(lo=0.0, lo_open=True, hi=60.0)


@dataclass(frozen=True)
class HistorySettings:
    frames: int = _f(lo=1)
    commands: int = _f(lo=1)
    messages: int = _f(lo=1)
    latency: int = _f(lo=1)
    nominal_points: int = _f(lo=2)


@dataclass(frozen=True)
class ParamLimits:
    """Inclusive ``[lo, hi]`` of each numeric weld parameter."""

    step_mm: tuple[float, ...] = _f(2, lo=0.0, lo_open=True)
    look_ahead_mm: tuple[float, ...] = _f(2, lo=0.0, lo_open=True)
    weld_speed_mm_s: tuple[float, ...] = _f(2, lo=0.0, lo_open=True)
    length_mm: tuple[float, ...] = _f(2, lo=0.0, lo_open=True)
    seed: tuple[int, ...] = _f(2, lo=0)

    def _check(self) -> None:
        for f in dataclasses.fields(self):
            lo, hi = getattr(self, f.name)
            if lo > hi:
                raise ValueError(f"{f.name}: lower bound {lo} above upper bound {hi}")


@dataclass(frozen=True)
class ConsoleConfig:
    """The operator console (``configs/console.yaml``)."""

    server: ServerSettings
    publish: PublishSettings
    history: HistorySettings
    limits: ParamLimits
    pace: float = _f(lo=0.0)
    rt_priority: int = _f(lo=0, hi=99)  # SCHED_FIFO priority of the paced weld thread; 0: normal


def load_console_config(path: str | Path | None = None) -> ConsoleConfig:
    """The console settings (default ``configs/console.yaml``)."""
    return load_config(ConsoleConfig, path or config_path("console.yaml"))


# --------------------------------------------------------------------------- weld parameters

class ParamError(TorchseamError, ValueError):
    """A weld parameter from the page is missing or out of range (the message says which)."""


@dataclass(frozen=True)
class WeldParams:
    """One weld as the operator set it up (``length_mm`` None: whole segments;
    ``start_offset_mm`` / ``start_angle_deg``: each segment starts that far across the seam /
    turned about the torch axis and searches for it, as ``torchseam demo --start-offset-mm
    --start-angle-deg``; 0: on the seam)."""

    step_mm: float
    look_ahead_mm: float
    weld_speed_mm_s: float
    segments: str
    length_mm: float | None
    noise: float
    seed: int
    faults: tuple[str, ...]
    tracker: str
    start_offset_mm: float = 0.0
    start_angle_deg: float = 0.0

    def apply(self, cell: CellConfig) -> CellConfig:
        """``cell`` with this weld's process settings."""
        proc = dataclasses.replace(cell.process, step_mm=self.step_mm,
                                   look_ahead_mm=self.look_ahead_mm,
                                   weld_speed_mm_s=self.weld_speed_mm_s)
        return dataclasses.replace(cell, process=proc)

    def as_dict(self) -> dict[str, Any]:
        d = dataclasses.asdict(self)
        d["faults"] = list(self.faults)
        return d


#: Longest number the form may send as text, and the largest whole number it may send (far
#: above every limit: a longer one is refused by name before any conversion can fail on it).
MAX_NUMBER_CHARS = 32
MAX_INT_BITS = 64


def _short(v: Any, n: int = 40) -> str:
    """``repr(v)`` clipped for a message (the page shows it; a 5000-digit value would not fit)."""
    r = repr(v)
    return r if len(r) <= n else f"{r[:n - 8]}... ({len(r)} chars)"


def _number(raw: dict[str, Any], name: str, limits: tuple[float, ...], unit: str,
            integer: bool = False) -> float:
    v = raw.get(name)
    if isinstance(v, str):
        v = v.strip()
        if len(v) > MAX_NUMBER_CHARS:
            raise ParamError(f"{name}: {len(v)} characters is too long for a number")
        try:
            v = float(v) if v else None
        except ValueError:
            raise ParamError(f"{name}: {_short(raw.get(name))} is not a number") from None
    if v is None:
        raise ParamError(f"{name}: missing")
    # strictly numbers: JSON's true / false are not (Python's bool is an int)
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise ParamError(f"{name}: {_short(v)} is not a number")
    if isinstance(v, int) and v.bit_length() > MAX_INT_BITS:
        raise ParamError(f"{name}: a {len(str(abs(v)))}-digit number is too large")
    if not math.isfinite(v):
        raise ParamError(f"{name}: {v!r} is not a number")
    lo, hi = limits
    fmt = (lambda x: f"{int(x)}") if integer else (lambda x: f"{x:g}")
    span = f"{fmt(lo)}..{fmt(hi)}" + (f" {unit}" if unit else "")
    if integer and not float(v).is_integer():
        raise ParamError(f"{name} must be a whole number in {span}, got {v:g}")
    if not lo <= v <= hi:
        raise ParamError(f"{name} must be in {span}, got {v:g}")
    return int(v) if integer else float(v)


def _text(raw: dict[str, Any], name: str, max_len: int = 64) -> str:
    """A text field (a JSON string: a list or a number is refused, not turned into text)."""
    v = raw.get(name)
    if not isinstance(v, str):
        raise ParamError(f"{name}: expected text, got {_short(v)}")
    if len(v) > max_len:
        raise ParamError(f"{name}: {len(v)} characters is too long (at most {max_len})")
    return v


def _noise_level(raw: dict[str, Any], noise: NoiseConfig) -> float:
    v = raw.get("noise")
    if isinstance(v, str):
        _text(raw, "noise")
    elif isinstance(v, bool) or not isinstance(v, (int, float)):
        # true would be level 1.0 to float(): a name or a number, nothing else
        raise ParamError(f"noise: expected a level name or a number, got {_short(v)}")
    elif isinstance(v, int) and v.bit_length() > MAX_INT_BITS:
        raise ParamError(f"noise: a {len(str(abs(v)))}-digit number is too large")
    try:
        return noise.level(v.strip() if isinstance(v, str) else v)
    except ValueError as e:
        raise ParamError(f"noise: {e}") from None


def _faults(raw: dict[str, Any], faults: tuple[str, ...]) -> tuple[str, ...]:
    fl = raw.get("faults", [])
    if fl is None:
        fl = []
    if isinstance(fl, str):
        if len(fl) > 256:
            raise ParamError(f"faults: {len(fl)} characters is too long")
        fl = fl.split(",")
    if not isinstance(fl, (list, tuple)):
        raise ParamError(f"faults: expected a list of names, got {_short(fl)}")
    if len(fl) > 4 * len(faults) + 4:
        raise ParamError(f"faults: {len(fl)} entries (there are {len(faults)} faults)")
    out: list[str] = []
    for f in fl:
        if not isinstance(f, str):
            raise ParamError(f"faults: expected fault names, got {_short(f)}")
        f = f.strip()
        if not f:
            continue
        if f not in faults:
            raise ParamError(f"faults: {_short(f)} is not one of {', '.join(faults)}")
        if f in out:
            raise ParamError(f"faults: {f!r} is given twice")
        out.append(f)
    return tuple(out)


def _start_off_seam(raw: dict[str, Any], name: str, bound: float | None, unit: str) -> float:
    """``start_offset_mm`` / ``start_angle_deg``: absent or empty is 0 (on the seam); else a
    number within ``+-bound`` (the search's bound). ``bound`` None: this console cannot start
    off the seam (a replay moves no torch), only 0 passes."""
    v = raw.get(name)
    if v is None or (isinstance(v, str) and not v.strip()):
        return 0.0
    if bound is None:
        if _number(raw, name, (-math.inf, math.inf), unit):
            raise ParamError(f"{name}: this console replays frames (open loop), it moves no "
                             "torch to start off the seam; leave it 0")
        return 0.0
    return _number(raw, name, (-bound, bound), unit)


def parse_params(raw: dict[str, Any], limits: ParamLimits, noise: NoiseConfig,
                 faults: tuple[str, ...], trackers: tuple[str, ...],
                 start_bounds: tuple[float, float] | None = None) -> WeldParams:
    """Check the page's parameter form. Raises :class:`ParamError` naming the field.

    ``start_bounds``: the largest start offset (mm) and angle (deg) off the seam, either side
    (the simulated cell: the seam search's ``max_extent_mm`` and ``max_angle_deg`` of
    ``configs/search.yaml``); None: the console starts on the seam only (a replay)."""
    if not isinstance(raw, dict):
        raise ParamError("parameters: expected a JSON object")
    known = {f.name for f in dataclasses.fields(WeldParams)}
    unknown = sorted(set(raw) - known)
    if unknown:
        raise ParamError(f"{_short(unknown[0])[1:-1]}: unknown parameter (expected "
                         f"{', '.join(sorted(known))})")
    missing = [n for n in ("step_mm", "look_ahead_mm", "weld_speed_mm_s", "segments", "noise",
                           "seed", "tracker") if n not in raw]
    if missing:
        raise ParamError(f"{missing[0]}: missing")
    segs = _text(raw, "segments").strip().lower()
    if not segs or set(segs) - set(SEGMENT_LETTERS) or len(set(segs)) != len(segs):
        raise ParamError(f"segments must be distinct letters from {SEGMENT_LETTERS}, "
                         f"got {_short(raw.get('segments'))}")
    length = raw.get("length_mm")
    if length is None or (isinstance(length, str) and not length.strip()):
        length_mm = None
    else:
        length_mm = _number(raw, "length_mm", limits.length_mm, "mm")
    level = _noise_level(raw, noise)
    fl = _faults(raw, faults)
    tracker = _text(raw, "tracker")
    if tracker not in trackers:
        raise ParamError(f"tracker must be one of {', '.join(trackers)}, got {_short(tracker)}")
    off_mm, off_deg = (None, None) if start_bounds is None else start_bounds
    return WeldParams(
        step_mm=_number(raw, "step_mm", limits.step_mm, "mm"),
        look_ahead_mm=_number(raw, "look_ahead_mm", limits.look_ahead_mm, "mm"),
        weld_speed_mm_s=_number(raw, "weld_speed_mm_s", limits.weld_speed_mm_s, "mm/s"),
        segments="".join(c for c in SEGMENT_LETTERS if c in segs),
        length_mm=length_mm, noise=level,
        seed=int(_number(raw, "seed", limits.seed, "", integer=True)),
        faults=fl, tracker=tracker,
        start_offset_mm=_start_off_seam(raw, "start_offset_mm", off_mm, "mm"),
        start_angle_deg=_start_off_seam(raw, "start_angle_deg", off_deg, "deg"))
