"""End-to-end latency on UDP loopback: target in → servo commands at the flight controller → ACK.

    python -m bench.latency [--targets 300] [--dialects ardupilot px4] [--input mavlink|control]
                            [--budget-ms 20] [--rate-hz 20] [--gap-ms 50] [--seed 0]
                            [--old-core DIR] [--markdown bench/results/latency.md] [--no-plot]

The default run (300 targets per dialect) takes about 45 s; ``--targets 1000`` is the full-size
run (about 2 min).

For each dialect the daemon (``armbridge run``) and the simulated flight controller
(``python -m sim_servo``, ArduCopter's link timing by default) run as subprocesses on UDP
loopback (see ``bench/loopback.py``). Both dialects' stacks run at once and get the same
targets, interleaved: target i goes to one stack and then to the other, the order alternating,
so that both see the same machine at the same time. Targets are reachable poses (FK of joints
drawn uniformly within the arm's limits, seeded), sent one at a time: each goes out a random
0…``gap_ms`` (seeded) after the previous answer, so targets land at random phases of the
daemon's control tick. The joint speed limit is at the config's maximum, 1000 °/s: a long move
takes further updates on the following ticks, and the next target may arrive while one of them
is in flight (it then waits for it: "tick wait"). Everything else is the shipped default config.

A servo update is the changed outputs' commands sent back-to-back (ardupilot: one DO_SET_SERVO
per output whose PWM changed since the autopilot acknowledged it, with random targets usually
all 6; px4: one DO_SET_ACTUATOR), then their COMMAND_ACKs counted; one update is in flight at a
time. The target's **first** update is what is timed: its servo commands are those the
simulator handled between the daemon starting the update (``timing.first_out_s``) and having all
its ACKs (``timing.acked_s``).

Per target, all on CLOCK_MONOTONIC (client, daemon ``Reply.timing`` / status
``last_target.timing``, simulator event log):

* ``→ servos``: target sent → the simulator handled the last servo command of its first update;
* ``→ last servo ACK``: the daemon received the target (``received_s``) → it had the
  last ACK of the target's first update (``acked_s``): the daemon's own share, without the way
  in and the answer's way out;
* ``→ ACK``: target sent → the answer (ACCEPTED) is back at the client;
* split into ``input`` (client → the daemon's input thread hands it on; for MAVLink this
  includes the autopilot routing it), ``solve`` (IK kernel), ``queue`` (rest of the control
  thread's handling before the solve result), ``tick wait`` (solved → first servo command
  started: an update still in flight, else ~0), ``first frame`` (encode + send + UDP + the
  autopilot's 400 Hz main-loop wait), ``rest of update`` (the update's first → last command
  handled: ardupilot's further DO_SET_SERVO, back-to-back; px4: 0), ``ACKs in`` (last command
  handled → the daemon has its ACK: the autopilot's link timing) and ``answer out`` (the
  daemon has the ACKs → the answer is at the client; for MAVLink, routed back by the autopilot).

``--old-core DIR`` adds, as peers in the same run on the same targets, a daemon run from another
checkout (e.g. an older core: ``git archive 22321ac | tar -x -C DIR``) for
each dialect, each with its own simulator: "not worse than before" is then measured on the
same simulator, the same machine and the same moment.

Also the daemon's and the simulator's CPU time (utime + stime, all threads) over the run,
beside its wall time.

Inputs (``--input``): ``mavlink`` (default), a ground station (``sim_servo.gcs``) sending
COMMAND_LONG ``MAV_CMD_USER_1`` to the simulator's ground-station link, which routes it to the
daemon and the COMMAND_ACK back, as a real autopilot does; ``control``, ``goto`` requests on the
daemon's control socket, whose reply is the ACK. Over MAVLink the daemon's timing comes from its
status after each ACK, outside the timed path, when the newest target is still the one
acknowledged.
"""

from __future__ import annotations

import argparse
import contextlib
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
    cpu_s,
    load_average,
    percentiles_ms,
    plt,
    servo_command_times,
)
from bench.report import machine, md_table, write_markdown
from companion.kinematics.arm import Arm, Pose

ROOT = Path(__file__).resolve().parent.parent
SEGMENTS = (
    "input", "solve", "queue", "tick wait", "first frame", "rest of update", "ACKs in",
    "answer out",
)  # fmt: skip
TOTALS = ("→ servos", "→ last servo ACK", "→ ACK")
#: The daemon's share (received → last ACK of the first update), p99, ardupilot.
TARGET_ARDUPILOT_P99_MS = 8.0
#: A reference px4 "→ ACK" (p50, p99 ms), measured on the simulator without its link timing
#: model: the bar "not worse" is measured against.
OLD_PX4_ACK_MS = (6.7, 8.0)
#: A tick wait longer than this: the target waited for an update in flight.
WAITED_S = 0.001


def targets(arm: Arm, count: int, seed: int) -> list[Pose]:
    q = arm.random_q_rad(np.random.default_rng(seed), count)
    return [Pose.from_matrix(t) for t in arm.fk_batch(q)]


def run(poses: list[Pose], args: argparse.Namespace) -> list[dict]:
    """Every peer's stack at once (each dialect; with ``--old-core`` each dialect again on the
    old code), the same targets interleaved; per peer the records, the simulator's servo
    command times and the CPU seconds over the run."""
    daemon = {
        "solver": {"budget_ms": args.budget_ms, "seed": args.seed},
        "control": {"rate_hz": args.rate_hz},
        "arm": {"joint_speed_deg_s": 1000.0},  # the config's maximum (the fastest servos)
    }
    rng = np.random.default_rng(args.seed + 1)
    peers = [(d, d, None) for d in args.dialects]
    if args.old_core is not None:
        peers += [(f"{d} (old core)", d, args.old_core.resolve()) for d in args.dialects]
    names = [name for name, _, _ in peers]
    records: dict[str, list[dict]] = {name: [] for name in names}
    with contextlib.ExitStack() as stacks_open:
        stacks = {
            name: stacks_open.enter_context(Stack(dialect=d, daemon=daemon, daemon_root=root))
            for name, d, root in peers
        }
        sources = {name: INPUTS[args.input](stacks[name]) for name in names}
        for name in names:
            stacks_open.callback(sources[name].close)
        pids = {name: (stacks[name].daemon_pid, stacks[name].sim_pid) for name in names}
        cpu0 = {name: (cpu_s(pids[name][0]), cpu_s(pids[name][1])) for name in names}
        gc.collect()
        gc.freeze()
        gc.disable()  # the client's collector must not stall its own clock readings
        wall0 = time.monotonic()
        try:
            for k, pose in enumerate(poses):
                for name in names if k % 2 == 0 else names[::-1]:
                    time.sleep(rng.uniform(0.0, args.gap_ms / 1e3))
                    records[name].append(answer_one(sources[name], pose.as_tuple()))
        finally:
            gc.enable()
        wall_s = time.monotonic() - wall0
        cpu = {
            name: (cpu_s(pids[name][0]) - cpu0[name][0], cpu_s(pids[name][1]) - cpu0[name][1])
            for name in names
        }
        events = {name: stacks[name].stop() for name in names}
    return [
        {
            **measure(records[name], servo_command_times(events[name])),
            "dialect": name,
            "base": d,
            "old": root is not None,
            "wall_s": wall_s,
            "daemon_cpu_s": cpu[name][0],
            "sim_cpu_s": cpu[name][1],
        }
        for name, d, root in peers
    ]


def measure(records: list[dict], sim_s: np.ndarray) -> dict:
    """Per accepted target with the daemon's timing: the segments and totals (s)."""
    rows = []
    counts = {"no timing": 0, "nothing to send": 0}
    outcomes: dict[str, int] = {}
    for rec in records:
        outcomes[rec["outcome"]] = outcomes.get(rec["outcome"], 0) + 1
        if rec["outcome"] != "accepted":
            continue
        t = rec["timing"]
        if t is None:  # MAVLink: a newer target was already the status's last one
            counts["no timing"] += 1
            continue
        if "acked_s" not in t:  # every output already held the first step: nothing sent
            counts["nothing to send"] += 1
            continue
        # One update is in flight at a time: the servo commands the autopilot handled between
        # the daemon starting this update and having all its ACKs are this update's.
        lo, hi = np.searchsorted(sim_s, [t["first_out_s"], t["acked_s"]], side="right")
        window = sim_s[lo:hi]
        if len(window) == 0:
            counts["no timing"] += 1
            continue
        solve_s = rec["solve_ms"] / 1e3
        rows.append({
            "input": t["received_s"] - rec["sent_s"],
            "solve": solve_s,
            "queue": t["solved_s"] - t["received_s"] - solve_s,
            "tick wait": t["first_out_s"] - t["solved_s"],
            "first frame": window[0] - t["first_out_s"],
            "rest of update": window[-1] - window[0],
            "ACKs in": t["acked_s"] - window[-1],
            "answer out": rec["answered_s"] - t["acked_s"],
            "→ servos": window[-1] - rec["sent_s"],
            "→ last servo ACK": t["acked_s"] - t["received_s"],
            "→ ACK": rec["answered_s"] - rec["sent_s"],
            "commands": len(window),
        })  # fmt: skip
    return {"rows": rows, "outcomes": outcomes, **counts}


def _target(r: dict, total: str, p50: float, p99: float, results: list[dict]) -> str:
    """The target's verdict for this row; beside it, the old core's figure from the same run."""
    if r["old"]:
        return ""
    verdicts = []
    if total == "→ last servo ACK" and r["base"] == "ardupilot":
        met = p99 <= TARGET_ARDUPILOT_P99_MS
        verdicts.append(f"p99 ≤ {TARGET_ARDUPILOT_P99_MS:g}: " + ("yes" if met else "**no**"))
    old = next((o for o in results if o["old"] and o["base"] == r["base"]), None)
    if old is not None:
        o50, o99, _ = percentiles_ms([row[total] for row in old["rows"]])
        worse = p50 > o50 or p99 > o99
        verdict = ("**worse**" if worse else "not worse") if r["base"] == "px4" else ""
        verdicts.append(f"old core, same run: {o50:.2f} / {o99:.2f} {verdict}".rstrip())
    elif total == "→ ACK" and r["base"] == "px4":
        old50, old99 = OLD_PX4_ACK_MS
        worse = p50 > old50 or p99 > old99
        verdicts.append(
            f"reference {old50:g} / {old99:g} (no link timing model): "
            + ("**worse**" if worse else "not worse")
        )
    return "; ".join(verdicts)


def report(results: list[dict], args: argparse.Namespace, load_before: str) -> list[str]:
    lines = [
        "# End-to-end latency on UDP loopback",
        "",
        f"`{' '.join(['python -m bench.latency', *sys.argv[1:]])}` on {machine()}; "
        f"load average (1, 5, 15 min) before: {load_before}, after: {load_average()}.",
        "",
        f"Daemon: shipped defaults (budget {args.budget_ms:g} ms, control {args.rate_hz:g} Hz) "
        f"with the joint speed limit at its maximum, 1000 °/s; simulator: ArduCopter link "
        f"timing (default); input: {INPUTS[args.input].name}; {args.targets} reachable targets "
        f"(seed {args.seed}) per dialect, one at a time, 0–{args.gap_ms:g} ms apart, the "
        "dialects' stacks running at once and the targets interleaved. Targets: "
        f"→ last servo ACK p99 ≤ {TARGET_ARDUPILOT_P99_MS:g} ms for ardupilot; px4 not worse "
        f"than the reference → ACK ({OLD_PX4_ACK_MS[0]:g} / {OLD_PX4_ACK_MS[1]:g} ms "
        "p50 / p99, measured on the simulator without its link timing model).",
        "",
    ]
    rows = []
    for r in results:
        for total in TOTALS:
            p50, p99, mx = percentiles_ms([row[total] for row in r["rows"]])
            rows.append([r["dialect"], f"target {total}", len(r["rows"]), p50, p99, mx,
                         _target(r, total, p50, p99, results)])  # fmt: skip
    lines += md_table(["dialect", "latency", "targets", "p50 ms", "p99 ms", "max ms", "target"],
                      rows)  # fmt: skip
    lines += ["", "Split (ms, p50 / p99 / max):", ""]
    rows = []
    for r in results:
        row = [r["dialect"]]
        for seg in SEGMENTS:
            p50, p99, mx = percentiles_ms([x[seg] for x in r["rows"]])
            row.append(f"{p50:.2f} / {p99:.2f} / {mx:.2f}")
        rows.append(row)
    lines += md_table(["dialect", *SEGMENTS], rows)
    lines += ["", "Per dialect:", ""]
    for r in results:
        waited = [x for x in r["rows"] if x["tick wait"] > WAITED_S]
        waited_note = ""
        if waited:
            p50, p99, mx = percentiles_ms([x["→ last servo ACK"] for x in waited])
            waited_note = (
                f" (their → last servo ACK p50 / p99 / max {p50:.2f} / {p99:.2f} / {mx:.2f} ms)"
            )
        lines.append(
            f"- {r['dialect']}: outcomes {r['outcomes']}; servo commands per first update "
            f"{np.mean([x['commands'] for x in r['rows']]):.2f}; "
            f"{len(waited)} targets waited > {WAITED_S * 1e3:g} ms for an update in flight"
            f"{waited_note}; {r['no timing']} without the daemon's timing, "
            f"{r['nothing to send']} with nothing to send; CPU over the {r['wall_s']:.1f} s run: "
            f"daemon {r['daemon_cpu_s']:.2f} s ({100 * r['daemon_cpu_s'] / r['wall_s']:.1f} %), "
            f"simulator {r['sim_cpu_s']:.2f} s ({100 * r['sim_cpu_s'] / r['wall_s']:.1f} %)"
        )
    return lines


def plot(results: list[dict], path: Path) -> None:
    fig, (hist, cdf) = plt.subplots(1, 2, figsize=(10, 3.8))
    for r in results:
        for total, style in zip(TOTALS, ("-", ":", "--"), strict=True):
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
    parser.add_argument("--targets", type=int, default=300, help="per dialect (full run: 1000)")
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
    parser.add_argument(
        "--old-core",
        type=Path,
        help="a checkout of older code whose daemon runs as a peer (e.g. git archive 22321ac)",
    )
    parser.add_argument("--markdown", type=Path, default=ROOT / "bench/results/latency.md")
    parser.add_argument("--no-plot", action="store_true")
    args = parser.parse_args()

    load_before = load_average()
    poses = targets(Arm.default(), args.targets, args.seed)
    results = run(poses, args)
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
