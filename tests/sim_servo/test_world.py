"""The hand in the world: vehicle (LOCAL_NED) ∘ mount (body FRD) ∘ hand (arm base frame)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from companion.kinematics.rotations import rpy_to_matrix
from sim_servo.config import MountConfig
from sim_servo.hover import VehicleState
from sim_servo.world import (
    WorldPose,
    hand_in_world,
    matrix_rpy,
    mount_matrix,
    pose_error,
    pose_matrix,
    rpy_matrix,
)


def still(north=0.0, east=0.0, down=0.0, roll_deg=0.0, pitch_deg=0.0, yaw_deg=0.0):
    angles = (math.radians(roll_deg), math.radians(pitch_deg), math.radians(yaw_deg))
    return VehicleState(0.0, north, east, down, 0.0, 0.0, 0.0, *angles, 0.0, 0.0, 0.0)


def test_a_90_degree_yaw_turns_the_hand_from_north_to_east():
    mount = mount_matrix(MountConfig())  # 10 cm below the body origin, axes the body's
    hand = pose_matrix(20.0, 0.0, 0.0, 0.0, 0.0, 0.0)  # 20 cm along the arm base's +x
    level = hand_in_world(still(1.0, 2.0, -3.0), mount, hand)
    np.testing.assert_allclose(level.position_m, [1.2, 2.0, -2.9], atol=1e-12)
    turned = hand_in_world(still(1.0, 2.0, -3.0, yaw_deg=90.0), mount, hand)
    np.testing.assert_allclose(turned.position_m, [1.0, 2.2, -2.9], atol=1e-12)
    assert turned.yaw_rad == pytest.approx(math.pi / 2)


def test_a_roll_to_the_right_swings_the_hanging_base_to_the_west():
    # Right wing down (roll +90°): the body's +y points down, its +z (down) points west.
    world = hand_in_world(
        still(roll_deg=90.0), mount_matrix(MountConfig()), pose_matrix(0, 0, 0, 0, 0, 0)
    )
    np.testing.assert_allclose(world.position_m, [0.0, -0.10, 0.0], atol=1e-12)


def test_composition_matches_an_independent_rotation_implementation():
    rng = np.random.default_rng(4)
    for _ in range(20):
        rpy_v = rng.uniform(-0.5, 0.5, 3)
        xyz_v = rng.uniform(-2.0, 2.0, 3)
        mount = MountConfig(tuple(rng.uniform(-20, 20, 3)), tuple(rng.uniform(-180, 180, 3)))
        pose = (*rng.uniform(-50, 50, 3), *rng.uniform(-180, 180, 3))
        vehicle = VehicleState(0.0, *xyz_v, 0.0, 0.0, 0.0, *rpy_v, 0.0, 0.0, 0.0)
        world = hand_in_world(vehicle, mount_matrix(mount), pose_matrix(*pose))
        rot_v = rpy_to_matrix(*rpy_v)
        rot_m = rpy_to_matrix(*np.radians(mount.rpy_deg))
        rot_h = rpy_to_matrix(*np.radians(pose[3:]))
        expected = xyz_v + rot_v @ (np.array(mount.xyz_cm) / 100 + rot_m @ np.array(pose[:3]) / 100)
        np.testing.assert_allclose(world.position_m, expected, atol=1e-12)
        np.testing.assert_allclose(
            rpy_to_matrix(world.roll_rad, world.pitch_rad, world.yaw_rad),
            rot_v @ rot_m @ rot_h,
            atol=1e-12,
        )


@pytest.mark.parametrize(
    "rpy", [(0.1, -0.2, 3.0), (-3.1, 1.2, -0.4), (0.3, math.pi / 2, 0.0), (0.3, -math.pi / 2, 0.0)]
)
def test_rpy_matrix_round_trips_and_agrees_with_the_kinematics(rpy):
    rot = rpy_matrix(*rpy)
    np.testing.assert_allclose(rot, rpy_to_matrix(*rpy), atol=1e-15)
    np.testing.assert_allclose(rpy_matrix(*matrix_rpy(rot)), rot, atol=1e-12)


def test_world_pose_round_trips():
    pose = WorldPose(1.0, -2.0, 3.0, 0.1, -0.2, 0.3)
    assert WorldPose.from_dict(pose.as_dict()) == pose
    back = WorldPose.from_matrix(pose.as_matrix())
    np.testing.assert_allclose(list(back.as_dict().values()), list(pose.as_dict().values()))


def test_pose_error_is_distance_and_rotation_angle():
    reference = WorldPose(1.0, 2.0, -3.0, 0.1, 0.2, 0.3)
    assert pose_error(reference, reference) == (0.0, 0.0)
    turned = WorldPose.from_matrix(reference.as_matrix() @ pose_matrix(3, 4, 0, 0, 0, 2.0))
    distance_m, angle_rad = pose_error(turned, reference)
    assert distance_m == pytest.approx(0.05) and angle_rad == pytest.approx(math.radians(2.0))
