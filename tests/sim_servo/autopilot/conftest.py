"""The autopilot on a fake clock, shared by the tests of its parts.

A plain pymavlink codec plays the daemon; nothing here sleeps. ``Harness.run_until`` jumps from
one scheduled event of the autopilot to the next, so stream rates and delays are exact. The
harness turns the link timing model off (frames leave on the main-loop pass that made them)
unless a test asks for it; the model itself is tested in ``tests/sim_servo/test_linktiming.py``
and through the autopilot in ``test_wire.py``.
"""

from __future__ import annotations

from dataclasses import replace

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from sim_servo.autopilot import SimAutopilot
from sim_servo.autopilot.flavour import flavour_for
from sim_servo.autopilot.state import AutopilotState
from sim_servo.config import (
    DEFAULT_ARM_OUTPUTS,
    FaultConfig,
    LinkTimingConfig,
    Px4TimingConfig,
    SimConfig,
    config_from_mapping,
    ready_setup,
)
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


def param_values(msgs):
    return [m for m in msgs if m.get_type() == "PARAM_VALUE"]


def faulty(**faults) -> Harness:
    return Harness(SimConfig(faults=FaultConfig(**faults)))


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


def wait_ack(h: Harness, count: int = 1) -> float:
    """Advance until ``count`` more COMMAND_ACKs arrived; the time the last one did."""
    seen = len(h.of_type("COMMAND_ACK"))
    while len(h.of_type("COMMAND_ACK")) < seen + count:
        h.now = h.ap.next_event_s(h.now + 1e-9)
        h._collect()
    return h.now


SET_ACTUATOR = mavlink.MAV_CMD_DO_SET_ACTUATOR
ARM_OUTPUTS = range(9, 15)


def px4(**settings) -> Harness:
    """A PX4 with the firmware's defaults, plus ``settings`` (TOML keys)."""
    return Harness(config_from_mapping({"flavour": "px4", **settings}))


def mapped(**settings) -> Harness:
    """PX4 with the arm's outputs on 301–306 and nothing else set up (disarmed, prearm off)."""
    outputs = {str(o): 301 + i for i, o in enumerate(ARM_OUTPUTS)}
    return px4(outputs=outputs, **settings)


def ardupilot(**settings) -> Harness:
    return Harness(config_from_mapping({"flavour": "ardupilot", **settings}))


def part_state(config: SimConfig | None = None, events: list | None = None) -> AutopilotState:
    """The shared state a part is built on, for testing the part alone (events into
    ``events``)."""
    config = config or SimConfig()
    return AutopilotState(
        config,
        flavour_for(config),
        now_s=START_S,
        emit=events.append if events is not None else None,
        wall_clock=lambda: WALL_S,
    )
