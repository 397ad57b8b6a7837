"""torchseam track / eval on a small simulated folder, for the classic and OpenCV trackers."""

import csv

import numpy as np
import pytest

from torchseam.cli import main
from torchseam.core.config import load_cell, load_noise, load_part
from torchseam.sim.record import write_sequence
from torchseam.sim.sequence import SequenceSpec


@pytest.fixture(scope="module")
def seq_dir(tmp_path_factory):
    d = tmp_path_factory.mktemp("trk") / "seq"
    write_sequence(d, load_cell(), load_part(), load_noise(),
                   SequenceSpec(n_frames=30, level=0.3, seed=5), progress=False)
    return d


@pytest.mark.parametrize("tracker", ["tipm", "mosse"])
def test_track_writes_one_row_per_frame(seq_dir, tmp_path, tracker, capsys):
    out = tmp_path / "t.csv"
    assert main(["track", str(seq_dir), "--tracker", tracker, "--out", str(out)]) == 0
    rows = list(csv.DictReader(out.open()))
    assert [int(r["frame"]) for r in rows] == list(range(30))
    assert set(r["status"] for r in rows) <= {"tracked", "coasting", "lost"}
    labels = np.loadtxt(seq_dir / "labels.csv", delimiter=",", skiprows=1)[:, 1:]
    uv = np.array([[float(r["u"] or "nan"), float(r["v"] or "nan")] for r in rows])
    err = np.linalg.norm(uv - labels, axis=1)
    # TIPM finds the point itself; MOSSE's box can slide along the stripe but stays near it
    assert np.nanmedian(err) < (1.0 if tracker == "tipm" else 30.0)
    assert "30 frames" in capsys.readouterr().out


def test_track_works_on_frames_only_and_with_init(seq_dir, tmp_path):
    bare = tmp_path / "bare"
    bare.mkdir()
    for p in sorted(seq_dir.glob("0*.png"))[:5]:
        (bare / p.name).write_bytes(p.read_bytes())
    out = tmp_path / "b.csv"
    assert main(["track", str(bare), "--tracker", "mosse", "--init", "300,220",
                 "--out", str(out)]) == 0
    rows = list(csv.DictReader(out.open()))
    assert len(rows) == 5 and rows[0]["u"] == "300.000"


def test_track_defaults_to_the_live_loops_tracker(seq_dir, tmp_path, capsys):
    """Without --tracker, track runs what the live loop runs (anchored), started by TIPM: on
    this folder within 0.25 px of the truth (plain EAKF-STC drifts to ~1 px)."""
    out = tmp_path / "d.csv"
    assert main(["track", str(seq_dir), "--out", str(out)]) == 0
    assert capsys.readouterr().out.startswith("anchored:")
    rows = list(csv.DictReader(out.open()))
    labels = np.loadtxt(seq_dir / "labels.csv", delimiter=",", skiprows=1)[:, 1:]
    uv = np.array([[float(r["u"]), float(r["v"])] for r in rows])
    assert np.linalg.norm(uv - labels, axis=1).max() < 0.5
    assert {r["status"] for r in rows} == {"tracked"}


def test_eval_prints_the_error_table(seq_dir, capsys):
    assert main(["eval", str(seq_dir), "--tracker", "tipm"]) == 0
    out = capsys.readouterr().out
    assert "RMSE px" in out and "lost %" in out
    row = out.strip().splitlines()[-1].split()
    assert row[0] == "tipm" and int(row[1]) == 30 and float(row[2]) < 2.0


def test_bad_input_is_named(tmp_path, capsys):
    assert main(["track", str(tmp_path / "none")]) == 2
    assert "no such folder" in capsys.readouterr().err
    assert main(["track", str(tmp_path), "--init", "1,x"]) == 2
    err = capsys.readouterr().err
    assert "--init" in err and "Traceback" not in err
    assert main(["eval", str(tmp_path)]) == 2
    assert "no frames" in capsys.readouterr().err


def test_a_gap_in_the_numbering_is_reported_not_dropped(seq_dir, tmp_path, capsys):
    gap = tmp_path / "gap"
    gap.mkdir()
    for p in sorted(seq_dir.glob("0*.png"))[:8]:
        if p.name not in ("00003.png", "00004.png"):
            (gap / p.name).write_bytes(p.read_bytes())
    out = tmp_path / "g.csv"
    assert main(["track", str(gap), "--tracker", "tipm", "--out", str(out)]) == 0
    rows = list(csv.DictReader(out.open()))
    assert [int(r["frame"]) for r in rows] == list(range(8))
    assert all(r["u"] == "" for r in rows if r["status"] == "missing")
    assert {int(r["frame"]) for r in rows if r["status"] == "missing"} == {3, 4}
    io = capsys.readouterr()
    assert "2 frame number(s) missing (3, 4)" in io.err and "missing 2" in io.out


def test_eval_counts_an_unreadable_frame_as_lost(seq_dir, tmp_path, capsys):
    """A frame that cannot be decoded is skipped by the tracker and scored as lost (no point),
    not tracked through and not a reason to stop."""
    bad = tmp_path / "bad"
    bad.mkdir()
    for p in sorted(seq_dir.glob("0*.png"))[:10]:
        (bad / p.name).write_bytes(p.read_bytes())
    lines = (seq_dir / "labels.csv").read_text().splitlines()[:11]
    (bad / "labels.csv").write_text("\n".join(lines) + "\n")
    (bad / "00005.png").write_bytes(b"\x89PNG\r\n\x1a\n broken")
    assert main(["eval", str(bad), "--tracker", "tipm"]) == 0
    io = capsys.readouterr()
    assert "1 unreadable, counted lost" in io.out and "00005.png" in io.err
    row = io.out.strip().splitlines()[-1].split()
    assert int(row[1]) == 10 and float(row[5]) == pytest.approx(10.0)


def test_eval_counts_the_frames_said_tracked_and_the_false_ones(seq_dir, tmp_path, capsys):
    """The status against the labels: TIPM says tracked on every frame of this light-arc
    folder; where the labels are moved 12 px (a corner it reads there but the label does not
    have) those frames are false tracked, and only those."""
    moved = tmp_path / "moved"
    moved.mkdir()
    for p in sorted(seq_dir.glob("0*.png")):
        (moved / p.name).write_bytes(p.read_bytes())
    lines = (seq_dir / "labels.csv").read_text().splitlines()
    for k in range(11, 15):  # frames 10..13 (line 0 is the header)
        frame, u, v = lines[k].split(",")
        lines[k] = f"{frame},{float(u) + 12.0},{v}"
    (moved / "labels.csv").write_text("\n".join(lines) + "\n")
    for folder, false in ((seq_dir, 0), (moved, 4)):
        assert main(["eval", str(folder), "--tracker", "tipm"]) == 0
        out = capsys.readouterr().out
        assert "tracked %" in out and "false trk" in out
        row = out.strip().splitlines()[-1].split()
        assert float(row[6]) == pytest.approx(100.0) and int(row[7]) == false, out


def test_ctrl_c_in_track_says_how_far_the_rows_go(seq_dir, tmp_path, monkeypatch, capsys):
    """Ctrl-C during `track` (here on frame 12): the rows written stay, and one line says
    which frames they hold; the command then ends as interrupted (130)."""
    from torchseam.core.dataset import Dataset

    read = Dataset.read

    def read_until_ctrl_c(self, i):
        if i == 12:
            raise KeyboardInterrupt
        return read(self, i)

    monkeypatch.setattr(Dataset, "read", read_until_ctrl_c)
    out = tmp_path / "c.csv"
    assert main(["track", str(seq_dir), "--tracker", "tipm", "--out", str(out)]) == 130
    rows = list(csv.DictReader(out.open()))
    assert [int(r["frame"]) for r in rows] == list(range(12))
    err = capsys.readouterr().err
    assert f"tipm: interrupted after 12 of 30 frames; {out} holds frames 0-11" in err


def test_ctrl_c_in_eval_prints_the_table_of_the_frames_done(seq_dir, monkeypatch, capsys):
    """Ctrl-C during `eval` (on frame 12): the table over the 12 frames tracked, said to be
    partial, then the command ends as interrupted (130)."""
    from torchseam.core.dataset import Dataset

    read = Dataset.read

    def read_until_ctrl_c(self, i, *a, **k):
        if i == 12:
            raise KeyboardInterrupt
        return read(self, i, *a, **k)

    monkeypatch.setattr(Dataset, "read", read_until_ctrl_c)
    assert main(["eval", str(seq_dir), "--tracker", "tipm"]) == 130
    cap = capsys.readouterr()
    assert "tipm: interrupted after 12 of 30 frames; the table is theirs" in cap.err
    assert "(12 of 30 frames labelled; " in cap.out and "start: interrupted)" in cap.out
    row = cap.out.strip().splitlines()[-1].split()
    assert row[0] == "tipm" and row[1] == "12" and float(row[3]) < 1.0  # max px: TIPM's own
