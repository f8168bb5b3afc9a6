"""The JSON-lines event log: one JSON object per line, flushed by :meth:`EventLog.flush` (the
server flushes once per loop pass, after the frames of that pass have left, and before it
answers a query: a frame never waits for the log, and a reader who asked sees everything).

Every event has ``t_s`` (seconds since the simulator started, monotonic) and ``event``; the other
fields depend on the event (see ``docs/sim_servo.md``). The last ``keep`` events are also kept in
memory so the query socket can return them.
"""

from __future__ import annotations

import collections
import json
from pathlib import Path
from typing import IO, Any

from sim_servo.errors import SimIOError


class EventLog:
    """Writes events to ``path`` (None: memory only) and keeps the last ``keep``."""

    def __init__(self, path: str | Path | None = None, keep: int = 10_000) -> None:
        self._file: IO[str] | None = None
        if path is not None:
            try:
                self._file = open(path, "a", encoding="utf-8")  # noqa: SIM115 - closed in close()
            except OSError as exc:
                raise SimIOError(f"cannot open event log {str(path)!r}: {exc}") from exc
        self.recent: collections.deque[dict[str, Any]] = collections.deque(maxlen=keep)

    def __call__(self, event: dict[str, Any]) -> None:
        self.recent.append(event)
        if self._file is not None:
            self._file.write(json.dumps(event, separators=(",", ":"), default=str) + "\n")

    def flush(self) -> None:
        if self._file is not None:
            self._file.flush()

    def close(self) -> None:
        if self._file is not None:
            self._file.close()  # flushes
            self._file = None


def read_events(path: str | Path) -> list[dict[str, Any]]:
    """All events in a log file (for tests and tools)."""
    with open(path, encoding="utf-8") as handle:
        return [json.loads(line) for line in handle if line.strip()]
