"""Keep-out at daemon level: adversarial targets and trajectories through the real daemon and
simulator, and every physical PWM the simulated servos received checked against the volumes.

    .venv/bin/python -m bench.keepout_daemon [--targets 100000] [--max-minutes 20]
                                             [--rate-hz 100] [--budget-ms 8] [--seed 2026]
                                             [--markdown FILE]

The daemon runs the shipped example config (``companion/daemon/examples/armbridge.toml``: the
default arm, its calibration, the 450 quad's body, propellers and legs, margin 1 cm) against
``sim_servo`` (ArduPilot) on loopback, with a faster control rate, a shorter solver budget and
a faster joint speed than the example (``--rate-hz``, ``--budget-ms``, ``--joint-speed-deg-s``)
so that many targets pass in the time. Targets go through the control socket: a trajectory
(one point due every control tick, ``--points`` of them) sweeping the hand through the vehicle,
then ``--gotos`` single targets of the other kinds, in turn:

* ``through``: hand poses along a joint-space line between two random configurations (the hand
  sweeps through and around the body, legs and propellers);
* ``inside``: hand poses of configurations that collide (a link in a volume);
* ``edge``: hand poses of configurations just clear of a volume (bisected onto the margin);
* ``alternate``: two clear poses on either side of the vehicle, alternating every point;
* ``far``: poses 90–150 cm out, beyond reach;
* and every tenth round a NaN pose.

A trajectory point refused ends its trajectory (the daemon's rule), so the count of targets
is what the daemon solved (its ``solved`` counter), not what was sent.

The check: the simulator's event log has every change of every output's physical pulse in
order. Starting from the first moment every joint output has a pulse, each change moves one
joint; each configuration the servos are then commanded to is checked with
:meth:`KeepOut.check`, and each one-joint step from the configuration before (the corner path
the outputs really take, not the straight line) with :meth:`KeepOut.check_motion` — the same
geometry code the daemon uses, with the same margin. The target is 0 of either.
"""

from __future__ import annotations

import argparse
import json
import math
import time
import tomllib
from pathlib import Path
from typing import Any

import numpy as np

from bench.loopback import Stack
from bench.report import interpreter, machine, md_table, write_markdown
from companion.daemon.config import parse_config
from companion.kinematics.arm import Pose
from companion.kinematics.collision import KeepOut
from devkit.control_client import ControlConnection
from devkit.timing import wait_until

EXAMPLE = Path(__file__).resolve().parents[1] / "companion" / "daemon" / "examples"
DEFAULT_MARKDOWN = Path(__file__).resolve().parent / "results" / "keepout_daemon.md"
KINDS = ("through", "inside", "edge", "alternate", "far")


def example_tables() -> dict[str, Any]:
    """The example config's tables the daemon takes from it (not its link or socket)."""
    with open(EXAMPLE / "armbridge.toml", "rb") as f:
        data = tomllib.load(f)
    return {k: v for k, v in data.items() if k not in ("link", "control")}


class Targets:
    """Adversarial hand poses (base frame) from configurations of the example arm."""

    def __init__(self, keepout: KeepOut, rng: np.random.Generator) -> None:
        self.ko, self.rng, self.arm = keepout, rng, keepout.arm
        pool = self.arm.random_q_rad(rng, 20_000)
        ok = keepout.clear_mask(pool)
        self.clear, self.colliding = pool[ok], pool[~ok]
        lo, hi = self.clear[: len(self.colliding)].copy(), self.colliding[: len(self.clear)].copy()
        for _ in range(16):  # bisect (clear, colliding) pairs onto the margin's edge
            mid = 0.5 * (lo + hi)
            good = keepout.clear_mask(mid)
            lo[good], hi[~good] = mid[good], mid[~good]
        self.edge = lo

    def pose(self, q: np.ndarray) -> list[float]:
        return list(Pose.from_matrix(self.arm.fk_matrix(q)).as_tuple())

    def _pick(self, pool: np.ndarray) -> np.ndarray:
        return pool[int(self.rng.integers(len(pool)))]

    def points(self, kind: str, n: int) -> list[list[float]]:
        rng = self.rng
        if kind == "through":
            a, b = self.arm.random_q_rad(rng, 2)
            return [self.pose(a + s * (b - a)) for s in np.linspace(0, 1, n)]
        if kind == "inside":
            return [self.pose(self._pick(self.colliding)) for _ in range(n)]
        if kind == "edge":
            return [self.pose(self._pick(self.edge)) for _ in range(n)]
        if kind == "alternate":
            a, b = self._pick(self.clear), self._pick(self.clear)
            return [self.pose(a if i % 2 else b) for i in range(n)]
        if kind == "far":
            out = []
            for _ in range(n):
                d = rng.normal(size=3)
                p = d / np.linalg.norm(d) * rng.uniform(90, 150)
                out.append([*p.tolist(), *rng.uniform(-180, 180, 3).tolist()])
            return out
        raise ValueError(f"kind={kind!r} must be one of {KINDS}")


def drive(stack: Stack, targets: Targets, args: argparse.Namespace) -> dict[str, Any]:
    """Until ``args.targets`` were solved or the time is up: a ``through`` trajectory (its
    end awaited on ``status``), then ``args.gotos`` single targets of the other kinds, each
    sent once the one before was answered; a NaN pose every tenth round. Returns the counts."""
    client = ControlConnection(stack.control_path, timeout_s=30.0)
    period_s = 1.0 / args.rate_hz
    sent: dict[str, int] = {k: 0 for k in (*KINDS, "nan")}
    answers: dict[str, int] = {}
    started = time.monotonic()
    deadline = started + 60.0 * args.max_minutes
    solved0 = stack.status()["counters"]["solved"]
    solved = 0
    rounds = 0
    singles = [k for k in KINDS if k != "through"]

    def note(what: str, reply: dict[str, Any]) -> None:
        key = f"{what} {reply.get('outcome', reply.get('error', 'error'))}"
        answers[key] = answers.get(key, 0) + 1

    while solved < args.targets and time.monotonic() < deadline:
        points = targets.points("through", args.points)
        payload = [[i * period_s, *p] for i, p in enumerate(points)]
        note("trajectory", client.request({"cmd": "trajectory", "points": payload}))
        sent["through"] += len(points)
        # The trajectory ends at its last point or its first refused one.
        wait_until(lambda: stack.status()["trajectory_points_left"] == 0, 10.0, poll_s=0.01)
        for i in range(args.gotos):
            kind = singles[(rounds + i) % len(singles)]
            pose = targets.points(kind, 1)[0]
            note(kind, client.request({"cmd": "goto", "pose": pose}))
            sent[kind] += 1
        if rounds % 10 == 0:
            note("nan", client.request({"cmd": "goto", "pose": [math.nan] * 6}))
            sent["nan"] += 1
        rounds += 1
        if rounds % 10 == 0:
            solved = stack.status()["counters"]["solved"] - solved0
            if rounds % 100 == 0:
                print(f"{time.monotonic() - started:6.0f} s: {solved} solved", flush=True)
    status = stack.status()
    client.close()
    return {
        "elapsed_s": time.monotonic() - started,
        "sent": sent,
        "answers": answers,
        "counters": status["counters"],
        "solved": status["counters"]["solved"] - solved0,
    }


def check_log(events: list[dict[str, Any]], keepout: KeepOut, config: Any) -> dict[str, Any]:
    """Every physical output change of the joints, in log order: the configuration it makes
    and the one-joint step to it, checked against the volumes."""
    cal = config.calibration
    outputs = list(cal.outputs)
    pwm: dict[int, int] = {}
    for event in events:
        if event["event"] == "start" and "outputs_us" in event:
            pwm = {int(o): int(v) for o, v in event["outputs_us"].items()}
    q_deg: list[float | None] = [None] * len(outputs)
    for i, o in enumerate(outputs):
        if pwm.get(o, 0) > 0:
            q_deg[i] = cal.for_output(o).pwm_us_to_angle_deg(pwm[o])
    changes = configurations = steps = 0
    bad_configurations: list[str] = []
    bad_steps: list[str] = []
    for event in events:
        if event["event"] != "output" or int(event["output"]) not in outputs:
            continue
        changes += 1
        if int(event["pwm_us"]) == 0:
            continue  # no pulses: the servo holds where it was
        j = outputs.index(int(event["output"]))
        before = list(q_deg)
        q_deg[j] = cal.for_output(outputs[j]).pwm_us_to_angle_deg(int(event["pwm_us"]))
        if any(a is None for a in q_deg):
            continue  # not every joint has had a pulse yet: the arm's pose is unknown
        q1 = np.radians(np.array(q_deg, float))
        configurations += 1
        hit = keepout.check(q1)
        if hit is not None:
            bad_configurations.append(f"t={event['t_s']:.3f} {q_deg}: {hit.reason}")
        if all(a is not None for a in before):
            steps += 1
            hit = keepout.check_motion(np.radians(np.array(before, float)), q1)
            if hit is not None:
                bad_steps.append(f"t={event['t_s']:.3f} {before} -> {q_deg}: {hit.reason}")
    return {
        "output changes": changes,
        "configurations checked": configurations,
        "colliding configurations": len(bad_configurations),
        "steps checked": steps,
        "colliding steps": len(bad_steps),
        "examples": (bad_configurations + bad_steps)[:5],
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--targets", type=int, default=100_000)
    parser.add_argument("--max-minutes", type=float, default=20.0)
    parser.add_argument("--rate-hz", type=float, default=100.0)
    parser.add_argument("--budget-ms", type=float, default=8.0)
    parser.add_argument("--joint-speed-deg-s", type=float, default=180.0)
    parser.add_argument("--points", type=int, default=50)
    parser.add_argument("--gotos", type=int, default=50)
    parser.add_argument("--seed", type=int, default=2026)
    parser.add_argument("--markdown", type=Path, default=DEFAULT_MARKDOWN)
    args = parser.parse_args(argv)
    tables = example_tables()
    tables["arm"] = {**tables.get("arm", {}), "joint_speed_deg_s": args.joint_speed_deg_s}
    tables["solver"] = {**tables.get("solver", {}), "budget_ms": args.budget_ms}
    tables["control"] = {"rate_hz": args.rate_hz}
    config = parse_config({"link": {"url": "udpout:127.0.0.1:14550"}, **tables})
    keepout = config.keepout_check()
    targets = Targets(keepout, np.random.default_rng(args.seed))
    with Stack(dialect="ardupilot", daemon=tables) as stack:
        driven = drive(stack, targets, args)
        events = stack.stop()
        log_text = Path(stack.daemon_log).read_text(errors="replace")
    # The daemon's internal errors, if any, with the first traceback (its log goes with the
    # stack's temporary directory).
    errors = [line for line in log_text.splitlines() if "internal error" in line]
    first = log_text.find("Traceback")
    driven["internal error lines"] = len(errors)
    if first >= 0:
        print(log_text[max(0, first - 300) : first + 3000], flush=True)
    print(json.dumps(driven, indent=1), flush=True)
    checked = check_log(events, keepout, config)
    print(json.dumps(checked, indent=1), flush=True)
    counters = driven["counters"]
    head = {
        "targets solved": driven["solved"],
        "minutes": round(driven["elapsed_s"] / 60, 1),
        "keep-out refusals": counters.get("keepout_refusals", 0),
        "failed": counters.get("failed", 0),
        "servo updates": counters.get("servo_updates", 0),
        **{k: v for k, v in checked.items() if k != "examples"},
    }
    lines = [
        "# Keep-out through the daemon",
        "",
        f"{machine()}; {interpreter()}; seed {args.seed}; ArduPilot simulator; control "
        f"{args.rate_hz:g} Hz, solver budget {args.budget_ms:g} ms, joint speed "
        f"{args.joint_speed_deg_s:g} deg/s, {args.points} points a trajectory.",
        "",
        *md_table(list(head), [list(head.values())]),
        "",
        f"Sent: {driven['sent']}; answers: {driven['answers']}.",
        "",
        *(f"- {e}" for e in checked["examples"]),
    ]
    text = "\n".join(lines) + "\n"
    print(text)
    write_markdown(args.markdown, text)
    bad = checked["colliding configurations"] + checked["colliding steps"]
    return 0 if bad == 0 else 1


if __name__ == "__main__":
    raise SystemExit(main())
