"""What the output-cycles bench (``bench/output_cycles.py``) and the udpin race found in the core,
in-process with a fake clock: each test is a rule the core broke before it was fixed.
"""

from __future__ import annotations

import math
from types import SimpleNamespace

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from companion.daemon.config import parse_config
from companion.daemon.core import Answer, ControlCore, ReadParam, SendCommand
from companion.daemon.requests import Outcome, Request
from tests.support.timing import FakeClock

#: BRD_SAFETY_MASK with the default arm outputs 9–14 (bits 8–13).
ARM_MASK = sum(1 << (o - 1) for o in range(9, 15))


def solve_to_itself(pose, q_start_deg, mode="pose", budget_ms=None):
    """A target's six numbers are the joint angles it solves to."""
    return SimpleNamespace(
        q_deg=pose.as_tuple(), converged=True, pos_err_cm=0.0, ori_err_deg=0.0, elapsed_ms=0.1
    )


class Autopilot:
    """A core linked to an autopilot whose frames are real pymavlink frames."""

    def __init__(self, dialect: str) -> None:
        self.clock = FakeClock()
        config = parse_config({"link": {"url": "udpout:127.0.0.1:14550", "dialect": dialect}})
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
