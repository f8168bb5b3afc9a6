"""The JSON-lines event log: one JSON object per line, flushed by :meth:`EventLog.flush` (the
server flushes once per loop pass, after the frames of that pass have left, and before it
answers a query: a frame never waits for the log, and a reader who asked sees everything).

Every event has ``t_s`` (seconds since the simulator started, monotonic) and ``event``; the other
fields depend on the event (see ``docs/simulator.md``). The last ``keep`` events are also kept in
memory so the query socket can return them.

What a servo physically receives is in the log: ``start`` has every output's pulse
(``outputs_us``) and each ``output`` event one change (``pwm_us``, ``from_us``, ``cause``), so
:func:`physical_pwm_timeline` rebuilds every output's pulse over time from the log alone —
arming, prearm, the safety switch and reboots included (``arming`` / ``prearm`` / ``safety``
events say why).

Where the hand is in the world is in the log too: the periodic ``vehicle`` events (``[vehicle]
log_rate_hz``) carry the vehicle's state and the hand's pose in LOCAL_NED at their ``t_s``, and
:func:`world_timeline` returns them; the ``start`` event's ``vehicle`` holds the settings (seed,
bounds, mount) that rebuild the same motion at any time:
``HoverDisturbance.from_config(config_from_mapping({"vehicle": start["vehicle"]}).vehicle)``.
``vehicle`` events are written up to 0.2 s late, in batches (see
:meth:`~sim_servo.autopilot.world.WorldLog.run`): in time order among themselves, not
with the other events.
"""

from __future__ import annotations

import collections
import json
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any

from sim_servo.errors import SimIOError
from sim_servo.hover import VehicleState
from sim_servo.world import WorldPose


class EventLog:
    """Writes events to ``path`` (None: memory only) and keeps the last ``keep``.

    An event is only kept when it is emitted; it is turned into JSON and written at
    :meth:`flush` (the server's, once its frames of the pass are out), so the JSON's cost never
    delays a frame. Events are not changed after they are emitted."""

    def __init__(self, path: str | Path | None = None, keep: int = 10_000) -> None:
        self._file: IO[str] | None = None
        if path is not None:
            try:
                self._file = open(path, "a", encoding="utf-8")  # noqa: SIM115 - closed in close()
            except OSError as exc:
                raise SimIOError(f"cannot open event log {str(path)!r}: {exc}") from exc
        self.recent: collections.deque[dict[str, Any]] = collections.deque(maxlen=keep)
        self._unwritten: list[dict[str, Any]] = []

    def __call__(self, event: dict[str, Any]) -> None:
        self.recent.append(event)
        if self._file is not None:
            self._unwritten.append(event)

    def flush(self) -> None:
        if self._file is not None:
            if self._unwritten:
                events, self._unwritten = self._unwritten, []
                self._file.write(
                    "".join(
                        json.dumps(event, separators=(",", ":"), default=str) + "\n"
                        for event in events
                    )
                )
            self._file.flush()

    def close(self) -> None:
        if self._file is not None:
            self.flush()
            self._file.close()
            self._file = None


def read_events(path: str | Path) -> list[dict[str, Any]]:
    """All events in a log file (for tests and tools). A log still being written may end in
    part of a line (a pass's events go out in one write, which the file's buffer may split):
    only whole lines are read."""
    with open(path, encoding="utf-8") as handle:
        return [json.loads(line) for line in handle if line.endswith("\n") and line.strip()]


def physical_pwm_timeline(events: list[dict[str, Any]]) -> dict[int, list[tuple[float, int]]]:
    """Each output's physical pulse over time, ``output → [(t_s, pwm_us), …]`` from the
    ``start`` event's ``outputs_us`` and the ``output`` events (0: no pulses). Raises
    ``ValueError`` when an ``output`` event does not follow on from the one before (a log
    that lost lines)."""
    timeline: dict[int, list[tuple[float, int]]] = {}
    for event in events:
        if event["event"] == "start" and "outputs_us" in event:
            for output, pwm in event["outputs_us"].items():
                timeline[int(output)] = [(float(event["t_s"]), int(pwm))]
        elif event["event"] == "output":
            output = int(event["output"])
            history = timeline.setdefault(output, [])
            if history and history[-1][1] != event["from_us"]:
                raise ValueError(
                    f"output {output}: event at t_s={event['t_s']} goes from "
                    f"{event['from_us']} µs but the log had it at {history[-1][1]} µs"
                )
            history.append((float(event["t_s"]), int(event["pwm_us"])))
    return timeline


@dataclass(frozen=True)
class WorldSample:
    """One ``vehicle`` event: the time (s since start), the vehicle, the hand in LOCAL_NED
    (None while the hand is unknown: a horn outside its joint's PWM range)."""

    t_s: float
    vehicle: VehicleState
    hand: WorldPose | None


def world_timeline(events: list[dict[str, Any]]) -> list[WorldSample]:
    """The ``vehicle`` events in log order: ``[(t_s, vehicle state, hand pose in LOCAL_NED)]``,
    for a bench computing the hand's world error over time."""
    return [
        WorldSample(
            float(event["t_s"]),
            VehicleState.from_dict(event["vehicle"]),
            WorldPose.from_dict(event["hand_ned"]) if event["hand_ned"] is not None else None,
        )
        for event in events
        if event["event"] == "vehicle"
    ]
