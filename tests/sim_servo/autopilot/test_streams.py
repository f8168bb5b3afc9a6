"""The streams: HEARTBEAT and its pause, SET_MESSAGE_INTERVAL / GET_MESSAGE_INTERVAL /
REQUEST_MESSAGE, the SERVO_OUTPUT_RAW floor, the interval cap, SYSTEM_TIME, ATTITUDE and
LOCAL_POSITION_NED."""

from __future__ import annotations

import numpy as np
import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from sim_servo.config import SimConfig
from tests.sim_servo.autopilot.conftest import (
    SERVO_OUTPUT_RAW,
    START_S,
    SYSTEM_TIME,
    WALL_S,
    Harness,
    acks,
    faulty,
)


def test_heartbeat_identity_and_rate():
    h = Harness()
    msgs = h.run_for(3.5)
    beats = h.of_type("HEARTBEAT", msgs)
    assert len(beats) == 4  # t = 0, 1, 2, 3
    beat = beats[0]
    assert (beat.get_srcSystem(), beat.get_srcComponent()) == (1, 1)
    assert beat.type == mavlink.MAV_TYPE_QUADROTOR
    assert beat.autopilot == mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA
    assert beat.system_status == mavlink.MAV_STATE_STANDBY
    times = [t for t, m in h.received if m.get_type() == "HEARTBEAT"]
    assert [round(b - a, 6) for a, b in zip(times, times[1:], strict=False)] == [1.0, 1.0, 1.0]


@pytest.mark.parametrize("rate_hz", [4, 20, 50])
def test_servo_output_raw_runs_at_the_requested_rate(rate_hz):
    h = Harness()
    assert h.of_type("SERVO_OUTPUT_RAW", h.run_for(1.0)) == []  # off until asked
    h.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, SERVO_OUTPUT_RAW, 1e6 / rate_hz)
    msgs = h.run_for(2.0 - 1e-6)
    assert acks(msgs)[0].result == mavlink.MAV_RESULT_ACCEPTED
    raws = h.of_type("SERVO_OUTPUT_RAW", msgs)
    assert len(raws) == 2 * rate_hz
    stamps = [m.time_usec for m in raws]
    assert all(b - a == 1_000_000 // rate_hz for a, b in zip(stamps, stamps[1:], strict=False))


def test_message_interval_special_values():
    # A 1 kHz loop, so the 80 %-of-loop-rate cap (next test) leaves 1 ms alone.
    h = Harness(SimConfig(loop_rate_hz=1000))
    h.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, SERVO_OUTPUT_RAW, 500)  # < 1 ms → 1 ms
    h.run_for(0.01)
    assert h.ap.snapshot(h.now)["streams"]["SERVO_OUTPUT_RAW"] == 1
    h.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, SERVO_OUTPUT_RAW, 1e9)  # > 60 s → 60 s
    h.run_for(0.01)
    assert h.ap.snapshot(h.now)["streams"]["SERVO_OUTPUT_RAW"] == 60_000
    h.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, SERVO_OUTPUT_RAW, 33_333)  # whole ms
    h.run_for(0.01)
    assert h.ap.snapshot(h.now)["streams"]["SERVO_OUTPUT_RAW"] == 33
    h.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, SERVO_OUTPUT_RAW, -1)  # stop
    h.run_for(0.01)
    assert h.of_type("SERVO_OUTPUT_RAW", h.run_for(1.0)) == []
    h.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, mavlink.MAVLINK_MSG_ID_VFR_HUD, 100_000)
    assert acks(h.run_for(0.01))[0].result == mavlink.MAV_RESULT_FAILED  # not simulated


def test_default_servo_output_rate_from_config():
    h = Harness(SimConfig(servo_output_rate_hz=10))
    assert len(h.of_type("SERVO_OUTPUT_RAW", h.run_for(1.0 - 1e-6))) == 10
    h.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, SERVO_OUTPUT_RAW, 0)  # back to default
    h.run_for(0.001)
    assert h.ap.snapshot(h.now)["streams"]["SERVO_OUTPUT_RAW"] == 100


def test_get_message_interval_and_request_message():
    h = Harness()
    h.command(mavlink.MAV_CMD_GET_MESSAGE_INTERVAL, SERVO_OUTPUT_RAW)
    msgs = h.run_for(0.01)
    assert acks(msgs)[0].result == mavlink.MAV_RESULT_ACCEPTED
    interval = h.of_type("MESSAGE_INTERVAL", msgs)[0]
    assert (interval.message_id, interval.interval_us) == (SERVO_OUTPUT_RAW, -1)
    h.command(mavlink.MAV_CMD_REQUEST_MESSAGE, SERVO_OUTPUT_RAW)
    msgs = h.run_for(0.01)
    assert acks(msgs)[0].result == mavlink.MAV_RESULT_ACCEPTED
    assert len(h.of_type("SERVO_OUTPUT_RAW", msgs)) == 1


def test_heartbeat_pause_after_and_for():
    h = faulty(heartbeat_pause_after_s=2.0, heartbeat_pause_for_s=3.0)
    h.run_for(8.5)
    times = [round(t - START_S, 6) for t, m in h.received if m.get_type() == "HEARTBEAT"]
    assert times == [0.0, 1.0, 5.0, 6.0, 7.0, 8.0]
    kinds = [e["fault"] for e in h.events if e["event"] == "fault"]
    assert kinds == ["heartbeat_paused", "heartbeat_resumed"]


def test_heartbeat_paused_and_resumed_on_demand_overrides_the_schedule():
    h = faulty(heartbeat_pause_after_s=100.0)
    h.run_for(2.5)
    h.ap.pause_heartbeat(True, h.now)
    h.run_for(3.0)
    h.ap.pause_heartbeat(False, h.now)
    h.run_for(2.01)
    times = [round(t - START_S, 6) for t, m in h.received if m.get_type() == "HEARTBEAT"]
    # Paused at 2.5 s, resumed at 5.5 s: a heartbeat at once, then every second from there.
    assert times == [0.0, 1.0, 2.0, 5.5, 6.5, 7.5]
    faults = [(e["fault"], round(e["t_s"], 6)) for e in h.events if e["event"] == "fault"]
    assert faults == [("heartbeat_paused", 2.5), ("heartbeat_resumed", 5.5)]


def test_servo_output_raw_never_beats_50_hz_on_ardupilot_and_reports_what_is_stored():
    h = Harness()
    h.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, SERVO_OUTPUT_RAW, 2500)  # 400 Hz
    assert acks(h.run_for(0.001))[0].result == mavlink.MAV_RESULT_ACCEPTED
    raws = h.of_type("SERVO_OUTPUT_RAW", h.run_for(1.0))
    assert len(raws) == 50
    stamps = [m.time_usec for m in raws]
    assert {b - a for a, b in zip(stamps, stamps[1:], strict=False)} == {20_000}
    h.command(mavlink.MAV_CMD_GET_MESSAGE_INTERVAL, SERVO_OUTPUT_RAW)
    interval = h.of_type("MESSAGE_INTERVAL", h.run_for(0.01))[0]
    # The stored interval: 2.5 ms → 2 ms → capped to 3 ms (80 % of the 400 Hz loop).
    assert interval.interval_us == 3000
    assert h.ap.snapshot(h.now)["streams"]["SERVO_OUTPUT_RAW"] == 3


def test_px4_has_no_servo_output_floor_and_the_floor_is_configurable():
    h = Harness(SimConfig(flavour="px4"))
    h.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, SERVO_OUTPUT_RAW, 5000)  # 200 Hz
    assert len(h.of_type("SERVO_OUTPUT_RAW", h.run_for(1.0 - 1e-6))) == 200
    h = Harness(SimConfig(servo_output_min_interval_ms=50))
    h.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, SERVO_OUTPUT_RAW, 5000)
    assert len(h.of_type("SERVO_OUTPUT_RAW", h.run_for(1.0 - 1e-6))) == 20


@pytest.mark.parametrize(("loop_rate_hz", "stored_ms"), [(400, 3), (100, 12), (1000, 1)])
def test_message_intervals_are_capped_at_80_percent_of_the_loop_rate(loop_rate_hz, stored_ms):
    h = Harness(SimConfig(loop_rate_hz=loop_rate_hz))
    h.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, mavlink.MAVLINK_MSG_ID_HEARTBEAT, 1000)
    h.run_for(0.05)
    assert h.ap.snapshot(h.now)["streams"]["HEARTBEAT"] == stored_ms


def test_system_time_is_off_on_ardupilot_until_asked_and_counts_from_boot():
    h = Harness()
    assert h.of_type("SYSTEM_TIME", h.run_for(2.0)) == []  # SR0_EXTRA3 is 0 on Copter
    h.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, SYSTEM_TIME, 200_000)  # 5 Hz
    msgs = h.run_for(1.0 - 1e-6)
    assert acks(msgs)[0].result == mavlink.MAV_RESULT_ACCEPTED
    times = h.of_type("SYSTEM_TIME", msgs)
    assert [m.time_boot_ms for m in times] == [2000, 2200, 2400, 2600, 2800]
    assert times[0].time_unix_usec == round((WALL_S + 2.0) * 1e6)


def test_px4_streams_system_time_at_1_hz_by_default():
    h = Harness(SimConfig(flavour="px4"))
    times = h.of_type("SYSTEM_TIME", h.run_for(2.5))
    assert [m.time_boot_ms for m in times] == [0, 1000, 2000]


ATTITUDE = mavlink.MAVLINK_MSG_ID_ATTITUDE
LOCAL_POSITION_NED = mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED


def test_ardupilot_streams_attitude_and_local_position_only_when_asked_at_the_rate_asked():
    h = Harness()
    msgs = h.run_for(1.0)
    assert h.of_type("ATTITUDE", msgs) == h.of_type("LOCAL_POSITION_NED", msgs) == []  # SRn_ 0
    h.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, ATTITUDE, 20_000)  # 50 Hz
    h.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, LOCAL_POSITION_NED, 100_000)  # 10 Hz
    msgs = h.run_for(1.0 - 1e-6)  # handled on the main-loop pass at 1.0 s
    assert [a.result for a in acks(msgs)] == [mavlink.MAV_RESULT_ACCEPTED] * 2
    attitude, position = h.of_type("ATTITUDE", msgs), h.of_type("LOCAL_POSITION_NED", msgs)
    assert (len(attitude), len(position)) == (50, 10)
    stamps = [m.time_boot_ms for m in attitude]
    assert {b - a for a, b in zip(stamps, stamps[1:], strict=False)} == {20}
    assert [m.time_boot_ms for m in position][:3] == [1000, 1100, 1200]


@pytest.mark.parametrize("flavour", ["ardupilot", "px4"])
def test_attitude_and_local_position_carry_the_vehicle_state_at_their_stamp(flavour):
    h = Harness(SimConfig(flavour=flavour, attitude_rate_hz=40, local_position_rate_hz=40))
    msgs = h.run_for(2.0 - 1e-6)
    hover = h.ap.vehicle
    attitude = h.of_type("ATTITUDE", msgs)
    assert len(attitude) == 80  # t = 0, 25 ms, … 1.975 s
    for msg in attitude:
        state = hover.state(msg.time_boot_ms / 1000.0)  # booted at the start: same clock
        expected = (*state.attitude_wrapped(), *state.body_rates())
        got = (msg.roll, msg.pitch, msg.yaw, msg.rollspeed, msg.pitchspeed, msg.yawspeed)
        np.testing.assert_allclose(got, expected, rtol=1e-6, atol=1e-7)  # float32 on the wire
    for msg in h.of_type("LOCAL_POSITION_NED", msgs):
        state = hover.state(msg.time_boot_ms / 1000.0)
        expected = (*state.position_m, *state.velocity_m_s)
        got = (msg.x, msg.y, msg.z, msg.vx, msg.vy, msg.vz)
        np.testing.assert_allclose(got, expected, rtol=1e-6, atol=1e-7)
    assert msgs and abs(attitude[-1].roll) > 1e-4  # it does move (hover is on by default)


def test_px4_streams_attitude_at_100_hz_and_local_position_at_30_hz_by_default():
    h = Harness(SimConfig(flavour="px4"))
    msgs = h.run_for(1.0 - 1e-6)
    assert len(h.of_type("ATTITUDE", msgs)) == 100
    # 30 Hz in whole ms: every 33 ms, so 0 … 990 ms.
    assert len(h.of_type("LOCAL_POSITION_NED", msgs)) == 31
    h.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, ATTITUDE, -1)
    h.run_for(0.01)
    assert h.of_type("ATTITUDE", h.run_for(0.5)) == []
    assert h.ap.snapshot(h.now)["streams"]["ATTITUDE"] == 0
