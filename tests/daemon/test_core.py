"""The control core in-process: events in, actions out, a fake clock, no threads or sockets.

A fake solver makes a target's six numbers the joint angles it "solves" to (a first number
above 1000 is unreachable), so each test says exactly which joints it asks for. Frames are real
pymavlink frames, encoded by a codec standing in for the autopilot and decoded again.
"""

from __future__ import annotations

import logging
import math
from types import SimpleNamespace

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from companion.daemon.config import parse_config
from companion.daemon.core import (
    MARKER_OFFSET_US,
    PIPELINE_DEPTH,
    UPDATE_ATTEMPTS,
    Answer,
    ControlCore,
    ReadParam,
    SendCommand,
    stream_intervals_s,
)
from companion.daemon.requests import Outcome, Request
from companion.kinematics.arm import Pose
from tests.support.timing import FakeClock

PARK = (0.0, 90.0, 0.0, 0.0, 0.0, 0.0)
SPEED_DEG_S, RATE_HZ = 60.0, 20.0
STEP_DEG = SPEED_DEG_S / RATE_HZ  # 3 degrees a tick
SERVO = mavlink.MAV_CMD_DO_SET_SERVO
ACCEPTED, FAILED = mavlink.MAV_RESULT_ACCEPTED, mavlink.MAV_RESULT_FAILED


def fake_solve(pose, q_start_deg, mode="pose", budget_ms=None, *, seed=None):
    q = pose.as_tuple()
    return SimpleNamespace(
        q_deg=tuple(q),
        q_rad=np.radians(q),
        converged=q[0] < 1000,
        pos_err_cm=0.0 if q[0] < 1000 else 99.0,
        ori_err_deg=0.0,
        cost=0.0 if q[0] < 1000 else 99.0**2,
        elapsed_ms=0.1,
    )


class Rig:
    """A core, the autopilot's codec, and what came out.

    ArduPilot: once the test says where the safety switch is (:meth:`sys_status`), the rig
    streams SYS_STATUS saying so at the interval the core asked for, as ArduPilot does, until
    the link goes down or the core asks for the stream again (a reboot or a silence: the test
    says when the autopilot answers)."""

    def __init__(
        self, dialect: str = "ardupilot", sections: dict | None = None, **link: object
    ) -> None:
        self.clock = FakeClock()
        config = parse_config(
            {
                "link": {"url": "udpout:127.0.0.1:14550", "dialect": dialect, **link},
                "arm": {"park_deg": list(PARK), "joint_speed_deg_s": SPEED_DEG_S},
                "control": {"rate_hz": RATE_HZ},
                **(sections or {}),
            }
        )
        self.config = config
        self.calibration = config.calibration
        self.core = ControlCore(config, solve=fake_solve, clock=self.clock)
        self.sent: list[SendCommand] = []
        self.reads: list[ReadParam] = []
        self.answers: dict[int, list] = {}
        self.requests: list[Request] = []
        self.codecs: dict[tuple[int, int], mavlink.MAVLink] = {}
        self.decoder = mavlink.MAVLink(None)
        #: The safety switch the rig's SYS_STATUS stream says (None: not streaming).
        self.safety_stream: bool | None = None
        self._status_due_s = math.inf
        self.status_interval_s = stream_intervals_s(ardupilot=True, url=config.link.url)[1]

    # -- driving ----------------------------------------------------------------------------

    def take(self, actions) -> list[SendCommand]:
        new = []
        for action in actions:
            if isinstance(action, Answer):
                self.answers.setdefault(id(action.request), []).append(action.reply)
                action.request.answer(action.reply)
            elif isinstance(action, ReadParam):
                self.reads.append(action)
            else:
                new.append(action)
                if (
                    action.command == mavlink.MAV_CMD_SET_MESSAGE_INTERVAL
                    and action.params[0] == mavlink.MAVLINK_MSG_ID_SYS_STATUS
                ):
                    self.safety_stream = None  # asked again: the test says when it answers
        self.sent += new
        return new

    def frame(self, build, src=(1, 1)):
        codec = self.codecs.setdefault(src, mavlink.MAVLink(None, *src))
        buf = build(codec).pack(codec)
        msg = self.decoder.parse_buffer(buf)[0]
        return self.take(self.core.frame(msg))

    def heartbeat(self, src=(1, 1), autopilot=mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA):
        return self.frame(
            lambda c: c.heartbeat_encode(mavlink.MAV_TYPE_QUADROTOR, autopilot, 0, 0, 3), src
        )

    def ack(self, result=ACCEPTED, command=SERVO, src=(1, 1)):
        return self.frame(lambda c: c.command_ack_encode(command, result, 0, 0, 1, 191), src)

    def statustext(self, text, src=(1, 1)):
        return self.frame(lambda c: c.statustext_encode(6, text.encode()), src)

    def system_time(self, boot_ms, src=(1, 1)):
        return self.frame(lambda c: c.system_time_encode(0, boot_ms), src)

    def readback(self, pwm_by_output, src=(1, 1)):
        """A SERVO_OUTPUT_RAW showing ``pwm_by_output`` (others 0)."""
        values = [int(pwm_by_output.get(n, 0)) for n in range(1, 17)]
        return self.frame(lambda c: c.servo_output_raw_encode(0, 0, *values), src)

    def sys_status(self, safety_on, src=(1, 1), *, stream=True):
        """A SYS_STATUS; from the autopilot (``stream``), it goes on streaming that."""
        outputs = mavlink.MAV_SYS_STATUS_SENSOR_MOTOR_OUTPUTS
        enabled = 0 if safety_on else outputs
        if stream and src == (1, 1):
            self.safety_stream = safety_on
            self._status_due_s = self.clock() + self.status_interval_s
        return self.frame(
            lambda c: c.sys_status_encode(outputs, enabled, outputs, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0),
            src,
        )

    def tick(self, link_up=True):
        if not link_up:
            self.safety_stream = None
        elif self.safety_stream is not None and self.clock() >= self._status_due_s:
            self.sys_status(self.safety_stream)
        return self.take(self.core.tick(link_up))

    def advance(self, seconds, link_up=True):
        self.clock.advance(seconds)
        return self.tick(link_up)

    def up(self):
        self.heartbeat()
        sent = self.tick()
        if self.config.link.dialect.startswith("ardupilot"):
            self.sys_status(safety_on=False)  # ArduPilot moves once it knows the switch is off
        return sent

    def request(self, kind, payload=None, **kw) -> Request:
        request = Request(kind, payload, received_s=self.clock(), **kw)
        self.requests.append(request)  # alive: answers are keyed by id()
        self.take(self.core.request(request))
        return request

    def goto(self, q_deg) -> Request:
        return self.request("goto", tuple(q_deg))

    def reply(self, request):
        [reply] = self.answers.get(id(request), [None]) or [None]
        return reply

    # -- reading ----------------------------------------------------------------------------

    def servo(self, commands=None) -> dict[int, int]:
        """{output: pwm_us} of the DO_SET_SERVO commands given (default: all sent)."""
        commands = self.sent if commands is None else commands
        return {int(c.params[0]): int(c.params[1]) for c in commands if c.command == SERVO}

    def angle(self, output, pwm):
        return self.calibration.for_output(output).pwm_us_to_angle_deg(pwm)

    def ack_all(self, commands, result=ACCEPTED):
        out = []
        for c in list(commands):
            if c.command == SERVO:
                out += self.ack(result)
        return out


@pytest.fixture
def rig():
    rig = Rig()
    rig.up()
    return rig


def near(q_deg, delta_deg=STEP_DEG / 2):
    """Joints each within one step of the park pose: a target reached in one update."""
    return tuple(p + delta_deg for p in PARK)


# -- pipelined updates and acknowledged state ---------------------------------------------------


def test_an_update_goes_out_back_to_back_and_is_answered_once_every_ack_is_in(rig):
    request = rig.goto(near(PARK))
    first = [c for c in rig.sent if c.command == SERVO]
    assert len(first) == 6  # all six at once, before any ACK
    assert [c.confirmation for c in first] == [0] * 6
    for _ in first[:5]:
        rig.ack()
        assert not request.answered  # not before the last one
    rig.ack()
    assert rig.reply(request).outcome is Outcome.ACCEPTED
    status = rig.core.status()
    assert status["last_pwm_us"] == rig.servo(first)
    assert {o["state"] for o in status["outputs"].values()} == {"acknowledged"}
    assert status["current_deg"] == pytest.approx(near(PARK))


def test_acks_to_progress_counts_down_the_oldest_update_short_of_acks(rig):
    # The service wakes its control thread only on the ACK that can change something: a
    # partial count decides nothing (the tracker's verdict waits for the last one).
    assert rig.core.acks_to_progress() == 1  # nothing in flight: any ACK may matter
    rig.goto(PARK)
    rig.ack_all(rig.sent)
    rig.sent.clear()
    rig.clock.advance(0.02)
    first = rig.goto(near(PARK))
    assert rig.core.acks_to_progress() == 6
    rig.ack()
    rig.ack()
    assert rig.core.acks_to_progress() == 4 and not first.answered
    rig.clock.advance(0.01)
    rig.goto(tuple(p + 20.0 for p in PARK))  # a second update behind the first
    assert rig.core.acks_to_progress() == 4  # still the oldest's count
    for _ in range(3):
        rig.ack()
    assert rig.core.acks_to_progress() == 1 and not first.answered
    rig.ack()
    assert rig.reply(first).outcome is Outcome.ACCEPTED
    assert rig.core.acks_to_progress() == 6  # now the one behind


def test_only_outputs_whose_pwm_changed_are_sent(rig):
    rig.ack_all(rig.take(rig.core.request(Request("goto", near(PARK)))))
    rig.sent.clear()
    rig.advance(1.0 / RATE_HZ)
    moved = list(near(PARK))
    moved[2] += 1.0  # one joint
    rig.goto(moved)
    assert list(rig.servo()) == [11]


def test_a_refused_output_stops_the_motion_reports_what_moved_and_the_next_step_keeps_the_limit(
    rig,
):
    # Joint 6's output (14) is a motor on the autopilot: DO_SET_SERVO is refused with a
    # STATUSTEXT naming the channel. Before this was fixed, status said nothing moved and the
    # next target's step was computed from the stale park pose (a 5.9 deg jump in one step).
    far = tuple(p + 30.0 for p in PARK)
    request = rig.goto(far)
    first = [c for c in rig.sent if c.command == SERVO]
    assert len(first) == 6
    for _ in first[:5]:
        rig.ack()
    rig.ack(FAILED)
    rig.statustext("ServoRelayEvent: Channel 14 is already in use")
    rig.advance(0.2)  # past the grace for the STATUSTEXT
    reply = rig.reply(request)
    assert reply.outcome is Outcome.FAILED
    assert "output 14" in reply.message and "SERVO14_FUNCTION = 0" in reply.message
    # A ground station shows 50 characters: the fix first, whole (real ArduPilot's
    # STATUSTEXT cut the old message mid-word).
    assert reply.statustext() == "Arm: set SERVO14_FUNCTION=0 (output in use)"
    status = rig.core.status()
    assert status["goal_deg"] is None and not status["moving"]
    assert status["outputs"][14]["state"] == "refused"
    moved = rig.servo(first)
    assert status["last_pwm_us"] == {o: moved[o] for o in (9, 10, 11, 12, 13)}
    for j in range(5):
        assert status["current_deg"][j] == pytest.approx(PARK[j] + STEP_DEG)
    assert status["current_deg"][5] == PARK[5]
    # The next target steps from what was acknowledged: no joint moves more than a step.
    rig.sent.clear()
    rig.advance(1.0 / RATE_HZ)
    rig.goto(tuple(p - 30.0 for p in PARK))
    for output, pwm in rig.servo().items():
        before = status["last_pwm_us"].get(output, rig.calibration.angles_to_pwm_us(PARK)[output])
        assert abs(rig.angle(output, pwm) - rig.angle(output, before)) <= STEP_DEG + 0.2


def test_missing_acks_leave_the_outputs_unknown_and_each_is_confirmed_alone(rig):
    request = rig.goto(near(PARK))
    first = [c for c in rig.sent if c.command == SERVO]
    for _ in range(4):
        rig.ack()  # two ACKs lost: which ones cannot be told
    rig.sent.clear()
    rig.advance(rig.config.link.command_timeout_s)
    assert not request.answered
    assert rig.core.status()["last_pwm_us"] is None  # nothing taken for granted
    # Now one command at a time, each answered before the next.
    for expected in first:
        [alone] = [c for c in rig.sent if c.command == SERVO]
        assert alone.params == expected.params and alone.confirmation == 1
        rig.sent.clear()
        rig.ack()
    assert rig.reply(request).outcome is Outcome.ACCEPTED
    assert rig.core.status()["last_pwm_us"] == rig.servo(first)


def test_an_ack_too_many_is_not_trusted(rig):
    # A forged FAILED arrives before the six genuine ACCEPTED: seven answers for six commands.
    # Believing it would abort the motion (it did before); counting shows the accounting was
    # disturbed, and the outputs are confirmed one at a time instead.
    request = rig.goto(near(PARK))
    rig.ack(FAILED)
    for _ in range(6):
        rig.ack()
    rig.sent.clear()
    rig.advance(0.2)
    assert not request.answered
    assert len([c for c in rig.sent if c.command == SERVO]) == 1  # confirming one at a time
    for _ in range(6):
        rig.ack()
    assert rig.reply(request).outcome is Outcome.ACCEPTED


def test_an_update_that_stays_unanswered_fails_its_target_and_is_resent_before_moving_on(rig):
    request = rig.goto(tuple(p + 30.0 for p in PARK))
    first = rig.servo()
    for _ in range(1 + rig.config.link.command_retries):
        rig.advance(rig.config.link.command_timeout_s)
    reply = rig.reply(request)
    assert reply.outcome is Outcome.FAILED and "no COMMAND_ACK" in reply.message
    status = rig.core.status()
    assert status["goal_deg"] is None and status["last_pwm_us"] is None
    assert status["counters"]["servo_errors"] == 1
    # Nothing more is sent on its own; a new target sends the unconfirmed step again first,
    # not a step beyond it.
    rig.sent.clear()
    rig.advance(1.0)
    assert rig.servo() == {}
    rig.goto(tuple(p - 30.0 for p in PARK))
    assert rig.servo() == first


def test_a_moving_arm_survives_unanswered_updates_up_to_update_attempts(rig):
    request = rig.goto(tuple(p + 30.0 for p in PARK))
    rig.ack_all(rig.sent)
    assert rig.reply(request).outcome is Outcome.ACCEPTED
    for attempt in range(1, UPDATE_ATTEMPTS + 1):
        rig.advance(1.0 / RATE_HZ)  # a tick: the next step goes out
        for _ in range(1 + rig.config.link.command_retries):
            rig.advance(rig.config.link.command_timeout_s)  # and is never answered
        moving = rig.core.status()["goal_deg"] is not None
        assert moving == (attempt < UPDATE_ATTEMPTS)


def test_a_target_goes_out_behind_the_update_in_flight_and_acks_are_counted_in_order(rig):
    # On a 115 200-baud line an update takes 13-21 ms: a target arriving meanwhile used to
    # wait out the whole round trip before its first step went out.
    rig.goto(PARK)
    rig.ack_all(rig.sent)  # every output acknowledged: the state the pipe starts from
    rig.sent.clear()
    rig.clock.advance(0.02)
    first = rig.goto(near(PARK))
    ahead = rig.servo()
    rig.sent.clear()
    rig.clock.advance(0.01)  # half a tick later, the first update still in flight
    target = tuple(p + 20.0 for p in PARK)
    second = rig.goto(target)
    behind = [c for c in rig.sent if c.command == SERVO]
    assert len(behind) == 6  # every output the update ahead sent, at the new step
    for c in behind:
        output, pwm = int(c.params[0]), int(c.params[1])
        # One step from the command ahead of it, limited by the time since that one went out.
        assert 0 < rig.angle(output, pwm) - rig.angle(output, ahead[output]) <= STEP_DEG / 2 + 0.2
    for _ in range(6):
        rig.ack()
    assert rig.reply(first).outcome is Outcome.ACCEPTED and not second.answered
    assert rig.core.status()["last_pwm_us"] == ahead
    for _ in range(6):
        rig.ack()
    assert rig.reply(second).outcome is Outcome.ACCEPTED
    assert rig.core.status()["last_pwm_us"] == rig.servo(behind)
    # Never a third: the step after waits for the one ahead of it.
    rig.sent.clear()
    for delta_deg in (-20.0, -21.0, -22.0):
        rig.clock.advance(0.005)
        rig.goto(tuple(p + delta_deg for p in PARK))
    assert len([c for c in rig.sent if c.command == SERVO]) == 12


def test_an_unanswered_update_with_one_behind_it_is_decided_by_the_one_behind(rig):
    rig.goto(PARK)
    rig.ack_all(rig.sent)
    parked = rig.core.status()["last_pwm_us"]
    rig.sent.clear()
    rig.clock.advance(0.02)
    first = rig.goto(near(PARK))
    rig.clock.advance(0.01)
    second = rig.goto(tuple(p + 20.0 for p in PARK))
    ahead = rig.servo(rig.sent[:6])
    behind = [c for c in rig.sent if c.command == SERVO][6:]
    for _ in range(3):
        rig.ack()  # three of the first update's six: the rest lost, and all of the second's
    rig.sent.clear()
    rig.advance(rig.config.link.command_timeout_s - 0.005)  # the first's deadline
    assert not first.answered and not second.answered
    status = rig.core.status()
    assert status["last_pwm_us"] is None  # unknown, not "acknowledged at park"
    assert rig.servo() == {}  # no retry of the first: the second re-sent its outputs
    rig.advance(0.01)  # the second's deadline: its commands confirmed one at a time
    confirmed = {}
    for expected in behind:
        [alone] = [c for c in rig.sent if c.command == SERVO]
        output, pwm = int(alone.params[0]), int(alone.params[1])
        assert output == int(expected.params[0])
        # Each output holds park, the first step or the second: it is confirmed at their
        # middle (within one step of each), not at the second step (two from park).
        held = [parked[output], ahead[output], int(expected.params[1])]
        assert pwm == pytest.approx((min(held) + max(held)) / 2, abs=1)
        confirmed[output] = pwm
        rig.sent.clear()
        rig.ack()
    # Both targets are answered by the outcome of the update that carried their outputs.
    assert rig.reply(first).outcome is Outcome.ACCEPTED
    assert rig.reply(second).outcome is Outcome.ACCEPTED
    assert rig.core.status()["last_pwm_us"] == confirmed


# -- requests ----------------------------------------------------------------------------------


def test_a_stop_before_the_first_step_went_out_cancels_the_target_and_nothing_is_sent(rig):
    first = rig.goto(near(PARK))  # its update is in flight ...
    second = rig.goto(tuple(p + 1.0 for p in PARK))  # ... so this one waits
    rig.sent.clear()
    stop = rig.request("stop")
    assert rig.reply(stop).outcome is Outcome.ACCEPTED
    assert rig.reply(second).outcome is Outcome.CANCELLED
    rig.ack_all([SendCommand((1, 1), SERVO, (0,) * 7)] * 6)
    # The first target's step was on its way: it is answered with what happened.
    assert rig.reply(first).outcome is Outcome.ACCEPTED
    rig.advance(1.0)
    assert rig.servo() == {}  # nothing for the cancelled target, ever


def test_a_newer_target_supersedes_one_waiting_for_its_first_step(rig):
    first = rig.goto(near(PARK))
    waiting = rig.goto(tuple(p + 1.0 for p in PARK))
    newest = rig.goto(tuple(p + 1.2 for p in PARK))
    assert rig.reply(waiting).outcome is Outcome.CANCELLED
    rig.ack_all(rig.sent)  # the first target's six
    assert rig.reply(first).outcome is Outcome.ACCEPTED
    before = len(rig.sent)
    rig.advance(1.0 / RATE_HZ)  # the speed limit counts from the last step
    rig.ack_all(rig.sent[before:])
    assert rig.reply(newest).outcome is Outcome.ACCEPTED
    assert rig.core.status()["current_deg"] == pytest.approx(tuple(p + 1.2 for p in PARK))


@pytest.mark.parametrize(
    ("payload", "outcome"),
    [((math.nan, 0, 0, 0, 0, 0), Outcome.DENIED), ((2000, 0, 0, 0, 0, 0), Outcome.FAILED)],
)
def test_bad_targets_are_refused_and_nothing_moves(rig, payload, outcome):
    request = rig.goto(payload)
    assert rig.reply(request).outcome is outcome
    assert rig.servo() == {}


def test_targets_while_the_link_is_down_are_temporarily_rejected():
    rig = Rig()
    rig.heartbeat()
    request = rig.goto(near(PARK))  # pinned, but no tick has seen the link up yet
    assert rig.reply(request).outcome is Outcome.TEMPORARILY_REJECTED


# -- the autopilot -----------------------------------------------------------------------------


def test_the_first_autopilot_is_pinned_and_others_are_ignored():
    rig = Rig()
    rig.heartbeat(src=(42, 1))  # heard first
    rig.tick()
    assert rig.core.status()["autopilot"] == [42, 1]
    rig.heartbeat(src=(1, 1))
    assert rig.core.status()["autopilot"] == [42, 1]  # never changed while running
    request = rig.goto(near(PARK))
    assert {c.target for c in rig.sent} == {(42, 1)}
    for _ in range(6):
        rig.ack(src=(1, 1))  # ACKs from anyone else do not count
    assert not request.answered
    assert rig.core.status()["counters"]["foreign_frames"] == 7


def test_a_configured_autopilot_is_the_only_one_pinned():
    # A fake autopilot (42/1) heard first used to be adopted for good.
    rig = Rig(target_system=1)
    rig.heartbeat(src=(42, 1))
    rig.heartbeat(src=(1, 1))
    rig.tick()
    assert rig.core.status()["autopilot"] == [1, 1]


def test_a_ground_station_heartbeat_is_not_an_autopilot():
    rig = Rig()
    rig.heartbeat(src=(255, 190), autopilot=mavlink.MAV_AUTOPILOT_INVALID)
    rig.tick()
    assert rig.core.status()["autopilot"] is None


def test_system_time_readback_and_safety_are_asked_for_once_pinned(rig):
    asks = [c for c in rig.sent if c.command == mavlink.MAV_CMD_SET_MESSAGE_INTERVAL]
    assert [a.params[0] for a in asks] == [
        mavlink.MAVLINK_MSG_ID_SYSTEM_TIME,
        mavlink.MAVLINK_MSG_ID_SERVO_OUTPUT_RAW,
        mavlink.MAVLINK_MSG_ID_SYS_STATUS,
    ]
    assert all(a.params[1] > 0 for a in asks)
    assert [r.name for r in rig.reads] == ["BRD_SAFETY_MASK"]


@pytest.mark.parametrize(
    ("url", "dialect", "interval_s"),
    [
        ("/dev/ttyAMA0,115200", "ardupilot-lua", 1.0),  # status only: spare the slow line
        ("/dev/ttyAMA0,921600", "ardupilot", 0.1),
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


def test_a_reboot_within_the_loss_timeout_is_seen_and_every_output_resent(rig):
    # An autopilot restarted in 0.36 s went unnoticed: status "up" with the old PWMs while its
    # outputs were at 0, and the next target sent only the output that changed.
    rig.system_time(600_000)
    request = rig.goto(near(PARK))
    rig.ack_all(rig.sent)
    assert rig.reply(request).outcome is Outcome.ACCEPTED
    rig.sent.clear()
    rig.advance(0.36)
    rig.system_time(150)  # time_boot_ms went back: it rebooted
    status = rig.core.status()
    assert status["counters"]["autopilot_reboots"] == 1
    assert status["last_pwm_us"] is None
    assert any(c.command == mavlink.MAV_CMD_SET_MESSAGE_INTERVAL for c in rig.sent)
    rig.advance(1.0 / RATE_HZ)
    # ArduPilot boots with its safety switch on (BRD_SAFETY_DEFLT): what is sent before a
    # SYS_STATUS says where it is would be stored, and go out in one step at its release.
    assert rig.servo() == {}
    rig.sys_status(safety_on=False)
    rig.advance(1.0 / RATE_HZ)
    assert sorted(rig.servo()) == [9, 10, 11, 12, 13, 14]  # every output, not only changes


def test_system_time_going_quiet_resends_every_output_at_once_even_with_the_arm_still(rig):
    rig.system_time(600_000)
    rig.ack_all(rig.take(rig.core.request(Request("goto", near(PARK)))))
    acked = rig.core.status()["last_pwm_us"]
    assert not rig.core.status()["moving"]
    rig.sys_status(safety_on=False)  # the switch off with the update acknowledged
    rig.sent.clear()
    rig.safety_stream = None  # silent: it may have rebooted and forgotten every stream
    rig.advance(1.5)  # no SYSTEM_TIME
    assert any(c.command == mavlink.MAV_CMD_SET_MESSAGE_INTERVAL for c in rig.sent)
    assert rig.servo() == {}  # not before a SYS_STATUS said where its safety switch is
    rig.sys_status(safety_on=False)
    rig.advance(1.0 / RATE_HZ)
    # A reboot left the outputs at their boot values: the acknowledged PWMs go out again with
    # no new target (before: only with the next target).
    assert rig.servo() == acked
    rig.ack_all(rig.sent)
    assert rig.core.status()["last_pwm_us"] == acked
    moved = list(near(PARK))
    moved[0] += 1.0
    rig.goto(moved)
    assert sorted(rig.servo()) == [9, 10, 11, 12, 13, 14]


def test_the_first_frame_after_a_silence_asks_for_every_stream_at_once(rig):
    # A rebooted autopilot forgot our streams; its first HEARTBEAT back brings them back
    # without waiting for a silence rule (status said "not known live" meanwhile).
    rig.system_time(600_000)
    rig.safety_stream = None
    rig.clock.advance(0.3)  # silent (no tick either)
    rig.sent.clear()
    rig.heartbeat()
    asked = {
        int(c.params[0]) for c in rig.sent if c.command == mavlink.MAV_CMD_SET_MESSAGE_INTERVAL
    }
    assert {mavlink.MAVLINK_MSG_ID_SYSTEM_TIME, mavlink.MAVLINK_MSG_ID_SYS_STATUS} <= asked
    rig.sent.clear()
    rig.heartbeat()  # not again for the next frame
    assert not [c for c in rig.sent if c.command == mavlink.MAV_CMD_SET_MESSAGE_INTERVAL]


def test_an_autopilot_that_only_beats_is_not_asked_for_its_streams_at_every_heartbeat():
    rig = Rig()
    rig.heartbeat()
    rig.tick()
    rig.sent.clear()
    for _ in range(3):  # 1 Hz HEARTBEATs, nothing else (streams not supported)
        rig.clock.advance(1.0)
        rig.heartbeat()
    assert not [c for c in rig.sent if c.command == mavlink.MAV_CMD_SET_MESSAGE_INTERVAL]


def test_link_loss_holds_rejects_waiting_targets_and_resends_every_output_when_back(rig):
    request = rig.goto(tuple(p + 30.0 for p in PARK))
    rig.ack_all(rig.sent)
    assert rig.reply(request).outcome is Outcome.ACCEPTED
    acked = rig.core.status()["last_pwm_us"]
    rig.sent.clear()
    rig.advance(1.0 / RATE_HZ)  # the next step is in flight when the link goes
    in_flight = rig.servo()
    assert len(in_flight) == 6
    rig.sent.clear()
    rig.advance(0.1, link_up=False)
    assert rig.core.status()["holding"]
    late = rig.goto(near(PARK))
    assert rig.reply(late).outcome is Outcome.TEMPORARILY_REJECTED
    rig.advance(5.0, link_up=False)
    assert rig.servo() == {}  # nothing while holding
    rig.advance(0.01)
    assert rig.servo() == {}  # not before a SYS_STATUS said where its safety switch is
    rig.sys_status(safety_on=False)
    rig.advance(1.0 / RATE_HZ)
    # Back: every output within half a step of both poses it may hold (the acknowledged one
    # and the step on its way), then on towards the goal.
    resent = rig.servo()
    assert sorted(resent) == sorted(in_flight)
    for output, pwm in resent.items():
        held = [acked[output], in_flight[output]]
        assert min(held) <= pwm <= max(held)
        for before in held:
            assert abs(rig.angle(output, pwm) - rig.angle(output, before)) <= STEP_DEG / 2 + 0.1


def test_shutdown_answers_everything_and_parks_every_output_directly(rig):
    first = rig.goto(tuple(p + 30.0 for p in PARK))  # in flight
    waiting = rig.goto(tuple(p + 20.0 for p in PARK))
    rig.sent.clear()
    rig.take(rig.core.shutdown(park=True))
    assert rig.reply(waiting).outcome is Outcome.CANCELLED  # never sent
    assert rig.reply(first).outcome is Outcome.FAILED  # sent, then overridden by the park
    assert rig.servo() == rig.calibration.angles_to_pwm_us(PARK)  # all six, past the limit
    rig.ack_all(rig.sent)
    assert rig.core.parked() and rig.core.idle


def test_px4_sends_one_frame_for_every_joint():
    rig = Rig(dialect="px4")
    rig.heartbeat(autopilot=mavlink.MAV_AUTOPILOT_PX4)
    rig.tick()
    rig.readback(rig.calibration.angles_to_pwm_us(PARK))  # PX4 moves once it knows where
    request = rig.goto(near(PARK))
    [frame] = [c for c in rig.sent if c.command == mavlink.MAV_CMD_DO_SET_ACTUATOR]
    rig.ack(command=mavlink.MAV_CMD_DO_SET_ACTUATOR)
    assert rig.reply(request).outcome is Outcome.ACCEPTED
    assert frame.params[6] == 0.0


# -- properties --------------------------------------------------------------------------------

_EVENTS = st.one_of(
    st.tuples(
        st.just("goto"), st.lists(st.floats(1, 40) | st.floats(-40, -1), min_size=6, max_size=6)
    ),
    st.tuples(st.just("unreachable"), st.none()),
    st.tuples(st.just("nan"), st.none()),
    st.tuples(st.sampled_from(["stop", "park"]), st.none()),
    st.tuples(st.just("ack"), st.sampled_from([ACCEPTED, ACCEPTED, ACCEPTED, FAILED, 1])),
    st.tuples(st.just("advance"), st.sampled_from([0.001, 0.02, 0.05, 0.3, 0.6])),
    st.tuples(st.just("link"), st.booleans()),
    st.tuples(st.just("reboot"), st.none()),
)


@settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(events=st.lists(_EVENTS, max_size=60))
def test_any_sequence_answers_every_request_once_keeps_the_limit_and_the_range(events):
    rig = Rig()
    rig.up()
    boot_ms = 10_000
    requests: list[tuple[Request, tuple | None]] = []
    link_up = True
    cal = rig.calibration
    for kind, arg in events:
        position = rig.core.status()["current_deg"]
        before = len(rig.sent)
        if kind == "goto":
            q = tuple(p + a for p, a in zip(PARK, arg, strict=True))
            requests.append((rig.goto(q), q))
        elif kind == "unreachable":
            requests.append((rig.goto((2000, 0, 0, 0, 0, 0)), None))
        elif kind == "nan":
            requests.append((rig.goto((math.nan,) * 6), None))
        elif kind in ("stop", "park"):
            requests.append((rig.request(kind), None))
        elif kind == "ack":
            rig.ack(arg)
        elif kind == "advance":
            rig.advance(arg, link_up)
        elif kind == "link":
            link_up = arg
            rig.tick(link_up)
        else:
            boot_ms = 5 if boot_ms > 1000 else 100_000
            rig.system_time(boot_ms)
        for c in rig.sent[before:]:
            if c.command != SERVO:
                continue
            output, pwm = int(c.params[0]), int(c.params[1])
            low, high = cal.for_output(output).pwm_range_us
            assert low <= pwm <= high
            joint = cal.outputs.index(output)
            # Never more than one step per update in flight from what the autopilot
            # acknowledged (the next step may go out behind the one in flight).
            bound = PIPELINE_DEPTH * STEP_DEG + 0.2
            assert abs(rig.angle(output, pwm) - position[joint]) <= bound
        goal = rig.core.status()["goal_deg"]
        replies = [(rig.reply(r), q) for r, q in requests if q is not None]
        live = {q for reply, q in replies if reply is None or reply.outcome is Outcome.ACCEPTED}
        for reply, q in replies:
            if reply is not None and reply.outcome is not Outcome.ACCEPTED and q not in live:
                assert goal is None or tuple(goal) != q  # never carried out
    rig.take(rig.core.shutdown(park=False))
    rig.take(rig.core.finish())
    for request, _ in requests:
        assert len(rig.answers.get(id(request), [])) == 1, request


def test_the_next_wake_moves_on_while_the_link_is_down():
    # It stayed in the past while no autopilot was heard: the control thread spun at 100 % CPU.
    rig = Rig()
    for _ in range(3):
        rig.advance(0.01, link_up=False)
        assert rig.core.next_wake_s() > rig.clock()


def test_a_reboot_soon_after_boot_is_seen_by_time_boot_falling_behind(rig):
    # Up 1 s, rebooted, its SYSTEM_TIME back 1.2 s later reading 900 ms: not below 1000, but
    # 1.3 s behind where it should be.
    rig.system_time(1_000)
    rig.clock.advance(1.2)
    rig.system_time(900)
    assert rig.core.status()["counters"]["autopilot_reboots"] == 1


def test_a_reboot_right_after_boot_is_seen_once_the_silent_stream_comes_back(rig):
    # Seen in a full test run: the simulator rebooted 0.22 s after it started; 1 s of silence
    # later the stream, asked for again, read 0.58 s less than the time since the last one:
    # under REBOOT_LAG_MS, but after a silence the smaller lag is evidence enough.
    rig.system_time(200)
    rig.advance(1.2)  # silent: asked again
    rig.system_time(200 + 1_200 - 580)
    assert rig.core.status()["counters"]["autopilot_reboots"] == 1


def test_a_reboot_right_after_boot_is_seen_when_the_stream_comes_back_before_its_silence(rig):
    # Seen in a full test run: the streams asked for again after a silent SYS_STATUS (0.5 s)
    # brought SYSTEM_TIME back before its own silence (1 s) was noticed, 0.56 s behind: the gap
    # itself is the silence.
    rig.system_time(200)
    rig.clock.advance(0.8)
    rig.system_time(200 + 800 - 560)
    assert rig.core.status()["counters"]["autopilot_reboots"] == 1


def test_a_late_system_time_is_not_a_reboot(rig):
    rig.system_time(60_000)
    rig.clock.advance(0.25)
    rig.system_time(60_000)  # arrived 250 ms late
    rig.clock.advance(0.25)
    rig.system_time(60_500)
    assert rig.core.status()["counters"]["autopilot_reboots"] == 0


def test_a_stream_of_targets_logs_one_accepted_line_a_second_per_source(rig, caplog):
    # Issue 15 wants each target carried out logged; at 50 Hz that is 180 000 journal lines an
    # hour on an SD card: one line a second per source, saying how many it stands for.
    caplog.set_level(logging.INFO, logger="armbridge")
    gcs = ("mavlink", 255, 190)
    kept = []  # alive: the rig files answers by id()
    for k in range(20):
        request = rig.request("goto", near(PARK, 0.2 * (k % 2)), source=gcs)
        kept.append(request)
        rig.ack_all(rig.sent)
        rig.sent.clear()
        assert rig.reply(request).outcome is Outcome.ACCEPTED
        rig.clock.advance(0.02)
    rig.request("goto", near(PARK), source=("socket", 3))  # another source: its own line
    rig.ack_all(rig.sent)
    rig.clock.advance(1.0)
    rig.request("goto", near(PARK, 0.2), source=gcs)
    rig.ack_all(rig.sent)
    rig.request("stop", source=gcs)  # never thinned out
    lines = [r.getMessage() for r in caplog.records if " accepted: " in r.getMessage()]
    assert len(lines) == 4, lines
    assert lines[0].startswith("goto (") and "from mavlink 255/190 accepted: moving" in lines[0]
    assert "from socket 3 accepted" in lines[1]
    assert lines[2].endswith("(and 19 more since the last line)")
    assert lines[3].startswith("stop from mavlink 255/190 accepted")


def test_the_autopilot_has_heard_us_only_once_it_answered_us_since_the_link_came_up():
    """Issue 20: the autopilot routes a ground station's targets to us only once it has heard
    us; its answer to the SYSTEM_TIME request sent at link-up proves it. A loss resets it."""
    rig = Rig()
    asks = rig.up()
    assert {a.command for a in asks} == {mavlink.MAV_CMD_SET_MESSAGE_INTERVAL}
    assert rig.core.status()["autopilot_heard_us"] is False
    rig.ack(command=mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, src=(2, 1))  # not the pinned one
    assert rig.core.status()["autopilot_heard_us"] is False
    rig.ack(command=mavlink.MAV_CMD_SET_MESSAGE_INTERVAL)
    assert rig.core.status()["autopilot_heard_us"] is True
    rig.tick(link_up=False)
    assert rig.core.status()["autopilot_heard_us"] is False
    rig.tick(link_up=True)
    assert rig.core.status()["autopilot_heard_us"] is False


# -- the outputs' truth (issue 20) --------------------------------------------------------------

ACTUATOR = mavlink.MAV_CMD_DO_SET_ACTUATOR


class Px4Outputs:
    """PX4's outputs as measured on SITL, for these tests: DO_SET_ACTUATOR stores values (NaN:
    unchanged) and is always ACCEPTED; the outputs show the disarmed PWM until live, then the
    stored values at once; SERVO_OUTPUT_RAW reads back what they show."""

    def __init__(self, rig: Rig, disarmed_us: int) -> None:
        self.rig = rig
        self.disarmed_us = disarmed_us
        self.live = False
        self.stored: dict[int, int | None] = dict.fromkeys(rig.calibration.outputs)
        self.physical_moves: list[tuple[int, int, int]] = []  # (output, from, to)
        self.shown = self._shown()

    def _shown(self) -> dict[int, int]:
        return {
            o: (v if self.live and v is not None else self.disarmed_us)
            for o, v in self.stored.items()
        }

    def _refresh(self, record: bool = True) -> None:
        shown = self._shown()
        for o, pwm in shown.items():
            if pwm != self.shown[o] and record:
                self.physical_moves.append((o, self.shown[o], pwm))
        self.shown = shown

    def handle(self) -> None:
        """Apply and acknowledge every DO_SET_ACTUATOR sent so far, one after the other."""
        for _ in self.apply(one=True):
            self.rig.ack(command=ACTUATOR)

    def apply(self, one: bool = False) -> list[SendCommand]:
        """Apply every DO_SET_ACTUATOR sent so far, its ACK not sent yet (PX4 answers on its
        commander's cycle, after the output cycle may have applied it); ``one``: each command's
        outputs change apart (as many physical moves as commands)."""
        commands = [c for c in self.rig.sent if c.command == ACTUATOR]
        self.rig.sent.clear()
        for c in commands:
            for slot, output in enumerate(self.rig.calibration.outputs):
                value = c.params[slot]
                if not math.isnan(value):
                    joint = self.rig.calibration.for_output(output)
                    span = joint.pwm_max_us - joint.pwm_min_us
                    self.stored[output] = round(joint.pwm_min_us + (value + 1) / 2 * span)
            if one:
                self._refresh()
        self._refresh()
        return commands

    def set_live(self, live: bool) -> None:
        """Arm or prearm (live), disarm or kill (not). Disarming drives every output to the
        disarmed PWM at once: PX4's doing, not ours, so not recorded as a move."""
        self.live = live
        self._refresh(record=live)

    def readback(self) -> None:
        self.rig.readback(self.shown)


def px4_rig(disarmed_us: int = 1500) -> tuple[Rig, Px4Outputs]:
    rig = Rig(dialect="px4")
    rig.heartbeat(autopilot=mavlink.MAV_AUTOPILOT_PX4)
    rig.tick()
    rig.sent.clear()
    return rig, Px4Outputs(rig, disarmed_us)


def run(rig: Rig, px4: Px4Outputs, seconds: float, step_s: float = 0.05) -> None:
    """Time passes: ticks, PX4 handles what was sent, readbacks every 0.1 s."""
    for _ in range(round(seconds / step_s)):
        rig.advance(step_s)
        px4.handle()
        if round(rig.clock() / step_s) % 2 == 0:
            px4.readback()


def test_px4_moves_only_once_a_readback_said_where_the_joints_are():
    rig, px4 = px4_rig(disarmed_us=1500)
    px4.set_live(True)  # prearmed: live, showing the disarmed PWM (nothing stored yet)
    request = rig.goto(near(PARK))
    assert not [c for c in rig.sent if c.command == ACTUATOR]  # no readback yet
    px4.readback()
    run(rig, px4, 0.2)
    assert rig.reply(request).outcome is Outcome.ACCEPTED
    # It started from where the outputs were (1500 us), not from the assumed park pose.
    first = px4.physical_moves[0]
    joint = rig.calibration.for_output(first[0])
    step_us = STEP_DEG / (joint.angle_max_deg - joint.angle_min_deg) * 1000
    assert first[1] == 1500 and abs(first[2] - first[1]) <= step_us + 1


def test_px4_outputs_that_do_not_show_what_they_acknowledged_hold_the_arm():
    rig, px4 = px4_rig(disarmed_us=1500)
    px4.readback()
    request = rig.goto(near(PARK, 20.0))  # far: many steps
    run(rig, px4, 1.0)  # disarmed: every step ACCEPTED, none shown
    assert rig.reply(request).outcome is Outcome.ACCEPTED
    status = rig.core.status()
    assert status["outputs_live"] is False
    why = status["not_live"][str(rig.calibration.outputs[0])]
    assert "shows 1500 us, not the" in why and "acknowledged" in why
    # Held: at most one probing step a second goes out while they stay dead.
    sent_before = len(px4.physical_moves), rig.core.counters["servo_updates"]
    run(rig, px4, 3.0)
    assert rig.core.counters["servo_updates"] - sent_before[1] <= 4
    later = rig.goto(near(PARK, 19.0))
    assert "outputs not live" in rig.reply(later).message
    assert rig.reply(later).outcome is Outcome.ACCEPTED
    # Armed: no output jumps by more than one step; then the arm goes on to the goal.
    px4.set_live(True)
    run(rig, px4, 6.0)
    assert rig.core.status()["outputs_live"] is True
    for output, before, after in px4.physical_moves:
        joint = rig.calibration.for_output(output)
        step_us = STEP_DEG / (joint.angle_max_deg - joint.angle_min_deg) * 1000
        assert abs(after - before) <= step_us + 1, (output, before, after)
    assert rig.core.status()["goal_deg"] == pytest.approx(list(near(PARK, 19.0)))
    assert rig.core.status()["moving"] is False


def test_px4_a_readback_showing_a_step_before_its_ack_is_not_a_dead_output():
    # PX4 applies DO_SET_ACTUATOR on its output cycle and answers on its commander's: a
    # readback in between shows a step not acknowledged yet. Taken for "not what was
    # acknowledged", it held the arm as if disarmed (a target waited 201 ms in bench.latency).
    rig, px4 = px4_rig(disarmed_us=1500)
    px4.set_live(True)
    px4.readback()
    rig.goto(near(PARK))
    run(rig, px4, 0.5)
    assert rig.core.status()["outputs_live"] is True
    request = rig.goto(near(PARK, 20.0))
    unanswered = px4.apply()
    px4.readback()  # shows the step before its ACK
    for _ in unanswered:
        rig.ack(command=ACTUATOR)
    assert rig.reply(request).outcome is Outcome.ACCEPTED
    assert rig.core.status()["outputs_live"] is True
    rig.advance(1.0 / RATE_HZ)
    assert [c for c in rig.sent if c.command == ACTUATOR]  # the next step at once


def test_px4_after_a_reboot_the_stale_pose_is_not_sent_again():
    rig, px4 = px4_rig(disarmed_us=1500)
    px4.set_live(True)
    px4.readback()
    rig.goto(near(PARK))
    run(rig, px4, 0.5)
    rig.system_time(600_000)
    rig.advance(0.36)
    rig.sent.clear()
    rig.system_time(150)  # rebooted: its outputs are back at the disarmed PWM
    px4.stored = dict.fromkeys(px4.stored)
    px4.set_live(True)
    rig.tick()
    assert not [c for c in rig.sent if c.command == ACTUATOR]


def max_physical_step_us(px4: Px4Outputs) -> float:
    """The largest physical move over one step's PWM (≤ 1: within the speed limit)."""
    worst = 0.0
    for output, before, after in px4.physical_moves:
        joint = px4.rig.calibration.for_output(output)
        step_us = STEP_DEG / (joint.angle_max_deg - joint.angle_min_deg) * 1000
        worst = max(worst, abs(after - before) / (step_us + 1))
    return worst


def assert_seen_live_at_the_next_readback(rig: Rig, px4: Px4Outputs) -> None:
    """Armed with the markers stored: the first readback says live, and nothing jumped."""
    px4.set_live(True)
    px4.readback()
    assert rig.core.status()["outputs_live"] is True
    assert max_physical_step_us(px4) <= 1.0


def test_px4_outputs_found_dead_hold_a_marker_and_are_seen_live_at_the_next_readback():
    rig, px4 = px4_rig(disarmed_us=1500)
    px4.set_live(True)
    px4.readback()
    rig.goto(near(PARK, 20.0))
    run(rig, px4, 0.5)
    assert rig.core.status()["outputs_live"] is True
    px4.set_live(False)  # disarm: every output at 1500
    px4.readback()  # the first readback tells (they were confirmed live)
    assert rig.core.status()["outputs_live"] is False
    # The markers go out at once (not at the next tick), 2 us from the disarmed PWM.
    sent = [c for c in rig.sent if c.command == ACTUATOR]
    assert len(sent) == 1
    px4.handle()
    assert set(px4.stored.values()) <= {1500 + MARKER_OFFSET_US, 1500 - MARKER_OFFSET_US}
    # Dead, nothing more is sent (no probing steps): the goal waits.
    updates = rig.core.counters["servo_updates"]
    run(rig, px4, 3.0)
    assert rig.core.counters["servo_updates"] == updates
    assert rig.core.status()["outputs_live"] is False
    # Armed: the next readback shows the markers; live again, and the motion goes on.
    px4.set_live(True)
    px4.readback()
    assert rig.core.status()["outputs_live"] is True
    run(rig, px4, 2.0)
    assert rig.core.counters["servo_updates"] > updates
    assert max_physical_step_us(px4) <= 1.0


def test_px4_an_update_on_its_way_when_the_outputs_die_does_not_replace_their_hold():
    # Found dead while a step was on its way: that step's ACK came after, and its pose was
    # taken as the joints' (the hold stored it: at a re-arm the outputs went from the
    # disarmed PWM to it, bench.output_cycles' "arm then arm" fast command steps).
    rig, px4 = px4_rig(disarmed_us=1500)
    px4.set_live(True)
    px4.readback()
    rig.goto(near(PARK, 20.0))  # 7 steps
    run(rig, px4, 0.2)
    rig.advance(1.0 / RATE_HZ)  # the next step goes out...
    on_its_way = px4.apply()
    assert on_its_way
    px4.set_live(False)
    px4.readback()  # ...the outputs are found dead before its ACK
    for _ in on_its_way:
        rig.ack(command=ACTUATOR)
    rig.advance(1.0 / RATE_HZ)
    px4.handle()  # the hold
    px4.set_live(True)  # re-armed before the readback saw the hold
    run(rig, px4, 2.0)
    assert max_physical_step_us(px4) <= 1.0


def test_px4_at_the_start_with_the_arm_still_the_markers_say_whether_it_is_live():
    rig, px4 = px4_rig(disarmed_us=1500)
    status = rig.core.status()
    assert status["outputs_live"] is False and "no SERVO_OUTPUT_RAW yet" in str(status["not_live"])
    px4.readback()  # disarmed, nothing stored: 1500 everywhere
    assert "not known live yet" in str(rig.core.status()["not_live"])
    run(rig, px4, 0.5)  # markers stored, not shown: not live
    assert px4.stored[rig.calibration.outputs[0]] == 1500 + MARKER_OFFSET_US
    status = rig.core.status()
    assert status["outputs_live"] is False and "shows 1500 us" in str(status["not_live"])
    assert_seen_live_at_the_next_readback(rig, px4)


def test_px4_a_reboot_while_not_live_forgets_the_markers_and_stores_them_again():
    # A rebooted PX4 holds nothing: waiting for the markers stored before it to show would
    # wait for ever (status "not live" through every later arm, bench.output_cycles).
    rig, px4 = px4_rig(disarmed_us=1500)
    px4.readback()
    run(rig, px4, 0.5)
    assert rig.core.status()["outputs_live"] is False  # held at the markers
    rig.system_time(600_000)
    rig.advance(0.3)
    rig.system_time(150)  # rebooted: nothing stored, disarmed
    px4.stored = dict.fromkeys(px4.stored)
    px4.set_live(False)
    assert "not known live" in str(rig.core.status()["not_live"])
    run(rig, px4, 0.5)
    assert set(px4.stored.values()) <= {1500 + MARKER_OFFSET_US, 1500 - MARKER_OFFSET_US}
    assert_seen_live_at_the_next_readback(rig, px4)


def test_px4_markers_go_out_even_where_the_disarmed_pose_lies_in_a_keepout_volume():
    # The outputs are where the readback shows them whatever the volumes; a marker moves them
    # 2 us. Checked as a motion, it was refused at every tick (and the outputs never known).
    from companion.kinematics.vehicle import Mount

    disarmed_us = 1100  # far from park: the config refuses a park in a volume

    calibration = Rig().calibration
    q_dis = [
        calibration.for_output(o).pwm_us_to_angle_deg(disarmed_us) for o in calibration.outputs
    ]
    centre = Mount().to_body(Rig().config.arm.fk(q_dis).position_cm)
    sphere = {"name": "ball", "type": "sphere", "center_cm": list(centre), "radius_cm": 4.0}
    rig = Rig(dialect="px4", sections={"keepout": [sphere]})
    rig.heartbeat(autopilot=mavlink.MAV_AUTOPILOT_PX4)
    rig.tick()
    px4 = Px4Outputs(rig, disarmed_us)
    px4.readback()
    run(rig, px4, 0.5)
    assert rig.core.status()["counters"]["keepout_refusals"] == 0
    assert px4.stored[rig.calibration.outputs[0]] == disarmed_us + MARKER_OFFSET_US
    assert_seen_live_at_the_next_readback(rig, px4)


def test_px4_a_silent_readback_says_nothing_of_the_outputs_and_the_streams_are_asked_again():
    rig, px4 = px4_rig(disarmed_us=1500)
    px4.set_live(True)
    run(rig, px4, 0.5)
    assert rig.core.status()["outputs_live"] is True
    rig.sent.clear()
    for _ in range(5):
        rig.advance(0.02)  # no readback: a reboot, a link gone quiet
    assert "no SERVO_OUTPUT_RAW for" in str(rig.core.status()["not_live"])
    for _ in range(25):
        rig.advance(0.02)
    assert any(c.command == mavlink.MAV_CMD_SET_MESSAGE_INTERVAL for c in rig.sent)


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
    rig.advance(0.05)
    assert rig.core.status()["outputs_live"] is True and rig.servo()


@settings(max_examples=40, deadline=None)
@given(
    st.lists(
        st.tuples(
            st.sampled_from(["live", "dead", "goto", "run"]),
            st.floats(-25, 25),
        ),
        min_size=1,
        max_size=12,
    )
)
def test_property_px4_outputs_never_jump_faster_than_the_speed_limit(events):
    """Issue 20: over any arm/disarm/prearm sequence and targets, no output moves by more than
    one step's PWM at once, neither on our commands nor when the outputs come alive (the
    disarmed PWM within the calibration, as PWM_MAIN_DIS = park makes it). Disarming drives
    them to the disarmed PWM at once: PX4's own jump, not counted."""
    rig, px4 = px4_rig(disarmed_us=rig_park_pwm())
    px4.readback()
    for kind, value in events:
        if kind == "live":
            px4.set_live(True)
        elif kind == "dead":
            px4.set_live(False)
        elif kind == "goto":
            rig.goto(near(PARK, value))
        # Each state lasts a second: a disarm and re-arm within the readback's detection
        # window (~0.3 s at 10 Hz) while moving would apply that window's steps at once.
        run(rig, px4, 1.0)
    for output, before, after in px4.physical_moves:
        joint = rig.calibration.for_output(output)
        step_us = STEP_DEG / (joint.angle_max_deg - joint.angle_min_deg) * 1000
        assert abs(after - before) <= step_us + 1, (output, before, after)


def rig_park_pwm() -> int:
    """One PWM inside every joint's calibration (the default 1000-2000 us)."""
    return 1500


def test_a_world_frame_target_is_refused_while_world_targets_are_off(rig):
    request = rig.request("goto", {"pose": near(PARK), "mode": "pose", "frame": "local_ned"})
    reply = rig.reply(request)
    assert reply.outcome is Outcome.DENIED and "local_ned" in reply.message
    assert not [c for c in rig.sent if c.command == SERVO]


# -- keep-out volumes (issue 18) ------------------------------------------------------------


def keepout_rig(q_in_the_way) -> Rig:
    """A rig whose config has a 4 cm sphere around the hand of ``q_in_the_way`` (body frame)."""
    from companion.kinematics.vehicle import Mount

    arm = Rig().config.arm
    centre = Mount().to_body(arm.fk(q_in_the_way).position_cm)
    sphere = {"name": "ball", "type": "sphere", "center_cm": list(centre), "radius_cm": 4.0}
    rig = Rig(sections={"keepout": [sphere]})
    rig.up()
    return rig


def test_a_target_whose_solution_hits_a_keepout_volume_is_refused_naming_it():
    goal = tuple(p + d for p, d in zip(PARK, (30.0, 0, 0, 0, 0, 0), strict=True))
    rig = keepout_rig(goal)
    reply = rig.reply(rig.goto(goal))
    assert reply.outcome is Outcome.FAILED and "keep-out" in reply.message
    assert "'ball'" in reply.message
    assert rig.servo() == {} and rig.core.status()["counters"]["keepout_refusals"] == 1


def test_a_target_whose_straight_motion_crosses_a_volume_is_refused_before_moving():
    # The goal is clear, the straight way there is not (the ball at +20 deg on q1): refused
    # with where along the motion, nothing sent (no detour is planned).
    rig = keepout_rig(tuple(p + d for p, d in zip(PARK, (20.0, 0, 0, 0, 0, 0), strict=True)))
    goal = tuple(p + d for p, d in zip(PARK, (40.0, 0, 0, 0, 0, 0), strict=True))
    reply = rig.reply(rig.goto(goal))
    assert reply.outcome is Outcome.FAILED
    assert "motion" in reply.message and "'ball'" in reply.message
    assert rig.servo() == {} and rig.core.status()["counters"]["keepout_refusals"] == 1


def test_a_motion_that_became_unsafe_stops_before_the_volume():
    # A clear target on its way; a reload puts a ball on the rest of the way: the step guard
    # stops the motion short of it.
    rig = Rig()
    rig.up()
    goal = tuple(p + d for p, d in zip(PARK, (40.0, 0, 0, 0, 0, 0), strict=True))
    request = rig.goto(goal)
    rig.core.reconfigure(
        keepout_rig(tuple(p + d for p, d in zip(PARK, (20.0, 0, 0, 0, 0, 0), strict=True))).config
    )
    for _ in range(40):  # 3 deg a tick
        rig.ack_all(rig.sent)
        rig.sent.clear()
        rig.advance(1.0 / RATE_HZ)
    assert rig.reply(request).outcome is Outcome.ACCEPTED  # its first step was clear
    status = rig.core.status()
    assert status["goal_deg"] is None and status["counters"]["keepout_refusals"] == 1
    assert 5.0 < status["current_deg"][0] < 20.0  # stopped on the way, short of the ball


def test_a_clear_verdict_is_checked_again_at_the_pwm_sent(monkeypatch):
    # Should solve_clear ever call a colliding answer clear, the core refuses it all the same.
    from companion.daemon.core import keepout_gate
    from companion.ik.keepout import ClearResult, ClearVerdict

    goal = tuple(p + d for p, d in zip(PARK, (30.0, 0, 0, 0, 0, 0), strict=True))
    rig = keepout_rig(goal)
    wrong = ClearResult(
        ClearVerdict.CLEAR, fake_solve(Pose.from_sequence(goal), None), None, 1, 0.1
    )
    monkeypatch.setattr(keepout_gate, "solve_clear", lambda *a, **k: wrong)
    reply = rig.reply(rig.goto(goal))
    assert reply.outcome is Outcome.FAILED and "'ball'" in reply.message
    assert "at the PWM sent" in reply.message
    assert rig.servo() == {} and rig.core.status()["counters"]["keepout_refusals"] == 1


def test_a_colliding_first_solution_is_replaced_by_a_clear_one():
    # The solver's first (warm) answer hits the ball; asked again from elsewhere it offers
    # another, clear one: the target is reached, not refused.
    ball_q = tuple(p + d for p, d in zip(PARK, (30.0, 0, 0, 0, 0, 0), strict=True))
    rig = keepout_rig(ball_q)
    other = tuple(p + d for p, d in zip(PARK, (-30.0, 0, 0, 0, 0, 0), strict=True))

    def two_branches(pose, q_start_deg, mode="pose", budget_ms=None, *, seed=None):
        return fake_solve(Pose.from_sequence(ball_q if q_start_deg == PARK else other), None)

    rig.core._solve = two_branches
    request = rig.goto(ball_q)
    rig.ack_all(rig.sent)
    assert rig.reply(request).outcome is Outcome.ACCEPTED
    assert rig.core.status()["goal_deg"] == list(other)


def test_px4_telemetry_streams_nobody_reads_are_stopped_on_our_link():
    # PX4 streams ATTITUDE (100 Hz) and LOCAL_POSITION_NED (30 Hz) on a companion's link unasked:
    # half a 115 200-baud line. With world-frame targets off the daemon stops both.
    rig = Rig(dialect="px4")
    rig.heartbeat(autopilot=mavlink.MAV_AUTOPILOT_PX4)
    rig.tick()
    asks = {
        int(c.params[0]): c.params[1]
        for c in rig.sent
        if c.command == mavlink.MAV_CMD_SET_MESSAGE_INTERVAL
    }
    assert asks[mavlink.MAVLINK_MSG_ID_ATTITUDE] == -1
    assert asks[mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED] == -1


# -- keep-out property (issue 18) ----------------------------------------------------------------


def _quad_sections() -> dict:
    """The example quad's volumes as config (tests/support/keepout.QUAD_450)."""
    from dataclasses import asdict

    from tests.support.keepout import QUAD_450

    kinds = {"Box": "box", "Cylinder": "cylinder", "Capsule": "capsule", "Sphere": "sphere"}
    volumes = [
        {"type": kinds[type(v).__name__], **{k: _plain(x) for k, x in asdict(v).items()}}
        for v in QUAD_450
    ]
    return {
        "keepout": volumes,
        "solver": {"budget_ms": 5.0, "seed": 3},
        "arm": {"park_deg": list(PARK), "joint_speed_deg_s": 300.0},  # 15 deg a tick
    }


def _plain(value):
    return list(value) if isinstance(value, tuple) else value


_KEEPOUT_EVENTS = st.one_of(
    # a target anywhere in the joint box (inside volumes, across the body, just outside)
    st.tuples(st.just("goto"), st.lists(st.floats(-90, 90), min_size=6, max_size=6)),
    # a solver that offers other solutions when asked again (solve_clear's path)
    st.tuples(st.just("branches"), st.lists(st.floats(-90, 90), min_size=6, max_size=6)),
    st.tuples(st.just("trajectory"), st.lists(st.floats(-60, 60), min_size=6, max_size=6)),
    st.tuples(st.sampled_from(["nan", "unreachable", "stop", "park"]), st.none()),
    st.tuples(st.just("ack"), st.sampled_from([ACCEPTED, ACCEPTED, ACCEPTED, FAILED])),
    st.tuples(st.just("advance"), st.sampled_from([0.001, 0.05, 0.3])),
    st.tuples(st.just("run"), st.integers(1, 30)),  # ticks, every update acknowledged
)


@settings(max_examples=15, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(events=st.lists(_KEEPOUT_EVENTS, max_size=30))
def test_property_no_commanded_configuration_or_step_enters_a_keepout_volume(events):
    """Issue 18: whatever the targets (in, across and around the quad's volumes), trajectories
    and solver answers, every configuration the servos are commanded to, and every straight
    step between two in a row (and each output's own change, in the order sent), keeps the
    margin by an independent dense sampling (tests/support/keepout)."""
    from tests.support.keepout import sampled_clearance

    rig = Rig(sections=_quad_sections())
    rig.up()
    keepout = rig.config.keepout_check()
    cal = rig.calibration
    lo = np.array([j.angle_min_deg for j in cal.joints])
    hi = np.array([j.angle_max_deg for j in cal.joints])
    alternative: list[tuple[float, ...]] = []

    def solver(pose, q_start_deg, mode="pose", budget_ms=None, *, seed=None):
        # The asked joints when warm from the park pose or with no alternative; else (cold or
        # from elsewhere) the alternative answer: solve_clear's retries see another branch.
        if alternative and (q_start_deg is None or seed is not None and seed % 2):
            return fake_solve(Pose.from_sequence(alternative[0]), None)
        return fake_solve(pose, q_start_deg)

    rig.core._solve = solver
    commanded = np.array(PARK, float)  # what the outputs hold (as sent, in order)
    path = [commanded.copy()]

    def drain() -> list:
        sent, rig.sent[:] = list(rig.sent), []
        for c in sent:
            if c.command == SERVO:
                output, pwm = int(c.params[0]), int(c.params[1])
                commanded[cal.outputs.index(output)] = rig.angle(output, pwm)
                path.append(commanded.copy())
        return sent

    for kind, arg in events:
        if kind in ("goto", "branches", "trajectory"):
            q = tuple(np.clip(np.add(PARK, arg) if kind == "trajectory" else arg, lo, hi))
            if kind == "branches":
                alternative[:] = [tuple(np.clip(np.subtract(PARK, arg), lo, hi))]
            if kind == "trajectory":
                mid = tuple((np.array(q) + PARK) / 2)
                rig.request("trajectory", [[0.0, *mid], [0.1, *q]])
            else:
                rig.goto(q)
        elif kind == "nan":
            rig.goto((math.nan,) * 6)
        elif kind == "unreachable":
            rig.goto((2000, 0, 0, 0, 0, 0))
        elif kind in ("stop", "park"):
            rig.request(kind)
        elif kind == "ack":
            rig.ack(arg)
        elif kind == "advance":
            rig.advance(arg)
        sent = drain()
        for _ in range(arg if kind == "run" else 0):
            rig.ack_all(sent)
            sent = drain()
            rig.advance(1.0 / RATE_HZ)
            sent += drain()
    q = np.radians(np.array(path))
    s = np.linspace(0.0, 1.0, 9)[:, None]
    dense = np.concatenate([q[:1]] + [a + s * (b - a) for a, b in zip(q[:-1], q[1:], strict=True)])
    assert sampled_clearance(keepout, dense, 60).min() >= keepout.margin_cm - 0.3
