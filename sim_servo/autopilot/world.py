"""The vehicle and the hand in the world (:mod:`sim_servo.hover`, ``[vehicle]``), and the
periodic ``vehicle`` event that logs both.

The motion goes on through a reboot of the autopilot. :meth:`WorldLog.hand_world` puts the hand
in LOCAL_NED: vehicle ∘ mount ∘ the hand the horns give (:mod:`sim_servo.world`).
"""

from __future__ import annotations

from typing import Any

from sim_servo.autopilot.state import AutopilotState
from sim_servo.hand import HandModel
from sim_servo.hover import HoverDisturbance, VehicleState
from sim_servo.servo import Servo
from sim_servo.world import FloatArray, WorldPose, hand_in_world, mount_matrix, pose_matrix

#: ``vehicle`` events are written in batches at most this long after they were due (a wake-up
#: per sample would cost more than the samples), and never more than VEHICLE_LOG_MAX_S behind.
VEHICLE_LOG_LAG_S = 0.2
VEHICLE_LOG_MAX_S = 2.0


class WorldLog:
    """The vehicle's motion (pure, seeded), the hand on it, and their log."""

    def __init__(
        self,
        state: AutopilotState,
        hand: HandModel | None,
        servos: dict[int, Servo],
        *,
        now_s: float,
    ) -> None:
        self._state = state
        self._hand = hand
        self._servos = servos
        vehicle = state.config.vehicle
        self.vehicle = HoverDisturbance.from_config(vehicle)
        self._mount = mount_matrix(vehicle.mount)
        #: The hand in the arm's base frame for the last horn positions seen (an FK is costly).
        self._hand_key: tuple[float, ...] | None = None
        self._hand_base: FloatArray | None = None
        log_rate_hz = vehicle.log_rate_hz
        self._period_s = 1.0 / log_rate_hz if log_rate_hz > 0 else 0.0
        self._due_s: float | None = now_s if log_rate_hz > 0 else None
        #: Samples fall at origin + n·period (no drift from adding periods up).
        self._origin_s, self._n = now_s, 0

    def vehicle_state(self, now_s: float) -> VehicleState:
        return self.vehicle.state(now_s - self._state.start_s)

    def hand_world(self, now_s: float, vehicle: VehicleState | None = None) -> WorldPose | None:
        """The hand in LOCAL_NED at ``now_s``: the vehicle's pose then (``vehicle``, if already
        computed), the mount, and the hand the servos' horns give (None without a hand model or
        while a horn is outside its joint's PWM range)."""
        if self._hand is None:
            return None
        key = tuple(round(self._servos[o].position_us(now_s), 3) for o in self._hand.outputs)
        if key != self._hand_key:
            pose = self._hand.state(dict(zip(self._hand.outputs, key, strict=True))).pose
            self._hand_key = key
            self._hand_base = None if pose is None else pose_matrix(*pose.as_tuple())
        if self._hand_base is None:
            return None
        if vehicle is None:
            vehicle = self.vehicle_state(now_s)
        return hand_in_world(vehicle, self._mount, self._hand_base)

    def sample(self, now_s: float) -> dict[str, Any]:
        """The vehicle's state and the hand in the world at ``now_s``, JSON-ready (the
        ``vehicle`` event's fields)."""
        vehicle = self.vehicle_state(now_s)
        hand = self.hand_world(now_s, vehicle)
        return {
            "vehicle": vehicle.as_dict(),
            "hand_ned": hand.as_dict() if hand is not None else None,
        }

    def run(self, now_s: float) -> None:
        """The ``vehicle`` events due by ``now_s``, each stamped and computed at its own due
        time. They are written late, in batches (on any pass, at most VEHICLE_LOG_LAG_S after
        they were due), and always before a servo is given a new course (every command and
        output change calls this first), so the horn positions of a past sample are exact: a
        servo's motion between two commands is known at any time. More than VEHICLE_LOG_MAX_S
        behind (a stalled process) the cadence restarts from now."""
        due = self._due_s
        if due is None or now_s < due:
            return
        if now_s - due > VEHICLE_LOG_MAX_S:
            self._origin_s, self._n, due = now_s, 0, now_s
        while due <= now_s:
            self._state.emit(due, "vehicle", **self.sample(due))
            self._n += 1
            due = self._origin_s + self._n * self._period_s
        self._due_s = due

    def next_event_s(self) -> float | None:
        # Samples are written late, in batches (see run): no wake-up for each.
        return None if self._due_s is None else self._due_s + VEHICLE_LOG_LAG_S
