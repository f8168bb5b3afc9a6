"""The hand in the world: vehicle (LOCAL_NED) ∘ mount (body FRD) ∘ hand (arm base frame).

The simulator's own small transform code (it shares none with the daemon, so a frame bug in
one shows up against the other): 4×4 homogeneous transforms in metres, rotations as roll /
pitch / yaw with ``R = Rz(yaw) · Ry(pitch) · Rx(roll)`` (ZYX intrinsic: MAVLink ATTITUDE's,
and :class:`companion.kinematics.Pose`'s).

* ``T_ned_body``: the vehicle's attitude and position (:class:`~sim_servo.hover.VehicleState`);
* ``T_body_base``: the mount (:class:`~sim_servo.config.MountConfig`, cm and degrees);
* ``T_base_hand``: the hand pose the arm's forward kinematics gives (cm and degrees).

``T_ned_hand = T_ned_body · T_body_base · T_base_hand`` (:func:`hand_in_world`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from sim_servo.config import MountConfig
from sim_servo.hover import VehicleState

FloatArray = NDArray[np.float64]


def rpy_matrix(roll_rad: float, pitch_rad: float, yaw_rad: float) -> FloatArray:
    """``Rz(yaw) · Ry(pitch) · Rx(roll)`` as a 3×3 array."""
    cr, sr = math.cos(roll_rad), math.sin(roll_rad)
    cp, sp = math.cos(pitch_rad), math.sin(pitch_rad)
    cy, sy = math.cos(yaw_rad), math.sin(yaw_rad)
    return np.array(
        [
            [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
            [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
            [-sp, cp * sr, cp * cr],
        ]
    )


def matrix_rpy(rot: FloatArray) -> tuple[float, float, float]:
    """(roll, pitch, yaw) rad of a rotation matrix, the inverse of :func:`rpy_matrix` (pitch in
    [−π/2, π/2]; at ±π/2 yaw is taken as 0)."""
    horizontal = math.hypot(rot[0, 0], rot[1, 0])
    pitch = math.atan2(-rot[2, 0], horizontal)
    if horizontal < 1e-12:
        return math.atan2(-rot[1, 2], rot[1, 1]), pitch, 0.0
    return math.atan2(rot[2, 1], rot[2, 2]), pitch, math.atan2(rot[1, 0], rot[0, 0])


def transform(rot: FloatArray, xyz_m: FloatArray | tuple[float, ...]) -> FloatArray:
    """The 4×4 homogeneous transform of rotation ``rot`` and translation ``xyz_m``."""
    out = np.eye(4)
    out[:3, :3] = rot
    out[:3, 3] = xyz_m
    return out


def vehicle_matrix(state: VehicleState) -> FloatArray:
    """``T_ned_body``: the body frame FRD in LOCAL_NED (m)."""
    return transform(
        rpy_matrix(state.roll_rad, state.pitch_rad, state.yaw_rad),
        (state.north_m, state.east_m, state.down_m),
    )


def mount_matrix(mount: MountConfig) -> FloatArray:
    """``T_body_base``: the arm's base frame in the body frame FRD (m)."""
    roll, pitch, yaw = (math.radians(a) for a in mount.rpy_deg)
    return transform(rpy_matrix(roll, pitch, yaw), tuple(c / 100.0 for c in mount.xyz_cm))


def pose_matrix(
    x_cm: float, y_cm: float, z_cm: float, roll_deg: float, pitch_deg: float, yaw_deg: float
) -> FloatArray:
    """A pose in cm and degrees (the arm's :class:`~companion.kinematics.Pose` fields) as a 4×4
    transform in m."""
    rot = rpy_matrix(math.radians(roll_deg), math.radians(pitch_deg), math.radians(yaw_deg))
    return transform(rot, (x_cm / 100.0, y_cm / 100.0, z_cm / 100.0))


@dataclass(frozen=True)
class WorldPose:
    """A pose in LOCAL_NED: position (m) and orientation (ZYX roll/pitch/yaw, rad)."""

    north_m: float
    east_m: float
    down_m: float
    roll_rad: float
    pitch_rad: float
    yaw_rad: float

    @classmethod
    def from_matrix(cls, matrix: FloatArray) -> WorldPose:
        roll, pitch, yaw = matrix_rpy(matrix[:3, :3])
        north, east, down = (float(c) for c in matrix[:3, 3])
        return cls(north, east, down, roll, pitch, yaw)

    def as_matrix(self) -> FloatArray:
        return transform(
            rpy_matrix(self.roll_rad, self.pitch_rad, self.yaw_rad),
            (self.north_m, self.east_m, self.down_m),
        )

    @property
    def position_m(self) -> FloatArray:
        return np.array([self.north_m, self.east_m, self.down_m])

    def as_dict(self) -> dict[str, float]:
        return {name: getattr(self, name) for name in self.__dataclass_fields__}

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> WorldPose:
        return cls(**{name: float(data[name]) for name in cls.__dataclass_fields__})


def hand_in_world(vehicle: VehicleState, mount: FloatArray, hand_base: FloatArray) -> WorldPose:
    """The hand in LOCAL_NED: ``T_ned_body · T_body_base · T_base_hand``, from the vehicle's
    state, the mount (:func:`mount_matrix`) and the hand in the arm's base frame
    (:func:`pose_matrix`), all in m."""
    return WorldPose.from_matrix(vehicle_matrix(vehicle) @ mount @ hand_base)


def pose_error(pose: WorldPose, reference: WorldPose) -> tuple[float, float]:
    """How far ``pose`` is from ``reference``: (distance m, rotation angle rad in [0, π]), the
    angle of ``R_referenceᵀ · R_pose`` (for a bench's hand world error)."""
    distance_m = float(np.linalg.norm(pose.position_m - reference.position_m))
    relative = reference.as_matrix()[:3, :3].T @ pose.as_matrix()[:3, :3]
    cos_angle = (np.trace(relative) - 1.0) / 2.0
    sin_angle = (
        np.linalg.norm(
            [
                relative[2, 1] - relative[1, 2],
                relative[0, 2] - relative[2, 0],
                relative[1, 0] - relative[0, 1],
            ]
        )
        / 2.0
    )
    return distance_m, float(math.atan2(sin_angle, cos_angle))
