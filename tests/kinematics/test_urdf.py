"""URDF import: the shipped UR5 URDF equals the DH arm; what is folded, what is refused."""

from __future__ import annotations

import math
import re

import numpy as np
import pytest

from companion.errors import ArmConfigError
from companion.kinematics.arm import Arm, JointKind
from companion.kinematics.urdf import load_urdf, parse_urdf


def test_shipped_ur5_urdf_has_the_dh_arms_fk():
    # ur5.urdf turns its joint axes to x, y, −z and a skew axis and has fixed joints at both ends.
    dh = Arm.from_package_file("ur5.toml")
    urdf = Arm.from_package_file("ur5.urdf")
    assert urdf.dof == 6 and urdf.convention is None
    q = dh.random_q_rad(np.random.default_rng(16), 200)
    np.testing.assert_allclose(urdf.fk_batch(q), dh.fk_batch(q), rtol=0, atol=1e-9)
    np.testing.assert_allclose(urdf.lower_q, dh.lower_q)


def _robot(*joints: str) -> str:
    used = sorted(set(re.findall(r'link="(l[0-8])"', "".join(joints))))  # l9 stays undefined
    names = "".join(f'<link name="{link}"/>' for link in used)
    return f'<robot name="t">{names}{"".join(joints)}</robot>'


def _joint(name, kind, parent, child, extra="", limit='<limit lower="-1" upper="1"/>'):
    return (
        f'<joint name="{name}" type="{kind}"><parent link="{parent}"/><child link="{child}"/>'
        f"{extra}{limit}</joint>"
    )


def test_fixed_joints_fold_and_prismatic_is_in_cm():
    text = _robot(
        _joint("mount", "fixed", "l0", "l1", '<origin xyz="0 0 0.5"/>', limit=""),
        _joint(
            "slide",
            "prismatic",
            "l1",
            "l2",
            '<axis xyz="1 0 0"/>',
            '<limit lower="0" upper="0.3"/>',
        ),
        _joint(
            "turn", "continuous", "l2", "l3", '<origin xyz="0.1 0 0"/><axis xyz="0 0 1"/>', limit=""
        ),
    )
    arm = parse_urdf(text)
    assert [j.name for j in arm.joints] == ["slide", "turn"]
    assert arm.joints[0].kind is JointKind.PRISMATIC
    assert (arm.joints[0].lower, arm.joints[0].upper) == pytest.approx((0.0, 30.0))
    assert (arm.joints[1].lower, arm.joints[1].upper) == pytest.approx((-math.pi, math.pi))
    t = arm.fk_matrix([20.0, math.pi / 2])
    np.testing.assert_allclose(t[:3, 3], [30.0, 0.0, 50.0], atol=1e-12)
    np.testing.assert_allclose(t[:3, 0], [0.0, 1.0, 0.0], atol=1e-12)


@pytest.mark.parametrize(
    ("joints", "field", "words"),
    [
        (
            [_joint("a", "revolute", "l0", "l1"), _joint("b", "revolute", "l0", "l2")],
            "joint b",
            "branches",
        ),
        ([_joint("a", "floating", "l0", "l1", limit="")], "joint a", "floating"),
        ([_joint("a", "planar", "l0", "l1", limit="")], "joint a", "planar"),
        (
            [
                _joint("a", "revolute", "l0", "l1"),
                _joint("m", "revolute", "l1", "l2", '<mimic joint="a"/>'),
            ],
            "joint m",
            "mimic",
        ),
        ([_joint("a", "revolute", "l0", "l1", limit="")], "joint a.limit", "lower"),
        ([_joint("a", "revolute", "l0", "l1", '<axis xyz="0 0 0"/>')], "joint a.axis", "zero"),
        ([_joint("a", "hinge", "l0", "l1")], "joint a.type", "hinge"),
        ([_joint("a", "revolute", "l0", "l9")], "joint a", "not defined"),
    ],
)
def test_refused_urdf_names_the_joint(joints, field, words):
    with pytest.raises(ArmConfigError) as info:
        parse_urdf(_robot(*joints), source="t.urdf")
    assert info.value.field == field
    assert words in str(info.value)


def test_tip_link_picks_one_branch():
    text = _robot(_joint("a", "revolute", "l0", "l1"), _joint("b", "revolute", "l0", "l2"))
    arm = parse_urdf(text, tip_link="l2")
    assert [j.name for j in arm.joints] == ["b"]


def test_not_xml_and_missing_file(tmp_path):
    with pytest.raises(ArmConfigError, match="not valid XML"):
        parse_urdf("<robot")
    with pytest.raises(ArmConfigError, match="cannot read"):
        load_urdf(tmp_path / "none.urdf")
