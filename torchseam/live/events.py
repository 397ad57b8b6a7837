"""The closed loop's events and controls: what an observer of a weld sees once per frame and
how an operator holds, resumes or stops it, whichever cell runs the weld.

The demo (:func:`~torchseam.live.demo.run_demo`: the in-process simulated cell), the weld of a
real or virtual cell (:class:`~torchseam.live.weld.WeldRunner`: frames and EGM over the cell's
interfaces) and the replay (:func:`~torchseam.live.replay.run_replay`: recorded frames, open
loop) all take a ``control`` (:class:`DemoControl`) and call an ``observer`` with a
:class:`DemoEvent` per frame; the operator console drives any of them through these two.
Where a cell does not know the truth (a real cell), the record's truth fields are NaN.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass

import numpy as np

from torchseam.live.loop import LiveLoop, PoseSink, StepReport


@dataclass
class FrameRecord:
    """One frame of a weld as the report and the console keep it; ``uv_true``, ``p_true`` and
    ``torch_err_mm`` are the simulator's truth (NaN where there is none); ``arc_on`` is the arc
    asked for from this frame to the next."""

    seg: str
    t_s: float
    arc_on: bool
    uv: np.ndarray
    uv_true: np.ndarray
    status: int
    state: str
    p: np.ndarray
    p_true: np.ndarray
    torch_err_mm: float
    fault: str


@dataclass
class DemoEvent:
    """What an observer of a weld sees once per frame (the console, say).

    ``frame`` is the BGR camera frame (H, W, 3) uint8 (the loop's input, do not modify);
    ``report`` is ``None`` on the start frame; ``loop`` / ``link`` are the live objects of the
    running segment, to read state and statistics from (not to drive): ``link`` is where the
    loop sends its poses (the demo's :class:`~torchseam.robot.egm.EgmLink`, a replay's sink).
    """

    seg: str
    k: int
    frame: np.ndarray
    record: FrameRecord
    report: StepReport | None
    T_B_W: np.ndarray
    loop: LiveLoop
    link: PoseSink


class DemoControl:
    """Operator control of a running weld, safe to use from another thread.

    ``hold()`` pauses the weld at the next frame (the simulated cell waits with the loop: no
    new target, no motion; a real cell's weld holds the robot where it stands, arc off) until
    ``resume()``; ``stop()`` ends it at the next frame (the
    result holds what was welded so far, ``summary["stopped"]`` is True; ``by`` names who
    stopped it in the segments' reasons, e.g. ``"SIGINT"`` from a signal handler, which may
    call it: it only sets events). ``parked`` says when a hold has taken effect: the weld has
    finished the frame in hand and waits.
    """

    def __init__(self) -> None:
        self._run = threading.Event()
        self._run.set()
        self._stop = threading.Event()
        self._parked = threading.Event()
        self.stopped_by = "the operator"

    def hold(self) -> None:
        self._run.clear()

    def resume(self) -> None:
        self._run.set()

    def stop(self, by: str | None = None) -> None:
        if by and not self._stop.is_set():
            self.stopped_by = by
        self._stop.set()
        self._run.set()

    @property
    def held(self) -> bool:
        return not self._run.is_set()

    @property
    def stopped(self) -> bool:
        return self._stop.is_set()

    @property
    def parked(self) -> bool:
        """The weld is waiting at a held checkpoint (no frame in hand)."""
        return self._parked.is_set()

    def checkpoint(self) -> bool:
        """Block while held; True when the weld must stop."""
        if not self._run.is_set():
            self._parked.set()
            self._run.wait()
            self._parked.clear()
        return self._stop.is_set()
