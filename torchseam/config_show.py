"""``torchseam config show [NAME]``: every setting's effective value and where it came from.

A setting's value comes from the config folder in use (the shipped configs, or yours with
``--config-dir`` / ``$TORCHSEAM_CONFIGS``), or is the dataclass's default when the file leaves
it out, or, for the live tracker's fitted values (``anchor``: the fusion's noise, gates and
glare scale), from the fitted model file (``configs/anchor.yaml`` holds only where a fit
starts them, ``start.*``). It imports every stage's config class, the offline fit's included,
so it sits beside the command line, above every stage; it reads and changes nothing.
"""

from __future__ import annotations

import argparse
import importlib
from pathlib import Path
from typing import Any

from torchseam.core.config import ConfigError, config_path, load_config, read_yaml, to_dict
from torchseam.core.errors import TorchseamError

#: config name -> (module, dataclass) of its file ``configs/NAME.yaml``
CONFIGS: dict[str, tuple[str, str]] = {
    "cell": ("torchseam.core.config", "CellConfig"),
    "noise": ("torchseam.core.config", "NoiseConfig"),
    "tipm": ("torchseam.vision.tipm", "TipmConfig"),
    "profiles": ("torchseam.vision.profiles", "ProfileConfig"),
    "exposure": ("torchseam.vision.exposure", "ExposureConfig"),
    "anchor": ("torchseam.track.anchored", "AnchorConfig"),
    "ecal": ("torchseam.geometry.ecal", "EcalConfig"),
    "calibration": ("torchseam.core.calibration", "CalibrationConfig"),
    "plan": ("torchseam.plan.path", "PlanConfig"),
    "robot": ("torchseam.robot.config", "RobotConfig"),
    "egm": ("torchseam.robot.egm.config", "EgmConfig"),
    "live": ("torchseam.live.loop", "LiveConfig"),
    "search": ("torchseam.live.search", "SearchConfig"),
    "profile_track": ("torchseam.live.profile_track", "ProfileTrackConfig"),
    "console": ("torchseam.console.config", "ConsoleConfig"),
    "train": ("torchseam.fit.config", "FitConfig"),
    "train_live": ("torchseam.fit.anchored", "AnchoredFitConfig"),
}


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "config", help="show every setting's effective value and where it came from",
        description="Show the settings the commands run with: each value and its source (the "
                    "config folder in use, a default the file leaves out, or the fitted model "
                    "file, which alone sets the live tracker's fitted values).")
    verbs = p.add_subparsers(dest="verb", metavar="VERB", required=True)
    s = verbs.add_parser("show", help="print the settings of one config, or of all",
                         description="Print NAME's settings (default: all): name, value, "
                                     "source.")
    s.add_argument("name", nargs="?", default=None, choices=sorted(CONFIGS), metavar="NAME",
                   help=f"one of {', '.join(sorted(CONFIGS))} (default: all)")
    s.add_argument("--model", type=Path, default=None, metavar="FILE",
                   help="the live tracker's model file (default: the shipped "
                        "models/live_tracker.safetensors, or $TORCHSEAM_MODELS)")
    s.set_defaults(func=run)


def _flat(d: Any, prefix: str = "") -> dict[str, Any]:
    if isinstance(d, dict):
        out: dict[str, Any] = {}
        for k, v in d.items():
            out.update(_flat(v, f"{prefix}{k}."))
        return out
    return {prefix[:-1]: d}


def settings(name: str, model_path: Path | None = None) -> list[tuple[str, Any, str]]:
    """``(setting, effective value, source)`` of config ``name`` (see the module)."""
    module, cls_name = CONFIGS[name]
    cls = getattr(importlib.import_module(module), cls_name)
    path = config_path(f"{name}.yaml")
    if name == "anchor":    # its loader also refuses a value the model sets
        from torchseam.track.anchored import load_anchor_config

        obj = load_anchor_config(path)
    else:
        obj = load_config(cls, path)
    raw = _flat(read_yaml(path) or {})
    rows = []
    for key, value in _flat(to_dict(obj)).items():
        given = key in raw or any(k.startswith(key + ".") for k in raw)
        rows.append((key, value, str(path) if given else "default (not in the file)"))
    if name == "anchor":
        rows = _fitted(rows, model_path)
    return rows


def _fitted(rows: list[tuple[str, Any, str]], model_path: Path | None
            ) -> list[tuple[str, Any, str]]:
    """The fusion's fitted values, from the model file the tracker runs with, after the
    settings; the file's ``start.*`` marked as only a fit's starting values."""
    from torchseam.track import model_file
    from torchseam.track.anchored import FITTED, load_anchored_model

    path = Path(model_path) if model_path is not None else model_file.DEFAULT_MODEL
    out = [(k, v, src + " (a fit's starting value, not the run's)" if k.startswith("start.")
            else src) for k, v, src in rows]
    if not path.is_file():
        return out + [(k, "-", f"no model file {path}: a tracker warns and runs start.{k}")
                      for k in FITTED]
    values = load_anchored_model(path).fusion.values()
    return out + [(k, round(values[k], 6), f"model {path}") for k in FITTED]


def run(args: argparse.Namespace) -> int:
    from torchseam.core.report import format_table

    names = [args.name] if args.name else sorted(CONFIGS)
    for name in names:
        try:
            rows = settings(name, args.model)
        except ConfigError:
            raise
        except (OSError, KeyError) as e:
            raise TorchseamError(f"config {name}: {e}") from None
        print(f"{name} ({config_path(name + '.yaml')})")
        print(format_table(["setting", "value", "source"],
                           [[k, str(v), s] for k, v, s in rows]))
        print()
    return 0
