"""torchseam ring on one segment: the error table's figures, and the per-command file that says
which commands miss the torch-axis bar."""

import csv
import json

from torchseam.cli import main


def test_ring_on_one_segment_writes_its_figures_and_every_command(tmp_path, capsys):
    out = tmp_path / "ring"
    assert main(["ring", "--noise", "strike", "--segments", "a", "--seed", "1",
                 "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    summary = json.loads((out / "ring.json").read_text())
    assert summary["3D seam point (located)"]["rmse"] < 0.1
    assert summary["planned path (tracked)"]["max"] < 0.3
    # the tracked path follows the deviated part; the programmed (nominal) one does not
    assert summary["nominal path (design)"]["rmse"] > 10 * summary["planned path (tracked)"]["rmse"]
    rows = list(csv.DictReader((out / "commands.csv").open()))
    n = summary["axis_within_1deg"]["of"]
    assert len(rows) == n > 30
    assert [r["segment"] for r in rows] == ["a"] * n
    assert [int(r["command"]) for r in rows] == list(range(n))
    axis = [float(r["axis_error_deg"]) for r in rows]
    assert sum(a <= 1.0 for a in axis) == summary["axis_within_1deg"]["n"]
    assert abs(max(axis) - summary["torch axis vs bisector"]["max"]) < 1e-3
    assert (out / "quaternions.png").stat().st_size > 0
    assert f"within 1 degree of the bisector: {summary['axis_within_1deg']['n']} of {n}" in printed
    over = [f"a{i} {a:.2f}" for i, a in enumerate(axis) if a > 1.0]
    for o in over[:12]:
        assert o in printed
