"""The seam search from a start off the seam (issue 26, item 3): ``torchseam demo
--start-offset-mm/--start-angle-deg`` finds the seam and welds; a seam beyond the search's
bound is a clear failure (segment incomplete, exit 1) with no motion beyond the bound; the
pattern stays within its bound and its steps within the link's."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from torchseam.cli import main
from torchseam.core.config import load_cell, load_noise, load_part
from torchseam.live.search import SeamSearch, load_search_config, offset_pose, pattern


def _in_start_frame(T_start: np.ndarray, T: np.ndarray) -> tuple[np.ndarray, float]:
    """(offset (3,) mm in the start pose's frame, turn about its z, deg)."""
    M = np.linalg.inv(T_start) @ T
    return M[:3, 3], float(np.degrees(np.arctan2(M[1, 0], M[0, 0])))


def test_pattern_stays_within_its_bound_and_the_links_steps():
    cfg = load_search_config()
    assert max(abs(y) for y, _ in pattern(cfg)) == cfg.max_extent_mm
    assert max(abs(a) for _, a in pattern(cfg)) == cfg.max_angle_deg
    T_start = offset_pose(np.eye(4), lateral_mm=3.0, angle_deg=5.0)
    # the gate refuses everything more than 20 mm to +y: those legs are cut short
    s = SeamSearch(T_start, cfg, 25.0, reachable=lambda T: _in_start_frame(T_start, T)[0][1]
                   <= 20.0)
    poses, t = [T_start], 0.0
    while True:
        assert not s.observe(False, np.full(2, np.nan), t)
        T = s.step()
        if T is None:
            break
        poses.append(T)
        t += 0.04
    assert s.failed and "seam not found" in s.reason and not s.found
    assert s.refused > 0
    for T in poses:
        off, ang = _in_start_frame(T_start, T)
        assert abs(off[0]) < 1e-9 and abs(off[2]) < 1e-9
        assert -cfg.max_extent_mm - 1e-9 <= off[1] <= 20.0 + 1e-9
        assert abs(ang) <= cfg.max_angle_deg + 1e-9
    P = np.array([T[:3, 3] for T in poses])
    assert np.linalg.norm(np.diff(P, axis=0), axis=1).max() <= cfg.speed_mm_s * 0.04 + 1e-9
    assert (len(poses) - 1) * 0.04 <= cfg.time_limit_s + 0.05   # one step a frame


def test_corner_confirmed_on_consecutive_frames_only():
    cfg = load_search_config()
    s = SeamSearch(np.eye(4), cfg, 25.0)
    uv = np.array([300.0, 200.0])
    seq = [uv, uv + 1, None, uv, uv + 40, uv + 41]   # a miss and a jump restart the count
    for i, x in enumerate(seq):
        assert not s.observe(x is not None, x if x is not None else np.full(2, np.nan), i * .04)
    assert s.observe(True, uv + 42, 0.3) and s.found
    assert cfg.confirm_frames == 3


def test_demo_finds_the_seam_from_an_offset_start(tmp_path, capsys):
    rc = main(["demo", "--segments", "a", "--length-mm", "3", "--no-video", "--out",
               str(tmp_path), "--start-offset-mm", "25", "--start-angle-deg", "-10"])
    out = capsys.readouterr().out
    assert rc == 0, out
    assert "segment a: seam found by the search in" in out
    import json

    s = json.loads((tmp_path / "summary.json").read_text())
    (srch,) = s["search"]
    assert srch["found"] and 0 < srch["time_s"] < 10 and srch["extent_mm"] <= 35
    assert s["segments_incomplete"] == [] and s["unsafe_poses_sent"] == 0
    assert s["poses_refused"] == 0 and s["poses_welded"] > 0


def test_start_beyond_the_bound_is_a_clear_failure_without_motion_beyond_it():
    from torchseam.live.cli import demo_exit_code
    from torchseam.live.demo import run_demo
    from torchseam.plan.path import load_plan_config

    cell, part, noise = load_cell(), load_part(), load_noise()
    # a small bound keeps the test short: the seam 60 mm away is never in view
    cfg = dataclasses.replace(load_search_config(), max_extent_mm=15.0, lateral_step_mm=15.0,
                              max_angle_deg=0.0)
    res = run_demo(cell, part, noise, noise.level("heavy"), 0, segments="a", length_mm=3.0,
                   start_offset_mm=60.0, search=cfg)
    s = res.summary
    assert demo_exit_code(s) == 1
    (inc,) = s["segments_incomplete"]
    assert inc["segment"] == "a" and inc["reason"].startswith("seam not found: the search "
                                                              "pattern ended")
    assert "15 mm / 0 deg bound" in inc["reason"]
    assert s["search"][0]["found"] is False and s["poses_welded"] == 0
    assert s["unsafe_poses_sent"] == 0
    # every pose sent lies within the bound around the start
    plan = res.report.plan
    seg = plan.segments[0]
    scene = plan.scene(seg)
    s0 = float(scene.s_at(np.array([seg.phi_start]))[0])
    approach = cell.process.look_ahead_mm + load_plan_config().approach_mm
    T0 = plan.nominal_tcp(seg, np.array([s0 - approach]))[0]
    T_start = offset_pose(T0, lateral_mm=60.0, lift_mm=cfg.standoff_mm)
    assert res.sent
    for _, p, _, _, _ in res.sent:
        off = np.linalg.inv(T_start) @ np.append(p, 1.0)
        assert np.abs(off[[0, 2]]).max() < 1e-6
        assert abs(off[1]) <= 15.0 + 1e-6


@pytest.mark.parametrize("opt", ["--start-offset-mm=500", "--start-angle-deg=nan"])
def test_start_options_refuse_bad_input(opt, tmp_path, capsys):
    rc = main(["demo", "--segments", "a", "--no-video", "--out", str(tmp_path), opt])
    err = capsys.readouterr().err
    assert rc == 2 and "must be within" in err


def test_a_start_the_gate_refuses_moves_nothing():
    """At no stand-off a start 30 mm across the T joint's seam runs the torch into the branch:
    the segment is incomplete with the gate's reason, and no pose is sent."""
    from torchseam.live.cli import demo_exit_code
    from torchseam.live.demo import run_demo

    cell, part, noise = load_cell(), load_part(), load_noise()
    cfg = dataclasses.replace(load_search_config(), standoff_mm=0.0)
    res = run_demo(cell, part, noise, noise.level("heavy"), 0, segments="a", length_mm=3.0,
                   start_offset_mm=-30.0, search=cfg)
    (inc,) = res.summary["segments_incomplete"]
    assert inc["reason"].startswith("start pose refused") and "clearance" in inc["reason"]
    assert res.sent == [] and demo_exit_code(res.summary) == 1


def test_cli_reports_a_seam_not_found_and_exits_1(tmp_path, capsys, monkeypatch):
    import json

    import torchseam.live.demo as demo

    small = dataclasses.replace(load_search_config(), max_extent_mm=15.0, lateral_step_mm=15.0,
                                max_angle_deg=0.0)
    monkeypatch.setattr(demo, "load_search_config", lambda: small)
    rc = main(["demo", "--segments", "a", "--length-mm", "3", "--no-video", "--out",
               str(tmp_path), "--start-offset-mm", "60"])
    out = capsys.readouterr().out
    assert rc == 1
    assert "segment a: seam not found: the search pattern ended" in out
    assert "segment a NOT completed: seam not found" in out
    s = json.loads((tmp_path / "summary.json").read_text())
    assert s["search"][0]["found"] is False and s["unsafe_poses_sent"] == 0
