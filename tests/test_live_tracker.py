"""The live tracker as one differentiable module (torchseam/track/anchored.py): the module run in
torch is the tracker the live loop runs in numpy, its every fitted value gets a gradient, a fit
moves them, and the model file round-trips."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from torchseam.core.config import load_cell, load_noise, load_part
from torchseam.fit import model_io
from torchseam.fit.anchored import load_anchored_fit_config, simulate_set, track_set
from torchseam.track.anchored import (
    FITTED,
    AnchoredModel,
    AnchoredTracker,
    load_anchor_config,
    load_anchored_model,
)
from torchseam.track.fusion import EAKFSTC
from torchseam.vision.tipm import load_tipm, red_response

F64 = torch.float64
TIPM = load_tipm()  # the shipped configs/tipm.yaml: the fixes' TIPM


@pytest.fixture(scope="module")
def seqs():
    """Two short labelled sequences: heavy arc (sim family) and the corner hidden (wide)."""
    c, p, n = load_cell(), load_part(), load_noise()
    return (simulate_set(c, p, n, ["sim"], ["heavy"], [1003], 60, tipm=TIPM)
            + simulate_set(c, p, n, ["wide"], ["beyond"], [7], 60, (12, 20), tipm=TIPM))


def _numpy_track(live, seq):
    trk = AnchoredTracker(live, TIPM)
    trk.init(seq.frames[0], seq.labels[0])
    out = [np.r_[seq.labels[0], 0]]
    for fr in seq.frames[1:]:
        r = trk.track(fr)
        trk.idle()
        out.append(np.r_[r.uv, r.status])
    return np.array(out), trk


def test_torch_module_is_the_numpy_live_tracker(seqs):
    """The same frames through AnchoredTracker (numpy, the live loop's) and through
    AnchoredModel.step_state (torch, batched, what the fit differentiates): the same points and
    statuses, frame by frame, with the shipped model's values."""
    live = load_anchored_model().to(F64)
    ref = [_numpy_track(live, s)[0] for s in seqs]
    with torch.no_grad():
        _, uvs, stats = track_set(live, seqs, batch=1, tipm=TIPM)
        _, uvs2, _ = track_set(live, seqs, batch=2, tipm=TIPM)
    for r, uv, uv2, st, s in zip(ref, uvs, uvs2, stats, seqs, strict=True):
        np.testing.assert_allclose(uv, r[:, :2], atol=1e-6, err_msg=s.group)
        assert list(r[:, 2].astype(int)) == st, s.group
        # B = 2: EAKF-STC's batched state counts learning steps for the batch, so a stream
        # re-anchored in the first frames shifts the other's start model a little
        np.testing.assert_allclose(uv2, r[:, :2], atol=0.01, err_msg=s.group)
    # and the tracker did its job on them (not two equal failures)
    err = np.linalg.norm(ref[0][1:, :2] - seqs[0].labels[1:], axis=1)
    assert np.median(err) < 1.0


def test_every_fitted_value_gets_a_gradient(seqs):
    """One truncated-BPTT chunk: the loss reaches every value of the fusion that acted on
    these frames (the gates and thresholds through their straight-through decisions) and
    EAKF-STC's parameters (through its weak measurement and the re-anchoring)."""
    eakf = EAKFSTC(dataclasses.replace(load_anchored_model().eakf_stc.config, learnable=True))
    model_io.load_fitted(eakf, model_io.DEFAULT_MODEL)
    live = AnchoredModel(eakf, load_anchor_config(), learnable=True).to(F64)
    loss = 0.0
    for seq in seqs:  # heavy arc (glare around the point) and the corner hidden (restarts)
        labels = torch.from_numpy(seq.labels).to(F64)
        state = live.init_state(seq.frames[:1],
                                torch.from_numpy(red_response(seq.frames[0]))[None], labels[:1],
                                TIPM)
        for t in range(1, 40):
            f = seq.frames[t]
            state, x, _ = live.step_state(state, [f], torch.from_numpy(red_response(f))[None])
            loss = loss + torch.nn.functional.huber_loss(x[0], labels[t], delta=2.0)
    loss.backward()
    grads = {n: p.grad for n, p in live.named_parameters()}
    got = {n for n, g in grads.items() if g is not None and float(g.abs().sum()) > 0}
    for name in ("motion_u_px", "motion_v_px", "fix_noise", "fix_gate", "track_u_px",
                 "track_gate", "glare_start", "glare_scale"):
        assert f"fusion.log_{name}" in got, name
    assert any(n.startswith("eakf_stc.") for n in got)
    assert all(torch.isfinite(g).all() for g in grads.values() if g is not None)


def test_model_file_round_trip_and_refusals(tmp_path):
    """The live model file holds EAKF-STC and the fusion; the live tracker runs with the
    file's fitted values, not configs/anchor.yaml's; EAKF-STC alone loads its part; a file of
    EAKF-STC alone is no live model; a non-positive fitted value is refused."""
    live = load_anchored_model()
    with torch.no_grad():
        live.fusion.log_fix_gate.fill_(np.log(5.5))
        live.fusion.log_motion_u_px.fill_(np.log(0.7))
    path = model_io.save_fitted(live, tmp_path / "live.safetensors", {"note": "test"})
    assert model_io.read_model(path)[1]["format"] == model_io.LIVE_FORMAT
    trk = AnchoredTracker(load_anchored_model(path), TIPM)
    assert trk.values["fix_gate"] == pytest.approx(5.5)
    assert trk.values["motion_u_px"] == pytest.approx(0.7)
    assert load_anchor_config().start.fix_gate != pytest.approx(5.5)
    inner = EAKFSTC(live.eakf_stc.config)
    assert model_io.load_fitted(inner, path)
    for k, v in inner.state_dict().items():
        assert torch.equal(v, live.eakf_stc.state_dict()[k]), k
    alone = model_io.save_fitted(live.eakf_stc, tmp_path / "alone.safetensors")
    with pytest.raises(model_io.FitError, match="not a live-tracker model"):
        model_io.load_fitted(AnchoredModel(EAKFSTC(live.eakf_stc.config), load_anchor_config()),
                             alone)
    with pytest.raises(model_io.FitError, match="cannot replace the live tracker"):
        model_io.install_model(alone)
    with torch.no_grad():
        live.fusion.log_fix_gate.fill_(float("nan"))
    bad = model_io.save_fitted(live, tmp_path / "bad.safetensors")
    with pytest.raises(model_io.FitError, match="NaN"):
        load_anchored_model(bad)


def test_shipped_model_is_a_fit_with_nothing_added_by_hand():
    """The shipped live model is the output of `torchseam train-live`: its header names the
    data it was fitted on (glint held out), the kept epoch, and no value added by hand."""
    tensors, meta = model_io.read_model(model_io.DEFAULT_MODEL)
    assert meta["format"] == model_io.LIVE_FORMAT
    info = meta["info"]
    assert info.get("added_by_hand") == []
    fams = info["data"]["train"]["families"]
    assert "glint" not in fams and len(fams) >= 3
    assert {f"fusion.log_{n}" for n in FITTED} <= set(tensors)


def test_train_live_command_fits_and_writes_a_run(tmp_path, monkeypatch, capsys):
    """`torchseam train-live` end to end on a tiny set: a run folder with the model and the
    metrics; the values moved from the start; the shipped model untouched without
    --install."""
    from torchseam.cli import main

    cfg = dataclasses.asdict(load_anchored_fit_config())
    cfg.update(families=["sim"], levels=["beyond"], val_levels=["heavy"], frames=40,
               hide_frames=[8], epochs=1, chunk=10, batch=1)
    (tmp_path / "c.yaml").write_text(
        "\n".join(f"{k}: {list(v) if isinstance(v, tuple) else v}" for k, v in cfg.items()))
    before = model_io.DEFAULT_MODEL.read_bytes()
    monkeypatch.chdir(tmp_path)
    rc = main(["train-live", "--config", str(tmp_path / "c.yaml"), "--name", "t1"])
    out = capsys.readouterr().out
    assert rc == 0, out
    run = tmp_path / "runs" / "t1"
    assert (run / "live_tracker.safetensors").is_file() and (run / "metrics.json").is_file()
    assert "epoch 1" in out and model_io.DEFAULT_MODEL.read_bytes() == before
    _, meta = model_io.read_model(run / "live_tracker.safetensors")
    assert meta["info"]["data"]["train"]["families"] == ["sim"]


def test_train_live_interrupted_keeps_the_best_epoch_done(tmp_path, monkeypatch, capsys):
    """Ctrl-C in epoch 1 of 2: exit 130, the best of what was done (the start, epoch 0) written
    to the run as a model the trackers load (said interrupted), nothing installed."""
    import torchseam.fit.anchored as fit_anchored_module
    from torchseam.cli import main

    cfg = dataclasses.asdict(load_anchored_fit_config())
    cfg.update(families=["sim"], levels=["heavy"], val_levels=["heavy"], frames=30,
               hide_frames=[4], epochs=2, chunk=10, batch=1)
    (tmp_path / "c.yaml").write_text(
        "\n".join(f"{k}: {list(v) if isinstance(v, tuple) else v}" for k, v in cfg.items()))
    calls = []
    real = fit_anchored_module.track_set

    def ctrl_c_in_epoch_1(*args, **kwargs):  # the start's validation, then epoch 1's training
        calls.append(1)
        if len(calls) == 2:
            raise KeyboardInterrupt
        return real(*args, **kwargs)

    monkeypatch.setattr(fit_anchored_module, "track_set", ctrl_c_in_epoch_1)
    before = model_io.DEFAULT_MODEL.read_bytes()
    monkeypatch.chdir(tmp_path)
    rc = main(["train-live", "--config", str(tmp_path / "c.yaml"), "--name", "t2", "--install"])
    out, err = capsys.readouterr()
    assert rc == 130 and len(calls) == 2, out + err
    assert "interrupted in epoch 1 of 2" in out and "not installed" in out
    run = tmp_path / "runs" / "t2"
    _, meta = model_io.read_model(run / "live_tracker.safetensors")
    assert meta["info"]["interrupted_in_epoch"] == 1 and meta["info"]["best_epoch"] == 0
    assert model_io.DEFAULT_MODEL.read_bytes() == before
    load_anchored_model(run / "live_tracker.safetensors")  # a model `--model` takes


def test_train_live_refuses_a_start_without_the_stc_extensions_it_fits(tmp_path, monkeypatch,
                                                                      capsys):
    """A start `torchseam train` wrote with its defaults has STC's reg and anchor switched off,
    which train-live's fit frees: one line that says how to fit a start it takes."""
    from torchseam.cli import main
    from torchseam.track.fusion import EAKFSTC

    start = model_io.save_fitted(EAKFSTC(learnable=True), tmp_path / "eakf_stc.safetensors")
    monkeypatch.chdir(tmp_path)
    rc = main(["train-live", "--start", str(start), "--name", "s"])
    err = capsys.readouterr().err
    assert rc == 2 and err.count("\n") == 1, err
    assert f"--start {start}" in err and "reg and anchor switched off" in err
    assert "--tracker reg=20,anchor=0.3" in err
    assert not (tmp_path / "runs" / "s").exists()


def test_train_live_fits_on_labelled_recordings(tmp_path, monkeypatch, capsys):
    """`train-live --data DIR --val-data DIR`: your own labelled recordings instead of the
    simulator (frames + labels.csv, here written by the simulator, some frames unlabelled:
    they count in no loss); --data without --val-data is one clear line."""
    import csv

    from torchseam.cli import main
    from torchseam.sim.record import write_sequence
    from torchseam.sim.sequence import SequenceSpec

    c, p, n = load_cell(), load_part(), load_noise()
    for name, seed in (("rec1", 3), ("rec2", 4)):
        write_sequence(tmp_path / name, c, p, n, SequenceSpec(n_frames=35, level=1.0, seed=seed),
                       progress=False)
    lab = tmp_path / "rec1" / "labels.csv"
    rows = list(csv.DictReader(lab.open()))
    with lab.open("w", newline="") as fh:  # every third frame after the first unlabelled
        w = csv.DictWriter(fh, fieldnames=["frame", "u", "v"])
        w.writeheader()
        w.writerows(r for r in rows if int(r["frame"]) == 0 or int(r["frame"]) % 3)
    cfg = dataclasses.asdict(load_anchored_fit_config())
    cfg.update(epochs=1, chunk=10, batch=1)
    (tmp_path / "c.yaml").write_text(
        "\n".join(f"{k}: {list(v) if isinstance(v, tuple) else v}" for k, v in cfg.items()))
    monkeypatch.chdir(tmp_path)
    rc = main(["train-live", "--config", "c.yaml", "--data", str(tmp_path / "rec1"),
               "--name", "r"])
    err = capsys.readouterr().err
    assert rc == 2 and "--data and --val-data go together" in err and err.count("\n") == 1
    rc = main(["train-live", "--config", "c.yaml", "--data", str(tmp_path / "rec1"),
               "--val-data", str(tmp_path / "rec2"), "--name", "r"])
    out = capsys.readouterr().out
    assert rc == 0, out
    _, meta = model_io.read_model(tmp_path / "runs" / "r" / "live_tracker.safetensors")
    assert meta["info"]["data"]["train"]["recordings"] == [str(tmp_path / "rec1")]
    import json

    m = json.loads((tmp_path / "runs" / "r" / "metrics.json").read_text())
    val = m["history"][0]["val"]["rec2"]
    assert np.isfinite(m["history"][1]["loss"]) and val["rmse"] < 1.5 and val["pct_lost"] == 0


def test_the_trackers_say_the_frame_rate_their_model_was_fitted_at():
    """The weld compares it with the camera's (a note when they differ): the live tracker and
    EAKF-STC carry the model's frame rate, a tracker with nothing fitted per frame none."""
    from torchseam.track.peers import make_tracker

    fps = 1.0 / float(model_io.read_model(model_io.DEFAULT_MODEL)[0]["eakf_stc.eakf.dt"])
    assert make_tracker("anchored", TIPM).fitted_fps == pytest.approx(fps)
    assert make_tracker("eakf-stc", TIPM).fitted_fps == pytest.approx(fps)
    assert make_tracker("tipm", TIPM).fitted_fps is None
