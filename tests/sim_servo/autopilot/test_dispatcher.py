"""The dispatcher: frames handled on the main-loop pass, every frame received logged, bad
and dropped frames counted, the configured identity."""

from __future__ import annotations

from dataclasses import replace

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from sim_servo.config import SimConfig
from tests.sim_servo.autopilot.conftest import START_S, Harness, acks, faulty


def test_system_id_is_configurable():
    h = Harness(SimConfig(system_id=42))
    beat = h.of_type("HEARTBEAT", h.run_for(0.0))[0]
    assert beat.get_srcSystem() == 42
    h.command(mavlink.MAV_CMD_DO_SET_SERVO, 9, 1500)  # addressed to system 1: not ours
    assert acks(h.run_for(0.1)) == []
    h.command(mavlink.MAV_CMD_DO_SET_SERVO, 9, 1500, target=(42, 1))
    assert len(acks(h.run_for(0.1))) == 1


def test_frames_are_handled_on_the_next_main_loop_pass():
    h = Harness()
    h.run_until(START_S + 0.001)
    h.command(mavlink.MAV_CMD_NAV_TAKEOFF)
    h.run_for(0.01)
    ack_time = [t for t, m in h.received if m.get_type() == "COMMAND_ACK"][0]
    assert ack_time == pytest.approx(START_S + 0.0025)  # 400 Hz loop


def test_drop_in_everything():
    h = faulty(drop_in=1.0)
    h.command(mavlink.MAV_CMD_DO_SET_SERVO, 9, 1600)
    assert acks(h.run_for(0.1)) == []
    assert h.ap.pwm_us[9] == 0 and h.ap.stats["dropped_in"] == 1


def test_corrupt_in_is_reported_as_bad_frames():
    h = faulty(corrupt_in=1.0)
    for _ in range(10):
        h.command(mavlink.MAV_CMD_NAV_TAKEOFF)
    assert h.ap.stats["corrupted_in"] == 10
    assert h.ap.stats["rx"] < 10 or h.ap.stats["bad_frames"] > 0


def test_every_command_is_logged_with_its_fields():
    h = Harness()
    h.command(mavlink.MAV_CMD_DO_SET_SERVO, 9, 1600)
    h.run_for(0.1)
    rx = [e for e in h.events if e["event"] == "rx" and e["msg"] == "COMMAND_LONG"][0]
    assert rx["src"] == [255, 190]
    assert rx["fields"]["command"] == mavlink.MAV_CMD_DO_SET_SERVO
    assert rx["fields"]["param1"] == 9 and rx["fields"]["param2"] == 1600
    ack = [e for e in h.events if e["event"] == "ack"][0]
    assert ack["result_name"] == "MAV_RESULT_ACCEPTED"


def test_replace_keeps_config_valid():
    config = replace(SimConfig(), system_id=3)
    assert config.functions[1] == 33
