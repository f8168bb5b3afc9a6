"""The daemon in-process against the simulated flight controller, a real subprocess: targets
go in through ``ArmDaemon.submit`` (the path the control socket uses) and move the simulated
hand, refusals move nothing, the speed limit holds, park and stop."""

from __future__ import annotations

import gc
import math

import pytest

from companion.daemon.config import parse_config
from companion.daemon.service import ArmDaemon, Outcome
from companion.ik import warm_up
from devkit.sim_process import assert_within_quantisation
from devkit.timing import wait_until
from sim_servo.query import query

pytestmark = pytest.mark.slow

WAIT_S = 10.0
HEARTBEAT_PERIOD_S = 1.0  # the simulator's HEARTBEAT rate is 1 Hz
G = (-20.0, 3.0, 40.0, 0.0, 10.0, 15.0)


@pytest.fixture
def sim(sims):
    """Starts simulated ArduPilots (UDP by default, or a pty); each start returns
    (link url, query socket path). The ``sims`` fixture stops them, asserting exit 0."""

    def start(*extra, transport=("--udp", "127.0.0.1:0")):
        process = sims(*transport, *extra)
        assert process.url.startswith(("udpout:", "/dev/")), process.url
        return process.url, process.query_path

    return start


def make_daemon(url, rate_hz=50.0, loss_timeout_s=3 * HEARTBEAT_PERIOD_S, **arm):
    # The loss timeout is three of the simulator's heartbeat periods: one heartbeat late on a
    # loaded machine is not a link loss.
    cfg = parse_config(
        {
            "link": {"url": url, "loss_timeout_s": loss_timeout_s, "command_timeout_s": 0.3},
            "arm": {"park_deg": [0, 90, 0, 0, 0, 0], "joint_speed_deg_s": 360.0, **arm},
            "control": {"rate_hz": rate_hz},
            "solver": {"seed": 1},
        }
    )
    daemon = ArmDaemon(cfg)
    warm_up()  # as `armbridge run` does: no solve pays for loading the kernels
    gc.freeze()  # and its heap: no full collection pass over it stalls the control thread
    daemon.start()
    assert daemon.wait_for_autopilot(WAIT_S)
    return daemon


def sim_hand(sock):
    return query(sock, "state")["hand"]


def settled(daemon, sock):
    return not daemon.status()["moving"] and query(sock, "state")["settled"]


@pytest.mark.parametrize("transport", [("--udp", "127.0.0.1:0"), ("--pty",)], ids=["udp", "pty"])
def test_goto_moves_the_simulated_hand_to_the_target(sim, transport):
    # Over UDP, and over a pseudo-terminal opened exactly like the flight controller's serial port.
    url, sock = sim(transport=transport)
    daemon = make_daemon(url)
    try:
        target = daemon.config.arm.fk([20, 70, 50, 20, 30, 10]).as_tuple()
        reply = daemon.submit("goto", target).result(WAIT_S)
        assert reply.outcome is Outcome.ACCEPTED, reply.message
        assert wait_until(lambda: settled(daemon, sock), WAIT_S)
        # 1 µs of PWM is 0.18° on a 180° joint: the hand is as close as the servos can put it.
        assert_within_quantisation(target, sim_hand(sock), daemon.status()["current_deg"])
        counters = daemon.status()["counters"]
        assert counters["accepted"] == 1 and counters["servo_errors"] == 0
    finally:
        daemon.close()


def test_unreachable_g_is_refused_and_nothing_moves(sim):
    url, sock = sim()
    daemon = make_daemon(url)
    try:
        before = query(sock, "state")["outputs"]
        reply = daemon.submit("goto", G).result(WAIT_S)
        assert reply.outcome is Outcome.FAILED
        assert "unreachable" in reply.message and reply.solve is not None
        assert not reply.solve.converged
        assert daemon.status()["counters"]["servo_updates"] == 0
        assert query(sock, "state")["outputs"] == before
    finally:
        daemon.close()


def test_status_asked_once_answered_counts_the_answer(sim):
    """The status snapshot is refreshed before the answers go out: a client that asks for
    status as soon as it has its answer (the control socket serves it within microseconds)
    sees its request counted. Read from the answer's own callback, the snapshot was the step's
    old one."""
    url, _ = sim()
    daemon = make_daemon(url)
    try:
        seen = []
        future = daemon.submit("goto", G)
        future.add_done_callback(lambda _: seen.append(daemon.status()["counters"]["failed"]))
        assert future.result(WAIT_S).outcome is Outcome.FAILED
        assert seen == [1]
    finally:
        daemon.close()


def test_invalid_targets_are_denied(sim):
    url, _ = sim()
    daemon = make_daemon(url)
    bad = [(1, 2, math.nan, 0, 0, 0), (1, 2, 3, math.inf, 0, 0), (1, 2, 3), "x"]
    try:
        for payload in bad:
            assert daemon.submit("goto", payload).result(WAIT_S).outcome is Outcome.DENIED
        assert daemon.status()["counters"]["denied"] == len(bad)
    finally:
        daemon.close()


def test_accepted_target_moves_at_once_and_reports_its_timing(sim):
    # 1 Hz ticks: right after target A's first step, target B would wait about a second for
    # the next tick. It does not: its first step goes out as soon as it is solved.
    url, _ = sim()
    daemon = make_daemon(url, rate_hz=1.0)
    try:
        arm = daemon.config.arm
        a = daemon.submit("goto", arm.fk([20, 70, 50, 20, 30, 10]).as_tuple()).result(WAIT_S)
        b = daemon.submit("goto", arm.fk([-20, 100, -30, 10, 20, 30]).as_tuple()).result(WAIT_S)
        assert a.outcome is Outcome.ACCEPTED and b.outcome is Outcome.ACCEPTED
        t = b.timing
        assert t["received_s"] <= t["solved_s"] <= t["first_out_s"] <= t["acked_s"]
        assert t["first_out_s"] - t["received_s"] < 0.5
        assert daemon.status()["last_target"]["timing"] == t
        assert b.as_dict()["timing"] == t
    finally:
        daemon.close()


def test_immediate_steps_keep_to_the_joint_speed_limit(sim):
    # Two targets in quick succession: the second's immediate step may only move the joints
    # as far as the joint speed allows in the time since the first step, not a whole period.
    url, _ = sim()
    speed_deg_s = 30.0
    daemon = make_daemon(url, rate_hz=2.0, joint_speed_deg_s=speed_deg_s)
    try:
        arm = daemon.config.arm
        a = daemon.submit("goto", arm.fk([20, 70, 50, 20, 30, 10]).as_tuple()).result(WAIT_S)
        after_a = daemon.status()["current_deg"]
        b = daemon.submit("goto", arm.fk([-20, 100, -30, 10, 20, 30]).as_tuple()).result(WAIT_S)
        after_b = daemon.status()["current_deg"]
        assert a.outcome is Outcome.ACCEPTED and b.outcome is Outcome.ACCEPTED
        # Both reads come long before the next 2 Hz tick, so they see exactly these steps.
        assert b.timing["first_out_s"] - a.timing["first_out_s"] < 0.25
        first = max(abs(x - p) for x, p in zip(after_a, [0, 90, 0, 0, 0, 0], strict=True))
        assert first == pytest.approx(speed_deg_s / 2.0)  # a whole period's step from rest
        second = max(abs(x - y) for x, y in zip(after_b, after_a, strict=True))
        assert 0 < second <= speed_deg_s * (b.timing["first_out_s"] - a.timing["solved_s"])
    finally:
        daemon.close()


def test_park_and_stop(sim):
    url, sock = sim()
    daemon = make_daemon(url)
    try:
        assert daemon.submit("park").result(WAIT_S).outcome is Outcome.ACCEPTED
        assert wait_until(lambda: settled(daemon, sock), WAIT_S)
        assert daemon.status()["current_deg"] == [0, 90, 0, 0, 0, 0]
        assert daemon.submit("stop").result(WAIT_S).outcome is Outcome.ACCEPTED
        assert daemon.status()["goal_deg"] is None
    finally:
        daemon.close()
