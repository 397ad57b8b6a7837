"""The live loop's seeing half and the simulator's renderer, timed on the demo's own frames.

The closed-loop demo prints frame -> command latency, but a demo run takes a minute and its
figures move with whatever else the machine runs. This replays what one demo run saw, as
often as asked, so that a change to the tracker, TIPM, ECAL or the triangulation (or to the
renderer) can be timed frame by frame and checked to compute the very same numbers:

    python bench/loop_latency.py record --segments ab --out /tmp/seg_ab.npz
    taskset -c 1 python bench/loop_latency.py replay /tmp/seg_ab.npz --reps 3
    taskset -c 1 python bench/loop_latency.py render /tmp/seg_ab.npz.render --reps 2
    python bench/loop_latency.py score /tmp/seg_ab.npz

``record`` runs ``torchseam demo`` (the T joint, heavy arc, seed 0, the ``anchored`` tracker;
``--segments``) and keeps every frame with its flange pose and what the loop's
:class:`~torchseam.live.locate.SeamLocator` made of it (pixel, 3D point, arm points), and,
in ``OUT.render``, every call of the renderer with its result. ``replay`` runs a fresh
locator over the frames (``start`` on a segment's first frame, ``step`` then the tracker's
``idle()`` on every other, as the loop does) ``--reps`` times and prints per-stage times
(track, ECAL, triangulation, the whole step; p50 / p90 / p99 over the frames of the per-frame
minimum over the repetitions, which keeps another job's bursts out of a comparison) and how
many frames came out different from the recording (bit for bit; 0 means the code computes what
the recorded one did). ``render`` does the same for the renderer (thread CPU time per frame;
frames and truth compared bit for bit). Run the two sides of a comparison alternately, pinned
to one core (``taskset -c 1``), several times each, and say the load. ``score`` replays once
and scores against the renderer's truth (from ``OUT.render``): the tracker's point and the
robot's expected pixel (px), the located 3D point against the true seam point (mm), the
arm directions against the true arms (deg, the larger of the two).
"""

from __future__ import annotations

import argparse
import os
import pickle
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import torch


def _record(args: argparse.Namespace) -> None:
    import torchseam.live.demo as demo
    from torchseam.core.config import load_cell, load_noise, load_part
    from torchseam.core.transforms import invert
    from torchseam.live.parts import load_live_parts
    from torchseam.sim.sequence import SensorRenderer

    cell, part, noise = load_cell(), load_part(), load_noise()
    tool_inv = invert(cell.tool.matrix())
    rec: dict[str, list] = {k: [] for k in ("frame", "T_B_F", "seg", "uv", "p", "q")}
    inits: list = []
    calls: list = []

    class Recorded(SensorRenderer):
        def __init__(self, *a, **k) -> None:
            inits.append((a, k))
            self._index = len(inits) - 1
            super().__init__(*a, **k)

        def render(self, *a, **k):
            frame, truth = super().render(*a, **k)
            calls.append((self._index, a, k, frame.copy(), truth))
            return frame, truth

    def observe(ev) -> None:
        loc = ev.report.location if ev.report is not None else None
        rec["frame"].append(ev.frame.copy())
        rec["T_B_F"].append(ev.T_B_W @ tool_inv)  # the flange pose the loop got
        rec["seg"].append(ev.seg)
        rec["uv"].append(loc.uv if loc is not None else np.full(2, np.nan))
        rec["p"].append(loc.p if loc is not None else np.full(3, np.nan))
        rec["q"].append(loc.q if loc is not None else np.full((2, 3), np.nan))

    demo.SensorRenderer = Recorded  # type: ignore[misc]
    res = demo.run_demo(cell, part, noise, noise.level(args.noise), args.seed,
                        segments=args.segments, parts=load_live_parts(), observer=observe)
    np.savez(args.out, **{k: np.array(v) for k, v in rec.items()})
    with open(f"{args.out}.render", "wb") as f:
        pickle.dump((inits, calls), f, protocol=pickle.HIGHEST_PROTOCOL)
    print(f"{len(rec['frame'])} frames of segments {args.segments} -> {args.out} (and "
          f"{args.out}.render); the run's frame -> command p50 / p99 "
          f"{res.summary['latency_p50_ms']:.2f} / {res.summary['latency_p99_ms']:.2f} ms")


def _started(cell, parts, frame: np.ndarray):
    """A seam locator with the live tracker, started on ``frame`` (a segment's first)."""
    from torchseam.live.locate import SeamLocator
    from torchseam.track.peers import make_tracker

    loc = SeamLocator(cell, make_tracker("anchored", parts.tipm), parts.tipm, parts.ecal)
    loc.start(frame)
    return loc


def _pct(a: np.ndarray) -> str:
    return " / ".join(f"{np.percentile(a, q):.3f}" for q in (50, 90, 99))


def _replay(args: argparse.Namespace) -> None:
    from torchseam.core.config import load_cell
    from torchseam.live.parts import load_live_parts

    d = np.load(args.recording)
    frames, poses, seg = d["frame"], d["T_B_F"], d["seg"]
    cell, parts = load_cell(), load_live_parts()
    stages = ("track", "ecal", "triangulate")
    times = {k: np.full((args.reps, len(frames)), np.nan) for k in (*stages, "step", "idle")}
    differ = 0
    for r in range(args.reps):
        loc = None
        for k in range(len(frames)):
            if k == 0 or seg[k] != seg[k - 1]:
                loc = _started(cell, parts, frames[k])
                continue
            assert loc is not None
            t0 = time.perf_counter()
            out = loc.step(frames[k], poses[k])
            t1 = time.perf_counter()
            idle = getattr(loc.tracker, "idle", None)
            if idle is not None:
                idle()
            t2 = time.perf_counter()
            for name in stages:
                times[name][r, k] = out.timings_ms.get(name, np.nan)
            times["step"][r, k], times["idle"][r, k] = (t1 - t0) * 1e3, (t2 - t1) * 1e3
            if r == 0:
                differ += not (np.array_equal(out.uv, d["uv"][k], equal_nan=True)
                               and np.array_equal(out.p, d["p"][k], equal_nan=True)
                               and np.array_equal(out.q, d["q"][k], equal_nan=True))
    load = os.getloadavg()[0]
    print(f"{np.count_nonzero(~np.isnan(times['step'][0]))} frames x {args.reps}, load average "
          f"{load:.2f}; frames differing from the recording: {differ}")
    print("ms, per-frame minimum over the repetitions: p50 / p90 / p99")
    stepped = ~np.isnan(times["step"][0])  # not the segments' start frames
    for name, t in times.items():
        t = t[:, stepped]
        ok = ~np.all(np.isnan(t), axis=0)  # a stage the frame reached
        if ok.any():
            print(f"  {name:<12} {_pct(np.nanmin(t[:, ok], axis=0))}")


def _arm_angle(p: np.ndarray, q: np.ndarray, seam: np.ndarray, arms: np.ndarray) -> float:
    """The larger angle (deg) between a located arm direction (q_i - p) and the true one
    (arm_B - seam_B), the arms paired the way that fits best."""
    def unit(a: np.ndarray) -> np.ndarray:
        return a / np.linalg.norm(a, axis=1, keepdims=True)

    got, true = unit(q - p), unit(arms - seam)
    ang = np.degrees(np.arccos(np.clip(got @ true.T, -1.0, 1.0)))  # (located, true)
    return float(min(max(ang[0, 0], ang[1, 1]), max(ang[0, 1], ang[1, 0])))


def _score(args: argparse.Namespace) -> None:
    from torchseam.core.config import load_cell
    from torchseam.live.parts import load_live_parts

    d = np.load(args.recording)
    frames, poses, seg = d["frame"], d["T_B_F"], d["seg"]
    with open(f"{args.recording}.render", "rb") as f:
        _, calls = pickle.load(f)
    truth = {hash(fr.tobytes()): tr for (_, _, _, fr, tr) in calls}
    found = [truth.get(hash(f.tobytes())) for f in frames]
    flat = np.zeros(len(frames), bool)
    if args.shallow:  # each segment's frames with bench/tracking.py's shallow stretch
        from torchseam.sim.variants import shallow_corner
        frames = list(frames)
        for n, s in enumerate(np.unique(seg)):
            idx = np.flatnonzero(seg == s)
            if any(found[i] is None for i in idx):
                continue
            uv = np.array([found[i].uv for i in idx], float)
            arm = np.array([found[i].arm_uv for i in idx], float)
            out_f, _, fl = shallow_corner([frames[i] for i in idx], uv, arm, n)
            for j, i in enumerate(idx):
                frames[i] = out_f[j]
            flat[idx] = fl
    cell, parts = load_cell(), load_live_parts()
    err: dict[str, list[float]] = {"tracker px": [], "expected px": [], "3D point mm": [],
                                   "arm deg": [], "flat: tracker px": []}
    loc = None
    for k in range(len(frames)):
        if k == 0 or seg[k] != seg[k - 1]:
            loc = _started(cell, parts, frames[k])
            continue
        assert loc is not None
        seen = loc._expect(poses[k])  # what step() hands the tracker first
        out = loc.step(frames[k], poses[k])
        idle = getattr(loc.tracker, "idle", None)
        if idle is not None:
            idle()
        t = found[k]
        if t is None or t.uv is None or not np.all(np.isfinite(t.uv)):
            continue
        if flat[k]:
            err["flat: tracker px"].append(float(np.linalg.norm(out.uv - t.uv)))
        if seen is not None:
            err["expected px"].append(float(np.linalg.norm(seen - t.uv)))
        if np.all(np.isfinite(out.uv)):
            err["tracker px"].append(float(np.linalg.norm(out.uv - t.uv)))
        if np.all(np.isfinite(out.p)) and np.all(np.isfinite(t.seam_B)):
            err["3D point mm"].append(float(np.linalg.norm(out.p - np.asarray(t.seam_B))))
        if out.arms_ok and np.all(np.isfinite(out.q)) and np.all(np.isfinite(t.arm_B)):
            err["arm deg"].append(_arm_angle(out.p, out.q, np.asarray(t.seam_B),
                                             np.asarray(t.arm_B)))
    print(f"{len(frames)} frames, scored against the renderer's truth: p50 / p99 / max (n)")
    for name, e in err.items():
        a = np.array(e)
        if a.size:
            print(f"  {name:<12} {np.percentile(a, 50):.3f} / {np.percentile(a, 99):.3f} / "
                  f"{a.max():.3f} ({a.size})")


def _render(args: argparse.Namespace) -> None:
    from torchseam.sim.sequence import SensorRenderer

    with open(args.recording, "rb") as f:
        inits, calls = pickle.load(f)
    per = np.zeros((args.reps, len(calls)))
    differ = 0
    for r in range(args.reps):
        renderers: dict[int, SensorRenderer] = {}
        for n, (i, a, k, frame, truth) in enumerate(calls):
            if i not in renderers:
                renderers[i] = SensorRenderer(*inits[i][0], **inits[i][1])
            t0 = time.thread_time()
            f2, t2 = renderers[i].render(*a, **k)
            per[r, n] = (time.thread_time() - t0) * 1e3
            if r == 0:
                differ += not (np.array_equal(f2, frame)
                               and np.array_equal(t2.uv, truth.uv, equal_nan=True)
                               and np.array_equal(t2.seam_B, truth.seam_B, equal_nan=True)
                               and np.array_equal(t2.arm_B, truth.arm_B, equal_nan=True)
                               and t2.visible == truth.visible)
    best = per.min(axis=0)
    print(f"{len(calls)} renders x {args.reps}, load average {os.getloadavg()[0]:.2f}; "
          f"differing from the recording: {differ}")
    print(f"  render ms (thread CPU, per-frame minimum): p50 / p90 / p99 {_pct(best)}; "
          f"mean {best.mean():.3f}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    rec = sub.add_parser("record", help="run the demo and keep its frames")
    rec.add_argument("--segments", default="a")
    rec.add_argument("--noise", default="heavy")
    rec.add_argument("--seed", type=int, default=0)
    rec.add_argument("--out", type=Path, required=True)
    for name in ("replay", "render", "score"):
        p = sub.add_parser(name)
        p.add_argument("recording", type=Path)
        p.add_argument("--reps", type=int, default=3)
        if name == "score":
            p.add_argument("--shallow", action="store_true",
                           help="give each segment bench/tracking.py's shallow-kink stretch "
                                "(glare and spatter on the corner) before replaying it")
    args = ap.parse_args()
    torch.set_num_threads(1)  # the live loop's setting: one core per camera
    cv2.setNumThreads(1)
    {"record": _record, "replay": _replay, "render": _render, "score": _score}[args.cmd](args)


if __name__ == "__main__":
    sys.exit(main())
