"""torchseam: laser-vision seam tracking of pipe-to-pipe welds (EAKF-STC) in torch.

The shipped data lies inside the package, read through :mod:`importlib.resources`:
``torchseam/configs`` (the YAML configs), ``torchseam/models`` (the fitted EAKF-STC model) and
``torchseam/urdf`` (the robot model). In a source checkout these are links to the repository's
``configs/``, ``models/`` and ``urdf/`` (one copy, the one the README names); a wheel holds the
files themselves (``[tool.setuptools.package-data]`` in ``pyproject.toml``).

This module imports nothing heavy: ``torchseam --help`` stays fast.
"""

from __future__ import annotations

import os
from pathlib import Path

__all__ = ["CONFIGS_ENV", "MODELS_ENV", "__version__", "config_dir", "model_dir", "shipped"]

#: names a folder of your own configs, used instead of the shipped ones (``--config-dir``)
CONFIGS_ENV = "TORCHSEAM_CONFIGS"
#: names a folder of your own fitted models, used instead of the shipped one
MODELS_ENV = "TORCHSEAM_MODELS"


def shipped(name: str) -> Path:
    """The shipped data folder ``name`` (``configs``, ``models`` or ``urdf``), resolved: the
    repository's folder in a source checkout (editable install), the package's own in a wheel."""
    from importlib.resources import files

    root = files(__name__)
    if not isinstance(root, Path):  # e.g. a zipped package: the data must be real files
        raise RuntimeError(f"torchseam is installed where its data are not files ({root}); "
                           "install it with pip into a folder")
    return (root / name).resolve()


def config_dir() -> Path:
    """The config folder: ``$TORCHSEAM_CONFIGS`` when set, else the shipped configs."""
    env = os.environ.get(CONFIGS_ENV)
    return Path(env).expanduser() if env else shipped("configs")


def model_dir() -> Path:
    """The fitted-model folder: ``$TORCHSEAM_MODELS`` when set, else the shipped models."""
    env = os.environ.get(MODELS_ENV)
    return Path(env).expanduser() if env else shipped("models")


def __getattr__(name: str) -> str:
    if name == "__version__":  # from the installed package's metadata, read when asked
        from importlib.metadata import PackageNotFoundError, version

        try:
            return version(__name__)
        except PackageNotFoundError:  # imported from a tree that was never installed
            return "0+unknown"
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
