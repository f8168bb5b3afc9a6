"""The state query on a local Unix stream socket.

Protocol: the client sends one request per line and gets one JSON object per line back, on the
same connection, as many times as it likes. A request is a bare word or a JSON object with a
``"query"`` key:

* ``state``  – outputs (function, PWM, horn position, target, moving), ``settled``, the hand
  (joint angles, pose in cm / degrees, or why they are unknown), streams, counters;
* ``events`` – the events kept in memory (``{"events": [...]}``);
* ``ping``   – ``{"ok": true}``;
* ``pause_heartbeat`` / ``resume_heartbeat`` – stop or restart the autopilot's HEARTBEAT now
  (a link loss on demand, for tests; ``--heartbeat-pause-after`` schedules one instead);
  ``{"ok": true}``;
* ``reboot`` – reboot the autopilot now (silent for ``--reboot-gap`` seconds, then back with
  time_boot from 0; ``--reboot-after`` schedules one instead); ``{"ok": true}``, or
  ``{"ok": false}`` while it is already rebooting.
* ``arm`` / ``disarm`` / ``kill`` – PX4: arm, disarm, or kill (a forced disarm) now, as
  MAV_CMD_COMPONENT_ARM_DISARM would; ``{"ok": true}``, or ``{"ok": false}`` on ArduPilot or
  while rebooting;
* ``safety_on`` / ``safety_off`` – ArduPilot: engage or disengage the safety switch now;
  ``{"ok": true}``, or ``{"ok": false}`` on PX4 or while rebooting;
* ``hangup`` – close the port now (with ``--hangup-for``, a new pty comes back that much later;
  ``--hangup-after`` schedules one instead); ``{"ok": true}``, or ``{"ok": false}`` while the
  port is away;
* ``forge`` – a test fault, as a JSON object only: frames forged as if from the autopilot on
  the companion's link, e.g. ``{"query": "forge", "msg": "SYS_STATUS", "safety_on": false,
  "for_s": 1.0}`` (see :mod:`sim_servo.autopilot.forge` for the messages and their fields);
  ``{"ok": true}``, or ``{"error": "..."}`` naming what it cannot carry out.

A JSON object's other keys are the request's arguments (only ``forge`` takes any).

An unknown request gets ``{"error": "..."}`` naming the valid ones.
"""

from __future__ import annotations

import json
import os
import socket
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from sim_servo.errors import SimIOError

#: Answers a request: its name and its arguments (a JSON object's other keys; empty for a bare
#: word).
Responder = Callable[[str, dict[str, Any]], dict[str, Any]]
QUERIES = (
    "state",
    "events",
    "ping",
    "pause_heartbeat",
    "resume_heartbeat",
    "reboot",
    "hangup",
    "arm",
    "disarm",
    "kill",
    "safety_on",
    "safety_off",
    "forge",
)
_MAX_LINE = 65536


class QueryServer:
    """Non-blocking Unix-socket server; the I/O loop calls :meth:`handle` when a fd is ready."""

    def __init__(self, path: str | Path, respond: Responder) -> None:
        self.path = str(path)
        self._respond = respond
        if os.path.exists(self.path):
            os.unlink(self.path)  # a stale socket from an earlier run
        self._listener = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        try:
            self._listener.bind(self.path)
            self._listener.listen(8)
        except OSError as exc:
            self._listener.close()
            raise SimIOError(f"cannot listen on query socket {self.path!r}: {exc}") from exc
        self._listener.setblocking(False)
        self._clients: dict[int, tuple[socket.socket, bytearray]] = {}

    def fds(self) -> list[int]:
        return [self._listener.fileno(), *self._clients]

    def handle(self, fd: int) -> None:
        if fd == self._listener.fileno():
            try:
                client, _ = self._listener.accept()
            except (BlockingIOError, InterruptedError):
                return
            client.setblocking(False)
            self._clients[client.fileno()] = (client, bytearray())
            return
        client, buffer = self._clients[fd]
        try:
            data = client.recv(4096)
        except (BlockingIOError, InterruptedError):
            return
        except OSError:
            data = b""
        if not data or len(buffer) > _MAX_LINE:
            self._drop(fd)
            return
        buffer += data
        while b"\n" in buffer:
            line, _, rest = bytes(buffer).partition(b"\n")
            buffer[:] = rest
            reply = self._answer(line.decode("utf-8", "replace").strip())
            try:
                client.setblocking(True)
                client.sendall((json.dumps(reply, default=str) + "\n").encode())
                client.setblocking(False)
            except OSError:
                self._drop(fd)
                return

    def _answer(self, line: str) -> dict[str, Any]:
        request, args = line, {}
        if line.startswith("{"):
            try:
                args = dict(json.loads(line))
            except (ValueError, TypeError):
                return {"error": f"request {line!r} is not a JSON object"}
            request = str(args.pop("query", ""))
        if request not in QUERIES:
            return {"error": f"unknown query {request!r}; valid: {list(QUERIES)}"}
        return self._respond(request, args)

    def _drop(self, fd: int) -> None:
        client, _ = self._clients.pop(fd)
        client.close()

    def close(self) -> None:
        for fd in list(self._clients):
            self._drop(fd)
        self._listener.close()
        try:
            os.unlink(self.path)
        except OSError:
            pass


def query(path: str | Path, request: str = "state", timeout_s: float = 5.0) -> dict[str, Any]:
    """Ask a running simulator one question over its query socket."""
    deadline = time.monotonic() + timeout_s
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as sock:
        sock.settimeout(timeout_s)
        try:
            sock.connect(str(path))
            sock.sendall(request.encode() + b"\n")
            reply = bytearray()
            while not reply.endswith(b"\n"):
                if time.monotonic() > deadline:
                    raise SimIOError(f"no reply to {request!r} within timeout_s={timeout_s}")
                chunk = sock.recv(65536)
                if not chunk:
                    raise SimIOError(f"query socket {str(path)!r} closed before replying")
                reply += chunk
        except OSError as exc:
            raise SimIOError(f"query {request!r} on {str(path)!r} failed: {exc}") from exc
    return json.loads(reply)
