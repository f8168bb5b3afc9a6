"""A pymavlink codec on one socket, for the calibration benches: send, wait for a matching
message (others dropped), drain. ``TcpClient`` (``bench.sim_calibration``) and ``UdpPeer``
(``bench.px4_calibration``) differ only in how they connect and send."""

from __future__ import annotations

import collections
import socket
import time
from collections.abc import Callable
from typing import Any

from pymavlink.dialects.v20 import ardupilotmega as mavlink

WAIT_S = 5.0


class SocketPeer:
    """``sock`` connected (TCP) or bound (UDP) by the subclass; ``_write`` sends one frame."""

    def __init__(self, sock: socket.socket, system: int, component: int) -> None:
        self.sock = sock
        self.mav = mavlink.MAVLink(None, system, component)
        self.dec = mavlink.MAVLink(None)
        self.dec.robust_parsing = True
        self._pending: collections.deque[Any] = collections.deque()

    def _write(self, frame: bytes) -> None:
        raise NotImplementedError

    def send(self, msg: Any) -> None:
        self._write(msg.pack(self.mav))
        self.mav.seq = (self.mav.seq + 1) % 256

    def wait_for(self, predicate: Callable[[Any], bool], timeout_s: float = WAIT_S) -> Any:
        """The next message matching ``predicate`` (others are dropped); raises on timeout."""
        deadline = time.monotonic() + timeout_s
        while True:
            while self._pending:
                msg = self._pending.popleft()
                if predicate(msg):
                    return msg
            left = deadline - time.monotonic()
            if left <= 0:
                raise TimeoutError("no matching message from the simulator")
            self.sock.settimeout(left)
            data = self.sock.recv(65536)
            if not data:
                raise ConnectionError("the simulator closed the connection")
            self._pending.extend(self.dec.parse_buffer(data) or [])

    def drain(self) -> None:
        """Forget whatever has arrived (heartbeats, stream frames)."""
        self._pending.clear()
        self.sock.setblocking(False)
        try:
            while self.sock.recv(65536):
                pass
        except BlockingIOError:
            pass
        finally:
            self.sock.setblocking(True)

    def close(self) -> None:
        self.sock.close()
