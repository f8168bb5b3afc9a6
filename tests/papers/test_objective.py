"""The papers' objective J = σ‖ΔP‖ + ε‖ΔO‖, its penalty and minimal-movement terms."""

from __future__ import annotations

import math

import numpy as np
import pytest

from companion.kinematics.arm import Arm, Pose
from companion.papers.objective import IKObjective, OrientationMetric

ARM = Arm.default()
Q = np.radians([[10.0, 60.0, -20.0, 30.0, 15.0, -5.0]])


def test_zero_at_the_configuration_that_produced_the_target():
    target = ARM.fk(np.degrees(Q[0]))
    for metric in OrientationMetric:
        obj = IKObjective(ARM, target, metric=metric)
        assert obj.cost(Q)[0] == pytest.approx(0.0, abs=1e-9)


def test_weights_default_to_papers_and_combine_linearly():
    exact = ARM.fk(np.degrees(Q[0]))
    moved = Pose(
        exact.x_cm + 3.0,
        exact.y_cm + 4.0,
        exact.z_cm,
        exact.roll_deg,
        exact.pitch_deg,
        exact.yaw_deg,
    )
    obj = IKObjective(ARM, moved)
    assert (obj.sigma, obj.epsilon) == (0.3, 0.7)
    # Position off by a 3-4-5 triangle, orientation exact: J = 0.3 · 5.
    assert obj.cost(Q)[0] == pytest.approx(1.5, abs=1e-9)


def test_euler_difference_is_wrapped():
    # Yaw 179° vs −179° is 2° apart, not 358°.
    exact = ARM.fk(np.degrees(Q[0]))
    shifted = Pose(*exact.as_tuple()[:5], exact.yaw_deg + 358.0)
    obj = IKObjective(ARM, shifted, sigma=0.0, epsilon=1.0)
    assert obj.cost(Q)[0] == pytest.approx(math.radians(2.0), abs=1e-9)


def test_rotation_metric_equals_rotation_angle():
    exact = ARM.fk(np.degrees(Q[0]))
    turned = Pose(*exact.as_tuple()[:3], exact.roll_deg + 7.0, exact.pitch_deg, exact.yaw_deg)
    obj = IKObjective(ARM, turned, sigma=0.0, epsilon=1.0, metric=OrientationMetric.ROTATION)
    assert obj.cost(Q)[0] == pytest.approx(math.radians(7.0), abs=1e-9)
    errors = obj.errors(Q[0])
    assert errors.ori_err_deg[0] == pytest.approx(7.0, abs=1e-9)
    assert errors.pos_err_cm[0] == pytest.approx(0.0, abs=1e-9)


def test_limit_penalty_counts_overshoot_only():
    target = ARM.fk(np.degrees(Q[0]))
    obj = IKObjective(ARM, target, limit_penalty_per_rad=10.0)
    inside = Q.copy()
    outside = Q.copy()
    outside[0, 5] = ARM.upper_rad[5] + 0.2
    base = IKObjective(ARM, target, limit_penalty_per_rad=0.0)
    assert obj.cost(inside)[0] == pytest.approx(base.cost(inside)[0])
    assert obj.cost(outside)[0] == pytest.approx(base.cost(outside)[0] + 2.0)


def test_movement_term_prefers_configurations_near_the_previous_one():
    target = ARM.fk(np.degrees(Q[0]))
    prev = Q[0] + np.radians([3.0, 0, 0, 0, 0, 4.0])  # 5° away in joint space
    obj = IKObjective(ARM, target, movement_weight=2.0, q_prev_rad=prev)
    assert obj.cost(Q)[0] == pytest.approx(2.0 * math.radians(5.0), abs=1e-9)
    assert obj.cost(prev[None, :])[0] > 0.0
    off = IKObjective(ARM, target, q_prev_rad=prev)  # weight 0 by default
    assert off.cost(Q)[0] == pytest.approx(0.0, abs=1e-9)


def test_vectorised_equals_one_by_one():
    rng = np.random.default_rng(5)
    q = ARM.random_q_rad(rng, 50)
    obj = IKObjective(ARM, Pose(-20, 3, 40, 0, 10, 15), movement_weight=0.5, q_prev_rad=q[0])
    batch = obj.cost(q)
    single = np.array([obj.cost(row[None, :])[0] for row in q])
    np.testing.assert_allclose(batch, single, rtol=1e-12)


@pytest.mark.parametrize(
    ("kwargs", "name"),
    [
        ({"sigma": -1.0}, "sigma"),
        ({"epsilon": math.nan}, "epsilon"),
        ({"q_prev_rad": np.zeros(5)}, "q_prev_rad"),
        ({"metric": "euler"}, "metric"),
    ],
)
def test_bad_settings_are_refused(kwargs, name):
    with pytest.raises(ValueError, match=name):
        IKObjective(ARM, Pose(0, 0, 50, 0, 0, 0), **kwargs)


def test_pose_objective_recomputes_the_papers_j_from_a_printed_pose():
    from companion.papers import constants
    from companion.papers.objective import pose_objective

    g = constants.TARGET_G
    assert pose_objective(g, g) == 0.0
    # Table 5 row 1 prints J = 4.60 beside a pose whose J is 0.21.
    row1 = constants.parse_pose(constants.TABLE5_DE[0][5])
    assert pose_objective(g, row1) == pytest.approx(0.2071, abs=1e-4)
    # A yaw of 15° − 359° is 16° away from 15°, not 344°.
    near = Pose(g.x_cm, g.y_cm, g.z_cm, g.roll_deg, g.pitch_deg, g.yaw_deg - 359.0)
    assert pose_objective(g, near) == pytest.approx(0.7 * np.radians(1.0))
