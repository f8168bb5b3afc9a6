"""Motion (``core/motion.py``): the goal, the targets waiting for their first step, stops and
supersessions, the speed limit."""

from __future__ import annotations

import math

import pytest

from companion.daemon.core import (
    SendCommand,
)
from companion.daemon.requests import Outcome
from tests.daemon.core.rig import PARK, RATE_HZ, SERVO, near


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


def test_a_trajectory_with_a_point_out_of_reach_is_abandoned_and_status_says_why(rig):
    # (t_s, pose) pairs, as the control socket hands them to the core
    request = rig.request("trajectory", [(0.0, near(PARK)), (0.2, (2000, 0, 0, 0, 0, 0))])
    assert rig.reply(request).outcome is Outcome.ACCEPTED
    assert rig.core.status()["trajectory_aborted"] is None
    for _ in range(10):  # 0.5 s of ticks, every update answered
        rig.ack_all(rig.sent)
        rig.sent.clear()
        rig.advance(0.05)
    status = rig.core.status()
    assert status["trajectory_points_left"] == 0
    assert status["trajectory_aborted"].startswith("the point at t_s=0.2: unreachable")
    again = rig.request("trajectory", [(0.0, PARK)])
    assert rig.reply(again).outcome is Outcome.ACCEPTED
    assert rig.core.status()["trajectory_aborted"] is None  # a new trajectory starts clean
