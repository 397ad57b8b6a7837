"""`torchseam weld` against `torchseam virtual-cell`, in separate processes, case by case.

Each case runs the virtual cell in the background and the weld right after it (as the README
does), then prints one row: the weld's exit code and what it said, and the virtual cell's truth
(seam RMSE / max, poses within 1 degree, unsafe poses, arc on while still / off seam, what was
welded, the arc-off time after a camera stall, the robot's stop after a lost weld).

    python bench/cell.py                       # the issue-34 cases
    python bench/cell.py --cases t_joint:20    # part:latency[:fault][:kill][@fps]
    python bench/cell.py --cases t_joint:20@30,t_joint:20@50   # the camera at 30 / 50 fps
    python bench/cell.py --cases t_joint:20@80 --noise clean   # 80 fps (clean: rendered fast)

A case ending ``@FPS`` runs both processes on a copy of the shipped configs whose camera runs at
FPS frames/s (``cell.yaml`` ``process.frame_rate_hz``): the virtual camera renders at that rate
and the weld keeps up with it or drops frames (``dropped`` counts those the weld passed over
for a newer one).
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
DEFAULT = ["t_joint:20", "y_joint_75:20", "pipe_on_plate:20", "t_joint:40",
           "t_joint:20:camera-stall", "t_joint:20:camera-drop", "t_joint:20:packet-loss",
           "t_joint:20:controller-restart", "t_joint:20::kill"]


def _configs_at(fps: str, work: Path) -> list[str]:
    """``--config-dir`` of a copy of the shipped configs with the camera at ``fps``."""
    import shutil

    d = work / f"configs_{fps}fps"
    if not d.exists():
        shutil.copytree(REPO / "configs", d)
        text = (d / "cell.yaml").read_text()
        key = "frame_rate_hz: "
        i = text.index(key) + len(key)
        j = text.index("\n", i)
        rest = text[i:j]
        comment = rest[rest.index("#"):] if "#" in rest else ""
        (d / "cell.yaml").write_text(text[:i] + f"{float(fps):g}  {comment}".rstrip() + text[j:])
    return ["--config-dir", str(d)]


def run_case(spec: str, length: float, seed: int, work: Path, noise: str = "") -> dict:
    spec_fps = spec.split("@")
    spec, fps = spec_fps[0], (spec_fps[1] if len(spec_fps) > 1 else "")
    part, latency, *rest = spec.split(":")
    fault = rest[0] if rest and rest[0] else ""
    kill = len(rest) > 1 and rest[1] == "kill"
    d = work / (spec.replace(":", "_") + (f"_{fps}fps" if fps else ""))
    d.mkdir(parents=True)
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    ts = [sys.executable, "-m", "torchseam", *(_configs_at(fps, work) if fps else [])]
    part_file = str(REPO / "configs" / "parts" / f"{part}.yaml")
    common = ["--part", part_file, "--segments", "a", "--length-mm", f"{length:g}"]
    vc = subprocess.Popen([*ts, "virtual-cell", *common, "--camera-latency-ms", latency,
                           "--clock-offset-s", "3600", "--seed", str(seed), "--out", "V",
                           *(["--noise", noise] if noise else []),
                           "--write-cell", "V/cell.yaml", *(["--fault", fault] if fault else [])],
                          cwd=d, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                          text=True)
    t0 = time.monotonic()
    weld = subprocess.Popen([*ts, "weld", "--cell", "V/cell.yaml", *common, "--out", "W"], cwd=d,
                            env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    if kill:
        assert weld.stdout is not None
        for line in weld.stdout:
            if "mm, tracking" in line and not line.split(":")[-1].strip().startswith("0.0"):
                break
        weld.send_signal(signal.SIGKILL)
    wout, _ = weld.communicate(timeout=300)
    vout, _ = vc.communicate(timeout=120)
    wall = time.monotonic() - t0
    row = {"case": spec + (f"@{fps}" if fps else ""), "weld_rc": weld.returncode,
           "wall_s": round(wall, 1)}
    try:
        s = json.loads((d / "V" / "summary.json").read_text())
    except OSError:
        row["error"] = vout[-500:]
        return row
    w = {}
    if (d / "W" / "summary.json").exists():
        w = json.loads((d / "W" / "summary.json").read_text())
    seg = s["segments"].get("a", {})
    row.update(
        rmse=s["seam_rmse_mm"], max=s["seam_max_mm"],
        within=f"{s['axis_within_1deg']}/{s['poses_welded']}", unsafe=s["unsafe_poses_sent"],
        still_s=s["arc_on_while_still_s"], off_seam_s=s["arc_on_off_seam_s"],
        welded_mm=seg.get("welded_mm"), outcome=seg.get("outcome"),
        stall_arc_off_s=s.get("arc_off_after_camera_stall_s"),
        stop_after_loss_s=s.get("robot_stopped_after_comm_loss_s"),
        late_frames=f"{s.get('camera_frames_late')}/{s.get('camera_frames_sent')}",
        weld_said=(w.get("segments_incomplete") or [{"reason": "welded"}])[0]["reason"][:70]
        if w else "(killed)",
        p99_ms=w.get("latency_p99_ms"), late_replies=(w.get("link") or {}).get("late_replies"),
        frames=w.get("frames"), dropped=w.get("frames_dropped_by_weld"),
        replies=(w.get("link") or {}).get("sent"),
        reply_p99_ms=(w.get("link") or {}).get("reply_p99_ms"))
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cases", default=",".join(DEFAULT))
    ap.add_argument("--length-mm", type=float, default=60.0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--noise", default="", help="the virtual camera's arc noise (default: "
                    "virtual-cell's own); clean renders fastest (80 frames/s on 2 cores)")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        rows = []
        for spec in args.cases.split(","):
            r = run_case(spec, args.length_mm, args.seed, Path(tmp), args.noise)
            rows.append(r)
            print(json.dumps(r), flush=True)
    keys = ["case", "weld_rc", "rmse", "max", "within", "unsafe", "still_s", "off_seam_s",
            "welded_mm", "outcome", "stall_arc_off_s", "stop_after_loss_s", "p99_ms",
            "frames", "dropped", "replies", "late_replies", "reply_p99_ms", "late_frames",
            "weld_said"]
    print("\n| " + " | ".join(keys) + " |")
    print("|" + "---|" * len(keys))
    for r in rows:
        cells = []
        for k in keys:
            v = r.get(k, "")
            cells.append(f"{v:.3f}" if isinstance(v, float) else str(v))
        print("| " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
