"""Servo positions → joint angles through the daemon's calibration → hand pose through FK."""

import math

import pytest

from companion.kinematics.arm import Arm
from firmware_interface.calibration import default_calibration
from sim_servo.config import ArmConfig
from sim_servo.errors import SimConfigError
from sim_servo.hand import HandModel


def model() -> HandModel:
    return HandModel.from_config(ArmConfig())


def test_default_calibration_is_the_daemons():
    assert model().calibration == default_calibration()


@pytest.mark.parametrize(
    "q_deg",
    [
        [0.0, 90.0, 0.0, 0.0, 0.0, 0.0],
        [30.0, 120.0, -45.0, 20.0, -10.0, 45.0],
        [-90.0, 0.0, 90.0, -90.0, 90.0, -70.0],
    ],
)
def test_round_trip_angles_pwm_pose(q_deg):
    hand = model()
    pwm = hand.calibration.angles_to_pwm_us(q_deg)
    state = hand.state(pwm)
    assert state.error is None
    expected = Arm.default().fk(q_deg)
    half_us_deg = 0.5 * 180.0 / 1000.0
    for name, q in zip([j.name for j in hand.calibration.joints], q_deg, strict=True):
        assert state.angles_deg[name] == pytest.approx(q, abs=half_us_deg + 1e-9)
    assert math.dist(state.pose.position_cm, expected.position_cm) < 0.5


def test_position_outside_the_calibrated_range_has_no_pose():
    hand = model()
    positions = {o: 1500.0 for o in hand.outputs}
    positions[12] = 2100.0
    state = hand.state(positions)
    assert state.pose is None and state.angles_deg is None
    assert "pwm_us=2100.0 outside [1000, 2000]" in state.error
    assert state.as_dict()["error"] == state.error


def test_deg_per_us_from_the_calibration():
    hand = model()
    assert hand.deg_per_us(9) == pytest.approx(0.18)
    assert hand.deg_per_us(14) == pytest.approx(160 / 1000)


def test_reversed_joint_and_custom_outputs():
    hand = HandModel.from_config(
        ArmConfig(outputs=(5, 6, 7, 8, 9, 10), reversed_joints=("theta1",))
    )
    state = hand.state({5: 1000.0, 6: 1500.0, 7: 1500.0, 8: 1500.0, 9: 1500.0, 10: 1500.0})
    assert state.angles_deg["theta1"] == pytest.approx(90.0)


def test_output_count_must_match_the_arm():
    with pytest.raises(SimConfigError, match="has 6 joints"):
        HandModel.from_config(ArmConfig(outputs=(9, 10)))


def test_missing_arm_file():
    with pytest.raises(SimConfigError, match="cannot load arm"):
        HandModel.from_config(ArmConfig(arm_file="/nonexistent/arm.toml"))
