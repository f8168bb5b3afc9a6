"""A minimal scripted autopilot for tests: its own pymavlink codec over a raw socket or pty fd.

It decodes everything the link sends (so frames are checked independently of the code under
test), answers COMMAND_LONG with COMMAND_ACK according to a small script, and sends HEARTBEAT /
STATUSTEXT / SERVO_OUTPUT_RAW only when the test asks, and SYS_STATUS (the safety switch off)
at the interval asked, as ArduPilot streams it, once asked for that stream.
"""

from __future__ import annotations

import os
import select
import socket
import threading
import time
from collections.abc import Callable

from pymavlink.dialects.v20 import ardupilotmega as mavlink

WAIT_S = 5.0


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


class ScriptedPeer:
    """Autopilot ``system_id``/``component_id`` speaking over ``endpoint``.

    Script knobs: ``drop_acks`` (ACKs to swallow before answering), ``failed_outputs``
    ({output: STATUSTEXT sent with a FAILED ACK; after it, as ArduPilot does, unless
    ``statustext_after_ack`` is False}), ``ack_result`` (default ACCEPTED),
    ``on_command`` (called with each COMMAND_LONG before answering), ``signing_key``.
    """

    def __init__(
        self,
        endpoint,
        *,
        system_id: int = 1,
        component_id: int = 1,
        signing_key: bytes | None = None,
    ) -> None:
        self.endpoint = endpoint
        self.mav = mavlink.MAVLink(None, system_id, component_id)
        self.mav.robust_parsing = True
        if signing_key is not None:
            for codec_signing in (self.mav.signing,):
                codec_signing.secret_key = signing_key
                codec_signing.link_id = 7
                codec_signing.sign_outgoing = True
                codec_signing.timestamp = 1
        self.received: list = []
        self.bad_frames: list = []
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
        self.on_command: Callable | None = None
        self._cond = threading.Condition()
        self._write_lock = threading.Lock()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="scripted-peer", daemon=True)
        self._thread.start()

    # --- sending ---
    def send(self, msg) -> bytes:
        with self._write_lock:
            buf = msg.pack(self.mav)
            self.mav.seq = (self.mav.seq + 1) % 256
            self.endpoint.write(buf)
            return buf

    def send_heartbeat(
        self, autopilot=mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA, vehicle_type=mavlink.MAV_TYPE_QUADROTOR
    ) -> None:
        self.send(
            self.mav.heartbeat_encode(vehicle_type, autopilot, 0, 0, mavlink.MAV_STATE_STANDBY)
        )

    def send_statustext(self, text: str) -> None:
        self.send(self.mav.statustext_encode(mavlink.MAV_SEVERITY_INFO, text.encode()))

    # --- receiving ---
    def _run(self) -> None:
        while not self._stop.is_set():
            timeout_s = 0.05
            interval_s = self._sys_status_interval_s
            if interval_s is not None:
                now = time.monotonic()
                if now >= self._sys_status_due_s:
                    self._sys_status_due_s = max(self._sys_status_due_s + interval_s, now)
                    self._send_sys_status()
                timeout_s = min(timeout_s, max(0.0, self._sys_status_due_s - now))
            try:
                data = self.endpoint.read(timeout_s)
            except (OSError, ValueError):
                return
            if not data:
                continue
            for msg in self.mav.parse_buffer(data) or ():
                if isinstance(msg, mavlink.MAVLink_bad_data):
                    with self._cond:
                        self.bad_frames.append(msg)
                        self._cond.notify_all()
                    continue
                with self._cond:
                    self.received.append(msg)
                    self._cond.notify_all()
                if msg.get_type() == "COMMAND_LONG":
                    self._answer(msg)

    def _answer(self, cmd) -> None:
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

    def messages(self, msg_type: str) -> list:
        with self._cond:
            return [m for m in self.received if m.get_type() == msg_type]

    def wait_for(self, predicate: Callable[[], bool], timeout_s: float = WAIT_S) -> bool:
        """Wait until ``predicate()`` holds (re-checked on every received frame), bounded."""
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while not predicate():
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    return False
                self._cond.wait(min(remaining, 0.05))
            return True

    def wait_for_messages(self, msg_type: str, count: int = 1, timeout_s: float = WAIT_S) -> list:
        assert self.wait_for(lambda: len(self.messages(msg_type)) >= count, timeout_s), (
            f"peer did not receive {count} {msg_type} within {timeout_s} s"
        )
        return self.messages(msg_type)

    def close(self) -> None:
        self._stop.set()
        self._thread.join()
        self.endpoint.close()
