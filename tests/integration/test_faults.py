"""The reliability campaign: the daemon against a real ``sim_servo`` subprocess with its faults on.

Each test starts the simulator with one family of fault flags (loss and jitter, a heartbeat
pause, a pty hang-up, withheld ACKs) and checks what the daemon promises under it: accepted
targets reach the servos, the arm holds while the autopilot is silent, the serial port comes
back, a command nobody answers ends in a bounded time with a clear error. In every case no PWM
outside the calibration reaches the simulator and the daemon's control thread stays alive.

Times are measured on the simulator's clock where possible (its event log and ``state`` carry
``t_s``), so a figure is an upper bound and never depends on how fast the test polls. The
measured figures are printed (``pytest -s`` shows them).
"""

from __future__ import annotations

import dataclasses
import gc
import json
import math
import time

import numpy as np
import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from companion.daemon.config import parse_config
from companion.daemon.service import ArmDaemon, Outcome
from companion.ik import warm_up
from devkit.sim_process import SimProcess, assert_within_quantisation, hand_errors
from devkit.timing import wait_until

pytestmark = pytest.mark.slow  # a simulator process per test, faults that take seconds

WAIT_S = 10.0
DO_SET_SERVO = mavlink.MAV_CMD_DO_SET_SERVO
#: 1 µs of PWM is 0.18° on a 180° joint: the hand is this close to a target at best.
QUANT_POS_CM = 0.2
QUANT_ORI_DEG = 0.5


def config_dict(url: str, **link) -> dict:
    return {
        "link": {"url": url, **link},
        "arm": {"park_deg": [0, 90, 0, 0, 0, 0], "joint_speed_deg_s": 360.0},
        "control": {"rate_hz": 50.0},
        "solver": {"seed": 1},
    }


def start_daemon(url: str, *, joint_speed_deg_s: float = 360.0, **link) -> ArmDaemon:
    # The speed is set after parsing: a test may go past the config's 1000 deg/s bound, which
    # load_config would refuse, to make every move a single servo update.
    config = dataclasses.replace(
        parse_config(config_dict(url, **link)), joint_speed_deg_s=joint_speed_deg_s
    )
    daemon = ArmDaemon(config)
    # As `armbridge run` does before READY: a first solve that compiles or loads the kernels
    # would overrun its 20 ms budget and fail a reachable target; and the heap they leave is
    # frozen, so no full collection pass over it stalls the control thread.
    warm_up()
    gc.freeze()
    daemon.start()
    assert daemon.wait_for_autopilot(WAIT_S)
    return daemon


def spy_on_frames(daemon: ArmDaemon) -> list[str]:
    """The types of the frames the daemon's control core takes, in the order it takes them
    (appended on the control thread)."""
    taken: list[str] = []
    core = daemon._core
    frame = core.frame

    def spy(msg, received_s=None):
        taken.append(msg.get_type())
        return frame(msg, received_s)

    core.frame = spy
    return taken


def poses(daemon_config, count: int, seed: int) -> list[tuple[float, ...]]:
    """``count`` reachable targets: FK of joints drawn inside the middle of each range, so the
    solver converges and consecutive targets are a real move apart."""
    rng = np.random.default_rng(seed)
    arm = daemon_config.arm
    out = []
    for _ in range(count):
        q_deg = [
            math.degrees(j.min_rad + (j.max_rad - j.min_rad) * rng.uniform(0.2, 0.8))
            for j in arm.joints
        ]
        out.append(arm.fk(q_deg).as_tuple())
    return out


def sim_pwm(state: dict, outputs) -> dict[int, int]:
    return {o: state["outputs"][str(o)]["pwm_us"] for o in outputs}


def assert_pwm_within_calibration(sim: SimProcess, calibration) -> int:
    """Every PWM the simulator was sent for, or applied to, an arm output is inside that
    joint's calibrated range, and no other output was touched. Returns how many were checked."""
    ranges = {j.output: j.pwm_range_us for j in calibration.joints}
    checked = 0
    for event in sim.events():
        if event["event"] == "servo":
            output, pwm = event["output"], event["pwm_us"]
        elif (
            event["event"] == "rx"
            and event["msg"] == "COMMAND_LONG"
            and event["fields"]["command"] == DO_SET_SERVO
        ):
            output, pwm = int(event["fields"]["param1"]), event["fields"]["param2"]
        else:
            continue
        assert output in ranges, f"output {output} is not an arm output: {event}"
        low, high = ranges[output]
        assert low <= pwm <= high, f"pwm_us={pwm} outside [{low}, {high}]: {event}"
        checked += 1
    return checked


def report(name: str, **figures) -> None:
    print(f"\n[{name}] " + json.dumps(figures, default=str))


# -- 1. loss and jitter -----------------------------------------------------------------------

LOSSY_TARGETS = 12


def test_every_accepted_target_reaches_the_servos_through_10_percent_loss_and_jitter(sims):
    # 10 % of frames lost each way; outgoing frames delayed 50 +- 50 ms (jitter alone would be
    # clipped at 0 for half the frames, so latency centres it), which also reorders them.
    sim = sims(
        "--udp",
        "127.0.0.1:0",
        "--drop-in",
        "0.1",
        "--drop-out",
        "0.1",
        "--latency-ms",
        "50",
        "--jitter-ms",
        "50",
        "--seed",
        "8",
        "--slew-s-per-60deg",
        "0",
    )
    # An ACK is at most 100 ms late, so 0.2 s per attempt never mistakes a late ACK for the
    # next one. A round trip fails 19 % of the time (1 - 0.9 * 0.9); 8 retries make a lost
    # update 0.19 ** 9 = 3e-7 likely per command.
    # Each target is one control tick away (joint speed 36 000 deg/s at 50 Hz), so every
    # target is one servo update of 6 commands.
    daemon = start_daemon(
        sim.url, joint_speed_deg_s=36_000.0, command_timeout_s=0.2, command_retries=8
    )
    calibration = daemon.config.calibration
    worst = (0.0, 0.0)
    t0 = time.monotonic()
    try:
        held = 0
        for target in poses(daemon.config, LOSSY_TARGETS, seed=5):
            reply = daemon.submit("goto", target).result(WAIT_S)
            while reply.outcome is Outcome.TEMPORARILY_REJECTED and held < 5:
                # The autopilot silent for its gap (lost frames, and on a busy machine a
                # starved simulator): the daemon holds and says so. Sent again once it is back.
                held += 1
                assert wait_until(lambda: not daemon.status()["holding"], WAIT_S)
                reply = daemon.submit("goto", target).result(WAIT_S)
            assert reply.outcome is Outcome.ACCEPTED, reply.message
            assert wait_until(lambda: not daemon.status()["moving"], WAIT_S)
            state = sim.state()
            assert sim_pwm(state, calibration.outputs) == daemon.status()["last_pwm_us"]
            errors = hand_errors(target, state["hand"])
            assert errors[0] < QUANT_POS_CM and errors[1] < QUANT_ORI_DEG, errors
            worst = max(worst[0], errors[0]), max(worst[1], errors[1])
        elapsed_s = time.monotonic() - t0
        status = daemon.status()
        assert status["counters"]["accepted"] == LOSSY_TARGETS
        assert status["counters"]["servo_errors"] == 0 and daemon.healthy
        stats = sim.state()["stats"]
        assert stats["dropped_in"] > 0 and stats["dropped_out"] > 0  # the faults did happen
        events = sim.events()
        sent = sum(
            1
            for e in events
            if e.get("msg") == "COMMAND_LONG"
            and (e["event"] == "rx" or e.get("fault") == "drop_in")
        )
        commands = status["counters"]["servo_updates"] * len(calibration)
        checked = assert_pwm_within_calibration(sim, calibration)
        report(
            "loss-jitter",
            targets=LOSSY_TARGETS,
            accepted=status["counters"]["accepted"],
            reached=LOSSY_TARGETS,
            sent_again_after_a_hold=held,
            servo_updates=status["counters"]["servo_updates"],
            commands=commands,
            command_sends=sent,
            retries=sent - commands,
            sim_dropped_in=stats["dropped_in"],
            sim_dropped_out=stats["dropped_out"],
            acks=stats["acks"],
            worst_pos_cm=round(worst[0], 4),
            worst_ori_deg=round(worst[1], 4),
            link_stats=daemon.link.stats,
            pwm_checked=checked,
            elapsed_s=round(elapsed_s, 2),
        )
    finally:
        daemon.close()


# -- 2. heartbeat pause (the daemon as the `armbridge run` service) ---------------------------


def test_heartbeat_pause_holds_within_3_s_refuses_targets_and_recovers(sims, daemons):
    # The autopilot's HEARTBEAT stops (asked over the simulator's query socket) just after a
    # slow move began; the daemon runs with the default loss timeout (3 s) and a slow joint
    # speed, so the arm is still moving when the link is declared lost: only the hold keeps
    # servo commands from going out. The heartbeat restarts once a target has been refused.
    sim = sims("--udp", "127.0.0.1:0", "--slew-s-per-60deg", "0")
    cfg = config_dict(sim.url)
    cfg["arm"]["joint_speed_deg_s"] = 10.0
    cfg["control"]["rate_hz"] = 20.0
    daemon = daemons(cfg)
    config = parse_config(daemon.config)
    calibration = config.calibration
    try:
        daemon.wait_link("up", WAIT_S)
        # The move below takes 8 s: started before the pause, it is still going at the hold.
        far = config.arm.fk([80, 20, 70, 60, -60, 80]).as_tuple()
        near = config.arm.fk([0, 80, 10, 0, 0, 0]).as_tuple()
        assert daemon.request("goto", pose=list(far))["outcome"] == "accepted"
        sim.pause_heartbeat()

        assert wait_until(lambda: daemon.status()["holding"], 3.0 + WAIT_S)
        held_sim_s = sim.state()["t_s"]
        held = daemon.status()
        [paused] = sim.events("fault", fault="heartbeat_paused")
        hold_s = held_sim_s - paused["t_s"]
        # The loss timeout counts from the last heartbeat, up to a period before the pause;
        # the hold comes on the next control tick, and this poll sees it a little later.
        assert hold_s <= 3.0 + 0.5, f"held {hold_s:.2f} s after the heartbeat stopped"
        assert held["moving"], "the move ended before the hold: nothing would be sent anyway"
        reply = daemon.request("goto", pose=list(near))
        assert reply["outcome"] == "temporarily_rejected", reply
        sim.pause_heartbeat(False)

        assert wait_until(lambda: not daemon.status()["holding"], WAIT_S)
        [resumed] = sim.events("fault", fault="heartbeat_resumed")
        commands = [
            e
            for e in sim.events("rx", msg="COMMAND_LONG")
            if e["fields"]["command"] == mavlink.MAV_CMD_DO_SET_SERVO
        ]
        during = [e for e in commands if held_sim_s <= e["t_s"] <= resumed["t_s"]]
        assert during == [], f"servo commands while holding: {during[:3]}"
        # Back up: the PWMs held are sent again first, then the move carries on.
        assert wait_until(
            lambda: (
                len([e for e in sim.events("servo") if e["t_s"] > resumed["t_s"]])
                >= len(calibration)
            ),
            WAIT_S,
        )
        first_after = [e for e in sim.events("servo") if e["t_s"] > resumed["t_s"]]
        first_after = {e["output"]: e["pwm_us"] for e in first_after[: len(calibration)]}
        # While held, what the outputs hold is unknown (status says so); what is sent again is
        # the pose last acknowledged, or the step that was on its way at the loss (the outputs
        # hold one of the two, a step apart).
        assert held["last_pwm_us"] is None
        assert {o["state"] for o in held["outputs"].values()} == {"unknown"}
        step_deg = cfg["arm"]["joint_speed_deg_s"] / cfg["control"]["rate_hz"]
        for output, pwm in first_after.items():
            joint = calibration.for_output(output)
            angle = joint.pwm_us_to_angle_deg(pwm)
            acked = held["current_deg"][calibration.outputs.index(output)]
            assert abs(angle - acked) <= step_deg + 0.2, (output, angle, acked)
        servo_after = [e["t_s"] for e in sim.events("servo") if e["t_s"] > resumed["t_s"]]
        recovered_s = min(servo_after) - resumed["t_s"]

        assert daemon.request("goto", pose=list(near))["outcome"] == "accepted"
        assert daemon.request("stop")["outcome"] == "accepted"
        assert wait_until(
            lambda: (
                sim_pwm(sim.state(), calibration.outputs)
                == {int(o): p for o, p in daemon.status()["last_pwm_us"].items()}
            ),
            WAIT_S,
        )
        status = daemon.status()
        assert status["counters"]["temporarily_rejected"] == 1
        assert status["counters"]["servo_errors"] == 0
        checked = assert_pwm_within_calibration(sim, calibration)
        assert daemon.proc.poll() is None
        report(
            "heartbeat-pause",
            pause_to_hold_s=round(hold_s, 3),
            servo_commands_while_holding=len(during),
            resume_to_first_servo_command_s=round(recovered_s, 3),
            counters=status["counters"],
            pwm_checked=checked,
        )
    finally:
        assert daemon.stop() == 0


# -- 3. pty hang-up ---------------------------------------------------------------------------


def test_pty_hangup_the_daemon_holds_reopens_within_2_s_and_resends_first(sims, tmp_path):
    # A USB serial adapter unplugged once the first move is done (the simulator's query
    # ``hangup``) and re-enumerated 3.2 s later under the same udev name. With a backoff
    # doubling to 5 s the daemon's reopen attempts would fall 3.1 s and 6.3 s after the
    # hang-up: 3 s late. The loss timeout (5 s) outlasts the gap, so only the
    # port's failure can tell the daemon to hold, and to re-send its PWMs when it is back.
    link = tmp_path / "ttyFC"
    sim = sims(
        "--pty",
        "--pty-link",
        str(link),
        "--hangup-for",
        "3.2",
        "--slew-s-per-60deg",
        "0",
    )
    assert sim.url == f"{link},115200"
    daemon = start_daemon(sim.url, command_timeout_s=0.3, loss_timeout_s=5.0)
    calibration = daemon.config.calibration
    taken = spy_on_frames(daemon)
    try:
        first, second, third = poses(daemon.config, 3, seed=3)
        assert daemon.submit("goto", first).result(WAIT_S).outcome is Outcome.ACCEPTED
        assert wait_until(lambda: not daemon.status()["moving"], WAIT_S)
        len_before = len(taken)  # frames the control thread took before its motion ended
        assert sim_pwm(sim.state(), calibration.outputs) == daemon.status()["last_pwm_us"]
        updates = daemon.status()["counters"]["servo_updates"]
        # Until a SYS_STATUS saying the safety switch is off comes after the last step, the
        # outputs may hold any step of the last SYS_STATUS interval (0.25 s on this line), and
        # a re-send goes to the middle of those (core.SAFETY_STEPS_AHEAD), not to the last one.
        # An "off" also keeps the pose a step was sent from when the step went out less than
        # half an interval before it (SYS_STATUS_AGE_INTERVALS, core/outputs_ardupilot.py):
        # the unplugging comes after two, the second an interval after the first, so the pose
        # re-sent is the one acknowledged.
        assert wait_until(lambda: taken[len_before:].count("SYS_STATUS") >= 2, WAIT_S)
        assert sim.hangup()

        assert wait_until(lambda: daemon.status()["holding"], WAIT_S)
        held_sim_s = sim.state()["t_s"]
        [hangup] = sim.events("fault", fault="hangup")
        assert daemon.link.stats.transport_errors >= 1 and not link.exists()
        hold_s = held_sim_s - hangup["t_s"]
        assert hold_s < 1.0, f"held {hold_s:.2f} s after the hang-up"
        # The daemon keeps trying: it neither ends the link nor stops its control loop, and it
        # refuses targets for now rather than failing them.
        reply = daemon.submit("goto", second).result(WAIT_S)
        assert reply.outcome is Outcome.TEMPORARILY_REJECTED, reply.message
        assert not daemon.link.closed and daemon.healthy and sim.state()["link"]["closed"]

        reconnects = daemon.link.stats.reconnects
        assert wait_until(lambda: daemon.link.stats.reconnects > reconnects, WAIT_S)
        reopened_sim_s = sim.state()["t_s"]  # the sim's clock, just after the daemon reopened
        assert wait_until(lambda: daemon.status()["link"] == "up", WAIT_S)
        up_sim_s = sim.state()["t_s"]
        [reopen] = sim.events("fault", fault="reopen")
        reopen_s = reopened_sim_s - reopen["t_s"]
        assert reopen_s <= 2.0, f"reopened {reopen_s:.2f} s after the pty came back"

        # Servo commands flow again: first the current PWMs, then a new target.
        def servo_since_reopen():
            return [e for e in sim.events("servo") if e["t_s"] > reopen["t_s"]]

        assert wait_until(lambda: len(servo_since_reopen()) >= len(calibration), WAIT_S)
        # The sim logs the sixth command before its ACK is back at the daemon: wait for that.
        assert wait_until(lambda: daemon.status()["counters"]["servo_updates"] == updates + 1)
        resent = {e["output"]: e["pwm_us"] for e in servo_since_reopen()[: len(calibration)]}
        assert resent == daemon.status()["last_pwm_us"]
        assert not daemon.status()["holding"]
        assert daemon.submit("goto", third).result(WAIT_S).outcome is Outcome.ACCEPTED
        assert wait_until(lambda: not daemon.status()["moving"], WAIT_S)
        state = sim.state()
        assert sim_pwm(state, calibration.outputs) == daemon.status()["last_pwm_us"]
        # Within what whole-µs PWMs allow at the joints reached: the solver's seed, and so
        # the solution and its rounding, differs from run to run, and at some solutions the
        # rounding adds up to more than a fixed 0.2 cm.
        pos_cm, ori_deg = assert_within_quantisation(
            third, state["hand"], daemon.status()["current_deg"]
        )

        first_rx = min(e["t_s"] for e in sim.events("rx") if e["t_s"] > reopen["t_s"])
        checked = assert_pwm_within_calibration(sim, calibration)
        assert daemon.healthy
        report(
            "pty-hangup",
            hangup_for_s=3.2,
            hangup_to_hold_s=round(hold_s, 3),
            reopen_to_daemon_reopened_s=round(reopen_s, 3),
            reopen_to_link_up_s=round(up_sim_s - reopen["t_s"], 3),
            reopen_to_first_daemon_frame_s=round(first_rx - reopen["t_s"], 3),
            link_stats=daemon.link.stats,
            pwm_checked=checked,
        )
    finally:
        daemon.close()


# -- 4. withheld ACKs -------------------------------------------------------------------------


def servo_commands(sim: SimProcess) -> list[dict]:
    """The DO_SET_SERVO the simulator received (the daemon also sends SET_MESSAGE_INTERVAL)."""
    return [
        e
        for e in sim.events("rx", msg="COMMAND_LONG")
        if e["fields"]["command"] == mavlink.MAV_CMD_DO_SET_SERVO
    ]


def test_withheld_acks_fail_the_target_in_bounded_time_and_a_rebooted_autopilot_is_used(sims):
    # The autopilot executes DO_SET_SERVO but never acknowledges it. An update's commands go
    # out together, then one at a time, each tried (retries + 1) times in all for
    # command_timeout_s each, stopping at the first that fails: a goto must end within
    # 3 x 0.3 s = 0.9 s of its first send.
    timeout_s, retries = 0.3, 2
    bound_s = timeout_s * (retries + 1)
    faulty = sims(
        "--udp", "127.0.0.1:0", "--withhold-ack", "DO_SET_SERVO", "--slew-s-per-60deg", "0"
    )
    daemon = start_daemon(faulty.url, command_timeout_s=timeout_s, command_retries=retries)
    calibration = daemon.config.calibration
    try:
        targets = poses(daemon.config, 3, seed=11)
        took_s, status_ms = [], []
        for target in targets[:2]:
            sent = len(servo_commands(faulty))
            t0 = time.monotonic()
            future = daemon.submit("goto", target)
            # While the control thread waits for the ACK, the daemon still answers.
            assert wait_until(lambda n=sent: len(servo_commands(faulty)) > n)
            assert wait_until(lambda: daemon.status()["goal_deg"] is not None)
            t1 = time.monotonic()
            assert daemon.status()["goal_deg"] is not None and not future.done()
            status_ms.append((time.monotonic() - t1) * 1000)
            failure = future.result(WAIT_S)
            took_s.append(time.monotonic() - t0)
            assert failure.outcome is Outcome.FAILED
            assert "MAV_CMD_DO_SET_SERVO" in failure.message, failure.message
            assert f"after {retries + 1} attempts of timeout_s={timeout_s}" in failure.message
        # solve (< 20 ms budget) + one control tick (20 ms) + the retries, and slack for a
        # machine loaded by other processes (the figure itself is printed below with -s): the
        # behaviour checked is a bounded answer, not its exact time.
        assert max(took_s) < bound_s + 1.0, took_s
        status = daemon.status()
        assert status["counters"]["servo_errors"] == 2 and status["counters"]["failed"] == 2
        assert status["last_pwm_us"] is None and status["goal_deg"] is None and daemon.healthy
        sends = servo_commands(faulty)
        withheld = faulty.events("ack", withheld=True)
        # Per target: the six commands back-to-back, then the first joint's alone until it is
        # answered (retries more times); the rest are not sent once that one fails.
        joints = len(calibration)
        assert len(sends) == len(withheld) == 2 * (joints + retries)
        per_target = [0] * joints + list(range(1, retries + 1))
        assert [int(e["fields"]["confirmation"]) for e in sends] == per_target * 2
        checked = assert_pwm_within_calibration(faulty, calibration)

        # The autopilot reboots without the fault on the same port: the daemon carries on.
        port = faulty.url.rpartition(":")[2]
        assert faulty.stop() == 0
        fixed = sims("--udp", f"127.0.0.1:{port}", "--slew-s-per-60deg", "0")
        assert wait_until(lambda: fixed.state()["peer"] is not None, WAIT_S)
        # On a loaded machine the gap may have outlasted loss_timeout_s: the link is back once
        # the new autopilot is heard and has answered us, and its first SYSTEM_TIME has shown
        # the reboot (a target before that is answered TEMPORARILY_REJECTED when it does).
        assert wait_until(
            lambda: (
                (s := daemon.status())["link"] == "up"
                and s["autopilot_heard_us"]
                and s["counters"]["autopilot_reboots"] >= 1
            ),
            WAIT_S,
        )
        reply = daemon.submit("goto", targets[2]).result(WAIT_S)
        assert reply.outcome is Outcome.ACCEPTED, reply.message
        assert wait_until(lambda: not daemon.status()["moving"], WAIT_S)
        state = fixed.state()
        assert sim_pwm(state, calibration.outputs) == daemon.status()["last_pwm_us"]
        # The bound for the joints it is at (a fixed one was 0.009 cm short for one solution).
        assert_within_quantisation(targets[2], state["hand"], daemon.status()["current_deg"])
        checked += assert_pwm_within_calibration(fixed, calibration)
        assert daemon.healthy
        report(
            "withheld-ack",
            bound_s=round(bound_s, 3),
            goto_to_failed_s=[round(t, 3) for t in took_s],
            status_during_retries_ms=[round(t, 2) for t in status_ms],
            message=failure.message,
            sends=len(sends),
            counters=daemon.status()["counters"],
            pwm_checked=checked,
        )
    finally:
        daemon.close()


# -- 5. a quick autopilot reboot -----------------------------------------------------------------


def test_a_reboot_shorter_than_the_loss_timeout_is_seen_and_every_output_resent(sims):
    # Seen by an adversarial review: an autopilot restarted within loss_timeout_s (0.36 s of
    # silence) went unnoticed, status "up" with the old PWMs while its outputs were at 0 µs.
    sim = sims("--udp", "127.0.0.1:0", "--slew-s-per-60deg", "0")
    daemon = start_daemon(sim.url)
    calibration = daemon.config.calibration
    try:
        [target] = poses(daemon.config, 1, seed=21)
        assert daemon.submit("goto", target).result(WAIT_S).outcome is Outcome.ACCEPTED
        assert wait_until(lambda: not daemon.status()["moving"], WAIT_S)
        # The daemon asked for SYSTEM_TIME (ArduCopter streams none by default) and has one: a
        # reboot before the first could not be told from a first boot.
        assert wait_until(lambda: daemon.status()["autopilot_boot_ms"] is not None, WAIT_S)
        held = daemon.status()["last_pwm_us"]
        assert sim.reboot()
        seen = wait_until(lambda: daemon.status()["counters"]["autopilot_reboots"] == 1, WAIT_S)
        # (A failure once, in a full run: kept with what explains it, should it come back.)
        assert seen, (daemon.status(), sim.events("fault"), sim.state()["time_boot_ms"])
        [booted] = sim.events("fault", fault="booted")
        # Every output sent again, with no new target asked for, within the band of poses it
        # may have held (half the safety band: a step or 50 ms of motion), and the arm holds
        # there: the goal accepted before the reboot is dropped.
        width_deg = daemon.config.joint_speed_deg_s * max(1 / daemon.config.rate_hz, 0.05)

        def near_held() -> bool:
            shown = sim_pwm(sim.state(), calibration.outputs)
            if shown.keys() != held.keys() or 0 in shown.values():  # 0: no pulses yet
                return False
            return all(
                abs(
                    calibration.for_output(o).pwm_us_to_angle_deg(shown[o])
                    - calibration.for_output(o).pwm_us_to_angle_deg(held[o])
                )
                <= width_deg / 2 + 0.2
                for o in held
            )

        assert wait_until(near_held, WAIT_S), (sim_pwm(sim.state(), calibration.outputs), held)
        resent = [
            e for e in sim.events("servo") if e["t_s"] >= booted["t_s"] and e["output"] in held
        ]
        assert sorted({e["output"] for e in resent}) == sorted(calibration.outputs)
        shown = sim_pwm(sim.state(), calibration.outputs)
        assert wait_until(lambda: daemon.status()["last_pwm_us"] == shown, WAIT_S)  # ACKs back
        assert daemon.status()["goal_deg"] is None
        assert daemon.status()["link"] == "up"
        report(
            "reboot",
            detected_s=round(min(e["t_s"] for e in resent) - booted["t_s"], 3),
        )
    finally:
        daemon.close()
