"""The daemon's local control socket: a Unix stream socket speaking JSON lines.

For onboard software (and the ``armbridge goto`` / ``status`` clients). One JSON object per
line in, one per line out, in order; a connection may send many requests.

Requests::

    {"cmd": "goto", "pose": [x_cm, y_cm, z_cm, roll_deg, pitch_deg, yaw_deg]}
    {"cmd": "trajectory", "points": [[t_s, x_cm, y_cm, z_cm, roll_deg, pitch_deg, yaw_deg], ...]}
    {"cmd": "status"}
    {"cmd": "park"}
    {"cmd": "stop"}

Replies: ``{"ok": true, "outcome": "accepted", "message": ..., "solve": {...}}``. ``ok`` is
false for any outcome other than accepted, and for a malformed request:
``{"ok": false, "error": "..."}``. ``status`` answers ``{"ok": true, "status": {...}}``.
Trajectory times are seconds from receipt; the daemon solves each point when it falls due.
"""

from __future__ import annotations

import json
import logging
import math
import os
import socket
import threading
import time
from pathlib import Path
from typing import Any

from companion.daemon.client import request  # the client half, re-exported
from companion.daemon.requests import Reply
from companion.daemon.service import ArmDaemon, Outcome

log = logging.getLogger("armbridge.control")

__all__ = ["ControlServer", "request"]

MAX_LINE = 1 << 20  # a request line longer than this is refused
_SUN_PATH_MAX = 107  # bytes of a Unix socket path (sockaddr_un.sun_path, less its NUL)


class ControlServer:
    """Serves ``daemon`` on the Unix socket ``path`` (a stale socket file is replaced).

    ``path`` appears only once the socket listens: a client that sees the file can connect.
    """

    def __init__(self, path: str | Path, daemon: ArmDaemon, *, reply_timeout_s: float = 5.0):
        self.path = str(path)
        self.daemon = daemon
        self.reply_timeout_s = reply_timeout_s
        self._stop = threading.Event()
        self._sock = _listening_socket(self.path)
        self._sock.settimeout(0.2)
        self._clients: set[socket.socket] = set()
        self._threads: set[threading.Thread] = set()
        self._connections = 0
        self._thread = threading.Thread(
            target=self._accept_loop, name="armbridge-control-socket", daemon=True
        )
        self._thread.start()

    def close(self, *, flush_s: float = 0.2) -> None:
        """Stop accepting, give the connections up to ``flush_s`` to write the answers they
        hold (the daemon answered everything before), then close them."""
        self._stop.set()
        self._sock.close()  # no new connection from here
        deadline = time.monotonic() + flush_s
        for thread in list(self._threads):
            if thread.ident is not None:  # started
                thread.join(timeout=max(0.0, deadline - time.monotonic()))
        self._thread.join(timeout=max(0.0, deadline - time.monotonic()))
        for client in list(self._clients):
            client.close()
        if os.path.exists(self.path):
            os.unlink(self.path)

    def _accept_loop(self) -> None:
        while not self._stop.is_set():
            try:
                conn, _ = self._sock.accept()
            except TimeoutError:
                continue
            except OSError:
                return
            self._clients.add(conn)
            self._connections += 1
            thread = threading.Thread(
                target=self._serve,
                args=(conn, self._connections),
                daemon=True,
                name="armbridge-control-client",
            )
            self._threads.add(thread)
            thread.start()

    def _serve(self, conn: socket.socket, number: int = 0) -> None:
        buffer = b""
        try:
            conn.settimeout(0.2)  # inside: close() may have closed it already
            while not self._stop.is_set():
                try:
                    chunk = conn.recv(65536)
                except TimeoutError:
                    continue
                if not chunk:
                    return
                buffer += chunk
                if len(buffer) > MAX_LINE and b"\n" not in buffer:
                    conn.sendall(_line({"ok": False, "error": "request line too long"}))
                    return
                while b"\n" in buffer:
                    line, buffer = buffer.split(b"\n", 1)
                    if line.strip():
                        conn.sendall(_line(self.handle_line(line, source=("socket", number))))
        except OSError as exc:
            log.info("control client went away: %s", exc)
        finally:
            self._clients.discard(conn)
            self._threads.discard(threading.current_thread())
            conn.close()

    def handle_line(self, line: bytes, source: tuple[Any, ...] = ("socket", 0)) -> dict[str, Any]:
        """One request line → one reply object (never raises). ``source`` (the connection)
        is what the daemon's per-source rate limits count."""
        try:
            request = json.loads(line)
        except (UnicodeDecodeError, json.JSONDecodeError) as exc:
            return {"ok": False, "error": f"not JSON: {exc}"}
        if not isinstance(request, dict) or not isinstance(request.get("cmd"), str):
            return {
                "ok": False,
                "error": 'a request is an object with "cmd": '
                "goto | trajectory | status | park | stop",
            }
        cmd = request["cmd"]
        if cmd == "status":
            return {"ok": True, "status": self.daemon.status()}
        if cmd == "goto":
            payload: Any = request.get("pose")
        elif cmd == "trajectory":
            points = request.get("points")
            if not isinstance(points, list) or not all(
                isinstance(p, list) and len(p) == 7 for p in points
            ):
                return {
                    "ok": False,
                    "error": "points must be a list of "
                    "[t_s, x_cm, y_cm, z_cm, roll_deg, pitch_deg, yaw_deg]",
                }
            payload = [(p[0], p[1:]) for p in points]
        elif cmd in ("park", "stop"):
            payload = None
        else:
            return {
                "ok": False,
                "error": f"unknown cmd {cmd!r}; valid: goto, trajectory, status, park, stop",
            }
        request = self.daemon.new_request(cmd, payload, source=source)
        future = self.daemon.submit_request(request)
        try:
            reply = future.result(timeout=self.reply_timeout_s)
        except TimeoutError:
            # Taken back while still waiting: it will never be carried out, say so. Otherwise
            # the control thread has it and answers within its own bound: wait for that.
            if self.daemon.withdraw(request):
                reply = Reply(Outcome.CANCELLED, f"no answer within {self.reply_timeout_s} s")
                request.answer(reply)
            try:
                reply = future.result(timeout=self.daemon.answer_bound_s())
            except TimeoutError:
                return {"ok": False, "error": f"no answer within {self.reply_timeout_s} s"}
        return {"ok": reply.outcome is Outcome.ACCEPTED, **reply.as_dict()}


def _listening_socket(path: str) -> socket.socket:
    """A Unix stream socket listening at ``path``, which appears only once it listens.

    Between ``bind()`` and ``listen()`` a client connecting gets ECONNREFUSED; so bind a
    temporary name in the same directory, listen, then ``rename()`` it onto ``path`` (atomic;
    it also replaces a stale socket file in the same step).
    """
    temporary = _temporary_name(path)
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    try:
        if temporary is None:  # no free short name: bind in place, as before
            if os.path.exists(path):
                os.unlink(path)
            sock.bind(path)
            sock.listen(8)
            return sock
        sock.bind(temporary)
        try:
            sock.listen(8)
            os.rename(temporary, path)
        except BaseException:
            os.unlink(temporary)
            raise
    except BaseException:
        sock.close()
        raise
    return sock


def _temporary_name(path: str) -> str | None:
    """A free name next to ``path`` that still fits ``sun_path`` (107 bytes), or None."""
    directory, name = os.path.split(path)
    pid = os.getpid()
    # Same directory, so that rename() stays on one file system.
    for candidate in (f".{name}.{pid}", f".{pid}", f".{pid % 10 ** max(1, len(name) - 1)}"):
        temporary = os.path.join(directory, candidate)
        if len(os.fsencode(temporary)) <= _SUN_PATH_MAX and not os.path.lexists(temporary):
            return temporary
    return None


def _json_safe(value: Any) -> Any:
    """Non-finite floats become null: strict JSON readers reject NaN and Infinity."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {str(k): _json_safe(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_json_safe(v) for v in value]
    return value


def _line(obj: dict[str, Any]) -> bytes:
    return (json.dumps(_json_safe(obj), allow_nan=False, default=str) + "\n").encode()
