"""The dispatcher (``core/dispatcher.py``): events in, actions out, whatever their order;
shutdown and the next wake."""

from __future__ import annotations

import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from companion.daemon.core import (
    PIPELINE_DEPTH,
)
from companion.daemon.requests import Outcome, Request
from tests.daemon.core.rig import ACCEPTED, FAILED, PARK, SERVO, STEP_DEG, Rig, near


def test_targets_while_the_link_is_down_are_temporarily_rejected():
    rig = Rig()
    rig.heartbeat()
    request = rig.goto(near(PARK))  # pinned, but no tick has seen the link up yet
    assert rig.reply(request).outcome is Outcome.TEMPORARILY_REJECTED


def test_shutdown_answers_everything_and_parks_at_the_speed_limit(rig):
    # park_on_stop parked in one step (up to 31 deg): at the speed limit, as any motion.
    first = rig.goto(tuple(p + 30.0 for p in PARK))  # in flight
    waiting = rig.goto(tuple(p + 20.0 for p in PARK))
    rig.take(rig.core.shutdown(park=True))
    assert rig.reply(waiting).outcome is Outcome.CANCELLED  # never sent
    assert rig.core.parking()
    before = dict(rig.servo())
    done = 0
    for _ in range(200):
        new, done = rig.sent[done:], len(rig.sent)
        rig.ack_all(new)
        for output, pwm in rig.servo(new).items():
            assert abs(rig.angle(output, pwm) - rig.angle(output, before[output])) <= (
                STEP_DEG + 0.2
            )
            before[output] = pwm
        if not rig.core.parking() and rig.core.idle:
            break
        rig.advance(1.0 / 20)
    assert rig.reply(first).outcome is Outcome.ACCEPTED  # its first step was acknowledged
    assert rig.core.parked() and rig.core.idle


_EVENTS = st.one_of(
    st.tuples(
        st.just("goto"), st.lists(st.floats(1, 40) | st.floats(-40, -1), min_size=6, max_size=6)
    ),
    st.tuples(st.just("unreachable"), st.none()),
    st.tuples(st.just("nan"), st.none()),
    st.tuples(st.sampled_from(["stop", "park", "resume", "link_stop", "link_resume"]), st.none()),
    st.tuples(st.just("link_goto"), st.lists(st.floats(1, 40), min_size=6, max_size=6)),
    st.tuples(st.just("ack"), st.sampled_from([ACCEPTED, ACCEPTED, ACCEPTED, FAILED, 1])),
    st.tuples(st.just("advance"), st.sampled_from([0.001, 0.02, 0.05, 0.3, 0.6])),
    st.tuples(st.just("link"), st.booleans()),
    st.tuples(st.just("reboot"), st.none()),
)


@settings(max_examples=200)
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
        elif kind in ("stop", "park", "resume"):
            requests.append((rig.request(kind), None))
        elif kind in ("link_stop", "link_resume"):
            requests.append((rig.request(kind[5:], source=("mavlink", 255, 190)), None))
        elif kind == "link_goto":
            stopped = rig.core.status()["stopped"]
            q = tuple(p + a for p, a in zip(PARK, arg, strict=True))
            request = rig.request("goto", q, source=("mavlink", 255, 190))
            requests.append((request, q))
            if stopped:  # held by a stop: refused, never carried out
                assert rig.reply(request).outcome is Outcome.DENIED
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


# -- stop holds until resume -------------------------------------------------------------------

GCS = ("mavlink", 255, 190)
OPERATOR = ("socket", 3)


def test_a_stop_holds_the_arm_until_resume_whatever_the_link_sends_meanwhile(rig):
    stop = rig.request("stop", source=OPERATOR)
    assert rig.reply(stop).outcome is Outcome.ACCEPTED
    status = rig.core.status()
    assert (status["stopped"], status["stopped_by"]) == (True, "socket 3")
    # A ground station retrying, and a flood from forged system ids: none of it moves the arm.
    retried = [rig.request("goto", near(PARK), source=GCS) for _ in range(3)]
    forged = [rig.request("goto", near(PARK), source=("mavlink", i, 1)) for i in range(1, 200)]
    for request in retried + forged:
        reply = rig.reply(request)
        assert reply.outcome is Outcome.DENIED and reply.message.startswith("stopped")
    assert "armbridge resume" in rig.reply(retried[0]).message
    # The companion's stop is not the link's to release.
    resume = rig.request("resume", source=GCS)
    assert rig.reply(resume).outcome is Outcome.DENIED
    rig.advance(1.0)
    assert rig.servo() == {} and rig.core.status()["goal_deg"] is None
    assert rig.reply(rig.request("resume", source=OPERATOR)).outcome is Outcome.ACCEPTED
    assert rig.core.status()["stopped"] is False
    target = rig.request("goto", near(PARK), source=GCS)
    rig.ack_all(rig.sent)
    assert rig.reply(target).outcome is Outcome.ACCEPTED


def test_a_stop_from_the_link_is_released_by_a_resume_from_the_link(rig):
    rig.request("stop", source=GCS)
    denied = rig.reply(rig.request("goto", near(PARK), source=("mavlink", 200, 1)))
    assert (denied.outcome, denied.statustext()) == (Outcome.DENIED, "stopped: send resume")
    assert "MAV_CMD_DO_PAUSE_CONTINUE" in denied.message
    # The companion's stop outranks it: from then on only the companion resumes.
    rig.request("stop", source=OPERATOR)
    assert rig.core.status()["stopped_by"] == "socket 3"
    assert rig.reply(rig.request("resume", source=GCS)).outcome is Outcome.DENIED
    rig.request("resume", source=OPERATOR)
    rig.request("stop", source=GCS)
    assert rig.core.status()["stopped_by"] == "mavlink 255/190"
    assert rig.reply(rig.request("resume", source=GCS)).message == "resumed"
    assert rig.reply(rig.request("resume", source=GCS)).message == "not stopped"
    target = rig.request("goto", near(PARK), source=GCS)
    rig.ack_all(rig.sent)
    assert rig.reply(target).outcome is Outcome.ACCEPTED


@pytest.mark.parametrize("kind", ["goto", "park", "trajectory"])
def test_a_motion_from_the_companion_releases_the_stop_once_carried_out(rig, kind):
    rig.request("stop", source=GCS)
    # Out of reach: not carried out, so the arm stays stopped.
    assert rig.reply(rig.request("goto", (2000, 0, 0, 0, 0, 0), source=OPERATOR)).outcome is (
        Outcome.FAILED
    )
    assert rig.core.status()["stopped"] is True
    goal = tuple(p + 1.0 for p in PARK)
    payload = {"goto": goal, "park": None, "trajectory": [(0.0, goal)]}[kind]
    request = rig.request(kind, payload, source=OPERATOR)
    assert rig.core.status()["stopped"] is False
    rig.ack_all(rig.sent)
    rig.advance(0.05)
    assert rig.reply(request).outcome is Outcome.ACCEPTED


def test_the_stop_survives_a_reload_and_a_restart_starts_without_it(rig):
    rig.request("stop", source=OPERATOR)
    rig.core.reconfigure(rig.config)  # SIGHUP
    assert rig.reply(rig.request("goto", near(PARK), source=GCS)).outcome is Outcome.DENIED
    assert rig.core.status()["stopped"] is True
    assert Rig().core.status()["stopped"] is False  # a new daemon process
