"""Options of ``torchseam train`` (``configs/train.yaml``), typed and validated.

Every field has a default here; ``configs/train.yaml`` and the command line override them (in
that order). A wrong field raises :class:`~torchseam.core.config.ConfigError` naming the file and
the field, e.g. ``configs/train.yaml: chunk: expected a whole number >= 1, got 0``.
"""

from __future__ import annotations

import dataclasses
import math
import re
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from torchseam.core.config import CONFIG_DIR, ConfigError
from torchseam.track.fusion import EAKFSTC, TrackerConfig

__all__ = ["FitConfig", "PARAM_GROUPS", "TRAIN_YAML", "load_fit_config", "parse_seeds"]

#: Default options file.
TRAIN_YAML = CONFIG_DIR / "train.yaml"

#: ``--fit`` names -> the EAKFSTC parameters they free (raw, unconstrained forms). A name ending
#: in "." frees every parameter under that prefix (the drift guard's set may grow).
PARAM_GROUPS: dict[str, tuple[str, ...]] = {
    "lam": ("eakf.lam_raw",),
    "a": ("eakf.a_raw",),
    "b": ("eakf.b_raw",),
    "q": ("eakf.log_q",),
    "r": ("eakf.log_r",),
    "rho": ("stc.logit_rho",),
    "guard": ("guard.",),
    "alpha": ("stc.log_alpha",),
    "sigma": ("stc.log_sigma",),
    "beta": ("stc.log_beta",),
    "reg": ("stc.log_reg",),        # only with tracker: {reg: > 0}
    "anchor": ("stc.logit_anchor",),  # only with tracker: {anchor: > 0}
}

_SEEDS_RE = re.compile(r"^\s*(\d+)\s*(?:-\s*(\d+)\s*)?$")


def parse_seeds(spec: str | int | list[int] | tuple[int, ...], name: str = "seeds"
                ) -> tuple[int, ...]:
    """Seeds from ``"0-15"``, ``"0,3,7-9"``, an int or a list of ints (duplicates kept out).

    Example:
        >>> parse_seeds("0-2,7")
        (0, 1, 2, 7)
    """
    if isinstance(spec, bool):
        raise ValueError(f"{name}: expected seeds like '0-15' or '1,4,9', got {spec!r}")
    if isinstance(spec, int):
        items: list[int] = [spec]
    elif isinstance(spec, (list, tuple)):
        if not all(isinstance(s, int) and not isinstance(s, bool) for s in spec):
            raise ValueError(f"{name}: expected whole numbers, got {list(spec)!r}")
        items = list(spec)
    elif isinstance(spec, str):
        items = []
        for part in spec.split(","):
            m = _SEEDS_RE.match(part)
            if not m:
                raise ValueError(f"{name}: {part.strip()!r} is not a seed or a range like 0-15")
            lo = int(m.group(1))
            hi = int(m.group(2)) if m.group(2) is not None else lo
            if hi < lo:
                raise ValueError(f"{name}: range {lo}-{hi} is empty")
            items.extend(range(lo, hi + 1))
    else:
        raise ValueError(f"{name}: expected seeds like '0-15' or '1,4,9', got {spec!r}")
    if any(s < 0 for s in items):
        raise ValueError(f"{name}: seeds must be >= 0")
    out = tuple(dict.fromkeys(items))
    if not out:
        raise ValueError(f"{name}: no seeds")
    return out


@dataclass
class FitConfig:
    """Everything ``torchseam train`` needs (see ``configs/train.yaml`` for the meaning).

    Paths are relative to the working directory. ``seeds``, ``val_seeds`` and ``test_seeds`` are
    specs for :func:`parse_seeds`.
    """

    # --- data
    data: str | None = None            # labelled sequences (a folder, or a folder of folders)
    val_data: str | None = None        # held-out sequences for validation
    val_fraction: float = 0.2          # of --data held out when no val_data is given
    generate: int = 0                  # > 0: simulate this many sequences per level
    levels: tuple[str, ...] = ("heavy", "strike")
    families: tuple[str, ...] = ("sim",)  # appearance families of the simulated sequences
    seeds: str = "0-15"
    val_seeds: str = "500-505"
    val_levels: tuple[str, ...] = ("heavy", "strike", "light", "clean")  # (): the same as levels
    frames: int = 150                  # frames per generated sequence
    max_frames: int = 0                # use at most this many frames per sequence (0: all)
    cache: str = "runs/fit-cache"      # generated sequences and the crop cache
    roi: int = 256                     # side of the square crop around each label track (px)
    margin: int = 48                   # crop margin around the label track (px)
    # --- optimisation
    fit: tuple[str, ...] = ("lam", "a", "b", "q", "r", "rho", "guard")
    epochs: int = 15
    batch: int = 16                    # sequences per step (the global batch under torchrun)
    chunk: int = 16                    # truncated BPTT length (frames)
    lr: float = 0.02
    huber: float = 2.0                 # Huber delta (px)
    clip: float = 1.0                  # gradient-norm clip (0: none)
    seed: int = 0
    threads: int = 1                   # torch threads per process (more is slower here: the
    #                                    ops are small; use torchrun processes for more cores)
    dtype: str = "float32"             # float32 | float64
    # --- bookkeeping
    out: str = "runs/fit"              # checkpoints and metrics
    model: str = "models/eakf_stc.safetensors"
    val_every: int = 1                 # validate every this many epochs
    lost_px: float = 15.0
    progress: bool = True
    # --- final table on held-out simulated sequences (paper defaults vs fitted)
    test_levels: tuple[str, ...] = ("clean", "light", "strike", "heavy")
    test_seeds: str = "1000-1011"
    test_frames: int = 300
    test_data: str | None = None       # a labelled folder instead of simulated test sequences
    test: bool = True                  # print the table (needs test_data or generate > 0)
    # --- tracker: TrackerConfig overrides of the starting point (e.g. window: [48, 48])
    tracker: dict[str, Any] = field(default_factory=dict)

    def tracker_config(self) -> TrackerConfig:
        return TrackerConfig.from_dict(self.tracker)

    def to_dict(self) -> dict[str, Any]:
        d = dataclasses.asdict(self)
        return {k: list(v) if isinstance(v, tuple) else v for k, v in d.items()}


def _check(cfg: FitConfig) -> None:
    """Field-level validation; raises ValueError('field: problem')."""
    def need(ok: bool, name: str, what: str) -> None:
        if not ok:
            raise ValueError(f"{name}: expected {what}, got {getattr(cfg, name)!r}")

    for name in ("generate", "frames", "max_frames", "margin", "epochs", "seed", "val_every",
                 "test_frames"):
        lo = 1 if name in ("epochs", "val_every", "test_frames") else 0
        need(getattr(cfg, name) >= lo, name, f"a whole number >= {lo}")
    for name in ("roi", "batch", "chunk", "threads"):
        need(getattr(cfg, name) >= 1, name, "a whole number >= 1")
    need(cfg.roi >= 16, "roi", "a crop side >= 16 px")
    for name in ("lr", "huber", "lost_px"):
        need(getattr(cfg, name) > 0, name, "a number > 0")
    need(cfg.clip >= 0, "clip", "a number >= 0")
    need(0.0 <= cfg.val_fraction < 1.0, "val_fraction", "a number in [0, 1)")
    need(cfg.dtype in ("float32", "float64"), "dtype", "float32 or float64")
    unknown = [g for g in cfg.fit if g not in PARAM_GROUPS]
    if unknown or not cfg.fit:
        raise ValueError(f"fit: unknown parameter group {unknown[0]!r} (use "
                         f"{', '.join(PARAM_GROUPS)})" if unknown else
                         f"fit: name at least one of {', '.join(PARAM_GROUPS)}")
    for name in ("seeds", "val_seeds", "test_seeds"):
        parse_seeds(getattr(cfg, name), name)
    need(bool(cfg.levels), "levels", "at least one noise level")
    need(bool(cfg.families), "families", "at least one appearance family")
    from torchseam.core.config import FAMILY_NAMES

    bad = [f for f in cfg.families if f not in FAMILY_NAMES]
    need(not bad, "families", f"appearance families of configs/noise.yaml "
         f"({', '.join(FAMILY_NAMES)}), not {', '.join(map(str, bad))}")
    need(bool(cfg.test_levels), "test_levels", "at least one noise level")
    try:
        EAKFSTC(cfg.tracker_config())  # the tracker validates its own values
    except Exception as e:  # TrackInputError or TypeError from a bad value
        raise ValueError(f"tracker: {e}") from None


def _bad(name: str, what: str, v: Any) -> ValueError:
    return ValueError(f"{name}: expected {what}, got {v!r}")


def _to_int(name: str, v: Any) -> int:
    if isinstance(v, bool) or not isinstance(v, int):
        if isinstance(v, float) and v.is_integer():
            return int(v)
        raise _bad(name, "a whole number", v)
    return v


def _to_float(name: str, v: Any) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise _bad(name, "a finite number", v)
    return float(v)


def _to_bool(name: str, v: Any) -> bool:
    if not isinstance(v, bool):
        raise _bad(name, "true or false", v)
    return v


def _to_str(name: str, v: Any) -> str:
    if isinstance(v, int) and not isinstance(v, bool) and name.endswith("seeds"):
        return str(v)
    if isinstance(v, list) and name.endswith("seeds"):
        return ",".join(str(x) for x in parse_seeds(v, name))
    if not isinstance(v, str) or not v:
        raise _bad(name, "a non-empty string", v)
    return v


def _to_path_or_none(name: str, v: Any) -> str | None:
    if v is None:
        return None
    if not isinstance(v, str) or not v:
        raise _bad(name, "a path or null", v)
    return v


def _to_names(name: str, v: Any) -> tuple[str, ...]:
    if isinstance(v, str):
        v = [s.strip() for s in v.split(",") if s.strip()]
    if not isinstance(v, (list, tuple)) or not all(isinstance(s, (str, int, float)) for s in v):
        raise _bad(name, "a list of names", v)
    return tuple(str(s) for s in v)


def _to_mapping(name: str, v: Any) -> dict[str, Any]:
    if v is None:
        return {}
    if not isinstance(v, Mapping):
        raise _bad(name, "a mapping", v)
    return dict(v)


#: field type (as :class:`FitConfig` spells it) -> its converter
_COERCE: dict[str, Callable[[str, Any], Any]] = {
    "int": _to_int, "float": _to_float, "bool": _to_bool, "str": _to_str,
    "str | None": _to_path_or_none, "tuple[str, ...]": _to_names,
    "dict[str, Any]": _to_mapping}


def _coerce(name: str, tp: Any, v: Any) -> Any:
    """Convert a YAML / CLI value to the field's type or raise ValueError('name: ...')."""
    convert = _COERCE.get(tp) if isinstance(tp, str) else None
    if convert is None:
        raise TypeError(f"unsupported field type {tp!r}")  # programming error
    return convert(name, v)


def load_fit_config(path: str | Path | None = None, overrides: Mapping[str, Any] | None = None,
                    ) -> FitConfig:
    """Defaults <- YAML file (default ``configs/train.yaml`` when it exists) <- ``overrides``.

    Raises:
        ConfigError: ``"<file>: <field>: <problem>"`` (``<command line>`` for overrides).
    """
    cfg = FitConfig()
    types = {f.name: f.type for f in dataclasses.fields(FitConfig)}
    sources: list[tuple[str, Mapping[str, Any]]] = []
    p = Path(path) if path is not None else TRAIN_YAML
    if path is not None or p.exists():
        try:
            data = yaml.safe_load(p.read_text())
        except OSError as e:
            raise ConfigError(f"{p}: cannot read config ({e.strerror or e})") from None
        except yaml.YAMLError as e:
            raise ConfigError(f"{p}: not valid YAML ({e})") from None
        if data is None:
            data = {}
        if not isinstance(data, dict):
            raise ConfigError(f"{p}: expected a mapping of options, got {data!r}")
        sources.append((str(p), data))
    if overrides:
        sources.append(("command line", {k: v for k, v in overrides.items() if v is not None}))
    for src, data in sources:
        for k, v in data.items():
            if k not in types:
                raise ConfigError(f"{src}: {k}: unknown field (expected one of "
                                  f"{', '.join(types)})")
            try:
                setattr(cfg, k, _coerce(k, types[k], v))
            except ValueError as e:
                raise ConfigError(f"{src}: {e}") from None
        try:
            _check(cfg)
        except ValueError as e:
            raise ConfigError(f"{src}: {e}") from None
    _check(cfg)
    return cfg
