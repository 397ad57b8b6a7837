"""Counters of the simulated IRC5: what it sent, what came back and how late, its own timing.

Kept apart from the cycle loop that fills them so that reports and tests read one plain record
(:meth:`SimStats.copy` under the controller's lock, :meth:`SimStats.as_dict` for JSON).
"""

from __future__ import annotations

import collections
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from torchseam.robot.egm import copy_stats, latency_summary


@dataclass
class SimStats:
    """Counters of the simulated controller.

    Attributes:
        cycles: control cycles run.
        sent: ``EgmRobot`` datagrams put on the wire (faulty ones included).
        expected: cycles that sent a valid, in-order ``EgmRobot`` and so expect a reply.
        replies: valid replies received.
        late_replies: expecting cycles whose reply came more than one period after their
            ``EgmRobot`` left (kernel time stamps), or not before the next one left.
        extra_replies: valid replies beyond the first to one ``EgmRobot``.
        rejected: replies that failed validation, by reason.
        faults: injected faults, by kind.
        send_errors: datagrams the socket refused to send.
        unstamped: expecting ``EgmRobot`` without a kernel transmit time stamp, timed from
            the clock right before ``sendto`` instead (a hold there counts against the sensor).
        max_lag_mm: largest distance between the planned and the fed-back TCP position.
        overruns: cycles that started more than half a period late (the schedule then
            moves: the next ``EgmRobot`` never leaves less than a period after the previous
            one).
        latency_ms: ``EgmRobot`` leaving to the reply arriving (kernel time stamps on both
            ends where the kernel gives them), ms (late replies
            included when they arrive during the next cycle).
        jitter_ms: cycle start minus its scheduled time, ms.
        send_ms: cycle start to its ``EgmRobot`` leaving (kernel transmit time stamp), ms:
            where this controller, not the sensor, held a cycle up.
        compute_ms: model update time per cycle, ms.
        late_cycles_ns: when (``time.time_ns()``) each cycle that got no reply in time sent
            its ``EgmRobot``; lets a test line late replies up with machine stalls.
    """

    cycles: int = 0
    sent: int = 0
    expected: int = 0
    replies: int = 0
    late_replies: int = 0
    extra_replies: int = 0
    rejected: collections.Counter[str] = field(default_factory=collections.Counter)
    faults: collections.Counter[str] = field(default_factory=collections.Counter)
    send_errors: int = 0
    unstamped: int = 0
    max_lag_mm: float = 0.0
    overruns: int = 0
    latency_ms: collections.deque[float] = field(
        default_factory=lambda: collections.deque(maxlen=100_000))
    jitter_ms: collections.deque[float] = field(
        default_factory=lambda: collections.deque(maxlen=100_000))
    send_ms: collections.deque[float] = field(
        default_factory=lambda: collections.deque(maxlen=100_000))
    compute_ms: collections.deque[float] = field(
        default_factory=lambda: collections.deque(maxlen=100_000))
    late_cycles_ns: collections.deque[int] = field(
        default_factory=lambda: collections.deque(maxlen=10_000))

    def copy(self) -> SimStats:
        return copy_stats(self)

    def as_dict(self) -> dict[str, Any]:
        return {"cycles": self.cycles, "sent": self.sent, "expected": self.expected,
                "replies": self.replies, "late_replies": self.late_replies,
                "extra_replies": self.extra_replies, "rejected": dict(self.rejected),
                "faults": dict(self.faults), "send_errors": self.send_errors,
                "unstamped": self.unstamped,
                "max_lag_mm": self.max_lag_mm,
                "overruns": self.overruns, "latency_ms": latency_summary(self.latency_ms),
                "jitter_ms": latency_summary(np.abs(np.fromiter(self.jitter_ms, float))),
                "send_ms": latency_summary(self.send_ms),
                "compute_ms": latency_summary(self.compute_ms)}
