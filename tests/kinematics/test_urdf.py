"""URDF import: the shipped UR5 URDF equals the DH arm; what is folded, what is refused."""

from __future__ import annotations

import math
import re
from importlib.resources import files

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
            "tip_link",
            "branches at link 'l0' into 2 chains of 1 moving joint: set tip_link to one of: l1, l2",
        ),
        (
            [_joint("a", "revolute", "l0", "l1"), _joint("b", "hinge", "l1", "l2")],
            "joint b.type",  # counted as moving, so refused by name, not cut off
            "hinge",
        ),
        ([_joint("a", "fixed", "l0", "l1"), _joint("b", "fixed", "l0", "l2")], "<robot>", "fixed"),
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


# Without tip_link, on trees shaped like real URDFs (ROS-Industrial frames, grippers, two arms).


def _tree(*joints: str) -> str:
    used = dict.fromkeys(re.findall(r'link="([^"]+)"', "".join(joints)))
    return (
        f'<robot name="t">{"".join(f"<link name={n!r}/>" for n in used)}{"".join(joints)}</robot>'
    )


def _fixed(name, parent, child, xyz="0 0 0", rpy="0 0 0"):
    return _joint(name, "fixed", parent, child, f'<origin xyz="{xyz}" rpy="{rpy}"/>', limit="")


def _arm_joints(prefix, parent, n):
    """``n`` revolute joints ``{prefix}j1``… from ``parent``, links 0.1 m apart, axes z, y, x…"""
    axes = ("0 0 1", "0 1 0", "1 0 0")
    return [
        _joint(
            f"{prefix}j{k + 1}",
            "revolute",
            parent if k == 0 else f"{prefix}link{k}",
            f"{prefix}link{k + 1}",
            f'<origin xyz="0.02 0 0.1" rpy="0 0 0.3"/><axis xyz="{axes[k % 3]}"/>',
            '<limit lower="-2" upper="2"/>',
        )
        for k in range(n)
    ]


def _same_fk(a: Arm, b: Arm) -> None:
    assert [j.name for j in a.joints] == [j.name for j in b.joints]
    q = a.random_q_rad(np.random.default_rng(3), 50)
    np.testing.assert_allclose(a.fk_batch(q), b.fk_batch(q), rtol=0, atol=1e-9)


def _shipped_ur5_with(*extra: str) -> str:
    text = (files("companion.kinematics") / "arms" / "ur5.urdf").read_text()
    links = "".join(
        f'<link name="{n}"/>' for n in re.findall(r'child link="([^"]+)"', "".join(extra))
    )
    return text.replace("</robot>", links + "".join(extra) + "</robot>")


def test_a_fixed_side_branch_at_the_base_is_left_off_and_fixed_frames_in_line_are_followed():
    # ur_description: base_link→base (the controller's base frame, a half turn) beside the arm,
    # and flange→tool0 in line after the wrist.
    text = _shipped_ur5_with(
        _fixed("base_link-base_fixed_joint", "base_link", "base", rpy="0 0 3.14159"),
        _fixed("flange-tool0", "flange", "tool0", "0 0 0.05", "1.5708 0 1.5708"),
    )
    arm = parse_urdf(text)
    _same_fk(arm, parse_urdf(text, tip_link="tool0"))
    shipped = Arm.from_package_file("ur5.urdf")  # ends at flange
    assert not np.allclose(arm.frames_array[-1], shipped.frames_array[-1])
    _same_fk(parse_urdf(text, tip_link="flange"), shipped)


def test_a_tool0_and_a_sensor_frame_beside_the_flange_stop_the_tip_at_the_wrist():
    text = _shipped_ur5_with(
        _fixed("link6-tool0", "link6", "tool0", "0 0 0.1"),
        _fixed("link6-ft_sensor", "link6", "ft_sensor", "0 0.03 0"),
    )
    arm = parse_urdf(text)
    _same_fk(arm, parse_urdf(text, tip_link="link6"))
    np.testing.assert_allclose(arm.frames_array[-1][:3, 3], 0, atol=1e-12)  # no flange offset


def test_a_shorter_moving_side_branch_is_left_off():
    camera = _joint("cam_pan", "continuous", "base_link", "camera", limit="")
    text = _tree(
        _fixed("world-base", "world", "base_link"), camera, *_arm_joints("", "base_link", 3)
    )
    assert [j.name for j in parse_urdf(text).joints] == ["j1", "j2", "j3"]


def _hand(prefix, parent, finger_joints):
    """A gripper on ``parent``: link8 and hand fixed, a hand_tcp frame and two fingers of
    ``finger_joints`` joints each (the second finger mimics the first), as franka_description's
    hand (one prismatic joint a finger) or a Robotiq 2F (two)."""
    out = [
        _fixed(f"{prefix}joint8", parent, f"{prefix}link8", "0 0 0.107"),
        _fixed(f"{prefix}hand_joint", f"{prefix}link8", f"{prefix}hand", rpy="0 0 -0.785"),
        _fixed(f"{prefix}hand_tcp_joint", f"{prefix}hand", f"{prefix}hand_tcp", "0 0 0.1034"),
    ]
    for side, sign in (("left", 1), ("right", -1)):
        link = f"{prefix}hand"
        for k in range(finger_joints):
            mimic = f'<mimic joint="{prefix}finger_{k}_left"/>' if side == "right" else ""
            out.append(
                _joint(
                    f"{prefix}finger_{k}_{side}",
                    "prismatic",
                    link,
                    f"{prefix}{side}finger{k}",
                    f'<origin xyz="0 0 0.0584"/><axis xyz="0 {sign} 0"/>{mimic}',
                    '<limit lower="0" upper="0.04"/>',
                )
            )
            link = f"{prefix}{side}finger{k}"
    return out


@pytest.mark.parametrize("finger_joints", [1, 2])
def test_a_grippers_fingers_are_left_off_and_the_arm_ends_at_the_hand(finger_joints):
    text = _tree(
        *_arm_joints("panda_", "panda_link0", 7), *_hand("panda_", "panda_link7", finger_joints)
    )
    arm = parse_urdf(text)
    assert arm.dof == 7
    _same_fk(arm, parse_urdf(text, tip_link="panda_hand"))


@pytest.mark.parametrize(
    ("torso", "gripper", "tips"),
    [
        (0, False, "left_tool0, right_tool0"),
        (1, False, "left_tool0, right_tool0"),  # a torso joint before two arms is no hand
        (0, True, "left_hand, right_hand"),  # each arm's fingers folded into its hand
    ],
)
def test_two_arms_are_refused_naming_the_candidate_tips(torso, gripper, tips):
    joints = [_fixed("world-torso", "world", "torso_base")]
    joints += _arm_joints("torso_", "torso_base", torso)
    top = f"torso_link{torso}" if torso else "torso_base"
    for side in ("left", "right"):
        joints += _arm_joints(f"{side}_", top, 7)
        if gripper:
            joints += _hand(f"{side}_", f"{side}_link7", 1)
        else:
            joints.append(
                _fixed(f"{side}_flange-tool0", f"{side}_link7", f"{side}_tool0", "0 0 0.1")
            )
    text = _tree(*joints)
    with pytest.raises(ArmConfigError) as info:
        parse_urdf(text, source="t.urdf")
    assert info.value.field == "tip_link"
    moving = torso + 7 + int(gripper)
    assert f"branches at link {top!r} into 2 chains of {moving} moving joints" in str(info.value)
    assert f"set tip_link to one of: {tips}" in str(info.value)
    right = parse_urdf(text, tip_link=tips.split(", ")[1])
    assert [j.name for j in right.joints] == [f"torso_j{k + 1}" for k in range(torso)] + [
        f"right_j{k + 1}" for k in range(7)
    ]


def test_an_explicit_tip_link_still_wins_over_the_rules():
    text = _tree(*_arm_joints("panda_", "panda_link0", 7), *_hand("panda_", "panda_link7", 1))
    finger = parse_urdf(text, tip_link="panda_leftfinger0")
    assert [j.name for j in finger.joints][-2:] == ["panda_j7", "panda_finger_0_left"]
    tcp = parse_urdf(text, tip_link="panda_hand_tcp")
    hand = parse_urdf(text)
    offset = np.eye(4)
    offset[2, 3] = 10.34  # cm
    np.testing.assert_allclose(tcp.frames_array[-1], hand.frames_array[-1] @ offset, atol=1e-12)
    with pytest.raises(ArmConfigError, match="mimic"):
        parse_urdf(text, tip_link="panda_rightfinger0")
