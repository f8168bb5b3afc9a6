"""The simulator's Lua bridge: the script's checks (the same verdicts as the real script under
Lua), its answer time, and the autopilot answering MAV_CMD_USER_2 on a fake clock."""

from __future__ import annotations

import math
from dataclasses import replace

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from sim_servo.config import ArmConfig, SimConfig
from sim_servo.errors import SimConfigError
from sim_servo.lua_bridge import (
    MAV_CMD_USER_2,
    SCRIPT_ANSWER_MS,
    SCRIPT_PERIOD_MS,
    LuaScriptTiming,
    check_user2,
    refusal_text,
)
from tests.firmware_interface.test_lua_bridge import Bridge, as_mavlink_message_t, command_long
from tests.sim_servo.autopilot.conftest import Harness, acks

NAN = math.nan


def params_of(functions: dict[int, int]):
    table: dict[str, float] = {}
    for output in range(1, 17):
        table[f"SERVO{output}_FUNCTION"] = float(functions.get(output, 0))
        table[f"SERVO{output}_MIN"] = 1000.0
        table[f"SERVO{output}_MAX"] = 2000.0
    return table.get


def test_checks_accept_and_refuse_as_the_script_describes():
    param = params_of({12: 33})
    ok = check_user2((1100, NAN, 1300, NAN, NAN, NAN, 1), param)
    assert ok.accepted and ok.settings == {1: 1100, 3: 1300}
    motor = check_user2((1500,) * 6 + (9,), param)
    assert (motor.accepted, motor.refused_output, motor.settings) == (False, 12, {})
    assert refusal_text(motor) == "armbridge: Channel 12 is already in use; none set"
    assert check_user2((2001, NAN, NAN, NAN, NAN, NAN, 9), param).refused_output == 9
    assert check_user2((1500.5, NAN, NAN, NAN, NAN, NAN, 9), param).refused_output == 9
    assert check_user2((1500,) * 6 + (0,), param).refused_output == 0
    assert check_user2((NAN,) * 6 + (9,), param).reason == "no PWM in params 1-6"
    assert check_user2((1500, 1500, 1500, NAN, NAN, NAN, 15), param).refused_output == 17


@settings(max_examples=25)
@given(
    pwms=st.lists(
        st.one_of(st.just(NAN), st.integers(900, 2100).map(float), st.floats(width=32)),
        min_size=6,
        max_size=6,
    ),
    first=st.integers(-1, 34).map(float),
    motor=st.integers(1, 16),
)
def test_same_verdict_as_the_real_script(pwms, first, motor):
    wire = command_long((*pwms, first))
    bridge = Bridge(functions={motor: 33})
    bridge.feed(as_mavlink_message_t(wire))
    [(_, ack)] = bridge.acks()
    # The params as the script read them: float32 on the wire (MAVLink 2 drops trailing zeros).
    payload = wire[10 : 10 + wire[1]].ljust(33, b"\0")
    params = mavlink.MAVLink_command_long_message.unpacker.unpack(payload)[:7]
    verdict = check_user2(params, params_of({motor: 33}))
    assert verdict.accepted == (ack["result"] == mavlink.MAV_RESULT_ACCEPTED)
    assert verdict.refused_output == ack["result_param2"]
    assert sorted((o - 1, p) for o, p in verdict.settings.items()) == sorted(bridge.set)


def test_answer_time_spans_the_measured_median_and_max():
    timing = LuaScriptTiming(0.0)
    loop_s = 1 / 400
    # Handed over at a main-loop pass 0–2.5 ms after the frame came in, then the script's run.
    delays = []
    for k in range(2000):
        arrived = k * 0.000_731  # phases spread over both periods
        handed = math.ceil(arrived / loop_s) * loop_s
        delays.append((timing.answer_s(handed) - arrived) * 1e3)
    delays.sort()
    assert min(delays) >= SCRIPT_ANSWER_MS - 1e-6
    assert max(delays) <= SCRIPT_ANSWER_MS + SCRIPT_PERIOD_MS + 2.5 + 1e-6  # 10.5 ms
    # + the link's 1.0 ms output floor: SITL's measured 8.9 ms median, 11.5 ms max.
    assert delays[len(delays) // 2] + 1.0 == pytest.approx(8.9, abs=0.3)


def lua_harness(**config) -> Harness:
    return Harness(SimConfig(lua_script=True, **config))


def test_autopilot_sets_all_outputs_and_answers_once_after_the_script_delay():
    h = lua_harness()
    sent_s = h.now
    h.command(MAV_CMD_USER_2, 1100, 1200, 1300, 1400, 1500, 1600, 9)
    msgs = h.run_for(0.05)
    (ack,) = acks(msgs)
    assert (ack.command, ack.result, ack.result_param2) == (MAV_CMD_USER_2, 0, 0)
    ack_s = next(t for t, m in h.received if m.get_type() == "COMMAND_ACK")
    assert SCRIPT_ANSWER_MS - 1e-6 <= (ack_s - sent_s) * 1e3 <= 11.5 + 1e-6
    assert [h.ap.pwm_us[o] for o in range(9, 15)] == [1100, 1200, 1300, 1400, 1500, 1600]


def test_autopilot_refuses_a_motor_output_setting_nothing():
    h = lua_harness()
    h.command(MAV_CMD_USER_2, 1500, 1500, 1500, 1500, 1500, 1500, 1)  # outputs 1-4: motors
    msgs = h.run_for(0.05)
    (ack,) = acks(msgs)
    assert (ack.result, ack.result_param2) == (mavlink.MAV_RESULT_FAILED, 1)
    texts = [m.text for m in h.of_type("STATUSTEXT", msgs)]
    assert texts == ["armbridge: Channel 1 is already in use; none set"]
    assert h.ap.pwm_us[5] == 0 and h.ap.pwm_us[6] == 0  # the free outputs did not move either


def test_arm_outputs_take_the_arm_pwm_range_and_limits_are_enforced():
    h = lua_harness(arm=ArmConfig(pwm_min_us=1000, pwm_max_us=2000))
    h.command(MAV_CMD_USER_2, 1000, 2000, NAN, NAN, NAN, NAN, 9)
    h.command(MAV_CMD_USER_2, 2001, NAN, NAN, NAN, NAN, NAN, 9)
    results = [a.result for a in acks(h.run_for(0.05))]
    assert results == [mavlink.MAV_RESULT_ACCEPTED, mavlink.MAV_RESULT_FAILED]
    assert (h.ap.pwm_us[9], h.ap.pwm_us[10]) == (1000, 2000)


def test_without_the_script_user_2_is_unsupported_and_px4_cannot_have_it():
    h = Harness()
    h.command(MAV_CMD_USER_2, 1500, NAN, NAN, NAN, NAN, NAN, 9)
    (ack,) = acks(h.run_for(0.05))
    assert ack.result == mavlink.MAV_RESULT_UNSUPPORTED
    with pytest.raises(SimConfigError, match="lua_script: true needs flavour = 'ardupilot'"):
        replace(SimConfig(flavour="px4"), lua_script=True)
