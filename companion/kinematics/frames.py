"""Where the arm sits on the vehicle: the mount, and the body FRD / LOCAL_NED frames.

Pure numpy, no I/O, no clocks. Frames (shared with the simulator's own copy of this maths):

* the arm's **base frame**: the frame the arm file's kinematics are written in (cm);
* the vehicle's **body frame FRD**: x forward, y right, z down, origin at the vehicle's centre
  of gravity (the autopilot's body origin). Keep-out volumes are written in it;
* MAVLink's **LOCAL_NED**: north, east, down from the autopilot's local origin (ATTITUDE gives
  the body's orientation in it, LOCAL_POSITION_NED its position, in metres).

The mount is the rigid transform base → body: ``p_body = R(rpy) · p_base + xyz``, with
``R = Rz(yaw) · Ry(pitch) · Rx(roll)`` (ZYX intrinsic yaw-pitch-roll, as
:func:`~companion.kinematics.rotations.rpy_to_matrix` and :class:`~companion.kinematics.arm.Pose`).
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from companion.kinematics.rotations import FloatArray, rpy_to_matrix

M_TO_CM = 100.0


def _finite_triple(owner: str, name: str, values: Sequence[object]) -> tuple[float, float, float]:
    items = list(values)
    if len(items) != 3:
        raise ValueError(f"{owner}.{name}={values!r} must be 3 numbers")
    out = []
    for i, v in enumerate(items):
        if isinstance(v, bool) or not isinstance(v, numbers.Real) or not math.isfinite(float(v)):
            raise ValueError(f"{owner}.{name}[{i}]={v!r} must be a finite number")
        out.append(float(v))
    return (out[0], out[1], out[2])


def pose_matrix(xyz_cm: ArrayLike, rpy_rad: ArrayLike) -> FloatArray:
    """4×4 transform: rotation ``Rz(yaw)·Ry(pitch)·Rx(roll)``, then translation ``xyz_cm``."""
    out = np.eye(4)
    roll, pitch, yaw = np.asarray(rpy_rad, float)
    out[:3, :3] = rpy_to_matrix(roll, pitch, yaw)
    out[:3, 3] = xyz_cm
    return out


def invert(transform: FloatArray) -> FloatArray:
    """Inverse of a rigid 4×4 transform (rotation transposed, no general matrix inverse)."""
    t = np.asarray(transform, float)
    out = np.eye(4)
    out[:3, :3] = t[:3, :3].T
    out[:3, 3] = -t[:3, :3].T @ t[:3, 3]
    return out


@dataclass(frozen=True)
class Mount:
    """The arm's base in the vehicle's body frame FRD: ``xyz_cm`` is the base origin (cm),
    ``rpy_deg`` the base axes' orientation (degrees, ZYX yaw-pitch-roll).

    The default is an arm hanging under a quadrotor: base axes = body axes (its +z points
    down), 10 cm below the body origin.
    """

    xyz_cm: tuple[float, float, float] = (0.0, 0.0, 10.0)
    rpy_deg: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def __post_init__(self) -> None:
        object.__setattr__(self, "xyz_cm", _finite_triple("Mount", "xyz_cm", self.xyz_cm))
        object.__setattr__(self, "rpy_deg", _finite_triple("Mount", "rpy_deg", self.rpy_deg))

    @property
    def matrix(self) -> FloatArray:
        """Base → body FRD, 4×4 (cm): ``p_body = M · p_base``."""
        return pose_matrix(self.xyz_cm, np.radians(self.rpy_deg))

    def to_body(self, points_cm: FloatArray) -> FloatArray:
        """Points ``(..., 3)`` in the arm's base frame → body FRD (cm)."""
        m = self.matrix
        return np.asarray(points_cm, float) @ m[:3, :3].T + m[:3, 3]


def body_to_local_ned(
    roll_rad: float,
    pitch_rad: float,
    yaw_rad: float,
    north_m: float = 0.0,
    east_m: float = 0.0,
    down_m: float = 0.0,
) -> FloatArray:
    """Body FRD → LOCAL_NED, 4×4 with translation in **cm**, from MAVLink ATTITUDE (roll,
    pitch, yaw; rad) and LOCAL_POSITION_NED (x = north, y = east, z = down; m). ATTITUDE's
    angles are the ZYX Euler angles of the body in NED, so the rotation is
    ``Rz(yaw)·Ry(pitch)·Rx(roll)``."""
    return pose_matrix(
        (north_m * M_TO_CM, east_m * M_TO_CM, down_m * M_TO_CM), (roll_rad, pitch_rad, yaw_rad)
    )
