"""``python -m sim_servo``: a simulated flight controller with servos, for tests without hardware.

The first line on stdout is the link URL to give the daemon (``udpout:127.0.0.1:PORT``;
with ``--udpout``, where we send to a daemon that listens, ``udpin:127.0.0.1:PORT``;
``tcp:127.0.0.1:PORT``, ``/dev/pts/N,115200`` or, with ``--pty-link``, ``PATH,115200``), printed
once the port is open. With ``--gcs`` a second line ``gcs udpout:HOST:PORT`` gives the ground
station's address: frames between the two links are routed as ArduPilot routes them (see
:class:`~sim_servo.autopilot.routing.ArduPilotRouter`). SIGTERM or
SIGINT stops the simulator cleanly (exit status 0).
"""

from __future__ import annotations

import argparse
import gc
import logging
import signal
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from sim_servo.autopilot import SimAutopilot
from sim_servo.config import (
    DEFAULT_ARM_OUTPUTS,
    DEFAULT_ATTITUDE_RATE_HZ,
    DEFAULT_LOCAL_POSITION_RATE_HZ,
    FLAVOURS,
    OUTPUT_COUNT,
    config_from_mapping,
    load_key,
    load_toml,
    parse_withhold,
    ready_setup,
)
from sim_servo.endpoints import (
    Endpoint,
    PtyEndpoint,
    TcpEndpoint,
    UdpEndpoint,
    UdpOutEndpoint,
    parse_host_port,
)
from sim_servo.errors import SimConfigError, SimError
from sim_servo.eventlog import EventLog
from sim_servo.faults import FaultInjector
from sim_servo.hand import HandModel
from sim_servo.serial_line import MAX_BAUD, MIN_BAUD, SerialLineEndpoint
from sim_servo.server import SimServer

log = logging.getLogger("sim_servo")

#: MAVLink 2 frame of ATTITUDE or LOCAL_POSITION_NED (10 header + 28 payload + 2 CRC bytes)
#: and of HEARTBEAT (10 + 9 + 2).
PX4_STREAM_FRAME_BYTES = 40
HEARTBEAT_FRAME_BYTES = 21


def _probability(text: str) -> float:
    value = float(text)
    if not 0.0 <= value <= 1.0:
        raise argparse.ArgumentTypeError(f"probability={value!r} outside [0, 1]")
    return value


def _non_negative(text: str) -> float:
    value = float(text)
    if not value >= 0.0:
        raise argparse.ArgumentTypeError(f"value={value!r} must be >= 0")
    return value


def _function(text: str) -> tuple[int, int]:
    output, sep, function = text.partition("=")
    try:
        pair = (int(output), int(function))
    except ValueError:
        pair = None
    if not sep or pair is None:
        raise argparse.ArgumentTypeError(f"{text!r} must be OUTPUT=FUNCTION, e.g. 9=0")
    if not 1 <= pair[0] <= OUTPUT_COUNT:
        raise argparse.ArgumentTypeError(f"output={pair[0]} outside [1, {OUTPUT_COUNT}]")
    return pair


def _baud(text: str) -> int:
    try:
        baud = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"baud={text!r} is not an integer") from None
    if not MIN_BAUD <= baud <= MAX_BAUD:
        raise argparse.ArgumentTypeError(f"baud={baud} outside [{MIN_BAUD}, {MAX_BAUD}]")
    return baud


def _param(text: str) -> tuple[str, int]:
    name, sep, value = text.partition("=")
    try:
        number = int(value)
    except ValueError:
        number = None
    if not sep or not name or number is None:
        raise argparse.ArgumentTypeError(f"{text!r} must be NAME=INTEGER, e.g. COM_PREARM_MODE=2")
    return name, number


def _outputs(text: str) -> tuple[int, ...]:
    try:
        return tuple(int(part) for part in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} must be comma-separated outputs") from None


def _triple(text: str) -> list[float]:
    try:
        values = [float(part) for part in text.split(",")]
    except ValueError:
        values = []
    if len(values) != 3:
        raise argparse.ArgumentTypeError(f"{text!r} must be three comma-separated numbers")
    return values


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m sim_servo",
        description="Simulated flight controller (ArduPilot or PX4 behaviour) with slew-limited "
        "servos and the arm's hand pose, over UDP, TCP or a pseudo-terminal. The "
        "first stdout line is the link URL for the daemon.",
    )
    link = parser.add_argument_group("link (exactly one)")
    where = link.add_mutually_exclusive_group(required=True)
    where.add_argument(
        "--udp",
        metavar="HOST:PORT",
        help="serve MAVLink 2 on UDP (port 0: any free port); replies go to the last sender",
    )
    where.add_argument(
        "--udpout",
        metavar="HOST:PORT",
        help="send MAVLink 2 on UDP to a companion listening at HOST:PORT, from a free port "
        "(real PX4 and ArduPilot SITL connect out this way); the first line is "
        "'udpin:HOST:PORT', the daemon's link.url",
    )
    where.add_argument("--tcp", metavar="HOST:PORT", help="listen on TCP for one client")
    where.add_argument(
        "--pty",
        action="store_true",
        help="serve on a new pseudo-terminal; its device path is printed",
    )
    link.add_argument(
        "--pty-link",
        metavar="PATH",
        help="with --pty: keep a symlink at PATH to the current pty (a stable "
        "name, as udev gives a USB serial adapter) and print PATH,115200",
    )
    link.add_argument(
        "--pty-baud",
        type=_baud,
        metavar="BAUD",
        help="with --pty: model a serial line at BAUD (8N1, 10 bits a byte, both ways; "
        "ArduPilot's 256-byte MAVLink transmit buffer) and print PATH,BAUD; the TCP-fitted "
        "link timing is then off unless --link-* or [link_timing] set it",
    )
    parser.add_argument(
        "--gcs",
        metavar="HOST:PORT",
        help="also serve a ground station on UDP (port 0: any free port; the "
        "second stdout line is 'gcs udpout:HOST:PORT'); frames addressed "
        "to the companion, and broadcasts, are routed between the links",
    )

    vehicle = parser.add_argument_group("vehicle")
    vehicle.add_argument(
        "--config",
        metavar="TOML",
        help="settings file (see sim_servo/examples/quad_arm.toml); flags win",
    )
    vehicle.add_argument(
        "--flavour", choices=FLAVOURS, help="autopilot behaviour (default ardupilot)"
    )
    vehicle.add_argument("--system-id", type=int, help="MAVLink system id (default 1)")
    vehicle.add_argument(
        "--function",
        type=_function,
        action="append",
        default=[],
        metavar="OUTPUT=FUNCTION",
        help="output function (SERVOn_FUNCTION / PWM_MAIN_FUNCn), repeatable; "
        "default: outputs 1-4 motors, others 0 (px4 too: --ready maps the arm's outputs "
        "to 301-306)",
    )
    vehicle.add_argument(
        "--param",
        type=_param,
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help="a parameter's value at start (e.g. COM_PREARM_MODE=2, BRD_SAFETY_MASK=7936), "
        "repeatable; flags win over --ready and the config file",
    )
    vehicle.add_argument(
        "--ready",
        action="store_true",
        help="a vehicle set up for the arm: px4 - arm outputs on functions 301-306, "
        "COM_PREARM_MODE=2, forwarding on both links, armed at start; ardupilot - nothing "
        "(safety off is the default)",
    )
    vehicle.add_argument(
        "--armed",
        action="store_true",
        help="px4: armed at start (a reboot comes back disarmed); the query 'arm' / 'disarm' / "
        "'kill' changes it later",
    )
    vehicle.add_argument(
        "--safety",
        choices=("on", "off"),
        help="ardupilot: the safety switch at boot (BRD_SAFETY_DEFLT; default off); the query "
        "'safety_on' / 'safety_off' changes it later",
    )
    vehicle.add_argument(
        "--lua-script",
        action="store_true",
        default=None,
        help="ardupilot: answer MAV_CMD_USER_2 as armbridge's Lua bridge script does "
        "(its checks, its ~9 ms answer)",
    )
    vehicle.add_argument(
        "--servo-output-rate-hz",
        type=_non_negative,
        help="SERVO_OUTPUT_RAW rate before any SET_MESSAGE_INTERVAL (default 0: off)",
    )

    vehicle.add_argument(
        "--system-time-rate-hz",
        type=_non_negative,
        help="SYSTEM_TIME rate before any SET_MESSAGE_INTERVAL (default: ardupilot 0, "
        "off, as ArduCopter; px4 1, as PX4's onboard mode)",
    )

    vehicle.add_argument(
        "--loop-rate-hz",
        type=_non_negative,
        help="main-loop rate: frames are handled, and STATUSTEXT / PARAM_VALUE "
        "sent, on loop passes (1-10000; default 400, as ArduCopter)",
    )

    motion = parser.add_argument_group(
        "vehicle motion (a seeded hover disturbance in LOCAL_NED; see sim_servo.hover)"
    )
    motion.add_argument(
        "--hover",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="drift and tilt as a hovering vehicle in light wind (default on; --no-hover: the "
        "vehicle holds its home, level)",
    )
    motion.add_argument("--hover-seed", type=int, help="seed of the hover motion (default 0)")
    motion.add_argument(
        "--drift-cm", type=_non_negative, help="largest drift north and east (default 10)"
    )
    motion.add_argument("--tilt-deg", type=_non_negative, help="largest roll and pitch (default 5)")
    motion.add_argument(
        "--mount-xyz-cm",
        type=_triple,
        metavar="X,Y,Z",
        help="the arm base's origin in the body frame FRD (default 0,0,10: 10 cm below)",
    )
    motion.add_argument(
        "--mount-rpy-deg",
        type=_triple,
        metavar="R,P,Y",
        help="the arm base's orientation in the body frame FRD (default 0,0,0)",
    )
    motion.add_argument(
        "--vehicle-log-hz",
        type=_non_negative,
        help="a 'vehicle' event (vehicle state, hand in the world) this often (default 25; 0: "
        "none)",
    )
    motion.add_argument(
        "--attitude-rate-hz",
        type=_non_negative,
        help="ATTITUDE before any SET_MESSAGE_INTERVAL (default: ardupilot 0, px4 100)",
    )
    motion.add_argument(
        "--local-position-rate-hz",
        type=_non_negative,
        help="LOCAL_POSITION_NED before any SET_MESSAGE_INTERVAL (default: ardupilot 0, px4 30)",
    )

    timing = parser.add_argument_group(
        "link timing (a model fitted to ArduCopter SITL; see docs/simulator.md)"
    )
    timing.add_argument(
        "--link-delay-ms",
        type=_non_negative,
        help="each frame we send leaves at least this long after it was produced (default 1.0)",
    )
    timing.add_argument(
        "--link-hold-ms",
        type=_non_negative,
        help="then it is held until the link sends a frame, or this long after the first "
        "frame the link sent since it was last quiet (default 4.8; 0 with --link-delay-ms 0: "
        "frames leave on the main-loop pass that made them)",
    )
    timing.add_argument(
        "--link-burst-frames",
        type=int,
        help="this many frames from a link within the hold release its replies at once (default 2)",
    )

    px4_timing = parser.add_argument_group(
        "px4 timing (a model fitted to PX4 SITL; see sim_servo.config.Px4TimingConfig)"
    )
    px4_timing.add_argument(
        "--px4-commander-period-ms",
        type=_non_negative,
        help="arm/disarm and DO_SET_ACTUATOR act and are answered on the commander's next "
        "cycle (default 10; 0: at once)",
    )
    px4_timing.add_argument(
        "--px4-mavlink-loop-ms",
        type=_non_negative,
        help="frames leave on their link's next MAVLink main-loop pass (default 1.5)",
    )
    px4_timing.add_argument(
        "--px4-forward-delay-ms",
        type=_non_negative,
        help="a frame routed to another link leaves this much later at the earliest",
    )

    servo = parser.add_argument_group("servos and arm")
    servo.add_argument(
        "--slew-s-per-60deg",
        type=_non_negative,
        help="servo speed (default 0.12 s per 60 degrees; 0: instant)",
    )
    servo.add_argument("--deadband-us", type=_non_negative, help="servo deadband (default 1 us)")
    servo.add_argument("--arm", metavar="TOML", help="arm file (default: the paper arm)")
    servo.add_argument(
        "--arm-outputs",
        type=_outputs,
        metavar="N,N,...",
        help="outputs of the arm's joints in order (default 9,10,11,12,13,14)",
    )

    report = parser.add_argument_group("observation")
    report.add_argument("--event-log", metavar="PATH", help="append JSON-lines events here")
    report.add_argument(
        "--query-socket",
        metavar="PATH",
        help="answer 'state' / 'events' / 'ping' (and the 'pause_heartbeat', "
        "'resume_heartbeat', 'reboot', 'hangup', 'arm', 'disarm', 'kill', 'safety_on', "
        "'safety_off' requests) lines on this Unix socket",
    )
    report.add_argument("-v", "--verbose", action="store_true", help="log to stderr")

    faults = parser.add_argument_group("fault injection")
    faults.add_argument("--seed", type=int, help="seed for every random fault (default 0)")
    faults.add_argument(
        "--drop-in",
        type=_probability,
        metavar="P",
        help="drop each incoming frame with probability P",
    )
    faults.add_argument(
        "--drop-out",
        type=_probability,
        metavar="P",
        help="drop each outgoing frame with probability P",
    )
    faults.add_argument(
        "--corrupt-in",
        type=_probability,
        metavar="P",
        help="flip a byte of each incoming read with probability P",
    )
    faults.add_argument(
        "--corrupt-out",
        type=_probability,
        metavar="P",
        help="flip a byte of each outgoing frame with probability P",
    )
    faults.add_argument("--latency-ms", type=_non_negative, help="delay every outgoing frame")
    faults.add_argument(
        "--jitter-ms",
        type=_non_negative,
        help="add uniform +-jitter to the delay (frames may reorder)",
    )
    faults.add_argument(
        "--heartbeat-pause-after",
        type=_non_negative,
        metavar="S",
        help="stop sending HEARTBEAT S seconds after start",
    )
    faults.add_argument(
        "--heartbeat-pause-for",
        type=_non_negative,
        metavar="S",
        help="... for S seconds (default: for ever)",
    )
    faults.add_argument(
        "--withhold-ack",
        action="append",
        default=[],
        metavar="CMD",
        help="execute but never acknowledge command CMD (id, name such as "
        "DO_SET_SERVO, or 'all'); repeatable",
    )
    faults.add_argument(
        "--nack-output",
        type=int,
        action="append",
        default=[],
        metavar="N",
        help="answer FAILED (no STATUSTEXT) to commands for output N; repeatable",
    )
    faults.add_argument(
        "--hangup-after",
        type=_non_negative,
        metavar="S",
        help="close the port (pty, socket) S seconds after start (the query 'hangup' does it "
        "on demand)",
    )
    faults.add_argument(
        "--hangup-for",
        type=_non_negative,
        metavar="S",
        help="with --pty: open a new pty S seconds after a hang-up and point "
        "--pty-link at it (default: the port never comes back)",
    )
    faults.add_argument(
        "--reboot-after",
        type=_non_negative,
        metavar="S",
        help="reboot the autopilot S seconds after start (the query 'reboot' does it on demand)",
    )
    faults.add_argument(
        "--reboot-gap",
        type=_non_negative,
        metavar="S",
        help="a reboot's silence: no frame out, input ignored (default 0.36, measured)",
    )
    faults.add_argument(
        "--signing-key",
        metavar="PATH",
        help="require MAVLink 2 signing with this key (32 bytes or 64 hex "
        "digits); unsigned frames are ignored, ours are signed",
    )
    return parser


def config_data(args: argparse.Namespace) -> tuple[dict[str, Any], Path | None]:
    """The TOML data (if any) with the flags layered on top."""
    base_dir = None
    data: dict[str, Any] = {}
    if args.config:
        data = load_toml(args.config)
        base_dir = Path(args.config).resolve().parent
    for key, value in (
        ("flavour", args.flavour),
        ("system_id", args.system_id),
        ("servo_output_rate_hz", args.servo_output_rate_hz),
        ("system_time_rate_hz", args.system_time_rate_hz),
        ("attitude_rate_hz", args.attitude_rate_hz),
        ("local_position_rate_hz", args.local_position_rate_hz),
        ("loop_rate_hz", args.loop_rate_hz),
        ("lua_script", args.lua_script),
    ):
        if value is not None:
            data[key] = value
    timing = dict(data.get("link_timing", {}))
    if args.pty_baud is not None and not timing:
        # The hold was fitted to TCP (a receiver's delayed ACK); a serial line's own timing is
        # the bytes (serial_line.py). The output delay is the autopilot's own floor (a burst's
        # answers leave no sooner on any link), so it stays.
        timing = {"hold_ms": 0.0}
    for key, value in (
        ("output_delay_ms", args.link_delay_ms),
        ("hold_ms", args.link_hold_ms),
        ("burst_frames", args.link_burst_frames),
    ):
        if value is not None:
            timing[key] = value
    data["link_timing"] = timing
    px4_timing = dict(data.get("px4_timing", {}))
    for key, value in (
        ("commander_period_ms", args.px4_commander_period_ms),
        ("mavlink_loop_ms", args.px4_mavlink_loop_ms),
        ("forward_delay_ms", args.px4_forward_delay_ms),
    ):
        if value is not None:
            px4_timing[key] = value
    data["px4_timing"] = px4_timing
    arm = dict(data.get("arm", {}))
    if args.arm:
        arm["file"] = str(Path(args.arm).resolve())
    if args.arm_outputs:
        arm["outputs"] = list(args.arm_outputs)
    data["arm"] = arm
    params = dict(data.get("params", {}))
    if args.ready:
        flavour = data.get("flavour", "ardupilot")
        setup = ready_setup(
            flavour if isinstance(flavour, str) else "",
            tuple(arm.get("outputs", DEFAULT_ARM_OUTPUTS)),
        )
        data["outputs"] = {**data.get("outputs", {}), **setup.get("outputs", {})}
        params.update(setup.get("params", {}))
        if "armed" in setup:
            data["armed"] = setup["armed"]
    if args.armed:
        data["armed"] = True
    if args.safety is not None:
        params["BRD_SAFETY_DEFLT"] = 1 if args.safety == "on" else 0
    params.update(dict(args.param))
    data["params"] = params
    if args.function:
        outputs = dict(data.get("outputs", {}))
        outputs.update({str(o): f for o, f in args.function})
        data["outputs"] = outputs
    servo = dict(data.get("servo", {}))
    for key, value in (
        ("slew_s_per_60deg", args.slew_s_per_60deg),
        ("deadband_us", args.deadband_us),
    ):
        if value is not None:
            servo[key] = value
    data["servo"] = servo
    faults = dict(data.get("faults", {}))
    for key in (
        "seed",
        "drop_in",
        "drop_out",
        "corrupt_in",
        "corrupt_out",
        "latency_ms",
        "jitter_ms",
    ):
        if getattr(args, key) is not None:
            faults[key] = getattr(args, key)
    for key, value in (
        ("heartbeat_pause_after_s", args.heartbeat_pause_after),
        ("heartbeat_pause_for_s", args.heartbeat_pause_for),
        ("hangup_after_s", args.hangup_after),
        ("hangup_for_s", args.hangup_for),
        ("reboot_after_s", args.reboot_after),
        ("reboot_gap_s", args.reboot_gap),
    ):
        if value is not None:
            faults[key] = value
    if args.withhold_ack:
        faults["withhold_ack"] = list(args.withhold_ack)
    if args.nack_output:
        faults["nack_outputs"] = list(args.nack_output)
    data["faults"] = faults
    vehicle = dict(data.get("vehicle", {}))
    for key, value in (
        ("hover", args.hover),
        ("seed", args.hover_seed),
        ("drift_cm", args.drift_cm),
        ("tilt_deg", args.tilt_deg),
        ("log_rate_hz", args.vehicle_log_hz),
    ):
        if value is not None:
            vehicle[key] = value
    mount = dict(vehicle.get("mount", {}))
    if args.mount_xyz_cm is not None:
        mount["xyz_cm"] = args.mount_xyz_cm
    if args.mount_rpy_deg is not None:
        mount["rpy_deg"] = args.mount_rpy_deg
    if mount:
        vehicle["mount"] = mount
    data["vehicle"] = vehicle
    if args.pty_baud is not None and data.get("flavour") == "px4":
        for key, rate_hz in px4_serial_stream_rates_hz(args.pty_baud).items():
            data.setdefault(key, rate_hz)
    return data, base_dir


def px4_serial_stream_rates_hz(baud: int) -> dict[str, float]:
    """PX4's ATTITUDE and LOCAL_POSITION_NED rates on a serial line at ``baud``: the ONBOARD
    defaults (100 and 30 Hz) scaled down to the link's data rate, as PX4 scales every stream
    (mavlink_main.cpp ``update_rate_mult``: × min(1, (datarate − constant-rate streams) /
    the others' bytes per second), with ``MAV_x_RATE`` 0 meaning half the line, ``baud / 20``
    bytes per second). Only the simulated streams share that budget here (a real PX4 has more
    ONBOARD streams, so lower rates); HEARTBEAT is the constant one."""
    datarate_b_s = baud / 20
    rates_hz = {
        "attitude_rate_hz": DEFAULT_ATTITUDE_RATE_HZ["px4"],
        "local_position_rate_hz": DEFAULT_LOCAL_POSITION_RATE_HZ["px4"],
    }
    streamed_b_s = PX4_STREAM_FRAME_BYTES * sum(rates_hz.values())
    multiplier = min(1.0, max(0.0, datarate_b_s - HEARTBEAT_FRAME_BYTES) / streamed_b_s)
    return {key: rate * multiplier for key, rate in rates_hz.items()}


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=logging.INFO if args.verbose else logging.WARNING,
        stream=sys.stderr,
        format="%(name)s: %(message)s",
    )
    events: EventLog | None = None
    endpoint: Endpoint | None = None
    gcs: UdpEndpoint | None = None
    try:
        data, base_dir = config_data(args)
        if args.withhold_ack:
            parse_withhold(list(args.withhold_ack))  # fail early with the flag's own message
        if args.pty_link and not args.pty:
            raise SimConfigError("--pty-link needs --pty")
        if args.pty_baud is not None and not args.pty:
            raise SimConfigError("--pty-baud needs --pty")
        config = config_from_mapping(data, source=args.config or "<flags>", base_dir=base_dir)
        if args.signing_key:
            from dataclasses import replace

            config = replace(config, signing_key=load_key(args.signing_key))
        if config.faults.hangup_for_s is not None and not args.pty:
            raise SimConfigError("--hangup-for (hangup_for_s) needs --pty: only a pty comes back")
        hand = HandModel.from_config(config.arm)
        events = EventLog(args.event_log)
        if args.gcs:
            gcs = UdpEndpoint(*parse_host_port(args.gcs, "--gcs"))
        if args.udp:
            endpoint = UdpEndpoint(*parse_host_port(args.udp, "--udp"))
        elif args.udpout:
            host, port = parse_host_port(args.udpout, "--udpout")
            if port == 0:
                raise SimConfigError("--udpout needs the companion's port, not 0")
            endpoint = UdpOutEndpoint(host, port)
        elif args.tcp:
            endpoint = TcpEndpoint(*parse_host_port(args.tcp, "--tcp"))
        elif args.pty_baud is not None:
            endpoint = SerialLineEndpoint(PtyEndpoint(args.pty_link, args.pty_baud), args.pty_baud)
        else:
            endpoint = PtyEndpoint(args.pty_link)
        start_s = time.monotonic()
        autopilot = SimAutopilot(
            config, now_s=start_s, emit=events, hand=hand, faults=FaultInjector(config.faults)
        )
        server = SimServer(
            autopilot,
            endpoint,
            events,
            gcs=gcs,
            query_path=args.query_socket,
            hangup_after_s=config.faults.hangup_after_s,
            hangup_for_s=config.faults.hangup_for_s,
            start_s=start_s,
        )
    except SimError as exc:
        for link in (endpoint, gcs):
            if link is not None:
                link.close()
        if events is not None:
            events.close()
        print(f"sim_servo: {exc}", file=sys.stderr)
        return 2

    def on_signal(signum: int, _frame: object) -> None:
        server.stop()

    previous = {sig: signal.signal(sig, on_signal) for sig in (signal.SIGTERM, signal.SIGINT)}
    # monotonic_s: t_s = 0 on CLOCK_MONOTONIC (system-wide), to line events up with other
    # processes' time.monotonic() stamps; wall_s: the same instant on the wall clock, for logs
    # stamped with the time of day (a daemon's, outside journald).
    autopilot.emit(
        start_s,
        "start",
        url=endpoint.url,
        flavour=config.flavour,
        system_id=config.system_id,
        functions=dict(config.functions),
        params=dict(config.params),
        armed=autopilot.armed,
        safety_on=autopilot.safety_on,
        outputs_us=dict(autopilot.output_us),
        gcs_url=gcs.url if gcs is not None else None,
        monotonic_s=start_s,
        wall_s=time.time() - (time.monotonic() - start_s),
        vehicle=config.vehicle.as_dict(),
    )
    print(endpoint.url, flush=True)
    if gcs is not None:
        print(f"gcs {gcs.url}", flush=True)
    # A flight controller has no garbage collector. Ours must not pause the autopilot for tens
    # of ms: the start-up heap (pymavlink's dialect, ~100k objects) never dies, so frozen, the
    # collector's full passes skip it.
    gc.freeze()
    try:
        status = server.run()
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        autopilot.emit(time.monotonic(), "stop", stats=dict(autopilot.stats))
        events.close()
    return status


if __name__ == "__main__":
    sys.exit(main())
