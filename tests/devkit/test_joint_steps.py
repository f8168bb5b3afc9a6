"""The fast-step count of ``bench/output_cycles.py`` on hand-made timelines."""

from __future__ import annotations

import pytest

from devkit.joint_steps import (
    AUTOPILOT,
    DAEMON_ALIVE,
    DAEMON_COMMAND,
    FOREIGN_ALIVE,
    FOREIGN_COMMAND,
    MARKER_RACE,
    RACE,
    RACE_DEAD,
    RACE_REBOOT,
    Change,
    JointStep,
    Reload,
    SpeedLimits,
    commands_received,
    first_shown_after,
    foreign_command_before,
    foreign_stored_at,
    joint_steps,
    judge,
    marker_race,
    output_changes,
    readbacks_shown,
    step_kind,
    stored_by_foreign,
    undriven_outside,
)

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
        JointStep(
            9, 5.0, 1400, 1600, pytest.approx(20.0), 1.0, pytest.approx(3.1), "command",
            gap_from_s=4.0, from_cause="command",
        )
    ]  # fmt: skip


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


def test_whose_step_it_is():
    events = [
        {"event": "start", "t_s": 0.0, "outputs_us": {"9": 1500}},
        {"event": "servo", "t_s": 0.5, "output": 9, "pwm_us": 1530},
        {"event": "output", "t_s": 0.5, "output": 9, "pwm_us": 1530, "from_us": 1500,
         "cause": "command"},
        {"event": "servo", "t_s": 1.0, "output": 9, "pwm_us": 2000, "src": [255, 190]},
        {"event": "output", "t_s": 1.0, "output": 9, "pwm_us": 2000, "from_us": 1530,
         "cause": "command", "src": [255, 190], "link": 1},
        {"event": "output", "t_s": 1.5, "output": 9, "pwm_us": 1000, "from_us": 2000,
         "cause": "kill"},
        {"event": "output", "t_s": 2.0, "output": 9, "pwm_us": 2000, "from_us": 1000,
         "cause": "arm"},
        {"event": "servo", "t_s": 2.5, "output": 9, "pwm_us": 1500},
        {"event": "output", "t_s": 2.5, "output": 9, "pwm_us": 1500, "from_us": 2000,
         "cause": "command"},
        {"event": "output", "t_s": 3.0, "output": 9, "pwm_us": 1000, "from_us": 1500,
         "cause": "query"},
        {"event": "output", "t_s": 3.5, "output": 9, "pwm_us": 1500, "from_us": 1000,
         "cause": "prearm"},
    ]  # fmt: skip
    changes = output_changes(events)[9]
    assert changes[2].source == (255, 190) and changes[1].source is None
    found, _ = steps(changes)
    stored = stored_by_foreign(events)[9]
    kinds = [
        step_kind(s, disarmed_us=1000, stored_foreign=foreign_stored_at(stored, s.t_s))
        for s in found
    ]
    assert kinds == [
        DAEMON_COMMAND,  # 1500 → 1530
        FOREIGN_COMMAND,  # 1530 → 2000 from 255/190
        AUTOPILOT,  # kill: to the disarmed PWM
        FOREIGN_ALIVE,  # arm: the foreign 2000 comes out
        DAEMON_COMMAND,  # the daemon's next command jumps back: 50°, its own
        AUTOPILOT,
        DAEMON_ALIVE,
    ]
    # ArduPilot has no disarmed PWM: a change to 1000 is whatever its cause says.
    arm = JointStep(9, 1.0, 1500, 1000, 50.0, 1.0, 3.1, "safety_off")
    assert step_kind(arm, disarmed_us=None, stored_foreign=False) == DAEMON_ALIVE


def test_overlapping_reload_windows_allow_any_of_their_limits():
    # Two reloads 40 ms apart (30 -> 40, then 40 -> 60): in the second's window the daemon may
    # already step at 60, though the first's window is not over (seen: a 2.3 deg step judged
    # against 40 deg/s alone).
    limits = SpeedLimits(30.0, [Reload(1.0, 1.105, 30.0, 40.0), Reload(1.04, 1.145, 40.0, 60.0)])
    assert limits.at(1.02) == (30.0, 40.0)
    assert limits.at(1.09) == (30.0, 60.0)
    assert limits.at(1.12) == (40.0, 60.0)
    assert limits.at(1.2) == (60.0, 60.0)


def test_a_reload_window_is_judged_against_both_limits():
    limits = SpeedLimits(60.0, [Reload(1.0, 1.2, 60.0, 20.0), Reload(3.0, 3.1, 20.0, 120.0)])
    assert limits.at(0.5) == (60.0, 60.0)
    assert limits.at(1.1) == (20.0, 60.0)
    assert limits.at(2.0) == (20.0, 20.0)
    assert limits.at(3.05) == (20.0, 120.0)
    assert limits.at(9.0) == (120.0, 120.0)

    def step(t_s, deg):
        return JointStep(9, t_s, 1500, 1600, deg, 0.05, 0.0, "command")

    def verdict(t_s, deg):
        return judge(step(t_s, deg), limits, rate_hz=20.0, quantum_deg=0.1)

    assert verdict(0.5, 3.0) == (False, False)
    assert verdict(1.1, 3.0) == (False, True)  # within 60 °/s, over 20 °/s: apart
    assert verdict(2.0, 3.0) == (True, True)  # 20 °/s in force: 1° + quantum a tick
    assert verdict(9.0, 6.0) == (False, False)


def test_changes_at_the_same_instant_are_one_step_to_the_last():
    # Two commands in one commander cycle: 1241 → 1612 → 1243 at once is 1241 → 1243.
    changes = [
        Change(0.0, 1241, "start"),
        Change(1.0, 1612, "command"),
        Change(1.0, 1243, "command"),
        Change(2.0, 1300, "command", (255, 190)),
        Change(2.0, 1250, "command"),
    ]
    found, _ = steps(changes)
    assert [(s.from_us, s.to_us, s.source) for s in found] == [
        (1241, 1243, None),
        (1243, 1250, None),
    ]


def test_the_daemons_command_right_after_a_foreign_one_is_a_race_later_its_own():
    stored = [(1.0, False), (2.0, True), (2.02, False), (3.0, True), (3.5, False)]
    assert foreign_command_before(stored, 2.02) == pytest.approx(0.02)
    assert foreign_command_before(stored, 3.5) == pytest.approx(0.5)
    assert foreign_command_before(stored, 1.0) is None  # nothing before
    assert foreign_command_before(stored, 2.0) is None  # the daemon's before it
    step = JointStep(9, 2.02, 2000, 1500, 50.0, 0.02, 3.1, "command")
    kind = {"disarmed_us": None, "stored_foreign": True, "race_window_s": 0.03}
    assert step_kind(step, foreign_before_s=0.02, **kind) == RACE
    assert step_kind(step, foreign_before_s=0.5, **kind) == DAEMON_COMMAND
    assert step_kind(step, foreign_before_s=None, **kind) == DAEMON_COMMAND
    # The autopilot rebooted before the foreign command's readbacks could be believed.
    cut = step_kind(step, foreign_before_s=0.5, reboot_cut_short=True, **kind)
    assert cut == RACE_REBOOT
    assert step_kind(step, foreign_before_s=None, reboot_cut_short=True, **kind) == DAEMON_COMMAND


def test_a_pulse_outside_the_servos_range_is_taken_as_no_pulses():
    changes = [
        Change(0.0, 1500, "start"),
        Change(1.0, 900, "disarm"),
        Change(2.0, 1510, "arm"),
        Change(3.0, 0, "reboot"),
        Change(4.0, 900, "boot"),
    ]
    out = undriven_outside(changes, 1000, 2000)
    assert [c.pwm_us for c in out] == [1500, 0, 1510, 0]


def test_a_command_that_restates_the_stored_pwm_leaves_it_the_earlier_senders():
    # The daemon re-sent (adopted) what a ground station stored while the outputs were held:
    # the jump at their release is the ground station's.
    events = [
        {"event": "servo", "t_s": 1.0, "output": 9, "pwm_us": 1500},
        {"event": "servo", "t_s": 2.0, "output": 9, "pwm_us": 1418, "src": [255, 190]},
        {"event": "servo", "t_s": 3.0, "output": 9, "pwm_us": 1418},
        {"event": "servo", "t_s": 4.0, "output": 9, "pwm_us": 1500},
    ]
    stored = stored_by_foreign(events)[9]
    assert foreign_stored_at(stored, 3.5)  # still the ground station's value
    assert not foreign_stored_at(stored, 4.0)  # the daemon's new one
    assert foreign_command_before(stored, 4.0) == pytest.approx(2.0)


def test_outputs_back_from_the_disarmed_pwm_within_the_readbacks_blind_time_are_a_race():
    # A kill, then an arm 33 ms later: PX4 brings out what it stored, a step from where the
    # joint was before; the readbacks could not show the outputs dead in that time.
    changes = [
        Change(0.0, 1044, "start"),
        Change(1.0, 1000, "kill"),
        Change(1.033, 1046, "arm"),
        Change(2.0, 1000, "kill"),
        Change(2.5, 1046, "arm"),  # dead long enough to be seen: the daemon's
        Change(3.0, 1000, "kill"),
        Change(3.03, 1200, "arm"),  # far from where it was: the daemon's
    ]
    found, _ = steps(changes)
    alive = [s for s in found if s.cause == "arm"]
    kind = {"disarmed_us": 1000, "stored_foreign": False, "dead_window_s": 0.07}
    assert [s.fast for s in alive] == [True, True, True]
    assert [step_kind(s, **kind) for s in alive] == [RACE_DEAD, DAEMON_ALIVE, DAEMON_ALIVE]
    assert step_kind(alive[0], disarmed_us=1000, stored_foreign=False) == DAEMON_ALIVE
    # After a reload to a higher speed, a step is the one in force.
    wider = JointStep(9, 1.033, 1000, 1070, 7.0, 0.033, 3.1, "arm", None, 4.5)
    assert step_kind(wider, **kind) == DAEMON_ALIVE
    assert step_kind(wider, back_allowed_deg=6.1, **kind) == RACE_DEAD


def test_when_a_readback_first_showed_a_pwm():
    events = [
        {"t_s": 1.0, "event": "readback", "pwm_us": {"9": 1500, "10": 1400}},
        {"t_s": 1.02, "event": "output", "output": 9},
        {"t_s": 1.04, "event": "readback", "pwm_us": {"9": 2000}},
        {"t_s": 1.06, "event": "readback", "pwm_us": {"9": 1510}},
    ]
    shown = readbacks_shown(events)
    assert shown == {9: [(1.0, 1500), (1.04, 2000), (1.06, 1510)], 10: [(1.0, 1400)]}
    assert first_shown_after(shown[9], 2000, 1.01) == 1.04
    assert first_shown_after(shown[9], 1500, 1.01) is None  # shown before, not since
    assert first_shown_after(shown[10], 1400, 0.0) == 1.0


def test_a_stored_value_coming_alive_is_judged_by_the_limit_it_was_stored_under_too():
    limits = SpeedLimits(120.0, [Reload(1.0, 1.2, 120.0, 20.0)])

    def verdict(cause, stored_s):
        step = JointStep(9, 5.0, 1500, 1520, 4.0, 0.05, 0.0, cause)
        return judge(step, limits, rate_hz=20.0, quantum_deg=0.1, stored_s=stored_s)

    assert verdict("safety_off", 0.5) == (False, True)  # stored at 120 °/s: apart
    assert verdict("safety_off", 2.0) == (True, True)  # stored at 20 °/s
    assert verdict("command", 0.5) == (True, True)  # a command is its own storing
    assert verdict("safety_off", None) == (True, True)


def test_the_first_pulse_after_a_gap_is_judged_by_the_limit_when_the_pulses_stopped_too():
    # The switch stopped the pulses at 60 °/s (a band of steps sent before it), a reload set
    # 20 °/s, a reboot; the restarted daemon re-sends the band's middle: 2.5° from the truth.
    changes = [
        Change(0.0, 1500, "start"),
        Change(0.5, 1530, "command"),
        Change(1.0, 0, "safety_on"),
        Change(2.0, 0, "reboot"),
        Change(4.0, 1555, "command"),
        Change(4.05, 1580, "command"),
    ]
    found, _ = joint_steps(
        9, changes, angle, joint_speed_deg_s=60.0, rate_hz=20.0, quantum_deg=DEG_PER_US
    )
    assert [s.gap_from_s for s in found] == [None, 1.0, None]
    limits = SpeedLimits(60.0, [Reload(1.5, 1.6, 60.0, 20.0)])
    verdicts = [judge(s, limits, rate_hz=20.0, quantum_deg=DEG_PER_US) for s in found]
    assert verdicts[1] == (False, True)  # within a step at 60 °/s; over 20 °/s: apart
    assert verdicts[2] == (True, True)  # the next step is judged by 20 °/s alone
    # Stopped after the reload: 20 °/s alone.
    late = SpeedLimits(60.0, [Reload(0.6, 0.7, 60.0, 20.0)])
    assert judge(found[1], late, rate_hz=20.0, quantum_deg=DEG_PER_US) == (True, True)


def test_a_command_for_outputs_shown_dead_taking_effect_after_they_came_alive_is_a_race():
    # Prearm off, then on 50 ms later: the readbacks showed the outputs dead, the daemon sent
    # their marker next to the disarmed PWM, and PX4's commander carried it out 14 ms after
    # they came alive, before a readback could show the daemon that they had.
    changes = [
        Change(0.0, 1500, "start"),
        Change(1.0, 1000, "prearm"),
        Change(1.05, 1500, "prearm"),
        Change(1.064, 1002, "command"),  # the marker, received at 1.058
        Change(2.0, 1000, "prearm"),
        Change(2.4, 1002, "prearm"),  # the marker stored while dead comes alive
        Change(2.45, 1030, "command"),  # the motion on from there: not fast
        Change(3.0, 1000, "prearm"),
        Change(3.05, 1500, "prearm"),
        Change(3.2, 1002, "command"),  # received after a readback showed them alive
    ]
    events = [
        {"t_s": 1.064, "event": "servo", "output": 9, "pwm_us": 1002, "received_t_s": 1.058},
        {"t_s": 3.2, "event": "servo", "output": 9, "pwm_us": 1002, "received_t_s": 3.19},
        {"t_s": 3.2, "event": "servo", "output": 10, "pwm_us": 1002},
    ]
    received = commands_received(events)
    assert received == {9: {1.064: 1.058, 3.2: 3.19}}
    shown = [(1.0, 1000), (1.07, 1500), (1.09, 1002), (3.01, 1000), (3.06, 1500)]
    found, _ = steps(changes)
    commands = [s for s in found if s.cause == "command"]
    assert [(s.from_us, s.to_us, s.before_us, s.from_cause) for s in commands] == [
        (1500, 1002, 1000, "prearm"),
        (1002, 1030, 1000, "prearm"),
        (1500, 1002, 1000, "prearm"),
    ]
    raced = [
        marker_race(s, disarmed_us=1000, received_s=received[9].get(s.t_s), shown=shown, hop_s=0.01)
        for s in commands
    ]
    assert raced == [True, False, False]  # (the second has no arrival: not one of PX4's waits)
    kind = {"disarmed_us": 1000, "stored_foreign": False}
    assert step_kind(commands[0], marker_raced=True, **kind) == MARKER_RACE
    assert step_kind(commands[2], **kind) == DAEMON_COMMAND
    # Received before the readback showing them alive, but more than a hop after it: the
    # daemon could have known.
    assert not marker_race(commands[0], disarmed_us=1000, received_s=1.081, shown=shown, hop_s=0.01)
    # On ArduPilot (no disarmed PWM) never.
    assert not marker_race(commands[0], disarmed_us=None, received_s=1.058, shown=shown, hop_s=0.01)
