"""The fitted tracker on disk: ``models/live_tracker.safetensors``.

The file holds only tensors, a module's ``state_dict()`` (raw parameter forms plus buffers), in
the safetensors format (no pickled objects); its header metadata (strings) records the format,
the tracker configuration it was fitted with and what it was fitted on. Two formats:

- ``torchseam-live-tracker/1``: the live tracker
  (:class:`~torchseam.track.anchored.AnchoredModel`: ``eakf_stc.*`` and ``fusion.*`` tensors), what
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

from torch import nn

from torchseam.track import model_file
from torchseam.track.model_file import (
    DEFAULT_MODEL,
    INNER,
    LIVE_FORMAT,
    MODEL_DIR,
    MODEL_FORMAT,
    FitError,
    load_fitted,
    read_model,
)

__all__ = ["DEFAULT_MODEL", "INNER", "LIVE_FORMAT", "MODEL_DIR", "MODEL_FORMAT", "FitError",
           "install_model", "load_fitted", "read_model", "save_fitted"]

log = logging.getLogger("torchseam.fit")

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
    from torchseam.track.anchored import AnchoredModel

    live = isinstance(module, AnchoredModel)  # the only module with a fusion head
    meta = {"format": LIVE_FORMAT if live else MODEL_FORMAT,
            "tracker_config": json.dumps(cfg.to_dict() if cfg is not None else {}),
            "info": json.dumps(dict(info or {}))}
    if isinstance(module, AnchoredModel):
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
                       f"model ({model_file.DEFAULT_MODEL.name}); fit the live tracker with "
                       "`torchseam train-live`, or pass this file with --model")
    dest = Path(dest) if dest is not None else model_file.DEFAULT_MODEL
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


