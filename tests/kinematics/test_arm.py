"""Arm files: the shipped default, the schema, and every kind of malformed file."""

from __future__ import annotations

import json
import math
from importlib import resources
from pathlib import Path

import numpy as np
import pytest

from companion.errors import ArmConfigError, JointLimitError, KinematicsError
from companion.kinematics import DHConvention, rpy_to_matrix
from companion.kinematics.arm import Arm, JointKind, Pose

PAPER_TOML = (resources.files("companion.kinematics") / "arms" / "paper_arm.toml").read_text()


def test_default_arm_is_the_papers_table():
    arm = Arm.default()
    assert arm.convention is DHConvention.STANDARD
    assert arm.dof == 6
    np.testing.assert_allclose([j.a_cm for j in arm.joints], [6.4, 30.2, 0, 0, 5.3, 5.6])
    np.testing.assert_allclose([j.d_cm for j in arm.joints], [0, 0, 0, 23.5, 0, -2])
    np.testing.assert_allclose(np.degrees(arm.lower_rad), [-90, 0, -90, -90, -90, -70])
    np.testing.assert_allclose(np.degrees(arm.upper_rad), [90, 180, 90, 90, 90, 90])


def test_from_toml_reads_a_file(tmp_path):
    path = tmp_path / "arm.toml"
    path.write_text(PAPER_TOML)
    arm = Arm.from_toml(path, dof=6)
    assert arm == Arm.default()


def test_length_unit_is_converted_to_cm(tmp_path):
    # The same arm written in millimetres and metres gives the same hand pose.
    mm = PAPER_TOML.replace('length_unit = "cm"', 'length_unit = "mm"')
    for key, value in (("a", "6.4"), ("a", "30.2"), ("a", "5.3"), ("a", "5.6"), ("d", "23.5")):
        mm = mm.replace(f"{key} = {value}\n", f"{key} = {float(value) * 10}\n")
    mm = mm.replace("d = -2\n", "d = -20\n")
    path = tmp_path / "mm.toml"
    path.write_text(mm)
    q = [10, 40, -20, 30, 15, -5]
    assert Arm.from_toml(path).fk(q).as_tuple() == pytest.approx(Arm.default().fk(q).as_tuple())


def test_tool_transform_moves_the_hand(tmp_path):
    path = tmp_path / "tool.toml"
    path.write_text(PAPER_TOML + "\n[tool]\nxyz = [0, 0, 10]\nrpy_deg = [0, 0, 90]\n")
    arm = Arm.from_toml(path)
    q = np.radians([0, 90, 0, 0, 0, 0])  # hand frame = base frame at (71, 0, -2)
    t = arm.fk_matrix(q)
    np.testing.assert_allclose(t[:3, 3], [71.0, 0.0, 8.0], atol=1e-12)
    np.testing.assert_allclose(t[:3, 0], [0, 1, 0], atol=1e-12)


def _write(tmp_path, text):
    path = tmp_path / "bad.toml"
    path.write_text(text)
    return path


MALFORMED = [
    # (description, text transform, expected field, expected words in the message)
    ("missing field", lambda t: t.replace("a = 30.2\n", "", 1), "joint[2].a", "missing"),
    (
        "min >= max",
        lambda t: t.replace("min_deg = 0\nmax_deg = 180", "min_deg = 180\nmax_deg = 0"),
        "joint[2].min_deg",
        "less than",
    ),
    ("NaN", lambda t: t.replace("d = 23.5", "d = nan"), "joint[4].d", "finite"),
    (
        "infinite",
        lambda t: t.replace("max_deg = 90", "max_deg = inf", 1),
        "joint[1].max_deg",
        "finite",
    ),
    (
        "unknown convention",
        lambda t: t.replace('"standard"', '"craig"'),
        "convention",
        "standard, modified",
    ),
    ("wrong joint count", lambda t: t.replace("dof = 6", "dof = 5"), "joint", "dof = 5"),
    ("unknown unit", lambda t: t.replace('"cm"', '"inch"'), "length_unit", "mm, cm, m"),
    (
        "typo in a field",
        lambda t: t.replace("offset_deg = -90", "ofset_deg = -90"),
        "joint[2].ofset_deg",
        "unknown field",
    ),
    ("string for number", lambda t: t.replace("a = 6.4", 'a = "6.4"'), "joint[1].a", "number"),
    ("not TOML", lambda t: t + "\n[[joint\n", "<file>", "not valid TOML"),
    (
        "no joints",
        lambda t: t[: t.index("[[joint]]")].replace("dof = 6\n", ""),
        "joint",
        "array of tables",
    ),
    ("bad tool", lambda t: t + "\n[tool]\nxyz = [1, 2]\n", "tool.xyz", "3 numbers"),
]


@pytest.mark.parametrize(
    ("desc", "edit", "field", "words"), MALFORMED, ids=[m[0] for m in MALFORMED]
)
def test_malformed_file_names_file_field_and_allowed_values(tmp_path, desc, edit, field, words):
    path = _write(tmp_path, edit(PAPER_TOML))
    with pytest.raises(ArmConfigError) as info:
        Arm.from_toml(path)
    assert info.value.field == field
    assert info.value.source == str(path)
    assert words in str(info.value)
    assert str(path) in str(info.value)


def test_required_dof_is_checked(tmp_path):
    with pytest.raises(ArmConfigError, match="this use needs 7"):
        Arm.from_toml(_write(tmp_path, PAPER_TOML), dof=7)


def test_missing_file_is_a_config_error(tmp_path):
    with pytest.raises(ArmConfigError, match="cannot read"):
        Arm.from_toml(tmp_path / "nope.toml")


def test_config_error_is_also_value_error(tmp_path):
    with pytest.raises(ValueError):
        Arm.from_toml(_write(tmp_path, PAPER_TOML.replace("dof = 6", "dof = 0")))


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf, "x", None])
def test_pose_refuses_non_finite_fields(bad):
    with pytest.raises(ValueError, match="Pose.pitch_deg"):
        Pose(1, 2, 3, 0, bad, 0)


def test_pose_from_sequence_checks_length():
    with pytest.raises(ValueError, match="6 values"):
        Pose.from_sequence([1, 2, 3])
    assert Pose.from_sequence([1, 2, 3, 4, 5, 6]).yaw_deg == 6.0


def test_pose_matrix_round_trip():
    pose = Pose(-20, 3, 40, 5, 10, 15)
    back = Pose.from_matrix(pose.as_matrix())
    assert back.as_tuple() == pytest.approx(pose.as_tuple(), abs=1e-12)


def test_check_limits_names_joint_value_and_range():
    arm = Arm.default()
    arm.check_limits([0, 90, 0, 0, 0, 0])
    with pytest.raises(JointLimitError, match=r"joint q6: angle_deg=-80 outside \[-70, 90\]"):
        arm.check_limits([0, 90, 0, 0, 0, -80])
    with pytest.raises(JointLimitError, match="q2"):
        arm.check_limits([0, math.nan, 0, 0, 0, 0])


def test_within_limits_and_random_q():
    arm = Arm.default()
    q = arm.random_q_rad(np.random.default_rng(0), 1000)
    assert arm.within_limits(q).all()
    q[3, 1] = -0.1
    assert not arm.within_limits(q)[3]


@pytest.mark.parametrize(
    ("values", "field"),
    [
        (("45", 10, 20, 0, 45, 0), "x_cm"),  # float() would take the text
        ((45, 10, 20, 0, b"4", 0), "pitch_deg"),
        ((45, 10, True, 0, 45, 0), "z_cm"),
        ((45, 10, 20, 0, 45, None), "yaw_deg"),
        ((45, 10**400, 20, 0, 45, 0), "y_cm"),  # OverflowError, not ValueError, before
        ((45, 10, 20, -(10**400), 45, 0), "roll_deg"),
    ],
)
def test_pose_field_that_is_not_a_finite_number_is_named(values, field):
    with pytest.raises(ValueError, match=f"Pose.{field}="):
        Pose(*values)


def test_pose_takes_numpy_numbers():
    pose = Pose(*np.arange(6, dtype=np.float32))
    assert pose.as_tuple() == (0.0, 1.0, 2.0, 3.0, 4.0, 5.0)
    assert Pose(*np.arange(6)).x_cm == 0.0


# -- the general arm model: rtb's arms, prismatic joints, base, direction, wide ranges -------------

RTB_FK = json.loads((Path(__file__).parent / "data" / "rtb_fk.json").read_text())


@pytest.mark.parametrize("name", sorted(RTB_FK["arms"]))
def test_arm_file_matches_roboticstoolbox_fk(name):
    # References written by bench/arm_references.py from rtb's DH models (metres).
    arm = Arm.from_package_file(f"{name}.toml")
    for case in RTB_FK["arms"][name]:
        t = arm.fk_matrix(case["q"])
        t[:3, 3] /= 100.0
        np.testing.assert_allclose(t, case["T"], rtol=0, atol=1e-9)


def test_puma560_keeps_its_full_range():
    arm = Arm.from_package_file("puma560.toml")
    assert np.degrees(arm.upper_q[5] - arm.lower_q[5]) == pytest.approx(532.0, abs=0.01)


def test_stanford_prismatic_joint_has_limits_in_cm():
    arm = Arm.from_package_file("stanford.toml")
    joint = arm.joints[2]
    assert joint.kind is JointKind.PRISMATIC
    assert (joint.lower, joint.upper) == pytest.approx((30.48, 127.0))
    q = np.zeros(6)
    q[2] = 50.0
    t0 = arm.fk_matrix(q)
    q[2] = 60.0
    moved = arm.fk_matrix(q)[:3, 3] - t0[:3, 3]
    assert np.linalg.norm(moved) == pytest.approx(10.0)
    with pytest.raises(KinematicsError, match="joint q3 is prismatic"):
        arm.lower_rad  # noqa: B018
    with pytest.raises(JointLimitError, match=r"joint q3: position_cm=20"):
        arm.check_limits([0, 0, 20, 0, 0, 0])


def test_direction_minus_one_negates_the_joint(tmp_path):
    flipped = PAPER_TOML.replace('name = "q3"\n', 'name = "q3"\ndirection = -1\n')
    arm = Arm.from_toml(_write(tmp_path, flipped))
    q = np.radians([10, 40, -20, 30, 15, -5])
    q_neg = q.copy()
    q_neg[2] = -q[2]
    np.testing.assert_allclose(arm.fk_matrix(q), Arm.default().fk_matrix(q_neg), atol=1e-12)


def test_bad_direction_is_named(tmp_path):
    text = PAPER_TOML.replace('name = "q2"\n', 'name = "q2"\ndirection = 0\n')
    with pytest.raises(ArmConfigError) as info:
        Arm.from_toml(_write(tmp_path, text))
    assert info.value.field == "joint[2].direction"


def test_base_transform_moves_the_whole_arm(tmp_path):
    text = PAPER_TOML + "\n[base]\nxyz = [1, 2, 3]\nrpy_deg = [180, 0, 90]\n"
    arm = Arm.from_toml(_write(tmp_path, text))
    q = np.radians([10, 40, -20, 30, 15, -5])
    base = np.eye(4)
    base[:3, :3] = rpy_to_matrix(np.pi, 0.0, np.pi / 2)
    base[:3, 3] = (1, 2, 3)
    np.testing.assert_allclose(arm.fk_matrix(q), base @ Arm.default().fk_matrix(q), atol=1e-12)


def test_range_beyond_a_turn_is_taken(tmp_path):
    text = PAPER_TOML.replace("min_deg = -70\nmax_deg = 90", "min_deg = -400\nmax_deg = 400")
    arm = Arm.from_toml(_write(tmp_path, text))
    assert np.degrees(arm.upper_q[5]) == pytest.approx(400.0)
    np.testing.assert_allclose(
        arm.fk_matrix(np.radians([0, 90, 0, 0, 0, 370])),
        arm.fk_matrix(np.radians([0, 90, 0, 0, 0, 10])),
        atol=1e-12,
    )


# Finite bounds on every number of an arm file (the reasons are at LENGTH_LIMIT_CM,
# ANGLE_LIMIT_DEG and JOINT_LIMIT_DEG in arm.py): each is refused naming field and range.
ABSURD = [
    ("a = 30.2\n", "a = 1e308\n", "joint[2].a", "1e+308 outside [-10000, 10000]"),
    ("a = 30.2\n", "a = -10000.5\n", "joint[2].a", "-10000.5 outside [-10000, 10000]"),
    ("d = 0\noffset_deg = -90", "d = 1e6\noffset_deg = -90", "joint[2].d", "outside"),
    ("alpha_deg = 0\n", "alpha_deg = 1e308\n", "joint[2].alpha_deg", "outside [-360, 360]"),
    ("offset_deg = -90\n", "offset_deg = 361\n", "joint[2].offset_deg", "361 outside [-360, 360]"),
    ("min_deg = 0\n", "min_deg = -3601\n", "joint[2].min_deg", "-3601 outside [-3600, 3600]"),
    ("max_deg = 180\n", "max_deg = 1e308\n", "joint[2].max_deg", "outside [-3600, 3600]"),
    ("link_radius = 2.5\n", "link_radius = 1e308\n", "link_radius", "outside (0, 10000]"),
    ("link_radius = 3.0\n", "link_radius = 2e4\n", "joint[3].link_radius", "outside (0, 10000]"),
]


@pytest.mark.parametrize(("old", "new", "field", "words"), ABSURD, ids=[a[2] for a in ABSURD])
def test_absurd_numbers_in_an_arm_file_are_refused_naming_field_and_range(
    tmp_path, old, new, field, words
):
    assert old in PAPER_TOML
    with pytest.raises(ArmConfigError) as info:
        Arm.from_toml(_write(tmp_path, PAPER_TOML.replace(old, new, 1)))
    assert info.value.field == field, str(info.value)
    assert words in info.value.problem, str(info.value)


def test_absurd_base_tool_and_capsule_lengths_are_refused():
    data = {
        "convention": "standard",
        "joint": [{"alpha_deg": 0, "a": 10, "d": 0, "min_deg": -90, "max_deg": 90}],
    }
    Arm.from_dict({**data, "base": {"xyz": [0, 0, 9999]}})
    for extra, field in (
        ({"base": {"xyz": [0, 0, 1e308]}}, "base.xyz[2]"),
        ({"tool": {"rpy_deg": [0, 720, 0]}}, "tool.rpy_deg[1]"),
    ):
        with pytest.raises(ArmConfigError) as info:
            Arm.from_dict({**data, **extra})
        assert info.value.field == field and "outside" in info.value.problem, str(info.value)
    capsule = {"from": [0, 0, 0], "to": [1e308, 0, 0], "radius": 1}
    row = {**data["joint"][0], "capsules": [capsule]}
    with pytest.raises(ArmConfigError) as info:
        Arm.from_dict({**data, "joint": [row]})
    assert info.value.field == "joint[1].capsules[0].to[0]", str(info.value)
    assert "outside [-10000, 10000]" in info.value.problem


def test_a_prismatic_limit_is_bounded_in_the_files_unit():
    joint = {"type": "prismatic", "alpha_deg": 0, "a": 0, "min": 0, "max": 101}
    data = {"convention": "standard", "length_unit": "m", "joint": [joint]}
    with pytest.raises(ArmConfigError) as info:
        Arm.from_dict(data)
    assert info.value.field == "joint[1].max" and "101 outside [-100, 100]" in str(info.value)
    joint["max"] = 100
    assert Arm.from_dict(data).joints[0].upper == 10_000.0  # cm


@pytest.mark.parametrize(
    ("edit", "field"),
    [
        (lambda t: t.replace('name = "q2"\n', 'name = "q2"\ntype = "slider"\n'), "joint[2].type"),
        # a prismatic joint's limits are min/max in the length unit, not min_deg/max_deg
        (lambda t: t.replace('name = "q2"\n', 'name = "q2"\ntype = "prismatic"\n'), "joint[2].d"),
    ],
)
def test_joint_type_errors_name_the_field(tmp_path, edit, field):
    with pytest.raises(ArmConfigError) as info:
        Arm.from_toml(_write(tmp_path, edit(PAPER_TOML)))
    assert info.value.field == field


# -- link shapes (collision capsules) -------------------------------------------------------------


def test_default_arm_links_are_capsules_between_joint_origins():
    arm = Arm.default()
    assert arm.has_shapes and len(arm.link_shapes) == 6
    radii = [cap.radius_cm for shapes in arm.link_shapes for cap in shapes]
    assert radii == [2.5, 2.5, 3.0, 2.5, 2.5, 3.0]
    # Each default capsule ends where the next joint's frame starts (the hand, for q6).
    q = np.radians([[20, 60, -30, 10, 40, -20]])
    axes, hand = arm.joint_frames(q)
    for i, (cap,) in enumerate(arm.link_shapes):
        nxt = axes[0, i + 1] if i + 1 < arm.dof else hand[0]
        link = nxt @ np.linalg.inv(arm.frames_array[i + 1])
        np.testing.assert_allclose(link[:3, 3], axes[0, i][:3, 3], atol=1e-12)  # on the axis
        np.testing.assert_allclose(link[:3, :3] @ cap.to_cm + link[:3, 3], nxt[:3, 3], atol=1e-9)


def test_explicit_capsules_and_units(tmp_path):
    text = PAPER_TOML.replace('length_unit = "cm"', 'length_unit = "mm"').replace(
        "link_radius = 3.0\n",
        "capsules = [{from = [0, 0, -10], to = [0, 0, 10], radius = 30},"
        " {from = [0, 0, 0], to = [50, 0, 0], radius = 5}]\n",
        1,
    )
    arm = Arm.from_toml(_write(tmp_path, text))
    caps = arm.link_shapes[2]
    assert [c.radius_cm for c in caps] == [3.0, 0.5]
    assert caps[0].from_cm == (0.0, 0.0, -1.0) and caps[1].to_cm == (5.0, 0.0, 0.0)
    assert arm.link_shapes[1][0].radius_cm == 0.25  # link_radius = 2.5 read as mm


def test_capsules_empty_list_leaves_a_link_bare_and_no_radius_no_shapes(tmp_path):
    bare = PAPER_TOML.replace("link_radius = 3.0\n", "capsules = []\n", 1)
    assert Arm.from_toml(_write(tmp_path, bare)).link_shapes[2] == ()
    none = "\n".join(line for line in PAPER_TOML.splitlines() if "link_radius" not in line)
    arm = Arm.from_toml(_write(tmp_path, none))
    assert arm.link_shapes == () and not arm.has_shapes


@pytest.mark.parametrize(
    ("edit", "field"),
    [
        (lambda t: t.replace("link_radius = 2.5", "link_radius = -1"), "link_radius"),
        (lambda t: t.replace("link_radius = 3.0", "link_radius = 0", 1), "joint[3].link_radius"),
        (
            lambda t: t.replace(
                "link_radius = 3.0", "capsules = [{from = [0, 0], to = [0, 0, 1]}]"
            ),
            "joint[3].capsules[0].from",
        ),
        (
            lambda t: t.replace(
                "link_radius = 3.0",
                "capsules = [{from = [0,0,0], to = [0,0,1], radius = 1, r = 2}]",
            ),
            "joint[3].capsules[0].r",
        ),
        (
            lambda t: t.replace("link_radius = 3.0", 'capsules = "big"', 1),
            "joint[3].capsules",
        ),
        (
            lambda t: t.replace("link_radius = 3.0", "link_radius = 3.0\ncapsules = []", 1),
            "joint[3].link_radius",
        ),
    ],
)
def test_shape_errors_name_the_joint_and_field(tmp_path, edit, field):
    with pytest.raises(ArmConfigError) as info:
        Arm.from_toml(_write(tmp_path, edit(PAPER_TOML)))
    assert info.value.field == field
