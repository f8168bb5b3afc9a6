"""The one control-socket client of the tests and benches: a persistent connection.

One request and its reply is :func:`companion.daemon.client.request` (the product's own client,
re-exported here). :class:`ControlConnection` keeps one connection open and speaks the same
framing, through that module's functions (``connect``, ``encode_line``, ``read_line``): it can
send without waiting for the reply, send raw bytes (a malformed or oversized line), and take
replies as they come, blocking (:meth:`ControlConnection.reply`) or not
(:meth:`ControlConnection.try_reply`, or :func:`select` over several connections then
:meth:`ControlConnection.receive`).
"""

from __future__ import annotations

import select
import time
from pathlib import Path
from typing import Any

from companion.daemon.client import connect, encode_line, read_line, request

__all__ = ["ControlConnection", "request"]


class ControlConnection:
    """One connection to the control socket at ``path``; blocking calls are bounded by
    ``timeout_s`` (``TimeoutError``)."""

    def __init__(self, path: str | Path, *, timeout_s: float = 10.0) -> None:
        self.path = path
        self.sock = connect(path, timeout_s=timeout_s)
        self._buffer = b""

    def fileno(self) -> int:
        return self.sock.fileno()

    def send(self, obj: Any) -> float:
        """Send ``obj`` as one request line without waiting for the reply; the monotonic time
        it left."""
        return self.send_raw(encode_line(obj))

    def send_raw(self, data: bytes) -> float:
        """Send ``data`` as it is (no newline added); the monotonic time it left."""
        sent_s = time.monotonic()
        self.sock.sendall(data)
        return sent_s

    def reply(self) -> Any:
        """The next reply, decoded, waiting for it (bounded by the socket's timeout)."""
        reply, self._buffer = read_line(self.sock, self.path, self._buffer)
        return reply

    def request(self, obj: dict[str, Any]) -> dict[str, Any]:
        """Send one request and return its reply."""
        self.send(obj)
        reply = self.reply()
        if not isinstance(reply, dict):
            raise ConnectionError(f"daemon at {self.path} sent a reply that is not a JSON object")
        return reply

    def receive(self) -> None:
        """Receive once (the socket is readable): what came waits for
        :meth:`buffered_reply`. ``ConnectionError`` if the daemon closed the connection."""
        chunk = self.sock.recv(65536)
        if not chunk:
            raise ConnectionError(f"{self.path} closed the connection")
        self._buffer += chunk

    def buffered_reply(self) -> Any | None:
        """A whole reply already received, decoded; None if there is none."""
        if b"\n" not in self._buffer:
            return None
        return self.reply()  # reads nothing more: the line is in the buffer

    def try_reply(self) -> Any | None:
        """A whole reply if one is received or readable now (never waits)."""
        if b"\n" not in self._buffer and select.select([self.sock], [], [], 0)[0]:
            self.receive()
        return self.buffered_reply()

    def close(self) -> None:
        self.sock.close()

    def __enter__(self) -> ControlConnection:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()
