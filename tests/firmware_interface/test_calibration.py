import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from firmware_interface.calibration import (
    TABLE2_RANGES_DEG,
    ArmCalibration,
    JointCalibration,
    calibration_from_ranges,
    default_calibration,
    round_half_up_us,
)
from firmware_interface.errors import (
    AngleOutOfRange,
    CalibrationError,
    ConfigurationError,
    NonFiniteAngle,
    PwmOutOfRange,
)


def theta2(**overrides):
    fields = dict(name="theta2", output=10, angle_min_deg=0.0, angle_max_deg=180.0)
    fields.update(overrides)
    return JointCalibration(**fields)


# --- golden values -------------------------------------------------------------------------


def test_default_calibration_matches_table2_on_outputs_9_to_14():
    cal = default_calibration()
    assert cal.outputs == (9, 10, 11, 12, 13, 14)
    assert [(j.angle_min_deg, j.angle_max_deg) for j in cal.joints] == list(TABLE2_RANGES_DEG)
    assert all(j.pwm_range_us == (1000, 2000) for j in cal.joints)
    assert [j.name for j in cal.joints] == [f"theta{i}" for i in range(1, 7)]


def test_golden_values_endpoints_and_middle():
    cal = default_calibration()
    assert cal.angles_to_pwm_us([-90, 0, -90, -90, -90, -70]) == {
        9: 1000,
        10: 1000,
        11: 1000,
        12: 1000,
        13: 1000,
        14: 1000,
    }
    assert cal.angles_to_pwm_us([90, 180, 90, 90, 90, 90]) == {
        9: 2000,
        10: 2000,
        11: 2000,
        12: 2000,
        13: 2000,
        14: 2000,
    }
    # θ6: -70…90 spans 160°, so 10° is the middle.
    assert cal.angles_to_pwm_us([0, 90, 0, 0, 0, 10]) == {
        9: 1500,
        10: 1500,
        11: 1500,
        12: 1500,
        13: 1500,
        14: 1500,
    }


def test_rounding_is_nearest_with_halves_up():
    assert round_half_up_us(1500.5) == 1501
    assert round_half_up_us(1500.4999) == 1500
    assert round_half_up_us(1499.5) == 1500
    joint = theta2()  # 180° over 1000 µs: 0.09° gives exactly 0.5 µs
    assert joint.angle_to_pwm_us(0.09) == 1001
    assert joint.angle_to_pwm_us(0.08) == 1000


def test_reversal_swaps_the_ends():
    joint = theta2(reversed=True)
    assert joint.angle_to_pwm_us(0.0) == 2000
    assert joint.angle_to_pwm_us(180.0) == 1000
    assert joint.angle_to_pwm_us(45.0) == 1750
    assert joint.pwm_us_to_angle_deg(1750) == pytest.approx(45.0)


def test_trim_shifts_and_refuses_rather_than_clamps():
    joint = theta2(trim_us=20)
    assert joint.angle_to_pwm_us(90.0) == 1520
    assert joint.pwm_us_to_angle_deg(1520) == pytest.approx(90.0)
    pattern = r"pwm_us=2020 outside \[1000, 2000\].*theta2.*output 10"
    with pytest.raises(PwmOutOfRange, match=pattern):
        joint.angle_to_pwm_us(180.0)


def test_mapped_pwm_says_where_a_refused_angle_lands():
    # What the daemon's config check quotes: the same mapping, without the range gate.
    joint = theta2(trim_us=20, reversed=True)
    assert joint.mapped_pwm_us(0.0) == 2020 and joint.mapped_pwm_us(180.0) == 1020
    assert joint.mapped_pwm_us(90.0) == joint.angle_to_pwm_us(90.0) == 1520
    with pytest.raises(AngleOutOfRange):
        joint.mapped_pwm_us(181.0)


def test_normalised_values_for_px4():
    joint = theta2()
    assert joint.pwm_us_to_normalized(1000) == -1.0
    assert joint.pwm_us_to_normalized(1500) == 0.0
    assert joint.pwm_us_to_normalized(2000) == 1.0


# --- refusals name joint, value and range ------------------------------------------------


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_non_finite_angles_are_refused(bad):
    with pytest.raises(NonFiniteAngle, match=r"theta2.*output 10"):
        theta2().angle_to_pwm_us(bad)


def test_angle_out_of_range_message_names_joint_value_and_range():
    with pytest.raises(AngleOutOfRange) as info:
        default_calibration().angles_to_pwm_us([0, 180.5, 0, 0, 0, 0])
    assert str(info.value) == (
        "angle_deg=180.5 outside [0.0, 180.0] for joint 'theta2' (servo output 10)"
    )


def test_non_numbers_are_refused():
    with pytest.raises(CalibrationError):
        theta2().angle_to_pwm_us("90")  # type: ignore[arg-type]
    with pytest.raises(CalibrationError):
        theta2().angle_to_pwm_us(True)  # type: ignore[arg-type]


def test_pwm_to_angle_refuses_out_of_range_and_nan():
    with pytest.raises(PwmOutOfRange, match=r"pwm_us=2001 outside \[1000, 2000\]"):
        theta2().pwm_us_to_angle_deg(2001)
    with pytest.raises(PwmOutOfRange):
        theta2().pwm_us_to_angle_deg(math.nan)


def test_check_pwm_refuses_floats_and_unknown_outputs():
    cal = default_calibration()
    with pytest.raises(PwmOutOfRange, match="not an integer"):
        cal.check_pwm_us({9: 1500.0})
    with pytest.raises(PwmOutOfRange, match="2210"):
        cal.check_pwm_us({9: 2210})
    with pytest.raises(ConfigurationError, match="output=3 is not calibrated"):
        cal.check_pwm_us({3: 1500})
    cal.check_pwm_us({9: 1000, 14: 2000})


def test_all_or_nothing_for_a_joint_vector():
    cal = default_calibration()
    with pytest.raises(ConfigurationError, match="got 5 joint angles, expected 6"):
        cal.angles_to_pwm_us([0, 90, 0, 0, 0])
    with pytest.raises(AngleOutOfRange, match="theta6"):
        cal.angles_to_pwm_us([0, 90, 0, 0, 0, -71])


def test_subset_by_name():
    cal = default_calibration(outputs=(1, 2, 3, 4, 5, 6))
    assert cal.angles_to_pwm_us({"theta2": 180, "theta6": -70}) == {2: 2000, 6: 1000}
    with pytest.raises(ConfigurationError, match="no joint named 'elbow'"):
        cal.angles_to_pwm_us({"elbow": 0})


@pytest.mark.parametrize(
    "overrides, pattern",
    [
        (dict(output=0), r"output: 0 outside \[1, 16\]"),
        (dict(output=17), r"output: 17 outside \[1, 16\]"),
        (dict(angle_min_deg=10.0, angle_max_deg=10.0), "must be below"),
        (dict(angle_min_deg=math.nan), "angle_min_deg: must be a finite number, got nan"),
        (dict(pwm_min_us=2000, pwm_max_us=1000), "must be below"),
        (dict(pwm_max_us=3000), r"pwm_max_us: 3000 outside \[500, 2500\] µs"),
        (dict(pwm_min_us=1000.5), "pwm_min_us: must be an integer, got 1000.5"),
        (dict(trim_us=600), r"trim_us: 600 outside \[-500, 500\] µs"),
        (dict(reversed=1), "reversed: must be true or false, got 1"),
    ],
)
def test_bad_joint_settings_are_refused(overrides, pattern):
    with pytest.raises(ConfigurationError, match=pattern):
        theta2(**overrides)


def test_arm_calibration_refuses_duplicates_and_mismatched_lengths():
    with pytest.raises(ConfigurationError, match=r"outputs must be unique, repeated: \[9\]"):
        ArmCalibration((theta2(output=9), theta2(name="other", output=9)))
    with pytest.raises(ConfigurationError, match="same length"):
        calibration_from_ranges(TABLE2_RANGES_DEG, outputs=(9, 10))
    with pytest.raises(ConfigurationError, match="unknown joint names"):
        calibration_from_ranges(TABLE2_RANGES_DEG, reversed_joints=("elbow",))


def test_calibration_from_ranges_passes_reversal_and_trim():
    cal = calibration_from_ranges(
        [(-45.0, 45.0), (0.0, 90.0)],
        outputs=(5, 6),
        names=("a", "b"),
        reversed_joints=("b",),
        trims_us={"a": -10},
    )
    assert cal.angles_to_pwm_us([0.0, 0.0]) == {5: 1490, 6: 2000}


# --- properties ---------------------------------------------------------------------------

any_float = st.floats(allow_nan=True, allow_infinity=True)
any_angle = st.one_of(any_float, st.integers(min_value=-(10**30), max_value=10**30))


@st.composite
def joints(draw):
    lo = draw(st.floats(min_value=-360.0, max_value=359.0))
    hi = draw(st.floats(min_value=lo, max_value=360.0).filter(lambda v: v > lo))
    pwm_min = draw(st.integers(min_value=500, max_value=2499))
    pwm_max = draw(st.integers(min_value=pwm_min + 1, max_value=2500))
    half = (pwm_max - pwm_min) // 2
    return JointCalibration(
        name="j",
        output=draw(st.integers(1, 16)),
        angle_min_deg=lo,
        angle_max_deg=hi,
        pwm_min_us=pwm_min,
        pwm_max_us=pwm_max,
        reversed=draw(st.booleans()),
        trim_us=draw(st.integers(-half, half)),
    )


@settings(max_examples=400)
@given(joint=joints(), angle=any_angle)
def test_no_input_ever_yields_pwm_outside_the_servo_range(joint, angle):
    try:
        pwm = joint.angle_to_pwm_us(angle)
    except CalibrationError:
        return
    assert isinstance(pwm, int)
    assert joint.pwm_min_us <= pwm <= joint.pwm_max_us


@settings(max_examples=300)
@given(joint=joints(), angle=any_angle)
def test_refusal_exactly_when_angle_is_bad_or_trim_pushes_it_out(joint, angle):
    in_range = (
        isinstance(angle, (int, float))
        and math.isfinite(angle)
        and joint.angle_min_deg <= angle <= joint.angle_max_deg
    )
    if not in_range:
        with pytest.raises((NonFiniteAngle, AngleOutOfRange)):
            joint.angle_to_pwm_us(angle)
    elif joint.trim_us == 0:
        joint.angle_to_pwm_us(angle)  # untrimmed: every in-range angle is accepted


@settings(max_examples=300)
@given(joint=joints(), fraction=st.floats(min_value=0.0, max_value=1.0))
def test_round_trip_angle_pwm_angle_within_half_a_microsecond(joint, fraction):
    span = joint.angle_max_deg - joint.angle_min_deg
    angle = min(joint.angle_max_deg, joint.angle_min_deg + fraction * span)
    try:
        pwm = joint.angle_to_pwm_us(angle)
    except PwmOutOfRange:
        assert joint.trim_us != 0
        return
    back = joint.pwm_us_to_angle_deg(pwm)
    step_deg = span / (joint.pwm_max_us - joint.pwm_min_us)
    assert abs(back - angle) <= 0.5 * step_deg + 1e-9 * max(1.0, abs(angle))


@settings(max_examples=200)
@given(joint=joints(), pwm=st.integers(min_value=-(10**6), max_value=10**6))
def test_pwm_to_normalized_stays_in_unit_interval_or_is_refused(joint, pwm):
    try:
        value = joint.pwm_us_to_normalized(pwm)
    except PwmOutOfRange:
        assert not joint.pwm_min_us <= pwm <= joint.pwm_max_us
        return
    assert -1.0 <= value <= 1.0
