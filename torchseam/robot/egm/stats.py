"""Counters of the EGM link and the latency summaries the link, the simulated controller and
the benchmarks print."""

from __future__ import annotations

import collections
import dataclasses
import math
from dataclasses import dataclass, field
from typing import Any, NamedTuple

import numpy as np


class LateReply(NamedTuple):
    """One late reply of the link, by where its time went (wall-clock ns / ms).

    A reply answers the newest of the ``EgmRobot`` queued when the serving thread woke (the
    older ones are superseded); it is late when it left more than ``link.late_reply_ms`` after
    the oldest of them arrived. ``wait_ms`` (that one in the kernel before the thread woke) and
    the part of ``work_ms`` not in ``cpu_ms`` are time the thread did not run: the scheduler,
    another process or the hypervisor had its CPU. ``cpu_ms`` is the link's own work (parse,
    answer, ``sendto``: the thread's CPU clock, which stops while it is off the CPU).
    """

    first_rx_ns: int  # kernel receive time of the oldest EgmRobot answered (CLOCK_REALTIME)
    rx_ns: int        # ... of the newest, the one the reply answers
    wait_ms: float    # first_rx_ns -> serving thread awake
    work_ms: float    # awake -> after ``sendto``
    cpu_ms: float     # CPU time the serving thread used in ``work_ms``


@dataclass
class EgmStats:
    """Counters of one link (all cumulative since start).

    Attributes:
        received: valid ``EgmRobot`` datagrams accepted (every datagram read is counted in
            ``received`` or in one ``dropped`` reason, never both).
        sent: replies sent.
        commands: replies that carried an accepted measurement (the rest are holds).
        holds: reply cycles answered with a hold, by cause (``no_measurement``, ``watchdog``,
            ``refused``, ``controller_silence``, ``new_session``).
        refused: refused measurements, by reason (each counted once per measurement and reason).
        dropped: dropped datagrams, by reason.
        late_replies: replies that left more than ``link.late_reply_ms`` after their
            ``EgmRobot`` arrived.
        superseded: valid ``EgmRobot`` left unanswered because a newer one was already queued.
        robot_missing: ``EgmRobot`` sequence numbers never seen (gaps in ``header.seqno``
            that the session accepted at once; a confirmed far jump is not counted).
        sessions: controller sessions started (the first datagram, then confirmed restarts).
        jumps: far jumps ahead in ``header.seqno`` believed after confirmation.
        kernel_dropped: datagrams the kernel dropped on the link's sockets because a receive
            buffer was full (Linux ``SO_RXQ_OVFL``; cumulative, as the last datagram read
            reported it; 0 where the kernel does not report it): the sum of the two below.
        kernel_dropped_controller: ... on the controller's own socket (connected to its
            address and port; only its datagrams arrive there). Not 0: the link did not read
            the controller's datagrams fast enough.
        kernel_dropped_other: ... on the link's shared socket, where every other sender's
            datagrams arrive (a flood fills it; read at a bounded rate) and, until the
            controller has a socket of its own (its port not yet known, or a platform without
            it), the controller's too.
        controller_unreachable: ICMP port-unreachable errors on the controller's socket: a
            reply reached a port the controller no longer listens on (it stopped or moved).
        controller_moves: times the controller was taken back on a new source port of its
            host (a restart believed after confirmation; also counted in ``sessions``).
        watchdog_trips: times the watchdog started holding (measurements stopped).
        controller_silences: times the controller stopped sending for longer than
            ``safety.watchdog_ms``; the first reply after one is a hold.
        send_errors: replies the socket refused.
        latency_ms: reply latency samples, ms (kernel receive time to after ``sendto``).
        late_log: the most recent late replies (superseded ``EgmRobot`` included), each split
            into where its time went (:class:`LateReply`): tells a machine that took the CPU
            away from the link from a link that was too slow.
    """

    received: int = 0
    sent: int = 0
    commands: int = 0
    holds: collections.Counter[str] = field(default_factory=collections.Counter)
    refused: collections.Counter[str] = field(default_factory=collections.Counter)
    dropped: collections.Counter[str] = field(default_factory=collections.Counter)
    late_replies: int = 0
    superseded: int = 0
    robot_missing: int = 0
    sessions: int = 0
    jumps: int = 0
    kernel_dropped: int = 0
    kernel_dropped_controller: int = 0
    kernel_dropped_other: int = 0
    controller_unreachable: int = 0
    controller_moves: int = 0
    watchdog_trips: int = 0
    controller_silences: int = 0
    send_errors: int = 0
    latency_ms: collections.deque[float] = field(
        default_factory=lambda: collections.deque(maxlen=100_000))
    late_log: collections.deque[LateReply] = field(
        default_factory=lambda: collections.deque(maxlen=10_000))

    def latency_summary(self) -> dict[str, float]:
        """Reply latency ``p50``, ``p99``, ``max`` and ``mean`` in ms (NaN without samples)."""
        return latency_summary(self.latency_ms)

    def copy(self) -> EgmStats:
        return copy_stats(self)

    def as_dict(self) -> dict[str, Any]:
        """Plain numbers (counters as dicts, latency as its summary) for printing or JSON."""
        return {"received": self.received, "sent": self.sent, "commands": self.commands,
                "holds": dict(self.holds), "refused": dict(self.refused),
                "dropped": dict(self.dropped), "late_replies": self.late_replies,
                "superseded": self.superseded, "robot_missing": self.robot_missing,
                "sessions": self.sessions, "jumps": self.jumps,
                "kernel_dropped": self.kernel_dropped,
                "kernel_dropped_controller": self.kernel_dropped_controller,
                "kernel_dropped_other": self.kernel_dropped_other,
                "controller_unreachable": self.controller_unreachable,
                "controller_moves": self.controller_moves,
                "watchdog_trips": self.watchdog_trips,
                "controller_silences": self.controller_silences, "send_errors": self.send_errors,
                "latency_ms": self.latency_summary()}


def copy_stats(stats: Any) -> Any:
    """A copy of a stats dataclass whose counters and sample deques are independent."""
    out = dataclasses.replace(stats)
    for f in dataclasses.fields(stats):
        v = getattr(stats, f.name)
        if isinstance(v, collections.Counter):
            setattr(out, f.name, collections.Counter(v))
        elif isinstance(v, collections.deque):
            setattr(out, f.name, collections.deque(v, maxlen=v.maxlen))
    return out


def latency_summary(samples: Any) -> dict[str, float]:
    """``p50``, ``p99``, ``max``, ``mean`` of latency samples in ms (NaN when empty)."""
    a = np.fromiter(samples, dtype=float)
    if a.size == 0:
        return {"n": 0, "p50": math.nan, "p99": math.nan, "max": math.nan, "mean": math.nan}
    return {"n": int(a.size), "p50": float(np.percentile(a, 50)),
            "p99": float(np.percentile(a, 99)), "max": float(a.max()), "mean": float(a.mean())}

