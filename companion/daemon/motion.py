"""Joint motion limits: how far the commanded joints may move in one control tick.

The daemon never jumps to a new solution: each tick it moves the commanded joints towards the
goal by at most ``joint_speed_deg_s / rate_hz`` degrees on any joint. All joints travel the same
fraction of their remaining distance, so they arrive together and the hand sweeps a path rather
than one joint finishing early.
"""

from __future__ import annotations

from collections.abc import Sequence


def limit_step(
    current_deg: Sequence[float], goal_deg: Sequence[float], max_step_deg: float
) -> tuple[float, ...]:
    """The next commanded joints: towards ``goal_deg``, no joint moving more than
    ``max_step_deg``; exactly ``goal_deg`` once it is within reach."""
    if not max_step_deg > 0:
        raise ValueError(f"max_step_deg={max_step_deg!r} must be > 0")
    if len(current_deg) != len(goal_deg):
        raise ValueError(f"{len(current_deg)} current joints but {len(goal_deg)} goal joints")
    largest = max(abs(g - c) for c, g in zip(current_deg, goal_deg, strict=True))
    if largest <= max_step_deg:
        return tuple(float(g) for g in goal_deg)
    fraction = max_step_deg / largest
    return tuple(c + fraction * (g - c) for c, g in zip(current_deg, goal_deg, strict=True))
