"""Seeded fault decisions: drop, corrupt, delay; and the hang-up schedule. Pure; the same seed
gives the same faults.

The generator is drawn from only when a fault is enabled, so turning one fault on does not
change the sequence another one sees in a run where it was already on.
"""

from __future__ import annotations

import numpy as np

from sim_servo.config import FaultConfig


class FaultInjector:
    """Decides, frame by frame, what the faulty link does. ``rng`` defaults to ``config.seed``."""

    def __init__(self, config: FaultConfig, rng: np.random.Generator | None = None) -> None:
        self.config = config
        self.rng = rng if rng is not None else np.random.default_rng(config.seed)

    def _hit(self, probability: float) -> bool:
        if probability <= 0.0:
            return False
        if probability >= 1.0:
            return True
        return bool(self.rng.random() < probability)

    def drop_in(self) -> bool:
        """True when the next incoming frame is lost."""
        return self._hit(self.config.drop_in)

    def drop_out(self) -> bool:
        """True when the next outgoing frame is lost."""
        return self._hit(self.config.drop_out)

    def _corrupt(self, data: bytes, probability: float) -> bytes:
        if not data or not self._hit(probability):
            return data
        index = int(self.rng.integers(0, len(data)))
        flip = int(self.rng.integers(1, 256))  # never 0: the byte always changes
        corrupted = bytearray(data)
        corrupted[index] ^= flip
        return bytes(corrupted)

    def corrupt_in(self, data: bytes) -> bytes:
        """``data`` with one byte flipped, with probability ``corrupt_in``; else unchanged."""
        return self._corrupt(data, self.config.corrupt_in)

    def corrupt_out(self, data: bytes) -> bytes:
        """``data`` with one byte flipped, with probability ``corrupt_out``; else unchanged."""
        return self._corrupt(data, self.config.corrupt_out)

    def delay_s(self) -> float:
        """Added latency for one outgoing frame: ``latency_ms ± jitter_ms`` (uniform), ≥ 0."""
        delay_ms = self.config.latency_ms
        if self.config.jitter_ms > 0:
            delay_ms += float(self.rng.uniform(-self.config.jitter_ms, self.config.jitter_ms))
        return max(0.0, delay_ms) / 1000.0


class HangupSchedule:
    """When the port goes away (``hangup_after_s`` after ``start_s``, or on demand with
    :meth:`hang_up_now`) and, if ``hangup_for_s`` is set, when it comes back: a USB serial
    adapter unplugged and re-enumerated. Each fault happens once; the server applies them to
    its endpoint."""

    HANGUP = "hangup"
    REOPEN = "reopen"

    def __init__(
        self, start_s: float, hangup_after_s: float | None, hangup_for_s: float | None = None
    ) -> None:
        self._due: list[tuple[float, str]] = []
        self._for_s = hangup_for_s
        self._down = False  # between a hang-up and its reopen (for good without one)
        if hangup_after_s is not None:
            hangup_at_s = start_s + hangup_after_s
            self._due.append((hangup_at_s, self.HANGUP))
            if hangup_for_s is not None:
                self._due.append((hangup_at_s + hangup_for_s, self.REOPEN))

    def hang_up_now(self, now_s: float) -> bool:
        """Hang up at ``now_s`` (and come back ``hangup_for_s`` later, if set) instead of at the
        scheduled time; False (nothing changes) while the port is away."""
        if self._down:
            return False
        self._due = [(now_s, self.HANGUP)]  # replaces the scheduled one
        if self._for_s is not None:
            self._due.append((now_s + self._for_s, self.REOPEN))
        return True

    def next_s(self) -> float:
        """The time of the next fault (``inf`` when none is left)."""
        return self._due[0][0] if self._due else float("inf")

    def due(self, now_s: float) -> list[str]:
        """The faults due by ``now_s``, in order (``HANGUP``, ``REOPEN``); each only once."""
        faults = [fault for at_s, fault in self._due if at_s <= now_s]
        self._due = self._due[len(faults) :]
        for fault in faults:
            self._down = fault == self.HANGUP
        return faults
