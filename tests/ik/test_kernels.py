"""The compiled kernels, checked against the numpy implementation and finite differences."""

from __future__ import annotations

import math

import numpy as np
import pytest

from companion.ik import kernel_arrays, kernels, layout
from companion.kinematics import rotation_angle, rpy_to_matrix
from companion.kinematics.arm import Arm

PAPER = Arm.default()
MODIFIED = Arm.from_package_file("paper_arm_modified.toml")
TOOLED = Arm.from_dict(
    {
        "convention": "standard",
        "joint": [
            {"alpha_deg": 90, "a": 2, "d": 3, "offset_deg": 10, "min_deg": -90, "max_deg": 90},
            {"alpha_deg": 0, "a": 20, "d": 0, "min_deg": -90, "max_deg": 90},
            {"alpha_deg": -90, "a": 1, "d": 5, "min_deg": -90, "max_deg": 90},
        ],
        "tool": {"xyz": [1, 2, 3], "rpy_deg": [10, 20, 30]},
    }
)
FLIPPED = Arm.from_dict(
    {
        "convention": "standard",
        "joint": [
            {"alpha_deg": 90, "a": 2, "d": 3, "min_deg": -90, "max_deg": 90, "direction": -1},
            {"type": "prismatic", "alpha_deg": -90, "a": 1, "theta_deg": 30, "min": 0, "max": 9},
            {"alpha_deg": 0, "a": 5, "d": 1, "min_deg": -400, "max_deg": 400},
        ],
        "base": {"xyz": [1, -2, 3], "rpy_deg": [180, 10, 90]},
    }
)
ARMS = pytest.mark.parametrize(
    "arm",
    [
        PAPER,
        MODIFIED,
        TOOLED,
        FLIPPED,
        Arm.from_package_file("stanford.toml"),
        Arm.from_package_file("baxter.toml"),
        Arm.from_package_file("panda.toml"),
        Arm.from_package_file("ur5.urdf"),
    ],
    ids=["std", "modified", "tool", "flip-prismatic-base", "stanford", "baxter", "panda", "urdf"],
)


def kernel_fk(arm, q, want_axes=False):
    k = kernel_arrays(arm)
    rot, pos = np.empty((3, 3)), np.empty(3)
    axes, points = np.empty((arm.dof, 3)), np.empty((arm.dof, 3))
    kernels.fk_frames(q, k.frames, k.joint_params, rot, pos, axes, points, want_axes)
    return rot, pos, axes, points


@ARMS
def test_compiled_fk_equals_numpy_fk(arm):
    q = arm.random_q_rad(np.random.default_rng(1), 100)
    expected = arm.fk_batch(q)
    for qi, ti in zip(q, expected, strict=True):
        rot, pos, _, _ = kernel_fk(arm, qi)
        np.testing.assert_allclose(rot, ti[:3, :3], atol=1e-12)
        np.testing.assert_allclose(pos, ti[:3, 3], atol=1e-10)


@ARMS
def test_joint_axes_give_the_geometric_jacobian(arm):
    # Velocity of the hand for a small turn of joint j equals z_j × (p − p_j); the hand's
    # rotation turns about z_j. Checked against central differences of the numpy FK.
    q = arm.random_q_rad(np.random.default_rng(2), 1)[0]
    _, pos, axes, points = kernel_fk(arm, q, want_axes=True)
    h = 1e-6
    for j in range(arm.dof):
        dq = np.zeros(arm.dof)
        dq[j] = h
        t_plus, t_minus = arm.fk_matrix(q + dq), arm.fk_matrix(q - dq)
        v = (t_plus[:3, 3] - t_minus[:3, 3]) / (2 * h)
        omega_hat = (t_plus[:3, :3] - t_minus[:3, :3]) / (2 * h) @ arm.fk_matrix(q)[:3, :3].T
        omega = np.array([omega_hat[2, 1], omega_hat[0, 2], omega_hat[1, 0]])
        if arm.joints[j].revolute:
            np.testing.assert_allclose(np.cross(axes[j], pos - points[j]), v, atol=1e-6)
            np.testing.assert_allclose(omega, axes[j], atol=1e-6)
        else:  # a slider moves the hand along its axis and turns nothing
            np.testing.assert_allclose(axes[j], v, atol=1e-6)
            np.testing.assert_allclose(omega, 0.0, atol=1e-6)


def test_pose_residual_is_position_and_rotation_vector():
    rot = rpy_to_matrix(0.3, -0.2, 1.0)
    pos = np.array([1.0, 2.0, 3.0])
    for angle in (0.0, 1e-7, 0.4, 3.0, math.pi):
        axis = np.array([1.0, -2.0, 0.5]) / np.linalg.norm([1.0, -2.0, 0.5])
        turn = rpy_to_matrix(0, 0, 0)
        k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
        turn = turn + math.sin(angle) * k + (1 - math.cos(angle)) * k @ k  # Rodrigues
        goal = np.eye(4)
        goal[:3, :3] = turn @ rot
        goal[:3, 3] = pos + [0.0, 3.0, 4.0]
        res = np.empty(6)
        pos_err, ori_err = kernels.pose_residual(rot, pos, goal, res)
        assert pos_err == pytest.approx(5.0)
        np.testing.assert_allclose(res[:3], [0.0, 3.0, 4.0])
        assert ori_err == pytest.approx(math.degrees(angle), abs=1e-9)
        assert ori_err == pytest.approx(math.degrees(rotation_angle(goal[:3, :3], rot)), abs=1e-9)
        # The rotation vector is the angle about ±axis (at half a turn the sign is free).
        np.testing.assert_allclose(np.abs(res[3:]), np.abs(math.degrees(angle) * axis), atol=1e-6)


def _lm_inputs(arm, seed):
    k = kernel_arrays(arm)
    fparams = np.zeros(layout.N_FPARAMS)
    fparams[kernels.F_TOL_POS] = 1e-9
    fparams[kernels.F_TOL_ORI] = 1e-9
    fparams[kernels.F_LM_LAMBDA0] = 1e-3
    q_true = arm.random_q_rad(np.random.default_rng(seed), 1)[0]
    return k, fparams, q_true, arm.fk_matrix(q_true)


@pytest.mark.parametrize("rows", [3, 6])
@pytest.mark.parametrize("lam", [0.1, 1e-5])
def test_the_residual_sized_step_equals_the_joint_sized_step(rows, lam):
    # 10 joints, one held: (J·D⁻¹·Jᵀ + I)·y = r, Δq = D⁻¹·Jᵀ·y is the same step as the n×n
    # normal equations (JᵀJ + D)·Δq = Jᵀr, D = λ·diag(JᵀJ) + 1e-9·I.
    n = 10
    rng = np.random.default_rng(rows)
    jac = rng.normal(size=(n, 6)) * 30.0
    jac[:, rows:] = 0.0
    r = rng.normal(size=6)
    r[rows:] = 0.0
    hold = np.zeros(n)
    hold[3] = 1.0
    full = jac @ jac.T
    free = hold < 0.5
    expected = np.zeros(n)
    system = full + np.diag(lam * np.diag(full) + 1e-9)
    expected[free] = np.linalg.solve(system[np.ix_(free, free)], (jac @ r)[free])

    steps = []
    for form in (0, rows):
        jtj, jtr, a, g = np.tril(full), jac @ r, np.zeros((n, n)), np.zeros(n)
        if form:
            jtj, jtr = np.diag(np.diag(full)), np.concatenate([r, np.zeros(n - 6)])
        assert kernels._damped_step(jac, jtj, jtr, lam, hold, a, g, form)
        steps.append(g.copy())
    for step in steps:
        np.testing.assert_allclose(step, expected, rtol=1e-9, atol=1e-12)
        assert step[3] == 0.0


def test_lm_converges_from_nearby_and_stays_in_limits():
    k, fparams, q_true, goal = _lm_inputs(PAPER, 5)
    q = np.clip(q_true + 0.1, k.lower, k.upper)
    out = np.empty(3)
    steps = kernels.lm_refine(
        q, k.lower, k.upper, k.frames, k.joint_params, goal, kernels.MODE_POSE, fparams, 30, out
    )
    assert 0 < steps <= 30
    assert out[1] < 1e-9 and out[2] < 1e-9
    assert np.all(q >= k.lower) and np.all(q <= k.upper)


@pytest.mark.parametrize("seed", range(5))
def test_lm_converges_to_a_solution_with_joints_at_their_limits(seed):
    # Every joint of the solution on a limit (Panda: 7 joints, none turning all the way), the
    # start inside the box: LM holds the joints a step pushes out and still converges.
    arm = Arm.from_package_file("panda.toml")
    k = kernel_arrays(arm)
    fparams = np.zeros(layout.N_FPARAMS)
    fparams[kernels.F_TOL_POS] = 1e-9
    fparams[kernels.F_TOL_ORI] = 1e-9
    fparams[kernels.F_LM_LAMBDA0] = 0.1
    rng = np.random.default_rng(seed)
    at_upper = rng.random(arm.dof) < 0.5
    q_true = np.where(at_upper, k.upper, k.lower)
    goal = arm.fk_matrix(q_true)
    q = q_true + np.where(at_upper, -1.0, 1.0) * np.radians(rng.uniform(2.0, 4.0, arm.dof))
    out = np.empty(3)
    kernels.lm_refine(
        q, k.lower, k.upper, k.frames, k.joint_params, goal, kernels.MODE_POSE, fparams, 60, out
    )
    assert out[1] < 1e-6 and out[2] < 1e-6
    assert np.all(q >= k.lower) and np.all(q <= k.upper)


def test_lm_never_leaves_the_box_even_when_the_solution_is_outside():
    k, fparams, _, _ = _lm_inputs(PAPER, 6)
    q_outside = np.radians([0.0, -40.0, 0.0, 0.0, 0.0, 0.0])  # q2 below its 0° limit
    goal = PAPER.fk_matrix(q_outside)
    q = np.radians([0.0, 10.0, 0.0, 0.0, 0.0, 0.0])
    out = np.empty(3)
    kernels.lm_refine(
        q, k.lower, k.upper, k.frames, k.joint_params, goal, kernels.MODE_POSE, fparams, 50, out
    )
    assert np.all(q >= k.lower) and np.all(q <= k.upper)


STANFORD = Arm.from_package_file("stanford.toml")  # q1, q2, q4, q6: ±170°, free in LM


def _stanford_lm(q_goal_deg, q_start_deg):
    k, fparams, _, _ = _lm_inputs(STANFORD, 0)
    goal = STANFORD.fk_matrix(STANFORD.q_from_user(q_goal_deg))
    q = STANFORD.q_from_user(q_start_deg)
    out = np.empty(3)
    kernels.lm_refine(
        q, k.lower, k.upper, k.frames, k.joint_params, goal, kernels.MODE_POSE, fparams, 30, out
    )
    assert np.all(q >= k.lower) and np.all(q <= k.upper)
    # The errors handed back are those of the configuration handed back.
    t = STANFORD.fk_matrix(q)
    assert out[1] == pytest.approx(np.linalg.norm(t[:3, 3] - goal[:3, 3]), abs=1e-9)
    assert out[2] == pytest.approx(math.degrees(rotation_angle(goal[:3, :3], t[:3, :3])), abs=1e-6)
    return q, out


def test_lm_turns_a_free_joint_through_its_forbidden_arc():
    # q1 from 165° to -165°: 30° through the 20° arc beyond ±170° (a clamped LM stalls at 170°).
    q, out = _stanford_lm([-165, 20, 60, 30, 40, 50], [165, 25, 55, 35, 35, 45])
    assert out[1] < 1e-9 and out[2] < 1e-9
    assert math.degrees(q[0]) == pytest.approx(-165.0, abs=1e-6)


@pytest.mark.parametrize("q1_deg", [172.0, 180.0])
def test_a_free_joint_that_ends_outside_its_range_comes_back_within_the_limits(q1_deg):
    # The target's q1 is beyond the limit (2° and 10°): LM hands back a configuration within
    # the limits, with its own errors (checked in _stanford_lm), not the one it converged to.
    q, out = _stanford_lm([q1_deg, 20, 60, 30, 40, 50], [165, 25, 55, 35, 35, 45])
    assert out[0] > 0.0


def test_lm_with_zero_iterations_leaves_q_alone():
    k, fparams, q_true, goal = _lm_inputs(PAPER, 7)
    q = q_true * 0.5
    before = q.copy()
    out = np.empty(3)
    assert (
        kernels.lm_refine(
            q, k.lower, k.upper, k.frames, k.joint_params, goal, kernels.MODE_POSE, fparams, 0, out
        )
        == 0
    )
    np.testing.assert_array_equal(q, before)


def test_rng_stream_is_uniform_and_repeatable():
    a = np.array([42], dtype=np.uint64)
    b = np.array([42], dtype=np.uint64)
    xs = np.array([kernels._rand(a) for _ in range(20000)])
    ys = np.array([kernels._rand(b) for _ in range(20000)])
    np.testing.assert_array_equal(xs, ys)
    assert xs.min() >= 0.0 and xs.max() < 1.0
    assert abs(xs.mean() - 0.5) < 0.01
    counts = np.bincount([kernels._randint(a, 7) for _ in range(70000)], minlength=7)
    assert counts.min() > 9000 and counts.max() < 11000


def test_goal_matrix_equals_pose_as_matrix():
    from companion.kinematics.arm import Pose

    pose = Pose(-20.0, 3.0, 40.0, 25.0, -80.0, 170.0)
    goal = np.empty((4, 4))
    kernels.goal_matrix(*pose.as_tuple()[:3], *np.radians(pose.as_tuple()[3:]), goal)
    np.testing.assert_allclose(goal, pose.as_matrix(), atol=1e-15)
