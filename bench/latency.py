"""End-to-end latency on UDP loopback: target in → servo commands at the flight controller → ACK.

    python -m bench.latency [--targets 1000] [--dialects ardupilot px4] [--input mavlink|control]
                            [--budget-ms 20] [--rate-hz 20] [--gap-ms 50] [--seed 0]
                            [--markdown bench/results/latency.md] [--no-plot]

The daemon (``armbridge run``) and the simulated flight controller (``python -m sim_servo``)
run as subprocesses on UDP loopback (see ``bench/loopback.py``). Targets are reachable poses
(FK of joints drawn uniformly within the arm's limits, seeded), sent one at a time: the next
goes out a random 0…``gap_ms`` (seeded) after the previous answer, so targets land at random
phases of the daemon's control tick. The joint speed limit is at the config's maximum,
1000 °/s (it was 1e6 °/s, "out of the way", before the config bounded it): a target's first
servo update (ardupilot: a DO_SET_SERVO per output whose PWM changed, each waiting for its ACK;
with random targets that is all 6; px4: 1 DO_SET_ACTUATOR) is what is timed, but a long move
now takes further updates on the following ticks, which the next target may have to wait for.
Everything else is the shipped default config.

Per target, all on CLOCK_MONOTONIC (client, daemon timing, simulator event log):

* ``→ servos``: target sent → the simulator handled the last servo command of its update;
* ``→ ACK``: target sent → the answer (ACCEPTED) is back at the client;
* split into ``input`` (client → the daemon's input thread hands it on; for MAVLink this
  includes the autopilot routing it on its main loop), ``solve`` (IK kernel),
  ``queue`` (rest of the control thread's handling before the solve result), ``tick wait``
  (solved → first servo command started), ``first frame`` (encode + send + UDP + the autopilot's
  400 Hz main-loop wait), ``rest of update`` (ardupilot: the 5 further ACK round trips; px4: 0)
  and ``ACK back`` (last servo command handled → its ACK to the daemon → the daemon's answer
  at the client; for MAVLink, routed back by the autopilot on its main loop).

Inputs (``--input``): ``mavlink`` (default), a ground station (``sim_servo.gcs``) sending
COMMAND_LONG ``MAV_CMD_USER_1`` to the simulator's ground-station link, which routes it to the
daemon and the COMMAND_ACK back, as a real autopilot does; ``control``, ``goto`` requests on the
daemon's control socket, whose reply is the ACK.

The simulator stamps a frame when its main loop handles it (every 2.5 ms, as ArduCopter), so
``first frame`` includes up to 2.5 ms of autopilot loop wait per command.
"""

from __future__ import annotations

import argparse
import gc
import math
import sys
import time
from pathlib import Path

import numpy as np

from bench.loopback import (
    DEFAULT_INPUT,
    INPUTS,
    Stack,
    answer_one,
    load_average,
    percentiles_ms,
    plt,
    servo_command_times,
)
from bench.report import machine, md_table, write_markdown
from companion.kinematics.arm import Arm, Pose

ROOT = Path(__file__).resolve().parent.parent
SEGMENTS = ("input", "solve", "queue", "tick wait", "first frame", "rest of update", "ACK back")
TOTALS = ("→ servos", "→ ACK")


def targets(arm: Arm, count: int, seed: int) -> list[Pose]:
    q = arm.random_q_rad(np.random.default_rng(seed), count)
    return [Pose.from_matrix(t) for t in arm.fk_batch(q)]


def run_dialect(dialect: str, poses: list[Pose], args: argparse.Namespace) -> dict:
    daemon = {
        "solver": {"budget_ms": args.budget_ms, "seed": args.seed},
        "control": {"rate_hz": args.rate_hz},
        "arm": {"joint_speed_deg_s": 1000.0},  # the config's maximum (the fastest servos)
    }
    rng = np.random.default_rng(args.seed + 1)
    records = []
    with Stack(dialect=dialect, daemon=daemon) as stack:
        source = INPUTS[args.input](stack)
        gc.collect()
        gc.freeze()
        gc.disable()  # the client's collector must not stall its own clock readings
        try:
            for pose in poses:
                time.sleep(rng.uniform(0.0, args.gap_ms / 1e3))
                records.append(answer_one(source, pose.as_tuple()))
        finally:
            gc.enable()
            source.close()
        events = stack.stop()
    sim_s = servo_command_times(events)
    rows = []
    bad_count = 0
    for rec in records:
        if rec["outcome"] != "accepted":
            continue
        lo, hi = np.searchsorted(sim_s, [rec["sent_s"], rec["answered_s"]])
        window = sim_s[lo:hi]
        if len(window) == 0:
            bad_count += 1
            continue
        t = rec["timing"]
        solve_s = rec["solve_ms"] / 1e3
        rows.append({
            "input": t["received_s"] - rec["sent_s"],
            "solve": solve_s,
            "queue": t["solved_s"] - t["received_s"] - solve_s,
            "tick wait": t["first_out_s"] - t["solved_s"],
            "first frame": window[0] - t["first_out_s"],
            "rest of update": window[-1] - window[0],
            "ACK back": rec["answered_s"] - window[-1],
            "→ servos": window[-1] - rec["sent_s"],
            "→ ACK": rec["answered_s"] - rec["sent_s"],
            "commands": len(window),
        })  # fmt: skip
    outcomes: dict[str, int] = {}
    for rec in records:
        outcomes[rec["outcome"]] = outcomes.get(rec["outcome"], 0) + 1
    return {"dialect": dialect, "rows": rows, "outcomes": outcomes, "unmatched": bad_count}


def report(results: list[dict], args: argparse.Namespace, load_before: str) -> list[str]:
    target_ms = args.budget_ms + 5.0
    lines = [
        "# End-to-end latency on UDP loopback",
        "",
        f"`{' '.join(['python -m bench.latency', *sys.argv[1:]])}` on {machine()}; "
        f"load average (1, 5, 15 min) before: {load_before}, after: {load_average()}.",
        "",
        f"Daemon: shipped defaults (budget {args.budget_ms:g} ms, control {args.rate_hz:g} Hz) "
        f"with the joint speed limit at its maximum, 1000 °/s; input: {INPUTS[args.input].name}; "
        f"{args.targets} reachable targets (seed {args.seed}), one at a time, 0–{args.gap_ms:g} ms "
        "apart. Issue 8's target: p99 ≤ budget + 5 ms = "
        f"{target_ms:g} ms.",
        "",
    ]
    rows = []
    for r in results:
        for total in TOTALS:
            p50, p99, mx = percentiles_ms([row[total] for row in r["rows"]])
            rows.append([r["dialect"], f"target {total}", len(r["rows"]), p50, p99, mx,
                         "yes" if p99 <= target_ms else "**no**"])  # fmt: skip
    lines += md_table(["dialect", "latency", "targets", "p50 ms", "p99 ms", "max ms",
                       f"p99 ≤ {target_ms:g} ms"], rows)  # fmt: skip
    lines += ["", "Split (ms, p50 / p99 / max):", ""]
    rows = []
    for r in results:
        row = [r["dialect"]]
        for seg in SEGMENTS:
            p50, p99, mx = percentiles_ms([x[seg] for x in r["rows"]])
            row.append(f"{p50:.2f} / {p99:.2f} / {mx:.2f}")
        rows.append(row)
    lines += md_table(["dialect", *SEGMENTS], rows)
    lines += ["", "Outcomes: " + "; ".join(
        f"{r['dialect']}: {r['outcomes']}"
        + f"; servo commands per target {np.mean([x['commands'] for x in r['rows']]):.2f}"
        + (f", {r['unmatched']} without a servo command at the sim" if r["unmatched"] else "")
        for r in results)]  # fmt: skip
    return lines


def plot(results: list[dict], path: Path) -> None:
    fig, (hist, cdf) = plt.subplots(1, 2, figsize=(10, 3.8))
    for r in results:
        for total, style in zip(TOTALS, ("-", "--"), strict=True):
            ms = np.sort(np.array([row[total] for row in r["rows"]]) * 1e3)
            if ms.size == 0:
                continue
            label = f"{r['dialect']} {total}"
            hist.hist(ms, bins=60, histtype="step", label=label)
            cdf.plot(ms, np.arange(1, ms.size + 1) / ms.size, style, label=label)
    hist.set_xlabel("latency (ms)")
    hist.set_ylabel("targets")
    cdf.set_xlabel("latency (ms)")
    cdf.set_ylabel("fraction of targets")
    cdf.grid(True, alpha=0.3)
    hist.legend(fontsize=7)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--targets", type=int, default=1000)
    parser.add_argument(
        "--dialects", nargs="+", default=["ardupilot", "px4"], choices=["ardupilot", "px4"]
    )
    parser.add_argument("--input", choices=sorted(INPUTS), default=DEFAULT_INPUT)
    parser.add_argument("--budget-ms", type=float, default=20.0)
    parser.add_argument("--rate-hz", type=float, default=20.0)
    parser.add_argument(
        "--gap-ms", type=float, default=50.0, help="random pause 0..GAP before each target (seeded)"
    )
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--markdown", type=Path, default=ROOT / "bench/results/latency.md")
    parser.add_argument("--no-plot", action="store_true")
    args = parser.parse_args()

    load_before = load_average()
    poses = targets(Arm.default(), args.targets, args.seed)
    results = [run_dialect(d, poses, args) for d in args.dialects]
    lines = report(results, args, load_before)
    if plt is not None and not args.no_plot:
        png = args.markdown.with_suffix(".png")
        plot(results, png)
        lines += ["", f"![latency CDF]({png.name})"]
    elif plt is None:
        lines += ["", "(No PNG: matplotlib is not installed; it is the optional `plots` extra.)"]
    text = "\n".join(lines) + "\n"
    print(text)
    write_markdown(args.markdown, text)
    return 0 if all(math.isfinite(len(r["rows"])) for r in results) else 1


if __name__ == "__main__":
    raise SystemExit(main())
