"""The console wired to recorded frames: a folder (dataset format) or a video file through the
live loop, open loop, as ``torchseam replay`` runs it.

Nothing moves and no controller is connected: the loop's poses go to a
:class:`~torchseam.live.loop.RecordingSink`. The page's tracker and its step / look-ahead /
speed (``cell.process``) apply; noise, seed, faults, segments and length are the simulator's
and do not (the page's source line says so).
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from torchseam.console.config import ConsoleConfig, WeldParams
from torchseam.console.server import ConsoleServer
from torchseam.console.sim import make_console
from torchseam.core.config import CellConfig, NoiseConfig
from torchseam.core.errors import FrameError
from torchseam.live.events import DemoControl, DemoEvent
from torchseam.live.parts import LiveParts
from torchseam.live.replay import ReplayResult, run_replay
from torchseam.live.sources import CameraSource, FolderSource, open_source

#: Shown on the page next to the source: the form fields a replay ignores.
IGNORED = "open loop, no controller; noise, seed, faults, segments and length do not apply"


@dataclass
class ReplayWeld:
    """What a replay weld returns to :class:`~torchseam.console.session.WeldSession`: the
    replay's result and the ``summary`` the session shows (NaN / None where not known)."""

    result: ReplayResult
    summary: dict[str, Any] = field(default_factory=dict)


def _truth(source: Any) -> dict[int, np.ndarray] | None:
    """Frame number -> true seam point from a recording's ``meta.json`` (``seam_mm``)."""
    meta = getattr(getattr(source, "ds", None), "meta", None)
    if not meta or not isinstance(meta.get("frames"), list):
        return None
    return {int(e["frame"]): np.asarray(e["seam_mm"], float)
            for e in meta["frames"] if "seam_mm" in e and "frame" in e} or None


def replay_summary(res: ReplayResult) -> dict[str, Any]:
    """The session's summary keys for an open-loop replay."""

    def rms(x: np.ndarray) -> float:
        return float(np.sqrt(np.mean(x**2))) if len(x) else math.nan

    pix = res.pixel_errors()
    d = np.linalg.norm(res.p - res.p_true, axis=1)
    d = d[np.isfinite(d)]
    lat = res.latency.get("frame->command", (math.nan, math.nan))
    return {
        # the start frame too, when one was read (a stop before it reads none)
        "frames": len(res.index) + (0 if math.isnan(res.read_ms[0]) else 1),
        "seam_rmse_mm": math.nan, "seam_max_mm": math.nan,   # no torch moves in a replay
        "located_rmse_mm": rms(d), "pixel_rmse_px": rms(pix),
        "latency_p50_ms": lat[0], "latency_p99_ms": lat[1],
        # open loop: the loop plans poses and a RecordingSink keeps them; none is sent to a
        # robot (``torchseam replay``'s "poses planned (open loop, not sent)")
        "poses_planned": sum(c.ok for c in res.commands),
        "poses_refused": sum(not c.ok for c in res.commands),
        "poses_sent": 0, "unsafe_poses_sent": 0, "open_loop": True, "stopped": res.stopped,
    }


def replay_weld(cell: CellConfig, path: str | os.PathLike[str], parts: LiveParts,
                joint: str = "fillet"
                ) -> Callable[[WeldParams, Callable[[DemoEvent], None], DemoControl], ReplayWeld]:
    """A weld function for :class:`WeldSession`: :func:`run_replay` of ``path`` (opened anew
    for every weld) with the page's tracker and process settings and ``parts``; ``joint``: the
    joint in the frames (:meth:`LiveParts.tracker`)."""

    def weld(p: WeldParams, observer: Callable[[DemoEvent], None],
             control: DemoControl) -> ReplayWeld:
        c = p.apply(cell)
        source = open_source(path, (c.camera.width, c.camera.height))
        with source:
            res = run_replay(c, source, parts.tracker(p.tracker, joint), parts=parts,
                             truth=_truth(source), observer=observer, control=control)
        return ReplayWeld(res, replay_summary(res))

    return weld


def replay_console(path: str | os.PathLike[str], cfg: ConsoleConfig, cell: CellConfig,
                   noise: NoiseConfig, parts: LiveParts,
                   defaults: dict[str, Any] | None = None, joint: str = "fillet"
                   ) -> ConsoleServer:
    """A :class:`ConsoleServer` running the recorded folder, video file or live camera at
    ``path`` (see :func:`~torchseam.live.sources.open_source`) open loop, with these settings
    (the command line reads them; :func:`~torchseam.live.parts.load_live_parts` the shipped
    ``parts``).

    Raises:
        DatasetError / FrameError: nothing readable at ``path``, or its first frame cannot be
            decoded or has the wrong format or size (named, as ``torchseam replay`` names
            it), found here, before anything is served.
    """
    with open_source(path, (cell.camera.width, cell.camera.height)) as src:
        inner = getattr(src, "source", src)  # a camera comes wrapped in a ThreadedSource
        kind, name = {FolderSource: ("recorded folder", str(Path(path))),
                      CameraSource: ("live camera", str(path))}.get(
            type(inner), ("video file", str(Path(path))))
        fps = getattr(inner, "fps", None)
        # the first frame through the source's own checks (decodes, format, the camera's
        # size), the ones a replay makes: a source the weld would fail on is refused now
        if next(iter(src), None) is None:
            raise FrameError(f"{name}: the source gave no frames")
    period = 1.0 / fps if fps and fps > 0 else 1.0 / cell.process.frame_rate_hz
    if kind == "live camera":
        period = 0.0  # a camera paces itself; pacing on top would only drop frames
    return make_console(cfg, cell, noise, replay_weld(cell, path, parts, joint), period,
                        f"{kind} {name} ({IGNORED})", defaults, open_loop=True)
