"""`torchseam config show`: every setting's effective value and its source, the fitted model's
values marked where they replace configs/anchor.yaml's."""

from __future__ import annotations

import shutil

import pytest

from torchseam.cli import main
from torchseam.core.config import CONFIG_DIR


def _rows(out: str) -> dict[str, tuple[str, str]]:
    rows = {}
    for line in out.splitlines():
        parts = line.split(None, 2)
        if len(parts) == 3 and not set(parts[0]) <= {"-"}:
            rows[parts[0]] = (parts[1], parts[2])
    return rows


def test_anchor_shows_the_models_values_and_the_files_starting_values(capsys):
    from torchseam.track.anchored import FITTED, load_anchor_config, load_anchored_model

    assert main(["config", "show", "anchor"]) == 0
    rows = _rows(capsys.readouterr().out)
    fitted = load_anchored_model().fusion.values()
    start = load_anchor_config().start
    for key in FITTED:
        value, source = rows[key]
        assert source.startswith("model ") and "live_tracker.safetensors" in source, key
        assert float(value) == pytest.approx(float(fitted[key]), rel=1e-5)
        # the file holds only where a fit starts, said as such
        value, source = rows[f"start.{key}"]
        assert float(value) == getattr(start, key)
        assert source.endswith("(a fit's starting value, not the run's)")
    assert fitted["fix_gate"] != pytest.approx(start.fix_gate)  # the model's is not the file's
    value, source = rows["window_px"]   # not fitted: the YAML's
    assert value == "110" and source.endswith("anchor.yaml")


@pytest.mark.parametrize("key", ["fix_gate", "glare_scale"])
def test_a_model_set_value_edited_into_the_file_is_refused(tmp_path, capsys, key):
    """Editing a value the model sets would change nothing: the run refuses it, naming the
    model file, with one line and exit 2 (no weld starts on a setting that does nothing)."""
    from torchseam import config_dir

    copy = tmp_path / "mycell"
    shutil.copytree(config_dir(), copy)
    with (copy / "anchor.yaml").open("a") as f:
        f.write(f"{key}: 5.0\n")
    for argv in (["config", "show", "anchor"], ["demo", "--segments", "a", "--length-mm", "4",
                                                "--no-video", "--out", str(tmp_path / "o")]):
        assert main(["--config-dir", str(copy), *argv]) == 2, argv
        err = capsys.readouterr().err
        assert "Traceback" not in err
        line = next(ln for ln in err.splitlines() if "anchor.yaml" in ln)
        assert f"{key}: set by the fitted model" in line and "live_tracker.safetensors" in line
    assert not (tmp_path / "o" / "summary.json").exists()


def test_the_fits_starting_value_is_where_a_fit_starts(tmp_path):
    """``start:`` does change what it is for: the fusion a fit starts from."""
    from torchseam import config_dir
    from torchseam.track.anchored import AnchoredModel, load_anchor_config
    from torchseam.track.fusion import EAKFSTC

    copy = tmp_path / "anchor.yaml"
    text = (config_dir() / "anchor.yaml").read_text().replace("  fix_gate: 4.0", "  fix_gate: 6.5")
    copy.write_text(text)
    live = AnchoredModel(EAKFSTC(), load_anchor_config(copy), learnable=True)
    assert live.fusion.values()["fix_gate"] == pytest.approx(6.5)


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
    # every config file of the folder, `torchseam train`'s train.yaml too (once left out)
    for path in sorted(CONFIG_DIR.glob("*.yaml")):
        assert f"\n{path.stem} ({path})\n" in f"\n{out}", path.name
