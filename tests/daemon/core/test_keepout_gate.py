"""The keep-out gate (``core/keepout_gate.py``): targets solved clear of the volumes, every
step's path checked."""

from __future__ import annotations

import math

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from companion.daemon.requests import Outcome
from companion.kinematics.arm import Pose
from tests.daemon.core.rig import (
    ACCEPTED,
    FAILED,
    PARK,
    RATE_HZ,
    SERVO,
    Rig,
    fake_solve,
    keepout_rig,
)


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

    rig.core.solve = two_branches
    request = rig.goto(ball_q)
    rig.ack_all(rig.sent)
    assert rig.reply(request).outcome is Outcome.ACCEPTED
    assert rig.core.status()["goal_deg"] == list(other)


def _quad_sections() -> dict:
    """The example quad's volumes as config (devkit/keepout.QUAD_450)."""
    from dataclasses import asdict

    from devkit.keepout import QUAD_450

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


@settings(max_examples=15)
@given(events=st.lists(_KEEPOUT_EVENTS, max_size=30))
def test_property_no_commanded_configuration_or_step_enters_a_keepout_volume(events):
    """Whatever the targets (in, across and around the quad's volumes), trajectories
    and solver answers, every configuration the servos are commanded to, and every straight
    step between two in a row (and each output's own change, in the order sent), keeps the
    margin by an independent dense sampling (devkit/keepout)."""
    from devkit.keepout import sampled_clearance

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

    rig.core.solve = solver
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
                rig.request("trajectory", [(0.0, mid), (0.1, q)])  # as the socket hands them
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


def test_a_target_out_of_reach_is_refused_as_unreachable_not_blamed_on_a_volume():
    from types import SimpleNamespace

    goal = tuple(p + d for p, d in zip(PARK, (30.0, 0, 0, 0, 0, 0), strict=True))
    rig = keepout_rig(goal)

    def short_of_it(pose, q_start_deg, mode="pose", budget_ms=None, *, seed=None):
        # The nearest the solver gets is 12 cm off, in the ball: the target is out of reach.
        return SimpleNamespace(
            q_deg=goal, q_rad=np.radians(goal), converged=False, pos_err_cm=12.0,
            ori_err_deg=3.0, cost=144.0, elapsed_ms=0.1,
        )  # fmt: skip

    rig.core.solve = short_of_it
    reply = rig.reply(rig.goto((1.0, 2.0, 3.0, 0.0, 0.0, 0.0)))
    assert reply.outcome is Outcome.FAILED
    assert reply.message.startswith("unreachable: pos 12.00cm ori 3.0deg")
    assert "(the nearest configurations found also put" in reply.message
    assert rig.servo() == {}
