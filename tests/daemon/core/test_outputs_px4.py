"""PX4's outputs' truth (``core/outputs_px4.py``): the readback, outputs found not live, the
markers, probes and the verdict on each step, against a model of PX4's outputs."""

from __future__ import annotations

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from companion.daemon.core import (
    MARKER_OFFSET_US,
)
from companion.daemon.core.outputs_px4 import marker_pwm_candidates
from companion.daemon.requests import Outcome
from tests.daemon.core.rig import (
    ACTUATOR,
    PARK,
    RATE_HZ,
    STEP_DEG,
    Px4OutputsModel,
    Rig,
    assert_seen_live_at_the_next_readback,
    max_physical_step_us,
    near,
    px4_rig,
    rig_park_pwm,
    run,
)


def test_px4_moves_only_once_a_readback_said_where_the_joints_are():
    rig, px4 = px4_rig(disarmed_us=1500)
    px4.set_live(True)  # prearmed: live, showing the disarmed PWM (nothing stored yet)
    request = rig.goto(near(PARK))
    assert not [c for c in rig.sent if c.command == ACTUATOR]  # no readback yet
    px4.readback()
    run(rig, px4, 0.5)  # readbacks steadily showing 1500 us, the clock going on: believed
    assert rig.reply(request).outcome is Outcome.ACCEPTED
    # It started from where the outputs were (1500 us), not from the assumed park pose.
    first = px4.physical_moves[0]
    joint = rig.calibration.for_output(first[0])
    step_us = STEP_DEG / (joint.angle_max_deg - joint.angle_min_deg) * 1000
    assert first[1] == 1500 and abs(first[2] - first[1]) <= step_us + 1


def test_px4_outputs_that_do_not_show_what_they_acknowledged_hold_the_arm():
    rig, px4 = px4_rig(disarmed_us=1500)
    px4.readback()
    request = rig.goto(near(PARK, 20.0))  # far: many steps
    run(rig, px4, 1.0)  # disarmed: every step ACCEPTED, none shown
    assert rig.reply(request).outcome is Outcome.ACCEPTED
    status = rig.core.status()
    assert status["outputs_live"] is False
    why = status["not_live"][str(rig.calibration.outputs[0])]
    assert "shows 1500 us, not the" in why and "acknowledged" in why
    # Held: at most one probing step a second goes out while they stay dead.
    sent_before = len(px4.physical_moves), rig.core.counters["servo_updates"]
    run(rig, px4, 3.0)
    assert rig.core.counters["servo_updates"] - sent_before[1] <= 4
    later = rig.goto(near(PARK, 19.0))
    assert "outputs not live" in rig.reply(later).message
    assert rig.reply(later).outcome is Outcome.ACCEPTED
    # Armed: no output jumps by more than one step; then the arm goes on to the goal.
    px4.set_live(True)
    run(rig, px4, 6.0)
    assert rig.core.status()["outputs_live"] is True
    for output, before, after in px4.physical_moves:
        joint = rig.calibration.for_output(output)
        step_us = STEP_DEG / (joint.angle_max_deg - joint.angle_min_deg) * 1000
        assert abs(after - before) <= step_us + 1, (output, before, after)
    assert rig.core.status()["goal_deg"] == pytest.approx(list(near(PARK, 19.0)))
    assert rig.core.status()["moving"] is False


def test_px4_a_readback_showing_a_step_before_its_ack_is_not_a_dead_output():
    # PX4 applies DO_SET_ACTUATOR on its output cycle and answers on its commander's: a
    # readback in between shows a step not acknowledged yet. Taken for "not what was
    # acknowledged", it held the arm as if disarmed (a target waited 201 ms in bench.latency).
    rig, px4 = px4_rig(disarmed_us=1500)
    px4.set_live(True)
    px4.readback()
    rig.goto(near(PARK))
    run(rig, px4, 0.5)
    assert rig.core.status()["outputs_live"] is True
    request = rig.goto(near(PARK, 20.0))
    unanswered = px4.apply()
    px4.readback()  # shows the step before its ACK
    for _ in unanswered:
        rig.ack(command=ACTUATOR)
    assert rig.reply(request).outcome is Outcome.ACCEPTED
    assert rig.core.status()["outputs_live"] is True
    rig.advance(1.0 / RATE_HZ)
    assert [c for c in rig.sent if c.command == ACTUATOR]  # the next step at once


def test_px4_a_readback_that_disagrees_once_says_not_known_live_until_the_next_agree():
    # Status said live 20-40 ms longer than the outputs were (the readbacks not believed yet).
    rig, px4 = px4_rig(disarmed_us=1500)
    px4.set_live(True)
    px4.readback()
    rig.goto(near(PARK, 20.0))
    run(rig, px4, 0.5)
    rig.clock.advance(0.2)  # settled
    real = dict(px4.shown)
    rig.readback(dict.fromkeys(real, 1500))  # forged, or the first of a disarm
    status = rig.core.status()
    assert status["outputs_live"] is False
    assert "not what it acknowledged" in status["not_live"][str(rig.calibration.outputs[0])]
    rig.clock.advance(0.02)
    rig.readback(real)
    rig.advance(0.05)  # two intervals after the one that disagreed
    rig.readback(real)
    assert rig.core.status()["outputs_live"] is True


def test_px4_after_a_reboot_the_stale_pose_is_not_sent_again():
    rig, px4 = px4_rig(disarmed_us=1500)
    px4.set_live(True)
    px4.readback()
    rig.goto(near(PARK))
    run(rig, px4, 0.5)
    rig.system_time(600_000)
    rig.advance(0.36)
    rig.sent.clear()
    rig.system_time(150)  # rebooted: its outputs are back at the disarmed PWM
    px4.stored = dict.fromkeys(px4.stored)
    px4.set_live(True)
    rig.tick()
    assert not [c for c in rig.sent if c.command == ACTUATOR]


def test_px4_outputs_found_dead_hold_a_marker_and_are_seen_live_at_the_next_readback():
    rig, px4 = px4_rig(disarmed_us=1500)
    px4.set_live(True)
    px4.readback()
    rig.goto(near(PARK, 20.0))
    run(rig, px4, 0.5)
    assert rig.core.status()["outputs_live"] is True
    px4.set_live(False)  # disarm: every output at 1500
    rig.sent.clear()
    # One readback alone is not believed (a forged one would do that), nor two an interval
    # apart (a forger's may fall between two of PX4's): no marker is sent on their word, but
    # status says at once the outputs are not known live.
    px4.readback()
    assert rig.core.status()["outputs_live"] is False
    rig.clock.advance(0.02)
    px4.readback()
    assert not [c for c in rig.sent if c.command == ACTUATOR]
    rig.clock.advance(0.02)
    px4.readback()  # the next: longer than an interval, none showing the stored PWM
    assert rig.core.status()["outputs_live"] is False
    # The autopilot's clock was heard an interval into them (while it reboots, silent, a
    # forger's frames would be all the readbacks there are): the markers go out at once (not
    # at the next tick), 2 us from the disarmed PWM.
    sent = [c for c in rig.sent if c.command == ACTUATOR]
    assert len(sent) == 1
    px4.handle()
    assert set(px4.stored.values()) <= {1500 + MARKER_OFFSET_US, 1500 - MARKER_OFFSET_US}
    # Dead, nothing more is sent (no probing steps): the goal waits.
    updates = rig.core.counters["servo_updates"]
    run(rig, px4, 3.0)
    assert rig.core.counters["servo_updates"] == updates
    assert rig.core.status()["outputs_live"] is False
    # Armed: the next readback shows the markers; live again, and the motion goes on.
    px4.set_live(True)
    px4.readback()
    assert rig.core.status()["outputs_live"] is True
    run(rig, px4, 2.0)
    assert rig.core.counters["servo_updates"] > updates
    assert max_physical_step_us(px4) <= 1.0


def _died_under_a_step() -> tuple[Rig, Px4OutputsModel, list]:
    """PX4 live, the arm moving; a step goes out, PX4 applies it (its ACK not sent yet), the
    outputs die (disarmed PWM 1500 us) and a readback shows them dead. Returns the rig, the
    model and the commands on their way."""
    rig, px4 = px4_rig(disarmed_us=1500)
    px4.set_live(True)
    px4.readback()
    rig.goto(near(PARK, 20.0))  # 7 steps
    run(rig, px4, 0.2)
    rig.advance(1.0 / RATE_HZ)  # the next step goes out ...
    on_its_way = px4.apply()
    assert on_its_way
    px4.set_live(False)
    px4.readback()  # ... the outputs are seen dead before its ACK
    return rig, px4, on_its_way


def test_px4_an_update_on_its_way_when_the_outputs_die_does_not_replace_their_hold():
    # Found dead while a step was on its way: that step's ACK came after, and its pose was
    # taken as the joints' (the hold stored it: at a re-arm the outputs went from the
    # disarmed PWM to it, bench.output_cycles' "arm then arm" fast command steps).
    rig, px4, on_its_way = _died_under_a_step()
    for _ in range(2):  # ...found dead before its ACK (three readbacks)
        rig.clock.advance(0.02)
        px4.readback()
    for _ in on_its_way:
        rig.ack(command=ACTUATOR)
    rig.advance(1.0 / RATE_HZ)
    px4.handle()  # the hold
    px4.set_live(True)  # re-armed before the readback saw the hold
    run(rig, px4, 2.0)
    assert max_physical_step_us(px4) <= 1.0


def test_px4_at_the_start_with_the_arm_still_the_markers_say_whether_it_is_live():
    rig, px4 = px4_rig(disarmed_us=1500)
    status = rig.core.status()
    assert status["outputs_live"] is False and "no SERVO_OUTPUT_RAW yet" in str(status["not_live"])
    px4.readback()  # disarmed, nothing stored: 1500 everywhere
    assert "not known live yet" in str(rig.core.status()["not_live"])
    run(rig, px4, 1.0)  # believed at 1500, markers stored, not shown: not live
    assert px4.stored[rig.calibration.outputs[0]] == 1500 + MARKER_OFFSET_US
    status = rig.core.status()
    assert status["outputs_live"] is False and "shows 1500 us" in str(status["not_live"])
    assert_seen_live_at_the_next_readback(rig, px4)


def test_px4_a_reboot_while_not_live_forgets_the_markers_and_stores_them_again():
    # A rebooted PX4 holds nothing: waiting for the markers stored before it to show would
    # wait for ever (status "not live" through every later arm, bench.output_cycles).
    rig, px4 = px4_rig(disarmed_us=1500)
    px4.readback()
    run(rig, px4, 0.5)
    assert rig.core.status()["outputs_live"] is False  # held at the markers
    rig.system_time(600_000)
    rig.advance(0.36)  # a reboot's silence
    rig.system_time(150)  # rebooted: nothing stored, disarmed
    px4.stored = dict.fromkeys(px4.stored)
    px4.set_live(False)
    assert "not known live" in str(rig.core.status()["not_live"])
    run(rig, px4, 0.5)
    assert set(px4.stored.values()) <= {1500 + MARKER_OFFSET_US, 1500 - MARKER_OFFSET_US}
    assert_seen_live_at_the_next_readback(rig, px4)


def test_px4_markers_go_out_even_where_the_disarmed_pose_lies_in_a_keepout_volume():
    # The outputs are where the readback shows them whatever the volumes; a marker moves them
    # 2 us. Checked as a motion, it was refused at every tick (and the outputs never known).
    from companion.kinematics.vehicle import Mount

    disarmed_us = 1100  # far from park: the config refuses a park in a volume

    calibration = Rig().calibration
    q_dis = [
        calibration.for_output(o).pwm_us_to_angle_deg(disarmed_us) for o in calibration.outputs
    ]
    centre = Mount().to_body(Rig().config.arm.fk(q_dis).position_cm)
    sphere = {"name": "ball", "type": "sphere", "center_cm": list(centre), "radius_cm": 4.0}
    rig = Rig(dialect="px4", sections={"keepout": [sphere]})
    rig.heartbeat(autopilot=mavlink.MAV_AUTOPILOT_PX4)
    rig.tick()
    px4 = Px4OutputsModel(rig, disarmed_us)
    px4.readback()
    run(rig, px4, 1.0)
    assert rig.core.status()["counters"]["keepout_refusals"] == 0
    assert px4.stored[rig.calibration.outputs[0]] == disarmed_us + MARKER_OFFSET_US
    assert_seen_live_at_the_next_readback(rig, px4)


def test_px4_a_silent_readback_says_nothing_of_the_outputs_and_the_streams_are_asked_again():
    rig, px4 = px4_rig(disarmed_us=1500)
    px4.set_live(True)
    run(rig, px4, 0.5)
    assert rig.core.status()["outputs_live"] is True
    rig.sent.clear()
    for _ in range(5):
        rig.advance(0.02)  # no readback: a reboot, a link gone quiet
    assert "no SERVO_OUTPUT_RAW for" in str(rig.core.status()["not_live"])
    for _ in range(25):
        rig.advance(0.02)
    assert any(c.command == mavlink.MAV_CMD_SET_MESSAGE_INTERVAL for c in rig.sent)


@settings(max_examples=40)
@given(
    st.lists(
        st.tuples(
            st.sampled_from(["live", "dead", "goto", "run"]),
            st.floats(-25, 25),
        ),
        min_size=1,
        max_size=12,
    )
)
def test_property_px4_outputs_never_jump_faster_than_the_speed_limit(events):
    """Over any arm/disarm/prearm sequence and targets, no output moves by more than
    one step's PWM at once, neither on our commands nor when the outputs come alive (the
    disarmed PWM within the calibration, as PWM_MAIN_DIS = park makes it). Disarming drives
    them to the disarmed PWM at once: PX4's own jump, not counted."""
    rig, px4 = px4_rig(disarmed_us=rig_park_pwm())
    px4.readback()
    for kind, value in events:
        if kind == "live":
            px4.set_live(True)
        elif kind == "dead":
            px4.set_live(False)
        elif kind == "goto":
            rig.goto(near(PARK, value))
        # Each state lasts a second: a disarm and re-arm within the readback's detection
        # window (~0.3 s at 10 Hz) while moving would apply that window's steps at once.
        run(rig, px4, 1.0)
    for output, before, after in px4.physical_moves:
        joint = rig.calibration.for_output(output)
        step_us = STEP_DEG / (joint.angle_max_deg - joint.angle_min_deg) * 1000
        assert abs(after - before) <= step_us + 1, (output, before, after)


# -- the marker, alone ---------------------------------------------------------------------------


def test_the_marker_is_tried_towards_the_middle_of_the_range_first():
    assert marker_pwm_candidates(1000, 1500.0, 1000) == [1000 + MARKER_OFFSET_US, 998, 1000]
    assert marker_pwm_candidates(2000, 1500.0, 2000) == [2000 - MARKER_OFFSET_US, 2002, 2000]


def test_an_output_showing_a_pwm_outside_its_range_waits_for_arming_and_holds_the_last_pwm():
    # PX4 SITL's disarmed PWM, 900 us, lies below every servo's range and says nothing of where
    # a joint is: nothing is sent before arming (a marker at the range's end sent every joint
    # to its minimum angle in one step when the outputs came alive; a restarted daemon's first
    # step, stored while disarmed, came out in one move at arming). A target is answered at
    # once (outputs not live); once armed the motion starts, and a joint found dead again
    # holds the last PWM known, not the range's end.
    rig, px4 = px4_rig(disarmed_us=900)
    px4.readback()
    run(rig, px4, 0.5)
    request = rig.goto(near(PARK))
    run(rig, px4, 0.5)
    assert rig.core.counters["servo_updates"] == 0
    assert set(px4.stored.values()) == {None}  # nothing stored
    reply = rig.reply(request)
    assert reply.outcome is Outcome.ACCEPTED and "outside its range" in reply.message
    assert rig.core.status()["outputs_live"] is False
    armed = mavlink.MAV_MODE_FLAG_SAFETY_ARMED
    rig.frame(
        lambda c: c.heartbeat_encode(
            mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_PX4, armed, 0, 3
        )
    )
    px4.set_live(True)
    run(rig, px4, 1.0)
    assert rig.core.counters["servo_updates"] > 0
    assert rig.core.status()["outputs_live"] is True
    output = rig.calibration.outputs[0]
    px4.set_live(False)  # disarmed again: 900 everywhere; the joint holds the last PWM
    run(rig, px4, 0.5)
    assert px4.stored[output] != rig.calibration.for_output(output).pwm_min_us
    moves = [(o, b, a) for o, b, a in px4.physical_moves if b != 900]
    px4.physical_moves[:] = moves
    assert max_physical_step_us(px4) <= 1.0


def test_px4_a_forged_readback_between_the_autopilots_own_never_sends_a_marker():
    # A forged SERVO_OUTPUT_RAW made the daemon itself command a 120 deg "marker" step on PX4:
    # the live outputs went where the forged frame said they were.
    rig, px4 = px4_rig(disarmed_us=1500)
    px4.set_live(True)
    px4.readback()
    rig.goto(near(PARK, 20.0))
    run(rig, px4, 1.0)
    assert rig.core.status()["outputs_live"] is True
    forged = {o: 1000 for o in px4.shown}
    rig.sent.clear()
    for _ in range(25):  # at the readback's own rate, between its frames
        rig.clock.advance(0.01)
        rig.readback(forged)
        rig.clock.advance(0.01)
        px4.readback()
        px4.handle()
    # Not known live while the readbacks disagree (status says so), but nothing was sent on
    # their word, and once they agree again the outputs are live.
    assert not [c for c in rig.sent if c.command == ACTUATOR]
    assert "not what it acknowledged" in rig.core.status()["not_live"][str(min(px4.shown))]
    rig.clock.advance(0.05)
    px4.readback()
    assert rig.core.status()["outputs_live"] is True
    assert max_physical_step_us(px4) <= 1.0


def test_px4_readbacks_of_a_dead_output_among_forged_ones_store_nothing_until_one_pwm_alone_shows():
    # The outputs died (showing the disarmed PWM) while frames forged with other PWMs came
    # between: the dead output was believed on the forged frame's word, and its marker stored
    # there, 160 deg away (PX4 applied it at the next prearm). Frames showing two PWMs by turns
    # believe neither: nothing is stored until one alone is shown, then the marker goes where
    # the autopilot's own frames show.
    rig, px4 = px4_rig(disarmed_us=1500)
    px4.set_live(True)
    px4.readback()
    rig.goto(near(PARK, 20.0))
    run(rig, px4, 1.0)
    px4.set_live(False)  # every output at 1500
    rig.sent.clear()
    stored = dict(px4.stored)
    forged = {o: 1100 for o in px4.shown}
    for _ in range(8):
        rig.clock.advance(0.01)
        px4.readback()
        rig.clock.advance(0.01)
        rig.readback(forged)
        px4.handle()
    assert rig.core.status()["outputs_live"] is False
    assert px4.stored == stored  # nothing stored on either PWM's word
    run(rig, px4, 0.5)  # the forger stopped
    assert rig.core.status()["outputs_live"] is False
    assert set(px4.stored.values()) <= {1500 + MARKER_OFFSET_US, 1500 - MARKER_OFFSET_US}


def test_px4_a_forged_readback_at_the_start_never_places_the_joints_nor_their_markers():
    # PX4 SITL's disarmed 900 us says nothing of where a joint is; one forged frame showing a
    # PWM in range placed the joints there at once and sent their markers: stored while
    # disarmed, they came out at the next prearm 130 deg from where the joints were. Frames
    # forged between the autopilot's own are never steady: nothing is sent.
    rig, px4 = px4_rig(disarmed_us=900)
    px4.readback()
    run(rig, px4, 0.5)
    forged = {o: 1989 for o in px4.shown}
    for _ in range(5):
        rig.clock.advance(0.01)
        rig.readback(forged)
        rig.tick()
        rig.clock.advance(0.01)
        px4.readback()
        px4.handle()
    run(rig, px4, 0.5)
    assert set(px4.stored.values()) == {None}  # nothing stored
    assert rig.core.counters["servo_updates"] == 0
    request = rig.goto(near(PARK))
    run(rig, px4, 0.5)
    assert "outside its range" in rig.reply(request).message
    assert set(px4.stored.values()) == {None}


def test_px4_an_output_holding_its_marker_that_shows_another_pwm_is_taken_where_it_shows():
    # Dead outputs hold their markers; a ground station's DO_SET_ACTUATOR stores 2000 us on one
    # of them meanwhile, and the prearm brings it out there. The readback showed 2000 us for
    # seconds, but the output was taken to still hold its marker: the next hold sent it there,
    # 160-180 deg in one command.
    rig, px4 = px4_rig(disarmed_us=1500)
    px4.set_live(True)
    px4.readback()
    rig.goto(near(PARK, 20.0))
    run(rig, px4, 1.0)
    px4.set_live(False)
    run(rig, px4, 0.5)  # found dead: the markers stored
    assert set(px4.stored.values()) <= {1500 + MARKER_OFFSET_US, 1500 - MARKER_OFFSET_US}
    first, second = rig.calibration.outputs[:2]
    px4.foreign_store(first, 2000)  # another sender's, stored while dead
    px4.set_live(True)  # prearm: the first output at 2000, the others at their markers
    del px4.physical_moves[:]
    run(rig, px4, 1.0)
    status = rig.core.status()
    assert str(first) not in status.get("not_live", {})
    px4.foreign_store(second, 1200)  # another sender's again, live: a hold goes out for it
    for k in range(100):  # the readback at its own rate (50 Hz), ticks at 20 Hz
        rig.clock.advance(0.01)
        if k % 2 == 0:
            px4.readback()
        if k % 5 == 0:
            rig.tick()
        px4.handle()
    assert max_physical_step_us(px4) <= 1.0
    # It went on from 2000 us at the speed limit, never back to its marker.
    assert next(m for m in px4.physical_moves if m[0] == first)[1] == 2000


def test_px4_the_clock_that_readbacks_waited_for_decides_at_once():
    # A start's readbacks, steady over the span, waited for the autopilot's clock; its answer
    # decided only at the next readback, an interval later (status said "not known live" past
    # its bound after every restart, bench.state_cycles).
    rig, px4 = px4_rig(disarmed_us=1500)
    for _ in range(2):
        rig.readback(px4.shown)
        rig.clock.advance(0.03)
    rig.readback(px4.shown)  # the span met: the clock is asked for
    assert "steadily" in str(rig.core.status()["not_live"])
    rig.clock.advance(0.002)
    rig.clock_goes_on()  # its answer
    assert "steadily" not in str(rig.core.status()["not_live"])
    rig.tick()
    assert [c for c in rig.sent if c.command == ACTUATOR]  # the markers go out


def _heartbeat(rig: Rig, *, armed: bool) -> None:
    flags = mavlink.MAV_MODE_FLAG_SAFETY_ARMED if armed else 0
    rig.frame(
        lambda c: c.heartbeat_encode(
            mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_PX4, flags, 0, 3
        )
    )


def _moving_at_900() -> tuple[Rig, Px4OutputsModel]:
    """PX4 with SITL's disarmed 900 us (outside every servo's range), armed, the arm moving
    towards a far target."""
    rig, px4 = px4_rig(disarmed_us=900)
    px4.readback()
    run(rig, px4, 0.5)
    _heartbeat(rig, armed=True)
    px4.set_live(True)
    run(rig, px4, 0.5)
    rig.goto(near(PARK, 20.0))  # far: many steps
    run(rig, px4, 0.3)
    return rig, px4


def test_px4_a_step_stored_as_the_outputs_died_outside_their_range_is_held_half_way():
    # With the disarmed PWM outside the servo's range (SITL's 900 us), a dead output says
    # nothing of where its joint is: at the last PWM a readback showed live, or at a step
    # acknowledged after it that PX4 applied just before the outputs died. The joint is held
    # at the middle of those. Once armed again (here after a reboot that forgot what was
    # stored, so the outputs show 900 us until told), the first update sends that middle
    # alone, half their spread from wherever the joint is, and the motion's steps go on from
    # there once a readback showed it (a step from the middle at once would go up to half the
    # spread past the limit).
    rig, px4 = _moving_at_900()
    px4.readback()
    shown_live = dict(px4.shown)
    rig.advance(0.05)  # the next step goes out ...
    px4.set_live(False)  # ... the outputs die before PX4 applies it ...
    px4.handle()  # ... and it is stored and acknowledged
    # What the outputs may hold: that, and the steps acknowledged until the readbacks are
    # believed (the hold stored then lies between them).
    band = {o: {pwm, px4.stored[o]} for o, pwm in shown_live.items()}
    for _ in range(10):
        run(rig, px4, 0.05)
        for o, pwm in px4.stored.items():
            band[o].add(pwm)
    assert rig.core.status()["outputs_live"] is False
    for i, output in enumerate(rig.calibration.outputs):
        joint = rig.calibration.for_output(output)
        middle_deg = (
            joint.pwm_us_to_angle_deg(min(band[output]))
            + joint.pwm_us_to_angle_deg(max(band[output]))
        ) / 2
        assert rig.core.state.position[i] == pytest.approx(middle_deg, abs=1e-6)
    rig.system_time(600_000)
    rig.advance(0.36)  # a reboot's silence
    rig.system_time(150)  # rebooted: nothing stored, disarmed
    px4.stored = dict.fromkeys(px4.stored)
    px4.set_live(False)
    _heartbeat(rig, armed=False)
    run(rig, px4, 0.5)
    px4.physical_moves.clear()
    _heartbeat(rig, armed=True)
    px4.set_live(True)
    rig.goto(near(PARK, -20.0))  # back: the first update is the pose held, then the steps
    run(rig, px4, 1.0)
    firsts: dict[int, int] = {}
    for output, before, after in px4.physical_moves:
        if before == 900:
            firsts.setdefault(output, after)
    assert set(firsts) == set(rig.calibration.outputs)
    for output, first in firsts.items():
        low, high = min(band[output]), max(band[output])
        assert high > low
        for physical in (low, high):
            assert abs(first - physical) <= (high - low) / 2 + 1
    px4.physical_moves[:] = [m for m in px4.physical_moves if m[1] != 900]
    assert len(px4.physical_moves) > 6  # the motion went on
    assert max_physical_step_us(px4) <= 1.0


def test_px4_readbacks_forged_while_it_reboots_never_place_a_dead_output():
    # The outputs died (a kill), then PX4 rebooted: while it is silent, frames forged at twice
    # its readback rate show other PWMs, with none of its own between them. Believed, they
    # would take the joints where they say and store a marker there; the pose file would keep
    # that, and the next daemon's first step after arming would jump from where the joint is
    # (57 deg in bench.state_cycles). A readback disagreeing with a dead output's hold is
    # believed only with the autopilot's clock heard going on into their run, as a live one's.
    rig, px4 = _moving_at_900()
    px4.set_live(False)  # a kill: 900 everywhere
    run(rig, px4, 0.5)
    assert rig.core.status()["outputs_live"] is False
    held = tuple(rig.core.state.position)
    rig.sent.clear()
    forged = {o: 1700 for o in px4.shown}  # PX4 reboots: silent; only forged frames come
    for _ in range(8):
        rig.clock.advance(0.01)
        rig.readback(forged)
        rig.tick()
    assert tuple(rig.core.state.position) == held
    assert not [c for c in rig.sent if c.command == ACTUATOR]


def test_px4_an_ack_arriving_after_the_outputs_died_does_not_restart_the_readbacks_run():
    # A step's ACK that comes after the first readback showing the disarmed PWM: a readback
    # may lag behind an ACK, but never shows a PWM the output never acknowledged, so the run
    # of readbacks showing it goes on. Restarted there, the marker would go out a readback
    # interval later, and outputs alive again within that (prearm off and on 70 ms apart)
    # would come back to it in one step.
    rig, px4, on_its_way = _died_under_a_step()
    rig.clock.advance(0.005)
    for _ in on_its_way:
        rig.ack(command=ACTUATOR)  # ... which comes after
    rig.sent.clear()
    for advance_s in (0.015, 0.02):
        rig.clock.advance(advance_s)
        px4.readback()
    # Three readbacks over 40 ms since the first, the clock heard in between: believed.
    assert [c for c in rig.sent if c.command == ACTUATOR]
    assert rig.core.status()["outputs_live"] is False
