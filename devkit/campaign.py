"""The reliability campaign's machinery, inputs side: adversarial targets, MAVLink
input fuzz, config fuzz.

The CI-sized tests (``tests/integration/test_reliability.py``, ``tests/daemon/test_config_fuzz.py``)
run these functions at a small size; ``python -m bench.reliability`` runs them longer and writes
a Markdown report. It lives here, not in ``bench/``, because tests never import ``bench``.

1. **Targets.** Seeded adversarial targets (non-finite, wrong arity and types, extreme finite
   magnitudes, out of the workspace, reachable, angle-wrapped, near the joint limits) go through
   the real :class:`~companion.daemon.ArmDaemon` (``submit("goto", ...)``), linked over UDP to a
   ``sim_servo`` subprocess. Every PWM the simulator received (its event log and its state
   query) and the daemon's own status is checked against the calibration.
2. **MAVLink fuzz.** ``armbridge run`` as a subprocess against a scripted autopilot (real UDP):
   random bytes, truncated and corrupted frames, valid frames of every ardupilotmega message
   type with random fields, commands with wrong target ids, USER_1 for someone else. The
   daemon must stay up (control socket answers, link up), send no servo command, and keep its
   resident memory (VmRSS) flat.
3. **Config fuzz.** Every field of the daemon config gets wrong types and out-of-range values,
   plus unknown keys, missing sections, broken TOML and unreadable files: ``check-config`` must
   exit 2 naming the field.
"""

from __future__ import annotations

import contextlib
import copy
import datetime
import functools
import gc
import io
import math
import os
import select
import socket
import time
import tomllib
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from companion.daemon import cli
from companion.daemon import config as config_module
from companion.daemon.config import parse_config
from companion.daemon.service import ArmDaemon, Outcome
from companion.ik import warm_up
from companion.kinematics.arm import Arm, Pose
from devkit.config import toml_document
from devkit.daemon_process import NOT_SERVING, DaemonProcess, run_daemon
from devkit.mavlink_peer import ScriptedPeer, UdpEndpoint
from devkit.sim_process import SimProcess
from firmware_interface import ArmCalibration

WAIT_S = 10.0
OUR_COMPONENT = mavlink.MAV_COMP_ID_ONBOARD_COMPUTER  # 191, the daemon's default
AUTOPILOT_SYSTEM = 1


def start_sim(directory: Path, *extra: str) -> SimProcess:
    """The simulated flight controller on UDP; returns once its query socket answers."""
    return SimProcess(directory, "--udp", "127.0.0.1:0", *extra)


# ---------------------------------------------------------------------------------------------
# 1. Adversarial targets through the daemon's target path
# ---------------------------------------------------------------------------------------------

#: Share of each category in a campaign of N targets (sums to 1).
TARGET_MIX = {
    "non_finite": 0.15,  # NaN / +-inf in one or more slots
    "wrong_arity": 0.08,  # 0-5 or 7-12 numbers
    "wrong_types": 0.15,  # strings, None, nested lists, bools, bytes, dicts, 10**400, ...
    "extreme_finite": 0.17,  # 1e308, subnormals, -0.0, random magnitudes 1e-320 .. 1e308
    "out_of_workspace": 0.12,  # finite, farther from the base than the arm reaches
    "reachable": 0.15,  # FK of random in-limit joints
    "angle_wrapped": 0.05,  # reachable, with roll/pitch/yaw shifted by whole turns
    "near_boundary": 0.13,  # FK of joints at, just inside or just outside the limits
}

#: Outcomes each category may end in. Everything invalid must be DENIED (it is checked before
#: the link); nothing out of reach may be ACCEPTED. TEMPORARILY_REJECTED is allowed only where
#: the link is consulted, in case it drops under load.
ALLOWED_OUTCOMES = {
    "non_finite": {Outcome.DENIED},
    "wrong_arity": {Outcome.DENIED},
    "wrong_types": {Outcome.DENIED},
    # A solved target is CANCELLED when the next one replaces it before its first step went out.
    "extreme_finite": {
        Outcome.FAILED,
        Outcome.ACCEPTED,
        Outcome.TEMPORARILY_REJECTED,
        Outcome.CANCELLED,
    },
    "out_of_workspace": {Outcome.FAILED, Outcome.TEMPORARILY_REJECTED},
    "reachable": {
        Outcome.ACCEPTED,
        Outcome.FAILED,
        Outcome.TEMPORARILY_REJECTED,
        Outcome.CANCELLED,
    },
    "angle_wrapped": {
        Outcome.ACCEPTED,
        Outcome.FAILED,
        Outcome.TEMPORARILY_REJECTED,
        Outcome.CANCELLED,
    },
    "near_boundary": {
        Outcome.ACCEPTED,
        Outcome.FAILED,
        Outcome.TEMPORARILY_REJECTED,
        Outcome.CANCELLED,
    },
}

_EXTREMES = (
    1e308,
    -1e308,
    1.7976931348623157e308,
    -1.7976931348623157e308,
    5e-324,
    -5e-324,
    2.2250738585072014e-308,
    1e-310,
    -0.0,
    0.0,
    1e154,
    1e155,
    -1e200,
    3.4e38,
    1e16,
)


class _Opaque:
    """An object that is not a number and refuses to be one."""

    def __repr__(self) -> str:
        return "<opaque>"


def _reach_cm(arm: Arm) -> float:
    """An upper bound on the hand's distance from the base frame's origin, in cm."""
    reach = sum(abs(j.a_cm) + abs(j.d_cm) for j in arm.joints)
    if arm.tool_matrix is not None:
        reach += float(np.linalg.norm(np.asarray(arm.tool_matrix)[:3, 3]))
    return reach


def _bad_element(rng: np.random.Generator) -> Any:
    choices = (
        lambda: str(rng.normal()),  # a number as text is still not a number
        lambda: "abc",
        lambda: "",
        lambda: None,
        lambda: [float(rng.normal())],
        lambda: [[1.0, 2.0], [3.0]],
        lambda: bool(rng.integers(2)),
        lambda: b"\x00",
        lambda: {"x": 1.0},
        lambda: complex(1.0, 2.0),
        lambda: 10**400,  # too big for a float
        lambda: -(10**400),
        lambda: _Opaque(),
        lambda: "nan",
        lambda: "1e999",
    )
    return choices[int(rng.integers(len(choices)))]()


def _bad_payload(rng: np.random.Generator) -> Any:
    kind = int(rng.integers(10))
    if kind < 5:  # six slots, at least one of them not a number
        values: list[Any] = list(rng.normal(0, 30, 6))
        for slot in rng.choice(6, size=int(rng.integers(1, 7)), replace=False):
            values[int(slot)] = _bad_element(rng)
        return values if rng.integers(2) else tuple(values)
    whole = (
        None,
        "1 2 3 4 5 6",
        "abcdef",
        b"\x00" * 6,
        bytearray(6),
        42,
        3.5,
        True,
        {"x_cm": 1.0},
        {1, 2, 3, 4, 5, 6},
        [[1, 2, 3, 4, 5, 6]],
        [[float(v)] for v in rng.normal(size=6)],
        _Opaque(),
    )
    return whole[int(rng.integers(len(whole)))]


def make_targets(arm: Arm, n: int, rng: np.random.Generator) -> list[tuple[str, Any]]:
    """``n`` (category, payload) pairs in TARGET_MIX proportions, shuffled by ``rng``."""
    lo = np.degrees(arm.lower_rad)
    hi = np.degrees(arm.upper_rad)
    reach = _reach_cm(arm)
    counts = {k: int(share * n) for k, share in TARGET_MIX.items()}
    counts["reachable"] += n - sum(counts.values())
    out: list[tuple[str, Any]] = []
    # Poses that need FK are drawn first (joints, and whatever is done to the pose after) and
    # computed in one batch at the end: one FK call per target was most of the campaign's
    # set-up time. ``rng`` is drawn in the same order as one FK call per target would.
    pending: list[tuple[int, np.ndarray, Callable[[list[float]], Any]]] = []

    def fk_later(category: str, q_deg: np.ndarray, finish: Callable[[list[float]], Any]) -> None:
        pending.append((len(out), q_deg, finish))
        out.append((category, None))

    for _ in range(counts["non_finite"]):
        q = rng.uniform(lo, hi)
        slots = [
            (int(slot), (math.nan, math.inf, -math.inf)[int(rng.integers(3))])
            for slot in rng.choice(6, size=int(rng.integers(1, 7)), replace=False)
        ]

        def non_finite(pose: list[float], slots: list[tuple[int, float]] = slots) -> list[float]:
            for slot, value in slots:
                pose[slot] = value
            return pose

        fk_later("non_finite", q, non_finite)
    for _ in range(counts["wrong_arity"]):
        length = int(rng.choice([0, 1, 2, 3, 4, 5, 7, 8, 12]))
        out.append(("wrong_arity", list(rng.normal(0, 30, length))))
    for _ in range(counts["wrong_types"]):
        out.append(("wrong_types", _bad_payload(rng)))
    for _ in range(counts["extreme_finite"]):
        values = []
        for _slot in range(6):
            if rng.random() < 0.5:
                values.append(float(rng.choice(_EXTREMES)))
            else:
                sign = -1.0 if rng.random() < 0.5 else 1.0
                values.append(sign * 10.0 ** rng.uniform(-320, 308))
        out.append(("extreme_finite", values))
    for _ in range(counts["out_of_workspace"]):
        direction = rng.normal(size=3)
        direction /= np.linalg.norm(direction)
        distance = reach * (1.0 + 10.0 ** rng.uniform(-3, 4))
        position = direction * distance
        out.append(("out_of_workspace", [*position, *rng.uniform(-180, 180, 3)]))
    for _ in range(counts["reachable"]):
        fk_later("reachable", rng.uniform(lo, hi), lambda pose: pose)
    for _ in range(counts["angle_wrapped"]):
        q = rng.uniform(lo, hi)
        turns = rng.integers(-1000, 1001, 3) * 360.0

        def wrapped(pose: list[float], turns: np.ndarray = turns) -> list[float]:
            return pose[:3] + [p + t for p, t in zip(pose[3:], turns, strict=True)]

        fk_later("angle_wrapped", q, wrapped)
    for _ in range(counts["near_boundary"]):
        q = rng.uniform(lo, hi)
        at_limit = rng.random(6) < 0.5
        side = np.where(rng.random(6) < 0.5, lo, hi)
        # On the limit, or 1e-9 .. 5 degrees inside or outside it.
        offset = rng.choice([0.0, 1.0, -1.0], 6) * 10.0 ** rng.uniform(-9, np.log10(5.0), 6)
        q = np.where(at_limit, side + np.where(side == lo, -offset, offset), q)
        nudge = rng.choice([0.0, 1.0], 6) * rng.normal(0, 1e-6, 6)  # tiny nudges

        def nudged(pose: list[float], nudge: np.ndarray = nudge) -> list[float]:
            return list(np.array(pose) + nudge)

        fk_later("near_boundary", q, nudged)
    if pending:
        transforms = arm.fk_batch(np.radians([q for _, q, _ in pending]))
        for (index, _, finish), transform in zip(pending, transforms, strict=True):
            out[index] = (out[index][0], finish(list(Pose.from_matrix(transform).as_tuple())))
    order = rng.permutation(len(out))
    return [out[i] for i in order]


@dataclass
class TargetReport:
    """What the target campaign saw."""

    inputs: Counter = field(default_factory=Counter)  # per category
    outcomes: dict[str, Counter] = field(default_factory=dict)  # category -> outcome -> count
    unexpected: list[str] = field(default_factory=list)  # outcome not allowed for a category
    # Refusals whose reported position error is below what geometry allows: the hand cannot
    # get nearer to a point than its distance from the base minus the arm's reach.
    dishonest: list[str] = field(default_factory=list)
    unresolved: int = 0  # futures that did not resolve
    non_outcome: int = 0  # futures resolved with something other than a Reply/Outcome
    submit_errors: list[str] = field(default_factory=list)
    control_thread_alive: bool = False
    counters: dict[str, int] = field(default_factory=dict)  # the daemon's own
    sim_servo_commands: int = 0  # DO_SET_SERVO frames the simulator received
    sim_servo_events: int = 0  # servo movements it applied
    pwm_violations: list[str] = field(default_factory=list)
    sim_exit_code: int | None = None
    elapsed_s: float = 0.0

    @property
    def total_outcomes(self) -> Counter:
        total: Counter = Counter()
        for per in self.outcomes.values():
            total.update(per)
        return total


def _pwm_violation(calibration: ArmCalibration, output: Any, pwm: Any, where: str) -> str | None:
    if output not in calibration.outputs:
        return f"{where}: output {output!r} is not an arm output {calibration.outputs}"
    lo, hi = calibration.for_output(output).pwm_range_us
    if not (isinstance(pwm, int | float) and float(pwm).is_integer() and lo <= pwm <= hi):
        return f"{where}: output {output} pwm_us={pwm!r} outside [{lo}, {hi}]"
    return None


def check_sim_state(sim: SimProcess, calibration: ArmCalibration, report: TargetReport) -> None:
    """The simulator's outputs now (its state query) against the calibration."""
    state = sim.state()
    for output in calibration.outputs:
        pwm = state["outputs"][str(output)]["pwm_us"]
        if pwm != 0:  # 0: never commanded
            problem = _pwm_violation(calibration, output, pwm, "sim state")
            if problem:
                report.pwm_violations.append(problem)


def check_sim_log(sim: SimProcess, calibration: ArmCalibration, report: TargetReport) -> None:
    """Every servo command the simulator received (its event log, read once it has stopped)
    against the calibration."""
    for event in sim.events():
        if event["event"] == "rx" and event["msg"] in ("COMMAND_LONG", "COMMAND_INT"):
            fields = event["fields"]
            if event["src"][1] != OUR_COMPONENT:
                continue
            if fields["command"] == mavlink.MAV_CMD_SET_MESSAGE_INTERVAL:
                continue  # the daemon asks for the streams it reads (see core)
            if fields["command"] != mavlink.MAV_CMD_DO_SET_SERVO:
                report.pwm_violations.append(f"sim rx: unexpected command {fields['command']}")
                continue
            report.sim_servo_commands += 1
            output = fields["param1"]
            output = int(output) if float(output).is_integer() else output
            problem = _pwm_violation(calibration, output, fields["param2"], "sim rx")
            if problem:
                report.pwm_violations.append(problem)
        elif event["event"] == "servo" and int(event["output"]) in calibration.outputs:
            report.sim_servo_events += 1
            problem = _pwm_violation(
                calibration, int(event["output"]), event["pwm_us"], "sim servo event"
            )
            if problem:
                report.pwm_violations.append(problem)


def check_daemon_pwm(daemon: ArmDaemon, report: TargetReport) -> None:
    status = daemon.status()
    for output, pwm in (status["last_pwm_us"] or {}).items():
        problem = _pwm_violation(daemon.config.calibration, output, pwm, "daemon status")
        if problem:
            report.pwm_violations.append(problem)
    arm = daemon.config.arm
    for i, angle in enumerate(status["current_deg"]):
        lo, hi = math.degrees(arm.lower_rad[i]), math.degrees(arm.upper_rad[i])
        if not lo - 1e-9 <= angle <= hi + 1e-9:
            report.pwm_violations.append(f"daemon current_deg[{i}]={angle} outside [{lo}, {hi}]")


def target_daemon_config(url: str, *, budget_ms: float, seed: int) -> dict[str, Any]:
    return {
        # Loopback loses nothing and an update's ACKs come back in milliseconds; the control
        # thread takes them, though, only when it runs, and on a loaded machine it runs over a
        # second late at times (measured): an update it judges then, past its timeout, counts
        # as a servo error. The timeout only has to outlast such a stall.
        "link": {"url": url, "loss_timeout_s": 5.0, "command_timeout_s": 5.0},
        "arm": {"park_deg": [0, 90, 0, 0, 0, 0], "joint_speed_deg_s": 360.0},
        # A tick sends six acknowledged DO_SET_SERVO (~10 ms): 10 Hz leaves the thread free
        # for targets most of the time.
        "control": {"rate_hz": 10.0},
        "solver": {"budget_ms": budget_ms, "seed": seed},
    }


def run_targets(
    directory: Path,
    n: int,
    *,
    seed: int,
    budget_ms: float = 0.2,
    batch: int = 5000,
    progress: Callable[[str], None] | None = None,
) -> TargetReport:
    """Push ``n`` adversarial targets through a daemon linked to a simulator subprocess."""
    report = TargetReport()
    rng = np.random.default_rng(seed)
    sim = start_sim(directory)
    daemon = None
    started = time.perf_counter()
    try:
        daemon = ArmDaemon(
            parse_config(target_daemon_config(sim.url, budget_ms=budget_ms, seed=seed))
        )
        warm_up()  # as `armbridge run` does before READY: no target pays for the kernels
        gc.freeze()  # and its heap: no full collection pass over it stalls the control thread
        daemon.start()
        if not daemon.wait_for_autopilot(WAIT_S):
            raise RuntimeError("the daemon did not hear the simulator")
        targets = make_targets(daemon.config.arm, n, rng)
        reach_cm = _reach_cm(daemon.config.arm)
        for start in range(0, len(targets), batch):
            chunk = targets[start : start + batch]
            futures = []
            for i, (category, payload) in enumerate(chunk):
                report.inputs[category] += 1
                try:
                    # Each from its own source (one source's burst is rate limited), and the
                    # next only once the control thread took this one: the newest target wins,
                    # so without the pacing most would be superseded before they reach the
                    # solver. Paced, every valid one is solved.
                    request = daemon.new_request("goto", payload, source=("campaign", i))
                    futures.append((category, payload, daemon.submit_request(request)))
                    request.taken.wait(WAIT_S)
                except Exception as exc:  # submit itself must never raise for a payload
                    report.submit_errors.append(f"{category}: {payload!r}: {exc!r}")
            deadline = time.monotonic() + 60.0 + len(chunk) * budget_ms / 1e3 * 4
            for category, payload, future in futures:
                reply = _await(future, deadline, daemon)
                if reply is None:
                    report.unresolved += 1
                    continue
                outcome = getattr(reply, "outcome", None)
                if not isinstance(outcome, Outcome):
                    report.non_outcome += 1
                    continue
                report.outcomes.setdefault(category, Counter())[outcome.value] += 1
                if outcome is Outcome.FAILED and reply.solve is not None:
                    floor_cm = math.hypot(*payload[:3]) - reach_cm
                    if not reply.solve.pos_err_cm >= floor_cm * (1 - 1e-9) and (
                        len(report.dishonest) < 50
                    ):
                        report.dishonest.append(
                            f"{category}: {payload!r}: reported pos_err "
                            f"{reply.solve.pos_err_cm} cm, at least {floor_cm} cm"
                        )
                if outcome not in ALLOWED_OUTCOMES[category] and len(report.unexpected) < 50:
                    report.unexpected.append(
                        f"{category}: {payload!r} -> {outcome.value}: {reply.message}"
                    )
            if progress:
                progress(f"targets: {start + len(chunk)}/{n}")
            if report.unresolved:
                break  # the control thread is gone: the rest would only time out
        report.control_thread_alive = daemon.healthy
        report.counters = daemon.status()["counters"]
        check_daemon_pwm(daemon, report)
    finally:
        if daemon is not None:
            daemon.close()
        try:
            if daemon is not None:
                check_sim_state(sim, daemon.config.calibration, report)
        finally:
            report.sim_exit_code = sim.stop()
    if daemon is not None:
        check_sim_log(sim, daemon.config.calibration, report)
    report.elapsed_s = time.perf_counter() - started
    return report


def _await(future: Any, deadline: float, daemon: ArmDaemon) -> Any:
    """The future's result, or None at the deadline or once the control thread has died (the
    private ``_thread``: a dead thread resolves nothing, so waiting on would only waste time)."""
    while True:
        remaining = deadline - time.monotonic()
        try:
            return future.result(timeout=max(0.0, min(1.0, remaining)))
        except TimeoutError:
            thread = daemon._thread
            if remaining <= 0 or thread is None or not thread.is_alive():
                return None


# ---------------------------------------------------------------------------------------------
# 2. Fuzzing the daemon's MAVLink input
# ---------------------------------------------------------------------------------------------

_INT_RANGES = {
    "int8_t": (-(2**7), 2**7 - 1),
    "uint8_t": (0, 2**8 - 1),
    "int16_t": (-(2**15), 2**15 - 1),
    "uint16_t": (0, 2**16 - 1),
    "int32_t": (-(2**31), 2**31 - 1),
    "uint32_t": (0, 2**32 - 1),
    "int64_t": (-(2**63), 2**63 - 1),
    "uint64_t": (0, 2**64 - 1),
}
_SPECIAL_FLOATS = (math.nan, math.inf, -math.inf, -0.0, 5e-324, 3.4e38, -3.4e38, 1e-40)
#: Message types whose fields steer the daemon; kept away from values that would be a target.
_COMMANDS = (mavlink.MAVLINK_MSG_ID_COMMAND_LONG, mavlink.MAVLINK_MSG_ID_COMMAND_INT)


def _random_scalar(rng: np.random.Generator, kind: str) -> Any:
    if kind in _INT_RANGES:
        lo, hi = _INT_RANGES[kind]
        if rng.random() < 0.3:
            return (lo, hi, 0, 1)[int(rng.integers(4))]  # rng.choice would go via float64
        return int(rng.integers(lo, hi, endpoint=True, dtype=np.int64 if hi < 2**63 else np.uint64))
    if kind in ("float", "double"):
        if rng.random() < 0.2:
            return float(rng.choice(_SPECIAL_FLOATS))
        value = float(rng.normal(0, 10.0 ** rng.uniform(-3, 30 if kind == "float" else 300)))
        return value if kind == "double" or abs(value) < 3.4e38 else math.copysign(3.4e38, value)
    raise ValueError(f"unknown MAVLink field type {kind!r}")


def random_message(rng: np.random.Generator, cls: Any) -> mavlink.MAVLink_message:
    """An instance of pymavlink message class ``cls`` with random values in every field."""
    lengths = dict(zip(cls.ordered_fieldnames, cls.array_lengths, strict=True))
    values: list[Any] = []
    for name, kind in zip(cls.fieldnames, cls.fieldtypes, strict=True):
        length = lengths[name]
        if kind == "char":
            values.append(bytes(rng.integers(0, 256, max(length, 1), dtype=np.uint8)))
        elif length:
            values.append([_random_scalar(rng, kind) for _ in range(length)])
        else:
            values.append(_random_scalar(rng, kind))
    msg = cls(*values)
    if cls.id in _COMMANDS and getattr(msg, "command", None) == mavlink.MAV_CMD_USER_1:
        msg.command = mavlink.MAV_CMD_USER_2  # a real target to us is the markers' business
    return msg


class FrameFactory:
    """Packs fuzz messages with random source ids and sequence numbers."""

    def __init__(self, rng: np.random.Generator) -> None:
        self.rng = rng
        self.mav = mavlink.MAVLink(None, 1, 1)
        self.classes = [mavlink.mavlink_map[k] for k in sorted(mavlink.mavlink_map)]
        self.v1_classes = [c for c in self.classes if c.id < 256]  # MAVLink 1 ids are 8 bits
        self.user1_not_for_us = 0  # COMMAND_LONG USER_1 frames addressed elsewhere, sent whole

    def pack(
        self, msg: mavlink.MAVLink_message, src: tuple[int, int] | None = None, *, v1: bool = False
    ) -> bytes:
        if src is None:
            src = (int(self.rng.integers(0, 256)), int(self.rng.integers(0, 256)))
            if src == (AUTOPILOT_SYSTEM, 1) and msg.get_type() == "HEARTBEAT":
                src = (AUTOPILOT_SYSTEM, 2)  # the real autopilot's heartbeat stays honest
        self.mav.srcSystem, self.mav.srcComponent = src
        self.mav.seq = int(self.rng.integers(0, 256))
        return bytes(msg.pack(self.mav, force_mavlink1=v1))

    def valid(self, cls: type | None = None) -> bytes:
        if cls is None:
            cls = self.classes[int(self.rng.integers(len(self.classes)))]
        return self.pack(random_message(self.rng, cls))

    def valid_v1(self) -> bytes:
        cls = self.v1_classes[int(self.rng.integers(len(self.v1_classes)))]
        return self.pack(random_message(self.rng, cls), v1=True)

    def command(self) -> bytes:
        """COMMAND_LONG / COMMAND_INT: random command, wrong target ids, random params."""
        target = (int(self.rng.integers(0, 256)), int(self.rng.integers(0, 256)))
        if target == (AUTOPILOT_SYSTEM, OUR_COMPONENT):
            target = (AUTOPILOT_SYSTEM, OUR_COMPONENT + 1)
        command = int(
            self.rng.choice(
                [
                    int(self.rng.integers(0, 2**16)),
                    mavlink.MAV_CMD_DO_SET_SERVO,
                    mavlink.MAV_CMD_DO_SET_ACTUATOR,
                    mavlink.MAV_CMD_USER_1,
                    mavlink.MAV_CMD_USER_2,
                ]
            )
        )
        params = [_random_scalar(self.rng, "float") for _ in range(7)]
        if self.rng.random() < 0.5:
            msg = mavlink.MAVLink_command_long_message(*target, command, 0, *params)
            self.user1_not_for_us += command == mavlink.MAV_CMD_USER_1
        else:
            msg = mavlink.MAVLink_command_int_message(
                *target,
                0,
                command,
                0,
                0,
                *params[:4],
                _random_scalar(self.rng, "int32_t"),
                _random_scalar(self.rng, "int32_t"),
                params[6],
            )
        return self.pack(msg)

    def user1_elsewhere(self, reachable_pose: Sequence[float]) -> bytes:
        """MAV_CMD_USER_1 with a reachable pose, addressed to another system or component."""
        if self.rng.random() < 0.5:
            target = (
                AUTOPILOT_SYSTEM,
                int(self.rng.choice([c for c in range(256) if c != OUR_COMPONENT])),
            )
        else:
            target = (int(self.rng.choice([0, *range(2, 256)])), OUR_COMPONENT)
        msg = mavlink.MAVLink_command_long_message(
            *target, mavlink.MAV_CMD_USER_1, 0, *reachable_pose, 0.0
        )
        self.user1_not_for_us += 1
        return self.pack(msg, src=(255, 190))

    def random_bytes(self) -> bytes:
        data = bytearray(self.rng.integers(0, 256, int(self.rng.integers(1, 300)), dtype=np.uint8))
        if self.rng.random() < 0.5:  # start like a frame, so the parser reads further
            data[0] = int(self.rng.choice([mavlink.PROTOCOL_MARKER_V2, mavlink.PROTOCOL_MARKER_V1]))
        return bytes(data)

    def truncated(self) -> bytes:
        frame = self.valid()
        return frame[: int(self.rng.integers(1, len(frame)))]

    def corrupted(self) -> bytes:
        frame = bytearray(self.valid())
        for _ in range(int(self.rng.integers(1, 4))):
            frame[int(self.rng.integers(len(frame)))] ^= int(self.rng.integers(1, 256))
        return bytes(frame)


@dataclass
class FuzzReport:
    frames: Counter = field(default_factory=Counter)  # per category
    message_types_sent: int = 0  # distinct valid message types sent
    daemon_alive: bool = False
    status_answers: int = 0  # control-socket status requests answered during the fuzz
    link_states: Counter = field(default_factory=Counter)
    servo_commands: list[str] = field(default_factory=list)  # what must stay empty
    peer_received: Counter = field(default_factory=Counter)  # types the daemon sent the peer
    user1_not_for_us_sent: int = 0  # the daemon must count each of them as not_for_us
    markers_answered: int = 0
    marker_rounds: int = 0
    rss_kb: list[tuple[int, int]] = field(default_factory=list)  # (frames so far, VmRSS kB)
    counters: dict[str, int] = field(default_factory=dict)
    exit_code: int | None = None
    stderr_tail: str = ""
    elapsed_s: float = 0.0

    @property
    def rss_growth_kb(self) -> int:
        return self.rss_kb[-1][1] - self.rss_kb[0][1]


def vm_rss_kb(pid: int) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1])
    raise RuntimeError(f"no VmRSS for pid {pid}")


def fuzz_daemon_config(port: int) -> dict[str, Any]:
    """The daemon config of the MAVLink fuzz: its autopilot on ``udpout:127.0.0.1:port``."""
    return {
        "link": {"url": f"udpout:127.0.0.1:{port}", "loss_timeout_s": 3.0},
        "arm": {"park_deg": [0, 90, 0, 0, 0, 0]},
        "solver": {"budget_ms": 2.0, "seed": 1},
        "control": {"rate_hz": 20.0},
    }


def run_mavlink_fuzz(
    directory: Path,
    *,
    rounds: int,
    seed: int,
    batch: int = 100,
    progress: Callable[[str], None] | None = None,
) -> FuzzReport:
    """``armbridge run`` against a scripted autopilot fed ``rounds`` rounds of fuzz.

    One round: one valid frame of every ardupilotmega message type, and as many frames again
    of each other category. Every ``batch`` frames a marker (USER_1 to us with a NaN param,
    from system 254) must come back DENIED: the daemon read the batch and still answers. RSS
    is sampled after the first round (warm-up) and at the end.
    """
    report = FuzzReport()
    rng = np.random.default_rng(seed)
    factory = FrameFactory(rng)
    endpoint = UdpEndpoint()
    peer = ScriptedPeer(endpoint, system_id=AUTOPILOT_SYSTEM, component_id=1)
    started = time.perf_counter()
    reachable = Arm.default().fk([20, 70, 50, 20, 30, 10]).as_tuple()
    marker_gcs = mavlink.MAVLink(None, 254, 190)
    daemon: DaemonProcess | None = None
    try:
        daemon = DaemonProcess(directory, fuzz_daemon_config(endpoint.port))
        if not peer.wait_for(lambda: endpoint.peer is not None, 30.0):
            raise RuntimeError("the daemon sent nothing")
        peer.send_heartbeat()
        daemon.wait_link("up", 30.0)

        def marker_acks() -> int:
            return sum(1 for m in peer.messages("COMMAND_ACK") if m.target_system == 254)

        def sync() -> None:
            """Heartbeat, then a marker; bounded wait for its DENIED (re-sent if lost)."""
            peer.send_heartbeat()
            report.marker_rounds += 1
            want = report.markers_answered + 1
            for _attempt in range(5):
                # 300 zero bytes first: a truncated frame still waiting for its tail gets it
                # from them, not from the marker.
                endpoint.write(bytes(300))
                msg = marker_gcs.command_long_encode(
                    AUTOPILOT_SYSTEM,
                    OUR_COMPONENT,
                    mavlink.MAV_CMD_USER_1,
                    0,
                    math.nan,
                    0,
                    0,
                    0,
                    0,
                    0,
                    0,
                )
                endpoint.write(msg.pack(marker_gcs))
                if peer.wait_for(lambda: marker_acks() >= want, 2.0):
                    report.markers_answered = marker_acks()
                    return
            raise AssertionError(f"marker {want} not answered: daemon unresponsive")

        def send(category: str, frame: bytes) -> None:
            endpoint.write(frame)
            report.frames[category] += 1
            if sum(report.frames.values()) % batch == 0:
                sync()

        def status_check() -> None:
            status = _status(daemon)
            if status is not None:
                report.status_answers += 1
                report.link_states[status["link"]] += 1

        types_sent = set()
        for round_index in range(rounds):
            for cls in factory.classes:
                send("valid_every_type", factory.valid(cls))
                types_sent.add(cls.id)
            per_round = len(factory.classes)
            for _ in range(per_round):
                send("random_bytes", factory.random_bytes())
                send("truncated", factory.truncated())
                send("corrupted", factory.corrupted())
                send("valid_random_type", factory.valid())
                send("valid_mavlink1", factory.valid_v1())
            # A corrupted length byte can make the parser swallow the next frames whole: flush
            # it, so that every USER_1 below arrives intact and must be counted.
            sync()
            for _ in range(per_round // 2):
                send("command_wrong_target", factory.command())
                send("user1_elsewhere", factory.user1_elsewhere(reachable))
            sync()
            status_check()
            # The first sample is after the warm-up round: every code path has run once.
            report.rss_kb.append((sum(report.frames.values()), vm_rss_kb(daemon.pid)))
            if progress:
                progress(
                    f"fuzz round {round_index + 1}/{rounds}: {sum(report.frames.values())} frames"
                )
        report.message_types_sent = len(types_sent)
        report.user1_not_for_us_sent = factory.user1_not_for_us
        status = _status(daemon)
        if status is not None:
            report.status_answers += 1
            report.link_states[status["link"]] += 1
            report.counters = status["counters"]
        report.daemon_alive = daemon.proc.poll() is None
    finally:
        if daemon is not None:
            report.exit_code = daemon.stop()  # SIGTERM; SIGKILL if it hangs
            report.stderr_tail = daemon.log()[-2000:]
        peer.close()
    for msg in peer.received:
        report.peer_received[msg.get_type()] += 1
        if msg.get_type() in ("COMMAND_LONG", "COMMAND_INT"):
            # The streams the core reads: SYSTEM_TIME, SERVO_OUTPUT_RAW, SYS_STATUS.
            if msg.command != mavlink.MAV_CMD_SET_MESSAGE_INTERVAL:
                report.servo_commands.append(f"{msg.get_type()} command {msg.command}")
        elif msg.get_type() not in ("HEARTBEAT", "COMMAND_ACK", "STATUSTEXT", "PARAM_REQUEST_READ"):
            report.servo_commands.append(f"unexpected {msg.get_type()}")
    report.elapsed_s = time.perf_counter() - started
    return report


def _status(daemon: DaemonProcess) -> dict[str, Any] | None:
    """The daemon's status, or None if it does not answer (counted, not raised)."""
    try:
        reply = daemon.request("status", timeout_s=5.0)
    except NOT_SERVING:
        return None
    return reply.get("status")


# ---------------------------------------------------------------------------------------------
# 3. Config fuzz
# ---------------------------------------------------------------------------------------------

EXAMPLE_TEXT = (resources.files("companion.daemon") / "examples" / "armbridge.toml").read_text()
ARM_DOF = 6
#: (section, keys) as companion.daemon.config declares them; [[joint]] rows are repeated per joint.
SCHEMA_SECTIONS = {
    "link": config_module._LINK_KEYS,
    "arm": config_module._ARM_KEYS,
    "solver": config_module._SOLVER_KEYS,
    "control": config_module._CONTROL_KEYS,
    "joint": config_module._JOINT_KEYS,
}

#: A TOML offset date-time: a type no field of the config accepts.
_DATETIME = datetime.datetime(1979, 5, 27, 7, 32, tzinfo=datetime.UTC)
_WRONG_TYPES: dict[str, tuple[Any, ...]] = {
    # A value of every TOML type that the field's kind does not accept.
    "string": (5, 2.5, True, [1], {"a": 1}, _DATETIME, ""),
    # control.socket: "" is valid there (no socket).
    "path_or_empty": (5, 2.5, True, [1], {"a": 1}, _DATETIME),
    "number": ("3", True, [1.0], {"a": 1}, _DATETIME, math.nan, math.inf, -math.inf),
    "integer": ("3", 2.5, True, [1], {"a": 1}, _DATETIME, math.nan),
    "bool": ("true", 1, 0.0, [True], {"a": 1}, _DATETIME),
    "numbers": (
        "0, 90",
        5,
        True,
        {"a": 1},
        _DATETIME,
        [0, 90, 0, 0, 0, "0"],
        [0, 90, 0, 0, 0, math.nan],
        [0, 90, 0, 0, 0, True],
        [[0], 90, 0, 0, 0, 0],
    ),
    "pairs": (
        "255,190",
        5,
        True,
        {"a": 1},
        _DATETIME,
        [255, 190],
        [[255, "190"]],
        [[255, 190.0]],
        [[True, 190]],
        [[255, 190, 1]],
        [[255, 190], []],
    ),
}
#: Kind of every field, and values of the right type that are still out of range.
FIELD_KINDS: dict[str, tuple[str, tuple[Any, ...]]] = {
    "link.url": (
        "string",
        (
            "carrier-pigeon:1",
            "udpout:127.0.0.1",
            "udpout:127.0.0.1:x",
            "udpout::14550",
            "/dev/ttyACM0,fast",
            "serial://",
            "tcp:host:99999",
        ),
    ),
    "link.dialect": ("string", ("inav", "ArduPilot", "px5")),
    "link.system_id": ("integer", (0, 256, -1, 2**63 - 1)),
    "link.component_id": ("integer", (0, 256, -1)),
    "link.target_system": ("integer", (0, 256, -1)),
    "link.target_component": ("integer", (0, 256, -1)),
    "link.loss_timeout_s": ("number", (0, -1.0, -1e-300, 1.999, 60.5, 1e300)),
    "link.command_timeout_s": ("number", (0, -0.5, 0.0009, 60.5, 1e300, 25.0)),  # 25: 3 x 25 s
    "link.command_retries": ("integer", (-1, 11, 2**63 - 1)),
    "link.signing_key": ("string", ("no-such.key", "short.key", "notakey.key", ".")),
    "link.signing_link_id": ("integer", (-1, 256)),
    # Out of range only at run time: systemd creates its StateDirectory= when the service
    # starts, so check-config cannot demand the directory (tests/test_config_fuzz.py runs it).
    "link.signing_state": ("string", ()),
    "link.allowed_senders": ("pairs", ([[0, 190]], [[255, 0]], [[256, 190]], [[255, -1]])),
    "arm.file": ("string", ("no-such-arm.toml", "broken-arm.toml", ".")),
    "arm.tip_link": ("string", ("no-such-link", "", "tool0")),
    "arm.pose_file": ("string", ("/no-such-dir/pose.json",)),
    "arm.park_deg": (
        "numbers",
        ([0, 90], [0, 90, 0, 0, 0, 0, 0], [], [0, -10, 0, 0, 0, 0], [0, 90, 0, 0, 0, 1e308]),
    ),
    "arm.park_on_stop": ("bool", ()),
    "arm.joint_speed_deg_s": ("number", (0, -60.0, 1000.5, 1e300)),
    "solver.budget_ms": ("number", (0, -1, 1000.5, 1e308)),
    "solver.tol_pos_cm": ("number", (0, -0.01, 9e-7, 10.5)),
    "solver.tol_ori_deg": ("number", (0, -0.1, 9e-7, 180.5)),
    "solver.seed": ("integer", (-1,)),
    "solver.method": ("string", ("DE", "genetic", "memetic ")),
    "solver.pop_size": ("integer", (3, 0, -4, 101, 2**40)),
    "solver.mutation_f": ("number", (0, -0.7, 2.001, 1e300)),
    "solver.crossover_cr": ("number", (-0.1, 1.001, 1e300)),
    "solver.lm_iterations": ("integer", (-1, 101, 2**40)),
    "solver.stall_generations": ("integer", (0, -1, 10_001)),
    "solver.stall_gain": ("number", (-0.5, 1.5, 1e300)),
    "control.rate_hz": ("number", (0, -20, 1e-10, 0.999, 400.5, 1e9)),
    "control.socket": (
        "path_or_empty",
        # A missing last directory is fine (run makes it); two missing levels are not.
        ("/tmp/" + "s" * 120 + ".sock", "/nonexistent-armbridge-dir/x/c.sock", ".", "good.key"),
    ),
    "control.socket_group": ("string", ("no-such-group-armbridge",)),
    "control.max_connections": ("integer", (0, -1, 257, 2**40)),
    "control.idle_timeout_s": ("number", (0, -1.0, 0.09, 3600.5, 1e300)),
    "control.resume_after_reboot": ("bool", ()),
    "joint.name": ("string", ()),
    "joint.output": ("integer", (0, 17, -9)),
    "joint.pwm_min_us": ("integer", (499, 2501, 2000, 2**40)),
    "joint.pwm_max_us": ("integer", (499, 2501, 1000, 900)),
    "joint.angle_min_deg": ("number", (361.0, -361.0, 100.0, 1e308)),
    "joint.angle_max_deg": ("number", (361.0, -361.0, -100.0, 5.0)),
    "joint.reversed": ("bool", ()),
    # Any trim: the example calibrates exactly the arm's limits, so a trimmed end leaves the
    # servo's range (joint[N].trim_us names it).
    "joint.trim_us": ("integer", (501, -501, 2**31, 1, -1, 100)),
}

#: Fields that only mean something next to another; the case adds what they need.
_NEEDS = {
    "link.signing_link_id": {"signing_key": "good.key"},
    "link.signing_state": {"signing_key": "good.key"},
    "control.socket_group": {"socket": "/tmp/armbridge-fuzz.sock"},
    "control.max_connections": {"socket": "/tmp/armbridge-fuzz.sock"},
    "control.idle_timeout_s": {"socket": "/tmp/armbridge-fuzz.sock"},
}


def schema_fields() -> list[str]:
    """Every dotted field the config accepts, from companion.daemon.config's own key lists."""
    return [f"{section}.{key}" for section, keys in SCHEMA_SECTIONS.items() for key in keys]


@dataclass(frozen=True)
class ConfigCase:
    """One malformed config: the file, what is wrong, and the field the message must name."""

    category: str
    description: str
    path: Path
    field: str  # dotted field, e.g. "joint[3].output" or "<file>"


def _base_config() -> dict[str, Any]:
    """A fresh copy (callers break it in place) of the parsed example with every joint key."""
    return copy.deepcopy(_base_config_once())


@functools.cache
def _base_config_once() -> dict[str, Any]:
    data = tomllib.loads(EXAMPLE_TEXT)
    # Give every joint row every key (at its default), so each can be broken in place.
    arm = Arm.default()
    for i, row in enumerate(data["joint"]):
        joint = arm.joints[i]
        row.update(
            name=joint.name,
            pwm_min_us=1000,
            pwm_max_us=2000,
            angle_min_deg=math.degrees(joint.min_rad),
            angle_max_deg=math.degrees(joint.max_rad),
            reversed=False,
            trim_us=0,
        )
    return data


def _support_files(directory: Path) -> None:
    (directory / "good.key").write_bytes(bytes(range(32)))
    (directory / "good.key").chmod(0o600)
    (directory / "short.key").write_bytes(bytes(31))
    (directory / "notakey.key").write_text("z" * 64)
    (directory / "broken-arm.toml").write_text("[[joint\n")


def config_cases(directory: Path, rng: np.random.Generator) -> list[ConfigCase]:
    """Every malformed config of the campaign, written under ``directory``."""
    _support_files(directory)
    cases: list[ConfigCase] = []
    counter = iter(range(1_000_000))

    def add(category: str, description: str, text: str | bytes, field_name: str) -> None:
        path = directory / f"case{next(counter):04d}.toml"
        if isinstance(text, bytes):
            path.write_bytes(text)
        else:
            path.write_text(text)
        cases.append(ConfigCase(category, description, path, field_name))

    def with_value(dotted: str, value: Any, joint_index: int | None) -> dict[str, Any]:
        data = _base_config()
        section, key = dotted.split(".")
        if section == "joint":
            assert joint_index is not None
            data["joint"][joint_index - 1][key] = value
        else:
            table = data.setdefault(section, {})
            table.update(_NEEDS.get(dotted, {}))
            table[key] = value
        return data

    for dotted in schema_fields():
        kind, out_of_range = FIELD_KINDS[dotted]
        section, key = dotted.split(".")
        rows = range(1, ARM_DOF + 1) if section == "joint" else [None]
        for joint_index in rows:
            named = f"joint[{joint_index}].{key}" if joint_index else dotted
            for category, values in (
                ("wrong_type", _WRONG_TYPES[kind]),
                ("out_of_range", out_of_range),
            ):
                for value in values:
                    shown = "datetime" if isinstance(value, datetime.datetime) else repr(value)[:40]
                    add(
                        category,
                        f"{named} = {shown}",
                        toml_document(with_value(dotted, value, joint_index)),
                        named,
                    )

    # An unknown key in every section and every [[joint]] row.
    for section in SCHEMA_SECTIONS:
        for joint_index in range(1, ARM_DOF + 1) if section == "joint" else [None]:
            data = _base_config()
            if joint_index:
                data["joint"][joint_index - 1]["bogus_key"] = 1
                named = f"joint[{joint_index}].bogus_key"
            else:
                data.setdefault(section, {})["bogus_key"] = 1
                named = f"{section}.bogus_key"
            add("unknown_key", f"{named} = 1", toml_document(data), named)

    # Duplicate output (a cross-field rule) on every joint pair with the first.
    for j in range(2, ARM_DOF + 1):
        data = _base_config()
        data["joint"][j - 1]["output"] = data["joint"][0]["output"]
        add("out_of_range", f"joint[{j}].output duplicates joint[1]", toml_document(data), "joint")

    # Structure: sections of the wrong type, missing required, unknown section, joint count.
    data = _base_config()
    del data["link"]["url"]
    add("missing_required", "link.url absent", toml_document(data), "link.url")
    data = _base_config()
    del data["link"]
    add("missing_required", "[link] absent", toml_document(data), "link.url")
    add("missing_required", "empty file", "", "link.url")
    add("missing_required", "only comments", "# nothing here\n\n", "link.url")
    for section in ("link", "arm", "solver", "control"):
        data = _base_config()
        data[section] = 5
        add("wrong_type", f"{section} = 5", toml_document(data), section)
    for value in (5, [], [1, 2]):
        data = _base_config()
        data["joint"] = value
        add("wrong_type", f"joint = {value!r}", toml_document(data), "joint")
    data = _base_config()
    data["bogus"] = {"x": 1}
    add("unknown_key", "[bogus] section", toml_document(data), "bogus")
    data = _base_config()
    data["url"] = "udpout:127.0.0.1:14550"
    add("unknown_key", "url at the top level", toml_document(data), "url")
    for count in (0, 5, 7):
        data = _base_config()
        data["joint"] = (data["joint"] * 2)[:count]
        if count:
            for i, row in enumerate(data["joint"]):
                row["output"] = i + 1
            add("out_of_range", f"{count} [[joint]] tables", toml_document(data), "joint")

    # Broken TOML, undecodable and unreadable files.
    good = toml_document(_base_config())
    broken = {
        "unterminated string": good.replace('"udpout:127.0.0.1:14550"', '"udpout:127.0.0.1'),
        "unclosed table header": good + "[[joint\n",
        "missing value": good.replace("budget_ms = 20.0", "budget_ms ="),
        "duplicate key": good.replace("budget_ms = 20.0", "budget_ms = 20.0\nbudget_ms = 1.0"),
        "duplicate table": good + "[solver]\n",
        "bad escape": good.replace("udpout:127", "udpout:\\q127"),
        "bare word value": good.replace('dialect = "ardupilot"', "dialect = ardupilot"),
        "unclosed array": good.replace("park_deg = [0", "park_deg = [[0"),
        "NUL byte": good.replace("[solver]", "[solver]\x00"),
        "deep nesting": good + "x = " + "[" * 5000 + "]" * 5000 + "\n",
        "random garbage line": good + "".join(chr(int(c)) for c in rng.integers(33, 127, 40)),
    }
    for description, text in broken.items():
        add("broken_toml", description, text, "<file>")
    add("broken_toml", "not UTF-8", good.encode() + b"# caf\xe9\n", "<file>")
    add("broken_toml", "UTF-16", good.encode("utf-16"), "<file>")
    add("broken_toml", "random bytes", bytes(rng.integers(0, 256, 512, dtype=np.uint8)), "<file>")
    missing = directory / "does-not-exist.toml"
    cases.append(ConfigCase("unreadable", "missing file", missing, "<file>"))
    a_dir = directory / "a-directory.toml"
    a_dir.mkdir(exist_ok=True)
    cases.append(ConfigCase("unreadable", "a directory", a_dir, "<file>"))
    below_file = directory / "good.key" / "armbridge.toml"
    cases.append(ConfigCase("unreadable", "path below a file", below_file, "<file>"))
    if os.geteuid() != 0:  # root reads a mode-000 file anyway
        locked = directory / "locked.toml"
        locked.write_text(good)
        locked.chmod(0)
        cases.append(ConfigCase("unreadable", "mode 000", locked, "<file>"))
    return cases


@dataclass
class ConfigReport:
    cases: Counter = field(default_factory=Counter)  # per category
    fields_covered: set = field(default_factory=set)
    failures: list[str] = field(default_factory=list)  # wrong exit code or field not named
    elapsed_s: float = 0.0


def check_config_case(case: ConfigCase) -> str | None:
    """Run ``armbridge check-config`` in-process; None if it exits 2 naming the field."""
    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        try:
            code = cli.main(["check-config", str(case.path)])
        except Exception as exc:  # a crash is what we are looking for
            return f"{case.description}: raised {exc!r}"
    message = err.getvalue()
    named = f": {case.field}: " in message or f": {case.field}[" in message  # park_deg[5]
    if not named and "." in case.field:
        # A joint's calibration is checked as a whole: "joint[3]: pwm_min_us=499 outside ...".
        prefix, _, key = case.field.rpartition(".")
        _, found, problem = message.partition(f": {prefix}: ")
        named = bool(found) and key in problem
    if code != 2 or not named or str(case.path) not in message:
        return f"{case.description}: exit {code}, expected 2 naming {case.field!r}: {message!r}"
    return None


def run_config_fuzz(directory: Path, *, seed: int) -> ConfigReport:
    report = ConfigReport()
    started = time.perf_counter()
    for case in config_cases(directory, np.random.default_rng(seed)):
        report.cases[case.category] += 1
        report.fields_covered.add(case.field)
        problem = check_config_case(case)
        if problem:
            report.failures.append(problem)
    report.elapsed_s = time.perf_counter() - started
    return report


def run_rejects_config(directory: Path, text: str) -> tuple[int, str, int]:
    """``armbridge run`` on a bad config with a peer listening at its URL:
    (exit code, stderr, datagrams the peer received)."""
    listener = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    listener.bind(("127.0.0.1", 0))
    port = listener.getsockname()[1]
    path = directory / "run-bad.toml"
    # The example's socket (/run/armbridge) would be shared with any other run on the machine.
    text = text.replace(
        'socket = "/run/armbridge/control.sock"', f'socket = "{directory / "control.sock"}"'
    )
    path.write_text(text.replace("udpout:127.0.0.1:14550", f"udpout:127.0.0.1:{port}"))
    try:
        proc = run_daemon(path, timeout_s=60.0)
        # The process has exited: anything it sent is already queued on our socket.
        received = 0
        while select.select([listener], [], [], 0)[0]:
            listener.recv(65535)
            received += 1
    finally:
        listener.close()
    return proc.returncode, proc.stderr, received
