"""SIGTERM with ``park_on_stop``: does the daemon exit 0 within a second, parked, without a
traceback, whatever it was doing?

    python -m bench.shutdown [--trials 4] [--scenarios flood withheld] [--rate-hz 5000]
                             [--seed 0] [--markdown bench/results/shutdown.md]

About 55 s with the defaults (4 trials of each scenario); ``--trials 10`` is the full run
(about 2.5 min).

Every trial starts a fresh simulator (ArduCopter link timing) and a fresh daemon (``armbridge
run``, ardupilot dialect, ``arm.park_on_stop = true``, ``park_deg = [0, 90, 0, 0, 0, 0]``)
as subprocesses on UDP loopback (``bench/loopback.py``), then:

* **flood**: the flood of ``bench/flood.py`` (``--rate-hz`` unsigned USER_1 a second straight
  at the daemon's UDP socket, reachable and unreachable poses mixed, seeded) runs; SIGTERM
  goes a seeded 1.0–2.5 s into it, while the flood and its backlog go on;
  (the flood costs the daemon the autopilot's frames too, see ``bench/flood.py``: its link
  may be down at that moment);
* **withheld**: the simulator runs with ``--withhold-ack DO_SET_SERVO`` (it applies the PWM and
  never answers); a ``goto`` is written on the control socket, and SIGTERM goes a seeded
  0.1–2.0 s later, while its update is unconfirmed or after it FAILED.

Measured per trial: the exit code (target 0); SIGTERM → exit (the process's pidfd becoming
readable; target ≤ 1 s); parked — every arm output's PWM in the simulator's state query equal
to the park PWM (through the daemon's calibration) within 1 s of the exit, and whether the arm
was away from park when SIGTERM went (else "parked" proves nothing), the daemon's link state
just before SIGTERM (its status), and the servo commands the simulator handled after SIGTERM
(the park: 6 expected) and the datagrams the kernel dropped meanwhile on the simulator's
sockets (a full receive buffer: under the flood the daemon answers every target, and those
answers go to the autopilot too); whether a goto written
before SIGTERM was answered; any ``Traceback`` in the daemon's stdout/stderr.
"""

from __future__ import annotations

import argparse
import gc
import os
import select
import signal
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from bench.flooder import Flooder, encode_targets, flood_poses
from bench.loopback import Stack, load_average, udp_ports, udp_sockets
from bench.report import machine, md_table, write_markdown
from companion.daemon.config import load_config
from companion.kinematics.arm import Arm, Pose
from devkit.control_client import ControlConnection
from devkit.timing import wait_until

ROOT = Path(__file__).resolve().parent.parent
PARK_DEG = [0.0, 90.0, 0.0, 0.0, 0.0, 0.0]
EXIT_TARGET_S = 1.0
EXIT_WAIT_S = 15.0
PARKED_WAIT_S = 1.0
FLOOD_S = 4.0
SCENARIOS = ("flood", "withheld")


def sim_pwm(stack: Stack, outputs: list[int]) -> dict[int, int]:
    assert stack.sim is not None
    state = stack.sim.state()["outputs"]
    return {o: state[str(o)]["pwm_us"] for o in outputs}


def sigterm(stack: Stack) -> tuple[int, float, float]:
    """SIGTERM the daemon; its exit code, the seconds until it exited (pidfd), and when the
    signal went (CLOCK_MONOTONIC)."""
    assert stack.daemon is not None
    proc = stack.daemon.proc
    pidfd = os.pidfd_open(proc.pid)
    try:
        start = time.monotonic()
        proc.send_signal(signal.SIGTERM)
        ready, _, _ = select.select([pidfd], [], [], EXIT_WAIT_S)
        elapsed = time.monotonic() - start
    finally:
        os.close(pidfd)
    if not ready:
        proc.kill()
    return proc.wait(5.0), elapsed, start


def servo_commands_since(stack: Stack, since_s: float) -> int:
    """Servo commands the simulator handled from ``since_s`` (CLOCK_MONOTONIC) on."""
    assert stack.sim is not None
    events = stack.sim.events()
    t0 = next(e for e in events if e["event"] == "start")["monotonic_s"]
    return sum(e["event"] == "servo" and t0 + e["t_s"] >= since_s for e in events)


def trial(scenario: str, k: int, args: argparse.Namespace) -> dict[str, Any]:
    rng = np.random.default_rng([args.seed, k, SCENARIOS.index(scenario)])
    daemon = {"arm": {"park_on_stop": True, "park_deg": PARK_DEG}}
    sim_args = ["--withhold-ack", "DO_SET_SERVO"] if scenario == "withheld" else []
    rec: dict[str, Any] = {"scenario": scenario, "trial": k}
    with Stack(dialect="ardupilot", daemon=daemon, sim_args=sim_args) as stack:
        config = load_config(stack.config_path)
        assert config.park_deg is not None
        park = config.calibration.angles_to_pwm_us(config.park_deg)
        outputs = sorted(park)
        flooder = None
        goto_conn = None
        try:
            if scenario == "flood":
                wait_until(lambda: stack.status()["autopilot"] is not None, 10.0)
                count = int(args.rate_hz * FLOOD_S)
                poses, _ = flood_poses(count, 0.5, args.seed + k)
                (port,) = udp_ports(stack.daemon_pid)
                flooder = Flooder(
                    encode_targets(poses, stack.status()["autopilot"][0]),
                    daemon_port=port,
                    gcs_url=stack.gcs_url,
                    rate_hz=args.rate_hz,
                )
                rec["delay_s"] = float(rng.uniform(1.0, 2.5))
                flooder.start()
                time.sleep(rec["delay_s"])
            else:
                arm = Arm.default()
                pose = Pose.from_matrix(arm.fk_batch(arm.random_q_rad(rng, 1))[0]).as_tuple()
                goto_conn = ControlConnection(stack.control_path)
                goto_conn.send({"cmd": "goto", "pose": list(pose)})
                rec["delay_s"] = float(rng.uniform(0.1, 2.0))
                time.sleep(rec["delay_s"])
            before = sim_pwm(stack, outputs)
            rec["away"] = any(before[o] != park[o] for o in outputs)
            rec["link"] = stack.status()["link"]
            drops0 = sum(udp_sockets(stack.sim_pid).values())
            rec["code"], rec["exit_s"], sigterm_s = sigterm(stack)
            rec["parked"] = wait_until(lambda: sim_pwm(stack, outputs) == park, PARKED_WAIT_S)
            after = sim_pwm(stack, outputs)
            rec["off_park_us"] = max(abs(after[o] - park[o]) for o in outputs)
            rec["park_commands"] = servo_commands_since(stack, sigterm_s)
            rec["sim_drops"] = sum(udp_sockets(stack.sim_pid).values()) - drops0
            if goto_conn is not None:
                goto_conn.sock.settimeout(1.0)
                try:
                    rec["goto"] = goto_conn.reply().get("outcome")
                except (OSError, ValueError) as exc:
                    rec["goto"] = f"no answer ({exc!r})"
        finally:
            if flooder is not None:
                flooder.kill()
            if goto_conn is not None:
                goto_conn.close()
        stack.stop()
        log = Path(stack.daemon_log).read_text(errors="replace")
    rec["traceback"] = "Traceback" in log
    rec["log_tail"] = [line for line in log.splitlines() if "park" in line or "stop" in line][-3:]
    return rec


def report(records: list[dict[str, Any]], args: argparse.Namespace, load: str) -> list[str]:
    lines = [
        "# SIGTERM with park_on_stop",
        "",
        f"`{' '.join(['python -m bench.shutdown', *sys.argv[1:]])}` on {machine()}; load average "
        f"(1, 5, 15 min) before: {load}, after: {load_average()}.",
        "",
        "Targets: exit code 0, SIGTERM → exit ≤ 1 s, parked (the simulator's outputs at the park "
        "PWMs), no traceback.",
        "",
    ]
    rows = []
    for scenario in args.scenarios:
        recs = [r for r in records if r["scenario"] == scenario]
        exits = np.array([r["exit_s"] for r in recs]) * 1e3
        rows.append([
            scenario, len(recs),
            f"{sum(r['code'] == 0 for r in recs)} ({sorted({r['code'] for r in recs})})",
            f"{np.median(exits):.0f} / {exits.max():.0f}",
            sum(r["exit_s"] <= EXIT_TARGET_S for r in recs),
            sum(r["away"] for r in recs), sum(r["link"] != "up" for r in recs),
            sum(r["parked"] for r in recs), sum(r["traceback"] for r in recs),
            sum(r.get("goto", "").startswith("no answer") for r in recs),
        ])  # fmt: skip
    lines += md_table(
        ["scenario", "trials", "exit 0 (codes)", "SIGTERM → exit ms median / max",
         "exit ≤ 1 s", "away from park at SIGTERM", "link not up at SIGTERM", "parked",
         "traceback", "goto unanswered (EOF)"],
        rows,
    )  # fmt: skip
    lines += ["", "Per trial:", ""]
    for r in records:
        goto = f", goto answered {r['goto']}" if "goto" in r else ""
        lines.append(
            f"- {r['scenario']} #{r['trial']}: SIGTERM {r['delay_s']:.2f} s in (link "
            f"{r['link']}), exit {r['code']} "
            f"after {r['exit_s'] * 1e3:.0f} ms, away {r['away']}, parked {r['parked']} "
            f"(max |PWM − park| {r['off_park_us']} µs, {r['park_commands']} servo commands after "
            f"SIGTERM, {r['sim_drops']} datagrams the kernel dropped at the simulator from "
            f"SIGTERM to the check){goto}; traceback {r['traceback']}; "
            f"log: {' | '.join(r['log_tail'])}"
        )
    return lines


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--trials", type=int, default=4, help="per scenario (full run: 10)")
    parser.add_argument("--scenarios", nargs="+", choices=SCENARIOS, default=list(SCENARIOS))
    parser.add_argument("--rate-hz", type=float, default=5000.0, help="the flood's targets/s")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--markdown", type=Path, default=ROOT / "bench/results/shutdown.md")
    args = parser.parse_args()
    load_before = load_average()
    gc.collect()
    records = []
    # Interleaved: one trial of each scenario in turn, so both see the same machine.
    for k in range(args.trials):
        for scenario in args.scenarios:
            records.append(trial(scenario, k, args))
            print(f"{scenario} #{k}: exit {records[-1]['code']} in "
                  f"{records[-1]['exit_s'] * 1e3:.0f} ms, parked {records[-1]['parked']}",
                  file=sys.stderr)  # fmt: skip
    text = "\n".join(report(records, args, load_before)) + "\n"
    print(text)
    write_markdown(args.markdown, text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
