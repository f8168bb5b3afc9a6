"""The inverse-kinematics objective of the papers, vectorised over a population.

``J(Θ) = σ·‖P_G − P_E(Θ)‖ + ε·‖O_G − O_E(Θ)‖``  (papers' Eq. 1)

with P in cm and O the roll–pitch–yaw angles in radians, ε = 1 − σ = 0.7 in the papers'
experiments. Two terms are added, both zero by default or inside the limits:

* a joint-limit penalty, ``limit_penalty_per_rad · Σ overshoot_rad`` (the solvers clamp into the
  limits after every update, so for them it is zero; it keeps the objective honest for any caller
  that evaluates a configuration outside the box);
* the papers' "minimal movement between the previous and the actual joint configurations":
  ``movement_weight · ‖Θ − Θ_prev‖`` (rad), which keeps a sequence of solutions on one branch.

The orientation term can be measured two ways (:class:`OrientationMetric`): the papers' Euler
difference (each roll/pitch/yaw difference wrapped to [−π, π)) or the rotation angle of
``R_goalᵀ·R``, which is the honest figure and behaves better near pitch = ±90°.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import Enum

import numpy as np

from companion.kinematics import FloatArray, matrix_to_rpy, rotation_angle, wrap_angle
from companion.kinematics.arm import Arm, Pose


class OrientationMetric(Enum):
    """How the orientation error ``‖O_G − O_E‖`` is measured (radians either way)."""

    EULER = "euler"
    """Papers' Eq. 1: Euclidean norm of the wrapped roll/pitch/yaw differences."""
    ROTATION = "rotation"
    """Angle of the relative rotation ``R_goalᵀ·R`` (geodesic distance on SO(3))."""


@dataclass(frozen=True)
class PoseErrors:
    """Position error in cm and orientation error (rotation angle) in degrees, per candidate."""

    pos_err_cm: FloatArray
    ori_err_deg: FloatArray


@dataclass(frozen=True)
class IKObjective:
    """Cost of joint vectors (radians) for reaching ``target`` with ``arm``.

    Satisfies the solvers' problem interface: ``lower``, ``upper`` and ``cost(X) -> (S,)``.
    """

    arm: Arm
    target: Pose
    sigma: float = 0.3  # papers: ε = 1 − σ = 0.7
    epsilon: float = 0.7
    metric: OrientationMetric = OrientationMetric.EULER
    limit_penalty_per_rad: float = 100.0
    movement_weight: float = 0.0
    q_prev_rad: FloatArray | None = field(default=None, compare=False)
    # Derived from ``target`` in __post_init__.
    _goal_pos: FloatArray = field(init=False, repr=False, compare=False)
    _goal_rot: FloatArray = field(init=False, repr=False, compare=False)
    _goal_rpy: FloatArray = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        for name in ("sigma", "epsilon", "limit_penalty_per_rad", "movement_weight"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value >= 0.0):
                raise ValueError(f"{name}={value!r} must be a finite number >= 0")
        if not isinstance(self.metric, OrientationMetric):
            raise ValueError(
                f"metric={self.metric!r} is not one of {[m.value for m in OrientationMetric]}"
            )
        if self.q_prev_rad is not None:
            q_prev = np.asarray(self.q_prev_rad, float)
            if q_prev.shape != (self.arm.dof,) or not np.all(np.isfinite(q_prev)):
                raise ValueError(
                    f"q_prev_rad must be {self.arm.dof} finite values, got {self.q_prev_rad!r}"
                )
            object.__setattr__(self, "q_prev_rad", q_prev)
        goal = self.target.as_matrix()
        object.__setattr__(self, "_goal_pos", goal[:3, 3])
        object.__setattr__(self, "_goal_rot", goal[:3, :3])
        object.__setattr__(self, "_goal_rpy", self.target.rpy_rad)

    @property
    def lower(self) -> FloatArray:
        return self.arm.lower_rad

    @property
    def upper(self) -> FloatArray:
        return self.arm.upper_rad

    def _terms(self, q_rad: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Position error (cm) and orientation error per ``metric`` (rad) of each row."""
        t = self.arm.fk_batch(q_rad)
        pos_err = np.linalg.norm(t[:, :3, 3] - self._goal_pos, axis=1)
        if self.metric is OrientationMetric.EULER:
            d_rpy = wrap_angle(self._goal_rpy - matrix_to_rpy(t[:, :3, :3]))
            ori_err = np.linalg.norm(d_rpy, axis=1)
        else:
            ori_err = rotation_angle(self._goal_rot, t[:, :3, :3])
        return pos_err, ori_err

    def cost(self, q_rad: FloatArray) -> FloatArray:
        """J for each row of ``q_rad`` ``(S, dof)``; returns ``(S,)``."""
        q = np.asarray(q_rad, float)
        pos_err, ori_err = self._terms(q)
        j = self.sigma * pos_err + self.epsilon * ori_err
        overshoot = np.maximum(q - self.arm.upper_rad, 0.0) + np.maximum(
            self.arm.lower_rad - q, 0.0
        )
        j = j + self.limit_penalty_per_rad * overshoot.sum(axis=1)
        if self.movement_weight and self.q_prev_rad is not None:
            j = j + self.movement_weight * np.linalg.norm(q - self.q_prev_rad, axis=1)
        return j

    def errors(self, q_rad: FloatArray) -> PoseErrors:
        """Position error (cm) and orientation error (deg) of ``(S, dof)`` or ``(dof,)`` joints.

        The orientation error reported is always the rotation angle of ``R_goalᵀ·R``, whatever
        metric the cost uses: it is the figure that means the same thing at every pose.
        """
        q = np.atleast_2d(np.asarray(q_rad, float))
        t = self.arm.fk_batch(q)
        pos_err = np.linalg.norm(t[:, :3, 3] - self._goal_pos, axis=1)
        ori_err = np.degrees(rotation_angle(self._goal_rot, t[:, :3, :3]))
        return PoseErrors(pos_err_cm=pos_err, ori_err_deg=ori_err)


def pose_objective(
    target: Pose, reached: Pose, *, sigma: float = 0.3, epsilon: float = 0.7
) -> float:
    """The papers' J (Eq. 1) of a reached pose rather than of joints: ``σ·‖ΔP‖ (cm) +
    ε·‖ΔO‖`` with ΔO the roll/pitch/yaw differences in radians, each wrapped to [−π, π).

    Used to check the papers' printed J against their own printed reached poses.
    """
    d_pos = np.linalg.norm(reached.position_cm - target.position_cm)
    d_rpy = wrap_angle(reached.rpy_rad - target.rpy_rad)
    return float(sigma * d_pos + epsilon * np.linalg.norm(d_rpy))
