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


def test_a_tip_link_on_a_loop_of_joints_is_refused_not_followed_forever():
    text = _robot(
        _joint("a", "revolute", "l0", "l1"),
        _joint("x", "revolute", "l2", "l3"),
        _joint("y", "revolute", "l3", "l2"),
    )
    with pytest.raises(ArmConfigError) as info:
        parse_urdf(text, source="t.urdf", tip_link="l3")
    assert info.value.field == "tip_link"
    assert "loop of joints" in str(info.value) and "root link 'l0'" in str(info.value)


def test_not_xml_and_missing_file(tmp_path):
    with pytest.raises(ArmConfigError, match="not valid XML"):
        parse_urdf("<robot")
    with pytest.raises(ArmConfigError, match="cannot read"):
        load_urdf(tmp_path / "none.urdf")


def _link(name, *collisions):
    return f'<link name="{name}">{"".join(collisions)}</link>'


def _collision(geometry, origin=""):
    return f"<collision>{origin}<geometry>{geometry}</geometry></collision>"


def test_collision_primitives_become_bounding_capsules_in_the_link_frame():
    joints = _joint("j1", "revolute", "l0", "l1", '<axis xyz="1 0 0"/>') + _joint(
        "tipfix", "fixed", "l1", "l2", '<origin xyz="0 0 0.2"/>', limit=""
    )
    links = (
        _link("l0", _collision('<box size="1 1 1"/>'))  # the base: fixed to the vehicle, skipped
        + _link(
            "l1",
            _collision('<cylinder radius="0.02" length="0.1"/>', '<origin xyz="0 0 0.05"/>'),
            _collision('<box size="0.02 0.3 0.04"/>'),
            _collision('<mesh filename="x.stl"/>'),
        )
        + _link("l2", _collision('<sphere radius="0.03"/>'))
    )
    arm = parse_urdf(f'<robot name="t">{links}{joints}</robot>')
    (caps,) = arm.link_shapes
    assert [c.radius_cm for c in caps] == pytest.approx([2.0, math.hypot(2, 4) / 2, 3.0])
    # Where the shapes are in the base frame at q = 0.3 rad about the URDF's x axis.
    axes, hand = arm.joint_frames(np.array([[0.3]]))
    link = hand[0] @ np.linalg.inv(arm.frames_array[1])
    world = [
        [link[:3, :3] @ np.asarray(p) + link[:3, 3] for p in (c.from_cm, c.to_cm)] for c in caps
    ]
    rot = np.array(
        [[1, 0, 0], [0, math.cos(0.3), -math.sin(0.3)], [0, math.sin(0.3), math.cos(0.3)]]
    )
    np.testing.assert_allclose(world[0], [rot @ [0, 0, 0], rot @ [0, 0, 10]], atol=1e-9)
    np.testing.assert_allclose(world[1], [rot @ [0, -15, 0], rot @ [0, 15, 0]], atol=1e-9)
    np.testing.assert_allclose(world[2], [rot @ [0, 0, 20], rot @ [0, 0, 20]], atol=1e-9)


def test_collision_errors_name_the_link():
    joints = _joint("j1", "revolute", "l0", "l1")
    for geometry, field in (
        ('<sphere radius="-1"/>', "link l1.collision[0].sphere"),
        ('<cylinder radius="1"/>', "link l1.collision[0].cylinder"),
        ('<cone radius="1"/>', "link l1.collision[0]"),
    ):
        text = f'<robot name="t">{_link("l0")}{_link("l1", _collision(geometry))}{joints}</robot>'
        with pytest.raises(ArmConfigError) as info:
            parse_urdf(text)
        assert info.value.field == field
