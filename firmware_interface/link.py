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
HEARTBEAT was heard within ``loss_timeout_s``, LOST after, WAITING before the first one. It is
also LOST while the transport is down, and after a reopen until a HEARTBEAT arrives on the new
port: a serial adapter that re-enumerated often means a flight controller that rebooted.
"""

from __future__ import annotations

import enum
import logging
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
from firmware_interface.signing import SigningConfig, TimestampKeeper
from firmware_interface.transport import Transport, open_transport, parse_url

log = logging.getLogger(__name__)

Clock = Callable[[], float]


class MavMessage(Protocol):
    """What the link and its users rely on in a pymavlink message (``MAVLink_message``, which
    has no type information). Its fields (``msg.command``, ``msg.param1`` …) depend on the message
    type and are read through ``__getattr__``, so they are ``Any``."""

    def get_type(self) -> str: ...
    def get_srcSystem(self) -> int: ...
    def get_srcComponent(self) -> int: ...
    def pack(self, mav: Any, force_mavlink1: bool = False) -> bytes: ...
    def __getattr__(self, name: str) -> Any: ...


#: Our HEARTBEAT identity (issue 5).
DEFAULT_COMPONENT_ID = mavlink.MAV_COMP_ID_ONBOARD_COMPUTER  # 191
#: Used as our own system id until the vehicle's is learned (ArduPilot's SYSID_THISMAV default).
PROVISIONAL_SYSTEM_ID = 1
_NOT_AN_AUTOPILOT_TYPES = frozenset(
    {mavlink.MAV_TYPE_GCS, mavlink.MAV_TYPE_ONBOARD_CONTROLLER, mavlink.MAV_TYPE_GIMBAL}
)
_MAVLINK_IFLAG_SIGNED = 0x01


def is_autopilot_heartbeat(msg: MavMessage) -> bool:
    """A HEARTBEAT from a flight controller (not a GCS, companion, gimbal or other device)."""
    return (
        msg.autopilot != mavlink.MAV_AUTOPILOT_INVALID and msg.type not in _NOT_AN_AUTOPILOT_TYPES
    )


class LinkState(enum.Enum):
    """Autopilot link state as seen from the companion."""

    WAITING = "waiting"  # no autopilot HEARTBEAT heard yet
    UP = "up"
    LOST = "lost"  # heard before, but nothing for loss_timeout_s
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
    """Counters since the link started."""

    rx_messages: int
    rx_bad_frames: int
    rejected_unsigned: int
    rejected_bad_signature: int
    tx_messages: int
    reconnects: int
    transport_errors: int


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
    """pymavlink's codec, with one fix: a *bad* signature must not advance the stream timestamp.

    pymavlink's ``check_signature`` records the incoming timestamp before comparing the
    signature, so one forged frame with a far-future timestamp would make every genuine frame
    of that stream look replayed. We restore the previous value when the check fails.
    """

    def check_signature(self, msgbuf: bytearray, srcSystem: int, srcComponent: int) -> bool:
        stream_key = (msgbuf[-13], srcSystem, srcComponent)
        streams = self.signing.stream_timestamps
        previous = streams.get(stream_key)
        ok = super().check_signature(msgbuf, srcSystem, srcComponent)
        if not ok:
            if previous is None:
                streams.pop(stream_key, None)
            else:
                streams[stream_key] = previous
        return ok


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

        own_system = self.config.system_id or PROVISIONAL_SYSTEM_ID
        self._encoder = _Codec(None, own_system, self.config.component_id)
        self._decoder = _Codec(None, own_system, self.config.component_id)
        self._decoder.robust_parsing = True  # garbage on a serial line is counted, not fatal
        self._keeper: TimestampKeeper | None = None
        if self.config.signing is not None:
            self._setup_signing(self.config.signing)

        self._write_lock = threading.Lock()
        self._state_lock = threading.Lock()
        self._sub_lock = threading.Lock()
        self._subscriptions: list[Subscription] = []
        self._state_callbacks: list[Callable[[LinkState], None]] = []
        self._published_state = LinkState.WAITING
        self._stop = threading.Event()
        self._closed = False
        self._started = False
        self.failure: BaseException | None = None

        self._autopilot: AutopilotInfo | None = None
        self._autopilot_event = threading.Event()
        self._last_heartbeat_at: float | None = None
        self._heard_on_transport = False  # an autopilot HEARTBEAT came in on this transport
        self._counts = dict.fromkeys(
            (
                "rx_messages",
                "rx_bad_frames",
                "rejected_unsigned",
                "rejected_bad_signature",
                "tx_messages",
                "reconnects",
                "transport_errors",
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
        cls, url: str, config: LinkConfig | None = None, *, clock: Clock = time.monotonic
    ) -> MavlinkLink:
        """Open the transport ``url`` names and start the link. The first open must succeed
        (a wrong URL or missing device is reported at once); later failures are retried."""
        spec = parse_url(url)
        link = cls(lambda: open_transport(spec), config, clock=clock, description=url)
        link.start()
        return link

    def start(self) -> None:
        """Open the transport and start the reader and heartbeat threads."""
        if self._started:
            raise LinkError(f"{self.description}: already started")
        self._transport = self._transport_factory()
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
    def stats(self) -> LinkStats:
        """A snapshot of the link counters."""
        return LinkStats(**self._counts)

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
                    except OSError as exc:
                        # Signing past the stored reservation could replay timestamps after a
                        # restart: refuse to send rather than sign unsafely.
                        raise SigningStateError(
                            f"{self.description}: cannot store the signing timestamp: {exc}"
                        ) from exc
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
        except TransportError as exc:
            log.debug("%s: heartbeat not sent: %s", self.description, exc)
        except SigningStateError as exc:
            log.warning("heartbeat not sent: %s", exc)

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
        return sub

    def messages(self, types: Iterable[str] | None = None, maxsize: int = 256) -> MessageQueue:
        """A queue of incoming messages of ``types``; close it (or use ``with``) when done."""
        return MessageQueue(self, frozenset(types) if types is not None else None, maxsize)

    def _remove_subscription(self, sub: Subscription) -> None:
        with self._sub_lock:
            if sub in self._subscriptions:
                self._subscriptions.remove(sub)

    def _handle(self, msg: MavMessage) -> None:
        if isinstance(msg, mavlink.MAVLink_bad_data):
            self._count_bad(msg)
            return
        self._counts["rx_messages"] += 1
        if msg.get_type() == "HEARTBEAT":
            self._handle_heartbeat(msg)
        with self._sub_lock:
            subscriptions = [s for s in self._subscriptions if s.matches(msg)]
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
            key = "rejected_bad_signature" if signed else "rejected_unsigned"
            self._counts[key] += 1
            log.warning(
                "%s: %s frame rejected (%d so far)",
                self.description,
                key.removeprefix("rejected_").replace("_", " "),
                self._counts[key],
            )
        else:
            self._counts["rx_bad_frames"] += 1
            log.debug("%s: bad frame: %s", self.description, reason)

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
                try:
                    data = transport.read(self.config.read_timeout_s)
                except TransportError as exc:
                    # Drop the port first: whoever sees the error counted sees the link lost.
                    self._drop_transport()
                    self._counts["transport_errors"] += 1
                    log.warning("%s: %s; reopening", self.description, exc)
                    continue
                if data:
                    for msg in self._decoder.parse_buffer(data) or ():
                        self._handle(msg)
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
        self._counts["reconnects"] += 1
        log.warning("%s: transport reopened", self.description)
        return True

    def _drop_transport(self) -> None:
        with self._write_lock:
            transport, self._transport = self._transport, None
            self._heard_on_transport = False
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
        self._keeper = TimestampKeeper(config)
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
