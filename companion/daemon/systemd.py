"""A tiny sd_notify client: the daemon's readiness, watchdog and status for systemd.

With ``Type=notify``, systemd passes the path of a datagram socket in ``NOTIFY_SOCKET``
(``@name`` for the Linux abstract namespace). Each notification is one datagram of
newline-separated ``KEY=value`` lines, e.g. ``READY=1`` or ``STATUS=link up``. Outside systemd
(no ``NOTIFY_SOCKET``) every call does nothing, so the daemon runs the same from a shell.

``WATCHDOG_USEC`` (and ``WATCHDOG_PID``, when set, naming this process) give the watchdog
period; the daemon pings ``WATCHDOG=1`` at half of it from its healthy main loop.

A failure to send is logged and swallowed: losing a status line must never stop the arm.
"""

from __future__ import annotations

import logging
import os
import socket
from collections.abc import Mapping

log = logging.getLogger(__name__)


class Notifier:
    """Sends notifications to ``NOTIFY_SOCKET`` from ``environ`` (default: the process's)."""

    def __init__(self, environ: Mapping[str, str] | None = None) -> None:
        env = os.environ if environ is None else environ
        address = env.get("NOTIFY_SOCKET", "")
        self._address: str | None = None
        self._sock: socket.socket | None = None
        if address:
            if address.startswith("@"):
                address = "\0" + address[1:]  # abstract namespace
            elif not address.startswith("/"):
                log.warning("NOTIFY_SOCKET=%r is neither a path nor @abstract; ignored", address)
                address = ""
        if address:
            self._address = address
            self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC)
        self.watchdog_period_s = _watchdog_period_s(env)

    @property
    def enabled(self) -> bool:
        return self._sock is not None

    def notify(self, *lines: str) -> bool:
        """Send ``lines`` as one datagram; returns False (and logs) if it could not be sent."""
        if self._sock is None or self._address is None:
            return False
        try:
            self._sock.sendto("\n".join(lines).encode("utf-8"), self._address)
        except OSError as exc:
            log.warning("sd_notify to %r failed: %s", self._address, exc)
            return False
        return True

    def ready(self, status: str | None = None) -> bool:
        return self.notify("READY=1", *([f"STATUS={status}"] if status else []))

    def stopping(self, status: str | None = None) -> bool:
        return self.notify("STOPPING=1", *([f"STATUS={status}"] if status else []))

    def reloading(self) -> bool:
        return self.notify("RELOADING=1")

    def watchdog(self) -> bool:
        return self.notify("WATCHDOG=1")

    def status(self, text: str) -> bool:
        # A status is one line: systemd would take anything after a newline as another field.
        return self.notify("STATUS=" + " ".join(text.splitlines()))

    def close(self) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None

    def __enter__(self) -> Notifier:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _watchdog_period_s(env: Mapping[str, str]) -> float | None:
    """The watchdog period systemd asked for, or None (unset, malformed, or for another PID)."""
    usec = env.get("WATCHDOG_USEC")
    if not usec:
        return None
    pid = env.get("WATCHDOG_PID")
    if pid and pid != str(os.getpid()):
        return None
    try:
        value = int(usec)
    except ValueError:
        log.warning("WATCHDOG_USEC=%r is not an integer; watchdog disabled", usec)
        return None
    return value / 1e6 if value > 0 else None
