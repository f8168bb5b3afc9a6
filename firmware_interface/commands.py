"""COMMAND_LONG with COMMAND_ACK tracking, retries and a bounded wait.

COMMAND_ACK carries no sequence number, so an ACK is matched to a command by
``(autopilot system, autopilot component, command id)`` alone. To keep that unambiguous, at most
one command with a given id is in flight to a given target: a second caller waits for the first
to finish. Retries resend the same command with ``confirmation`` incremented (0, 1, 2 …), as the
MAVLink command protocol asks. A late ACK for an earlier attempt of the same command is taken as
the answer — it is the same request. A late ACK arriving after a command has given up cannot be
told apart from an ACK for the next command with the same id; that is a limit of the protocol.

Deadlines are measured with the link's injected clock, so tests drive timeouts by advancing a
fake clock instead of sleeping.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Sequence
from dataclasses import dataclass, field

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from firmware_interface.errors import CommandRejected, ConfigurationError, LinkClosed, LinkTimeout
from firmware_interface.link import MavlinkLink, MavMessage

log = logging.getLogger(__name__)


def command_name(command: int) -> str:
    """``MAV_CMD_DO_SET_SERVO`` for 183, or the number if unknown."""
    entry = mavlink.enums["MAV_CMD"].get(command)
    return entry.name if entry is not None else str(command)


def result_name(result: int) -> str:
    """``MAV_RESULT_FAILED`` for 4, or the number if unknown."""
    entry = mavlink.enums["MAV_RESULT"].get(result)
    return entry.name if entry is not None else str(result)


@dataclass(frozen=True)
class CommandOutcome:
    """An accepted command: how many sends it took and the confirmation value acknowledged."""

    command: int
    target: tuple[int, int]
    attempts: int
    confirmation: int


@dataclass
class _Pending:
    target_system: int
    event: threading.Event = field(default_factory=threading.Event)
    ack: MavMessage | None = None
    confirmation: int = 0
    statustexts: list[str] = field(default_factory=list)
    statustext_event: threading.Event = field(default_factory=threading.Event)


class CommandSender:
    """Sends COMMAND_LONG to the link's autopilot and waits for its COMMAND_ACK.

    ``timeout_s`` is the wait per attempt, ``retries`` the number of resends after the first.
    ArduPilot queues the STATUSTEXT explaining a refusal for its main loop, so it arrives just
    *after* the FAILED ACK: after a refusal we keep listening up to ``statustext_grace_s``
    (stopping as soon as one arrives) so the error can carry it.
    """

    def __init__(
        self,
        link: MavlinkLink,
        *,
        timeout_s: float = 1.0,
        retries: int = 2,
        poll_s: float = 0.01,
        statustext_grace_s: float = 0.2,
    ) -> None:
        if not timeout_s > 0:
            raise ConfigurationError(f"timeout_s={timeout_s!r} must be > 0")
        if not isinstance(retries, int) or not 0 <= retries <= 254:
            raise ConfigurationError(f"retries={retries!r} outside [0, 254]")
        self.link = link
        self.timeout_s = timeout_s
        self.retries = retries
        self._poll_s = poll_s
        self.statustext_grace_s = statustext_grace_s
        self._lock = threading.Lock()
        self._key_locks: dict[tuple[int, int, int], threading.Lock] = {}
        self._pending: dict[tuple[int, int, int], _Pending] = {}
        self.unmatched_acks = 0
        self._subscription = link.subscribe(self._on_message, ["COMMAND_ACK", "STATUSTEXT"])

    def close(self) -> None:
        """Stop listening for ACKs."""
        self._subscription.cancel()

    # Runs on the link's reader thread.
    def _on_message(self, msg: MavMessage) -> None:
        if msg.get_type() == "STATUSTEXT":
            with self._lock:
                for waiting in self._pending.values():
                    if waiting.target_system == msg.get_srcSystem():
                        waiting.statustexts.append(msg.text)
                        waiting.statustext_event.set()
            return
        if msg.target_system not in (0, self.link.system_id) or msg.target_component not in (
            0,
            self.link.config.component_id,
        ):
            return  # an ACK meant for another component (a GCS)
        key = (msg.get_srcSystem(), msg.get_srcComponent(), msg.command)
        with self._lock:
            pending = self._pending.get(key)
            if pending is None:
                self.unmatched_acks += 1
                log.info(
                    "unmatched COMMAND_ACK %s %s from %d/%d",
                    command_name(msg.command),
                    result_name(msg.result),
                    key[0],
                    key[1],
                )
                return
            if msg.result == mavlink.MAV_RESULT_IN_PROGRESS:
                return
            pending.ack = msg
        pending.event.set()

    def _key_lock(self, key: tuple[int, int, int]) -> threading.Lock:
        with self._lock:
            return self._key_locks.setdefault(key, threading.Lock())

    def command_long(
        self,
        command: int,
        params: Sequence[float],
        *,
        target: tuple[int, int] | None = None,
        timeout_s: float | None = None,
        retries: int | None = None,
    ) -> CommandOutcome:
        """Send ``command`` with up to 7 ``params`` and wait for an ACCEPTED COMMAND_ACK.

        Raises :class:`LinkTimeout` when every attempt went unanswered, and
        :class:`CommandRejected` (with ``result`` and the last ``statustext``) otherwise.
        """
        values = [float(p) for p in params]
        if len(values) > 7:
            raise ConfigurationError(f"COMMAND_LONG takes at most 7 params, got {len(values)}")
        values += [0.0] * (7 - len(values))
        target = target or self.link.target
        timeout_s = self.timeout_s if timeout_s is None else timeout_s
        retries = self.retries if retries is None else retries
        key = (target[0], target[1], command)
        name = command_name(command)
        clock = self.link.clock
        with self._key_lock(key):
            pending = _Pending(target_system=target[0])
            with self._lock:
                self._pending[key] = pending
            try:
                for attempt in range(retries + 1):
                    pending.confirmation = attempt
                    # The deadline is fixed before sending, so it covers the send itself and
                    # an answer can never arrive "before" the clock started.
                    deadline = clock() + timeout_s
                    self.link.send(
                        self.link.mav.command_long_encode(
                            target[0], target[1], command, attempt, *values
                        )
                    )
                    while not pending.event.wait(self._poll_s):
                        if self.link.closed:
                            raise LinkClosed(
                                f"link closed while waiting for {name} ACK"
                            ) from self.link.failure
                        if clock() >= deadline:
                            break
                    if pending.event.is_set():
                        break
                    log.info(
                        "no ACK for %s to %d/%d (attempt %d of %d)",
                        name,
                        *target,
                        attempt + 1,
                        retries + 1,
                    )
                else:
                    raise LinkTimeout(
                        f"no COMMAND_ACK for {name} from {target[0]}/{target[1]} after "
                        f"{retries + 1} attempts of timeout_s={timeout_s}"
                    )
                ack = pending.ack
                if ack is not None and ack.result != mavlink.MAV_RESULT_ACCEPTED:
                    pending.statustext_event.wait(self.statustext_grace_s)
            finally:
                with self._lock:
                    del self._pending[key]
        ack = pending.ack
        assert ack is not None
        if ack.result != mavlink.MAV_RESULT_ACCEPTED:
            statustext = pending.statustexts[-1] if pending.statustexts else None
            raise CommandRejected(
                f"{name} to {target[0]}/{target[1]} rejected: {result_name(ack.result)}"
                + (f" ({statustext!r})" if statustext else ""),
                command=command,
                result=ack.result,
                result_name=result_name(ack.result),
                statustext=statustext,
            )
        return CommandOutcome(
            command=command,
            target=target,
            attempts=pending.confirmation + 1,
            confirmation=pending.confirmation,
        )
