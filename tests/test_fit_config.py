"""``torchseam train``'s options (FitConfig) read by core's config reader."""

from __future__ import annotations

from pathlib import Path

import pytest

from torchseam.core.config import ConfigError
from torchseam.fit.config import FitConfig, load_fit_config
from torchseam.track import TrackerConfig


def _load(tmp_path: Path, text: str, over: dict | None = None) -> FitConfig:
    p = tmp_path / "t.yaml"
    p.write_text(text)
    return load_fit_config(p, over)


def test_values_in_yaml_and_command_line_forms(tmp_path: Path) -> None:
    cfg = _load(tmp_path, "seeds: 7\nval_seeds: [3, 1]\nlevels: [heavy, 0.4]\ntracker:\n",
                {"families": "sim,wide", "val_levels": "", "val_fraction": 0.0})
    assert (cfg.seeds, cfg.val_seeds) == ("7", "3,1")
    assert cfg.levels == ("heavy", "0.4") and cfg.families == ("sim", "wide")
    assert cfg.val_levels == () and cfg.tracker == {} and cfg.val_fraction == 0.0
    assert load_fit_config(None, {"generate": 2.0}).generate == 2  # a whole float is an int
    assert load_fit_config(None, {"tracker": {"window": [48, 48]}}).tracker_config().window == \
        (48, 48)
    assert FitConfig().tracker == {} and FitConfig().tracker is not FitConfig().tracker


@pytest.mark.parametrize(("text", "over", "msg"), [
    ("val_fraction: 1.0\n", None, r"t\.yaml: val_fraction: expected a number < 1\.0"),
    ("roi: 8\n", None, r"t\.yaml: roi: expected a whole number >= 16, got 8"),
    ("epochs: 2.5\n", None, r"t\.yaml: epochs: expected a whole number, got 2\.5"),
    ("dtype: float16\n", None, r"dtype: expected one of float32, float64, got 'float16'"),
    ("families: [sim, nope]\n", None, r"families: expected one of sim, .*got 'nope'"),
    ("seeds: 5-2\n", None, r"t\.yaml: seeds: range 5-2 is empty"),
    ("levels: []\n", None, r"levels: expected at least one noise level"),
    ("progress: 1\n", None, r"progress: expected true or false, got 1"),
    ("data: 3\n", None, r"data: expected a string, got 3"),
    ("tracker: [1]\n", None, r"tracker: expected a mapping"),
    ("tracker: {lam: x}\n", None, r"tracker: tracker config: lam: expected a number"),
    ("tracker: {windoww: 3}\n", None, r"tracker: tracker config: windoww: unknown field"),
    ("[1, 2]\n", None, r"t\.yaml: expected a mapping of options"),
    ("epochs: 3\n", {"epochs": 0}, r"command line: epochs: expected a whole number >= 1"),
    ("epochs: 0\n", {"epochs": 3}, r"t\.yaml: epochs"),  # the file's own error is the file's
    ("", {"fit": "lam,zeta"}, r"command line: fit: unknown parameter group 'zeta'"),
])
def test_errors_name_the_source_and_the_field(tmp_path: Path, text: str, over: dict | None,
                                              msg: str) -> None:
    with pytest.raises(ConfigError, match=msg):
        _load(tmp_path, text, over)


def test_tracker_config_reads_types_through_core() -> None:
    cfg = TrackerConfig.from_dict({"lam": [0.1, 0.2], "sigma": None, "q": 30000}, rho=0.05)
    assert cfg.lam == (0.1, 0.2) and cfg.sigma is None and cfg.q == 30000.0 and cfg.rho == 0.05
    with pytest.raises(ConfigError, match=r"tracker config: p0: expected 4 values, got 3"):
        TrackerConfig.from_dict({"p0": [1, 2, 3]})
    with pytest.raises(ConfigError, match=r"tracker config: learnable: expected true or false"):
        TrackerConfig.from_dict(learnable=1)
