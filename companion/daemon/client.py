"""Client side of a JSON-lines Unix socket: one request out, one reply back.

Standard library only, so that ``armbridge status | goto | park | stop | resume`` start at once (the
solver and pymavlink are never imported for them). The server side is
:mod:`companion.daemon.control_socket`.
"""

from __future__ import annotations

import errno
import grp
import json
import os
import socket
import stat
import struct
from pathlib import Path
from typing import Any

MAX_REPLY_BYTES = 1 << 20
"""A reply longer than this is refused: a socket that streams without a newline is not ours."""


def json_line_request(path: str | Path, obj: Any, *, timeout_s: float = 10.0) -> Any:
    """Send ``obj`` as one JSON line to the Unix socket at ``path``; return the first reply line,
    decoded. ``ConnectionError`` if the peer closes first or the reply exceeds
    :data:`MAX_REPLY_BYTES`; ``OSError`` (``TimeoutError`` …) from the socket itself."""
    with connect(path, timeout_s=timeout_s) as sock:
        sock.sendall(encode_line(obj))
        reply, _ = read_line(sock, path)
    return reply


def connect(path: str | Path, *, timeout_s: float = 10.0) -> socket.socket:
    """A stream socket connected to the Unix socket at ``path``, its timeout ``timeout_s``
    (the waiting of :func:`_connect`)."""
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    try:
        _connect(sock, path, timeout_s)
        sock.settimeout(timeout_s)
    except BaseException:
        sock.close()
        raise
    return sock


def encode_line(obj: Any) -> bytes:
    """``obj`` as one request line: JSON, then a newline."""
    return (json.dumps(obj) + "\n").encode()


def read_line(sock: socket.socket, path: str | Path, buffer: bytes = b"") -> tuple[Any, bytes]:
    """Receive on ``sock`` until ``buffer`` plus what came holds a whole line; return that line
    decoded and the bytes after it (the start of the next reply). Nothing is received when
    ``buffer`` already holds a line. ``ConnectionError`` as :func:`json_line_request`."""
    while b"\n" not in buffer:
        if len(buffer) > MAX_REPLY_BYTES:
            raise ConnectionError(f"reply from {path} exceeds {MAX_REPLY_BYTES} bytes")
        chunk = sock.recv(65536)
        if not chunk:
            raise ConnectionError(f"{path} closed the connection without a reply")
        buffer += chunk
    line, rest = buffer.split(b"\n", 1)
    return json.loads(line), rest


def _connect(sock: socket.socket, path: str | Path, timeout_s: float) -> None:
    """Connect, waiting in the kernel's queue while the server's backlog is full (a busy
    server) for up to ``timeout_s``: a non-blocking connect to a Unix socket fails at once with
    EAGAIN instead, and Python's socket timeouts make it non-blocking; ``SO_SNDTIMEO`` bounds
    the blocking one. ``PermissionError`` says which group the socket wants."""
    whole_s = int(timeout_s)
    sock.setsockopt(
        socket.SOL_SOCKET,
        socket.SO_SNDTIMEO,
        struct.pack("@ll", whole_s, int((timeout_s - whole_s) * 1e6)),
    )
    try:
        sock.connect(str(path))
    except BlockingIOError as exc:  # SO_SNDTIMEO expired
        raise TimeoutError(
            errno.ETIMEDOUT, f"{path} accepted no connection within {timeout_s:g} s"
        ) from exc
    except PermissionError as exc:
        raise PermissionError(exc.errno, _permission_hint(path), str(path)) from exc


def _permission_hint(path: str | Path) -> str:
    """Which group the socket wants: its own, or, when its directory cannot be searched (the
    service's /run/armbridge is 0750), the directory's."""
    try:
        st = os.stat(path)
    except OSError:
        try:
            st = os.stat(os.path.dirname(os.path.abspath(path)))
        except OSError:
            return "Permission denied"
    try:
        group = grp.getgrgid(st.st_gid).gr_name
    except KeyError:
        group = str(st.st_gid)
    return (
        f"Permission denied (mode {stat.S_IMODE(st.st_mode):04o}, group {group}): the daemon's "
        f"operators are the members of group {group!r}; ask to be added (then log in again)"
    )


def request(path: str | Path, obj: dict[str, Any], *, timeout_s: float = 10.0) -> dict[str, Any]:
    """Send one request to the daemon's control socket at ``path`` and return its reply."""
    reply = json_line_request(path, obj, timeout_s=timeout_s)
    if not isinstance(reply, dict):
        raise ValueError(f"daemon at {path} sent a reply that is not a JSON object")
    return reply
