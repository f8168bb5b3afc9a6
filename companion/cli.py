"""The ``armbridge`` command line.

* ``run --config FILE``: the daemon (systemd ``Type=notify`` service or foreground).
* ``demo``: starts the simulated flight controller and the daemon on loopback, sends the arm
  through a few reachable poses, the papers' unreachable target G and a figure-eight, and
  prints per target: solve time, errors, PWM sent and the hand pose the simulator reports.
  With matplotlib installed it also writes a PNG (``--plot PATH``, default
  ``armbridge-demo.png`` in the current directory): targets against the simulator's hand.
* ``goto X Y Z ROLL PITCH YAW``, ``status``, ``park``, ``stop``: clients of a running daemon's
  control socket.
* ``solve X Y Z ROLL PITCH YAW``: one-off IK, no daemon.
* ``check-config FILE``: validate a daemon config and exit.

Exit codes: 0 success; 1 refused (unreachable target, daemon said no); 2 bad input or
configuration; 3 daemon not reachable.
"""

from __future__ import annotations

import argparse
import gc
import json
import logging
import math
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path

from companion import ik
from companion.arm import Arm, Pose
from companion.errors import ConfigError

DEFAULT_SOCKET = os.environ.get("ARMBRIDGE_SOCKET", "/run/armbridge/control.sock")
PAPER_TARGET_G = Pose(-20.0, 3.0, 40.0, 0.0, 10.0, 15.0)  # papers' test target (cm, deg)

# Joint configurations (deg) whose hand poses the demo asks for: reachable by construction.
DEMO_JOINTS_DEG = (
    (30.0, 60.0, -20.0, 45.0, 30.0, 10.0),
    (-45.0, 120.0, 30.0, -30.0, -20.0, 60.0),
    (20.0, 70.0, 50.0, 20.0, 30.0, 10.0),
)

log = logging.getLogger("armbridge")


def _fmt_pose(p: Pose | Sequence[float]) -> str:
    v = p.as_tuple() if isinstance(p, Pose) else tuple(p)
    return "({:.2f}, {:.2f}, {:.2f}) cm  ({:.2f}, {:.2f}, {:.2f}) deg".format(*v)


# -- solve ----------------------------------------------------------------------------------------


def _cmd_solve(args: argparse.Namespace) -> int:
    arm = Arm.from_toml(args.arm) if args.arm else Arm.default()
    target = Pose.from_sequence(args.pose)
    res = ik.solve(
        arm,
        target,
        budget_ms=args.budget_ms,
        seed=args.seed,
        tol_pos_cm=args.tol_pos_cm,
        tol_ori_deg=args.tol_ori_deg,
    )
    print(f"target      {_fmt_pose(target)}")
    print(f"joints_deg  [{', '.join(f'{v:.3f}' for v in res.q_deg)}]")
    print(
        f"pos_err {res.pos_err_cm:.1e} cm  ori_err {res.ori_err_deg:.1e} deg  "
        f"{res.elapsed_ms:.3f} ms  {'REACHED' if res.converged else 'NOT REACHED'}"
    )
    return 0 if res.converged else 1


# -- check-config / run ---------------------------------------------------------------------------


def _cmd_check_config(args: argparse.Namespace) -> int:
    from companion.config import load_config

    cfg = load_config(args.config)
    print(
        f"{args.config}: OK (link {cfg.link.url} {cfg.link.dialect}, arm {cfg.arm.name}, "
        f"outputs {list(cfg.calibration.outputs)})"
    )
    return 0


def _cmd_run(args: argparse.Namespace) -> int:
    from companion.config import load_config
    from companion.control import ControlServer
    from companion.daemon import ArmDaemon
    from companion.systemd import Notifier
    from firmware_interface import LinkError, LinkState

    config = load_config(args.config)  # ConfigError → exit 2, nothing opened or sent
    # The start-up heap (numpy, numba, pymavlink: ~120k objects) never dies. Frozen, the
    # collector's full passes skip it: one took ~55 ms here, long enough to stall the control
    # thread past a 20 ms target slot; after the freeze it takes microseconds.
    gc.freeze()
    stop = threading.Event()
    reload = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    signal.signal(signal.SIGHUP, lambda *_: reload.set())

    notifier = Notifier()
    daemon = ArmDaemon(config)
    server = None
    try:
        if config.control_socket:
            # Before the link opens: a socket path the system refuses is a config error, and
            # nothing has been sent yet. Requests wait in the queue until start().
            try:
                server = ControlServer(config.control_socket, daemon)
            except OSError as exc:
                raise ConfigError(
                    config.source, "control.socket", f"cannot listen on it: {exc.strerror or exc}"
                ) from exc
        try:
            daemon.start()
        except LinkError as exc:
            # E.g. the serial device is not there (yet): say so in one line and fail, so
            # systemd's Restart=on-failure tries again (RestartSec=2 in the shipped unit).
            log.error("cannot open the autopilot link: %s", exc)
            return 1
        except OSError as exc:
            # The link maps transport errors to its own; an OSError left is the signing state
            # file, the only file it writes (its directory may be missing or read-only).
            signing = config.link.signing
            if signing is None or signing.state_path is None:
                raise
            raise ConfigError(
                config.source, "link.signing_state", f"cannot write it: {exc.strerror or exc}"
            ) from exc
        notifier.status("waiting for the autopilot heartbeat")
        ready = False
        ping_s = notifier.watchdog_period_s / 2 if notifier.watchdog_period_s else 1.0
        while not stop.is_set():
            link_up = daemon.link is not None and daemon.link.state is LinkState.UP
            if link_up and not ready:
                ready = True
                notifier.ready("autopilot link up")
                log.info("ready: autopilot link up")
            if reload.is_set():
                reload.clear()
                notifier.reloading()
                try:
                    daemon.reload(load_config(args.config))
                except ConfigError as exc:
                    log.error("reload refused, keeping the running config: %s", exc)
                notifier.ready()
            if daemon.healthy:
                notifier.watchdog()
            s = daemon.status()
            notifier.status(
                f"link {s['link']}; {s['counters']['accepted']} targets accepted, "
                f"{s['counters']['failed'] + s['counters']['denied']} refused"
            )
            stop.wait(min(ping_s, 0.5))
    finally:
        notifier.stopping()
        log.info("stopping%s", " (parking)" if config.park_on_stop else "")
        if server is not None:
            server.close()
        daemon.close(park=config.park_on_stop)
        notifier.close()
    return 0


# -- control-socket clients ---------------------------------------------------------------------


def _client(args: argparse.Namespace, obj: dict) -> int:
    from companion.control import request

    try:
        reply = request(args.socket, obj, timeout_s=args.timeout_s)
    except (OSError, ConnectionError) as exc:
        print(f"armbridge: cannot reach the daemon at {args.socket}: {exc}", file=sys.stderr)
        return 3
    print(json.dumps(reply, indent=2))
    return 0 if reply.get("ok") else 1


# -- demo ---------------------------------------------------------------------------------------


def _wait(predicate: Callable[[], bool], timeout_s: float) -> bool:
    deadline = time.monotonic() + timeout_s
    while not predicate():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.02)
    return True


def write_demo_plot(
    path: str | Path,
    targets: Sequence[tuple[str, Pose, Pose | None]],
    path_targets: Sequence[Pose],
    path_hand: Sequence[Pose],
) -> str:
    """Draw the demo's targets against the simulator's hand and save a PNG at ``path``.

    ``targets``: ``(name, target, hand pose reached or None if refused)``; ``path_targets``
    and ``path_hand``: the figure-eight's points and the hand sampled while it ran. Returns a
    one-line note for the user: where the plot went, or why it was skipped (no matplotlib)."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return "plot skipped: matplotlib is not installed (pip install 'armbridge[plots]')"
    fig, (side, eight) = plt.subplots(1, 2, figsize=(10, 4.2))
    for k, (name, target, hand) in enumerate(targets):
        colour = f"C{k}"
        side.plot(target.x_cm, target.z_cm, "x", color=colour, markersize=9, label=f"{name}")
        if hand is None:
            side.annotate("refused", (target.x_cm, target.z_cm), fontsize=7, color=colour,
                          xytext=(4, 4), textcoords="offset points")
        else:
            side.plot(hand.x_cm, hand.z_cm, "o", mfc="none", color=colour, markersize=9)
            error_cm = math.dist(hand.position_cm, target.position_cm)
            side.annotate(f"{error_cm:.2f} cm", (hand.x_cm, hand.z_cm), fontsize=7,
                          color=colour, xytext=(6, -10), textcoords="offset points")
    side.set_title("targets (x) and the simulator's hand (o), side view", fontsize=9)
    side.set_xlabel("x (cm)")
    side.set_ylabel("z (cm)")
    side.legend(fontsize=7)
    side.set_aspect("equal", adjustable="datalim")
    side.grid(True, alpha=0.3)
    if path_targets:
        eight.plot([p.y_cm for p in path_targets], [p.z_cm for p in path_targets], "-",
                   color="C0", label="figure-eight targets")
    if path_hand:
        eight.plot([p.y_cm for p in path_hand], [p.z_cm for p in path_hand], ".",
                   color="C1", markersize=3, label="simulator's hand (sampled)")
    eight.set_title("figure-eight, front view", fontsize=9)
    eight.set_xlabel("y (cm)")
    eight.set_ylabel("z (cm)")
    eight.legend(fontsize=7)
    eight.set_aspect("equal", adjustable="datalim")
    eight.grid(True, alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return f"plot written to {path}"


def _cmd_demo(args: argparse.Namespace) -> int:
    from companion.config import parse_config
    from companion.daemon import ArmDaemon, Outcome
    from companion.kinematics import rotation_angle
    from sim_servo.query import query

    with tempfile.TemporaryDirectory(prefix="armbridge-demo-") as tmp:
        sim_sock = str(Path(tmp) / "sim.sock")
        sim = subprocess.Popen(
            [sys.executable, "-m", "sim_servo", "--udp", "127.0.0.1:0", "--query-socket", sim_sock],
            stdout=subprocess.PIPE,
            text=True,
        )
        daemon = None
        try:
            url = sim.stdout.readline().strip()
            print(f"simulated flight controller (ArduPilot behaviour) at {url}")
            config = parse_config(
                {
                    "link": {"url": url, "dialect": "ardupilot"},
                    "arm": {"park_deg": [0, 90, 0, 0, 0, 0], "joint_speed_deg_s": 120.0},
                    "solver": {"budget_ms": 20.0, "seed": args.seed},
                    "control": {"rate_hz": 20.0},
                }
            )
            daemon = ArmDaemon(config)
            daemon.start()
            if not daemon.wait_for_autopilot(10.0) or not _wait(
                lambda: os.path.exists(sim_sock), 10.0
            ):
                print("armbridge: the simulator did not come up", file=sys.stderr)
                return 3
            print(
                f"daemon up: arm {config.arm.name}, outputs {list(config.calibration.outputs)}"
                f", {config.rate_hz:g} Hz, {config.joint_speed_deg_s:g} deg/s\n"
            )

            def settled() -> bool:
                return not daemon.status()["moving"] and query(sim_sock, "state")["settled"]

            plotted: list[tuple[str, Pose, Pose | None]] = []

            def report(name: str, target: Pose) -> None:
                reply = daemon.submit("goto", target).result(10.0)
                print(f"{name}: target {_fmt_pose(target)}")
                if reply.solve is not None:
                    s = reply.solve
                    print(
                        f"  solve {s.elapsed_ms:.3f} ms, pos_err {s.pos_err_cm:.1e} cm, "
                        f"ori_err {s.ori_err_deg:.1e} deg"
                    )
                if reply.outcome is not Outcome.ACCEPTED:
                    print(f"  {reply.outcome.value.upper()}: {reply.message}; nothing sent\n")
                    plotted.append((name.split(" (")[0], target, None))
                    return
                _wait(settled, 15.0)
                status = daemon.status()
                hand = Pose(**query(sim_sock, "state")["hand"]["pose"])
                pos = math.dist(hand.position_cm, target.position_cm)
                ori = math.degrees(rotation_angle(target.rotation, hand.rotation))
                print(
                    f"  ACCEPTED; PWM sent (us) {status['last_pwm_us']}, every DO_SET_SERVO "
                    f"acked ({status['counters']['servo_updates']} updates so far)"
                )
                print(f"  sim hand {_fmt_pose(hand)}: {pos:.3f} cm / {ori:.2f} deg from target\n")
                plotted.append((name, target, hand))

            for i, q in enumerate(DEMO_JOINTS_DEG, start=1):
                report(f"pose {i}", config.arm.fk(q))
            report("papers' target G (unreachable within the Table 2 limits)", PAPER_TARGET_G)

            centre = config.arm.fk(DEMO_JOINTS_DEG[2])
            points = []
            for k in range(41):  # 4 s figure-eight, 10 points per second
                s = 2 * math.pi * k / 40
                points.append(
                    (
                        0.1 * k,
                        (
                            centre.x_cm,
                            centre.y_cm + 5 * math.sin(s),
                            centre.z_cm + 2.5 * math.sin(2 * s),
                            centre.roll_deg,
                            centre.pitch_deg,
                            centre.yaw_deg,
                        ),
                    )
                )
            before = daemon.status()["counters"]["servo_updates"]
            reply = daemon.submit("trajectory", points).result(10.0)
            print(f"figure-eight (10 x 5 cm, 4 s, {len(points)} points): {reply.message}")
            hand_path: list[Pose] = []

            def done_sampling() -> bool:
                hand_path.append(Pose(**query(sim_sock, "state")["hand"]["pose"]))
                return daemon.status()["trajectory_points_left"] == 0 and settled()

            _wait(done_sampling, 20.0)
            status = daemon.status()
            hand = Pose(**query(sim_sock, "state")["hand"]["pose"])
            end = Pose(*points[-1][1])
            print(
                f"  {status['counters']['servo_updates'] - before} servo updates; hand ends "
                f"{math.dist(hand.position_cm, end.position_cm):.3f} cm from the last point"
            )
            print(f"\ncounters: {status['counters']}")
            if args.plot:
                path_targets = [Pose(*values) for _, values in points]
                print(write_demo_plot(args.plot, plotted, path_targets, hand_path))
        finally:
            if daemon is not None:
                daemon.close()
            sim.terminate()
            sim.wait(timeout=5)
            sim.stdout.close()
    return 0


# -- parser -------------------------------------------------------------------------------------


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="armbridge", description=__doc__.split("\n")[0])
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = parser.add_subparsers(dest="command", required=True)

    def pose_args(p: argparse.ArgumentParser) -> None:
        p.add_argument(
            "pose",
            nargs=6,
            type=float,
            metavar=("X_CM", "Y_CM", "Z_CM", "ROLL_DEG", "PITCH_DEG", "YAW_DEG"),
        )

    def client_args(p: argparse.ArgumentParser) -> None:
        p.add_argument(
            "--socket",
            default=DEFAULT_SOCKET,
            help=f"daemon control socket (default {DEFAULT_SOCKET}; $ARMBRIDGE_SOCKET)",
        )
        p.add_argument("--timeout-s", type=float, default=10.0)

    p = sub.add_parser("run", help="run the daemon")
    p.add_argument("--config", required=True, help="daemon config TOML")
    p.set_defaults(func=_cmd_run)

    p = sub.add_parser("demo", help="simulator + daemon on loopback, a tour of targets")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument(
        "--plot",
        default="armbridge-demo.png",
        metavar="PATH",
        help="PNG of targets against the simulator's hand, if matplotlib is installed "
        "(default %(default)s; '' for none)",
    )
    p.set_defaults(func=_cmd_demo)

    p = sub.add_parser("check-config", help="validate a daemon config")
    p.add_argument("config")
    p.set_defaults(func=_cmd_check_config)

    p = sub.add_parser("solve", help="one-off IK for a target pose (no daemon)")
    pose_args(p)
    p.add_argument("--arm", help="arm TOML file (default: the papers' arm)")
    p.add_argument("--tol-pos-cm", type=float, default=1e-3)
    p.add_argument("--tol-ori-deg", type=float, default=1e-3)
    p.add_argument("--budget-ms", type=float, default=20.0)
    p.add_argument("--seed", type=int, default=0)
    p.set_defaults(func=_cmd_solve)

    p = sub.add_parser("goto", help="send the hand to a pose (running daemon)")
    pose_args(p)
    client_args(p)
    p.set_defaults(func=lambda a: _client(a, {"cmd": "goto", "pose": a.pose}))
    for name in ("status", "park", "stop"):
        p = sub.add_parser(name, help=f"{name} (running daemon)")
        client_args(p)
        p.set_defaults(func=lambda a, name=name: _client(a, {"cmd": name}))
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.INFO,
        format="%(levelname)s %(name)s: %(message)s",  # one line per event; journald timestamps
        stream=sys.stderr,
    )
    try:
        return int(args.func(args))
    except (ConfigError, ValueError) as exc:
        print(f"armbridge: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
