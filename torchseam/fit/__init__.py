"""Fitting the EAKF-STC tracker's parameters by gradient descent (truncated BPTT, DDP).

- :func:`load_fitted` / :func:`save_fitted`: the fitted model file
  (``models/eakf_stc.safetensors``, tensors only).
- :func:`train`: the optimisation (one process or a torchrun job).
- :func:`load_sequences`, :func:`find_sequences`, :func:`generate_sequences`: training data.
- ``torchseam train`` / ``train/fit_tracker.py``: the command (:mod:`torchseam.fit.cli`).

The names above are imported on first use, so that the command line's parsers
(:mod:`torchseam.fit.cli`, :mod:`torchseam.fit.anchored_cli`) do not import torch.
"""

from __future__ import annotations

import sys
import types
from typing import TYPE_CHECKING, Any

from torchseam.core.lazy import lazy_exports

if TYPE_CHECKING:
    from torchseam.fit.config import PARAM_GROUPS, FitConfig, load_fit_config, parse_seeds
    from torchseam.fit.data import (
        SequenceSet,
        find_sequences,
        generate_sequences,
        load_sequences,
    )
    from torchseam.fit.model_io import (
        DEFAULT_MODEL,
        FitError,
        load_fitted,
        read_model,
        save_fitted,
    )
    from torchseam.fit.train import (
        ChunkLoss,
        DistInfo,
        evaluate,
        evaluate_folders,
        init_distributed,
        make_module,
        select_parameters,
        train,
    )

#: each exported name: its module
_LAZY = {
    **dict.fromkeys(("PARAM_GROUPS", "FitConfig", "load_fit_config", "parse_seeds"),
                    "torchseam.fit.config"),
    **dict.fromkeys(("SequenceSet", "find_sequences", "generate_sequences", "load_sequences"),
                    "torchseam.fit.data"),
    **dict.fromkeys(("DEFAULT_MODEL", "FitError", "load_fitted", "read_model", "save_fitted"),
                    "torchseam.fit.model_io"),
    **dict.fromkeys(("ChunkLoss", "DistInfo", "evaluate", "evaluate_folders",
                     "init_distributed", "make_module", "select_parameters", "train"),
                    "torchseam.fit.train"),
}

__all__ = ["DEFAULT_MODEL", "PARAM_GROUPS", "ChunkLoss", "DistInfo", "FitConfig", "FitError",
           "SequenceSet", "evaluate", "evaluate_folders", "find_sequences",
           "generate_sequences", "init_distributed", "load_fitted", "load_fit_config",
           "load_sequences", "make_module", "parse_seeds", "read_model", "save_fitted",
           "select_parameters", "train"]


class _Package(types.ModuleType):
    """The package's module: ``torchseam.fit.train`` stays the function :func:`train` when its
    module is imported (the import system would set the attribute to the module)."""

    def __setattr__(self, name: str, value: Any) -> None:
        if name == "train" and isinstance(value, types.ModuleType):
            value = value.train
        super().__setattr__(name, value)


sys.modules[__name__].__class__ = _Package

__getattr__ = lazy_exports(__name__, _LAZY)
