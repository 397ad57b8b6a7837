"""Fitting EAKF-STC (torchseam.fit): direction of the fit, data errors, resume, DDP, model file."""

from __future__ import annotations

import json
import logging
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from torchseam.core.config import ConfigError
from torchseam.core.errors import DatasetError
from torchseam.fit import (
    FitConfig,
    FitError,
    SequenceSet,
    evaluate,
    evaluate_folders,
    find_sequences,
    load_fit_config,
    load_fitted,
    load_sequences,
    make_module,
    parse_seeds,
    read_model,
    save_fitted,
    train,
)
from torchseam.fit.cli import main as fit_main
from torchseam.fit.synthetic import coloured_track, render_v_stripes, write_synthetic_sequences
from torchseam.track.fusion import EAKFSTC
from torchseam.vision.tipm import red_response

REPO = Path(__file__).resolve().parents[1]
SMALL_TRACKER = {"window": [32, 32], "target": [16, 16]}


def small_yaml(tmp: Path, **extra) -> Path:
    """An options file for tiny, fast runs (32 px windows, 64 px crops, no table)."""
    cfg = {"tracker": SMALL_TRACKER, "roi": 64, "margin": 20, "batch": 4, "chunk": 6,
           "epochs": 2, "lr": 0.05, "progress": False, "test": False,
           "cache": str(tmp / "cache"), **extra}
    p = tmp / "train.yaml"
    p.write_text(json.dumps(cfg))  # JSON is YAML
    return p


@pytest.fixture(scope="module")
def syn_dir(tmp_path_factory):
    """Four labelled synthetic sequences on disk (dataset format)."""
    root = tmp_path_factory.mktemp("syn")
    write_synthetic_sequences(root, n=4, T=20, seed=3)
    return root


# --------------------------------------------------------------------------- the fit itself

def _coloured_set(lam: float, q: float, n: int = 16, T: int = 40, size: int = 96,
                  jitter: float = 0.5, seed: int = 1) -> SequenceSet:
    truth = coloured_track(n, T, lam, q, centre=(size / 2, size / 2), seed=seed,
                           max_extent=size / 2.5)
    rng = np.random.default_rng(seed + 1)
    frames = [render_v_stripes(truth[i] + jitter * rng.standard_normal(truth[i].shape),
                               (size, size), seed=i) for i in range(n)]
    return SequenceSet(frames, [t.astype(np.float32) for t in truth],
                       np.zeros((n, 2), int), [f"s{i}" for i in range(n)], ["syn"] * n, size)


def test_fit_moves_lambda_towards_the_datas_colour_and_lowers_the_loss(tmp_path):
    # Tracks whose acceleration is coloured with lambda = 0.9 (eq. 16); the filter starts from
    # a white-acceleration model (lambda = 0) with the data's Q and R. Fitting lambda alone must
    # move it towards 0.9 and lower the loss on held-out tracks of the same kind.
    q, jitter = 1000.0, 0.5
    tracker = {**SMALL_TRACKER, "lam": 0.0, "q": q, "r_pos": jitter**2 + 0.05,
               "r_disp": 2 * jitter**2 + 0.1}
    fit_set = _coloured_set(0.9, q, seed=1)
    held_out = _coloured_set(0.9, q, seed=11)
    cfg = FitConfig(fit=("lam",), tracker=tracker, epochs=5, batch=16, chunk=13, lr=0.15,
                    out=str(tmp_path / "run"), progress=False)
    before = evaluate(make_module(tracker), held_out)["loss"]
    module, history = train(cfg, fit_set, None, log_fn=lambda s: None)
    lam = module.eakf.lam.detach()
    after = evaluate(module, held_out)["loss"]
    assert bool((lam > 0.6).all()), lam          # from 0 towards the data's 0.9
    assert bool((lam < 0.99).all()), lam
    assert after < 0.6 * before, (before, after)
    assert history[-1].loss < history[0].loss
    # every other parameter stayed where it was
    ref = make_module(tracker)
    for (n, p), (_, p0) in zip(module.named_parameters(), ref.named_parameters(), strict=True):
        if n != "eakf.lam_raw":
            assert torch.equal(p.detach(), p0.detach()), n


# --------------------------------------------------------------------------- data

def test_crops_hold_the_red_response_and_shift_the_labels(syn_dir, tmp_path):
    dirs = find_sequences(syn_dir)
    assert [d.name for d in dirs] == ["seq-00", "seq-01", "seq-02", "seq-03"]
    s = load_sequences(dirs, roi=64, margin=16, cache=tmp_path / "c", progress=False)
    assert s.roi == 64 and len(s) == 4 and s.frames[0].dtype == np.uint8
    import cv2
    full = red_response(cv2.imread(str(dirs[1] / "00007.png")))
    u0, v0 = s.origin[1]
    pad = np.pad(full, 64, mode="edge")  # the crop replicates the border like the tracker
    np.testing.assert_array_equal(s.frames[1][7], pad[v0 + 64:v0 + 128, u0 + 64:u0 + 128])
    lab = np.loadtxt(dirs[1] / "labels.csv", delimiter=",", skiprows=1)[:, 1:]
    np.testing.assert_allclose(s.labels[1] + s.origin[1], lab, atol=1e-4)
    inside = (s.labels[1] >= 16 - 1) & (s.labels[1] <= 64 - 16)
    assert inside.all()
    # a second load comes from the cache (memory-mapped) and is identical
    s2 = load_sequences(dirs, roi=64, margin=16, cache=tmp_path / "c", progress=False,
                        build=False)
    assert isinstance(s2.frames[1], np.memmap)
    np.testing.assert_array_equal(s2.frames[1], s.frames[1])
    # a track longer than the ROI allows grows the ROI for every sequence (steps of 16 px)
    big = load_sequences(dirs, roi=16, margin=40, progress=False)
    assert big.roi >= 80 and big.roi % 16 == 0


def test_crops_track_like_full_frames(syn_dir):
    # the training crops are a faithful stand-in for the full frames: the same tracker gives
    # the same errors on both (evaluate: crops; evaluate_folders: full frames read on demand)
    dirs = find_sequences(syn_dir)
    trk = make_module(SMALL_TRACKER)
    crops = evaluate(trk, load_sequences(dirs, roi=128, margin=20, progress=False))
    rows = evaluate_folders({"m": trk, "m2": make_module(SMALL_TRACKER)}, dirs, batch=3,
                            progress=False)
    assert [(r["group"], r["model"]) for r in rows] == [("data", "m"), ("data", "m2")]
    assert rows[0]["n"] == crops["groups"]["data"]["n"] == 4 * 19
    assert rows[0]["rmse"] == pytest.approx(crops["groups"]["data"]["rmse"], abs=1e-3)
    assert rows[0]["rmse"] == rows[1]["rmse"] and rows[0]["rmse"] < 1.5


def test_data_folder_errors_name_the_problem(tmp_path, syn_dir):
    with pytest.raises(DatasetError, match="no such folder"):
        find_sequences(tmp_path / "nope")
    (tmp_path / "empty").mkdir()
    with pytest.raises(DatasetError, match="no sequences"):
        find_sequences(tmp_path / "empty")
    nolab = tmp_path / "nolab" / "a"
    nolab.mkdir(parents=True)
    (nolab / "00000.png").write_bytes((syn_dir / "seq-00" / "00000.png").read_bytes())
    with pytest.raises(DatasetError, match="labels.csv is missing"):
        load_sequences(find_sequences(tmp_path / "nolab"), progress=False)
    bad = tmp_path / "bad"
    bad.mkdir()
    for p in (syn_dir / "seq-00").glob("0000[0-3].png"):
        (bad / p.name).write_bytes(p.read_bytes())
    (bad / "labels.csv").write_text("frame,u,v\n9,11,11\n")  # no label has an image
    with pytest.raises(DatasetError, match="no label names a frame in the folder "
                                           r"\(line 2: frame 9 has no image 00009.png\)"):
        load_sequences([bad], progress=False)
    (bad / "labels.csv").write_text("frame,u,v\n3,10,10\n")  # only the last frame labelled
    with pytest.raises(DatasetError, match="at least 2 frames"):
        load_sequences([bad], progress=False)


def test_cli_reports_data_errors_without_a_traceback(tmp_path, capsys):
    cfg = small_yaml(tmp_path)
    assert fit_main(["--config", str(cfg), "--data", str(tmp_path / "missing")]) == 2
    err = capsys.readouterr().err
    assert "missing: no such folder" in err and "Traceback" not in err
    assert fit_main(["--config", str(cfg)]) == 2
    assert "no training data" in capsys.readouterr().err
    assert fit_main(["--config", str(cfg), "--data", str(tmp_path), "--fit", "lam,zeta"]) == 2
    assert "unknown parameter group 'zeta'" in capsys.readouterr().err


def test_train_subcommand_registers_the_same_options():
    import argparse

    from torchseam.fit.cli import config_from_args, register, run

    parser = argparse.ArgumentParser(prog="torchseam")
    register(parser.add_subparsers(dest="command"))
    args = parser.parse_args(["train", "--data", "d", "--epochs", "2", "--fit", "lam,guard",
                              "--tracker", "rho=0.05,window=[48,48]", "--resume"])
    assert args.func is run and args.resume is True
    cfg = config_from_args(args)
    assert (cfg.data, cfg.epochs, cfg.fit) == ("d", 2, ("lam", "guard"))
    assert cfg.tracker == {"rho": 0.05, "window": [48, 48]}


def test_config_file_and_seeds(tmp_path):
    assert parse_seeds("0-3,7") == (0, 1, 2, 3, 7)
    assert parse_seeds([5, 5, 2]) == (5, 2)
    with pytest.raises(ValueError, match="range 5-2 is empty"):
        parse_seeds("5-2")
    cfg = load_fit_config(REPO / "configs" / "train.yaml")
    assert cfg == FitConfig()  # the shipped file states the defaults
    p = tmp_path / "t.yaml"
    p.write_text("chunk: 0\n")
    with pytest.raises(ConfigError, match=r"t\.yaml: chunk: expected a whole number >= 1"):
        load_fit_config(p)
    p.write_text("chunks: 4\n")
    with pytest.raises(ConfigError, match="chunks: unknown field"):
        load_fit_config(p)
    p.write_text("tracker: {rho: 2.0}\n")
    with pytest.raises(ConfigError, match="tracker: rho"):
        load_fit_config(p)
    over = load_fit_config(None, {"epochs": 3, "levels": "clean,heavy"})
    assert over.levels == ("clean", "heavy") and over.epochs == 3
    with pytest.raises(ConfigError, match="command line: lr: expected a number > 0"):
        load_fit_config(None, {"lr": -1.0})


# --------------------------------------------------------------------------- resume, DDP

def _last_params(out: Path) -> dict[str, torch.Tensor]:
    return torch.load(out / "last.pt", weights_only=True)["model"]


def test_resume_gives_the_uninterrupted_result(syn_dir, tmp_path):
    cfg = small_yaml(tmp_path, val_fraction=0.25)
    common = ["--config", str(cfg), "--data", str(syn_dir), "--batch", "3"]
    a, b = tmp_path / "a", tmp_path / "b"
    assert fit_main([*common, "--epochs", "3", "--out", str(a), "--model", str(a / "m.st")]) == 0
    assert fit_main([*common, "--epochs", "1", "--out", str(b), "--model", str(b / "m.st")]) == 0
    assert fit_main([*common, "--epochs", "3", "--out", str(b), "--model", str(b / "m.st"),
                     "--resume"]) == 0
    pa, pb = _last_params(a), _last_params(b)
    assert set(pa) == set(pb)
    for k in pa:
        assert torch.equal(pa[k], pb[k]), k
    ta, _ = read_model(a / "m.st")
    tb, _ = read_model(b / "m.st")
    for k in ta:
        assert torch.equal(ta[k], tb[k]), k
    moved = EAKFSTC(SMALL_TRACKER).state_dict()
    assert any(not torch.allclose(pa[k], moved[k]) for k in pa)  # training did something
    hist = json.loads((b / "metrics.json").read_text())["history"]
    assert [h["epoch"] for h in hist] == [0, 1, 2, 3]


def test_two_ddp_processes_match_one_process(syn_dir, tmp_path):
    cfg = small_yaml(tmp_path, dtype="float64", val_fraction=0.0, batch=4, epochs=2,
                     chunk=5)
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONWARNINGS": "ignore"}
    script = str(REPO / "train" / "fit_tracker.py")
    args = ["--config", str(cfg), "--data", str(syn_dir)]
    one, two = tmp_path / "one", tmp_path / "two"
    assert fit_main([*args, "--out", str(one), "--model", str(one / "m.st")]) == 0
    r2 = subprocess.run([sys.executable, "-m", "torch.distributed.run", "--nproc_per_node", "2",
                         "--master_port", str(29400 + os.getpid() % 500), script, *args,
                         "--out", str(two), "--model", str(two / "m.st")],
                        env=env, capture_output=True, text=True, timeout=180)
    assert r2.returncode == 0, r2.stderr[-3000:]
    assert "processes: 2" in r2.stdout
    p1, _ = read_model(one / "m.st")
    p2, _ = read_model(two / "m.st")
    start = EAKFSTC(SMALL_TRACKER).state_dict()
    moved = 0
    for k in p1:
        torch.testing.assert_close(p2[k], p1[k], rtol=1e-6, atol=1e-8, msg=k)
        moved += not torch.allclose(p1[k].float(), start[k], atol=1e-4)
    assert moved >= 5  # the comparison is about fitted values, not the starting point


# --------------------------------------------------------------------------- model file

def test_load_fitted_round_trip_fallback_and_errors(tmp_path, caplog, monkeypatch):
    import torchseam.fit.model_io as mio
    from torchseam.track import model_file

    fitted = EAKFSTC()
    with torch.no_grad():
        fitted.stc.logit_rho.fill_(-1.5)
        fitted.eakf.log_r.add_(0.7)
        fitted.guard.log_gate.fill_(1.9)
    path = save_fitted(fitted, tmp_path / "m.safetensors", {"note": "test"})
    tensors, meta = read_model(path)
    assert meta["info"] == {"note": "test"} and meta["tracker_config"]["rho"] == 0.075
    assert all(isinstance(v, torch.Tensor) for v in tensors.values())
    fresh = EAKFSTC()
    assert load_fitted(fresh, path) is True
    for (k, a), (_, b) in zip(fresh.state_dict().items(), fitted.state_dict().items(),
                              strict=True):
        assert torch.equal(a, b), k
    frozen = EAKFSTC(learnable=False)  # buffers instead of parameters: same names
    assert load_fitted(frozen, path) and float(frozen.stc.rho) == pytest.approx(
        float(torch.sigmoid(torch.tensor(-1.5))))

    # no model file at the default place: False, a warning, the paper's values untouched
    monkeypatch.setattr(model_file, "DEFAULT_MODEL", tmp_path / "absent.safetensors")
    trk = EAKFSTC()
    with caplog.at_level(logging.WARNING, logger="torchseam.fit"):
        assert load_fitted(trk) is False
    assert "paper's defaults" in caplog.text
    assert float(trk.stc.rho.detach()) == pytest.approx(0.075)
    monkeypatch.setattr(model_file, "DEFAULT_MODEL", path)
    assert load_fitted(EAKFSTC()) is True

    with pytest.raises(FitError, match="no such model file"):
        load_fitted(EAKFSTC(), tmp_path / "other.safetensors")
    bad = tmp_path / "corrupt.safetensors"
    bad.write_bytes(path.read_bytes()[: len(path.read_bytes()) // 2])
    with pytest.raises(FitError, match="not a readable safetensors model file"):
        load_fitted(EAKFSTC(), bad)
    (tmp_path / "junk.safetensors").write_bytes(b"\x00" * 64)
    with pytest.raises(FitError, match="not a readable"):
        load_fitted(EAKFSTC(), tmp_path / "junk.safetensors")
    with pytest.raises(FitError, match="fitted at 25 frames/s, the tracker runs at 50"):
        load_fitted(EAKFSTC(frame_rate=50.0), path)

    from safetensors.torch import save_file
    sd = {k: v.clone() for k, v in fitted.state_dict().items()}
    meta_ok = {"format": mio.MODEL_FORMAT, "tracker_config": "{}", "info": "{}"}
    save_file({k: v for k, v in sd.items() if k != "eakf.log_q"}, str(tmp_path / "m1.st"),
              metadata=meta_ok)
    with pytest.raises(FitError, match="missing eakf.log_q"):
        load_fitted(EAKFSTC(), tmp_path / "m1.st")
    save_file({**sd, "eakf.log_q": torch.zeros(3)}, str(tmp_path / "m2.st"), metadata=meta_ok)
    with pytest.raises(FitError, match=r"eakf.log_q has shape \(3,\)"):
        load_fitted(EAKFSTC(), tmp_path / "m2.st")
    save_file({**sd, "eakf.log_q": torch.full((2,), float("nan"))}, str(tmp_path / "m3.st"),
              metadata=meta_ok)
    with pytest.raises(FitError, match="NaN or inf"):
        load_fitted(EAKFSTC(), tmp_path / "m3.st")
    save_file(sd, str(tmp_path / "m4.st"), metadata={"format": "something-else"})
    with pytest.raises(FitError, match="not a tracker model"):
        load_fitted(EAKFSTC(), tmp_path / "m4.st")


def test_shipped_model_loads_into_the_default_tracker():
    path = REPO / "models" / "eakf_stc.safetensors"
    if not path.exists():
        pytest.skip("no shipped model yet")
    from torchseam.track.anchored import STRUCTURAL_STC, fitted_eakf_stc

    _, meta = read_model(path)
    assert meta["info"]["data"]["train"]["seeds"]  # it says what it was fitted on
    # the tracker it was made for: the default one plus the STC extensions the file names
    cfg = meta["tracker_config"]
    trk = EAKFSTC({k: cfg[k] for k in STRUCTURAL_STC if k in cfg})
    assert load_fitted(trk, path)
    assert fitted_eakf_stc().state_dict().keys() == trk.state_dict().keys()
