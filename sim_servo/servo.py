"""One hobby servo: slew-limited motion towards the commanded pulse, with a deadband.

Pure and clock-free: every method takes the time ``now_s`` (any monotonic seconds), so tests
drive it with plain numbers. Positions are expressed in the pulse width (µs) the horn
corresponds to, so "at target" is a comparison with the commanded PWM.

Model:

* the horn moves at a constant ``rate_us_per_s`` towards the target and stops there
  (``60° / slew_s_per_60deg`` converted with ``deg_per_us``);
* a command within ``deadband_us`` of the horn's current position does not start the motor: the
  horn stays where it is (a real servo's dead band);
* a pulse of 0 µs means no pulses (ArduPilot's "output off"): the horn holds its position;
* the horn stops at its mechanical travel ``[travel_min_us, travel_max_us]`` — the PWM itself is
  never clamped (that is the autopilot's business, and ArduPilot does not clamp).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from sim_servo.errors import SimConfigError


@dataclass(frozen=True)
class ServoParams:
    """Physical parameters of one servo (see :class:`sim_servo.config.ServoConfig`)."""

    slew_s_per_60deg: float = 0.12
    deg_per_us: float = 0.09
    deadband_us: float = 1.0
    travel_min_us: float = 500.0
    travel_max_us: float = 2500.0

    def __post_init__(self) -> None:
        if not (math.isfinite(self.deg_per_us) and self.deg_per_us > 0):
            raise SimConfigError(f"deg_per_us={self.deg_per_us!r} must be > 0")
        if not (math.isfinite(self.slew_s_per_60deg) and self.slew_s_per_60deg >= 0):
            raise SimConfigError(f"slew_s_per_60deg={self.slew_s_per_60deg!r} must be >= 0")

    @property
    def rate_us_per_s(self) -> float:
        """Horn speed in µs of pulse per second (infinite for ``slew_s_per_60deg`` 0)."""
        if self.slew_s_per_60deg == 0:
            return math.inf
        return (60.0 / self.slew_s_per_60deg) / self.deg_per_us


class Servo:
    """Position over time of one servo. ``commanded_us`` is the last PWM applied (0 = none)."""

    def __init__(self, params: ServoParams, initial_us: float, start_s: float) -> None:
        self.params = params
        self.commanded_us: float = 0.0
        self._from_us = float(initial_us)
        self._target_us = float(initial_us)
        self._start_s = float(start_s)

    @property
    def target_us(self) -> float:
        """Where the horn is heading (its resting place once it arrives)."""
        return self._target_us

    def position_us(self, now_s: float) -> float:
        """Horn position at ``now_s`` (µs of pulse it corresponds to)."""
        distance = self._target_us - self._from_us
        if distance == 0 or now_s >= self.arrival_s():
            return self._target_us
        travelled = self.params.rate_us_per_s * max(0.0, now_s - self._start_s)
        return self._from_us + math.copysign(min(travelled, abs(distance)), distance)

    def arrival_s(self) -> float:
        """When the horn reaches its target (``start`` of the last move if already there)."""
        distance = abs(self._target_us - self._from_us)
        if distance == 0 or math.isinf(self.params.rate_us_per_s):
            return self._start_s
        return self._start_s + distance / self.params.rate_us_per_s

    def moving(self, now_s: float) -> bool:
        return self.position_us(now_s) != self._target_us

    def command(self, pwm_us: float, now_s: float) -> bool:
        """Apply pulse ``pwm_us`` at ``now_s``; True when the horn starts moving."""
        self.commanded_us = float(pwm_us)
        here = self.position_us(now_s)
        if pwm_us == 0:
            goal = here  # no pulses: the horn holds where it is
        else:
            goal = min(max(float(pwm_us), self.params.travel_min_us), self.params.travel_max_us)
            if abs(goal - here) <= self.params.deadband_us:
                goal = here
        self._from_us, self._target_us, self._start_s = here, goal, float(now_s)
        return goal != here
