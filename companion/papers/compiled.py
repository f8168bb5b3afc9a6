"""The papers' objective compiled with numba: the same J as :class:`IKObjective`, ~100× faster.

The solvers evaluate a handful of candidates per call (MSFLA leaps one frog per memeplex, 3 at
a time), where numpy spends ~0.2 ms per call on overhead whatever the batch size; the report's
thousands of runs (``bench/papers.py``) take hours that way. :class:`CompiledIKObjective` wraps
an :class:`IKObjective` and computes its ``cost`` in one compiled loop — same terms, same
conventions (standard or modified DH, tool, Euler or rotation metric, limit penalty, movement
term); the tests hold it equal to the numpy objective within 1e-12. Everything else
(``lower``, ``upper``, ``errors``) is the wrapped objective's.

numba caches the compiled code on disk when it can (the first use in a fresh install compiles
for about two seconds). Independent of :mod:`companion.ik`, which has its own kernels.
"""

from __future__ import annotations

import math
import os
import tempfile

import numba as nb
import numpy as np

from companion.kinematics import FloatArray
from companion.kinematics.dh import DHConvention
from companion.papers.objective import IKObjective, OrientationMetric, PoseErrors


def _caching_available() -> bool:
    """Whether numba can cache here (else ``cache=True`` raises at decoration, i.e. import)."""
    if os.environ.get("NUMBA_CACHE_DIR"):
        return True
    here = os.path.join(os.path.dirname(os.path.abspath(__file__)), "__pycache__")
    try:
        os.makedirs(here, exist_ok=True)
        with tempfile.TemporaryFile(dir=here):
            return True
    except OSError:
        return False


_CACHE = _caching_available()


@nb.njit(cache=_CACHE)
def _cost_kernel(
    q: FloatArray,
    cos_alpha: FloatArray,
    sin_alpha: FloatArray,
    a: FloatArray,
    d: FloatArray,
    offset: FloatArray,
    modified: bool,
    tool: FloatArray,
    has_tool: bool,
    goal_pos: FloatArray,
    goal_rot: FloatArray,
    goal_rpy: FloatArray,
    sigma: float,
    epsilon: float,
    euler: bool,
    lower: FloatArray,
    upper: FloatArray,
    penalty: float,
    move_w: float,
    q_prev: FloatArray,
    out: FloatArray,
) -> None:
    n_rows, n = q.shape
    rot = np.empty((3, 3))
    pos = np.empty(3)
    two_pi = 2.0 * math.pi
    for k in range(n_rows):
        # Hand transform, built column by column: T ← T · A_i.
        for r in range(3):
            for c in range(3):
                rot[r, c] = 1.0 if r == c else 0.0
            pos[r] = 0.0
        for i in range(n):
            theta = q[k, i] + offset[i]
            ct = math.cos(theta)
            st = math.sin(theta)
            ca = cos_alpha[i]
            sa = sin_alpha[i]
            for r in range(3):
                x = rot[r, 0]
                y = rot[r, 1]
                z = rot[r, 2]
                if modified:
                    # Rx(α)·Tx(a)·Rz(θ)·Tz(d)
                    y1 = ca * y + sa * z
                    z1 = -sa * y + ca * z
                    rot[r, 0] = ct * x + st * y1
                    rot[r, 1] = -st * x + ct * y1
                    rot[r, 2] = z1
                    pos[r] += a[i] * x + d[i] * z1
                else:
                    # Rz(θ)·Tz(d)·Tx(a)·Rx(α)
                    nx = ct * x + st * y
                    ny0 = -st * x + ct * y
                    rot[r, 0] = nx
                    rot[r, 1] = ca * ny0 + sa * z
                    rot[r, 2] = -sa * ny0 + ca * z
                    pos[r] += d[i] * z + a[i] * nx
        if has_tool:
            for r in range(3):
                x = rot[r, 0]
                y = rot[r, 1]
                z = rot[r, 2]
                pos[r] += x * tool[0, 3] + y * tool[1, 3] + z * tool[2, 3]
                for c in range(3):
                    rot[r, c] = x * tool[0, c] + y * tool[1, c] + z * tool[2, c]
        dp = math.sqrt(
            (pos[0] - goal_pos[0]) ** 2 + (pos[1] - goal_pos[1]) ** 2 + (pos[2] - goal_pos[2]) ** 2
        )
        if euler:
            # matrix_to_rpy, gimbal lock included, then wrapped differences.
            h = math.hypot(rot[0, 0], rot[1, 0])
            pitch = math.atan2(-rot[2, 0], h)
            if h < 1e-12:
                sign = np.sign(-rot[2, 0])
                roll = math.atan2(sign * rot[0, 1], rot[1, 1])
                yaw = 0.0
            else:
                roll = math.atan2(rot[2, 1], rot[2, 2])
                yaw = math.atan2(rot[1, 0], rot[0, 0])
            e2 = 0.0
            for j in range(3):
                v = roll if j == 0 else (pitch if j == 1 else yaw)
                diff = (goal_rpy[j] - v + math.pi) % two_pi - math.pi
                e2 += diff * diff
            ori = math.sqrt(e2)
        else:
            # Angle of goal_rotᵀ·rot, as companion.kinematics.rotation_angle.
            e = np.empty((3, 3))
            for r in range(3):
                for c in range(3):
                    e[r, c] = (
                        goal_rot[0, r] * rot[0, c]
                        + goal_rot[1, r] * rot[1, c]
                        + goal_rot[2, r] * rot[2, c]
                    )
            cos_angle = (e[0, 0] + e[1, 1] + e[2, 2] - 1.0) * 0.5
            sx = e[2, 1] - e[1, 2]
            sy = e[0, 2] - e[2, 0]
            sz = e[1, 0] - e[0, 1]
            ori = math.atan2(0.5 * math.sqrt(sx * sx + sy * sy + sz * sz), cos_angle)
        j_cost = sigma * dp + epsilon * ori
        over = 0.0
        for i in range(n):
            over += max(q[k, i] - upper[i], 0.0) + max(lower[i] - q[k, i], 0.0)
        j_cost += penalty * over
        if move_w != 0.0:
            m2 = 0.0
            for i in range(n):
                m2 += (q[k, i] - q_prev[i]) ** 2
            j_cost += move_w * math.sqrt(m2)
        out[k] = j_cost


class CompiledIKObjective:
    """``objective``'s J, computed by a compiled kernel; satisfies the solvers' problem
    interface (``lower``, ``upper``, ``cost``) and forwards ``errors``."""

    def __init__(self, objective: IKObjective) -> None:
        self.objective = objective
        arm = objective.arm
        # The compiled J is the DH chain the papers use: revolute joints, no base, no reversed
        # joint. Other arms (prismatic, base, URDF) go through the numpy IKObjective.
        if (
            arm.convention is None
            or arm.base is not None
            or not arm.all_revolute
            or any(j.direction != 1 for j in arm.joints)
        ):
            raise ValueError(
                f"arm {arm.name}: the compiled objective takes revolute DH arms without a base "
                "transform or reversed joints; use IKObjective"
            )
        alpha, a, d, offset = (
            np.array([j.alpha_rad for j in arm.joints]),
            np.array([j.a_cm for j in arm.joints]),
            np.array([j.d_cm for j in arm.joints]),
            np.array([j.offset_rad for j in arm.joints]),
        )
        tool = arm.tool_matrix
        goal = objective.target.as_matrix()
        use_prev = objective.movement_weight != 0.0 and objective.q_prev_rad is not None
        self._args = (
            np.cos(alpha),
            np.sin(alpha),
            a,
            d,
            offset,
            arm.convention is DHConvention.MODIFIED,
            np.eye(4) if tool is None else np.array(tool, float),
            tool is not None,
            goal[:3, 3].copy(),
            goal[:3, :3].copy(),
            np.asarray(objective.target.rpy_rad, float),
            float(objective.sigma),
            float(objective.epsilon),
            objective.metric is OrientationMetric.EULER,
            arm.lower_rad.copy(),
            arm.upper_rad.copy(),
            float(objective.limit_penalty_per_rad),
            float(objective.movement_weight) if use_prev else 0.0,
            np.asarray(objective.q_prev_rad, float) if use_prev else np.zeros(arm.dof),
        )

    @property
    def lower(self) -> FloatArray:
        return self.objective.lower

    @property
    def upper(self) -> FloatArray:
        return self.objective.upper

    def cost(self, q_rad: FloatArray) -> FloatArray:
        """J for each row of ``q_rad`` ``(S, dof)``; returns ``(S,)``."""
        q = np.ascontiguousarray(q_rad, dtype=float)
        if q.ndim != 2 or q.shape[1] != self.objective.arm.dof:
            raise ValueError(f"q_rad must have shape (S, {self.objective.arm.dof}), got {q.shape}")
        out = np.empty(q.shape[0])
        _cost_kernel(q, *self._args, out)
        return out

    def errors(self, q_rad: FloatArray) -> PoseErrors:
        """The wrapped objective's position (cm) and rotation-angle (deg) errors."""
        return self.objective.errors(q_rad)
