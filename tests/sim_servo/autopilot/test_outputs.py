"""The servo outputs: DO_SET_SERVO (ArduPilot), DO_SET_ACTUATOR, arming and prearm (PX4), the
safety switch (ArduPilot), the servos' motion, and the ``output`` events that log what each
servo physically received."""

from __future__ import annotations

import math
import struct

import numpy as np
import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from firmware_interface.calibration import default_calibration
from sim_servo.autopilot import PX4_FORCE_MAGIC as PX4_FORCE
from sim_servo.config import SimConfig
from sim_servo.eventlog import physical_pwm_timeline
from tests.sim_servo.autopilot.conftest import (
    ARM_OUTPUTS,
    READY_PX4,
    SERVO_OUTPUT_RAW,
    SET_ACTUATOR,
    START_S,
    Harness,
    acks,
    ardupilot,
    faulty,
    mapped,
    param_values,
    px4,
    routing_harness,
)


def test_do_set_servo_on_free_output_is_accepted_and_reported():
    h = Harness()
    h.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, SERVO_OUTPUT_RAW, 100_000)
    h.command(mavlink.MAV_CMD_DO_SET_SERVO, 9, 1700)
    msgs = h.run_for(0.25)
    ack = acks(msgs)[-1]
    assert (ack.command, ack.result) == (mavlink.MAV_CMD_DO_SET_SERVO, mavlink.MAV_RESULT_ACCEPTED)
    assert (ack.target_system, ack.target_component) == (255, 190)
    raw = h.of_type("SERVO_OUTPUT_RAW", msgs)[-1]
    assert raw.port == 0 and raw.servo9_raw == 1700
    assert [raw.servo1_raw, raw.servo10_raw] == [1000, 0]  # disarmed motor, untouched output
    assert h.of_type("STATUSTEXT", msgs) == []


@pytest.mark.parametrize("output", [1, 2, 3, 4])
def test_do_set_servo_on_motor_fails_with_exact_statustext_after_the_ack(output):
    h = Harness()
    h.run_for(0.0)
    h.command(mavlink.MAV_CMD_DO_SET_SERVO, output, 1500)
    sent_at = h.now
    msgs = h.run_for(0.1)
    ack = acks(msgs)[0]
    assert ack.result == mavlink.MAV_RESULT_FAILED
    text = h.of_type("STATUSTEXT", msgs)[0]
    assert text.text == f"ServoRelayEvent: Channel {output} is already in use"
    assert text.severity == mavlink.MAV_SEVERITY_INFO
    times = {
        m.get_type(): t for t, m in h.received if m.get_type() in ("COMMAND_ACK", "STATUSTEXT")
    }
    assert times["COMMAND_ACK"] == sent_at
    assert times["STATUSTEXT"] == pytest.approx(sent_at + 1 / 400)  # next main-loop pass
    assert h.ap.pwm_us[output] == 1000


@pytest.mark.parametrize("pwm", [2500, 800, 0, 65535])
def test_pwm_applied_as_given_without_clamping(pwm):
    h = Harness()
    h.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, SERVO_OUTPUT_RAW, 100_000)
    h.command(mavlink.MAV_CMD_DO_SET_SERVO, 9, pwm)
    msgs = h.run_for(0.15)
    assert acks(msgs)[-1].result == mavlink.MAV_RESULT_ACCEPTED
    assert h.of_type("SERVO_OUTPUT_RAW", msgs)[-1].servo9_raw == pwm
    servo_events = [e for e in h.events if e["event"] == "servo"]
    assert servo_events[-1]["pwm_us"] == pwm


def test_out_of_range_pwm_shows_in_the_hand_state():
    h = Harness()
    h.command(mavlink.MAV_CMD_DO_SET_SERVO, 9, 2200)
    h.run_for(1.0)
    hand = h.ap.snapshot(h.now)["hand"]
    assert hand["pose"] is None
    assert "pwm_us=2200" in hand["error"] and "[1000, 2000]" in hand["error"]


@pytest.mark.parametrize("output", [0, 17, 255, -1, math.nan])
def test_do_set_servo_on_nonexistent_output_fails_silently(output):
    h = Harness()
    h.command(mavlink.MAV_CMD_DO_SET_SERVO, output, 1500)
    msgs = h.run_for(0.1)
    assert acks(msgs)[0].result == mavlink.MAV_RESULT_FAILED
    assert h.of_type("STATUSTEXT", msgs) == []


@pytest.mark.parametrize("function", [1, 51, 66])
def test_passthrough_functions_also_accept(function):
    h = Harness(SimConfig(functions={9: function}))
    h.command(mavlink.MAV_CMD_DO_SET_SERVO, 9, 1600)
    assert acks(h.run_for(0.1))[0].result == mavlink.MAV_RESULT_ACCEPTED


def test_do_set_servo_over_command_int():
    h = Harness()
    h.send(
        h.gcs.command_int_encode(
            1, 1, 0, mavlink.MAV_CMD_DO_SET_SERVO, 0, 0, 10, 1234, 0, 0, 0, 0, 0
        )
    )
    assert acks(h.run_for(0.1))[0].result == mavlink.MAV_RESULT_ACCEPTED
    assert h.ap.pwm_us[10] == 1234


def test_slew_timing_in_the_snapshot_and_settled_event():
    h = Harness()
    h.run_for(0.0)
    h.command(mavlink.MAV_CMD_DO_SET_SERVO, 9, 2000)  # theta1: +90°, 0.18 °/µs
    start = h.now
    rate_us_per_s = (60 / 0.12) / 0.18
    h.run_for(0.05)
    out9 = h.ap.snapshot(h.now)["outputs"]["9"]
    assert out9["moving"] and out9["position_us"] == pytest.approx(
        1500 + rate_us_per_s * 0.05, abs=1e-3
    )
    h.run_for(1.0)
    settled = [e for e in h.events if e["event"] == "settled"][-1]
    assert settled["t_s"] == pytest.approx(start - START_S + 500 / rate_us_per_s, abs=1e-6)
    assert settled["hand"]["angles_deg"]["theta1"] == pytest.approx(90.0)


def test_hand_reaches_the_commanded_pose():
    h = Harness()
    q_deg = [30.0, 120.0, -45.0, 20.0, -10.0, 45.0]
    # The PWM the daemon would send for q_deg (the simulator has no angle → PWM of its own).
    pwm = default_calibration().angles_to_pwm_us(q_deg)
    for output, value in pwm.items():
        h.command(mavlink.MAV_CMD_DO_SET_SERVO, output, value)
    assert all(a.result == mavlink.MAV_RESULT_ACCEPTED for a in acks(h.run_for(2.0)))
    state = h.ap.snapshot(h.now)
    assert state["settled"]
    expected = h.hand.arm.fk(q_deg)
    pose = state["hand"]["pose"]
    # Rounding to whole µs costs at most 0.09° per joint.
    for name in ("x_cm", "y_cm", "z_cm"):
        assert pose[name] == pytest.approx(getattr(expected, name), abs=0.5)
    for name, q in zip(
        ("theta1", "theta2", "theta3", "theta4", "theta5", "theta6"), q_deg, strict=True
    ):
        assert state["hand"]["angles_deg"][name] == pytest.approx(q, abs=0.1)


def test_nack_output_fails_without_statustext():
    h = faulty(nack_outputs=frozenset({10}))
    h.command(mavlink.MAV_CMD_DO_SET_SERVO, 10, 1600)
    h.command(mavlink.MAV_CMD_DO_SET_SERVO, 11, 1600)
    msgs = h.run_for(0.1)
    assert [a.result for a in acks(msgs)] == [
        mavlink.MAV_RESULT_FAILED,
        mavlink.MAV_RESULT_ACCEPTED,
    ]
    assert h.of_type("STATUSTEXT", msgs) == []
    assert h.ap.pwm_us[10] == 0 and h.ap.pwm_us[11] == 1600


ARM_DISARM = mavlink.MAV_CMD_COMPONENT_ARM_DISARM


def arm_pwms(h: Harness) -> list[int]:
    return [h.ap.output_us[o] for o in ARM_OUTPUTS]


def set_param(h: Harness, name: str, value: int) -> None:
    raw = struct.unpack("<f", struct.pack("<i", value))[0]  # PX4 sends INT32 bytewise
    h.send(h.gcs.param_set_encode(1, 1, name.encode(), raw, mavlink.MAV_PARAM_TYPE_INT32))


def test_px4_defaults_disarmed_functions_0_and_set_actuator_accepted_doing_nothing():
    h = px4()
    beat = h.of_type("HEARTBEAT", h.run_for(0.0))[0]
    assert not beat.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED
    assert [h.ap.params[f"PWM_MAIN_FUNC{o}"].value for o in ARM_OUTPUTS] == [0] * 6
    assert h.ap.params["COM_PREARM_MODE"].value == 0
    h.command(SET_ACTUATOR, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0)
    assert [a.result for a in acks(h.run_for(0.1))] == [mavlink.MAV_RESULT_ACCEPTED]
    assert set(h.ap.output_us.values()) == {1000}  # every output at PWM_MAIN_DISn
    h.run_for(10.0)  # prearm mode 0: nothing comes alive, ever
    assert set(h.ap.output_us.values()) == {1000} and not h.ap.prearmed


def test_px4_function_change_applies_without_reboot_and_stored_values_jump_on_arm():
    h = px4()
    for i, output in enumerate(ARM_OUTPUTS):
        set_param(h, f"PWM_MAIN_FUNC{output}", 301 + i)
    h.run_for(0.01)
    assert [h.ap.params.function(o) for o in ARM_OUTPUTS] == [301, 302, 303, 304, 305, 306]
    values = (0.112, -0.778, -0.334, 0.444, -0.222, 0.0)
    h.command(SET_ACTUATOR, *values, 0)
    h.run_for(0.1)
    assert arm_pwms(h) == [1000] * 6  # disarmed: dead, whatever was accepted
    h.command(ARM_DISARM, 1)
    msgs = h.run_for(0.1)
    assert acks(msgs)[-1].result == mavlink.MAV_RESULT_ACCEPTED
    # The stored values in one step, as measured: [1556, 1111, 1333, 1722, 1389, 1500].
    assert arm_pwms(h) == [1556, 1111, 1333, 1722, 1389, 1500]
    steps = [e for e in h.events if e["event"] == "output" and e["output"] in ARM_OUTPUTS]
    assert [(e["from_us"], e["pwm_us"], e["cause"]) for e in steps[-6:]] == [
        (1000, p, "arm") for p in [1556, 1111, 1333, 1722, 1389, 1500]
    ]
    beat = h.of_type("HEARTBEAT", h.run_for(1.0))[-1]
    assert beat.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED


def test_px4_disarm_kill_and_bad_arm_parameter():
    h = mapped(armed=True)
    h.command(SET_ACTUATOR, 0.5, 0.5, 0.5, 0.5, 0.5, 0.5, 0)
    h.run_for(0.1)
    assert arm_pwms(h) == [1750] * 6
    h.command(ARM_DISARM, 0)
    assert acks(h.run_for(0.1))[-1].result == mavlink.MAV_RESULT_ACCEPTED
    assert arm_pwms(h) == [1000] * 6 and not h.ap.armed
    h.command(ARM_DISARM, 1)
    h.run_for(0.1)
    assert arm_pwms(h) == [1750] * 6  # still stored
    h.command(ARM_DISARM, 0, PX4_FORCE)
    h.run_for(0.1)
    assert arm_pwms(h) == [1000] * 6
    assert [e["cause"] for e in h.events if e["event"] == "arming"] == ["command"] * 2 + ["kill"]
    h.command(ARM_DISARM, 2)
    assert acks(h.run_for(0.1))[-1].result == mavlink.MAV_RESULT_DENIED
    assert h.ap.set_armed(True, h.now, cause="kill") and h.ap.armed  # the query's way in


def test_px4_prearm_mode_2_makes_outputs_live_5_s_after_boot():
    h = mapped(params={"COM_PREARM_MODE": 2})
    h.command(SET_ACTUATOR, 0.2, 0.2, 0.2, 0.2, 0.2, 0.2, 0)
    h.run_until(START_S + 4.99)
    assert arm_pwms(h) == [1000] * 6 and not h.ap.prearmed
    h.run_until(START_S + 5.01)
    assert arm_pwms(h) == [1600] * 6 and h.ap.prearmed and not h.ap.armed
    [event] = [e for e in h.events if e["event"] == "prearm"]
    assert event["t_s"] == pytest.approx(5.0)
    h.ap.reboot(h.now, gap_s=0.5)  # back disarmed, slots never set, prearm 5 s after boot
    h.run_for(0.6)
    assert arm_pwms(h) == [1000] * 6
    h.command(SET_ACTUATOR, -0.2, -0.2, -0.2, -0.2, -0.2, -0.2, 0)  # re-sent after the reboot
    h.run_for(4.8)
    assert arm_pwms(h) == [1000] * 6
    h.run_for(0.2)
    assert arm_pwms(h) == [1400] * 6


def test_px4_prearm_mode_set_at_runtime_applies_at_once():
    h = mapped()
    h.command(SET_ACTUATOR, 0.2, 0.2, 0.2, 0.2, 0.2, 0.2, 0)
    h.run_for(6.0)
    assert arm_pwms(h) == [1000] * 6
    set_param(h, "COM_PREARM_MODE", 2)
    h.run_for(0.01)
    assert arm_pwms(h) == [1600] * 6


def test_px4_limits_nan_and_other_sets():
    h = mapped(armed=True, params={"PWM_MAIN_MAX9": 1800, "PWM_MAIN_MIN10": 1200})
    h.command(SET_ACTUATOR, 1.0, -1.0, 0.5, 0, 0, 0, 0)
    h.run_for(0.01)
    assert arm_pwms(h)[:3] == [1800, 1200, 1750]
    h.command(SET_ACTUATOR, math.nan, 0.0, math.nan, math.nan, math.nan, math.nan, 0)
    h.run_for(0.01)
    assert arm_pwms(h)[:3] == [1800, 1500, 1750]  # NaN: that output unchanged
    h.command(SET_ACTUATOR, 0, 0, 0, 0, 0, 0, 1)  # param7 = 1: ACCEPTED, no effect
    assert acks(h.run_for(0.01))[-1].result == mavlink.MAV_RESULT_ACCEPTED
    assert arm_pwms(h)[:3] == [1800, 1500, 1750]


def test_px4_servo_output_raw_and_actuator_output_status_show_the_disarmed_pwm():
    h = mapped()
    for msg_id in (SERVO_OUTPUT_RAW, mavlink.MAVLINK_MSG_ID_ACTUATOR_OUTPUT_STATUS):
        h.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, msg_id, 20_000)
    h.command(SET_ACTUATOR, 0.5, 0, 0, 0, 0, 0, 0)
    msgs = h.run_for(0.1)
    assert h.of_type("SERVO_OUTPUT_RAW", msgs)[-1].servo9_raw == 1000
    status = h.of_type("ACTUATOR_OUTPUT_STATUS", msgs)[-1]
    assert status.active == 16 and status.actuator[8] == 1000.0
    h.ap.set_armed(True, h.now)
    msgs = h.run_for(0.1)
    assert h.of_type("SERVO_OUTPUT_RAW", msgs)[-1].servo9_raw == 1750
    assert h.of_type("ACTUATOR_OUTPUT_STATUS", msgs)[-1].actuator[8] == 1750.0


def test_ardupilot_safety_off_by_default():
    h = ardupilot()
    assert not h.ap.safety_on and h.ap.params["BRD_SAFETY_DEFLT"].value == 0
    h.command(mavlink.MAV_CMD_DO_SET_SERVO, 9, 1700)
    h.run_for(0.01)
    assert h.ap.output_us[9] == 1700


def test_ardupilot_safety_on_keeps_outputs_out_of_the_mask_dead_then_they_jump():
    mask = 1 << (10 - 1)  # output 10 bypasses the safety switch
    h = ardupilot(params={"BRD_SAFETY_DEFLT": 1, "BRD_SAFETY_MASK": mask})
    h.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, SERVO_OUTPUT_RAW, 20_000)
    h.command(mavlink.MAV_CMD_DO_SET_SERVO, 9, 1700)
    h.command(mavlink.MAV_CMD_DO_SET_SERVO, 10, 1300)
    msgs = h.run_for(0.5)
    assert [a.result for a in acks(msgs)] == [mavlink.MAV_RESULT_ACCEPTED] * 3
    # SERVO_OUTPUT_RAW reports what the outputs were given; the servo on 9 gets no pulses.
    raw = h.of_type("SERVO_OUTPUT_RAW", msgs)[-1]
    assert (raw.servo9_raw, raw.servo10_raw) == (1700, 1300)
    assert (h.ap.output_us[9], h.ap.output_us[10]) == (0, 1300)
    assert h.ap.servos[9].position_us(h.now) == 1500.0  # where it started
    assert h.ap.set_safety(False, h.now)
    assert h.ap.output_us[9] == 1700
    [step] = [e for e in h.events if e["event"] == "output" and e["output"] == 9]
    assert (step["from_us"], step["pwm_us"], step["cause"]) == (0, 1700, "safety_off")
    h.ap.reboot(h.now, gap_s=0.1)  # BRD_SAFETY_DEFLT = 1: back on at boot
    h.run_for(0.2)
    assert h.ap.safety_on and h.ap.output_us[9] == 0
    assert [e["on"] for e in h.events if e["event"] == "safety"] == [False, True]


def test_ardupilot_a_new_safety_mask_applies_at_the_output_drivers_next_tick():
    # ArduPilot's output driver reads BRD_SAFETY_MASK at 10 Hz: the PARAM_VALUE of a change
    # comes at once, the outputs follow at the next tenth of a second since boot.
    h = ardupilot(params={"BRD_SAFETY_DEFLT": 1})
    h.command(mavlink.MAV_CMD_DO_SET_SERVO, 9, 1700)
    h.run_for(0.02)
    assert h.ap.output_us[9] == 0  # held by the switch
    h.run_for(0.05 - (h.now - START_S) % 0.1)  # half a tick to the next (booted at START_S)
    mask = 1 << (9 - 1)
    h.send(h.gcs.param_set_encode(1, 1, b"BRD_SAFETY_MASK", mask, mavlink.MAV_PARAM_TYPE_INT32))
    assert param_values(h.run_for(0.01))[0].param_value == mask
    assert h.ap.output_us[9] == 0
    h.run_for(0.05)
    assert h.ap.output_us[9] == 1700
    [step] = [e for e in h.events if e["event"] == "output" and e["output"] == 9]
    assert step["cause"] == "mask"
    assert step["t_s"] == pytest.approx(round(step["t_s"], 1), abs=1e-6)  # (since the boot)


def test_ardupilot_sys_status_says_whether_the_safety_switch_holds_the_outputs():
    h = ardupilot(params={"BRD_SAFETY_DEFLT": 1})
    h.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, mavlink.MAVLINK_MSG_ID_SYS_STATUS, 100_000)
    motors = mavlink.MAV_SYS_STATUS_SENSOR_MOTOR_OUTPUTS
    status = h.of_type("SYS_STATUS", h.run_for(0.25))[-1]
    assert status.onboard_control_sensors_present & motors
    assert not status.onboard_control_sensors_enabled & motors
    h.ap.set_safety(False, h.now)
    status = h.of_type("SYS_STATUS", h.run_for(0.25))[-1]
    assert status.onboard_control_sensors_enabled & motors


@pytest.mark.parametrize("flavour", ["px4", "ardupilot"])
def test_output_events_replay_every_physical_pwm(flavour):
    """Random arming, prearm, safety, reboots and commands: replaying the ``output`` events
    gives each output's physical PWM after every step (so a bench can check joint speed from
    the log alone)."""
    rng = np.random.default_rng(7)
    if flavour == "px4":
        h = mapped(params={"COM_PREARM_MODE": 2})
    else:
        h = ardupilot(params={"BRD_SAFETY_DEFLT": 1, "BRD_SAFETY_MASK": 1 << 8})
    replayed = dict(h.ap.output_us)
    first = dict(replayed)
    seen = 0
    for _ in range(150):
        action = rng.integers(5)
        if action == 0:
            if flavour == "px4":
                h.command(SET_ACTUATOR, *rng.uniform(-1, 1, 6), 0)
            else:
                h.command(
                    mavlink.MAV_CMD_DO_SET_SERVO,
                    int(rng.integers(9, 15)),
                    1000 + 10 * int(rng.integers(101)),
                )
        elif action == 1:
            h.ap.set_armed(bool(rng.integers(2)), h.now)
            h.ap.set_safety(bool(rng.integers(2)), h.now)
        elif action == 2 and rng.random() < 0.2:
            h.ap.reboot(h.now, gap_s=float(rng.uniform(0, 0.5)))
        h.run_for(float(rng.uniform(0, 1.5)))
        for event in h.events[seen:]:
            if event["event"] == "output":
                assert replayed[event["output"]] == event["from_us"]
                replayed[event["output"]] = event["pwm_us"]
        seen = len(h.events)
        assert replayed == h.ap.output_us
    kinds = {e["event"] for e in h.events}
    assert "output" in kinds and ("prearm" in kinds or flavour == "ardupilot")
    start = {"t_s": 0.0, "event": "start", "outputs_us": {str(o): p for o, p in first.items()}}
    timeline = physical_pwm_timeline([start, *h.events])
    assert {o: history[-1][1] for o, history in timeline.items()} == h.ap.output_us


def test_a_ground_station_s_servo_command_is_tagged_with_its_sender():
    h, companion = routing_harness()
    h.ap.receive(
        companion.command_long_encode(
            1, 1, mavlink.MAV_CMD_DO_SET_SERVO, 0, 9, 1200, 0, 0, 0, 0, 0
        ).pack(companion),
        h.now,
        0,
    )
    h.run_for(0.01)
    h.send(
        h.gcs.command_long_encode(1, 1, mavlink.MAV_CMD_DO_SET_SERVO, 0, 9, 2000, 0, 0, 0, 0, 0),
        channel=1,
    )
    h.run_for(0.01)
    outputs = [e for e in h.events if e["event"] == "output" and e["output"] == 9]
    servos = [e for e in h.events if e["event"] == "servo" and e["output"] == 9]
    assert [e["pwm_us"] for e in outputs] == [1200, 2000]
    assert "src" not in outputs[0] and "src" not in servos[0]
    assert outputs[1]["src"] == [255, 190] and outputs[1]["link"] == 1
    assert servos[1]["src"] == [255, 190] and h.ap.output_us[9] == 2000


def test_px4_refuses_a_ground_station_s_servo_command_and_tags_its_actuator_command():
    h = Harness(READY_PX4, links=2)
    h.command(SET_ACTUATOR, *[0.0] * 6, 0)
    h.run_for(0.05)
    h.send(
        h.gcs.command_long_encode(1, 1, mavlink.MAV_CMD_DO_SET_SERVO, 0, 9, 2000, 0, 0, 0, 0, 0),
        channel=1,
    )
    nan = math.nan
    h.send(
        h.gcs.command_long_encode(1, 1, SET_ACTUATOR, 0, nan, 1.0, nan, nan, nan, nan, 0),
        channel=1,
    )
    h.run_for(0.05)
    results = [e["result_name"] for e in h.events if e["event"] == "ack"]
    assert results[-2:] == ["MAV_RESULT_UNSUPPORTED", "MAV_RESULT_ACCEPTED"]
    changed = [e for e in h.events if e["event"] == "output" and e.get("src")]
    assert [(e["output"], e["pwm_us"], e["src"]) for e in changed] == [(10, 2000, [255, 190])]
    tagged = [e["output"] for e in h.events if e["event"] == "servo" and e.get("src")]
    assert tagged == [10] and h.ap.output_us[9] == 1500
