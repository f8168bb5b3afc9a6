"""The parameter table and PARAM_SET / PARAM_REQUEST_READ / PARAM_REQUEST_LIST."""

from __future__ import annotations

import math

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from sim_servo.autopilot.params import ParamTable
from sim_servo.config import SimConfig
from sim_servo.errors import SimConfigError
from tests.sim_servo.autopilot.conftest import (
    READY_PX4,
    START_S,
    Harness,
    acks,
    ardupilot,
    mapped,
    param_values,
    part_state,
    px4,
)


def test_param_request_read_by_name_and_index():
    h = Harness()
    h.send(h.gcs.param_request_read_encode(1, 1, b"SERVO3_FUNCTION", -1))
    value = param_values(h.run_for(0.01))[0]
    assert (value.param_id, value.param_value) == ("SERVO3_FUNCTION", 35.0)
    assert value.param_type == mavlink.MAV_PARAM_TYPE_INT16
    assert (value.param_index, value.param_count) == (65535, 66)  # -1 as uint16; 16 × 4 + BRD_
    h.send(h.gcs.param_request_read_encode(1, 1, b"", 1))
    value = param_values(h.run_for(0.01))[0]
    assert (value.param_id, value.param_value, value.param_index) == ("SERVO1_MIN", 1100.0, 1)
    h.send(h.gcs.param_request_read_encode(1, 1, b"NO_SUCH_PARAM", -1))
    assert param_values(h.run_for(0.1)) == []


def test_param_set_changes_what_do_set_servo_accepts():
    h = Harness()
    h.send(h.gcs.param_set_encode(1, 1, b"SERVO9_FUNCTION", 32.999, mavlink.MAV_PARAM_TYPE_INT16))
    value = param_values(h.run_for(0.01))[0]
    assert (value.param_id, value.param_value) == ("SERVO9_FUNCTION", 33.0)
    assert value.param_index == 65535
    h.command(mavlink.MAV_CMD_DO_SET_SERVO, 9, 1500)
    msgs = h.run_for(0.01)
    assert acks(msgs)[0].result == mavlink.MAV_RESULT_FAILED
    assert h.of_type("STATUSTEXT", msgs)[0].text == "ServoRelayEvent: Channel 9 is already in use"
    h.send(h.gcs.param_set_encode(1, 1, b"SERVO3_FUNCTION", 0, mavlink.MAV_PARAM_TYPE_INT16))
    h.command(mavlink.MAV_CMD_DO_SET_SERVO, 3, 1500)
    assert acks(h.run_for(0.01))[0].result == mavlink.MAV_RESULT_ACCEPTED


def test_param_set_min_max_does_not_clamp_do_set_servo():
    h = Harness()
    h.send(h.gcs.param_set_encode(1, 1, b"SERVO9_MAX", 1600, mavlink.MAV_PARAM_TYPE_INT16))
    assert param_values(h.run_for(0.01))[0].param_value == 1600
    h.command(mavlink.MAV_CMD_DO_SET_SERVO, 9, 1900)
    h.run_for(0.01)
    assert h.ap.pwm_us[9] == 1900


def test_param_set_unknown_or_nan_gets_no_reply():
    h = Harness()
    h.send(h.gcs.param_set_encode(1, 1, b"SERVO99_MIN", 1000, mavlink.MAV_PARAM_TYPE_INT16))
    h.send(h.gcs.param_set_encode(1, 1, b"SERVO9_MIN", math.nan, mavlink.MAV_PARAM_TYPE_INT16))
    assert param_values(h.run_for(0.1)) == []
    assert h.ap.params["SERVO9_MIN"].value == 1100


def test_param_request_list_sends_every_parameter():
    h = Harness()
    h.send(h.gcs.param_request_list_encode(1, 1))
    values = param_values(h.run_for(0.01))
    assert len(values) == 66  # SERVOn_FUNCTION / MIN / MAX / TRIM, BRD_SAFETY_DEFLT / MASK
    assert [v.param_index for v in values] == list(range(66))


def test_px4_disarmed_pwm_is_a_parameter():
    h = mapped(params={"PWM_MAIN_DIS9": 900})
    assert h.ap.output_us[9] == 900 and h.ap.output_us[10] == 1000
    with pytest.raises(SimConfigError, match="NO_SUCH_PARAM"):
        px4(params={"NO_SUCH_PARAM": 1})
    with pytest.raises(SimConfigError, match="COM_PREARM_MODE=3"):
        px4(params={"COM_PREARM_MODE": 3})


def test_ardupilot_safety_parameters_read_and_set():
    h = ardupilot()
    h.send(h.gcs.param_set_encode(1, 1, b"BRD_SAFETY_MASK", 7936, mavlink.MAV_PARAM_TYPE_INT32))
    value = param_values(h.run_for(0.01))[0]
    assert (value.param_id, value.param_value) == ("BRD_SAFETY_MASK", 7936.0)
    h.send(h.gcs.param_request_read_encode(1, 1, b"BRD_SAFETY_DEFLT", -1))
    value = param_values(h.run_for(0.01))[0]
    assert (value.param_value, value.param_type) == (0.0, mavlink.MAV_PARAM_TYPE_INT8)
    assert not h.ap.set_armed(True, h.now)  # no arming here: PX4 only
    assert not Harness(READY_PX4).ap.set_safety(True, START_S)  # no safety switch on PX4


# -- the parameter table alone ---------------------------------------------------------------


def test_the_table_is_a_mapping_in_index_order_with_functions_and_limits():
    table = ParamTable(part_state(SimConfig(params={"SERVO9_MIN": 1050})))
    assert table.names[:4] == ["SERVO1_FUNCTION", "SERVO1_MIN", "SERVO1_MAX", "SERVO1_TRIM"]
    assert list(table) == table.names and len(table) == 66 and "BRD_SAFETY_MASK" in table
    assert table.function(1) == 33 and table.function(9) == 0  # a motor, a free output
    assert table.pwm_limits(9) == (1050, 1900)
    px4 = ParamTable(part_state(SimConfig(flavour="px4", functions={9: 301})))
    assert (px4.function(9), px4.pwm_limits(9)) == (301, (1000, 2000))


@pytest.mark.parametrize(
    ("params", "message"),
    [
        ({"SERVO99_MIN": 1}, "parameter 'SERVO99_MIN' unknown to the ardupilot flavour"),
        ({"SERVO9_MIN": 40_000}, r"parameter SERVO9_MIN=40000 outside \[-32768, 32767\]"),
    ],
)
def test_configured_values_are_checked(params, message):
    with pytest.raises(SimConfigError, match=message):
        ParamTable(part_state(SimConfig(params=params)))
