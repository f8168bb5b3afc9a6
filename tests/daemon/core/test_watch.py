"""The autopilot watch (``core/watch.py``): pinning, the streams asked for, reboots, silences,
link loss."""

from __future__ import annotations

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from companion.daemon.core.watch import is_reboot
from companion.daemon.requests import Outcome, Request
from tests.daemon.core.autopilot_models import (
    SERVO_OUTPUT_RAW,
    SYS_STATUS,
    SYSTEM_TIME,
    ArduPilotOutputsModel,
    Autopilot,
)
from tests.daemon.core.rig import PARK, RATE_HZ, STEP_DEG, Rig, near


def test_the_first_autopilot_is_pinned_and_others_are_ignored():
    rig = Rig()
    rig.heartbeat(src=(42, 1))  # heard first
    rig.tick()
    assert rig.core.status()["autopilot"] == [42, 1]
    rig.heartbeat(src=(1, 1))
    assert rig.core.status()["autopilot"] == [42, 1]  # never changed while running
    request = rig.goto(near(PARK))
    assert {c.target for c in rig.sent} == {(42, 1)}
    for _ in range(6):
        rig.ack(src=(1, 1))  # ACKs from anyone else do not count
    assert not request.answered
    assert rig.core.status()["counters"]["foreign_frames"] == 7


def test_a_configured_autopilot_is_the_only_one_pinned():
    # A fake autopilot (42/1) heard first is never adopted in place of the configured one.
    rig = Rig(target_system=1)
    rig.heartbeat(src=(42, 1))
    rig.heartbeat(src=(1, 1))
    rig.tick()
    assert rig.core.status()["autopilot"] == [1, 1]


def test_a_ground_station_heartbeat_is_not_an_autopilot():
    rig = Rig()
    rig.heartbeat(src=(255, 190), autopilot=mavlink.MAV_AUTOPILOT_INVALID)
    rig.tick()
    assert rig.core.status()["autopilot"] is None


def test_system_time_readback_and_safety_are_asked_for_once_pinned(rig):
    asks = [c for c in rig.sent if c.command == mavlink.MAV_CMD_SET_MESSAGE_INTERVAL]
    assert [a.params[0] for a in asks] == [
        mavlink.MAVLINK_MSG_ID_SYSTEM_TIME,
        mavlink.MAVLINK_MSG_ID_SERVO_OUTPUT_RAW,
        mavlink.MAVLINK_MSG_ID_SYS_STATUS,
    ]
    assert all(a.params[1] > 0 for a in asks)
    assert [r.name for r in rig.reads] == ["BRD_SAFETY_MASK"]


def test_a_reboot_within_the_loss_timeout_is_seen_and_every_output_resent(rig):
    # An autopilot restarted in 0.36 s went unnoticed: status "up" with the old PWMs while its
    # outputs were at 0, and the next target sent only the output that changed.
    rig.system_time(600_000)
    request = rig.goto(near(PARK))
    rig.ack_all(rig.sent)
    assert rig.reply(request).outcome is Outcome.ACCEPTED
    rig.sent.clear()
    rig.advance(0.36)
    rig.system_time(150)  # time_boot_ms went back: it rebooted
    status = rig.core.status()
    assert status["counters"]["autopilot_reboots"] == 1
    assert status["last_pwm_us"] is None
    assert any(c.command == mavlink.MAV_CMD_SET_MESSAGE_INTERVAL for c in rig.sent)
    rig.advance(1.0 / RATE_HZ)
    # ArduPilot boots with its safety switch on (BRD_SAFETY_DEFLT): what is sent before a
    # SYS_STATUS says where it is would be stored, and go out in one step at its release.
    assert rig.servo() == {}
    rig.sys_status(safety_on=False)
    rig.advance(1.0 / RATE_HZ)
    assert rig.servo() == {}  # nor before a readback said what the outputs show since the boot
    rig.readback({})  # no pulses: nothing set them since
    rig.advance(1.0 / RATE_HZ)
    assert sorted(rig.servo()) == [9, 10, 11, 12, 13, 14]  # every output, not only changes


def test_system_time_going_quiet_resends_every_output_at_once_even_with_the_arm_still(rig):
    rig.system_time(600_000)
    rig.ack_all(rig.take(rig.core.request(Request("goto", near(PARK)))))
    acked = rig.core.status()["last_pwm_us"]
    assert not rig.core.status()["moving"]
    rig.clock.advance(0.02)
    rig.sys_status(safety_on=False)  # the switch off with the update acknowledged
    rig.sent.clear()
    rig.safety_stream = None  # silent: it may have rebooted and forgotten every stream
    rig.advance(1.5)  # no SYSTEM_TIME
    assert any(c.command == mavlink.MAV_CMD_SET_MESSAGE_INTERVAL for c in rig.sent)
    assert rig.servo() == {}  # not before a SYS_STATUS said where its safety switch is
    rig.sys_status(safety_on=False)
    rig.readback({})  # nor before a readback (no pulses: it rebooted)
    rig.advance(1.0 / RATE_HZ)
    # A reboot left the outputs at their boot values: the acknowledged PWMs go out again with
    # no new target (before: only with the next target).
    assert rig.servo() == acked
    rig.ack_all(rig.sent)
    assert rig.core.status()["last_pwm_us"] == acked
    moved = list(near(PARK))
    moved[0] += 1.0
    rig.goto(moved)
    assert sorted(rig.servo()) == [9, 10, 11, 12, 13, 14]


def test_the_first_frame_after_a_silence_asks_for_every_stream_at_once(rig):
    # A rebooted autopilot forgot our streams; its first HEARTBEAT back brings them back
    # without waiting for a silence rule (status said "not known live" meanwhile).
    rig.system_time(600_000)
    rig.safety_stream = None
    rig.clock.advance(0.3)  # silent (no tick either)
    rig.sent.clear()
    rig.heartbeat()
    asked = {
        int(c.params[0]) for c in rig.sent if c.command == mavlink.MAV_CMD_SET_MESSAGE_INTERVAL
    }
    assert {mavlink.MAVLINK_MSG_ID_SYSTEM_TIME, mavlink.MAVLINK_MSG_ID_SYS_STATUS} <= asked
    rig.sent.clear()
    rig.heartbeat()  # not again for the next frame
    assert not [c for c in rig.sent if c.command == mavlink.MAV_CMD_SET_MESSAGE_INTERVAL]


def test_an_autopilot_that_only_beats_is_not_asked_for_its_streams_at_every_heartbeat():
    rig = Rig()
    rig.heartbeat()
    rig.tick()
    rig.sent.clear()
    for _ in range(3):  # 1 Hz HEARTBEATs, nothing else (streams not supported)
        rig.clock.advance(1.0)
        rig.heartbeat()
    assert not [c for c in rig.sent if c.command == mavlink.MAV_CMD_SET_MESSAGE_INTERVAL]


def test_link_loss_holds_rejects_waiting_targets_and_resends_every_output_when_back(rig):
    request = rig.goto(tuple(p + 30.0 for p in PARK))
    rig.ack_all(rig.sent)
    assert rig.reply(request).outcome is Outcome.ACCEPTED
    acked = rig.core.status()["last_pwm_us"]
    rig.sent.clear()
    rig.advance(1.0 / RATE_HZ)  # the next step is in flight when the link goes
    in_flight = rig.servo()
    assert len(in_flight) == 6
    rig.sent.clear()
    rig.advance(0.1, link_up=False)
    assert rig.core.status()["holding"]
    late = rig.goto(near(PARK))
    assert rig.reply(late).outcome is Outcome.TEMPORARILY_REJECTED
    rig.advance(5.0, link_up=False)
    assert rig.servo() == {}  # nothing while holding
    rig.advance(0.01)
    assert rig.servo() == {}  # not before a SYS_STATUS said where its safety switch is
    rig.sys_status(safety_on=False)
    rig.readback({})  # nor before a readback (no pulses: it rebooted)
    rig.advance(1.0 / RATE_HZ)
    # Back: every output within half a step of both poses it may hold (the acknowledged one
    # and the step on its way), then on towards the goal.
    resent = rig.servo()
    assert sorted(resent) == sorted(in_flight)
    for output, pwm in resent.items():
        held = [acked[output], in_flight[output]]
        assert min(held) <= pwm <= max(held)
        for before in held:
            assert abs(rig.angle(output, pwm) - rig.angle(output, before)) <= STEP_DEG / 2 + 0.1


def test_a_reboot_soon_after_boot_is_seen_by_time_boot_falling_behind(rig):
    # Up 1 s, rebooted, its SYSTEM_TIME back 1.2 s later reading 900 ms: not below 1000, but
    # 1.3 s behind where it should be.
    rig.system_time(1_000)
    rig.clock.advance(1.2)
    rig.system_time(900)
    assert rig.core.status()["counters"]["autopilot_reboots"] == 1


def test_a_reboot_right_after_boot_is_seen_once_the_silent_stream_comes_back(rig):
    # Seen in a full test run: the simulator rebooted 0.22 s after it started; 1 s of silence
    # later the stream, asked for again, read 0.58 s less than the time since the last one:
    # under REBOOT_LAG_MS, but after a silence the smaller lag is evidence enough.
    rig.system_time(200)
    rig.advance(1.2)  # silent: asked again
    rig.system_time(200 + 1_200 - 580)
    assert rig.core.status()["counters"]["autopilot_reboots"] == 1


def test_a_reboot_right_after_boot_is_seen_when_the_stream_comes_back_before_its_silence(rig):
    # Seen in a full test run: the streams asked for again after a silent SYS_STATUS (0.5 s)
    # brought SYSTEM_TIME back before its own silence (1 s) was noticed, 0.56 s behind: the gap
    # itself is the silence.
    rig.system_time(200)
    rig.clock.advance(0.8)
    rig.system_time(200 + 800 - 560)
    assert rig.core.status()["counters"]["autopilot_reboots"] == 1


def test_a_late_system_time_is_not_a_reboot(rig):
    rig.system_time(60_000)
    rig.clock.advance(0.25)
    rig.system_time(60_000)  # arrived 250 ms late
    rig.clock.advance(0.25)
    rig.system_time(60_500)
    assert rig.core.status()["counters"]["autopilot_reboots"] == 0


def test_the_autopilot_has_heard_us_only_once_it_answered_us_since_the_link_came_up():
    """The autopilot routes a ground station's targets to us only once it has heard
    us; its answer to the SYSTEM_TIME request sent at link-up proves it. A loss resets it."""
    rig = Rig()
    asks = rig.up()
    assert {a.command for a in asks} == {mavlink.MAV_CMD_SET_MESSAGE_INTERVAL}
    assert rig.core.status()["autopilot_heard_us"] is False
    rig.ack(command=mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, src=(2, 1))  # not the pinned one
    assert rig.core.status()["autopilot_heard_us"] is False
    rig.ack(command=mavlink.MAV_CMD_SET_MESSAGE_INTERVAL)
    assert rig.core.status()["autopilot_heard_us"] is True
    rig.tick(link_up=False)
    assert rig.core.status()["autopilot_heard_us"] is False
    rig.tick(link_up=True)
    assert rig.core.status()["autopilot_heard_us"] is False


def test_px4_telemetry_streams_nobody_reads_are_stopped_on_our_link():
    # PX4 streams ATTITUDE (100 Hz) and LOCAL_POSITION_NED (30 Hz) on a companion's link unasked:
    # half a 115 200-baud line. With world-frame targets off the daemon stops both.
    rig = Rig(dialect="px4")
    rig.heartbeat(autopilot=mavlink.MAV_AUTOPILOT_PX4)
    rig.tick()
    asks = {
        int(c.params[0]): c.params[1]
        for c in rig.sent
        if c.command == mavlink.MAV_CMD_SET_MESSAGE_INTERVAL
    }
    assert asks[mavlink.MAVLINK_MSG_ID_ATTITUDE] == -1
    assert asks[mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED] == -1


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


def test_after_a_reboot_every_stream_the_core_reads_is_asked_for_again():
    """Cause 1: ArduPilot (and the simulator) forget every message interval when they reboot:
    SYSTEM_TIME, SERVO_OUTPUT_RAW and SYS_STATUS are asked for again once it is seen."""
    ap = ArduPilotOutputsModel()
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


def test_a_reboot_is_time_boot_going_back_or_falling_behind_the_time_elapsed():
    # Backwards by more than a reordering:
    assert is_reboot(60_000, 0.0, 59_000, 0.25, after_silence=False)
    assert not is_reboot(60_000, 0.0, 59_950, 0.0, after_silence=False)
    # Behind the time elapsed by more than a delayed frame (REBOOT_LAG_MS) ...
    assert not is_reboot(60_000, 0.0, 60_000, 0.5, after_silence=False)
    assert is_reboot(60_000, 0.0, 60_000, 1.0, after_silence=False)
    # ... or after a silence, by more than REBOOT_LAG_AFTER_SILENCE_MS.
    assert is_reboot(60_000, 0.0, 60_000, 0.6, after_silence=True)


def test_a_system_time_that_arrived_on_time_but_is_taken_late_is_not_a_reboot(rig):
    # The control thread stalled for 0.26 s: the SYSTEM_TIME that arrived 0.25 s after the one
    # before is taken 0.51 s after it. Its arrival dates it, not when it was taken.
    rig.goto(near(PARK))
    rig.ack_all(rig.sent)
    acknowledged = rig.core.status()["last_pwm_us"]
    assert acknowledged
    rig.system_time(60_000)
    arrived_s = rig.clock() + 0.25
    rig.clock.advance(0.51)
    rig.system_time(60_250, received_s=arrived_s)
    status = rig.core.status()
    assert status["counters"]["autopilot_reboots"] == 0
    assert status["last_pwm_us"] == acknowledged  # nothing forgotten, nothing to re-send
    rig.clock.advance(0.05)
    rig.system_time(60_560)
    assert rig.core.status()["counters"]["autopilot_reboots"] == 0


def _stream_system_time(rig, boot_ms, seconds, *, forged=None):
    """The autopilot's SYSTEM_TIME every 0.25 s from ``boot_ms``; ``forged``: a time_boot_ms
    forged as its frame between each two of its own."""
    for _ in range(round(seconds / 0.25)):
        rig.clock.advance(0.125)
        if forged is not None:
            rig.system_time(forged)
            forged += 125
        rig.clock.advance(0.125)
        boot_ms += 250
        rig.system_time(boot_ms)
        rig.tick()


def test_a_forged_system_time_between_the_autopilots_own_is_no_reboot(rig):
    # 1 013 false reboots in 6 minutes from forged SYSTEM_TIME: each dropped the outputs'
    # state and rejected the targets.
    rig.system_time(600_000)
    request = rig.goto(near(PARK))
    rig.ack_all(rig.sent)
    assert rig.reply(request).outcome is Outcome.ACCEPTED
    _stream_system_time(rig, 600_000, 3.0, forged=100)
    status = rig.core.status()
    assert status["counters"]["autopilot_reboots"] == 0
    assert status["counters"]["forged_frames"] > 0
    assert status["last_pwm_us"] is not None


def test_a_reboot_with_no_silence_before_it_is_taken_on_the_new_clocks_second_signal(rig):
    rig.system_time(600_000)
    rig.clock.advance(0.25)
    rig.system_time(40)  # went back, the frames never stopped: not evidence enough alone
    assert rig.core.status()["counters"]["autopilot_reboots"] == 0
    _stream_system_time(rig, 40, 0.5)  # the new clock goes on, the old one is gone
    assert rig.core.status()["counters"]["autopilot_reboots"] == 1


def test_nothing_is_sent_while_a_reboot_awaits_its_second_signal(rig):
    # A step was on its way when the autopilot rebooted (frames forged meanwhile shortened its
    # silence): its ACKs never came, and it was confirmed one command at a time while the
    # reboot waited for its second signal, over a ground station's command given since the
    # boot (a 106 deg step).
    rig.system_time(600_000)
    rig.goto(tuple(p + 30.0 for p in PARK))
    rig.tick()
    assert rig.servo()  # the first step, never answered
    rig.clock.advance(0.25)
    rig.system_time(40)  # went back, no silence before it: suspected
    rig.sent.clear()
    for _ in range(3):  # past the update's deadline (0.5 s), the new clock not long enough
        rig.advance(0.1)
    assert not rig.servo()
    _stream_system_time(rig, 40, 0.5)  # the second signal: a reboot, the outputs re-sent anew
    assert rig.core.status()["counters"]["autopilot_reboots"] == 1


def test_a_control_thread_stall_is_no_reboot(rig):
    # A 0.26 s stall of the control thread: frames taken late, dated by their arrival.
    rig.system_time(600_000, received_s=rig.clock())
    arrived_s = rig.clock() + 0.25
    rig.clock.advance(0.51)
    rig.system_time(600_250, received_s=arrived_s)
    assert rig.core.status()["counters"]["autopilot_reboots"] == 0


@pytest.mark.parametrize("dialect", ["px4", "ardupilot"])
@pytest.mark.parametrize("resume", [False, True])
def test_after_a_reboot_the_goal_accepted_before_it_is_dropped_unless_resume_is_set(
    resume, dialect
):
    # After PX4 crashed and restarted, the arm went on towards its old goal on its own.
    rig = Rig(dialect=dialect, sections={"control": {"resume_after_reboot": resume}})
    rig.up()
    rig.readback({})
    rig.system_time(600_000)
    far = tuple(p + 30.0 for p in PARK)
    request = rig.goto(far)
    for c in list(rig.sent):
        if c.command in (mavlink.MAV_CMD_DO_SET_SERVO, mavlink.MAV_CMD_DO_SET_ACTUATOR):
            rig.ack(command=c.command)
    assert rig.reply(request).outcome is Outcome.ACCEPTED
    rig.advance(0.36)
    rig.system_time(150)
    assert rig.core.status()["counters"]["autopilot_reboots"] == 1
    assert (rig.core.status()["goal_deg"] is not None) is resume
