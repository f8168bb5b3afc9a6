"""Planning a servo update and counting its ACKs: pure, no link."""

from __future__ import annotations

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from firmware_interface import PwmOutOfRange, default_calibration, make_servo_dialect
from firmware_interface.updates import UpdateState, UpdateTracker

SERVO = mavlink.MAV_CMD_DO_SET_SERVO
ACCEPTED, FAILED = mavlink.MAV_RESULT_ACCEPTED, mavlink.MAV_RESULT_FAILED
PWM = {9: 1500, 10: 1510, 11: 1520, 12: 1530, 13: 1540, 14: 1550}


def plan(dialect="ardupilot", pwm=PWM, acked=None):
    return make_servo_dialect(dialect, None, default_calibration()).plan(pwm, acked)


def test_ardupilot_plans_one_command_per_output_not_yet_acknowledged_at_its_value():
    commands = plan()
    assert [c.outputs for c in commands] == [(o,) for o in PWM]
    assert [c.params[:2] for c in commands] == [(float(o), float(p)) for o, p in PWM.items()]
    assert [c.outputs for c in plan(acked={**PWM, 11: 1000})] == [(11,)]
    assert plan(acked=PWM) == []


def test_px4_plans_one_command_for_every_output():
    [command] = plan("px4", acked=PWM)
    assert command.command == mavlink.MAV_CMD_DO_SET_ACTUATOR
    assert command.outputs == tuple(PWM)


def test_a_pwm_out_of_range_is_refused_before_anything_is_planned():
    with pytest.raises(PwmOutOfRange):
        plan(pwm={**PWM, 12: 2600})


def tracker(n=6, timeout_s=0.5):
    return UpdateTracker(plan()[:n], sent_s=0.0, timeout_s=timeout_s, grace_s=0.05)


def test_all_accepted_is_done_at_the_last_ack():
    t = tracker()
    for _ in range(5):
        t.on_ack(SERVO, ACCEPTED, 0.001)
        assert t.poll(0.001) is None
    t.on_ack(SERVO, ACCEPTED, 0.002)
    outcome = t.poll(0.002)
    assert outcome.state is UpdateState.DONE and outcome.accepted == PWM


def test_fewer_acks_by_the_deadline_leave_every_output_unknown():
    t = tracker()
    for _ in range(5):
        t.on_ack(SERVO, ACCEPTED, 0.001)
    assert t.poll(0.49) is None
    outcome = t.poll(0.5)
    assert outcome.state is UpdateState.UNKNOWN and set(outcome.unknown) == set(PWM)
    assert outcome.accepted == {}


def test_one_ack_too_many_is_not_trusted():
    # A forged FAILED first, then the six genuine ACKs: seven answers for six commands.
    t = tracker()
    t.on_ack(SERVO, FAILED, 0.001)
    for _ in range(6):
        t.on_ack(SERVO, ACCEPTED, 0.002)
    assert t.poll(0.002) is None  # waits out the grace for a STATUSTEXT or an extra ACK
    assert t.poll(0.06).state is UpdateState.UNKNOWN


def test_a_refusal_named_by_the_statustext_refuses_that_output_only():
    t = tracker()
    for _ in range(5):
        t.on_ack(SERVO, ACCEPTED, 0.001)
    t.on_ack(SERVO, FAILED, 0.001)
    assert t.poll(0.01) is None  # the STATUSTEXT comes a loop pass later
    t.on_statustext("ServoRelayEvent: Channel 14 is already in use")
    outcome = t.poll(0.06)
    assert outcome.state is UpdateState.DONE
    assert set(outcome.accepted) == {9, 10, 11, 12, 13}
    assert "Channel 14 is already in use" in outcome.refused[14]


def test_a_statustext_naming_an_accepted_output_means_the_count_is_wrong():
    t = tracker()
    for _ in range(5):
        t.on_ack(SERVO, ACCEPTED, 0.001)
    t.on_ack(SERVO, FAILED, 0.001)
    t.on_statustext("ServoRelayEvent: Channel 10 is already in use")
    assert t.poll(0.06).state is UpdateState.UNKNOWN


def test_a_temporary_rejection_is_not_final_and_other_commands_acks_do_not_count():
    t = tracker(n=2)
    assert not t.on_ack(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, ACCEPTED, 0.0)
    assert not t.on_ack(SERVO, mavlink.MAV_RESULT_IN_PROGRESS, 0.0)
    t.on_ack(SERVO, ACCEPTED, 0.001)
    t.on_ack(SERVO, mavlink.MAV_RESULT_TEMPORARILY_REJECTED, 0.001)
    outcome = t.poll(0.1)
    assert outcome.state is UpdateState.UNKNOWN
    assert outcome.accepted == {9: 1500} and outcome.unknown == (10,)
