"""The daemon's local control socket: a Unix stream socket speaking JSON lines.

For onboard software (and the ``armbridge goto`` / ``status`` clients). One JSON object per
line in, one per line out, in order; a connection may send many requests.

Requests::

    {"cmd": "goto", "pose": [x_cm, y_cm, z_cm, roll_deg, pitch_deg, yaw_deg]}
    (optional "mode": "pose" | "position" | "position_axis": what of the pose must be met;
    optional "frame": "base" (default) | "local_ned": the world, the hand held there while the
    vehicle moves, with ``[world]`` on)
    {"cmd": "trajectory", "points": [[t_s, x_cm, y_cm, z_cm, roll_deg, pitch_deg, yaw_deg], ...]}
    {"cmd": "status"}
    {"cmd": "park"}
    {"cmd": "stop"}      (the arm holds until a resume, or a goto, trajectory or park here)
    {"cmd": "resume"}

Replies: ``{"ok": true, "outcome": "accepted", "message": ..., "solve": {...}}``. ``ok`` is
false for any outcome other than accepted, and for a malformed or refused request:
``{"ok": false, "error": "..."}``. ``status`` answers ``{"ok": true, "status": {...}}``.
Trajectory times are seconds from receipt; the daemon solves each point when it falls due.

Who may connect: the socket is mode 0660 and belongs to ``control.socket_group`` (default: the
daemon's primary group); each connection's peer credentials (``SO_PEERCRED``) are checked as
well: root, the daemon's own user and members of that group. Anyone else gets one line
``{"ok": false, "error": "permission denied: ..."}`` and the connection is closed.

Limits (nothing a client sends makes the daemon hold more than a bounded amount of memory or
stop serving others):

* one thread for all connections (``selectors``, non-blocking sockets);
* at most ``max_connections`` open; a new one at the cap closes the one that has gone longest
  without a request (one that never completed a request first); only if every connection waits
  for an answer is the newcomer refused;
* a request line is at most :data:`MAX_LINE_BYTES`; a longer one is refused and its connection
  closed;
* at most :data:`MAX_QUEUED_REPLY_BYTES` of replies wait for a client to read them: past that
  its further requests wait, and a client that then reads nothing is closed as idle;
* a connection that completes no request for ``idle_timeout_s`` is closed (a request line sent
  a byte at a time does not count until it is complete);
* JSON: nesting at most :data:`MAX_DEPTH` deep, numbers of at most :data:`MAX_INT_DIGITS`
  digits in a row, finite floats (no NaN, Infinity or overflow to it), no duplicate key.

One request at a time per connection: the next line is read once the previous one is answered,
so replies come in request order and a ``stop`` after a ``goto`` on one connection is asked
after the goto's answer, as with a blocking client. A request that waits for the daemon is
submitted and answered when its answer comes, without holding up the other connections.
"""

from __future__ import annotations

import errno
import grp
import itertools
import json
import logging
import math
import os
import re
import selectors
import socket
import stat
import struct
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from companion.daemon.client import request  # the client half, re-exported
from companion.daemon.config import file_kind
from companion.daemon.intake import RefusalLog
from companion.daemon.requests import (
    MAX_TRAJECTORY_POINTS,
    POINT_JSON_BYTES,
    Reply,
    Request,
)
from companion.daemon.service import ArmDaemon, Outcome

log = logging.getLogger("armbridge.control")

__all__ = [
    "ControlServer",
    "ControlSocketError",
    "parse_request_line",
    "request",
]

#: A request line longer than this (without its newline) is refused: room for a trajectory of
#: MAX_TRAJECTORY_POINTS points however its numbers are written (the limit follows points, not
#: bytes), ~370 KiB; this per connection times the connection cap bounds the memory (12 MiB
#: at the default 32).
MAX_LINE_BYTES = MAX_TRAJECTORY_POINTS * POINT_JSON_BYTES + 4096
#: Replies waiting for a client to read them; past this its further requests wait.
MAX_QUEUED_REPLY_BYTES = 64 * 1024
#: Nesting of JSON arrays and objects: a request needs 3 (object, points, point).
MAX_DEPTH = 32
#: Digits in a row in a JSON number (an integer, or a float's parts): 20 hold any 64-bit
#: integer and more than a double's 17 significant digits; Python would parse 4 300 at a cost
#: that grows with the square of the length.
MAX_INT_DIGITS = 20
DEFAULT_MAX_CONNECTIONS = 32
DEFAULT_IDLE_TIMEOUT_S = 30.0
#: Pending connections the kernel queues before connect() blocks or fails.
BACKLOG = 64
#: New connections taken per round of the loop, so that the ones already open are served too.
_ACCEPTS_PER_ROUND = 16
#: Failures in a row of the loop itself (not of one connection) before the socket gives up.
_LOOP_FAILURES_MAX = 10
#: After accept() failed for lack of file descriptors, it is retried after this.
_ACCEPT_PAUSE_S = 0.1
_SUN_PATH_MAX = 107  # bytes of a Unix socket path (sockaddr_un.sun_path, less its NUL)
#: SO_PEERGROUPS (Linux 4.13): the peer's supplementary groups; Python has no name for it.
_SO_PEERGROUPS = getattr(socket, "SO_PEERGROUPS", 59)

_COMMANDS = "goto | trajectory | status | park | stop | resume"


class ControlSocketError(OSError):
    """The control socket cannot be set up at its path; ``strerror`` says why in full (``run``
    reports it as the config error ``control.socket: cannot listen on it: ...``, exit 2)."""


class ControlServer:
    """Serves ``daemon`` on the Unix socket ``path``, from one thread.

    ``path`` appears only once the socket listens, with mode 0660 and group ``group`` (a name
    or gid). ``group``, ``max_connections`` and ``idle_timeout_s`` default to the daemon
    config's ``control.socket_group`` (itself defaulting to the daemon's primary group),
    ``control.max_connections`` and ``control.idle_timeout_s``.

    Whatever is at ``path`` is kept unless it is a stale socket (one nobody listens on): a file
    of another kind, or a socket a live process listens on, raise :class:`ControlSocketError`
    and nothing is touched.

    A request not answered within ``reply_timeout_s`` is withdrawn if the daemon has not taken
    it yet (answered ``cancelled``: it will never be carried out); otherwise its answer is
    awaited up to :meth:`ArmDaemon.answer_bound_s` more.
    """

    def __init__(
        self,
        path: str | Path,
        daemon: ArmDaemon,
        *,
        reply_timeout_s: float = 5.0,
        group: str | int | None = None,
        max_connections: int | None = None,
        idle_timeout_s: float | None = None,
    ) -> None:
        config = daemon.config
        self.path = str(path)
        self.daemon = daemon
        self.reply_timeout_s = reply_timeout_s
        self.max_connections = (
            config.control_max_connections if max_connections is None else max_connections
        )
        self.idle_timeout_s = (
            config.control_idle_timeout_s if idle_timeout_s is None else idle_timeout_s
        )
        if self.max_connections < 1 or not self.idle_timeout_s > 0:
            raise ValueError(
                f"max_connections={self.max_connections} must be >= 1 and "
                f"idle_timeout_s={self.idle_timeout_s} > 0"
            )
        self.gid, self.group_name = _group(config.control_socket_group if group is None else group)
        self.uid = os.geteuid()
        #: Connections refused, closed idle, evicted: a summary line at most every 10 s.
        self.refusals = RefusalLog()
        self._connections: dict[int, _Connection] = {}  # by file descriptor
        self._number = 0
        self._accept_paused_until = 0.0
        self._stopping = threading.Event()
        self._flush_deadline = math.inf
        self._closed = False
        #: Set once the last round has read what every connection sent: only then may a
        #: connection with nothing to answer be closed for the stop (closing one with bytes
        #: unread makes the kernel reset it, and its client never sees the answer).
        self._drained = False
        self._sock, self._identity = _listening_socket(self.path, self.gid, self.group_name)
        try:
            self._sock.setblocking(False)
            self._wake_in, self._wake_out = socket.socketpair()
            self._wake_in.setblocking(False)
            self._wake_out.setblocking(False)
            self._selector = selectors.DefaultSelector()
            self._selector.register(self._sock, selectors.EVENT_READ, _LISTENER)
            self._selector.register(self._wake_in, selectors.EVENT_READ, _WAKE)
        except BaseException:
            self._sock.close()
            self._unlink_if_ours()
            raise
        self._thread = threading.Thread(
            target=self._loop, name="armbridge-control-socket", daemon=True
        )
        self._thread.start()

    def reconfigure(self, max_connections: int, idle_timeout_s: float) -> None:
        """SIGHUP: new limits (``load_config`` bounded them). They apply from the next accept
        and idle check; connections over a lowered cap stay until they idle out or close."""
        self.max_connections = max_connections
        self.idle_timeout_s = idle_timeout_s
        self._wake()  # the loop recomputes its idle deadline

    @property
    def connections(self) -> int:
        """Connections open now."""
        return len(self._connections)

    @property
    def waiting(self) -> int:
        """Connections whose request waits for the daemon's answer now."""
        return sum(c.waiting is not None for c in tuple(self._connections.values()))

    def close(self, *, flush_s: float = 0.2) -> None:
        """Stop accepting, give the connections up to ``flush_s`` to write the answers they
        hold (the daemon answered everything before; a request it has not taken yet is
        withdrawn and answered cancelled), then close them and remove the socket."""
        if self._closed:
            return
        self._closed = True
        self._flush_deadline = time.monotonic() + flush_s
        self._stopping.set()
        self._wake()
        self._thread.join(timeout=flush_s + 2.0)
        if self._thread.is_alive():  # pragma: no cover - the loop never blocks that long
            log.error("the control socket's thread did not stop within %.1f s", flush_s + 2.0)

    # -- the loop (its own thread) ---------------------------------------------------------------

    @property
    def alive(self) -> bool:
        """Whether the socket is served (its thread runs and was not asked to stop)."""
        return self._thread.is_alive() and not self._stopping.is_set()

    def _loop(self) -> None:
        failures = 0
        try:
            while True:
                try:
                    if self._round():
                        return
                    failures = 0
                except Exception:  # a bug outside any one connection: say so, serve on
                    failures += 1
                    log.exception("the control socket's loop failed (%d in a row)", failures)
                    if failures >= _LOOP_FAILURES_MAX:
                        log.error("the control socket is closed: its loop keeps failing")
                        return
        finally:
            self._shutdown()

    def _round(self) -> bool:
        """One pass: the events, then every connection; True once stopped."""
        for key, mask in self._selector.select(self._timeout_s(time.monotonic())):
            self._event(key.data, mask)
        now = time.monotonic()
        stopping = self._stopping.is_set()
        if stopping and self._sock.fileno() >= 0:
            self._last_round()
        elif self._accept_paused_until and now >= self._accept_paused_until:
            self._accept_paused_until = 0.0
            self._selector.register(self._sock, selectors.EVENT_READ, _LISTENER)
        for conn in list(self._connections.values()):
            self._guarded(conn, self._service, now)
        return stopping and (not self._connections or now >= self._flush_deadline)

    def _event(self, data: Any, mask: int) -> None:
        if data is _LISTENER:
            self._accept()
        elif data is _WAKE:
            try:
                while self._wake_in.recv(4096):
                    pass
            except BlockingIOError:
                pass
        else:
            conn: _Connection = data
            if mask & selectors.EVENT_READ:
                self._guarded(conn, self._read)
            if mask & selectors.EVENT_WRITE:
                self._guarded(conn, self._flush)

    def _guarded(self, conn: _Connection, work: Any, *args: Any) -> None:
        """``work(conn, *args)``; a bug there closes that connection, never the loop."""
        if conn.closed:
            return
        try:
            work(conn, *args)
        except Exception:
            log.exception("control connection %d failed; closing it", conn.number)
            self._close(conn, "the daemon failed on it")

    def _timeout_s(self, now: float) -> float | None:
        deadlines = [c.deadline_s(self.idle_timeout_s) for c in self._connections.values()]
        if self._accept_paused_until:
            deadlines.append(self._accept_paused_until)
        if self._stopping.is_set():
            deadlines.append(self._flush_deadline)
        if not deadlines:
            return None
        return max(0.0, min(deadlines) - now)

    def _wake(self, *_: Any) -> None:
        """Wake the loop (from any thread: a future's done-callback runs on the daemon's)."""
        try:
            self._wake_out.send(b"\0")
        except OSError:  # full (a wake is pending anyway) or closed (the loop has ended)
            pass

    # -- connections -----------------------------------------------------------------------------

    def _accept(self) -> None:
        now = time.monotonic()
        for _ in range(_ACCEPTS_PER_ROUND):
            try:
                sock, _ = self._sock.accept()
            except (BlockingIOError, InterruptedError, ConnectionAbortedError):
                return
            except OSError as exc:  # EMFILE, ENFILE, ENOBUFS: pause instead of spinning
                self.refusals.note("connection", Outcome.TEMPORARILY_REJECTED, str(exc))
                self._accept_paused_until = now + _ACCEPT_PAUSE_S
                self._selector.unregister(self._sock)
                return
            self._admit(sock, now)

    def _admit(self, sock: socket.socket, now: float) -> None:
        sock.setblocking(False)
        refusal = self._peer_refusal(sock)
        if refusal is None and len(self._connections) >= self.max_connections:
            refusal = self._make_room()
        if refusal is not None:
            self.refusals.note("connection", Outcome.DENIED, refusal)
            _send_and_close(sock, _line({"ok": False, "error": refusal}))
            return
        self._number += 1
        conn = _Connection(sock, self._number, now)
        self._connections[conn.fd] = conn
        self._selector.register(sock, selectors.EVENT_READ, conn)
        # A client usually sends its request with the connection: serve it now, before another
        # newcomer could push it out.
        self._guarded(conn, self._read)
        self._guarded(conn, self._service, now)

    def _peer_refusal(self, sock: socket.socket) -> str | None:
        """Why the peer may not use the socket, or None: root, the daemon's user and the
        members of its group may."""
        try:
            pid, uid, gid = struct.unpack(
                "3i", sock.getsockopt(socket.SOL_SOCKET, socket.SO_PEERCRED, 12)
            )
        except OSError as exc:
            return f"permission denied: cannot read the peer's credentials ({exc})"
        if uid in (0, self.uid) or gid == self.gid:
            return None
        groups = _peer_groups(sock, pid)
        if groups is not None and self.gid in groups:
            return None
        return (
            f"permission denied: uid {uid} is not root, not the daemon's user (uid {self.uid}) "
            f"and not in group {self.group_name!r} (control.socket_group): ask to be added to it"
        )

    def _make_room(self) -> str | None:
        """At the cap: close the connection longest without a request (one that never
        completed one first) and return None; if every one waits for an answer, the reason to
        refuse the newcomer."""
        idle = [c for c in self._connections.values() if c.waiting is None]
        if not idle:
            return (
                f"too many connections: {len(self._connections)} open, each waiting for an "
                f"answer (control.max_connections = {self.max_connections})"
            )
        victim = min(idle, key=lambda c: (c.proven, c.active_s))
        self._refuse(
            victim,
            f"closed to make room for a new connection: {len(self._connections)} open "
            f"(control.max_connections = {self.max_connections}) and this one had "
            + ("gone longest without a request" if victim.proven else "completed no request"),
        )
        return None

    def _read(self, conn: _Connection) -> None:
        room = MAX_LINE_BYTES + 1 - len(conn.inbox)
        if room <= 0 or conn.eof:
            return
        try:
            data = conn.sock.recv(min(room, 65536))
        except (BlockingIOError, InterruptedError):
            return
        except OSError as exc:
            self._close(conn, f"went away ({exc})")
            return
        if data:
            conn.inbox += data
            return
        conn.eof = True  # closed, or only its sending half (it may still read): which?
        try:
            conn.sock.send(b"")  # EPIPE once the client closed its reading half too
        except OSError:
            self._close(conn, "went away")

    def _flush(self, conn: _Connection) -> None:
        if not conn.outbox:
            return
        try:
            sent = conn.sock.send(conn.outbox)
        except (BlockingIOError, InterruptedError):
            return
        except OSError as exc:
            self._close(conn, f"went away ({exc})")
            return
        del conn.outbox[:sent]
        if not conn.outbox:
            conn.active_s = time.monotonic()

    def _service(self, conn: _Connection, now: float) -> None:
        """Everything a connection may be due for: its answer, its next request, its timeout,
        writing, and what it waits on in the selector."""
        waiting = conn.waiting
        if waiting is not None:
            self._follow(conn, waiting, now)
        stopping = self._drained
        while conn.waiting is None and len(conn.outbox) < MAX_QUEUED_REPLY_BYTES:
            end = conn.inbox.find(b"\n", conn.scanned)
            if end < 0 and conn.eof and conn.inbox:
                end = len(conn.inbox)  # the last request, sent without its newline
            if end < 0:
                conn.scanned = len(conn.inbox)
                if conn.scanned > MAX_LINE_BYTES:
                    self._refuse(
                        conn,
                        f"request line longer than {MAX_LINE_BYTES} bytes: refused, "
                        "connection closed",
                    )
                    return
                break
            line = bytes(conn.inbox[:end])
            del conn.inbox[: end + 1]
            conn.scanned = 0
            conn.active_s = now
            if line.strip():
                self._handle(conn, line, now)
        if conn.waiting is None and now - conn.active_s >= self.idle_timeout_s:
            if conn.outbox:
                self._close(conn, f"read no reply for {self.idle_timeout_s:g} s")
            else:
                self._refuse(
                    conn,
                    f"idle for {self.idle_timeout_s:g} s without a complete request "
                    "(control.idle_timeout_s): connection closed",
                )
            return
        self._flush(conn)
        if conn.closed:
            return
        if conn.waiting is None and not conn.outbox and (conn.eof or stopping):
            self._close(conn, "done")  # everything it sent is answered
            return
        events = 0
        if not conn.eof and not stopping and len(conn.inbox) <= MAX_LINE_BYTES:
            events |= selectors.EVENT_READ
        if conn.outbox:
            events |= selectors.EVENT_WRITE
        if events != conn.events:
            if conn.events and events:
                self._selector.modify(conn.sock, events, conn)
            elif events:
                self._selector.register(conn.sock, events, conn)
            else:
                self._selector.unregister(conn.sock)
            conn.events = events

    def _handle(self, conn: _Connection, line: bytes, now: float) -> None:
        parsed = parse_request_line(line)
        if isinstance(parsed, dict):
            self._reply(conn, parsed)
            return
        conn.proven = True
        kind, payload = parsed
        if kind == "status":
            self._reply(conn, {"ok": True, "status": self.daemon.status()})
            return
        request = self.daemon.new_request(kind, payload, source=("socket", conn.number))
        future = self.daemon.submit_request(request)
        if future.done():
            self._reply(conn, _reply_object(future.result()))
            return
        conn.waiting = _Waiting(request, now + self.reply_timeout_s)
        future.add_done_callback(self._wake)

    def _follow(self, conn: _Connection, waiting: _Waiting, now: float) -> None:
        """A request in the daemon: its answer if it came, else its deadlines."""
        future = waiting.request.future
        if not future.done() and (now >= waiting.deadline_s or self._stopping.is_set()):
            if not waiting.taken:
                # Taken back while still waiting: it will never be carried out, say so.
                # Otherwise the control thread has it and answers within its own bound.
                if self.daemon.withdraw(waiting.request):
                    waiting.request.answer(
                        Reply(
                            Outcome.CANCELLED,
                            "the control socket is closing"
                            if self._stopping.is_set()
                            else f"no answer within {self.reply_timeout_s:g} s",
                        )
                    )
                else:
                    waiting.taken = True
                    waiting.deadline_s = now + self.daemon.answer_bound_s()
            elif now >= waiting.deadline_s:
                conn.waiting = None
                self._reply(
                    conn, {"ok": False, "error": f"no answer within {self.reply_timeout_s:g} s"}
                )
                return
        if future.done():
            conn.waiting = None
            conn.active_s = now
            self._reply(conn, _reply_object(future.result()))

    def _reply(self, conn: _Connection, obj: dict[str, Any]) -> None:
        conn.outbox += _line(obj)

    def _refuse(self, conn: _Connection, reason: str) -> None:
        """One line saying why, then close (what does not fit the client's buffer is lost)."""
        self.refusals.note("connection", Outcome.DENIED, reason)
        conn.outbox += _line({"ok": False, "error": reason})
        self._flush(conn)
        self._close(conn, reason)

    def _close(self, conn: _Connection, why: str) -> None:
        """Close ``conn``; a request of it the daemon has not taken yet is withdrawn (and never
        carried out)."""
        if conn.closed:
            return
        conn.closed = True
        del self._connections[conn.fd]
        waiting = conn.waiting
        if waiting is not None and not waiting.request.answered:
            if self.daemon.withdraw(waiting.request):
                waiting.request.answer(Reply(Outcome.CANCELLED, "its client went away"))
        if conn.events:
            self._selector.unregister(conn.sock)
        conn.sock.close()
        log.debug("control connection %d closed: %s", conn.number, why)

    # -- stopping --------------------------------------------------------------------------------

    def _last_round(self) -> None:
        """Closing: take the connections still in the kernel's backlog and what every
        connection sent so far, so that each request sent before the close is answered (the
        daemon, closed first, answers at once); then stop listening."""
        for _ in range(BACKLOG // _ACCEPTS_PER_ROUND + 1):
            if self._accept_paused_until:
                break
            self._accept()
        for conn in list(self._connections.values()):
            self._guarded(conn, self._read)
        self._drained = True
        self._stop_accepting()

    def _stop_accepting(self) -> None:
        if self._sock.fileno() < 0:
            return
        if not self._accept_paused_until:
            self._selector.unregister(self._sock)
        self._sock.close()
        self._unlink_if_ours()

    def _shutdown(self) -> None:
        self._stopping.set()
        for conn in list(self._connections.values()):
            self._close(conn, "the control socket closed")
        try:
            self._stop_accepting()
        finally:
            self._selector.close()
            self._wake_in.close()
            self._wake_out.close()

    def _unlink_if_ours(self) -> None:
        """Remove the socket file if it is still the one this server bound."""
        try:
            st = os.lstat(self.path)
            if stat.S_ISSOCK(st.st_mode) and (st.st_dev, st.st_ino) == self._identity:
                os.unlink(self.path)
        except FileNotFoundError:
            pass
        except OSError as exc:
            log.warning("cannot remove the control socket %s: %s", self.path, exc)


_LISTENER = object()
_WAKE = object()


@dataclass(eq=False)
class _Waiting:
    """A request of a connection that the daemon has not answered yet."""

    request: Request
    deadline_s: float
    taken: bool = False  # the daemon had taken it at the first deadline: the answer bound runs


@dataclass(eq=False)
class _Connection:
    sock: socket.socket
    number: int
    active_s: float  # accepted, completed a line, got an answer, or read all its replies
    inbox: bytearray = field(default_factory=bytearray)
    outbox: bytearray = field(default_factory=bytearray)
    scanned: int = 0  # bytes of inbox known to hold no newline
    waiting: _Waiting | None = None
    proven: bool = False  # sent at least one well-formed request
    eof: bool = False  # the client will send no more
    closed: bool = False
    events: int = selectors.EVENT_READ  # what the selector watches for
    fd: int = field(init=False)  # its key in ControlServer._connections

    def __post_init__(self) -> None:
        self.fd = self.sock.fileno()

    def deadline_s(self, idle_timeout_s: float) -> float:
        if self.waiting is not None:
            return self.waiting.deadline_s
        return self.active_s + idle_timeout_s


# -- parsing ------------------------------------------------------------------------------------


class _Refused(Exception):
    """A JSON value past the parser's limits (the message says which)."""


#: A JSON string, escapes included (the unrolled form: linear time, no backtracking blow-up).
_JSON_STRING = re.compile(r'"[^"\\]*(?:\\.[^"\\]*)*"', re.S)
_NOT_BRACKET = re.compile(r"[^\[\]{}]+")
_NESTING = {"[": 1, "{": 1, "]": -1, "}": -1}
_DIGIT_RUN = re.compile(f"[0-9]{{{MAX_INT_DIGITS + 1},}}")
#: Only a float with an exponent of 3 digits or more can overflow to infinity (the digits
#: before it are bounded by _DIGIT_RUN).
_BIG_EXPONENT = re.compile(r"[eE][+-]?[0-9]{3,}")


def _parse_float(text: str) -> float:
    value = float(text)
    if not math.isfinite(value):
        raise _Refused(f"the number {text} is out of a float's range")
    return value


def _parse_constant(name: str) -> Any:
    raise _Refused(f"{name} is not a JSON number")


def _object(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    obj: dict[str, Any] = {}
    for key, value in pairs:
        if key in obj:
            raise _Refused(f"duplicate key {key!r}")
        obj[key] = value
    return obj


def _loads(line: bytes) -> Any:
    """One request line → a JSON value within the limits; ``_Refused`` or ``ValueError``.

    Nesting and digits are counted on the line with its strings taken out, before parsing:
    the parser recurses once per level, and Python's ``int()`` takes time quadratic in the
    digits (it refuses only past 4 300). Per-number hooks would cost a Python call per number
    of a trajectory; only a float that may overflow goes through one.
    """
    text = line.decode("utf-8")
    bare = _JSON_STRING.sub('""', text)  # what is left: structure, numbers, literals
    steps = map(_NESTING.__getitem__, _NOT_BRACKET.sub("", bare))
    if max(itertools.accumulate(steps), default=0) > MAX_DEPTH:
        raise _Refused(f"nested more than {MAX_DEPTH} deep")
    run = _DIGIT_RUN.search(bare)
    if run is not None:
        raise _Refused(
            f"a number with {len(run.group())} digits in a row (at most {MAX_INT_DIGITS})"
        )
    try:
        return json.loads(
            text,
            object_pairs_hook=_object,
            parse_float=_parse_float if _BIG_EXPONENT.search(bare) else float,
            parse_constant=_parse_constant,
        )
    except RecursionError:  # not reached past the nesting count; kept as the last guard
        raise _Refused(f"nested more than {MAX_DEPTH} deep") from None


def parse_request_line(line: bytes) -> dict[str, Any] | tuple[str, Any]:
    """One request line → ``(cmd, payload)`` for the daemon, or the error reply to send
    (``{"ok": false, "error": ...}``). Never raises."""
    try:
        obj = _loads(line)
    except _Refused as exc:
        return {"ok": False, "error": f"refused: {exc}"}
    except (UnicodeDecodeError, ValueError) as exc:
        return {"ok": False, "error": f"not JSON: {exc}"}
    if not isinstance(obj, dict) or not isinstance(obj.get("cmd"), str):
        return {"ok": False, "error": f'a request is an object with "cmd": {_COMMANDS}'}
    cmd = obj["cmd"]
    if cmd == "goto":
        if "mode" in obj or "frame" in obj:  # requests.TARGET_MODES, requests.TARGET_FRAMES
            return cmd, {
                "pose": obj.get("pose"),
                "mode": obj.get("mode", "pose"),
                "frame": obj.get("frame", "base"),
            }
        return cmd, obj.get("pose")
    if cmd == "trajectory":
        points = obj.get("points")
        if not isinstance(points, list) or not all(
            isinstance(p, list) and len(p) == 7 for p in points
        ):
            return {
                "ok": False,
                "error": "points must be a list of "
                "[t_s, x_cm, y_cm, z_cm, roll_deg, pitch_deg, yaw_deg]",
            }
        return cmd, [(p[0], p[1:]) for p in points]
    if cmd in ("status", "park", "stop", "resume"):
        return cmd, None
    return {
        "ok": False,
        "error": f"unknown cmd {cmd!r}; valid: goto, trajectory, status, park, stop, resume",
    }


def _reply_object(reply: Reply) -> dict[str, Any]:
    return {"ok": reply.outcome is Outcome.ACCEPTED, **reply.as_dict()}


# -- the socket file ------------------------------------------------------------------------------


def _group(group: str | int | None) -> tuple[int, str]:
    """(gid, name) of ``group`` (a name or gid; None: the daemon's primary group)."""
    if group is None:
        group = os.getegid()
    try:
        entry = grp.getgrgid(group) if isinstance(group, int) else grp.getgrnam(group)
    except KeyError:
        if isinstance(group, int):
            return group, str(group)
        raise ControlSocketError(
            errno.EINVAL, f"no group {group!r} on this system (control.socket_group)"
        ) from None
    return entry.gr_gid, entry.gr_name


def _peer_groups(sock: socket.socket, pid: int) -> set[int] | None:
    """The peer's supplementary groups as the kernel recorded them at connect
    (``SO_PEERGROUPS``), else from ``/proc/PID/status``; None if neither can tell."""
    for count in (64, 65536):  # NGROUPS_MAX is 65536
        try:
            raw = sock.getsockopt(socket.SOL_SOCKET, _SO_PEERGROUPS, 4 * count)
        except OSError as exc:
            if exc.errno == errno.ERANGE:
                continue
            break
        return set(struct.unpack(f"{len(raw) // 4}I", raw))
    try:
        with open(f"/proc/{pid}/status") as status:
            for row in status:
                if row.startswith("Groups:"):
                    return {int(g) for g in row.split()[1:]}
    except (OSError, ValueError):
        pass
    return None


def _listening_socket(
    path: str, gid: int, group_name: str
) -> tuple[socket.socket, tuple[int, int]]:
    """A Unix stream socket listening at ``path`` (mode 0660, group ``gid``), and its file's
    (st_dev, st_ino).

    ``path`` appears only once the socket listens (between ``bind()`` and ``listen()`` a
    client connecting gets ECONNREFUSED): the socket is bound under a temporary name in the
    same directory, given its mode and group, made to listen, and then linked onto ``path``
    (which fails if something appeared there) or, over a stale socket, renamed onto it.
    """
    _check_directory(os.path.dirname(os.path.abspath(path)))
    stale = _check_path(path)
    temporary = _temporary_name(path)
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    try:
        if temporary is None:  # no free short name: bind in place
            if stale:
                os.unlink(path)
            sock.bind(path)
            _set_mode_and_group(path, gid, group_name)
            sock.listen(BACKLOG)
            st = os.lstat(path)
            return sock, (st.st_dev, st.st_ino)
        sock.bind(temporary)
        try:
            _set_mode_and_group(temporary, gid, group_name)
            sock.listen(BACKLOG)
            st = os.lstat(temporary)
            _publish(temporary, path, stale)
        finally:
            if os.path.lexists(temporary):
                os.unlink(temporary)
    except BaseException:
        sock.close()
        raise
    return sock, (st.st_dev, st.st_ino)


def _check_directory(directory: str) -> None:
    """Refuse a socket directory that a user other than the daemon's (or root) could write,
    unless it is sticky: there another user could swap the socket's name for a symlink between
    ``bind()`` and ``chmod()`` (making a file of root's readable by the group), or put a socket
    of their own at ``path`` to read the operators' commands."""
    try:
        st = os.stat(directory)
    except OSError as exc:
        raise ControlSocketError(
            exc.errno or errno.ENOENT, f"socket directory {directory}: {exc.strerror or exc}"
        ) from exc
    me = os.geteuid()
    sticky = bool(st.st_mode & stat.S_ISVTX)
    if st.st_uid not in (me, 0):
        raise ControlSocketError(
            errno.EPERM,
            f"socket directory {directory} belongs to uid {st.st_uid}, not to the daemon's user "
            f"(uid {me}) or root: choose a directory of the daemon's own (control.socket)",
        )
    if st.st_mode & 0o022 and not sticky:
        raise ControlSocketError(
            errno.EPERM,
            f"socket directory {directory} is writable by its group or others (mode "
            f"{stat.S_IMODE(st.st_mode):04o}): another user could replace the socket; make it "
            f"writable by the daemon's user only (chmod go-w {directory}; systemd's "
            "RuntimeDirectoryMode=0750)",
        )


def _check_path(path: str) -> bool:
    """Whether ``path`` holds a stale socket (to be replaced); False if nothing is there.
    :class:`ControlSocketError` if it holds anything else, or a socket someone listens on."""
    try:
        mode = os.lstat(path).st_mode
    except FileNotFoundError:
        return False
    if not stat.S_ISSOCK(mode):
        raise ControlSocketError(
            errno.EEXIST,
            f"{path} exists and is not a socket ({file_kind(mode)}): the daemon replaces only "
            "a stale socket of its own; move it away or choose another path",
        )
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as probe:
        probe.settimeout(1.0)
        try:
            probe.connect(path)
        except ConnectionRefusedError:
            return True  # nobody listens: a stale socket, e.g. of a daemon that was killed
        except FileNotFoundError:
            return False
        except TimeoutError:  # a full backlog: someone listens and is busy
            pass
        except OSError as exc:
            raise ControlSocketError(
                exc.errno or errno.EACCES,
                f"cannot tell whether a daemon listens on {path} ({exc.strerror or exc}); "
                "not replacing it",
            ) from exc
    raise ControlSocketError(
        errno.EADDRINUSE,
        f"another daemon listens on {path}: stop it first, or give this one another control.socket",
    )


def _set_mode_and_group(path: str, gid: int, group_name: str) -> None:
    if not stat.S_ISSOCK(os.lstat(path).st_mode):  # never through a link put in its place
        raise ControlSocketError(errno.EEXIST, f"{path} is no longer the socket just bound")
    os.chmod(path, 0o660)
    if os.lstat(path).st_gid == gid:
        return
    try:
        os.chown(path, -1, gid, follow_symlinks=False)
    except PermissionError as exc:
        raise ControlSocketError(
            exc.errno,
            f"cannot give the socket to group {group_name!r} (gid {gid}): the daemon's user "
            f"(uid {os.geteuid()}) is not a member (control.socket_group)",
        ) from exc


def _publish(temporary: str, path: str, stale: bool) -> None:
    """Make the listening socket at ``temporary`` appear at ``path`` in one step."""
    if stale:
        os.rename(temporary, path)  # atomic, over the stale socket
        return
    try:
        os.link(temporary, path)  # fails rather than replace what appeared meanwhile
    except FileExistsError:
        if _check_path(path):  # a stale socket appeared meanwhile (anything else raises)
            os.rename(temporary, path)
        else:  # and went again
            os.link(temporary, path)
    except PermissionError:  # a file system without hard links
        if os.path.lexists(path):
            raise
        os.rename(temporary, path)


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


def _send_and_close(sock: socket.socket, data: bytes) -> None:
    try:
        sock.send(data)
    except OSError:
        pass
    sock.close()


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
