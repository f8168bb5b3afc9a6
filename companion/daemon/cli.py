"""The ``armbridge`` command line.

* ``run --config FILE``: the daemon (systemd ``Type=notify`` service or foreground).
* ``demo``: starts the simulated flight controller and the daemon on loopback, sends the arm
  through a few reachable poses, the papers' unreachable target G and a figure-eight, and
  prints per target: solve time, errors, PWM sent and the hand pose the simulator reports.
  With matplotlib installed it also writes a PNG (``--plot PATH``, default
  ``armbridge-demo.png`` in the current directory): targets against the simulator's hand.
* ``goto X Y Z ROLL PITCH YAW [--wait]``, ``trajectory FILE [--wait]``, ``status [--json]
  [--watch [S]]``, ``park``, ``stop``, ``resume``: clients of a running daemon's control
  socket.
* ``solve X Y Z ROLL PITCH YAW``: one-off IK, no daemon.
* ``check-config FILE``: validate a daemon config and exit.
* ``doctor --config FILE``: check the flight controller's setup against the config, item by item
  with the fix (:mod:`companion.daemon.doctor`); exit 1 if an item failed.

Exit codes: 0 success; 1 refused (unreachable target, daemon said no, ``--wait`` timed out);
2 bad input or configuration; 3 daemon not reachable. ``-v``/``-q``/``--log-level`` work before
or after the verb.
"""

from __future__ import annotations

import argparse
import csv
import functools
import json
import logging
import math
import os
import sys
import time
from collections.abc import Mapping, Sequence
from typing import Any, TextIO

from companion import __version__
from companion.errors import ConfigError

# Only the standard library and companion.errors at the top: ``--help``, ``--version`` and the
# socket clients must start in a blink, so the solver (numba) and pymavlink are imported by the
# subcommands that need them.

POSE_FIELDS = ("x_cm", "y_cm", "z_cm", "roll_deg", "pitch_deg", "yaw_deg")

DEFAULT_SOCKET = os.environ.get("ARMBRIDGE_SOCKET", "/run/armbridge/control.sock")


# -- solve ----------------------------------------------------------------------------------------


#: ``solve``'s search flags: the ``[solver]`` keys of the daemon config, checked alike.
SEARCH_FLAGS = (
    "method",
    "pop_size",
    "mutation_f",
    "crossover_cr",
    "lm_iterations",
    "stall_generations",
    "stall_gain",
)


def _cmd_solve(args: argparse.Namespace) -> int:
    from companion import ik
    from companion.daemon.config import search_changes
    from companion.daemon.demo import _fmt_pose
    from companion.kinematics import Arm, Pose
    from tomlfields import FieldError, Table

    class FlagError(FieldError):
        """A search flag out of range, named as typed (``--pop-size``)."""

        def __init__(self, source: str, field: str, problem: str) -> None:
            super().__init__(source, "--" + field.replace("_", "-"), problem)

    flags = {key: getattr(args, key) for key in SEARCH_FLAGS if getattr(args, key) is not None}
    changes = search_changes(Table(flags, "", error=FlagError))
    settings = ik.method_settings(flags.get("method", ik.DEFAULT_METHOD), **dict(changes))

    if args.arm and args.arm.lower().endswith(".urdf"):
        arm = Arm.from_urdf(args.arm, tip_link=args.tip_link)
    elif args.tip_link is not None:
        raise ValueError("--tip-link goes with a URDF --arm file")
    else:
        arm = Arm.from_toml(args.arm) if args.arm else Arm.default()
    target = Pose.from_sequence(_pose(args))
    res = ik.solve(
        arm,
        target,
        budget_ms=args.budget_ms,
        ceiling_ms=args.ceiling_ms,
        seed=args.seed,
        tol_pos_cm=args.tol_pos_cm,
        tol_ori_deg=args.tol_ori_deg,
        settings=settings,
    )
    print(f"target      {_fmt_pose(target)}")
    print(f"joints_deg  [{', '.join(f'{v:.3f}' for v in res.q_deg)}]")
    print(
        f"pos_err {res.pos_err_cm:.1e} cm  ori_err {res.ori_err_deg:.1e} deg  "
        f"{res.elapsed_ms:.3f} ms  "
        + ("REACHED" if res.converged else f"NOT REACHED ({res.stop_reason.value})")
    )
    return 0 if res.converged else 1


# -- check-config / run ---------------------------------------------------------------------------


def _cmd_check_config(args: argparse.Namespace) -> int:
    from companion.daemon.config import link_budget_of, load_config
    from firmware_interface.transport import parse_url

    cfg = load_config(args.config)
    print(
        f"{args.config}: OK (link {cfg.link.url} {cfg.link.dialect}, arm {cfg.arm.name}, "
        f"outputs {list(cfg.calibration.outputs)})"
    )
    for warning in motor_output_warnings(cfg.link.dialect, cfg.calibration.outputs):
        print(f"{args.config}: warning: {warning}", file=sys.stderr)
    if cfg.keepout:
        names = ", ".join(v.name for v in cfg.keepout)
        print(f"{args.config}: keep-out: {names} (margin {cfg.keepout_margin_cm:g} cm)")
    else:
        print(
            f"{args.config}: warning: no [[keepout]] volumes: nothing keeps the arm off the "
            "vehicle (see the example config)",
            file=sys.stderr,
        )
    budget = link_budget_of(cfg)
    if not budget.fits:  # a serial link too slow for this dialect at control.rate_hz
        print(f"{args.config}: warning: {budget.message}", file=sys.stderr)
    spec = parse_url(cfg.link.url)
    if spec.kind == "serial" and not os.path.exists(spec.address):
        print(
            f"{args.config}: warning: link.url: {spec.address} is not there now (the flight "
            "controller not plugged in?): run serves and waits for it",
            file=sys.stderr,
        )
    return 0


def _cmd_doctor(args: argparse.Namespace) -> int:
    from companion.daemon import doctor
    from companion.daemon.config import load_config
    from companion.daemon.instance_lock import AlreadyRunning, InstanceLock, lock_path

    cfg = load_config(args.config)
    # The service holds the link (a serial port has one reader): doctor runs beside it never.
    lock = InstanceLock(lock_path(args.config, cfg.control_socket))
    try:
        lock.acquire()
    except AlreadyRunning as exc:
        print(
            f"armbridge doctor: {exc}: it holds the link. Stop it first "
            "(sudo systemctl stop armbridge), run doctor, then start it again.",
            file=sys.stderr,
        )
        return 3
    except OSError:
        pass  # no runtime directory yet (the service never ran): nothing holds the link
    try:
        findings = doctor.gather(cfg, timeout_s=args.timeout_s, listen_s=args.listen_s)
    finally:
        lock.release()
    checks = doctor.evaluate(cfg, findings)
    if args.json:
        print(json.dumps({"url": findings.url, "checks": [c.as_dict() for c in checks]}, indent=2))
    else:
        print(doctor.format_report(findings, checks))
    return 1 if any(c.verdict is doctor.Verdict.FAIL for c in checks) else 0


#: ArduCopter's default output functions: motors on outputs 1-4 (quad), 1-6 (hexa), 1-8 (octa).
_MOTOR_FRAMES = ((4, "quad"), (6, "hexa"), (8, "octa"))


def motor_output_warnings(dialect: str, outputs: Sequence[int]) -> list[str]:
    """ArduPilot: a joint on an output that is a motor by default on a common multirotor frame.
    The autopilot refuses DO_SET_SERVO there ("Channel N is already in use") unless
    SERVOn_FUNCTION = 0, and on a vehicle where it is a motor, it must not be an arm joint.
    (PX4 outputs are actuator slots 1-6 mapped by PWM_MAIN_FUNCn: nothing to tell here.)"""
    if not dialect.startswith("ardupilot"):  # ardupilot and ardupilot-lua
        return []
    warnings = []
    for output in outputs:
        frames = [name for count, name in _MOTOR_FRAMES if output <= count]
        if frames:
            warnings.append(
                f"output {output} drives a motor by default on a {'/'.join(frames)} frame: "
                f"only if this vehicle has none there, set SERVO{output}_FUNCTION = 0; "
                "otherwise map this joint to an output above 8"
            )
    return warnings


# -- control-socket clients ---------------------------------------------------------------------


class _Unreachable(Exception):
    """The daemon's socket could not be reached (exit 3)."""


class _BadReply(Exception):
    """What answered on the socket is not the daemon's protocol (exit 1)."""


def _ask(args: argparse.Namespace, obj: dict[str, Any]) -> dict[str, Any]:
    from companion.daemon.client import request

    try:
        reply = request(args.socket, obj, timeout_s=args.timeout_s)
    except (OSError, ConnectionError) as exc:
        raise _Unreachable(f"cannot reach the daemon at {args.socket}: {exc}") from exc
    except ValueError as exc:  # not JSON: not our daemon on that socket
        raise _BadReply(f"{args.socket} answered something that is not JSON: {exc}") from exc
    if not isinstance(reply, dict) or not isinstance(reply.get("status", {}), dict):
        raise _BadReply(f"unexpected reply from {args.socket}: {json.dumps(reply)[:200]}")
    return reply


def _client(args: argparse.Namespace, obj: dict[str, Any]) -> int:
    reply = _ask(args, obj)
    print(json.dumps(reply, indent=2))
    if reply.get("ok") and getattr(args, "wait", False):
        return _wait_until_still(args, trajectory=obj.get("cmd") == "trajectory")
    return 0 if reply.get("ok") else 1


def _wait_until_still(args: argparse.Namespace, *, trajectory: bool = False) -> int:
    """``--wait``: poll status until the arm stops moving with no trajectory point left (exit
    0, the hand printed) or ``--timeout-s`` passes (exit 1). A ``trajectory`` the daemon
    abandoned (a point out of reach, the motion stopped) exits 1 saying why."""
    deadline = time.monotonic() + args.timeout_s
    while True:
        status = _ask(args, {"cmd": "status"}).get("status") or {}
        aborted = status.get("trajectory_aborted") if trajectory else None
        if aborted:
            print(f"armbridge: the daemon abandoned the trajectory: {aborted}", file=sys.stderr)
            return 1
        if not status.get("moving", True) and not status.get("trajectory_points_left"):
            print(f"still: hand {_fmt_hand(status.get('hand'))}")
            return 0
        if time.monotonic() >= deadline:
            print(f"armbridge: still moving after {args.timeout_s:g} s", file=sys.stderr)
            return 1
        time.sleep(0.05)


def _cmd_status(args: argparse.Namespace) -> int:
    while True:
        reply = _ask(args, {"cmd": "status"})
        if args.json:
            print(json.dumps(reply, indent=2), flush=True)
        else:
            if args.watch is not None and sys.stdout.isatty():
                print("\033[H\033[J", end="")  # clear the screen between frames
            try:
                text = format_status(reply.get("status") or {})
            except (TypeError, ValueError, KeyError, IndexError, AttributeError) as exc:
                raise _BadReply(
                    f"a status reply this version cannot show ({type(exc).__name__}: {exc}); "
                    "`armbridge status --json` prints it as it came"
                ) from exc
            print(text, flush=True)
        if args.watch is None:
            return 0 if reply.get("ok") else 1
        try:
            time.sleep(args.watch)
        except KeyboardInterrupt:
            return 0


def _fmt_hand(hand: dict[str, float] | None) -> str:
    if not hand:
        return "unknown"
    return "  ".join(f"{k.split('_')[0]} {v:8.2f} {k.split('_')[1]}" for k, v in hand.items())


def _fmt(value: Any, spec: str) -> str:
    if value is None:
        return "-".rjust(len(format(0.0, spec)))  # as wide as a number would be
    return format(value, spec)


def format_status(status: dict[str, Any]) -> str:
    """The daemon's status for a person: link and autopilot, the hand, per joint its angle,
    goal, output, acknowledged PWM and state, the last target and the counters."""
    autopilot = status.get("autopilot")
    boot_ms = status.get("autopilot_boot_ms")
    flags = [name for name in ("moving", "holding", "stopped") if status.get(name)] or ["still"]
    lines = [
        f"link {status.get('link', '?')}  autopilot "
        + (f"{autopilot[0]}/{autopilot[1]}" if autopilot else "none yet")
        + (f" (up {boot_ms / 1000:.1f} s)" if boot_ms is not None else "")
        + f"  {' '.join(flags)}",
    ]
    if status.get("link_signing_problem"):
        lines.append(f"  signing: {status['link_signing_problem']}")
    if not autopilot:
        lines.append(
            "  no autopilot heard yet: targets are refused until it is "
            "(`journalctl -u armbridge` says what the daemon waits for; `armbridge doctor`)"
        )
    elif status.get("link") == "up" and status.get("autopilot_heard_us") is False:
        lines.append("  the autopilot has not answered us yet: it may not route targets to us")
    if status.get("stopped"):
        lines.append(
            f"  stopped by {status.get('stopped_by') or '?'}: the arm holds until "
            "`armbridge resume` (or a goto, trajectory or park from here)"
        )
    lines += [
        f"hand  {_fmt_hand(status.get('hand'))}",
        "joint  angle_deg   goal_deg  output  pwm_us  state",
    ]
    current = status.get("current_deg") or []
    goal = status.get("goal_deg") or [None] * len(current)
    outputs = list((status.get("outputs") or {}).items())
    for i, angle in enumerate(current):
        output, state = outputs[i] if i < len(outputs) else ("?", {})
        reason = f" ({state['reason']})" if state.get("reason") else ""
        lines.append(
            f"{i + 1:>5}  {_fmt(angle, '9.2f')}  {_fmt(goal[i], '9.2f')}  {output:>6}  "
            f"{_fmt(state.get('pwm_us'), '>6')}  {state.get('state', '?')}{reason}"
        )
    last = status.get("last_target")
    if last:
        timing = last.get("timing") or {}
        took = ""
        if "acked_s" in timing and "received_s" in timing:
            took_ms = (timing["acked_s"] - timing["received_s"]) * 1e3
            took = f", received → acknowledged {took_ms:.1f} ms"
        lines.append(
            "last target  ("
            + ", ".join(f"{v:.2f}" for v in last.get("pose", []))
            + f")  {_target_word(status, last)}, "
            f"solve {last.get('solve_ms', math.nan):.2f} ms{took}"
        )
    counters = status.get("counters") or {}
    shown = [f"{k} {v}" for k, v in counters.items() if v]
    lines.append("counters  " + (", ".join(shown) if shown else "all 0"))
    return "\n".join(lines)


#: ``armbridge shipped NAME``: (package, resource) of each file shipped for the user to install.
SHIPPED = {
    "unit": ("companion.daemon", "examples/armbridge.service"),
    "config": ("companion.daemon", "examples/armbridge.toml"),
    "lua": ("firmware_interface", "lua/armbridge_servo.lua"),
}


def _cmd_shipped(args: argparse.Namespace) -> int:
    import importlib.resources

    package, resource = SHIPPED[args.name]
    sys.stdout.write(importlib.resources.files(package).joinpath(resource).read_text("utf-8"))
    return 0


def _target_word(status: dict[str, Any], last: dict[str, Any]) -> str:
    """What became of the last target, as its answer and the outputs say: "reached" only for
    one accepted, with the arm no longer moving and its outputs live."""
    outcome = last.get("outcome")
    if not last.get("converged"):
        return "NOT reachable"
    if outcome is None:
        return "waiting for its answer"
    if outcome != "accepted":
        return f"{str(outcome).upper()}: {last.get('answer') or ''}".rstrip(": ")
    if status.get("moving"):
        return "moving"
    if not status.get("outputs_live"):
        return "accepted, outputs not live"
    return "reached"


def read_trajectory(path: str) -> list[list[float]]:
    """A trajectory file: JSON (a list of ``[t_s, x_cm, y_cm, z_cm, roll_deg, pitch_deg,
    yaw_deg]`` rows, or ``{"points": [...]}``) or CSV (the same seven columns per row; a header
    row, blank lines and ``#`` comments are skipped). Times are seconds from receipt, never
    decreasing. At most :data:`~companion.daemon.requests.MAX_TRAJECTORY_POINTS` points: a CSV
    is read row by row and refused at the first point past it, whatever the file's size.
    ``ValueError`` names the row and the column."""
    from companion.daemon.requests import MAX_TRAJECTORY_POINTS

    too_many = f"{path}: more than {MAX_TRAJECTORY_POINTS} points (the daemon's limit)"
    with open(path, encoding="utf-8", newline="") as file:
        head = file.read(64)
        file.seek(0)
        rows: list[tuple[str, Any]] = []
        if head.lstrip().startswith(("[", "{")):
            # A JSON point takes at most ~200 bytes; anything larger is refused unread.
            if os.fstat(file.fileno()).st_size > MAX_TRAJECTORY_POINTS * 256:
                raise ValueError(too_many)
            try:
                data = json.load(file)
            except RecursionError:
                raise ValueError(f"{path}: JSON nested too deeply") from None
            except json.JSONDecodeError as exc:
                raise ValueError(f"{path}: not valid JSON: {exc}") from None
            if isinstance(data, dict):
                data = data.get("points")
            if not isinstance(data, list):
                raise ValueError(f'{path}: JSON must be a list of rows or {{"points": [...]}}')
            if len(data) > MAX_TRAJECTORY_POINTS:
                raise ValueError(too_many)
            rows = [(f"point {i}", row) for i, row in enumerate(data)]
        else:
            for number, row in enumerate(csv.reader(file), start=1):
                if not row or not "".join(row).strip() or row[0].lstrip().startswith("#"):
                    continue
                if not rows and not _numeric(row[0]):
                    continue  # a header
                if len(rows) == MAX_TRAJECTORY_POINTS:
                    raise ValueError(too_many)
                rows.append((f"line {number}", row))
    points: list[list[float]] = []
    for where, row in rows:
        if not isinstance(row, list) or len(row) != 7:
            raise ValueError(f"{path}: {where}: expected 7 values ({TRAJECTORY_COLUMNS})")
        point: list[float] = []
        for name, value in zip(TRAJECTORY_COLUMNS.split(", "), row, strict=True):
            try:
                coordinate = float(value)
            except (TypeError, ValueError, OverflowError):
                raise ValueError(f"{path}: {where}: {name} = {value!r} is not a number") from None
            if not math.isfinite(coordinate):
                raise ValueError(f"{path}: {where}: {name} = {value!r} is not finite")
            point.append(coordinate)
        if points and point[0] < points[-1][0]:
            raise ValueError(
                f"{path}: {where}: t_s = {point[0]:g} after {points[-1][0]:g}: times must "
                "not go back from row to row"
            )
        points.append(point)
    if not points:
        raise ValueError(f"{path}: no points")
    return points


TRAJECTORY_COLUMNS = "t_s, x_cm, y_cm, z_cm, roll_deg, pitch_deg, yaw_deg"


def _numeric(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def _cmd_trajectory(args: argparse.Namespace) -> int:
    try:
        points = read_trajectory(args.file)
    except OSError as exc:
        raise ValueError(f"cannot read {args.file}: {exc.strerror}") from None
    return _client(args, {"cmd": "trajectory", "points": points})


def _cmd_run(args: argparse.Namespace) -> int:
    from companion.daemon.run import run

    return run(args.config)


def _cmd_demo(args: argparse.Namespace) -> int:
    from companion.daemon.demo import demo

    return demo(seed=args.seed, plot=args.plot)


def _pose(args: argparse.Namespace) -> list[float]:
    return [getattr(args, name) for name in POSE_FIELDS]


# -- parser -------------------------------------------------------------------------------------


def _logging_options(defaults: bool) -> argparse.ArgumentParser:
    """-v/-q/--log-level, accepted before the verb (``defaults``) and after it (there they
    leave the value alone unless given)."""
    parent = argparse.ArgumentParser(add_help=False)
    unset: dict[str, Any] = {} if defaults else {"default": argparse.SUPPRESS}
    group = parent.add_argument_group("logging")
    group.add_argument(
        "-v", "--verbose", action="store_true", help="debug logging (--log-level DEBUG)", **unset
    )
    group.add_argument(
        "-q", "--quiet", action="store_true", help="warnings and errors only", **unset
    )
    group.add_argument(
        "--log-level",
        choices=("DEBUG", "INFO", "WARNING", "ERROR"),
        type=str.upper,
        help="log level (default INFO)",
        **unset,
    )
    return parent


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="armbridge",
        description=(__doc__ or "").split("\n")[0],
        parents=[_logging_options(defaults=True)],
    )
    parser.add_argument("--version", action="version", version=f"armbridge {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    logging_after = _logging_options(defaults=False)

    def verb(name: str, help_text: str) -> argparse.ArgumentParser:
        return sub.add_parser(name, help=help_text, description=help_text, parents=[logging_after])

    def pose_args(p: argparse.ArgumentParser) -> None:
        # Six named positionals rather than nargs=6 with a tuple metavar, which argparse cannot
        # format in --help (ValueError: too many values to unpack).
        for name, unit in zip(POSE_FIELDS, ("cm", "cm", "cm", "deg", "deg", "deg"), strict=True):
            p.add_argument(name, type=_finite, help=f"{name.split('_')[0]} of the hand, {unit}")

    def client_args(p: argparse.ArgumentParser) -> None:
        p.add_argument(
            "--socket",
            default=DEFAULT_SOCKET,
            help=f"daemon control socket (default {DEFAULT_SOCKET}; $ARMBRIDGE_SOCKET)",
        )
        p.add_argument(
            "--timeout-s",
            type=_positive_seconds,
            default=10.0,
            help="give up waiting for the daemon (and for --wait) after this long "
            "(default %(default)s)",
        )

    def wait_arg(p: argparse.ArgumentParser) -> None:
        p.add_argument(
            "--wait",
            action="store_true",
            help="once accepted, wait until the arm stops moving and print where the hand is",
        )

    p = verb("run", "run the daemon (the systemd service, or in the foreground)")
    p.add_argument("--config", required=True, help="daemon config TOML")
    p.set_defaults(func=_cmd_run)

    p = verb("demo", "simulator + daemon on loopback, a tour of targets")
    p.add_argument("--seed", type=int, default=0, help="the solver's seed (default 0)")
    p.add_argument(
        "--plot",
        default="armbridge-demo.png",
        metavar="PATH",
        help="PNG of targets against the simulator's hand, if matplotlib is installed "
        "(default %(default)s; '' for none)",
    )
    p.set_defaults(func=_cmd_demo)

    p = verb("shipped", "print a file shipped in the package (the unit, the example config)")
    p.add_argument(
        "name",
        choices=sorted(SHIPPED),
        help="unit: the systemd unit; config: the example config, every field with its "
        "default; lua: ArduPilot's Lua bridge script (for the SD card's APM/scripts/)",
    )
    p.set_defaults(func=_cmd_shipped)

    p = verb("check-config", "validate a daemon config as `run` would, then exit")
    p.add_argument("config", help="daemon config TOML")
    p.set_defaults(func=_cmd_check_config)

    p = verb("doctor", "check the flight controller's setup against the config (service stopped)")
    p.add_argument("--config", required=True, help="daemon config TOML")
    p.add_argument(
        "--timeout-s",
        type=_positive_seconds,
        default=10.0,
        help="wait this long for the autopilot's heartbeat (default %(default)s)",
    )
    p.add_argument(
        "--listen-s",
        type=_positive_seconds,
        default=3.0,
        help="listen at least this long for a ground station routed to us (default %(default)s)",
    )
    p.add_argument("--json", action="store_true", help="the checks as JSON")
    p.set_defaults(func=_cmd_doctor)

    p = verb("solve", "one-off IK for a target pose (no daemon)")
    pose_args(p)
    p.add_argument("--arm", help="arm file, TOML or .urdf (default: the papers' arm)")
    p.add_argument(
        "--tip-link",
        help="URDF: the link the chain ends at (default: the end of its longest moving chain)",
    )
    p.add_argument("--tol-pos-cm", type=float, default=1e-3, help="default %(default)s")
    p.add_argument("--tol-ori-deg", type=float, default=1e-3, help="default %(default)s")
    p.add_argument(
        "--budget-ms", type=float, default=20.0, help="CPU time of the search (default %(default)s)"
    )
    p.add_argument(
        "--ceiling-ms",
        type=float,
        help="wall-clock bound of the solve, however busy the machine (default 4 x the budget)",
    )
    p.add_argument("--seed", type=int, default=0, help="the solver's seed (default 0)")
    search = p.add_argument_group(
        "search", "as the daemon config's [solver] keys; absent, the method's own settings"
    )
    search.add_argument(
        "--method",
        help="restarts (default: least squares from the best of NP fresh draws, again and "
        "again), memetic (DE generations with least-squares steps) or de (the papers' DE, no "
        "least squares)",
    )
    search.add_argument(
        "--pop-size", type=int, help="NP: draws per restart, DE's population [4, 100]"
    )
    search.add_argument("--mutation-f", type=float, help="DE scale factor F (0, 2] (DE methods)")
    search.add_argument(
        "--crossover-cr", type=float, help="DE crossover probability Cr [0, 1] (DE methods)"
    )
    search.add_argument(
        "--lm-iterations",
        type=int,
        help="least-squares steps per refinement [0, 100] (restarts, memetic)",
    )
    search.add_argument(
        "--stall-generations",
        type=int,
        help="generations without progress before a restart [1, 10000] (DE methods)",
    )
    search.add_argument(
        "--stall-gain",
        type=float,
        help="progress: the best cost cut below this times what it was [0, 1] (DE methods)",
    )
    p.set_defaults(func=_cmd_solve)

    p = verb("goto", "send the hand to a pose (running daemon)")
    pose_args(p)
    client_args(p)
    wait_arg(p)
    p.add_argument(
        "--mode",
        choices=("pose", "position", "position_axis"),
        default="pose",
        help="what must be met: the whole pose (default), the position only, or the position "
        "with the hand's z axis along the pose's (roll about it free)",
    )
    p.add_argument(
        "--frame",
        choices=("base", "local_ned"),
        default="base",
        help="the pose's frame: the arm's base (default), or the world (LOCAL_NED, "
        "north-east-down from the autopilot's origin, cm): the hand is held there while the "
        "vehicle moves (needs [world] enabled)",
    )
    p.set_defaults(
        func=lambda a: _client(
            a,
            {"cmd": "goto", "pose": _pose(a)}
            | ({"mode": a.mode} if a.mode != "pose" else {})
            | ({"frame": a.frame} if a.frame != "base" else {}),
        )
    )

    p = verb("trajectory", "send a timed list of hand poses (running daemon)")
    p.add_argument(
        "file",
        help=f"CSV or JSON, one row per point: {TRAJECTORY_COLUMNS} (t_s from receipt)",
    )
    client_args(p)
    wait_arg(p)
    p.set_defaults(func=_cmd_trajectory)

    p = verb("status", "what the daemon and the autopilot report (running daemon)")
    client_args(p)
    p.add_argument("--json", action="store_true", help="the raw reply, as JSON")
    p.add_argument(
        "--watch",
        type=_positive_seconds,
        nargs="?",
        const=1.0,
        metavar="S",
        help="refresh every S seconds (default 1) until Ctrl-C",
    )
    p.set_defaults(func=_cmd_status)

    for name, help_text in (
        ("park", "move the arm to its park pose (running daemon)"),
        (
            "stop",
            "halt the arm and hold it until `resume` (running daemon; the daemon keeps "
            "running; a goto, trajectory or park from here also resumes)",
        ),
        ("resume", "let the arm move again after a stop (running daemon)"),
    ):
        p = verb(name, help_text)
        client_args(p)
        p.set_defaults(func=lambda a, name=name: _client(a, {"cmd": name}))
    return parser


def _finite(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"invalid float value: {text!r}") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"{text!r} is not a finite number")
    return value


def _positive_seconds(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number of seconds") from None
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"{text!r} must be a positive number of seconds")
    return value


@functools.cache
def _parser() -> argparse.ArgumentParser:
    return build_parser()  # ~10 ms to build (a parser per verb): once per process


#: The time of day a log line starts with outside journald (:func:`log_format`), to which
#: ``%(msecs)03d`` adds the milliseconds.
LOG_DATE_FORMAT = "%Y-%m-%d %H:%M:%S"


def log_format(environ: Mapping[str, str], stream: TextIO) -> str:
    """One line per event. Under systemd with ``stream`` going to the journal (it is the
    ``JOURNAL_STREAM`` systemd names, device:inode), journald stamps each line; elsewhere (a
    terminal, a file a bench keeps) the line starts with the time of day to the millisecond."""
    device, _, inode = environ.get("JOURNAL_STREAM", "").partition(":")
    try:
        st = os.fstat(stream.fileno())
    except (OSError, ValueError, AttributeError):  # not a file (a test's StringIO)
        st = None
    if st is not None and device.isdigit() and inode.isdigit():
        if (st.st_dev, st.st_ino) == (int(device), int(inode)):
            return "%(levelname)s %(name)s: %(message)s"
    return "%(asctime)s.%(msecs)03d %(levelname)s %(name)s: %(message)s"


def main(argv: Sequence[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    level = args.log_level or ("DEBUG" if args.verbose else "WARNING" if args.quiet else "INFO")
    logging.basicConfig(
        level=level,
        format=log_format(os.environ, sys.stderr),
        datefmt=LOG_DATE_FORMAT,
        stream=sys.stderr,
    )
    try:
        return int(args.func(args))
    except (ConfigError, ValueError) as exc:
        print(f"armbridge: error: {exc}", file=sys.stderr)
        return 2
    except _Unreachable as exc:
        print(f"armbridge: {exc}", file=sys.stderr)
        return 3
    except _BadReply as exc:
        print(f"armbridge: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
