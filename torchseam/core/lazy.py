"""Package names imported on first use (PEP 562), for packages whose modules import torch.

``torchseam.track``, ``torchseam.fit`` and ``torchseam.console`` export their modules' names
(``from torchseam.track import EAKFSTC``); importing them all in ``__init__`` would make every
module of the package, the command line's parsers (``torchseam COMMAND --help``) among them,
import torch first. Each package instead sets ``__getattr__ = lazy_exports(__name__, ...)``
(and imports the names under ``TYPE_CHECKING`` for the type checker).
"""

from __future__ import annotations

import importlib
import sys
from collections.abc import Callable, Mapping
from typing import Any


def lazy_exports(package: str, names: Mapping[str, str | tuple[str, str]]
                 ) -> Callable[[str], Any]:
    """The module ``__getattr__`` of ``package``: ``names`` maps each exported name to the
    module that defines it, or to ``(module, its name there)``. The module is imported when
    the name is first asked for; the value is then kept in the package."""

    def __getattr__(name: str) -> Any:
        where = names.get(name)
        if where is None:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        module, attr = (where, name) if isinstance(where, str) else where
        value = getattr(importlib.import_module(module), attr)
        setattr(sys.modules[package], name, value)
        return value

    return __getattr__
