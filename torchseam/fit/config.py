"""Options of ``torchseam train`` (``configs/train.yaml``), typed and validated.

Every field has a default here; ``configs/train.yaml`` and the command line override them (in
that order), read and checked by core's config reader like every file in ``configs/``. A wrong
field raises :class:`~torchseam.core.config.ConfigError` naming the file and the field, e.g.
``configs/train.yaml: chunk: expected a whole number >= 1, got 0``.
"""

from __future__ import annotations

import dataclasses
import re
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from torchseam.core.config import (
    FAMILY_NAMES,
    ConfigError,
    config_field,
    config_path,
    from_dict,
    read_yaml,
)
from torchseam.track.config import TrackerConfig

__all__ = ["FitConfig", "PARAM_GROUPS", "train_yaml", "load_fit_config", "parse_seeds"]

#: Default options file.


def train_yaml() -> Path:
    """The fit's options file: ``train.yaml`` of the config folder in use."""
    return config_path("train.yaml")

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


def _seeds(spec: str | int | list[int] | tuple[int, ...]) -> tuple[int, ...]:
    """:func:`parse_seeds` without the name in its messages."""
    if isinstance(spec, bool):
        raise ValueError(f"expected seeds like '0-15' or '1,4,9', got {spec!r}")
    if isinstance(spec, int):
        items: list[int] = [spec]
    elif isinstance(spec, (list, tuple)):
        if not all(isinstance(s, int) and not isinstance(s, bool) for s in spec):
            raise ValueError(f"expected whole numbers, got {list(spec)!r}")
        items = list(spec)
    elif isinstance(spec, str):
        items = []
        for part in spec.split(","):
            m = _SEEDS_RE.match(part)
            if not m:
                raise ValueError(f"{part.strip()!r} is not a seed or a range like 0-15")
            lo = int(m.group(1))
            hi = int(m.group(2)) if m.group(2) is not None else lo
            if hi < lo:
                raise ValueError(f"range {lo}-{hi} is empty")
            items.extend(range(lo, hi + 1))
    else:
        raise ValueError(f"expected seeds like '0-15' or '1,4,9', got {spec!r}")
    if any(s < 0 for s in items):
        raise ValueError("seeds must be >= 0")
    out = tuple(dict.fromkeys(items))
    if not out:
        raise ValueError("no seeds")
    return out


def parse_seeds(spec: str | int | list[int] | tuple[int, ...], name: str = "seeds"
                ) -> tuple[int, ...]:
    """Seeds from ``"0-15"``, ``"0,3,7-9"``, an int or a list of ints (duplicates kept out).

    Raises ValueError('<name>: problem').

    Example:
        >>> parse_seeds("0-2,7")
        (0, 1, 2, 7)
    """
    try:
        return _seeds(spec)
    except ValueError as e:
        raise ValueError(f"{name}: {e}") from None


def _seed_spec(v: Any) -> Any:
    """A seeds field's value as the spec text it is kept as: an int or a list of ints (YAML)
    becomes ``"1,4,9"``; a spec is checked and kept as written."""
    seeds = _seeds(v)
    return v if isinstance(v, str) else ",".join(map(str, seeds))


def _names(v: Any) -> Any:
    """A list of names from comma-separated text (the command line) or a list in which numbers
    (noise levels in 0..1) are names too."""
    if isinstance(v, str):
        return [s.strip() for s in v.split(",") if s.strip()]
    if isinstance(v, (list, tuple)):
        return [str(s) if isinstance(s, (int, float)) and not isinstance(s, bool) else s
                for s in v]
    return v


def _mapping(v: Any) -> Any:
    """An empty section (``tracker:`` with nothing under it) is an empty mapping."""
    return {} if v is None else v


def _seeds_field(default: str) -> Any:
    return config_field(default=default, convert=_seed_spec)


def _names_field(default: tuple[str, ...], **kw: Any) -> Any:
    return config_field(default=default, convert=_names, **kw)


@dataclass
class FitConfig:
    """Everything ``torchseam train`` needs (see ``configs/train.yaml`` for the meaning).

    Loaded and checked by core's config reader (:func:`~torchseam.core.config.from_dict`): the
    limits are in the fields, what spans fields in :meth:`_check`. Paths are relative to the
    working directory. ``seeds``, ``val_seeds`` and ``test_seeds`` are specs for
    :func:`parse_seeds`.
    """

    # --- data
    data: str | None = None            # labelled sequences (a folder, or a folder of folders)
    val_data: str | None = None        # held-out sequences for validation
    # share of data held out when no val_data is given
    val_fraction: float = config_field(default=0.2, lo=0.0, hi=1.0, hi_open=True)
    generate: int = config_field(default=0, lo=0)  # > 0: simulate this many per level
    levels: tuple[str, ...] = _names_field(("heavy", "strike"))
    # appearance families of the simulated sequences
    families: tuple[str, ...] = _names_field(("sim",), choices=FAMILY_NAMES)
    seeds: str = _seeds_field("0-15")
    val_seeds: str = _seeds_field("500-505")
    # (): the same as levels
    val_levels: tuple[str, ...] = _names_field(("heavy", "strike", "light", "clean"))
    frames: int = config_field(default=150, lo=0)   # frames per generated sequence
    max_frames: int = config_field(default=0, lo=0)  # at most this many per sequence (0: all)
    cache: str = "runs/fit-cache"      # generated sequences and the crop cache
    roi: int = config_field(default=256, lo=16)  # square crop around each label track (px)
    margin: int = config_field(default=48, lo=0)  # crop margin around the label track (px)
    # --- optimisation
    fit: tuple[str, ...] = _names_field(("lam", "a", "b", "q", "r", "rho", "guard"))
    epochs: int = config_field(default=15, lo=1)
    batch: int = config_field(default=16, lo=1)  # sequences per step (global under torchrun)
    chunk: int = config_field(default=16, lo=1)  # truncated BPTT length (frames)
    lr: float = config_field(default=0.02, lo=0, lo_open=True)
    huber: float = config_field(default=2.0, lo=0, lo_open=True)  # Huber delta (px)
    clip: float = config_field(default=1.0, lo=0)  # gradient-norm clip (0: none)
    seed: int = config_field(default=0, lo=0)
    # torch threads per process (more is slower here: the ops are small; use torchrun
    # processes for more cores)
    threads: int = config_field(default=1, lo=1)
    dtype: str = config_field(default="float32", choices=("float32", "float64"))
    # --- bookkeeping
    out: str = "runs/fit"              # checkpoints and metrics
    model: str = "models/eakf_stc.safetensors"
    val_every: int = config_field(default=1, lo=1)  # validate every this many epochs
    lost_px: float = config_field(default=15.0, lo=0, lo_open=True)
    progress: bool = True
    # --- final table on held-out simulated sequences (paper defaults vs fitted)
    test_levels: tuple[str, ...] = _names_field(("clean", "light", "strike", "heavy"))
    test_seeds: str = _seeds_field("1000-1011")
    test_frames: int = config_field(default=300, lo=1)
    test_data: str | None = None       # a labelled folder instead of simulated test sequences
    test: bool = True                  # print the table (needs test_data or generate > 0)
    # --- tracker: TrackerConfig overrides of the starting point (e.g. window: [48, 48])
    tracker: dict[str, Any] = config_field(default_factory=dict, convert=_mapping)

    def tracker_config(self) -> TrackerConfig:
        return TrackerConfig.from_dict(self.tracker)

    def to_dict(self) -> dict[str, Any]:
        d = dataclasses.asdict(self)
        return {k: list(v) if isinstance(v, tuple) else v for k, v in d.items()}

    def _check(self) -> None:
        """What spans fields or needs the tracker; raises ValueError('field: problem')."""
        for name, what in (("levels", "at least one noise level"),
                           ("families", "at least one appearance family"),
                           ("test_levels", "at least one noise level"),
                           ("fit", f"at least one of {', '.join(PARAM_GROUPS)}"),
                           ("cache", "a folder"), ("out", "a folder"), ("model", "a file")):
            if not getattr(self, name):
                raise ValueError(f"{name}: expected {what}, got {getattr(self, name)!r}")
        unknown = [g for g in self.fit if g not in PARAM_GROUPS]
        if unknown:
            raise ValueError(f"fit: unknown parameter group {unknown[0]!r} (use "
                             f"{', '.join(PARAM_GROUPS)})")
        from torchseam.track.fusion import EAKFSTC  # torch: not for the parser's defaults

        try:
            EAKFSTC(self.tracker_config())  # the tracker checks its own values
        except Exception as e:  # ConfigError, InputError or TypeError from a bad value
            raise ValueError(f"tracker: {e}") from None


def load_fit_config(path: str | Path | None = None, overrides: Mapping[str, Any] | None = None,
                    ) -> FitConfig:
    """Defaults <- YAML file (default ``configs/train.yaml`` when it exists) <- ``overrides``.

    Raises:
        ConfigError: ``"<file>: <field>: <problem>"`` (``command line`` for overrides).
    """
    sources: list[tuple[str, Any]] = []
    p = Path(path) if path is not None else train_yaml()
    if path is not None or p.exists():
        data = read_yaml(p)
        sources.append((str(p), {} if data is None else data))
    if overrides:
        sources.append(("command line", {k: v for k, v in overrides.items() if v is not None}))
    merged: dict[str, Any] = {}
    cfg = FitConfig()
    for src, data in sources or [("defaults", {})]:
        if not isinstance(data, dict):
            raise ConfigError(f"{src}: expected a mapping of options, got {data!r}")
        merged = {**merged, **data}
        cfg = from_dict(FitConfig, merged, src)  # a problem is the latest source's
    return cfg
