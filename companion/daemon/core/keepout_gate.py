"""The keep-out gate: targets solved clear of the keep-out volumes, and every step's path
from the step commanded last checked before it goes out."""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

from companion.ik.keepout import ClearVerdict, solve_clear
from companion.ik.solver import TargetMode
from companion.kinematics.arm import Pose
from firmware_interface import CalibrationError
from firmware_interface.updates import ServoCommand

if TYPE_CHECKING:
    from companion.daemon.core.dispatcher import ControlCore


class KeepoutGate:
    """Solve clear, and check a step's path (no volumes configured: everything passes)."""

    def __init__(self, core: ControlCore) -> None:
        self._core = core

    @property
    def active(self) -> bool:
        return self._core.settings.keepout is not None

    def solve(
        self, pose: Pose, start: Sequence[float], mode: str, budget_ms: float | None
    ) -> tuple[Any, str | None]:
        """Solve a target: ``(result, None)``, or ``(result or None, why it is refused)``.

        Without keep-out volumes, the injected solver once, warm from ``start``. With them,
        :func:`~companion.ik.keepout.solve_clear` within the same budget: a target reachable
        clear of every volume is reached (another solution is looked for when the first
        collides; the one taken is steered away from the volumes where the target leaves
        freedom); one that is not is refused naming the link and the volume. The motion is
        judged from the step commanded last (where the outputs go next) **straight** to the
        solution, the path the speed limit steps along: a solution whose straight motion would
        cross a volume is not taken (another is looked for), and if every one found would, the
        target is refused naming where along the motion. The daemon does not plan detours
        round a volume: a user who wants one sends a waypoint first (a trajectory)."""
        core = self._core
        keepout = core.settings.keepout
        if keepout is None:
            return core.solve(pose, start, mode, budget_ms), None
        config = core.config

        def solver(arm: Any, target: Pose, **kwargs: Any) -> Any:
            return core.solve(
                target,
                kwargs["q_start_deg"],
                kwargs["mode"].value,
                kwargs["budget_ms"],
                seed=kwargs["seed"],
            )

        out = solve_clear(
            keepout,
            pose,
            budget_ms=config.budget_ms if budget_ms is None else budget_ms,
            seed=config.seed,
            q_start_deg=core.state.commanded(),
            tol_pos_cm=config.tol_pos_cm,
            tol_ori_deg=config.tol_ori_deg,
            mode=TargetMode(mode),
            solver=solver,
            clock=core.clock,  # the core's: a test's fake clock makes the attempts exact
        )
        if out.verdict is ClearVerdict.CLEAR:
            return out.result, None
        why = None if out.collision is None else out.collision.reason
        if out.verdict in (ClearVerdict.COLLIDES, ClearVerdict.MOTION_COLLIDES):
            core.state.counters["keepout_refusals"] += 1
            what = (
                "the motion to every solution found"
                if out.verdict is ClearVerdict.MOTION_COLLIDES
                else "every solution found"
            )
            return out.refused_answer, f"keep-out: {what} is refused: {why}"
        nearest = out.result
        if nearest is None and out.refused_answer is not None:
            # No answer met the tolerances: the target is out of reach, whatever the volumes;
            # that the nearest configurations also collide is the lesser news.
            near = out.refused_answer
            return near, (
                f"unreachable: pos {near.pos_err_cm:.2f}cm ori {near.ori_err_deg:.1f}deg"
                + ("" if why is None else f" (the nearest configurations found also put {why})")
            )
        if nearest is None:
            return None, "unreachable clear of the keep-out volumes within the budget"
        return nearest, (
            f"unreachable: pos {nearest.pos_err_cm:.2f}cm ori {nearest.ori_err_deg:.1f}deg"
        )

    def solution_refusal(self, q_deg: Sequence[float]) -> str | None:
        """Why a solution is refused (a link within the margin of a volume, checked at the PWM
        sent, once more after :meth:`solve`), or None."""
        keepout = self._core.settings.keepout
        if keepout is None:
            return None
        collision = keepout.check(self._as_sent_rad(q_deg))
        return (
            None if collision is None else f"the solution puts {collision.reason} (at the PWM sent)"
        )

    def step_refusal(
        self,
        befores: Sequence[Sequence[float]],
        step: Sequence[float],
        commands: Sequence[ServoCommand],
    ) -> str | None:
        """Why the motion to ``step`` is refused (None: clear), from each pose in ``befores``.

        As the servos get it: each angle through its PWM rounded to whole µs (a 60 cm link
        moves up to ~0.05 cm with the rounding), and each command's outputs changing in the
        order sent (ArduPilot: one output a command, so not the straight line; at 180 deg/s
        and 100 Hz its corners came 0.09 cm into the margin in bench.keepout_daemon)."""
        keepout = self._core.settings.keepout
        if keepout is None:
            return None
        target = self._as_sent_rad(step)
        for before in befores:
            path = self._output_path(self._as_sent_rad(before), target, commands)
            collision = keepout.check_path(path)
            if collision is not None:
                return str(collision.reason)
        return None

    def _output_path(
        self, before_rad: Any, step_rad: Any, commands: Sequence[ServoCommand]
    ) -> list[Any]:
        """The configurations (rad) the outputs go through from ``before_rad`` to ``step_rad``
        when ``commands`` land in order: each command's outputs change together."""
        index = {output: i for i, output in enumerate(self._core.state.outputs)}
        q = np.array(before_rad, float)
        path = [q.copy()]
        for command in commands:
            for output in command.outputs:
                if output in index:
                    q[index[output]] = step_rad[index[output]]
            if not np.array_equal(q, path[-1]):
                path.append(q.copy())
        if not np.array_equal(q, step_rad):  # outputs left out as already there, by the ACKs
            path.append(np.array(step_rad, float))
        return path

    def _as_sent_rad(self, q_deg: Sequence[float]) -> Any:
        """The joints (rad) the servos get for ``q_deg``: each angle through its PWM, rounded
        to whole µs as sent (angles outside the calibration: as they are, never sent)."""
        cal = self._core.config.calibration
        try:
            pwm = cal.angles_to_pwm_us(q_deg)
        except CalibrationError:
            return np.radians(np.asarray(q_deg, float))
        return np.radians([j.pwm_us_to_angle_deg(pwm[j.output]) for j in cal.joints])
