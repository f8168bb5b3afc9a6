"""What differs between ArduPilot and PX4, through the autopilot and on the flavour objects
themselves."""

from __future__ import annotations

import math
import struct

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from tests.sim_servo.autopilot.conftest import (
    READY_PX4,
    SET_ACTUATOR,
    Harness,
    acks,
    mapped,
    param_values,
)


def test_px4_heartbeat_and_do_set_actuator():
    h = Harness(READY_PX4)
    beat = h.of_type("HEARTBEAT", h.run_for(0.0))[0]
    assert beat.autopilot == mavlink.MAV_AUTOPILOT_PX4
    h.command(
        mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, mavlink.MAVLINK_MSG_ID_ACTUATOR_OUTPUT_STATUS, 100_000
    )
    h.command(mavlink.MAV_CMD_DO_SET_ACTUATOR, -1.0, 0.0, 1.0, 0.5, 2.0, math.nan, 0)
    msgs = h.run_for(0.2)
    assert [a.result for a in acks(msgs)] == [mavlink.MAV_RESULT_ACCEPTED] * 2
    status = h.of_type("ACTUATOR_OUTPUT_STATUS", msgs)[-1]
    assert status.active == 16
    # NaN: slot 6 never set, so still the disarmed PWM (not "off").
    assert status.actuator[8:14] == [1000.0, 1500.0, 2000.0, 1750.0, 2000.0, 1000.0]
    assert status.actuator[0] == 1000.0  # motor 1, armed: its minimum


def test_px4_refuses_do_set_servo_as_unsupported_and_params_are_bytewise():
    h = Harness(READY_PX4)
    h.command(mavlink.MAV_CMD_DO_SET_SERVO, 9, 1500)
    assert acks(h.run_for(0.01))[0].result == mavlink.MAV_RESULT_UNSUPPORTED
    h.send(h.gcs.param_request_read_encode(1, 1, b"PWM_MAIN_FUNC9", -1))
    value = param_values(h.run_for(0.01))[0]
    assert value.param_type == mavlink.MAV_PARAM_TYPE_INT32

    assert struct.unpack("<i", struct.pack("<f", value.param_value))[0] == 301


@pytest.mark.parametrize(
    ("value", "pwm"),
    [
        (0.001, 1501),  # 1500.5: half away from zero
        (-0.0009, 1500),  # 1499.55
        (0.9979, 1999),  # 1998.95
        (0.5, 1750),
        (-1.0, 1000),
        (1.0, 2000),
        (2.0, 2000),  # out of range: clamped to PWM_MAIN_MAXn, still ACCEPTED
        (-7.5, 1000),
        (math.inf, 2000),
    ],
)
def test_px4_actuator_value_to_pwm(value, pwm):
    h = mapped(armed=True)
    h.command(SET_ACTUATOR, value, 0, 0, 0, 0, 0, 0)
    assert acks(h.run_for(0.01))[-1].result == mavlink.MAV_RESULT_ACCEPTED
    assert h.ap.output_us[9] == pwm
