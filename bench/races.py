"""goto/stop races on the control socket: is every request answered, and is an answer ever
contradicted by what reaches the servos?

    python -m bench.races [--races 1000] [--dialect ardupilot] [--rate-hz 20]
                          [--joint-speed-deg-s 1000] [--seed 0]
                          [--markdown bench/results/races.md]

About 35 s with the defaults (1 000 rounds).

The daemon (``armbridge run``) and the simulated flight controller (ArduCopter link timing) run
as subprocesses on UDP loopback (``bench/loopback.py``). Each round:

1. wait until the daemon reports no motion (status ``moving`` false: no update in flight, no
   goal left), and note the simulator's servo outputs as the round starts;
2. on two connections opened once, write a ``goto`` on one and a ``stop`` on the other, one right
   after the other (microseconds apart), alternating which goes first; read both answers as
   they come (select, each timestamped).

The goto poses are a seeded random walk in joint space (each joint ±``WALK_DEG`` a step, within
its limits, through FK), so each is a real move of a few ticks at most.

**Unanswered**: no reply line within :data:`REPLY_TIMEOUT_S`, or the daemon's own "no answer"
error. Target: 0.

**Carried out after a contrary answer** (target 0). The simulator's event log (its ``servo``
events: every servo command it applied, stamped on CLOCK_MONOTONIC when its main loop handled
it) is replayed after the run; each PWM *change* on an arm output (a command whose PWM differs
from what that output held) is assigned to the round whose window contains it: from the
round's first write to the next round's first write (which comes only after the daemon
reported no motion, so the window covers everything the round caused, including an update
still in flight when the stop was answered). Then per round:

* goto answered anything but ACCEPTED (CANCELLED, FAILED, …): **no** PWM change at all in the
  window — a contrary answer carried out if there is one. The check does not need the goto's
  solution (a CANCELLED reply has none): nothing else can move the arm in that window, since the
  previous round's motion had ended and the stop moves nothing;
* goto answered ACCEPTED: every PWM change in the window must lie between the output's PWM at
  the round's start and the PWM of the goto's solution (``solve.q_deg`` in the reply, through
  the daemon's calibration), within 1 µs. A change anywhere else is counted too ("move off the
  accepted path"): it would be a move towards some other goal, e.g. a late step from an earlier
  round showing up in this one's window;
* informational: ACCEPTED with no PWM change at all; and the stop's position in time (answered
  before or after the goto).

A change that a faulty daemon sent late enough to fall in a following round's window is still
caught there, unless that round's goto was ACCEPTED and the stray PWM happens to lie between
that round's start and goal on every output it touched.
"""

from __future__ import annotations

import argparse
import gc
import math
import select
import sys
import time
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np

from bench.loopback import Stack, cpu_s, load_average, percentiles_ms, run_and_report
from bench.report import machine, md_table
from companion.daemon.config import load_config
from companion.daemon.service import SOURCE_RATE_HZ
from companion.kinematics.arm import Arm, Pose
from devkit.control_client import ControlConnection
from devkit.timing import wait_until

ROOT = Path(__file__).resolve().parent.parent
REPLY_TIMEOUT_S = 10.0
#: Rounds start at most this often: the daemon rate-limits motion targets per source
#: (``SOURCE_RATE_HZ``, burst ``SOURCE_BURST``); faster, most gotos would be refused as rate
#: limited before they could race anything (766 of 1 000 rounds were, unpaced).
ROUND_MIN_S = 1.0 / (0.9 * SOURCE_RATE_HZ)
IDLE_TIMEOUT_S = 10.0
WALK_DEG = 15.0
PWM_SLACK_US = 1


def walk(arm: Arm, start_deg: np.ndarray, count: int, seed: int) -> list[Pose]:
    """A seeded random walk in joint space from ``start_deg``: the FK poses of its steps."""
    rng = np.random.default_rng(seed)
    lo, hi = np.degrees(arm.lower_rad), np.degrees(arm.upper_rad)
    q = np.array(start_deg, dtype=float)
    poses = []
    for _ in range(count):
        q = np.clip(q + rng.uniform(-WALK_DEG, WALK_DEG, arm.dof), lo, hi)
        poses.append(arm.fk(list(q)))
    return poses


def race(
    goto: ControlConnection, stop: ControlConnection, pose: Pose, goto_first: bool
) -> dict[str, Any]:
    """One round's two writes and their answers."""
    rec: dict[str, Any] = {"goto_first": goto_first}
    writes = [
        ("goto", goto, {"cmd": "goto", "pose": list(pose.as_tuple())}),
        ("stop", stop, {"cmd": "stop"}),
    ]
    if not goto_first:
        writes.reverse()
    for name, conn, obj in writes:
        rec[f"{name}_sent_s"] = conn.send(obj)
    pending = {"goto": goto, "stop": stop}
    deadline = time.monotonic() + REPLY_TIMEOUT_S
    while pending and (left := deadline - time.monotonic()) > 0:
        ready, _, _ = select.select([c.sock for c in pending.values()], [], [], left)
        now = time.monotonic()
        for name, conn in list(pending.items()):
            if conn.sock in ready and (reply := conn.try_reply()) is not None:
                rec[f"{name}_reply"] = reply
                rec[f"{name}_answered_s"] = now
                del pending[name]
    for name in pending:
        rec[f"{name}_reply"] = None
    return rec


def outcome(reply: dict[str, Any] | None) -> str:
    if reply is None:
        return "unanswered"
    if "outcome" in reply:
        return str(reply["outcome"])
    return "unanswered" if "no answer" in str(reply.get("error")) else "error"


def servo_changes(events: list[dict[str, Any]], initial: dict[int, int], outputs: set[int]):
    """Each servo command that changed an arm output's PWM: (monotonic s, output, from, to)."""
    t0 = next(e for e in events if e["event"] == "start")["monotonic_s"]
    held = dict(initial)
    changes = []
    for e in events:
        if e["event"] != "servo" or e["output"] not in outputs:
            continue
        if e["pwm_us"] != held.get(e["output"]):
            changes.append((t0 + e["t_s"], e["output"], held.get(e["output"]), e["pwm_us"]))
            held[e["output"]] = e["pwm_us"]
    return changes


def judge(
    rounds: list[dict[str, Any]], changes: list, initial: dict[int, int], calibration: Any
) -> None:
    """Assign the PWM changes to rounds and judge each round (fields added in place)."""
    starts = [min(r["goto_sent_s"], r["stop_sent_s"]) for r in rounds]
    held = dict(initial)
    for r in rounds:
        r["changes"] = []
    changes = sorted(changes)
    i = 0
    for k, start_s in enumerate(starts):
        while i < len(changes) and changes[i][0] < start_s:
            _, output, _, new = changes[i]
            held[output] = new
            if k > 0:
                rounds[k - 1]["changes"].append(changes[i][1:])
            i += 1
        rounds[k]["pwm_at_start"] = dict(held)
    for change in changes[i:]:
        rounds[-1]["changes"].append(change[1:])
    for r in rounds:
        r["goto_outcome"] = outcome(r["goto_reply"])
        r["stop_outcome"] = outcome(r["stop_reply"])
        r["contrary"] = r["goto_outcome"] != "accepted" and bool(r["changes"])
        r["off_path"] = []
        r["reached"] = False
        if r["goto_outcome"] == "accepted":
            goal = calibration.angles_to_pwm_us(r["goto_reply"]["solve"]["q_deg"])
            end = dict(r["pwm_at_start"])
            end.update({output: new for output, _, new in r["changes"]})
            r["reached"] = all(abs(end.get(o, -1) - pwm) <= PWM_SLACK_US for o, pwm in goal.items())
            for output, old, new in r["changes"]:
                start = r["pwm_at_start"].get(output)
                if not start:  # the output's first pulses ever (0: none): no start to be between
                    continue
                lo, hi = sorted((start, goal[output]))
                if not lo - PWM_SLACK_US <= new <= hi + PWM_SLACK_US:
                    r["off_path"].append((output, start, goal[output], old, new))


def self_test(calibration: Any) -> bool:
    """The judge flags an injected contrary move and an off-path move, and passes clean ones."""
    q = [0.0, 90.0, 0.0, 0.0, 0.0, 0.0]
    start = calibration.angles_to_pwm_us(q)
    goal = calibration.angles_to_pwm_us([10.0, 80.0, 5.0, 0.0, 0.0, 0.0])
    o = min(start)
    step = (start[o] + goal[o]) // 2

    def rounds() -> list[dict[str, Any]]:
        base = {"goto_first": True, "stop_reply": {"outcome": "accepted"}}
        return [
            {**base, "goto_sent_s": 1.0, "stop_sent_s": 1.0,
             "goto_reply": {"outcome": "cancelled"}},
            {**base, "goto_sent_s": 2.0, "stop_sent_s": 2.0,
             "goto_reply": {"outcome": "accepted", "solve": {"q_deg": [10, 80, 5, 0, 0, 0]}}},
        ]  # fmt: skip

    clean = rounds()
    judge(clean, [(2.5, o, start[o], step)], start, calibration)
    contrary = rounds()
    judge(contrary, [(1.5, o, start[o], step)], start, calibration)
    off = rounds()
    judge(off, [(2.5, o, start[o], max(start[o], goal[o]) + 5)], start, calibration)
    return (
        not any(r["contrary"] or r["off_path"] for r in clean)
        and contrary[0]["contrary"]
        and bool(off[1]["off_path"])
    )


def run(args: argparse.Namespace) -> dict[str, Any]:
    arm = Arm.default()
    daemon = {
        "solver": {"seed": args.seed},
        "control": {"rate_hz": args.rate_hz},
        "arm": {"joint_speed_deg_s": args.joint_speed_deg_s},
    }
    with Stack(dialect=args.dialect, daemon=daemon) as stack:
        calibration = load_config(stack.config_path).calibration
        judge_works = self_test(calibration)
        outputs = {j.output for j in calibration.joints}
        assert stack.sim is not None
        initial = {int(o): v["pwm_us"] for o, v in stack.sim.state()["outputs"].items()}
        current = np.array(stack.status()["current_deg"])
        poses = walk(arm, current, args.races, args.seed)
        goto_conn, stop_conn = (
            ControlConnection(stack.control_path, timeout_s=REPLY_TIMEOUT_S) for _ in range(2)
        )
        rounds: list[dict[str, Any]] = []
        idle_timeouts = 0
        cpu0 = (cpu_s(stack.daemon_pid), cpu_s(stack.sim_pid))
        gc.collect()
        gc.freeze()
        gc.disable()
        wall0 = time.monotonic()
        try:
            next_round_s = time.monotonic()
            for k, pose in enumerate(poses):
                if not wait_until(lambda: not stack.status()["moving"], IDLE_TIMEOUT_S):
                    idle_timeouts += 1
                while (now := time.monotonic()) < next_round_s:
                    time.sleep(next_round_s - now)  # pacing, not synchronisation
                next_round_s = now + ROUND_MIN_S
                rounds.append(race(goto_conn, stop_conn, pose, goto_first=k % 2 == 0))
            wait_until(lambda: not stack.status()["moving"], IDLE_TIMEOUT_S)
            time.sleep(0.5)  # a stray late command would still be logged
        finally:
            gc.enable()
            goto_conn.close()
            stop_conn.close()
        wall_s = time.monotonic() - wall0
        cpu = (cpu_s(stack.daemon_pid) - cpu0[0], cpu_s(stack.sim_pid) - cpu0[1])
        counters = stack.status()["counters"]
        events = stack.stop()
        log = Path(stack.daemon_log).read_text(errors="replace")
    judge(rounds, servo_changes(events, initial, outputs), initial, calibration)
    return {
        "rounds": rounds,
        "idle_timeouts": idle_timeouts,
        "wall_s": wall_s,
        "cpu_daemon_s": cpu[0],
        "cpu_sim_s": cpu[1],
        "counters": counters,
        "tracebacks": log.count("Traceback"),
        "judge_works": judge_works,
    }


def report(out: dict[str, Any], args: argparse.Namespace, load_before: str) -> list[str]:
    rounds = out["rounds"]
    unanswered = sum(r[f"{n}_outcome"] == "unanswered" for r in rounds for n in ("goto", "stop"))
    contrary = [r for r in rounds if r["contrary"]]
    off_path = [r for r in rounds if r["off_path"]]
    lines = [
        "# goto/stop races on the control socket",
        "",
        f"`{' '.join(['python -m bench.races', *sys.argv[1:]])}` on {machine()}; load average "
        f"(1, 5, 15 min) before: {load_before}, after: {load_average()}.",
        "",
        f"{len(rounds)} rounds ({args.dialect}, control {args.rate_hz:g} Hz, joint speed "
        f"{args.joint_speed_deg_s:g} °/s, seed {args.seed}): a goto and a stop written on two "
        "connections microseconds apart, alternating which first. Wall "
        f"{out['wall_s']:.1f} s; CPU daemon {out['cpu_daemon_s']:.2f} s, simulator "
        f"{out['cpu_sim_s']:.2f} s.",
        "",
        f"- **Unanswered**: {unanswered} (target 0).",
        f"- **Carried out after a contrary answer** (goto not ACCEPTED, yet a PWM change at the "
        f"simulator in its round): {len(contrary)} (target 0).",
        f"- Moves off the accepted path (goto ACCEPTED, a PWM change not between the round's "
        f"start and the goto's solution): {len(off_path)}.",
        "- The check's self-test (an injected PWM change in a CANCELLED round, and one off the "
        "path of an ACCEPTED round, are flagged; a step on the path is not): "
        + ("passed" if out["judge_works"] else "**FAILED**")
        + ".",
        f"- Rounds that waited > {IDLE_TIMEOUT_S:g} s for the daemon to stop moving: "
        f"{out['idle_timeouts']}; tracebacks in the daemon's log: {out['tracebacks']}.",
        "",
    ]
    rows = []
    for goto_first in (True, False):
        group = [r for r in rounds if r["goto_first"] == goto_first]
        counts = Counter(r["goto_outcome"] for r in group)
        for goto_outcome, n in sorted(counts.items()):
            sub = [r for r in group if r["goto_outcome"] == goto_outcome]
            stop_first = sum(
                r.get("stop_answered_s", math.inf) < r.get("goto_answered_s", math.inf) for r in sub
            )
            moved = sum(bool(r["changes"]) for r in sub)
            reached = sum(r["reached"] for r in sub)
            goto_ms = percentiles_ms([r["goto_answered_s"] - r["goto_sent_s"] for r in sub
                                      if "goto_answered_s" in r])  # fmt: skip
            stop_ms = percentiles_ms([r["stop_answered_s"] - r["stop_sent_s"] for r in sub
                                      if "stop_answered_s" in r])  # fmt: skip
            rows.append([
                "goto" if goto_first else "stop", goto_outcome, n, stop_first, moved, reached,
                sum(bool(r["contrary"]) for r in sub), sum(bool(r["off_path"]) for r in sub),
                f"{goto_ms[0]:.1f} / {goto_ms[1]:.1f} / {goto_ms[2]:.1f}",
                f"{stop_ms[0]:.1f} / {stop_ms[1]:.1f} / {stop_ms[2]:.1f}",
            ])  # fmt: skip
    lines += md_table(
        ["written first", "goto answered", "rounds", "stop answered first", "arm moved",
         "arm at the goto's solution",
         "contrary", "off path", "goto answer ms p50/p99/max", "stop answer ms p50/p99/max"],
        rows,
    )  # fmt: skip
    messages = Counter(
        (r["goto_outcome"], (r["goto_reply"] or {}).get("message", "")) for r in rounds
    )
    lines += ["", "goto answers: " + "; ".join(f"{o} «{m}» ×{n}" for (o, m), n in
                                                 messages.most_common())]  # fmt: skip
    lines += ["", "Daemon counters at the end: " + ", ".join(
        f"{k} {v}" for k, v in out["counters"].items() if v)]  # fmt: skip
    for r in (contrary + off_path)[:10]:
        lines.append(
            f"- round at {r['goto_sent_s']:.3f}: goto {r['goto_outcome']} "
            f"({(r['goto_reply'] or {}).get('message')}), stop {r['stop_outcome']}, changes "
            f"{r['changes']}, off path {r['off_path']}"
        )
    return lines


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--races", type=int, default=1000, help="rounds")
    parser.add_argument("--dialect", choices=["ardupilot", "px4"], default="ardupilot")
    parser.add_argument("--rate-hz", type=float, default=20.0, help="daemon control rate")
    parser.add_argument("--joint-speed-deg-s", type=float, default=1000.0)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--markdown", type=Path, default=ROOT / "bench/results/races.md")
    return run_and_report(run, report, parser.parse_args())


if __name__ == "__main__":
    raise SystemExit(main())
