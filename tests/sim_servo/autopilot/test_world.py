"""The ``vehicle`` events: the vehicle and the hand in the world, written in batches."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from companion.kinematics.rotations import rpy_to_matrix
from sim_servo.autopilot.outputs import make_servos
from sim_servo.autopilot.world import VEHICLE_LOG_LAG_S, WorldLog
from sim_servo.config import SimConfig, VehicleConfig
from sim_servo.eventlog import world_timeline
from tests.sim_servo.autopilot.conftest import START_S, Harness, part_state


def test_vehicle_events_log_the_vehicle_and_the_hand_in_the_world():
    h = Harness(SimConfig(vehicle=VehicleConfig(log_rate_hz=20, seed=5)))
    h.command(mavlink.MAV_CMD_DO_SET_SERVO, 10, 1800)
    h.run_for(1.0)
    samples = world_timeline(h.events)
    assert [s.t_s for s in samples][:3] == [0.0, 0.05, 0.1]
    assert len(samples) == 21
    mount = VehicleConfig().mount
    rot_m = rpy_to_matrix(*np.radians(mount.rpy_deg))
    for sample in samples[::4]:
        assert sample.vehicle == h.ap.vehicle.state(sample.vehicle.t_s)
        assert sample.vehicle.t_s == pytest.approx(sample.t_s, abs=1e-6)
        # The hand from the horn positions then (the servos' own model), independently composed.
        positions = {o: s.position_us(START_S + sample.t_s) for o, s in h.ap.servos.items()}
        pose = h.hand.state(positions).pose
        v = sample.vehicle
        rot_v = rpy_to_matrix(v.roll_rad, v.pitch_rad, v.yaw_rad)
        rot_h = rpy_to_matrix(*np.radians([pose.roll_deg, pose.pitch_deg, pose.yaw_deg]))
        hand_base_m = np.array([pose.x_cm, pose.y_cm, pose.z_cm]) / 100.0
        expected = v.position_m + rot_v @ (np.array(mount.xyz_cm) / 100.0 + rot_m @ hand_base_m)
        np.testing.assert_allclose(sample.hand.position_m, expected, atol=1e-6)
        np.testing.assert_allclose(
            rpy_to_matrix(sample.hand.roll_rad, sample.hand.pitch_rad, sample.hand.yaw_rad),
            rot_v @ rot_m @ rot_h,
            atol=1e-6,
        )
    # The servo on output 10 moved meanwhile: the hand in the world moved with it.
    first, last = samples[0].hand, samples[-1].hand
    assert np.linalg.norm(first.position_m - last.position_m) > 0.05
    state = h.ap.snapshot(h.now)
    assert state["vehicle"]["t_s"] == pytest.approx(1.0)
    assert state["hand_ned"]["down_m"] == pytest.approx(last.down_m, abs=0.01)


def test_no_vehicle_events_at_rate_0_and_an_unknown_hand_is_none():
    h = Harness(SimConfig(vehicle=VehicleConfig(log_rate_hz=0)))
    h.run_for(1.0)
    assert world_timeline(h.events) == []
    h = Harness(SimConfig(vehicle=VehicleConfig(log_rate_hz=10)))
    h.command(mavlink.MAV_CMD_DO_SET_SERVO, 9, 2400)  # beyond the joint's PWM range
    h.run_for(1.0)
    assert world_timeline(h.events)[-1].hand is None


def test_vehicle_samples_written_late_keep_the_horn_positions_of_their_time():
    h = Harness(SimConfig(vehicle=VehicleConfig(hover=False, log_rate_hz=100)))
    h.run_for(0.5)
    assert len(world_timeline(h.events)) == 51  # a pass writes every sample due
    # No wake-up for each sample: the next one is written on any pass, at the latest 0.2 s late.
    assert h.ap.next_event_s(h.now) == pytest.approx(h.now + 0.01 + 0.2)
    h.command(mavlink.MAV_CMD_DO_SET_SERVO, 10, 1800)  # handled at the next pass, ≤ 2.5 ms
    h.run_for(1.0)
    ack_t_s = next(e["t_s"] for e in h.events if e["event"] == "ack")
    samples = world_timeline(h.events)
    assert len(samples) == 151  # 0 … 1.5 s, none lost to the batching
    before = [s.hand for s in samples if s.t_s <= ack_t_s]
    after = [s.hand for s in samples if s.t_s > ack_t_s]
    assert len(before) == 51 and all(hand == before[0] for hand in before)
    assert after[0] != before[0]  # the horn started at once
    assert after[-1] != after[0] and after[-1] == after[-2]  # it moved, then stopped


# -- the world log alone ---------------------------------------------------------------------


def test_samples_fall_on_their_cadence_and_are_written_in_batches():
    events: list = []
    config = replace(SimConfig(), vehicle=replace(SimConfig().vehicle, log_rate_hz=10.0))
    state = part_state(config, events)
    servos = make_servos(state, None, START_S)
    log = WorldLog(state, None, servos, now_s=START_S)
    assert log.next_event_s() == pytest.approx(START_S + VEHICLE_LOG_LAG_S)
    log.run(START_S + 0.25)
    assert [e["t_s"] for e in events] == [0.0, 0.1, 0.2]
    assert all(e["hand_ned"] is None for e in events)  # no hand model
    assert log.next_event_s() == pytest.approx(START_S + 0.3 + VEHICLE_LOG_LAG_S)
    log.run(START_S + 10.0)  # far behind: the cadence restarts from now
    assert events[-1]["t_s"] == 10.0 and len(events) == 4
