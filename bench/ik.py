"""IK and reachability-gate timings of the IRB 1410 model (one CPU thread).

    .venv/bin/python bench/ik.py [--n 360] [--repeats 5]

Rows: the closed-form IK (``IRB1410.solve_ik``, branch chosen nearest a seed) and
pytorch-kinematics' ``PseudoInverseIK`` (``method="numeric"``), each cold (seed = home / random
restarts) and warm-started (seed = the neighbouring pose's joints); the path IK along a saddle
ring (``ik_path``), the batched gate (``ReachGate.check``) and the per-pose gate
(``ReachGate.step``). Goals: N random reachable tool0 poses (from random in-range joints) and the
N-pose ring of the T joint of configs/parts/t_joint.yaml. Times are the best of ``--repeats``
runs (the machine may be shared); errors are FK residuals (chain FK) over the solved goals.
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable

import numpy as np
import torch

from torchseam.core.config import load_cell, load_part
from torchseam.robot.kinematics import IKSolution, load_irb1410
from torchseam.robot.reach import ReachGate, nominal_torch_poses


def best_time(f: Callable[[], object], repeats: int) -> tuple[float, float, object]:
    """Best wall time, best CPU time of this process (immune to a shared machine), result."""
    out, wall, cpu = None, float("inf"), float("inf")
    for _ in range(repeats):
        t0, c0 = time.perf_counter(), time.process_time()
        out = f()
        wall = min(wall, time.perf_counter() - t0)
        cpu = min(cpu, time.process_time() - c0)
    return wall, cpu, out


def row(name: str, n: int, seconds: float, cpu: float, sol: IKSolution | None) -> str:
    if sol is None:
        tail = f"{'-':>7} {'-':>12} {'-':>12}"
    else:
        ok = sol.reached
        rate = f"{100.0 * float(ok.float().mean()):.1f}%"
        pos = float(sol.pos_err_mm[ok].max()) if bool(ok.any()) else float("nan")
        rot = float(sol.rot_err_deg[ok].max()) if bool(ok.any()) else float("nan")
        tail = f"{rate:>7} {pos:>12.2e} {rot:>12.2e}"
    return (f"{name:<42} {n:>5} {seconds * 1e3:>9.2f} {cpu * 1e3:>9.2f} {cpu / n * 1e6:>9.1f} "
            f"{tail}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=360, help="goals per problem set (default 360)")
    ap.add_argument("--repeats", type=int, default=5, help="runs per row, best kept")
    args = ap.parse_args()
    torch.set_num_threads(1)
    torch.manual_seed(0)

    robot = load_irb1410()
    cell, part = load_cell(), load_part()
    n, rep = args.n, args.repeats

    g = torch.Generator().manual_seed(1)
    q = robot.min_deg + (robot.max_deg - robot.min_deg) * torch.rand(
        4 * n, 6, generator=g, dtype=torch.float64)
    q_true = q[robot.in_range(q)][:n]
    T_rand = robot.fk(q_true)
    near = q_true + torch.randn(q_true.shape, generator=g, dtype=torch.float64)  # ~1 deg off

    T_tcp = nominal_torch_poses(part, n)
    T_ring = T_tcp @ torch.linalg.inv(torch.as_tensor(cell.tool.matrix()))
    ring_q = robot.ik_path(T_ring).q_deg
    ring_prev = torch.cat([ring_q[:1], ring_q[:-1]])  # each pose seeded from its neighbour

    print(f"IRB 1410 IK / reachability, torch {torch.__version__}, 1 thread, best of {rep}")
    print(f"{'method':<42} {'N':>5} {'wall ms':>9} {'cpu ms':>9} {'cpu us/N':>9} {'solved':>7} "
          f"{'max pos mm':>12} {'max rot deg':>12}")
    rows = [
        ("analytic, cold (seed home), random goals", T_rand, None, "analytic"),
        ("analytic, warm (seed ~1 deg off), random", T_rand, near, "analytic"),
        ("PseudoInverseIK, cold (16 restarts), random", T_rand, None, "numeric"),
        ("PseudoInverseIK, warm (~1 deg off), random", T_rand, near, "numeric"),
        ("analytic, cold (seed home), ring", T_ring, None, "analytic"),
        ("analytic, warm (neighbour), ring", T_ring, ring_prev, "analytic"),
        ("PseudoInverseIK, cold (16 restarts), ring", T_ring, None, "numeric"),
        ("PseudoInverseIK, warm (neighbour), ring", T_ring, ring_prev, "numeric"),
    ]
    for name, T, seed, method in rows:
        s, c, sol = best_time(lambda T=T, seed=seed, method=method:
                              robot.solve_ik(T, seed, method=method), rep)
        print(row(name, len(T), s, c, sol))

    s, c, sol = best_time(lambda: robot.ik_path(T_ring), rep)
    print(row("ik_path, ring (each from its neighbour)", n, s, c, sol))

    gate = ReachGate(robot, cell=cell, part=part)
    s, c, res = best_time(lambda: gate.check(T_tcp), rep)
    print(row("ReachGate.check, ring (all 5 checks)", n, s, c, None) + f"  {res.summary()}")

    wall, cpu = [], []
    for _ in range(rep):
        gate.reset()
        for i in range(n):
            t0, c0 = time.perf_counter(), time.process_time()
            v = gate.step(T_tcp[i])
            wall.append(time.perf_counter() - t0)
            cpu.append(time.process_time() - c0)
            assert v.ok, v.reason
    w, c = np.array(wall) * 1e6, np.array(cpu) * 1e6
    print(f"ReachGate.step, one pose at a time ({n} x {rep}): wall median {np.median(w):.0f} us, "
          f"p99 {np.percentile(w, 99):.0f} us, min {w.min():.0f} us; cpu median "
          f"{np.median(c):.0f} us, p99 {np.percentile(c, 99):.0f} us")


if __name__ == "__main__":
    main()
