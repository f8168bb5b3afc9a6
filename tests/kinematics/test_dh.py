"""Forward kinematics against hand-derived golden values and an independent implementation."""

from __future__ import annotations

import math

import numpy as np
import pytest

from companion.kinematics import (
    DHConvention,
    matrix_to_rpy,
    rotation_angle,
    rpy_to_matrix,
    wrap_angle,
)
from companion.kinematics.arm import Arm

# -- an independent reference: plain Python, elementary transforms multiplied one by one ----------


def _matmul(a, b):
    return [[sum(a[i][k] * b[k][j] for k in range(4)) for j in range(4)] for i in range(4)]


def _rz(t):
    c, s = math.cos(t), math.sin(t)
    return [[c, -s, 0, 0], [s, c, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]


def _rx(t):
    c, s = math.cos(t), math.sin(t)
    return [[1, 0, 0, 0], [0, c, -s, 0], [0, s, c, 0], [0, 0, 0, 1]]


def _tx(v):
    return [[1, 0, 0, v], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]


def _tz(v):
    return [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, v], [0, 0, 0, 1]]


def reference_fk(arm: Arm, q_rad) -> np.ndarray:
    """Textbook definition, one elementary transform at a time (no closed-form link matrix)."""
    t = [[float(i == j) for j in range(4)] for i in range(4)]
    for joint, q in zip(arm.joints, q_rad, strict=True):
        theta = q + joint.offset_rad
        if arm.convention is DHConvention.STANDARD:
            parts = [_rz(theta), _tz(joint.d_cm), _tx(joint.a_cm), _rx(joint.alpha_rad)]
        else:
            parts = [_rx(joint.alpha_rad), _tx(joint.a_cm), _rz(theta), _tz(joint.d_cm)]
        for p in parts:
            t = _matmul(t, p)
    if arm.tool is not None:
        t = _matmul(t, [list(row) for row in arm.tool])
    return np.array(t)


PAPER = Arm.default()
MODIFIED = Arm.from_package_file("paper_arm_modified.toml")


def _ry(deg):
    b = math.radians(deg)
    return np.array([[math.cos(b), 0, math.sin(b)], [0, 1, 0], [-math.sin(b), 0, math.cos(b)]])


def _rz3(deg):
    g = math.radians(deg)
    return np.array([[math.cos(g), -math.sin(g), 0], [math.sin(g), math.cos(g), 0], [0, 0, 1]])


# Golden values derived by hand, frame by frame, from the tables in companion/kinematics/arms/:
# * standard, q = 0: the chain stands straight up; x: 6.4 (a1) + 2 (−d6 along −x) = 8.4,
#   z: 30.2 + 23.5 + 5.3 + 5.6 = 64.6; hand axes x6 = z0, y6 = y0, z6 = −x0, i.e. Ry(−90°).
# * standard, q1 = 90°: the same rotated by Rz(90°) about the base axis.
# * standard, q2 = 90°: the chain lies along x0: 6.4 + 30.2 + 23.5 + 5.3 + 5.6 = 71.0, z = d6 = −2,
#   hand axes equal to the base axes.
# * modified, q = 0: x = a0 = 3.5, z = −a1 = −6.5, y = −(28.2 + 23.5) + 7.5 + 5 (tool) = −39.2,
#   hand axes x = y0, y = −x0, z = z0, i.e. Rz(90°).
GOLDEN = [
    (PAPER, [0, 0, 0, 0, 0, 0], [8.4, 0.0, 64.6], _ry(-90)),
    (PAPER, [90, 0, 0, 0, 0, 0], [0.0, 8.4, 64.6], _rz3(90) @ _ry(-90)),
    (PAPER, [0, 90, 0, 0, 0, 0], [71.0, 0.0, -2.0], np.eye(3)),
    (MODIFIED, [0, 0, 0, 0, 0, 0], [3.5, -39.2, -6.5], _rz3(90)),
]


@pytest.mark.parametrize(("arm", "q_deg", "pos_cm", "rot"), GOLDEN)
def test_fk_matches_hand_derived_golden_values(arm, q_deg, pos_cm, rot):
    t = arm.fk_matrix(np.radians(q_deg))
    np.testing.assert_allclose(t[:3, 3], pos_cm, atol=1e-12)
    np.testing.assert_allclose(t[:3, :3], rot, atol=1e-12)


@pytest.mark.parametrize("convention", list(DHConvention))
def test_planar_two_link_closed_form(convention):
    # For a planar 2R arm both conventions give x = L1·cos q1 + L2·cos(q1 + q2).
    if convention is DHConvention.STANDARD:
        rows = [{"alpha_deg": 0, "a": 3.0, "d": 0}, {"alpha_deg": 0, "a": 2.0, "d": 0}]
        tool = None
    else:
        rows = [{"alpha_deg": 0, "a": 0.0, "d": 0}, {"alpha_deg": 0, "a": 3.0, "d": 0}]
        tool = {"xyz": [2.0, 0, 0]}
    for r in rows:
        r.update(min_deg=-180, max_deg=180)
    data = {"convention": convention.value, "joint": rows}
    if tool:
        data["tool"] = tool
    arm = Arm.from_dict(data)
    q = np.radians([30.0, 45.0])
    t = arm.fk_matrix(q)
    assert t[0, 3] == pytest.approx(3 * math.cos(q[0]) + 2 * math.cos(q.sum()), abs=1e-12)
    assert t[1, 3] == pytest.approx(3 * math.sin(q[0]) + 2 * math.sin(q.sum()), abs=1e-12)
    np.testing.assert_allclose(t[:3, :3], _rz3(75.0), atol=1e-12)


@pytest.mark.parametrize("arm", [PAPER, MODIFIED], ids=["standard", "modified"])
def test_batched_fk_agrees_with_independent_reference(arm):
    rng = np.random.default_rng(7)
    # Beyond the limits on purpose: FK itself must be right everywhere.
    q = rng.uniform(-np.pi, np.pi, size=(200, arm.dof))
    batch = arm.fk_batch(q)
    assert batch.shape == (200, 4, 4)
    for qi, ti in zip(q, batch, strict=True):
        np.testing.assert_allclose(ti, reference_fk(arm, qi), atol=1e-10)


def test_single_pose_fk_equals_batched_row():
    rng = np.random.default_rng(3)
    q = PAPER.random_q_rad(rng, 5)
    batch = PAPER.fk_batch(q)
    for qi, ti in zip(q, batch, strict=True):
        np.testing.assert_array_equal(PAPER.fk_matrix(qi), ti)


def test_fk_rejects_wrong_shape():
    with pytest.raises(ValueError, match=r"shape \(S, 6\)"):
        PAPER.fk_batch(np.zeros((3, 5)))
    with pytest.raises(ValueError, match="6 values"):
        PAPER.fk([0, 0, 0])


def test_rpy_round_trip_random():
    rng = np.random.default_rng(11)
    rpy = np.column_stack(
        [
            rng.uniform(-np.pi, np.pi, 500),
            rng.uniform(-np.pi / 2 + 1e-3, np.pi / 2 - 1e-3, 500),
            rng.uniform(-np.pi, np.pi, 500),
        ]
    )
    rot = rpy_to_matrix(rpy[:, 0], rpy[:, 1], rpy[:, 2])
    np.testing.assert_allclose(matrix_to_rpy(rot), rpy, atol=1e-9)


def test_rpy_convention_is_z_y_x():
    # R = Rz(yaw)·Ry(pitch)·Rx(roll): a pure yaw turns x into y.
    rot = rpy_to_matrix(0.0, 0.0, math.pi / 2)
    np.testing.assert_allclose(rot @ [1, 0, 0], [0, 1, 0], atol=1e-15)
    rot = rpy_to_matrix(0.3, 0.2, 0.1)
    rx = np.array(
        [[1, 0, 0], [0, math.cos(0.3), -math.sin(0.3)], [0, math.sin(0.3), math.cos(0.3)]]
    )
    np.testing.assert_allclose(
        rot, _rz3(math.degrees(0.1)) @ _ry(math.degrees(0.2)) @ rx, atol=1e-15
    )


@pytest.mark.parametrize("pitch_deg", [90.0, -90.0])
def test_rpy_at_gimbal_lock_still_reproduces_matrix(pitch_deg):
    rot = rpy_to_matrix(0.4, math.radians(pitch_deg), -0.7)
    back = matrix_to_rpy(rot)
    np.testing.assert_allclose(rpy_to_matrix(*back), rot, atol=1e-12)


def test_rotation_angle_small_and_large():
    base = rpy_to_matrix(0.1, 0.2, 0.3)
    for angle in (1e-9, 1e-4, 0.5, 3.0):
        turned = base @ rpy_to_matrix(angle, 0.0, 0.0)
        assert rotation_angle(base, turned) == pytest.approx(angle, rel=1e-7)


def test_wrap_angle():
    np.testing.assert_allclose(
        wrap_angle(np.radians([359.0, -359.0, 181.0])), np.radians([-1, 1, -179])
    )
