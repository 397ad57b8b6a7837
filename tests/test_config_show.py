"""`torchseam config show`: every setting's effective value and its source, the fitted model's
values marked where they replace configs/anchor.yaml's."""

from __future__ import annotations

import shutil

import pytest

from torchseam.cli import main


def _rows(out: str) -> dict[str, tuple[str, str]]:
    rows = {}
    for line in out.splitlines():
        parts = line.split(None, 2)
        if len(parts) == 3 and not set(parts[0]) <= {"-"}:
            rows[parts[0]] = (parts[1], parts[2])
    return rows


def test_anchor_shows_the_models_values_and_that_the_files_are_not_used(capsys):
    from torchseam.track.anchored import FITTED, load_anchored_model

    assert main(["config", "show", "anchor"]) == 0
    rows = _rows(capsys.readouterr().out)
    fitted = load_anchored_model().fusion.values()
    for key in FITTED:
        value, source = rows[key]
        assert source.startswith("model ") and "live_tracker.safetensors" in source, key
        assert float(value) == pytest.approx(float(fitted[key]), rel=1e-5)
    # fix_gate: 4 in the YAML, fitted 8.09: the table says the file's value is not used
    assert "the file's 4 is not used" in rows["fix_gate"][1]
    value, source = rows["window_px"]   # not fitted: the YAML's
    assert value == "110" and source.endswith("anchor.yaml")


def test_a_setting_the_file_leaves_out_is_its_default(tmp_path, capsys):
    from torchseam import config_dir

    copy = tmp_path / "mycell"
    shutil.copytree(config_dir(), copy)
    text = (copy / "live.yaml").read_text()
    kept = [line for line in text.splitlines() if not line.startswith("min_step_mm:")]
    (copy / "live.yaml").write_text("\n".join(kept) + "\n")
    assert main(["--config-dir", str(copy), "config", "show", "live"]) == 0
    rows = _rows(capsys.readouterr().out)
    assert rows["min_step_mm"] == ("1.0", "default (not in the file)")
    assert rows["max_blind_ms"][1] == str(copy / "live.yaml")


def test_every_config_shows(capsys):
    assert main(["config", "show"]) == 0
    out = capsys.readouterr().out
    for name in ("cell", "tipm", "anchor", "egm", "live", "console", "train_live"):
        assert f"{name} (" in out
