"""Arm files: the shipped default, the schema, and every kind of malformed file."""

from __future__ import annotations

import math
from importlib import resources

import numpy as np
import pytest

from companion.errors import ArmConfigError, JointLimitError
from companion.kinematics import DHConvention
from companion.kinematics.arm import Arm, Pose

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
