"""The one loader of a package's compiled kernels (its numba ``_kernels`` module).

Importing numba and compiling (or loading from numba's on-disk cache) a package's kernels takes
a while, which commands that never run them need not pay: each package imports its kernels on
first use, from where it builds the object that runs them (never in the middle of the live
loop), with ``load_kernels(__package__)``. The package names its own private module, so
``_kernels`` stays inside its package (the import-linter contract).
"""

from __future__ import annotations

import importlib
import sys
from types import ModuleType

from torchseam.core.errors import TorchseamError

__all__ = ["KernelError", "load_kernels"]


class KernelError(TorchseamError, RuntimeError):
    """A package's compiled kernels cannot be loaded: numba is missing or compilation failed."""


def load_kernels(package: str | None) -> ModuleType:
    """The module ``<package>._kernels``, imported (and so compiled) on the first call.

    Later calls return the imported module. Raises :class:`KernelError` naming the module when
    numba is not installed or a kernel fails to compile.

    Example:
        >>> load_kernels("torchseam.track").__name__
        'torchseam.track._kernels'
    """
    if not package:
        raise ValueError("load_kernels: give the calling package's __package__")
    name = f"{package}._kernels"
    module = sys.modules.get(name)
    if module is not None:
        return module
    try:
        return importlib.import_module(name)
    except ImportError as e:
        if e.name is not None and (e.name == "numba" or e.name.startswith("numba.")):
            raise KernelError(f"{name}: the compiled kernels need numba, which is not "
                              f"installed (pip install numba)") from e
        raise
    except Exception as e:  # numba's typing / lowering errors while compiling
        raise KernelError(f"{name}: compiling the kernels failed "
                          f"({type(e).__name__}: {e})") from e
