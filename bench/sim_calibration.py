"""The simulator's timing against real ArduCopter SITL: command round trips and the servo stream.

    python -m bench.sim_calibration [--trials 200] [--seed 0] [--stream-s 2]
                                    [--markdown bench/results/sim_calibration.md]
                                    [-- SIM_ARGS ...]

Starts ``python -m sim_servo`` (ArduPilot flavour, default link timing) as a subprocess on TCP
loopback and measures it with a plain pymavlink codec over a real TCP socket (TCP_NODELAY, as
pymavlink's ``mavtcp``), the way the reference figures were taken on ArduCopter 4.7.0-dev SITL:

1. one MAV_CMD_DO_SET_SERVO round trip: COMMAND_LONG sent → its COMMAND_ACK received;
2. six one after another, each waiting for its ACK: the total;
3. six back-to-back (six socket writes), then the six ACKs collected: the total, and whether all
   were ACCEPTED;
4. SERVO_OUTPUT_RAW after SET_MESSAGE_INTERVAL asked for 400 Hz: the rate received, and what
   GET_MESSAGE_INTERVAL reports.

Before each trial the client waits a random 0–20 ms (seeded), so trials land at random phases of
the autopilot's 400 Hz main loop. Arguments after ``--`` go to the simulator (e.g.
``-- --link-hold-ms 0 --link-delay-ms 0`` for the uncalibrated timing).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from bench.report import machine, md_table, write_markdown
from devkit.mavlink_peer import MavPeer
from devkit.sim_process import SimProcess

ROOT = Path(__file__).resolve().parent.parent
WAIT_S = 5.0
COMPANION = (1, mavlink.MAV_COMP_ID_ONBOARD_COMPUTER)
SERVO_OUTPUT_RAW = mavlink.MAVLINK_MSG_ID_SERVO_OUTPUT_RAW
#: Measured on ArduCopter 4.7.0-dev SITL, TCP loopback, pymavlink client (the brief's figures):
#: (median ms, "range" text).
REAL = {
    "single": (5.7, "5.3–6.1"),
    "sequential": (32.2, "–"),
    "burst": (3.2, "max 6.0"),
}
REAL_STREAM_HZ = 50.0


def set_servo(client: MavPeer, pwm_us: int) -> None:
    client.command(mavlink.MAV_CMD_DO_SET_SERVO, 9, pwm_us)


def single(client: MavPeer, trial: int) -> tuple[float, bool]:
    t0 = time.monotonic()
    set_servo(client, 1400 + trial % 200)
    ack = client.ack(mavlink.MAV_CMD_DO_SET_SERVO)
    return time.monotonic() - t0, ack.result == mavlink.MAV_RESULT_ACCEPTED


def sequential(client: MavPeer, trial: int) -> tuple[float, bool]:
    ok = True
    t0 = time.monotonic()
    for k in range(6):
        set_servo(client, 1400 + k + trial % 100)
        ok &= client.ack(mavlink.MAV_CMD_DO_SET_SERVO).result == mavlink.MAV_RESULT_ACCEPTED
    return time.monotonic() - t0, ok


def burst(client: MavPeer, trial: int) -> tuple[float, bool]:
    t0 = time.monotonic()
    for k in range(6):
        set_servo(client, 1400 + k + trial % 100)
    results = [client.ack(mavlink.MAV_CMD_DO_SET_SERVO).result for _ in range(6)]
    return time.monotonic() - t0, results == [mavlink.MAV_RESULT_ACCEPTED] * 6


FIGURES: dict[str, tuple[str, Callable[[MavPeer, int], tuple[float, bool]]]] = {
    "single": ("1 DO_SET_SERVO round trip", single),
    "sequential": ("6 sequential, each waiting for its ACK (total)", sequential),
    "burst": ("6 back-to-back, then 6 ACKs (total)", burst),
}


def measure(client: MavPeer, trials: int, rng: np.random.Generator) -> dict[str, dict[str, Any]]:
    results = {}
    for name, (_, run) in FIGURES.items():
        times_ms, accepted = [], 0
        for trial in range(trials):
            time.sleep(rng.uniform(0.0, 0.020))
            client.drain()
            elapsed_s, ok = run(client, trial)
            times_ms.append(elapsed_s * 1e3)
            accepted += ok
        results[name] = {"ms": np.array(times_ms), "accepted": accepted}
    return results


def stream_rate(client: MavPeer, window_s: float) -> tuple[float, int, int]:
    """(received Hz, interval_us GET_MESSAGE_INTERVAL reports, SET result) for a 400 Hz ask."""
    client.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, SERVO_OUTPUT_RAW, 2500)
    result = client.ack(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL).result
    client.command(mavlink.MAV_CMD_GET_MESSAGE_INTERVAL, SERVO_OUTPUT_RAW)
    reported = client.next_message(lambda m: m.get_type() == "MESSAGE_INTERVAL").interval_us
    client.next_message(lambda m: m.get_type() == "SERVO_OUTPUT_RAW")  # the stream has started
    stamps = []
    end_s = time.monotonic() + window_s
    while (left := end_s - time.monotonic()) > 0:
        try:
            msg = client.next_message(lambda m: m.get_type() == "SERVO_OUTPUT_RAW", left)
        except TimeoutError:
            break
        stamps.append(msg.time_usec)
    client.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, SERVO_OUTPUT_RAW, -1)
    client.ack(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL)
    # The autopilot's own stamps (µs since boot): the rate it sent at, not our reading jitter.
    hz = (len(stamps) - 1) / ((stamps[-1] - stamps[0]) / 1e6) if len(stamps) > 1 else 0.0
    return hz, reported, result


def report(results: dict, stream: tuple[float, int, int], args: argparse.Namespace) -> list[str]:
    sim_args = " ".join(args.sim_args) or "(defaults)"
    lines = [
        "# sim_servo against ArduCopter SITL",
        "",
        f"`{' '.join(['python -m bench.sim_calibration', *sys.argv[1:]])}` on {machine()}.",
        "",
        f"Simulator: `python -m sim_servo --tcp 127.0.0.1:0` {sim_args}; client: a pymavlink "
        f"codec over TCP loopback (TCP_NODELAY), {args.trials} trials per figure, each after "
        f"a random 0–20 ms pause (seed {args.seed}). Reference: ArduCopter 4.7.0-dev SITL, TCP "
        "loopback, pymavlink client.",
        "",
    ]
    rows = []
    for name, (label, _) in FIGURES.items():
        ms = results[name]["ms"]
        p5, p50, p95 = np.percentile(ms, [5, 50, 95])
        real_median, real_range = REAL[name]
        rows.append([
            label, f"{p50:.2f}", f"{p5:.2f}–{p95:.2f}", f"{ms.min():.2f} / {ms.max():.2f}",
            f"{results[name]['accepted']}/{len(ms)}", f"{real_median:g}", real_range,
            f"{p50 / real_median:.2f}",
        ])  # fmt: skip
    lines += md_table(
        ["figure (ms)", "sim median", "sim p5–p95", "sim min / max", "all ACCEPTED",
         "SITL median", "SITL range", "sim / SITL"],
        rows,
    )  # fmt: skip
    hz, reported_us, result = stream
    lines += [
        "",
        f"SERVO_OUTPUT_RAW asked for at 400 Hz (SET_MESSAGE_INTERVAL 2500 µs: "
        f"{mavlink.enums['MAV_RESULT'][result].name}): received at {hz:.1f} Hz "
        f"(SITL: at most {REAL_STREAM_HZ:g} Hz); GET_MESSAGE_INTERVAL reports "
        f"{reported_us} µs (the stored interval, capped at 80 % of the loop rate).",
    ]
    return lines


def main() -> int:
    argv = sys.argv[1:]
    sim_args: list[str] = []
    if "--" in argv:
        split = argv.index("--")
        argv, sim_args = argv[:split], argv[split + 1 :]
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--trials", type=int, default=200)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--stream-s", type=float, default=2.0)
    parser.add_argument("--markdown", type=Path, default=ROOT / "bench/results/sim_calibration.md")
    args = parser.parse_args(argv)
    args.sim_args = sim_args
    rng = np.random.default_rng(args.seed)
    with tempfile.TemporaryDirectory(prefix="sim-calibration-") as tmp:
        with SimProcess(
            Path(tmp), "--tcp", "127.0.0.1:0", "--slew-s-per-60deg", "0", *sim_args
        ) as sim:
            client = MavPeer.connect(sim.url, system_id=COMPANION[0], component_id=COMPANION[1])
            try:
                client.next_message(lambda m: m.get_type() == "HEARTBEAT")
                results = measure(client, args.trials, rng)
                stream = stream_rate(client, args.stream_s)
            finally:
                client.close()
    text = "\n".join(report(results, stream, args)) + "\n"
    print(text)
    write_markdown(args.markdown, text)
    ok = all(r["accepted"] == len(r["ms"]) for r in results.values())
    return 0 if ok else 1


if __name__ == "__main__":
    raise SystemExit(main())
