import math

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from companion.daemon.telemetry import OFFSET_WINDOW_S, VehicleTelemetry

CODEC = mavlink.MAVLink(None, 1, 1)
DECODER = mavlink.MAVLink(None)


def decoded(msg):
    return DECODER.parse_buffer(msg.pack(CODEC))[0]


def attitude(boot_ms, roll=0.0, yaw=0.0, yawspeed=0.0):
    return decoded(CODEC.attitude_encode(boot_ms, roll, 0.0, yaw, 0.0, 0.0, yawspeed))


def position(boot_ms, x_m=0.0, vx_m_s=0.0):
    return decoded(CODEC.local_position_ned_encode(boot_ms, x_m, 0.0, -5.0, vx_m_s, 0.0, 0.0))


def test_no_state_until_both_streams_are_heard():
    telemetry = VehicleTelemetry()
    assert telemetry.on_frame(attitude(1000), 10.0)
    assert telemetry.state() is None
    assert telemetry.on_frame(position(1000, x_m=2.0, vx_m_s=0.5), 10.001)
    state = telemetry.state()
    assert state.position_cm == pytest.approx((200.0, 0.0, -500.0))
    assert state.velocity_cm_s == pytest.approx((50.0, 0.0, 0.0))


def test_the_state_is_dated_by_the_frame_that_waited_least():
    # The autopilot's clock is 9 s behind ours; frames wait 5, 1 and 3 ms on the way. The
    # 1 ms one gives the offset (9.001 s), so the last frame is dated 2 ms before it came.
    telemetry = VehicleTelemetry()
    telemetry.on_frame(position(1000), 10.005)
    telemetry.on_frame(attitude(1020), 10.021)
    telemetry.on_frame(attitude(1040), 10.043)
    state = telemetry.state()
    assert state.attitude_t_s == pytest.approx(10.041)  # 1.040 + 9.001, not 10.043
    assert state.position_t_s == pytest.approx(10.005)  # dated when it came, with the offset then


def test_the_offset_follows_the_clocks_after_its_window():
    telemetry = VehicleTelemetry()
    telemetry.on_frame(attitude(1000), 9.001)  # offset 8.001
    later = 1000 + int((OFFSET_WINDOW_S + 1) * 1000)
    telemetry.on_frame(attitude(later), later / 1000 + 8.004)
    telemetry.on_frame(position(later), later / 1000 + 8.004)
    assert telemetry.state().attitude_t_s == pytest.approx(later / 1000 + 8.004)


def test_a_reboot_starts_over():
    telemetry = VehicleTelemetry()
    telemetry.on_frame(attitude(100_000), 200.0)
    telemetry.on_frame(position(100_000), 200.0)
    telemetry.on_frame(attitude(50), 201.0)
    assert telemetry.state() is None  # the position from before the reboot is gone


def test_a_frame_with_a_nan_is_dropped_and_counted():
    telemetry = VehicleTelemetry()
    telemetry.on_frame(position(1000), 10.0)
    assert not telemetry.on_frame(attitude(1000, roll=math.nan), 10.0)
    assert telemetry.dropped == 1 and telemetry.state() is None
    assert not telemetry.on_frame(decoded(CODEC.heartbeat_encode(2, 3, 0, 0, 3)), 10.0)
