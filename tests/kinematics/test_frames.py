"""The mount and the body FRD / LOCAL_NED transforms."""

from __future__ import annotations

import math

import numpy as np
import pytest

from companion.kinematics.frames import Mount, body_to_local_ned, invert, pose_matrix


def test_default_mount_hangs_the_arm_10_cm_below_the_body_origin():
    mount = Mount()
    np.testing.assert_allclose(mount.to_body([0.0, 0.0, 5.0]), [0.0, 0.0, 15.0])  # base +z: down
    np.testing.assert_allclose(mount.matrix, pose_matrix((0, 0, 10), (0, 0, 0)))


def test_a_turned_mount_and_its_inverse():
    mount = Mount((5.0, -2.0, 8.0), (0.0, 0.0, 90.0))  # base x along the body's y (right)
    np.testing.assert_allclose(mount.to_body([10.0, 0.0, 0.0]), [5.0, 8.0, 8.0], atol=1e-12)
    np.testing.assert_allclose(invert(mount.matrix) @ mount.matrix, np.eye(4), atol=1e-12)


def test_body_to_local_ned_from_attitude_and_position():
    # Yawed 90° (nose east), 2 m north, 1 m up (down = -1): the nose point 1 m ahead of the body
    # origin is 1 m east of it, in cm.
    t = body_to_local_ned(0.0, 0.0, math.pi / 2, north_m=2.0, east_m=0.0, down_m=-1.0)
    np.testing.assert_allclose(t @ [100.0, 0.0, 0.0, 1.0], [200.0, 100.0, -100.0, 1.0], atol=1e-9)
    # Pitched nose-up 10°: a point ahead rises (its down coordinate is negative).
    t = body_to_local_ned(0.0, math.radians(10.0), 0.0)
    assert (t @ [100.0, 0.0, 0.0, 1.0])[2] == pytest.approx(-100.0 * math.sin(math.radians(10)))


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [({"xyz_cm": (0.0, math.nan, 0.0)}, "Mount.xyz_cm[1]"), ({"rpy_deg": (0.0, 0.0)}, "rpy_deg")],
)
def test_bad_mount_names_the_field(kwargs, field):
    with pytest.raises(ValueError, match=field.replace("[", r"\[").replace("]", r"\]")):
        Mount(**kwargs)
