"""Open-loop replay: recorded frames through the live loop, nothing moving.

:func:`run_replay` feeds any frame source (a recording's folder, a video, a camera:
:mod:`torchseam.live.sources`) through a :class:`~torchseam.live.loop.LiveLoop` whose pose sink
moves nothing (a :class:`~torchseam.live.loop.RecordingSink` by default), and reports what the
loop found per frame (:class:`ReplayResult`). Its observer gets the same per-frame events as the
closed-loop demo's (:class:`~torchseam.live.demo.DemoEvent`), so the console and the report
show a replay like a weld. Apart from the loop (the demo imports the loop; the replay imports
both).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from torchseam.core.config import CellConfig
from torchseam.core.errors import TorchseamError
from torchseam.core.transforms import invert, quat_to_matrix
from torchseam.live.events import DemoControl, DemoEvent, FrameRecord
from torchseam.live.loop import Command, LiveLoop, LoopState, PoseSink, RecordingSink
from torchseam.live.parts import LiveParts
from torchseam.track.fusion import TrackStatus
from torchseam.track.peers import FrameTracker

__all__ = ["ReplayResult", "run_replay"]


@dataclass
class ReplayResult:
    """What an open-loop replay of recorded frames found (N frames after the start frame).

    Attributes:
        index: (N,) frame numbers; t_s: (N,) frame times; uv: (N, 2) tracked pixels;
        status: (N,) TrackStatus; label: (N, 2) labelled pixels (NaN: none);
        p: (N, 3) located seam points (base, mm; NaN when not located);
        p_true: (N, 3) true seam points from the recording's meta.json (NaN: none).
        commands: every pose handed to the sink; latency: (p50, p99) ms per loop stage;
        read_ms: (p50, p99) of reading a frame from the source (not part of the loop);
        poses_known: whether the source gave the torch pose of every frame.
    """

    index: np.ndarray
    t_s: np.ndarray
    uv: np.ndarray
    status: np.ndarray
    label: np.ndarray
    p: np.ndarray
    p_true: np.ndarray
    commands: list[Command]
    latency: dict[str, tuple[float, float]]
    read_ms: tuple[float, float]
    poses_known: bool
    start_index: int = 0
    messages: list[str] = field(default_factory=list)
    stopped: bool = False      # ended early by ``control`` (run_replay's operator stop)

    def pixel_errors(self) -> np.ndarray:
        """(M,) px distances tracked-to-label over the frames with a label and a track."""
        d = np.linalg.norm(self.uv - self.label, axis=1)
        return d[np.isfinite(d)]


def run_replay(cell: CellConfig, source: Iterable[Any], tracker: FrameTracker,
               T_B_W: np.ndarray | None = None, uv0: np.ndarray | None = None, *,
               parts: LiveParts, max_frames: int | None = None, sink: PoseSink | None = None,
               truth: dict[int, np.ndarray] | None = None,
               observer: Callable[[DemoEvent], None] | None = None,
               control: DemoControl | None = None) -> ReplayResult:
    """Feed recorded frames through a :class:`LiveLoop` (open loop: nothing moves).

    Each frame's flange pose is the recorded torch pose (``Frame.T_B_W``, from a recording's
    ``meta.json``) times the inverse tool; frames without one use ``T_B_W`` (default: the
    flange at the base origin, so 3D points come out in the flange frame). The loop's torch is
    an ideal follower: it sits on its last target once the recorded torch has come level with
    it along the travel direction (without recorded poses: always), so the loop plans one IPI
    step per step of recorded travel, as in the cell.

    Args:
        cell: calibration and process settings.
        source: iterable of :class:`~torchseam.live.sources.Frame` (any frame source).
        tracker: the feature-point tracker.
        T_B_W: (4, 4) torch pose for frames that carry none.
        uv0: (2,) start pixel (default: TIPM on the first frame, which must be arc-off).
        parts: the loop's settings, TIPM and ECAL (``plan``, ``live``, ``tipm``, ``ecal``;
            :func:`~torchseam.live.parts.load_live_parts` reads the shipped ones).
        max_frames: stop after this many frames.
        sink: where poses go (default a :class:`RecordingSink`).
        truth: frame number -> (3,) true seam point (base, mm), for the 3D error.
        observer: called once per frame (the start frame included, with ``report`` None)
            with a :class:`~torchseam.live.demo.DemoEvent`, as in ``run_demo``: segment
            ``"replay"``, the frame's label as ``uv_true`` and ``truth`` as ``p_true`` (NaN
            where unknown), ``torch_err_mm`` NaN (nothing moves), ``link`` the sink.
        control: a :class:`~torchseam.live.demo.DemoControl`; ``checkpoint()`` runs before
            each frame is read (hold: wait; stop: end here, ``stopped`` True).

    Raises:
        TorchseamError: the start frame shows no usable stripe (names the frame).
    """
    loop = LiveLoop(cell, tracker, sink or RecordingSink(), parts.plan, parts.live, parts.tipm,
                    parts.ecal, open_loop=True)
    tool_inv = invert(cell.tool.matrix())
    fixed = (np.asarray(T_B_W, float) if T_B_W is not None else cell.tool.matrix())
    rows: list[tuple] = []
    commands: list[Command] = []
    read: list[float] = []
    messages: list[str] = []
    poses_known, started, start_index, last_msg = True, False, 0, ""
    stopped = False
    sink = loop.sink
    nan2, nan3 = np.full(2, np.nan), np.full(3, np.nan)
    it = iter(source)
    n = 0
    while max_frames is None or n < max_frames:
        if control is not None and control.checkpoint():
            stopped = True
            messages.append(f"[frame {n}] stopped by {control.stopped_by}")
            break
        t0 = time.perf_counter()
        try:
            fr = next(it)
        except StopIteration:
            break
        read.append((time.perf_counter() - t0) * 1e3)
        n += 1
        rec = fr.T_B_W if fr.T_B_W is not None else fixed
        poses_known &= fr.T_B_W is not None
        if not started:
            try:
                loop.start(fr.image, rec, uv0, t_s=fr.t_s)
            except TorchseamError as e:
                raise TorchseamError(f"frame {fr.index}: {e}") from None
            started, start_index = True, fr.index
            if observer is not None:
                rec0 = FrameRecord("replay", fr.t_s, False, nan2,
                                   fr.label if fr.label is not None else nan2,
                                   int(TrackStatus.LOST), LoopState.STARTING.value, nan3,
                                   truth.get(fr.index, nan3) if truth else nan3, math.nan, "")
                observer(DemoEvent("replay", n - 1, fr.image, rec0, None, np.array(rec, float),
                                   loop, sink))
            continue
        torch_T = np.array(rec, float)
        if loop.target is not None and loop.last_q is not None:
            x = quat_to_matrix(loop.last_q)[:, 0]
            if fr.T_B_W is None or float((rec[:3, 3] - loop.target) @ x) >= 0.0:
                torch_T[:3, 3] = loop.target
        rep = loop.on_frame(fr.image, rec @ tool_inv, torch_T, fr.t_s)
        if rep.command is not None:
            commands.append(rep.command)
        if rep.message and rep.message != last_msg:
            messages.append(f"[frame {fr.index} t={fr.t_s:.2f}s] {rep.state.value}: "
                            f"{rep.message}")
        last_msg = rep.message
        loc = rep.location
        rows.append((fr.index, fr.t_s, loc.uv if loc else nan2,
                     int(loc.status) if loc else int(TrackStatus.LOST),
                     fr.label if fr.label is not None else nan2,
                     loc.p if loc else nan3,
                     truth.get(fr.index, nan3) if truth else nan3))
        if observer is not None:
            r = rows[-1]
            observer(DemoEvent("replay", n - 1, fr.image, FrameRecord(
                "replay", fr.t_s, True, r[2], r[4], r[3], rep.state.value, r[5], r[6],
                math.nan, ""), rep, torch_T, loop, sink))
    if not started and not stopped:
        raise TorchseamError("the source gave no frames")
    close = getattr(source, "close", None)
    if close is not None:
        close()

    def col(i: int, shape: tuple[int, ...]) -> np.ndarray:
        return (np.array([r[i] for r in rows], float) if rows
                else np.zeros((0, *shape)))

    return ReplayResult(
        col(0, ()).astype(int), col(1, ()), col(2, (2,)), col(3, ()).astype(int),
        col(4, (2,)), col(5, (3,)), col(6, (3,)), commands, loop.latency_ms(),
        (float(np.percentile(read, 50)), float(np.percentile(read, 99))) if read
        else (math.nan, math.nan), poses_known, start_index, messages, stopped)
