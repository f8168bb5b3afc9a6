"""Byte transports under the MAVLink layer, chosen from a URL.

A :class:`Transport` writes bytes, reads bytes with a timeout and closes; nothing more. The link
(``firmware_interface.link``) puts pymavlink's codec on top of it, so a serial port, a pty, a
UDP socket and a TCP connection are interchangeable.

Accepted URLs (the forms MAVProxy / pymavlink users already type)::

    /dev/ttyACM0,921600                serial device and baud
    serial:///dev/ttyACM0?baud=921600  the same as a URL
    udpin:0.0.0.0:14550                listen on UDP; replies go to the autopilot's address
    udp:0.0.0.0:14550                  alias of udpin (as in pymavlink)
    udpout:192.168.1.10:14550          send to this address; accept datagrams from it only
    tcp:127.0.0.1:5760                 TCP client

**Who may talk to us over UDP.** A datagram socket hears anyone who can reach its port, so:

* ``udpout`` binds the local address the kernel would send from towards the peer (found with a
  ``connect()`` of a probe socket, which sends nothing): ``127.0.0.1`` for a peer on loopback,
  the right interface's address otherwise, never ``0.0.0.0``; and it keeps only datagrams whose
  source is exactly the configured ``HOST:PORT`` (ArduPilot's, MAVProxy's and mavlink-router's
  UDP servers answer from the port they listen on). Others are dropped and counted in
  :attr:`Transport.foreign_datagrams`. The socket is not ``connect()``-ed itself: a connected
  UDP socket reports ICMP "port unreachable" as errors on later calls, which would turn an
  autopilot not yet listening into transport failures and reopen cycles.
* ``udpin`` cannot know its peer in advance. It never changes its peer by itself:
  :meth:`UdpInTransport.read_from` returns each datagram with its sender, and the link (which
  decodes) calls :meth:`UdpInTransport.set_peer` only for a valid frame from the pinned
  autopilot (correctly signed when signing is on); see ``link.MavlinkLink``. Garbage, or frames
  from anyone else, never change where we send.

Every OS-level failure is re-raised as :class:`~firmware_interface.errors.TransportError` with the
original ``serial.SerialException`` / ``OSError`` as its ``__cause__``.
"""

from __future__ import annotations

import abc
import logging
import select
import socket
from collections.abc import Callable
from dataclasses import dataclass
from urllib.parse import parse_qs, urlsplit

import serial

from firmware_interface.errors import InvalidUrl, TransportError

log = logging.getLogger(__name__)

URL_FORMS = (
    "DEVICE,BAUD (e.g. /dev/ttyACM0,921600)",
    "serial://DEVICE?baud=BAUD (e.g. serial:///dev/ttyACM0?baud=921600)",
    "udpin:HOST:PORT",
    "udp:HOST:PORT (alias of udpin)",
    "udpout:HOST:PORT",
    "tcp:HOST:PORT",
    "MAVSDK's udp://[HOST]:PORT, udpin://, udpout://, tcp://HOST:PORT, serial://DEVICE:BAUD",
)
MAX_BAUD = 12_000_000
_READ_CHUNK = 4096


Address = tuple[str, int]


class Transport(abc.ABC):
    """A bidirectional byte pipe. Not thread-safe by itself: the link serialises writers and
    keeps a single reader.

    ``datagrams``: each read returns whole datagrams, one at a time (a frame never spans two,
    so the link parses each on its own). ``foreign_datagrams`` counts datagrams dropped because
    they came from an address we do not talk to."""

    description: str = "transport"
    datagrams: bool = False
    foreign_datagrams: int = 0

    @abc.abstractmethod
    def write(self, data: bytes) -> None:
        """Write all of ``data`` or raise :class:`TransportError`."""

    @abc.abstractmethod
    def read(self, timeout_s: float) -> bytes:
        """Return the bytes available within ``timeout_s`` (``b""`` if none arrived)."""

    def read_from(self, timeout_s: float) -> tuple[bytes, Address | None]:
        """As :meth:`read`, with the sender's address for a datagram transport (None for a
        byte stream, or when nothing arrived)."""
        return self.read(timeout_s), None

    def pending(self) -> bool:
        """Whether bytes received are waiting to be read (polled without reading: another
        thread than the reader may ask; default: unknown, False)."""
        return False

    @abc.abstractmethod
    def close(self) -> None:
        """Release the port or socket. Idempotent."""

    def __enter__(self) -> Transport:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"<{type(self).__name__} {self.description}>"


@dataclass(frozen=True)
class TransportSpec:
    """A parsed link URL. ``kind`` is one of ``serial``, ``udpin``, ``udpout``, ``tcp``."""

    kind: str
    address: str  # device path for serial, host otherwise
    port: int | None = None
    baud: int | None = None


def _invalid(url: str, why: str) -> InvalidUrl:
    return InvalidUrl(f"invalid link URL {url!r}: {why}; valid forms: {', '.join(URL_FORMS)}")


def _parse_baud(url: str, text: str) -> int:
    try:
        baud = int(text)
    except ValueError:
        raise _invalid(url, f"baud={text!r} is not an integer") from None
    if not 0 < baud <= MAX_BAUD:
        raise _invalid(url, f"baud={baud} outside [1, {MAX_BAUD}]")
    return baud


def _parse_host_port(url: str, kind: str, rest: str) -> TransportSpec:
    host, sep, port_text = rest.rpartition(":")
    if not sep or not host:
        raise _invalid(url, f"{kind} needs HOST:PORT")
    try:
        port = int(port_text)
    except ValueError:
        raise _invalid(url, f"port={port_text!r} is not an integer") from None
    low = 0 if kind == "udpin" else 1  # only a listener may let the OS choose its port
    if not low <= port <= 65535:
        raise _invalid(url, f"port={port} outside [{low}, 65535] for {kind}")
    return TransportSpec(kind=kind, address=host, port=port)


def parse_url(url: str) -> TransportSpec:
    """Parse a link URL into a :class:`TransportSpec`, or raise :class:`InvalidUrl`."""
    if not isinstance(url, str) or not url.strip():
        raise _invalid(str(url), "empty")
    url = url.strip()
    if url.startswith("serial://"):
        parts = urlsplit(url)
        device = parts.netloc + parts.path
        query = parse_qs(parts.query)
        if "baud" not in query:
            # MAVSDK's form: serial:///dev/ttyACM0:921600
            path, colon, baud_text = device.rpartition(":")
            if not (colon and baud_text.isdigit()):
                raise _invalid(url, "missing ?baud=N")
            device, query = path, {"baud": [baud_text]}
        if not device:
            raise _invalid(url, "no serial device")
        baud = _parse_baud(url, query["baud"][-1])
        return TransportSpec(kind="serial", address=device, baud=baud)
    scheme, sep, rest = url.partition(":")
    if sep and scheme in _HOST_PORT_SCHEMES:
        kind = _HOST_PORT_SCHEMES[scheme]
        if rest.startswith("//"):
            # MAVSDK's forms: udp://:14540 and udpin://0.0.0.0:14540 listen (an empty host:
            # every interface), udpout://HOST:PORT and tcp://HOST:PORT connect.
            rest = rest[2:]
            if kind == "udpin" and rest.startswith(":"):
                rest = "0.0.0.0" + rest
        return _parse_host_port(url, kind, rest)
    if "," in url and "://" not in url:
        device, _, baud_text = url.rpartition(",")
        if not device:
            raise _invalid(url, "no serial device")
        return TransportSpec(kind="serial", address=device, baud=_parse_baud(url, baud_text))
    if sep and "/" not in scheme:
        raise _invalid(url, f"unknown scheme {scheme!r}")
    raise _invalid(url, "not a recognised form")


_HOST_PORT_SCHEMES = {"udpin": "udpin", "udp": "udpin", "udpout": "udpout", "tcp": "tcp"}


class SerialTransport(Transport):
    """A serial port (or pty) through pyserial."""

    def __init__(self, device: str, baud: int, *, write_timeout_s: float = 1.0) -> None:
        self.description = f"{device},{baud}"
        try:
            self._port = serial.Serial(
                device, baud, timeout=0.1, write_timeout=write_timeout_s, exclusive=True
            )
        except (serial.SerialException, OSError, ValueError) as exc:
            raise TransportError(f"cannot open serial port {self.description}: {exc}") from exc
        self._read_timeout_s = 0.1

    def write(self, data: bytes) -> None:
        try:
            self._port.write(data)
        except (serial.SerialException, OSError) as exc:
            raise TransportError(f"write to {self.description} failed: {exc}") from exc

    def read(self, timeout_s: float) -> bytes:
        try:
            if timeout_s != self._read_timeout_s:
                self._port.timeout = timeout_s
                self._read_timeout_s = timeout_s
            data = self._port.read(1)
            if data:
                waiting = self._port.in_waiting
                if waiting:
                    data += self._port.read(min(waiting, _READ_CHUNK))
            return bytes(data)
        except (serial.SerialException, OSError, TypeError) as exc:
            # pyserial raises TypeError when the fd vanished under it during a read.
            raise TransportError(f"read from {self.description} failed: {exc}") from exc

    def pending(self) -> bool:
        try:
            return bool(self._port.in_waiting)
        except (serial.SerialException, OSError, TypeError, ValueError):
            return False

    def close(self) -> None:
        try:
            self._port.close()
        except (serial.SerialException, OSError) as exc:
            log.debug("closing %s: %s", self.description, exc)


class _SocketTransport(Transport):
    _sock: socket.socket

    @property
    def local_address(self) -> tuple[str, int]:
        """The ``(host, port)`` this socket is bound to (useful with port 0)."""
        return self._sock.getsockname()[:2]

    def _wait_readable(self, timeout_s: float) -> bool:
        try:
            readable, _, _ = select.select([self._sock], [], [], max(0.0, timeout_s))
        except (OSError, ValueError) as exc:
            raise TransportError(f"{self.description}: {exc}") from exc
        return bool(readable)

    def pending(self) -> bool:
        try:
            readable, _, _ = select.select([self._sock], [], [], 0.0)
        except (OSError, ValueError):
            return False
        return bool(readable)

    def _recv_datagram(self, timeout_s: float) -> tuple[bytes, tuple[str, int] | None]:
        """One datagram and its sender, or ``(b"", None)`` when none arrived in time."""
        if not self._wait_readable(timeout_s):
            return b"", None
        try:
            return self._sock.recvfrom(65535)
        except OSError as exc:
            raise TransportError(f"receive on {self.description} failed: {exc}") from exc

    def close(self) -> None:
        self._sock.close()


class UdpInTransport(_SocketTransport):
    """Listen on a UDP port; send to the peer the link chose (:meth:`set_peer`).

    Unlike MAVProxy's ``udpin``, a datagram never moves the peer by itself: only the link,
    having decoded a valid frame from the pinned autopilot in it, does (module docstring)."""

    datagrams = True

    def __init__(self, host: str, port: int) -> None:
        self.description = f"udpin:{host}:{port}"
        self._peer: Address | None = None
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            self._sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            self._sock.bind((host, port))
        except OSError as exc:
            self._sock.close()
            raise TransportError(f"cannot bind {self.description}: {exc}") from exc

    @property
    def peer(self) -> Address | None:
        """Where our writes go; None until the link chose one."""
        return self._peer

    def set_peer(self, address: Address) -> None:
        """Send to ``address`` from now on (the link calls this; see the module docstring)."""
        self._peer = (address[0], address[1])

    def write(self, data: bytes) -> None:
        if self._peer is None:
            log.debug("%s: no peer yet, %d bytes dropped", self.description, len(data))
            return
        try:
            self._sock.sendto(data, self._peer)
        except OSError as exc:
            raise TransportError(f"send on {self.description} failed: {exc}") from exc

    def read(self, timeout_s: float) -> bytes:
        return self.read_from(timeout_s)[0]

    def read_from(self, timeout_s: float) -> tuple[bytes, Address | None]:
        data, sender = self._recv_datagram(timeout_s)
        return data, (sender[0], sender[1]) if sender is not None else None


def local_address_towards(host: str, port: int) -> str:
    """The local IPv4 address the kernel sends from towards ``host:port`` (a ``connect()`` on
    a UDP probe socket picks the route and sends nothing)."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
        probe.connect((host, port))
        return str(probe.getsockname()[0])


class UdpOutTransport(_SocketTransport):
    """Send to a fixed UDP address; read only the datagrams that come from it.

    Bound to the local address that routes to the peer, on an ephemeral port (module
    docstring); datagrams from any other address are dropped and counted."""

    datagrams = True

    def __init__(self, host: str, port: int) -> None:
        self.description = f"udpout:{host}:{port}"
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            self._target: Address = (socket.gethostbyname(host), port)
            self._sock.bind((local_address_towards(*self._target), 0))
        except OSError as exc:
            self._sock.close()
            raise TransportError(f"cannot set up {self.description}: {exc}") from exc

    @property
    def peer(self) -> Address:
        """The configured peer: where we send, and the only source we read."""
        return self._target

    def write(self, data: bytes) -> None:
        try:
            self._sock.sendto(data, self._target)
        except OSError as exc:
            raise TransportError(f"send on {self.description} failed: {exc}") from exc

    def read(self, timeout_s: float) -> bytes:
        return self.read_from(timeout_s)[0]

    def read_from(self, timeout_s: float) -> tuple[bytes, Address | None]:
        data, sender = self._recv_datagram(timeout_s)
        if sender is None:
            return b"", None
        if (sender[0], sender[1]) != self._target:
            self.foreign_datagrams += 1
            log.debug("%s: datagram from %s:%d dropped", self.description, *sender[:2])
            return b"", None
        return data, self._target


class TcpTransport(_SocketTransport):
    """A TCP client connection (e.g. to SITL's ``tcp:127.0.0.1:5760``)."""

    def __init__(
        self, host: str, port: int, *, connect_timeout_s: float = 5.0, send_timeout_s: float = 1.0
    ) -> None:
        self.description = f"tcp:{host}:{port}"
        try:
            self._sock = socket.create_connection((host, port), timeout=connect_timeout_s)
        except OSError as exc:
            raise TransportError(f"cannot connect {self.description}: {exc}") from exc
        self._sock.settimeout(send_timeout_s)
        self._sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)

    def write(self, data: bytes) -> None:
        try:
            self._sock.sendall(data)
        except OSError as exc:
            raise TransportError(f"send on {self.description} failed: {exc}") from exc

    def read(self, timeout_s: float) -> bytes:
        if not self._wait_readable(timeout_s):
            return b""
        try:
            data = self._sock.recv(_READ_CHUNK)
        except OSError as exc:
            raise TransportError(f"receive on {self.description} failed: {exc}") from exc
        if not data:
            raise TransportError(f"{self.description}: connection closed by peer")
        return data


def _open_serial(spec: TransportSpec) -> Transport:
    assert spec.baud is not None
    return SerialTransport(spec.address, spec.baud)


def _open_udpin(spec: TransportSpec) -> Transport:
    assert spec.port is not None
    return UdpInTransport(spec.address, spec.port)


def _open_udpout(spec: TransportSpec) -> Transport:
    assert spec.port is not None
    return UdpOutTransport(spec.address, spec.port)


def _open_tcp(spec: TransportSpec) -> Transport:
    assert spec.port is not None
    return TcpTransport(spec.address, spec.port)


#: One opener per transport kind; ``parse_url`` produces only these kinds.
OPENERS: dict[str, Callable[[TransportSpec], Transport]] = {
    "serial": _open_serial,
    "udpin": _open_udpin,
    "udpout": _open_udpout,
    "tcp": _open_tcp,
}


def open_transport(url: str | TransportSpec) -> Transport:
    """Open the transport a URL (or an already parsed spec) describes."""
    spec = parse_url(url) if isinstance(url, str) else url
    try:
        opener = OPENERS[spec.kind]
    except KeyError:
        raise InvalidUrl(
            f"unknown transport kind {spec.kind!r}; valid kinds: {sorted(OPENERS)}"
        ) from None
    return opener(spec)
