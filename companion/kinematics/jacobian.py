"""Geometric Jacobian of a revolute DH chain and its time derivative, vectorised over a batch.

For joint vectors ``q_rad`` ``(S, n)`` the geometric Jacobian ``J`` ``(S, 6, n)`` maps joint rates
to the hand's twist ``(v, ω)`` expressed in the base frame:

* rows 0–2, linear velocity of the hand point (the origin of the last frame, tool included):
  ``J_v,i = a_i × (p_e − p_i)``, in the arm's length unit per radian — **centimetres** for an
  :class:`~companion.kinematics.arm.Arm`, which keeps every length in cm;
* rows 3–5, angular velocity: ``J_ω,i = a_i`` (rad/rad, dimensionless);

where ``a_i`` is the unit axis of joint ``i`` and ``p_i`` a point on it, both in the base frame:

* standard DH: joint ``i`` turns about ``z_{i−1}`` through ``o_{i−1}`` (frame ``i−1``; the base
  is frame 0);
* modified DH: joint ``i`` turns about ``z_i`` through ``o_i`` (frame ``i``; ``Rz(θ_i)`` does not
  move that axis).

The time derivative follows from the fact that each axis is fixed in the link before its joint,
which turns with ``ω_{i−1} = Σ_{k<i} a_k q̇_k``:

* ``ȧ_i = ω_{i−1} × a_i``,
* ``ṗ_i = Σ_{k<i} q̇_k a_k × (p_i − p_k)`` and ``ṗ_e = J_v q̇``,
* ``J̇_v,i = ȧ_i × (p_e − p_i) + a_i × (ṗ_e − ṗ_i)``, ``J̇_ω,i = ȧ_i``.

So the hand's linear acceleration is ``ẍ = J_v q̈ + J̇_v q̇`` (Siciliano et al., *Robotics*,
§3.1 and eq. 3.107). The geometric Jacobian takes prismatic joints too (column ``(a_i, 0)``);
the derivative is for all-revolute arms.
"""

from __future__ import annotations

import numpy as np

from companion.kinematics.arm import Arm
from companion.kinematics.rotations import FloatArray


def joint_axes(arm: Arm, q_rad: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Joint axes ``(S, n, 3)``, points on them ``(S, n, 3)`` (cm) and hand position ``(S, 3)``
    (cm), all in the base frame, for joint vectors ``q_rad`` ``(S, n)``.

    The axis is the z axis of the frame the joint moves in (:meth:`Arm.joint_frames`), signed by
    the joint's ``direction``, so that it is the axis of a positive ``q``."""
    q = _check_q(arm, q_rad)
    frames, hand = arm.joint_frames(q)
    axes = frames[..., :3, 2] * arm.directions[None, :, None]
    return axes, frames[..., :3, 3], hand[:, :3, 3]


def geometric_jacobian(arm: Arm, q_rad: FloatArray) -> FloatArray:
    """Geometric Jacobian ``(S, 6, n)`` of ``arm`` at ``q_rad`` ``(S, n)``.

    Rows 0–2: hand-point linear velocity in cm/rad (cm/cm for a prismatic joint, whose column
    is ``(a_i, 0)``); rows 3–5: angular velocity in rad/rad; both in the base frame (see the
    module docstring for the formulas).
    """
    axes, points, p_e = joint_axes(arm, q_rad)
    j_v = np.cross(axes, p_e[:, None, :] - points)
    j_w = axes.copy()
    prismatic = ~arm.revolute
    j_v[:, prismatic] = axes[:, prismatic]
    j_w[:, prismatic] = 0.0
    return np.concatenate([j_v, j_w], axis=2).transpose(0, 2, 1)


def jacobian_and_derivative(
    arm: Arm, q_rad: FloatArray, qd_rad_s: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """``(J, J̇)``, each ``(S, 6, n)``, at joints ``q_rad`` and joint rates ``qd_rad_s`` ``(S, n)``.

    ``J̇`` is analytic (module docstring); its linear rows are in cm/(rad·s), angular in 1/s.
    Revolute joints only: an arm with a prismatic joint raises ``KinematicsError``.
    """
    arm.lower_rad  # noqa: B018 - raises for an arm with a prismatic joint
    axes, points, p_e = joint_axes(arm, q_rad)
    qd = np.asarray(qd_rad_s, float)
    if qd.shape != axes.shape[:2]:
        raise ValueError(f"qd_rad_s must have shape {axes.shape[:2]}, got {qd.shape}")
    w_axes = axes * qd[..., None]  # a_k q̇_k, (S, n, 3)
    # ω of the link carrying axis i: Σ_{k<i} a_k q̇_k (exclusive cumulative sum)
    omega_before = np.cumsum(w_axes, axis=1) - w_axes
    axes_dot = np.cross(omega_before, axes)
    # ṗ_i = Σ_{k<i} q̇_k a_k × (p_i − p_k): an (S, i, k, 3) table masked to k < i
    rel = points[:, :, None, :] - points[:, None, :, :]
    n = axes.shape[1]
    lower = np.tril(np.ones((n, n), dtype=bool), k=-1)[None, :, :, None]
    terms = np.cross(np.broadcast_to(w_axes[:, None, :, :], rel.shape), rel)
    points_dot = np.where(lower, terms, 0.0).sum(axis=2)
    r_e = p_e[:, None, :] - points
    j_v = np.cross(axes, r_e)
    p_e_dot = np.einsum("sij,si->sj", j_v, qd)
    j_v_dot = np.cross(axes_dot, r_e) + np.cross(axes, p_e_dot[:, None, :] - points_dot)
    jac = np.concatenate([j_v, axes], axis=2).transpose(0, 2, 1)
    jac_dot = np.concatenate([j_v_dot, axes_dot], axis=2).transpose(0, 2, 1)
    return jac, jac_dot


def hand_acceleration(
    arm: Arm, q_rad: FloatArray, qd_rad_s: FloatArray, qdd_rad_s2: FloatArray
) -> FloatArray:
    """Hand twist derivative ``(S, 6)``: ``J q̈ + J̇ q̇`` — linear in cm/s², angular in rad/s²."""
    jac, jac_dot = jacobian_and_derivative(arm, q_rad, qd_rad_s)
    qdd = np.asarray(qdd_rad_s2, float)
    expected = (jac.shape[0], jac.shape[2])
    if qdd.shape != expected:
        raise ValueError(f"qdd_rad_s2 must have shape {expected}, got {qdd.shape}")
    return np.einsum("sij,sj->si", jac, qdd) + np.einsum(
        "sij,sj->si", jac_dot, np.asarray(qd_rad_s, float)
    )


def _check_q(arm: Arm, q_rad: FloatArray) -> FloatArray:
    q = np.asarray(q_rad, float)
    if q.ndim != 2 or q.shape[1] != arm.dof:
        raise ValueError(f"q_rad must have shape (S, {arm.dof}), got {q.shape}")
    return q
