"""Joint steps faster than the speed limit, from what the servos physically received.

Pure functions over the simulator's event log (``start`` and ``output`` events, see
:mod:`sim_servo.eventlog`), used by ``bench/output_cycles.py`` and tested on hand-made timelines.

**A fast step.** Per output, each change of the physical pulse is a step of the joint from the
angle of the last pulse before it to the angle of the new one (angles through the joint's
calibration). It is *fast* when

    |Δangle| > joint_speed_deg_s / rate_hz + quantum_deg

i.e. more than one control tick's step (the most the daemon ever sends at once: its step is
``joint_speed_deg_s × min(1 / rate_hz, time since its previous step)``) plus one PWM quantum
(the joint's degrees per µs: a step is rounded to whole µs). ``Δt`` (the time since the output's
previous physical change) does not widen the allowance: a servo held for seconds and then given
a new pulse moves there at its own slew rate, so a jump after a long hold (the disarmed PWM to a
stored value when PX4 arms; a stored value when ArduPilot's safety switch is released) is as
fast as one after a tick. The looser reading, allowance ``joint_speed_deg_s × max(Δt, 1 /
rate_hz)`` (a jump spread over the time since the previous change), is also given per step
(``loose``), for comparison.

**No pulses** (PWM 0: an ArduPilot output held by its safety switch, any output during a
reboot): the servo holds where it was, so a change to 0 is no step, and the next pulse is
compared with the last pulse before the gap. The first pulse an output ever gets has nothing to
compare with (ArduPilot outputs start without pulses, the servo wherever it was left): it is
returned apart, never counted as fast.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from typing import Any


@dataclass(frozen=True)
class Change:
    """One change of an output's physical pulse (``pwm_us`` 0: no pulses), and why."""

    t_s: float
    pwm_us: int
    cause: str


@dataclass(frozen=True)
class JointStep:
    """A physical step of one joint (see the module docstring)."""

    output: int
    t_s: float
    from_us: int
    to_us: int
    step_deg: float  # |Δangle|
    dt_s: float  # since the output's previous physical change (a change to 0 included)
    allowed_deg: float  # joint_speed_deg_s / rate_hz + quantum_deg
    cause: str  # the simulator's cause of the change: command, arm, prearm, safety_off ...

    @property
    def fast(self) -> bool:
        return self.step_deg > self.allowed_deg

    def loose(self, joint_speed_deg_s: float, rate_hz: float, quantum_deg: float) -> bool:
        """Fast even against ``joint_speed_deg_s × max(Δt, 1 / rate_hz) + quantum_deg``."""
        return self.step_deg > joint_speed_deg_s * max(self.dt_s, 1.0 / rate_hz) + quantum_deg


def output_changes(events: Iterable[Mapping[str, Any]]) -> dict[int, list[Change]]:
    """Each output's physical pulse over time from the log: the ``start`` event's
    ``outputs_us`` (cause ``start``), then each ``output`` event. Raises ``ValueError`` when an
    ``output`` event does not follow on from the one before (a log that lost lines)."""
    changes: dict[int, list[Change]] = {}
    for event in events:
        if event["event"] == "start" and "outputs_us" in event:
            for output, pwm in event["outputs_us"].items():
                changes[int(output)] = [Change(float(event["t_s"]), int(pwm), "start")]
        elif event["event"] == "output":
            output = int(event["output"])
            history = changes.setdefault(output, [])
            if history and history[-1].pwm_us != event["from_us"]:
                raise ValueError(
                    f"output {output}: event at t_s={event['t_s']} goes from "
                    f"{event['from_us']} µs but the log had it at {history[-1].pwm_us} µs"
                )
            history.append(Change(float(event["t_s"]), int(event["pwm_us"]), str(event["cause"])))
    return changes


def joint_steps(
    output: int,
    changes: Iterable[Change],
    to_angle_deg: Callable[[int], float],
    *,
    joint_speed_deg_s: float,
    rate_hz: float,
    quantum_deg: float,
) -> tuple[list[JointStep], list[Change]]:
    """``output``'s physical steps (every change to a pulse, compared with the last pulse before
    it) and its first pulses (nothing to compare with). ``to_angle_deg`` maps a PWM (µs, > 0)
    to the joint's angle."""
    if not (joint_speed_deg_s > 0 and rate_hz > 0 and quantum_deg >= 0):
        raise ValueError(
            f"joint_speed_deg_s={joint_speed_deg_s!r} and rate_hz={rate_hz!r} must be > 0, "
            f"quantum_deg={quantum_deg!r} >= 0"
        )
    allowed_deg = joint_speed_deg_s / rate_hz + quantum_deg
    steps: list[JointStep] = []
    first: list[Change] = []
    pulse: int | None = None  # the last pulse (> 0): where the servo holds
    previous_s: float | None = None
    for change in changes:
        dt_s = change.t_s - previous_s if previous_s is not None else float("inf")
        previous_s = change.t_s
        if change.pwm_us == 0:
            continue  # no pulses: the servo holds
        if pulse is None:
            first.append(change)
        elif change.pwm_us != pulse:
            steps.append(
                JointStep(
                    output=output,
                    t_s=change.t_s,
                    from_us=pulse,
                    to_us=change.pwm_us,
                    step_deg=abs(to_angle_deg(change.pwm_us) - to_angle_deg(pulse)),
                    dt_s=dt_s,
                    allowed_deg=allowed_deg,
                    cause=change.cause,
                )
            )
        pulse = change.pwm_us
    return steps, first
