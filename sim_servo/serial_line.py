"""A serial line's bandwidth, for a pty link: bytes take ``10 / baud`` seconds each, both ways.

A pseudo-terminal moves bytes at memory speed whatever baud rate its URL names; a flight
controller's TELEM port at 57 600 or 115 200 baud does not (8N1: a start bit, 8 data bits and a
stop bit per byte, so 44 bytes take 7.6 ms at 57 600). :class:`SerialLine` is one direction of
such a line, pure (times are given): bytes queue behind those still on the wire and come out
when their last bit would have. :class:`SerialLineEndpoint` puts one on each side of a
:class:`~sim_servo.endpoints.PtyEndpoint`:

* **to the autopilot** (what the daemon writes): the pty hands us the bytes at once; they reach
  the autopilot's parser frame by frame, each when its last byte would have arrived, so the
  first of six back-to-back commands is handled while the sixth is still on the wire;
* **from the autopilot**: each frame is written to the pty when its last byte would have left.
  The UART's transmit buffer is bounded, ``tx_buffer_bytes`` (ArduPilot opens a MAVLink port
  with 256 bytes, ``AP_SERIALMANAGER_MAVLINK_BUFSIZE_TX`` in AP_SerialManager.h): a frame waits
  behind the bytes queued before it, and one that does not fit is dropped and counted, as
  ArduPilot's ``comm_send_buffer`` drops a message without room.

The daemon's own UART transmit buffer (the kernel's) is large: nothing is dropped towards the
autopilot. No hardware flow control is modelled.
"""

from __future__ import annotations

import math
import time
from collections import deque
from collections.abc import Callable

from sim_servo.endpoints import Endpoint

#: 8N1: start bit, eight data bits, stop bit.
BITS_PER_BYTE = 10
#: AP_SerialManager.h: AP_SERIALMANAGER_MAVLINK_BUFSIZE_TX.
ARDUPILOT_MAVLINK_TX_BUFFER_BYTES = 256
#: Serial rates a flight controller's SERIALn_BAUD offers (pyserial accepts these too).
MIN_BAUD = 1200
MAX_BAUD = 12_000_000


def byte_time_s(baud: int) -> float:
    """Seconds one byte takes on the wire at ``baud`` (8N1)."""
    return BITS_PER_BYTE / baud


class FrameSplitter:
    """Finds where MAVLink frames end in a byte stream (v1 ``0xFE``: len + 8 bytes; v2
    ``0xFD``: len + 12, + 13 when signed), across chunk boundaries. Bytes between frames
    (garbage) are never a frame of their own: they go with what follows."""

    def __init__(self) -> None:
        self._head = bytearray()  # the start of a header: magic, len, incompat flags
        self._need = 0  # bytes still to come of the current frame

    def cuts(self, data: bytes) -> list[int]:
        """Offsets in ``data`` just past each frame that ends in it."""
        cuts: list[int] = []
        i = 0
        while i < len(data):
            if self._need:
                take = min(self._need, len(data) - i)
                i += take
                self._need -= take
                if not self._need:
                    cuts.append(i)
                continue
            byte = data[i]
            i += 1
            if not self._head and byte not in (0xFD, 0xFE):
                continue
            self._head.append(byte)
            magic = self._head[0]
            if magic == 0xFE and len(self._head) == 2:
                total = self._head[1] + 8
            elif magic == 0xFD and len(self._head) == 3:
                total = self._head[1] + 12 + (13 if self._head[2] & 0x01 else 0)
            else:
                continue
            self._need = total - len(self._head)
            self._head.clear()
        return cuts


class SerialLine:
    """One direction of a UART at ``baud`` (8N1), optionally with a bounded transmit buffer.

    :meth:`send` queues bytes written at ``now_s``; they come out of :meth:`take` once their
    last byte has crossed the line. With ``split_frames`` each MAVLink frame comes out on its
    own, when its own last byte arrives."""

    def __init__(
        self, baud: int, *, buffer_bytes: int | None = None, split_frames: bool = False
    ) -> None:
        if isinstance(baud, bool) or not isinstance(baud, int) or not MIN_BAUD <= baud <= MAX_BAUD:
            raise ValueError(f"baud={baud!r} outside [{MIN_BAUD}, {MAX_BAUD}]")
        if buffer_bytes is not None and buffer_bytes < 1:
            raise ValueError(f"buffer_bytes={buffer_bytes!r} must be >= 1")
        self.baud = baud
        self.byte_s = byte_time_s(baud)
        self.buffer_bytes = buffer_bytes
        self._splitter = FrameSplitter() if split_frames else None
        self._free_s = -math.inf  # when the last byte queued so far is through
        self._queue: deque[tuple[float, bytes]] = deque()
        self.dropped = 0
        self.bytes_sent = 0

    def queued_bytes(self, now_s: float) -> float:
        """Bytes written but not yet through the line at ``now_s``."""
        return max(0.0, (self._free_s - now_s) / self.byte_s)

    def send(self, data: bytes, now_s: float) -> bool:
        """Queue ``data`` written at ``now_s``; False (dropped, counted) if it does not fit."""
        if not data:
            return True
        if (
            self.buffer_bytes is not None
            and self.queued_bytes(now_s) + len(data) > self.buffer_bytes + 1e-9
        ):
            self.dropped += 1
            return False
        start_s = max(now_s, self._free_s)
        cuts = self._splitter.cuts(data) if self._splitter is not None else []
        if not cuts or cuts[-1] != len(data):
            cuts.append(len(data))
        begin = 0
        for end in cuts:
            self._queue.append((start_s + end * self.byte_s, data[begin:end]))
            begin = end
        self._free_s = start_s + len(data) * self.byte_s
        self.bytes_sent += len(data)
        return True

    def next_event_s(self) -> float | None:
        """When :meth:`take` next has something, or None."""
        return self._queue[0][0] if self._queue else None

    def take(self, now_s: float) -> list[bytes]:
        """The pieces whose last byte is through by ``now_s``, in order."""
        out: list[bytes] = []
        while self._queue and self._queue[0][0] <= now_s:
            out.append(self._queue.popleft()[1])
        return out

    def clear(self) -> None:
        """Forget everything queued (the port closed)."""
        self._queue.clear()
        self._free_s = -math.inf
        self._splitter = FrameSplitter() if self._splitter is not None else None


class SerialLineEndpoint(Endpoint):
    """A pty endpoint behind a serial line of ``baud`` each way (see the module docstring).

    The server calls :meth:`service` on every pass (and wakes for :meth:`next_event_s`): it
    writes the frames whose bytes have left, and returns the bytes that have arrived, which
    :meth:`read_ready` only queued."""

    def __init__(
        self,
        inner: Endpoint,
        baud: int,
        *,
        tx_buffer_bytes: int = ARDUPILOT_MAVLINK_TX_BUFFER_BYTES,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.inner = inner
        self.clock = clock
        self.rx = SerialLine(baud, split_frames=True)
        self.tx = SerialLine(baud, buffer_bytes=tx_buffer_bytes)
        self.dropped_writes = 0
        self.url = inner.url

    def fds(self) -> list[int]:
        return self.inner.fds()

    def read_ready(self, fd: int) -> bytes:
        data = self.inner.read_ready(fd)
        if data:
            self.rx.send(data, self.clock())
        return b""

    def write(self, frame: bytes) -> None:
        if self.inner.closed or not self.tx.send(frame, self.clock()):
            self.dropped_writes += 1

    def next_event_s(self) -> float | None:
        due = [t for t in (self.rx.next_event_s(), self.tx.next_event_s()) if t is not None]
        return min(due) if due else None

    def service(self, now_s: float) -> bytes:
        for frame in self.tx.take(now_s):
            before = self.inner.dropped_writes
            self.inner.write(frame)
            self.dropped_writes += self.inner.dropped_writes - before
        return b"".join(self.rx.take(now_s))

    def close(self) -> None:
        self.rx.clear()
        self.tx.clear()
        self.inner.close()

    def reopen(self) -> None:
        self.inner.reopen()
