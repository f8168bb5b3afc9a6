"""IK solver benchmark: companion.ik.solve against the papers' DE and the IK libraries, one run.

    .venv/bin/python -m bench.solver [--poses 10000] [--baseline-poses 1000] [--paper-poses 200]
                                     [--budget-ms 20] [--seed 0] [--markdown FILE]

Targets are random reachable poses of the default arm: FK of joints drawn uniformly within the
Table 2 limits, seeded. Success means a position error ≤ 1e-3 cm, an orientation error (rotation
angle) ≤ 1e-3°, and every joint within its limits. The errors are recomputed for every solver
with the numpy FK (``IKObjective.errors``), not taken from the solver. Times are wall time
around the call, in ms.

Rows (a row is skipped, with a note, when its package is missing: ``pip install -e '.[bench]'``):
* this solver, cold (no start configuration) and warm (100 Hz circle and figure-eight paths);
* the same kernel with the least-squares refinement off (DE only, NP 20), same budget;
* an ablation: the same compiled LM from random starts, no DE (what DE adds is the gap);
* the papers' DE as published (numpy, rand/1/bin, F 0.9, Cr 0.95, NP 12, 400 generations,
  Euler objective);
* scipy ``least_squares`` (trf, bounds) from mid-range, then ≤ 10 random restarts;
* roboticstoolbox-python's C++ ``ik_LM`` (ets fast path, joint limits on, tol 1e-12).
Also: the budget overrun on unreachable targets, and the first call after import (numba cache
warm, and cold in an empty cache directory), each in a fresh interpreter.
"""

from __future__ import annotations

import argparse
import math
import os
import platform
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from bench.report import interpreter, md_table, write_markdown
from companion.ik import SolverSettings, kernel_arrays, kernels, solve
from companion.kinematics.arm import Arm, Pose
from companion.papers.de import differential_evolution
from companion.papers.objective import IKObjective

TOL_POS_CM = 1e-3
TOL_ORI_DEG = 1e-3

Solver = Callable[[Pose, int], np.ndarray]  # (target, seed) -> joints in radians


def targets(arm: Arm, count: int, seed: int) -> list[Pose]:
    q = arm.random_q_rad(np.random.default_rng(seed), count)
    return [Pose.from_matrix(t) for t in arm.fk_batch(q)]


def judge(arm: Arm, target: Pose, q_rad: np.ndarray | None) -> bool:
    if q_rad is None or not np.all(np.isfinite(q_rad)) or not arm.within_limits(q_rad, 1e-12):
        return False
    e = IKObjective(arm, target).errors(q_rad)
    return bool(e.pos_err_cm[0] <= TOL_POS_CM and e.ori_err_deg[0] <= TOL_ORI_DEG)


def run_row(arm: Arm, name: str, solver: Solver, poses: list[Pose]) -> dict:
    ms, ok = [], []
    for k, target in enumerate(poses):
        t = time.perf_counter()
        q = solver(target, k)
        ms.append((time.perf_counter() - t) * 1e3)
        ok.append(judge(arm, target, q))
    ms_arr = np.asarray(ms)
    return {
        "solver": name,
        "poses": len(poses),
        "success %": 100.0 * float(np.mean(ok)),
        "median ms": float(np.median(ms_arr)),
        "p99 ms": float(np.percentile(ms_arr, 99)),
        "max ms": float(ms_arr.max()),
    }


# -- solvers -------------------------------------------------------------------------------------


def ours(arm: Arm, budget_ms: float, settings: SolverSettings | None = None) -> Solver:
    kwargs = {} if settings is None else {"settings": settings}

    def run(target: Pose, seed: int) -> np.ndarray:
        return solve(arm, target, budget_ms=budget_ms, seed=seed, **kwargs).q_rad

    return run


DE_ONLY = SolverSettings(lm_iterations=0, pop_size=20, stall_generations=100)
"""DE alone in the compiled kernel; NP 20 because NP 12 stalls at about half the poses."""


def multistart_lm(arm: Arm, budget_ms: float) -> Solver:
    """Ablation: the solver's LM (20 steps) from uniform random starts until the tolerances
    are met or the budget is spent: what DE adds is the difference to this row."""
    k = kernel_arrays(arm)
    fp = np.zeros(kernels.N_FPARAMS)
    fp[kernels.F_TOL_POS] = TOL_POS_CM
    fp[kernels.F_TOL_ORI] = TOL_ORI_DEG
    fp[kernels.F_LM_LAMBDA0] = SolverSettings().lm_lambda0
    out = np.empty(3)

    def run(target: Pose, seed: int) -> np.ndarray:
        started = time.perf_counter()
        rng = np.random.default_rng(seed)
        goal = target.as_matrix()
        best, best_cost = None, math.inf
        while time.perf_counter() - started < budget_ms / 1e3:
            q = k.lower + rng.random(arm.dof) * (k.upper - k.lower)
            kernels.lm_refine(
                q, k.lower, k.upper, k.frames, k.jp, goal, kernels.MODE_POSE, fp, 20, out
            )
            if out[0] < best_cost:
                best, best_cost = q, out[0]
            if out[1] <= TOL_POS_CM and out[2] <= TOL_ORI_DEG:
                break
        return best

    return run


def papers_de(arm: Arm) -> Solver:
    def run(target: Pose, seed: int) -> np.ndarray:
        obj = IKObjective(arm, target)
        return differential_evolution(
            obj, pop_size=12, generations=400, F=0.9, Cr=0.95, seed=seed
        ).x

    return run


def scipy_least_squares(arm: Arm) -> Solver | None:
    try:
        from scipy.optimize import least_squares
        from scipy.spatial.transform import Rotation
    except ImportError:
        return None
    lo, hi = arm.lower_rad, arm.upper_rad

    def residual(q: np.ndarray, goal: np.ndarray) -> np.ndarray:
        # Position (cm) and the rotation vector of R_goalᵀ·R (deg): zero only at the goal.
        t = arm.fk_matrix(q)
        rotvec = Rotation.from_matrix(goal[:3, :3].T @ t[:3, :3]).as_rotvec(degrees=True)
        return np.concatenate([t[:3, 3] - goal[:3, 3], rotvec])

    def run(target: Pose, seed: int) -> np.ndarray:
        goal = target.as_matrix()
        rng = np.random.default_rng(seed)
        starts = [0.5 * (lo + hi)] + [lo + rng.random(lo.size) * (hi - lo) for _ in range(10)]
        best = None
        for q0 in starts:
            sol = least_squares(
                residual,
                q0,
                bounds=(lo, hi),
                method="trf",
                args=(goal,),
                xtol=1e-15,
                ftol=1e-15,
                gtol=1e-15,
            )
            if best is None or sol.cost < best.cost:
                best = sol
            if judge(arm, target, sol.x):
                break
        return best.x

    return run


def rtb_ik_lm(arm: Arm) -> Solver | None:
    try:
        import roboticstoolbox as rtb
        import spatialmath
    except ImportError:
        return None
    link_type = rtb.RevoluteDH if arm.convention.value == "standard" else rtb.RevoluteMDH
    robot = rtb.DHRobot(
        [
            link_type(
                d=j.d_cm,
                a=j.a_cm,
                alpha=j.alpha_rad,
                offset=j.offset_rad,
                qlim=[j.min_rad, j.max_rad],
            )
            for j in arm.joints
        ]
    )
    if arm.tool_matrix is not None:
        robot.tool = spatialmath.SE3(np.array(arm.tool_matrix), check=False)
    ets = robot.ets()
    lo, hi = arm.lower_rad, arm.upper_rad

    def run(target: Pose, seed: int) -> np.ndarray:
        # First start seeded here; rtb draws its further restarts itself.
        q0 = lo + np.random.default_rng(seed).random(lo.size) * (hi - lo)
        sol = ets.ik_LM(target.as_matrix(), q0=q0, tol=1e-12, joint_limits=True)
        return np.asarray(sol.q)

    return run


# -- paths and extra figures ---------------------------------------------------------------------


def path_poses(arm: Arm, kind: str, samples: int) -> list[Pose]:
    """A hand path sampled at 100 Hz: a 5 cm circle or a 10 × 5 cm figure-eight, 2 s long,
    orientation held, around a comfortable pose (elbow bent)."""
    centre = arm.fk([20, 70, 50, 20, 30, 10])
    out = []
    for k in range(samples):
        s = 2 * math.pi * k / samples
        if kind == "circle":
            dy, dz = 5.0 * math.cos(s), 5.0 * math.sin(s)
        else:
            dy, dz = 5.0 * math.sin(s), 2.5 * math.sin(2 * s)
        out.append(
            Pose(
                centre.x_cm,
                centre.y_cm + dy,
                centre.z_cm + dz,
                centre.roll_deg,
                centre.pitch_deg,
                centre.yaw_deg,
            )
        )
    return out


def warm_row(arm: Arm, kind: str, budget_ms: float, laps: int) -> dict:
    poses = path_poses(arm, kind, 200) * laps
    first = solve(arm, poses[0], budget_ms=1e3, seed=0)
    q_prev = np.array(first.q_deg)
    ms, ok, steps = [], [], []
    for k, target in enumerate(poses[1:], start=1):
        t = time.perf_counter()
        res = solve(arm, target, budget_ms=budget_ms, seed=k, q_start_deg=q_prev)
        ms.append((time.perf_counter() - t) * 1e3)
        ok.append(judge(arm, target, res.q_rad))
        steps.append(float(np.abs(np.array(res.q_deg) - q_prev).max()))
        q_prev = np.array(res.q_deg)
    ms_arr = np.asarray(ms)
    return {
        "solver": f"this solver, warm, 100 Hz {kind} ({laps} laps)",
        "poses": len(ms),
        "success %": 100.0 * float(np.mean(ok)),
        "median ms": float(np.median(ms_arr)),
        "p99 ms": float(np.percentile(ms_arr, 99)),
        "max ms": float(ms_arr.max()),
        "max joint step deg": max(steps),
    }


def overrun_row(arm: Arm, budget_ms: float, count: int, seed: int) -> dict:
    """Unreachable targets (reachable positions with orientation turned 90–180° off, and
    positions beyond reach) must come back by the budget."""
    rng = np.random.default_rng(seed)
    over = []
    for k, target in enumerate(targets(arm, count, seed + 1)):
        if k % 2:
            target = Pose(target.x_cm * 3, target.y_cm * 3, target.z_cm * 3 + 100, 0, 0, 0)
        else:
            target = Pose(
                *target.as_tuple()[:3],
                target.roll_deg + 180,
                -target.pitch_deg,
                target.yaw_deg + rng.uniform(90, 180),
            )
        t = time.perf_counter()
        solve(arm, target, budget_ms=budget_ms, seed=k)
        over.append((time.perf_counter() - t) * 1e3 - budget_ms)
    over_arr = np.asarray(over)
    return {
        "budget ms": budget_ms,
        "targets": count,
        "median overrun ms": float(np.median(over_arr)),
        "max overrun ms": float(over_arr.max()),
    }


def first_call(cache_dir: str | None) -> dict:
    """Import, ``ik.warm_up()`` and first solve in a fresh interpreter; ``cache_dir`` forces
    numba's cache there."""
    code = (
        "import time; t0 = time.perf_counter()\n"
        "from companion.kinematics import Arm\n"
        "from companion import ik\n"
        "t1 = time.perf_counter(); warm_s = ik.warm_up()\n"
        "arm = Arm.default(); target = arm.fk([10, 80, 20, 10, 20, 30])\n"
        "t2 = time.perf_counter(); r = ik.solve(arm, target, seed=0)\n"
        "t3 = time.perf_counter()\n"
        "print(t1 - t0, warm_s, t3 - t2)\n"
    )
    env = dict(os.environ)
    if cache_dir is not None:
        env["NUMBA_CACHE_DIR"] = cache_dir
    out = subprocess.run(
        [sys.executable, "-c", code], env=env, check=True, capture_output=True, text=True
    ).stdout.split()
    return {
        "import s": float(out[0]),
        "warm_up() s": float(out[1]),
        "first solve ms": float(out[2]) * 1e3,
    }


def table(rows: list[dict]) -> list[str]:
    keys = list(dict.fromkeys(k for r in rows for k in r))
    return md_table(
        keys,
        [[r.get(k, "") for k in keys] for r in rows],
        cell=lambda v: f"{v:.3g}" if isinstance(v, float) else str(v),
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--poses", type=int, default=10_000, help="poses for this solver (cold)")
    parser.add_argument(
        "--baseline-poses", type=int, default=1000, help="poses for DE-only, scipy and rtb"
    )
    parser.add_argument("--paper-poses", type=int, default=200, help="poses for the papers' DE")
    parser.add_argument("--budget-ms", type=float, default=20.0)
    parser.add_argument("--laps", type=int, default=5, help="laps of each warm path (200 samples)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--markdown", type=Path)
    args = parser.parse_args()

    arm = Arm.default()
    poses = targets(arm, args.poses, args.seed)
    base = poses[: args.baseline_poses]
    notes = []
    rows = [run_row(arm, "this solver (memetic DE), cold", ours(arm, args.budget_ms), poses)]
    rows.append(
        run_row(
            arm,
            "same kernel, DE only (NP 20, no least-squares steps)",
            ours(arm, args.budget_ms, DE_ONLY),
            base,
        )
    )
    rows.append(
        run_row(
            arm,
            "ablation: multi-start LM, same compiled LM, no DE",
            multistart_lm(arm, args.budget_ms),
            base,
        )
    )
    rows.append(
        run_row(
            arm,
            "papers' DE: NP 12, 400 gen, F 0.9, Cr 0.95 (numpy)",
            papers_de(arm),
            poses[: args.paper_poses],
        )
    )
    for name, make in (
        ("scipy least_squares trf, mid-range + ≤ 10 restarts", scipy_least_squares),
        ("roboticstoolbox 1.5 ik_LM (C++, ets), limits on, tol 1e-12", rtb_ik_lm),
    ):
        solver = make(arm)
        if solver is None:
            notes.append(f"skipped: {name} (package not installed; pip install -e '.[bench]')")
        else:
            rows.append(run_row(arm, name, solver, base))
    warm = [warm_row(arm, kind, args.budget_ms, args.laps) for kind in ("circle", "figure-eight")]
    overrun = [overrun_row(arm, b, 200, args.seed) for b in (1.0, args.budget_ms)]
    with tempfile.TemporaryDirectory() as empty:
        start = [
            dict(cache="numba cache warm", **first_call(None)),
            dict(cache="empty numba cache (first run ever)", **first_call(empty)),
        ]

    lines = [
        f"machine: {platform.machine()}, {os.cpu_count()} cores, {interpreter()}; "
        f"budget {args.budget_ms} ms; success = pos ≤ {TOL_POS_CM} cm "
        f"and ori ≤ {TOL_ORI_DEG}° and within limits",
        "",
    ]
    lines += ["Cold solves of random reachable poses:", ""] + table(rows) + [""]
    lines += ["Warm solves along paths (start = previous solution):", ""] + table(warm) + [""]
    lines += ["Budget overrun on unreachable targets (wall time − budget):", ""]
    lines += table(overrun) + [""]
    lines += ["First call after import (fresh interpreter):", ""] + table(start)
    lines += [""] + notes
    text = "\n".join(lines)
    print(text)
    if args.markdown:
        write_markdown(args.markdown, text + "\n")


if __name__ == "__main__":
    main()
