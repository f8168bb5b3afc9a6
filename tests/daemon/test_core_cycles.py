"""What the output-cycles bench (``bench/output_cycles.py``) and the udpin race found in the core,
in-process with a fake clock: each test is a rule the core broke before it was fixed.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from companion.daemon.config import parse_config
from companion.daemon.core import (
    SAFETY_STEPS_AHEAD,
    SYS_STATUS_SILENT_S,
    Answer,
    ControlCore,
    ReadParam,
    SendCommand,
)
from companion.daemon.requests import Outcome, Request
from devkit.timing import FakeClock

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


@pytest.mark.parametrize("dialect", ["px4", "ardupilot"])
def test_after_a_reboot_the_autopilot_has_not_heard_us_until_it_answers_again(dialect):
    ap = Autopilot(dialect)
    ap.answer_intervals()
    assert ap.core.status()["autopilot_heard_us"] is True
    actions = ap.reboot()
    assert any(getattr(a, "command", None) == mavlink.MAV_CMD_SET_MESSAGE_INTERVAL for a in actions)
    # Its routing table is empty now: it knows our route again only once it answers us.
    assert ap.core.status()["autopilot_heard_us"] is False
    ap.answer_intervals()
    assert ap.core.status()["autopilot_heard_us"] is True


def test_ardupilot_safety_mask_is_read_again_after_a_reboot():
    ap = Autopilot("ardupilot")
    assert [a.name for a in ap.actions if isinstance(a, ReadParam)] == ["BRD_SAFETY_MASK"]
    ap.answer_intervals()
    ap.frame(
        ap.codec.param_value_encode(
            b"BRD_SAFETY_MASK", float(ARM_MASK), mavlink.MAV_PARAM_TYPE_INT32, 1, 65535
        )
    )
    actions = ap.reboot()
    assert [a.name for a in actions if isinstance(a, ReadParam)] == ["BRD_SAFETY_MASK"]


def test_ardupilot_steps_sent_before_the_switch_was_seen_do_not_jump_at_its_release():
    """An autopilot streaming SYS_STATUS at the interval the core asked for; the switch goes on
    just after one (the worst case) while the arm moves, and is released a second later. What
    the outputs then show must be within one step of what they showed when it went on."""
    ap = Autopilot("ardupilot")
    asked = {
        int(a.params[0]): a.params[1] / 1e6
        for a in ap.actions
        if isinstance(a, SendCommand) and a.command == mavlink.MAV_CMD_SET_MESSAGE_INTERVAL
    }
    status_interval_s = asked[mavlink.MAVLINK_MSG_ID_SYS_STATUS]
    ap.answer_intervals()
    ap.frame(ap.codec.param_value_encode(b"BRD_SAFETY_MASK", 0.0, 9, 1, 65535))  # arm not in it
    outputs = mavlink.MAV_SYS_STATUS_SENSOR_MOTOR_OUTPUTS

    def sys_status(switch_on: bool) -> list:
        enabled = 0 if switch_on else outputs
        return ap.frame(
            ap.codec.sys_status_encode(outputs, enabled, outputs, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0)
        )

    sys_status(False)
    start = ap.core.status()["current_deg"]
    low = math.degrees(ap.config.arm.joints[0].min_rad)
    goal = [low + 1.0, *start[1:]]  # a long way on joint 1: seconds at 60 deg/s
    request = Request("goto", tuple(goal))
    step_us = ap.config.joint_speed_deg_s / ap.config.rate_hz / _deg_per_us(ap) + 1

    def acked_pwm() -> int:
        return int((ap.core.status()["last_pwm_us"] or {}).get(9, 0))

    def carry_out(actions: list) -> None:
        """The edge: answers set, every servo command acknowledged (and what that brings)."""
        while actions:
            action = actions.pop(0)
            if isinstance(action, Answer):
                action.request.answer(action.reply)
            elif isinstance(action, SendCommand) and action.command == mavlink.MAV_CMD_DO_SET_SERVO:
                actions += ap.frame(
                    ap.codec.command_ack_encode(
                        action.command, mavlink.MAV_RESULT_ACCEPTED, 0, 0, 1, 191
                    )
                )

    carry_out(ap.core.request(request))
    switch_on, t0_pwm, released_pwm = False, None, None
    next_status_s = ap.clock() + status_interval_s
    t_start = ap.clock()
    while ap.clock() - t_start < 2.0:
        ap.clock.advance(0.005)
        now = ap.clock() - t_start
        carry_out(ap.core.tick(True))
        if ap.clock() >= next_status_s:
            carry_out(sys_status(switch_on))
            next_status_s += status_interval_s
            if t0_pwm is None and now >= 0.3:
                # Just after a SYS_STATUS: the switch goes on, and the outputs hold this PWM.
                switch_on, t0_pwm = True, acked_pwm()
        if switch_on and now >= 1.3:
            released_pwm = acked_pwm()  # released: the stored PWM goes out at once
            break
    assert request.future.result(0).outcome is Outcome.ACCEPTED
    assert t0_pwm is not None and released_pwm is not None
    assert abs(released_pwm - t0_pwm) <= step_us, (t0_pwm, released_pwm, step_us)


def _deg_per_us(ap: Autopilot) -> float:
    joint = ap.config.calibration.for_output(9)
    return (joint.angle_max_deg - joint.angle_min_deg) / (joint.pwm_max_us - joint.pwm_min_us)


# -- ArduPilot's safety switch and reboots against a model of its outputs ----------------------

SERVO = mavlink.MAV_CMD_DO_SET_SERVO
INTERVAL = mavlink.MAV_CMD_SET_MESSAGE_INTERVAL
SYS_STATUS = mavlink.MAVLINK_MSG_ID_SYS_STATUS
SYSTEM_TIME = mavlink.MAVLINK_MSG_ID_SYSTEM_TIME
SERVO_OUTPUT_RAW = mavlink.MAVLINK_MSG_ID_SERVO_OUTPUT_RAW
MOTORS = mavlink.MAV_SYS_STATUS_SENSOR_MOTOR_OUTPUTS


class ArduPilotOutputs(Autopilot):
    """The core linked to a model of ArduPilot's outputs, as the simulator has them: a servo
    command is applied (and its ACK comes) ``ack_delay_s`` after it was sent; the safety switch
    (``BRD_SAFETY_MASK`` 0) keeps every arm output without pulses (its servo holds where it was)
    while the commands are still stored and acknowledged, and they go out at its release; a
    reboot is silent for 0.36 s and comes back with no pulses on the arm's outputs, the switch at
    ``BRD_SAFETY_DEFLT`` and every stream forgotten (SYSTEM_TIME, SYS_STATUS: asked again or
    never sent). ``changes`` collects every physical change of a pulse: (t_s, output, from_us,
    to_us), from the last pulse before a gap."""

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
        self.streams: dict[int, float] = {}
        self.due_s: dict[int, float] = {}
        self.boot_s = self.clock()
        self.rebooting_until_s: float | None = None
        self.commanded: dict[int, int] = {}
        self.pulse: dict[int, int] = {}  # the last pulse each servo got (held through gaps)
        self.changes: list[tuple[float, int, int, int]] = []
        self.pending: list[tuple[float, Any]] = []  # (due, SendCommand) on their way
        self.carry_out(self.actions)

    # -- what the outputs do --

    def live(self) -> bool:
        return self.rebooting_until_s is None and not self.safety_on

    def refresh(self) -> None:
        if not self.live():
            return
        for output, pwm in self.commanded.items():
            if pwm and self.pulse.get(output) != pwm:
                if output in self.pulse:
                    self.changes.append((self.clock(), output, self.pulse[output], pwm))
                self.pulse[output] = pwm

    def set_safety(self, on: bool) -> None:
        if self.rebooting_until_s is None:  # (as the simulator: not while rebooting)
            self.safety_on = on
            self.refresh()

    def reboot_now(self) -> None:
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
            self.carry_out(
                self.frame(self.codec.param_value_encode(b"BRD_SAFETY_MASK", 0.0, 6, 1, 65535))
            )
            return
        if action.command == SERVO:
            self.commanded[int(action.params[0])] = int(action.params[1])
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
                self.frame(
                    self.codec.heartbeat_encode(
                        mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA, 0, 0, 3
                    )
                )
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
        """Physical changes more than one control tick's step (plus one µs) of the joint."""
        step_deg = self.config.joint_speed_deg_s / self.config.rate_hz
        fast = []
        for t_s, output, before, after in self.changes:
            joint = self.config.calibration.for_output(output)
            moved = abs(joint.pwm_us_to_angle_deg(after) - joint.pwm_us_to_angle_deg(before))
            if moved > step_deg + _deg_per_us(self) + 1e-9:
                fast.append((t_s, output, before, after, moved))
        return fast


def _far_target(ap: Autopilot, rng: np.random.Generator) -> tuple[float, ...]:
    """Joint angles drawn within 90 % of each joint's limits."""
    q = []
    for joint in ap.config.arm.joints:
        lo, hi = math.degrees(joint.min_rad), math.degrees(joint.max_rad)
        mid, half = (lo + hi) / 2, (hi - lo) / 2 * 0.9
        q.append(float(rng.uniform(mid - half, mid + half)))
    return tuple(q)


def test_after_a_reboot_every_stream_the_core_reads_is_asked_for_again():
    """Cause 1: ArduPilot (and the simulator) forget every message interval when they reboot:
    SYSTEM_TIME, SERVO_OUTPUT_RAW and SYS_STATUS are asked for again once it is seen."""
    ap = ArduPilotOutputs()
    ap.run(0.5)
    asked_before = dict(ap.streams)
    assert {SYSTEM_TIME, SERVO_OUTPUT_RAW, SYS_STATUS} <= asked_before.keys()
    ap.reboot_now()
    ap.run(0.5)  # back after 0.36 s, with no stream at all
    assert not ap.streams or ap.core.status()["counters"]["autopilot_reboots"] == 1
    ap.run(2.0)  # SYSTEM_TIME silent for 1 s: asked again, then the reboot is seen
    assert ap.core.status()["counters"]["autopilot_reboots"] == 1
    assert ap.streams == asked_before
    assert ap.core.status()["safety_on"] is False


def test_ardupilot_a_switch_seen_on_after_a_reboot_rewinds_to_no_pose_from_before_it():
    """Cause 2: moving, the switch goes on and is seen (the outputs sent back), the autopilot
    reboots and comes back with its switch on (BRD_SAFETY_DEFLT 1): nothing is sent while it is
    on (the rewind was to a pose recorded before the reboot), and its release moves no joint by
    more than a step."""
    ap = ArduPilotOutputs(safety_default_on=True)
    ap.run(0.3)
    start = ap.core.status()["current_deg"]
    ap.goto([start[0] + 40.0, *start[1:]])
    ap.run(0.4)
    ap.set_safety(True)
    ap.run(0.3)  # seen on: the held outputs are sent back
    ap.reboot_now()
    ap.run(0.4)
    assert ap.commanded == {}  # rebooted: nothing stored
    ap.run(2.0)
    assert ap.core.status()["counters"]["autopilot_reboots"] == 1
    assert ap.core.status()["safety_on"] is True
    assert ap.commanded == {}  # nothing sent while its switch is on after the reboot
    ap.set_safety(False)
    ap.run(1.0)
    assert ap.commanded  # moving again
    assert ap.fast_changes() == []


def test_ardupilot_a_silent_sys_status_stream_stops_the_arm_within_a_step():
    """Cause 3: a SYS_STATUS that said "off" long ago is not trusted: with the stream silent,
    the arm moves at most SAFETY_STEPS_AHEAD steps (one) from where it was when the last one
    came, status says the outputs are not known to be live after SYS_STATUS_STALE_INTERVALS,
    and every stream is asked for again after SYS_STATUS_SILENT_S; the arm goes on once
    SYS_STATUS is back."""
    ap = ArduPilotOutputs()
    ap.run(0.3)
    start = ap.core.status()["current_deg"]
    ap.goto([start[0] + 60.0, *start[1:]])
    ap.run(0.2)
    interval_s = ap.streams.pop(SYS_STATUS)  # the stream stops
    at_last_status = ap.core.status()["current_deg"][0]
    ap.run(SYS_STATUS_SILENT_S - 0.05)
    step_deg = ap.config.joint_speed_deg_s / ap.config.rate_hz
    moved_deg = abs(ap.core.status()["current_deg"][0] - at_last_status)
    assert moved_deg <= SAFETY_STEPS_AHEAD * step_deg + 1e-6
    status = ap.core.status()
    assert status["outputs_live"] is False
    assert "no SYS_STATUS for" in status["not_live"]["9"]
    ap.run(0.1)  # silent SYS_STATUS_SILENT_S: asked for again (the model streams it again)
    assert ap.streams.get(SYS_STATUS) == interval_s
    ap.run(0.5)
    assert ap.core.status()["outputs_live"] is True
    assert abs(ap.core.status()["current_deg"][0] - at_last_status) > 5 * step_deg
    assert ap.fast_changes() == []


@pytest.mark.parametrize("ack_delay_s", [0.003, 0.012])
def test_ardupilot_at_50_hz_the_safety_band_does_not_slow_the_arm(ack_delay_s):
    """At 50 Hz control SYS_STATUS (40 Hz) comes less often than the ticks, and one may come
    while a step is on its way: a band one 50 Hz step wide held the arm to 48 of 60 deg/s (and
    a followed world target fell behind). SAFETY_BAND_MIN_S keeps it at full speed."""
    ap = ArduPilotOutputs(rate_hz=50.0, ack_delay_s=ack_delay_s)
    ap.run(0.3)
    start = ap.core.status()["current_deg"]
    ap.goto([start[0] + 90.0, *start[1:]])
    ap.run(0.1)
    at_deg = ap.core.status()["current_deg"][0]
    ap.run(1.0)
    speed_deg_s = abs(ap.core.status()["current_deg"][0] - at_deg) / 1.0
    assert speed_deg_s >= 0.95 * ap.config.joint_speed_deg_s
    assert ap.fast_changes() == []


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_ardupilot_no_joint_moves_faster_than_a_step_through_switch_and_reboot_cycles(seed):
    """Causes 2, 4 and 5 together: random targets (some in 50 Hz bursts), the safety switch on
    and off at any moment (some presses shorter than a SYS_STATUS interval) and reboots with the
    switch at either default: every physical change of a pulse is within one control tick's
    step (plus one µs) of the last pulse before it."""
    rng = np.random.default_rng(seed)
    ap = ArduPilotOutputs(safety_default_on=bool(seed % 2))
    ap.run(0.3)
    if ap.safety_on:
        ap.set_safety(False)
    for _ in range(60):
        roll = rng.random()
        if roll < 0.4:
            ap.goto(_far_target(ap, rng))
        elif roll < 0.5:
            for _ in range(10):  # a ground station's 50 Hz stream, each a little further
                ap.goto(_far_target(ap, rng))
                ap.run(0.02)
        elif roll < 0.8:
            ap.set_safety(not ap.safety_on)
        elif roll < 0.85 and ap.rebooting_until_s is None:
            ap.reboot_now()
        ap.run(float(np.exp(rng.uniform(math.log(0.01), math.log(0.6)))))
    assert len(ap.changes) > 100
    assert ap.fast_changes() == []
