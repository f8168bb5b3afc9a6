"""The papers' numbers are defined once in companion.papers.constants; the copies that other
packages must keep (they may not import papers) are checked against it here."""

from __future__ import annotations

import math

from companion.daemon.demo import PAPER_TARGET_G
from companion.kinematics import Arm
from companion.papers import constants
from firmware_interface.calibration import TABLE2_RANGES_DEG, default_calibration


def test_default_arm_file_has_the_table2_ranges():
    arm = Arm.default()
    ranges = [(math.degrees(j.min_rad), math.degrees(j.max_rad)) for j in arm.joints]
    assert ranges == [tuple(r) for r in constants.TABLE2_RANGES_DEG]


def test_default_calibration_has_the_table2_ranges():
    assert tuple(TABLE2_RANGES_DEG) == constants.TABLE2_RANGES_DEG
    cal = default_calibration()
    assert [(j.angle_min_deg, j.angle_max_deg) for j in cal.joints] == list(
        constants.TABLE2_RANGES_DEG
    )


def test_the_demo_refuses_the_papers_target_g():
    assert PAPER_TARGET_G == constants.TARGET_G


def test_table5_and_table7_rows_are_complete_and_in_order():
    assert [row[0] for row in constants.TABLE5_DE] == list(range(1, 15))
    assert [row[0] for row in constants.TABLE7_MSFLA] == list(range(1, 21))
    # Table 5 test 9 is the authors' pick, the DE defaults.
    test9 = constants.TABLE5_DE[8]
    assert (test9[1], test9[2]) == (constants.DE_POP_SIZE, constants.DE_GENERATIONS)


def test_printed_poses_parse_and_a_bad_one_is_named():
    import pytest

    assert constants.parse_pose("(-20, 3, 40, -1.40416e-9, 10, 15)").yaw_deg == 15.0
    with pytest.raises(ValueError, match="x, y, z"):
        constants.parse_pose("(-20, 3, forty, 0, 10, 15)")
    assert len(constants.TABLE5_TOTAL_ERROR) == 14 and len(constants.TABLE7_TOTAL_ERROR) == 20


def test_the_modified_arm_file_has_the_table1_links():
    arm = Arm.from_package_file("paper_arm_modified.toml")
    l0, l1, l2, l3, l4, l5, l6 = constants.TABLE1_LINK_LENGTHS_CM
    assert [j.a_cm for j in arm.joints] == [l0, l1, l2, 0.0, 0.0, l5]
    assert [j.d_cm for j in arm.joints] == [0.0, 0.0, 0.0, l3 + l4, 0.0, 0.0]
    assert arm.tool is not None and arm.tool[0][3] == l6
