"""A reboot: silent and deaf for the gap, then time, sequence, streams, routes and outputs
from their boot values; parameters and the vehicle's motion go on."""

from __future__ import annotations

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from sim_servo.autopilot.reboot import Reboot
from sim_servo.autopilot.state import AutopilotState
from sim_servo.config import FaultConfig, SimConfig
from tests.sim_servo.autopilot.conftest import (
    READY_PX4,
    START_S,
    SYSTEM_TIME,
    Harness,
    faulty,
    part_state,
    routing_harness,
)


def test_a_reboot_is_silent_deaf_then_restarts_time_seq_streams_routes_and_outputs():
    h, companion = routing_harness()
    h.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, SYSTEM_TIME, 100_000)
    h.command(mavlink.MAV_CMD_DO_SET_SERVO, 9, 1700)
    h.send(h.gcs.param_set_encode(1, 1, b"SERVO10_MIN", 1050, mavlink.MAV_PARAM_TYPE_INT16))
    before = h.of_type("SYSTEM_TIME", h.run_for(1.0))
    assert before[-1].time_boot_ms > 900 and h.ap.pwm_us[9] == 1700
    h.ap.reboot(h.now)
    rebooted_at = h.now
    h.command(mavlink.MAV_CMD_DO_SET_SERVO, 11, 1600)  # ignored: nobody is listening
    assert h.run_until(rebooted_at + 0.36 - 1e-6) == []
    assert h.forwarded() == [] and h.ap.snapshot(h.now)["rebooting"]
    first = h.run_until(rebooted_at + 0.36)
    assert first[0].get_type() == "HEARTBEAT" and first[0].get_seq() == 0
    assert h.ap.pwm_us[9] == 0 and h.ap.pwm_us[11] == 0 and h.ap.pwm_us[1] == 1000
    state = h.ap.snapshot(h.now)
    assert state["routes"] == [] and state["peer"] is None and not state["rebooting"]
    assert state["streams"]["SYSTEM_TIME"] == 0  # back to the default: the request is lost
    assert h.ap.params["SERVO10_MIN"].value == 1050  # parameters survive
    h.command(mavlink.MAV_CMD_REQUEST_MESSAGE, SYSTEM_TIME)
    after = h.of_type("SYSTEM_TIME", h.run_for(0.1))
    assert after[0].time_boot_ms < 10 < before[-1].time_boot_ms
    faults = [(e["fault"], e["t_s"]) for e in h.events if e["event"] == "fault"]
    t0 = round(rebooted_at - START_S, 6)
    assert faults == [("reboot", t0), ("booted", pytest.approx(t0 + 0.36))]
    assert h.ap.stats["reboots"] == 1 and h.ap.stats["ignored_rebooting"] == 1


def test_a_reboot_while_rebooting_is_refused_and_the_gap_is_configurable():
    h = Harness(SimConfig(faults=FaultConfig(reboot_gap_s=1.0)))
    h.run_for(0.5)
    assert h.ap.reboot(h.now)
    assert not h.ap.reboot(h.now + 0.1)
    h.run_for(1.0 - 1e-6)
    assert h.ap.rebooting
    h.run_for(1e-6)
    assert not h.ap.rebooting


def test_a_scheduled_reboot_restarts_the_heartbeat_from_boot():
    h = faulty(reboot_after_s=2.2, reboot_gap_s=0.5)
    h.run_for(4.0)
    times = [round(t - START_S, 6) for t, m in h.received if m.get_type() == "HEARTBEAT"]
    assert times == [0.0, 1.0, 2.0, 2.7, 3.7]


def test_px4_outputs_return_to_their_disarmed_value_after_a_reboot():
    h = Harness(READY_PX4)
    h.command(mavlink.MAV_CMD_DO_SET_ACTUATOR, 0.5, 0, 0, 0, 0, 0, 0)
    h.run_for(0.1)
    assert h.ap.pwm_us[9] == 1750
    h.ap.reboot(h.now, gap_s=0.1)
    h.run_for(0.2)
    assert not h.ap.armed and not h.ap.prearmed
    assert h.ap.pwm_us[9] == 1000 and h.ap.pwm_us[1] == 1000 and h.ap.pwm_us[16] == 1000


def test_the_vehicle_goes_on_through_a_reboot_and_its_frames_restart_with_time_boot():
    h = Harness(SimConfig(attitude_rate_hz=10))
    h.run_for(1.0)
    h.ap.reboot(h.now, gap_s=0.5)
    msgs = h.run_for(1.0)
    after = h.of_type("ATTITUDE", msgs)
    assert [m.time_boot_ms for m in after][:2] == [0, 100]  # from the boot 1.5 s after start
    state = h.ap.vehicle.state(1.5)
    assert after[0].roll == pytest.approx(state.roll_rad, rel=1e-6)


# -- the reboot part alone -------------------------------------------------------------------


def reboot_part(events: list, steps: list, **faults) -> tuple[Reboot, AutopilotState]:
    state = part_state(SimConfig(faults=FaultConfig(**faults)), events)
    part = Reboot(
        state,
        halt=[lambda t: steps.append(("halt a", t)), lambda t: steps.append(("halt b", t))],
        boot=[lambda t: steps.append(("boot a", t)), lambda t: steps.append(("boot b", t))],
        now_s=START_S,
    )
    return part, state


def test_the_parts_halt_then_boot_in_order_after_the_gap():
    events: list = []
    steps: list = []
    part, state = reboot_part(events, steps)
    assert part.reboot(START_S + 1.0, gap_s=0.5) is True
    assert steps == [("halt a", START_S + 1.0), ("halt b", START_S + 1.0)]
    assert state.rebooting and part.next_events_s() == [START_S + 1.5]
    assert part.reboot(START_S + 1.2) is False  # already rebooting
    part.run(START_S + 1.4)
    assert len(steps) == 2
    part.run(START_S + 1.7)  # late: the boot keeps the gap's end as its time
    assert steps[2:] == [("boot a", START_S + 1.5), ("boot b", START_S + 1.5)]
    assert not state.rebooting and state.boot_s == START_S + 1.5
    assert [e.get("fault") for e in events] == ["reboot", "booted"]
    assert state.stats["reboots"] == 1


def test_a_zero_gap_boots_at_once_and_the_gap_is_bounded():
    steps: list = []
    part, state = reboot_part([], steps)
    part.reboot(START_S, gap_s=0.0)
    assert [name for name, _ in steps] == ["halt a", "halt b", "boot a", "boot b"]
    assert not state.rebooting
    with pytest.raises(ValueError, match=r"gap_s=600.5 outside \[0.0, 600.0\]"):
        part.reboot(START_S, gap_s=600.5)


def test_a_scheduled_reboot_happens_once_at_its_time():
    steps: list = []
    part, state = reboot_part([], steps, reboot_after_s=2.0, reboot_gap_s=0.25)
    assert part.next_events_s() == [START_S + 2.0]
    part.run(START_S + 2.1)
    assert steps[0] == ("halt a", START_S + 2.0)
    assert state.rebooting_until_s == START_S + 2.25
    part.run(START_S + 2.3)
    part.run(START_S + 9.0)
    assert [name for name, _ in steps] == ["halt a", "halt b", "boot a", "boot b"]
