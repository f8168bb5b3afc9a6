"""Servo positions → joint angles (the simulator's own servo model) → hand pose through FK.

The first part checks the simulator's model on its own, with golden values worked out by hand.
The last part cross-checks it against the daemon's calibration (``firmware_interface``): only
this test may import both; ``sim_servo`` itself never imports the daemon's code.
"""

import math

import pytest
from hypothesis import given
from hypothesis import strategies as st

from companion.kinematics import Arm
from firmware_interface.calibration import calibration_from_ranges, default_calibration
from firmware_interface.errors import ConfigurationError, PwmOutOfRange
from sim_servo.config import ArmConfig
from sim_servo.errors import ServoPwmOutOfRange, SimConfigError
from sim_servo.hand import HandModel, JointServo

NAMES = ("theta1", "theta2", "theta3", "theta4", "theta5", "theta6")
#: The paper arm's joint limits in degrees (Table 2), written out here as golden values.
PAPER_LIMITS_DEG = ((-90, 90), (0, 180), (-90, 90), (-90, 90), (-90, 90), (-70, 90))
CENTRE_US = {output: 1500.0 for output in (9, 10, 11, 12, 13, 14)}


def model(**kwargs) -> HandModel:
    return HandModel.from_config(ArmConfig(**kwargs))


def servo(**kwargs) -> JointServo:
    """A ±90° joint on output 9 over 1000–2000 µs, with ``kwargs`` changed."""
    fields = dict(
        name="theta1",
        output=9,
        pwm_min_us=1000,
        pwm_max_us=2000,
        angle_min_deg=-90.0,
        angle_max_deg=90.0,
    )
    return JointServo(**(fields | kwargs))


# -- one joint -----------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("kwargs", "pwm_us", "angle_deg"),
    [
        ({}, 1000, -90.0),
        ({}, 1500, 0.0),
        ({}, 2000, 90.0),
        ({}, 1250, -45.0),
        ({"angle_min_deg": -70.0}, 1000, -70.0),
        ({"angle_min_deg": -70.0}, 1500, 10.0),
        ({"angle_min_deg": 0.0, "angle_max_deg": 180.0}, 1500, 90.0),
        ({"pwm_min_us": 1100, "pwm_max_us": 1900}, 1100, -90.0),
        ({"pwm_min_us": 1100, "pwm_max_us": 1900}, 1700, 45.0),
        ({"reversed": True}, 1000, 90.0),
        ({"reversed": True}, 1500, 0.0),
        ({"reversed": True}, 2000, -90.0),
        ({"reversed": True}, 1750, -45.0),
        # A trim shifts the sweep: the lower limit is now at 1100 µs, the middle at 1600 µs …
        ({"trim_us": 100}, 1100, -90.0),
        ({"trim_us": 100}, 1600, 0.0),
        # … and the ends of the PWM range are beyond the limits, reported as they are.
        ({"trim_us": 100}, 2000, 72.0),
        ({"trim_us": 100}, 1000, -108.0),
        ({"trim_us": -100}, 1400, 0.0),
        ({"trim_us": -100}, 1900, 90.0),
        ({"trim_us": 100, "reversed": True}, 1100, 90.0),
        ({"trim_us": 100, "reversed": True}, 1600, 0.0),
    ],
)
def test_angle_golden_values(kwargs, pwm_us, angle_deg):
    assert servo(**kwargs).angle_deg(pwm_us) == pytest.approx(angle_deg, abs=1e-12)


@pytest.mark.parametrize("pwm_us", [999.999, 2000.001, 0, 2500, math.nan, math.inf])
def test_pwm_outside_the_range_has_no_angle(pwm_us):
    with pytest.raises(ServoPwmOutOfRange) as info:
        servo(trim_us=100).angle_deg(pwm_us)
    assert str(info.value) == (
        f"pwm_us={pwm_us!r} outside [1000, 2000] for joint 'theta1' (servo output 9)"
    )


@given(st.floats(1000.0, 2000.0), st.booleans(), st.integers(-500, 500))
def test_angle_is_linear_in_pwm(pwm_us, reversed_, trim_us):
    joint = servo(reversed=reversed_, trim_us=trim_us)
    slope_deg_per_us = -0.18 if reversed_ else 0.18
    expected_deg = joint.angle_deg(1500.0) + slope_deg_per_us * (pwm_us - 1500.0)
    assert joint.angle_deg(pwm_us) == pytest.approx(expected_deg, abs=1e-9)


def test_deg_per_us_is_the_joint_span_over_the_pwm_span():
    assert servo().deg_per_us == pytest.approx(0.18)
    assert servo(reversed=True, trim_us=50).deg_per_us == pytest.approx(0.18)
    assert servo(pwm_min_us=1100, pwm_max_us=1900).deg_per_us == pytest.approx(180 / 800)


# -- the whole arm -------------------------------------------------------------------------------


def test_default_model_is_the_paper_arm_on_outputs_9_to_14():
    hand = model()
    assert hand.outputs == (9, 10, 11, 12, 13, 14)
    assert [j.name for j in hand.joints] == list(NAMES)
    for joint, (low_deg, high_deg) in zip(hand.joints, PAPER_LIMITS_DEG, strict=True):
        assert (joint.angle_min_deg, joint.angle_max_deg) == pytest.approx((low_deg, high_deg))
        assert (joint.pwm_min_us, joint.pwm_max_us) == (1000, 2000)
        assert not joint.reversed and joint.trim_us == 0


def test_centred_servos_put_every_joint_mid_range():
    state = model().state(CENTRE_US)
    assert state.error is None
    mid_deg = [0.0, 90.0, 0.0, 0.0, 0.0, 10.0]
    assert list(state.angles_deg) == list(NAMES)
    assert list(state.angles_deg.values()) == pytest.approx(mid_deg)
    expected = Arm.default().fk(mid_deg)
    assert state.pose.position_cm == pytest.approx(expected.position_cm)
    assert state.as_dict()["pose"]["z_cm"] == pytest.approx(expected.z_cm)


def test_servos_at_the_ends_put_the_joints_at_their_limits():
    hand = model()
    low = hand.state(dict.fromkeys(hand.outputs, 1000.0)).angles_deg
    high = hand.state(dict.fromkeys(hand.outputs, 2000.0)).angles_deg
    assert list(low.values()) == pytest.approx([lo for lo, _ in PAPER_LIMITS_DEG])
    assert list(high.values()) == pytest.approx([hi for _, hi in PAPER_LIMITS_DEG])


def test_position_outside_the_pwm_range_has_no_pose():
    positions = dict(CENTRE_US)
    positions[12] = 2100.0
    state = model().state(positions)
    assert state.pose is None and state.angles_deg is None
    assert state.error == "pwm_us=2100.0 outside [1000, 2000] for joint 'theta4' (servo output 12)"
    assert state.as_dict() == {"angles_deg": None, "pose": None, "error": state.error}


def test_the_first_joint_out_of_range_is_named():
    positions = dict(CENTRE_US)
    positions[11], positions[13] = 990.0, 2010.0
    assert "joint 'theta3' (servo output 11)" in model().state(positions).error


def test_deg_per_us_by_output():
    hand = model()
    assert hand.deg_per_us(9) == pytest.approx(0.18)
    assert hand.deg_per_us(14) == pytest.approx(160 / 1000)
    with pytest.raises(KeyError, match="output 1 drives no joint"):
        hand.deg_per_us(1)


def test_reversed_joint_and_custom_outputs():
    hand = model(outputs=(5, 6, 7, 8, 9, 10), reversed_joints=("theta1",))
    state = hand.state({5: 1000.0, 6: 1500.0, 7: 1500.0, 8: 1500.0, 9: 1500.0, 10: 1500.0})
    assert state.angles_deg["theta1"] == pytest.approx(90.0)
    assert state.angles_deg["theta2"] == pytest.approx(90.0)


def test_trims_from_the_config():
    hand = model(pwm_min_us=1100, pwm_max_us=1900, trims_us={"theta2": 40, "theta6": -20})
    positions = dict(CENTRE_US)
    positions[10], positions[14] = 1540.0, 1480.0
    angles = hand.state(positions).angles_deg
    assert angles["theta2"] == pytest.approx(90.0)
    assert angles["theta6"] == pytest.approx(10.0)
    assert angles["theta1"] == pytest.approx(0.0)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        (
            {"reversed_joints": ("theta7",)},
            "arm reversed names unknown joints ['theta7']; the arm's joints are ['theta1',",
        ),
        (
            {"trims_us": {"q1": 10}},
            "arm trims_us names unknown joints ['q1']; the arm's joints are ['theta1',",
        ),
        ({"outputs": (9, 10)}, "arm outputs=[9, 10] name 2 outputs; arm 'paper-6dof' has 6"),
        ({"arm_file": "/nonexistent/arm.toml"}, "cannot load arm"),
    ],
)
def test_config_errors_name_the_field(kwargs, message):
    with pytest.raises(SimConfigError) as info:
        model(**kwargs)
    assert message in str(info.value)


# -- cross-check against the daemon's calibration ------------------------------------------------


def test_agrees_with_the_daemons_default_calibration_on_every_whole_us():
    hand, calibration = model(), default_calibration()
    for joint, daemon_joint in zip(hand.joints, calibration.joints, strict=True):
        assert joint.output == daemon_joint.output
        for pwm_us in range(1000, 2001):
            assert joint.angle_deg(pwm_us) == pytest.approx(
                daemon_joint.pwm_us_to_angle_deg(pwm_us), abs=1e-9
            )


@pytest.mark.parametrize(
    "q_deg",
    [
        [0.0, 90.0, 0.0, 0.0, 0.0, 0.0],
        [30.0, 120.0, -45.0, 20.0, -10.0, 45.0],
        [-90.0, 0.0, 90.0, -90.0, 90.0, -70.0],
    ],
)
def test_the_daemons_pwm_puts_the_hand_where_it_aimed(q_deg):
    state = model().state(default_calibration().angles_to_pwm_us(q_deg))
    assert state.error is None
    # Rounding to whole µs costs at most half a µs of travel: 0.09° on a 180° joint.
    assert list(state.angles_deg.values()) == pytest.approx(q_deg, abs=0.5 * 0.18 + 1e-9)
    assert math.dist(state.pose.position_cm, Arm.default().fk(q_deg).position_cm) < 0.5


@st.composite
def arm_configs(draw) -> ArmConfig:
    """A valid arm configuration: any PWM range, outputs, reversed joints and trims."""
    pwm_min_us = draw(st.integers(500, 2499))
    pwm_max_us = draw(st.integers(pwm_min_us + 1, 2500))
    half_span_us = (pwm_max_us - pwm_min_us) // 2
    return ArmConfig(
        outputs=tuple(draw(st.permutations(range(1, 17)))[:6]),
        pwm_min_us=pwm_min_us,
        pwm_max_us=pwm_max_us,
        reversed_joints=tuple(sorted(draw(st.sets(st.sampled_from(NAMES))))),
        trims_us=draw(
            st.dictionaries(st.sampled_from(NAMES), st.integers(-half_span_us, half_span_us))
        ),
    )


def daemon_calibration(config: ArmConfig):
    """The daemon's calibration for the same arm, ranges, outputs, reversals and trims."""
    arm = Arm.default()
    return calibration_from_ranges(
        [(math.degrees(j.min_rad), math.degrees(j.max_rad)) for j in arm.joints],
        outputs=config.outputs,
        pwm_min_us=config.pwm_min_us,
        pwm_max_us=config.pwm_max_us,
        reversed_joints=config.reversed_joints,
        trims_us=config.trims_us,
    )


@given(arm_configs(), st.integers(0, 5), st.floats(-0.1, 1.1))
def test_agrees_with_the_daemons_calibration_across_each_range(config, index, where):
    """Same angle for any PWM in range (``where`` 0…1 across it), and no angle outside it."""
    joint = HandModel.from_config(config).joints[index]
    daemon_joint = daemon_calibration(config).for_output(joint.output)
    assert daemon_joint.name == joint.name
    pwm_us = config.pwm_min_us + where * (config.pwm_max_us - config.pwm_min_us)
    try:
        daemon_deg = daemon_joint.pwm_us_to_angle_deg(pwm_us)
    except PwmOutOfRange:
        with pytest.raises(ServoPwmOutOfRange):
            joint.angle_deg(pwm_us)
    else:
        assert joint.angle_deg(pwm_us) == pytest.approx(daemon_deg, rel=1e-12, abs=1e-9)


@given(st.integers(400, 2600), st.integers(400, 2600), st.integers(-1300, 1300))
def test_accepts_the_pwm_ranges_and_trims_the_daemon_accepts(pwm_min_us, pwm_max_us, trim_us):
    try:
        calibration_from_ranges(
            PAPER_LIMITS_DEG,
            pwm_min_us=pwm_min_us,
            pwm_max_us=pwm_max_us,
            trims_us={"theta1": trim_us},
        )
    except ConfigurationError:
        daemon_accepts = False
    else:
        daemon_accepts = True
    try:
        model(pwm_min_us=pwm_min_us, pwm_max_us=pwm_max_us, trims_us={"theta1": trim_us})
    except SimConfigError:
        sim_accepts = False
    else:
        sim_accepts = True
    assert sim_accepts == daemon_accepts
