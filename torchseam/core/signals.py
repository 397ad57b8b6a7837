"""SIGINT / SIGTERM for the commands that stop the work in hand gracefully (``torchseam demo``,
``torchseam console``): the first signal asks the work to stop, and the command ends once it
has, with the signal's exit code; a second quits at once.

Ctrl-C sends SIGINT; systemd, ``docker stop`` and ``kill`` send SIGTERM. Both take the same
path: a weld stops at its next frame (arc off, the robot held), the command says why and what
was done, and its exit code says which signal ended it (128 + the signal's number, as a shell
reports a process a signal killed).
"""

from __future__ import annotations

import contextlib
import signal
from collections.abc import Callable, Iterable, Iterator
from typing import Any

#: the exit code of a command a signal stopped: 128 + the signal's number
EXIT_SIGNAL = {"SIGINT": 130, "SIGTERM": 143}
#: the signals :class:`SignalStop` takes by default
STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)


class SignalStop:
    """SIGINT / SIGTERM while a command runs: the first calls ``stop(name)`` (``"SIGINT"`` or
    ``"SIGTERM"``, kept in :attr:`signal`); a second of the same run quits at once (SIGINT:
    ``KeyboardInterrupt``, SIGTERM: ``SystemExit(143)``), leaving what the first had asked
    unfinished.

    ``stop`` runs in the signal handler, on the main thread between two of its bytecodes:
    it must only set flags or events (``DemoControl.stop``, an event loop's
    ``call_soon_threadsafe``), never take a lock the interrupted code may hold.
    """

    def __init__(self, stop: Callable[[str], object]) -> None:
        self.stop = stop
        self.signal: str | None = None

    def on_signal(self, signum: int, _frame: Any) -> None:
        name = signal.Signals(signum).name
        if self.signal is not None:
            if signum == signal.SIGINT:
                raise KeyboardInterrupt
            raise SystemExit(EXIT_SIGNAL.get(name, 128 + signum))
        self.signal = name
        self.stop(name)

    @contextlib.contextmanager
    def installed(self, signals: Iterable[int] = STOP_SIGNALS) -> Iterator[None]:
        """The handler on ``signals`` while the block runs (main thread only), the earlier
        handlers back after it."""
        old = {s: signal.signal(s, self.on_signal) for s in signals}
        try:
            yield
        finally:
            for s, h in old.items():
                signal.signal(s, h)
