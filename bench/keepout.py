"""Keep-out bench: adversarial configurations, motions and targets against the example quad;
every command the checks let through is re-checked by an independent dense sampling.

    .venv/bin/python -m bench.keepout [--configurations 100000] [--motions 100000]
                                      [--targets 2000] [--seed 2026] [--markdown FILE]
                                      [--soft-margin-cm 3 (0: the cost term off)]

The vehicle is the example config's 450 quad (``devkit.keepout.QUAD_450``) with the
papers' arm hanging 10 cm under the body origin, margin 1 cm. A *colliding command* is one the
checks accept although a dense sampling finds a capsule closer than the margin. The target is 0.
Configurations (and the answers to targets) are sampled independently of the checked code:
points every ≤ 0.31 cm along each capsule's axis, exact point-to-volume distances written apart
(``devkit/keepout.py``). Motions are sampled at 200 configurations along the motion with
the exact clearances (the compiled ones, which the configuration run and the tests validate):
what is tested there is the motion logic, the speed bound and the halving.

* configurations: uniform in the joint limits, half of them then pulled to the boundary of the
  margin (a bisection in joint space between an accepted and a refused one), where a wrong
  distance would show first;
* motions: from an accepted configuration to a random one at most 5° away per joint (a control
  tick or a few), or anywhere (a whole move), a third each; plus motions between two accepted
  configurations on either side of a volume;
* targets: hand positions of refused (colliding) configurations and points in and around the
  volumes, solved by ``solve_clear`` (position mode, 20 ms budget) warm from the park pose; its
  answer and the motion from park (64 configurations along it) are sampled independently; with
  the verdicts, the clearance of each clear answer (its least over the (link, volume) pairs the
  joints change), the time and the thread CPU per target, with the cost term
  (``--soft-margin-cm``) or without it (0).

It also prints the check times: thread CPU µs per :meth:`KeepOut.check`, per
:meth:`KeepOut.check_motion` of one 50 Hz tick and per configuration of a batch.
"""

from __future__ import annotations

import argparse
import gc
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from bench.report import interpreter, machine, md_table, write_markdown
from companion.ik import TargetMode, warm_up
from companion.ik.keepout import SOFT_MARGIN_CM, ClearVerdict, solve_clear
from companion.kinematics.arm import Arm, Pose
from companion.kinematics.collision import KeepOut
from companion.kinematics.vehicle import Mount, invert
from devkit.keepout import QUAD_450, sampled_clearance

MARGIN_CM = 1.0
PARK_DEG = (0.0, 90.0, 0.0, 0.0, 0.0, 0.0)
POINTS = 100  # samples per capsule axis: ≤ 30.2 / 99 ≈ 0.31 cm apart
CHUNK = 2000
DEFAULT_MARKDOWN = Path(__file__).resolve().parent / "results" / "keepout.md"


def _cpu_us(fn: Callable[[], object], repeat: int) -> float:
    """Median thread CPU µs of ``fn`` over ``repeat`` calls in 5 rounds."""
    rounds = []
    for _ in range(5):
        t = time.thread_time()
        for _ in range(repeat):
            fn()
        rounds.append((time.thread_time() - t) / repeat * 1e6)
    return float(np.median(rounds))


def _bad(ko: KeepOut, q: np.ndarray) -> np.ndarray:
    """Per configuration: the independent sampling finds a capsule inside the margin."""
    out = np.zeros(len(q), dtype=bool)
    for i in range(0, len(q), CHUNK):
        out[i : i + CHUNK] = sampled_clearance(ko, q[i : i + CHUNK], POINTS) < MARGIN_CM - 1e-9
    return out


def _boundary(ko: KeepOut, good: np.ndarray, bad: np.ndarray, steps: int = 20) -> np.ndarray:
    """Configurations on the margin's boundary: bisect each (accepted, refused) pair."""
    lo, hi = good.copy(), bad.copy()
    for _ in range(steps):
        mid = 0.5 * (lo + hi)
        ok = ko.clear_mask(mid)
        lo[ok], hi[~ok] = mid[ok], mid[~ok]
    return lo  # the accepted side


def configurations(ko: KeepOut, rng: np.random.Generator, count: int) -> dict:
    arm = ko.arm
    q = arm.random_q_rad(rng, count)
    ok = np.concatenate([ko.clear_mask(q[i : i + CHUNK]) for i in range(0, count, CHUNK)])
    half = count // 2
    goods, bads = q[ok], q[~ok]
    pairs = min(half, len(goods), len(bads))
    edge = _boundary(
        ko, goods[rng.integers(len(goods), size=pairs)], bads[rng.integers(len(bads), size=pairs)]
    )
    q = np.concatenate([q[: count - pairs], edge])
    ok = np.concatenate([ok[: count - pairs], np.ones(pairs, dtype=bool)])
    colliding = int((_bad(ko, q[ok])).sum())
    return {
        "checked": count,
        "accepted": int(ok.sum()),
        "on the margin": pairs,
        "colliding": colliding,
    }


def motions(ko: KeepOut, rng: np.random.Generator, count: int) -> dict:
    arm = ko.arm
    pool = arm.random_q_rad(rng, 4 * count)
    pool = pool[ko.clear_mask(pool)]
    starts = pool[rng.integers(len(pool), size=count)]
    ends = arm.random_q_rad(rng, count)
    kind = rng.integers(0, 3, size=count)
    near = np.clip(
        starts + rng.uniform(-1, 1, starts.shape) * np.radians(5.0), arm.lower_q, arm.upper_q
    )
    ends = np.where((kind == 0)[:, None], near, ends)
    across = pool[rng.integers(len(pool), size=count)]  # clear to clear, often across a volume
    ends = np.where((kind == 2)[:, None], across, ends)
    accepted = colliding = unproven = 0
    s = np.linspace(0.0, 1.0, 200)[:, None]
    for q0, q1 in zip(starts, ends, strict=True):
        hit = ko.check_motion(q0, q1)
        if hit is not None:
            unproven += not hit.proven
            continue
        accepted += 1
        colliding += int(ko.clearances(q0 + s * (q1 - q0)).min() < MARGIN_CM - 1e-9)
    return {
        "checked": count,
        "accepted": accepted,
        "refused unproven": unproven,
        "colliding": colliding,
    }


def targets(
    ko: KeepOut, rng: np.random.Generator, count: int, soft_margin_cm: float = SOFT_MARGIN_CM
) -> dict:
    arm = ko.arm
    to_base = invert(ko.mount.matrix)
    q = arm.random_q_rad(rng, 8 * count)
    refused = q[~ko.clear_mask(q)][: count // 2]
    goals = [Pose.from_matrix(arm.fk_matrix(qq)) for qq in refused]
    # Points in and around the volumes (6 cm spread about their centres), base frame.
    while len(goals) < count:
        v = QUAD_450[int(rng.integers(len(QUAD_450)))]
        center = np.asarray(getattr(v, "center_cm", getattr(v, "from_cm", (0, 0, 0))), float)
        point = center + rng.normal(0, 6.0, 3)
        p = to_base[:3, :3] @ point + to_base[:3, 3]
        goals.append(Pose(float(p[0]), float(p[1]), float(p[2]), 0.0, 0.0, 0.0))
    verdicts: dict[str, int] = {}
    colliding = 0
    times = []
    q_park = arm.q_from_user(PARK_DEG)
    s = np.linspace(0.0, 1.0, 64)[:, None]
    cpu = []
    clearance = []  # per CLEAR answer: the least clearance of a link that moves it (cm)
    moving = _moving_pairs(ko)
    for i, goal in enumerate(goals):
        started = time.thread_time()
        out = solve_clear(
            ko, goal, budget_ms=20.0, seed=i, q_start_deg=PARK_DEG, mode=TargetMode.POSITION,
            tol_pos_cm=0.05, soft_margin_cm=soft_margin_cm,
        )  # fmt: skip
        cpu.append(time.thread_time() - started)
        times.append(out.elapsed_ms)
        verdicts[out.verdict.value] = verdicts.get(out.verdict.value, 0) + 1
        if out.result is not None:
            q1 = out.result.q_rad
            colliding += int(_bad(ko, q_park + s * (q1 - q_park)).any())
            if out.verdict is ClearVerdict.CLEAR:
                clearance.append(float(ko.clearances(q1[None])[0][moving].min()))
    t = np.array(times)
    c = np.array(clearance) if clearance else np.full(1, np.nan)
    return {
        "solved": count,
        **{f"{v.value}": verdicts.get(v.value, 0) for v in ClearVerdict},
        "colliding": colliding,
        "clearance cm p5": float(np.percentile(c, 5)),
        "p25": float(np.percentile(c, 25)),
        "p50": float(np.percentile(c, 50)),
        f"< {MARGIN_CM + 2:g} cm": int((c < MARGIN_CM + 2).sum()),
        "ms p50": float(np.percentile(t, 50)),
        "ms p99": float(np.percentile(t, 99)),
        "CPU ms mean": float(np.mean(cpu) * 1e3),
    }


def _moving_pairs(ko: KeepOut) -> np.ndarray:
    """``(C, V)``: the (capsule, volume) pairs whose clearance the joints change (the arm's
    first links pass the body at a fixed distance, which would hide every other one)."""
    c = ko.clearances(ko.arm.random_q_rad(np.random.default_rng(0), 2000))
    return np.asarray(c.max(axis=0) - c.min(axis=0) > 1e-6)


def timings(ko: KeepOut, rng: np.random.Generator) -> dict:
    arm = ko.arm
    q = arm.q_from_user(PARK_DEG)
    tick = q + np.radians(60.0 / 50.0)  # one 50 Hz tick at the example's 60 deg/s
    batch = arm.random_q_rad(rng, 1000)
    return {
        "check (µs)": _cpu_us(lambda: ko.check(q), 300),
        "check_motion, one tick (µs)": _cpu_us(lambda: ko.check_motion(q, tick), 300),
        "batch, per configuration (µs)": _cpu_us(lambda: ko.clear_mask(batch), 3) / 1000,
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--configurations", type=int, default=100_000)
    parser.add_argument("--motions", type=int, default=100_000)
    parser.add_argument("--targets", type=int, default=2000)
    parser.add_argument("--seed", type=int, default=2026)
    parser.add_argument(
        "--soft-margin-cm",
        type=float,
        default=SOFT_MARGIN_CM,
        help="solve_clear's cost term (0: off, the search before it)",
    )
    parser.add_argument("--markdown", type=Path, default=DEFAULT_MARKDOWN)
    args = parser.parse_args(argv)
    rng = np.random.default_rng(args.seed)
    ko = KeepOut(Arm.default(), QUAD_450, Mount(), MARGIN_CM)
    warm_up()
    gc.freeze()
    started = time.perf_counter()
    rows = []
    for name, fn, n in (
        ("configurations", configurations, args.configurations),
        ("motions", motions, args.motions),
        ("targets", targets, args.targets),
    ):
        if n > 0:
            result = targets(ko, rng, n, args.soft_margin_cm) if fn is targets else fn(ko, rng, n)
            rows.append((name, result))
            print(name, result, flush=True)
    times = timings(ko, rng)
    print(times, flush=True)
    lines = [
        "# Keep-out bench",
        "",
        f"{machine()}; {interpreter()}; seed {args.seed}; soft margin {args.soft_margin_cm:g} "
        f"cm; {time.perf_counter() - started:.0f} s.",
        "",
    ]
    for name, result in rows:
        lines += [f"## {name}", "", *md_table(list(result), [list(result.values())]), ""]
    lines += ["## check times (thread CPU)", "", *md_table(list(times), [list(times.values())])]
    text = "\n".join(lines) + "\n"
    print(text)
    write_markdown(args.markdown, text)
    total = sum(r["colliding"] for _, r in rows)
    return 0 if total == 0 else 1


if __name__ == "__main__":
    raise SystemExit(main())
