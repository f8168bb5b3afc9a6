"""What every part of the autopilot reads: the settings, the firmware's flavour, the times of
this run and of the current boot, the event log and the counters.

The reboot part alone moves ``boot_s`` and ``rebooting_until_s``; every part may emit events
and count in ``stats``. Nothing else is shared: each part owns its own state and the others use
its public methods.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from sim_servo.config import SimConfig

if TYPE_CHECKING:
    from sim_servo.autopilot.flavour import Flavour

Emit = Callable[[dict[str, Any]], None]

#: The counters ``stats`` holds, in the order the snapshot lists them.
STAT_NAMES = (
    "rx",
    "tx",
    "bad_frames",
    "rejected_signature",
    "dropped_in",
    "dropped_out",
    "corrupted_in",
    "corrupted_out",
    "acks",
    "acks_withheld",
    "routed",
    "reboots",
    "ignored_rebooting",
    "forged",
)


class AutopilotState:
    """The run's shared state; ``now_s`` is the injected clock's time at start."""

    def __init__(
        self,
        config: SimConfig,
        flavour: Flavour,
        *,
        now_s: float,
        emit: Emit | None,
        wall_clock: Callable[[], float],
    ) -> None:
        self.config = config
        self.flavour = flavour
        self._emit_sink = emit or (lambda event: None)
        self.start_s = now_s
        #: When the current boot started: time_boot, the main-loop phase (a reboot moves it).
        self.boot_s = now_s
        #: While rebooting: when the autopilot comes back (silent and deaf until then).
        self.rebooting_until_s: float | None = None
        #: The wall clock at ``now_s``, for SYSTEM_TIME; later read as ``now_s`` goes on.
        self.unix_at_start_s = wall_clock()
        self.loop_s = 1.0 / config.loop_rate_hz
        self.stats = dict.fromkeys(STAT_NAMES, 0)

    @property
    def rebooting(self) -> bool:
        return self.rebooting_until_s is not None

    def t(self, now_s: float) -> float:
        """``now_s`` as the event log's time: seconds since start, to the microsecond."""
        return round(now_s - self.start_s, 6)

    def emit(self, now_s: float, event: str, **fields: Any) -> None:
        self._emit_sink({"t_s": self.t(now_s), "event": event, **fields})

    def time_boot_us(self, now_s: float) -> int:
        return max(0, round((now_s - self.boot_s) * 1e6))

    def time_unix_us(self, now_s: float) -> int:
        return max(0, round((self.unix_at_start_s + now_s - self.start_s) * 1e6))

    def next_tick_s(self, now_s: float) -> float:
        """The next main-loop pass at or after ``now_s`` (passes every ``1/loop_rate_hz`` from
        boot)."""
        ticks = math.ceil(round((now_s - self.boot_s) / self.loop_s, 9))
        return self.boot_s + ticks * self.loop_s
