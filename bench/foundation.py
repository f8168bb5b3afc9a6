"""Foundation figures: forward-kinematics cost, and the papers' DE on reachable poses.

    .venv/bin/python -m bench.foundation [--poses 200] [--seed 0] [--markdown FILE]

Prints two tables:
1. FK cost per pose: single-pose ``Arm.fk_matrix`` and batched ``Arm.fk_batch`` for several
   batch sizes (best of 5 repeats of a timed loop).
2. The papers' DE setting (Table 5 test 9: rand/1/bin, F 0.9, Cr 0.95, NP 12, 400 generations,
   Euler objective of Eq. 1, Table 2 limits) on ``--poses`` random reachable poses (FK of joints
   drawn uniformly within the limits): J reached, position / orientation error, time per solve.
"""

from __future__ import annotations

import argparse
import platform
import timeit
from pathlib import Path

import numpy as np

from bench.report import interpreter, write_markdown
from companion.kinematics.arm import Arm, Pose
from companion.papers.de import differential_evolution
from companion.papers.objective import IKObjective


def time_per_call(fn, repeats: int = 5) -> float:
    """Best-of-``repeats`` seconds per call of ``fn`` (timeit's auto-ranged loop count)."""
    timer = timeit.Timer(fn)
    loops, _ = timer.autorange()
    return min(timer.repeat(repeats, loops)) / loops


def fk_table(arm: Arm, rng: np.random.Generator) -> list[tuple[str, float, float]]:
    rows = []
    q1 = arm.random_q_rad(rng, 1)[0]
    per_call = time_per_call(lambda: arm.fk_matrix(q1))
    rows.append(("fk_matrix (one pose)", 1, per_call * 1e6))
    for size in (12, 100, 1000, 10000):
        q = arm.random_q_rad(rng, size)
        per_call = time_per_call(lambda q=q: arm.fk_batch(q))
        rows.append((f"fk_batch (S={size})", size, per_call / size * 1e6))
    return rows


def de_table(arm: Arm, poses: int, seed: int) -> dict[str, float]:
    rng = np.random.default_rng(seed)
    qs = arm.random_q_rad(rng, poses)
    costs, pos, ori, ms = [], [], [], []
    for k, q in enumerate(qs):
        obj = IKObjective(arm, Pose.from_matrix(arm.fk_matrix(q)))
        res = differential_evolution(
            obj, pop_size=12, generations=400, F=0.9, Cr=0.95, seed=seed + k
        )
        e = obj.errors(res.x)
        costs.append(res.cost)
        pos.append(e.pos_err_cm[0])
        ori.append(e.ori_err_deg[0])
        ms.append(res.elapsed_s * 1e3)
    costs, pos, ori, ms = map(np.asarray, (costs, pos, ori, ms))
    return {
        "poses": poses,
        "J median": float(np.median(costs)),
        "J p90": float(np.percentile(costs, 90)),
        "pos_err median (cm)": float(np.median(pos)),
        "ori_err median (deg)": float(np.median(ori)),
        "within 0.01 cm & 0.01 deg (%)": float(np.mean((pos <= 0.01) & (ori <= 0.01)) * 100),
        "within 1e-3 cm & 1e-3 deg (%)": float(np.mean((pos <= 1e-3) & (ori <= 1e-3)) * 100),
        "time median (ms)": float(np.median(ms)),
        "time p99 (ms)": float(np.percentile(ms, 99)),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--poses", type=int, default=200)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--markdown", type=Path, help="also write the tables to this file")
    args = parser.parse_args()

    arm = Arm.default()
    lines = [
        f"machine: {platform.machine()}, {interpreter()}",
        "",
    ]
    lines += ["| FK call | poses per call | µs per pose |", "|---|---|---|"]
    for name, size, us in fk_table(arm, np.random.default_rng(args.seed)):
        lines.append(f"| {name} | {size} | {us:.2f} |")
    lines += [
        "",
        "Papers' DE (rand/1/bin, F 0.9, Cr 0.95, NP 12, 400 generations, Euler objective),",
        "random reachable poses of the default arm:",
        "",
        "| figure | value |",
        "|---|---|",
    ]
    for key, value in de_table(arm, args.poses, args.seed).items():
        lines.append(f"| {key} | {value:.4g} |")
    text = "\n".join(lines)
    print(text)
    if args.markdown:
        write_markdown(args.markdown, text + "\n")


if __name__ == "__main__":
    main()
