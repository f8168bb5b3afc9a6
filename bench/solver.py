"""IK solver benchmark: companion.ik.solve against roboticstoolbox's ``ik_LM``, on every arm.

    .venv/bin/pip install -q -e '.[bench]'
    .venv/bin/python -m bench.solver [--poses 1000] [--sweep-poses N] [--limit-poses 200]
                                     [--methods restarts,memetic,de] [--method-poses 300]
                                     [--hog-poses 300] [--busy 1] [--tol-poses 300]
                                     [--budget-ms 20] [--seed 2026] [--arms a,b] [--laps 5]
                                     [--only-extras] [--only-hog] [--ceiling-ms MS]
                                     [--no-cold-start] [--context-poses N] [--markdown FILE]

The peer is roboticstoolbox-python's C++ ``ets().ik_LM`` (joint limits on, its own restarts) on
every arm of rtb's DH zoo (``roboticstoolbox.models.DH``, :data:`ZOO`: each converted to our arm
model, none skipped) and on the default arm's DH table (converted to metres). rtb's ``tol`` is
chosen per arm: the loosest of :data:`RTB_TOLS` at which it still meets our success criterion
on as many of ``--tol-poses`` calibration poses (other draws than the measured ones) as at
1e-12. Honest by construction:

* interleaved pose by pose in one thread, the order of the solvers shuffled for each pose;
* the same per-call work outside the timed region for both: the target ``Pose`` (ours) and the
  4×4 target matrix and start ``q0`` (rtb) are built before the clock starts; inside it, each
  call turns its answer into a numpy joint vector in our units; what the tables read of our
  result is recorded after it (the result then dropped, as rtb's is);
* the garbage collector frozen (``gc.freeze()``) and disabled around both;
* thread CPU time (``time.thread_time``) beside wall time, per call; the two clock reads are
  inside every timed call of both (1-3 µs of CPU each call, more after other work: the
  ``--context-poses`` table's last column);
* per call, whether this thread was switched out (its context switches, voluntary and
  involuntary, from ``getrusage(RUSAGE_THREAD)``, read before and after the clocks, outside the
  timed region): the tables give the share of calls switched out, the p99 over the calls that
  were not beside the full p99 (which is the target's), and the median over each kind (what a
  switch costs a call: the kernel's work and caches the other task left cold);
* optionally (``--sweep-poses``) an 8 MB buffer touched before every call of either, outside the
  timed region (a daemon that does other work between solves: caches cold for both);
* optionally (``--busy``) busy-loop processes beside the interleaved tables (the issue's targets
  are for a machine at load ≥ 2);
* every call as cold as its neighbours make it, for both: what runs before a timed call (the
  other peer, the judge's numpy FK, building the next pose's calls) leaves the caches and branch
  predictors cold for whichever peer comes next, and the order is shuffled, so each peer pays it
  alike in expectation. ``--context-poses N`` measures it: each peer timed after each of those
  alone, after all three, after an 8 MB sweep, and right after its own previous call (as warm as
  a tight loop). On hyper, cobra600, coil and planar3, ours took 9.5-15 µs right after its own
  previous call and 15-30 µs after any of the others, rtb 36-110 µs and 8-35 µs more: a cold
  start costs rtb more than ours, and it is a larger share of ours; the 8 MB sweep cost ours
  no more than the other contexts (``--arms hyper,cobra600,coil,planar3 --poses 10
  --sweep-poses 0 --limit-poses 0 --hog-poses 0 --laps 0 --methods restarts --no-cold-start
  --context-poses 600 --tol-poses 10``);
* a seed the solver was not tuned on (the default, 2026; tuning used 0–99 and only the arms
  of :data:`TUNING_ARMS`);
* success = position ≤ 1e-3 cm, orientation (rotation angle) ≤ 1e-3° and every joint within its
  limits, all recomputed with the numpy FK of our arm model, for both solvers.

Targets: FK of joints drawn uniformly within the limits. The target table, the sweep and the
joints-at-limits tables run the first of ``--methods`` (the default method) beside rtb alone;
the method table runs every method of ``--methods`` beside rtb on the first
``--method-poses`` poses. Then:

* joints-at-limits poses: every joint within 0.5° (0.5 cm for a slider) of one of its limits;
* a CPU hog (one busy subprocess per core) beside ours, the first ``--hog-poses`` poses of each
  arm: success, and how the deadline ends the failures, with the budget counted in wall time
  (as before the solver counted CPU time) and in CPU time (``--ceiling-ms``), interleaved pose
  by pose; ``--only-hog`` runs just these;
* ours warm along 100 Hz paths of the default arm (``--laps``), and the budget overrun on
  unreachable targets (``--only-extras`` runs just these and the cold start);
* the first call in a fresh interpreter: with the ahead-of-time module (built by ``python -m
  companion.ik``; without it the row says "numba JIT"), and on numba's JIT with its cache warm
  and empty (``ARMBRIDGE_IK_JIT=1``); and the install step itself into an empty cache.
"""

from __future__ import annotations

import argparse
import gc
import math
import os
import resource
import subprocess
import sys
import tempfile
import time
import tomllib
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

from bench.report import interpreter, md_table, write_markdown
from companion.ik import (
    DEFAULT_SETTINGS,
    METHODS,
    IKResult,
    SolverSettings,
    StopReason,
    solve,
    warm_up,
)
from companion.kinematics import rotation_angle
from companion.kinematics.arm import Arm, Pose

TOL_POS_CM = 1e-3
TOL_ORI_DEG = 1e-3
#: roboticstoolbox-python's DH zoo (``roboticstoolbox.models.DH``, rtb 1.5.0): our name → its
#: model. Every one converts to our arm model (bench/arm_references.py ``model_toml``; FK equal
#: to rtb's to 1e-15 m), so none is skipped. The 2-joint ones are measured but have no target.
ZOO = {
    "al5d": "AL5D",
    "ball": "Ball",
    "baxter": "Baxter",
    "cobra600": "Cobra600",
    "coil": "Coil",
    "hyper": "Hyper",
    "hyper3d": "Hyper3d",
    "irb140": "IRB140",
    "jaco": "Jaco",
    "kr5": "KR5",
    "lwr4": "LWR4",
    "mico": "Mico",
    "orion5": "Orion5",
    "p8": "P8",
    "panda": "Panda",
    "planar2": "Planar2",
    "planar3": "Planar3",
    "puma560": "Puma560",
    "sawyer": "Sawyer",
    "stanford": "Stanford",
    "twolink": "TwoLink",
    "ur10": "UR10",
    "ur3": "UR3",
    "ur5": "UR5",
}
ARMS = ["paper_arm", *ZOO]
#: The arms the solver's settings were tuned on (seeds 0-99); the others were not looked at
#: while tuning.
TUNING_ARMS = ("paper_arm", "puma560", "ur5", "panda", "stanford", "orion5")
#: rtb ``ik_LM`` tolerances tried (its residual E = ½·eᵀe, metres and radians: 1e-3 cm alone is
#: E = 5e-11): the loosest that still meets our criterion as often as 1e-12 is used.
RTB_TOLS = (1e-12, 5e-11, 1e-10)
#: The ratio targets: ours/rtb CPU time at the median and p99, by number of joints.
TARGET_5_PLUS = 0.33
TARGET_3_4 = 0.5

Call = Callable[[], np.ndarray]  # a prepared call: returns joints in our units (rad, cm)


def judge(arm: Arm, target: Pose, q: np.ndarray | None) -> bool:
    if q is None or q.shape != (arm.dof,) or not np.all(np.isfinite(q)):
        return False
    if not arm.within_limits(q, 1e-9):
        return False
    t = arm.fk_matrix(q)
    pos = float(np.linalg.norm(t[:3, 3] - target.position_cm))
    ori = math.degrees(float(rotation_angle(target.rotation, t[:3, :3])))
    return pos <= TOL_POS_CM and ori <= TOL_ORI_DEG


def random_targets(arm: Arm, count: int, rng: np.random.Generator) -> list[Pose]:
    return [Pose.from_matrix(t) for t in arm.fk_batch(arm.random_q_rad(rng, count))]


def limit_targets(arm: Arm, count: int, rng: np.random.Generator) -> list[Pose]:
    """Every joint within 0.5° (0.5 cm for a slider) of its lower or upper limit."""
    margin = np.where(arm.revolute, math.radians(0.5), 0.5)
    at_upper = rng.random((count, arm.dof)) < 0.5
    inward = rng.random((count, arm.dof)) * margin
    q = np.where(at_upper, arm.upper_q - inward, arm.lower_q + inward)
    return [Pose.from_matrix(t) for t in arm.fk_batch(q)]


def rtb_robot(name: str, arm: Arm) -> Any:
    import roboticstoolbox as rtb

    if name in ZOO:
        return getattr(rtb.models.DH, ZOO[name])()
    links = []
    for j in arm.joints:  # the default arm: revolute, standard DH, no tool
        links.append(
            rtb.RevoluteDH(
                d=j.d_cm / 100.0,
                a=j.a_cm / 100.0,
                alpha=j.alpha_rad,
                offset=j.offset_rad,
                qlim=[j.min_rad, j.max_rad],
            )
        )
    return rtb.DHRobot(links, name=name)


def load_arm(name: str) -> Arm:
    """The default arm from its file; a zoo arm converted from rtb's model (metres, its
    limits, ±180° where it has none: the limits its ``ik_LM`` applies)."""
    if name in ZOO:
        from bench.arm_references import model_toml

        return Arm.from_dict(tomllib.loads(model_toml(ZOO[name], name)), source=ZOO[name])
    return Arm.from_package_file(f"{name}.toml")


def prepare_ours(
    arm: Arm,
    target: Pose,
    seed: int,
    budget_ms: float,
    settings: SolverSettings = DEFAULT_SETTINGS,
    results: list[IKResult] | None = None,
) -> Call:
    def call() -> np.ndarray:
        res = solve(arm, target, budget_ms=budget_ms, seed=seed, settings=settings)
        if results is not None:
            results.append(res)
        return res.q_rad

    return call


def prepare_rtb(arm: Arm, ets: Any, target: Pose, seed: int, tol: float = 1e-12) -> Call:
    tep = target.as_matrix()
    tep[:3, 3] /= 100.0  # cm -> m
    lo, hi = ets.qlim[0], ets.qlim[1]
    q0 = lo + np.random.default_rng(seed).random(lo.size) * (hi - lo)
    to_ours = np.where(arm.revolute, 1.0, 100.0)  # rtb's slider in m

    def call() -> np.ndarray:
        return np.asarray(ets.ik_LM(tep, q0=q0, tol=tol, joint_limits=True).q) * to_ours

    return call


# 8 MB, more than the development machine's L1 and L2 (1 MB a core), less than its L3 (32 MB,
# shared): touching a float in every 64-byte line of it evicts what the solvers had in L1 and
# L2, code as well as data (L2 holds both), as a daemon that does other work between solves.
_SWEEP = np.zeros(8 * 2**20 // 8)


def cache_sweep() -> None:
    """Touch (read and write) every cache line of an 8 MB buffer (about 1 ms)."""
    _SWEEP[::8] += 1.0


def _switches() -> int:
    """Context switches of this thread so far, voluntary and involuntary (Linux)."""
    r = resource.getrusage(resource.RUSAGE_THREAD)
    return r.ru_nvcsw + r.ru_nivcsw


def timed(call: Call, sweep: bool = False) -> tuple[np.ndarray, float, float, bool]:
    """``call``'s joints, thread CPU and wall time in ms, and whether this thread was switched
    out meanwhile (its context-switch counts read before and after, outside the timed region:
    a switch between a count and a clock is counted too, never missed)."""
    if sweep:
        cache_sweep()  # outside the timed region
    before = _switches()
    w, c = time.perf_counter(), time.thread_time()
    q = call()
    cpu = time.thread_time() - c
    wall = time.perf_counter() - w
    return q, cpu * 1e3, wall * 1e3, _switches() != before


def rtb_tolerance(arm: Arm, ets: Any, poses: list[Pose], seed: int) -> tuple[float, str]:
    """The loosest of :data:`RTB_TOLS` at which rtb's ``ik_LM`` still meets our success
    criterion on at least as many of ``poses`` as at 1e-12, and a note of the counts."""
    counts = {}
    for tol in RTB_TOLS:
        counts[tol] = sum(
            judge(arm, t, prepare_rtb(arm, ets, t, seed + k, tol)()) for k, t in enumerate(poses)
        )
    chosen = max(t for t in RTB_TOLS if counts[t] >= counts[RTB_TOLS[0]])
    note = ", ".join(f"{t:g}: {counts[t]}" for t in RTB_TOLS)
    return chosen, note


def interleaved(
    name: str,
    arm: Arm,
    poses: list[Pose],
    budget_ms: float,
    seed: int,
    methods: list[str],
    ets: Any = None,
    rtb_tol: float = 1e-12,
    sweep: bool = False,
) -> list[dict[str, Any]]:
    """Each method of ours and rtb on every pose, taking turns pose by pose (in an order
    shuffled for each pose), all in this thread: a worker thread per solver measured 10-15 µs
    more CPU time per call for ours and for rtb alike (the thread woken on another core,
    cold). The solver keeps a workspace per (arm, settings) in the thread, so each method
    keeps its arrays and estimates from one pose to the next, as a daemon would. One row per
    solver."""
    peers = list(methods) + (["rtb"] if ets is not None else [])
    # Every figure goes into arrays made beforehand, for both peers. Each of our results is
    # handed out of the timed call and dropped after what the table reads of it is recorded,
    # as a daemon drops each result. Kept, every solve grew the heap by its result (~1.5 KB):
    # the first touch of each new page, a page fault, fell in the timed call of 9 % of hyper's
    # solves (~7 µs each). Lists of floats grew it too (~100 bytes a pose): a fault in 2 % of
    # hyper's solves, enough to set a p99.
    n = len(poses)
    stats: dict[str, dict[str, np.ndarray]] = {
        who: {
            "ok": np.zeros(n, dtype=bool),
            "cpu": np.zeros(n),
            "wall": np.zeros(n),
            "switched": np.zeros(n, dtype=bool),
        }
        for who in peers
    }
    last: dict[str, list[IKResult]] = {m: [] for m in methods}
    de_gen = {m: np.zeros(len(poses), dtype=bool) for m in methods}
    lm_its = {m: np.zeros(len(poses)) for m in methods}
    de_gain = {m: np.zeros(len(poses), dtype=bool) for m in methods}
    stops: dict[str, list[StopReason | None]] = {m: [None] * len(poses) for m in methods}
    for m in methods:  # each method's workspace is made before the clock starts
        prepare_ours(arm, poses[0], 0, budget_ms, METHODS[m])()
    # The order is shuffled pose by pose: a fixed rotation would always run the same solver
    # right after rtb (which leaves the caches coldest), and a method's median came out 10-20 %
    # higher for that alone.
    order = np.random.default_rng(seed)
    gc.collect()
    gc.freeze()
    gc.disable()
    try:
        for k, target in enumerate(poses):
            calls = {
                m: prepare_ours(arm, target, seed + k, budget_ms, METHODS[m], last[m])
                for m in methods
            }
            if ets is not None:
                calls["rtb"] = prepare_rtb(arm, ets, target, seed + k, rtb_tol)
            for i in order.permutation(len(peers)):
                who = peers[i]
                q, cpu_ms, wall_ms, was_switched = timed(calls[who], sweep)
                if who in last:
                    res = last[who].pop()
                    de_gen[who][k] = res.generations > res.restarts
                    lm_its[who][k] = res.lm_iterations
                    de_gain[who][k] = res.de_improvements > 0
                    stops[who][k] = res.stop_reason
                    del res
                s = stats[who]
                s["ok"][k] = judge(arm, target, q)
                s["cpu"][k] = cpu_ms
                s["wall"][k] = wall_ms
                s["switched"][k] = was_switched
    finally:
        gc.enable()
        gc.unfreeze()
    rtb_cpu = stats["rtb"]["cpu"] if ets is not None else None
    rows = []
    for who in peers:
        s = stats[who]
        cpu, wall, switched = s["cpu"], s["wall"], s["switched"]
        row: dict[str, Any] = {
            "arm": name,
            "dof": arm.dof,
            "solver": who if who != "rtb" else f"rtb ik_LM tol {rtb_tol:g}",
            "poses": len(poses),
            "ok %": 100.0 * float(np.mean(s["ok"])),
            "cpu med": float(np.median(cpu)),
            "cpu p99": float(np.percentile(cpu, 99)),
            "switched %": 100.0 * float(np.mean(switched)),
            "cpu p99 unswitched": _p99(cpu[~switched]),
            "cpu med unswitched": float(np.median(cpu[~switched])),
            "cpu med switched": float(np.median(cpu[switched])) if switched.any() else math.nan,
            "wall med": float(np.median(wall)),
            "wall p99": float(np.percentile(wall, 99)),
        }
        if rtb_cpu is not None:
            row["ratio med"] = row["cpu med"] / float(np.median(rtb_cpu))
            row["ratio p99"] = row["cpu p99"] / float(np.percentile(rtb_cpu, 99))
            rtb_unswitched = _p99(rtb_cpu[~stats["rtb"]["switched"]])
            row["ratio p99 unswitched"] = row["cpu p99 unswitched"] / rtb_unswitched
        if who in last:
            row["DE gen %"] = 100.0 * float(np.mean(de_gen[who]))
            row["DE gain %"] = 100.0 * float(np.mean(de_gain[who]))
            # Whether the slowest calls did more search than the rest, or the same work slower.
            slowest = np.argsort(cpu)[-max(1, len(poses) // 50) :]
            row["LM its med, all / slowest 2 %"] = (
                f"{np.median(lm_its[who]):g} / {np.median(lm_its[who][slowest]):g}"
            )
            failed = [i for i, good in enumerate(s["ok"]) if not good]
            row["failures: stop, wall/cpu ms"] = (
                ", ".join(f"{_stop(stops[who][i])} {wall[i]:.1f}/{cpu[i]:.2f}" for i in failed[:3])
                or "–"
            )
        rows.append(row)
    return rows


#: What runs just before a timed call in :func:`context_costs` (its table's rows).
CONTEXTS = (
    "itself",
    "the other peer",
    "judge",
    "next calls built",
    "all three (as interleaved)",
    "8 MB sweep",
)


def context_costs(
    name: str, arm: Arm, poses: list[Pose], budget_ms: float, seed: int, ets: Any, rtb_tol: float
) -> list[dict[str, Any]]:
    """What the interleaved tables' surroundings cost each peer: every call of both peers timed
    right after one of :data:`CONTEXTS` (the same peer's previous pose: as warm as a tight loop;
    the other peer's call; :func:`judge`'s numpy FK; building a pose's two calls, as
    :func:`interleaved` does before each pose; all three, in that order; an 8 MB
    :func:`cache_sweep` after the same peer's previous pose). Peer and context take turns
    pose by pose in a shuffled order, so the machine's drift hits every cell alike. Also the
    floor: the two clock reads of :func:`timed` with nothing between them, after the same
    contexts. One row per context: medians and p90 of thread CPU time, ms."""
    calls = {
        "ours": [
            prepare_ours(arm, t, seed + k, budget_ms, DEFAULT_SETTINGS) for k, t in enumerate(poses)
        ],
        "rtb": [prepare_rtb(arm, ets, t, seed + k, rtb_tol) for k, t in enumerate(poses)],
    }
    other = {"ours": "rtb", "rtb": "ours"}
    zero = np.zeros(arm.dof)

    def before(context: str, who: str, k: int) -> None:
        if context in ("itself", "8 MB sweep"):
            calls[who][k - 1]()
            if context == "8 MB sweep":
                cache_sweep()
            return
        if context in ("next calls built", "all three (as interleaved)"):
            prepare_ours(arm, poses[k], seed + k, budget_ms, DEFAULT_SETTINGS)
            prepare_rtb(arm, ets, poses[k], seed + k, rtb_tol)
        if context in ("the other peer", "all three (as interleaved)"):
            calls[other[who]][k]()
        if context in ("judge", "all three (as interleaved)"):
            judge(arm, poses[k], zero)

    cells = [(who, c) for c in CONTEXTS for who in ("ours", "rtb", "floor")]
    # In arrays made beforehand, as in :func:`interleaved` (lists of floats grow the heap).
    times = {cell: np.zeros(len(poses) - 1) for cell in cells}
    order = np.random.default_rng(seed)
    gc.collect()
    gc.freeze()
    gc.disable()
    try:
        for k in range(1, len(poses)):
            for i in order.permutation(len(cells)):
                who, context = cells[i]
                before(context, "ours" if who == "floor" else who, k)
                if who == "floor":
                    c = time.thread_time()
                    times[who, context][k - 1] = (time.thread_time() - c) * 1e3
                else:
                    times[who, context][k - 1] = timed(calls[who][k])[1]
    finally:
        gc.enable()
        gc.unfreeze()
    rows = []
    for context in CONTEXTS:
        ours, rtb, floor = (times[who, context] for who in ("ours", "rtb", "floor"))
        rows.append(
            {
                "arm": name,
                "just before the call": context,
                "ours cpu med": float(np.median(ours)),
                "ours cpu p90": float(np.percentile(ours, 90)),
                "rtb cpu med": float(np.median(rtb)),
                "rtb cpu p90": float(np.percentile(rtb, 90)),
                "ratio med": float(np.median(ours) / np.median(rtb)),
                "clocks alone med": float(np.median(floor)),
            }
        )
    return rows


def _p99(values: np.ndarray) -> float:
    return float(np.percentile(values, 99)) if values.size else math.nan


def _stop(reason: StopReason | None) -> str:
    return reason.value if reason is not None else "?"


#: The two ways of counting the budget compared beside the hog. "wall budget": the CPU clock is
#: the wall clock and the ceiling out of reach, i.e. the budget counted in wall time, as the
#: solver did before it counted CPU time. "CPU budget": the solver's own (``time.thread_time``),
#: with the wall-clock ceiling ``--ceiling-ms`` (default: the solver's, 4 x the budget).
HOG_MODES = ("wall budget", "CPU budget")


def hog_compare(
    name: str,
    arm: Arm,
    poses: list[Pose],
    budget_ms: float,
    seed: int,
    ceiling_ms: float | None,
    nice: int = 0,
) -> list[dict]:
    """Ours with one busy process per core beside it, the budget counted in wall time and in
    CPU time, interleaved pose by pose (the order alternating). Each way runs on a thread of
    its own, so each keeps its own estimates from one solve to the next, as a daemon would.
    ``nice``: the solving threads' niceness (the hogs keep 0): at 19 a thread gets about a
    tenth of a core beside a busy one, as on a machine with ten times the hogs, without
    taking more CPU from anything else on it."""
    kwargs: dict[str, dict[str, Any]] = {
        "wall budget": {"cpu_clock": time.perf_counter, "ceiling_ms": 1e9},
        "CPU budget": {"ceiling_ms": ceiling_ms},
    }
    workers = {mode: ThreadPoolExecutor(1) for mode in HOG_MODES}
    stats: dict[str, dict[str, list]] = {
        mode: {"ok": [], "cpu": [], "wall": [], "reason": []} for mode in HOG_MODES
    }

    def one(mode: str, k: int, target: Pose) -> None:
        w, c = time.perf_counter(), time.thread_time()
        res = solve(arm, target, budget_ms=budget_ms, seed=seed + k, **kwargs[mode])
        cpu = (time.thread_time() - c) * 1e3
        wall = (time.perf_counter() - w) * 1e3
        s = stats[mode]
        s["cpu"].append(cpu)
        s["wall"].append(wall)
        s["ok"].append(judge(arm, target, res.q_rad))
        s["reason"].append(res.stop_reason)

    for mode in HOG_MODES:  # each worker thread loads its workspace before the clock starts
        workers[mode].submit(solve, arm, poses[0], budget_ms=budget_ms, seed=0).result()
        # Linux: a thread's own niceness (setpriority on the calling thread).
        workers[mode].submit(os.nice, nice).result()
    hogs = [
        subprocess.Popen([sys.executable, "-c", "while True: pass"])
        for _ in range(os.cpu_count() or 1)
    ]
    try:
        gc.collect()
        gc.freeze()
        gc.disable()
        for k, target in enumerate(poses):
            order = HOG_MODES if k % 2 == 0 else HOG_MODES[::-1]
            for mode in order:
                workers[mode].submit(one, mode, k, target).result()
    finally:
        gc.enable()
        gc.unfreeze()
        for h in hogs:
            h.kill()
            h.wait()
        for worker in workers.values():
            worker.shutdown()
    rows = []
    for mode in HOG_MODES:
        s = stats[mode]
        ok, cpu, wall, reasons = s["ok"], s["cpu"], s["wall"], s["reason"]
        failed = [i for i, good in enumerate(ok) if not good]
        rows.append(
            {
                "arm": name,
                "budget": mode,
                "poses": len(poses),
                "failed": len(failed),
                "ok %": 100.0 * float(np.mean(ok)),
                "cpu med": float(np.median(cpu)),
                "wall med": float(np.median(wall)),
                "wall p99": float(np.percentile(wall, 99)),
                "wall max": float(np.max(wall)),
                "wall > budget, ok": sum(
                    w > budget_ms and good for w, good in zip(wall, ok, strict=True)
                ),
                "deadline stops": sum(r is StopReason.DEADLINE for r in reasons),
                "ceiling stops": sum(r is StopReason.CEILING for r in reasons),
                "failures: stop, wall/cpu ms": ", ".join(
                    f"{reasons[i].value} {wall[i]:.1f}/{cpu[i]:.2f}" for i in failed[:5]
                )
                or "–",
            }
        )
    return rows


def path_poses(arm: Arm, kind: str, samples: int) -> list[Pose]:
    """A hand path sampled at 100 Hz: a 5 cm circle or a 10 × 5 cm figure-eight, 2 s long,
    orientation held, around a comfortable pose of the default arm (elbow bent)."""
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
    """Ours along a path, each solve started from the previous solution (the daemon's way)."""
    poses = path_poses(arm, kind, 200) * laps
    q_prev = np.array(solve(arm, poses[0], budget_ms=1e3, seed=0).q_deg)
    # In arrays made beforehand, as in :func:`interleaved` (lists of floats grow the heap).
    cpu, ok, steps = (
        np.zeros(len(poses) - 1),
        np.zeros(len(poses) - 1, dtype=bool),
        np.zeros(len(poses) - 1),
    )
    gc.collect()
    gc.freeze()
    gc.disable()
    try:
        for k, target in enumerate(poses[1:], start=1):
            c = time.thread_time()
            res = solve(arm, target, budget_ms=budget_ms, seed=k, q_start_deg=q_prev)
            cpu[k - 1] = (time.thread_time() - c) * 1e3
            ok[k - 1] = judge(arm, target, res.q_rad)
            steps[k - 1] = np.abs(np.array(res.q_deg) - q_prev).max()
            q_prev = np.array(res.q_deg)
    finally:
        gc.enable()
        gc.unfreeze()
    return {
        "path": f"100 Hz {kind} ({laps} laps)",
        "poses": len(cpu),
        "ok %": 100.0 * float(np.mean(ok)),
        "cpu med": float(np.median(cpu)),
        "cpu p99": float(np.percentile(cpu, 99)),
        "max joint step deg": float(steps.max()),
    }


def overrun_row(arm: Arm, budget_ms: float, count: int, seed: int) -> dict:
    """Unreachable targets (orientation turned 90–180° off, or positions beyond reach) must
    come back by the budget: wall time minus budget."""
    rng = np.random.default_rng(seed)
    over = []
    for k, target in enumerate(random_targets(arm, count, rng)):
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
    return {
        "budget ms": budget_ms,
        "targets": count,
        "median overrun ms": float(np.median(over)),
        "max overrun ms": float(np.max(over)),
    }


def first_call(cache_dir: str | None, without_scipy: bool = False, jit: bool = False) -> dict:
    """Import, ``ik.warm_up()`` and the first solve in a fresh interpreter; ``cache_dir`` forces
    numba's cache there (an empty one: the first run ever). ``without_scipy``: as installed on
    a board, where scipy (a bench extra) is absent; numba imports it when it is there, on its
    first call (~0.3 s more), to find a BLAS. ``jit``: ignore the ahead-of-time module
    (``ARMBRIDGE_IK_JIT=1``); otherwise it is used where ``python -m companion.ik`` built it."""
    code = (
        ("import sys; sys.modules['scipy'] = None\n" if without_scipy else "")
        + "import sys, time; t0 = time.perf_counter()\n"
        "from companion.kinematics import Arm\n"
        "from companion import ik\n"
        "t1 = time.perf_counter(); warm_s = ik.warm_up()\n"
        "arm = Arm.default(); target = arm.fk([10, 80, 20, 10, 20, 30])\n"
        "t2 = time.perf_counter(); r = ik.solve(arm, target, seed=0)\n"
        "t3 = time.perf_counter()\n"
        "print(t1 - t0, warm_s, t3 - t2, t3 - t0, time.process_time(), 'numba' in sys.modules,"
        " ik.kernels_origin() != 'numba JIT')\n"
    )
    env = dict(os.environ)
    if cache_dir is not None:
        env["NUMBA_CACHE_DIR"] = cache_dir
    env.pop("ARMBRIDGE_IK_JIT", None)
    if jit:
        env["ARMBRIDGE_IK_JIT"] = "1"
    out = subprocess.run(
        [sys.executable, "-c", code], env=env, check=True, capture_output=True, text=True
    ).stdout.split()
    return {
        "kernels": "ahead of time" if out[6] == "True" else "numba JIT",
        "numba imported": out[5] == "True",
        "import s": float(out[0]),
        "warm_up() s": float(out[1]),
        "first solve ms": float(out[2]) * 1e3,
        "start to solved s": float(out[3]),
        "process CPU s": float(out[4]),
    }


def install_compile(cache_dir: str) -> dict:
    """The install step, ``python -P -m companion.ik``, into an empty ``NUMBA_CACHE_DIR``: the
    ahead-of-time module (where a C compiler is found) and the keep-out kernel's JIT cache.
    CPU is the child's and its compiler's (``RUSAGE_CHILDREN``)."""
    env = dict(os.environ, NUMBA_CACHE_DIR=cache_dir)
    env.pop("ARMBRIDGE_IK_JIT", None)
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    started = time.perf_counter()
    out = subprocess.run(
        [sys.executable, "-P", "-m", "companion.ik"],
        env=env,
        check=True,
        capture_output=True,
        text=True,
        cwd=tempfile.gettempdir(),
    )
    wall_s = time.perf_counter() - started
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu_s = (after.ru_utime + after.ru_stime) - (before.ru_utime + before.ru_stime)
    return {
        "step": "python -P -m companion.ik, empty cache",
        "ahead-of-time module built": "compiled ahead of time" in out.stdout,
        "wall s": wall_s,
        "CPU s": cpu_s,
    }


def table(rows: list[dict]) -> list[str]:
    keys = list(dict.fromkeys(k for r in rows for k in r))
    return md_table(
        keys,
        [[r.get(k, "") for k in keys] for r in rows],
        cell=lambda v: f"{v:.3g}" if isinstance(v, float) else str(v),
    )


#: What the tables compare (static text at the top of the report).
METHODS_NOTE = [
    "Methods (companion.ik.METHODS; the solver module's docstring has the details): "
    "**restarts**, the default: Levenberg–Marquardt (LM) from the best of NP = 4 fresh random "
    "draws, again and again, no DE generation; **memetic**: DE rand/1/bin generations (NP 6, "
    "F 0.5, Cr 0.3) each followed by LM on the best, the population drawn anew after 2 "
    "generations without improvement; **de**: the papers' DE (rand/1/bin, F 0.9, Cr 0.95, "
    "NP 12), no LM, a restart after 50 generations without improvement. Restarts is the "
    "default because no setting of the DE searches did less work (tuning arms and seeds: "
    "memetic's median about equal or up to a fifth higher, its p99 up to 40 % higher; its DE "
    "generations lower the population's best cost in a few % of solves, DE gain % below).",
]


def run_conditions() -> list[str]:
    """What the shared header (``report.write_markdown``: command, commit, date, machine, load
    when written) leaves out: the interpreter and numpy, and the load average at the start."""
    load = ", ".join(f"{v:.2f}" for v in os.getloadavg())
    return [
        f"- {interpreter()}",
        f"- load average at the start (1, 5, 15 min): {load}",
    ]


def target_rows(main_rows: list[dict], sweep_rows: list[dict], method: str) -> list[dict]:
    """Per arm, ``method`` against the issue's targets, without and with the cache sweep."""
    out = []
    swept = {r["arm"]: r for r in sweep_rows if r["solver"] == method}
    for r in main_rows:
        if r["solver"] != method or "ratio med" not in r:
            continue
        limit = TARGET_5_PLUS if r["dof"] >= 5 else TARGET_3_4 if r["dof"] >= 3 else math.nan
        row = {
            "arm": r["arm"],
            "dof": r["dof"],
            "target": limit,
            "ratio med": r["ratio med"],
            "ratio p99": r["ratio p99"],
        }
        s = swept.get(r["arm"])
        if s is not None:
            row["swept ratio med"] = s["ratio med"]
            row["swept ratio p99"] = s["ratio p99"]
        # The target is on the four ratios above; the ones over the calls that were not
        # switched out stand beside them, for reading the tail, not for the verdict.
        ratios = [v for k, v in row.items() if "ratio" in k]
        row["ratio p99 unswitched"] = r["ratio p99 unswitched"]
        if s is not None:
            row["swept ratio p99 unswitched"] = s["ratio p99 unswitched"]
        row["ours switched %"] = r["switched %"]
        row["ours cpu med, unswitched / switched"] = (
            f"{r['cpu med unswitched'] * 1e3:.0f} / {r['cpu med switched'] * 1e3:.0f} µs"
        )
        row["ours ok %"] = r["ok %"]
        row["met"] = "–" if math.isnan(limit) else "yes" if max(ratios) <= limit else "no"
        out.append(row)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--poses", type=int, default=1000)
    parser.add_argument("--limit-poses", type=int, default=200)
    parser.add_argument("--hog-poses", type=int, default=300)
    parser.add_argument("--budget-ms", type=float, default=20.0)
    parser.add_argument("--seed", type=int, default=2026)
    parser.add_argument("--arms", default=",".join(ARMS))
    parser.add_argument("--no-cold-start", action="store_true")
    parser.add_argument("--laps", type=int, default=5, help="laps of each warm path (0: none)")
    parser.add_argument(
        "--only-extras", action="store_true", help="only warm paths, overrun and cold start"
    )
    parser.add_argument(
        "--only-hog",
        action="store_true",
        help="only the rows beside the CPU hog (--hog-poses random poses per arm)",
    )
    parser.add_argument(
        "--ceiling-ms",
        type=float,
        help="the CPU budget's wall-clock ceiling beside the hog (default: the solver's, 4 x "
        "the budget; the daemon's is its control period, 50 ms at 20 Hz)",
    )
    parser.add_argument(
        "--nice",
        type=int,
        default=0,
        help="niceness of the solving threads beside the hog (19: about a tenth of a core)",
    )
    parser.add_argument(
        "--methods",
        default=",".join(METHODS),
        help="our search methods to compare (names of companion.ik.METHODS; the first is "
        "the one the target table is for)",
    )
    parser.add_argument(
        "--sweep-poses",
        type=int,
        default=None,
        help="poses per arm measured again with an 8 MB cache sweep between solves "
        "(default: --poses; 0: none)",
    )
    parser.add_argument("--tol-poses", type=int, default=300, help="poses to choose rtb's tol")
    parser.add_argument(
        "--method-poses",
        type=int,
        default=300,
        help="poses per arm of the method table (every --methods interleaved with rtb; the "
        "target, sweep and limit tables run the first method alone beside rtb)",
    )
    parser.add_argument(
        "--busy",
        type=int,
        default=0,
        help="busy-loop processes beside the interleaved tables (the issue's targets are for a "
        "machine at load >= 2: on 2 cores, 1)",
    )
    parser.add_argument(
        "--context-poses",
        type=int,
        default=0,
        help="poses per arm of the table of what runs before a timed call costs each peer "
        "(0: none; needs rtb)",
    )
    parser.add_argument("--markdown", type=Path)
    args = parser.parse_args()

    try:
        import roboticstoolbox  # noqa: F401

        peer = True
    except ImportError:
        peer = False
    warm_up()
    methods = args.methods.split(",")
    for m in methods:
        if m not in METHODS:
            parser.error(f"--methods: {m!r} is not one of {', '.join(METHODS)}")
    sweep_poses = args.poses if args.sweep_poses is None else args.sweep_poses
    names = [] if args.only_extras else args.arms.split(",")
    for n in names:
        if n not in ARMS:
            parser.error(f"--arms: {n!r} is not one of {', '.join(ARMS)}")
    started = time.perf_counter()
    lines = ["# IK solver: ours against roboticstoolbox ik_LM (bench/solver.py)", ""]
    lines += run_conditions()
    main_rows: list[dict] = []
    sweep_rows: list[dict] = []
    limit_rows: list[dict] = []
    hog_rows: list[dict] = []
    tol_rows: list[dict] = []
    method_rows: list[dict] = []
    context_rows: list[dict] = []
    arms = {n: load_arm(n) for n in names}
    hog_poses: dict[str, list[Pose]] = {}
    busy = [
        subprocess.Popen([sys.executable, "-c", "while True: pass"])
        for _ in range(0 if args.only_hog else args.busy)
    ]
    try:
        for n, arm in arms.items():
            rng = np.random.default_rng([args.seed, ARMS.index(n)])
            poses = random_targets(arm, max(args.poses, args.hog_poses), rng)
            hog_poses[n] = poses[: args.hog_poses]
            if args.only_hog:
                continue
            poses = poses[: args.poses]
            ets, tol = None, 1e-12
            if peer:
                ets = rtb_robot(n, arm).ets()
                tol_poses = random_targets(arm, args.tol_poses, rng)
                tol, note = rtb_tolerance(arm, ets, tol_poses, args.seed + 10**6)
                tol_rows.append({"arm": n, "chosen tol": f"{tol:g}", "successes by tol": note})
            first = methods[:1]
            rows = interleaved(n, arm, poses, args.budget_ms, args.seed, first, ets, tol)
            main_rows += rows
            print(table(rows[:1])[-1], flush=True)
            if sweep_poses:
                swept = poses[:sweep_poses]
                sweep_rows += interleaved(
                    n, arm, swept, args.budget_ms, args.seed, first, ets, tol, True
                )
                print(table(sweep_rows[-len(rows) :])[-1], flush=True)
            if args.limit_poses:
                at_limits = limit_targets(arm, args.limit_poses, rng)
                limit_rows += interleaved(
                    n, arm, at_limits, args.budget_ms, args.seed, first, ets, tol
                )
            if ets is not None and args.context_poses:
                context_rows += context_costs(
                    n, arm, poses[: args.context_poses + 1], args.budget_ms, args.seed, ets, tol
                )
            if len(methods) > 1 and args.method_poses:
                method_rows += interleaved(
                    n, arm, poses[: args.method_poses], args.budget_ms, args.seed, methods, ets, tol
                )
    finally:
        for h in busy:
            h.kill()
            h.wait()
    load_main = ", ".join(f"{v:.2f}" for v in os.getloadavg())
    for n, arm in arms.items():
        if args.hog_poses:
            hog_rows += hog_compare(
                n,
                arm,
                hog_poses[n],
                args.budget_ms,
                args.seed,
                args.ceiling_ms,
                args.nice,
            )
    load = ", ".join(f"{v:.2f}" for v in os.getloadavg())
    lines += [
        f"- busy-loop processes beside the interleaved tables: {args.busy}; load average at "
        f"their end: {load_main}; at the end: {load}; {time.perf_counter() - started:.0f} s",
        f"- budget {args.budget_ms} ms; seed {args.seed}; success = pos ≤ {TOL_POS_CM} cm and "
        f"ori ≤ {TOL_ORI_DEG}° and within limits (our numpy FK, for every solver); times in "
        "ms, CPU = thread CPU time; ratio = ours/rtb CPU time (median/median, p99/p99)",
        f"- settings tuned on seeds 0–99 and the arms {', '.join(TUNING_ARMS)}; every other "
        "arm, and this seed, were not used to tune",
        "",
    ]
    lines += METHODS_NOTE + [""]
    if main_rows and peer:
        lines += [
            f"Targets ({methods[0]}, the default method, against rtb ik_LM): ratio ≤ "
            f"{TARGET_5_PLUS} at the median and p99 on arms of ≥ 5 joints, ≤ {TARGET_3_4} on "
            "3–4 joints, without and with an 8 MB cache sweep between solves:",
            "",
        ]
        lines += table(target_rows(main_rows, sweep_rows, methods[0])) + [""]
        lines += ["rtb's tolerance per arm (successes of the calibration poses at each):", ""]
        lines += table(tol_rows) + [""]
    if main_rows:
        lines += [
            f"Random reachable poses, {methods[0]} interleaved pose by pose with rtb ik_LM (C++, "
            "limits on, tol as above). DE gen % = solves in which at least one DE generation "
            "(not a restart) ran; DE gain % = solves in which one lowered the population's "
            "best cost:"
        ]
        lines += [""] + table(main_rows) + [""]
    if sweep_rows:
        lines += ["The same, with an 8 MB cache sweep before every solve (outside the timing):"]
        lines += [""] + table(sweep_rows) + [""]
    if method_rows:
        lines += [
            f"Every method (the first {args.method_poses} poses of each arm), all of them and "
            "rtb taking turns pose by pose (each call is colder than beside rtb alone, so the "
            "times run higher than above, for rtb too):",
            "",
        ]
        lines += table(method_rows) + [""]
    if context_rows:
        lines += [
            f"What runs just before a timed call, and what it costs each peer (the first "
            f"{args.context_poses} poses of each arm, ours the default method; every peer and "
            "context taking turns pose by pose in a shuffled order; 'itself': the same peer's "
            "call on the previous pose, as warm as a tight loop; 'clocks alone': the two clock "
            "reads of a timed call with nothing between them, after the same context, a cost "
            "inside every timed call of both peers):",
            "",
        ]
        lines += table(context_rows) + [""]
    if limit_rows:
        lines += ["Joints-at-limits poses (every joint within 0.5° of a limit):", ""]
        lines += table(limit_rows) + [""]
    if hog_rows:
        lines += [
            "Ours (the default method) beside a CPU hog (one busy process per core), the "
            "budget counted in wall time and in CPU time (ceiling "
            f"{f'{args.ceiling_ms} ms' if args.ceiling_ms else 'the solver default, 4 × budget'}"
            f"), solving threads at nice {args.nice}, interleaved:",
            "",
        ]
        lines += table(hog_rows) + [""]
    if not peer:
        lines.append("rtb not installed: pip install -e '.[bench]'")
    if args.laps and not args.only_hog:
        default = Arm.default()
        warm = [warm_row(default, k, args.budget_ms, args.laps) for k in ("circle", "figure-eight")]
        lines += ["Ours, warm, along paths of the default arm (start = previous solution):", ""]
        lines += table(warm) + [""]
        over = [overrun_row(default, b, 200, args.seed) for b in (1.0, args.budget_ms)]
        lines += ["Budget overrun on unreachable targets, default arm (wall − budget):", ""]
        lines += table(over) + [""]
    if not (args.no_cold_start or args.only_hog):
        with tempfile.TemporaryDirectory() as empty, tempfile.TemporaryDirectory() as install:
            start = [
                dict(cache="ahead-of-time module (python -m companion.ik)", **first_call(None)),
                dict(cache="numba cache warm", **first_call(None, jit=True)),
                dict(
                    cache="numba cache warm, no scipy (a board without the module)",
                    **first_call(None, True, jit=True),
                ),
                dict(cache="empty numba cache (first run ever)", **first_call(empty, jit=True)),
            ]
            compiled = [install_compile(install)]
        lines += ["First call after import (fresh interpreter):", ""] + table(start) + [""]
        lines += ["The install step (kernels compiled ahead of time):", ""] + table(compiled)
    text = "\n".join(lines)
    print(text)
    if args.markdown:
        write_markdown(args.markdown, text + "\n")


if __name__ == "__main__":
    main()
