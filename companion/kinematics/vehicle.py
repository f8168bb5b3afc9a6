"""The vehicle in the world, and a hand target carried between the world and the arm's base.

Frames (MAVLink's):

* **world**: LOCAL_NED, north-east-down from the autopilot's origin (LOCAL_POSITION_NED);
* **body**: FRD (forward-right-down), its attitude in the world from ATTITUDE:
  ``R_world_body = Rz(yaw) · Ry(pitch) · Rx(roll)``, the same roll–pitch–yaw convention as
  :class:`~companion.kinematics.arm.Pose`; ATTITUDE's ``rollspeed``/``pitchspeed``/``yawspeed``
  are the body rates (p, q, r) about the body axes;
* **base**: the arm's base frame, mounted on the body at ``T_body_base`` (the config's mount).

Lengths in cm (MAVLink's metres are converted at the edge), angles in rad inside. Pure numpy:
no clocks (times are given), no I/O.

Prediction (:meth:`VehicleState.predict`) carries a sample forward at constant velocity and
constant body rates: over the few tens of ms between a telemetry sample and the servos moving,
a hovering vehicle's acceleration changes the position by ``a·t²/2`` (1 m/s² over 40 ms:
0.08 cm), well under what the servos resolve.
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from companion.kinematics.arm import Pose
from companion.kinematics.rotations import FloatArray, rpy_to_matrix

#: A sample is never carried forward further than this (a stale sample is refused instead).
MAX_PREDICT_S = 0.5


def skew(v: ArrayLike) -> FloatArray:
    """The cross-product matrix ``[v]×``."""
    x, y, z = (float(c) for c in np.asarray(v, float))
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def rotation_about(omega_rad_s: ArrayLike, dt_s: float) -> FloatArray:
    """``exp([ω]× dt)``: the rotation turned at constant rate ``ω`` for ``dt`` (Rodrigues)."""
    wx, wy, wz = (float(c) * dt_s for c in np.asarray(omega_rad_s, float))
    angle = math.sqrt(wx * wx + wy * wy + wz * wz)
    if angle < 1e-12:
        return np.array([[1.0, -wz, wy], [wz, 1.0, -wx], [-wy, wx, 1.0]])
    # I + sin·K + (1 − cos)·K², K = [w/|w|]×, written out (K² = k kᵀ − I).
    x, y, z = wx / angle, wy / angle, wz / angle
    s, c = math.sin(angle), 1.0 - math.cos(angle)
    return np.array(
        [
            [1.0 + c * (x * x - 1.0), c * x * y - s * z, c * x * z + s * y],
            [c * x * y + s * z, 1.0 + c * (y * y - 1.0), c * y * z - s * x],
            [c * x * z - s * y, c * y * z + s * x, 1.0 + c * (z * z - 1.0)],
        ]
    )


def transform(rotation: FloatArray, translation: ArrayLike) -> FloatArray:
    out = np.eye(4)
    out[:3, :3] = rotation
    out[:3, 3] = np.asarray(translation, float)
    return out


def invert(t: FloatArray) -> FloatArray:
    """The inverse of a rigid 4×4 transform."""
    out = np.eye(4)
    rt = t[:3, :3].T
    out[:3, :3] = rt
    out[:3, 3] = -rt @ t[:3, 3]
    return out


@dataclass(frozen=True)
class VehicleState:
    """The vehicle's last known position and attitude, each with the time it held (any one
    clock, e.g. the daemon's): position and velocity in NED (cm, cm/s), attitude as roll,
    pitch, yaw (rad) and the body rates p, q, r (rad/s)."""

    position_t_s: float
    position_cm: tuple[float, float, float]
    velocity_cm_s: tuple[float, float, float]
    attitude_t_s: float
    rpy_rad: tuple[float, float, float]
    body_rates_rad_s: tuple[float, float, float]

    def __post_init__(self) -> None:
        for name in ("position_cm", "velocity_cm_s", "rpy_rad", "body_rates_rad_s"):
            value = getattr(self, name)
            if len(value) != 3 or not all(math.isfinite(float(v)) for v in value):
                raise ValueError(f"VehicleState.{name}={value!r} must be 3 finite numbers")
        for name in ("position_t_s", "attitude_t_s"):
            if not math.isfinite(getattr(self, name)):
                raise ValueError(f"VehicleState.{name} must be finite")

    def age_s(self, now_s: float) -> float:
        """How old the older of the two samples is at ``now_s``."""
        return now_s - min(self.position_t_s, self.attitude_t_s)

    def predict(self, t_s: float) -> FloatArray:
        """``T_world_body`` at ``t_s`` (4×4, cm): each sample carried forward at constant
        velocity and body rates, by at most :data:`MAX_PREDICT_S` (never backwards)."""
        dt_pos = min(max(t_s - self.position_t_s, 0.0), MAX_PREDICT_S)
        dt_att = min(max(t_s - self.attitude_t_s, 0.0), MAX_PREDICT_S)
        position = np.asarray(self.position_cm) + np.asarray(self.velocity_cm_s) * dt_pos
        # Body rates turn the body about its own axes: R(t) = R0 · exp([ω]× dt).
        rotation = rpy_to_matrix(*self.rpy_rad) @ rotation_about(self.body_rates_rad_s, dt_att)
        return transform(rotation, position)


def mount_transform(xyz_cm: ArrayLike, rpy_deg: ArrayLike) -> FloatArray:
    """``T_body_base`` from a mount given as the base origin in body FRD (cm) and its
    orientation (roll, pitch, yaw in degrees, the :class:`Pose` convention)."""
    return transform(rpy_to_matrix(*np.radians(np.asarray(rpy_deg, float))), xyz_cm)


def world_to_base(target_world: Pose, t_world_body: FloatArray, t_body_base: FloatArray) -> Pose:
    """A hand pose given in the world (NED, cm) as the arm's base frame sees it with the
    vehicle at ``t_world_body``."""
    return matrix_to_base(target_world.as_matrix(), t_world_body, t_body_base)


def matrix_to_base(
    t_world_target: FloatArray, t_world_body: FloatArray, t_body_base: FloatArray
) -> Pose:
    """:func:`world_to_base` of a target given as its 4×4 matrix (one held for many ticks is
    built once)."""
    t_world_base = t_world_body @ t_body_base
    return Pose.from_matrix(invert(t_world_base) @ t_world_target)


def base_to_world(hand_base: Pose, t_world_body: FloatArray, t_body_base: FloatArray) -> Pose:
    """A hand pose in the arm's base frame, in the world (NED, cm)."""
    return Pose.from_matrix(t_world_body @ t_body_base @ hand_base.as_matrix())


def finite_triple(owner: str, name: str, values: Sequence[object]) -> tuple[float, float, float]:
    """Three finite numbers as floats, or ``ValueError`` naming ``owner.name`` (and the index)."""
    items = list(values)
    if len(items) != 3:
        raise ValueError(f"{owner}.{name}={values!r} must be 3 numbers")
    out = []
    for i, v in enumerate(items):
        if isinstance(v, bool) or not isinstance(v, numbers.Real) or not math.isfinite(float(v)):
            raise ValueError(f"{owner}.{name}[{i}]={v!r} must be a finite number")
        out.append(float(v))
    return (out[0], out[1], out[2])


@dataclass(frozen=True)
class Mount:
    """The config's mount (``[mount]``): the arm's base origin in body FRD, ``xyz_cm``, and the
    base axes' orientation, ``rpy_deg`` (the :class:`Pose` convention).

    The default is an arm hanging under a quadrotor: base axes = body axes (its +z points
    down), 10 cm below the body origin.
    """

    xyz_cm: tuple[float, float, float] = (0.0, 0.0, 10.0)
    rpy_deg: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def __post_init__(self) -> None:
        object.__setattr__(self, "xyz_cm", finite_triple("Mount", "xyz_cm", self.xyz_cm))
        object.__setattr__(self, "rpy_deg", finite_triple("Mount", "rpy_deg", self.rpy_deg))

    @property
    def matrix(self) -> FloatArray:
        """``T_body_base`` (4×4, cm): :func:`mount_transform` of the two fields."""
        return mount_transform(self.xyz_cm, self.rpy_deg)

    def to_body(self, points_cm: ArrayLike) -> FloatArray:
        """Points ``(..., 3)`` in the arm's base frame → body FRD (cm)."""
        m = self.matrix
        return np.asarray(points_cm, float) @ m[:3, :3].T + m[:3, 3]
