"""Client side of a JSON-lines Unix socket: one request out, one reply back.

Standard library only, so that ``armbridge status | goto | park | stop`` start at once (the
solver and pymavlink are never imported for them). The server side is
:mod:`companion.daemon.control_socket`.
"""

from __future__ import annotations

import json
import socket
from pathlib import Path
from typing import Any

MAX_REPLY_BYTES = 1 << 20
"""A reply longer than this is refused: a socket that streams without a newline is not ours."""


def json_line_request(path: str | Path, obj: Any, *, timeout_s: float = 10.0) -> Any:
    """Send ``obj`` as one JSON line to the Unix socket at ``path``; return the first reply line,
    decoded. ``ConnectionError`` if the peer closes first or the reply exceeds
    :data:`MAX_REPLY_BYTES`; ``OSError`` (``TimeoutError`` …) from the socket itself."""
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as sock:
        sock.settimeout(timeout_s)
        sock.connect(str(path))
        sock.sendall((json.dumps(obj) + "\n").encode())
        buffer = b""
        while b"\n" not in buffer:
            if len(buffer) > MAX_REPLY_BYTES:
                raise ConnectionError(f"reply from {path} exceeds {MAX_REPLY_BYTES} bytes")
            chunk = sock.recv(65536)
            if not chunk:
                raise ConnectionError(f"{path} closed the connection without a reply")
            buffer += chunk
    return json.loads(buffer.split(b"\n", 1)[0])


def request(path: str | Path, obj: dict[str, Any], *, timeout_s: float = 10.0) -> dict[str, Any]:
    """Send one request to the daemon's control socket at ``path`` and return its reply."""
    reply = json_line_request(path, obj, timeout_s=timeout_s)
    if not isinstance(reply, dict):
        raise ConnectionError(f"daemon at {path} sent a reply that is not a JSON object")
    return reply
