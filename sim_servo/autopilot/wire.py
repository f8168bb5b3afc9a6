"""The autopilot's side of its links: decoding what arrives, encoding (and signing) what it
sends, the frames held for the next main-loop pass, and each link's timing model."""

from __future__ import annotations

from collections.abc import Callable

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from sim_servo.autopilot.state import AutopilotState
from sim_servo.faults import FaultInjector
from sim_servo.linktiming import LinkOutput, LoopLinkOutput

#: Signing timestamps: 10 µs ticks since 2015-01-01 UTC (MAVLink signing spec).
SIGNING_EPOCH_UNIX_S = 1_420_070_400
#: Accepted unsigned even when signing is required (GCS_Signing.cpp accept list).
UNSIGNED_ALLOWED_IDS = frozenset({mavlink.MAVLINK_MSG_ID_RADIO_STATUS})


class Wire:
    """Frames in and out of every link (channel 0: the companion's)."""

    def __init__(
        self,
        state: AutopilotState,
        faults: FaultInjector,
        *,
        links: int,
        wall_clock: Callable[[], float],
    ) -> None:
        self._state = state
        self._faults = faults
        config = state.config
        self.encoder = mavlink.MAVLink(
            None, srcSystem=config.system_id, srcComponent=config.component_id
        )
        # One decoder per link: a serial stream's partial frame must not meet another link's.
        self._decoders: dict[int, mavlink.MAVLink] = {}
        if config.signing_key is not None:
            self.encoder.signing.secret_key = config.signing_key
            self.encoder.signing.sign_outgoing = True
            self.encoder.signing.link_id = 0
            self.encoder.signing.timestamp = max(
                1, int((wall_clock() - SIGNING_EPOCH_UNIX_S) * 100_000)
            )
        #: Each link's outgoing side: delay and hold, see :mod:`sim_servo.linktiming`.
        self.links: list[LinkOutput | LoopLinkOutput] = []
        self.set_links(links)
        #: Our frames waiting for the next main-loop pass: (due, message).
        self._deferred: list[tuple[float, mavlink.MAVLink_message]] = []

    def set_links(self, count: int) -> None:
        """Serve ``count`` links (channels 0 … count−1): our own frames go out on each."""
        if count < 1:
            raise ValueError(f"links={count} must be >= 1")
        while len(self.links) < count:
            self.links.append(
                self._state.flavour.new_link_output(self._state.config, self._state.boot_s)
            )

    def link(self, channel: int) -> LinkOutput | LoopLinkOutput:
        self.set_links(channel + 1)  # a link we hear from exists
        return self.links[channel]

    # -- in ----------------------------------------------------------------------------------

    def decode(self, data: bytes, now_s: float, channel: int) -> list[mavlink.MAVLink_message]:
        """The messages in ``data`` (BAD_DATA for what fails), told to the link's timing."""
        try:
            messages = self._decoder(channel).parse_buffer(data) or []
        except mavlink.MAVError as exc:  # robust_parsing reports most problems as BAD_DATA
            messages = [mavlink.MAVLink_bad_data(b"", str(exc))]
        self.link(channel).arrived(len(messages), now_s)
        return messages

    def _decoder(self, channel: int) -> mavlink.MAVLink:
        decoder = self._decoders.get(channel)
        if decoder is None:
            decoder = mavlink.MAVLink(None)
            decoder.robust_parsing = True
            key = self._state.config.signing_key
            if key is not None:
                decoder.signing.secret_key = key
                decoder.signing.allow_unsigned_callback = lambda _mav, msg_id: (
                    msg_id in UNSIGNED_ALLOWED_IDS
                )
            self._decoders[channel] = decoder
        return decoder

    # -- out ---------------------------------------------------------------------------------

    def send(self, msg: mavlink.MAVLink_message, now_s: float, channel: int | None = None) -> None:
        """Send ``msg`` on every link, or only on ``channel``."""
        state = self._state
        if state.config.signing_key is not None:
            self.encoder.signing.timestamp = self._signing_timestamp(now_s)
        frame = msg.pack(self.encoder)
        self.encoder.seq = (self.encoder.seq + 1) % 256
        self.encoder.total_packets_sent += 1
        if self._faults.drop_out():
            state.stats["dropped_out"] += 1
            state.emit(now_s, "fault", fault="drop_out", msg=msg.get_type())
            return
        corrupted = self._faults.corrupt_out(frame)
        if corrupted != frame:
            state.stats["corrupted_out"] += 1
            state.emit(now_s, "fault", fault="corrupt_out", msg=msg.get_type())
        state.stats["tx"] += 1
        delay_s = self._faults.delay_s()
        links = self.links if channel is None else [self.link(channel)]
        for link in links:
            link.write(corrupted, now_s, delay_s)

    def write_routed(self, frame: bytes, channel: int, now_s: float, delay_s: float) -> None:
        """A frame routed from another link: the same way out as ours, without faults."""
        self.link(channel).write(frame, now_s, delay_s)

    def _signing_timestamp(self, now_s: float) -> int:
        """The timestamp our next signed frame carries, as the MAVLink signing spec asks
        ("Timestamp Handling"): never below the last one sent (pymavlink adds 1 per frame),
        the system clock's, or any correctly signed incoming one (each link's decoder keeps the
        highest it accepted, as the C library does). The last rule matters to a companion that
        restarts over a minute after we booted: its clock is then ahead of our frames by more
        than a minute, and it would refuse every frame of ours as a stale stream."""
        wall_ticks = (self._state.time_unix_us(now_s) - SIGNING_EPOCH_UNIX_S * 1_000_000) // 10
        seen = max((d.signing.timestamp for d in self._decoders.values()), default=0)
        return max(self.encoder.signing.timestamp, wall_ticks, seen)

    def defer(self, msg: mavlink.MAVLink_message, now_s: float) -> None:
        """Send on the next main-loop pass, as ArduPilot does for STATUSTEXT and PARAM_VALUE."""
        self._deferred.append((now_s + self._state.loop_s, msg))

    def statustext(self, severity: int, text: str, now_s: float) -> None:
        """A STATUSTEXT, queued for the main loop (GCS.cpp ``service_statustext``)."""
        self._state.emit(now_s, "statustext", severity=severity, text=text)
        self.defer(self.encoder.statustext_encode(severity, text.encode()), now_s)

    def run_deferred(self, now_s: float) -> None:
        due = [msg for at, msg in self._deferred if at <= now_s]
        self._deferred = [(at, msg) for at, msg in self._deferred if at > now_s]
        for msg in due:
            self.send(msg, now_s)

    def take(self, now_s: float) -> list[tuple[int, bytes]]:
        """The frames every link writes now, as ``(link, frame)``."""
        return [
            (channel, frame)
            for channel, link in enumerate(self.links)
            for frame in link.take(now_s)
        ]

    def deferred_due_s(self) -> list[float]:
        """When our deferred frames are due (the next main-loop pass after each was made)."""
        return [due for due, _ in self._deferred]

    def links_due_s(self) -> list[float]:
        """When a link next has frames to write."""
        return [due for link in self.links if (due := link.next_event_s()) is not None]

    # -- reboot ------------------------------------------------------------------------------

    def halt(self, now_s: float) -> None:
        """Frames not yet sent are lost, and so is a partial frame received."""
        self._deferred.clear()
        self._decoders.clear()
        for link in self.links:
            link.clear()

    def boot(self, now_s: float) -> None:
        """The sequence number restarts; a loop-paced link's passes start from the boot."""
        self.encoder.seq = 0
        for link in self.links:
            if isinstance(link, LoopLinkOutput):
                link.phase_s = now_s
