"""Girth joints (issue 37): the ``inline`` kind's butt and lap (core/part.py InlineJoint), their
checks, the simulator's frames of them and their truth, against the butt and lap profiles."""

from __future__ import annotations

import numpy as np
import pytest

from torchseam.core.config import CONFIG_DIR, ConfigError, load_cell, load_noise, load_part
from torchseam.core.part import InlineJoint, make_joint, torch_frames
from torchseam.sim.sequence import SequenceSpec, simulate
from torchseam.vision.profiles import LAP_DARK_FACE, ProfileFinder, load_profile_config
from torchseam.vision.tipm import load_tipm

BUTT = CONFIG_DIR / "parts" / "pipe_butt.yaml"
LAP = CONFIG_DIR / "parts" / "pipe_lap.yaml"
PHI = np.linspace(0.0, 2.0 * np.pi, 37)


def _radial(j: InlineJoint, p: np.ndarray) -> np.ndarray:
    """Unit directions out from the branch's axis at points p (N, 3)."""
    q = p - j.o - np.outer((p - j.o) @ j.d, j.d)
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def test_butt_seam_is_the_middle_of_the_gap():
    part = load_part(BUTT)
    j = make_joint(part)
    assert isinstance(j, InlineJoint) and not j.seam_on_surface
    s = j.seam(PHI)
    g = part.root_gap_mm
    # inside the outer walls (the hi-lo puts them 0.5 mm apart), along the axis: the upper
    # pipe's end face half the gap up (surface 2), the lower pipe's half the gap down (1)
    inner = s.point - 1.0 * _radial(j, s.point)
    t, surf = j.raycast(inner, np.tile(j.d, (len(PHI), 1)))
    assert np.allclose(t, g / 2, atol=0.02) and np.all(surf == 2)
    t, surf = j.raycast(inner, np.tile(-j.d, (len(PHI), 1)))
    assert np.allclose(t, g / 2, atol=0.02) and np.all(surf == 1)
    # the end faces look along the axis; the torch stands on the pipe's normal
    face_up = j.normal_main(inner + np.outer(np.full(len(PHI), -g / 2), j.d))
    assert np.allclose(face_up, j.d)
    z = torch_frames(s)[:, :3, 2]
    assert np.allclose(z @ j.d, 0.0, atol=0.02)                     # the hi-lo tilts it a hair
    assert np.all(np.einsum("ij,ij->i", z, _radial(j, s.point)) < -0.999)
    # a ray straight into the gap from outside goes into the bore: lost
    out = s.point + 5.0 * _radial(j, s.point)
    t, _ = j.raycast(out, -_radial(j, s.point))
    assert np.all(np.isinf(t))


def test_lap_seam_is_the_corner_of_the_sleeve_and_the_pipe():
    part = load_part(LAP)
    j = make_joint(part)
    assert j.seam_on_surface
    s = j.seam(PHI)
    assert np.allclose((s.point - j.o) @ j.d, 0.0, atol=1e-9)       # in the end face's plane
    # down the axis from just above, just out from the pipe: the sleeve's end face (1)
    start = s.point + 0.5 * _radial(j, s.point) + 0.3 * j.d
    t, surf = j.raycast(start, np.tile(-j.d, (len(PHI), 1)))
    assert np.allclose(t, 0.3, atol=1e-9) and np.all(surf == 1)
    # in from beyond the sleeve just above its face: the pipe (2); just below: the sleeve (1)
    for dz, sid, depth in ((0.3, 2, part.sleeve_wall_mm + 5.0), (-0.3, 1, 5.0)):
        o = s.point + (part.sleeve_wall_mm + 5.0) * _radial(j, s.point) + dz * j.d
        t, surf = j.raycast(o, -_radial(j, s.point))
        assert np.all(surf == sid) and np.allclose(t, depth, atol=0.1), (dz, t[:3])
    # the torch bisects the end face and the pipe: 45 degrees off the axis
    z = torch_frames(s)[:, :3, 2]
    assert np.allclose(np.degrees(np.arccos(z @ -j.d)), 45.0, atol=0.5)


def test_main_solid_is_the_pipe_on_the_branch_axis():
    for path in (BUTT, LAP):
        j = make_joint(load_part(path))
        m = j.main_solid()
        assert np.allclose(m["rotation"][:, 0], j.d)                  # its own x: the axis
        assert np.allclose(m["rotation"].T @ m["rotation"], np.eye(3))
        assert m["origin"] @ j.d < 0 and m["half_length"] > 0


@pytest.mark.parametrize("change, message", [
    ({"joint": "fillet"}, "joint: a part of kind inline is a butt or a lap"),
    ({"root_gap_mm": 0.0}, "root_gap_mm: a butt's gap"),
    ({"branch_offset_mm": [6.0, 4.0]}, "branch_offset_mm: the pipes' ends must overlap"),
    ({"intersection_angle_deg": 80.0}, "intersection_angle_deg: a part of kind inline"),
    ({"sleeve_wall_mm": 3.0}, "sleeve_wall_mm: a butt has no sleeve"),
    ({"kind": "pipe", "main_od_mm": 203.0}, "joint: a butt joint is a part of kind inline"),
])
def test_bad_girth_parts_are_named(tmp_path, change, message):
    import yaml

    data = yaml.safe_load(BUTT.read_text())
    data.update(change)
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump(data))
    with pytest.raises(ConfigError, match=message):
        load_part(path)
    lap = yaml.safe_load(LAP.read_text())
    lap["root_gap_mm"] = 1.0
    path.write_text(yaml.safe_dump(lap))
    with pytest.raises(ConfigError, match="root_gap_mm: a lap has none"):
        load_part(path)


@pytest.mark.parametrize("path, family", [(BUTT, "sim"), (BUTT, "thin"), (LAP, "sim"),
                                          (LAP, "smoke")])
def test_rendered_girth_joint_shows_its_aim_point(path, family):
    """Clean frames of each girth joint along its seam: the profile on the whole frame puts
    the aim point within a pixel of the simulator's truth (the gap's centre; the lap's
    corner), the held-out families included."""
    part, noise = load_part(path), load_noise()
    finder = ProfileFinder(load_tipm(), load_profile_config(), part.joint)
    errs = []
    for img, truth in simulate(load_cell(), part, noise, SequenceSpec(
            n_frames=8, start_mm=60.0, level=0.0, seed=3, family=family)):
        res = finder(img)
        assert truth.visible and res.ok, res.status
        errs.append(float(np.linalg.norm(res.aim - truth.uv)))
    assert max(errs) <= 1.0, errs


def _track_along(path, family: str, level: str, n_frames: int, seed: int = 1000
                 ) -> tuple[list[float], int, int]:
    """The profile tracker along a girth joint as bench/profiles.py runs it (``seed``, from
    100 mm; the locator's prediction: the truth a frame before): the errors (px) of the
    frames tracked, the frames lost and the frames scored (arc frames with the seam in
    view)."""
    from torchseam.track.fusion import TrackStatus
    from torchseam.track.profile import ProfileTracker, load_profile_track_config

    part, noise = load_part(path), load_noise()
    tracker = ProfileTracker(ProfileFinder(load_tipm(), load_profile_config(), part.joint),
                             load_profile_track_config())
    seq = iter(simulate(load_cell(), part, noise, SequenceSpec(
        n_frames=n_frames, start_mm=100.0, level=noise.level(level), seed=seed,
        family=family)))
    img0, truth0 = next(seq)
    res0 = tracker.find(img0)
    assert res0.ok and np.linalg.norm(res0.aim - truth0.uv) < 1.0, res0.status
    tracker.init(img0, res0.aim)
    prev, tracked, lost, frames = truth0.uv, [], 0, 0
    for k, (img, truth) in enumerate(seq, start=1):
        tracker.expect(prev)
        r = tracker.track(img)
        prev = truth.uv
        if k < noise.clean_lead_frames or not truth.visible:
            continue
        frames += 1
        if r.status == TrackStatus.TRACKED:
            tracked.append(float(np.linalg.norm(r.uv - truth.uv)))
        lost += r.status == TrackStatus.LOST
    return tracked, lost, frames


@pytest.mark.parametrize("path, family, level, share", [
    (BUTT, "smoke", "extreme", 0.0), (BUTT, "wide", "extreme", 0.0),
    (LAP, "wide", "extreme", 0.8), (BUTT, "glint", "heavy", 0.8)])
def test_profile_tracker_on_held_out_families_under_the_arc(path, family, level, share):
    """The bench's rows on held-out families (bench/profiles.py, 80 frames, seed 1000;
    docs/benchmarks.md), each against the simulator's truth: no frame ``tracked`` more than
    3 px off, none lost, at least ``share`` of the frames tracked. Before h20: the butt in
    ``smoke`` extreme: the glare, standing on the seam, ate both gap edges alike and the
    tracker kept one "in its place" and put the other back from it, 3.17 px off, ``tracked``
    (now the span's centre as read is one of the readings). The butt in ``wide`` extreme: the
    gap reads ~15 px under the arc against 11.7 on the clean lead-in, and a far-off structure
    whose span agreed by chance reset the count of frames off it: 7 frames lost (the span's
    history learns from evidence only). The lap in ``wide`` extreme: its step white under the
    arc, the red excess blind there and its step 30-230 px off on half the frames: 40 %
    tracked (the brightness is read where the red excess's centre line breaks on white).
    The butt in ``glint`` heavy: a glint streak over the stripe dropped its columns from the
    centre line, a break wider than the gap 40-50 px beside it: 29 % tracked (the gap is the
    widest break as the stripe's ends read it)."""
    tracked, lost, frames = _track_along(path, family, level, 80)
    assert max(tracked, default=0.0) <= 3.0, sorted(tracked)[-5:]
    assert lost == 0
    assert len(tracked) >= share * frames, (len(tracked), frames)


def test_a_lap_whose_lit_face_lost_its_centre_line_is_no_dark_face():
    """The bench's lap row in ``smoke`` heavy, seed 1001 (bench/profiles.py, 80 frames): on
    frame 73 the speckled, fume-dimmed stripe down the lap's lit edge face is dropped from the
    centre line (its pieces too small) and fume breaks it at the root; the finder saw two
    plates and no face and read the plates' ends apart (a dark face): the root 4.9 px short
    along its plate, the edge 2.7 px carried on into the face's light at its corner, their
    span 2.2 px off its recent one (within ``edge_tol_px``): ``tracked`` 4.91 px off the
    simulator's truth. The face is lit between the two ends (89 % of the way): no dark face,
    no profile (the tracker coasts). Against the truth: no frame tracked more than 3 px off,
    none lost, most tracked."""
    tracked, lost, frames = _track_along(LAP, "smoke", "heavy", 80, seed=1001)
    assert max(tracked, default=0.0) <= 3.0, sorted(tracked)[-5:]
    assert lost == 0
    assert len(tracked) >= 0.7 * frames, (len(tracked), frames)


@pytest.mark.parametrize("path, family", [(BUTT, "sim"), (BUTT, "wide"), (LAP, "sim")])
def test_profile_tracker_is_honest_on_a_girth_joint_under_the_arc(path, family):
    """The profile tracker along a girth joint under heavy arc light (the bench's set-up:
    bench/profiles.py): the arc's glare eats a gap edge now and then, so the gap reads wider
    and its centre moves off by half the loss; no frame may be ``tracked`` more than 3 px off
    the simulator's truth; on the family the profiles were chosen on most frames are tracked
    (the held-out wide family, its stripe wide and saturated, loses the butt's gap under the
    arc's glare: docs/benchmarks.md; it may coast, never claim a wrong point)."""
    tracked, _, frames = _track_along(path, family, "heavy", 60)
    assert max(tracked, default=0.0) <= 3.0, sorted(tracked)[-5:]
    if family == "sim":
        assert len(tracked) >= 0.6 * frames, (len(tracked), frames)


@pytest.mark.parametrize("path", [BUTT, LAP])
def test_closed_loop_welds_a_girth_joint(tmp_path, path):
    """``torchseam demo`` on each girth joint under the default (heavy) arc, a short stretch of
    segment a: the loop follows the profile's aim point; the butt's torch frame stands across
    its straight stripe (arms in one line: no corner to bisect), the lap's bisects its far
    plate and edge face; torch path and axis against the simulator's truth."""
    import json

    from torchseam.cli import main

    rc = main(["demo", "--part", str(path), "--segments", "a", "--length-mm", "15",
               "--no-video", "--out", str(tmp_path)])
    s = json.loads((tmp_path / "summary.json").read_text())
    assert rc == 0 and s["segments_incomplete"] == [], s["hold_reasons"]
    assert s["seam_rmse_mm"] <= 0.1 and s["seam_max_mm"] <= 0.3
    assert s["axis_max_deg"] <= 1.0 and s["axis_within_1deg"] >= 5
    assert s["unsafe_poses_sent"] == 0


def _lap_tracker(note: str, frames: list[tuple[np.ndarray, np.ndarray]]):
    """A profile tracker on a lap whose profile per frame is given ((root, edge) px, the note
    :attr:`ProfileResult.reason` of the profile: LAP_DARK_FACE or none) in place of a finder's
    reading of a frame; its results for frames 1 on, each with the prediction the locator
    gives it (the first root: the seam stands still)."""
    from torchseam.track.profile import ProfileTracker, load_profile_track_config
    from torchseam.vision.profiles import ProfileResult

    plate = np.array([-0.84, 0.54])   # the far plate from the root (image directions)
    tracker = ProfileTracker(ProfileFinder(load_tipm(), load_profile_config(), "lap"),
                             load_profile_track_config())
    it = iter(frames)

    def window(frame, centre):
        root, edge = next(it)
        face = (edge - root) / np.linalg.norm(edge - root)
        return ProfileResult("lap", True, root.copy(), {"root": root, "edge": edge}, note,
                             width_px=30.0, arm_points=np.stack([root + 40 * plate,
                                                                 root + 40 * face]))

    tracker._window = window
    img = np.zeros((480, 640), np.uint8)
    tracker.init(img, frames[0][0])
    out = []
    for _ in frames[1:]:
        tracker.expect(frames[0][0])
        out.append((tracker.track(img), tracker.result))
    return out


@pytest.mark.parametrize("dark", [False, True])
def test_a_lap_step_off_its_span_is_put_back_only_where_its_ends_are_read_apart(dark):
    """The arc's glare over a lap's lit edge face bends the face's centre line: the root and
    the edge, where that one line meets the plates', both slide along their plates, the edge
    less (it lies nearer the line's turn). The step reads off its recent span, and the edge,
    still near its place, is no reading to put the root back from (it carried its own error
    into the seam, the same way on every such frame): no evidence. Where the face is dark the
    two ends are the plates' own ends, read apart: a root the glare ate is put back at the
    span from the edge, as before."""
    from torchseam.track.fusion import TrackStatus

    root, edge = np.array([311.0, 230.0]), np.array([365.5, 264.8])
    clean = [(root, edge)] * 6
    if dark:    # the root eaten back along its plate, the edge where it is
        off = (root + 4.0 * np.array([0.84, -0.54]), edge)
    else:       # the face's line turned: the root 4.7 px down its plate, the edge 1.7 up its
        off = (root + 4.7 * np.array([-0.84, 0.54]), edge + 1.7 * np.array([0.84, -0.54]))
    results = _lap_tracker(LAP_DARK_FACE if dark else "", [*clean, off])
    for r, _ in results[:-1]:
        assert r.status == TrackStatus.TRACKED and np.allclose(r.uv, root)
    r, res = results[-1]
    if dark:
        assert r.status == TrackStatus.TRACKED and np.allclose(r.uv, root), r.uv
        assert "root at its recent span" in res.reason
    else:
        assert r.status == TrackStatus.COASTING and res is None, r.status


def test_a_lap_whose_two_ends_are_eaten_is_not_read_at_the_span_centre():
    """A butt's two gap edges flank the seam, and the glare standing on it eats them alike:
    the span's centre as read holds. A lap's aim is one of its ends (the root); the glare
    round it eats the root and the edge (the face's length away) unlike each other, and the
    root moved by half the span's excess is off by half the difference (the bench's lap
    `smoke` extreme row, seed 1002, frame 58: root 15.6 px and edge 9.1 px short, taken so
    3.17 px off). Here the root is eaten 8.5 px back along its plate, the edge 4 px along its:
    the root as read (8.5 px off) and the root put back from the edge (4 px off) are both
    farther than edge_tol_px from the prediction; half the excess would put it 2.25 px off.
    No evidence."""
    from torchseam.track.fusion import TrackStatus

    root, edge = np.array([311.0, 230.0]), np.array([365.5, 264.8])
    along = np.array([0.84, -0.54]) / np.linalg.norm([0.84, -0.54])  # root -> edge's plate
    eaten = (root - 8.5 * along, edge + 4.0 * along)
    results = _lap_tracker(LAP_DARK_FACE, [*[(root, edge)] * 6, eaten])
    for r, _ in results[:-1]:
        assert r.status == TrackStatus.TRACKED and np.allclose(r.uv, root)
    r, res = results[-1]
    assert r.status == TrackStatus.COASTING and res is None, (r.status, res and res.reason)


def _butt_tracker(frames: list[tuple[np.ndarray, np.ndarray]]):
    """A profile tracker on a butt whose gap edges per frame are given ((left, right) px) in
    place of a finder's reading of a frame; its results for frames 1 on, the prediction the
    first frame's centre (the seam stands still), and the tracker."""
    from torchseam.track.profile import ProfileTracker, load_profile_track_config
    from torchseam.vision.profiles import ProfileResult

    tracker = ProfileTracker(ProfileFinder(load_tipm(), load_profile_config(), "butt"),
                             load_profile_track_config())
    it = iter(frames)

    def window(frame, centre):
        a, b = next(it)
        return ProfileResult("butt", True, (a + b) / 2, {"left_edge": a, "right_edge": b},
                             "break", width_px=float(b[0] - a[0]),
                             arm_points=np.stack([a - [40.0, 0.0], b + [40.0, 0.0]]))

    tracker._window = window
    img = np.zeros((480, 640), np.uint8)
    centre = (frames[0][0] + frames[0][1]) / 2
    tracker.init(img, centre)
    out = []
    for _ in frames[1:]:
        tracker.expect(centre)
        out.append((tracker.track(img), tracker.result))
    return out, tracker


def test_a_butt_gap_eaten_at_both_edges_keeps_its_centre_as_read():
    """The arc's glare stands on the seam (the torch is there) and eats a butt's two gap
    edges alike as often as one: the gap reads wider, its centre stays. An edge "in its
    place" within edge_tol_px beside an edge eaten as far is no reading to put the other back
    from (it carried its own loss into the seam: 3.17 px off, ``tracked``, on the bench's
    butt `smoke` extreme row): of the three readings (either edge as read and the other at the
    recent span from it, or both off alike: the centre as read) the one nearest the
    prediction is taken. One edge eaten far is still put back from the other."""
    from torchseam.track.fusion import TrackStatus

    left, right = np.array([300.0, 240.0]), np.array([315.0, 240.0])
    truth = (left + right) / 2
    clean = [(left, right)] * 6
    both = (left - [4.0, 0.0], right + [2.0, 0.0])       # both eaten, the left more
    one = (left - [20.0, 0.0], right)                     # the left eaten far
    results, _ = _butt_tracker([*clean, both, one])
    for r, _ in results[:-2]:
        assert r.status == TrackStatus.TRACKED and np.allclose(r.uv, truth)
    r, res = results[-2]
    assert r.status == TrackStatus.TRACKED, r.status
    assert np.allclose(r.uv, truth - [1.0, 0.0]) and "both ends off alike" in res.reason, (
        r.uv, res.reason)     # 1 px off (the edges' losses differ by 2); put back: 2 px off
    r, res = results[-1]
    assert r.status == TrackStatus.TRACKED and np.allclose(r.uv, truth), r.uv
    assert "left_edge at its recent span" in res.reason


def test_a_butt_span_joins_its_history_only_on_evidence():
    """A structure far from the prediction whose span agrees with the gap's by chance is no
    evidence (the gate refuses its aim): it neither joins the span's history nor counts as a
    span in its place (before h20 it did both: on the bench's butt `wide` extreme row such
    chance agreements held a span read on the clean lead-in, 11.7 px, against the ~15 px the
    gap reads under the arc, and 7 frames were lost). A span read as it is, both ends off
    alike, joins it (the history follows the gap as the arc shows it); one put back from an
    end does not (its other end is off)."""
    from torchseam.track.fusion import TrackStatus

    left, right = np.array([300.0, 240.0]), np.array([315.0, 240.0])
    one = (left - [20.0, 0.0], right)                     # the left edge eaten far
    far = (left + [90.0, 0.0], right + [90.0, 0.0])       # the same span, 90 px off
    wider = (left - [2.0, 0.0], right + [2.0, 0.0])       # the gap as read under the arc
    results, tracker = _butt_tracker([(left, right)] * 3 + [one, far, wider])
    status = [r.status for r, _ in results]
    assert status[-3:] == [TrackStatus.TRACKED, TrackStatus.COASTING, TrackStatus.TRACKED]
    assert "left_edge at its recent span" in results[-3][1].reason
    assert "both ends off alike" in results[-1][1].reason
    spans = [float(d[0]) for d in tracker._pair]
    assert spans == [15.0, 15.0, 15.0, 19.0], spans       # not the far one's, nor 35
    assert tracker._stale_pair == 0


def test_a_butt_break_beside_the_gap_is_no_evidence_however_long_the_tracker_was_blind():
    """The locator's prediction (the seam seen so far, cut with the laser plane at the
    camera's pose now) is made afresh from the robot's motion on every frame: the joint does
    not move away from it while the tracker is blind, and the gate round it does not grow.
    The bench's butt `wide` extreme rows (seed 1002 frame 31, seed 1003 frame 42): after two
    or three frames without evidence, a break beside the gap (the glare's, ending at the
    gap's left edge) whose span agreed with the gap's by chance was taken 17.4 and 11.8 px
    off the simulator's truth, inside a gate grown to 24 and 18 px. Here: three frames with
    both edges eaten far (no evidence), then the same span 17 px to the left: coasting; the
    gap as it was: tracked. (The tracker's own prediction, its point held while blind, goes
    stale as the joint moves on: its gate still grows.)"""
    from torchseam.track.fusion import TrackStatus

    left, right = np.array([300.0, 240.0]), np.array([315.0, 240.0])
    truth = (left + right) / 2
    eaten = (left - [20.0, 0.0], right + [5.0, 0.0])     # eaten unlike: no reading near it
    beside = (left - [17.0, 0.0], right - [17.0, 0.0])    # the gap's span, 17 px to the left
    results, _ = _butt_tracker([*[(left, right)] * 6, eaten, eaten, eaten, beside,
                                (left, right)])
    status = [r.status for r, _ in results]
    assert status[:5] == [TrackStatus.TRACKED] * 5
    assert status[5:8] == [TrackStatus.COASTING] * 3
    assert status[8] == TrackStatus.COASTING, results[8][0].uv    # before h24: tracked, 17 px
    assert status[9] == TrackStatus.TRACKED and np.allclose(results[9][0].uv, truth)


def test_a_butt_span_started_again_keeps_the_gap_width_last_tracked():
    """A span off its history for ``edge_max_frames`` frames in a row is no longer known and
    its history starts again from the next span read. It starts from a gap as wide as the one
    last tracked (within half of it, as a groove found again keeps its shape): the bench's
    flat coupon in `wide` extreme, seed 1002, read the 22 px gap as breaks of 80-120 px for 25
    frames, then started again from a 93 px break round it and took it, 6.57 px off the
    simulator's truth (5.99 px a frame earlier before h24). Here: 26 frames with the edges
    eaten unlike (no evidence; the history runs stale), a 99 px break whose centre lies 2 px
    from the prediction: not tracked; the gap as it was: tracked."""
    from torchseam.track.fusion import TrackStatus

    left, right = np.array([300.0, 240.0]), np.array([315.0, 240.0])
    truth = (left + right) / 2
    eaten = (left - [20.0, 0.0], right + [5.0, 0.0])
    blown = (left - [40.0, 0.0], right + [44.0, 0.0])    # a 99 px break, its centre 2 px off
    results, _ = _butt_tracker([*[(left, right)] * 6, *[eaten] * 26, blown, (left, right)])
    status = [r.status for r, _ in results]
    assert status[:5] == [TrackStatus.TRACKED] * 5
    assert TrackStatus.TRACKED not in status[5:31]
    assert status[31] != TrackStatus.TRACKED, results[31][0].uv    # before h24: tracked
    assert status[32] == TrackStatus.TRACKED and np.allclose(results[32][0].uv, truth)


def test_a_butt_gap_whose_two_edges_moved_alike_is_held_to_the_prediction():
    """The arc's glare beside a butt's gap moves its two edges the same way: the span agrees
    with its history, the centre moved with them, and the 6 px gate took it (the bench's butt
    rows at extreme: both edges 3-6 px to one side, ``tracked`` 3.1-5.7 px off). The gap's
    centre is held to ``centre_tol_px`` of the locator's prediction after a frame with
    evidence, ``centre_tol_growth_px`` more per frame without since (the prediction ages
    while blind). Here: both edges 3.5 px to the right after tracked frames: coasting (before
    h26: tracked, 3.5 px off); again on the next frame (2.75 px allowed): coasting; 1.5 px to
    the right: tracked; the same 3.5 px after four frames without evidence (4.25 px allowed):
    tracked."""
    from torchseam.track.fusion import TrackStatus

    left, right = np.array([300.0, 240.0]), np.array([315.0, 240.0])
    truth = (left + right) / 2
    moved = (left + [3.5, 0.0], right + [3.5, 0.0])       # the span in place, moved 3.5 px
    near = (left + [1.5, 0.0], right + [1.5, 0.0])
    eaten = (left - [20.0, 0.0], right + [5.0, 0.0])      # eaten unlike: no evidence
    results, _ = _butt_tracker([*[(left, right)] * 4, moved, moved, near,
                                *[eaten] * 4, moved])
    status = [r.status for r, _ in results]
    assert status[:3] == [TrackStatus.TRACKED] * 3
    assert status[3:5] == [TrackStatus.COASTING] * 2, [r.uv for r, _ in results[3:5]]
    assert np.allclose(results[3][0].uv, truth)                  # the prediction held
    assert status[5] == TrackStatus.TRACKED and np.allclose(results[5][0].uv, truth + [1.5, 0])
    assert status[6:10] == [TrackStatus.COASTING] * 4
    assert status[10] == TrackStatus.TRACKED, results[10][0].uv
