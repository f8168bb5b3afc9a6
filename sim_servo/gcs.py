"""A minimal ground station for tests and benches: sends the daemon's MAVLink target command.

It talks to the simulator's ground-station link (``python -m sim_servo --gcs HOST:PORT``; the
second stdout line ``gcs udpout:HOST:PORT``) over a real UDP socket with pymavlink's codec, as
QGroundControl or MAVProxy would: it sends a HEARTBEAT first (the autopilot routes only to links
it has heard from), then ``COMMAND_LONG MAV_CMD_USER_1`` to the companion's system/component, and
reads the COMMAND_ACK and STATUSTEXT the daemon sends back through the autopilot.

Not part of the daemon: a tool to exercise it end to end.
"""

from __future__ import annotations

import socket
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from sim_servo.autopilot import SIGNING_EPOCH_UNIX_S
from sim_servo.errors import SimIOError

GCS_SYSTEM_ID = 255
GCS_COMPONENT_ID = mavlink.MAV_COMP_ID_MISSIONPLANNER  # 190
COMPANION_COMPONENT_ID = mavlink.MAV_COMP_ID_ONBOARD_COMPUTER  # 191


@dataclass(frozen=True)
class Ack:
    """A COMMAND_ACK for our target command, with the STATUSTEXTs seen while waiting for it."""

    result: int
    elapsed_s: float
    statustexts: tuple[str, ...]

    @property
    def result_name(self) -> str:
        return mavlink.enums["MAV_RESULT"][self.result].name


class GroundStation:
    """A UDP ground station: ``send_target`` a pose, ``wait_ack`` its COMMAND_ACK.

    ``url`` is ``udpout:HOST:PORT`` (what the simulator prints after ``gcs``). ``signing_key``
    (32 bytes) signs every frame, as a ground station sharing the vehicle's key does.
    """

    def __init__(
        self,
        url: str,
        *,
        system_id: int = GCS_SYSTEM_ID,
        component_id: int = GCS_COMPONENT_ID,
        signing_key: bytes | None = None,
        link_id: int = 1,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        scheme, _, address = url.partition(":")
        host, _, port_text = address.rpartition(":")
        if scheme != "udpout" or not host or not port_text.isdigit():
            raise SimIOError(f"ground station url={url!r} must be udpout:HOST:PORT")
        self.clock = clock
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._sock.connect((host, int(port_text)))
        self.mav = mavlink.MAVLink(None, srcSystem=system_id, srcComponent=component_id)
        self._dec = mavlink.MAVLink(None)
        self._dec.robust_parsing = True
        if signing_key is not None:
            for codec in (self.mav, self._dec):
                codec.signing.secret_key = signing_key
                codec.signing.link_id = link_id
                codec.signing.timestamp = int((time.time() - SIGNING_EPOCH_UNIX_S) * 100_000)
            self.mav.signing.sign_outgoing = True
        self.received: list[Any] = []

    def close(self) -> None:
        self._sock.close()

    def __enter__(self) -> GroundStation:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()

    def send(self, msg: Any) -> bytes:
        """Encode (and sign) ``msg`` and send it; the frame's bytes. A signed frame's timestamp
        is never behind the clock (pymavlink only counts up by one per frame), as the spec
        asks of a system that knows the time: a receiver refuses a stream signed before its
        own start."""
        if self.mav.signing.sign_outgoing:
            now = int((time.time() - SIGNING_EPOCH_UNIX_S) * 100_000)
            self.mav.signing.timestamp = max(self.mav.signing.timestamp, now)
        frame = msg.pack(self.mav)
        self.mav.seq = (self.mav.seq + 1) % 256
        self._sock.send(frame)
        return frame

    def send_raw(self, frame: bytes) -> None:
        self._sock.send(frame)

    def heartbeat(self) -> None:
        self.send(
            self.mav.heartbeat_encode(
                mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, mavlink.MAV_STATE_ACTIVE
            )
        )

    def target_message(
        self,
        pose: Sequence[float],
        *,
        system_id: int = 1,
        component_id: int = COMPANION_COMPONENT_ID,
        mode: int = 0,
    ) -> Any:
        """COMMAND_LONG MAV_CMD_USER_1 with params 1–6 = x_cm, y_cm, z_cm, roll, pitch, yaw and
        param7 = the target mode (0 pose, 1 position, 2 position + pointing)."""
        x_cm, y_cm, z_cm, roll_deg, pitch_deg, yaw_deg = pose
        return self.mav.command_long_encode(
            system_id,
            component_id,
            mavlink.MAV_CMD_USER_1,
            0,
            x_cm,
            y_cm,
            z_cm,
            roll_deg,
            pitch_deg,
            yaw_deg,
            mode,
        )

    def send_target(self, pose: Sequence[float], **ids: int) -> float:
        """Send a target (``ids``: system_id, component_id, mode); the time it left."""
        msg = self.target_message(pose, **ids)
        sent_s = self.clock()
        self.send(msg)
        return sent_s

    def receive(self, timeout_s: float) -> list[Any]:
        """The messages in the next datagram (empty on timeout); also kept in ``received``."""
        self._sock.settimeout(max(timeout_s, 1e-6))
        try:
            data = self._sock.recv(65535)
        except (TimeoutError, ConnectionRefusedError):
            return []
        messages = self._dec.parse_buffer(data) or []
        self.received.extend(messages)
        return messages

    def wait_for(self, predicate: Callable[[Any], bool], timeout_s: float) -> Any | None:
        """The first message (from now on) matching ``predicate``, or None after ``timeout_s``."""
        deadline = self.clock() + timeout_s
        while (left := deadline - self.clock()) > 0:
            for msg in self.receive(left):
                if predicate(msg):
                    return msg
        return None

    def wait_ack(self, timeout_s: float, *, since_s: float | None = None) -> Ack | None:
        """The next COMMAND_ACK for MAV_CMD_USER_1, or None after ``timeout_s``."""
        start_s = self.clock() if since_s is None else since_s
        texts: list[str] = []

        def is_ack(msg: Any) -> bool:
            if msg.get_type() == "STATUSTEXT":
                texts.append(msg.text)
            return msg.get_type() == "COMMAND_ACK" and msg.command == mavlink.MAV_CMD_USER_1

        ack = self.wait_for(is_ack, timeout_s)
        if ack is None:
            return None
        # The daemon sends its STATUSTEXT just before the ACK; both may share a datagram batch.
        return Ack(ack.result, self.clock() - start_s, tuple(texts))

    def connect(self, timeout_s: float) -> bool:
        """Heartbeat until the companion's HEARTBEAT comes back through the autopilot."""
        deadline = self.clock() + timeout_s
        while self.clock() < deadline:
            self.heartbeat()
            msg = self.wait_for(
                lambda m: (
                    m.get_type() == "HEARTBEAT" and m.get_srcComponent() == COMPANION_COMPONENT_ID
                ),
                min(0.5, max(0.0, deadline - self.clock())),
            )
            if msg is not None:
                return True
        return False
