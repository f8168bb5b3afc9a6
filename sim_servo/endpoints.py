"""The simulator's side of the link: a UDP socket, a TCP listener or a pseudo-terminal.

Each endpoint exposes the file descriptors to wait on (:meth:`Endpoint.fds`), reads what one of
them has (:meth:`Endpoint.read_ready`), writes whole frames and can *hang up* (close the port,
the ``--hangup-after`` fault). A pty can also come back (:meth:`Endpoint.reopen`, the
``--hangup-for`` fault) as a new device, like a USB serial adapter re-enumerating. They never
block: a frame that cannot be written now is dropped and counted, as bytes sent to an unread
serial port are lost.

``url`` is what the daemon should be given to reach us (a link URL in the form the daemon's
``link.url`` setting takes): ``udpout:HOST:PORT``, ``tcp:HOST:PORT``, ``/dev/pts/N,115200`` or, with
a stable link name (``--pty-link``), ``PATH,115200``; for :class:`UdpOutEndpoint`, which sends to
a companion that listens, ``udpin:HOST:PORT`` (the address the daemon must listen on).
"""

from __future__ import annotations

import abc
import errno
import logging
import os
import socket
import tty

from sim_servo.errors import SimIOError

log = logging.getLogger(__name__)
PTY_BAUD = 115200
_READ_CHUNK = 65535


class Endpoint(abc.ABC):
    url: str
    dropped_writes: int = 0

    @abc.abstractmethod
    def fds(self) -> list[int]:
        """The descriptors to wait on for reading (empty once closed)."""

    @abc.abstractmethod
    def read_ready(self, fd: int) -> bytes:
        """Handle readability of ``fd`` (one of :meth:`fds`); the bytes received, maybe b""."""

    @abc.abstractmethod
    def write(self, frame: bytes) -> None:
        """Send one frame now, or drop it (no peer, buffer full, closed)."""

    @abc.abstractmethod
    def close(self) -> None:
        """Release everything; idempotent. Used for shutdown and for the hang-up fault."""

    def next_event_s(self) -> float | None:
        """When :meth:`service` next has work (a modelled serial line); None: never."""
        return None

    def service(self, now_s: float) -> bytes:
        """Timed work due by ``now_s`` (a modelled serial line: frames whose bytes have left
        are written); the bytes received that are due now. Plain endpoints have none."""
        return b""

    def reopen(self) -> None:
        """Come back after a hang-up (the ``--hangup-for`` fault); only a pty can."""
        raise SimIOError(f"{type(self).__name__} cannot reopen after a hang-up (only --pty can)")

    @property
    def closed(self) -> bool:
        return not self.fds()


class UdpEndpoint(Endpoint):
    """Listens on HOST:PORT (0: any free port); replies go to the last sender, as ArduPilot's
    SITL and MAVProxy's ``udpin`` do."""

    def __init__(self, host: str, port: int) -> None:
        self._sock: socket.socket | None = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            self._sock.bind((host, port))
        except OSError as exc:
            self._sock.close()
            raise SimIOError(f"cannot bind UDP {host}:{port}: {exc}") from exc
        self._sock.setblocking(False)
        bound_host, bound_port = self._sock.getsockname()[:2]
        self.url = f"udpout:{bound_host}:{bound_port}"
        self.peer: tuple[str, int] | None = None

    def fds(self) -> list[int]:
        return [self._sock.fileno()] if self._sock is not None else []

    def read_ready(self, fd: int) -> bytes:
        if self._sock is None:
            return b""
        try:
            data, self.peer = self._sock.recvfrom(_READ_CHUNK)
        except (BlockingIOError, InterruptedError):
            return b""
        except OSError as exc:  # e.g. ICMP port unreachable from a vanished peer
            log.debug("UDP receive: %s", exc)
            return b""
        return data

    def write(self, frame: bytes) -> None:
        if self._sock is None or self.peer is None:
            self.dropped_writes += 1
            return
        try:
            self._sock.sendto(frame, self.peer)
        except OSError as exc:
            self.dropped_writes += 1
            log.debug("UDP send: %s", exc)

    def close(self) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None


class UdpOutEndpoint(Endpoint):
    """Sends to HOST:PORT from a port of its own (``bind_port``, 0: any free one), as real PX4
    and ArduPilot SITL connect out to a companion (PX4: ``mavlink start -o PORT``, frames to
    14540 by default); the companion listens (``udpin:HOST:PORT``).

    Datagrams are read from any sender. The first one re-aims our frames at its sender, once
    (PX4's ``mavlink_receiver``: the client's source address is adopted from the first frame
    and then kept); later senders are read but never move it. Until a companion listens, the
    frames we send are lost, as UDP loses them (a refused send is counted, never raised)."""

    def __init__(self, host: str, port: int, bind_port: int = 0) -> None:
        self._sock: socket.socket | None = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            # Bound to the address that routes to the companion (127.0.0.1 for a local one).
            self._sock.bind((_local_address_for(host), bind_port))
        except OSError as exc:
            self._sock.close()
            raise SimIOError(f"cannot bind UDP for {host}:{port}: {exc}") from exc
        self._sock.setblocking(False)
        self.local = self._sock.getsockname()[:2]
        self.url = f"udpin:{host}:{port}"
        self.peer: tuple[str, int] = (host, port)
        self._adopted = False

    def fds(self) -> list[int]:
        return [self._sock.fileno()] if self._sock is not None else []

    def read_ready(self, fd: int) -> bytes:
        if self._sock is None:
            return b""
        try:
            data, sender = self._sock.recvfrom(_READ_CHUNK)
        except (BlockingIOError, InterruptedError):
            return b""
        except OSError as exc:  # ICMP port unreachable: nobody listens there (yet)
            log.debug("UDP receive: %s", exc)
            return b""
        if not self._adopted:
            self.peer, self._adopted = sender[:2], True
        return data

    def write(self, frame: bytes) -> None:
        if self._sock is None:
            self.dropped_writes += 1
            return
        try:
            self._sock.sendto(frame, self.peer)
        except OSError as exc:  # e.g. ECONNREFUSED reported from an earlier datagram
            self.dropped_writes += 1
            log.debug("UDP send: %s", exc)

    def close(self) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None


def _local_address_for(host: str) -> str:
    """The local address the kernel would send to ``host`` from (no packet is sent)."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
        try:
            probe.connect((host, 9))
        except OSError as exc:
            raise SimIOError(f"no route to {host}: {exc}") from exc
        return str(probe.getsockname()[0])


class TcpEndpoint(Endpoint):
    """Listens on HOST:PORT for one client at a time (a new client replaces the old one)."""

    def __init__(self, host: str, port: int) -> None:
        self._listener: socket.socket | None = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        try:
            self._listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            self._listener.bind((host, port))
            self._listener.listen(1)
        except OSError as exc:
            self._listener.close()
            raise SimIOError(f"cannot listen on TCP {host}:{port}: {exc}") from exc
        self._listener.setblocking(False)
        bound_host, bound_port = self._listener.getsockname()[:2]
        self.url = f"tcp:{bound_host}:{bound_port}"
        self._client: socket.socket | None = None

    def fds(self) -> list[int]:
        fds = [s.fileno() for s in (self._listener, self._client) if s is not None]
        return fds

    def read_ready(self, fd: int) -> bytes:
        if self._listener is not None and fd == self._listener.fileno():
            try:
                client, _ = self._listener.accept()
            except (BlockingIOError, InterruptedError):
                return b""
            if self._client is not None:
                self._client.close()
            client.setblocking(False)
            client.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            self._client = client
            return b""
        if self._client is None:
            return b""
        try:
            data = self._client.recv(_READ_CHUNK)
        except (BlockingIOError, InterruptedError):
            return b""
        except OSError as exc:
            log.debug("TCP receive: %s", exc)
            data = b""
        if not data:  # the client went away; wait for the next one
            self._client.close()
            self._client = None
        return data

    def write(self, frame: bytes) -> None:
        if self._client is None:
            self.dropped_writes += 1
            return
        try:
            sent = self._client.send(frame)
        except (BlockingIOError, InterruptedError):
            sent = 0
        except OSError as exc:
            log.debug("TCP send: %s", exc)
            sent = 0
        if sent < len(frame):
            # A partial frame would desynchronise the stream less than a lost one: count it.
            self.dropped_writes += 1

    def close(self) -> None:
        for sock in (self._client, self._listener):
            if sock is not None:
                sock.close()
        self._client = self._listener = None


class PtyEndpoint(Endpoint):
    """A pseudo-terminal: the daemon opens the slave device like a serial port.

    We keep our own slave descriptor open so the master never reads EIO while the daemon has not
    opened the device yet (or is reopening it), and put the line in raw mode so no byte is
    echoed or translated. Hanging up closes both ends: the daemon's reads then fail as on an
    unplugged USB serial port.

    ``link_path`` plays udev's stable name (``/dev/serial/by-id/...``): a symlink to the current
    ``/dev/pts/N``, and ``url`` names the link. It is removed at a hang-up, as udev removes it on
    unplug (a stale link could otherwise lead to another program's pty once N is reused), and
    :meth:`reopen` opens a new pty and creates the link again by renaming a fresh symlink over
    its name, so a reader never sees a half-made link.
    """

    def __init__(self, link_path: str | None = None, baud: int = PTY_BAUD) -> None:
        self.link_path = link_path
        if link_path is not None and os.path.lexists(link_path) and not os.path.islink(link_path):
            raise SimIOError(f"--pty-link {link_path!r} exists and is not a symlink")
        self._open = False
        self._open_pty()
        self.url = f"{link_path or self.path},{baud}"

    def _open_pty(self) -> None:
        try:
            self._master, self._slave = os.openpty()
        except OSError as exc:
            raise SimIOError(f"cannot open a pseudo-terminal: {exc}") from exc
        tty.setraw(self._slave)
        os.set_blocking(self._master, False)
        self.path = os.ttyname(self._slave)
        self._open = True
        if self.link_path is not None:
            fresh = f"{self.link_path}.{os.getpid()}.new"
            try:
                if os.path.lexists(fresh):
                    os.unlink(fresh)
                os.symlink(self.path, fresh)
                os.replace(fresh, self.link_path)  # atomic: old target or new, never neither
            except OSError as exc:
                self.close()
                raise SimIOError(
                    f"cannot point --pty-link {self.link_path!r} at {self.path}: {exc}"
                ) from exc

    def reopen(self) -> None:
        """A new pty (a new ``/dev/pts/N``), with the link pointing at it."""
        if not self._open:
            self._open_pty()

    def fds(self) -> list[int]:
        return [self._master] if self._open else []

    def read_ready(self, fd: int) -> bytes:
        if not self._open:
            return b""
        try:
            return os.read(self._master, _READ_CHUNK)
        except (BlockingIOError, InterruptedError):
            return b""
        except OSError as exc:
            if exc.errno == errno.EIO:
                return b""
            raise SimIOError(f"pty read: {exc}") from exc

    def write(self, frame: bytes) -> None:
        if not self._open:
            self.dropped_writes += 1
            return
        try:
            written = os.write(self._master, frame)
        except (BlockingIOError, InterruptedError):
            written = 0
        except OSError as exc:
            log.debug("pty write: %s", exc)
            written = 0
        if written < len(frame):
            self.dropped_writes += 1

    def close(self) -> None:
        if self._open:
            self._open = False
            if self.link_path is not None:
                try:
                    if os.readlink(self.link_path) == self.path:
                        os.unlink(self.link_path)
                except OSError as exc:
                    log.debug("removing %s: %s", self.link_path, exc)
            for fd in (self._master, self._slave):
                try:
                    os.close(fd)
                except OSError:
                    pass


def parse_host_port(text: str, option: str) -> tuple[str, int]:
    """``HOST:PORT`` → (host, port); port 0 lets the OS choose."""
    host, sep, port_text = text.rpartition(":")
    if not sep or not host:
        raise SimIOError(f"{option}={text!r} must be HOST:PORT")
    try:
        port = int(port_text)
    except ValueError:
        raise SimIOError(f"{option}={text!r}: port {port_text!r} is not an integer") from None
    if not 0 <= port <= 65535:
        raise SimIOError(f"{option}={text!r}: port={port} outside [0, 65535]")
    return host, port
