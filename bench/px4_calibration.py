"""The simulator's PX4 timing against PX4 SITL: DO_SET_ACTUATOR round trips and routed hops.

    python -m bench.px4_calibration [--trials 300] [--seed 0]
                                    [--markdown bench/results/px4_calibration.md]
                                    [-- SIM_ARGS ...]

Starts ``python -m sim_servo --flavour px4 --ready`` (default PX4 timing, see
``sim_servo.config.Px4TimingConfig``) as a subprocess on UDP loopback with a ground-station link,
and measures it with plain pymavlink codecs over real UDP sockets, as the reference figures were
taken on PX4 SITL (main of 2026-03, SIH quadrotor, UDP loopback):

1. one MAV_CMD_DO_SET_ACTUATOR from the companion (1/191): sent → its COMMAND_ACK received
   (SITL: median 5.8 ms, p90 10.8, max 13.0);
2. the simulator's share of a ground station's target: MAV_CMD_USER_1 from 255/190 on the
   ground-station link, routed to the companion, which answers at once with a COMMAND_ACK,
   routed back: sent → ACK at the ground station (two routed hops, no daemon). SITL's whole
   path with the daemon (its solve and its DO_SET_ACTUATOR round trip inside) was 17.9–18.4 ms
   median; ``python -m bench.latency --dialects px4`` measures that path on the simulator.

Before each trial the client waits a random 0–20 ms (seeded), so trials land at random phases of
the commander's and the main loops' cycles. Arguments after ``--`` go to the simulator.
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
#: PX4 SITL: DO_SET_ACTUATOR → ACK median, p90, max (ms); USER_1 through PX4 to the
#: daemon's ACK, median range (ms).
REAL_ACK_MS = (5.8, 10.8, 13.0)
REAL_CHAIN_MEDIAN_MS = "17.9–18.4"


def is_ack(command: int) -> Callable[[Any], bool]:
    return lambda m: m.get_type() == "COMMAND_ACK" and m.command == command


def actuator_round_trip(companion: MavPeer, trial: int) -> float:
    value = (trial % 200) / 100.0 - 1.0
    t0 = time.monotonic()
    companion.send(
        companion.mav.command_long_encode(
            1, 1, mavlink.MAV_CMD_DO_SET_ACTUATOR, 0, value, value, value, value, value, value, 0
        )
    )
    ack = companion.next_message(is_ack(mavlink.MAV_CMD_DO_SET_ACTUATOR))
    assert ack.result == mavlink.MAV_RESULT_ACCEPTED
    return time.monotonic() - t0


def routed_round_trip(gcs: MavPeer, companion: MavPeer) -> float:
    t0 = time.monotonic()
    gcs.send(gcs.mav.command_long_encode(1, 191, mavlink.MAV_CMD_USER_1, 0, 0, 0, 0, 0, 0, 0, 0))
    command = companion.next_message(
        lambda m: m.get_type() == "COMMAND_LONG" and m.command == mavlink.MAV_CMD_USER_1
    )
    companion.send(
        companion.mav.command_ack_encode(
            command.command, mavlink.MAV_RESULT_ACCEPTED, 0, 0, 255, 190
        )
    )
    gcs.next_message(is_ack(mavlink.MAV_CMD_USER_1))
    return time.monotonic() - t0


def summary(ms: np.ndarray) -> list[str]:
    p50, p90 = np.percentile(ms, [50, 90])
    return [f"{p50:.2f}", f"{p90:.2f}", f"{ms.min():.2f} / {ms.max():.2f}"]


def main() -> int:
    argv = sys.argv[1:]
    sim_args: list[str] = []
    if "--" in argv:
        split = argv.index("--")
        argv, sim_args = argv[:split], argv[split + 1 :]
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--trials", type=int, default=300)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--markdown", type=Path, default=ROOT / "bench/results/px4_calibration.md")
    args = parser.parse_args(argv)
    rng = np.random.default_rng(args.seed)
    with tempfile.TemporaryDirectory(prefix="px4-calibration-") as tmp:
        command = ["--udp", "127.0.0.1:0", "--flavour", "px4", "--gcs", "127.0.0.1:0"]
        with SimProcess(Path(tmp), *command, "--slew-s-per-60deg", "0", *sim_args) as sim:
            companion = MavPeer.connect(sim.url, system_id=1, component_id=191)
            gcs = MavPeer.connect(sim.gcs_url, system_id=255, component_id=190)
            try:
                companion.send(
                    companion.mav.heartbeat_encode(
                        mavlink.MAV_TYPE_ONBOARD_CONTROLLER, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0
                    )
                )
                gcs.send(gcs.mav.heartbeat_encode(mavlink.MAV_TYPE_GCS, 8, 0, 0, 0))
                companion.next_message(lambda m: m.get_type() == "HEARTBEAT")
                acks, chains = [], []
                for trial in range(args.trials):
                    time.sleep(rng.uniform(0.0, 0.020))
                    companion.drain()
                    acks.append(actuator_round_trip(companion, trial) * 1e3)
                for _ in range(args.trials):
                    time.sleep(rng.uniform(0.0, 0.020))
                    companion.drain()
                    gcs.drain()
                    chains.append(routed_round_trip(gcs, companion) * 1e3)
            finally:
                companion.close()
                gcs.close()
    ack_ms, chain_ms = np.array(acks), np.array(chains)
    real = REAL_ACK_MS
    lines = [
        "# sim_servo's PX4 flavour against PX4 SITL",
        "",
        f"`{' '.join(['python -m bench.px4_calibration', *sys.argv[1:]])}` on {machine()}.",
        "",
        f"Simulator: `python -m sim_servo --udp 127.0.0.1:0 --flavour px4 --gcs 127.0.0.1:0 "
        f"--ready` {' '.join(sim_args) or '(default timing)'}; clients: pymavlink codecs on UDP "
        f"loopback, {args.trials} trials per figure, each after a random 0–20 ms pause "
        f"(seed {args.seed}). Reference: PX4 SITL (main of 2026-03, SIH), UDP loopback.",
        "",
    ]
    lines += md_table(
        ["figure (ms)", "sim median", "sim p90", "sim min / max", "SITL"],
        [
            [
                "DO_SET_ACTUATOR → ACK",
                *summary(ack_ms),
                f"{real[0]:g} / p90 {real[1]:g} / max {real[2]:g}",
            ],
            [
                "USER_1 routed to the companion, its ACK routed back (no daemon)",
                *summary(chain_ms),
                f"with the daemon: median {REAL_CHAIN_MEDIAN_MS}",
            ],
        ],
    )
    text = "\n".join(lines) + "\n"
    print(text)
    write_markdown(args.markdown, text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
