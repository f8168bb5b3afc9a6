"""Batched Denavit–Hartenberg forward kinematics (numpy only, radians).

Everything here is pure: arrays in, arrays out, no I/O and no clocks. Joint vectors come as a
population of shape ``(S, n)`` and transforms go out as ``(S, 4, 4)``, so a whole solver
generation is evaluated in one call.

Lengths are in whatever unit the DH parameters are in (the :class:`~companion.kinematics.Arm` keeps
them in centimetres, the papers' unit).
"""

from __future__ import annotations

from enum import Enum

import numpy as np

from companion.kinematics.rotations import FloatArray


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


def _rot_x(angle_rad: float) -> FloatArray:
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    return np.array([[1.0, 0, 0, 0], [0, c, -s, 0], [0, s, c, 0], [0, 0, 0, 1.0]])


def _rot_z(angle_rad: float) -> FloatArray:
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    return np.array([[c, -s, 0, 0], [s, c, 0, 0], [0, 0, 1.0, 0], [0, 0, 0, 1.0]])


def _trans(x: float, y: float, z: float) -> FloatArray:
    out = np.eye(4)
    out[:3, 3] = (x, y, z)
    return out


def split_dh_row(
    convention: DHConvention,
    revolute: bool,
    alpha_rad: float,
    a: float,
    d: float,
    theta_rad: float,
) -> tuple[FloatArray, FloatArray]:
    """The fixed transforms ``(before, after)`` around a DH row's joint motion.

    The row's transform is ``before · M(v) · after``, where ``M`` is ``Rz(v)`` for a revolute
    joint (``v`` = θ; ``d`` is fixed, ``theta_rad`` unused) and ``Tz(v)`` for a prismatic one
    (``v`` = d; ``theta_rad`` is the fixed θ, ``d`` unused):

    * standard, revolute: ``I · Rz(θ) · Tz(d)·Tx(a)·Rx(α)``;
    * standard, prismatic: ``Rz(θ) · Tz(d) · Tx(a)·Rx(α)``;
    * modified, revolute: ``Rx(α)·Tx(a) · Rz(θ) · Tz(d)``;
    * modified, prismatic: ``Rx(α)·Tx(a)·Rz(θ) · Tz(d) · I``.
    """
    if convention is DHConvention.STANDARD:
        tail = _trans(a, 0.0, 0.0) @ _rot_x(alpha_rad)
        if revolute:
            return np.eye(4), _trans(0.0, 0.0, d) @ tail
        return _rot_z(theta_rad), tail
    if convention is DHConvention.MODIFIED:
        head = _rot_x(alpha_rad) @ _trans(a, 0.0, 0.0)
        if revolute:
            return head, _trans(0.0, 0.0, d)
        return head @ _rot_z(theta_rad), np.eye(4)
    raise ValueError(f"unknown DH convention {convention!r}")  # pragma: no cover
