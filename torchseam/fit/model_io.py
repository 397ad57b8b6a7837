"""The fitted tracker on disk: ``models/live_tracker.safetensors``.

The file holds only tensors, a module's ``state_dict()`` (raw parameter forms plus buffers), in
the safetensors format (no pickled objects); its header metadata (strings) records the format,
the tracker configuration it was fitted with and what it was fitted on. Two formats:

- ``torchseam-live-tracker/1``: the live tracker
  (:class:`~torchseam.track.live.LiveTracker`: ``eakf_stc.*`` and ``fusion.*`` tensors), what
  ships and what ``torchseam train`` writes;
- ``torchseam-eakf-stc/1``: EAKF-STC alone (older fits, and component fits).

An EAKF-STC module loads its part of either.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import torch
from torch import nn

from torchseam import model_dir
from torchseam.core.errors import TorchseamError

__all__ = ["DEFAULT_MODEL", "MODEL_DIR", "MODEL_FORMAT", "FitError", "install_model",
           "load_fitted", "read_model", "save_fitted"]

log = logging.getLogger("torchseam.fit")

#: Folder of the fitted model: ``$TORCHSEAM_MODELS``, else the one shipped in the package (the
#: repository's ``models/`` in a checkout).
MODEL_DIR = model_dir()
#: The model the tracker loads by default.
DEFAULT_MODEL = MODEL_DIR / "live_tracker.safetensors"
MODEL_FORMAT = "torchseam-eakf-stc/1"
LIVE_FORMAT = "torchseam-live-tracker/1"
_FORMATS = (MODEL_FORMAT, LIVE_FORMAT)
#: the prefix of the EAKF-STC tensors in a live-tracker file
INNER = "eakf_stc."
#: TrackerConfig fields that change what the fitted numbers mean: a mismatch is logged.
_STRUCTURAL = ("window", "target", "peak", "crop", "exclude", "scale_update")


class FitError(TorchseamError):
    """A fitted-model file is unreadable or does not fit the tracker; or training failed."""


def save_fitted(module: nn.Module, path: str | os.PathLike[str],
                info: Mapping[str, Any] | None = None) -> Path:
    """Write ``module.state_dict()`` to ``path`` (safetensors, written atomically).

    Args:
        module: an :class:`~torchseam.track.fusion.EAKFSTC`.
        path: output file (its folder is created).
        info: JSON-able description (data, seeds, metrics) kept in the header metadata.
    """
    from safetensors.torch import save_file

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tensors = {k: v.detach().to("cpu", copy=True).contiguous()
               for k, v in module.state_dict().items()}
    cfg = getattr(module, "config", None)
    live = hasattr(module, "fusion")
    meta = {"format": LIVE_FORMAT if live else MODEL_FORMAT,
            "tracker_config": json.dumps(cfg.to_dict() if cfg is not None else {}),
            "info": json.dumps(dict(info or {}))}
    if live:
        meta["anchor_config"] = json.dumps(dataclasses.asdict(module.cfg))
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}")
    save_file(tensors, str(tmp), metadata=meta)
    mask = os.umask(0)
    os.umask(mask)
    os.chmod(tmp, 0o666 & ~mask)  # an ordinary readable file, like open() would make
    os.replace(tmp, path)
    return path


def install_model(src: str | os.PathLike[str], dest: str | os.PathLike[str] | None = None,
                  stamp: str | None = None) -> tuple[Path, Path | None]:
    """Replace the model the trackers load (``dest``, default :data:`DEFAULT_MODEL`) with the
    model file ``src``, keeping the one it replaces as ``<dest>.bak-<stamp>`` (``stamp``:
    default the local time, ``YYYYmmdd-HHMMSS``; ``-2``, ``-3``... when that name is taken).
    ``src`` is checked to be an EAKF-STC model first; the new file appears atomically.

    Returns:
        ``(dest, backup)``; backup is None when there was no model to replace.

    Raises:
        FitError: ``src`` is not a readable EAKF-STC model file.
    """
    import shutil
    import time

    fmt = read_model(src)[1]["format"]  # refuse to install something the trackers cannot load
    if dest is None and fmt != LIVE_FORMAT:
        raise FitError(f"{src}: an EAKF-STC model alone cannot replace the live tracker's "
                       f"model ({DEFAULT_MODEL.name}); fit the live tracker with "
                       "`torchseam train-live`, or pass this file with --model")
    dest = Path(dest) if dest is not None else DEFAULT_MODEL
    dest.parent.mkdir(parents=True, exist_ok=True)
    backup = None
    if dest.exists():
        stamp = stamp or time.strftime("%Y%m%d-%H%M%S")
        backup = dest.with_name(f"{dest.name}.bak-{stamp}")
        n = 2
        while backup.exists():
            backup = dest.with_name(f"{dest.name}.bak-{stamp}-{n}")
            n += 1
        shutil.copy2(dest, backup)
    tmp = dest.with_name(f".{dest.name}.tmp{os.getpid()}")
    shutil.copyfile(src, tmp)
    os.replace(tmp, dest)
    return dest, backup


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
