"""The console wired to the simulated cell: the same closed-loop weld as ``torchseam demo``."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from torchseam.console.config import SEGMENT_LETTERS, ConsoleConfig, WeldParams, parse_params
from torchseam.console.server import ConsoleServer
from torchseam.console.session import WeldFn, WeldSession
from torchseam.core.config import CellConfig, NoiseConfig, PartConfig
from torchseam.live.demo import DemoResult, run_demo
from torchseam.live.events import DemoControl, DemoEvent
from torchseam.live.names import FAULTS
from torchseam.live.parts import LiveParts
from torchseam.track.peers import TRACKERS

#: Form defaults that are not in ``cell.yaml`` (the demo's own defaults).
DEMO_DEFAULTS: dict[str, Any] = {"segments": SEGMENT_LETTERS, "length_mm": None,
                                 "noise": "heavy", "seed": 0, "faults": [],
                                 "tracker": "anchored", "start_offset_mm": 0.0,
                                 "start_angle_deg": 0.0}


def sim_weld(cell: CellConfig, part: PartConfig, noise: NoiseConfig, parts: LiveParts
             ) -> Callable[[WeldParams, Callable[[DemoEvent], None], DemoControl], DemoResult]:
    """A weld function for :class:`WeldSession`: :func:`run_demo` with the page's parameters
    and ``parts``."""

    def weld(p: WeldParams, observer: Callable[[DemoEvent], None],
             control: DemoControl) -> DemoResult:
        return run_demo(p.apply(cell), part, noise, p.noise, p.seed, p.faults, p.segments,
                        p.tracker, length_mm=p.length_mm, observer=observer, control=control,
                        start_offset_mm=p.start_offset_mm, start_angle_deg=p.start_angle_deg,
                        parts=parts)

    return weld


def simulated_console(cfg: ConsoleConfig, cell: CellConfig, part: PartConfig,
                      noise: NoiseConfig, parts: LiveParts,
                      defaults: dict[str, Any] | None = None) -> ConsoleServer:
    """A :class:`ConsoleServer` driving the simulated cell with these settings (the command
    line reads them; :func:`~torchseam.live.parts.load_live_parts` the shipped ``parts``);
    ``defaults`` overrides the parameter form's initial values."""
    search = parts.search
    return make_console(cfg, cell, noise, sim_weld(cell, part, noise, parts),
                        1.0 / cell.process.frame_rate_hz, "simulated cell", defaults,
                        start_bounds=(search.max_extent_mm, search.max_angle_deg))


def make_console(cfg: ConsoleConfig, cell: CellConfig, noise: NoiseConfig, weld: WeldFn,
                 frame_period_s: float, source: str,
                 defaults: dict[str, Any] | None = None,
                 open_loop: bool = False,
                 start_bounds: tuple[float, float] | None = None) -> ConsoleServer:
    """A :class:`ConsoleServer` running ``weld`` with the demo's parameter form (initial
    values from ``cell``'s process settings, overridden by ``defaults``; a start request that
    leaves a field out gets its initial value); ``source`` is what
    the page shows as the frame source, ``open_loop`` says it replays frames.
    ``start_bounds``: the largest start offset (mm) and angle (deg) off the seam the form
    takes (None: it starts on the seam only)."""
    proc = cell.process
    form = {"step_mm": proc.step_mm, "look_ahead_mm": proc.look_ahead_mm,
            "weld_speed_mm_s": proc.weld_speed_mm_s, **DEMO_DEFAULTS, **(defaults or {})}
    session = WeldSession(cfg, weld, frame_period_s, open_loop)

    def validate(raw: dict[str, Any]) -> WeldParams:
        # a field the request leaves out takes the form's default (the config's and the
        # command line's values: --segments, --length-mm, ...), as the page would send it;
        # one sent empty or null is the request's own (an empty length: whole segments)
        if isinstance(raw, dict):
            raw = {**form, **raw}
        return parse_params(raw, cfg.limits, noise, FAULTS, TRACKERS, start_bounds)

    validate(form)  # the defaults themselves must pass (a bad --length-mm, say)
    choices = {"noise": list(noise.levels), "faults": list(FAULTS), "trackers": list(TRACKERS),
               "segments": SEGMENT_LETTERS}
    extra = {} if start_bounds is None else {
        "start_offset_mm": [-start_bounds[0], start_bounds[0]],
        "start_angle_deg": [-start_bounds[1], start_bounds[1]]}
    return ConsoleServer(cfg, session, validate, form, choices, source=source,
                         extra_limits=extra)
