"""Time for tests: the one bounded wait and the one fake clock.

Tests synchronise only by waiting, with a bound, on a condition they can observe; never by a
bare sleep. Code under test that takes a ``clock`` gets :class:`FakeClock` instead of time.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

#: The default bound of a wait: long enough for a loaded 2-core machine, short enough to fail.
WAIT_S = 10.0
#: How often :func:`wait_until` re-checks its predicate.
POLL_S = 0.005


def wait_until(
    predicate: Callable[[], object],
    timeout_s: float = WAIT_S,
    *,
    poll_s: float = POLL_S,
    ignore: tuple[type[BaseException], ...] = (),
) -> bool:
    """Poll ``predicate`` until it is true or ``timeout_s`` has passed; whether it became true.

    ``ignore``: exceptions that count as "not yet" (e.g. ``OSError`` while a socket is not
    there yet) rather than failing the wait. The predicate is checked once more at the
    deadline, so a slow predicate still gets its last chance.
    """
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            if predicate():
                return True
        except ignore:
            pass
        if time.monotonic() >= deadline:
            return False
        # The poll interval of a bounded wait: the only sleep the tests use.
        time.sleep(poll_s)


class FakeClock:
    """A monotonic clock in seconds that moves only when told to (thread-safe).

    ``advance(s)`` moves it by hand; with ``tick_s`` every reading also moves it on by that
    much after returning (a clock that "costs" time to read).
    """

    def __init__(self, start_s: float = 1000.0, *, tick_s: float = 0.0) -> None:
        self.now = start_s
        self.tick_s = tick_s
        self._lock = threading.Lock()

    def __call__(self) -> float:
        with self._lock:
            value = self.now
            self.now += self.tick_s
            return value

    def advance(self, seconds: float) -> None:
        with self._lock:
            self.now += seconds
