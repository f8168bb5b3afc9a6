"""What differs between ArduPilot and PX4, through the autopilot and on the flavour objects
themselves."""

from __future__ import annotations

import math
import struct

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from sim_servo.autopilot.flavour import ArduPilot, Px4, flavour_for
from sim_servo.autopilot.params import Param
from sim_servo.config import SimConfig
from sim_servo.errors import SimConfigError
from sim_servo.linktiming import LinkOutput, LoopLinkOutput
from tests.sim_servo.autopilot.conftest import (
    READY_PX4,
    SET_ACTUATOR,
    START_S,
    Harness,
    acks,
    mapped,
    param_values,
    part_state,
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


# -- the flavour objects alone -------------------------------------------------------------


def test_flavour_for_each_firmware_and_an_unknown_name_lists_the_valid_ones():
    assert isinstance(flavour_for(SimConfig()), ArduPilot)
    assert isinstance(flavour_for(SimConfig(flavour="px4")), Px4)
    config = SimConfig()
    object.__setattr__(config, "flavour", "betaflight")
    with pytest.raises(
        SimConfigError, match=r"flavour='betaflight'; valid: \['ardupilot', 'px4'\]"
    ):
        flavour_for(config)


def test_parameter_names_and_how_values_travel():
    ap, px = ArduPilot(), Px4()
    assert (ap.function_param(9), ap.limit_params(9)) == (
        "SERVO9_FUNCTION",
        ("SERVO9_MIN", "SERVO9_MAX"),
    )
    assert (px.function_param(9), px.limit_params(9)) == (
        "PWM_MAIN_FUNC9",
        ("PWM_MAIN_MIN9", "PWM_MAIN_MAX9"),
    )
    int16 = Param("X", 1500, mavlink.MAV_PARAM_TYPE_INT16, -32768, 32767)
    assert ap.encode_param_value(int16) == 1500.0
    assert ap.decode_param_value(int16, 1499.995) == 1500  # +0.01 away from zero, truncated
    assert ap.decode_param_value(int16, -2.995) == -3
    assert ap.decode_param_value(int16, 1e9) == 32767  # constrained to the type
    assert ap.decode_param_value(int16, math.nan) is None
    int32 = Param("Y", 1500, mavlink.MAV_PARAM_TYPE_INT32, -(2**31), 2**31 - 1)
    raw = px.encode_param_value(int32)
    assert struct.pack("<f", raw) == struct.pack("<i", 1500)  # the int32's bytes
    assert px.decode_param_value(int32, raw) == 1500
    names = ["A", "B", "C"]
    assert (ap.param_set_index(names, "B"), px.param_set_index(names, "B")) == (-1, 1)


def test_default_tables_and_what_a_configured_value_may_be():
    ap_params = ArduPilot().default_params(SimConfig())
    assert len(ap_params) == 16 * 4 + 2 and ap_params["BRD_SAFETY_DEFLT"].value == 0
    px_params = Px4().default_params(SimConfig(flavour="px4"))
    assert len(px_params) == 16 * 4 + 3
    assert (px_params["MAV_0_FORWARD"].value, px_params["MAV_1_FORWARD"].value) == (1, 0)
    Px4().check_param("COM_PREARM_MODE", 2)
    with pytest.raises(SimConfigError, match=r"COM_PREARM_MODE=3; valid: \[0, 1, 2\]"):
        Px4().check_param("COM_PREARM_MODE", 3)


def test_when_a_command_is_acted_on_and_a_frame_handled():
    px, config = Px4(), SimConfig(flavour="px4")
    period_s = config.px4_timing.commander_period_ms / 1000.0
    arm = mavlink.MAV_CMD_COMPONENT_ARM_DISARM
    # The commander's next cycle, counted from boot: a command on a cycle waits a whole one.
    assert px.commander_due_s(config, arm, 10.0, 10.0) == pytest.approx(10.0 + period_s)
    assert px.commander_due_s(config, arm, 10.0 + 0.4 * period_s, 10.0) == pytest.approx(
        10.0 + period_s
    )
    assert px.commander_due_s(config, mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, 10.0, 10.0) is None
    assert ArduPilot().commander_due_s(SimConfig(), arm, 10.0, 10.0) is None
    ap_state, px_state = part_state(), part_state(config)
    assert px.rx_due_s(px_state, START_S + 0.0001) == START_S + 0.0001  # on arrival
    assert ArduPilot().rx_due_s(ap_state, START_S + 0.0001) == pytest.approx(START_S + 0.0025)


def test_prearm_and_safety_at_boot():
    px_params = Px4().default_params(SimConfig(flavour="px4"))
    px_params["COM_PREARM_MODE"].value = 0
    assert Px4().prearm_due_s(px_params, 7.0) is None
    for mode in (1, 2):
        px_params["COM_PREARM_MODE"].value = mode
        assert Px4().prearm_due_s(px_params, 7.0) == 12.0
    ap_params = ArduPilot().default_params(SimConfig())
    assert ArduPilot().safety_at_boot(ap_params) is False
    ap_params["BRD_SAFETY_DEFLT"].value = 1
    assert ArduPilot().safety_at_boot(ap_params) is True
    assert Px4().safety_at_boot(px_params) is False


def test_link_outputs_and_capabilities():
    assert isinstance(ArduPilot().new_link_output(SimConfig(), 0.0), LinkOutput)
    assert isinstance(Px4().new_link_output(SimConfig(flavour="px4"), 0.0), LoopLinkOutput)
    assert (ArduPilot.arms, ArduPilot.has_safety_switch, ArduPilot.runs_lua) == (False, True, True)
    assert (Px4.arms, Px4.has_safety_switch, Px4.runs_lua) == (True, False, False)
