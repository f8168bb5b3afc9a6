"""MAVLink 2 message signing: key file, link id and a timestamp that never goes backwards.

What we rely on from the MAVLink signing spec (mavlink.io/en/guide/message_signing.html,
"Timestamp Handling" and "Accepting Signed Packets"):

* the timestamp counts 10 µs units since 2015-01-01 00:00 GMT (Unix offset 1 420 070 400 s);
  pymavlink's ``mavutil.setup_signing`` computes the same;
* a *stream* is ``(link id, system id, component id)``; on it, a frame whose timestamp is not
  newer than the last accepted one is rejected (pymavlink's ``MAVLink.check_signature`` rejects
  ``<=``), and a stream not heard before is accepted only if its timestamp is at most one minute
  (6 000 000 ticks) behind ours;
* a sender's timestamp starts at ``max(clock, stored value)``, the stored value being written
  regularly (at least once a minute), and moves up to a correctly signed incoming timestamp
  that is greater than its own (the C library and pymavlink both do this).

:class:`TimestampKeeper` persists a *reservation*, a value ahead of anything sent so far, and
starts from ``max(wall clock, reservation)``, so a restart on a board without RTC continues
above everything sent. It rewrites the reservation when half of it is used. The in-memory
reservation moves only once the new value is on disk (written, fsynced, renamed): if the state
cannot be written (disk full, read-only file or directory), no timestamp past the stored one
is ever used — :meth:`TimestampKeeper.next_timestamp` raises :class:`SigningStateError`, and
keeps :attr:`TimestampKeeper.fault` until a later write succeeds (tried at most once per
``RETRY_S``). A state file without write permission is refused, never silently replaced.

Incoming frames (checked in ``link._Codec``), two rules beyond the spec's:

* **not from the future.** A frame stamped more than ``FUTURE_LIMIT_S`` (60 s) ahead of our
  :meth:`local clock <TimestampKeeper.local_ticks>` is refused (and counted) instead of
  adopted: adopting it would move that stream, our own timestamp and the stored reservation
  a year ahead, after which a sender with a correct clock is refused as a replay, and after a
  restart every stream is refused as more than a minute behind. The local clock is
  ``max(wall clock, start timestamp + time since start)``: it never adopts incoming values, so
  accepting frames near the limit cannot walk it forward.
* **not from before our start.** After a restart the per-stream memory is gone, and the spec
  would accept a captured frame up to a minute old as a "new stream". We refuse a new stream's
  frame if it is older than our start timestamp ``max(wall clock, stored reservation)``.
  The reservation is above every timestamp we signed, and each of those is at least the
  newest incoming timestamp accepted before it (we adopt incoming timestamps): a target that
  moved the arm was followed by our signed servo commands, so its replay is refused. A peer
  following the spec adopts our (newer) timestamp from our first signed frame after the
  restart, and is accepted from then on; until then its frames are refused and counted.

**The autopilot ahead of us** (:class:`SigningLockout`). An autopilot follows the spec: it
adopts a correctly signed incoming timestamp greater than its own, and stores it (ArduPilot with
its key, at least every 30 s, and starts a minute past it; PX4 at SETUP_SIGNING and at a
graceful shutdown). One frame from a key holder whose clock is a day ahead moves the autopilot
a day on. From then on its frames are from the future for us (refused by the first rule), and
once it restarts it refuses ours as more than a minute behind its own: the link is dead both
ways, for good (ArduPilot only ever moves its timestamp up, GPS time included). The same is
seen when *our* clock is behind (a board without RTC or NTP). Frames refused as from the future
that come from the autopilot's ids are therefore reported as a problem of their own, with both
clocks and the fix (:data:`LOCKOUT_FIX`): the link's ``signing_problem``, the daemon's status
and log, ``armbridge doctor``.

We do not follow the autopilot ahead. Its frame proves a key holder signed it, but not when: a
far-future frame recorded once and replayed after the autopilot was reset would carry us, and
through our frames the autopilot again, back into the future, and our stored reservation with
it. The future rule is what keeps a key holder's wrong clock from spreading; the fix belongs
where the wrong timestamp is (the autopilot's stored one: SETUP_SIGNING resets it).
"""

from __future__ import annotations

import errno
import logging
import math
import os
import stat
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path

from firmware_interface.errors import ConfigurationError, SigningStateError

log = logging.getLogger(__name__)

#: 2015-01-01T00:00:00Z, the MAVLink signing epoch, in Unix seconds.
SIGNING_EPOCH_UNIX_S = 1_420_070_400
#: Signing timestamps tick every 10 µs.
TICKS_PER_S = 100_000
KEY_LEN = 32
#: Incoming timestamps further ahead of our local clock than this are refused (module docstring).
FUTURE_LIMIT_S = 60.0
#: The spec's "new stream" window: one minute, in ticks.
NEW_STREAM_WINDOW_TICKS = 60 * TICKS_PER_S
#: After a failed write of the state, the next attempt waits at least this long (monotonic).
RETRY_S = 1.0
#: ArduPilot accepts these unsigned even with signing on (GCS_Signing.cpp accept_list).
MAVLINK_MSG_ID_RADIO_STATUS = 109
#: The autopilot's signing problem stands this long after its last frame refused as from the
#: future (it sends a HEARTBEAT every second).
LOCKOUT_HOLD_S = 5.0
#: What to do when the autopilot signs from the future (:class:`SigningLockout`).
LOCKOUT_FIX = (
    "if this computer's clock is wrong (a board without RTC or NTP), set it; otherwise a "
    "signing-key holder's clock was ahead and the autopilot took its timestamp: correct that "
    "clock, then reset the autopilot's timestamp: disarmed, send it the same key again with "
    "SETUP_SIGNING from a ground station (MAVProxy: signing setup with the same passphrase; "
    "Mission Planner: MAVLink Signing), which stores the current time (docs/signing.md)"
)


#: Key file permissions refused: anything for others, and writing for the group (reading for
#: the group is the documented 0640 root:armbridge-key set-up).
KEY_MODE_REFUSED = 0o027


def load_key(path: str | os.PathLike[str]) -> bytes:
    """Read a 32-byte signing key: either 32 raw bytes or 64 hex digits (whitespace ignored).
    A key file others may read or anyone but its owner may write is refused: whoever reads
    the key may sign frames that move the arm."""
    try:
        with open(path, "rb") as file:
            mode = os.fstat(file.fileno()).st_mode
            if mode & KEY_MODE_REFUSED:
                raise ConfigurationError(
                    f"signing key file {str(path)!r} has mode {mode & 0o777:04o}: anyone who "
                    "reads it can sign frames that move the arm; chmod 0600 it (or 0640 for a "
                    "group of its own)"
                )
            data = file.read()
    except OSError as exc:
        raise ConfigurationError(
            f"cannot read signing key file {str(path)!r}: {exc.strerror or exc}"
        ) from exc
    if len(data) == KEY_LEN:
        return data
    text = data.strip()
    if len(text) == 2 * KEY_LEN:
        try:
            return bytes.fromhex(text.decode("ascii"))
        except (UnicodeDecodeError, ValueError):
            pass
    raise ConfigurationError(
        f"signing key file {str(path)!r} holds {len(data)} bytes; expected {KEY_LEN} raw bytes "
        f"or {2 * KEY_LEN} hex digits"
    )


def wall_to_ticks(unix_s: float) -> int:
    """Unix time in seconds → signing timestamp ticks (0 for clocks before 2015)."""
    return max(0, int((unix_s - SIGNING_EPOCH_UNIX_S) * TICKS_PER_S))


def ticks_to_utc(ticks: int) -> str:
    """Signing timestamp ticks → ``2026-12-03 04:00:00 UTC``."""
    unix_s = SIGNING_EPOCH_UNIX_S + ticks / TICKS_PER_S
    try:
        return datetime.fromtimestamp(unix_s, UTC).strftime("%Y-%m-%d %H:%M:%S UTC")
    except (OverflowError, OSError, ValueError):  # past the year 9999 (48-bit ticks reach 2104)
        return f"{ticks} ticks"


def duration_text(seconds: float) -> str:
    """``75 s``, ``42 min``, ``5.3 h``, ``3.0 days``, ``1.0 years``."""
    if seconds < 120:
        return f"{seconds:.0f} s"
    if seconds < 7200:
        return f"{seconds / 60:.0f} min"
    if seconds < 2 * 86_400:
        return f"{seconds / 3600:.1f} h"
    if seconds < 730 * 86_400:
        return f"{seconds / 86_400:.1f} days"
    return f"{seconds / (365.25 * 86_400):.1f} years"


class SigningLockout:
    """Whether the autopilot signs from the future (module docstring, "The autopilot ahead of
    us"): fed the autopilot's frames refused as more than ``FUTURE_LIMIT_S`` ahead of our local
    clock, it reports the problem for ``hold_s`` after the latest one. Pure; ``now_s`` is the
    caller's monotonic clock."""

    def __init__(self, hold_s: float = LOCKOUT_HOLD_S) -> None:
        self.hold_s = hold_s
        #: (system, component, its timestamp, our local clock), ticks, of the latest one.
        self.latest: tuple[int, int, int, int] | None = None
        self._at_s = -math.inf

    def refused(
        self, source: tuple[int, int], timestamp: int, local_ticks: int, now_s: float
    ) -> bool:
        """The autopilot's frame, correctly signed at ``timestamp``, refused as from the future
        at our ``local_ticks``. True if this begins the problem (say so once)."""
        began = self.problem(now_s) is None
        self.latest = (source[0], source[1], timestamp, local_ticks)
        self._at_s = now_s
        return began

    def clear(self) -> bool:
        """The autopilot's frames are accepted again; True if a problem was standing."""
        stood, self._at_s = self._at_s > -math.inf, -math.inf
        return stood

    @property
    def seen(self) -> bool:
        """A refused frame was noted since the last :meth:`clear`."""
        return self._at_s > -math.inf

    def problem(self, now_s: float) -> str | None:
        """What is wrong, with both clocks, or None (the fix: :data:`LOCKOUT_FIX`)."""
        if self.latest is None or now_s - self._at_s > self.hold_s:
            return None
        system, component, timestamp, local = self.latest
        ahead = duration_text((timestamp - local) / TICKS_PER_S)
        return (
            f"the autopilot {system}/{component} signs {ahead} ahead of our clock "
            f"(its {ticks_to_utc(timestamp)}, ours {ticks_to_utc(local)}): "
            "we refuse its frames as from the future, and once it restarts it refuses ours as "
            "too old"
        )


def lockout_message(problem: str) -> str:
    """:meth:`SigningLockout.problem` with the fix, for the log and the status."""
    return f"{problem}. Fix: {LOCKOUT_FIX}"


def write_state_file(path: Path, reserved_until: int) -> None:
    """Store ``reserved_until`` in ``path`` durably: refuse a file without write permission
    (it was made read-only on purpose, or belongs to someone else: never replace it), write a
    temporary file, fsync it, rename it over ``path`` and fsync the directory. Raises
    ``OSError`` (``EACCES`` for a read-only file, ``ENOSPC`` for a full disk …)."""
    try:
        mode = path.stat().st_mode
    except FileNotFoundError:
        pass
    else:
        if not mode & stat.S_IWUSR or not os.access(path, os.W_OK):
            raise PermissionError(
                errno.EACCES,
                f"signing state file is read-only (mode {stat.S_IMODE(mode):04o}); refusing to "
                "replace it: make it writable by the daemon's user, or remove it only if the "
                "wall clock is known to be right",
                str(path),
            )
    tmp = path.with_name(path.name + ".tmp")
    try:
        with open(tmp, "w", encoding="ascii") as file:
            file.write(f"{reserved_until}\n")
            file.flush()
            os.fsync(file.fileno())
        os.replace(tmp, path)
    except OSError:
        try:
            tmp.unlink()
        except OSError:
            pass
        raise
    directory = os.open(path.parent, os.O_RDONLY)
    try:
        os.fsync(directory)
    finally:
        os.close(directory)


@dataclass(frozen=True)
class SigningConfig:
    """Optional MAVLink 2 signing for a link.

    ``key`` is the 32-byte secret, ``link_id`` (0–255) tags our outgoing stream, ``state_path``
    keeps the timestamp monotonic across restarts (None: wall clock only). Unsigned incoming
    messages are rejected except ids in ``allow_unsigned_msg_ids``. ``wall_clock`` and
    ``write_state`` (how the state file is written, :func:`write_state_file`) are seams for
    tests.
    """

    key: bytes
    link_id: int = 0
    state_path: Path | None = None
    allow_unsigned_msg_ids: frozenset[int] = frozenset({MAVLINK_MSG_ID_RADIO_STATUS})
    wall_clock: Callable[[], float] = field(default=time.time, repr=False)
    reservation_s: float = 60.0
    write_state: Callable[[Path, int], None] = field(default=write_state_file, repr=False)

    def __post_init__(self) -> None:
        if not isinstance(self.key, bytes) or len(self.key) != KEY_LEN:
            raise ConfigurationError(f"signing key must be {KEY_LEN} bytes, got {len(self.key)}")
        if not isinstance(self.link_id, int) or not 0 <= self.link_id <= 255:
            raise ConfigurationError(f"link_id={self.link_id!r} outside [0, 255]")
        if not self.reservation_s > 0:
            raise ConfigurationError(f"reservation_s={self.reservation_s!r} must be > 0")

    @classmethod
    def from_key_file(
        cls,
        key_path: str | os.PathLike[str],
        *,
        link_id: int = 0,
        state_path: str | os.PathLike[str] | None = None,
    ) -> SigningConfig:
        """Load the key from ``key_path``; see :func:`load_key`."""
        return cls(
            key=load_key(key_path),
            link_id=link_id,
            state_path=Path(state_path) if state_path is not None else None,
        )


class TimestampKeeper:
    """Hands out signing timestamps that only increase, across restarts too, and never past
    the reservation stored on disk (module docstring). ``clock``: monotonic seconds, for the
    local clock and the write retries.

    Raises ``OSError`` at construction if the state cannot be written (nothing was signed yet:
    the caller refuses to start), :class:`ConfigurationError` if it cannot be read.
    """

    def __init__(self, config: SigningConfig, *, clock: Callable[[], float] = time.monotonic):
        self._config = config
        self._clock = clock
        self._reservation_ticks = int(config.reservation_s * TICKS_PER_S)
        stored = self._load()
        #: The reservation stored by the previous run (0 if none): see the module docstring.
        self.stored_at_start = stored
        self._reserved_until = stored
        self.initial_timestamp = max(wall_to_ticks(config.wall_clock()), stored)
        self._started_s = clock()
        #: Why signing is stopped (the state cannot be written), or None.
        self.fault: str | None = None
        self._retry_at_s = -float("inf")
        self._reserve(self.initial_timestamp)

    def _load(self) -> int:
        path = self._config.state_path
        if path is None or not path.exists():
            return 0
        try:
            return int(path.read_text().strip())
        except (OSError, ValueError) as exc:
            raise ConfigurationError(
                f"signing state file {str(path)!r} is unreadable ({exc}); remove it only if "
                "the wall clock is known to be right"
            ) from exc

    def _reserve(self, timestamp: int) -> None:
        reserved_until = timestamp + self._reservation_ticks
        path = self._config.state_path
        if path is not None:
            self._config.write_state(path, reserved_until)
        # Only now: a reservation that is not on disk is no reservation.
        self._reserved_until = reserved_until

    @property
    def reserved_until(self) -> int:
        """The value persisted in the state file (next start begins at least here)."""
        return self._reserved_until

    def local_ticks(self) -> int:
        """Our own clock in ticks: ``max(wall clock, start timestamp + time since start)``.
        It never adopts incoming timestamps (the future limit is measured from it)."""
        elapsed_ticks = int((self._clock() - self._started_s) * TICKS_PER_S)
        return max(wall_to_ticks(self._config.wall_clock()), self.initial_timestamp + elapsed_ticks)

    def next_timestamp(self, current: int) -> int:
        """The timestamp to sign the next message with, given the codec's ``current`` value.

        Raises :class:`SigningStateError` (and sets :attr:`fault`) when that timestamp would
        need a new reservation that cannot be stored; it clears once one could be.
        """
        timestamp = max(current, wall_to_ticks(self._config.wall_clock()))
        if timestamp >= self._reserved_until - self._reservation_ticks // 2:
            now_s = self._clock()
            if self.fault is not None and now_s < self._retry_at_s:
                raise SigningStateError(self.fault)
            try:
                self._reserve(timestamp)
            except OSError as exc:
                first = self.fault is None
                self.fault = (
                    f"cannot store the signing timestamp in {str(self._config.state_path)!r}: "
                    f"{exc.strerror or exc}; nothing is signed past the stored reservation"
                )
                self._retry_at_s = now_s + RETRY_S
                if first:
                    log.error("%s; holding until it can be stored", self.fault)
                raise SigningStateError(self.fault) from exc
            if self.fault is not None:
                log.warning("signing state stored again: signing resumes")
                self.fault = None
        return timestamp
