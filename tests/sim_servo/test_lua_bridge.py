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
    DENIED_TEXT_S,
    MAV_CMD_USER_2,
    SCRIPT_ANSWER_MS,
    SCRIPT_PERIOD_MS,
    DeniedTexts,
    LuaScriptTiming,
    check_user2,
    refusal_text,
)
from tests.firmware_interface.test_lua_bridge import (
    COMPANION,
    GCS,
    Bridge,
    as_mavlink_message_t,
    command_long,
)
from tests.sim_servo.autopilot.conftest import Harness, acks

NAN = math.nan
OWN_SYSTEM = 1
DENIED_TEXT = "armbridge: denied 255/190: not ARMB_SYSID/COMPID"


def params_of(functions: dict[int, int], **script: float):
    table: dict[str, float] = {f"ARMB_{name.upper()}": value for name, value in script.items()}
    for output in range(1, 17):
        table[f"SERVO{output}_FUNCTION"] = float(functions.get(output, 0))
        table[f"SERVO{output}_MIN"] = 1000.0
        table[f"SERVO{output}_MAX"] = 2000.0
    return table.get


def test_checks_accept_and_refuse_as_the_script_describes():
    param = params_of({12: 33})

    def check(params, sender=COMPANION):
        return check_user2(params, param, sender=sender, own_system=OWN_SYSTEM)

    ok = check((1100, NAN, 1300, NAN, NAN, NAN, 1))
    assert ok.accepted and ok.settings == {1: 1100, 3: 1300}
    motor = check((1500,) * 6 + (9,))
    assert (motor.accepted, motor.refused_output, motor.settings) == (False, 12, {})
    assert not motor.denied
    assert refusal_text(motor) == "armbridge: Channel 12 is already in use; none set"
    assert check((2001, NAN, NAN, NAN, NAN, NAN, 9)).refused_output == 9
    assert check((1500.5, NAN, NAN, NAN, NAN, NAN, 9)).refused_output == 9
    assert check((1500,) * 6 + (0,)).refused_output == 0
    assert check((NAN,) * 6 + (9,)).reason == "no PWM in params 1-6"
    assert check((1500, 1500, 1500, NAN, NAN, NAN, 15)).refused_output == 17


@pytest.mark.parametrize("sender", [GCS, (1, 190), (2, 191)])
def test_checks_deny_any_sender_but_the_companion_before_anything_else(sender):
    motor = check_user2((1500,) * 6 + (9,), params_of({9: 33}), sender=sender, own_system=1)
    assert (motor.accepted, motor.denied, motor.refused_output, motor.settings) == (
        False,
        True,
        0,
        {},
    )
    said = f"armbridge: denied {sender[0]}/{sender[1]}: not ARMB_SYSID/COMPID"
    assert refusal_text(motor) == said


def test_checks_obey_the_ids_the_parameters_name():
    good = (1500,) + (NAN,) * 5 + (9,)
    gcs_obeyed = params_of({}, sysid=255, compid=190)
    assert check_user2(good, gcs_obeyed, sender=GCS, own_system=1).accepted
    assert check_user2(good, gcs_obeyed, sender=COMPANION, own_system=1).denied
    # 0 (the default): the autopilot's own system id, whatever it is
    own = params_of({}, sysid=0, compid=191)
    assert check_user2(good, own, sender=(7, 191), own_system=7).accepted
    assert check_user2(good, own, sender=(1, 191), own_system=7).denied
    # without the parameters (the script could not add them): its defaults
    assert check_user2(good, params_of({}), sender=COMPANION, own_system=1).accepted
    assert check_user2(good, params_of({}), sender=GCS, own_system=1).denied


def test_denials_are_said_first_then_at_most_every_5_s():
    texts = DeniedTexts()
    said = [texts.due(t) for t in (10.0, 10.1, 14.99, 15.0, 15.5, 20.0)]
    assert said == [True, False, False, True, False, True]
    texts.reset()
    assert texts.due(20.1)
    assert DENIED_TEXT_S == 5.0


@settings(max_examples=25)
@given(
    pwms=st.lists(
        st.one_of(st.just(NAN), st.integers(900, 2100).map(float), st.floats(width=32)),
        min_size=6,
        max_size=6,
    ),
    first=st.integers(-1, 34).map(float),
    motor=st.integers(1, 16),
    sender=st.sampled_from([COMPANION, GCS, (1, 190), (2, 191)]),
    obeyed=st.sampled_from([(0, 191), (255, 190), (2, 191)]),
)
def test_same_verdict_as_the_real_script(pwms, first, motor, sender, obeyed):
    wire = command_long((*pwms, first), sender=sender)
    bridge = Bridge(functions={motor: 33})
    bridge.param("ARMB_SYSID", obeyed[0])
    bridge.param("ARMB_COMPID", obeyed[1])
    bridge.feed(as_mavlink_message_t(wire))
    [(_, ack)] = bridge.acks()
    # The params as the script read them: float32 on the wire (MAVLink 2 drops trailing zeros).
    payload = wire[10 : 10 + wire[1]].ljust(33, b"\0")
    params = mavlink.MAVLink_command_long_message.unpacker.unpack(payload)[:7]
    param = params_of({motor: 33}, sysid=obeyed[0], compid=obeyed[1])
    verdict = check_user2(params, param, sender=sender, own_system=OWN_SYSTEM)
    assert verdict.accepted == (ack["result"] == mavlink.MAV_RESULT_ACCEPTED)
    assert verdict.denied == (ack["result"] == mavlink.MAV_RESULT_DENIED)
    assert verdict.refused_output == ack["result_param2"]
    if verdict.denied:  # (other refusals quote numbers, which Lua and Python print apart)
        assert bridge.texts[-1] == refusal_text(verdict)
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


def companion_command(h: Harness, *params: float, sender=COMPANION, target=(OWN_SYSTEM, 1)) -> None:
    """MAV_CMD_USER_2 from the companion (armbridge's default ids) on link 0."""
    codec = mavlink.MAVLink(None, *sender)
    msg = codec.command_long_encode(*target, MAV_CMD_USER_2, 0, *params)
    h.ap.receive(msg.pack(codec), h.now, 0)


def test_autopilot_sets_all_outputs_and_answers_once_after_the_script_delay():
    h = lua_harness()
    sent_s = h.now
    companion_command(h, 1100, 1200, 1300, 1400, 1500, 1600, 9)
    msgs = h.run_for(0.05)
    (ack,) = acks(msgs)
    assert (ack.command, ack.result, ack.result_param2) == (MAV_CMD_USER_2, 0, 0)
    ack_s = next(t for t, m in h.received if m.get_type() == "COMMAND_ACK")
    assert SCRIPT_ANSWER_MS - 1e-6 <= (ack_s - sent_s) * 1e3 <= 11.5 + 1e-6
    assert [h.ap.pwm_us[o] for o in range(9, 15)] == [1100, 1200, 1300, 1400, 1500, 1600]


def test_autopilot_refuses_a_motor_output_setting_nothing():
    h = lua_harness()
    companion_command(h, 1500, 1500, 1500, 1500, 1500, 1500, 1)  # outputs 1-4: motors
    msgs = h.run_for(0.05)
    (ack,) = acks(msgs)
    assert (ack.result, ack.result_param2) == (mavlink.MAV_RESULT_FAILED, 1)
    texts = [m.text for m in h.of_type("STATUSTEXT", msgs)]
    assert texts == ["armbridge: Channel 1 is already in use; none set"]
    assert h.ap.pwm_us[5] == 0 and h.ap.pwm_us[6] == 0  # the free outputs did not move either


def test_arm_outputs_take_the_arm_pwm_range_and_limits_are_enforced():
    h = lua_harness(arm=ArmConfig(pwm_min_us=1000, pwm_max_us=2000))
    companion_command(h, 1000, 2000, NAN, NAN, NAN, NAN, 9)
    companion_command(h, 2001, NAN, NAN, NAN, NAN, NAN, 9)
    results = [a.result for a in acks(h.run_for(0.05))]
    assert results == [mavlink.MAV_RESULT_ACCEPTED, mavlink.MAV_RESULT_FAILED]
    assert (h.ap.pwm_us[9], h.ap.pwm_us[10]) == (1000, 2000)


def test_autopilot_denies_a_ground_stations_user_2_and_sets_nothing():
    h = lua_harness()
    h.command(MAV_CMD_USER_2, 1100, 1200, 1300, 1400, 1500, 1600, 9)  # from 255/190
    msgs = h.run_for(0.05)
    (ack,) = acks(msgs)
    assert (ack.command, ack.result, ack.result_param2) == (
        MAV_CMD_USER_2,
        mavlink.MAV_RESULT_DENIED,
        0,
    )
    assert (ack.target_system, ack.target_component) == GCS
    assert [m.text for m in h.of_type("STATUSTEXT", msgs)] == [DENIED_TEXT]
    assert all(h.ap.pwm_us[o] == 0 for o in range(9, 15))


def test_autopilot_denies_a_flood_each_time_and_says_so_once_per_5_s():
    h = lua_harness()
    for _ in range(20):
        h.command(MAV_CMD_USER_2, 1500, NAN, NAN, NAN, NAN, NAN, 9)
    msgs = h.run_for(1.0)
    assert [a.result for a in acks(msgs)] == [mavlink.MAV_RESULT_DENIED] * 20
    assert [m.text for m in h.of_type("STATUSTEXT", msgs)] == [DENIED_TEXT]
    h.run_for(DENIED_TEXT_S)
    h.command(MAV_CMD_USER_2, 1500, NAN, NAN, NAN, NAN, NAN, 9)
    msgs = h.run_for(0.05)
    assert [m.text for m in h.of_type("STATUSTEXT", msgs)] == [DENIED_TEXT]
    assert h.ap.pwm_us[9] == 0


def test_autopilot_obeys_whom_armb_sysid_and_compid_name():
    h = lua_harness(params={"ARMB_SYSID": 255, "ARMB_COMPID": 190})
    h.command(MAV_CMD_USER_2, 1100, NAN, NAN, NAN, NAN, NAN, 9)  # the ground station's
    companion_command(h, 1200, NAN, NAN, NAN, NAN, NAN, 10)
    results = [a.result for a in acks(h.run_for(0.05))]
    assert results == [mavlink.MAV_RESULT_ACCEPTED, mavlink.MAV_RESULT_DENIED]
    assert (h.ap.pwm_us[9], h.ap.pwm_us[10]) == (1100, 0)
    # Set back at run time (a PARAM_SET, REAL32 as a script's parameters are): the next
    # command is judged by the new value.
    for name, value in (("ARMB_SYSID", 0.0), ("ARMB_COMPID", 191.0)):
        h.send(h.gcs.param_set_encode(1, 1, name.encode(), value, mavlink.MAV_PARAM_TYPE_REAL32))
    values = {m.param_id: m for m in h.of_type("PARAM_VALUE", h.run_for(0.05))}
    assert values["ARMB_COMPID"].param_type == mavlink.MAV_PARAM_TYPE_REAL32
    assert values["ARMB_COMPID"].param_value == 191.0
    companion_command(h, 1200, NAN, NAN, NAN, NAN, NAN, 10)
    (ack,) = acks(h.run_for(0.05))
    assert ack.result == mavlink.MAV_RESULT_ACCEPTED and h.ap.pwm_us[10] == 1200


def test_armb_sysid_0_is_the_autopilots_own_system_id():
    h = lua_harness(system_id=7)
    companion_command(h, 1100, NAN, NAN, NAN, NAN, NAN, 9, sender=(7, 191), target=(7, 1))
    companion_command(h, 1200, NAN, NAN, NAN, NAN, NAN, 9, sender=(1, 191), target=(7, 1))
    results = [a.result for a in acks(h.run_for(0.05))]
    assert results == [mavlink.MAV_RESULT_ACCEPTED, mavlink.MAV_RESULT_DENIED]
    assert h.ap.pwm_us[9] == 1100


def test_the_script_parameters_exist_only_with_the_script():
    h = lua_harness()
    assert (h.ap.params["ARMB_SYSID"].value, h.ap.params["ARMB_COMPID"].value) == (0, 191)
    with pytest.raises(SimConfigError, match="'ARMB_SYSID' unknown"):
        Harness(SimConfig(params={"ARMB_SYSID": 1}))


def test_without_the_script_user_2_is_unsupported_and_px4_cannot_have_it():
    h = Harness()
    h.command(MAV_CMD_USER_2, 1500, NAN, NAN, NAN, NAN, NAN, 9)
    (ack,) = acks(h.run_for(0.05))
    assert ack.result == mavlink.MAV_RESULT_UNSUPPORTED
    with pytest.raises(SimConfigError, match="lua_script: true needs flavour = 'ardupilot'"):
        replace(SimConfig(flavour="px4"), lua_script=True)
