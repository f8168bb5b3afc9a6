"""ArduPilot's outputs' truth (``core/outputs_ardupilot.py``): the safety switch from
SYS_STATUS, BRD_SAFETY_MASK, the safety band and the rewind, against a model of its outputs."""

from __future__ import annotations

import math

import numpy as np
import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from companion.daemon.core import (
    SAFETY_STEPS_AHEAD,
    SYS_STATUS_SILENT_S,
    Answer,
    ReadParam,
    SendCommand,
)
from companion.daemon.core.outputs import READBACK_SILENT_S, band_of, middle
from companion.daemon.core.outputs_ardupilot import (
    MASK_APPLY_S,
    READBACK_STALE_INTERVALS,
    band_allows,
    widen,
)
from companion.daemon.requests import Outcome, Request
from tests.daemon.core.autopilot_models import (
    ARM_MASK,
    MOTORS,
    SERVO_OUTPUT_RAW,
    SYS_STATUS,
    ArduPilotOutputsModel,
    Autopilot,
    deg_per_us,
    far_target,
)
from tests.daemon.core.rig import PARK, RATE_HZ, STEP_DEG, Rig, near


def test_ardupilot_safety_on_holds_everything_unless_the_mask_frees_the_outputs(rig):
    rig.sys_status(safety_on=True)
    rig.sent.clear()
    request = rig.goto(near(PARK))
    assert not rig.servo()  # nothing: it would be applied at once when the switch goes off
    reply = rig.reply(request)
    assert reply.outcome is Outcome.ACCEPTED
    assert "outputs not live: safety switch on (output 9 not in BRD_SAFETY_MASK)" in reply.message
    assert rig.core.status()["safety_on"] is True
    rig.frame(lambda c: c.param_value_encode(b"BRD_SAFETY_MASK", math.nan, 6, 1, 0))
    assert rig.core.status()["outputs_live"] is False  # a NaN mask frees nothing
    mask = sum(1 << (o - 1) for o in rig.calibration.outputs)
    rig.frame(lambda c: c.param_value_encode(b"BRD_SAFETY_MASK", mask, 6, 1, 0))
    rig.advance(0.05)  # ArduPilot frees them within 0.1 s of the change: not before
    assert rig.core.status()["outputs_live"] is False
    rig.advance(MASK_APPLY_S)
    rig.readback({})  # its readback stream goes on (nothing of ours applied yet)
    assert rig.core.status()["outputs_live"] is True and rig.servo()


def test_ardupilot_safety_mask_is_read_again_after_a_reboot():
    ap = Autopilot("ardupilot")
    assert [a.name for a in ap.actions if isinstance(a, ReadParam)] == ["BRD_SAFETY_MASK"]
    ap.answer_intervals()
    ap.frame(
        ap.codec.param_value_encode(
            b"BRD_SAFETY_MASK", float(ARM_MASK), mavlink.MAV_PARAM_TYPE_INT32, 1, 65535
        )
    )
    actions = ap.reboot()
    assert [a.name for a in actions if isinstance(a, ReadParam)] == ["BRD_SAFETY_MASK"]


def test_ardupilot_steps_sent_before_the_switch_was_seen_do_not_jump_at_its_release():
    """An autopilot streaming SYS_STATUS at the interval the core asked for; the switch goes on
    just after one (the worst case) while the arm moves, and is released a second later. What
    the outputs then show must be within one step of what they showed when it went on."""
    ap = Autopilot("ardupilot")
    asked = {
        int(a.params[0]): a.params[1] / 1e6
        for a in ap.actions
        if isinstance(a, SendCommand) and a.command == mavlink.MAV_CMD_SET_MESSAGE_INTERVAL
    }
    status_interval_s = asked[mavlink.MAVLINK_MSG_ID_SYS_STATUS]
    ap.answer_intervals()
    ap.frame(ap.codec.param_value_encode(b"BRD_SAFETY_MASK", 0.0, 9, 1, 65535))  # arm not in it
    outputs = mavlink.MAV_SYS_STATUS_SENSOR_MOTOR_OUTPUTS

    def sys_status(switch_on: bool) -> list:
        enabled = 0 if switch_on else outputs
        return ap.frame(
            ap.codec.sys_status_encode(outputs, enabled, outputs, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0)
        )

    sys_status(False)
    ap.frame(ap.codec.servo_output_raw_encode(0, 0, *[0] * 16))  # no pulses since its boot
    start = ap.core.status()["current_deg"]
    low = math.degrees(ap.config.arm.joints[0].min_rad)
    goal = [low + 1.0, *start[1:]]  # a long way on joint 1: seconds at 60 deg/s
    request = Request("goto", tuple(goal))
    step_us = ap.config.joint_speed_deg_s / ap.config.rate_hz / deg_per_us(ap) + 1

    def acked_pwm() -> int:
        return int((ap.core.status()["last_pwm_us"] or {}).get(9, 0))

    def carry_out(actions: list) -> None:
        """The edge: answers set, every servo command acknowledged (and what that brings)."""
        while actions:
            action = actions.pop(0)
            if isinstance(action, Answer):
                action.request.answer(action.reply)
            elif isinstance(action, SendCommand) and action.command == mavlink.MAV_CMD_DO_SET_SERVO:
                actions += ap.frame(
                    ap.codec.command_ack_encode(
                        action.command, mavlink.MAV_RESULT_ACCEPTED, 0, 0, 1, 191
                    )
                )

    carry_out(ap.core.request(request))
    switch_on, t0_pwm, released_pwm = False, None, None
    next_status_s = ap.clock() + status_interval_s
    t_start = ap.clock()
    while ap.clock() - t_start < 2.0:
        ap.clock.advance(0.005)
        now = ap.clock() - t_start
        carry_out(ap.core.tick(True))
        if ap.clock() >= next_status_s:
            carry_out(sys_status(switch_on))
            next_status_s += status_interval_s
            if t0_pwm is None and now >= 0.3:
                # Just after a SYS_STATUS: the switch goes on, and the outputs hold this PWM.
                switch_on, t0_pwm = True, acked_pwm()
        if switch_on and now >= 1.3:
            released_pwm = acked_pwm()  # released: the stored PWM goes out at once
            break
    assert request.future.result(0).outcome is Outcome.ACCEPTED
    assert t0_pwm is not None and released_pwm is not None
    assert abs(released_pwm - t0_pwm) <= step_us, (t0_pwm, released_pwm, step_us)


def test_ardupilot_a_switch_seen_on_after_a_reboot_rewinds_to_no_pose_from_before_it():
    """Cause 2: moving, the switch goes on and is seen (the outputs sent back), the autopilot
    reboots and comes back with its switch on (BRD_SAFETY_DEFLT 1): nothing is sent while it is
    on (the rewind was to a pose recorded before the reboot), and its release moves no joint by
    more than a step."""
    ap = ArduPilotOutputsModel(safety_default_on=True)
    ap.run(0.3)
    start = ap.core.status()["current_deg"]
    ap.goto([start[0] + 40.0, *start[1:]])
    ap.run(0.4)
    ap.set_safety(True)
    ap.run(0.3)  # seen on: the held outputs are sent back
    ap.reboot_now()
    ap.run(0.4)
    assert ap.commanded == {}  # rebooted: nothing stored
    ap.run(2.0)
    assert ap.core.status()["counters"]["autopilot_reboots"] == 1
    assert ap.core.status()["safety_on"] is True
    assert ap.commanded == {}  # nothing sent while its switch is on after the reboot
    ap.set_safety(False)
    ap.run(1.0)
    assert ap.commanded  # moving again
    assert ap.fast_changes() == []


def test_ardupilot_a_silent_sys_status_stream_stops_the_arm_within_a_step():
    """Cause 3: a SYS_STATUS that said "off" long ago is not trusted: with the stream silent,
    the arm moves at most SAFETY_STEPS_AHEAD steps (one) from where it was when the last one
    came, status says the outputs are not known to be live after SYS_STATUS_STALE_INTERVALS,
    and every stream is asked for again after SYS_STATUS_SILENT_S; the arm goes on once
    SYS_STATUS is back."""
    ap = ArduPilotOutputsModel()
    ap.run(0.3)
    start = ap.core.status()["current_deg"]
    ap.goto([start[0] + 60.0, *start[1:]])
    ap.run(0.2)
    interval_s = ap.streams.pop(SYS_STATUS)  # the stream stops
    at_last_status = ap.core.status()["current_deg"][0]
    ap.run(SYS_STATUS_SILENT_S - 0.05)
    step_deg = ap.config.joint_speed_deg_s / ap.config.rate_hz
    moved_deg = abs(ap.core.status()["current_deg"][0] - at_last_status)
    assert moved_deg <= SAFETY_STEPS_AHEAD * step_deg + 1e-6
    status = ap.core.status()
    assert status["outputs_live"] is False
    assert "no SYS_STATUS for" in status["not_live"]["9"]
    ap.run(0.1)  # silent SYS_STATUS_SILENT_S: asked for again (the model streams it again)
    assert ap.streams.get(SYS_STATUS) == interval_s
    ap.run(0.5)
    assert ap.core.status()["outputs_live"] is True
    assert abs(ap.core.status()["current_deg"][0] - at_last_status) > 5 * step_deg
    assert ap.fast_changes() == []


@pytest.mark.parametrize("ack_delay_s", [0.003, 0.012])
def test_ardupilot_at_50_hz_the_safety_band_does_not_slow_the_arm(ack_delay_s):
    """At 50 Hz control SYS_STATUS (40 Hz) comes less often than the ticks, and one may come
    while a step is on its way: a band one 50 Hz step wide held the arm to 48 of 60 deg/s (and
    a followed world target fell behind). SAFETY_BAND_MIN_S keeps it at full speed."""
    ap = ArduPilotOutputsModel(rate_hz=50.0, ack_delay_s=ack_delay_s)
    ap.run(0.3)
    start = ap.core.status()["current_deg"]
    ap.goto([start[0] + 90.0, *start[1:]])
    ap.run(0.1)
    at_deg = ap.core.status()["current_deg"][0]
    ap.run(1.0)
    speed_deg_s = abs(ap.core.status()["current_deg"][0] - at_deg) / 1.0
    assert speed_deg_s >= 0.95 * ap.config.joint_speed_deg_s
    assert ap.fast_changes() == []


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_ardupilot_no_joint_moves_faster_than_a_step_through_switch_and_reboot_cycles(seed):
    """Causes 2, 4 and 5 together: random targets (some in 50 Hz bursts), the safety switch on
    and off at any moment (some presses shorter than a SYS_STATUS interval) and reboots with the
    switch at either default: every physical change of a pulse is within one control tick's
    step (plus one µs) of the last pulse before it."""
    rng = np.random.default_rng(seed)
    ap = ArduPilotOutputsModel(safety_default_on=bool(seed % 2))
    ap.run(0.3)
    if ap.safety_on:
        ap.set_safety(False)
    for _ in range(60):
        roll = rng.random()
        if roll < 0.4:
            ap.goto(far_target(ap, rng))
        elif roll < 0.5:
            for _ in range(10):  # a ground station's 50 Hz stream, each a little further
                ap.goto(far_target(ap, rng))
                ap.run(0.02)
        elif roll < 0.8:
            ap.set_safety(not ap.safety_on)
        elif roll < 0.85 and ap.rebooting_until_s is None:
            ap.reboot_now()
        ap.run(float(np.exp(rng.uniform(math.log(0.01), math.log(0.6)))))
    assert len(ap.changes) > 100
    assert ap.fast_changes() == []


def test_ardupilot_with_the_arm_in_the_safety_mask_it_moves_on_with_the_switch_on():
    """The arm's outputs in BRD_SAFETY_MASK (doctor's advice), the switch goes on mid-motion:
    the arm pauses (the mask is asked for, and believed MASK_APPLY_S after the first answer)
    and then goes on at its speed to the target, the switch still on."""
    ap = ArduPilotOutputsModel()
    ap.set_mask(ARM_MASK)
    ap.run(0.3)
    start = ap.core.status()["current_deg"]
    target = [start[0] + 60.0, *start[1:]]
    ap.goto(target)
    ap.run(0.2)
    ap.set_safety(True)
    ap.run(0.3)
    at_deg = ap.core.status()["current_deg"][0]
    ap.run(0.3)
    assert ap.core.status()["safety_on"] is True
    speed_deg_s = abs(ap.core.status()["current_deg"][0] - at_deg) / 0.3
    assert speed_deg_s >= 0.95 * ap.config.joint_speed_deg_s
    ap.run(1.0)
    assert ap.core.status()["current_deg"][0] == pytest.approx(target[0], abs=0.01)
    asked = sum(isinstance(a, ReadParam) for a in ap.core.tick(True))
    assert asked <= 1  # one request at a time
    assert ap.fast_changes() == []


def test_ardupilot_outputs_a_new_mask_frees_get_nothing_until_it_applied():
    """Moving, the switch on holds the arm (mask 0); a ground station's servo test stores
    2000 us on one output. Then BRD_SAFETY_MASK takes the arm in: ArduPilot frees the outputs
    up to 0.1 s later, bringing out what they store. The core sends nothing to them before
    (it would be stored, and its step from where the readback shows would go out from where
    the servo was held), so the release brings out the ground station's PWM, not ours."""
    ap = ArduPilotOutputsModel()
    ap.run(0.3)
    start = ap.core.status()["current_deg"]
    ap.goto([start[0] + 60.0, *start[1:]])
    ap.run(0.3)
    ap.set_safety(True)
    ap.run(0.3)
    ap.commanded[10] = 2000  # behind the switch: stored, the readback shows it
    ap.run(0.5)
    held = ap.pulse[10]
    ap.set_mask(ARM_MASK)
    while ap.applied_mask != ARM_MASK:
        ap.run(0.005)
    assert ap.changes[-1][1:] == (10, held, 2000)  # out with the release: the ground station's
    at_deg = ap.core.status()["current_deg"][0]
    ap.run(0.5)
    assert ap.core.status()["safety_on"] is True
    assert abs(ap.core.status()["current_deg"][0] - at_deg) > 10.0  # on its way again


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_ardupilot_a_mask_changed_with_the_switch_on_never_releases_a_jump(seed):
    """A ground station sets BRD_SAFETY_MASK at any moment, the switch on or off, its
    PARAM_VALUE broadcast reaching the core or lost (it applies within 0.1 s either way):
    every physical change of a pulse is within one control tick's step of the one before."""
    rng = np.random.default_rng(seed)
    ap = ArduPilotOutputsModel()
    ap.set_mask(ARM_MASK)
    ap.run(0.3)
    for _ in range(80):
        roll = rng.random()
        if roll < 0.35:
            ap.goto(far_target(ap, rng))
        elif roll < 0.6:
            ap.set_safety(not ap.safety_on)
        elif roll < 0.9:
            ap.set_mask(ARM_MASK if ap.mask == 0 else 0, broadcast=bool(rng.random() < 0.5))
        ap.run(float(np.exp(rng.uniform(math.log(0.01), math.log(0.6)))))
    assert len(ap.changes) > 100
    assert ap.fast_changes() == []


# -- the safety band, alone ----------------------------------------------------------------------


def test_the_band_of_poses_spans_each_joint_and_its_middle_is_within_half_of_it():
    band = band_of([(0.0, 10.0), (3.0, 8.0), (1.0, 9.0)])
    assert band == ([0.0, 8.0], [3.0, 10.0])
    assert middle(band) == (1.5, 9.0)


def test_a_step_may_widen_the_band_only_up_to_its_width():
    band = band_of([(0.0, 0.0)])
    assert band_allows(band, (3.0, -3.0), 3.0)
    assert not band_allows(band, (3.1, 0.0), 3.0)
    widen(band, (3.0, -1.0))
    assert band == ([0.0, -1.0], [3.0, 0.0])
    # Back within the band is always allowed; further out on the wide joint is not.
    assert band_allows(band, (1.0, -0.5), 3.0)
    assert not band_allows(band, (-0.5, 0.0), 3.0)


def test_a_switch_seen_off_from_the_start_is_not_warned_of(rig, caplog):
    # A board without a safety switch reports it off from its first SYS_STATUS: nothing to say.
    with caplog.at_level("INFO", logger="armbridge"):
        rig.sys_status(safety_on=False)
        assert not [r for r in caplog.records if "safety switch" in r.getMessage()]
        rig.sys_status(safety_on=True)
        rig.clock.advance(2 * rig.status_interval_s)  # off believed an interval and a half on
        rig.sys_status(safety_on=False)
        assert rig.core.status()["safety_on"] is True  # and once the clock went on after it
        rig.clock.advance(0.005)  # the probe's answer, a round trip later
        rig.answer_clock_probes()
        rig.clock.advance(rig.status_interval_s)
        rig.sys_status(safety_on=False)
    said = [(r.levelname, r.getMessage()) for r in caplog.records if "safety" in r.getMessage()]
    assert said == [
        ("WARNING", "safety switch on: outputs not live"),
        ("INFO", "safety switch off"),
    ]


# -- the readback: where the joints are ----------------------------------------------------


def _pwm_of(rig, pose) -> dict[int, int]:
    return {
        o: rig.calibration.for_output(o).angle_to_pwm_us(a)
        for o, a in zip(rig.calibration.outputs, pose, strict=True)
    }


def _first_step_deg(rig, start_pose) -> float:
    """The largest joint move of the first servo update sent, from ``start_pose``."""
    sent = rig.servo()
    return max(
        abs(rig.angle(o, pwm) - start_pose[rig.calibration.outputs.index(o)])
        for o, pwm in sent.items()
    )


def _restarted_away() -> tuple[Rig, tuple[float, ...]]:
    """A daemon just started, the switch off, and the pose an earlier daemon left the arm at
    (far from park), which ArduPilot still holds and shows."""
    rig = Rig()
    rig.heartbeat()
    rig.tick()
    rig.switch_off()
    return rig, tuple(p + 40.0 for p in PARK[:1]) + tuple(p - 30.0 for p in PARK[1:])


def test_ardupilot_a_restarted_daemon_starts_where_the_readback_shows_and_not_before():
    # A daemon restarted with the arm away from park: ArduPilot still holds what the earlier
    # daemon sent, and its readback shows it. Assuming park, the first goto moved every joint
    # ~42 deg in one command.
    rig, away = _restarted_away()
    request = rig.goto(tuple(a + 1.5 for a in away))
    for _ in range(4):
        rig.advance(0.025)
    assert not rig.servo()  # no readback yet: where the joints are is unknown
    _readbacks_believed(rig, _pwm_of(rig, away))
    rig.advance(0.05)
    assert rig.servo()
    assert _first_step_deg(rig, away) <= STEP_DEG + 0.2
    rig.ack_all(rig.sent)
    assert rig.reply(request).outcome is Outcome.ACCEPTED


def _readbacks_believed(rig, shown) -> None:
    """Readbacks show ``shown`` over more than an interval, the autopilot's clock going on
    after them: believed."""
    for _ in range(3):
        rig.readback(shown)
        rig.clock.advance(0.02)
    rig.system_time(600_000)
    rig.clock.advance(0.02)
    rig.readback(shown)


def test_ardupilot_a_forged_readback_at_the_start_never_places_the_joints():
    # One forged frame at the start placed the joints where it said, and a goto's first step
    # went from there: the autopilot's own frames corrected it only at the next readback.
    # Frames showing two PWMs by turns place nothing, and the motion waits.
    rig, away = _restarted_away()
    rig.goto(tuple(a + 1.5 for a in away))
    for _ in range(10):
        rig.readback(_pwm_of(rig, away))
        rig.advance(0.01)
        rig.readback(_pwm_of(rig, PARK))  # forged between the autopilot's own
        rig.advance(0.01)
    rig.system_time(600_000)
    rig.advance(0.05)
    assert not rig.servo()
    _readbacks_believed(rig, _pwm_of(rig, away))  # the forger stopped
    rig.advance(0.05)
    assert rig.servo()
    assert _first_step_deg(rig, away) <= STEP_DEG + 0.2


def test_ardupilot_a_restored_pose_a_pwm_off_the_readback_is_placed_where_it_shows():
    # A pose restored from the file a PWM off what the readback showed was taken as held (the
    # readback's tolerance), and the first step went from it: a PWM further than a step from
    # where the joint was (1.26 deg where 1.18 was allowed, bench.state_cycles).
    rig = Rig()
    outputs = rig.calibration.outputs
    left = dict.fromkeys(outputs, 1671)
    rig.core.restore_pose((left, left))
    rig.heartbeat()
    rig.tick()
    rig.switch_off()
    rig.goto(tuple(p - 30.0 for p in PARK))
    _readbacks_believed(rig, dict.fromkeys(outputs, 1672))
    shown_deg = [rig.angle(o, 1672) for o in outputs]
    assert rig.core.status()["current_deg"] == shown_deg
    rig.advance(0.05)
    quantum_deg = max(abs(rig.angle(o, 1001) - rig.angle(o, 1000)) for o in outputs)
    assert 0.0 < _first_step_deg(rig, shown_deg) <= STEP_DEG + quantum_deg


def test_ardupilot_with_no_readback_the_arm_moves_after_the_wait():
    rig = Rig()
    rig.heartbeat()
    rig.tick()
    rig.switch_off()
    rig.goto(near(PARK))
    for _ in range(40):  # the SYS_STATUS stream flowing
        rig.advance(0.025)
    assert not rig.servo()
    for _ in range(44):
        rig.advance(0.025)
    assert rig.servo()  # READBACK_WAIT_S: from the park pose, said once in the log


def _settle(rig, pose, seconds=1.0):
    """The arm at ``pose``, acknowledged, with the readback streaming it every 0.1 s."""
    rig.goto(pose)
    done = 0
    for i in range(round(seconds / 0.05)):
        new, done = rig.sent[done:], len(rig.sent)
        rig.ack_all(new)
        rig.advance(0.05)
        if i % 2:
            rig.readback(rig.core.status()["last_pwm_us"] or {})
    assert rig.core.status()["moving"] is False


def _foreign_2000_believed(rig) -> tuple[int, dict[int, int]]:
    """A ground station's servo command put the first output at 2000 us: readbacks show it
    over more than an interval, the autopilot's clock goes on after them, and the daemon
    believes it. Returns the output and what the readback shows."""
    output = rig.calibration.outputs[0]
    shown = {**rig.core.status()["last_pwm_us"], output: 2000}
    _readbacks_believed(rig, shown)
    assert rig.core.status()["foreign_command"]["output"] == output
    return output, shown


def _far_goal(*, second_deg: float = 0.0) -> list[float]:
    """A goal seconds of motion away on joint 1 (at 60 deg/s), and ``second_deg`` on joint 2."""
    goal = list(PARK)
    goal[0] += 60.0
    goal[1] += second_deg
    return goal


def _moving(rig) -> int:
    """The arm moving towards a far goal for half a second, every step acknowledged but the
    last sent, the readback streaming what was acknowledged; how many commands were sent
    before that last step."""
    rig.goto(_far_goal(second_deg=-40.0))
    done = 0
    for i in range(10):
        new, done = rig.sent[done:], len(rig.sent)
        rig.ack_all(new)
        rig.advance(0.05)
        if i % 2:
            rig.readback(rig.core.status()["last_pwm_us"] or {})
    return done


def _rebooted_and_released(rig) -> None:
    """The autopilot reboots (silent 0.36 s, its clock back at 150 ms), shows no pulses since
    its boot while its clock goes on, and says its switch is off; what the core sends after
    that is left in ``rig.sent``."""
    rig.advance(0.36)
    rig.system_time(150)
    assert rig.core.status()["counters"]["autopilot_reboots"] == 1
    rig.sent.clear()
    for boot_ms in (170, 190, 210):
        rig.readback({})
        rig.clock.advance(0.02)
        rig.system_time(boot_ms)
    rig.switch_off()
    rig.advance(0.05)


def _step_us(rig) -> float:
    """One control step of the first output's joint in PWM, plus the 1 us quantum."""
    joint = rig.calibration.for_output(rig.calibration.outputs[0])
    span_deg = joint.angle_max_deg - joint.angle_min_deg
    return STEP_DEG / span_deg * (joint.pwm_max_us - joint.pwm_min_us) + 1


def test_ardupilot_a_foreign_servo_command_is_taken_as_where_the_joint_is(rig, caplog):
    # A ground station's servo test (DO_SET_SERVO) put output 9 at 2000 us: status showed the
    # readback but the daemon went on believing its own PWM, and the next goto jumped 78-132
    # deg in one command.
    _settle(rig, near(PARK))
    output = rig.calibration.outputs[0]
    shown = dict(rig.core.status()["last_pwm_us"])
    acked = shown[output]
    shown[output] = 2000
    rig.readback(shown)
    assert rig.core.status()["foreign_command"] is None  # one readback alone is not believed
    rig.advance(0.1)
    rig.readback(shown)
    # Nor two, until the autopilot's clock is heard after them (it did not reboot meanwhile, when
    # forged frames alone would show): it is asked for now.
    assert rig.core.status()["foreign_command"] is None
    [probe] = [c for c in rig.sent if c.command == mavlink.MAV_CMD_REQUEST_MESSAGE]
    assert probe.params[0] == mavlink.MAVLINK_MSG_ID_SYSTEM_TIME
    rig.clock.advance(0.005)  # its answer, a round trip later
    rig.system_time(600_000)
    rig.clock.advance(0.02)
    with caplog.at_level("WARNING", logger="armbridge"):
        rig.readback(shown)
    [said] = [r.getMessage() for r in caplog.records if "another sender" in r.getMessage()]
    assert f"output {output} shows 2000 us, not the {acked} us acknowledged" in said
    status = rig.core.status()
    assert status["foreign_command"]["output"] == output
    assert status["foreign_command"]["shown_us"] == 2000
    assert status["foreign_command"]["acknowledged_us"] == acked
    assert status["counters"]["foreign_commands"] == 1
    assert status["last_pwm_us"][output] == 2000
    assert status["moving"] is False  # the arm was still: it stays where it was put
    assert not rig.servo(rig.advance(0.2))
    position = tuple(status["current_deg"])
    rig.sent.clear()
    rig.goto(near(PARK))
    rig.sys_status(safety_on=False)  # the band of poses held: the joint where it shows
    rig.advance(0.05)
    assert _first_step_deg(rig, position) <= STEP_DEG + 0.2


def test_ardupilot_a_forged_readback_between_the_autopilots_own_is_not_believed(rig):
    _settle(rig, near(PARK))
    real = dict(rig.core.status()["last_pwm_us"])
    forged = {o: 2000 for o in real}
    for _ in range(10):  # forged frames between the autopilot's own, at its rate
        rig.readback(forged)
        rig.clock.advance(0.05)
        rig.readback(real)
        rig.clock.advance(0.05)
    status = rig.core.status()
    assert status["foreign_command"] is None
    assert status["last_pwm_us"] == real


def test_ardupilot_a_forged_safety_off_between_the_autopilots_own_is_not_believed(rig):
    # A forged "safety off" made the daemon send 132 commands into held outputs, which came on
    # 35-58 deg away at the real release.
    rig.sys_status(safety_on=True)  # the autopilot streams "on"
    rig.advance(0.05)
    rig.sent.clear()
    rig.goto(near(PARK, 20.0))
    for _ in range(20):
        rig.clock.advance(rig.status_interval_s / 2)
        rig.sys_status(safety_on=False, stream=False)  # forged, between two of its own
        rig.tick()
    assert not rig.servo()
    assert rig.core.status()["outputs_live"] is False


def test_ardupilot_forged_readbacks_faster_than_the_autopilots_own_are_not_believed(rig):
    # Forged frames four times as often as the autopilot's readback: two of them always fall
    # between two of its own, so "two in a row" alone would believe them.
    _settle(rig, near(PARK))
    real = dict(rig.core.status()["last_pwm_us"])
    forged = {o: 2000 for o in real}
    for _ in range(20):
        rig.readback(real)
        for _ in range(4):
            rig.clock.advance(0.005)
            rig.readback(forged)
    status = rig.core.status()
    assert status["foreign_command"] is None
    assert status["last_pwm_us"] == real


def test_ardupilot_a_disagreeing_readback_holds_the_motion_until_the_next_ones_say(rig):
    rig.goto(near(PARK, 20.0))
    done = 0
    for _ in range(4):
        new, done = rig.sent[done:], len(rig.sent)
        rig.ack_all(new)
        rig.advance(0.05)
    rig.ack_all(rig.sent[done:])
    rig.clock.advance(0.2)  # settled
    shown = dict(rig.core.status()["last_pwm_us"])
    output = rig.calibration.outputs[0]
    rig.readback({**shown, output: 2000})  # one disagrees: not believed, not ignored
    rig.sent.clear()
    assert not rig.servo(rig.advance(0.01))
    rig.readback(shown)  # the next agrees: the motion goes on
    rig.sys_status(safety_on=False)  # (the streams were asked again after the quiet 0.2 s)
    assert rig.servo(rig.advance(0.05))


def test_ardupilot_after_a_reboot_an_output_another_sender_set_is_resent_where_it_shows(rig):
    # Rebooted, then a ground station set output 9 to 2000 us before our outputs went out
    # again: the re-send of the pose from before the reboot jumped it back 100 deg.
    _settle(rig, near(PARK))
    rig.system_time(600_000)
    rig.advance(0.36)  # the reboot's silence
    rig.system_time(150)
    assert rig.core.status()["counters"]["autopilot_reboots"] == 1
    output = rig.calibration.outputs[0]
    rig.sent.clear()
    rig.readback({output: 2000})  # the other outputs: no pulses since the boot
    rig.clock.advance(0.02)
    rig.readback({output: 2000})
    rig.clock.advance(0.02)
    rig.readback({output: 2000})
    rig.clock.advance(0.005)
    rig.system_time(190)  # its clock goes on
    rig.clock.advance(0.02)
    rig.readback({output: 2000})
    rig.sys_status(safety_on=False)
    rig.advance(0.05)
    assert rig.servo()[output] == 2000


def test_ardupilot_after_a_reboot_the_resend_waits_for_an_output_another_sender_set(rig):
    # Rebooted; the switch known off, the outputs were re-sent at once, over a ground station's
    # servo command shown in one readback and not believed yet: a 72 deg step back.
    _settle(rig, near(PARK))
    rig.system_time(600_000)
    rig.advance(0.36)  # the reboot's silence
    rig.system_time(150)
    output = rig.calibration.outputs[0]
    rig.sent.clear()
    rig.readback({output: 2000})  # the other outputs: no pulses since the boot
    rig.sys_status(safety_on=False)
    rig.advance(0.01)
    assert not rig.servo()  # the re-send holds while the readbacks decide
    rig.clock.advance(0.02)
    rig.readback({output: 2000})
    assert not rig.servo()
    rig.clock.advance(0.005)
    rig.system_time(180)  # the answer to the probe: its clock goes on
    rig.clock.advance(0.02)
    rig.readback({output: 2000})
    rig.advance(0.01)
    assert rig.servo()[output] == 2000


def test_ardupilot_the_clock_heard_before_the_readbacks_disagreed_long_enough_is_not_enough(
    rig,
):
    # Forged frames began before the reboot, the autopilot's SYSTEM_TIME came between them,
    # then it fell silent: the forged ones alone went on and were believed (104 deg).
    _settle(rig, near(PARK))
    rig.clock.advance(0.3)  # settled
    acked = dict(rig.core.status()["last_pwm_us"])
    forged = {o: 1000 for o in acked}
    rig.readback(forged)
    rig.clock.advance(0.005)
    rig.system_time(600_000)  # the autopilot, still there
    for _ in range(8):  # then only forged frames: it reboots, silent
        rig.clock.advance(0.01)
        rig.readback(forged)
    assert rig.core.status()["foreign_command"] is None


def test_ardupilot_readbacks_forged_while_it_reboots_are_not_believed(rig):
    # Forged readbacks while the autopilot is silent, rebooting, are all the readbacks there
    # are: taken as a foreign command, the daemon re-sent the forged pose after the boot (a
    # 119 deg step on the simulator).
    _settle(rig, near(PARK))
    rig.system_time(600_000)
    acked = dict(rig.core.status()["last_pwm_us"])
    rig.clock.advance(0.3)  # settled
    forged = {o: 1000 for o in acked}
    for _ in range(10):
        rig.readback(forged)
        rig.clock.advance(0.01)
    assert rig.core.status()["foreign_command"] is None
    rig.advance(0.3)  # the reboot's silence
    rig.system_time(150)
    assert rig.core.status()["counters"]["autopilot_reboots"] == 1
    rig.sent.clear()
    rig.readback({})  # no pulses since the boot
    rig.sys_status(safety_on=False)
    rig.advance(0.05)
    assert rig.servo() == acked  # its own pose re-sent, not the forged one


def test_ardupilot_after_a_reboot_forged_readbacks_among_its_own_no_pulses_are_not_believed(
    rig,
):
    _settle(rig, near(PARK))
    rig.system_time(600_000)
    rig.advance(0.36)
    rig.system_time(150)
    output = rig.calibration.outputs[0]
    for _ in range(10):  # the autopilot's own: no pulses since its boot; forged ones between
        rig.readback({})
        rig.clock.advance(0.01)
        rig.readback({output: 2000})
        rig.clock.advance(0.01)
    rig.sys_status(safety_on=False)
    rig.advance(0.05)
    assert rig.servo().get(output) != 2000


def test_ardupilot_no_clock_probe_goes_out_while_the_link_is_down(rig):
    _settle(rig, near(PARK))
    rig.advance(4.0, link_up=False)  # lost: nothing is sent
    assert rig.core.status()["holding"]
    rig.sent.clear()
    output = rig.calibration.outputs[0]
    for _ in range(3):
        rig.readback({output: 2000})
        rig.clock.advance(0.02)
    assert not rig.sent


def test_ardupilot_after_a_reboot_off_is_believed_only_once_the_stream_said_so_long_enough(rig):
    # A SYS_STATUS forged as "off" came before the autopilot's own stream was back after its
    # reboot (it boots with the switch on): the outputs were re-sent and the arm moved on,
    # stored, and jumped up to 16 deg at the switch's release.
    _settle(rig, near(PARK))
    rig.system_time(600_000)
    rig.advance(0.36)  # the reboot's silence
    rig.system_time(150)
    assert rig.core.status()["counters"]["autopilot_reboots"] == 1
    rig.readback({})
    rig.sent.clear()
    rig.sys_status(safety_on=False, stream=False)  # forged, the stream not back yet
    rig.clock.advance(0.01)
    rig.sys_status(safety_on=False, stream=False)
    rig.advance(0.01)
    assert rig.core.status()["safety_on"] is None
    assert not rig.servo()
    rig.sys_status(safety_on=True)  # its own stream
    rig.clock.advance(0.03)
    rig.sys_status(safety_on=False, stream=False)  # forged again
    assert rig.core.status()["safety_on"] is True


def test_ardupilot_the_rewind_never_sends_an_output_back_over_another_senders_command(rig):
    # The arm moving, a ground station's DO_SET_SERVO put an output at 2000 us, and the safety
    # switch went on 37 ms later, before the readbacks could be believed: the rewind sent the
    # output back to where the daemon had it (1634 us) while its readback showed 2000, and the
    # release brought that out, 58 deg from the 2000 us the servo had last been given.
    done = _moving(rig)
    rig.ack_all(rig.sent[done:])
    output = rig.calibration.outputs[0]
    shown = {**rig.core.status()["last_pwm_us"], output: 2000}
    rig.readback(shown)  # the ground station's command: one readback, not believed yet
    rig.sys_status(safety_on=True)  # the switch on
    rig.sent.clear()
    for _ in range(3):
        rig.clock.advance(0.02)
        rig.readback(shown)
        rig.tick()
    # While the readback is in doubt nothing goes to that output but 2000.
    assert rig.servo().get(output, 2000) == 2000
    rig.system_time(600_000)  # the autopilot's clock: the readbacks are believed
    rig.clock.advance(0.02)
    rig.readback(shown)
    assert rig.core.status()["foreign_command"]["output"] == output
    for _ in range(5):
        rig.ack_all(rig.sent)
        rig.clock.advance(0.02)
        rig.readback(shown)
        rig.tick()
    # The rewind leaves it where the other sender put it.
    assert rig.servo().get(output, 2000) == 2000


def test_ardupilot_with_the_arm_in_the_safety_mask_a_resend_goes_where_another_sender_put_it(
    rig,
):
    # The arm's outputs in BRD_SAFETY_MASK, the switch on (they stay live), a ground station's
    # servo command believed; then a reboot. The re-send went to the pose the switch had been
    # seen on at (the rewind, never carried out since no output was held), 58 deg from where
    # the ground station had put the output.
    rig.frame(lambda c: c.param_value_encode(b"BRD_SAFETY_MASK", float(ARM_MASK), 9, 1, 65535))
    _settle(rig, near(PARK))
    rig.sys_status(safety_on=True)
    rig.advance(0.05)
    output, _ = _foreign_2000_believed(rig)
    _rebooted_and_released(rig)
    assert rig.servo()[output] == 2000


def test_ardupilot_forged_safety_off_frames_do_not_narrow_what_the_outputs_may_hold(rig):
    # The switch went on between a SYS_STATUS saying off and the next step, and frames forged
    # saying off came every 10 ms from then on: each was taken as the autopilot's, and what the
    # outputs may hold was narrowed to the latest steps, without the pose they held when the
    # switch went on. The rewind went to the middle of those steps, and the release moved the
    # joints 3.4-3.8 deg (here two of the autopilot's "on" frames are lost: two steps go out).
    rig.goto(_far_goal(second_deg=-40.0))
    step_us = _step_us(rig)
    held: dict[int, int] = {}
    t0, done = rig.clock(), 0
    for k in range(300):  # 5 ms a pass
        acked = dict(rig.core.status()["last_pwm_us"] or {})
        new, done = rig.sent[done:], len(rig.sent)
        if not held and rig.clock() - t0 >= 0.5 and rig.servo(new):
            # The switch went on just before this step: the outputs hold what they had.
            held = acked
            rig.safety_stream = True  # the autopilot's frames say on from now ...
            rig._status_due_s = rig.clock() + 3 * rig.status_interval_s  # ... two lost
        rig.ack_all(new)  # carried out at once (stored, once the switch is on)
        rig.advance(0.005)
        if held and k % 2:
            rig.sys_status(safety_on=False, stream=False)  # forged, every 10 ms
    assert held and rig.core.status()["outputs_live"] is False
    released = rig.core.status()["last_pwm_us"]  # what goes out at the release
    assert max(abs(released[o] - held[o]) for o in held) <= step_us, (held, released)


def test_ardupilot_an_off_taken_after_a_steps_ack_still_holds_the_pose_before_that_step(rig):
    # A SYS_STATUS saying off left the autopilot just before the switch went on, and was taken
    # after the next step's ACK: what the outputs may hold was narrowed to that step, without
    # the pose they held when the switch went on; the rewind went to the middle of the steps
    # sent since (here two: the "on" frame comes late too), and the release moved a joint 4 deg.
    rig.goto(_far_goal(second_deg=-40.0))
    step_us = _step_us(rig)
    held: dict[int, int] = {}
    motors = mavlink.MAV_SYS_STATUS_SENSOR_MOTOR_OUTPUTS  # enabled: the switch off
    done = 0
    for k in range(300):  # 5 ms a pass; a step every 10 passes
        if k == 109:
            rig._status_due_s = math.inf  # the stream's next frame is late
        acked = dict(rig.core.status()["last_pwm_us"] or {})
        new, done = rig.sent[done:], len(rig.sent)
        rig.ack_all(new)
        if k == 110:
            # The switch went on just before this step, and the autopilot's last "off", sent
            # before that (stamped 2 ms ago), is taken only after the step's ACK.
            assert rig.servo(new)
            held = acked
            rig.frame(
                lambda c: c.sys_status_encode(motors, motors, motors, *[0] * 10),
                received_s=rig.clock() - 0.002,
            )
            rig.safety_stream = True  # its next frames say on, the first after the next step
            rig._status_due_s = rig.clock() + 2.2 * rig.status_interval_s
        rig.advance(0.005)
    assert held and rig.core.status()["outputs_live"] is False
    released = rig.core.status()["last_pwm_us"]  # what goes out at the release
    assert max(abs(released[o] - held[o]) for o in held) <= step_us, (held, released)


def test_ardupilot_a_foreign_pwm_shown_before_the_first_acks_settle_holds_the_motion():
    # A daemon (re)started moments before: its first steps were acknowledged less than a
    # readback's settling time ago when a ground station's servo command showed in the
    # readback. It was taken as a readback lagging behind those steps, and the next step went
    # out over the ground station's 2000 us: 61-107 deg.
    rig = Rig()
    rig.heartbeat()
    rig.tick()
    start = {o: 1500 for o in rig.calibration.outputs}
    rig.readback(start)
    rig.switch_off()
    rig.goto(_far_goal())
    done = 0
    for _ in range(2):  # two steps, acknowledged at once; the readback lags behind them
        new, done = rig.sent[done:], len(rig.sent)
        rig.ack_all(new)
        rig.advance(0.05)
        rig.readback(start)
    new, done = rig.sent[done:], len(rig.sent)
    rig.ack_all(new)
    output = rig.calibration.outputs[0]
    for _ in range(2):  # the ground station's command shows, at the readback's rate
        rig.clock.advance(0.02)
        rig.readback({**start, output: 2000})
    rig.sent.clear()
    rig.advance(0.01)  # the next tick: the motion holds while the readbacks decide
    assert output not in rig.servo()


def test_ardupilot_a_readback_back_at_a_pwm_it_showed_before_newer_ones_disagrees(rig):
    # The readback had shown the arm's first step when a ground station's command put an
    # output back at the PWM it held before it: taken as a readback lagging behind the step
    # (that PWM was acknowledged last before the readback's settling time), and the next step
    # went out over it (9 deg).
    _settle(rig, near(PARK))
    output = rig.calibration.outputs[0]
    before = dict(rig.core.status()["last_pwm_us"])
    rig.ack_all(rig.take(rig.core.request(Request("goto", tuple(_far_goal())))))  # first step
    rig.clock.advance(0.01)
    rig.readback(rig.core.status()["last_pwm_us"])  # shown
    for _ in range(2):  # then the output shows the PWM it held before that step
        rig.clock.advance(0.015)
        rig.readback({**rig.core.status()["last_pwm_us"], output: before[output]})
    rig.sent.clear()
    rig.advance(0.01)  # the next tick
    assert output not in rig.servo()


def test_ardupilot_a_resend_keeps_an_output_where_another_sender_put_it_behind_the_switch(rig):
    # The switch holding the arm, a ground station's servo command stored 2000 us on an output
    # (believed from the readback); then the link was lost. The re-send went to the middle of
    # the band of poses the outputs might hold, widened to take 2000 us in beside the pose
    # held before: half that width from the stored 2000 us, which the release then brought
    # out in one step (10 deg).
    rig.goto(_far_goal())
    done = 0
    for _ in range(4):  # moving
        new, done = rig.sent[done:], len(rig.sent)
        rig.ack_all(new)
        rig.advance(0.05)
    rig.ack_all(rig.sent[done:])
    rig.sys_status(safety_on=True)  # the switch on: held
    rig.advance(0.05)
    output, shown = _foreign_2000_believed(rig)
    rig.advance(0.5, link_up=False)  # lost
    rig.sent.clear()
    rig.heartbeat()
    rig.readback(shown)
    rig.switch_off()
    rig.advance(0.05)
    assert rig.servo()[output] == 2000


def test_ardupilot_a_readback_that_arrived_during_a_gotos_solve_is_seen_before_its_first_step(
    rig,
):
    # A ground station's servo command landed just before a goto: the readback showing it
    # arrived while the goto was being solved, and the goto's first step went out before it
    # was looked at (36 deg over the other sender's command, bench.state_cycles). Frames that
    # arrived during the solve are fed first; the readback holds the motion until the next
    # ones say.
    _settle(rig, near(PARK))
    output = rig.calibration.outputs[0]
    shown = {**rig.core.status()["last_pwm_us"], output: 2000}
    rig.core.before_first_step = lambda: rig.readback(shown)
    rig.sent.clear()
    rig.goto(near(PARK, -STEP_DEG / 2))
    assert not rig.servo()
    assert rig.core.status()["moving"] is True


def test_ardupilot_frames_fed_as_a_batch_send_no_step_before_the_last_is_weighed(rig):
    # Queued before a readback that showed a ground station's command, a frame (the ACK that
    # completed an update, the SYS_STATUS a step waited for) sent a step at once, before the
    # readback was read: 45-103 deg over the other sender's command (bench.state_cycles). Fed
    # as one batch, the step waits for the batch's end, and the readback holds it.
    _settle(rig, near(PARK))
    rig.sent.clear()
    rig.goto(near(PARK, -STEP_DEG / 2))
    first = list(rig.sent)
    rig.goto(near(PARK, -3 * STEP_DEG))  # waits for the update in flight
    before = len(rig.sent)
    output = rig.calibration.outputs[0]
    shown = {**rig.core.status()["last_pwm_us"], output: 2000}
    rig.clock.advance(0.03)
    rig.core.feeding_frames = True
    rig.ack_all(first)
    rig.sys_status(safety_on=False)
    rig.readback(shown)
    rig.core.feeding_frames = False
    assert not rig.servo(rig.sent[before:])
    rig.take(rig.core.frames_fed())
    assert not rig.servo(rig.sent[before:])  # in doubt: the readbacks decide first


def test_ardupilot_undone_narrowings_keep_an_output_where_another_sender_put_it(rig):
    # A ground station's command believed, then a SYS_STATUS forged as "off" right after the
    # autopilot's own (the cadence broken: the last narrowings of the band undone) and the
    # switch on: the undone bands still held the joint's pose from before the command, the
    # rewind went to the middle of that and 2000 us, and the release moved the joint 57 deg
    # from where the ground station had put it (bench.state_cycles).
    _settle(rig, near(PARK))
    output, shown = _foreign_2000_believed(rig)
    rig.sent.clear()
    rig.sys_status(safety_on=False)  # the autopilot's own
    rig.clock.advance(0.005)
    rig.sys_status(safety_on=False, stream=False)  # forged, 5 ms after it
    rig.clock.advance(rig.status_interval_s)
    rig.sys_status(safety_on=True)  # the switch on
    for _ in range(5):
        rig.ack_all(rig.sent)
        rig.clock.advance(0.02)
        rig.readback(shown)
        rig.tick()
    assert rig.core.status()["outputs_live"] is False
    assert rig.servo().get(output, 2000) == 2000


def test_ardupilot_off_forged_while_it_is_silent_is_not_believed(rig):
    # The switch on, the autopilot went silent (a reboot) and SYS_STATUS frames forged as its
    # own said "off" every 10 ms: with no frame of its own between them they kept the
    # cadence, "off" was believed, and what the outputs may hold was narrowed to the pose
    # acknowledged behind the switch. After the reboot the arm stepped from there: 2.5 deg
    # from where the switch had held it (bench.state_cycles).
    _settle(rig, near(PARK))
    rig.clock_goes_on()
    rig.sys_status(safety_on=True)
    rig.advance(0.05)
    rig.safety_stream = None  # silent
    for _ in range(20):
        rig.clock.advance(0.011)
        rig.sys_status(safety_on=False, stream=False)  # forged
        rig.tick()
    assert rig.core.status()["safety_on"] is True
    rig.clock.advance(0.005)
    rig.answer_clock_probes()  # not rebooting after all: its clock goes on
    rig.sys_status(safety_on=False)  # and its own stream says off
    rig.advance(0.03)
    assert rig.core.status()["safety_on"] is False


def test_ardupilot_a_step_acknowledged_after_another_senders_command_was_believed_keeps_it(rig):
    # The arm moving, a ground station's command on an output was believed while a step sent
    # before it was still waiting for ACKs: their arrival took the joint back to that step's
    # angle, and the next step went from there, 22.7 deg from the 2000 us the output held
    # (bench.state_cycles).
    done = _moving(rig)
    in_flight, done = rig.sent[done:], len(rig.sent)
    assert rig.servo(in_flight)  # a step on its way, not acknowledged yet
    output, shown = _foreign_2000_believed(rig)
    rig.ack_all(in_flight)  # its ACKs come now
    angle = rig.angle(output, 2000)
    assert rig.core.status()["current_deg"][0] == pytest.approx(angle)
    assert rig.core.status()["last_pwm_us"][output] == 2000
    previous = angle
    for _ in range(3):  # the motion goes on from where the other sender put it
        rig.advance(0.05)
        new, done = rig.sent[done:], len(rig.sent)
        rig.ack_all(new)
        if output in rig.servo(new):
            step = rig.angle(output, rig.servo(new)[output])
            assert abs(step - previous) <= STEP_DEG + 0.2
            previous = step


def test_ardupilot_with_the_arm_in_the_safety_mask_a_resend_goes_where_the_motion_went_on(rig):
    # The arm's outputs in BRD_SAFETY_MASK: the switch seen on leaves them live and the motion
    # goes on (within the band), but the pose it would have rewound them to was kept, and the
    # re-send after a reboot went there: 5 deg from where the motion had taken a joint
    # (bench.state_cycles).
    rig.frame(lambda c: c.param_value_encode(b"BRD_SAFETY_MASK", float(ARM_MASK), 9, 1, 65535))
    rig.goto(_far_goal())
    done = 0
    for i in range(16):  # moving; the switch goes on halfway, the motion goes on
        if i == 8:
            rig.sys_status(safety_on=True)
            at_switch = rig.core.status()["current_deg"][0]
        new, done = rig.sent[done:], len(rig.sent)
        rig.ack_all(new)
        rig.advance(0.05)
    rig.ack_all(rig.sent[done:])
    assert rig.core.status()["safety_on"] is True
    held = rig.core.status()["current_deg"][0]
    assert held > at_switch  # a step went out after it (the band allows one)
    rig.clock_goes_on()
    _rebooted_and_released(rig)
    output = rig.calibration.outputs[0]
    assert abs(rig.angle(output, rig.servo()[output]) - held) <= STEP_DEG + 0.2


def test_ardupilot_status_is_not_fooled_by_forged_sys_status_while_the_autopilot_reboots():
    """The autopilot reboots (silent 0.36 s, its outputs without pulses) while SYS_STATUS frames
    forged as its own keep saying the switch is off, every 10 ms: its readback stream stopped,
    so within READBACK_STALE_INTERVALS of its interval status no longer says the outputs are
    live, and says why."""
    ap = ArduPilotOutputsModel()
    ap.run(0.3)
    assert ap.core.status()["outputs_live"] is True
    readback_s = ap.core.settings.readback_interval_s
    forged = ap.codec.sys_status_encode(MOTORS, MOTORS, MOTORS, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0)
    ap.reboot_now()
    said_live_s = 0.0
    while ap.rebooting_until_s is not None and ap.clock() < ap.rebooting_until_s - 0.02:
        ap.carry_out(ap.frame(forged))
        ap.run(0.01)
        status = ap.core.status()
        if status["outputs_live"]:
            said_live_s += 0.01
        else:
            assert "no SERVO_OUTPUT_RAW for" in status["not_live"]["9"]
    assert said_live_s <= (READBACK_STALE_INTERVALS + 1) * readback_s + 0.01
    assert status["outputs_live"] is False


def test_ardupilot_streams_are_asked_for_again_after_a_reboot_forged_sys_status_hides():
    """SYS_STATUS frames forged as the autopilot's, every 10 ms, through its reboot: no silence
    of SYS_STATUS or of the autopilot shows that it forgot every stream. Its readback stream's
    silence does: every stream is asked for again within READBACK_SILENT_S of its last
    readback, so an output another sender sets after the boot shows within a readback."""
    ap = ArduPilotOutputsModel()
    ap.run(0.3)
    forged = ap.codec.sys_status_encode(MOTORS, MOTORS, MOTORS, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0)
    rebooted_s = ap.clock()  # its last readback came just before
    ap.reboot_now()
    end_s = ap.clock() + 2.0
    booted_s = None
    while ap.clock() < end_s and (booted_s is None or SERVO_OUTPUT_RAW not in ap.streams):
        ap.carry_out(ap.frame(forged))
        ap.run(0.01)
        if booted_s is None and ap.rebooting_until_s is None:
            booted_s = ap.clock()  # back, every stream forgotten
    assert booted_s is not None and SERVO_OUTPUT_RAW in ap.streams
    assert ap.clock() - rebooted_s <= READBACK_SILENT_S + 0.03  # (and the command's way)


def test_ardupilot_a_ground_station_setting_back_the_pwm_before_a_step_shown_early_is_doubted(
    rig,
):
    """A readback showed our step before its ACK came (the output took it), then a ground
    station set the PWM the output held before that step: the readback can no longer show
    that PWM as a lag, so it is doubted and the motion holds, rather than the next step going
    out from ours and moving the joint from the ground station's PWM (9.4 deg in
    bench.state_cycles)."""
    _settle(rig, near(PARK))
    output = rig.calibration.outputs[0]
    before = dict(rig.core.status()["last_pwm_us"])
    start = rig.core.status()["current_deg"]
    rig.goto((start[0] + 40.0, *start[1:]))
    step = rig.servo()
    assert output in step
    shown = {**before, **step}
    rig.clock.advance(0.005)
    rig.readback(shown)  # the step shows before its ACK
    rig.clock.advance(0.002)
    rig.ack_all(list(rig.sent))
    rig.sent.clear()
    rig.clock.advance(0.013)
    rig.readback({**shown, output: before[output]})  # a ground station's command
    rig.advance(1.0 / RATE_HZ - 0.02)
    assert output not in rig.servo()


def test_ardupilot_a_release_believed_among_forged_off_frames_holds_what_the_outputs_showed():
    """The switch goes on mid-motion and the held outputs are sent back to the middle of the
    band (the rewind); then SYS_STATUS frames forged as "off" come every 10 ms (the cadence
    broken), and a reload lowers the speed limit. The switch is released: the outputs show the
    rewind live, and "off" is believed. It goes on again: the rewind must go to what the
    outputs showed. The middle of the band from before the first hold (restored by the broken
    cadence, and kept through the release) moved a joint 1.26 deg where 20 deg/s allows 1.18
    (bench.state_cycles)."""
    ap = ArduPilotOutputsModel()
    ap.run(0.3)
    start = ap.core.status()["current_deg"]
    ap.goto([start[0] + 80.0, start[1] - 60.0, *start[2:]])
    ap.run(0.25)
    forged = ap.codec.sys_status_encode(MOTORS, MOTORS, MOTORS, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0)

    def run(seconds: float, *, forge: bool = True) -> None:
        for _ in range(round(seconds / 0.01)):
            ap.run(0.01)
            if forge:
                ap.carry_out(ap.frame(forged))

    ap.set_safety(True)
    run(0.2, forge=False)  # seen on, the held outputs sent back
    run(0.1)
    ap.reload(ap.config.joint_speed_deg_s / 3)
    run(0.2)
    ap.set_safety(False)
    run(0.2)
    assert ap.core.status()["safety_on"] is False
    live = dict(ap.pulse)
    ap.set_safety(True)
    run(0.5)
    ap.set_safety(False)
    ap.run(0.01)
    step_deg = ap.config.joint_speed_deg_s / ap.config.rate_hz + deg_per_us(ap)
    calibration = ap.config.calibration
    moved = {
        o: abs(
            calibration.for_output(o).pwm_us_to_angle_deg(ap.pulse[o])
            - calibration.for_output(o).pwm_us_to_angle_deg(live[o])
        )
        for o in live
    }
    assert max(moved.values()) <= step_deg + 1e-9, (live, ap.pulse)


@pytest.mark.parametrize("seed", range(10))
def test_ardupilot_no_joint_moves_faster_than_a_step_through_forged_sys_status_and_reloads(seed):
    """Random targets, the safety switch on and off, reboots, daemon restarts, reloads of the
    speed limit (20 to 120 deg/s) and spells of SYS_STATUS frames forged as "off" every 10 ms:
    every physical change of a pulse is within a step at the limit that judges it
    (``allowed_deg``). A band of poses kept from before a release, or from a faster limit,
    whose middle the held outputs were sent back to, moved joints up to 2.2 deg where 20 deg/s
    allows 1."""
    rng = np.random.default_rng(seed)
    ap = ArduPilotOutputsModel(safety_default_on=bool(seed % 2))
    forged = ap.codec.sys_status_encode(MOTORS, MOTORS, MOTORS, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0)
    ap.run(0.3)
    if ap.safety_on:
        ap.set_safety(False)
    forging = False
    for _ in range(80):
        roll = rng.random()
        if roll < 0.3:
            ap.goto(far_target(ap, rng))
        elif roll < 0.55:
            ap.set_safety(not ap.safety_on)
        elif roll < 0.7:
            forging = not forging
        elif roll < 0.85:
            ap.reload(float(rng.choice([20.0, 30.0, 60.0, 90.0, 120.0])))
        elif roll < 0.9 and ap.rebooting_until_s is None:
            ap.reboot_now()
        elif roll < 0.95:
            ap.restart_daemon()
        for _ in range(round(float(np.exp(rng.uniform(math.log(0.01), math.log(0.6)))) / 0.01)):
            ap.run(0.01)
            if forging:
                ap.carry_out(ap.frame(forged))
    assert len(ap.changes) > 50
    assert ap.fast_changes() == []
