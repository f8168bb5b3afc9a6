"""The vehicle's motion from the autopilot's ATTITUDE and LOCAL_POSITION_NED, on the daemon's
clock.

Each frame says when its state held in the autopilot's clock (``time_boot_ms``). To carry the
state forward to when the servos will move, that time is mapped onto the daemon's clock: the
offset ``received_s − time_boot`` of a frame is the clocks' offset plus that frame's delay on
the way (never negative), so the smallest offset over the last :data:`OFFSET_WINDOW_S` is the
best estimate (the frame that waited least; the window lets the estimate follow the crystals'
drift, ~100 ppm: 0.5 ms in 5 s). A ``time_boot_ms`` going backwards (a reboot) starts over.

Pure: frames and times in, a :class:`~companion.kinematics.vehicle.VehicleState` out; fed by
the control core from the pinned autopilot only. A frame with a NaN or infinite field is
dropped and counted (a frame forged as the autopilot can say anything; it is not believed).
"""

from __future__ import annotations

import collections
import math
from typing import Any

from companion.kinematics.vehicle import VehicleState

#: The smallest offset over this long is the clocks' offset.
OFFSET_WINDOW_S = 5.0
#: ``time_boot_ms`` back by more than this: the autopilot rebooted; everything starts over.
BACKSTEP_MS = 100
KINDS = frozenset({"ATTITUDE", "LOCAL_POSITION_NED"})


class VehicleTelemetry:
    """ATTITUDE and LOCAL_POSITION_NED → :class:`VehicleState` (see the module docstring)."""

    def __init__(self) -> None:
        self._offsets: collections.deque[tuple[float, float]] = collections.deque()
        self._last_boot_ms: int | None = None
        self._attitude: tuple[float, tuple[float, ...], tuple[float, ...]] | None = None
        self._position: tuple[float, tuple[float, ...], tuple[float, ...]] | None = None
        self._state: VehicleState | None = None  # built from the two samples, once
        self.dropped = 0

    def reset(self) -> None:
        self._offsets.clear()
        self._last_boot_ms = None
        self._attitude = None
        self._position = None
        self._state = None

    def on_frame(self, msg: Any, received_s: float) -> bool:
        """Take an ATTITUDE or LOCAL_POSITION_NED received at ``received_s`` (daemon clock);
        False if it is neither, or was dropped."""
        kind = msg.get_type()
        if kind not in KINDS:
            return False
        if kind == "ATTITUDE":
            first = (msg.roll, msg.pitch, msg.yaw)
            second = (msg.rollspeed, msg.pitchspeed, msg.yawspeed)
        else:  # metres → cm
            first = (msg.x * 100.0, msg.y * 100.0, msg.z * 100.0)
            second = (msg.vx * 100.0, msg.vy * 100.0, msg.vz * 100.0)
        values = (*first, *second)
        if not all(isinstance(v, float | int) and math.isfinite(v) for v in values):
            self.dropped += 1
            return False
        boot_ms = int(msg.time_boot_ms)
        if self._last_boot_ms is not None and boot_ms + BACKSTEP_MS < self._last_boot_ms:
            self.reset()  # rebooted: its clock started over
        self._last_boot_ms = (
            boot_ms if self._last_boot_ms is None else max(boot_ms, self._last_boot_ms)
        )
        held_s = self._held_s(boot_ms, received_s)
        sample = (held_s, tuple(map(float, first)), tuple(map(float, second)))
        if kind == "ATTITUDE":
            self._attitude = sample
        else:
            self._position = sample
        self._state = None
        return True

    def _held_s(self, boot_ms: int, received_s: float) -> float:
        """When a frame's state held, on the daemon clock."""
        boot_s = boot_ms / 1000.0
        offset = received_s - boot_s
        offsets = self._offsets
        # A monotonic deque: the smallest offset of the window at its front.
        while offsets and offsets[-1][1] >= offset:
            offsets.pop()
        offsets.append((received_s, offset))
        while offsets[0][0] < received_s - OFFSET_WINDOW_S:
            offsets.popleft()
        return boot_s + offsets[0][1]

    def state(self) -> VehicleState | None:
        """The vehicle's last known state, or None until both streams have been heard."""
        if self._state is None:
            if self._attitude is None or self._position is None:
                return None
            att_t, rpy, rates = self._attitude
            pos_t, position, velocity = self._position
            self._state = VehicleState(pos_t, position, velocity, att_t, rpy, rates)  # type: ignore[arg-type]
        return self._state
