"""Where an ``ardupilot-lua`` target's time goes on a serial line, target by target.

    python -m bench.lua_latency_parts [--baud 115200] [--targets 100] [--seed 0]

The daemon and the simulator (``--pty --pty-baud BAUD --lua-script``) as processes, as in
``bench/serial_links.py``'s from-rest latency (same targets, same settings). Each target's
``target → last ACK`` is cut at the daemon's and the simulator's CLOCK_MONOTONIC stamps: the
daemon's solve (``received_s`` → ``solved_s``), solved → its first update written
(``first_out_s``), written → the autopilot handing the USER_2 frame to the script (its ``rx``
event: the frame's bytes on the line and the 400 Hz loop pass), the script's run and answer
(its ``ack`` event), and the answer out, its bytes back and into the daemon (``acked_s``).
Prints p50 / p90 / p99 / max of each part, and the worst targets.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from bench.loopback import ControlSocketInput, Stack, answer_one
from bench.serial_links import GAP_MS, random_targets
from companion.kinematics.arm import Arm
from devkit.timing import wait_until

MAV_CMD_USER_2 = 31011
PARTS = (
    "solve",
    "solved → written",
    "written → script has it",
    "script run + answer",
    "answer → daemon",
    "total",
)


def measure(baud: int, targets: int, seed: int) -> np.ndarray:
    """One row of part durations (s) per accepted target."""
    daemon = {"control": {"rate_hz": 50.0}, "arm": {"joint_speed_deg_s": 1000.0}}
    transport = ("--pty", "--pty-baud", str(baud))
    timings = []
    with Stack(dialect="ardupilot-lua", daemon=daemon, transport=transport) as stack:
        source = ControlSocketInput(stack)
        rng = np.random.default_rng(seed + 1)
        try:
            for pose in random_targets(Arm.default(), targets, seed):
                wait_until(lambda: not stack.status()["moving"], 5.0)
                time.sleep(rng.uniform(0.0, GAP_MS / 1e3))
                rec = answer_one(source, pose.as_tuple())
                if rec["outcome"] == "accepted" and "acked_s" in (rec.get("timing") or {}):
                    timings.append(rec["timing"])
        finally:
            source.close()
        events = stack.stop()
    t0 = next(e for e in events if e["event"] == "start")["monotonic_s"]
    rx = np.array([
        t0 + e["t_s"] for e in events
        if e["event"] == "rx" and e["msg"] == "COMMAND_LONG"
        and e["fields"].get("command") == MAV_CMD_USER_2
    ])  # fmt: skip
    ack = np.array(
        [
            t0 + e["t_s"]
            for e in events
            if e["event"] == "ack" and e.get("command") == MAV_CMD_USER_2
        ]
    )
    rows = []
    for t in timings:
        i = int(np.searchsorted(rx, t["first_out_s"]))
        if i >= len(rx):
            continue
        j = int(np.searchsorted(ack, rx[i]))
        if j >= len(ack):
            continue
        rows.append((
            t["solved_s"] - t["received_s"],
            t["first_out_s"] - t["solved_s"],
            rx[i] - t["first_out_s"],
            ack[j] - rx[i],
            t["acked_s"] - ack[j],
            t["acked_s"] - t["received_s"],
        ))  # fmt: skip
    return np.array(rows)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--baud", type=int, default=115_200)
    parser.add_argument("--targets", type=int, default=100)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    rows = measure(args.baud, args.targets, args.seed) * 1e3
    print(f"ardupilot-lua at {args.baud} baud, {len(rows)} targets from rest (ms):")
    for k, name in enumerate(PARTS):
        p50, p90, p99 = np.percentile(rows[:, k], [50, 90, 99])
        worst = rows[:, k].max()
        print(f"  {name:24s} p50 {p50:6.2f}  p90 {p90:6.2f}  p99 {p99:6.2f}  max {worst:6.2f}")
    print("worst targets (the parts above, in order):")
    for k in np.argsort(rows[:, -1])[-5:]:
        print("  " + " ".join(f"{x:6.2f}" for x in rows[k]))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
