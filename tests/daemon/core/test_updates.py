"""The update pipeline (``core/updates.py``): updates back-to-back, ACKs counted in order, a
step behind the one in flight, confirmation one command at a time, retries, refusals."""

from __future__ import annotations

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from companion.daemon.core import (
    UPDATE_ATTEMPTS,
)
from companion.daemon.requests import Outcome, Request
from tests.daemon.core.rig import ACCEPTED, FAILED, PARK, RATE_HZ, SERVO, STEP_DEG, Rig, near


def test_an_update_goes_out_back_to_back_and_is_answered_once_every_ack_is_in(rig):
    request = rig.goto(near(PARK))
    first = [c for c in rig.sent if c.command == SERVO]
    assert len(first) == 6  # all six at once, before any ACK
    assert [c.confirmation for c in first] == [0] * 6
    for _ in first[:5]:
        rig.ack()
        assert not request.answered  # not before the last one
    rig.ack()
    assert rig.reply(request).outcome is Outcome.ACCEPTED
    status = rig.core.status()
    assert status["last_pwm_us"] == rig.servo(first)
    assert {o["state"] for o in status["outputs"].values()} == {"acknowledged"}
    assert status["current_deg"] == pytest.approx(near(PARK))


def test_acks_to_progress_counts_down_the_oldest_update_short_of_acks(rig):
    # The service wakes its control thread only on the ACK that can change something: a
    # partial count decides nothing (the tracker's verdict waits for the last one).
    assert rig.core.acks_to_progress() == 1  # nothing in flight: any ACK may matter
    rig.goto(PARK)
    rig.ack_all(rig.sent)
    rig.sent.clear()
    rig.clock.advance(0.02)
    first = rig.goto(near(PARK))
    assert rig.core.acks_to_progress() == 6
    rig.ack()
    rig.ack()
    assert rig.core.acks_to_progress() == 4 and not first.answered
    rig.clock.advance(0.01)
    rig.goto(tuple(p + 20.0 for p in PARK))  # a second update behind the first
    assert rig.core.acks_to_progress() == 4  # still the oldest's count
    for _ in range(3):
        rig.ack()
    assert rig.core.acks_to_progress() == 1 and not first.answered
    rig.ack()
    assert rig.reply(first).outcome is Outcome.ACCEPTED
    assert rig.core.acks_to_progress() == 6  # now the one behind


def test_only_outputs_whose_pwm_changed_are_sent(rig):
    rig.ack_all(rig.take(rig.core.request(Request("goto", near(PARK)))))
    rig.sent.clear()
    rig.advance(1.0 / RATE_HZ)
    moved = list(near(PARK))
    moved[2] += 1.0  # one joint
    rig.goto(moved)
    assert list(rig.servo()) == [11]


def test_a_refused_output_stops_the_motion_reports_what_moved_and_the_next_step_keeps_the_limit(
    rig,
):
    # Joint 6's output (14) is a motor on the autopilot: DO_SET_SERVO is refused with a
    # STATUSTEXT naming the channel. Status says what did move, and the next target's step is
    # computed from there (from the stale park pose it would be a 5.9 deg jump in one step).
    far = tuple(p + 30.0 for p in PARK)
    request = rig.goto(far)
    first = [c for c in rig.sent if c.command == SERVO]
    assert len(first) == 6
    for _ in first[:5]:
        rig.ack()
    rig.ack(FAILED)
    rig.statustext("ServoRelayEvent: Channel 14 is already in use")
    rig.advance(0.2)  # past the grace for the STATUSTEXT
    reply = rig.reply(request)
    assert reply.outcome is Outcome.FAILED
    assert "output 14" in reply.message and "map the joint to a free output" in reply.message
    # A ground station shows 50 characters: the fix first, whole (real ArduPilot's
    # STATUSTEXT cut the old message mid-word).
    assert reply.statustext() == "Arm: output 14 in use (SERVO14_FUNCTION)"
    status = rig.core.status()
    assert status["goal_deg"] is None and not status["moving"]
    assert status["outputs"][14]["state"] == "refused"
    moved = rig.servo(first)
    assert status["last_pwm_us"] == {o: moved[o] for o in (9, 10, 11, 12, 13)}
    for j in range(5):
        assert status["current_deg"][j] == pytest.approx(PARK[j] + STEP_DEG)
    assert status["current_deg"][5] == PARK[5]
    assert status["outputs_live"] is False
    assert "refused" in status["not_live"]["14"]
    # The refusal is remembered: the next target fails before any step (a ground station
    # retrying crept the arm a step a target).
    rig.sent.clear()
    rig.advance(1.0 / RATE_HZ)
    retried = rig.goto(tuple(p - 30.0 for p in PARK))
    assert rig.reply(retried).outcome is Outcome.FAILED
    assert "SERVO14_FUNCTION" in rig.reply(retried).message
    assert "reload" in rig.reply(retried).message
    assert not rig.servo(rig.advance(0.5))
    # Fixed on the autopilot, the daemon reloaded: the next target steps from what was
    # acknowledged, no joint more than a step.
    rig.core.reconfigure(rig.config)
    rig.goto(tuple(p - 30.0 for p in PARK))
    for output, pwm in rig.servo().items():
        before = status["last_pwm_us"].get(output, rig.calibration.angles_to_pwm_us(PARK)[output])
        assert abs(rig.angle(output, pwm) - rig.angle(output, before)) <= STEP_DEG + 0.2


def test_missing_acks_leave_the_outputs_unknown_and_each_is_confirmed_alone(rig):
    request = rig.goto(near(PARK))
    first = [c for c in rig.sent if c.command == SERVO]
    for _ in range(4):
        rig.ack()  # two ACKs lost: which ones cannot be told
    rig.sent.clear()
    rig.advance(rig.config.link.command_timeout_s)
    assert not request.answered
    assert rig.core.status()["last_pwm_us"] is None  # nothing taken for granted
    # Now one command at a time, each answered before the next.
    for expected in first:
        [alone] = [c for c in rig.sent if c.command == SERVO]
        assert alone.params == expected.params and alone.confirmation == 1
        rig.sent.clear()
        rig.ack()
    assert rig.reply(request).outcome is Outcome.ACCEPTED
    assert rig.core.status()["last_pwm_us"] == rig.servo(first)


def test_an_ack_too_many_is_not_trusted(rig):
    # A forged FAILED arrives before the six genuine ACCEPTED: seven answers for six commands.
    # Believing it would abort the motion (it did before); counting shows the accounting was
    # disturbed, and the outputs are confirmed one at a time instead.
    request = rig.goto(near(PARK))
    rig.ack(FAILED)
    for _ in range(6):
        rig.ack()
    rig.sent.clear()
    rig.advance(0.2)
    assert not request.answered
    assert len([c for c in rig.sent if c.command == SERVO]) == 1  # confirming one at a time
    for _ in range(6):
        rig.ack()
    assert rig.reply(request).outcome is Outcome.ACCEPTED


def test_an_update_that_stays_unanswered_fails_its_target_and_is_resent_before_moving_on(rig):
    request = rig.goto(tuple(p + 30.0 for p in PARK))
    first = rig.servo()
    for _ in range(1 + rig.config.link.command_retries):
        rig.advance(rig.config.link.command_timeout_s)
        rig.readback(first)  # (after an update with no ACK at all, confirmed once one came)
        rig.advance(0.001)
    reply = rig.reply(request)
    assert reply.outcome is Outcome.FAILED and "no COMMAND_ACK" in reply.message
    status = rig.core.status()
    assert status["goal_deg"] is None and status["last_pwm_us"] is None
    assert status["counters"]["servo_errors"] == 1
    # Nothing more is sent on its own; a new target sends the unconfirmed step again first,
    # not a step beyond it.
    rig.sent.clear()
    rig.advance(1.0)
    assert rig.servo() == {}
    rig.goto(tuple(p - 30.0 for p in PARK))
    assert rig.servo() == first


def test_a_moving_arm_survives_unanswered_updates_up_to_update_attempts(rig):
    request = rig.goto(tuple(p + 30.0 for p in PARK))
    rig.ack_all(rig.sent)
    assert rig.reply(request).outcome is Outcome.ACCEPTED
    for attempt in range(1, UPDATE_ATTEMPTS + 1):
        rig.advance(1.0 / RATE_HZ)  # a tick: the next step goes out
        for _ in range(1 + rig.config.link.command_retries):
            rig.advance(rig.config.link.command_timeout_s)  # and is never answered
            rig.readback(rig.core.status()["last_pwm_us"] or {})
            rig.advance(0.001)
        moving = rig.core.status()["goal_deg"] is not None
        assert moving == (attempt < UPDATE_ATTEMPTS)


def test_a_target_goes_out_behind_the_update_in_flight_and_acks_are_counted_in_order(rig):
    # On a 115 200-baud line an update takes 13-21 ms: a target arriving meanwhile does not
    # wait out the whole round trip before its first step goes out.
    rig.goto(PARK)
    rig.ack_all(rig.sent)  # every output acknowledged: the state the pipe starts from
    rig.sent.clear()
    rig.clock.advance(0.02)
    first = rig.goto(near(PARK))
    ahead = rig.servo()
    rig.sent.clear()
    rig.clock.advance(0.01)  # half a tick later, the first update still in flight
    target = tuple(p + 20.0 for p in PARK)
    second = rig.goto(target)
    behind = [c for c in rig.sent if c.command == SERVO]
    assert len(behind) == 6  # every output the update ahead sent, at the new step
    for c in behind:
        output, pwm = int(c.params[0]), int(c.params[1])
        # One step from the command ahead of it, limited by the time since that one went out.
        assert 0 < rig.angle(output, pwm) - rig.angle(output, ahead[output]) <= STEP_DEG / 2 + 0.2
    for _ in range(6):
        rig.ack()
    assert rig.reply(first).outcome is Outcome.ACCEPTED and not second.answered
    assert rig.core.status()["last_pwm_us"] == ahead
    for _ in range(6):
        rig.ack()
    assert rig.reply(second).outcome is Outcome.ACCEPTED
    assert rig.core.status()["last_pwm_us"] == rig.servo(behind)
    # Never a third: the step after waits for the one ahead of it.
    rig.sent.clear()
    for delta_deg in (-20.0, -21.0, -22.0):
        rig.clock.advance(0.005)
        rig.goto(tuple(p + delta_deg for p in PARK))
    assert len([c for c in rig.sent if c.command == SERVO]) == 12


def test_an_unanswered_update_with_one_behind_it_is_decided_by_the_one_behind(rig):
    rig.goto(PARK)
    rig.ack_all(rig.sent)
    parked = rig.core.status()["last_pwm_us"]
    rig.sent.clear()
    rig.clock.advance(0.02)
    first = rig.goto(near(PARK))
    rig.clock.advance(0.01)
    second = rig.goto(tuple(p + 20.0 for p in PARK))
    ahead = rig.servo(rig.sent[:6])
    behind = [c for c in rig.sent if c.command == SERVO][6:]
    for _ in range(3):
        rig.ack()  # three of the first update's six: the rest lost, and all of the second's
    rig.sent.clear()
    rig.advance(rig.config.link.command_timeout_s - 0.005)  # the first's deadline
    assert not first.answered and not second.answered
    status = rig.core.status()
    assert status["last_pwm_us"] is None  # unknown, not "acknowledged at park"
    assert rig.servo() == {}  # no retry of the first: the second re-sent its outputs
    rig.advance(0.01)  # the second's deadline: no ACK at all for it
    rig.readback(parked)  # the confirmations wait for a readback since (a reboot?)
    rig.advance(0.001)  # its commands confirmed one at a time
    confirmed = {}
    for expected in behind:
        [alone] = [c for c in rig.sent if c.command == SERVO]
        output, pwm = int(alone.params[0]), int(alone.params[1])
        assert output == int(expected.params[0])
        # Each output holds park, the first step or the second: it is confirmed at their
        # middle (within one step of each), not at the second step (two from park).
        held = [parked[output], ahead[output], int(expected.params[1])]
        assert pwm == pytest.approx((min(held) + max(held)) / 2, abs=1)
        confirmed[output] = pwm
        rig.sent.clear()
        rig.ack()
    # Both targets are answered by the outcome of the update that carried their outputs.
    assert rig.reply(first).outcome is Outcome.ACCEPTED
    assert rig.reply(second).outcome is Outcome.ACCEPTED
    assert rig.core.status()["last_pwm_us"] == confirmed


def test_px4_sends_one_frame_for_every_joint():
    rig = Rig(dialect="px4")
    rig.heartbeat(autopilot=mavlink.MAV_AUTOPILOT_PX4)
    rig.tick()
    for _ in range(3):  # PX4 moves once the readbacks steadily show where the joints are
        rig.readback(rig.calibration.angles_to_pwm_us(PARK))
        rig.clock.advance(0.015)
        rig.clock_goes_on()  # the autopilot's clock going on after them
        rig.clock.advance(0.015)
    request = rig.goto(near(PARK))
    [frame] = [c for c in rig.sent if c.command == mavlink.MAV_CMD_DO_SET_ACTUATOR]
    rig.ack(command=mavlink.MAV_CMD_DO_SET_ACTUATOR)
    assert rig.reply(request).outcome is Outcome.ACCEPTED
    assert frame.params[6] == 0.0


def test_acks_taken_late_by_a_stalled_control_thread_are_judged_at_their_arrival(rig):
    # Under a stall the first ACK was judged at the thread's late time: its update seemed
    # unanswered while its other ACKs waited in the queue (a false servo error).
    request = rig.goto(near(PARK))
    sent = [c for c in rig.sent if c.command == SERVO]
    arrived_s = rig.clock() + 0.01
    rig.clock.advance(2 * rig.config.link.command_timeout_s)  # the thread stalled meanwhile
    for _ in sent:
        rig.frame(
            lambda c: c.command_ack_encode(SERVO, ACCEPTED, 0, 0, 1, 191), received_s=arrived_s
        )
    assert rig.reply(request).outcome is Outcome.ACCEPTED
    assert rig.core.status()["counters"]["servo_errors"] == 0


def test_an_update_with_no_ack_at_all_waits_for_a_readback_and_not_over_another_sender(
    rig,
):
    # The autopilot rebooted unseen (frames forged as its own filled its silence): not one ACK
    # came, and the step was confirmed one command at a time over a ground station's command
    # given since the boot (a 73 deg step).
    rig.system_time(600_000)
    request = rig.goto(near(PARK))
    rig.ack_all(rig.sent)
    assert rig.reply(request).outcome is Outcome.ACCEPTED
    acked = dict(rig.core.status()["last_pwm_us"])
    rig.goto(tuple(p + 30.0 for p in PARK))
    rig.advance(1.0 / RATE_HZ)
    rig.sent.clear()
    rig.advance(rig.config.link.command_timeout_s)  # not one ACK
    assert any(c.command == mavlink.MAV_CMD_SET_MESSAGE_INTERVAL for c in rig.sent)
    assert rig.servo() == {}  # nothing confirmed before a readback says where they are
    output = rig.calibration.outputs[0]
    shown = {**acked, output: 2000}
    for boot_ms in (600_900, 600_920, 600_940):  # a ground station's command shows
        rig.clock.advance(0.02)
        rig.readback(shown)
        rig.clock.advance(0.005)
        rig.system_time(boot_ms)  # the autopilot, there
        rig.advance(0.001)
    assert rig.core.status()["foreign_command"]["output"] == output
    rig.advance(0.05)
    assert output not in rig.servo()  # its command of the update is not confirmed over it
