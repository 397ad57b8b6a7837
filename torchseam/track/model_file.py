"""Reading the fitted tracker's model file (``models/live_tracker.safetensors``): the trackers'
side of the file :mod:`torchseam.fit.model_io` writes.

The file holds only tensors, a module's ``state_dict()`` (raw parameter forms plus buffers), in
the safetensors format (no pickled objects); its header metadata (strings) records the format,
the tracker configuration it was fitted with and what it was fitted on. Two formats:

- ``torchseam-live-tracker/1``: the live tracker
  (:class:`~torchseam.track.anchored.AnchoredModel`: ``eakf_stc.*`` and ``fusion.*`` tensors), what
  ships and what ``torchseam train-live`` writes;
- ``torchseam-eakf-stc/1``: EAKF-STC alone (``torchseam train``).

An EAKF-STC module loads its part of either.
"""

from __future__ import annotations

import json
import logging
import os
from pathlib import Path
from typing import Any

import torch
from torch import nn

from torchseam import MODELS_ENV, model_dir
from torchseam.core.errors import TorchseamError

__all__ = ["DEFAULT_MODEL", "EAKF_STC_MODEL", "INNER", "LIVE_FORMAT", "MODEL_DIR",
           "MODEL_FORMAT", "MODELS_FROM_ENV", "FitError", "check_models_env", "load_fitted",
           "read_model"]

log = logging.getLogger("torchseam.fit")

#: Folder of the fitted model: ``$TORCHSEAM_MODELS``, else the one shipped in the package (the
#: repository's ``models/`` in a checkout).
MODEL_DIR = model_dir()
#: ``$TORCHSEAM_MODELS`` as it was set when :data:`MODEL_DIR` was read (None: not set): a
#: folder the user named, so a missing model there is an error, not a silent fallback.
MODELS_FROM_ENV = os.environ.get(MODELS_ENV) or None
#: The model the tracker loads by default.
DEFAULT_MODEL = MODEL_DIR / "live_tracker.safetensors"
#: The plain ``eakf-stc`` tracker's model: EAKF-STC fitted alone, as a tracker of its own (the
#: live tracker's EAKF-STC was fitted as a part of the fusion, a weak pull beside TIPM's fixes).
EAKF_STC_MODEL = MODEL_DIR / "eakf_stc.safetensors"
MODEL_FORMAT = "torchseam-eakf-stc/1"
LIVE_FORMAT = "torchseam-live-tracker/1"
_FORMATS = (MODEL_FORMAT, LIVE_FORMAT)
#: the prefix of the EAKF-STC tensors in a live-tracker file
INNER = "eakf_stc."
#: TrackerConfig fields that change what the fitted numbers mean: a mismatch is logged.
_STRUCTURAL = ("window", "target", "peak", "crop", "exclude", "scale_update")


class FitError(TorchseamError):
    """A fitted-model file is unreadable or does not fit the tracker; or training failed."""


def read_model(path: str | os.PathLike[str]) -> tuple[dict[str, torch.Tensor], dict[str, Any]]:
    """Tensors and decoded metadata (``format``, ``tracker_config``, ``info``) of a model file.

    Raises:
        FitError: missing, unreadable or not a torchseam model file.
    """
    from safetensors import safe_open

    path = Path(path)
    if not path.is_file():
        raise FitError(f"{path}: no such model file")
    try:
        with safe_open(str(path), framework="pt") as f:
            raw_meta = f.metadata() or {}
            tensors = {k: f.get_tensor(k) for k in f.keys()}  # noqa: SIM118 - not a dict
    except Exception as e:  # safetensors raises its own error types (and OSError)
        raise FitError(f"{path}: not a readable safetensors model file ({e}); fit it again "
                       "with `torchseam train` or delete it to use the paper's defaults"
                       ) from None
    if raw_meta.get("format") not in _FORMATS:
        raise FitError(f"{path}: not a tracker model (format {raw_meta.get('format')!r}, "
                       f"expected one of {', '.join(_FORMATS)})")
    meta: dict[str, Any] = {"format": raw_meta["format"]}
    for key in ("tracker_config", "info", "anchor_config"):
        try:
            meta[key] = json.loads(raw_meta.get(key, "{}"))
        except ValueError:
            raise FitError(f"{path}: header field {key!r} is not valid JSON") from None
    return tensors, meta


def check_models_env(path: Path) -> None:
    """Refuse a missing default model ``path`` when ``$TORCHSEAM_MODELS`` named its folder:
    the user asked for the models there (a typo must not fall back to other parameters).

    Raises:
        FitError: naming the variable and the folder or the file missing in it.
    """
    if MODELS_FROM_ENV is None or path.parent != MODEL_DIR:
        return
    if not MODEL_DIR.is_dir():
        raise FitError(f"${MODELS_ENV}={MODELS_FROM_ENV}: "
                       + ("no such folder" if not MODEL_DIR.exists() else "not a folder")
                       + " (unset it to use the shipped models)")
    raise FitError(f"${MODELS_ENV}={MODELS_FROM_ENV}: no {path.name} in that folder (install "
                   "one there with `torchseam train-live --install`, or unset the variable "
                   "to use the shipped models)")


def load_fitted(module: nn.Module, path: str | os.PathLike[str] | None = None) -> bool:
    """Load fitted parameters into an EAKF-STC tracker.

    Args:
        module: an :class:`~torchseam.track.fusion.EAKFSTC` (learnable or not: the state-dict
            names are the same).
        path: model file; None: :data:`DEFAULT_MODEL` (``models/live_tracker.safetensors``).

    Returns:
        True when loaded. False, with a logged warning, when ``path`` is None and no model file
        is present: the module keeps its configuration (the paper's defaults).

    Raises:
        FitError: the file is corrupt, is not an EAKF-STC model, was fitted at another frame
            rate, or its tensors do not match the module (names, shapes, non-finite values);
            also when an explicitly given ``path`` does not exist.

    Example:
        >>> from torchseam.track.fusion import EAKFSTC
        >>> trk = EAKFSTC()
        >>> load_fitted(trk)            # doctest: +SKIP
        True
    """
    if path is None:
        path = DEFAULT_MODEL
        if not Path(path).is_file():
            check_models_env(Path(path))
            log.warning("no fitted EAKF-STC model at %s: using the paper's defaults "
                        "(fit one with `torchseam train`)", path)
            return False
    path = Path(path)
    tensors, meta = read_model(path)
    live_file, live_module = meta["format"] == LIVE_FORMAT, hasattr(module, "fusion")
    if live_module and not live_file:
        raise FitError(f"{path}: an EAKF-STC model, not a live-tracker model (it has no "
                       "fitted fusion); fit the live tracker with `torchseam train`")
    if live_file and not live_module:  # EAKF-STC's part of the live tracker
        tensors = {k[len(INNER):]: v for k, v in tensors.items() if k.startswith(INNER)}
    own = module.state_dict()
    missing = sorted(set(own) - set(tensors))
    extra = sorted(set(tensors) - set(own))
    if missing or extra:
        what = (f"missing {', '.join(missing)}" if missing else "") + (
            "; " if missing and extra else "") + (f"unexpected {', '.join(extra)}" if extra
                                                  else "")
        raise FitError(f"{path}: tensors do not match the EAKF-STC module ({what}): it was "
                       "fitted for another version of the tracker; fit it again with "
                       "`torchseam train` or delete it to use the paper's defaults")
    for k, v in tensors.items():
        if tuple(v.shape) != tuple(own[k].shape):
            raise FitError(f"{path}: {k} has shape {tuple(v.shape)}, the module's is "
                           f"{tuple(own[k].shape)}")
        if not bool(torch.isfinite(v).all()):
            raise FitError(f"{path}: {k} holds NaN or inf")
    dt_key = next((k for k in tensors if k.endswith("eakf.dt")), None)
    if dt_key is not None:
        fps_file = 1.0 / float(tensors[dt_key])
        fps_mod = 1.0 / float(own[dt_key])
        if abs(fps_file - fps_mod) > 1e-3 * fps_mod:
            raise FitError(f"{path}: fitted at {fps_file:g} frames/s, the tracker runs at "
                           f"{fps_mod:g} frames/s (Q and the motion model depend on it)")
    cfg = getattr(module, "config", None)
    fitted_cfg = meta.get("tracker_config") or {}
    if cfg is not None and fitted_cfg:
        mine = cfg.to_dict()
        diff = [k for k in _STRUCTURAL
                if k in fitted_cfg and _norm(fitted_cfg[k]) != _norm(mine.get(k))]
        if diff:
            log.warning("%s was fitted with %s; this tracker has %s", path,
                        ", ".join(f"{k}={fitted_cfg[k]}" for k in diff),
                        ", ".join(f"{k}={mine.get(k)}" for k in diff))
    with torch.no_grad():
        module.load_state_dict({k: v.to(own[k]) for k, v in tensors.items()})
    return True


def _norm(v: Any) -> Any:
    return list(v) if isinstance(v, (list, tuple)) else v
