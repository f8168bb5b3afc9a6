"""Rotation helpers: roll–pitch–yaw ↔ matrix, angle wrapping, the angle between rotations.

Pure numpy, radians, broadcasting over leading axes; no I/O and no clocks.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

FloatArray = NDArray[np.float64]


def rpy_to_matrix(roll_rad: ArrayLike, pitch_rad: ArrayLike, yaw_rad: ArrayLike) -> FloatArray:
    """Rotation ``R = Rz(yaw) · Ry(pitch) · Rx(roll)``; broadcasts, returns ``(..., 3, 3)``."""
    angles: tuple[object, ...] = (roll_rad, pitch_rad, yaw_rad)
    if all(isinstance(a, float) for a in angles):
        # One rotation (the daemon's world path, every tick): the same products in scalars,
        # a tenth of the broadcasting path's cost.
        r_s, p_s, y_s = (float(a) for a in angles)  # type: ignore[arg-type]
        cr, sr = math.cos(r_s), math.sin(r_s)
        cp, sp = math.cos(p_s), math.sin(p_s)
        cy, sy = math.cos(y_s), math.sin(y_s)
        return np.array(
            [
                [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
                [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
                [-sp, cp * sr, cp * cr],
            ]
        )
    r, p, y = np.broadcast_arrays(
        np.asarray(roll_rad, float), np.asarray(pitch_rad, float), np.asarray(yaw_rad, float)
    )
    cr, sr = np.cos(r), np.sin(r)
    cp, sp = np.cos(p), np.sin(p)
    cy, sy = np.cos(y), np.sin(y)
    out = np.empty(r.shape + (3, 3))
    out[..., 0, 0] = cy * cp
    out[..., 0, 1] = cy * sp * sr - sy * cr
    out[..., 0, 2] = cy * sp * cr + sy * sr
    out[..., 1, 0] = sy * cp
    out[..., 1, 1] = sy * sp * sr + cy * cr
    out[..., 1, 2] = sy * sp * cr - cy * sr
    out[..., 2, 0] = -sp
    out[..., 2, 1] = cp * sr
    out[..., 2, 2] = cp * cr
    return out


def matrix_to_rpy(rot: FloatArray) -> FloatArray:
    """Inverse of :func:`rpy_to_matrix`: ``(..., 3, 3)`` → ``(..., 3)`` as (roll, pitch, yaw) rad.

    Pitch is in [−π/2, π/2]; roll and yaw in (−π, π]. At pitch = ±π/2 (gimbal lock) roll and
    yaw are not unique; the pair returned still reproduces the matrix.
    """
    rot = np.asarray(rot, float)
    if rot.shape == (3, 3):
        # One rotation: the same formulas in scalars.
        (r00, r01, _), (r10, r11, _), (r20, r21, r22) = rot.tolist()
        horizontal = math.hypot(r00, r10)
        pitch_s = math.atan2(-r20, horizontal)
        if horizontal < 1e-12:
            sign_s = float(np.sign(-r20))
            return np.array([math.atan2(sign_s * r01, r11), pitch_s, 0.0])
        return np.array([math.atan2(r21, r22), pitch_s, math.atan2(r10, r00)])
    pitch = np.arctan2(-rot[..., 2, 0], np.hypot(rot[..., 0, 0], rot[..., 1, 0]))
    roll = np.arctan2(rot[..., 2, 1], rot[..., 2, 2])
    yaw = np.arctan2(rot[..., 1, 0], rot[..., 0, 0])
    locked = np.hypot(rot[..., 0, 0], rot[..., 1, 0]) < 1e-12
    if np.any(locked):
        # Gimbal lock: only roll ∓ yaw is defined; take yaw = 0.
        sign = np.sign(-rot[..., 2, 0])
        roll = np.where(locked, np.arctan2(sign * rot[..., 0, 1], rot[..., 1, 1]), roll)
        yaw = np.where(locked, 0.0, yaw)
    return np.stack([roll, pitch, yaw], axis=-1)


def wrap_angle(angle_rad: ArrayLike) -> FloatArray:
    """Wrap angles to [−π, π): a difference of 359° is −1°."""
    return (np.asarray(angle_rad, float) + np.pi) % (2.0 * np.pi) - np.pi


def rotation_angle(rot_a: FloatArray, rot_b: FloatArray) -> FloatArray:
    """Angle (rad, in [0, π]) of the relative rotation ``rot_aᵀ · rot_b``; broadcasts over ``...``.

    Computed as ``atan2(|vee(E − Eᵀ)|/2, (tr E − 1)/2)``, which keeps full precision for small
    angles, where ``arccos`` of the trace loses half the digits.
    """
    e = np.swapaxes(rot_a, -1, -2) @ rot_b
    cos_angle = (e[..., 0, 0] + e[..., 1, 1] + e[..., 2, 2] - 1.0) * 0.5
    sx = e[..., 2, 1] - e[..., 1, 2]
    sy = e[..., 0, 2] - e[..., 2, 0]
    sz = e[..., 1, 0] - e[..., 0, 1]
    sin_angle = 0.5 * np.sqrt(sx * sx + sy * sy + sz * sz)
    return np.arctan2(sin_angle, cos_angle)
