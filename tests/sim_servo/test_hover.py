"""The seeded hover disturbance: bounds, periods, analytic derivatives, repeatability."""

from __future__ import annotations

import math

import numpy as np
import pytest

from companion.kinematics.rotations import rpy_to_matrix
from sim_servo.config import VehicleConfig
from sim_servo.hover import AXES, HoverDisturbance

CONFIG = VehicleConfig(
    seed=7,
    drift_cm=8.0,
    heave_cm=4.0,
    tilt_deg=3.0,
    yaw_deg=6.0,
    period_min_s=1.5,
    period_max_s=4.0,
    yaw_period_min_s=10.0,
    yaw_period_max_s=15.0,
    home_ned_m=(1.0, -2.0, -3.0),
    home_yaw_deg=170.0,
)
#: Bounds per axis in AXES order (m, m, m, rad, rad, rad).
BOUNDS = np.array([0.08, 0.08, 0.04, *np.radians([3.0, 3.0, 6.0])])


def offsets_over(hover: HoverDisturbance, times_s: np.ndarray) -> np.ndarray:
    """``(len(times_s), 6)`` offsets from home, through :meth:`HoverDisturbance.offsets`."""
    return np.array([hover.offsets(t)[0] for t in times_s]) - hover.home


def offsets_vectorised(hover: HoverDisturbance, times_s: np.ndarray) -> np.ndarray:
    """The same, for many times at once (the model's formula, written again)."""
    arg = hover.omegas_rad_s[None] * times_s[:, None, None] + hover.phases_rad[None]
    return (hover.amplitudes[None] * np.sin(arg)).sum(axis=2)


def test_amplitudes_and_periods_stay_within_the_configured_bounds():
    hover = HoverDisturbance.from_config(CONFIG)
    periods = hover.periods_s
    assert np.all((periods[:5] >= 1.5) & (periods[:5] <= 4.0))
    assert np.all((periods[5] >= 10.0) & (periods[5] <= 15.0))  # the slow yaw wander
    np.testing.assert_allclose(hover.amplitudes.sum(axis=1), BOUNDS)  # the bound is the sum
    assert np.all(hover.amplitudes >= 0.5 / 3 * BOUNDS[:, None] * 0.999)  # no dead component
    times = np.arange(0.0, 300.0, 0.02)
    np.testing.assert_allclose(
        offsets_vectorised(hover, times[::500]), offsets_over(hover, times[::500]), atol=1e-12
    )
    deviation = np.abs(offsets_vectorised(hover, times)).max(axis=0)
    assert np.all(deviation <= BOUNDS + 1e-12)
    # ... and the motion uses its bounds: over 5 minutes each axis comes near them.
    assert np.all(deviation >= 0.6 * BOUNDS), dict(zip(AXES, deviation / BOUNDS, strict=True))


def test_velocities_and_angle_rates_are_the_derivatives_of_the_pose():
    hover = HoverDisturbance.from_config(CONFIG)
    step_s = 1e-6
    for t_s in np.random.default_rng(1).uniform(0.0, 100.0, size=20):
        values, rates = hover.offsets(t_s)
        numeric = (hover.offsets(t_s + step_s)[0] - hover.offsets(t_s - step_s)[0]) / (2 * step_s)
        np.testing.assert_allclose(rates, numeric, rtol=1e-5, atol=1e-7)
        state = hover.state(t_s)
        assert (state.vn_m_s, state.yaw_rate_rad_s) == (rates[0], rates[5])
        assert (state.north_m, state.yaw_rad) == (values[0], values[5])


def test_body_rates_are_the_angular_velocity_in_the_body_frame():
    # ATTITUDE's rollspeed/pitchspeed/yawspeed: ω_body, from Rᵀ·Ṙ (skew), not the Euler rates.
    hover = HoverDisturbance.from_config(VehicleConfig(seed=3, tilt_deg=30.0, yaw_deg=90.0))
    step_s = 1e-6
    for t_s in (0.3, 4.1, 17.9):
        state = hover.state(t_s)
        before, after = hover.state(t_s - step_s), hover.state(t_s + step_s)
        rot = rpy_to_matrix(state.roll_rad, state.pitch_rad, state.yaw_rad)
        rot_dot = (
            rpy_to_matrix(after.roll_rad, after.pitch_rad, after.yaw_rad)
            - rpy_to_matrix(before.roll_rad, before.pitch_rad, before.yaw_rad)
        ) / (2 * step_s)
        skew = rot.T @ rot_dot
        omega = np.array([skew[2, 1], skew[0, 2], skew[1, 0]])
        np.testing.assert_allclose(state.body_rates(), omega, rtol=1e-5, atol=1e-8)
        assert not np.allclose(
            state.body_rates(),
            (state.roll_rate_rad_s, state.pitch_rate_rad_s, state.yaw_rate_rad_s),
            rtol=1e-3,
        )


def test_a_seed_reproduces_the_same_motion_and_another_seed_does_not():
    times = np.linspace(0.0, 30.0, 301)
    first = offsets_over(HoverDisturbance.from_config(CONFIG), times)
    again = offsets_over(HoverDisturbance.from_config(CONFIG), times)
    assert np.array_equal(first, again)  # bit for bit
    generator = HoverDisturbance.from_config(CONFIG, np.random.default_rng(CONFIG.seed))
    assert np.array_equal(offsets_over(generator, times), first)
    other = HoverDisturbance.from_config(VehicleConfig(seed=8))
    assert not np.allclose(offsets_over(other, times), first)


def test_without_hover_the_vehicle_holds_home_level():
    config = VehicleConfig(hover=False, home_ned_m=(1.0, 2.0, -3.0), home_yaw_deg=90.0)
    hover = HoverDisturbance.from_config(config)
    for t_s in (0.0, 1.7, 1e4):
        state = hover.state(t_s)
        assert (state.north_m, state.east_m, state.down_m) == (1.0, 2.0, -3.0)
        assert (state.roll_rad, state.pitch_rad, state.yaw_rad) == (0.0, 0.0, math.pi / 2)
        assert state.body_rates() == (0.0, 0.0, 0.0)
        assert (state.vn_m_s, state.ve_m_s, state.vd_m_s) == (0.0, 0.0, 0.0)


def test_state_round_trips_through_json_data_and_wraps_yaw():
    hover = HoverDisturbance.from_config(CONFIG)  # home yaw 170° ± 6°: crosses ±180°
    yaws = [hover.state(t).attitude_wrapped()[2] for t in np.arange(0.0, 30.0, 0.1)]
    assert all(-math.pi <= yaw < math.pi for yaw in yaws)
    state = hover.state(12.5)
    data = state.as_dict()
    assert type(state).from_dict(data) == state
    assert (data["p_rad_s"], data["q_rad_s"], data["r_rad_s"]) == state.body_rates()


def test_shapes_are_checked():
    with pytest.raises(ValueError, match="expected \\(6, components\\)"):
        HoverDisturbance((0.0, 0.0, 0.0), 0.0, np.zeros((5, 2)), np.ones((5, 2)), np.zeros((5, 2)))
    with pytest.raises(ValueError, match="must have the amplitudes' shape"):
        HoverDisturbance((0.0, 0.0, 0.0), 0.0, np.zeros((6, 2)), np.ones((6, 3)), np.zeros((6, 2)))
