"""The one MAVLink peer of the tests and benches: its own pymavlink codec on a byte link.

:class:`MavPeer` decodes everything its link receives on a reader thread (so frames are checked
independently of the code under test), keeps each message with its arrival time, and sends what
it is asked to. It plays a ground station or a companion computer towards the simulator
(:meth:`MavPeer.connect` with the simulator's URL, over firmware_interface's transports);
:class:`ScriptedPeer` plays the autopilot towards the daemon's link: it answers COMMAND_LONG
with COMMAND_ACK according to a small script, sends HEARTBEAT / STATUSTEXT / SERVO_OUTPUT_RAW
only when the test asks, and SYS_STATUS (the safety switch off) at the interval asked, as
ArduPilot streams it, once asked for that stream.

The link is anything with ``read(timeout_s) -> bytes``, ``write(bytes)`` and ``close()``: the
autopilot-side endpoints below (a UDP socket, a pty master, an accepted TCP connection) or a
:class:`firmware_interface.transport.Transport`.
"""

from __future__ import annotations

import os
import select
import socket
import threading
import time
from collections.abc import Callable
from typing import Any, Protocol

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from firmware_interface.errors import LinkError
from firmware_interface.transport import open_transport

WAIT_S = 5.0

#: A ground station's ids (MAVProxy's 255/190); the companion computer is 1/191.
GCS_IDS = (255, 190)


class ByteLink(Protocol):
    """What a peer speaks over: an endpoint below or a firmware_interface transport."""

    def read(self, timeout_s: float) -> bytes: ...

    def write(self, data: bytes) -> None: ...

    def close(self) -> None: ...


class UdpEndpoint:
    """The autopilot's side of a UDP link: bound on 127.0.0.1, replies to the last sender."""

    def __init__(self) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.port = self.sock.getsockname()[1]
        self.peer: tuple[str, int] | None = None

    def read(self, timeout_s: float) -> bytes:
        ready, _, _ = select.select([self.sock], [], [], timeout_s)
        if not ready:
            return b""
        data, self.peer = self.sock.recvfrom(65535)
        return data

    def write(self, data: bytes) -> None:
        assert self.peer is not None, "the link has not sent anything yet"
        self.sock.sendto(data, self.peer)

    def close(self) -> None:
        self.sock.close()


class UdpClientEndpoint:
    """The autopilot's side of a ``udpin`` link: it sends first, to ``address`` (ArduPilot's
    ``udpclient``), from its own port on 127.0.0.1; it reads whatever comes back to that port."""

    def __init__(self, address: tuple[str, int]) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.port = self.sock.getsockname()[1]
        self.peer = address

    def read(self, timeout_s: float) -> bytes:
        ready, _, _ = select.select([self.sock], [], [], timeout_s)
        return self.sock.recvfrom(65535)[0] if ready else b""

    def write(self, data: bytes) -> None:
        self.sock.sendto(data, self.peer)

    def close(self) -> None:
        self.sock.close()


class PtyEndpoint:
    """The autopilot's side of a serial link: the master of a pty pair."""

    def __init__(self) -> None:
        self.master, self._slave = os.openpty()
        self.path = os.ttyname(self._slave)

    def read(self, timeout_s: float) -> bytes:
        ready, _, _ = select.select([self.master], [], [], timeout_s)
        if not ready:
            return b""
        try:
            return os.read(self.master, 4096)
        except OSError:  # EIO while nobody holds the slave open (link reopening)
            # Not a synchronisation: the master stays "readable" with EIO until the link
            # reopens its side, so the reader thread backs off instead of spinning a core.
            time.sleep(0.01)
            return b""

    def write(self, data: bytes) -> None:
        os.write(self.master, data)

    def close(self) -> None:
        for fd in (self.master, self._slave):
            try:
                os.close(fd)
            except OSError:
                pass


class TcpEndpoint:
    """The autopilot's side of a TCP link (like SITL on 5760): accepts one connection."""

    def __init__(self, listener: socket.socket) -> None:
        self.listener = listener
        self.sock, _ = listener.accept()

    def read(self, timeout_s: float) -> bytes:
        ready, _, _ = select.select([self.sock], [], [], timeout_s)
        return self.sock.recv(4096) if ready else b""

    def write(self, data: bytes) -> None:
        self.sock.sendall(data)

    def close(self) -> None:
        self.sock.close()


class MavPeer:
    """MAVLink system ``system_id``/``component_id`` speaking over ``link``.

    Every decoded message is kept in :attr:`received` (its arrival time on the monotonic clock
    in :attr:`received_s`); frames that fail to decode in :attr:`bad_frames`. Two ways to wait:
    :meth:`wait_for` re-checks a condition on every frame; :meth:`next_message` consumes the
    received messages in order from a cursor (the ones that do not match are passed over) and
    :meth:`drain` moves the cursor past everything received so far.
    ``signing_key``: sign what it sends (link id 7) and accept only signed frames.
    """

    def __init__(
        self,
        link: ByteLink,
        *,
        system_id: int = GCS_IDS[0],
        component_id: int = GCS_IDS[1],
        signing_key: bytes | None = None,
    ) -> None:
        self.endpoint = link
        self.mav = mavlink.MAVLink(None, system_id, component_id)
        self.mav.robust_parsing = True
        if signing_key is not None:
            self.mav.signing.secret_key = signing_key
            self.mav.signing.link_id = 7
            self.mav.signing.sign_outgoing = True
            self.mav.signing.timestamp = 1
        #: The default bound of the waits (s).
        self.wait_s = WAIT_S
        self.received: list[Any] = []
        self.received_s: list[float] = []
        self.bad_frames: list[Any] = []
        #: What ended the reader thread (the link failed or closed), if it ended by itself.
        self.error: BaseException | None = None
        self._cursor = 0
        self._cond = threading.Condition()
        self._write_lock = threading.Lock()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="mavlink-peer", daemon=True)
        self._thread.start()

    @classmethod
    def connect(cls, url: str, **kwargs: Any) -> MavPeer:
        """A peer on the transport ``url`` opens (``udpout:HOST:PORT``, ``tcp:HOST:PORT``,
        ``DEVICE,BAUD``: the URLs the simulator prints and the daemon's link takes)."""
        return cls(open_transport(url), **kwargs)

    # --- sending ---
    def send(self, msg: Any) -> bytes:
        """Encode ``msg`` with the next sequence number and write it; the frame's bytes."""
        with self._write_lock:
            buf: bytes = msg.pack(self.mav)
            self.mav.seq = (self.mav.seq + 1) % 256
            self.endpoint.write(buf)
            return buf

    def command(self, command: int, *params: float, target: tuple[int, int] = (1, 1)) -> float:
        """Send COMMAND_LONG ``command`` (missing params 0) to ``target``; the monotonic time
        it left."""
        values = list(params) + [0.0] * (7 - len(params))
        sent_s = time.monotonic()
        self.send(self.mav.command_long_encode(*target, command, 0, *values))
        return sent_s

    def send_heartbeat(
        self,
        autopilot: int = mavlink.MAV_AUTOPILOT_INVALID,
        vehicle_type: int = mavlink.MAV_TYPE_GCS,
    ) -> None:
        self.send(
            self.mav.heartbeat_encode(vehicle_type, autopilot, 0, 0, mavlink.MAV_STATE_STANDBY)
        )

    def send_statustext(self, text: str) -> None:
        self.send(self.mav.statustext_encode(mavlink.MAV_SEVERITY_INFO, text.encode()))

    # --- receiving ---
    def _run(self) -> None:
        while not self._stop.is_set():
            timeout_s = self._tick()
            try:
                data = self.endpoint.read(timeout_s)
            except (OSError, ValueError, LinkError) as exc:
                if not self._stop.is_set():
                    self.error = exc
                with self._cond:
                    self._cond.notify_all()
                return
            if not data:
                continue
            arrived_s = time.monotonic()
            for msg in self.mav.parse_buffer(data) or ():
                if isinstance(msg, mavlink.MAVLink_bad_data):
                    with self._cond:
                        self.bad_frames.append(msg)
                        self._cond.notify_all()
                    continue
                with self._cond:
                    self.received.append(msg)
                    self.received_s.append(arrived_s)
                    self._cond.notify_all()
                self._handle(msg)

    def _tick(self) -> float:
        """Called before each read; the longest the read may wait (s)."""
        return 0.05

    def _handle(self, msg: Any) -> None:
        """Called on the reader thread with each message after it is recorded."""

    @property
    def log(self) -> list[tuple[float, Any]]:
        """(arrival time, message) of everything received so far."""
        with self._cond:
            return list(zip(self.received_s, self.received, strict=True))

    def messages(self, msg_type: str) -> list[Any]:
        with self._cond:
            return [m for m in self.received if m.get_type() == msg_type]

    def arrival_s(self, msg: Any) -> float:
        """When ``msg`` (a message this peer received) arrived, on the monotonic clock."""
        with self._cond:
            return next(t for t, m in zip(self.received_s, self.received, strict=True) if m is msg)

    def wait_for(self, predicate: Callable[[], bool], timeout_s: float | None = None) -> bool:
        """Wait until ``predicate()`` holds (re-checked on every received frame), bounded."""
        timeout_s = self.wait_s if timeout_s is None else timeout_s
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while not predicate():
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    return False
                self._cond.wait(min(remaining, 0.05))
            return True

    def wait_for_messages(
        self, msg_type: str, count: int = 1, timeout_s: float | None = None
    ) -> list[Any]:
        timeout_s = self.wait_s if timeout_s is None else timeout_s
        assert self.wait_for(lambda: len(self.messages(msg_type)) >= count, timeout_s), (
            f"peer did not receive {count} {msg_type} within {timeout_s} s"
        )
        return self.messages(msg_type)

    def next_message(self, predicate: Callable[[Any], bool], timeout_s: float | None = None) -> Any:
        """The next message after the cursor matching ``predicate``; the cursor moves past it.
        ``TimeoutError`` if none comes within ``timeout_s``; ``ConnectionError`` if the link
        ended first."""
        timeout_s = self.wait_s if timeout_s is None else timeout_s
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while True:
                while self._cursor < len(self.received):
                    msg = self.received[self._cursor]
                    self._cursor += 1
                    if predicate(msg):
                        return msg
                if self.error is not None:
                    raise ConnectionError(f"the link ended: {self.error!r}") from self.error
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    raise TimeoutError(f"no matching message within {timeout_s} s")
                self._cond.wait(min(remaining, 0.05))

    def ack(self, command: int, timeout_s: float | None = None) -> Any:
        """The next COMMAND_ACK for ``command`` (:meth:`next_message`)."""
        return self.next_message(
            lambda m: m.get_type() == "COMMAND_ACK" and m.command == command, timeout_s
        )

    def drain(self) -> None:
        """Pass over everything received so far: :meth:`next_message` waits for what comes
        next."""
        with self._cond:
            self._cursor = len(self.received)

    def close(self) -> None:
        self._stop.set()
        self._thread.join()
        self.endpoint.close()

    def __enter__(self) -> MavPeer:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()


class ScriptedPeer(MavPeer):
    """Autopilot ``system_id``/``component_id`` (1/1 unless given) speaking over ``endpoint``.

    Script knobs: ``drop_acks`` (ACKs to swallow before answering), ``failed_outputs``
    ({output: STATUSTEXT sent with a FAILED ACK; after it, as ArduPilot does, unless
    ``statustext_after_ack`` is False}), ``ack_result`` (default ACCEPTED),
    ``on_command`` (called with each COMMAND_LONG before answering), ``signing_key``,
    ``answers_heartbeat_requests`` (a HEARTBEAT after the ACK of MAV_CMD_REQUEST_MESSAGE for one,
    as ArduPilot and PX4 do; off unless set, so a test's HEARTBEATs are its own).
    """

    def __init__(
        self,
        endpoint: ByteLink,
        *,
        system_id: int = 1,
        component_id: int = 1,
        signing_key: bytes | None = None,
    ) -> None:
        self.drop_acks = 0
        self.failed_outputs: dict[int, str] = {}
        # ArduPilot queues STATUSTEXT for its main loop, so it goes out after the ACK.
        self.statustext_after_ack = True
        self.statustext_delay_s = 0.02
        #: Asked for SYS_STATUS (as the daemon's core does of ArduPilot), stream it saying the
        #: safety switch is off (None: send none, as an autopilot that never says).
        self.safety_on: bool | None = False
        self._sys_status_interval_s: float | None = None
        self._sys_status_due_s = 0.0
        self.ack_result = mavlink.MAV_RESULT_ACCEPTED
        self.answers_heartbeat_requests = False
        self.on_command: Callable[[Any], object] | None = None
        super().__init__(
            endpoint, system_id=system_id, component_id=component_id, signing_key=signing_key
        )

    def send_heartbeat(
        self,
        autopilot: int = mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA,
        vehicle_type: int = mavlink.MAV_TYPE_QUADROTOR,
    ) -> None:
        super().send_heartbeat(autopilot, vehicle_type)

    def _tick(self) -> float:
        timeout_s = 0.05
        interval_s = self._sys_status_interval_s
        if interval_s is not None:
            now = time.monotonic()
            if now >= self._sys_status_due_s:
                self._sys_status_due_s = max(self._sys_status_due_s + interval_s, now)
                self._send_sys_status()
            timeout_s = min(timeout_s, max(0.0, self._sys_status_due_s - now))
        return timeout_s

    def _handle(self, msg: Any) -> None:
        if msg.get_type() == "COMMAND_LONG":
            self._answer(msg)

    def _answer(self, cmd: Any) -> None:
        if self.on_command is not None:
            self.on_command(cmd)
        if self.drop_acks > 0:
            self.drop_acks -= 1
            return
        result = self.ack_result
        text = None
        if cmd.command == mavlink.MAV_CMD_DO_SET_SERVO and int(cmd.param1) in self.failed_outputs:
            text = self.failed_outputs[int(cmd.param1)]
            result = mavlink.MAV_RESULT_FAILED
        if text is not None and not self.statustext_after_ack:
            self.send_statustext(text)
        self.send(
            self.mav.command_ack_encode(
                cmd.command, result, 0, 0, cmd.get_srcSystem(), cmd.get_srcComponent()
            )
        )
        if (
            cmd.command == mavlink.MAV_CMD_SET_MESSAGE_INTERVAL
            and int(cmd.param1) == mavlink.MAVLINK_MSG_ID_SYS_STATUS
            and self.safety_on is not None
        ):
            self._send_sys_status()
            if cmd.param2 > 0:
                self._sys_status_interval_s = cmd.param2 / 1e6
                self._sys_status_due_s = time.monotonic() + self._sys_status_interval_s
        if (
            self.answers_heartbeat_requests
            and cmd.command == mavlink.MAV_CMD_REQUEST_MESSAGE
            and int(cmd.param1) == mavlink.MAVLINK_MSG_ID_HEARTBEAT
        ):
            self.send_heartbeat()
        if text is not None and self.statustext_after_ack:
            # One main-loop pass later, as ArduPilot's queued STATUSTEXT goes out.
            timer = threading.Timer(self.statustext_delay_s, self.send_statustext, (text,))
            timer.daemon = True
            timer.start()

    def _send_sys_status(self) -> None:
        if self.safety_on is None:
            return
        outputs = mavlink.MAV_SYS_STATUS_SENSOR_MOTOR_OUTPUTS
        enabled = 0 if self.safety_on else outputs
        try:
            self.send(
                self.mav.sys_status_encode(outputs, enabled, outputs, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0)
            )
        except OSError:
            pass  # no peer (yet), or the link closed: the next one may go
