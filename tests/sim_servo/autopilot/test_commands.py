"""COMMAND_LONG / COMMAND_INT: UNSUPPORTED for what no part handles, withheld ACKs, PX4's
commander cycle."""

from __future__ import annotations

import numpy as np
import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from sim_servo.autopilot.commands import Command, Commands
from sim_servo.autopilot.wire import Wire
from sim_servo.config import Px4TimingConfig, SimConfig
from sim_servo.faults import FaultInjector
from tests.sim_servo.autopilot.conftest import (
    INSTANT,
    READY_PX4,
    SET_ACTUATOR,
    START_S,
    WALL_S,
    Harness,
    acks,
    faulty,
    part_state,
    wait_ack,
)


@pytest.mark.parametrize(
    "command", [mavlink.MAV_CMD_NAV_TAKEOFF, mavlink.MAV_CMD_DO_SET_ACTUATOR, 31999]
)
def test_unknown_commands_are_unsupported(command):
    h = Harness()
    h.command(command, 1, 2, 3)
    ack = acks(h.run_for(0.1))[0]
    assert (ack.command, ack.result) == (command, mavlink.MAV_RESULT_UNSUPPORTED)


def test_withheld_ack_still_executes():
    h = faulty(withhold_ack_commands=frozenset({mavlink.MAV_CMD_DO_SET_SERVO}))
    h.command(mavlink.MAV_CMD_DO_SET_SERVO, 9, 1600)
    h.command(mavlink.MAV_CMD_NAV_TAKEOFF)
    msgs = h.run_for(0.5)
    assert [a.command for a in acks(msgs)] == [mavlink.MAV_CMD_NAV_TAKEOFF]
    assert h.ap.pwm_us[9] == 1600
    assert any(e["event"] == "ack" and e["withheld"] for e in h.events)


def test_withhold_all_acks():
    h = faulty(withhold_all_acks=True)
    h.command(mavlink.MAV_CMD_NAV_TAKEOFF)
    assert acks(h.run_for(0.5)) == []


def test_px4_timing_commander_cycle_and_main_loop():
    timing = Px4TimingConfig()  # the defaults: commander 10 ms, main loop 1.5 ms
    h = Harness(READY_PX4, px4_timing=timing)
    rng = np.random.default_rng(3)
    rtts = []
    for _ in range(200):
        h.run_for(rng.uniform(0.0, 0.02))
        sent = h.now
        h.command(SET_ACTUATOR, 0.1, 0, 0, 0, 0, 0, 0)
        rtts.append(wait_ack(h) - sent)
    rtts_ms = np.array(rtts) * 1000
    assert rtts_ms.min() > 0.0 and rtts_ms.max() <= 11.5 + 1e-6
    assert 4.5 <= float(np.median(rtts_ms)) <= 7.0
    # Every frame leaves on a 1.5 ms main-loop pass from boot.
    phases = [((t - START_S) * 1000 / 1.5) % 1 for t, _, _ in h.wire]
    assert all(min(p, 1 - p) < 1e-6 for p in phases)


def test_px4_a_servo_event_says_when_its_command_arrived_before_the_commander_acted():
    h = Harness(READY_PX4, px4_timing=Px4TimingConfig())
    h.run_for(0.013)
    sent = h.now
    h.command(SET_ACTUATOR, 0.1, 0, 0, 0, 0, 0, 0)
    wait_ack(h)
    servos = [e for e in h.events if e["event"] == "servo"]
    assert servos
    for event in servos:
        assert event["received_t_s"] == pytest.approx(sent - START_S, abs=1e-6)
        assert event["t_s"] > event["received_t_s"]  # the commander's next cycle


# -- the commands part alone -----------------------------------------------------------------


def commands_part(config: SimConfig, events: list, handlers: dict) -> tuple[Commands, Wire]:
    state = part_state(config, events)
    wire = Wire(state, FaultInjector(config.faults), links=2, wall_clock=lambda: WALL_S)
    return Commands(state, wire, handlers, lua=None), wire


def test_a_command_goes_to_its_handler_and_the_ack_only_to_the_link_it_came_from():
    events: list = []
    seen: list = []
    handler = {31010: lambda command, now_s: seen.append(command) or mavlink.MAV_RESULT_DENIED}
    part, wire = commands_part(SimConfig(link_timing=INSTANT), events, handler)
    command = Command(31010, (1.0, *[0.0] * 6), (255, 190), channel=1)
    part.execute(command, START_S)
    assert seen == [command]
    (ack,) = [e for e in events if e["event"] == "ack"]
    assert (ack["result"], ack["result_name"], ack["withheld"]) == (
        mavlink.MAV_RESULT_DENIED,
        "MAV_RESULT_DENIED",
        False,
    )
    assert [channel for channel, _ in wire.take(START_S)] == [1]


def test_px4_commander_commands_wait_for_the_next_cycle_and_a_reboot_drops_them():
    config = SimConfig(flavour="px4")
    handler = {mavlink.MAV_CMD_COMPONENT_ARM_DISARM: lambda c, t: mavlink.MAV_RESULT_ACCEPTED}
    events: list = []
    part, _ = commands_part(config, events, handler)
    msg = mavlink.MAVLink(None, 255, 190).command_long_encode(
        1, 1, mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0
    )
    part.on_command_long(msg, START_S + 0.001, 0)
    (due_s,) = part.next_events_s()
    period_s = config.px4_timing.commander_period_ms / 1000.0
    assert due_s == pytest.approx(START_S + period_s)
    part.run_commander(due_s - 1e-6)
    assert events == []
    part.run_commander(due_s)
    assert [e["event"] for e in events] == ["ack"] and part.next_events_s() == []
    part.on_command_long(msg, START_S + 0.02, 0)
    part.halt(START_S + 0.021)
    assert part.next_events_s() == []
