"""Geometric Jacobian and its time derivative against finite differences and paper 004."""

from __future__ import annotations

import numpy as np
import pytest

from companion.kinematics.arm import Arm
from companion.kinematics.jacobian import (
    geometric_jacobian,
    hand_acceleration,
    jacobian_and_derivative,
)
from companion.papers.inverse_acceleration import planar_3r_arm

ARMS = {
    "standard": Arm.default(),
    "modified": Arm.from_package_file("paper_arm_modified.toml"),  # has a tool frame
}


def _numeric_jacobian(arm, q, h=1e-6):
    """Central differences of fk_batch: position rows, and ω from (dR/dq)·Rᵀ."""
    s, n = q.shape
    out = np.zeros((s, 6, n))
    rot = arm.fk_batch(q)[:, :3, :3]
    for i in range(n):
        e = np.zeros(n)
        e[i] = h
        tp, tm = arm.fk_batch(q + e), arm.fk_batch(q - e)
        out[:, :3, i] = (tp[:, :3, 3] - tm[:, :3, 3]) / (2 * h)
        w = (tp[:, :3, :3] - tm[:, :3, :3]) / (2 * h) @ np.swapaxes(rot, 1, 2)
        out[:, 3:, i] = np.stack([w[:, 2, 1], w[:, 0, 2], w[:, 1, 0]], axis=1)
    return out


@pytest.mark.parametrize("name", list(ARMS))
def test_jacobian_matches_finite_differences_of_fk(name):
    arm = ARMS[name]
    q = arm.random_q_rad(np.random.default_rng(0), 8)
    jac = geometric_jacobian(arm, q)
    assert jac.shape == (8, 6, 6)
    np.testing.assert_allclose(jac, _numeric_jacobian(arm, q), atol=1e-6)


@pytest.mark.parametrize("name", list(ARMS))
def test_jacobian_derivative_matches_finite_differences_along_the_motion(name):
    arm = ARMS[name]
    rng = np.random.default_rng(1)
    q = arm.random_q_rad(rng, 8)
    qd = rng.normal(size=q.shape)
    jac, jac_dot = jacobian_and_derivative(arm, q, qd)
    np.testing.assert_array_equal(jac, geometric_jacobian(arm, q))
    h = 1e-6
    numeric = (geometric_jacobian(arm, q + h * qd) - geometric_jacobian(arm, q - h * qd)) / (2 * h)
    np.testing.assert_allclose(jac_dot, numeric, atol=1e-6)


@pytest.mark.parametrize("name", list(ARMS))
def test_hand_acceleration_is_the_second_derivative_of_fk(name):
    arm = ARMS[name]
    rng = np.random.default_rng(2)
    q0, qd, qdd = arm.random_q_rad(rng, 4), rng.normal(size=(4, 6)), rng.normal(size=(4, 6))
    h = 1e-4

    def pos(t):
        return arm.fk_batch(q0 + qd * t + 0.5 * qdd * t * t)[:, :3, 3]

    numeric = (pos(h) - 2 * pos(0.0) + pos(-h)) / (h * h)
    np.testing.assert_allclose(hand_acceleration(arm, q0, qd, qdd)[:, :3], numeric, atol=1e-4)


def test_planar_3r_matches_paper_004_closed_form():
    a1, a2, a3 = 1.0, 0.7, 0.3
    arm = planar_3r_arm((a1, a2, a3))
    rng = np.random.default_rng(3)
    q, qd = rng.uniform(-3, 3, (5, 3)), rng.normal(size=(5, 3))
    jac, jac_dot = jacobian_and_derivative(arm, q, qd)
    c1, c12, c123 = np.cos(q[:, 0]), np.cos(q[:, :2].sum(1)), np.cos(q.sum(1))
    s1, s12, s123 = np.sin(q[:, 0]), np.sin(q[:, :2].sum(1)), np.sin(q.sum(1))
    w1, w12, w123 = qd[:, 0], qd[:, :2].sum(1), qd.sum(1)
    # Paper 004 eqs. 18–23 (m; the Arm is in cm)
    j_paper = np.stack(
        [
            np.stack([-a1 * s1 - a2 * s12 - a3 * s123, -a2 * s12 - a3 * s123, -a3 * s123], 1),
            np.stack([a1 * c1 + a2 * c12 + a3 * c123, a2 * c12 + a3 * c123, a3 * c123], 1),
        ],
        1,
    )
    # eqs. 25–30
    jd_paper = np.stack(
        [
            np.stack(
                [
                    -a1 * w1 * c1 - a2 * w12 * c12 - a3 * w123 * c123,
                    -a2 * w12 * c12 - a3 * w123 * c123,
                    -a3 * w123 * c123,
                ],
                1,
            ),
            np.stack(
                [
                    -a1 * w1 * s1 - a2 * w12 * s12 - a3 * w123 * s123,
                    -a2 * w12 * s12 - a3 * w123 * s123,
                    -a3 * w123 * s123,
                ],
                1,
            ),
        ],
        1,
    )
    np.testing.assert_allclose(jac[:, :2] / 100.0, j_paper, atol=1e-12)
    np.testing.assert_allclose(jac_dot[:, :2] / 100.0, jd_paper, atol=1e-12)
    np.testing.assert_allclose(jac[:, 2], 0.0, atol=1e-12)  # planar: no z motion
    np.testing.assert_allclose(jac[:, 5], 1.0)  # every axis is z


def test_shapes_are_checked():
    arm = Arm.default()
    with pytest.raises(ValueError, match=r"\(S, 6\)"):
        geometric_jacobian(arm, np.zeros(6))
    with pytest.raises(ValueError, match="qd_rad_s"):
        jacobian_and_derivative(arm, np.zeros((2, 6)), np.zeros((3, 6)))
    with pytest.raises(ValueError, match="qdd_rad_s2"):
        hand_acceleration(arm, np.zeros((2, 6)), np.zeros((2, 6)), np.zeros((2, 5)))
