"""COMMAND_LONG / COMMAND_INT: UNSUPPORTED for what no part handles, withheld ACKs, PX4's
commander cycle."""

from __future__ import annotations

import numpy as np
import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from sim_servo.config import Px4TimingConfig
from tests.sim_servo.autopilot.conftest import (
    READY_PX4,
    SET_ACTUATOR,
    START_S,
    Harness,
    acks,
    faulty,
    wait_ack,
)


@pytest.mark.parametrize(
    "command", [mavlink.MAV_CMD_NAV_TAKEOFF, mavlink.MAV_CMD_DO_SET_ACTUATOR, 31999]
)
def test_unknown_commands_are_unsupported(command):
    h = Harness()
    h.command(command, 1, 2, 3)
    ack = acks(h.run_for(0.1))[0]
    assert (ack.command, ack.result) == (command, mavlink.MAV_RESULT_UNSUPPORTED)


def test_withheld_ack_still_executes():
    h = faulty(withhold_ack_commands=frozenset({mavlink.MAV_CMD_DO_SET_SERVO}))
    h.command(mavlink.MAV_CMD_DO_SET_SERVO, 9, 1600)
    h.command(mavlink.MAV_CMD_NAV_TAKEOFF)
    msgs = h.run_for(0.5)
    assert [a.command for a in acks(msgs)] == [mavlink.MAV_CMD_NAV_TAKEOFF]
    assert h.ap.pwm_us[9] == 1600
    assert any(e["event"] == "ack" and e["withheld"] for e in h.events)


def test_withhold_all_acks():
    h = faulty(withhold_all_acks=True)
    h.command(mavlink.MAV_CMD_NAV_TAKEOFF)
    assert acks(h.run_for(0.5)) == []


def test_px4_timing_commander_cycle_and_main_loop():
    timing = Px4TimingConfig()  # the defaults: commander 10 ms, main loop 1.5 ms
    h = Harness(READY_PX4, px4_timing=timing)
    rng = np.random.default_rng(3)
    rtts = []
    for _ in range(200):
        h.run_for(rng.uniform(0.0, 0.02))
        sent = h.now
        h.command(SET_ACTUATOR, 0.1, 0, 0, 0, 0, 0, 0)
        rtts.append(wait_ack(h) - sent)
    rtts_ms = np.array(rtts) * 1000
    assert rtts_ms.min() > 0.0 and rtts_ms.max() <= 11.5 + 1e-6
    assert 4.5 <= float(np.median(rtts_ms)) <= 7.0
    # Every frame leaves on a 1.5 ms main-loop pass from boot.
    phases = [((t - START_S) * 1000 / 1.5) % 1 for t, _, _ in h.wire]
    assert all(min(p, 1 - p) < 1e-6 for p in phases)
