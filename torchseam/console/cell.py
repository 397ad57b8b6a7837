"""The console wired to a cell through its interfaces (``torchseam console --cell FILE``): the
same weld as ``torchseam weld`` (:class:`~torchseam.live.weld.WeldRunner`), started, held,
resumed and stopped from the page. A real cell (or ``torchseam virtual-cell``) has its own
camera, controller and RAPID program: the page's segments and length apply, its noise, seed
and faults do not (the cell has none to set)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from torchseam.console.config import ConsoleConfig, WeldParams
from torchseam.console.server import ConsoleServer
from torchseam.console.sim import make_console
from torchseam.core.config import CellConfig, NoiseConfig, PartConfig
from torchseam.live.cellfile import WeldCell
from torchseam.live.events import DemoControl, DemoEvent
from torchseam.live.parts import LiveParts
from torchseam.live.weld import WeldResult, WeldRunner, weld_summary

IGNORED = "the cell's own camera and controller; noise, seed and faults do not apply"


@dataclass
class CellWeld:
    """What a cell weld returns to :class:`~torchseam.console.session.WeldSession`."""

    result: WeldResult
    summary: dict[str, Any] = field(default_factory=dict)


def cell_weld(cell: WeldCell, part: PartConfig, report: Any, parts: LiveParts,
              part_name: str
              ) -> Callable[[WeldParams, Callable[[DemoEvent], None], DemoControl], CellWeld]:
    """A weld function for :class:`WeldSession`: a :class:`WeldRunner` on ``cell`` with the
    page's segments, length and tracker (the pre-flight ``report`` of ``part`` passed)."""

    def weld(p: WeldParams, observer: Callable[[DemoEvent], None],
             control: DemoControl) -> CellWeld:
        runner = WeldRunner(cell, report, parts, p.segments, p.length_mm, tracker=p.tracker,
                            progress=lambda m: None, observer=observer, control=control)
        res = runner.run()
        s = weld_summary(res, {"part": part_name, "segments": p.segments,
                               "length_mm": p.length_mm, "tracker": p.tracker})
        # the session's table: what a cell knows (no truth columns)
        s.update(seam_rmse_mm=float("nan"), seam_max_mm=float("nan"),
                 poses_sent=len(res.poses), unsafe_poses_sent=None,
                 stopped=bool(control.stopped))
        return CellWeld(res, s)

    return weld


def cell_console(cfg: ConsoleConfig, cell: WeldCell, part: PartConfig, report: Any,
                 noise: NoiseConfig, parts: LiveParts, part_name: str,
                 defaults: dict[str, Any] | None = None) -> ConsoleServer:
    """A :class:`ConsoleServer` driving ``cell`` (its camera paces the weld)."""
    calib: CellConfig = cell.calibration
    return make_console(cfg, calib, noise, cell_weld(cell, part, report, parts, part_name),
                        0.0, f"cell {cell.camera.source} ({IGNORED})", defaults)
