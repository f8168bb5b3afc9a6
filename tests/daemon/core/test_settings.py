"""The settings derived from the config (``core/settings.py``), and a reload that changes
them."""

from __future__ import annotations

import math

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from companion.daemon.config import parse_config
from companion.daemon.core import SAFETY_STEPS_AHEAD, CoreSettings
from companion.daemon.core.settings import (
    AUTOPILOT_GAP_INTERVALS,
    SAFETY_BAND_MIN_S,
    safety_band_width_deg,
)
from tests.daemon.core.rig import PARK, RATE_HZ, SPEED_DEG_S, Px4OutputsModel, Rig, px4_rig


@pytest.mark.parametrize(
    ("url", "dialect", "interval_s"),
    [
        ("/dev/ttyAMA0,115200", "ardupilot-lua", 1.0),  # status only: spare the slow line
        ("/dev/ttyAMA0,921600", "ardupilot", 0.02),  # a foreign command seen before a step
        ("/dev/ttyAMA0,57600", "px4", 0.1),  # PX4's liveness comes from it
        ("udpin:0.0.0.0:14550", "px4", 0.02),  # room for it: a disarm seen sooner
    ],
)
def test_the_readback_is_asked_for_less_often_where_it_only_feeds_status_on_a_slow_line(
    url, dialect, interval_s
):
    rig = Rig(dialect=dialect, url=url)
    autopilot = (
        mavlink.MAV_AUTOPILOT_PX4 if dialect == "px4" else mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA
    )
    rig.heartbeat(autopilot=autopilot)
    rig.tick()
    [ask] = [
        c
        for c in rig.sent
        if c.command == mavlink.MAV_CMD_SET_MESSAGE_INTERVAL
        and c.params[0] == mavlink.MAVLINK_MSG_ID_SERVO_OUTPUT_RAW
    ]
    assert ask.params[1] == pytest.approx(interval_s * 1e6)


# -- derived values ------------------------------------------------------------------------------


def _config(dialect="ardupilot", url="udpout:127.0.0.1:14550", **tables):
    return parse_config({"link": {"url": url, "dialect": dialect}, **tables})


def test_the_settings_are_a_pure_function_of_the_config():
    config = _config()
    one, two = CoreSettings.from_config(config), CoreSettings.from_config(config)
    assert one is not two
    for name in ("outputs", "ardupilot", "period_s", "step_deg", "streams", "autopilot_gap_s"):
        assert getattr(one, name) == getattr(two, name)
    assert one.safety_band_width_deg == two.safety_band_width_deg


def test_the_safety_band_is_a_step_and_at_least_its_minimum_motion():
    # 60 deg/s at 20 Hz: a step is 3 deg, SAFETY_BAND_MIN_S of motion too.
    assert safety_band_width_deg(
        joint_speed_deg_s=60.0, rate_hz=20.0, sys_status_interval_s=0.025
    ) == pytest.approx(3.0)
    # At 50 Hz a step is 1.2 deg: the band stays at 0.05 s of motion.
    assert safety_band_width_deg(
        joint_speed_deg_s=60.0, rate_hz=50.0, sys_status_interval_s=0.025
    ) == pytest.approx(60.0 * SAFETY_BAND_MIN_S)
    # Faster joints, a wider band (SAFETY_STEPS_AHEAD steps).
    assert safety_band_width_deg(
        joint_speed_deg_s=120.0, rate_hz=20.0, sys_status_interval_s=0.025
    ) == pytest.approx(6.0 * SAFETY_STEPS_AHEAD)
    # A slow serial line (SYS_STATUS every 0.25 s): the steps of one interval.
    assert safety_band_width_deg(
        joint_speed_deg_s=60.0, rate_hz=20.0, sys_status_interval_s=0.25
    ) == pytest.approx(15.0)


def test_the_silence_gap_is_a_few_intervals_of_the_fastest_stream():
    px4 = CoreSettings.from_config(_config("px4"))
    ardupilot = CoreSettings.from_config(_config("ardupilot"))
    assert px4.autopilot_gap_s == pytest.approx(AUTOPILOT_GAP_INTERVALS * 0.02)  # readback
    assert ardupilot.autopilot_gap_s == pytest.approx(AUTOPILOT_GAP_INTERVALS * 0.02)  # readback
    assert not px4.ardupilot and ardupilot.ardupilot
    streams = dict(ardupilot.streams)
    assert streams[mavlink.MAVLINK_MSG_ID_SYS_STATUS] == 0.025
    assert mavlink.MAVLINK_MSG_ID_SYS_STATUS not in dict(px4.streams)


def test_the_world_solve_budget_is_a_share_of_the_control_period():
    settings_ = CoreSettings.from_config(_config(control={"rate_hz": 50.0}))
    assert settings_.world_solve_budget_ms == pytest.approx(2.0)  # 10 % of 20 ms
    assert settings_.period_s == pytest.approx(0.02)


def test_a_reload_may_not_change_the_firmware():
    core = Rig().core
    with pytest.raises(ValueError, match="restart"):
        core.reconfigure(_config("px4"))


# -- a reload that changes the speed limit ---------------------------------------------------------


def _reloaded(rig: Rig, speed_deg_s: float, rate_hz: float):
    return Rig(
        rig.config.link.dialect,
        sections={
            "arm": {"park_deg": list(PARK), "joint_speed_deg_s": speed_deg_s},
            "control": {"rate_hz": rate_hz},
        },
    ).config


def _drive(rig: Rig, px4: Px4OutputsModel | None, seconds: float) -> list[float]:
    """Time passes at the configured rate, the autopilot streaming every 20 ms at most (its
    frames do not wait for our ticks), every update applied and acknowledged: joint 1's
    acknowledged angle after each control period."""
    angles = []
    period_s = 1.0 / rig.core.config.rate_hz
    substeps = math.ceil(period_s / 0.02 - 1e-9)
    for _ in range(round(seconds / period_s)):
        for _ in range(substeps):
            sent = rig.advance(period_s / substeps)
            if px4 is not None:
                px4.handle()
                px4.readback()
            else:
                while sent:
                    sent = rig.ack_all(sent)
        angles.append(rig.core.status()["current_deg"][0])
    return angles


def _moving_rig(dialect: str) -> tuple[Rig, Px4OutputsModel | None]:
    """A rig on its way to joint 1 at +80 deg, every output acknowledged as it goes."""
    if dialect == "px4":
        rig, px4 = px4_rig(disarmed_us=1500)
        px4.set_live(True)
        px4.readback()
    else:
        rig, px4 = Rig(dialect), None
        rig.up()
    rig.goto((80.0, *PARK[1:]))
    if px4 is None:
        sent = list(rig.sent)
        while sent:
            sent = rig.ack_all(sent)
    _drive(rig, px4, 0.5)
    return rig, px4


@pytest.mark.parametrize("dialect", ["ardupilot", "px4"])
@pytest.mark.parametrize(
    ("speed_deg_s", "rate_hz"),
    [(120.0, RATE_HZ), (30.0, RATE_HZ), (SPEED_DEG_S, 50.0), (SPEED_DEG_S, 10.0)],
    ids=["faster", "slower", "higher-rate", "lower-rate"],
)
def test_after_a_reload_the_arm_keeps_moving_at_the_new_speed_limit(dialect, speed_deg_s, rate_hz):
    rig, px4 = _moving_rig(dialect)
    before = rig.core.status()["current_deg"][0]
    assert 5.0 < before < 40.0  # on its way
    rig.core.reconfigure(_reloaded(rig, speed_deg_s, rate_hz))
    angles = _drive(rig, px4, 0.5)
    steps = [b - a for a, b in zip([before, *angles], angles, strict=False) if b != a]
    new_step_deg = speed_deg_s / rate_hz
    # It moves on (not held by a band sized for the old limit) ...
    assert angles[-1] - before >= 0.5 * speed_deg_s * 0.5
    # ... and each step follows the new limit (the last one may stop short, at the goal).
    assert max(steps) == pytest.approx(new_step_deg)
    assert all(step <= new_step_deg + 1e-9 for step in steps)


@pytest.mark.parametrize("dialect", ["ardupilot", "px4"])
@pytest.mark.parametrize(
    "sections",
    [
        {"solver": {"budget_ms": 5.0}},
        {"solver": {"budget_ms": 50.0}},
        {"arm": {"park_deg": [10.0, 80.0, 0, 0, 0, 0]}},
        {"safety": {"keepout_margin_cm": 3.0}},
        {"control": {"resume_after_reboot": True}},
    ],
    ids=["budget-down", "budget-up", "park", "margin", "resume"],
)
def test_after_a_reload_of_any_other_field_the_arm_keeps_moving(dialect, sections):
    rig, px4 = _moving_rig(dialect)
    before = rig.core.status()["current_deg"][0]
    tables = {"arm": {"park_deg": list(PARK), "joint_speed_deg_s": SPEED_DEG_S}, **sections}
    tables["arm"] = {"joint_speed_deg_s": SPEED_DEG_S, "park_deg": list(PARK), **tables["arm"]}
    rig.core.reconfigure(Rig(dialect, sections=tables).config)
    angles = _drive(rig, px4, 0.5)
    assert angles[-1] - before >= 0.5 * SPEED_DEG_S * 0.5
