"""What the simulated IRC5 does to its datagrams on the way out: injected faults and loss.

:class:`FaultPlan` holds the faults queued for the next cycles (:class:`Fault`) and the random
packet loss (:class:`BurstLoss`, a Gilbert-Elliott channel), and turns one cycle's datagram into
what goes on the wire. It knows nothing of sockets or clocks, so the cycle loop and the lockstep
simulation share it and a test can drive it alone.
"""

from __future__ import annotations

import collections
import enum
import threading
from dataclasses import dataclass, field

import numpy as np


class Fault(str, enum.Enum):
    """Faults :meth:`~torchseam.robot.sim_controller.SimController.inject` can put on the wire.

    ``drop`` (send nothing), ``duplicate`` (send twice), ``reorder`` (hold back, send after the
    next cycle's datagram: N reorders in a row all arrive after the N+1th), ``corrupt`` (flip
    bytes and cut the tail), ``oversized`` (pad past the sensor's limit with an unknown field)
    and ``silence`` (send nothing; the controller has stopped).
    """

    DROP = "drop"
    DUPLICATE = "duplicate"
    REORDER = "reorder"
    CORRUPT = "corrupt"
    OVERSIZED = "oversized"
    SILENCE = "silence"


class BurstLoss:
    """Packet loss in bursts (a Gilbert-Elliott channel): a good state that loses nothing and a
    bad state that loses every datagram. Each cycle the channel goes bad with probability
    ``p`` and back to good with ``r``: bursts last ``1 / r`` cycles on average and the long-run
    loss is ``p / (p + r)``.

    Args:
        fraction: long-run fraction of cycles lost, in [0, 1).
        mean_burst: mean burst length, cycles (>= 1).
        seed: seed of the channel's random draws (the same seed loses the same cycles).

    Example:
        >>> ch = BurstLoss(0.1, 4.0, seed=1)
        >>> lost = [ch.lose() for _ in range(100_000)]
        >>> round(sum(lost) / len(lost), 2)
        0.1
    """

    def __init__(self, fraction: float, mean_burst: float, seed: int = 0) -> None:
        if not (0.0 <= fraction < 1.0) or not mean_burst >= 1.0:
            raise ValueError(f"loss fraction must lie in [0, 1) and the mean burst be >= 1 "
                             f"cycle, got {fraction!r}, {mean_burst!r}")
        self.fraction, self.mean_burst = float(fraction), float(mean_burst)
        self.r = 1.0 / self.mean_burst                      # bad -> good
        self.p = self.fraction * self.r / (1.0 - self.fraction)  # good -> bad
        self._rng = np.random.default_rng(seed)
        self.bad = False
        self.lost = 0
        self.cycles = 0
        self.bursts = 0

    def lose(self) -> bool:
        """Advance one cycle; True when this cycle's datagram is lost."""
        u = float(self._rng.random())
        if self.bad:
            self.bad = u >= self.r
        else:
            self.bad = u < self.p
            self.bursts += int(self.bad)
        self.cycles += 1
        self.lost += int(self.bad)
        return self.bad


@dataclass
class Outgoing:
    """One cycle's datagram after the fault plan.

    Attributes:
        datagrams: what to send, in order (this cycle's first where it goes out at all).
        expect: whether the first datagram is this cycle's, valid and in order, so that a reply
            is due.
        fault: what to count against this cycle: a :class:`Fault` value, ``"loss"`` (random
            packet loss took it), or None.
    """

    datagrams: list[bytes] = field(default_factory=list)
    expect: bool = False
    fault: str | None = None


class FaultPlan:
    """Faults queued for the next cycles, random loss, and the datagrams held back by
    ``reorder``. :meth:`inject`, :meth:`set_loss` and :meth:`clear_loss` may be called from any
    thread; :meth:`shape` and :meth:`lost` from the cycle's.

    Args:
        oversize_bytes: the size an ``oversized`` datagram is padded to.
        seed: seed of the ``corrupt`` fault's byte flips.
    """

    def __init__(self, oversize_bytes: int, seed: int = 0) -> None:
        self.oversize_bytes = oversize_bytes
        self._rng = np.random.default_rng(seed)
        self._lock = threading.Lock()
        self._faults: collections.deque[Fault] = collections.deque(maxlen=100_000)
        self._held: list[bytes] = []       # datagrams held back by reorder faults
        self.loss: BurstLoss | None = None  # random packet loss (set_loss), None: none

    def inject(self, fault: Fault | str, cycles: int = 1) -> None:
        """Apply ``fault`` to the next ``cycles`` cycles (queued after earlier injections)."""
        kind = Fault(fault)
        if cycles < 0:
            raise ValueError(f"cycles must be >= 0, got {cycles}")
        with self._lock:
            self._faults.extend([kind] * cycles)

    def set_loss(self, fraction: float, mean_burst: float = 1.0, seed: int = 0) -> None:
        """Lose ``fraction`` of the cycles' datagrams, in bursts of ``mean_burst`` cycles on
        average (:class:`BurstLoss`), from the next cycle on, until :meth:`clear_loss`."""
        self.loss = BurstLoss(fraction, mean_burst, seed) if fraction > 0 else None

    def clear_loss(self) -> None:
        """No more random packet loss."""
        self.loss = None

    def lost(self) -> bool:
        """Whether random packet loss takes this cycle's datagram."""
        return self.loss is not None and self.loss.lose()

    def shape(self, data: bytes) -> Outgoing:
        """This cycle's datagram ``data`` through the next queued fault (random loss where none
        is queued); datagrams held back by earlier reorders follow any that is not one."""
        with self._lock:
            fault = self._faults.popleft() if self._faults else None
        out = Outgoing(fault=None if fault is None else fault.value)
        if fault in (Fault.DROP, Fault.SILENCE):
            pass
        elif fault is None and self.lost():
            out.fault = "loss"
        elif fault is Fault.DUPLICATE:
            out.datagrams, out.expect = [data, data], True
        elif fault is Fault.REORDER:
            self._held.append(data)  # goes out after the next non-reordered cycle's datagram
        elif fault is Fault.CORRUPT:
            buf = bytearray(data)
            for i in self._rng.choice(len(buf), size=max(1, len(buf) // 16), replace=False):
                buf[i] ^= int(self._rng.integers(1, 256))
            out.datagrams = [bytes(buf[:-1])]  # cutting the last byte truncates utilizationRate
        elif fault is Fault.OVERSIZED:
            pad = self.oversize_bytes - len(data)
            # an unknown length-delimited field 15: valid protobuf, just too large
            out.datagrams = [data + bytes([0x7A]) + _varint(pad) + b"\0" * pad]
        else:
            out.datagrams, out.expect = [data], True
        if self._held and fault is not Fault.REORDER:
            out.datagrams += self._held
            self._held = []
        return out


def _varint(n: int) -> bytes:
    """``n`` as a protobuf varint (7 bits a byte, low first, high bit: more follow)."""
    out = bytearray()
    while True:
        b = n & 0x7F
        n >>= 7
        out.append(b | (0x80 if n else 0))
        if not n:
            return bytes(out)
