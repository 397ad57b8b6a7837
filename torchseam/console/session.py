"""The weld behind the console: a worker thread running :func:`run_demo`, and its bounded state.

The observer runs on the weld thread once per frame and must cost microseconds: it keeps a
reference to the newest frame and appends a few numbers to ring buffers (``deque(maxlen=...)``)
under a lock. It never encodes, copies images or touches a socket; the publisher (the server's
event loop) reads from here at its own rate. Everything here is bounded by
``configs/console.yaml: history``, however long the weld or however many clients.
"""

from __future__ import annotations

import collections
import itertools
import math
import sys
import threading
import time
import traceback
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from torchseam.console.config import ConsoleConfig, WeldParams
from torchseam.core.errors import TorchseamError
from torchseam.live.events import DemoControl, DemoEvent
from torchseam.robot.egm import set_realtime_priority


class WeldOutcome(Protocol):
    """What a weld function returns (a demo's :class:`~torchseam.live.demo.DemoResult`, a
    replay's :class:`~torchseam.console.replay.ReplayWeld`): the summary the session shows."""

    @property
    def summary(self) -> dict[str, Any]: ...


#: ``weld(params, observer, control) -> WeldOutcome``: what the session runs on its thread.
WeldFn = Callable[[WeldParams, Callable[[DemoEvent], None], DemoControl], WeldOutcome]


class RunState:
    """The weld's run states as the page shows them."""

    IDLE = "idle"
    RUNNING = "running"
    HELD = "held"
    STOPPING = "stopping"
    FINISHED = "finished"
    STOPPED = "stopped"
    FAILED = "failed"


def num(x: Any, nd: int = 3) -> float | None:
    """A float for JSON: rounded, ``None`` for NaN / inf (JSON has no NaN)."""
    x = float(x)
    return round(x, nd) if math.isfinite(x) else None


class PacedControl(DemoControl):
    """:class:`DemoControl` that also keeps the weld from running faster than ``period_s`` per
    frame (a simulated cell then runs in real time, as a real camera would)."""

    def __init__(self, period_s: float = 0.0) -> None:
        super().__init__()
        self.period_s = period_s
        self._last = -math.inf

    def checkpoint(self) -> bool:
        stop = super().checkpoint()
        if self.period_s > 0 and not stop:
            wait = self._last + self.period_s - time.perf_counter()
            if wait > 0:
                time.sleep(wait)
            self._last = time.perf_counter()
        return stop


@dataclass
class LatestFrame:
    """The newest camera frame and what to draw on it (a reference, not a copy: a source must
    hand the loop a new array per frame, as the simulator does, not refill one buffer)."""

    seq: int
    image: np.ndarray
    uv: tuple[float, float] | None
    uv_true: tuple[float, float] | None
    status: int
    state: str
    seg: str
    t_s: float
    message: str


@dataclass
class _Rings:
    """History of one weld (cleared when a new weld starts)."""

    frames: collections.deque
    commands: collections.deque
    latency: collections.deque
    nominal: dict[str, list[list[float]]] = field(default_factory=dict)
    frame_seq: int = 0
    command_seq: int = 0
    nominal_seq: int = 0


#: Where a client is in the streams: weld id, frame, command, message and nominal-path seqs.
Cursor = tuple[int, int, int, int, int]


class WeldSession:
    """One console's weld: start / hold / resume / stop, and the state the page shows.

    Args:
        cfg: console settings (ring-buffer sizes, pacing).
        weld: runs one weld (see :data:`WeldFn`); the CLI passes the simulated cell.
        frame_period_s: the camera's frame period (pacing; ``cfg.pace`` scales it).
        open_loop: the weld replays frames (a recording, a camera): nothing moves, and the
            simulator's segments, length and faults do not apply (the log says what does).
    """

    def __init__(self, cfg: ConsoleConfig, weld: WeldFn, frame_period_s: float,
                 open_loop: bool = False) -> None:
        self.cfg = cfg
        self.open_loop = open_loop
        self._weld = weld
        self._period = frame_period_s / cfg.pace if cfg.pace > 0 else 0.0
        self.lock = threading.Lock()
        h = cfg.history
        self.messages: collections.deque = collections.deque(maxlen=h.messages)
        self.message_seq = 0
        self.weld_id = 0
        self.state = RunState.IDLE
        self.params: WeldParams | None = None
        self.summary: dict[str, Any] | None = None
        self.error: str | None = None  # why the last weld failed (state FAILED), for the page
        self.latest: LatestFrame | None = None
        self.link: Any = None          # the running segment's EgmLink (its .stats is locked)
        self.loop_stats: dict[str, Any] = {}
        self.started_wall = math.nan
        self.control: PacedControl | None = None
        self._thread: threading.Thread | None = None
        self._rings = self._new_rings()
        self._loop_ref: Any = None
        self._last_msg = ""
        # holds and refusals of the weld's finished segments (each segment has its own loop),
        # and the holds of the running one already logged
        self._done_holds: collections.Counter = collections.Counter()
        self._done_refused: collections.Counter = collections.Counter()
        self._holds_seen = 0
        self.observer_s = 0.0          # time spent in the observer (all frames), s
        # told (on the weld thread) when a frame's record is stored: the publisher does its
        # work then, between frames, rather than beside the loop (ConsoleServer sets it)
        self.frame_done: Callable[[], None] | None = None

    def _new_rings(self) -> _Rings:
        h = self.cfg.history
        return _Rings(collections.deque(maxlen=h.frames), collections.deque(maxlen=h.commands),
                      collections.deque(maxlen=h.latency))

    # ------------------------------------------------------------------ control
    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def start(self, params: WeldParams) -> None:
        """Start a weld on a new thread. Raises ``RuntimeError`` while one runs."""
        with self.lock:
            if self.running:
                raise RuntimeError("a weld is running: stop it before starting another")
            self.weld_id += 1
            self._rings = self._new_rings()
            self._loop_ref, self._last_msg = None, ""
            self._done_holds, self._done_refused = collections.Counter(), collections.Counter()
            self._holds_seen = 0
            self.latest, self.link, self.loop_stats = None, None, {}
            self.params, self.summary, self.error = params, None, None
            self.state = RunState.RUNNING
            self.started_wall = time.time()
            self.control = PacedControl(self._period)
            self._thread = threading.Thread(target=self._run, args=(params, self.control),
                                            name="torchseam-weld", daemon=True)
        plan = (f"step {params.step_mm:g} mm, look-ahead {params.look_ahead_mm:g} mm, speed "
                f"{params.weld_speed_mm_s:g} mm/s")
        if self.open_loop:
            self.log(f"weld {self.weld_id} started (open loop): tracker {params.tracker}, {plan}")
        else:
            self.log(f"weld {self.weld_id} started: segments {params.segments}, {plan}"
                     + (f", {params.length_mm:g} mm per segment" if params.length_mm else "")
                     + (f", faults {', '.join(params.faults)}" if params.faults else ""))
        self._thread.start()

    def hold(self) -> None:
        self._need_running("hold").hold()
        with self.lock:
            self.state = RunState.HELD
        self.log("held by the operator")

    def resume(self) -> None:
        self._need_running("resume").resume()
        with self.lock:
            self.state = RunState.RUNNING
        self.log("resumed by the operator")

    def stop(self, by: str | None = None) -> None:
        """Stop the weld at its next frame; ``by`` names who asked (``"SIGTERM"``: the
        segments' reasons say "stopped by SIGTERM"; None: the operator)."""
        self._need_running("stop").stop(by)
        with self.lock:
            self.state = RunState.STOPPING
        self.log(f"stop requested by {by or 'the operator'}")

    def join(self, timeout: float | None = None) -> bool:
        """Wait for the weld thread; True when it has ended."""
        if self._thread is not None:
            self._thread.join(timeout)
        return not self.running

    def _need_running(self, what: str) -> PacedControl:
        """The running weld's control (raises when none runs)."""
        if not self.running or self.control is None or self.control.stopped:
            raise RuntimeError(f"{what}: no weld is running")
        return self.control

    def _run(self, params: WeldParams, control: PacedControl) -> None:
        prio = self.cfg.rt_priority
        if prio > 0 and self._period > 0:
            # a paced weld sleeps most of each frame period; at real-time priority it gets a
            # core the moment its frame is due, ahead of the browser and this server (flat
            # out, it would keep a core from them)
            if set_realtime_priority(prio, "console weld thread"):
                self.log(f"weld thread at real-time priority {prio} (SCHED_FIFO)")
            else:
                self.log(f"real-time priority {prio} refused for the weld thread (needs "
                         "CAP_SYS_NICE or an RLIMIT_RTPRIO): normal scheduling, so a browser "
                         "on this PC can slow the loop", level="warn")
        try:
            res = self._weld(params, self.observe, control)
        except Exception as e:  # noqa: BLE001 - shown to the operator, the console lives on
            why = failure_text(e)
            with self.lock:
                self.state = RunState.FAILED
                self.error = why
            self.log(f"weld {self.weld_id} failed: {why}", level="error")
            # the terminal gets the same one line (no traceback: the message names the cause)
            print(f"torchseam console: weld {self.weld_id} failed: {why}", file=sys.stderr,
                  flush=True)
            return
        s: dict[str, Any] = {k: (num(v) if isinstance(v, float) else v)
                             for k, v in res.summary.items()}
        with self.lock:
            self.summary = s
            self.state = RunState.STOPPED if s.get("stopped") else RunState.FINISHED
        accuracy = (f"pixel RMSE {s.get('pixel_rmse_px')} px, located RMSE "
                    f"{s.get('located_rmse_mm')} mm" if s.get("open_loop") else
                    f"torch vs seam RMSE {s.get('seam_rmse_mm')} mm, axis RMSE "
                    f"{s.get('axis_rmse_deg')} deg")
        holds, refused = self.hold_counts()
        poses = (f"poses planned (open loop, not sent) {s.get('poses_planned')}"
                 if s.get("open_loop") else f"poses sent {s.get('poses_sent')}")
        self.log(f"weld {'stopped' if s.get('stopped') else 'finished'}: {s.get('frames')} "
                 f"frames, {accuracy}, {poses}, refused {s.get('poses_refused')}, "
                 f"frame->command p99 {s.get('latency_p99_ms')} ms")
        if holds or refused:
            self.log(f"weld {'stopped' if s.get('stopped') else 'finished'} with "
                     f"{_counted(holds, 'hold')} and {_counted(refused, 'refusal')} seen by "
                     "the loop", level="warn")
        for seg in s.get("segments_incomplete") or []:
            self.log(f"segment {seg.get('segment')} not completed: {seg.get('reason')}",
                     level="warn")

    # ------------------------------------------------------------------ the observer
    def observe(self, ev: DemoEvent) -> None:
        """Per-frame hook (weld thread): store references and a few numbers, nothing more."""
        t0 = time.perf_counter()
        r = ev.record
        loop = ev.loop
        new_seg = loop is not self._loop_ref
        if new_seg:
            prev = self._loop_ref
            if prev is not None:  # the finished segment's loop: its counts are final
                with self.lock:
                    self._done_holds.update(prev.stats.hold_reasons)
                    self._done_refused.update(prev.stats.refused)
            self._loop_ref = loop
            self._holds_seen = 0
            nominal = self._subsample(loop.nominal)
        cmd = ev.report.command if ev.report is not None else None
        timings = loop.stats.timings_ms.get("frame->command")
        lat = timings[-1] if timings and ev.report is not None else None
        uv_ok = bool(np.isfinite(r.uv).all())
        p = ev.T_B_W
        rep = ev.report
        msg = rep.message if rep is not None else ""
        with self.lock:
            rings = self._rings
            if new_seg:
                rings.nominal[ev.seg] = nominal
                rings.nominal_seq += 1
            rings.frame_seq += 1
            rings.frames.append((rings.frame_seq, r.seg, r.t_s, r.uv[0] - r.uv_true[0],
                                 r.uv[1] - r.uv_true[1], r.torch_err_mm, r.status, r.state,
                                 r.p_true, r.p, p[:3, 3].copy(), p[:3, :3].copy(), r.fault))
            if cmd is not None:
                rings.command_seq += 1
                rings.commands.append((rings.command_seq, ev.seg, cmd.t_s, cmd.q, cmd.p,
                                       cmd.ok, cmd.reason))
            if lat is not None:
                rings.latency.append(lat)
            self.latest = LatestFrame(
                rings.frame_seq, ev.frame, (r.uv[0], r.uv[1]) if uv_ok else None,
                (r.uv_true[0], r.uv_true[1]), r.status, r.state, ev.seg, r.t_s, msg)
            self.link = ev.link
            st = loop.stats
            self.loop_stats = {"frames": st.frames, "dropped_frames": st.dropped_frames,
                               "sent": st.sent, "holds": st.holds,
                               "refused": dict(st.refused),
                               "hold_reasons": dict(st.hold_reasons)}
        if msg and msg != self._last_msg:
            self.log(f"[{ev.seg} t={r.t_s:.2f}s] {r.state}: {msg}", level="warn")
        self._last_msg = msg
        if st.holds != self._holds_seen:  # a new hold (one line per hold, not per frame)
            self._holds_seen = st.holds
            holds, _ = self.hold_counts()
            self.log(f"[{ev.seg} t={r.t_s:.2f}s] hold ({getattr(loop, 'hold_key', '') or '?'}):"
                     f" arc off; this weld so far: {_counted(holds, 'hold')}", level="warn")
        done = self.frame_done
        if done is not None:
            done()
        self.observer_s += time.perf_counter() - t0

    def _subsample(self, path: np.ndarray | None) -> list[list[float]]:
        if path is None or len(path) == 0:
            return []
        idx = np.linspace(0, len(path) - 1, min(len(path), self.cfg.history.nominal_points))
        return np.round(np.asarray(path)[idx.astype(int)], 2).tolist()

    def hold_counts(self) -> tuple[collections.Counter, collections.Counter]:
        """The weld's loop holds and the poses its link refused, each by reason (all segments
        so far: the finished ones' and the running loop's)."""
        with self.lock:
            holds = collections.Counter(self._done_holds)
            refused = collections.Counter(self._done_refused)
            loop = self._loop_ref
        if loop is not None:
            holds.update(loop.stats.hold_reasons)
            refused.update(loop.stats.refused)
        return holds, refused

    # ------------------------------------------------------------------ messages
    def log(self, text: str, level: str = "info") -> None:
        """Add a line to the message log (any thread)."""
        with self.lock:
            self.message_seq += 1
            self.messages.append((self.message_seq, time.time(), level, text))

    # ------------------------------------------------------------------ reading (publisher)
    def cursor(self) -> Cursor:
        """Where the newest data is (see :data:`Cursor`)."""
        with self.lock:
            return self._cursor()

    def _cursor(self) -> Cursor:
        r = self._rings
        return (self.weld_id, r.frame_seq, r.command_seq, self.message_seq, r.nominal_seq)

    def delta(self, since: Cursor | None) -> tuple[dict[str, Any], Cursor]:
        """Everything newer than cursor ``since`` (``None``: the whole history, a snapshot),
        as plain JSON-able data, and the new cursor. A client whose cursor fell out of the ring
        buffers simply gets what is left (its plots have a gap; nothing grows)."""
        with self.lock:
            rings = self._rings
            new_weld = since is None or since[0] != self.weld_id
            f0, c0, m0, n0 = (0, 0, 0, -1) if since is None else since[1:]
            if new_weld:
                f0, c0, n0 = 0, 0, -1
            frames = _newer(rings.frames, rings.frame_seq, f0)
            cmds = _newer(rings.commands, rings.command_seq, c0)
            msgs = _newer(self.messages, self.message_seq, m0)
            nominal = dict(rings.nominal) if rings.nominal_seq != n0 else None
            cur = self._cursor()
        out: dict[str, Any] = {
            "weld_id": cur[0], "reset": new_weld,
            "frames": {"seq": [f[0] for f in frames],
                       "t": [num(f[2]) for f in frames],
                       "seg": [f[1] for f in frames],
                       "u_err": [num(f[3], 2) for f in frames],
                       "v_err": [num(f[4], 2) for f in frames],
                       "torch_err": [num(f[5]) for f in frames],
                       "status": [f[6] for f in frames],
                       "p_true": [[num(x, 2) for x in f[8]] for f in frames],
                       "p": [[num(x, 2) for x in f[9]] for f in frames],
                       "torch": [[num(x, 2) for x in f[10]] for f in frames]},
            "commands": {"t": [num(c[2]) for c in cmds],
                         "q": [[num(x, 5) for x in c[3]] for c in cmds],
                         "p": [[num(x, 2) for x in c[4]] for c in cmds],
                         "ok": [bool(c[5]) for c in cmds]},
            "messages": [{"seq": m[0], "time": m[1], "level": m[2], "text": m[3]}
                         for m in msgs],
        }
        if nominal is not None:
            out["nominal"] = nominal
        if frames:
            R = frames[-1][11]
            out["torch_pose"] = {"p": [num(x, 2) for x in frames[-1][10]],
                                 "z": [num(x, 4) for x in R[:, 2]],
                                 "x": [num(x, 4) for x in R[:, 0]]}
        return out, cur

    def status(self) -> dict[str, Any]:
        """The small always-sent part: run state, newest frame's numbers, loop counters."""
        with self.lock:
            lf = self.latest
            lat = np.fromiter(self._rings.latency, float)
            out = {"state": self.state, "weld_id": self.weld_id,
                   "held": bool(self.control is not None and self.control.held
                                and self.running),
                   "params": self.params.as_dict() if self.params else None,
                   "summary": self.summary, "error": self.error,
                   "open_loop": self.open_loop, "loop": dict(self.loop_stats),
                   "frame": None if lf is None else {
                       "seq": lf.seq, "seg": lf.seg, "t": num(lf.t_s), "state": lf.state,
                       "status": lf.status, "message": lf.message,
                       "uv": None if lf.uv is None else [num(x, 2) for x in lf.uv]}}
        out["latency_ms"] = ({"p50": num(np.percentile(lat, 50)),
                              "p99": num(np.percentile(lat, 99)), "n": int(lat.size)}
                             if lat.size else None)
        return out


def failure_text(e: BaseException) -> str:
    """One line for the operator saying why a weld failed: a :class:`TorchseamError` (bad
    input: a frame of the wrong size, a source that ended, a start without a stripe) is its
    own message, which names the file, frame or field; anything else is a fault of the
    program, named with its type and where it was raised (file:line), still one line."""
    if isinstance(e, TorchseamError):
        return str(e) or type(e).__name__
    tb = traceback.extract_tb(e.__traceback__)
    where = f" at {Path(tb[-1].filename).name}:{tb[-1].lineno}" if tb else ""
    text = " ".join(str(e).split())
    if len(text) > 300:
        text = text[:297] + "..."
    return f"internal error ({type(e).__name__}{': ' + text if text else ''}{where})"


def _counted(counts: collections.Counter, what: str) -> str:
    """``"3 holds (blind 2, refused 1)"``: a total and its reasons, most frequent first."""
    n = sum(counts.values())
    if not n:
        return f"no {what}s"
    return (f"{n} {what}{'s' if n != 1 else ''} ("
            + ", ".join(f"{k} {v}" for k, v in counts.most_common()) + ")")


def _newer(ring: collections.deque, last_seq: int, since: int) -> list:
    """Items of ``ring`` (seq first, consecutive) with seq > ``since``."""
    n = min(len(ring), max(0, last_seq - since))
    if n == 0:
        return []
    return list(itertools.islice(ring, len(ring) - n, len(ring)))

