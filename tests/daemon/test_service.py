"""The daemon in-process against a scripted autopilot (or none): the MAVLink input, unanswered
updates, a bug in the control thread, coalescing, reload, and when the control thread wakes.

MAVLink targets come as COMMAND_LONG frames from a scripted autopilot that routes a ground
station's command, the way a real autopilot forwards it to its companion. Against the simulated
flight controller (a subprocess): ``test_service_sim.py``.
"""

from __future__ import annotations

import dataclasses
import math
import threading
import time
from importlib import resources

import numpy as np
import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from companion.daemon.config import parse_config
from companion.daemon.requests import Reply
from companion.daemon.service import ArmDaemon, Outcome
from devkit.mavlink_peer import ScriptedPeer, UdpEndpoint
from devkit.timing import wait_until
from tests.daemon.core.rig import PARK, RATE_HZ, Rig, near, telemetry, world_goto, world_rig

WAIT_S = 10.0
SERVO = mavlink.MAV_CMD_DO_SET_SERVO
G = (-20.0, 3.0, 40.0, 0.0, 10.0, 15.0)
URL = "udpout:127.0.0.1:14550"


@pytest.fixture
def autopilot():
    """A scripted autopilot on UDP (accepts every servo command) and its endpoint."""
    endpoint = UdpEndpoint()
    peer = ScriptedPeer(endpoint)
    yield endpoint, peer
    peer.close()


def gcs_command(endpoint, params, *, target=(1, 191)):
    """A ground station's COMMAND_LONG USER_1 as the autopilot forwards it (source 255/190)."""
    gcs = mavlink.MAVLink(None, 255, 190)
    msg = gcs.command_long_encode(target[0], target[1], mavlink.MAV_CMD_USER_1, 0, *params, 0)
    endpoint.write(msg.pack(gcs))


def acks_to_gcs(peer):
    return [m for m in peer.messages("COMMAND_ACK") if m.target_system == 255]


@pytest.mark.parametrize(
    ("params", "result"),
    [
        ((45.0, 10.0, 20.0, 0.0, 45.0, 0.0), None),
        ((1.0, 2.0, math.nan, 0.0, 0.0, 0.0), mavlink.MAV_RESULT_DENIED),
        (G, mavlink.MAV_RESULT_FAILED),
    ],
    ids=["reachable", "nan", "unreachable-G"],
)
def test_mavlink_user_1_target_is_answered(autopilot, params, result):
    endpoint, peer = autopilot
    daemon = ArmDaemon(
        parse_config(
            {
                "link": {"url": f"udpout:127.0.0.1:{endpoint.port}"},
                "arm": {"park_deg": [0, 90, 0, 0, 0, 0]},
            }
        )
    )
    daemon.start()
    try:
        assert peer.wait_for(lambda: endpoint.peer is not None)
        peer.send_heartbeat()
        assert daemon.wait_for_autopilot(WAIT_S)
        if result is None:  # a reachable pose: pick one from the arm itself
            params = daemon.config.arm.fk([20, 70, 50, 20, 30, 10]).as_tuple()
            result = mavlink.MAV_RESULT_ACCEPTED
        gcs_command(endpoint, params)
        assert peer.wait_for(lambda: acks_to_gcs(peer))
        ack = acks_to_gcs(peer)[0]
        assert (ack.command, ack.result, ack.target_component) == (
            mavlink.MAV_CMD_USER_1,
            result,
            190,
        )
        texts = [m.text for m in peer.messages("STATUSTEXT")]
        if result == mavlink.MAV_RESULT_FAILED:
            assert any("unreachable" in t for t in texts)
        servo = [
            m for m in peer.messages("COMMAND_LONG") if m.command == mavlink.MAV_CMD_DO_SET_SERVO
        ]
        assert bool(servo) == (result == mavlink.MAV_RESULT_ACCEPTED)
        assert all(1000 <= m.param2 <= 2000 for m in servo)
    finally:
        daemon.close()


def test_mavlink_target_for_another_component_is_ignored(autopilot):
    endpoint, peer = autopilot
    daemon = ArmDaemon(parse_config({"link": {"url": f"udpout:127.0.0.1:{endpoint.port}"}}))
    daemon.start()
    try:
        assert peer.wait_for(lambda: endpoint.peer is not None)
        peer.send_heartbeat()
        assert daemon.wait_for_autopilot(WAIT_S)
        gcs_command(endpoint, (45.0, 10.0, 20.0, 0.0, 45.0, 0.0), target=(1, 100))
        assert wait_until(lambda: daemon.status()["counters"]["not_for_us"] == 1, WAIT_S)
        assert acks_to_gcs(peer) == []
    finally:
        daemon.close()


def gcs_pause(endpoint, param1):
    """A ground station's MAV_CMD_DO_PAUSE_CONTINUE to us: 0 stop, 1 resume."""
    gcs = mavlink.MAVLink(None, 255, 190)
    msg = gcs.command_long_encode(
        1, 191, mavlink.MAV_CMD_DO_PAUSE_CONTINUE, 0, param1, 0, 0, 0, 0, 0, 0
    )
    endpoint.write(msg.pack(gcs))


def test_a_stop_over_mavlink_holds_the_arm_until_a_resume(autopilot):
    endpoint, peer = autopilot
    daemon = ArmDaemon(parse_config({"link": {"url": f"udpout:127.0.0.1:{endpoint.port}"}}))
    daemon.start()
    try:
        assert peer.wait_for(lambda: endpoint.peer is not None)
        peer.send_heartbeat()
        assert daemon.wait_for_autopilot(WAIT_S)
        pose = daemon.config.arm.fk([20, 70, 50, 20, 30, 10]).as_tuple()

        def answer(count):
            assert peer.wait_for(lambda: len(acks_to_gcs(peer)) >= count)
            ack = acks_to_gcs(peer)[count - 1]
            return ack.command, ack.result

        gcs_pause(endpoint, 0)
        assert answer(1) == (mavlink.MAV_CMD_DO_PAUSE_CONTINUE, mavlink.MAV_RESULT_ACCEPTED)
        assert daemon.status()["stopped_by"] == "mavlink 255/190"
        gcs_command(endpoint, pose)
        assert answer(2) == (mavlink.MAV_CMD_USER_1, mavlink.MAV_RESULT_DENIED)
        assert "stopped: send resume" in [m.text for m in peer.messages("STATUSTEXT")]
        gcs_pause(endpoint, 7)
        assert answer(3) == (mavlink.MAV_CMD_DO_PAUSE_CONTINUE, mavlink.MAV_RESULT_DENIED)
        assert not [m for m in peer.messages("COMMAND_LONG") if m.command == SERVO]
        gcs_pause(endpoint, 1)
        assert answer(4) == (mavlink.MAV_CMD_DO_PAUSE_CONTINUE, mavlink.MAV_RESULT_ACCEPTED)
        assert daemon.status()["stopped"] is False
        gcs_command(endpoint, pose)
        assert answer(5) == (mavlink.MAV_CMD_USER_1, mavlink.MAV_RESULT_ACCEPTED)
    finally:
        daemon.close()


def test_an_accepted_motion_survives_an_unanswered_update(autopilot):
    """One servo update of a moving arm gets no ACK (after the sender's retries): the next tick
    sends it again and the arm still reaches the target; a second failure in a row does not
    happen here, so the motion is not abandoned."""
    endpoint, peer = autopilot
    daemon = ArmDaemon(
        parse_config(
            {
                "link": {
                    "url": f"udpout:127.0.0.1:{endpoint.port}",
                    "loss_timeout_s": 30.0,
                    "command_timeout_s": 0.5,  # ample on a loaded machine
                    "command_retries": 0,
                },
                "arm": {"park_deg": [0, 90, 0, 0, 0, 0], "joint_speed_deg_s": 100.0},
                "control": {"rate_hz": 50.0},
            }
        )
    )
    daemon.start()
    try:
        assert peer.wait_for(lambda: endpoint.peer is not None)
        peer.send_heartbeat()
        assert daemon.wait_for_autopilot(WAIT_S)
        target = daemon.config.arm.fk([20, 70, 20, 0, 10, 0]).as_tuple()  # ≥ 20° away: 10 ticks
        reply = daemon.submit("goto", target).result(WAIT_S)
        assert reply.outcome is Outcome.ACCEPTED
        peer.drop_acks = 1  # the next DO_SET_SERVO goes unanswered
        assert wait_until(lambda: daemon.status()["counters"]["servo_errors"] == 1, WAIT_S)
        assert wait_until(lambda: not daemon.status()["moving"], WAIT_S)
        status = daemon.status()
        assert status["goal_deg"] == pytest.approx(list(reply.solve.q_deg))
        assert status["current_deg"] == status["goal_deg"]
        assert status["counters"]["servo_errors"] == 1
    finally:
        daemon.close()


class _BuggyDaemon(ArmDaemon):
    """Its first solve raises, as a bug anywhere under the control thread would."""

    bugs = 1

    def _solve(self, pose, q_start_deg, mode="pose", budget_ms=None):
        if self.bugs:
            self.bugs -= 1
            raise RuntimeError("a bug under the control thread")
        return super()._solve(pose, q_start_deg, mode, budget_ms)


def test_a_bug_in_the_control_thread_fails_the_request_holds_and_keeps_serving(autopilot):
    endpoint, peer = autopilot
    daemon = _BuggyDaemon(
        parse_config({"link": {"url": f"udpout:127.0.0.1:{endpoint.port}", "loss_timeout_s": 30.0}})
    )
    daemon.start()
    try:
        assert peer.wait_for(lambda: endpoint.peer is not None)
        peer.send_heartbeat()
        assert daemon.wait_for_autopilot(WAIT_S)
        target = daemon.config.arm.fk([20, 70, 50, 20, 30, 10]).as_tuple()
        reply = daemon.submit("goto", target).result(WAIT_S)
        assert reply.outcome is Outcome.FAILED and "internal error" in reply.message
        assert daemon.healthy and daemon.status()["counters"]["internal_errors"] == 1
        servo_commands = [
            m for m in peer.messages("COMMAND_LONG") if m.command == mavlink.MAV_CMD_DO_SET_SERVO
        ]
        assert servo_commands == []  # nothing was sent for it
        assert daemon.submit("goto", target).result(WAIT_S).outcome is Outcome.ACCEPTED
    finally:
        daemon.close()


def test_a_burst_of_targets_is_coalesced_into_one_update(autopilot):
    """Targets that arrive while an update is under way are all answered at once: the newest
    wins, the others are CANCELLED (superseded), and only the newest goal is sent, in one
    update: a flood of targets never becomes a flood of servo updates."""
    endpoint, peer = autopilot
    config = parse_config(
        {
            "link": {
                "url": f"udpout:127.0.0.1:{endpoint.port}",
                "loss_timeout_s": 30.0,
                "command_timeout_s": 15.0,  # the peer holds its answers until told
            }
        }
    )
    # Past the config's bounds ([1, 400] Hz, 1000 deg/s), which load_config would refuse, on
    # purpose: no regular tick during the test and no speed limit on a step, so the only
    # updates are the ones the coalescing decides. ArmDaemon takes any DaemonConfig.
    daemon = ArmDaemon(dataclasses.replace(config, rate_hz=0.2, joint_speed_deg_s=36_000.0))
    daemon.start()
    try:
        assert peer.wait_for(lambda: endpoint.peer is not None)
        peer.send_heartbeat()
        assert daemon.wait_for_autopilot(WAIT_S)
        rng = np.random.default_rng(4)
        arm = daemon.config.arm
        lows = np.array([math.degrees(j.min_rad) for j in arm.joints])
        highs = np.array([math.degrees(j.max_rad) for j in arm.joints])
        targets = [arm.fk(rng.uniform(lows, highs)).as_tuple() for _ in range(40)]
        first_command, burst_queued = threading.Event(), threading.Event()

        def answer_once_the_burst_is_queued(cmd):
            if cmd.command == mavlink.MAV_CMD_DO_SET_SERVO:
                first_command.set()
                burst_queued.wait(WAIT_S)

        peer.on_command = answer_once_the_burst_is_queued
        futures = [daemon.submit("goto", targets[0])]
        assert first_command.wait(WAIT_S)  # the first target's update is under way ...
        # ... when the rest arrive (from many sources: one source's burst is rate limited).
        futures += [daemon.submit("goto", t, source=("test", i)) for i, t in enumerate(targets[1:])]
        # All but the newest are answered before the autopilot has said anything.
        superseded = [f.result(WAIT_S) for f in futures[1:-1]]
        assert {r.outcome for r in superseded} == {Outcome.CANCELLED}
        assert not futures[0].done() and not futures[-1].done()
        burst_queued.set()
        replies = [f.result(WAIT_S) for f in futures]
        assert replies[0].outcome is Outcome.ACCEPTED and replies[-1].outcome is Outcome.ACCEPTED
        status = daemon.status()
        assert status["counters"]["servo_updates"] == 2, status["counters"]
        # The latest goal is the one followed (the step towards it may be cut short by the
        # speed limit when the two updates come close together; the ticks finish it).
        last_accepted = [r for r in replies if r.outcome is Outcome.ACCEPTED][-1]
        assert status["goal_deg"] == pytest.approx(list(last_accepted.solve.q_deg))
    finally:
        daemon.close()


def test_reload_keeps_a_park_the_running_arm_cannot_reach(tmp_path):
    """SIGHUP keeps the running arm and calibration (a change needs a restart), but load_config
    proved the new park against the new ones: a park only the new arm reaches is not taken."""
    running = parse_config({"link": {"url": URL}, "arm": {"park_deg": [0, 90, 0, 0, 0, 0]}})
    daemon = ArmDaemon(running)  # never started: reload needs no link
    # The new arm's q2 reaches 200 deg (the running one's stops at 180): park there.
    paper = resources.files("companion.kinematics") / "arms" / "paper_arm.toml"
    text = paper.read_text().replace("min_deg = 0\nmax_deg = 180", "min_deg = 0\nmax_deg = 200")
    (tmp_path / "wider.toml").write_text(text)
    new = parse_config(
        {"link": {"url": URL}, "arm": {"file": "wider.toml", "park_deg": [0, 190, 0, 0, 0, 0]}},
        source=str(tmp_path / "armbridge.toml"),
    )
    warnings = daemon.reload(new)
    assert "arm changed: restart the daemon to apply it" in warnings
    assert daemon.config.arm == running.arm and daemon.config.calibration == running.calibration
    assert daemon.config.park_deg == (0, 90, 0, 0, 0, 0)
    assert any("park_deg [0.0, 190.0, 0.0, 0.0, 0.0, 0.0] does not fit" in w for w in warnings)
    # A park the running arm reaches is taken, arm change or not.
    assert not any(
        "park_deg" in w
        for w in daemon.reload(dataclasses.replace(new, park_deg=(0, 120, 0, 0, 0, 0)))
    )
    assert daemon.config.park_deg == (0, 120, 0, 0, 0, 0)


def test_statustext_fits_in_50_characters_cut_at_a_word():
    # A ground station's STATUSTEXT holds 50 characters; a longer message is cut at
    # a word, marked, ASCII only.
    long = Reply(Outcome.FAILED, "unreachable: pos 30.02cm ori 10.2deg, and a much longer tail")
    text = long.statustext()
    assert len(text) <= 50 and text == "unreachable: pos 30.02cm ori 10.2deg, and a..."
    assert Reply(Outcome.DENIED, "x" * 80).statustext() == "x" * 47 + "..."
    assert Reply(Outcome.FAILED, "pose ±1°").statustext() == "pose ?1?"
    assert Reply(Outcome.FAILED, "long " * 20, brief="short").statustext() == "short"


def _ack_frame(result=mavlink.MAV_RESULT_ACCEPTED):
    codec = mavlink.MAVLink(None, 1, 1)
    frame = codec.command_ack_encode(mavlink.MAV_CMD_DO_SET_SERVO, result, 0, 0, 1, 191)
    return mavlink.MAVLink(None).parse_buffer(frame.pack(codec))[0]


def test_the_control_thread_is_woken_by_the_ack_that_completes_an_update_not_by_each():
    """In-process, no threads: the reader's side (_on_frame) and the control thread's
    (_feed_frames, _arm_ack_wake) around a core driven as in tests/daemon/core."""
    rig = Rig()
    rig.up()
    daemon = ArmDaemon(rig.config, clock=rig.clock)
    daemon._core = rig.core
    request = daemon.new_request("goto", near(PARK))
    daemon._carry_out(rig.core.request(request))  # six DO_SET_SERVO out (no link: not sent)
    daemon._arm_ack_wake()
    for _ in range(5):
        daemon._on_frame(_ack_frame())
        assert not daemon._wake.is_set()
    daemon._on_frame(_ack_frame())
    assert daemon._wake.is_set()
    daemon._wake.clear()
    daemon._feed_frames()
    assert request.future.result(0).outcome is Outcome.ACCEPTED
    daemon._arm_ack_wake()
    # Nothing in flight: any ACK wakes it; so does every other frame the core reads but the
    # vehicle's telemetry, and a refusal at once, whatever the count.
    daemon._on_frame(_ack_frame())
    assert daemon._wake.is_set()
    daemon._wake.clear()
    daemon._feed_frames()
    daemon._arm_ack_wake()
    rig.clock.advance(0.02)
    second = daemon.new_request("goto", PARK)
    daemon._carry_out(rig.core.request(second))
    daemon._arm_ack_wake()
    codec = mavlink.MAVLink(None, 1, 1)
    attitude = codec.attitude_encode(1000, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0).pack(codec)
    daemon._on_frame(mavlink.MAVLink(None).parse_buffer(attitude)[0])
    assert not daemon._wake.is_set()
    daemon._on_frame(_ack_frame(mavlink.MAV_RESULT_FAILED))
    assert daemon._wake.is_set()
    # ACKs queued before the count was set (they came during the step) wake it at once.
    daemon._wake.clear()
    daemon._feed_frames()
    for _ in range(5):
        daemon._on_frame(_ack_frame())
    daemon._arm_ack_wake()
    assert daemon._wake.is_set()


def test_an_update_nobody_waits_on_is_taken_on_the_next_tick_not_woken_for():
    """Following a world target (a step a tick, no request waiting on it), the ACKs of an
    update wait for the next tick; a target waiting on one makes its completing ACK wake."""
    rig = world_rig()
    daemon = ArmDaemon(rig.config, clock=rig.clock)
    daemon._core = rig.core
    telemetry(rig)
    first = world_goto(rig, PARK)
    rig.ack_all(rig.sent)
    assert rig.reply(first).outcome is Outcome.ACCEPTED
    rig.clock.advance(1.0 / RATE_HZ)
    telemetry(rig, north_cm=3.0)
    step = rig.servo(rig.tick())
    assert step  # the hold's next step, in flight
    daemon._arm_ack_wake()
    for _ in step:
        daemon._on_frame(_ack_frame())
    assert not daemon._wake.is_set()
    acked = rig.core.status()["last_pwm_us"]
    assert any(acked[o] != pwm for o, pwm in step.items())  # not taken yet
    daemon._feed_frames()  # the next tick's first work
    acked = rig.core.status()["last_pwm_us"]
    assert all(acked[o] == pwm for o, pwm in step.items())
    # A base-frame target waits on its first update: the ACK that completes it wakes.
    rig.clock.advance(1.0 / RATE_HZ)
    request = daemon.new_request("goto", near(PARK))
    step = rig.servo(rig.take(rig.core.request(request)))
    daemon._arm_ack_wake()
    assert step
    for _ in step:
        daemon._on_frame(_ack_frame())
    assert daemon._wake.is_set()


def test_a_streamed_frame_wakes_the_control_thread_only_if_its_next_pass_is_far():
    rig = Rig()
    daemon = ArmDaemon(rig.config, clock=rig.clock)
    codec = mavlink.MAVLink(None, 1, 1)
    outputs = mavlink.MAV_SYS_STATUS_SENSOR_MOTOR_OUTPUTS
    frames = [
        codec.sys_status_encode(outputs, 0, outputs, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0),
        codec.system_time_encode(0, 1000),
        codec.servo_output_raw_encode(0, 0, *[1500] * 16),
    ]
    for frame in frames:
        msg = mavlink.MAVLink(None).parse_buffer(frame.pack(codec))[0]
        daemon._next_pass_s = rig.clock() + 0.02  # the next tick is near: it takes the frame
        daemon._on_frame(msg)
        assert not daemon._wake.is_set()
        daemon._next_pass_s = rig.clock() + 0.04
        daemon._on_frame(msg)
        assert daemon._wake.is_set()
        daemon._wake.clear()
    # A HEARTBEAT wakes it at once, however near its next pass.
    heartbeat = codec.heartbeat_encode(mavlink.MAV_TYPE_QUADROTOR, 3, 0, 0, 3).pack(codec)
    daemon._next_pass_s = rig.clock() + 0.001
    daemon._on_frame(mavlink.MAVLink(None).parse_buffer(heartbeat)[0])
    assert daemon._wake.is_set()
    assert len(daemon._frames) == 2 * len(frames) + 1  # all queued for the core


def test_brief_gives_status_figures_as_of_the_last_step_without_a_snapshot():
    rig = Rig()
    rig.up()
    daemon = ArmDaemon(rig.config, clock=rig.clock)
    daemon._core = rig.core
    accepted = daemon.new_request("goto", near(PARK))
    rig.take(rig.core.request(accepted))
    rig.ack_all(rig.sent)
    assert accepted.future.result(0).outcome is Outcome.ACCEPTED
    denied = daemon.submit_request(daemon.new_request("goto", {"pose": [math.nan] * 6}))
    assert denied.result(0).outcome is Outcome.DENIED  # refused before the core
    assert daemon.brief()["accepted"] == 0  # the control thread has not stepped since
    daemon._step()
    assert daemon.brief() == {
        "link": "closed",  # no link opened in this test
        "autopilot_heard_us": rig.core.status()["autopilot_heard_us"],
        "accepted": 1,
        "refused": 1,
    }


def test_status_is_built_for_whoever_asks_and_only_then():
    daemon = ArmDaemon(parse_config({"link": {"url": URL}}))
    builds, steps = [], []
    core_status, step = daemon._core.status, daemon._step
    daemon._core.status = lambda: builds.append(1) or core_status()  # type: ignore[method-assign]
    daemon._step = lambda: steps.append(1) or step()  # type: ignore[method-assign]
    # The control thread alone (no link: the core sees it down and ticks on).
    daemon._thread = threading.Thread(target=daemon._run, daemon=True)
    daemon._thread.start()
    try:
        assert wait_until(lambda: len(steps) >= 5, WAIT_S)
        assert builds == []
        daemon._core.counters["solved"] = 7  # before the call: the snapshot must count it
        assert daemon.status()["counters"]["solved"] == 7
        assert len(builds) == 1
    finally:
        daemon.close()
    assert not daemon._thread.is_alive()


def test_a_reload_says_what_it_applied(caplog):
    running = parse_config({"link": {"url": URL}})
    daemon = ArmDaemon(running)  # never started: reload needs no link
    with caplog.at_level("INFO", logger="armbridge"):
        daemon.reload(dataclasses.replace(running, budget_ms=5.0, joint_speed_deg_s=120.0))
        daemon.reload(daemon.config)
    said = [r.getMessage() for r in caplog.records if r.getMessage().startswith("reloaded")]
    assert said[0].endswith(": budget_ms 20.0 → 5.0, joint_speed_deg_s 60.0 → 120.0 applied")
    assert said[1].endswith(": nothing to apply")


def test_status_names_an_autopilot_signing_far_ahead_of_us_with_the_fix(tmp_path):
    from companion.daemon.cli import format_status
    from firmware_interface.signing import TICKS_PER_S, wall_to_ticks

    key = bytes(range(32))
    (tmp_path / "signing.key").write_bytes(key)
    (tmp_path / "signing.key").chmod(0o600)
    endpoint = UdpEndpoint()
    peer = ScriptedPeer(endpoint, signing_key=key)
    daemon = ArmDaemon(
        parse_config(
            {
                "link": {
                    "url": f"udpout:127.0.0.1:{endpoint.port}",
                    "signing_key": "signing.key",
                    "signing_state": "signing.state",
                }
            },
            source=str(tmp_path / "armbridge.toml"),
        )
    )
    daemon.start()
    try:
        assert peer.wait_for(lambda: endpoint.peer is not None)
        assert daemon.status()["link_signing_problem"] is None
        # The autopilot took the timestamp of a key holder whose clock is a week ahead.
        peer.mav.signing.timestamp = wall_to_ticks(time.time()) + 7 * 86_400 * TICKS_PER_S
        peer.send_heartbeat()
        assert wait_until(lambda: daemon.status()["link_signing_problem"] is not None, WAIT_S)
        status = daemon.status()
        problem = status["link_signing_problem"]
        assert problem.startswith("the autopilot 1/1 signs 7.0 days ahead of our clock")
        assert "Fix: " in problem and "SETUP_SIGNING" in problem
        assert status["autopilot"] is None and status["link_counters"]["rejected_future"] >= 1
        assert f"  signing: {problem}" in format_status(status).splitlines()
    finally:
        daemon.close()
        peer.close()


@pytest.mark.parametrize(
    ("rate_hz", "budget_ms", "ceiling_ms"), [(20.0, 20.0, 50.0), (100.0, 20.0, 20.0)]
)
def test_a_solve_is_bounded_by_the_control_period_in_wall_time(
    monkeypatch, rate_hz, budget_ms, ceiling_ms
):
    # The budget is the solver's CPU time; the wall-clock ceiling is the control period, or
    # the budget where that is longer.
    calls = []
    monkeypatch.setattr("companion.ik.solve", lambda *args, **kwargs: calls.append(kwargs))
    config = parse_config(
        {
            "link": {"url": URL},
            "solver": {"budget_ms": budget_ms},
            "control": {"rate_hz": rate_hz, "socket": ""},
        }
    )
    ArmDaemon(config)._solve(config.arm.fk([0, 90, 0, 0, 0, 0]), None)
    assert calls[0]["budget_ms"] == budget_ms and calls[0]["ceiling_ms"] == ceiling_ms


def test_a_solve_runs_the_configured_search(monkeypatch):
    calls = []
    monkeypatch.setattr("companion.ik.solve", lambda *args, **kwargs: calls.append(kwargs))
    config = parse_config(
        {
            "link": {"url": URL},
            "solver": {"method": "de", "pop_size": 16},
            "control": {"socket": ""},
        }
    )
    ArmDaemon(config)._solve(config.arm.fk([0, 90, 0, 0, 0, 0]), None)
    settings = calls[0]["settings"]
    assert settings is config.search_settings  # one object: the solver keeps its workspace
    assert (settings.pop_size, settings.lm_iterations, settings.F) == (16, 0, 0.9)


def test_frames_that_arrived_during_a_solve_are_fed_before_its_first_step():
    # A readback showing another sender's command, arrived while a goto was solved, was looked
    # at only after the goto's first step went out over that command (the core's side:
    # tests/daemon/core/test_outputs_ardupilot.py; the link's, which lets the reader hand on
    # what arrived while the solve held the interpreter: tests/firmware_interface).
    daemon = ArmDaemon(Rig().config)
    assert daemon._core.before_first_step == daemon._frames_before_step


def test_the_queued_frames_are_fed_as_one_batch_and_its_step_taken_after():
    rig = Rig()
    rig.up()
    daemon = ArmDaemon(rig.config, clock=rig.clock)
    daemon._core = rig.core
    during: list[bool] = []
    frame = rig.core.frame
    rig.core.frame = lambda msg, at_s=None: (
        during.append(rig.core.feeding_frames) or frame(msg, at_s)
    )
    fed: list[bool] = []
    rig.core.frames_fed = lambda: fed.append(rig.core.feeding_frames) or []
    daemon._on_frame(_ack_frame())
    daemon._on_frame(_ack_frame())
    daemon._feed_frames()
    assert during == [True, True] and fed == [False]
