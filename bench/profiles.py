"""The live loop's profile tracker on simulated sequences: part (joint) x family x noise level.

Usage: python bench/profiles.py [--parts configs/parts/t_joint_bevel.yaml,...]
                                [--families sim,wide,thin,smoke] [--levels clean,heavy,extreme]
                                [--sequences 2] [--frames 150] [--first-seed 1000]
                                [--start-mm 100] [--worst 0]

For a part whose joint is not a fillet the live loop follows the joint profile's aim point
(:class:`torchseam.track.profile.ProfileTracker`, settings ``configs/profile_track.yaml``,
the profile's ``configs/profiles.yaml``). Here it runs open loop on the simulator's frames along
the nominal path (:func:`torchseam.sim.sequence.simulate`): started on frame 0 (arc off) from
the whole frame's profile, then each frame read in the window round the point the robot's motion
predicts, which the live locator computes from the seam seen so far and the camera's pose; here
the simulator's true aim pixel of the frame before stands in for it (the feature moves a
fraction of a pixel a frame in the sensor's view).

Scored against the simulator's truth (the root centre's pixel) over the arc frames: frames
``tracked`` and the RMSE / max of their aim points (px), ``false`` tracked frames (``tracked``
while more than ``--false-px`` off: the status must be honest), frames ``lost``, the longest
run without evidence (frames: the live loop holds the weld blind after ``lost_frames``), and the
error of every point handed on (coasting: the prediction). ``held out``: the appearance families
the profile's thresholds were not chosen on (all but ``sim``).
"""

from __future__ import annotations

import argparse
import platform
import time
from pathlib import Path

import cv2
import numpy as np

from torchseam.core.config import CONFIG_DIR, FAMILY_NAMES, load_cell, load_noise, load_part
from torchseam.core.report import format_table
from torchseam.sim.sequence import SequenceSpec, simulate
from torchseam.track.fusion import TrackStatus
from torchseam.track.profile import ProfileTracker, load_profile_track_config
from torchseam.vision.profiles import ProfileFinder, load_profile_config
from torchseam.vision.tipm import load_tipm

#: the families the profiles' thresholds were chosen on
FIT_ON = ("sim",)


def run(part_path: Path, family: str, level_name: str, seed: int, frames: int,
        start_mm: float, false_px: float, worst: int) -> dict:
    cell, noise, part = load_cell(), load_noise(), load_part(part_path)
    finder = ProfileFinder(load_tipm(), load_profile_config(), part.joint)
    tracker = ProfileTracker(finder, load_profile_track_config())
    seq = iter(simulate(cell, part, noise, SequenceSpec(
        n_frames=frames, start_mm=start_mm, level=noise.level(level_name), seed=seed,
        family=family)))
    lead = noise.clean_lead_frames
    img0, truth0 = next(seq)
    res0 = tracker.find(img0)
    out = {"frames": 0, "tracked": 0, "lost": 0, "false": 0, "blind": 0, "err_t": [],
           "err_all": [], "start_px": float("nan"), "worst": [], "ms": []}
    if not res0.ok:
        out["start"] = res0.reason
        return out
    out["start_px"] = float(np.linalg.norm(res0.aim - truth0.uv))
    tracker.init(img0, res0.aim)
    prev, run_len = truth0.uv, 0
    for k, (img, truth) in enumerate(seq, start=1):
        tracker.expect(prev)
        t0 = time.perf_counter()
        r = tracker.track(img)
        dt = (time.perf_counter() - t0) * 1e3
        prev = truth.uv
        if k < lead or not truth.visible:
            continue
        out["frames"] += 1
        out["ms"].append(dt)
        err = float(np.linalg.norm(r.uv - truth.uv)) if np.all(np.isfinite(r.uv)) else np.inf
        out["err_all"].append(err)
        if r.status == TrackStatus.TRACKED:
            out["tracked"] += 1
            out["err_t"].append(err)
            out["false"] += err > false_px
            if err > false_px and len(out["worst"]) < worst:
                out["worst"].append((k, round(err, 2)))
            run_len = 0
        else:
            out["lost"] += r.status == TrackStatus.LOST
            run_len += 1
            out["blind"] = max(out["blind"], run_len)
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--parts", default=str(CONFIG_DIR / "parts" / "t_joint_bevel.yaml"))
    ap.add_argument("--families", default=",".join(FAMILY_NAMES))
    ap.add_argument("--levels", default="clean,heavy,extreme")
    ap.add_argument("--sequences", type=int, default=2)
    ap.add_argument("--frames", type=int, default=150)
    ap.add_argument("--first-seed", type=int, default=1000)
    ap.add_argument("--start-mm", type=float, default=100.0,
                    help="seam arc length at frame 0 of the first sequence (the next ones "
                    "start 120 mm further round the seam)")
    ap.add_argument("--false-px", type=float, default=3.0)
    ap.add_argument("--worst", type=int, default=0, help="list this many false-tracked frames")
    a = ap.parse_args(argv)
    paths = []
    for name in a.parts.split(","):  # a file, or a shipped part's name (t_joint_bevel)
        path = Path(name) if Path(name).is_file() else CONFIG_DIR / "parts" / f"{name}.yaml"
        if not path.is_file():
            ap.error(f"--parts: {name}: no such part file, nor configs/parts/{name}.yaml")
        paths.append(path)
    for fam in a.families.split(","):
        if fam not in FAMILY_NAMES:
            ap.error(f"--families: {fam!r}: not one of {', '.join(FAMILY_NAMES)}")
    for lev in a.levels.split(","):
        try:
            load_noise().level(lev)
        except ValueError as e:
            ap.error(f"--levels: {e}")
    cv2.setNumThreads(1)
    rows = []
    for part_path in paths:
        for fam in a.families.split(","):
            for lev in a.levels.split(","):
                agg: dict = {}
                for i in range(a.sequences):
                    r = run(part_path, fam, lev, a.first_seed + i, a.frames,
                            a.start_mm + 120.0 * i, a.false_px, a.worst)
                    if "start" in r:
                        print(f"  {part_path.stem} {fam} {lev} seed {a.first_seed + i}: "
                              f"no start: {r['start']}")
                    if r["worst"]:
                        print(f"  {part_path.stem} {fam} {lev} seed {a.first_seed + i}: false "
                              f"(frame, px): {r['worst']}")
                    for key, val in r.items():
                        if isinstance(val, list):
                            agg.setdefault(key, []).extend(val)
                        elif key == "blind":
                            agg[key] = max(agg.get(key, 0), val)
                        elif key != "start_px":
                            agg[key] = agg.get(key, 0) + val
                et = np.array(agg["err_t"]) if agg["err_t"] else np.array([np.nan])
                ea = np.array(agg["err_all"]) if agg["err_all"] else np.array([np.nan])
                ms = np.array(agg["ms"]) if agg["ms"] else np.array([np.nan])
                n = max(agg["frames"], 1)
                rows.append([
                    part_path.stem, load_part(part_path).joint, fam, lev,
                    "no" if fam in FIT_ON else "yes", str(agg["frames"]),
                    f"{100 * agg['tracked'] / n:.1f}", f"{np.sqrt(np.mean(et ** 2)):.2f}",
                    f"{et.max():.2f}", str(agg["false"]), str(agg["lost"]), str(agg["blind"]),
                    f"{np.sqrt(np.mean(np.minimum(ea, 1e3) ** 2)):.2f}", f"{ea.max():.1f}",
                    f"{np.percentile(ms, 50):.1f}/{np.percentile(ms, 99):.1f}"])
                print(" | ".join(rows[-1]), flush=True)
    print()
    print(f"{platform.node()}, {a.sequences} sequences x {a.frames} frames from seed "
          f"{a.first_seed}, start {a.start_mm:g} mm (+120 each)")
    print(format_table(["part", "joint", "family", "level", "held out", "frames", "tracked %",
                        "tracked RMSE px", "tracked max px", f"false (> {a.false_px:g} px)",
                        "lost", "longest blind", "all RMSE px", "all max px", "ms p50/p99"],
                       rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
