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
    # poses.csv: one row per command, read unchanged by `torchseam robot check`
    poses = list(csv.DictReader((out / "poses.csv").open()))
    assert len(poses) == n and list(poses[0]) == ["t", "x", "y", "z", "q1", "q2", "q3", "q4"]
    capsys.readouterr()
    assert main(["robot", "check", str(out / "poses.csv")]) == 0
    assert f"poses: {n} ok, 0 refused" in capsys.readouterr().out


def test_torch_axis_errors_measure_the_angle_to_the_true_bisector(part, parts):
    import numpy as np

    from torchseam.core.transforms import apply, rotation_about
    from torchseam.live.ring import torch_axis_errors
    from torchseam.sim.scene import Scene, torch_frames

    scene = Scene(part, -60.0)
    seam = scene.true_joint.seam(np.linspace(0.3, 1.2, 7))
    T_B_T = scene.part_pose(1.0)
    R = T_B_T[:3, :3] @ torch_frames(seam)[:, :3, :3]
    p = apply(T_B_T, seam.point)
    tilt = np.radians(np.linspace(0.0, 3.0, 7))      # about each frame's own x (travel)
    x = np.array([1.0, 0, 0])
    R_off = np.stack([r @ rotation_about(x, a) for r, a in zip(R, tilt, strict=True)])
    plan = parts.plan  # the work and travel angles of configs/plan.yaml
    angle, dist = torch_axis_errors(scene, p, R_off, np.full(7, 1.0),
                                    angles=(plan.work_angle_deg, plan.travel_angle_deg))
    np.testing.assert_allclose(angle, np.degrees(tilt), atol=0.02)
    assert dist.max() < 0.02   # the poses sit on the true seam (20 001 samples round it)


def test_ring_poses_csv_round_trips_through_robot_check(cell, part, noise, parts, tmp_path,
                                                        capsys):
    """Every planned command's torch pose (t, x, y, z, q1..q4 in the base frame) in the file
    ``torchseam robot check`` reads, which accepts it unchanged and passes every pose."""
    import numpy as np

    from torchseam.live.ring import run_ring, write_ring_poses

    runs = run_ring(cell, part, noise, noise.level("strike"), 1, segments=[0], length_mm=20.0,
                    parts=parts)
    assert runs[0].report is not None and runs[0].report.ok
    path = write_ring_poses(runs, tmp_path / "poses.csv")
    lines = path.read_text().splitlines()
    assert lines[0] == "t,x,y,z,q1,q2,q3,q4"
    n = len(runs[0].commands)
    assert len(lines) == n + 1 and n >= 8
    rows = np.array([[float(v) for v in ln.split(",")] for ln in lines[1:]])
    np.testing.assert_allclose(rows[:, 1:4], np.array(runs[0].commands), atol=1e-4)
    np.testing.assert_allclose(rows[:, 4:], runs[0].quats, atol=1e-8)
    assert (np.diff(rows[:, 0]) > 0).all()  # at weld speed: 2 mm in 0.25 s
    np.testing.assert_allclose(np.diff(rows[:, 0]), 0.25, atol=0.01)
    capsys.readouterr()
    assert main(["robot", "check", str(path)]) == 0
    assert f"{n} poses: {n} ok, 0 refused" in capsys.readouterr().out
