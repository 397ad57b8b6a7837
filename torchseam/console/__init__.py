"""The operator console: ``torchseam console``, a browser page to run and watch the weld.

:class:`~torchseam.console.session.WeldSession` runs the live loop's closed-loop weld on a worker
thread and keeps bounded history; :class:`~torchseam.console.server.ConsoleServer` serves the
page and pushes updates over a WebSocket. See ``docs/console.md``.

The names below are imported on first use, so that the command line's parser
(:mod:`torchseam.console.cli`) does not import torch.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from torchseam.core.lazy import lazy_exports

if TYPE_CHECKING:
    from torchseam.console.config import (
        ConsoleConfig,
        ParamError,
        WeldParams,
        load_console_config,
        parse_params,
    )
    from torchseam.console.server import ConsoleServer
    from torchseam.console.session import PacedControl, RunState, WeldSession

#: each exported name: its module
_LAZY = {
    **dict.fromkeys(("ConsoleConfig", "ParamError", "WeldParams", "load_console_config",
                     "parse_params"), "torchseam.console.config"),
    "ConsoleServer": "torchseam.console.server",
    **dict.fromkeys(("PacedControl", "RunState", "WeldSession"), "torchseam.console.session"),
}

__all__ = ["ConsoleConfig", "ConsoleServer", "PacedControl", "ParamError", "RunState",
           "WeldParams", "WeldSession", "load_console_config", "parse_params"]

__getattr__ = lazy_exports(__name__, _LAZY)
