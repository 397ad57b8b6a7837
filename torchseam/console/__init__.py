"""The operator console: ``torchseam console``, a browser page to run and watch the weld.

:class:`~torchseam.console.session.WeldSession` runs the live loop's closed-loop weld on a worker
thread and keeps bounded history; :class:`~torchseam.console.server.ConsoleServer` serves the
page and pushes updates over a WebSocket. See ``docs/console.md``.
"""

from torchseam.console.config import (
    ConsoleConfig,
    ParamError,
    WeldParams,
    load_console_config,
    parse_params,
)
from torchseam.console.server import ConsoleServer
from torchseam.console.session import PacedControl, RunState, WeldSession

__all__ = ["ConsoleConfig", "ConsoleServer", "PacedControl", "ParamError", "RunState",
           "WeldParams", "WeldSession", "load_console_config", "parse_params"]
