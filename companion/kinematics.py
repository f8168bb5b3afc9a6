"""Batched Denavit–Hartenberg forward kinematics and rotation helpers (numpy only, radians).

Everything here is pure: arrays in, arrays out, no I/O and no clocks. Joint vectors come as a
population of shape ``(S, n)`` and transforms go out as ``(S, 4, 4)``, so a whole solver
generation is evaluated in one call.

Lengths are in whatever unit the DH parameters are in (the :class:`~companion.arm.Arm` keeps
them in centimetres, the papers' unit).
"""

from __future__ import annotations

from enum import Enum

import numpy as np
from numpy.typing import ArrayLike, NDArray

FloatArray = NDArray[np.float64]


class DHConvention(Enum):
    """Which Denavit–Hartenberg convention a table is written in.

    STANDARD (Denavit–Hartenberg 1955, as in Spong): link ``i`` is
        ``T_i = Rz(θ_i) · Tz(d_i) · Tx(a_i) · Rx(α_i)``.
    MODIFIED (Craig 1986): row ``i`` holds ``α_{i−1}, a_{i−1}, d_i`` and
        ``T_i = Rx(α_{i−1}) · Tx(a_{i−1}) · Rz(θ_i) · Tz(d_i)``.
    """

    STANDARD = "standard"
    MODIFIED = "modified"


def link_transforms(
    q_rad: FloatArray,
    alpha_rad: FloatArray,
    a: FloatArray,
    d: FloatArray,
    offset_rad: FloatArray,
    convention: DHConvention,
) -> FloatArray:
    """Per-link homogeneous transforms, shape ``(S, n, 4, 4)``, for joints ``q_rad`` ``(S, n)``.

    ``θ_i = q_i + offset_i``. The matrices are the closed products of the four elementary
    transforms named in :class:`DHConvention` (roboticstoolbox ``DHLink.A`` writes the same two):

    standard::

        [cθ  −sθ·cα   sθ·sα   a·cθ]
        [sθ   cθ·cα  −cθ·sα   a·sθ]
        [0    sα      cα      d   ]
        [0    0       0       1   ]

    modified::

        [cθ     −sθ     0     a    ]
        [sθ·cα   cθ·cα  −sα   −d·sα]
        [sθ·sα   cθ·sα   cα    d·cα]
        [0       0       0     1   ]
    """
    theta = q_rad + offset_rad
    ct, st = np.cos(theta), np.sin(theta)
    ca = np.broadcast_to(np.cos(alpha_rad), ct.shape)
    sa = np.broadcast_to(np.sin(alpha_rad), ct.shape)
    a_b = np.broadcast_to(a, ct.shape)
    d_b = np.broadcast_to(d, ct.shape)
    out = np.zeros(ct.shape + (4, 4))
    out[..., 3, 3] = 1.0
    if convention is DHConvention.STANDARD:
        out[..., 0, 0] = ct
        out[..., 0, 1] = -st * ca
        out[..., 0, 2] = st * sa
        out[..., 0, 3] = a_b * ct
        out[..., 1, 0] = st
        out[..., 1, 1] = ct * ca
        out[..., 1, 2] = -ct * sa
        out[..., 1, 3] = a_b * st
        out[..., 2, 1] = sa
        out[..., 2, 2] = ca
        out[..., 2, 3] = d_b
    elif convention is DHConvention.MODIFIED:
        out[..., 0, 0] = ct
        out[..., 0, 1] = -st
        out[..., 0, 3] = a_b
        out[..., 1, 0] = st * ca
        out[..., 1, 1] = ct * ca
        out[..., 1, 2] = -sa
        out[..., 1, 3] = -d_b * sa
        out[..., 2, 0] = st * sa
        out[..., 2, 1] = ct * sa
        out[..., 2, 2] = ca
        out[..., 2, 3] = d_b * ca
    else:  # pragma: no cover - the Enum has exactly two members
        raise ValueError(f"unknown DH convention {convention!r}")
    return out


def chain(links: FloatArray, tool: FloatArray | None = None) -> FloatArray:
    """Compose link transforms ``(S, n, 4, 4)`` and an optional fixed tool into ``(S, 4, 4)``."""
    t = links[:, 0]
    for i in range(1, links.shape[1]):
        t = t @ links[:, i]
    if tool is not None:
        t = t @ tool
    return t


def rpy_to_matrix(roll_rad: ArrayLike, pitch_rad: ArrayLike, yaw_rad: ArrayLike) -> FloatArray:
    """Rotation ``R = Rz(yaw) · Ry(pitch) · Rx(roll)``; broadcasts, returns ``(..., 3, 3)``."""
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
