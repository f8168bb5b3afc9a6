"""What the moving vehicle costs the simulator: CPU with and without the hover, its ``vehicle``
events and the ATTITUDE / LOCAL_POSITION_NED streams.

    python -m bench.hover_cost [--seconds 20] [--markdown FILE]

Each case starts ``python -m sim_servo`` on UDP loopback (as the tests do, with an event log
and a query socket), a pymavlink peer says HEARTBEAT once a second (and asks for the streams
where the case says so) and counts what arrives; the simulator's CPU time (user + system, from
``/proc/PID/stat``) over the window gives its share of one core. The peer's decoding cost per
frame (what a daemon pays to receive the streams) is timed in-process.
"""

from __future__ import annotations

import argparse
import collections
import os
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from bench.report import machine, md_table, write_markdown
from devkit.mavlink_peer import MavPeer
from devkit.sim_process import SimProcess

STILL = ("--no-hover", "--vehicle-log-hz", "0")
PX4_QUIET = ("--attitude-rate-hz", "0", "--local-position-rate-hz", "0")
#: (name, simulator arguments, stream requests {message id: interval µs}).
CASES: list[tuple[str, tuple[str, ...], dict[int, int]]] = [
    ("ardupilot, still, no vehicle events (as before)", STILL, {}),
    ("ardupilot, hover + vehicle events 25 Hz (default)", (), {}),
    (
        "ardupilot, default + ATTITUDE 50 Hz + LOCAL_POSITION_NED 50 Hz asked",
        (),
        {
            mavlink.MAVLINK_MSG_ID_ATTITUDE: 20_000,
            mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED: 20_000,
        },
    ),
    ("px4, still, streams off (as before)", ("--flavour", "px4", *STILL, *PX4_QUIET), {}),
    ("px4, default (hover, events 25 Hz, streams 100 + 30 Hz)", ("--flavour", "px4"), {}),
]


def cpu_s(pid: int) -> float:
    """User + system CPU seconds of process ``pid``."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def run_case(args: tuple[str, ...], requests: dict[int, int], seconds: float) -> dict[str, Any]:
    with (
        tempfile.TemporaryDirectory() as tmp,
        SimProcess(Path(tmp), "--udp", "127.0.0.1:0", *args) as sim,
    ):
        peer = MavPeer.connect(sim.url, system_id=1, component_id=191)

        def heartbeat() -> None:
            peer.send_heartbeat(8, mavlink.MAV_TYPE_ONBOARD_CONTROLLER)

        heartbeat()
        for msg_id, interval_us in requests.items():
            peer.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, msg_id, interval_us)
        time.sleep(0.5)  # a bench, not a test: let the streams start before the window
        start_cpu, start_s = cpu_s(sim.proc.pid), time.monotonic()
        first = len(peer.received)
        next_beat_s = start_s + 1.0
        while (now := time.monotonic()) < start_s + seconds:
            if now >= next_beat_s:
                heartbeat()
                next_beat_s += 1.0
            time.sleep(max(0.0, min(next_beat_s, start_s + seconds) - time.monotonic()))
        used_s, elapsed_s = cpu_s(sim.proc.pid) - start_cpu, time.monotonic() - start_s
        counts = collections.Counter(m.get_type() for m in peer.received[first:])
        vehicle_events = len(sim.events("vehicle"))
        peer.close()
    return {
        "cpu_pct": 100.0 * used_s / elapsed_s,
        "attitude_hz": counts["ATTITUDE"] / elapsed_s,
        "position_hz": counts["LOCAL_POSITION_NED"] / elapsed_s,
        "vehicle_events": vehicle_events,
    }


def decode_cost_us(frames: int = 5000) -> float:
    """µs to decode one ATTITUDE frame with pymavlink (a daemon's share of a stream)."""
    enc = mavlink.MAVLink(None, 1, 1)
    frame = enc.attitude_encode(123, 0.01, 0.02, 0.03, 0.1, 0.2, 0.3).pack(enc)
    dec = mavlink.MAVLink(None)
    start = time.perf_counter()
    for _ in range(frames):
        dec.parse_buffer(frame)
    return (time.perf_counter() - start) / frames * 1e6


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.hover_cost", description=__doc__)
    parser.add_argument("--seconds", type=float, default=20.0, help="window per case (s)")
    parser.add_argument("--markdown", type=Path, help="also write the report here")
    args = parser.parse_args(argv)
    rows = []
    for name, sim_args, requests in CASES:
        result = run_case(sim_args, requests, args.seconds)
        rows.append(
            [
                name,
                result["cpu_pct"],
                result["attitude_hz"],
                result["position_hz"],
                result["vehicle_events"],
            ]
        )
        print(f"{name}: {result}", file=sys.stderr)
    load = os.getloadavg()[0]
    headers = ["case", "CPU % of a core", "ATTITUDE Hz", "LOCAL_POSITION_NED Hz", "vehicle events"]
    lines = [
        f"Simulator CPU over {args.seconds:.0f} s per case ({machine()}; load {load:.1f}):",
        "",
        *md_table(headers, rows),
        "",
        f"pymavlink decodes one ATTITUDE frame in {decode_cost_us():.1f} µs (a receiver's share).",
    ]
    text = "\n".join(lines)
    print(text)
    if args.markdown:
        write_markdown(args.markdown, text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
