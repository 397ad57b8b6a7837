"""Calibration (issue 5, item 1): recovered values against the simulator's truth, clear errors
for bad sets, and the ``torchseam calibrate`` command writing a cell config that loads back."""

from __future__ import annotations

import argparse
import dataclasses
import json

import cv2
import numpy as np
import pytest
import torch

from torchseam.core.camera import intrinsics, laser_plane_tensor, pixels_to_plane
from torchseam.core.config import CONFIG_DIR, ConfigError, load_cell, load_config
from torchseam.core.errors import TorchseamError
from torchseam.core.poses_csv import PoseFileError, read_pose_csv, write_pose_csv
from torchseam.core.transforms import invert, matrix_to_quat, pose_matrix, rotation_about
from torchseam.geometry import calib_cli
from torchseam.geometry.calibrate import (
    CalibrationConfig,
    CalibrationError,
    board_pose,
    calibrate_camera,
    calibrate_hand_eye,
    calibrate_laser_plane,
    calibrate_tcp,
    detect_board,
    extract_stripe,
    hand_eye_linear,
    load_calibration,
    load_laser_set,
    stripe_on_board,
    update_cell,
)
from torchseam.sim.board import (
    BoardRenderer,
    board_fits,
    simulate_camera_set,
    simulate_handeye_set,
    simulate_laser_set,
    simulate_tcp_set,
)
from torchseam.vision.tipm import load_tipm_config


def angle_deg(a, b) -> float:
    return float(np.degrees(np.arccos(np.clip(np.dot(a, b), -1.0, 1.0))))


def rot_deg(A, B) -> float:
    c = (np.trace(A[:3, :3].T @ B[:3, :3]) - 1) / 2
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def as_matrix(pose) -> np.ndarray:
    return pose_matrix(np.asarray(pose.position_mm), np.asarray(pose.quaternion))


@pytest.fixture(scope="module")
def cfg() -> CalibrationConfig:
    return load_calibration()


@pytest.fixture(scope="module")
def renderer(cell, cfg):
    return BoardRenderer(cell.camera, cfg.board, cfg.simulate.render)


@pytest.fixture(scope="module")
def camera_set(cell, cfg):
    return simulate_camera_set(cell, cfg)


@pytest.fixture(scope="module")
def camera_result(camera_set, cfg):
    return calibrate_camera(camera_set.images, camera_set.names, cfg)


@pytest.fixture(scope="module")
def laser_set(cell, cfg):
    return simulate_laser_set(cell, cfg)


@pytest.fixture(scope="module")
def handeye_set(cell, cfg):
    return simulate_handeye_set(cell, cfg)


def facing_pose(cfg, tilt_axis, tilt_deg, centre, spin_deg=0.0) -> np.ndarray:
    """T_C_O with the board grid centred on ``centre`` (camera frame, mm)."""
    R = rotation_about(np.asarray(tilt_axis, float), np.radians(tilt_deg)) @ rotation_about(
        np.array([0.0, 0.0, 1.0]), np.radians(spin_deg))
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = np.asarray(centre, float) - R @ cfg.board.centre()
    return T


# --------------------------------------------------------------------------- camera

def test_camera_recovers_true_intrinsics(camera_result, cell):
    true, got = cell.camera, camera_result.camera
    assert (got.width, got.height) == (true.width, true.height)
    for k in ("fx", "fy", "cx", "cy"):
        assert abs(getattr(got, k) / getattr(true, k) - 1) < 0.005, k
    assert camera_result.rms_px < 0.1
    assert len(camera_result.view_rms_px) == len(camera_result.names) == 25
    # What matters downstream: the fitted model images the working volume like the true one.
    X = np.stack(np.meshgrid(np.linspace(-25, 25, 11), np.linspace(-18, 18, 9), [130.0]),
                 -1).reshape(-1, 3)
    uv_true = cv2.projectPoints(X, np.zeros(3), np.zeros(3), true.K, np.array(true.dist))[0]
    uv_got = cv2.projectPoints(X, np.zeros(3), np.zeros(3), got.K, np.array(got.dist))[0]
    # the same scene seen by both lenses differs by at most a small shift + scale: compare
    # after the best similarity in the image (extrinsics absorb it in a calibrated system)
    d = (uv_got - uv_true).reshape(-1, 2)
    assert np.abs(d - d.mean(axis=0)).max() < 0.5


def test_camera_board_poses_match_truth(camera_result, camera_set):
    T_true, T_got = camera_set.T_C_O, camera_result.board_poses
    pos = np.linalg.norm(T_true[:, :3, 3] - T_got[:, :3, 3], axis=1)
    assert pos.max() < 0.5  # mm at 100-140 mm
    assert max(rot_deg(a, b) for a, b in zip(T_true, T_got, strict=True)) < 0.2


def test_detection_is_subpixel_and_in_the_board_order(camera_set, cell, cfg, renderer):
    obj = cfg.board.object_points()
    # a board turned by half a turn must come back in the same corner order
    T = facing_pose(cfg, [1.0, 0.4, 0.0], 30.0, [1.0, -1.0, 125.0], spin_deg=178.0)
    assert board_fits(T, cell.camera, cfg.board)
    images = [*camera_set.images[:4], renderer.board_image(T, np.random.default_rng(5))]
    poses = [*camera_set.T_C_O[:4], T]
    errs = []
    for img, P in zip(images, poses, strict=True):
        c = detect_board(img, cfg.board, cfg.detect, "view")
        uv = cv2.projectPoints(obj, cv2.Rodrigues(P[:3, :3])[0], P[:3, 3], cell.camera.K,
                               np.array(cell.camera.dist))[0].reshape(-1, 2)
        errs.append(np.linalg.norm(c - uv, axis=1))
    e = np.concatenate(errs)
    assert np.sqrt(np.mean(e**2)) < 0.05 and e.max() < 0.2


def test_failed_detection_names_the_image(camera_set, cfg):
    blank = np.full_like(camera_set.images[0], 40)
    images = [*camera_set.images[:3], blank]
    names = [*camera_set.names[:3], "blank_07.png"]
    with pytest.raises(CalibrationError, match=r"blank_07\.png: no 11x8 checkerboard found"
                       r".*--skip-failed leaves out"):
        calibrate_camera(images, names, cfg)
    # --skip-failed goes on with the rest (3 views are enough to run) and says what it left out
    res = calibrate_camera(images, names, dataclasses.replace(
        cfg, camera=dataclasses.replace(cfg.camera, max_focal_std_rel=1.0)), skip_failed=True)
    assert res.names == camera_set.names[:3]
    assert [e.split(":")[0] for e in res.skipped] == ["blank_07.png"]
    assert "skipped             1 of 4 images, board not found: blank_07.png" in res.summary()


def test_too_few_camera_views_is_a_clear_error(camera_set, cfg):
    with pytest.raises(CalibrationError,
                       match=r"2 usable views, need at least 3.*camera\.min_views"):
        calibrate_camera(camera_set.images[:2], camera_set.names[:2], cfg)


def test_parallel_boards_are_refused(cell, cfg, renderer):
    rng = np.random.default_rng(1)
    poses = [facing_pose(cfg, [1.0, 0.3, 0.0], 25.0, c) for c in
             ([-3, -2, 120], [3, 2, 130], [0, 3, 125], [-2, 1, 135], [2, -3, 118])]
    assert all(board_fits(T, cell.camera, cfg.board) for T in poses)
    images = [renderer.board_image(T, rng) for T in poses]
    with pytest.raises(CalibrationError, match="parallel"):
        calibrate_camera(images, [f"{k}.png" for k in range(5)], cfg)


def test_image_sizes_must_agree(camera_set, cfg):
    small = camera_set.images[1][:400, :600]
    with pytest.raises(CalibrationError, match=r"odd\.png: image is 600x400"):
        calibrate_camera([camera_set.images[0], small, camera_set.images[2]],
                         ["a.png", "odd.png", "c.png"], cfg)


# --------------------------------------------------------------------------- laser plane

def test_laser_plane_recovers_truth(laser_set, cell, cfg):
    true = cell.laser_plane
    res = calibrate_laser_plane(laser_set.laser_images, laser_set.laser_names, cell.camera, cfg,
                                laser_set.board_images, laser_set.board_names,
                                source_mm=true.source_mm)
    assert angle_deg(res.plane.normal, true.normal) < 0.05
    assert abs(res.plane.distance_mm - true.distance_mm) < 0.05
    assert res.rms_mm < 0.02 and res.view_points.min() >= cfg.laser.min_points_per_view
    # the kept source lies on the new plane (the config checks it) and near the old one
    src = np.asarray(res.plane.source_mm)
    assert abs(np.dot(res.plane.normal, src) - res.plane.distance_mm) < 1e-9
    assert np.linalg.norm(src - np.asarray(true.source_mm)) < 0.1
    # with known board poses instead of board images: the same
    res2 = calibrate_laser_plane(laser_set.laser_images, laser_set.laser_names, cell.camera, cfg,
                                 board_poses=laser_set.T_C_O)
    assert angle_deg(res2.plane.normal, true.normal) < 0.05
    assert abs(res2.plane.distance_mm - true.distance_mm) < 0.05


def test_laser_plane_with_the_calibrated_camera(laser_set, camera_result, cell, cfg):
    """The chain a user runs: the plane through the calibrated lens triangulates like the truth."""
    cam = camera_result.camera
    res = calibrate_laser_plane(laser_set.laser_images, laser_set.laser_names, cam, cfg,
                                laser_set.board_images, laser_set.board_names)
    u, v = np.meshgrid(np.arange(0, 656, 16.0), np.arange(0, 492, 16.0))
    uv = torch.from_numpy(np.stack([u.ravel(), v.ravel()], 1))
    K0, d0 = intrinsics(cell.camera)
    K1, d1 = intrinsics(cam)
    P0 = pixels_to_plane(uv, K0, d0, laser_plane_tensor(cell.laser_plane))
    P1 = pixels_to_plane(uv, K1, d1, laser_plane_tensor(res.plane))
    assert float((P0 - P1).norm(dim=-1).max()) < 0.1  # mm, anywhere in the image


def test_stripe_centre_is_subpixel(laser_set, cell, cfg, renderer):
    from torchseam.sim.sensor import LaserSensor

    sensor = LaserSensor(cell)
    for k in (0, 1):
        T, img = laser_set.T_C_O[k], laser_set.laser_images[k]
        uv, X = stripe_on_board(img, T, cell.camera, cfg, laser_set.laser_names[k])
        true = sensor.project(renderer.stripe_points(T, cell.laser_plane))
        order = np.argsort(true[:, 0])
        err = uv[:, 1] - np.interp(uv[:, 0], true[order, 0], true[order, 1])
        assert len(uv) >= cfg.laser.min_points_per_view
        assert abs(err.mean()) < 0.03 and np.abs(err).max() < 0.4  # px, speckle included
        # the 3D points lie on the true plane
        n, d = np.asarray(cell.laser_plane.normal), cell.laser_plane.distance_mm
        assert np.abs(X @ n - d).max() < 0.05


def test_too_few_laser_views_is_a_clear_error(laser_set, cell, cfg):
    with pytest.raises(CalibrationError,
                       match=r"2 usable views, need at least 3.*laser\.min_views"):
        calibrate_laser_plane(laser_set.laser_images[:2], laser_set.laser_names[:2], cell.camera,
                              cfg, board_poses=laser_set.T_C_O[:2])


def test_laser_image_without_stripe_is_named(laser_set, cell, cfg):
    lasers = list(laser_set.laser_images[:3])
    lasers[1] = np.zeros_like(lasers[1])
    names = ["a_laser.png", "b_laser.png", "c_laser.png"]
    with pytest.raises(CalibrationError, match=r"b_laser\.png: no laser stripe found"):
        calibrate_laser_plane(lasers, names, cell.camera, cfg, board_poses=laser_set.T_C_O[:3])


def test_laser_views_on_one_line_are_refused(laser_set, cell, cfg):
    """The board at one pose three times: every stripe is the same line of the plane."""
    img, T = laser_set.laser_images[0], laser_set.T_C_O[0]
    with pytest.raises(CalibrationError, match="lie on one line"):
        calibrate_laser_plane([img] * 3, ["x.png", "y.png", "z.png"], cell.camera, cfg,
                              board_poses=[T] * 3)


def test_laser_board_image_failure_is_named(laser_set, cell, cfg):
    boards = list(laser_set.board_images[:3])
    boards[2] = np.zeros_like(boards[2])
    with pytest.raises(CalibrationError, match=r"02_board\.png: no 11x8 checkerboard"):
        calibrate_laser_plane(laser_set.laser_images[:3], laser_set.laser_names[:3], cell.camera,
                              cfg, boards, laser_set.board_names[:3])


# --------------------------------------------------------------------------- hand-eye

def test_hand_eye_recovers_truth(handeye_set, cell, cfg):
    res = calibrate_hand_eye(handeye_set.images, handeye_set.names, handeye_set.T_B_F,
                             cell.camera, cfg)
    X, X_true = as_matrix(res.hand_eye), cell.hand_eye.matrix()
    assert np.linalg.norm(X[:3, 3] - X_true[:3, 3]) < 0.2
    assert rot_deg(X, X_true) < 0.05
    assert np.linalg.norm(res.T_B_O[:3, 3] - handeye_set.T_B_O[:3, 3]) < 0.2
    # residuals: the board seen from every pose lands where the fit puts it, within robot noise
    assert np.sqrt(np.mean(res.view_pos_mm**2)) < 0.15
    assert len(res.view_reproj_px) == len(handeye_set.names)


def test_hand_eye_bundle_adjustment_with_exact_robot_poses(cell, cfg):
    sim = dataclasses.replace(cfg.simulate, handeye=dataclasses.replace(
        cfg.simulate.handeye, robot_noise_mm=0.0, robot_noise_deg=0.0))
    s = simulate_handeye_set(cell, dataclasses.replace(cfg, simulate=sim), seed=3, views=6)
    res = calibrate_hand_eye(s.images, s.names, s.T_B_F, cell.camera, cfg, refine=True)
    X, X_true = as_matrix(res.hand_eye), cell.hand_eye.matrix()
    assert res.refined and res.reproj_rms_px < 0.1
    assert np.linalg.norm(X[:3, 3] - X_true[:3, 3]) < 0.02 and rot_deg(X, X_true) < 0.01


def test_hand_eye_closed_form_is_exact_on_exact_motions(cell):
    rng = np.random.default_rng(0)
    X = cell.hand_eye.matrix()
    T_B_O = pose_matrix(np.array([900.0, 0.0, 150.0]), np.array([0.0, 1.0, 0.0, 0.0]))
    G = []
    for _ in range(5):
        T = np.eye(4)
        T[:3, :3] = rotation_about(rng.normal(size=3), rng.uniform(0.2, 0.8))
        T[:3, 3] = rng.uniform(-200, 200, 3) + [800, 0, 500]
        G.append(T)
    G = np.stack(G)
    C = invert(G @ X) @ T_B_O  # T_C_O seen from each pose
    X_got, _ = hand_eye_linear(G, C)
    np.testing.assert_allclose(X_got, X, atol=1e-8)


def test_too_few_robot_poses_is_a_clear_error(handeye_set, cell, cfg):
    s = handeye_set
    with pytest.raises(CalibrationError,
                       match=r"3 usable robot poses, need at least 4.*handeye\.min_views"):
        calibrate_hand_eye(s.images[:3], s.names[:3], s.T_B_F[:3], cell.camera, cfg)


def test_pure_translations_are_refused(handeye_set, cell, cfg):
    s = handeye_set
    G = s.T_B_F[:5].copy()
    G[:, :3, :3] = G[0, :3, :3]
    with pytest.raises(CalibrationError, match="only translates"):
        calibrate_hand_eye(s.images[:5], s.names[:5], G, cell.camera, cfg)


def test_turns_about_one_axis_are_refused(handeye_set, cell, cfg):
    s = handeye_set
    G = s.T_B_F[:5].copy()
    for k in range(5):
        G[k, :3, :3] = G[0, :3, :3] @ rotation_about(np.array([0.0, 0.0, 1.0]), 0.2 * k)
    with pytest.raises(CalibrationError, match="about one axis"):
        calibrate_hand_eye(s.images[:5], s.names[:5], G, cell.camera, cfg)


# --------------------------------------------------------------------------- TCP

def test_tcp_recovers_truth(cell, cfg):
    s = simulate_tcp_set(cell, cfg)
    res = calibrate_tcp(s.T_B_F, s.names, cfg, orientation=cell.tool.quaternion)
    assert np.linalg.norm(np.asarray(res.tool.position_mm) - cell.tool.position_mm) < 0.2
    assert np.linalg.norm(res.point_B - s.point_B) < 0.2
    assert res.tool.quaternion == cell.tool.quaternion
    assert res.rms_mm < 0.2
    # exact touches: exact TCP
    exact = calibrate_tcp(s.T_B_F_true, s.names, cfg)
    touch = np.einsum("nij,j->ni", s.T_B_F_true[:, :3, :3], exact.tool.position_mm) \
        + s.T_B_F_true[:, :3, 3]
    assert np.ptp(touch, axis=0).max() < 0.25  # the touch noise, not the fit


def test_tcp_bad_sets_are_refused(cell, cfg):
    s = simulate_tcp_set(cell, cfg)
    with pytest.raises(CalibrationError, match=r"3 usable poses, need at least 4"):
        calibrate_tcp(s.T_B_F[:3], s.names[:3], cfg)
    same = s.T_B_F.copy()
    same[:, :3, :3] = same[0, :3, :3]
    with pytest.raises(CalibrationError, match="only translates"):
        calibrate_tcp(same, s.names, cfg)
    one_axis = s.T_B_F.copy()
    for k in range(len(one_axis)):
        one_axis[k, :3, :3] = rotation_about(np.array([1.0, 0.0, 0.0]), 0.3 * k)
    with pytest.raises(CalibrationError, match="about one axis"):
        calibrate_tcp(one_axis, s.names, cfg)


# --------------------------------------------------------------------------- files and config

def write_flange_poses(path, label, names, T) -> None:
    """A set's poses.csv as a user writes it: label column, then x,y,z,q1..q4 of T_B_F."""
    write_pose_csv(path, T[:, :3, 3], matrix_to_quat(T[:, :3, :3]), label=label, labels=names)


def test_pose_csv_round_trip_and_errors(tmp_path, handeye_set):
    p = tmp_path / "poses.csv"
    write_flange_poses(p, "image", handeye_set.names, handeye_set.T_B_F)
    assert p.read_text().splitlines()[0] == "image,x,y,z,q1,q2,q3,q4"
    got = read_pose_csv(p, label="image")
    assert got.labels == handeye_set.names and got.t is None
    np.testing.assert_allclose(got.T, handeye_set.T_B_F, atol=1e-5)
    lines = p.read_text().splitlines()
    p.write_text("\n".join([lines[0], lines[1], lines[2].replace(",", ",abc,", 1)[:-4]]))
    with pytest.raises(PoseFileError, match=r"poses\.csv: line 3: expected 8 fields, got 9"):
        read_pose_csv(p, label="image")
    p.write_text("\n".join([lines[0], lines[1].split(",", 1)[0] + ",1,2,x,1,0,0,0"]))
    with pytest.raises(PoseFileError, match=r"poses\.csv: line 2: field 'z': not a number"):
        read_pose_csv(p, label="image")
    p.write_text("x,y,z,q1,q2,q3,q4\n1,2,3,1,0,0,0\n")  # a path file: no image column
    with pytest.raises(PoseFileError, match=r"line 1: header lacks column\(s\) image "
                                            r"\(expected image,x,y,z,q1,q2,q3,q4\)"):
        read_pose_csv(p, label="image")
    # a set recorded with the old header still reads; its messages name its own columns
    p.write_text("pose,x_mm,y_mm,z_mm,qw,qx,qy,qz\np0,0,0,0,0.5,0,0,0\n")
    with pytest.raises(PoseFileError, match=r"line 2: quaternion qw..qz has norm 0.500000"):
        read_pose_csv(p, label="pose")


def test_laser_folder_needs_pairs(tmp_path, laser_set):
    cv2.imwrite(str(tmp_path / "00_board.png"), laser_set.board_images[0])
    cv2.imwrite(str(tmp_path / "00_laser.png"), laser_set.laser_images[0])
    cv2.imwrite(str(tmp_path / "01_board.png"), laser_set.board_images[1])
    with pytest.raises(CalibrationError, match=r"01_board\.png: has no 01_laser image"):
        load_laser_set(tmp_path)


def test_board_with_ambiguous_corner_order_is_a_config_error(tmp_path):
    text = (CONFIG_DIR / "calibration.yaml").read_text()
    bad = tmp_path / "calibration.yaml"
    bad.write_text(text.replace("rows: 8", "rows: 9", 1))
    with pytest.raises(ConfigError,
                       match=r"calibration\.yaml: board\.cols: cols \+ rows must be odd"):
        load_config(CalibrationConfig, bad)


# --------------------------------------------------------------------------- command line

def cli(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="torchseam")
    calib_cli.register(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args(argv)
    return args.func(args)


def test_cli_camera_end_to_end(tmp_path, cell, capsys):
    folder = tmp_path / "cam"
    assert cli(["calibrate", "simulate", "camera", str(folder), "--views", "12",
                "--seed", "4"]) == 0
    assert len(list(folder.glob("*.png"))) == 12 and (folder / "truth.json").exists()
    capsys.readouterr()
    assert cli(["calibrate", "camera", str(folder)]) == 0
    out = capsys.readouterr().out
    assert "reprojection RMS" in out and "vs simulator truth" in out
    written = load_cell(folder / "cell.yaml")
    truth = json.loads((folder / "truth.json").read_text())["camera"]
    assert abs(written.camera.fx / truth["fx"] - 1) < 0.005
    assert written.camera != cell.camera
    # only the camera section changed; the file keeps its comments
    assert (written.laser_plane, written.hand_eye, written.tool, written.process) == (
        cell.laser_plane, cell.hand_eye, cell.tool, cell.process)
    text = (folder / "cell.yaml").read_text()
    assert "# OpenCV order: k1 k2 p1 p2 k3" in text
    assert "# calibrated: torchseam calibrate camera" in text


def test_cli_tcp_updates_the_cell_in_place(tmp_path, cell, capsys):
    folder = tmp_path / "tcp"
    assert cli(["calibrate", "simulate", "tcp", str(folder)]) == 0
    target = tmp_path / "my_cell.yaml"
    target.write_text((CONFIG_DIR / "cell.yaml").read_text())
    assert cli(["calibrate", "tcp", str(folder), "--cell", str(target),
                "--write", str(target)]) == 0
    assert "pivot residual" in capsys.readouterr().out
    got = load_cell(target)
    assert np.linalg.norm(np.asarray(got.tool.position_mm) - cell.tool.position_mm) < 0.2
    assert got.tool.position_mm != cell.tool.position_mm
    assert got.camera == cell.camera


def test_the_four_calibrations_in_turn_keep_the_file_s_comments(tmp_path, cell):
    """The README's order (camera, laser plane, hand-eye, TCP), each written into the same
    file: every step keeps the person's comments. (The hand-eye step once rewrote the file
    without them: the laser plane's normal, normalised again on reading, differed in its last
    bits from the config it was compared with.)"""
    def unit(v):
        return np.asarray(v, float) / np.linalg.norm(v)

    target = tmp_path / "my_cell.yaml"
    target.write_text((CONFIG_DIR / "cell.yaml").read_text())
    # a laser plane `calibrate laser` wrote (the simulated set, seed 0)
    normal = unit([0.000144589, 0.766088658, 0.642734896])
    steps = [
        ("camera", dataclasses.replace(cell.camera, fx=1599.7401, fy=1599.8815, cx=331.1456,
                                       cy=243.0019)),
        ("laser_plane", dataclasses.replace(cell.laser_plane, normal=tuple(normal),
                                            distance_mm=83.557177,
                                            source_mm=(-1e-06, 77.129445, 38.070414))),
        ("hand_eye", dataclasses.replace(cell.hand_eye, position_mm=(103.5722, 0.0251, 250.3927),
                                         quaternion=tuple(unit(np.array(
                                             [0.664519501, -0.241648919, -0.241864475,
                                              0.664470622]))))),
        ("tool", dataclasses.replace(cell.tool, position_mm=(0.0204, -0.031, 349.9121))),
    ]
    for section, value in steps:
        written, kept = update_cell(target, target, section, value, f"calibrated: {section}")
        assert kept, section
        assert written == load_cell(target), section
        text = target.read_text()
        assert "# OpenCV order: k1 k2 p1 p2 k3" in text, section
        assert f"# calibrated: {section}" in text, section
    got = load_cell(target)
    assert np.allclose(got.laser_plane.normal, normal, atol=1e-9)
    assert got.tool.position_mm == (0.0204, -0.031, 349.9121)


def test_a_calibration_goes_into_a_cell_file_in_place(tmp_path, cell):
    """`calibrate KIND --cell CELLFILE --write CELLFILE` on the cell file `weld --cell` reads
    (the calibration under `calibration:`, then the camera and controller links, whose
    top-level `camera:` must not be taken for the calibrated camera): only the calibrated
    section changes, the links and a person's comments stay, and weld reads the result."""
    from torchseam.geometry.calibrate import load_calibrated_cell
    from torchseam.live.cellfile import (
        CameraLink,
        ControllerLink,
        WeldCell,
        load_weld_cell,
        save_weld_cell,
    )

    target = tmp_path / "cell.yaml"
    links = (CameraLink(source="tcp://10.0.0.5:7000", latency_ms=21.5),
             ControllerLink(host="10.0.0.2", port=6510, controller_host="10.0.0.7",
                            controller_port=6511))
    save_weld_cell(WeldCell(cell, *links), target, header="# cell 3, line B\n")
    target.write_text(target.read_text().replace("    fx:", "    # the lens: 16 mm\n    fx:", 1)
                      + "# end of the cell file\n")
    steps = [("camera", dataclasses.replace(cell.camera, fx=1599.7401, fy=1599.8815,
                                            cx=331.1456, cy=243.0019,
                                            dist=(-0.0805, 0.1411, 0.00058, -0.00036, 0.0))),
             ("tool", dataclasses.replace(cell.tool, position_mm=(0.0204, -0.031, 349.9121)))]
    for section, value in steps:
        written, kept = update_cell(target, target, section, value, f"calibrated: {section}")
        assert kept, section
        weld_cell = load_weld_cell(target)
        assert written == load_calibrated_cell(target) == weld_cell.calibration, section
        assert (weld_cell.camera, weld_cell.controller) == links, section
        text = target.read_text()
        assert text.startswith("# cell 3, line B\n") and "# end of the cell file" in text
        assert "    # the lens: 16 mm\n" in text
        assert f"# calibrated: {section}" in text, section
    got = load_weld_cell(target).calibration
    assert (got.camera.fx, got.camera.dist[1]) == (1599.7401, 0.1411)
    assert got.tool.position_mm == (0.0204, -0.031, 349.9121)
    assert got.laser_plane == cell.laser_plane and got.hand_eye == cell.hand_eye


def test_cli_handeye_reads_its_folder(tmp_path, handeye_set, cell, capsys):
    folder = tmp_path / "he"
    folder.mkdir()
    for name, img in zip(handeye_set.names, handeye_set.images, strict=True):
        cv2.imwrite(str(folder / name), img)
    write_flange_poses(folder / "poses.csv", "image", handeye_set.names, handeye_set.T_B_F)
    assert cli(["calibrate", "handeye", str(folder), "--write", str(tmp_path / "c.yaml")]) == 0
    got = load_cell(tmp_path / "c.yaml")
    X, X_true = as_matrix(got.hand_eye), cell.hand_eye.matrix()
    assert np.linalg.norm(X[:3, 3] - X_true[:3, 3]) < 0.2 and rot_deg(X, X_true) < 0.05
    (folder / handeye_set.names[4]).unlink()
    with pytest.raises(CalibrationError, match=rf"image {handeye_set.names[4]} is not in"):
        cli(["calibrate", "handeye", str(folder)])
    # a bad pose file: one line naming file, line and field, exit code 2, no traceback
    from torchseam.cli import main

    (folder / "poses.csv").write_text("image,x,y,z,q1,q2,q3,q4\n00.png,1,2,3,1,0,0,nan\n")
    capsys.readouterr()
    assert main(["calibrate", "handeye", str(folder)]) == 2
    assert capsys.readouterr().err == (f"torchseam calibrate: error: {folder / 'poses.csv'}: "
                                       "line 2: field 'q4': not finite (nan)\n")


def test_cli_errors_name_the_folder(tmp_path):
    with pytest.raises(CalibrationError, match="no such folder"):
        cli(["calibrate", "camera", str(tmp_path / "missing")])
    (tmp_path / "empty").mkdir()
    with pytest.raises(CalibrationError, match="holds no images"):
        cli(["calibrate", "camera", str(tmp_path / "empty")])


def test_board_pose_from_detection(camera_set, cell, cfg):
    c = detect_board(camera_set.images[3], cfg.board, cfg.detect, "03.png")
    T, rms = board_pose(c, cfg.board, cell.camera)
    assert rms < 0.1
    assert np.linalg.norm(T[:3, 3] - camera_set.T_C_O[3][:3, 3]) < 0.3


def test_simulated_sets_are_deterministic(cell, cfg, tmp_path):
    a, b = simulate_tcp_set(cell, cfg, seed=9), simulate_tcp_set(cell, cfg, seed=9)
    np.testing.assert_array_equal(a.T_B_F, b.T_B_F)
    assert not np.array_equal(a.T_B_F, simulate_tcp_set(cell, cfg, seed=10).T_B_F)
    c1, c2 = (simulate_camera_set(cell, cfg, seed=9, views=2) for _ in range(2))
    assert all(np.array_equal(x, y) for x, y in zip(c1.images, c2.images, strict=True))
    # a folder that holds a set is not overwritten by accident
    assert cli(["calibrate", "simulate", "tcp", str(tmp_path / "t")]) == 0
    with pytest.raises(TorchseamError, match="already holds"):
        cli(["calibrate", "simulate", "tcp", str(tmp_path / "t")])


def test_a_two_lobed_stripe_on_the_board_is_read_between_its_lobes():
    """The laser plane must be where TIPM reads the stripe: a stripe of two unequal lobes (a
    diode in two modes) is read at their middle by the calibration as by TIPM, not at the
    centroid that leans toward the brighter."""
    h, w, v0, half = 120, 200, 60.3, 1.9
    rows = np.arange(h, dtype=float)[:, None]
    prof = (200 * np.exp(-((rows - v0 - half) ** 2) / 2)
            + 120 * np.exp(-((rows - v0 + half) ** 2) / 2))
    img = np.zeros((h, w, 3), np.uint8)
    img[..., 2] = np.clip(np.rint(20 + prof), 0, 255).astype(np.uint8)
    rule = load_tipm_config().lobes
    uv = extract_stripe(img, 40.0, 6, rule)
    assert len(uv) == w
    np.testing.assert_allclose(uv[:, 1], v0, atol=0.1)
    plain = extract_stripe(img, 40.0, 6, dataclasses.replace(rule, ridge=1.0))
    assert np.all(plain[:, 1] - v0 > 0.4)  # the centroid's lean
