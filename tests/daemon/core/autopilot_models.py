"""Autopilots as the output-cycles bench (``bench/output_cycles.py``) and the udpin race
measured them, for the core in-process with a fake clock: a core linked to an autopilot whose
frames are real pymavlink frames, and a model of ArduPilot's outputs behind its safety
switch."""

from __future__ import annotations

import math
from collections.abc import Sequence
from types import SimpleNamespace
from typing import Any

import numpy as np
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from companion.daemon.config import parse_config
from companion.daemon.core import (
    Answer,
    ControlCore,
    ReadParam,
    SendCommand,
)
from companion.daemon.requests import Request
from devkit.timing import FakeClock
from tests.daemon.core.rig import SERVO

#: BRD_SAFETY_MASK with the default arm outputs 9–14 (bits 8–13).
ARM_MASK = sum(1 << (o - 1) for o in range(9, 15))


def solve_to_itself(pose, q_start_deg, mode="pose", budget_ms=None):
    """A target's six numbers are the joint angles it solves to."""
    return SimpleNamespace(
        q_deg=pose.as_tuple(), converged=True, pos_err_cm=0.0, ori_err_deg=0.0, elapsed_ms=0.1
    )


class Autopilot:
    """A core linked to an autopilot whose frames are real pymavlink frames."""

    def __init__(self, dialect: str, rate_hz: float | None = None) -> None:
        self.clock = FakeClock()
        tables: dict[str, Any] = {"link": {"url": "udpout:127.0.0.1:14550", "dialect": dialect}}
        if rate_hz is not None:
            tables["control"] = {"rate_hz": rate_hz}
        config = parse_config(tables)
        self.tables = tables
        self.config = config
        self.core = ControlCore(config, solve=solve_to_itself, clock=self.clock)
        self.codec = mavlink.MAVLink(None, 1, 1)
        self.decoder = mavlink.MAVLink(None)
        kind = (
            mavlink.MAV_AUTOPILOT_PX4 if dialect == "px4" else mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA
        )
        self.frame(self.codec.heartbeat_encode(mavlink.MAV_TYPE_QUADROTOR, kind, 0, 0, 3))
        self.actions = self.core.tick(True)

    def frame(self, msg) -> list:
        return self.core.frame(self.decoder.parse_buffer(msg.pack(self.codec))[0])

    def answer_intervals(self) -> list:
        return self.frame(
            self.codec.command_ack_encode(
                mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, mavlink.MAV_RESULT_ACCEPTED, 0, 0, 1, 191
            )
        )

    def reboot(self) -> list:
        """Up for 600 s, then back after a 0.36 s reboot (time_boot_ms went back)."""
        self.frame(self.codec.system_time_encode(0, 600_000))
        self.clock.advance(0.36)
        actions = self.frame(self.codec.system_time_encode(0, 150))
        assert self.core.status()["counters"]["autopilot_reboots"] == 1
        return actions


def deg_per_us(ap: Autopilot) -> float:
    joint = ap.config.calibration.for_output(9)
    return (joint.angle_max_deg - joint.angle_min_deg) / (joint.pwm_max_us - joint.pwm_min_us)


INTERVAL = mavlink.MAV_CMD_SET_MESSAGE_INTERVAL


SYS_STATUS = mavlink.MAVLINK_MSG_ID_SYS_STATUS


SYSTEM_TIME = mavlink.MAVLINK_MSG_ID_SYSTEM_TIME


SERVO_OUTPUT_RAW = mavlink.MAVLINK_MSG_ID_SERVO_OUTPUT_RAW


MOTORS = mavlink.MAV_SYS_STATUS_SENSOR_MOTOR_OUTPUTS


class ArduPilotOutputsModel(Autopilot):
    """The core linked to a model of ArduPilot's outputs, as the simulator has them: a servo
    command is applied (and its ACK comes) ``ack_delay_s`` after it was sent; the safety switch
    keeps every arm output not in ``BRD_SAFETY_MASK`` (``mask``, 0 unless set) without pulses
    (its servo holds where it was) while the commands are still stored and acknowledged, and
    they go out at its release; a new mask applies at the next tenth of a second since boot
    (ArduPilot's output driver reads it at 10 Hz); a
    reboot is silent for 0.36 s and comes back with no pulses on the arm's outputs, the switch at
    ``BRD_SAFETY_DEFLT`` and every stream forgotten (SYSTEM_TIME, SYS_STATUS: asked again or
    never sent). ``changes`` collects every physical change of a pulse: (t_s, output, from_us,
    to_us), from the last pulse before a gap, and ``allowed_deg`` the most each may move the
    joint, as ``devkit/joint_steps.py`` judges the simulator's: a step at the speed limit in
    force (either, within RELOAD_WINDOW_S of a :meth:`reload`), or at the one when the value
    coming out was stored or the pulses stopped, if higher."""

    #: A step computed before a reload goes out up to a control period and the command's way
    #: after it.
    RELOAD_WINDOW_S = 0.06

    def __init__(
        self,
        *,
        safety_default_on: bool = False,
        ack_delay_s: float = 0.003,
        rate_hz: float | None = None,
    ) -> None:
        super().__init__("ardupilot", rate_hz)
        self.ack_delay_s = ack_delay_s
        self.safety_default_on = safety_default_on
        self.safety_on = False
        self.mask = self.applied_mask = 0
        self.mask_due_s: float | None = None
        self.streams: dict[int, float] = {}
        self.due_s: dict[int, float] = {}
        self.boot_s = self.clock()
        self.rebooting_until_s: float | None = None
        self.commanded: dict[int, int] = {}
        self.pulse: dict[int, int] = {}  # the last pulse each servo got (held through gaps)
        self.changes: list[tuple[float, int, int, int]] = []
        self.allowed_deg: list[float] = []
        self.speeds: list[tuple[float, float]] = [(self.clock(), self.config.joint_speed_deg_s)]
        self.stored_s: dict[int, float] = {}  # per output, when its value was stored
        self.held_s: dict[int, float] = {}  # per output, when its pulses stopped
        self.pose_left: tuple[dict[int, int], dict[int, int]] | None = None
        self.pending: list[tuple[float, Any]] = []  # (due, SendCommand) on their way
        self.carry_out(self.actions)

    # -- what the outputs do --

    def live(self, output: int) -> bool:
        if self.rebooting_until_s is not None:
            return False
        return not self.safety_on or bool(self.applied_mask >> (output - 1) & 1)

    def refresh(self) -> None:
        now = self.clock()
        for output, pwm in self.commanded.items():
            if not self.live(output):
                self.held_s.setdefault(output, now)
            elif pwm and self.pulse.get(output) != pwm:
                if output in self.pulse:
                    self.changes.append((now, output, self.pulse[output], pwm))
                    times = (now, self.stored_s.get(output, now), self.held_s.get(output, now))
                    fastest = max(self.speed_at(t) for t in times)
                    self.allowed_deg.append(fastest / self.config.rate_hz)
                self.pulse[output] = pwm
            if self.live(output) and pwm:
                self.held_s.pop(output, None)

    def speed_at(self, t_s: float) -> float:
        """The highest speed limit that may be in force at ``t_s``."""
        return max(
            speed
            for k, (since_s, speed) in enumerate(self.speeds)
            if since_s <= t_s
            and (k + 1 == len(self.speeds) or self.speeds[k + 1][0] >= t_s - self.RELOAD_WINDOW_S)
        )

    def reload(self, joint_speed_deg_s: float) -> None:
        """The daemon reloaded with a new speed limit."""
        arm = {**self.tables.get("arm", {}), "joint_speed_deg_s": joint_speed_deg_s}
        self.tables = {**self.tables, "arm": arm}
        self.config = parse_config(self.tables)
        self.core.reconfigure(self.config)
        self.speeds.append((self.clock(), joint_speed_deg_s))

    def set_safety(self, on: bool) -> None:
        if self.rebooting_until_s is None:  # (as the simulator: not while rebooting)
            self.safety_on = on
            self.refresh()

    def set_mask(self, mask: int, *, broadcast: bool = True) -> None:
        """A ground station sets BRD_SAFETY_MASK (``broadcast``: the PARAM_VALUE ArduPilot
        sends every link on a change reaches the core); it applies at the next tick."""
        self.mask = mask
        ticks = math.floor((self.clock() - self.boot_s) / 0.1 + 1e-9) + 1
        self.mask_due_s = self.boot_s + ticks * 0.1
        if broadcast:
            self.carry_out(self.frame(self.mask_value()))

    def mask_value(self) -> Any:
        return self.codec.param_value_encode(
            b"BRD_SAFETY_MASK", float(self.mask), mavlink.MAV_PARAM_TYPE_INT32, 1, 65535
        )

    def restart_daemon(self) -> None:
        """The daemon is killed and started again at once: a new core, given where the
        outputs were left as the last daemon to know wrote it (``pose_file``)."""
        left = self.core.outputs_left()
        if left is not None:
            self.pose_left = left
        self.core = ControlCore(self.config, solve=solve_to_itself, clock=self.clock)
        if self.pose_left is not None:
            self.core.restore_pose(self.pose_left)
        kind = mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA
        self.carry_out(
            self.frame(self.codec.heartbeat_encode(mavlink.MAV_TYPE_QUADROTOR, kind, 0, 0, 3))
        )
        self.carry_out(self.core.tick(True))

    def reboot_now(self) -> None:
        for output in self.pulse:
            self.held_s.setdefault(output, self.clock())
        self.rebooting_until_s = self.clock() + 0.36
        self.pending.clear()

    # -- the link --

    def carry_out(self, actions: list) -> None:
        for action in actions:
            if isinstance(action, Answer):
                action.request.answer(action.reply)
            elif isinstance(action, ReadParam):
                self.pending.append((self.clock() + self.ack_delay_s, action))
            elif isinstance(action, SendCommand):
                self.pending.append((self.clock() + self.ack_delay_s, action))

    def deliver(self, action: Any) -> None:
        if self.rebooting_until_s is not None:
            return  # deaf
        if isinstance(action, ReadParam):
            self.carry_out(self.frame(self.mask_value()))
            return
        if action.command == SERVO:
            self.commanded[int(action.params[0])] = int(action.params[1])
            self.stored_s[int(action.params[0])] = self.clock()
            self.refresh()
        elif action.command == INTERVAL:
            msg_id, interval_us = int(action.params[0]), action.params[1]
            if interval_us > 0:
                self.streams[msg_id] = interval_us / 1e6
                self.due_s[msg_id] = self.clock()
        self.carry_out(
            self.frame(
                self.codec.command_ack_encode(
                    action.command, mavlink.MAV_RESULT_ACCEPTED, 0, 0, 1, 191
                )
            )
        )
        if action.command == mavlink.MAV_CMD_REQUEST_MESSAGE:  # (a clock probe)
            self.carry_out(self.frame(self.stream_frame(int(action.params[0]))))

    def run(self, seconds: float, dt_s: float = 0.005) -> None:
        end_s = self.clock() + seconds
        while self.clock() < end_s - 1e-9:
            self.clock.advance(dt_s)
            now = self.clock()
            if self.rebooting_until_s is not None and now >= self.rebooting_until_s:
                self.rebooting_until_s = None
                self.boot_s = now
                self.commanded = {}
                self.streams.clear()
                self.safety_on = self.safety_default_on
                self.applied_mask, self.mask_due_s = self.mask, None
                self.frame(
                    self.codec.heartbeat_encode(
                        mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA, 0, 0, 3
                    )
                )
            if self.mask_due_s is not None and now >= self.mask_due_s - 1e-9:
                self.applied_mask, self.mask_due_s = self.mask, None
                self.refresh()
            due = [p for p in self.pending if p[0] <= now]
            self.pending = [p for p in self.pending if p[0] > now]
            for _, action in due:
                self.deliver(action)
            if self.rebooting_until_s is None:
                for msg_id, interval_s in list(self.streams.items()):
                    if now >= self.due_s[msg_id]:
                        self.due_s[msg_id] = max(self.due_s[msg_id] + interval_s, now)
                        self.carry_out(self.frame(self.stream_frame(msg_id)))
            self.carry_out(self.core.tick(True))

    def stream_frame(self, msg_id: int) -> Any:
        if msg_id == SYS_STATUS:
            enabled = 0 if self.safety_on else MOTORS
            return self.codec.sys_status_encode(
                MOTORS, enabled, MOTORS, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0
            )
        if msg_id == SYSTEM_TIME:
            return self.codec.system_time_encode(0, int((self.clock() - self.boot_s) * 1000) + 1)
        values = [self.commanded.get(n, 0) for n in range(1, 17)]
        return self.codec.servo_output_raw_encode(0, 0, *values)

    def goto(self, q_deg: Sequence[float]) -> Request:
        request = Request("goto", tuple(q_deg), received_s=self.clock())
        self.carry_out(self.core.request(request))
        return request

    def fast_changes(self) -> list[tuple[float, int, int, int, float]]:
        """Physical changes more than their allowance (``allowed_deg``) plus one µs of the
        joint."""
        fast = []
        for (t_s, output, before, after), step_deg in zip(
            self.changes, self.allowed_deg, strict=True
        ):
            joint = self.config.calibration.for_output(output)
            moved = abs(joint.pwm_us_to_angle_deg(after) - joint.pwm_us_to_angle_deg(before))
            if moved > step_deg + deg_per_us(self) + 1e-9:
                fast.append((t_s, output, before, after, moved))
        return fast


def far_target(ap: Autopilot, rng: np.random.Generator) -> tuple[float, ...]:
    """Joint angles drawn within 90 % of each joint's limits."""
    q = []
    for joint in ap.config.arm.joints:
        lo, hi = math.degrees(joint.min_rad), math.degrees(joint.max_rad)
        mid, half = (lo + hi) / 2, (hi - lo) / 2 * 0.9
        q.append(float(rng.uniform(mid - half, mid + half)))
    return tuple(q)
