"""The Lua bridge script as a part of the autopilot: its setup, which commands it takes and when
it answers. Its verdicts and its answers through the whole autopilot are tested in
``tests/sim_servo/test_lua_bridge.py``."""

from __future__ import annotations

import math
from dataclasses import replace

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from sim_servo.autopilot.commands import Command
from sim_servo.autopilot.lua import LuaScript
from sim_servo.autopilot.outputs import Outputs, make_servos
from sim_servo.autopilot.params import ParamTable
from sim_servo.autopilot.wire import Wire
from sim_servo.config import ArmConfig, SimConfig
from sim_servo.faults import FaultInjector
from sim_servo.lua_bridge import MAV_CMD_USER_2, SCRIPT_ANSWER_MS
from tests.sim_servo.autopilot.conftest import START_S, WALL_S, part_state

#: armbridge's default ids on the default vehicle (system 1); a ground station's.
COMPANION = (1, 191)
GCS = (255, 190)


def script(config: SimConfig, events: list) -> tuple[LuaScript, Outputs, Wire, ParamTable]:
    state = part_state(config, events)
    wire = Wire(state, FaultInjector(config.faults), links=1, wall_clock=lambda: WALL_S)
    params = ParamTable(state)
    servos = make_servos(state, None, START_S)
    outputs = Outputs(
        state, params, servos, wire, hand=None, before_course_change=lambda _: None, now_s=START_S
    )
    return LuaScript(state, params, outputs, wire, now_s=START_S), outputs, wire, params


def test_the_arm_outputs_take_the_arm_pwm_range_at_setup():
    config = replace(SimConfig(), arm=ArmConfig(pwm_min_us=1050, pwm_max_us=1950))
    _, _, _, params = script(config, [])
    assert [params.pwm_limits(o) for o in config.arm.outputs] == [(1050, 1950)] * 6
    assert params.pwm_limits(1) == (1100, 1900)  # not an arm output: the firmware's default


def test_the_script_needs_ardupilot():
    state = part_state(SimConfig(flavour="px4"))
    with pytest.raises(ValueError, match="lua_script needs flavour='ardupilot'"):
        LuaScript(state, ParamTable(state), None, None, now_s=START_S)  # type: ignore[arg-type]


def test_user_2_waits_for_the_script_then_sets_the_outputs_and_answers():
    events: list = []
    lua, outputs, wire, _ = script(SimConfig(), events)
    other = Command(mavlink.MAV_CMD_DO_SET_SERVO, (9.0, 1500.0, *[0.0] * 5), COMPANION)
    assert not lua.takes(other)
    command = Command(MAV_CMD_USER_2, (1100, 1200, 1300, 1400, 1500, 1600, 9), COMPANION)
    assert lua.takes(command)
    lua.queue(command, START_S)
    (due_s,) = lua.next_events_s()
    assert due_s - START_S >= SCRIPT_ANSWER_MS / 1000.0 - 1e-9
    lua.run(due_s - 1e-6)
    assert outputs.pwm_us[9] == 0 and lua.next_events_s() == [due_s]
    lua.run(due_s)
    assert [outputs.pwm_us[o] for o in range(9, 15)] == [1100, 1200, 1300, 1400, 1500, 1600]
    (ack,) = [e for e in events if e["event"] == "ack"]
    assert (ack["command_name"], ack["result"], ack["refused_output"]) == (
        "MAV_CMD_USER_2 (lua)",
        mavlink.MAV_RESULT_ACCEPTED,
        0,
    )
    assert wire.links_due_s() != [] and lua.next_events_s() == []


def test_a_reboot_drops_the_commands_waiting():
    lua, _, _, _ = script(SimConfig(), [])
    lua.queue(Command(MAV_CMD_USER_2, (1500, *[math.nan] * 5, 9), COMPANION), START_S)
    lua.halt(START_S)
    assert lua.next_events_s() == []


def denied_texts(events: list) -> list[str]:
    return [e["text"] for e in events if e["event"] == "statustext"]


def test_another_senders_user_2_is_denied_and_said_once_a_5_s_until_a_reboot():
    events: list = []
    lua, outputs, _, _ = script(SimConfig(lua_script=True), events)
    command = Command(MAV_CMD_USER_2, (1500, *[math.nan] * 5, 9), GCS)
    for at in (START_S, START_S + 1.0):
        lua.queue(command, at)
        lua.run(max(lua.next_events_s()))
    assert outputs.pwm_us[9] == 0
    results = [(e["result"], e["refused_output"]) for e in events if e["event"] == "ack"]
    assert results == [(mavlink.MAV_RESULT_DENIED, 0)] * 2
    said = ["armbridge: denied 255/190: not ARMB_SYSID/COMPID"]
    assert denied_texts(events) == said
    lua.halt(START_S + 2.0)  # a reboot restarts the script
    lua.queue(command, START_S + 2.0)
    lua.run(max(lua.next_events_s()))
    assert denied_texts(events) == said * 2


def test_the_script_parameters_are_read_at_each_command():
    events: list = []
    lua, outputs, _, params = script(SimConfig(lua_script=True), events)
    params["ARMB_SYSID"].value, params["ARMB_COMPID"].value = GCS
    lua.queue(Command(MAV_CMD_USER_2, (1500, *[math.nan] * 5, 9), GCS), START_S)
    lua.run(max(lua.next_events_s()))
    assert outputs.pwm_us[9] == 1500
