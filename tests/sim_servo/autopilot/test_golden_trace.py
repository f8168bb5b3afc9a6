"""Golden traces: the frames :meth:`SimAutopilot.poll` returns, with their times and links, and
the events it logs, for scripted sessions of both flavours under the default link timing models.

The benches compare the simulator with measurements of the real firmware, so when a frame leaves
(the link timing models, the main-loop pass, the commander cycle, the order of frames) must not
change by accident: these traces are compared bit for bit (times as exact floats, frames as
bytes). ``python -m tests.sim_servo.autopilot.test_golden_trace`` rewrites the file after a
change of behaviour that is meant.
"""

from __future__ import annotations

import json
import math
import struct
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from sim_servo.autopilot import SimAutopilot
from sim_servo.config import DEFAULT_ARM_OUTPUTS, SimConfig, config_from_mapping, ready_setup
from sim_servo.hand import HandModel
from sim_servo.lua_bridge import MAV_CMD_USER_2

GOLDEN = Path(__file__).with_name("golden_traces.json")
START_S = 100.0
WALL_S = 1.7e9
KEY = bytes(range(32))

Step = tuple[float, Callable[["Session"], None]]


class Session:
    """An autopilot on a fake clock with a companion (1/191, link 0) and a ground station
    (255/190, link 1); every frame polled and every event logged, in order."""

    def __init__(self, config: SimConfig) -> None:
        self.events: list[dict[str, Any]] = []
        self.ap = SimAutopilot(
            config,
            now_s=START_S,
            emit=self.events.append,
            hand=HandModel.from_config(config.arm),
            wall_clock=lambda: WALL_S,
            links=2,
        )
        self.now = START_S
        self.frames: list[list[Any]] = []
        self.gcs = mavlink.MAVLink(None, 255, 190)
        self.companion = mavlink.MAVLink(None, 1, 191)
        if config.signing_key is not None:
            for codec in (self.gcs, self.companion):
                codec.signing.secret_key = config.signing_key
                codec.signing.sign_outgoing = True
                codec.signing.timestamp = 1

    def gcs_send(self, msg: Any) -> None:
        self.ap.receive(msg.pack(self.gcs), self.now, 1)

    def companion_send(self, msg: Any) -> None:
        self.ap.receive(msg.pack(self.companion), self.now, 0)

    def command(self, command: int, *params: float, target=(1, 1), int_frame=False) -> None:
        values = list(params) + [0.0] * (7 - len(params))
        if int_frame:
            msg = self.companion.command_int_encode(
                *target, 0, command, 0, 0, *values[:4], int(values[4]), int(values[5]), values[6]
            )
        else:
            msg = self.companion.command_long_encode(*target, command, 0, *values)
        self.companion_send(msg)

    def _poll(self) -> None:
        for channel, frame in self.ap.poll(self.now):
            self.frames.append([self.now, channel, frame.hex()])

    def run(self, steps: list[Step], end_s: float) -> None:
        pending = sorted(((START_S + t, i, act) for i, (t, act) in enumerate(steps)))
        self._poll()
        while True:
            due = self.ap.next_event_s(self.now)
            if pending and pending[0][0] <= due:
                at, _, act = pending.pop(0)
                self.now = max(self.now, at)
                act(self)
                self._poll()
                continue
            if due > START_S + end_s:
                break
            self.now = max(due, self.now + 1e-9) if due <= self.now else due
            self._poll()

    def trace(self) -> dict[str, Any]:
        return {"frames": self.frames, "events": _jsonable(self.events)}


def _jsonable(value: Any) -> Any:
    if isinstance(value, float) and not math.isfinite(value):
        return str(value)
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_jsonable(v) for v in value]
    return value


def _heartbeats(s: Session) -> None:
    s.companion_send(s.companion.heartbeat_encode(mavlink.MAV_TYPE_ONBOARD_CONTROLLER, 8, 0, 0, 0))
    s.gcs_send(s.gcs.heartbeat_encode(mavlink.MAV_TYPE_GCS, 8, 0, 0, 0))


def _interval(msg_id: int, interval_us: float) -> Callable[[Session], None]:
    return lambda s: s.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, msg_id, interval_us)


def _params(s: Session, name: str, raw: float, param_type: int) -> None:
    s.gcs_send(s.gcs.param_set_encode(1, 1, name.encode(), raw, param_type))
    s.gcs_send(s.gcs.param_request_read_encode(1, 1, name.encode(), -1))
    s.gcs_send(s.gcs.param_request_read_encode(1, 1, b"", 3))


def _servo_burst(s: Session) -> None:
    for i, output in enumerate(range(9, 15)):
        s.command(mavlink.MAV_CMD_DO_SET_SERVO, output, 1100 + 100 * i)
    s.command(mavlink.MAV_CMD_DO_SET_SERVO, 2, 1500)  # a motor: STATUSTEXT and FAILED
    s.command(mavlink.MAV_CMD_DO_SET_SERVO, 12, 1900, int_frame=True)


def _to_companion(s: Session) -> None:
    s.gcs_send(s.gcs.command_long_encode(1, 191, 31010, 0, 1, 0, 0, 0, 0, 0, 0))


def ardupilot_steps() -> list[Step]:
    srv, st = mavlink.MAVLINK_MSG_ID_SERVO_OUTPUT_RAW, mavlink.MAVLINK_MSG_ID_SYSTEM_TIME
    int16 = mavlink.MAV_PARAM_TYPE_INT16
    return [
        (0.01, _heartbeats),
        (0.2, _interval(srv, 20_000)),
        (0.2005, _interval(st, 500_000)),
        (0.25, _interval(mavlink.MAVLINK_MSG_ID_ATTITUDE, 100_000)),
        (0.25, _interval(mavlink.MAVLINK_MSG_ID_SYS_STATUS, 250_000)),
        (0.3, _servo_burst),
        (0.5, lambda s: s.command(mavlink.MAV_CMD_GET_MESSAGE_INTERVAL, srv)),
        (0.5, lambda s: s.command(mavlink.MAV_CMD_REQUEST_MESSAGE, st)),
        (0.6, lambda s: _params(s, "SERVO2_FUNCTION", 0.0, int16)),
        (0.62, lambda s: s.command(mavlink.MAV_CMD_DO_SET_SERVO, 2, 1234)),
        (0.7, _to_companion),
        (0.8, lambda s: s.gcs_send(s.gcs.param_request_list_encode(1, 1))),
        (1.1, lambda s: s.ap.set_safety(True, s.now)),
        (1.15, lambda s: s.command(mavlink.MAV_CMD_DO_SET_SERVO, 10, 1700)),
        (1.3, lambda s: s.ap.set_safety(False, s.now)),
        (1.5, lambda s: s.ap.pause_heartbeat(True, s.now)),
        (1.8, lambda s: s.ap.pause_heartbeat(False, s.now)),
        (2.0, lambda s: s.ap.reboot(s.now)),
        (2.1, _servo_burst),  # deaf
        (2.5, _heartbeats),
        (2.5, _servo_burst),
        (2.6, lambda s: s.command(mavlink.MAV_CMD_DO_SET_ACTUATOR, 0.5)),
    ]


def px4_steps() -> list[Step]:
    srv = mavlink.MAVLINK_MSG_ID_SERVO_OUTPUT_RAW
    int32 = mavlink.MAV_PARAM_TYPE_INT32

    def bytewise(value: int) -> float:
        return float(struct.unpack("<f", struct.pack("<i", value))[0])

    arm = mavlink.MAV_CMD_COMPONENT_ARM_DISARM
    act = mavlink.MAV_CMD_DO_SET_ACTUATOR
    return [
        (0.01, _heartbeats),
        (0.2, _interval(srv, 20_000)),
        (0.2, _interval(mavlink.MAVLINK_MSG_ID_ACTUATOR_OUTPUT_STATUS, 50_000)),
        (0.3, lambda s: s.command(act, 0.1, -0.2, 0.3, math.nan, 1.5, -1.0, 0)),
        (0.4, lambda s: s.command(arm, 1)),
        (0.4035, lambda s: s.command(act, 0.2, 0.2, 0.2, 0.2, 0.2, 0.2, 0)),
        (0.5, lambda s: s.command(mavlink.MAV_CMD_DO_SET_SERVO, 9, 1500)),
        (0.55, lambda s: _params(s, "PWM_MAIN_DIS9", bytewise(950), int32)),
        (0.6, _to_companion),
        (0.65, lambda s: s.command(arm, 0, 21196)),
        (0.7, lambda s: s.command(arm, 7)),
        (0.8, lambda s: s.gcs_send(s.gcs.param_request_list_encode(1, 1))),
        (0.9, lambda s: s.command(mavlink.MAV_CMD_GET_MESSAGE_INTERVAL, srv)),
        (0.95, lambda s: s.command(31010, 1, target=(1, 191))),
        (1.0, lambda s: s.command(arm, 1)),
        (1.2, lambda s: s.ap.reboot(s.now)),
        (1.7, _heartbeats),
        (1.75, lambda s: s.ap.set_armed(True, s.now)),
        (1.8, lambda s: s.command(act, -0.5, 0.5, 0, 0, 0, 0, 0)),
    ]


def scenarios() -> dict[str, Callable[[], dict[str, Any]]]:
    ardupilot = replace(SimConfig(), servo_output_rate_hz=0)
    ready_px4 = config_from_mapping({"flavour": "px4", **ready_setup("px4", DEFAULT_ARM_OUTPUTS)})
    prearm_px4 = config_from_mapping(
        {
            "flavour": "px4",
            "params": {"COM_PREARM_MODE": 2},
            "attitude_rate_hz": 0.0,
            "local_position_rate_hz": 0.0,
        }
    )

    def run(config: SimConfig, steps: list[Step], end_s: float) -> dict[str, Any]:
        # A few vehicle samples a second keep the file small and still interleave with commands.
        session = Session(replace(config, vehicle=replace(config.vehicle, log_rate_hz=7.0)))
        session.run(steps, end_s)
        return session.trace()

    def lua() -> dict[str, Any]:
        steps: list[Step] = [
            (0.1, lambda s: s.command(MAV_CMD_USER_2, 1100, 1200, 1300, 1400, 1500, 1600, 9)),
            (0.1, lambda s: s.command(MAV_CMD_USER_2, 1500, 1500, 1500, 1500, 1500, 1500, 1)),
            (0.3, lambda s: s.command(MAV_CMD_USER_2, 2001, math.nan, 0, 0, 0, 0, 9)),
        ]
        return run(replace(SimConfig(), lua_script=True), steps, 0.6)

    return {
        "ardupilot": lambda: run(ardupilot, ardupilot_steps(), 3.2),
        "ardupilot_signed": lambda: run(
            replace(ardupilot, signing_key=KEY), ardupilot_steps()[:8], 0.8
        ),
        "ardupilot_lua": lua,
        "px4_ready": lambda: run(ready_px4, px4_steps(), 2.2),
        "px4_prearm": lambda: run(prearm_px4, px4_steps()[:4], 5.3),
    }


def test_poll_and_events_match_the_golden_traces():
    golden = json.loads(GOLDEN.read_text())
    for name, make in scenarios().items():
        got = json.loads(json.dumps(make()))
        want = golden[name]
        for key in ("frames", "events"):
            for i, (g, w) in enumerate(zip(got[key], want[key], strict=False)):
                assert g == w, f"{name}: {key}[{i}] differs"
            assert len(got[key]) == len(want[key]), f"{name}: {key} count"


if __name__ == "__main__":
    GOLDEN.write_text(json.dumps({n: m() for n, m in scenarios().items()}, indent=None) + "\n")
