"""The servo model: slew timing, deadband, travel limits, no-pulse hold — on plain numbers."""

import math

import pytest
from hypothesis import given
from hypothesis import strategies as st

from sim_servo.errors import SimConfigError
from sim_servo.servo import Servo, ServoParams

# 0.12 s / 60° at 0.18 °/µs (180° over 1000 µs): 60/0.12 = 500 °/s = 2777.7… µs/s.
PARAMS = ServoParams(slew_s_per_60deg=0.12, deg_per_us=0.18, deadband_us=2.0)
RATE = 500.0 / 0.18


def test_rate_from_datasheet_speed():
    assert PARAMS.rate_us_per_s == pytest.approx(RATE)


def test_moves_at_constant_rate_and_stops_at_target():
    servo = Servo(PARAMS, initial_us=1500, start_s=10.0)
    assert servo.command(2000, now_s=10.0)
    assert servo.position_us(10.0) == 1500
    assert servo.position_us(10.05) == pytest.approx(1500 + RATE * 0.05)
    travel_s = 500 / RATE  # 0.18 s for 90°
    assert servo.arrival_s() == pytest.approx(10.0 + travel_s)
    assert servo.moving(10.0 + travel_s - 1e-3)
    assert servo.position_us(10.0 + travel_s) == 2000
    assert servo.position_us(99.0) == 2000 and not servo.moving(99.0)


def test_moves_down_as_well():
    servo = Servo(PARAMS, initial_us=1500, start_s=0.0)
    servo.command(1000, now_s=0.0)
    assert servo.position_us(0.09) == pytest.approx(1500 - RATE * 0.09)


def test_new_command_mid_move_starts_from_current_position():
    servo = Servo(PARAMS, initial_us=1000, start_s=0.0)
    servo.command(2000, now_s=0.0)
    here = servo.position_us(0.1)
    servo.command(1000, now_s=0.1)
    assert servo.position_us(0.1) == pytest.approx(here)
    assert servo.position_us(0.15) == pytest.approx(here - RATE * 0.05)


def test_deadband_ignores_small_changes():
    servo = Servo(PARAMS, initial_us=1500, start_s=0.0)
    assert not servo.command(1502, now_s=0.0)
    assert servo.position_us(1.0) == 1500
    assert servo.commanded_us == 1502
    assert servo.command(1503, now_s=1.0)
    assert servo.position_us(2.0) == 1503


def test_zero_pulse_holds_position():
    servo = Servo(PARAMS, initial_us=1000, start_s=0.0)
    servo.command(2000, now_s=0.0)
    here = servo.position_us(0.1)
    assert not servo.command(0, now_s=0.1)
    assert servo.position_us(5.0) == pytest.approx(here)


def test_horn_stops_at_mechanical_travel_but_pwm_is_kept():
    servo = Servo(PARAMS, initial_us=1500, start_s=0.0)
    servo.command(3000, now_s=0.0)
    assert servo.commanded_us == 3000
    assert servo.position_us(10.0) == PARAMS.travel_max_us


def test_instant_servo():
    servo = Servo(ServoParams(slew_s_per_60deg=0.0), initial_us=1500, start_s=0.0)
    servo.command(1800, now_s=1.0)
    assert servo.position_us(1.0) == 1800 and servo.arrival_s() == 1.0


def test_bad_params_refused():
    with pytest.raises(SimConfigError, match="deg_per_us"):
        ServoParams(deg_per_us=0.0)


@given(st.floats(500, 2500), st.floats(0, 3000), st.floats(0, 1))
def test_position_stays_between_start_and_goal(start, pwm, t):
    servo = Servo(PARAMS, initial_us=start, start_s=0.0)
    servo.command(pwm, now_s=0.0)
    goal = servo.target_us
    position = servo.position_us(t)
    assert min(start, goal) - 1e-9 <= position <= max(start, goal) + 1e-9
    assert PARAMS.travel_min_us <= position <= PARAMS.travel_max_us
    assert math.isfinite(position)
