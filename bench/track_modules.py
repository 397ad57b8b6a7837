"""Speed of the batched tracker modules (STC, EAKF, EAKF-STC): one table.

Single stream: one 656 x 492 grey uint8 frame in memory -> filtered point, torch on ONE thread
(``torch.set_num_threads(1)``), per-step wall time (and the thread's CPU time, which a busy
machine inflates less) p50 / p99 over many steps, inference mode. Batched: B sequences stepped
together on ``--threads`` threads (default 2), frames/s = B * steps / wall time. On a CUDA
machine the batched rows are repeated on the GPU (synchronised timing).

    python bench/track_modules.py [--steps 1000] [--batch 64] [--threads 2]

The batched rows run the module with the paper's defaults and the shipped fit (what
``torchseam train-live`` and the batched evaluation step): pin them to one core with
``taskset -c 1`` and ``--threads 1`` for the one-core figure (two threads on one core only
contend; unpinned, a busy second core stalls torch's threads).
"""

from __future__ import annotations

import argparse
import os
import time
from collections.abc import Callable

import numpy as np
import torch

from torchseam.sim.vstripe import v_stripe_sequence
from torchseam.track.anchored import fitted_eakf_stc
from torchseam.track.eakf import EAKF
from torchseam.track.fusion import EAKFSTC
from torchseam.track.stc import STC

H, W = 492, 656


def _frames(n: int, batch: int, device: str) -> tuple[torch.Tensor, torch.Tensor]:
    """n steps of (batch, H, W) uint8 frames (a few distinct ones, cycled) and start points."""
    seq = v_stripe_sequence(1, n, size=(H, W), seed=0, noise_sigma=6.0, amplitude=30.0,
                            period=60.0)
    base = seq.frames[0].round().to(torch.uint8)  # (n, H, W)
    shifts = torch.arange(batch) % 7 - 3  # spread the sequences a little
    frames = torch.stack([base.roll(int(s), dims=-1) for s in shifts], dim=1)  # (n, B, H, W)
    uv0 = seq.uv[0, 0].expand(batch, 2) + torch.stack([shifts.float(), 0 * shifts.float()], 1)
    return frames.to(device), uv0.to(device)


def _pct(xs: list[float], q: float) -> float:
    return float(np.percentile(np.asarray(xs), q))


def _runner(name: str, frames: torch.Tensor, uv0: torch.Tensor) -> Callable[[int], object]:
    """A step function t -> one tracking step on frame t (modules initialised on frame 0)."""
    cycle = frames.shape[0]
    if name in ("EAKF-STC", "STC"):
        mod = EAKFSTC() if name == "EAKF-STC" else STC()
        mod.init(frames[0], uv0)
        return lambda t: mod.step(frames[t % cycle])
    f = EAKF()
    m = f.matrices()
    state = [f.init_state(uv0)]
    z = uv0 + torch.randn(cycle, 1, 2)

    def run(t: int) -> None:
        state[0] = f.step(state[0], z[t % cycle], m=m)
    return run


def single_stream(steps: int) -> list[tuple[str, float, float, float, float]]:
    torch.set_num_threads(1)
    frames, uv0 = _frames(50, 1, "cpu")
    rows = []
    with torch.inference_mode():
        for name in ("EAKF-STC", "STC", "EAKF"):
            run = _runner(name, frames, uv0)
            wall, cpu = [], []
            for t in range(1, steps + 100):
                w0, c0 = time.perf_counter_ns(), time.thread_time_ns()
                run(t)
                w1, c1 = time.perf_counter_ns(), time.thread_time_ns()
                if t > 100:  # warm-up
                    wall.append((w1 - w0) * 1e-6)
                    cpu.append((c1 - c0) * 1e-6)
            rows.append((name, _pct(wall, 50), _pct(wall, 99), _pct(cpu, 50), _pct(cpu, 99)))
    return rows


def batched(batch: int, steps: int, threads: int, device: str, fitted: bool = False) -> float:
    torch.set_num_threads(threads)
    frames, uv0 = _frames(8, batch, device)
    trk = (fitted_eakf_stc() if fitted else EAKFSTC()).to(device)
    with torch.inference_mode():
        trk.init(frames[0], uv0)
        for t in range(1, 11):
            trk.step(frames[t % 8])
        if device == "cuda":
            torch.cuda.synchronize()
        t0 = time.perf_counter()
        for t in range(steps):
            trk.step(frames[t % 8])
        if device == "cuda":
            torch.cuda.synchronize()
        dt = time.perf_counter() - t0
    return batch * steps / dt


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--steps", type=int, default=1000, help="single-stream steps per module")
    ap.add_argument("--batch", type=int, default=64)
    ap.add_argument("--batch-steps", type=int, default=60)
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args()
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    print(f"torch {torch.__version__}, {os.cpu_count()} CPUs, load average {load:.2f}")
    print("\nsingle stream (B = 1, 656 x 492 uint8 grey frame in memory), 1 torch thread")
    print(f"{'module':<10} {'wall p50 ms':>12} {'wall p99 ms':>12} {'cpu p50 ms':>11} "
          f"{'cpu p99 ms':>11}")
    for name, w50, w99, c50, c99 in single_stream(args.steps):
        print(f"{name:<10} {w50:>12.3f} {w99:>12.3f} {c50:>11.3f} {c99:>11.3f}")
    print(f"\nbatched EAKF-STC, {args.batch_steps} steps (module: the paper's defaults, or "
          "the shipped fit, models/live_tracker.safetensors, with its STC extensions)")
    print(f"{'device':<8} {'module':<8} {'B':>5} {'threads':>8} {'frames/s':>10}")
    devices = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])
    for dev in devices:
        for b in ([args.batch] if dev == "cpu" else [args.batch, 1024]):
            for fitted in (False, True):
                fps = batched(b, args.batch_steps, args.threads, dev, fitted)
                name = "fitted" if fitted else "default"
                print(f"{dev:<8} {name:<8} {b:>5} {args.threads:>8} {fps:>10.0f}")


if __name__ == "__main__":
    main()
