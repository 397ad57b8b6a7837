"""One runner for every weld: a segment's frames in; torch poses, the arc request and events out.

The demo (the simulated cell in this process, in lockstep), ``torchseam weld`` (a real cell, or
the virtual one, through its interfaces) and the console driving either weld each segment
with :func:`run_segment`. What differs between them is the cell (:class:`SegmentCell`):
where a frame and the torch's pose at its exposure time come from, how the arc request and a
hold reach the robot, and who may take the segment back. What the weld decides is here, once:

- **the start**: the first frame with the stripe's corner in it starts the loop (retried for
  ``start_timeout_s`` of frames, then the segment is not welded, with TIPM's reason);
- **the travel**: from the torch's pose at each frame's exposure, plus how far the torch has
  gone since (the cell's newest pose): the segment ends where the torch is;
- **the arc**: asked for past the approach while the loop lets it
  (:attr:`~torchseam.live.loop.LiveLoop.arc_ok`) and the torch moves, decided once a frame a
  frame's travel early (so it burns when the torch passes the approach's end);
- **the gaps**: the seam passed with the arc out (:class:`ArcGapMeter`, fed by the cell from
  every pose it knows) with where and why; more than :data:`MAX_GAP_MM` and the segment is not
  welded, whatever else happened;
- **the operator** (:class:`~torchseam.live.events.DemoControl`): a hold puts the arc out and
  holds the robot where it stands until resumed; a stop ends the segment (and the weld);
- **the events**: one :class:`~torchseam.live.events.DemoEvent` per frame for the console.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from torchseam.core.errors import TorchseamError
from torchseam.live.events import DemoControl, DemoEvent, FrameRecord
from torchseam.live.loop import Command, LiveLoop, StepReport

#: seam passed with the arc out past the approach, per segment, above which the segment is not
#: welded (a gap in the bead). Not zero: the arc is decided once a frame, so a stretch passed
#: with the arc out is known to within a frame's travel (0.32 mm at 8 mm/s and 25 frames/s).
MAX_GAP_MM = 0.5
#: the torch moves when it went at least this fraction of the weld speed over the last
#: MOVING_WINDOW_S (decided once a frame, the arc asked for only then)
MOVING_FRACTION = 0.2
MOVING_WINDOW_S = 0.1
#: the link's replies check every EGM cycle that the torch is not standing (slower than
#: STANDING_MM_S over REPLY_MOVING_WINDOW_S), so that a torch left standing between two frames
#: (a loop that fell behind) has the arc out within a few cycles, not at the next frame
STANDING_MM_S = 0.5
REPLY_MOVING_WINDOW_S = 0.04


@dataclass(frozen=True)
class CellFrame:
    """One frame as the cell delivers it.

    Attributes:
        image: (H, W, 3) uint8; None: the frame was lost on the way (the loop coasts).
        t_s: its exposure time on the loop's clock (s).
        T_B_W: (4, 4) the torch's pose at that time (mm, base frame): the controller's
            fed-back pose interpolated there (a real cell), the simulated arm's (the demo).
    """

    image: np.ndarray | None
    t_s: float
    T_B_W: np.ndarray


class SegmentCell(Protocol):
    """What :func:`run_segment` needs of a cell during one segment."""

    gap: ArcGapMeter

    def next_frame(self) -> CellFrame | str | None:
        """The next frame; None: none this time (the cell waits, holds, counts); a str: the
        segment cannot go on (the reason)."""

    def torch_now(self) -> np.ndarray | None:
        """(3,) where the torch is now (its newest pose), None: where the last frame saw it."""

    def moving(self) -> bool:
        """The torch moves (the arc is never asked for over a torch that stands)."""

    def set_arc(self, on: bool) -> None:
        """The arc request until the next frame."""

    def hold_here(self) -> None:
        """Hold the robot where it stands."""

    def guided(self) -> str:
        """'' while the cell lets the loop guide this segment, else why not."""

    def label(self, t_s: float | None = None) -> str:
        """The prefix of this segment's messages."""

    def record(self, f: CellFrame, rep: StepReport | None, arc: bool,
               along_mm: float) -> FrameRecord:
        """What the report and the console keep of a frame (the cell adds what it knows: the
        truth, in the demo). ``arc``: the arc asked for from this frame to the next."""


@dataclass
class ArcGapMeter:
    """The seam passed with the arc out, from every pose the cell knows of the torch.

    The path the torch tip travelled from the segment's start (``start_mm`` when it starts
    into the approach); of it, the stretch between ``zone_mm`` (the approach's end) and
    ``end_mm`` (the segment's) passed while the arc was not burning: ``gap_mm`` in all, and
    each stretch with where it lies along the segment and when and why the arc went out.
    The loop does not go back over a gap: the cell reports how much instead."""

    path_mm: float = 0.0
    passed_mm: float = 0.0
    gap_mm: float = 0.0
    zone_mm: float = float("inf")
    end_mm: float = float("inf")
    stretches: list[dict[str, Any]] = field(default_factory=list)
    _p: np.ndarray | None = None
    _open: dict[str, Any] | None = None
    _out: tuple[float, str] | None = None

    def reset(self, zone_mm: float, end_mm: float = float("inf"), start_mm: float = 0.0
              ) -> None:
        self.path_mm, self.passed_mm, self.gap_mm = start_mm, 0.0, 0.0
        self.zone_mm, self.end_mm = zone_mm, end_mm
        self.stretches, self._p, self._open, self._out = [], None, None, None

    def arc_out(self, t_s: float, cause: str) -> None:
        """The arc went out at ``t_s`` for ``cause`` (the stretch that follows says so)."""
        self._out = (t_s, cause)

    def add(self, p: np.ndarray, arc: bool) -> None:
        """The torch is at ``p`` (3,); it came from the previous pose with the arc ``arc``."""
        p = np.asarray(p, float)
        if self._p is not None:
            a = self.path_mm
            self.path_mm = b = a + float(np.linalg.norm(p - self._p))
            lo, hi = max(a, self.zone_mm), min(b, self.end_mm)
            if hi > lo:
                self.passed_mm += hi - lo
                if arc:
                    self._open = None
                else:
                    self.gap_mm += hi - lo
                    if self._open is None:
                        t_out, cause = self._out if self._out is not None else (None, "")
                        self._open = {"from_mm": lo - self.zone_mm, "to_mm": hi - self.zone_mm,
                                      "arc_out_t_s": t_out,
                                      "cause": cause or "before the arc first struck"}
                        self.stretches.append(self._open)
                    self._open["to_mm"] = hi - self.zone_mm
        self._p = p

    def reason(self) -> str:
        """Why the segment is not welded for its gaps ('' within :data:`MAX_GAP_MM`)."""
        if self.gap_mm <= MAX_GAP_MM:
            return ""
        parts = []
        for g in self.stretches:
            n = g["to_mm"] - g["from_mm"]
            where = f"{n:.1f} mm from {g['from_mm']:.1f} mm into the segment"
            parts.append(where + (" before the arc first struck" if g["arc_out_t_s"] is None
                                  else f" after the arc went out at t={g['arc_out_t_s']:.2f} s "
                                       f"({g['cause']})"))
        return (f"{self.gap_mm:.1f} mm of seam unwelded (more than {MAX_GAP_MM:g} mm): "
                + ", ".join(parts))


@dataclass(frozen=True)
class SegmentJob:
    """One segment to weld.

    Attributes:
        name: its letter.
        approach_mm: the approach (arc out) before the seam to weld.
        length_mm: the seam to weld after it.
        frame_mm: the torch's travel in a frame at weld speed (the arc strikes that early).
        frame_s: the frame period (s).
        tool_inv: (4, 4) the tool's inverse (torch pose -> flange pose).
        start_along_mm: where along the path the loop starts (a search's approach ends there).
        start_timeout_s: how long (frame time) the start may wait for a frame with a corner.
    """

    name: str
    approach_mm: float
    length_mm: float
    frame_mm: float
    frame_s: float
    tool_inv: np.ndarray
    start_along_mm: float = 0.0
    start_timeout_s: float = 2.0


@dataclass
class SegmentRun:
    """What :func:`run_segment` did.

    Attributes:
        reached_end: the torch reached the segment's end.
        reason: why not ('' when it did): the cell's, the start's, the operator's.
        stopped: the operator stopped it.
        travelled_mm: along the path from the approach's start.
        frames: frames the cell delivered.
        commands: every pose handed to the link; ``welding``: the arc was asked for then.
        arc_off_s: past the approach with the arc out (frame time); ``arc_interruptions``:
            times the arc went out there.
    """

    reached_end: bool = False
    reason: str = ""
    stopped: bool = False
    travelled_mm: float = 0.0
    frames: int = 0
    commands: list[Command] = field(default_factory=list)
    welding: list[bool] = field(default_factory=list)
    arc_off_s: float = 0.0
    arc_interruptions: int = 0


def run_segment(cell: SegmentCell, loop: LiveLoop, job: SegmentJob, *,
                control: DemoControl | None = None,
                observer: Callable[[DemoEvent], None] | None = None,
                link: Any = None, messages: list[str] | None = None) -> SegmentRun:
    """Weld one segment: the cell's frames through ``loop`` to the segment's end (or until the
    cell, the start or the operator ends it). See the module's docstring for what it decides.

    ``messages`` gets the loop's messages (a new one each time it changes), the operator's
    holds and stops, each prefixed by the cell's :meth:`~SegmentCell.label`; ``observer`` one
    :class:`~torchseam.live.events.DemoEvent` per frame (``link``: the one the event names)."""
    return _Segment(cell, loop, job, control, observer, link,
                    messages if messages is not None else []).run()


class _Segment:
    """The state of one :func:`run_segment`."""

    def __init__(self, cell: SegmentCell, loop: LiveLoop, job: SegmentJob,
                 control: DemoControl | None, observer: Callable[[DemoEvent], None] | None,
                 link: Any, messages: list[str]) -> None:
        self.cell, self.loop, self.job = cell, loop, job
        self.control, self.observer, self.link, self.msgs = control, observer, link, messages
        self.out = SegmentRun(travelled_mm=job.start_along_mm)
        self.started, self.held, self.arc, self.last_msg = False, False, False, ""
        self.prev: np.ndarray | None = None
        self.t_first: float | None = None
        self.t_s: float | None = None
        self.shown: np.ndarray | None = None   # the newest image (a lost frame shows it)

    def run(self) -> SegmentRun:
        cell, out = self.cell, self.out
        cell.gap.reset(self.job.approach_mm, self.job.approach_mm + self.job.length_mm,
                       self.job.start_along_mm)
        try:
            while not self._operator_stops():
                why = cell.guided()
                if why:
                    out.reason = why
                    break
                f = cell.next_frame()
                if f is None:
                    continue
                if isinstance(f, str):
                    out.reason = f
                    break
                out.frames += 1
                self.t_s = f.t_s
                self.shown = f.image if f.image is not None else self.shown
                if not self.started:
                    if not self._start(f):
                        break
                elif self._frame(f):
                    break
        finally:
            cell.set_arc(False)
        return out

    def _operator_stops(self) -> bool:
        """A hold: arc out, the robot held where it stands, until resumed; True on a stop."""
        c, cell = self.control, self.cell
        if c is None:
            return False
        if c.held and not self.held:
            self.held = True
            cell.set_arc(False)
            cell.hold_here()
            self.msgs.append(f"{cell.label(self.t_s)} held by the operator: arc off, robot held")
        if c.checkpoint():
            self.out.stopped = True
            self.out.reason = f"stopped by {c.stopped_by}"
            self.msgs.append(f"{cell.label(self.t_s)} {self.out.reason}")
            return True
        self.held = False
        return False

    def _start(self, f: CellFrame) -> bool:
        """The loop's start on ``f`` when it shows the corner; False: give up."""
        job = self.job
        if f.image is None:
            return True
        self.t_first = f.t_s if self.t_first is None else self.t_first
        try:
            self.loop.start(f.image, f.T_B_W, t_s=f.t_s)
        except TorchseamError as e:
            if f.t_s - self.t_first > job.start_timeout_s:
                self.out.reason = f"no start frame in {job.start_timeout_s:g} s: {e}"
                return False
            return True
        self.started, self.prev = True, f.T_B_W[:3, 3]
        self._emit(f, None, self.out.travelled_mm)
        return True

    def _frame(self, f: CellFrame) -> bool:
        """One frame of the loop; True when the torch reached the segment's end."""
        cell, loop, job, out = self.cell, self.loop, self.job, self.out
        p = f.T_B_W[:3, 3]
        out.travelled_mm += float(np.linalg.norm(p - self.prev))
        self.prev = p
        # where the torch is now: the frame's pose is the latency and the frame's handling
        # old (the arc strikes, and the segment ends, where the torch is)
        now = cell.torch_now()
        along = out.travelled_mm + (0.0 if now is None else float(np.linalg.norm(now - p)))
        if along >= job.approach_mm + job.length_mm:
            out.reached_end = True
            return True
        rep = loop.on_frame(f.image, f.T_B_W @ job.tool_inv, f.T_B_W, f.t_s)
        # the arc strikes a frame's travel early: decided once a frame, it then burns until
        # the next (struck later, the frame's travel past the approach's end is unwelded)
        on = bool(along + job.frame_mm >= job.approach_mm and loop.arc_ok and cell.moving())
        if along >= job.approach_mm and not on:
            out.arc_off_s += job.frame_s
            if self.arc:
                out.arc_interruptions += 1
                cell.gap.arc_out(f.t_s, f"{loop.state.value}: {loop.hold_key}"
                                 if loop.hold_key else loop.state.value)
        self.arc = on
        cell.set_arc(on)
        if rep.command is not None:       # (the robot goes there with the arc as set now)
            out.commands.append(rep.command)
            out.welding.append(on)
        if rep.message and rep.message != self.last_msg:
            self.msgs.append(f"{cell.label(f.t_s)} {rep.state.value}: {rep.message}")
        self.last_msg = rep.message
        self._emit(f, rep, along)
        return False

    def _emit(self, f: CellFrame, rep: StepReport | None, along: float) -> None:
        rec = self.cell.record(f, rep, self.arc, along)
        if self.observer is not None and self.shown is not None:
            self.observer(DemoEvent(self.job.name, self.out.frames - 1, self.shown, rec, rep,
                                    f.T_B_W, self.loop, self.link))


__all__ = ["MAX_GAP_MM", "MOVING_FRACTION", "MOVING_WINDOW_S", "REPLY_MOVING_WINDOW_S",
           "STANDING_MM_S", "ArcGapMeter", "CellFrame", "SegmentCell", "SegmentJob", "SegmentRun",
           "run_segment"]
