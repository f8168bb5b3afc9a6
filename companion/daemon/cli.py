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
import json
import logging
import os
import sys
from collections.abc import Sequence

from companion import __version__
from companion.errors import ConfigError

# Only the standard library and companion.errors at the top: ``--help``, ``--version`` and the
# socket clients must start in a blink, so the solver (numba) and pymavlink are imported by the
# subcommands that need them.

POSE_FIELDS = ("x_cm", "y_cm", "z_cm", "roll_deg", "pitch_deg", "yaw_deg")

DEFAULT_SOCKET = os.environ.get("ARMBRIDGE_SOCKET", "/run/armbridge/control.sock")


# -- solve ----------------------------------------------------------------------------------------


def _cmd_solve(args: argparse.Namespace) -> int:
    from companion import ik
    from companion.daemon.demo import _fmt_pose
    from companion.kinematics import Arm, Pose

    arm = Arm.from_toml(args.arm) if args.arm else Arm.default()
    target = Pose.from_sequence(_pose(args))
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
    from companion.daemon.config import load_config

    cfg = load_config(args.config)
    print(
        f"{args.config}: OK (link {cfg.link.url} {cfg.link.dialect}, arm {cfg.arm.name}, "
        f"outputs {list(cfg.calibration.outputs)})"
    )
    return 0


# -- control-socket clients ---------------------------------------------------------------------


def _client(args: argparse.Namespace, obj: dict) -> int:
    from companion.daemon.client import request

    try:
        reply = request(args.socket, obj, timeout_s=args.timeout_s)
    except (OSError, ConnectionError) as exc:
        print(f"armbridge: cannot reach the daemon at {args.socket}: {exc}", file=sys.stderr)
        return 3
    print(json.dumps(reply, indent=2))
    return 0 if reply.get("ok") else 1


def _cmd_run(args: argparse.Namespace) -> int:
    from companion.daemon.run import run

    return run(args.config)


def _cmd_demo(args: argparse.Namespace) -> int:
    from companion.daemon.demo import demo

    return demo(seed=args.seed, plot=args.plot)


def _pose(args: argparse.Namespace) -> list[float]:
    return [getattr(args, name) for name in POSE_FIELDS]


# -- parser -------------------------------------------------------------------------------------


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="armbridge", description=(__doc__ or "").split("\n")[0])
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    parser.add_argument("--version", action="version", version=f"armbridge {__version__}")
    sub = parser.add_subparsers(dest="command", required=True)

    def pose_args(p: argparse.ArgumentParser) -> None:
        # Six named positionals rather than nargs=6 with a tuple metavar, which argparse cannot
        # format in --help (ValueError: too many values to unpack).
        for name, unit in zip(POSE_FIELDS, ("cm", "cm", "cm", "deg", "deg", "deg"), strict=True):
            p.add_argument(name, type=float, help=f"{name.split('_')[0]} of the hand, {unit}")

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
    p.set_defaults(func=lambda a: _client(a, {"cmd": "goto", "pose": _pose(a)}))
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
