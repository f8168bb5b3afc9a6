"""The MAVLink link to the flight controller: heartbeat, one reader, one serialised writer.

pymavlink's generated MAVLink 2 codec (``pymavlink.dialects.v20.ardupilotmega``) runs on top of a
:class:`~firmware_interface.transport.Transport`. The threads are kept apart from the protocol:

* the **reader thread** owns the transport: it reads bytes, feeds the decoder, dispatches each
  message to subscribers, and reopens the transport with exponential backoff when it fails
  (a serial port that vanished). An exception in protocol code or in a subscriber callback ends
  the link cleanly: it is logged, kept as :attr:`MavlinkLink.failure`, and every later call
  raises :class:`LinkClosed` with it as the cause.
* the **heartbeat thread** sends HEARTBEAT (MAV_TYPE_ONBOARD_CONTROLLER / MAV_AUTOPILOT_INVALID)
  at ``heartbeat_rate_hz`` from start-up — ArduPilot routes to a component only after hearing
  it — and publishes link-state changes.
* every writer goes through :meth:`MavlinkLink.send`, which holds one lock while packing and
  writing: pymavlink's encoder (sequence number, signing timestamp) is not thread-safe. Encoding
  and decoding use two separate codec objects for the same reason.

Link state (:class:`LinkState`) is computed from the injected ``clock``: UP while the autopilot's
HEARTBEAT was heard within ``loss_timeout_s``, LOST after, WAITING before the first one. An
autopilot HEARTBEAT comes once a second: while the link is not up (a start, a reopen, a
loss), another frame from the autopilot's component (its streams flow on, asked for by an
earlier run) makes the link ask that system for one at once (MAV_CMD_REQUEST_MESSAGE, at most
every ``HEARTBEAT_ASK_INTERVAL_S``): the link comes up within a round trip, not up to a second
later. Only a HEARTBEAT pins the autopilot, as before. It is
also LOST while the transport is down, and after a reopen until a HEARTBEAT arrives on the new
port: a serial adapter that re-enumerated often means a flight controller that rebooted. It is
FAULT while signing is on and its state cannot be stored (:attr:`MavlinkLink.fault` says why):
nothing signed goes out then, so the link is as unusable as a lost one.

**Datagrams and the UDP peer.** On a datagram transport each datagram is parsed on its own (a
partial frame left by one sender never swallows the start of the next datagram). On ``udpin``
the link chooses where to send: the sender of a datagram holding a valid frame from the pinned
autopilot (its HEARTBEAT pins it: configured ids, else the first autopilot heard), signed when
signing is on (an unsigned RADIO_STATUS let through by ``allow_unsigned_msg_ids`` does not
count). Once a peer is chosen, datagrams from other addresses are dropped (counted in
``rx_foreign_address``), except a valid autopilot frame after the current peer has sent none for
``PEER_HOLD_S``: an autopilot that came back from another port (a reboot) is followed, a
spoofer racing a live one is not. With signing, until a peer is confirmed (an accepted
autopilot frame came from it), a correctly signed autopilot frame refused only for being older
than our start also chooses the peer: the autopilot must hear our newer timestamp to adopt it
(``signing`` module docstring), and on udpin it hears us only once we send to it. A replayer
can delay that bootstrap, not move the arm. Without signing, a host that forges the
autopilot's ids can still take its place once the autopilot falls silent: sign links other
hosts can reach.
"""

from __future__ import annotations

import enum
import hashlib
import logging
import os
import queue
import threading
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any, Protocol

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from firmware_interface.errors import (
    ConfigurationError,
    LinkClosed,
    LinkError,
    LinkTimeout,
    SigningStateError,
    TransportError,
)
from firmware_interface.signing import (
    FUTURE_LIMIT_S,
    NEW_STREAM_WINDOW_TICKS,
    TICKS_PER_S,
    SigningConfig,
    SigningLockout,
    TimestampKeeper,
    lockout_message,
)
from firmware_interface.transport import (
    Address,
    Transport,
    UdpInTransport,
    open_transport,
    parse_url,
)

log = logging.getLogger(__name__)

Clock = Callable[[], float]
#: Frames refused as from the future kept between two reads (the latest matter; a flood of
#: them is counted, not kept).
FUTURE_KEPT = 64


class MavMessage(Protocol):
    """What the link and its users rely on in a pymavlink message (``MAVLink_message``, which
    has no type information). Its fields (``msg.command``, ``msg.param1`` …) depend on the message
    type and are read through ``__getattr__``, so they are ``Any``."""

    def get_type(self) -> str: ...
    def get_srcSystem(self) -> int: ...
    def get_srcComponent(self) -> int: ...
    def pack(self, mav: Any, force_mavlink1: bool = False) -> bytes: ...
    def __getattr__(self, name: str) -> Any: ...


#: Our HEARTBEAT identity.
DEFAULT_COMPONENT_ID = mavlink.MAV_COMP_ID_ONBOARD_COMPUTER  # 191
#: Used as our own system id until the vehicle's is learned (ArduPilot's SYSID_THISMAV default).
PROVISIONAL_SYSTEM_ID = 1
_NOT_AN_AUTOPILOT_TYPES = frozenset(
    {mavlink.MAV_TYPE_GCS, mavlink.MAV_TYPE_ONBOARD_CONTROLLER, mavlink.MAV_TYPE_GIMBAL}
)
_MAVLINK_IFLAG_SIGNED = 0x01
#: On udpin, a valid autopilot frame from a new address moves the peer there only once the
#: current peer has sent none for this long: longer than the autopilot's 1 Hz HEARTBEAT period,
#: shorter than the shortest loss timeout (2 s).
PEER_HOLD_S = 1.5


def is_autopilot_heartbeat(msg: MavMessage) -> bool:
    """A HEARTBEAT from a flight controller (not a GCS, companion, gimbal or other device)."""
    return (
        msg.autopilot != mavlink.MAV_AUTOPILOT_INVALID and msg.type not in _NOT_AN_AUTOPILOT_TYPES
    )


#: :meth:`MavlinkLink.caught_up`: how long a caller waits at most for the reader, and how
#: often it looks (sleeping meanwhile, so the reader thread gets the interpreter).
#: Asking for a HEARTBEAT while the link is not up (module docstring): no more often than this.
HEARTBEAT_ASK_INTERVAL_S = 0.25
CATCH_UP_S = 0.005
CATCH_UP_POLL_S = 0.0002


class LinkState(enum.Enum):
    """Autopilot link state as seen from the companion."""

    WAITING = "waiting"  # no autopilot HEARTBEAT heard yet
    UP = "up"
    LOST = "lost"  # heard before, but nothing for loss_timeout_s
    FAULT = "fault"  # the link cannot send safely (see MavlinkLink.fault)
    CLOSED = "closed"


@dataclass(frozen=True)
class AutopilotInfo:
    """What the first autopilot HEARTBEAT told us."""

    system_id: int
    component_id: int
    autopilot: int  # MAV_AUTOPILOT
    vehicle_type: int  # MAV_TYPE


@dataclass(frozen=True)
class LinkStats:
    """Counters since the link started.

    ``rejected_replay``: correctly signed, but not newer than its stream's last frame, older
    than our start (after a restart) or over a minute behind; ``rejected_future``: correctly
    signed but over ``FUTURE_LIMIT_S`` ahead of our clock; ``rx_foreign_datagrams``: UDP
    datagrams dropped for their source address (udpout); ``rx_foreign_address``: frames from
    an address that is not the udpin peer, dropped; ``peer_changes``: udpin peer moves.
    """

    rx_messages: int
    rx_bad_frames: int
    rejected_unsigned: int
    rejected_bad_signature: int
    tx_messages: int
    reconnects: int
    transport_errors: int
    rejected_replay: int = 0
    rejected_future: int = 0
    rx_foreign_datagrams: int = 0
    rx_foreign_address: int = 0
    peer_changes: int = 0
    signing_state_errors: int = 0


@dataclass(frozen=True)
class LinkConfig:
    """Identity and timing of a link. ``None`` ids are learned from the autopilot HEARTBEAT."""

    system_id: int | None = None
    component_id: int = DEFAULT_COMPONENT_ID
    target_system: int | None = None
    target_component: int | None = None
    heartbeat_rate_hz: float = 1.0
    loss_timeout_s: float = 3.0
    read_timeout_s: float = 0.05
    reconnect_initial_s: float = 0.1
    # A failed reopen costs one open() (or one connect) attempt, so trying twice a second is
    # cheap; a longer cap would leave a re-enumerated serial port unused for seconds.
    reconnect_max_s: float = 0.5
    signing: SigningConfig | None = field(default=None, repr=False)

    def __post_init__(self) -> None:
        for label, value, low, high in (
            ("system_id", self.system_id, 1, 255),
            ("component_id", self.component_id, 1, 255),
            ("target_system", self.target_system, 1, 255),
            ("target_component", self.target_component, 1, 255),
        ):
            if value is not None and (not isinstance(value, int) or not low <= value <= high):
                raise ConfigurationError(f"{label}={value!r} outside [{low}, {high}]")
        for label, number in (
            ("heartbeat_rate_hz", self.heartbeat_rate_hz),
            ("loss_timeout_s", self.loss_timeout_s),
            ("read_timeout_s", self.read_timeout_s),
            ("reconnect_initial_s", self.reconnect_initial_s),
            ("reconnect_max_s", self.reconnect_max_s),
        ):
            if not isinstance(number, (int, float)) or not 0 < number < float("inf"):
                raise ConfigurationError(f"{label}={number!r} must be a positive finite number")


class Subscription:
    """A registered message callback; :meth:`cancel` removes it."""

    def __init__(
        self,
        link: MavlinkLink,
        callback: Callable[[MavMessage], None],
        types: frozenset[str] | None,
    ) -> None:
        self._link = link
        self.callback = callback
        self.types = types

    def matches(self, msg: MavMessage) -> bool:
        return self.types is None or msg.get_type() in self.types

    def cancel(self) -> None:
        self._link._remove_subscription(self)


class MessageQueue:
    """Incoming messages of chosen types, buffered for a consumer thread (e.g. COMMAND_LONG
    from a GCS). When full, new messages are dropped and counted in :attr:`dropped`."""

    def __init__(self, link: MavlinkLink, types: frozenset[str] | None, maxsize: int) -> None:
        self._queue: queue.Queue[MavMessage] = queue.Queue(maxsize)
        self.dropped = 0
        self._subscription = link.subscribe(self._put, types)

    def _put(self, msg: MavMessage) -> None:
        try:
            self._queue.put_nowait(msg)
        except queue.Full:
            self.dropped += 1
            log.warning("message queue full, %s dropped (%d so far)", msg.get_type(), self.dropped)

    def get(self, timeout_s: float) -> MavMessage:
        """The next message, waiting at most ``timeout_s``; raises :class:`LinkTimeout`."""
        try:
            return self._queue.get(timeout=timeout_s)
        except queue.Empty:
            raise LinkTimeout(f"no message within timeout_s={timeout_s}") from None

    def get_nowait(self) -> MavMessage | None:
        try:
            return self._queue.get_nowait()
        except queue.Empty:
            return None

    def close(self) -> None:
        self._subscription.cancel()

    def __enter__(self) -> MessageQueue:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()


class _Codec(mavlink.MAVLink):
    """pymavlink's codec, with our incoming signature rules (``signing`` module docstring).

    pymavlink's ``check_signature`` (2.4.x) records the incoming timestamp for its stream
    *before* comparing the signature, so one forged frame with a far-future timestamp would
    make every genuine frame of that stream look replayed. Here the signature is checked first,
    and nothing is recorded for a frame that fails any rule. The rules, in order:

    1. the 48-bit signature, ``sha256(key + frame without signature)[:6]`` (spec "Signature");
    2. with a ``keeper``: not more than ``FUTURE_LIMIT_S`` ahead of its local clock;
    3. a known stream ``(link id, system, component)``: newer than its last timestamp;
       a new stream: newer than ``stream_floor`` (just below our start timestamp), at most a minute
       behind our current timestamp (spec "Timestamp Handling");
    4. accepted: the stream's timestamp is recorded, ours moves up to it (spec, and pymavlink).

    Rejections are counted in :attr:`rejections` (``signature``, ``future``, ``replay``).
    """

    keeper: TimestampKeeper | None = None
    stream_floor = 0

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.rejections = {"signature": 0, "future": 0, "replay": 0}
        self.last_future: tuple[int, int, float] | None = None  # system, component, s ahead
        #: Sources of frames refused *only* for being older than our start (see take_stale).
        self._stale: list[tuple[int, int]] = []
        #: Frames refused as from the future: (system, component, timestamp, our local clock).
        self._future: list[tuple[int, int, int, int]] = []

    def check_signature(self, msgbuf: bytearray, srcSystem: int, srcComponent: int) -> bool:
        signing = self.signing
        assert signing.secret_key is not None
        if hashlib.sha256(signing.secret_key + msgbuf[:-6]).digest()[:6] != msgbuf[-6:]:
            self.rejections["signature"] += 1
            return False
        link_id = msgbuf[-13]
        timestamp = int.from_bytes(msgbuf[-12:-6], "little")
        keeper = self.keeper
        if keeper is not None:
            local = keeper.local_ticks()
            ahead = timestamp - local
            if ahead > FUTURE_LIMIT_S * TICKS_PER_S:
                self.rejections["future"] += 1
                self.last_future = (srcSystem, srcComponent, ahead / TICKS_PER_S)
                if len(self._future) < FUTURE_KEPT:
                    self._future.append((srcSystem, srcComponent, timestamp, local))
                return False
        stream = (link_id, srcSystem, srcComponent)
        last = signing.stream_timestamps.get(stream)
        if last is not None:
            fresh = timestamp > last
        else:
            fresh = timestamp > self.stream_floor
            if timestamp + NEW_STREAM_WINDOW_TICKS < signing.timestamp:
                fresh = False
            elif not fresh:
                self._stale.append((srcSystem, srcComponent))
        if not fresh:
            self.rejections["replay"] += 1
            return False
        signing.stream_timestamps[stream] = timestamp
        signing.timestamp = max(signing.timestamp, timestamp)
        return True

    def take_stale(self) -> list[tuple[int, int]]:
        """The ``(system, component)`` of correctly signed frames refused since the last call
        only because they are older than our start (a peer that has not yet adopted our
        timestamp, or a replay): a udpin link may send to their address meanwhile, so that
        the peer hears our timestamp (``MavlinkLink._receive``)."""
        stale, self._stale = self._stale, []
        return stale

    def take_future(self) -> list[tuple[int, int, int, int]]:
        """The frames refused as from the future since the last call (at most
        :data:`FUTURE_KEPT`): ``(system, component, their timestamp, our local clock)``."""
        future, self._future = self._future, []
        return future

    def parse_datagram(self, data: bytes) -> list[Any]:
        """The frames of one datagram, each standing alone (any partial frame before it is
        forgotten). A datagram holding exactly one MAVLink 2 frame (what an autopilot on UDP
        mostly sends) goes straight to :meth:`decode`, which checks it as pymavlink's byte
        parser would (length, CRC, signature) at half the cost; anything else takes that
        parser, which also finds the frames in what is not one clean frame."""
        self.reset_parser()
        n = len(data)
        if (
            n >= 3
            and data[0] == mavlink.PROTOCOL_MARKER_V2
            and self.robust_parsing
            and self.callback is None
        ):
            flags = data[2]
            signed = flags & mavlink.MAVLINK_IFLAG_SIGNED
            size = data[1] + mavlink.HEADER_LEN_V2 + 2
            if signed:
                size += mavlink.MAVLINK_SIGNATURE_BLOCK_LEN
            if size == n and not flags & ~mavlink.MAVLINK_IFLAG_SIGNED:
                # As pymavlink's parse_char does for one whole frame (robust parsing).
                self.total_bytes_received += n
                self.total_packets_received += 1
                frame = bytearray(data)
                try:
                    return [self.decode(frame)]
                except mavlink.MAVError as reason:
                    self.total_receive_errors += 1
                    return [mavlink.MAVLink_bad_data(frame, reason.message)]
        return self.parse_buffer(data) or []

    def reset_parser(self) -> None:
        """Forget any partial frame (a datagram transport: each datagram stands alone)."""
        self.buf = bytearray()
        self.buf_index = 0
        self.expected_length = mavlink.HEADER_LEN_V1 + 2
        self.have_prefix_error = False


class MavlinkLink:
    """A running MAVLink link to one autopilot. Use :meth:`open` (or the constructor plus
    :meth:`start`), and :meth:`close` — or a ``with`` block."""

    def __init__(
        self,
        transport_factory: Callable[[], Transport],
        config: LinkConfig | None = None,
        *,
        clock: Clock = time.monotonic,
        description: str = "link",
    ) -> None:
        self.config = config or LinkConfig()
        self.clock = clock
        self.description = description
        self._transport_factory = transport_factory
        self._transport: Transport | None = None
        self._write_failed: Transport | None = None
        #: The reader thread: how many reads it began, and whether it waits in one now (see
        #: :meth:`caught_up`).
        self._reads_begun = 0
        self._in_read = False

        own_system = self.config.system_id or PROVISIONAL_SYSTEM_ID
        self._encoder = _Codec(None, own_system, self.config.component_id)
        self._decoder = _Codec(None, own_system, self.config.component_id)
        self._decoder.robust_parsing = True  # garbage on a serial line is counted, not fatal
        self._keeper: TimestampKeeper | None = None
        self._fault_logged = False
        self._lockout = SigningLockout()
        self._peer_heard_at = -float("inf")  # udpin: when the peer last sent an autopilot frame
        self._foreign_datagrams_closed = 0  # of transports already dropped
        if self.config.signing is not None:
            self._setup_signing(self.config.signing)

        self._write_lock = threading.Lock()
        self._state_lock = threading.Lock()
        self._sub_lock = threading.Lock()
        self._subscriptions: list[Subscription] = []
        # Per message type, the subscriptions that take it (built on first use; cleared when
        # one is added or cancelled): the reader dispatches a few hundred frames a second.
        self._subs_by_type: dict[str, tuple[Subscription, ...]] = {}
        self._state_callbacks: list[Callable[[LinkState], None]] = []
        self._published_state = LinkState.WAITING
        self._stop = threading.Event()
        self._closed = False
        self._started = False
        self.failure: BaseException | None = None

        #: A serial device not there yet, waited for (:meth:`open`'s ``wait_for_device``).
        self.waiting_for_device: str | None = None
        self._autopilot: AutopilotInfo | None = None
        self._autopilot_event = threading.Event()
        self._last_heartbeat_at: float | None = None
        self._heard_on_transport = False  # an autopilot HEARTBEAT came in on this transport
        self._heartbeat_asked_at = -float("inf")
        self._counts = dict.fromkeys(
            (
                "rx_messages",
                "rx_bad_frames",
                "rejected_unsigned",
                "rejected_bad_signature",
                "tx_messages",
                "reconnects",
                "transport_errors",
                "rx_foreign_address",
                "peer_changes",
                "signing_state_errors",
            ),
            0,
        )
        self._reader = threading.Thread(target=self._read_loop, name="mavlink-reader", daemon=True)
        self._heartbeat = threading.Thread(
            target=self._heartbeat_loop, name="mavlink-heartbeat", daemon=True
        )

    # ----- life cycle ---------------------------------------------------------------------

    @classmethod
    def open(
        cls,
        url: str,
        config: LinkConfig | None = None,
        *,
        clock: Clock = time.monotonic,
        wait_for_device: bool = False,
    ) -> MavlinkLink:
        """Open the transport ``url`` names and start the link. The first open must succeed
        (a wrong URL or missing device is reported at once; later failures are retried),
        except, with ``wait_for_device``, a serial device that is not there yet (a flight
        controller not plugged in, or not enumerated yet at boot): the link then starts
        without it and opens it once it appears (:attr:`waiting_for_device` says which)."""
        spec = parse_url(url)
        link = cls(lambda: open_transport(spec), config, clock=clock, description=url)
        link.start(
            missing_device=spec.address if wait_for_device and spec.kind == "serial" else None
        )
        return link

    def start(self, *, missing_device: str | None = None) -> None:
        """Open the transport and start the reader and heartbeat threads. ``missing_device``:
        a serial device whose absence is waited for rather than raised."""
        if self._started:
            raise LinkError(f"{self.description}: already started")
        try:
            self._transport = self._transport_factory()
        except TransportError:
            if missing_device is None or os.path.exists(missing_device):
                raise
            log.warning("%s: waiting for %s to appear", self.description, missing_device)
            self.waiting_for_device = missing_device
        self._started = True
        self._reader.start()
        self._heartbeat.start()

    def close(self) -> None:
        """Stop both threads, close the transport and save the signing state. Idempotent."""
        self._stop.set()
        for thread in (self._heartbeat, self._reader):
            if thread.is_alive() and thread is not threading.current_thread():
                thread.join()
        if not self._reader.is_alive():
            self._drop_transport()
        self._closed = True
        self._publish_state()

    def __enter__(self) -> MavlinkLink:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()

    @property
    def closed(self) -> bool:
        """True once the link was closed or ended on an error."""
        return self._closed or self._stop.is_set()

    def _raise_if_closed(self) -> None:
        if self.closed:
            raise LinkClosed(f"{self.description}: link is closed") from self.failure

    # ----- identity and state -------------------------------------------------------------

    @property
    def autopilot(self) -> AutopilotInfo | None:
        """The autopilot we talk to, once its HEARTBEAT was heard."""
        return self._autopilot

    @property
    def target(self) -> tuple[int, int]:
        """``(target_system, target_component)`` for commands; raises until known."""
        system = self.config.target_system
        component = self.config.target_component
        if self._autopilot is not None:
            system = system or self._autopilot.system_id
            component = component or self._autopilot.component_id
        if system is None:
            raise LinkError(f"{self.description}: target system unknown, no autopilot heard yet")
        return system, component or mavlink.MAV_COMP_ID_AUTOPILOT1

    @property
    def transport(self) -> Transport | None:
        """The open transport, or None while it is being reopened."""
        return self._transport

    @property
    def system_id(self) -> int:
        """Our own system id (the vehicle's once learned, unless configured)."""
        return self._encoder.srcSystem

    @property
    def state(self) -> LinkState:
        """The link state now, by the injected clock (does not fire callbacks)."""
        if self.closed:
            return LinkState.CLOSED
        if self.fault is not None:
            return LinkState.FAULT
        last = self._last_heartbeat_at
        if last is None:
            return LinkState.WAITING
        if not self._heard_on_transport or self.clock() - last > self.config.loss_timeout_s:
            return LinkState.LOST
        return LinkState.UP

    def poll_state(self) -> LinkState:
        """Evaluate the state and fire state callbacks if it changed; returns the state.
        The heartbeat thread calls this every beat; the daemon may call it more often."""
        return self._publish_state()

    def on_state_change(self, callback: Callable[[LinkState], None]) -> None:
        """Call ``callback(new_state)`` on every change (from the thread that observed it)."""
        with self._state_lock:
            self._state_callbacks.append(callback)

    def _publish_state(self) -> LinkState:
        with self._state_lock:
            state = self.state
            changed = state != self._published_state
            self._published_state = state
            callbacks = list(self._state_callbacks) if changed else []
        if changed:
            log.info("%s: link %s", self.description, state.value)
        for callback in callbacks:
            callback(state)
        return state

    def caught_up(self, timeout_s: float = CATCH_UP_S) -> bool:
        """Wait, at most ``timeout_s``, until what the transport received by now has been read
        and handed to the subscribers: the reader waits in a read, the same one twice
        CATCH_UP_POLL_S apart, with nothing pending. For a thread about to act on what the
        autopilot said: a frame that arrived while it held the interpreter (a solve in
        compiled code) is then seen first. False if the reader did not catch up in time (a
        flood: the caller goes on)."""
        deadline_s = time.monotonic() + timeout_s
        seen: tuple[int, bool] | None = None
        while True:
            transport = self._transport
            if transport is None or self._stop.is_set():
                return True
            now = (self._reads_begun, self._in_read)
            if now[1] and not transport.pending():
                if now == seen:
                    return True
                seen = now
            else:
                seen = None
            if time.monotonic() >= deadline_s:
                return False
            time.sleep(CATCH_UP_POLL_S)

    def wait_for_autopilot(self, timeout_s: float) -> AutopilotInfo:
        """Block until an autopilot HEARTBEAT was heard, at most ``timeout_s`` (real time)."""
        deadline = time.monotonic() + timeout_s
        while not self._autopilot_event.is_set():
            self._raise_if_closed()
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise LinkTimeout(
                    f"{self.description}: no autopilot HEARTBEAT within timeout_s={timeout_s}"
                )
            self._autopilot_event.wait(min(remaining, 0.05))
        assert self._autopilot is not None
        return self._autopilot

    @property
    def fault(self) -> str | None:
        """Why the link cannot send safely now (the signing state cannot be stored), or None.
        The state is FAULT meanwhile; it clears by itself once the state can be stored."""
        return self._keeper.fault if self._keeper is not None else None

    @property
    def signing_problem(self) -> str | None:
        """Why the autopilot and we cannot agree on signing timestamps (its frames come signed
        far ahead of our clock: ``signing`` module docstring, "The autopilot ahead of us"), or
        None. The fix: :data:`~firmware_interface.signing.LOCKOUT_FIX`."""
        if self._keeper is None:
            return None
        return self._lockout.problem(self.clock())

    @property
    def stats(self) -> LinkStats:
        """A snapshot of the link counters."""
        transport = self._transport
        live = transport.foreign_datagrams if transport is not None else 0
        rejections = self._decoder.rejections
        counts = {**self._counts, "rejected_bad_signature": rejections["signature"]}
        return LinkStats(
            **counts,
            rejected_replay=rejections["replay"],
            rejected_future=rejections["future"],
            rx_foreign_datagrams=self._foreign_datagrams_closed + live,
        )

    # ----- sending ------------------------------------------------------------------------

    @property
    def mav(self) -> mavlink.MAVLink:
        """The encoder, for building messages: ``link.send(link.mav.statustext_encode(...))``.
        Only call its ``*_encode`` methods; :meth:`send` does the packing."""
        return self._encoder

    def send(self, msg: MavMessage) -> bytes:
        """Pack and write one message; returns the bytes written. Thread-safe.

        Raises :class:`LinkClosed` after close, :class:`TransportError` while the transport is
        down (it is being reopened in the background).
        """
        return self.send_many([msg])

    def send_many(self, msgs: Iterable[MavMessage]) -> bytes:
        """Pack several messages and write them in **one** write (one UDP datagram, one serial
        or TCP write): an autopilot reading the link once per main-loop pass then meets them
        all in the same pass. Returns the bytes written; raises as :meth:`send`."""
        with self._write_lock:
            self._raise_if_closed()
            transport = self._transport
            if transport is None:
                raise TransportError(f"{self.description}: transport down, reconnecting")
            frames = []
            for msg in msgs:
                if self._keeper is not None:
                    try:
                        self._encoder.signing.timestamp = self._keeper.next_timestamp(
                            max(self._encoder.signing.timestamp, self._decoder.signing.timestamp)
                        )
                    except SigningStateError as exc:
                        # Signing past the stored reservation could replay timestamps after a
                        # restart: refuse to send rather than sign unsafely (state FAULT).
                        self._counts["signing_state_errors"] += 1
                        raise SigningStateError(f"{self.description}: {exc}") from exc
                frames.append(msg.pack(self._encoder))
                self._encoder.seq = (self._encoder.seq + 1) % 256
            buf = b"".join(frames)
            try:
                transport.write(buf)
            except TransportError:
                self._write_failed = transport  # the reader thread reopens it
                self._heard_on_transport = False  # lost from now on, as after a read error
                self._counts["transport_errors"] += 1
                raise
            self._counts["tx_messages"] += len(frames)
            return buf

    def _send_heartbeat(self) -> None:
        msg = self._encoder.heartbeat_encode(
            mavlink.MAV_TYPE_ONBOARD_CONTROLLER,
            mavlink.MAV_AUTOPILOT_INVALID,
            0,
            0,
            mavlink.MAV_STATE_ACTIVE,
        )
        try:
            self.send(msg)
        except LinkClosed:
            # Closed, or ended by the reader on an error, since the heartbeat loop looked: it
            # stops at its next look; the reason is the link's to report, not this thread's.
            pass
        except TransportError as exc:
            log.debug("%s: heartbeat not sent: %s", self.description, exc)
        except SigningStateError as exc:
            # The keeper logged the fault once; a line a second would fill the journal.
            log.debug("heartbeat not sent: %s", exc)

    # ----- receiving ----------------------------------------------------------------------

    def subscribe(
        self, callback: Callable[[MavMessage], None], types: Iterable[str] | None = None
    ) -> Subscription:
        """Call ``callback(msg)`` on the reader thread for every incoming message whose type
        name (``"COMMAND_LONG"``, ``"HEARTBEAT"`` …) is in ``types`` (all if None). Keep it
        short; an exception in it ends the link (see :attr:`failure`)."""
        sub = Subscription(self, callback, frozenset(types) if types is not None else None)
        with self._sub_lock:
            self._subscriptions.append(sub)
            self._subs_by_type = {}
        return sub

    def messages(self, types: Iterable[str] | None = None, maxsize: int = 256) -> MessageQueue:
        """A queue of incoming messages of ``types``; close it (or use ``with``) when done."""
        return MessageQueue(self, frozenset(types) if types is not None else None, maxsize)

    def _remove_subscription(self, sub: Subscription) -> None:
        with self._sub_lock:
            if sub in self._subscriptions:
                self._subscriptions.remove(sub)
                self._subs_by_type = {}

    def _handle(self, msg: MavMessage) -> None:
        if isinstance(msg, mavlink.MAVLink_bad_data):
            self._count_bad(msg)
            return
        self._counts["rx_messages"] += 1
        kind = msg.get_type()
        if kind == "HEARTBEAT":
            self._handle_heartbeat(msg)
        elif self._published_state is not LinkState.UP:  # no clock read per frame while up
            self._ask_heartbeat(msg)
        with self._sub_lock:
            subscriptions = self._subs_by_type.get(kind)
            if subscriptions is None:
                subscriptions = tuple(s for s in self._subscriptions if s.matches(msg))
                self._subs_by_type[kind] = subscriptions
        for sub in subscriptions:
            sub.callback(msg)

    def _count_bad(self, msg: Any) -> None:
        reason = str(getattr(msg, "reason", ""))
        data = bytes(getattr(msg, "data", b""))
        if "signature" in reason.lower():
            signed = (
                len(data) > 2
                and data[0] == mavlink.PROTOCOL_MARKER_V2
                and (data[2] & _MAVLINK_IFLAG_SIGNED)
            )
            if signed:
                self._log_signed_rejection()
                return
            self._counts["rejected_unsigned"] += 1
            log.warning(
                "%s: unsigned frame rejected (%d so far)",
                self.description,
                self._counts["rejected_unsigned"],
            )
        else:
            self._counts["rx_bad_frames"] += 1
            log.debug("%s: bad frame: %s", self.description, reason)

    def _log_signed_rejection(self) -> None:
        rejections = self._decoder.rejections
        total = sum(rejections.values())
        if total & (total - 1):  # log the 1st, 2nd, 4th, 8th …: a flood cannot fill the journal
            return
        future = ""
        if self._decoder.last_future is not None:
            system, component, ahead_s = self._decoder.last_future
            future = (
                f"; latest future frame: {system}/{component}, {ahead_s:.0f} s ahead of our "
                "clock (a key holder's clock is wrong?)"
            )
        log.warning(
            "%s: signed frames rejected: %d bad signature, %d replayed or too old, %d from the "
            "future%s",
            self.description,
            rejections["signature"],
            rejections["replay"],
            rejections["future"],
            future,
        )

    def _is_autopilot_frame(self, msg: MavMessage) -> bool:
        """A valid frame from the pinned autopilot (signed, when signing is on)."""
        autopilot = self._autopilot
        if autopilot is None or isinstance(msg, mavlink.MAVLink_bad_data):
            return False
        if (msg.get_srcSystem(), msg.get_srcComponent()) != (
            autopilot.system_id,
            autopilot.component_id,
        ):
            return False
        return self._keeper is None or bool(getattr(msg, "_signed", False))

    def _may_be_autopilot(self, source: tuple[int, int]) -> bool:
        """``source`` is the pinned autopilot, or (none pinned yet) matches the configured
        target ids."""
        if self._autopilot is not None:
            return source == (self._autopilot.system_id, self._autopilot.component_id)
        wanted = (self.config.target_system, self.config.target_component)
        return all(want in (None, got) for want, got in zip(wanted, source, strict=True))

    def _set_peer(self, transport: UdpInTransport, sender: Address, why: str) -> None:
        was = transport.peer
        log.warning(
            "%s: sending to %s:%d (%s)%s",
            self.description,
            *sender,
            why,
            "" if was is None else f", was {was[0]}:{was[1]}",
        )
        transport.set_peer(sender)
        self._counts["peer_changes"] += 1
        # Our HEARTBEAT at once, not at the next beat (up to a second away): the autopilot
        # routes to us only once it has heard us, and PX4 drops a ground station's command for
        # a component it has not heard ("Ignore command ... to 1/191").
        self._send_heartbeat()

    def _receive(self, transport: Transport, data: bytes, sender: Address | None) -> None:
        """Decode and dispatch what one read returned (udpin: choose the peer; module
        docstring)."""
        if transport.datagrams:
            msgs = self._decoder.parse_datagram(data)
        else:
            msgs = self._decoder.parse_buffer(data) or []
        stale = self._decoder.take_stale()
        future = self._decoder.take_future()
        if future or self._lockout.seen:
            self._watch_lockout(future, msgs)
        if not isinstance(transport, UdpInTransport) or sender is None:
            for msg in msgs:
                self._handle(msg)
            return
        confirmed = self._peer_heard_at > -float("inf")
        if (
            not confirmed
            and sender != transport.peer
            and any(self._may_be_autopilot(s) for s in stale)
        ):
            # Signed by the autopilot's key holder but older than our start: the autopilot
            # has not heard our (newer) timestamp yet, and on udpin it never will unless we
            # send to it. Provisional: the first accepted autopilot frame confirms a peer.
            self._set_peer(transport, sender, "a signed autopilot frame older than our start")
        peer = transport.peer
        if peer is not None and sender != peer:
            now = self.clock()
            if not (
                now - self._peer_heard_at > PEER_HOLD_S
                and any(self._is_autopilot_frame(m) for m in msgs)
            ):
                for msg in msgs:
                    if isinstance(msg, mavlink.MAVLink_bad_data):
                        self._count_bad(msg)
                    else:
                        self._counts["rx_foreign_address"] += 1
                return
        for msg in msgs:
            self._handle(msg)  # a HEARTBEAT may pin the autopilot here
            if not self._is_autopilot_frame(msg):
                continue
            if sender != transport.peer:
                self._set_peer(transport, sender, "autopilot frame")
            self._peer_heard_at = self.clock()

    def _watch_lockout(self, future: list[tuple[int, int, int, int]], msgs: list[Any]) -> None:
        """The autopilot's frames refused as from the future begin its signing problem (logged
        once, with the fix); one of its frames accepted ends it."""
        now = self.clock()
        began = False
        for system, component, timestamp, local in future:
            if self._looks_like_autopilot((system, component)):
                began |= self._lockout.refused((system, component), timestamp, local, now)
        if began:
            problem = self._lockout.problem(now)
            assert problem is not None
            log.error("%s: signing: %s", self.description, lockout_message(problem))
        elif not future and any(self._is_autopilot_frame(m) for m in msgs):
            if self._lockout.clear():
                log.warning(
                    "%s: signing: the autopilot's frames are accepted again", self.description
                )

    def _looks_like_autopilot(self, source: tuple[int, int]) -> bool:
        """``source`` is the pinned autopilot, or (none pinned yet: its HEARTBEAT may be what
        is refused) the configured target ids, the component defaulting to the autopilot's
        (1, MAV_COMP_ID_AUTOPILOT1: a ground station's frames are not the autopilot's)."""
        if self._autopilot is not None:
            return source == (self._autopilot.system_id, self._autopilot.component_id)
        system = self.config.target_system
        component = self.config.target_component or mavlink.MAV_COMP_ID_AUTOPILOT1
        return system in (None, source[0]) and component == source[1]

    def _ask_heartbeat(self, msg: MavMessage) -> None:
        """The link not up and ``msg`` came from the autopilot's component (the
        configured ids, the pinned autopilot's, else component 1 of any system): ask that
        system for a HEARTBEAT now (module docstring)."""
        autopilot = self._autopilot
        system, component = msg.get_srcSystem(), msg.get_srcComponent()
        wanted_system = self.config.target_system or (autopilot.system_id if autopilot else None)
        wanted_component = self.config.target_component or (
            autopilot.component_id if autopilot else mavlink.MAV_COMP_ID_AUTOPILOT1
        )
        if component != wanted_component or wanted_system not in (None, system):
            return
        now = self.clock()
        if now - self._heartbeat_asked_at < HEARTBEAT_ASK_INTERVAL_S:
            return
        self._heartbeat_asked_at = now
        ask = self._encoder.command_long_encode(
            system,
            component,
            mavlink.MAV_CMD_REQUEST_MESSAGE,
            0,
            float(mavlink.MAVLINK_MSG_ID_HEARTBEAT),
            0.0,
            0.0,
            0.0,
            0.0,
            0.0,
            0.0,
        )
        try:
            self.send(ask)
        except LinkError as exc:  # closed, a write that failed, signing at fault: a loss's
            log.debug("%s: HEARTBEAT not asked for: %s", self.description, exc)

    def _handle_heartbeat(self, msg: MavMessage) -> None:
        if not is_autopilot_heartbeat(msg):
            return
        system, component = msg.get_srcSystem(), msg.get_srcComponent()
        wanted_system = self.config.target_system or (
            self._autopilot.system_id if self._autopilot else None
        )
        if wanted_system is not None and system != wanted_system:
            return
        wanted_component = self.config.target_component or (
            self._autopilot.component_id if self._autopilot else None
        )
        if wanted_component is not None and component != wanted_component:
            return
        if self._autopilot is None:
            self._autopilot = AutopilotInfo(system, component, msg.autopilot, msg.type)
            if self.config.system_id is None:
                with self._write_lock:
                    self._encoder.srcSystem = system
            log.info("%s: autopilot %d/%d found", self.description, system, component)
            self._autopilot_event.set()
        self._last_heartbeat_at = self.clock()
        self._heard_on_transport = True
        self._publish_state()

    # ----- threads ------------------------------------------------------------------------

    def _read_loop(self) -> None:
        backoff_s = self.config.reconnect_initial_s
        failed_reopens = 0
        try:
            while not self._stop.is_set():
                transport = self._transport
                if transport is None or self._write_failed is transport:
                    if transport is not None:
                        self._drop_transport()
                    if not self._reopen(quiet=failed_reopens > 0):
                        failed_reopens += 1
                        self._stop.wait(backoff_s)
                        backoff_s = min(2 * backoff_s, self.config.reconnect_max_s)
                    else:
                        failed_reopens = 0
                        backoff_s = self.config.reconnect_initial_s
                    continue
                self._reads_begun += 1
                self._in_read = True
                try:
                    data, sender = transport.read_from(self.config.read_timeout_s)
                except TransportError as exc:
                    self._in_read = False
                    # Drop the port first: whoever sees the error counted sees the link lost.
                    self._drop_transport()
                    self._counts["transport_errors"] += 1
                    log.warning("%s: %s; reopening", self.description, exc)
                    continue
                self._in_read = False
                if data:
                    self._receive(transport, data, sender)
        except Exception as exc:  # protocol or subscriber bug: end the link, keep the cause
            log.exception("%s: link ended by an error in protocol code", self.description)
            self.failure = exc
            self._stop.set()
        finally:
            self._drop_transport()

    def _reopen(self, *, quiet: bool = False) -> bool:
        try:
            transport = self._transport_factory()
        except TransportError as exc:
            # Only the first failure of an outage is logged at INFO: at reconnect_max_s the
            # attempts would otherwise fill the journal.
            log.log(
                logging.DEBUG if quiet else logging.INFO,
                "%s: reopen failed: %s",
                self.description,
                exc,
            )
            return False
        with self._write_lock:
            self._transport = transport
            self._write_failed = None
        self.waiting_for_device = None
        self._counts["reconnects"] += 1
        log.warning("%s: transport reopened", self.description)
        return True

    def _drop_transport(self) -> None:
        with self._write_lock:
            transport, self._transport = self._transport, None
            self._heard_on_transport = False
            if transport is not None:
                self._foreign_datagrams_closed += transport.foreign_datagrams
        if transport is not None:
            transport.close()

    def _heartbeat_loop(self) -> None:
        period_s = 1.0 / self.config.heartbeat_rate_hz
        while not self._stop.is_set():
            self._send_heartbeat()
            try:
                self._publish_state()
            except Exception:
                log.exception("%s: state callback failed", self.description)
            self._stop.wait(period_s)

    # ----- signing ------------------------------------------------------------------------

    def _setup_signing(self, config: SigningConfig) -> None:
        self._keeper = TimestampKeeper(config, clock=self.clock)
        self._decoder.keeper = self._keeper
        # Every timestamp signed before this start is below the stored reservation, hence
        # below initial_timestamp; a peer that adopted our first frame's may send it back.
        self._decoder.stream_floor = self._keeper.initial_timestamp - 1
        allowed = config.allow_unsigned_msg_ids
        for codec in (self._encoder, self._decoder):
            codec.signing.secret_key = config.key
            codec.signing.link_id = config.link_id
            codec.signing.timestamp = self._keeper.initial_timestamp
            codec.signing.allow_unsigned_callback = lambda _mav, msg_id, allowed=allowed: (
                msg_id in allowed
            )
        self._encoder.signing.sign_outgoing = True

    @property
    def signing_reserved_until(self) -> int | None:
        """The signing timestamp persisted in the state file (None without signing)."""
        return self._keeper.reserved_until if self._keeper else None
