"""Calibration on simulated sets: recovered vs true values, residuals, run time.

Usage: python bench/calibration.py [--seeds 3] [--threads 1]

For each seed: the camera from its checkerboard set; the laser plane and the hand-eye pose
both with the true camera (each stage alone) and with the camera just calibrated (the chain a
user runs); the TCP by pivoting. Prints the first seed in detail (true, recovered, error,
tolerance of issue 5) and the worst error over all seeds. "triangulation" is what the
calibration alone costs a 3D point: pixels over the whole image cut with the laser plane by
the true and by the calibrated camera + plane, max distance between the two (mm).
"""

from __future__ import annotations

import argparse
import platform
import time

import cv2
import numpy as np
import torch

from torchseam.core.camera import intrinsics, laser_plane_tensor, pixels_to_plane
from torchseam.core.config import CameraConfig, LaserPlane, load_cell
from torchseam.core.report import format_table
from torchseam.core.transforms import pose_matrix
from torchseam.geometry.calibrate import (
    calibrate_camera,
    calibrate_hand_eye,
    calibrate_laser_plane,
    calibrate_tcp,
    load_calibration,
)
from torchseam.sim.board import (
    simulate_camera_set,
    simulate_handeye_set,
    simulate_laser_set,
    simulate_tcp_set,
)


def angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip(np.dot(a, b), -1.0, 1.0))))


def rot_err_deg(A: np.ndarray, B: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(A[:3, :3].T @ B[:3, :3]) - 1) / 2,
                                              -1.0, 1.0))))


def triangulation_err_mm(true_cam: CameraConfig, true_plane: LaserPlane, cam: CameraConfig,
                         plane: LaserPlane) -> float:
    """Max distance between points triangulated by the true and the calibrated model."""
    u, v = np.meshgrid(np.arange(0, true_cam.width, 8.0), np.arange(0, true_cam.height, 8.0))
    uv = torch.from_numpy(np.stack([u.ravel(), v.ravel()], 1))
    K0, d0 = intrinsics(true_cam)
    K1, d1 = intrinsics(cam)
    P0 = pixels_to_plane(uv, K0, d0, laser_plane_tensor(true_plane))
    P1 = pixels_to_plane(uv, K1, d1, laser_plane_tensor(plane))
    return float((P0 - P1).norm(dim=-1).max())


def he_err(res, X_true: np.ndarray) -> tuple[float, float]:
    X = pose_matrix(np.asarray(res.hand_eye.position_mm), np.asarray(res.hand_eye.quaternion))
    return float(np.linalg.norm(X[:3, 3] - X_true[:3, 3])), rot_err_deg(X, X_true)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--threads", type=int, default=1, help="OpenCV / torch threads (default 1)")
    args = ap.parse_args()
    cv2.setNumThreads(args.threads)
    torch.set_num_threads(args.threads)
    cell, cfg = load_cell(), load_calibration()
    cam0, lp0, X0 = cell.camera, cell.laser_plane, cell.hand_eye.matrix()
    tool0 = np.asarray(cell.tool.position_mm)
    n0 = np.asarray(lp0.normal)
    worst: dict[str, float] = {}
    detail: list[list[object]] = []
    times: dict[str, list[float]] = {}

    def note(key: str, value: float) -> None:
        worst[key] = max(worst.get(key, 0.0), abs(value))

    def timed(key: str, fn, *a, **kw):
        t0 = time.perf_counter()
        out = fn(*a, **kw)
        times.setdefault(key, []).append(time.perf_counter() - t0)
        return out

    for seed in range(args.seeds):
        cs = timed("render camera set", simulate_camera_set, cell, cfg, seed=seed)
        cr = timed("calibrate camera", calibrate_camera, cs.images, cs.names, cfg)
        c = cr.camera
        for k in ("fx", "fy", "cx", "cy"):
            note(f"camera {k} %", 100 * (getattr(c, k) / getattr(cam0, k) - 1))
        note("camera RMS px", cr.rms_px)
        ls = timed("render laser set", simulate_laser_set, cell, cfg, seed=seed)
        lr = timed("calibrate laser", calibrate_laser_plane, ls.laser_images, ls.laser_names,
                   cam0, cfg, ls.board_images, ls.board_names, source_mm=lp0.source_mm)
        lc = calibrate_laser_plane(ls.laser_images, ls.laser_names, c, cfg, ls.board_images,
                                   ls.board_names, source_mm=lp0.source_mm)
        for tag, r in (("true cam", lr), ("chained", lc)):
            note(f"laser normal deg ({tag})", angle_deg(np.asarray(r.plane.normal), n0))
            note(f"laser distance mm ({tag})", r.plane.distance_mm - lp0.distance_mm)
            note(f"laser fit RMS mm ({tag})", r.rms_mm)
        note("triangulation max mm (chained)", triangulation_err_mm(cam0, lp0, c, lc.plane))
        hs = timed("render hand-eye set", simulate_handeye_set, cell, cfg, seed=seed)
        hr = timed("calibrate hand-eye", calibrate_hand_eye, hs.images, hs.names, hs.T_B_F, cam0,
                   cfg)
        hc = calibrate_hand_eye(hs.images, hs.names, hs.T_B_F, c, cfg)
        for tag, r in (("true cam", hr), ("chained", hc)):
            e_mm, e_deg = he_err(r, X0)
            note(f"hand-eye mm ({tag})", e_mm)
            note(f"hand-eye deg ({tag})", e_deg)
        note("hand-eye board spread RMS mm", float(np.sqrt(np.mean(hr.view_pos_mm**2))))
        ts = simulate_tcp_set(cell, cfg, seed=seed)
        tr = timed("calibrate TCP", calibrate_tcp, ts.T_B_F, ts.names, cfg)
        note("TCP mm", float(np.linalg.norm(np.asarray(tr.tool.position_mm) - tool0)))
        note("TCP pivot RMS mm", tr.rms_mm)
        if seed == 0:
            for k in ("fx", "fy", "cx", "cy"):
                t, r = getattr(cam0, k), getattr(c, k)
                detail.append([f"camera {k} (px)", f"{t:.4f}", f"{r:.4f}",
                               f"{r - t:+.4f} ({100 * (r / t - 1):+.3f} %)", "0.5 %"])
            detail.append(["camera k1 k2", f"{cam0.dist[0]:+.4f} {cam0.dist[1]:+.4f}",
                           f"{c.dist[0]:+.4f} {c.dist[1]:+.4f}", "", ""])
            detail.append(["camera reprojection RMS (px)", "", f"{cr.rms_px:.4f}", "", ""])
            for tag, r in (("true cam", lr), ("chained", lc)):
                detail.append([f"laser normal ({tag})", " ".join(f"{x:.6f}" for x in n0),
                               " ".join(f"{x:.6f}" for x in r.plane.normal),
                               f"{angle_deg(np.asarray(r.plane.normal), n0):.4f} deg",
                               "0.05 deg"])
                detail.append([f"laser distance ({tag}, mm)", f"{lp0.distance_mm:.4f}",
                               f"{r.plane.distance_mm:.4f}",
                               f"{r.plane.distance_mm - lp0.distance_mm:+.4f}", "0.05 mm"])
            detail.append(["laser fit RMS (mm)", "", f"{lr.rms_mm:.4f}", "", ""])
            detail.append(["triangulation, chained (mm max)", "", "",
                           f"{triangulation_err_mm(cam0, lp0, c, lc.plane):.4f}", ""])
            for tag, r in (("true cam", hr), ("chained", hc)):
                e_mm, e_deg = he_err(r, X0)
                detail.append([f"hand-eye position ({tag}, mm)",
                               " ".join(f"{x:.3f}" for x in X0[:3, 3]),
                               " ".join(f"{x:.3f}" for x in r.hand_eye.position_mm),
                               f"{e_mm:.4f}", "0.2 mm"])
                detail.append([f"hand-eye rotation ({tag})", "", "", f"{e_deg:.4f} deg",
                               "0.05 deg"])
            detail.append(["hand-eye board spread RMS (mm / deg)", "",
                           f"{np.sqrt(np.mean(hr.view_pos_mm**2)):.4f} / "
                           f"{np.sqrt(np.mean(hr.view_rot_deg**2)):.4f}", "", ""])
            detail.append(["TCP (mm)", " ".join(f"{x:.3f}" for x in tool0),
                           " ".join(f"{x:.3f}" for x in tr.tool.position_mm),
                           f"{np.linalg.norm(np.asarray(tr.tool.position_mm) - tool0):.4f}",
                           "0.2 mm"])
            detail.append(["TCP pivot RMS (mm)", "", f"{tr.rms_mm:.4f}", "", ""])

    cpu = platform.processor() or platform.machine()
    sim = cfg.simulate
    print(f"Calibration on simulated sets ({cpu}, {args.threads} thread): camera "
          f"{sim.camera.views} views, laser {sim.laser.views} poses, hand-eye "
          f"{sim.handeye.views} poses (robot noise {sim.handeye.robot_noise_mm} mm / "
          f"{sim.handeye.robot_noise_deg} deg), TCP {sim.tcp.poses} touches")
    print()
    print("seed 0:")
    print(format_table(["quantity", "true", "recovered", "error", "tolerance"], detail))
    print()
    print(f"worst |error| over {args.seeds} seeds:")
    print(format_table(["quantity", "worst"], [[k, v] for k, v in worst.items()]))
    print()
    print(format_table(["step", "s (mean)"], [[k, float(np.mean(v))] for k, v in times.items()]))


if __name__ == "__main__":
    main()
