import math

import numpy as np
import pytest

from companion.kinematics.arm import Pose
from companion.kinematics.rotations import matrix_to_rpy, rpy_to_matrix
from companion.kinematics.vehicle import (
    MAX_PREDICT_S,
    Mount,
    VehicleState,
    base_to_world,
    matrix_to_base,
    mount_transform,
    world_to_base,
)


def state(
    rpy=(0.0, 0.0, 0.0), rates=(0.0, 0.0, 0.0), position=(0.0, 0.0, 0.0), velocity=(0.0, 0.0, 0.0)
):
    return VehicleState(1.0, position, velocity, 1.0, rpy, rates)


def test_a_yawed_vehicle_carries_a_forward_hand_to_the_east():
    # Nose east (yaw 90 deg): the arm's forward (+x, mount identity) is the world's east.
    vehicle = state(rpy=(0.0, 0.0, math.pi / 2), position=(100.0, 0.0, -500.0))
    hand = Pose(10.0, 0.0, 20.0, 0.0, 0.0, 0.0)
    world = base_to_world(hand, vehicle.predict(1.0), mount_transform((0, 0, 10), (0, 0, 0)))
    assert (world.x_cm, world.y_cm, world.z_cm) == pytest.approx((100.0, 10.0, -470.0))
    assert world.yaw_deg == pytest.approx(90.0)


def test_world_to_base_undoes_base_to_world():
    rng = np.random.default_rng(3)
    for _ in range(50):
        vehicle = state(
            rpy=tuple(rng.uniform(-0.3, 0.3, 3)), position=tuple(rng.uniform(-500, 500, 3))
        )
        mount = mount_transform(rng.uniform(-10, 10, 3), rng.uniform(-180, 180, 3))
        hand = Pose(*rng.uniform(-30, 30, 3), *rng.uniform(-80, 80, 3))
        back = world_to_base(
            base_to_world(hand, vehicle.predict(1.0), mount), vehicle.predict(1.0), mount
        )
        assert back.as_matrix() == pytest.approx(hand.as_matrix(), abs=1e-9)
        world = base_to_world(hand, vehicle.predict(1.0), mount)
        from_matrix = matrix_to_base(world.as_matrix(), vehicle.predict(1.0), mount)
        assert from_matrix.as_matrix() == pytest.approx(hand.as_matrix(), abs=1e-9)


def test_prediction_moves_at_constant_velocity_and_turns_about_the_body_axes():
    # Rolled 30 deg, turning about the body's z at 1 rad/s: in the world that is not a pure
    # yaw; after 0.1 s the body z has turned 0.1 rad about itself, x advanced 10 cm at 1 m/s.
    roll = math.radians(30)
    vehicle = state(rpy=(roll, 0.0, 0.0), rates=(0.0, 0.0, 1.0), velocity=(100.0, 0.0, 0.0))
    t = vehicle.predict(1.1)
    assert t[:3, 3] == pytest.approx((10.0, 0.0, 0.0))
    start = vehicle.predict(1.0)[:3, :3]
    relative = start.T @ t[:3, :3]  # the turn, seen in the body frame
    assert relative[:, 2] == pytest.approx((0.0, 0.0, 1.0))  # about body z
    assert math.atan2(relative[1, 0], relative[0, 0]) == pytest.approx(0.1)


def test_prediction_never_goes_backwards_nor_beyond_its_horizon():
    vehicle = state(velocity=(100.0, 0.0, 0.0))
    assert vehicle.predict(0.5)[0, 3] == 0.0  # before the sample: the sample
    assert vehicle.predict(100.0)[0, 3] == pytest.approx(100.0 * MAX_PREDICT_S)


@pytest.mark.parametrize("field", ["position_cm", "velocity_cm_s", "rpy_rad", "body_rates_rad_s"])
def test_a_non_finite_state_is_refused_naming_the_field(field):
    values = {
        "position_cm": (0.0, 0.0, 0.0),
        "velocity_cm_s": (0.0, 0.0, 0.0),
        "rpy_rad": (0.0, 0.0, 0.0),
        "body_rates_rad_s": (0.0, 0.0, 0.0),
    }
    values[field] = (0.0, math.nan, 0.0)
    with pytest.raises(ValueError, match=field):
        VehicleState(
            0.0,
            values["position_cm"],
            values["velocity_cm_s"],
            0.0,
            values["rpy_rad"],
            values["body_rates_rad_s"],
        )


# -- the config's mount (keep-out checks) ----------------------------------------------------------


def test_default_mount_hangs_the_arm_10_cm_below_the_body_origin():
    mount = Mount()
    np.testing.assert_allclose(mount.to_body([0.0, 0.0, 5.0]), [0.0, 0.0, 15.0])  # base +z: down
    np.testing.assert_allclose(mount.matrix, mount_transform((0, 0, 10), (0, 0, 0)))
    turned = Mount((5.0, -2.0, 8.0), (0.0, 0.0, 90.0))  # base x along the body's y (right)
    np.testing.assert_allclose(turned.to_body([10.0, 0.0, 0.0]), [5.0, 8.0, 8.0], atol=1e-12)


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        ({"xyz_cm": (0.0, math.nan, 0.0)}, r"Mount.xyz_cm\[1\]"),
        ({"rpy_deg": (0.0, 0.0)}, "rpy_deg"),
    ],
)
def test_bad_mount_names_the_field(kwargs, field):
    with pytest.raises(ValueError, match=field):
        Mount(**kwargs)


def test_one_rotation_takes_the_scalar_path_to_the_same_numbers():
    """rpy_to_matrix / matrix_to_rpy on one rotation (scalars, the world path's every tick)
    give what the broadcasting path gives for the same rotation, gimbal lock included."""
    rng = np.random.default_rng(3)
    rpy = rng.uniform(-np.pi, np.pi, (200, 3))
    rpy[:20, 1] = np.pi / 2  # gimbal lock
    rpy[20:40, 1] = -np.pi / 2
    batch = rpy_to_matrix(rpy[:, 0], rpy[:, 1], rpy[:, 2])
    back = matrix_to_rpy(batch)
    for i, (r, p, y) in enumerate(rpy):
        one = rpy_to_matrix(float(r), float(p), float(y))
        np.testing.assert_allclose(one, batch[i], rtol=0, atol=1e-15)
        np.testing.assert_allclose(matrix_to_rpy(batch[i]), back[i], rtol=0, atol=1e-15)
        np.testing.assert_allclose(rpy_to_matrix(*matrix_to_rpy(one)), one, rtol=0, atol=1e-12)
