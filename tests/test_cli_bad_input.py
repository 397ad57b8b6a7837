"""Every bad input gets one clear line (issue 25): exit code 2, one line on stderr naming the
file, field, frame or option, nothing on stdout; and no silent wrong results: bad frames are
marked, not tracked; labels outside the image are refused; ``train`` keeps the shipped model."""

from __future__ import annotations

import csv
import json
import os
import re
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from torchseam.cli import main
from torchseam.core.config import CONFIG_DIR, load_cell, load_noise, load_part
from torchseam.core.dataset import Dataset
from torchseam.fit import model_io
from torchseam.sim.record import write_sequence
from torchseam.sim.sequence import SequenceSpec
from torchseam.track import model_file


def _run(argv: list[str], capsys) -> tuple[int, str, str]:
    """``torchseam ARGV`` in this process: (exit code, stdout, stderr)."""
    try:
        rc = main(argv)
    except SystemExit as e:  # argparse refuses an option
        rc = e.code
    out, err = capsys.readouterr()
    return rc, out, err


@pytest.fixture(scope="module")
def seq(tmp_path_factory) -> Path:
    """Eight clean simulated frames with labels (the dataset format)."""
    d = tmp_path_factory.mktemp("bad") / "seq"
    write_sequence(d, load_cell(), load_part(), load_noise(),
                   SequenceSpec(n_frames=8, level=0.0, seed=5), progress=False)
    return d


def _copy(src: Path, dst: Path) -> Path:
    dst.mkdir()
    for p in src.iterdir():
        (dst / p.name).write_bytes(p.read_bytes())
    return dst


def _yaml_with(path: Path, key: str, value: str) -> str:
    """The text of config ``path`` with the first ``key: ...`` line's value replaced."""
    text = path.read_text()
    new, n = re.subn(rf"^(\s*{key}:)\s*\S+", rf"\g<1> {value}", text, count=1, flags=re.M)
    assert n == 1, key
    return new


def _part_file(tmp: Path, value: str) -> Path:
    p = tmp / "part.yaml"
    p.write_text(_yaml_with(CONFIG_DIR / "parts" / "t_joint.yaml", "main_od_mm", value))
    return p


def _cell_file(tmp: Path) -> Path:
    p = tmp / "cell.yaml"
    p.write_text(_yaml_with(CONFIG_DIR / "cell.yaml", "width", "1000000000"))
    return p


def _labels_outside(tmp: Path, seq: Path) -> Path:
    d = _copy(seq, tmp / "far")
    rows = (d / "labels.csv").read_text().splitlines()
    rows[2] = "1,99999999999,5"  # line 3
    (d / "labels.csv").write_text("\n".join(rows) + "\n")
    return d


def _bad_yaml(tmp: Path, name: str = "bad.yaml") -> Path:
    p = tmp / name
    p.write_text("a: 1\nnot: [valid\n")
    return p


def _bad_yaml_dir(tmp: Path) -> Path:
    d = tmp / "cfgs"
    d.mkdir()
    _bad_yaml(d, "cell.yaml")
    return d


_NOT_YAML = (r"bad\.yaml: not valid YAML: expected ',' or '\]', but got '<stream end>' "
             r"\(line 3, column 1\)$")


def _a_file(tmp: Path) -> Path:
    p = tmp / "a_file"
    p.write_text("not a folder")
    return p


# (case id, argv from (tmp, seq), what the one line must name)
CASES = [
    ("part 1e300", lambda t, s: ["simulate", str(t / "o"), "--frames", "1", "--part",
                                 str(_part_file(t, "1.0e+300"))],
     r"part\.yaml: main_od_mm: expected a number <= 3000"),
    ("part 400 digits", lambda t, s: ["simulate", str(t / "o"), "--frames", "1", "--part",
                                      str(_part_file(t, "9" * 400))],
     r"part\.yaml: main_od_mm: .*400-digit number"),
    ("part 1e300 as text", lambda t, s: ["simulate", str(t / "o"), "--frames", "1", "--part",
                                         str(_part_file(t, "1e300"))],
     r"part\.yaml: main_od_mm: expected a number, got '1e300' \(YAML reads this as text"),
    ("part od 0", lambda t, s: ["simulate", str(t / "o"), "--frames", "1", "--part",
                                str(_part_file(t, "0"))],
     r"part\.yaml: main_od_mm: the main pipe's outer diameter must be > 0 \(at least 10 mm\), "
     r"got 0\.0$"),
    ("part od -5", lambda t, s: ["simulate", str(t / "o"), "--frames", "1", "--part",
                                 str(_part_file(t, "-5"))],
     r"part\.yaml: main_od_mm: the main pipe's outer diameter must be > 0 .*got -5\.0$"),
    ("camera width", lambda t, s: ["simulate", str(t / "o"), "--frames", "1", "--cell",
                                   str(_cell_file(t))],
     r"cell\.yaml: camera\.width: expected a whole number <= 16384"),
    ("part not yaml", lambda t, s: ["simulate", str(t / "o"), "--part", str(_bad_yaml(t))],
     _NOT_YAML),
    ("cell not yaml", lambda t, s: ["simulate", str(t / "o"), "--cell", str(_bad_yaml(t))],
     _NOT_YAML),
    ("train config not yaml", lambda t, s: ["train", "--config", str(_bad_yaml(t))], _NOT_YAML),
    ("plan robot-config not yaml", lambda t, s: ["plan", "--robot-config", str(_bad_yaml(t))],
     _NOT_YAML),
    ("simulate start nan", lambda t, s: ["simulate", str(t / "o"), "--start-mm", "nan"],
     r"--start-mm must be an arc length"),
    ("simulate seed -1", lambda t, s: ["simulate", str(t / "o"), "--seed", "-1"],
     r"argument --seed: -1 is out of range"),
    ("simulate into a file", lambda t, s: ["simulate", str(_a_file(t))],
     r"argument out: .*a_file is a file, not a folder"),
    ("demo seed -1", lambda t, s: ["demo", "--seed", "-1"], r"argument --seed: -1 is out of"),
    ("demo out a file", lambda t, s: ["demo", "--out", str(_a_file(t))],
     r"argument --out: .*a_file is a file, not a folder"),
    ("demo segments aa", lambda t, s: ["demo", "--segments", "aa"],
     r"argument --segments: 'aa': segment 'a' is given twice"),
    ("demo segments xz", lambda t, s: ["demo", "--segments", "xz"],
     r"argument --segments: 'xz': unknown letter 'x'"),
    ("labels outside the image", lambda t, s: ["eval", str(_labels_outside(t, s))],
     r"far/labels\.csv: line 3: u 99999999999 lies outside the 656 x 492 px frames"),
    ("track out a folder", lambda t, s: ["track", str(s), "--out", str(t)],
     r"argument --out: .* is a folder, not a file"),
    ("track threads 0", lambda t, s: ["track", str(s), "--threads", "0"],
     r"argument --threads: 0: use 1 or more threads"),
    ("eval threads -1", lambda t, s: ["eval", str(s), "--threads", "-1"],
     r"argument --threads: -1: use 1 or more threads"),
    ("calibrate write into a file", lambda t, s: ["calibrate", "tcp", str(t),
                                                  "--write", str(_a_file(t) / "c.yaml")],
     r"argument --write: .*a_file/c\.yaml: .*a_file is a file, not a folder"),
    ("calibrate write a folder", lambda t, s: ["calibrate", "tcp", str(t), "--write", str(t)],
     r"argument --write: .* is a folder, not a file"),
    ("calibrate simulate into a file", lambda t, s: ["calibrate", "simulate", "tcp",
                                                     str(_a_file(t))],
     r"argument DIR: .*a_file is a file, not a folder"),
    ("detect no such file", lambda t, s: ["detect", str(t / "nofile.png")],
     r"^torchseam detect: error: .*nofile\.png: no such file$"),
    ("detect overlay a file", lambda t, s: ["detect", str(s / "00000.png"), "--overlay",
                                            str(_a_file(t))],
     r"argument --overlay: .*a_file is a file, not a folder"),
    ("track model missing", lambda t, s: ["track", str(s), "--model", str(t / "no.st")],
     r"argument --model: .*no\.st: no such model file"),
    ("track a video", lambda t, s: ["track", str(_a_file(t).rename(t / "weld.avi"))],
     r"weld\.avi: not a folder of frames .*torchseam replay .*weld\.avi"),
    ("track model junk", lambda t, s: ["track", str(s), "--model", str(_a_file(t))],
     r"a_file: not a readable safetensors model file"),
    ("model for tipm", lambda t, s: ["track", str(s), "--tracker", "tipm", "--model",
                                     str(model_io.DEFAULT_MODEL)],
     r"--model .*: tracker tipm loads no model"),
    ("replay model missing", lambda t, s: ["replay", str(s), "--model", str(t / "no.st")],
     r"argument --model: .*no\.st: no such model file"),
    ("replay pose not unit", lambda t, s: ["replay", str(s), "--pose", "900,0,400,2,0,0,0"],
     r"--pose: quaternion Q1\.\.Q4 \(w, x, y, z\) must have norm 1, got 2\.000000"),
    ("train the shipped model", lambda t, s: ["train", "--data", str(s), "--model",
                                              str(model_io.DEFAULT_MODEL)],
     r"--model .*live_tracker\.safetensors is the model the trackers load: .*--install"),
    ("train resume unnamed", lambda t, s: ["train", "--data", str(s), "--resume"],
     r"--resume: name the run to continue with --name"),
    ("train bad name", lambda t, s: ["train", "--data", str(s), "--name", "../x"],
     r"argument --name: '\.\./x': use a plain folder name"),
]


@pytest.mark.parametrize(("argv", "message"), [c[1:] for c in CASES], ids=[c[0] for c in CASES])
def test_bad_input_is_one_line(argv, message, tmp_path, seq, capsys, monkeypatch):
    work = tmp_path / "cwd"
    work.mkdir()
    monkeypatch.chdir(work)  # default outputs (track.csv, demo_out, runs/) land here
    args = argv(tmp_path, seq)
    rc, out, err = _run(args, capsys)
    assert rc == 2, err
    assert out == ""
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert re.match(rf"torchseam {args[0]}( {args[1]})?: error: ", lines[0]), lines[0]
    assert re.search(message, lines[0]), lines[0]
    assert not any(work.iterdir())  # a refused command leaves no output behind


# --------------------------------------------------------------------------- track, labels

def test_track_marks_bad_frames_unreadable_and_goes_on(seq, tmp_path, capsys):
    d = _copy(seq, tmp_path / "mixed")
    (d / "00002.png").write_text("not a png")  # undecodable
    small = cv2.resize(cv2.imread(str(seq / "00004.png")), (320, 240))
    cv2.imwrite(str(d / "00004.png"), small)  # a frame of another size
    (d / "labels.csv").write_text("frame,u,v\n99,1,1\n")  # names no image: track ignores it
    out = tmp_path / "t.csv"
    rc, stdout, err = _run(["track", str(d), "--out", str(out)], capsys)
    assert rc == 0, err
    rows = list(csv.DictReader(out.open()))
    assert [int(r["frame"]) for r in rows] == list(range(8))
    status = {int(r["frame"]): r["status"] for r in rows}
    assert status[2] == status[4] == "unreadable"
    assert {status[f] for f in (0, 1, 3, 5, 6, 7)} == {"tracked"}
    assert all(r["u"] == "" for r in rows if r["status"] == "unreadable")
    assert "00002.png: cannot be decoded" in err and "320 x 240" in err
    assert "unreadable 2" in stdout


def test_track_writes_each_row_as_it_goes(seq, tmp_path, capsys, monkeypatch):
    """A run that stops part-way keeps the rows of the frames it tracked."""
    import torchseam.track.peers as peers
    from torchseam.core.errors import TorchseamError

    class Failing:
        name = "failing"
        n = 0

        def init(self, frame, uv):
            pass

        def update(self, frame):
            self.n += 1
            if self.n == 3:
                raise TorchseamError("the tracker gave up")
            return np.array([300.0, 200.0]), 0

    monkeypatch.setattr(peers, "make_tracker", lambda *a, **k: Failing())
    out = tmp_path / "t.csv"
    rc, _, err = _run(["track", str(seq), "--out", str(out), "--init", "300,200"], capsys)
    assert rc == 2 and "the tracker gave up" in err
    rows = list(csv.DictReader(out.open()))
    assert [int(r["frame"]) for r in rows] == [0, 1, 2]


def test_labels_with_a_byte_order_mark_are_read(seq, tmp_path, capsys):
    d = _copy(seq, tmp_path / "bom")
    text = (seq / "labels.csv").read_text()
    (d / "labels.csv").write_bytes(b"\xef\xbb\xbf" + text.encode())
    ds = Dataset.open(d, require_labels=True)
    np.testing.assert_array_equal(ds.labels, Dataset.open(seq).labels)
    rc, out, err = _run(["eval", str(d), "--tracker", "tipm"], capsys)
    assert rc == 0, err
    assert "RMSE px" in out


# --------------------------------------------------------------------------- --model

def _track_uv(capsys, seq: Path, out: Path, *extra: str) -> np.ndarray:
    rc, _, err = _run(["track", str(seq), "--tracker", "eakf-stc", "--out", str(out), *extra],
                      capsys)
    assert rc == 0, err
    return np.array([[float(r["u"]), float(r["v"])] for r in csv.DictReader(out.open())])


def test_model_option_loads_that_model(seq, tmp_path, capsys):
    from torchseam.track.anchored import fitted_eakf_stc

    module = fitted_eakf_stc(model_path=model_file.EAKF_STC_MODEL)  # eakf-stc's default
    same = model_io.save_fitted(module, tmp_path / "same.safetensors")
    with torch.no_grad():
        module.eakf.log_r.add_(6.0)  # a far noisier measurement: the filter lags
    other = model_io.save_fitted(module, tmp_path / "other.safetensors")
    base = _track_uv(capsys, seq, tmp_path / "a.csv")
    np.testing.assert_array_equal(_track_uv(capsys, seq, tmp_path / "b.csv", "--model",
                                            str(same)), base)
    moved = _track_uv(capsys, seq, tmp_path / "c.csv", "--model", str(other))
    assert np.abs(moved - base).max() > 1e-3


# --------------------------------------------------------------------------- train outputs

def test_train_writes_a_run_folder_and_install_keeps_a_backup(tmp_path, monkeypatch, capsys):
    from torchseam.fit.synthetic import write_synthetic_sequences

    syn = tmp_path / "syn"
    write_synthetic_sequences(syn, n=2, T=12, seed=3)
    cfg = tmp_path / "small.yaml"
    cfg.write_text(json.dumps({"tracker": {"window": [32, 32], "target": [16, 16]}, "roi": 64,
                               "margin": 20, "batch": 2, "chunk": 6, "epochs": 1,
                               "val_fraction": 0.0, "progress": False, "test": False,
                               "cache": str(tmp_path / "cache")}))
    shipped = tmp_path / "models" / "live_tracker.safetensors"
    shipped.parent.mkdir()
    shipped.write_bytes(model_io.DEFAULT_MODEL.read_bytes())
    old = shipped.read_bytes()
    monkeypatch.setattr(model_io, "DEFAULT_MODEL", shipped)
    monkeypatch.setattr(model_file, "DEFAULT_MODEL", shipped)
    monkeypatch.chdir(tmp_path)
    common = ["train", "--config", str(cfg), "--data", str(syn)]

    rc, out, err = _run(common, capsys)
    assert rc == 0, err
    (run,) = (tmp_path / "runs").iterdir()
    assert re.fullmatch(r"\d{8}-\d{6}", run.name)
    assert {"eakf_stc.safetensors", "last.pt", "metrics.json"} <= {p.name for p in run.iterdir()}
    assert shipped.read_bytes() == old
    assert len(list(shipped.parent.iterdir())) == 1  # nothing replaced, no backup
    # the closing advice names what works: train --install is refused (below)
    advice = out.strip().splitlines()[-1]
    assert "--model " in advice and "`torchseam train-live --install`" in advice, advice
    assert "train --install" not in out

    # EAKF-STC alone cannot replace the live tracker's model: refused before any fitting
    rc, out, err = _run([*common, "--name", "r1", "--install"], capsys)
    assert rc == 2 and out == "" and "train-live --install" in err
    assert not (tmp_path / "runs" / "r1").exists() and shipped.read_bytes() == old

    rc, out, err = _run([*common, "--name", "r1"], capsys)
    assert rc == 0, err
    rc, out, err = _run([*common, "--name", "r1"], capsys)  # that run exists
    assert rc == 2 and out == "" and "last.pt exists" in err and "--resume" in err


# --------------------------------------------------------------------------- bad YAML, one line

def test_bad_yaml_in_a_config_folder_is_one_line(tmp_path, capsys):
    """A config folder (``--config-dir`` or ``$TORCHSEAM_CONFIGS``) with a file that is not
    YAML: one line naming the file, the problem, its line and column; exit code 2."""
    d = _bad_yaml_dir(tmp_path)
    rc, out, err = _run(["--config-dir", str(d), "simulate", str(tmp_path / "o")], capsys)
    assert rc == 2 and out == ""
    assert err.count("\n") == 1, err
    assert re.search(r"^torchseam simulate: error: .*cfgs/cell\.yaml: not valid YAML: "
                     r"expected ',' or '\]', but got '<stream end>' \(line 3, column 1\)$",
                     err.strip()), err
    env = dict(os.environ, TORCHSEAM_CONFIGS=str(d))
    r = subprocess.run([sys.executable, "-m", "torchseam", "simulate", str(tmp_path / "o")],
                       capture_output=True, text=True, env=env, timeout=120)
    assert r.returncode == 2 and r.stdout == ""
    assert r.stderr.count("\n") == 1, r.stderr
    assert "cfgs/cell.yaml: not valid YAML: expected ',' or ']'" in r.stderr
    assert not (tmp_path / "o").exists()


# --------------------------------------------------------------------------- $TORCHSEAM_MODELS

@pytest.mark.parametrize("folder", ["missing", "empty"])
def test_models_env_naming_no_model_is_an_error(folder, seq, tmp_path, capsys, monkeypatch):
    """``$TORCHSEAM_MODELS`` set to a folder that is missing, or has no live-tracker model: one
    line naming the variable and the path, exit code 2 (no silent fallback to other values).
    The variable is read at import (as the command does at start): set here as it was read."""
    d = tmp_path / folder
    if folder == "empty":
        d.mkdir()
    monkeypatch.setattr(model_file, "MODELS_FROM_ENV", str(d))
    monkeypatch.setattr(model_file, "MODEL_DIR", d)
    monkeypatch.setattr(model_file, "DEFAULT_MODEL", d / "live_tracker.safetensors")
    monkeypatch.setattr(model_file, "EAKF_STC_MODEL", d / "eakf_stc.safetensors")
    for tracker in ("anchored", "eakf-stc"):
        rc, out, err = _run(["eval", str(seq), "--tracker", tracker], capsys)
        assert rc == 2 and out == ""
        assert err.count("\n") == 1, err
        want = ("no such folder" if folder == "missing"
                else "no live_tracker.safetensors in that folder")
        assert err.startswith(f"torchseam eval: error: $TORCHSEAM_MODELS={d}: {want}"), err
    # TIPM loads no model: the variable does not matter
    rc, out, err = _run(["eval", str(seq), "--tracker", "tipm"], capsys)
    assert rc == 0, err


# --------------------------------------------------------------------------- a label, no image

def test_eval_skips_a_label_whose_image_is_missing_with_a_warning(seq, tmp_path, capsys):
    """A frame lost from the folder while its label stays (a dropped frame) is a gap, which
    the README says is not an error: eval scores the rest and names the frame on stderr."""
    d = _copy(seq, tmp_path / "gap")
    (d / "00005.png").unlink()
    rc, out, err = _run(["eval", str(d), "--tracker", "tipm"], capsys)
    assert rc == 0, err
    assert "Traceback" not in err and "error" not in err
    assert re.search(r"warning: .*gap/labels\.csv: 1 label\(s\) of frames with no image "
                     r"skipped \(frame 5\)", err), err
    assert re.search(r"warning: .*gap: 1 frame number\(s\) missing \(5\)", err), err
    assert re.search(r"^ *tipm +7 ", out, re.M), out  # the 7 frames with images, scored
