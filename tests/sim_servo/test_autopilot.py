"""The simulated autopilot's MAVLink behaviour, driven frame by frame on a fake clock.

A plain pymavlink codec plays the daemon; nothing here sleeps. ``Harness.run_until`` jumps from
one scheduled event of the autopilot to the next, so stream rates and delays are exact. The
harness turns the link timing model off (frames leave on the main-loop pass that made them)
unless a test asks for it; the model itself is tested in ``test_linktiming.py`` and at the end
of this file.
"""

from __future__ import annotations

import math
import struct
from dataclasses import replace

import numpy as np
import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from companion.kinematics.rotations import rpy_to_matrix
from firmware_interface.calibration import default_calibration
from sim_servo.autopilot import PX4_FORCE_MAGIC as PX4_FORCE
from sim_servo.autopilot import SimAutopilot
from sim_servo.config import (
    DEFAULT_ARM_OUTPUTS,
    FaultConfig,
    LinkTimingConfig,
    Px4TimingConfig,
    SimConfig,
    VehicleConfig,
    config_from_mapping,
    ready_setup,
)
from sim_servo.errors import SimConfigError
from sim_servo.eventlog import physical_pwm_timeline, world_timeline
from sim_servo.hand import HandModel

KEY = bytes(range(32))
START_S = 100.0
WALL_S = 1.7e9
SERVO_OUTPUT_RAW = mavlink.MAVLINK_MSG_ID_SERVO_OUTPUT_RAW
SYSTEM_TIME = mavlink.MAVLINK_MSG_ID_SYSTEM_TIME
INSTANT = LinkTimingConfig.instant()
PX4_INSTANT = Px4TimingConfig.instant()
#: A PX4 set up for the arm (functions 301–306, prearm mode 2, forwarding, armed at start).
READY_PX4 = config_from_mapping({"flavour": "px4", **ready_setup("px4", DEFAULT_ARM_OUTPUTS)})


def frame_source(frame: bytes) -> tuple[int, int]:
    """(system, component) from a raw MAVLink 2 (or 1) frame's header."""
    return (frame[5], frame[6]) if frame[0] == 0xFD else (frame[3], frame[4])


class Harness:
    """The autopilot on a fake clock; ``received`` is what link 0 got, decoded, with times;
    ``wire`` every frame on every link. ``link_timing`` replaces the config's (default: off)."""

    def __init__(
        self,
        config: SimConfig | None = None,
        *,
        signing_key: bytes | None = None,
        link_timing: LinkTimingConfig = INSTANT,
        px4_timing: Px4TimingConfig = PX4_INSTANT,
        links: int = 1,
    ) -> None:
        self.config = replace(
            config or SimConfig(),
            link_timing=link_timing,
            px4_timing=px4_timing,
        )
        self.now = START_S
        self.events: list[dict] = []
        self.hand = HandModel.from_config(self.config.arm)
        self.ap = SimAutopilot(
            self.config,
            now_s=self.now,
            emit=self.events.append,
            hand=self.hand,
            wall_clock=lambda: WALL_S,
            links=links,
        )
        self.gcs = mavlink.MAVLink(None, 255, 190)
        self.dec = mavlink.MAVLink(None)
        self.dec.robust_parsing = True
        if signing_key is not None:
            self.gcs.signing.secret_key = signing_key
            self.gcs.signing.sign_outgoing = True
            self.gcs.signing.link_id = 3
            self.gcs.signing.timestamp = 1
            self.dec.signing.secret_key = signing_key
        self.received: list[tuple[float, mavlink.MAVLink_message]] = []
        self.wire: list[tuple[float, int, bytes]] = []
        self._forwarded_seen = 0

    def send(self, msg, channel: int = 0) -> None:
        self.ap.receive(msg.pack(self.gcs), self.now, channel)

    def command(self, command: int, *params: float, target=(1, 1)) -> None:
        values = list(params) + [0.0] * (7 - len(params))
        self.send(self.gcs.command_long_encode(*target, command, 0, *values))

    def _collect(self) -> None:
        for channel, frame in self.ap.poll(self.now):
            self.wire.append((self.now, channel, frame))
            if channel == 0:
                for msg in self.dec.parse_buffer(frame) or []:
                    self.received.append((self.now, msg))

    def forwarded(self) -> list[tuple[int, bytes]]:
        """Frames routed (not ours) onto a link since the last call: ``(link, frame)``."""
        own = (self.config.system_id, self.config.component_id)
        frames = self.wire[self._forwarded_seen :]
        self._forwarded_seen = len(self.wire)
        return [(ch, f) for _, ch, f in frames if frame_source(f) != own]

    def on_link(self, channel: int, kind: str | None = None) -> list:
        """Our own messages (decoded) that went out on ``channel``, optionally of one type."""
        dec = mavlink.MAVLink(None)
        own = (self.config.system_id, self.config.component_id)
        msgs = []
        for _, ch, frame in self.wire:
            if ch == channel and frame_source(frame) == own:
                msgs += dec.parse_buffer(frame) or []
        return [m for m in msgs if kind is None or m.get_type() == kind]

    def run_until(self, end_s: float) -> list:
        """Advance to ``end_s`` through every scheduled event; the messages received meanwhile."""
        first = len(self.received)
        self._collect()
        while True:
            due = self.ap.next_event_s(self.now)
            if due > end_s:
                break
            self.now = max(due, self.now + 1e-9) if due <= self.now else due
            self._collect()
        self.now = end_s
        self._collect()
        return [msg for _, msg in self.received[first:]]

    def run_for(self, seconds: float) -> list:
        return self.run_until(self.now + seconds)

    def of_type(self, kind: str, msgs=None) -> list:
        msgs = msgs if msgs is not None else [m for _, m in self.received]
        return [m for m in msgs if m.get_type() == kind]


def acks(msgs):
    return [m for m in msgs if m.get_type() == "COMMAND_ACK"]


# -- heartbeat ------------------------------------------------------------------------------


def test_heartbeat_identity_and_rate():
    h = Harness()
    msgs = h.run_for(3.5)
    beats = h.of_type("HEARTBEAT", msgs)
    assert len(beats) == 4  # t = 0, 1, 2, 3
    beat = beats[0]
    assert (beat.get_srcSystem(), beat.get_srcComponent()) == (1, 1)
    assert beat.type == mavlink.MAV_TYPE_QUADROTOR
    assert beat.autopilot == mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA
    assert beat.system_status == mavlink.MAV_STATE_STANDBY
    times = [t for t, m in h.received if m.get_type() == "HEARTBEAT"]
    assert [round(b - a, 6) for a, b in zip(times, times[1:], strict=False)] == [1.0, 1.0, 1.0]


def test_system_id_is_configurable():
    h = Harness(SimConfig(system_id=42))
    beat = h.of_type("HEARTBEAT", h.run_for(0.0))[0]
    assert beat.get_srcSystem() == 42
    h.command(mavlink.MAV_CMD_DO_SET_SERVO, 9, 1500)  # addressed to system 1: not ours
    assert acks(h.run_for(0.1)) == []
    h.command(mavlink.MAV_CMD_DO_SET_SERVO, 9, 1500, target=(42, 1))
    assert len(acks(h.run_for(0.1))) == 1


# -- DO_SET_SERVO ---------------------------------------------------------------------------


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


def test_frames_are_handled_on_the_next_main_loop_pass():
    h = Harness()
    h.run_until(START_S + 0.001)
    h.command(mavlink.MAV_CMD_NAV_TAKEOFF)
    h.run_for(0.01)
    ack_time = [t for t, m in h.received if m.get_type() == "COMMAND_ACK"][0]
    assert ack_time == pytest.approx(START_S + 0.0025)  # 400 Hz loop


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


@pytest.mark.parametrize(
    "command", [mavlink.MAV_CMD_NAV_TAKEOFF, mavlink.MAV_CMD_DO_SET_ACTUATOR, 31999]
)
def test_unknown_commands_are_unsupported(command):
    h = Harness()
    h.command(command, 1, 2, 3)
    ack = acks(h.run_for(0.1))[0]
    assert (ack.command, ack.result) == (command, mavlink.MAV_RESULT_UNSUPPORTED)


def test_commands_for_another_component_heard_elsewhere_are_not_handled_here():
    # Once 1/154 (a camera, say) has been heard on link 1, a command for it is its business
    # (routing: forwarded there, not handled). Never heard: see the routing tests below.
    h = Harness(links=2)
    camera = mavlink.MAVLink(None, 1, 154)
    h.ap.receive(camera.heartbeat_encode(30, 8, 0, 0, 0).pack(camera), h.now, 1)
    h.run_for(0.01)
    h.command(mavlink.MAV_CMD_DO_SET_SERVO, 9, 1500, target=(1, 154))
    assert acks(h.run_for(0.1)) == [] and h.ap.pwm_us[9] == 0
    assert [ch for ch, _ in h.forwarded()] == [1]
    h.command(mavlink.MAV_CMD_DO_SET_SERVO, 9, 1500, target=(0, 0))  # broadcast
    assert len(acks(h.run_for(0.1))) == 1


# -- streams --------------------------------------------------------------------------------


@pytest.mark.parametrize("rate_hz", [4, 20, 50])
def test_servo_output_raw_runs_at_the_requested_rate(rate_hz):
    h = Harness()
    assert h.of_type("SERVO_OUTPUT_RAW", h.run_for(1.0)) == []  # off until asked
    h.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, SERVO_OUTPUT_RAW, 1e6 / rate_hz)
    msgs = h.run_for(2.0 - 1e-6)
    assert acks(msgs)[0].result == mavlink.MAV_RESULT_ACCEPTED
    raws = h.of_type("SERVO_OUTPUT_RAW", msgs)
    assert len(raws) == 2 * rate_hz
    stamps = [m.time_usec for m in raws]
    assert all(b - a == 1_000_000 // rate_hz for a, b in zip(stamps, stamps[1:], strict=False))


def test_message_interval_special_values():
    # A 1 kHz loop, so the 80 %-of-loop-rate cap (next test) leaves 1 ms alone.
    h = Harness(SimConfig(loop_rate_hz=1000))
    h.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, SERVO_OUTPUT_RAW, 500)  # < 1 ms → 1 ms
    h.run_for(0.01)
    assert h.ap.snapshot(h.now)["streams"]["SERVO_OUTPUT_RAW"] == 1
    h.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, SERVO_OUTPUT_RAW, 1e9)  # > 60 s → 60 s
    h.run_for(0.01)
    assert h.ap.snapshot(h.now)["streams"]["SERVO_OUTPUT_RAW"] == 60_000
    h.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, SERVO_OUTPUT_RAW, 33_333)  # whole ms
    h.run_for(0.01)
    assert h.ap.snapshot(h.now)["streams"]["SERVO_OUTPUT_RAW"] == 33
    h.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, SERVO_OUTPUT_RAW, -1)  # stop
    h.run_for(0.01)
    assert h.of_type("SERVO_OUTPUT_RAW", h.run_for(1.0)) == []
    h.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, mavlink.MAVLINK_MSG_ID_VFR_HUD, 100_000)
    assert acks(h.run_for(0.01))[0].result == mavlink.MAV_RESULT_FAILED  # not simulated


def test_default_servo_output_rate_from_config():
    h = Harness(SimConfig(servo_output_rate_hz=10))
    assert len(h.of_type("SERVO_OUTPUT_RAW", h.run_for(1.0 - 1e-6))) == 10
    h.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, SERVO_OUTPUT_RAW, 0)  # back to default
    h.run_for(0.001)
    assert h.ap.snapshot(h.now)["streams"]["SERVO_OUTPUT_RAW"] == 100


def test_get_message_interval_and_request_message():
    h = Harness()
    h.command(mavlink.MAV_CMD_GET_MESSAGE_INTERVAL, SERVO_OUTPUT_RAW)
    msgs = h.run_for(0.01)
    assert acks(msgs)[0].result == mavlink.MAV_RESULT_ACCEPTED
    interval = h.of_type("MESSAGE_INTERVAL", msgs)[0]
    assert (interval.message_id, interval.interval_us) == (SERVO_OUTPUT_RAW, -1)
    h.command(mavlink.MAV_CMD_REQUEST_MESSAGE, SERVO_OUTPUT_RAW)
    msgs = h.run_for(0.01)
    assert acks(msgs)[0].result == mavlink.MAV_RESULT_ACCEPTED
    assert len(h.of_type("SERVO_OUTPUT_RAW", msgs)) == 1


# -- parameters -----------------------------------------------------------------------------


def param_values(msgs):
    return [m for m in msgs if m.get_type() == "PARAM_VALUE"]


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


# -- servo motion and the hand ---------------------------------------------------------------


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


# -- PX4 flavour ----------------------------------------------------------------------------


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
    import struct

    assert struct.unpack("<i", struct.pack("<f", value.param_value))[0] == 301


# -- faults ---------------------------------------------------------------------------------


def faulty(**faults) -> Harness:
    return Harness(SimConfig(faults=FaultConfig(**faults)))


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


def test_heartbeat_pause_after_and_for():
    h = faulty(heartbeat_pause_after_s=2.0, heartbeat_pause_for_s=3.0)
    h.run_for(8.5)
    times = [round(t - START_S, 6) for t, m in h.received if m.get_type() == "HEARTBEAT"]
    assert times == [0.0, 1.0, 5.0, 6.0, 7.0, 8.0]
    kinds = [e["fault"] for e in h.events if e["event"] == "fault"]
    assert kinds == ["heartbeat_paused", "heartbeat_resumed"]


def test_heartbeat_paused_and_resumed_on_demand_overrides_the_schedule():
    h = faulty(heartbeat_pause_after_s=100.0)
    h.run_for(2.5)
    h.ap.pause_heartbeat(True, h.now)
    h.run_for(3.0)
    h.ap.pause_heartbeat(False, h.now)
    h.run_for(2.01)
    times = [round(t - START_S, 6) for t, m in h.received if m.get_type() == "HEARTBEAT"]
    # Paused at 2.5 s, resumed at 5.5 s: a heartbeat at once, then every second from there.
    assert times == [0.0, 1.0, 2.0, 5.5, 6.5, 7.5]
    faults = [(e["fault"], round(e["t_s"], 6)) for e in h.events if e["event"] == "fault"]
    assert faults == [("heartbeat_paused", 2.5), ("heartbeat_resumed", 5.5)]


def test_drop_out_everything():
    h = faulty(drop_out=1.0)
    h.command(mavlink.MAV_CMD_DO_SET_SERVO, 9, 1600)
    assert h.run_for(2.0) == []
    assert h.ap.stats["dropped_out"] >= 3 and h.ap.pwm_us[9] == 1600


def test_drop_in_everything():
    h = faulty(drop_in=1.0)
    h.command(mavlink.MAV_CMD_DO_SET_SERVO, 9, 1600)
    assert acks(h.run_for(0.1)) == []
    assert h.ap.pwm_us[9] == 0 and h.ap.stats["dropped_in"] == 1


def _drop_pattern(seed: int) -> list[bool]:
    h = faulty(drop_in=0.5, seed=seed)
    pattern = []
    for _ in range(40):
        before = h.ap.stats["dropped_in"]
        h.command(mavlink.MAV_CMD_NAV_TAKEOFF)
        h.run_for(0.003)
        pattern.append(h.ap.stats["dropped_in"] > before)
    return pattern


def test_drops_are_reproducible_from_the_seed():
    first = _drop_pattern(7)
    assert first == _drop_pattern(7)
    assert first != _drop_pattern(8)
    assert 5 < sum(first) < 35


def test_corrupt_out_makes_every_frame_fail_its_check():
    h = faulty(corrupt_out=1.0)
    h.command(mavlink.MAV_CMD_DO_SET_SERVO, 9, 1600)
    msgs = h.run_for(0.1)
    assert acks(msgs) == [] and h.of_type("HEARTBEAT", msgs) == []
    assert h.ap.stats["corrupted_out"] >= 2


def test_corrupt_in_is_reported_as_bad_frames():
    h = faulty(corrupt_in=1.0)
    for _ in range(10):
        h.command(mavlink.MAV_CMD_NAV_TAKEOFF)
    assert h.ap.stats["corrupted_in"] == 10
    assert h.ap.stats["rx"] < 10 or h.ap.stats["bad_frames"] > 0


def test_latency_and_jitter_delay_replies():
    h = faulty(latency_ms=50, jitter_ms=20, seed=3)
    h.run_for(0.0)
    delays = []
    for _ in range(20):
        h.command(mavlink.MAV_CMD_NAV_TAKEOFF)
        sent = h.now
        h.run_for(0.2)
        ack_times = [t for t, m in h.received if m.get_type() == "COMMAND_ACK"]
        delays.append(ack_times[-1] - sent)
    assert all(0.030 - 1e-9 <= d <= 0.070 + 1e-9 for d in delays)
    assert max(delays) - min(delays) > 0.01


# -- signing --------------------------------------------------------------------------------


def test_signing_required_rejects_unsigned_and_signs_replies():
    config = SimConfig(signing_key=KEY)
    unsigned = Harness(config)
    unsigned.command(mavlink.MAV_CMD_DO_SET_SERVO, 9, 1600)
    assert acks(unsigned.run_for(0.1)) == []
    assert unsigned.ap.stats["rejected_signature"] == 1 and unsigned.ap.pwm_us[9] == 0

    signed = Harness(config, signing_key=KEY)
    signed.command(mavlink.MAV_CMD_DO_SET_SERVO, 9, 1600)
    ack = acks(signed.run_for(0.1))[0]
    assert ack.result == mavlink.MAV_RESULT_ACCEPTED
    assert ack.get_signed() and signed.dec.signing.goodsig_count >= 1

    wrong = Harness(config, signing_key=bytes(32))
    wrong.command(mavlink.MAV_CMD_DO_SET_SERVO, 9, 1600)
    assert acks(wrong.run_for(0.1)) == []


def own_timestamps(h: Harness) -> list[int]:
    """The signing timestamps of our own frames on link 0, in the order sent."""
    own = (h.config.system_id, h.config.component_id)
    return [
        int.from_bytes(f[-12:-6], "little")
        for _, ch, f in h.wire
        if ch == 0 and frame_source(f) == own and f[2] & 0x01
    ]


def test_signing_timestamp_follows_the_clock_and_adopts_newer_signed_incoming_ones():
    """The signing spec's "Timestamp Handling": our timestamp is at least the system clock's
    and moves up to a correctly signed incoming one. Without it, a companion restarted over a
    minute after the simulator booted refused every frame of ours, for ever."""
    h = Harness(SimConfig(signing_key=KEY), signing_key=KEY)
    h.run_for(5.0)
    wall_ticks = int((WALL_S - 1_420_070_400) * 100_000)
    assert own_timestamps(h)[-1] >= wall_ticks + 4 * 100_000  # 4 s of clock, not 4 frames
    # A companion restarted with its clock two minutes ahead of ours.
    ahead = own_timestamps(h)[-1] + 120 * 100_000
    h.gcs.signing.timestamp = ahead
    h.send(h.gcs.heartbeat_encode(mavlink.MAV_TYPE_ONBOARD_CONTROLLER, 8, 0, 0, 4))
    sent_before = len(own_timestamps(h))
    h.run_for(1.5)
    later = own_timestamps(h)[sent_before:]
    assert later and all(t >= ahead for t in later)
    assert later == sorted(later)
    # Such a companion (its own timestamp at `ahead`) takes our frames as a fresh stream.
    restarted = mavlink.MAVLink(None)
    restarted.signing.secret_key = KEY
    restarted.signing.timestamp = ahead
    own = (h.config.system_id, h.config.component_id)
    frames = [f for _, ch, f in h.wire if ch == 0 and frame_source(f) == own][sent_before:]
    assert all(restarted.parse_buffer(f) for f in frames)


# -- event log content ----------------------------------------------------------------------


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


# -- routing between links (ArduPilot's MAVLink_routing) ------------------------------------

COMPANION = (1, 191)


def routing_harness(signing_key: bytes | None = None):
    """Link 0: the companion (1/191); link 1: a ground station (255/190). Both heard once."""
    h = Harness(replace(SimConfig(), signing_key=signing_key), signing_key=signing_key, links=2)
    companion = mavlink.MAVLink(None, *COMPANION)
    if signing_key is not None:
        companion.signing.secret_key = signing_key
        companion.signing.sign_outgoing = True
        companion.signing.timestamp = 1
    hb = companion.heartbeat_encode(
        mavlink.MAV_TYPE_ONBOARD_CONTROLLER, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0
    )
    h.ap.receive(hb.pack(companion), h.now, 0)
    gcs_hb = h.gcs.heartbeat_encode(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0)
    h.ap.receive(gcs_hb.pack(h.gcs), h.now, 1)
    h.run_for(0.01)
    h.forwarded()  # the heartbeats' own forwarding is checked in its own test
    return h, companion


def test_heartbeats_are_forwarded_to_the_other_link_and_routes_learned():
    h = Harness(links=2)
    companion = mavlink.MAVLink(None, *COMPANION)
    frame = companion.heartbeat_encode(
        mavlink.MAV_TYPE_ONBOARD_CONTROLLER, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0
    ).pack(companion)
    h.ap.receive(frame, h.now, 0)
    h.run_for(0.01)
    assert h.forwarded() == []  # nobody heard on another link yet: nowhere to forward
    gcs_frame = h.gcs.heartbeat_encode(6, 8, 0, 0, 0).pack(h.gcs)
    h.ap.receive(gcs_frame, h.now, 1)
    h.ap.receive(frame, h.now, 0)
    h.run_for(0.01)
    assert h.forwarded() == [(0, gcs_frame), (1, frame)]
    assert h.ap.snapshot(h.now)["routes"] == [[1, 191, 0], [255, 190, 1]]


def test_target_for_the_companion_is_forwarded_unchanged_and_not_handled_here():
    h, _ = routing_harness()
    routed = h.ap.stats["routed"]
    msg = h.gcs.command_long_encode(*COMPANION, mavlink.MAV_CMD_USER_1, 0, 1, 2, 3, 4, 5, 6, 0)
    frame = msg.pack(h.gcs)
    h.ap.receive(frame, h.now, 1)
    replies = h.run_for(0.01)
    assert h.forwarded() == [(0, frame)]
    assert h.of_type("COMMAND_ACK", replies) == []  # the companion answers, not the autopilot
    assert h.ap.stats["routed"] == routed + 1


def test_commands_for_the_autopilot_are_handled_and_not_forwarded():
    h, _ = routing_harness()
    h.ap.receive(
        h.gcs.command_long_encode(
            1, 1, mavlink.MAV_CMD_DO_SET_SERVO, 0, 9, 1500, 0, 0, 0, 0, 0
        ).pack(h.gcs),
        h.now,
        1,
    )
    replies = h.run_for(0.01)
    assert h.forwarded() == []
    # The ACK goes back on the ground station's link only, as GCS_Common.cpp sends it on
    # the command's channel: the companion's link (0) does not see it.
    assert [a.result for a in h.on_link(1, "COMMAND_ACK")] == [mavlink.MAV_RESULT_ACCEPTED]
    assert h.of_type("COMMAND_ACK", replies) == []


def test_unknown_targets_go_nowhere_and_replies_go_back_to_their_sender():
    h, companion = routing_harness()
    h.ap.receive(
        h.gcs.command_long_encode(7, 191, mavlink.MAV_CMD_USER_1, 0, *[0] * 7).pack(h.gcs), h.now, 1
    )
    h.run_for(0.01)
    assert h.forwarded() == []
    ack = companion.command_ack_encode(mavlink.MAV_CMD_USER_1, 0, 0, 0, 255, 190)
    frame = ack.pack(companion)
    h.ap.receive(frame, h.now, 0)
    h.run_for(0.01)
    assert h.forwarded() == [(1, frame)]


def test_statustext_is_a_broadcast_and_is_also_handled_here():
    h, companion = routing_harness()
    frame = companion.statustext_encode(4, b"unreachable").pack(companion)
    h.ap.receive(frame, h.now, 0)
    h.run_for(0.01)
    assert h.forwarded() == [(1, frame)]


def test_signed_frames_are_forwarded_with_their_signature_unsigned_ones_dropped():
    h, _ = routing_harness(signing_key=KEY)
    signed = h.gcs.command_long_encode(*COMPANION, mavlink.MAV_CMD_USER_1, 0, *[1] * 7)
    frame = signed.pack(h.gcs)
    assert frame[2] & mavlink.MAVLINK_IFLAG_SIGNED
    h.ap.receive(frame, h.now, 1)
    h.run_for(0.01)
    assert h.forwarded() == [(0, frame)]
    plain = mavlink.MAVLink(None, 255, 190)
    h.ap.receive(
        plain.command_long_encode(*COMPANION, mavlink.MAV_CMD_USER_1, 0, *[1] * 7).pack(plain),
        h.now,
        1,
    )
    forger = mavlink.MAVLink(None, 255, 190)
    forger.signing.secret_key = bytes(32)
    forger.signing.sign_outgoing = True
    forger.signing.timestamp = 10**12
    h.ap.receive(
        forger.command_long_encode(*COMPANION, mavlink.MAV_CMD_USER_1, 0, *[1] * 7).pack(forger),
        h.now,
        1,
    )
    h.run_for(0.01)
    assert h.forwarded() == []
    assert h.ap.stats["rejected_signature"] == 2


def test_a_stream_split_across_reads_on_one_link_survives_frames_on_another():
    h, companion = routing_harness()
    frame = h.gcs.command_long_encode(*COMPANION, mavlink.MAV_CMD_USER_1, 0, *[2] * 7).pack(h.gcs)
    other = companion.statustext_encode(6, b"hello").pack(companion)
    h.ap.receive(frame[:10], h.now, 1)
    h.ap.receive(other, h.now, 0)
    h.ap.receive(frame[10:], h.now, 1)
    h.run_for(0.01)
    assert sorted(h.forwarded()) == [(0, frame), (1, other)]
    assert h.ap.stats["bad_frames"] == 0


# -- ArduPilot's routing rules, as measured on ArduCopter SITL (MAVLink_routing.cpp) --------

USER_1 = mavlink.MAV_CMD_USER_1


def user_1(h: Harness, target=COMPANION) -> bytes:
    return h.gcs.command_long_encode(*target, USER_1, 0, *[1] * 7).pack(h.gcs)


def heartbeat_from(codec) -> bytes:
    return codec.heartbeat_encode(18, 8, 0, 0, 0).pack(codec)


def test_a_command_for_a_component_never_heard_is_answered_unsupported_by_the_autopilot():
    h = Harness(links=2)
    h.ap.receive(heartbeat_from(h.gcs), h.now, 1)  # the ground station on link 1
    h.run_for(0.01)
    h.ap.receive(user_1(h), h.now, 1)  # for 1/191, before any companion was heard
    h.run_for(0.01)
    ack = h.on_link(1, "COMMAND_ACK")[0]
    assert (ack.get_srcSystem(), ack.get_srcComponent()) == (1, 1)
    assert (ack.command, ack.result) == (USER_1, mavlink.MAV_RESULT_UNSUPPORTED)
    assert (ack.target_system, ack.target_component) == (255, 190)
    assert h.forwarded() == []


def test_a_component_that_left_keeps_its_route_and_gets_the_frames_no_ack_comes():
    h, companion = routing_harness()
    h.run_for(60.0)  # the companion's link closed / it stopped talking long ago
    frame = user_1(h)
    h.ap.receive(frame, h.now, 1)
    h.run_for(0.5)
    assert h.forwarded() == [(0, frame)]  # to the dead link, as ArduPilot never forgets
    assert h.on_link(1, "COMMAND_ACK") == []
    assert [1, 191, 0] in h.ap.snapshot(h.now)["routes"]


def test_a_frame_is_never_forwarded_back_out_of_the_link_it_came_in_on():
    # A ground station and the companion behind one link (link 0): the GCS's USER_1 for the
    # companion is not sent back down that link, so the autopilot answers it itself.
    h = Harness(links=2)
    companion = mavlink.MAVLink(None, *COMPANION)
    h.ap.receive(heartbeat_from(companion), h.now, 0)
    h.ap.receive(heartbeat_from(h.gcs), h.now, 0)
    h.run_for(0.01)
    h.forwarded()
    h.ap.receive(user_1(h), h.now, 0)
    replies = h.run_for(0.01)
    assert h.forwarded() == []
    assert [(a.command, a.result) for a in acks(replies)] == [
        (USER_1, mavlink.MAV_RESULT_UNSUPPORTED)
    ]


def test_a_component_heard_on_two_links_gets_frames_on_the_other_one():
    h, companion = routing_harness()
    h.ap.receive(heartbeat_from(companion), h.now, 1)  # now also heard on link 1
    h.run_for(0.01)
    h.forwarded()
    frame = user_1(h)
    h.ap.receive(frame, h.now, 1)
    h.run_for(0.01)
    assert h.forwarded() == [(0, frame)]  # not back onto link 1, and not handled here
    assert h.on_link(1, "COMMAND_ACK") == []


def test_another_system_is_reached_whatever_its_component():
    h = Harness(links=2)
    other = mavlink.MAVLink(None, 7, 1)
    h.ap.receive(heartbeat_from(other), h.now, 1)
    h.run_for(0.01)
    frame = user_1(h, target=(7, 50))  # a component of system 7 never heard
    h.ap.receive(frame, h.now, 0)
    replies = h.run_for(0.01)
    assert (1, frame) in h.forwarded() and acks(replies) == []


def test_our_own_frames_looped_back_teach_no_route_and_radio_status_is_not_forwarded():
    h, companion = routing_harness()
    me = mavlink.MAVLink(None, 1, 1)
    h.ap.receive(heartbeat_from(me), h.now, 1)
    radio = companion.radio_status_encode(200, 190, 100, 10, 10, 0, 0).pack(companion)
    h.ap.receive(radio, h.now, 0)
    h.run_for(0.01)
    assert h.forwarded() == []
    assert [1, 1, 1] not in h.ap.snapshot(h.now)["routes"]


def test_the_routing_table_holds_at_most_20_routes():
    h = Harness(links=2)
    for component in range(1, 31):
        codec = mavlink.MAVLink(None, 9, component)
        h.ap.receive(heartbeat_from(codec), h.now, 1)
    h.run_for(0.01)
    assert len(h.ap.routes) == 20
    assert h.ap.routes[-1] == (9, 20, 1)


# -- streams: the 50 Hz SERVO_OUTPUT_RAW floor, the interval cap, SYSTEM_TIME ----------------


def test_servo_output_raw_never_beats_50_hz_on_ardupilot_and_reports_what_is_stored():
    h = Harness()
    h.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, SERVO_OUTPUT_RAW, 2500)  # 400 Hz
    assert acks(h.run_for(0.001))[0].result == mavlink.MAV_RESULT_ACCEPTED
    raws = h.of_type("SERVO_OUTPUT_RAW", h.run_for(1.0))
    assert len(raws) == 50
    stamps = [m.time_usec for m in raws]
    assert {b - a for a, b in zip(stamps, stamps[1:], strict=False)} == {20_000}
    h.command(mavlink.MAV_CMD_GET_MESSAGE_INTERVAL, SERVO_OUTPUT_RAW)
    interval = h.of_type("MESSAGE_INTERVAL", h.run_for(0.01))[0]
    # The stored interval: 2.5 ms → 2 ms → capped to 3 ms (80 % of the 400 Hz loop).
    assert interval.interval_us == 3000
    assert h.ap.snapshot(h.now)["streams"]["SERVO_OUTPUT_RAW"] == 3


def test_px4_has_no_servo_output_floor_and_the_floor_is_configurable():
    h = Harness(SimConfig(flavour="px4"))
    h.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, SERVO_OUTPUT_RAW, 5000)  # 200 Hz
    assert len(h.of_type("SERVO_OUTPUT_RAW", h.run_for(1.0 - 1e-6))) == 200
    h = Harness(SimConfig(servo_output_min_interval_ms=50))
    h.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, SERVO_OUTPUT_RAW, 5000)
    assert len(h.of_type("SERVO_OUTPUT_RAW", h.run_for(1.0 - 1e-6))) == 20


@pytest.mark.parametrize(("loop_rate_hz", "stored_ms"), [(400, 3), (100, 12), (1000, 1)])
def test_message_intervals_are_capped_at_80_percent_of_the_loop_rate(loop_rate_hz, stored_ms):
    h = Harness(SimConfig(loop_rate_hz=loop_rate_hz))
    h.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, mavlink.MAVLINK_MSG_ID_HEARTBEAT, 1000)
    h.run_for(0.05)
    assert h.ap.snapshot(h.now)["streams"]["HEARTBEAT"] == stored_ms


def test_system_time_is_off_on_ardupilot_until_asked_and_counts_from_boot():
    h = Harness()
    assert h.of_type("SYSTEM_TIME", h.run_for(2.0)) == []  # SR0_EXTRA3 is 0 on Copter
    h.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, SYSTEM_TIME, 200_000)  # 5 Hz
    msgs = h.run_for(1.0 - 1e-6)
    assert acks(msgs)[0].result == mavlink.MAV_RESULT_ACCEPTED
    times = h.of_type("SYSTEM_TIME", msgs)
    assert [m.time_boot_ms for m in times] == [2000, 2200, 2400, 2600, 2800]
    assert times[0].time_unix_usec == round((WALL_S + 2.0) * 1e6)


def test_px4_streams_system_time_at_1_hz_by_default():
    h = Harness(SimConfig(flavour="px4"))
    times = h.of_type("SYSTEM_TIME", h.run_for(2.5))
    assert [m.time_boot_ms for m in times] == [0, 1000, 2000]


# -- reboot -------------------------------------------------------------------------------------


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


# -- the link timing model through the autopilot (no I/O overhead: the model's own figures) --


def _timed_harness(rng_seed: int = 0):
    h = Harness(link_timing=LinkTimingConfig())
    return h, np.random.default_rng(rng_seed)


def _wait_ack(h: Harness, count: int = 1) -> float:
    """Advance until ``count`` more COMMAND_ACKs arrived; the time the last one did."""
    seen = len(h.of_type("COMMAND_ACK"))
    while len(h.of_type("COMMAND_ACK")) < seen + count:
        h.now = h.ap.next_event_s(h.now + 1e-9)
        h._collect()
    return h.now


def test_default_timing_a_lone_command_is_answered_hold_ms_after_it_arrived():
    h, rng = _timed_harness()
    hold_s = h.config.link_timing.hold_ms / 1000
    rtts = []
    for _ in range(40):
        h.run_for(rng.uniform(0.0, 0.02))  # a random phase of the 400 Hz loop
        sent = h.now
        h.command(mavlink.MAV_CMD_DO_SET_SERVO, 9, 1500)
        rtts.append(_wait_ack(h) - sent)
    assert rtts == pytest.approx([hold_s] * 40)
    sent = h.now
    for _ in range(6):  # six in sequence, each waiting for its ACK
        h.command(mavlink.MAV_CMD_DO_SET_SERVO, 9, 1500)
        _wait_ack(h)
    assert h.now - sent == pytest.approx(6 * hold_s)


def test_default_timing_a_burst_is_answered_faster_than_a_lone_command():
    h, rng = _timed_harness(1)
    timing = h.config.link_timing
    loop_s, delay_s = 1 / h.config.loop_rate_hz, timing.output_delay_ms / 1000
    totals = []
    for _ in range(60):
        h.run_for(rng.uniform(0.0, 0.02))
        sent = h.now
        for output in range(9, 15):
            h.command(mavlink.MAV_CMD_DO_SET_SERVO, output, 1500)
        _wait_ack(h, 6)
        totals.append(h.now - sent)
    assert all(delay_s - 1e-9 <= t <= loop_s + delay_s + 1e-9 for t in totals)
    assert float(np.median(totals)) < timing.hold_ms / 1000
    assert all(a.result == mavlink.MAV_RESULT_ACCEPTED for a in h.of_type("COMMAND_ACK"))


def test_a_statustext_still_follows_its_ack_under_the_timing_model():
    h, _ = _timed_harness()
    h.command(mavlink.MAV_CMD_DO_SET_SERVO, 2, 1500)  # a motor: FAILED + STATUSTEXT
    kinds = [m.get_type() for m in h.run_for(0.1) if m.get_type() != "HEARTBEAT"]
    assert kinds == ["COMMAND_ACK", "STATUSTEXT"]


# -- PX4 as measured on SITL (issue 20) ---------------------------------------------------------

ARM_DISARM = mavlink.MAV_CMD_COMPONENT_ARM_DISARM
SET_ACTUATOR = mavlink.MAV_CMD_DO_SET_ACTUATOR
ARM_OUTPUTS = range(9, 15)


def px4(**settings) -> Harness:
    """A PX4 with the firmware's defaults, plus ``settings`` (TOML keys)."""
    return Harness(config_from_mapping({"flavour": "px4", **settings}))


def mapped(**settings) -> Harness:
    """PX4 with the arm's outputs on 301–306 and nothing else set up (disarmed, prearm off)."""
    outputs = {str(o): 301 + i for i, o in enumerate(ARM_OUTPUTS)}
    return px4(outputs=outputs, **settings)


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


def test_px4_disarmed_pwm_is_a_parameter():
    h = mapped(params={"PWM_MAIN_DIS9": 900})
    assert h.ap.output_us[9] == 900 and h.ap.output_us[10] == 1000
    with pytest.raises(SimConfigError, match="NO_SUCH_PARAM"):
        px4(params={"NO_SUCH_PARAM": 1})
    with pytest.raises(SimConfigError, match="COM_PREARM_MODE=3"):
        px4(params={"COM_PREARM_MODE": 3})


def px4_pair(**settings) -> Harness:
    """PX4 with the companion (1/191) on link 0, heard; the ground station on link 1."""
    h = Harness(config_from_mapping({"flavour": "px4", **settings}), links=2)
    companion = mavlink.MAVLink(None, 1, 191)
    h.ap.receive(
        companion.heartbeat_encode(mavlink.MAV_TYPE_ONBOARD_CONTROLLER, 8, 0, 0, 0).pack(companion),
        h.now,
        0,
    )
    h.run_for(0.01)
    h.forwarded()
    return h


def test_px4_forwards_only_between_links_with_forwarding_on_to_a_heard_component():
    user_1 = mavlink.MAV_CMD_USER_1
    both = {"MAV_0_FORWARD": 1, "MAV_1_FORWARD": 1}

    def send_user_1(h, component=191):
        h.send(h.gcs.command_long_encode(1, component, user_1, 0, 0, 0, 0, 0, 0, 0, 0), 1)
        h.run_for(0.01)
        return [channel for channel, _ in h.forwarded()]

    # PX4's defaults: forwarding on for instance 0 (the ground station's), off for the
    # companion's: nothing goes through, and the command is not ours: no answer.
    h = px4_pair()
    assert send_user_1(h) == [] and h.of_type("COMMAND_ACK") == []
    assert [e["to"] for e in h.events if e["event"] == "ignored"] == [[1, 191]]
    h = px4_pair(params=both)
    assert send_user_1(h) == [0]
    assert send_user_1(h, component=192) == []  # never heard on link 0
    h = px4_pair(params={"MAV_0_FORWARD": 0, "MAV_1_FORWARD": 1})
    assert send_user_1(h) == []  # the link it came in on does not forward


def test_px4_udpin_race_a_target_before_the_companion_spoke_is_dropped():
    h = Harness(
        config_from_mapping({"flavour": "px4", "params": {"MAV_0_FORWARD": 1, "MAV_1_FORWARD": 1}}),
        links=2,
    )
    h.send(h.gcs.command_long_encode(1, 191, mavlink.MAV_CMD_USER_1, 0, 0, 0, 0, 0, 0, 0, 0), 1)
    h.run_for(0.01)
    assert h.forwarded() == [] and h.of_type("COMMAND_ACK") == []


def test_px4_timing_commander_cycle_and_main_loop():
    timing = Px4TimingConfig()  # the defaults: commander 10 ms, main loop 1.5 ms
    h = Harness(READY_PX4, px4_timing=timing)
    rng = np.random.default_rng(3)
    rtts = []
    for _ in range(200):
        h.run_for(rng.uniform(0.0, 0.02))
        sent = h.now
        h.command(SET_ACTUATOR, 0.1, 0, 0, 0, 0, 0, 0)
        rtts.append(_wait_ack(h) - sent)
    rtts_ms = np.array(rtts) * 1000
    assert rtts_ms.min() > 0.0 and rtts_ms.max() <= 11.5 + 1e-6
    assert 4.5 <= float(np.median(rtts_ms)) <= 7.0
    # Every frame leaves on a 1.5 ms main-loop pass from boot.
    phases = [((t - START_S) * 1000 / 1.5) % 1 for t, _, _ in h.wire]
    assert all(min(p, 1 - p) < 1e-6 for p in phases)


def test_px4_timing_forwarded_frames_wait_forward_delay_then_a_main_loop_pass():
    timing = Px4TimingConfig(commander_period_ms=10.0, mavlink_loop_ms=1.5, forward_delay_ms=3.5)
    h = Harness(READY_PX4, px4_timing=timing, links=2)
    companion = mavlink.MAVLink(None, 1, 191)
    h.ap.receive(companion.heartbeat_encode(18, 8, 0, 0, 0).pack(companion), h.now, 0)
    h.run_for(0.01)
    h.forwarded()
    h.run_until(START_S + 0.1003)
    sent = h.now
    h.send(h.gcs.command_long_encode(1, 191, mavlink.MAV_CMD_USER_1, 0, 0, 0, 0, 0, 0, 0, 0), 1)
    while not (out := h.forwarded()):
        h.now = h.ap.next_event_s(h.now + 1e-9)
        h._collect()
    assert out[0][0] == 0
    # 100.3 ms after boot + 3.5 ms = 103.8 ms, then the next 1.5 ms pass: 105.0 ms.
    assert (h.now - sent) * 1000 == pytest.approx(4.7)


# -- ArduPilot's safety switch -------------------------------------------------------------------


def ardupilot(**settings) -> Harness:
    return Harness(config_from_mapping({"flavour": "ardupilot", **settings}))


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


# -- the event log tells what each servo physically received -----------------------------------


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


# -- the vehicle: ATTITUDE, LOCAL_POSITION_NED, the hand in the world ------------------------

ATTITUDE = mavlink.MAVLINK_MSG_ID_ATTITUDE
LOCAL_POSITION_NED = mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED


def test_ardupilot_streams_attitude_and_local_position_only_when_asked_at_the_rate_asked():
    h = Harness()
    msgs = h.run_for(1.0)
    assert h.of_type("ATTITUDE", msgs) == h.of_type("LOCAL_POSITION_NED", msgs) == []  # SRn_ 0
    h.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, ATTITUDE, 20_000)  # 50 Hz
    h.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, LOCAL_POSITION_NED, 100_000)  # 10 Hz
    msgs = h.run_for(1.0 - 1e-6)  # handled on the main-loop pass at 1.0 s
    assert [a.result for a in acks(msgs)] == [mavlink.MAV_RESULT_ACCEPTED] * 2
    attitude, position = h.of_type("ATTITUDE", msgs), h.of_type("LOCAL_POSITION_NED", msgs)
    assert (len(attitude), len(position)) == (50, 10)
    stamps = [m.time_boot_ms for m in attitude]
    assert {b - a for a, b in zip(stamps, stamps[1:], strict=False)} == {20}
    assert [m.time_boot_ms for m in position][:3] == [1000, 1100, 1200]


@pytest.mark.parametrize("flavour", ["ardupilot", "px4"])
def test_attitude_and_local_position_carry_the_vehicle_state_at_their_stamp(flavour):
    h = Harness(SimConfig(flavour=flavour, attitude_rate_hz=40, local_position_rate_hz=40))
    msgs = h.run_for(2.0 - 1e-6)
    hover = h.ap.vehicle
    attitude = h.of_type("ATTITUDE", msgs)
    assert len(attitude) == 80  # t = 0, 25 ms, … 1.975 s
    for msg in attitude:
        state = hover.state(msg.time_boot_ms / 1000.0)  # booted at the start: same clock
        expected = (*state.attitude_wrapped(), *state.body_rates())
        got = (msg.roll, msg.pitch, msg.yaw, msg.rollspeed, msg.pitchspeed, msg.yawspeed)
        np.testing.assert_allclose(got, expected, rtol=1e-6, atol=1e-7)  # float32 on the wire
    for msg in h.of_type("LOCAL_POSITION_NED", msgs):
        state = hover.state(msg.time_boot_ms / 1000.0)
        expected = (*state.position_m, *state.velocity_m_s)
        got = (msg.x, msg.y, msg.z, msg.vx, msg.vy, msg.vz)
        np.testing.assert_allclose(got, expected, rtol=1e-6, atol=1e-7)
    assert msgs and abs(attitude[-1].roll) > 1e-4  # it does move (hover is on by default)


def test_px4_streams_attitude_at_100_hz_and_local_position_at_30_hz_by_default():
    h = Harness(SimConfig(flavour="px4"))
    msgs = h.run_for(1.0 - 1e-6)
    assert len(h.of_type("ATTITUDE", msgs)) == 100
    # 30 Hz in whole ms: every 33 ms, so 0 … 990 ms.
    assert len(h.of_type("LOCAL_POSITION_NED", msgs)) == 31
    h.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, ATTITUDE, -1)
    h.run_for(0.01)
    assert h.of_type("ATTITUDE", h.run_for(0.5)) == []
    assert h.ap.snapshot(h.now)["streams"]["ATTITUDE"] == 0


def test_the_vehicle_goes_on_through_a_reboot_and_its_frames_restart_with_time_boot():
    h = Harness(SimConfig(attitude_rate_hz=10))
    h.run_for(1.0)
    h.ap.reboot(h.now, gap_s=0.5)
    msgs = h.run_for(1.0)
    after = h.of_type("ATTITUDE", msgs)
    assert [m.time_boot_ms for m in after][:2] == [0, 100]  # from the boot 1.5 s after start
    state = h.ap.vehicle.state(1.5)
    assert after[0].roll == pytest.approx(state.roll_rad, rel=1e-6)


def test_vehicle_events_log_the_vehicle_and_the_hand_in_the_world():
    h = Harness(SimConfig(vehicle=VehicleConfig(log_rate_hz=20, seed=5)))
    h.command(mavlink.MAV_CMD_DO_SET_SERVO, 10, 1800)
    h.run_for(1.0)
    samples = world_timeline(h.events)
    assert [s.t_s for s in samples][:3] == [0.0, 0.05, 0.1]
    assert len(samples) == 21
    mount = VehicleConfig().mount
    rot_m = rpy_to_matrix(*np.radians(mount.rpy_deg))
    for sample in samples[::4]:
        assert sample.vehicle == h.ap.vehicle.state(sample.vehicle.t_s)
        assert sample.vehicle.t_s == pytest.approx(sample.t_s, abs=1e-6)
        # The hand from the horn positions then (the servos' own model), independently composed.
        positions = {o: s.position_us(START_S + sample.t_s) for o, s in h.ap.servos.items()}
        pose = h.hand.state(positions).pose
        v = sample.vehicle
        rot_v = rpy_to_matrix(v.roll_rad, v.pitch_rad, v.yaw_rad)
        rot_h = rpy_to_matrix(*np.radians([pose.roll_deg, pose.pitch_deg, pose.yaw_deg]))
        hand_base_m = np.array([pose.x_cm, pose.y_cm, pose.z_cm]) / 100.0
        expected = v.position_m + rot_v @ (np.array(mount.xyz_cm) / 100.0 + rot_m @ hand_base_m)
        np.testing.assert_allclose(sample.hand.position_m, expected, atol=1e-6)
        np.testing.assert_allclose(
            rpy_to_matrix(sample.hand.roll_rad, sample.hand.pitch_rad, sample.hand.yaw_rad),
            rot_v @ rot_m @ rot_h,
            atol=1e-6,
        )
    # The servo on output 10 moved meanwhile: the hand in the world moved with it.
    first, last = samples[0].hand, samples[-1].hand
    assert np.linalg.norm(first.position_m - last.position_m) > 0.05
    state = h.ap.snapshot(h.now)
    assert state["vehicle"]["t_s"] == pytest.approx(1.0)
    assert state["hand_ned"]["down_m"] == pytest.approx(last.down_m, abs=0.01)


def test_no_vehicle_events_at_rate_0_and_an_unknown_hand_is_none():
    h = Harness(SimConfig(vehicle=VehicleConfig(log_rate_hz=0)))
    h.run_for(1.0)
    assert world_timeline(h.events) == []
    h = Harness(SimConfig(vehicle=VehicleConfig(log_rate_hz=10)))
    h.command(mavlink.MAV_CMD_DO_SET_SERVO, 9, 2400)  # beyond the joint's PWM range
    h.run_for(1.0)
    assert world_timeline(h.events)[-1].hand is None


def test_vehicle_samples_written_late_keep_the_horn_positions_of_their_time():
    h = Harness(SimConfig(vehicle=VehicleConfig(hover=False, log_rate_hz=100)))
    h.run_for(0.5)
    assert len(world_timeline(h.events)) == 51  # a pass writes every sample due
    # No wake-up for each sample: the next one is written on any pass, at the latest 0.2 s late.
    assert h.ap.next_event_s(h.now) == pytest.approx(h.now + 0.01 + 0.2)
    h.command(mavlink.MAV_CMD_DO_SET_SERVO, 10, 1800)  # handled at the next pass, ≤ 2.5 ms
    h.run_for(1.0)
    ack_t_s = next(e["t_s"] for e in h.events if e["event"] == "ack")
    samples = world_timeline(h.events)
    assert len(samples) == 151  # 0 … 1.5 s, none lost to the batching
    before = [s.hand for s in samples if s.t_s <= ack_t_s]
    after = [s.hand for s in samples if s.t_s > ack_t_s]
    assert len(before) == 51 and all(hand == before[0] for hand in before)
    assert after[0] != before[0]  # the horn started at once
    assert after[-1] != after[0] and after[-1] == after[-2]  # it moved, then stopped
