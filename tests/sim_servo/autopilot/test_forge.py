"""The forger: frames forged as if from the autopilot on the companion's link (a test fault)."""

from __future__ import annotations

import math

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from sim_servo.autopilot.forge import parse_forgery

from .conftest import Harness, ardupilot, frame_source, routing_harness


def forged(h: Harness, kind: str) -> list:
    """The frames of ``kind`` on link 0 (ArduPilot streams none of the three unless asked)."""
    dec = mavlink.MAVLink(None)
    out = []
    for _, channel, frame in h.wire:
        if channel != 0:
            continue
        for msg in dec.parse_buffer(frame) or []:
            if msg.get_type() == kind:
                out.append(msg)
    return out


def test_a_forged_sys_status_says_the_switch_is_off_on_the_companion_link_only():
    h, _ = routing_harness()
    h.ap.set_safety(True, h.now)
    h.ap.forge({"msg": "SYS_STATUS", "safety_on": False, "for_s": 0.1, "interval_s": 0.02}, h.now)
    h.run_for(0.2)
    frames = forged(h, "SYS_STATUS")
    assert len(frames) == 6  # t = 0, 0.02 … 0.1
    motors = mavlink.MAV_SYS_STATUS_SENSOR_MOTOR_OUTPUTS
    assert all(m.onboard_control_sensors_enabled & motors for m in frames)
    assert all((m.get_srcSystem(), m.get_srcComponent()) == (1, 1) for m in frames)
    on_gcs = [f for _, ch, f in h.wire if ch == 1 and frame_source(f) == (1, 1)]
    dec = mavlink.MAVLink(None)
    assert not any(m.get_type() == "SYS_STATUS" for f in on_gcs for m in dec.parse_buffer(f) or [])
    # Nothing in the autopilot changed: the switch is still on, the outputs still held.
    assert h.ap.safety_on and h.ap.stats["forged"] == 6
    fault = [e for e in h.events if e.get("fault") == "forge"]
    assert fault and fault[0]["msg"] == "SYS_STATUS" and fault[0]["fields"] == {"safety_on": False}


def test_a_forged_readback_shows_the_outputs_named_and_the_rest_as_reported():
    h = ardupilot()
    h.command(mavlink.MAV_CMD_DO_SET_SERVO, 10, 1700)
    h.run_for(0.01)
    h.ap.forge({"msg": "servo_output_raw", "pwm_us": {"9": 1234}}, h.now)
    h.run_for(0.01)
    (frame,) = forged(h, "SERVO_OUTPUT_RAW")
    assert frame.servo9_raw == 1234 and frame.servo10_raw == 1700
    assert h.ap.pwm_us[9] == 0  # the autopilot's own is unchanged


def test_a_forged_system_time_goes_back_once():
    h = ardupilot()
    h.run_for(3.0)
    h.ap.forge({"msg": "SYSTEM_TIME", "time_boot_ms": 5}, h.now)
    h.run_for(0.5)
    (frame,) = forged(h, "SYSTEM_TIME")
    assert frame.time_boot_ms == 5 and frame.time_unix_usec > 0
    assert h.ap.stats["forged"] == 1


def test_a_forgery_goes_on_through_a_reboot_and_a_new_one_replaces_it():
    h = ardupilot()
    h.ap.forge({"msg": "SYSTEM_TIME", "for_s": 1.0, "interval_s": 0.1}, h.now)
    h.run_for(0.05)
    h.ap.reboot(h.now)
    h.run_for(0.2)
    assert h.ap.rebooting and h.ap.stats["forged"] == 3
    h.ap.forge({"msg": "SYSTEM_TIME", "time_boot_ms": 7}, h.now)
    h.run_for(1.0)
    assert h.ap.stats["forged"] == 4


@pytest.mark.parametrize(
    ("request_", "message"),
    [
        ({}, "msg=None"),
        ({"msg": "HEARTBEAT"}, "msg='HEARTBEAT'"),
        ({"msg": "SYS_STATUS", "for_s": -1}, "for_s=-1"),
        ({"msg": "SYS_STATUS", "interval_s": 0}, "interval_s=0"),
        ({"msg": "SYS_STATUS", "safety_on": "no"}, "safety_on='no'"),
        ({"msg": "SERVO_OUTPUT_RAW", "pwm_us": {"17": 1500}}, "pwm_us output='17'"),
        ({"msg": "SERVO_OUTPUT_RAW", "pwm_us": [1500]}, "must map outputs"),
        ({"msg": "SYSTEM_TIME", "time_boot_ms": math.nan}, "time_boot_ms=nan"),
    ],
)
def test_a_forgery_it_cannot_carry_out_is_refused_by_its_field(request_, message):
    with pytest.raises(ValueError, match=message.replace("[", r"\[")):
        parse_forgery(request_, 0.0)
