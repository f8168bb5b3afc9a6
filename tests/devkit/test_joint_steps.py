"""The fast-step count of ``bench/output_cycles.py`` on hand-made timelines."""

from __future__ import annotations

import pytest

from devkit.joint_steps import Change, JointStep, joint_steps, output_changes

#: 0.1 ° per µs around 1500 µs (1000 µs ↔ −50°, 2000 µs ↔ 50°).
DEG_PER_US = 0.1


def angle(pwm_us: int) -> float:
    return (pwm_us - 1500) * DEG_PER_US


def steps(changes, speed=60.0, rate=20.0):
    return joint_steps(
        9, changes, angle, joint_speed_deg_s=speed, rate_hz=rate, quantum_deg=DEG_PER_US
    )


def test_ticks_within_the_limit_are_not_fast_and_a_jump_after_a_long_hold_is():
    # 60 °/s at 20 Hz: 3° a tick (+0.1° quantum) = 31 µs at most.
    ticks = [Change(0.05 * k, 1500 + 30 * k, "command") for k in range(5)]
    found, first = steps([Change(0.0, 1000, "start"), *ticks[1:]])
    assert first == [Change(0.0, 1000, "start")]
    assert [s.fast for s in found] == [True, False, False, False]  # 1000 → 1530: 53°
    held = [Change(0.0, 1500, "start"), Change(5.0, 1000, "query"), Change(9.0, 1531, "arm")]
    found, _ = steps(held)
    assert [(s.to_us, s.fast, s.cause) for s in found] == [
        (1000, True, "query"),
        (1531, True, "arm"),  # 53.1° after 4 s held: fast, although 60 °/s × 4 s is 240°
    ]
    assert not found[1].loose(60.0, 20.0, DEG_PER_US)  # the loose reading misses it
    assert found[1].dt_s == pytest.approx(4.0)
    found, _ = steps([Change(0.0, 1500, "start"), Change(0.01, 1531, "command")])
    assert not found[0].fast  # one tick's step, even if it lands early


def test_no_pulses_hold_and_the_next_pulse_is_compared_with_the_last():
    changes = [
        Change(0.0, 0, "start"),  # ArduPilot: no pulses until the first command
        Change(1.0, 1400, "command"),  # first pulse: nothing to compare with
        Change(2.0, 0, "safety_on"),
        Change(3.0, 1400, "safety_off"),  # the same pulse again: no step
        Change(4.0, 0, "reboot"),
        Change(5.0, 1600, "command"),  # 20° from 1400: fast
    ]
    found, first = steps(changes)
    assert first == [Change(1.0, 1400, "command")]
    assert found == [
        JointStep(9, 5.0, 1400, 1600, pytest.approx(20.0), 1.0, pytest.approx(3.1), "command")
    ]


def test_output_changes_from_the_log_and_a_gap_is_an_error():
    events = [
        {"event": "start", "t_s": 0.0, "outputs_us": {"9": 1000, "10": 1000}},
        {"event": "output", "t_s": 0.5, "output": 9, "pwm_us": 1500, "from_us": 1000,
         "cause": "arm"},
    ]  # fmt: skip
    assert output_changes(events) == {
        9: [Change(0.0, 1000, "start"), Change(0.5, 1500, "arm")],
        10: [Change(0.0, 1000, "start")],
    }
    lost = {"event": "output", "t_s": 0.6, "output": 10, "pwm_us": 1500, "from_us": 1200,
            "cause": "command"}  # fmt: skip
    with pytest.raises(ValueError, match="output 10"):
        output_changes([*events, lost])
    with pytest.raises(ValueError, match="rate_hz"):
        steps([], rate=0.0)
