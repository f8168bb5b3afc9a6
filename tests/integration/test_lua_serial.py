"""The ``ardupilot-lua`` dialect end to end over a modelled 115 200 baud serial line: the daemon
(in-process) on the simulator's pty, the simulator emulating the Lua bridge script."""

from __future__ import annotations

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from companion.daemon.service import Outcome
from devkit.sim_process import hand_errors
from devkit.timing import wait_until
from sim_servo.lua_bridge import SCRIPT_ANSWER_MS
from tests.integration.test_faults import (
    QUANT_ORI_DEG,
    QUANT_POS_CM,
    WAIT_S,
    poses,
    sim_pwm,
    start_daemon,
)

pytestmark = pytest.mark.slow  # a simulator process

MAV_CMD_USER_2 = 31011


def test_ardupilot_lua_dialect_over_a_115200_baud_pty(sims):
    sim = sims("--pty", "--pty-baud", "115200", "--lua-script", "--slew-s-per-60deg", "0")
    assert sim.url.endswith(",115200")
    # One control tick per target (36 000 deg/s): each target is one update, one frame.
    daemon = start_daemon(sim.url, dialect="ardupilot-lua", joint_speed_deg_s=36_000.0)
    try:
        outputs = daemon.config.calibration.outputs
        for target in poses(daemon.config, 2, seed=3):
            reply = daemon.submit("goto", target).result(WAIT_S)
            assert reply.outcome is Outcome.ACCEPTED, reply.message
            assert wait_until(lambda: not daemon.status()["moving"], WAIT_S)
            state = sim.state()
            assert sim_pwm(state, outputs) == daemon.status()["last_pwm_us"]
            pos_cm, ori_deg = hand_errors(target, state["hand"])
            assert pos_cm < QUANT_POS_CM and ori_deg < QUANT_ORI_DEG
        events = sim.events()
        commands = [e for e in events if e["event"] == "rx" and e["msg"] == "COMMAND_LONG"]
        sent = {e["fields"]["command"] for e in commands}
        assert MAV_CMD_USER_2 in sent and mavlink.MAV_CMD_DO_SET_SERVO not in sent
        frames = [e for e in commands if e["fields"]["command"] == MAV_CMD_USER_2]
        answers = [e for e in events if e["event"] == "ack" and e["command"] == MAV_CMD_USER_2]
        assert len(frames) == 2
        assert [a["result"] for a in answers] == [0, 0]
        # The script answers no sooner than its fixed part after the frame was whole.
        for frame, answer in zip(frames, answers, strict=True):
            assert answer["t_s"] - frame["t_s"] >= SCRIPT_ANSWER_MS / 1e3 - 1e-6
        assert daemon.status()["counters"]["servo_errors"] == 0
    finally:
        daemon.close()
