"""Fitting the EAKF-STC tracker's parameters by gradient descent (truncated BPTT, DDP).

- :func:`load_fitted` / :func:`save_fitted`: the fitted model file
  (``models/eakf_stc.safetensors``, tensors only).
- :func:`train`: the optimisation (one process or a torchrun job).
- :func:`load_sequences`, :func:`find_sequences`, :func:`generate_sequences`: training data.
- ``torchseam train`` / ``train/fit_tracker.py``: the command (:mod:`torchseam.fit.cli`).
"""

from torchseam.fit.config import PARAM_GROUPS, FitConfig, load_fit_config, parse_seeds
from torchseam.fit.data import SequenceSet, find_sequences, generate_sequences, load_sequences
from torchseam.fit.model_io import DEFAULT_MODEL, FitError, load_fitted, read_model, save_fitted
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

__all__ = ["DEFAULT_MODEL", "PARAM_GROUPS", "ChunkLoss", "DistInfo", "FitConfig", "FitError",
           "SequenceSet", "evaluate", "evaluate_folders", "find_sequences",
           "generate_sequences", "init_distributed", "load_fitted", "load_fit_config",
           "load_sequences", "make_module", "parse_seeds", "read_model", "save_fitted",
           "select_parameters", "train"]
