"""MAVLink 2 message signing: key file, link id and a timestamp that never goes backwards.

The signing timestamp counts 10 µs units since 2015-01-01 00:00 UTC (MAVLink signing spec;
pymavlink's ``mavutil.setup_signing`` computes the same). A receiver rejects a stream whose
timestamp does not increase, so after a restart we must not reuse old values even when the
companion has no RTC and boots with a clock in the past. :class:`TimestampKeeper` therefore
persists a *reservation* — a value ahead of anything sent so far — to a state file and starts
from ``max(wall clock, reservation)``. It rewrites the reservation only when half of it has been
used, so the file is written rarely, yet a crash can never make timestamps repeat.
"""

from __future__ import annotations

import logging
import os
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from firmware_interface.errors import ConfigurationError

log = logging.getLogger(__name__)

#: 2015-01-01T00:00:00Z, the MAVLink signing epoch, in Unix seconds.
SIGNING_EPOCH_UNIX_S = 1_420_070_400
#: Signing timestamps tick every 10 µs.
TICKS_PER_S = 100_000
KEY_LEN = 32
#: ArduPilot accepts these unsigned even with signing on (GCS_Signing.cpp accept_list).
MAVLINK_MSG_ID_RADIO_STATUS = 109


def load_key(path: str | os.PathLike[str]) -> bytes:
    """Read a 32-byte signing key: either 32 raw bytes or 64 hex digits (whitespace ignored)."""
    try:
        data = Path(path).read_bytes()
    except OSError as exc:
        raise ConfigurationError(f"cannot read signing key file {str(path)!r}: {exc}") from exc
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


@dataclass(frozen=True)
class SigningConfig:
    """Optional MAVLink 2 signing for a link.

    ``key`` is the 32-byte secret, ``link_id`` (0–255) tags our outgoing stream, ``state_path``
    keeps the timestamp monotonic across restarts (None: wall clock only). Unsigned incoming
    messages are rejected except ids in ``allow_unsigned_msg_ids``.
    """

    key: bytes
    link_id: int = 0
    state_path: Path | None = None
    allow_unsigned_msg_ids: frozenset[int] = frozenset({MAVLINK_MSG_ID_RADIO_STATUS})
    wall_clock: Callable[[], float] = field(default=time.time, repr=False)
    reservation_s: float = 60.0

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
    """Hands out signing timestamps that only increase, across restarts too."""

    def __init__(self, config: SigningConfig) -> None:
        self._config = config
        self._reservation_ticks = int(config.reservation_s * TICKS_PER_S)
        stored = self._load()
        self._reserved_until = stored
        self.initial_timestamp = max(wall_to_ticks(config.wall_clock()), stored)
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
        self._reserved_until = timestamp + self._reservation_ticks
        path = self._config.state_path
        if path is None:
            return
        tmp = path.with_name(path.name + ".tmp")
        tmp.write_text(f"{self._reserved_until}\n")
        os.replace(tmp, path)

    @property
    def reserved_until(self) -> int:
        """The value persisted in the state file (next start begins at least here)."""
        return self._reserved_until

    def next_timestamp(self, current: int) -> int:
        """The timestamp to sign the next message with, given the codec's ``current`` value."""
        timestamp = max(current, wall_to_ticks(self._config.wall_clock()))
        if timestamp >= self._reserved_until - self._reservation_ticks // 2:
            self._reserve(timestamp)
        return timestamp
