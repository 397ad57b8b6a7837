"""The one runner (torchseam/live/runner.py) on a scripted cell: what it decides, against the
cell's own record of where the torch went and what the arc did.

The scripted cell moves the torch along x at a set speed per frame (standing still where the
script says), and keeps, per frame interval, the arc the runner asked for: the ground truth the
runner's figures (travel, gaps, arc-off time) are checked against. The loop is a stand-in with
the live loop's interface whose ``arc_ok`` follows a script (a hold), so that each rule is seen
on its own; the real loop runs through the same runner in tests/test_live.py and
tests/test_weld_cell.py.
"""

from __future__ import annotations

import numpy as np
import pytest

from torchseam.core.errors import TorchseamError
from torchseam.live.events import DemoControl, FrameRecord
from torchseam.live.loop import LoopState
from torchseam.live.runner import MAX_GAP_MM, ArcGapMeter, CellFrame, SegmentJob, run_segment

FRAME_MM, FRAME_S = 0.32, 0.04


class Rep:
    def __init__(self) -> None:
        self.command = None
        self.message = ""
        self.state = LoopState.TRACKING
        self.location = None


class ScriptLoop:
    """The live loop's interface; ``arc_ok`` False on the frames in ``hold``; ``start`` fails
    on the first ``no_corner`` frames."""

    def __init__(self, hold: range = range(0), no_corner: int = 0) -> None:
        self.hold, self.no_corner = hold, no_corner
        self.k, self.starts = 0, 0
        self.arc_ok, self.state, self.hold_key = True, LoopState.TRACKING, ""

    def start(self, image, T_B_W, t_s=None) -> None:
        self.starts += 1
        if self.starts <= self.no_corner:
            raise TorchseamError("TIPM found no corner")

    def on_frame(self, image, T_B_F, T_B_W, t_s) -> Rep:
        self.k += 1
        held = self.k in self.hold
        self.arc_ok = not held
        self.state = LoopState.HOLD if held else LoopState.TRACKING
        self.hold_key = "blind" if held else ""
        return Rep()


class ScriptCell:
    """The torch moves ``FRAME_MM`` along x a frame, except in ``still`` (frame numbers)."""

    def __init__(self, still: range = range(0), n: int = 1000) -> None:
        self.gap = ArcGapMeter()
        self.still, self.n = still, n
        self.k, self.x, self.arc = 0, 0.0, False
        self.arcs: list[tuple[float, float, bool]] = []   # (x from, x to, arc) per interval
        self.holds = 0

    def next_frame(self):
        if self.k >= self.n:
            return "out of frames"
        if self.k:
            x0 = self.x
            if self.k not in self.still:
                self.x += FRAME_MM
            self.arcs.append((x0, self.x, self.arc))
        self.k += 1
        T = np.eye(4)
        T[0, 3] = self.x
        self.gap.add(T[:3, 3], self.arc)
        return CellFrame(np.zeros((4, 4, 3), np.uint8), self.k * FRAME_S, T)

    def torch_now(self):
        return None

    def moving(self) -> bool:
        return self.k not in self.still and (self.k - 1) not in self.still

    def set_arc(self, on: bool) -> None:
        self.arc = on

    def hold_here(self) -> None:
        self.holds += 1

    def guided(self) -> str:
        return ""

    def label(self, t_s=None) -> str:
        return "[x]"

    def record(self, f, rep, arc, along_mm) -> FrameRecord:
        n2, n3 = np.full(2, np.nan), np.full(3, np.nan)
        return FrameRecord("x", f.t_s, arc, n2, n2, 0, "", n3, n3, float("nan"), "")


def job(approach=5.0, length=10.0) -> SegmentJob:
    return SegmentJob("x", approach, length, FRAME_MM, FRAME_S, np.eye(4))


def unwelded(cell: ScriptCell, approach: float, length: float) -> float:
    """The seam (approach .. approach + length along x) passed with the arc out, from the
    cell's own record."""
    return sum(max(0.0, min(b, approach + length) - max(a, approach))
               for a, b, arc in cell.arcs if not arc)


def test_arc_strikes_at_the_approach_end_and_the_segment_ends_where_asked():
    cell, loop = ScriptCell(), ScriptLoop()
    run = run_segment(cell, loop, job(), messages=[])
    assert run.reached_end and run.reason == ""
    assert run.travelled_mm == pytest.approx(15.0, abs=FRAME_MM)
    # no seam passed with the arc out: it struck a frame's travel early
    assert unwelded(cell, 5.0, 10.0) == 0.0 and cell.gap.gap_mm == 0.0
    first_arc = min(a for a, _, arc in cell.arcs if arc)
    assert 5.0 - FRAME_MM - 1e-9 <= first_arc <= 5.0
    assert not cell.arc       # out at the end


def test_a_hold_puts_the_arc_out_and_the_gap_is_measured_with_its_cause():
    cell, loop = ScriptCell(), ScriptLoop(hold=range(30, 40))
    msgs: list[str] = []
    run = run_segment(cell, loop, job(), messages=msgs)
    truth = unwelded(cell, 5.0, 10.0)
    assert truth > MAX_GAP_MM
    assert cell.gap.gap_mm == pytest.approx(truth, abs=1e-9)
    assert run.arc_interruptions == 1 and run.arc_off_s == pytest.approx(10 * FRAME_S)
    (g,) = cell.gap.stretches
    assert g["to_mm"] - g["from_mm"] == pytest.approx(truth)
    assert g["cause"] == "hold: blind" and g["arc_out_t_s"] is not None
    assert f"{truth:.1f} mm of seam unwelded" in cell.gap.reason()


def test_no_arc_over_a_torch_that_stands():
    cell, loop = ScriptCell(still=range(25, 35)), ScriptLoop()
    run_segment(cell, loop, job(), messages=[])
    # every interval the torch stood (after the arc first struck) went with the arc out
    standing = [arc for a, b, arc in cell.arcs if a == b and a > 5.0]
    assert standing and not any(standing)


def test_the_start_waits_for_a_corner_then_gives_up_with_the_reason():
    cell, loop = ScriptCell(), ScriptLoop(no_corner=5)
    run = run_segment(cell, loop, job(), messages=[])
    assert run.reached_end and loop.starts == 6
    cell, loop = ScriptCell(), ScriptLoop(no_corner=10_000)
    run = run_segment(cell, loop, job(), messages=[])
    assert not run.reached_end and run.reason.startswith("no start frame in 2 s: TIPM found")
    assert run.frames == int(2.0 / FRAME_S) + 2
    assert not any(arc for *_, arc in cell.arcs)


def test_the_operator_stops_and_the_cell_ends_the_segment_with_its_reason():
    control = DemoControl()
    control.stop("SIGTERM")
    cell = ScriptCell()
    msgs: list[str] = []
    run = run_segment(cell, ScriptLoop(), job(), control=control, messages=msgs)
    assert run.stopped and run.reason == "stopped by SIGTERM" and run.frames == 0
    assert msgs == ["[x] stopped by SIGTERM"]
    cell = ScriptCell(n=20)
    run = run_segment(cell, ScriptLoop(), job(), messages=[])
    assert not run.reached_end and run.reason == "out of frames"
    assert not cell.arc


def test_gap_meter_counts_only_the_seam_between_approach_and_end():
    m = ArcGapMeter()
    m.reset(zone_mm=2.0, end_mm=5.0)
    for x in np.arange(0.0, 8.01, 0.5):
        m.add(np.array([x, 0.0, 0.0]), arc=False)
    assert m.gap_mm == pytest.approx(3.0) and m.passed_mm == pytest.approx(3.0)
    (g,) = m.stretches
    assert (g["from_mm"], g["to_mm"]) == (pytest.approx(0.0), pytest.approx(3.0))
    assert g["cause"] == "before the arc first struck" and g["arc_out_t_s"] is None
