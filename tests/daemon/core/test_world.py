"""World-frame targets (``core/world.py``): the hand held in LOCAL_NED while the vehicle moves.
The fake solver reads a base-frame pose as joint angles, so the goal's first three "angles" are
the target's position in the arm's base frame."""

from __future__ import annotations

import math

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from companion.daemon.requests import Outcome
from tests.daemon.core.rig import (
    LEAD_MS,
    MOUNT_Z_CM,
    PARK,
    RATE_HZ,
    SERVO,
    near,
    telemetry,
    world_goto,
    world_rig,
)


def test_a_world_frame_target_is_refused_while_world_targets_are_off(rig):
    request = rig.request("goto", {"pose": near(PARK), "mode": "pose", "frame": "local_ned"})
    reply = rig.reply(request)
    assert reply.outcome is Outcome.DENIED and "local_ned" in reply.message
    assert not [c for c in rig.sent if c.command == SERVO]


def test_the_streams_are_asked_for_when_world_targets_are_on():
    rig = world_rig(telemetry_hz=25.0)
    asks = {
        int(c.params[0]): c.params[1]
        for c in rig.sent
        if c.command == mavlink.MAV_CMD_SET_MESSAGE_INTERVAL
    }
    assert asks[mavlink.MAVLINK_MSG_ID_ATTITUDE] == pytest.approx(40_000)
    assert asks[mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED] == pytest.approx(40_000)


def test_without_telemetry_a_world_target_is_temporarily_rejected():
    rig = world_rig()
    reply = rig.reply(world_goto(rig, PARK))
    assert reply.outcome is Outcome.TEMPORARILY_REJECTED
    assert "ATTITUDE" in reply.message and "LOCAL_POSITION_NED" in reply.message


def test_a_world_target_follows_the_vehicle_and_leads_its_motion():
    rig = world_rig()
    telemetry(rig)
    request = world_goto(rig, PARK)
    rig.clock.advance(0.01)  # the update's round trip: 10 ms
    rig.ack_all(rig.sent)
    assert rig.reply(request).outcome is Outcome.ACCEPTED
    assert rig.core.status()["world"]["following"] is True
    # The vehicle drifts 4 cm north at 50 cm/s: the target, fixed in the world, is 4 cm
    # further back in the arm's frame, plus what the vehicle covers until the step lands
    # (the link's one-way time, half the measured round trip, and lead_ms).
    rig.clock.advance(1.0 / RATE_HZ)
    telemetry(rig, north_cm=4.0, vn_cm_s=50.0)
    rig.tick()
    goal = rig.core.status()["goal_deg"]
    lead_s = 0.005 + LEAD_MS / 1000
    assert goal[0] == pytest.approx(PARK[0] - 4.0 - 50.0 * lead_s, abs=0.05)
    assert goal[1:] == pytest.approx(list(PARK[1:]), abs=1e-6)


def test_the_link_time_is_measured_to_the_acks_reception_not_to_when_they_are_taken():
    # Following a world target, the driver may leave the ACKs queued until the next tick: the
    # round trip (half of it leads the motion) ends when the last ACK came, not 10 ms later.
    rig = world_rig()
    telemetry(rig)
    request = world_goto(rig, PARK)
    sent_s = rig.clock()
    rig.clock.advance(0.02)
    codec = rig.codecs.setdefault((1, 1), mavlink.MAVLink(None, 1, 1))
    for c in list(rig.sent):
        if c.command == SERVO:
            ack = codec.command_ack_encode(SERVO, mavlink.MAV_RESULT_ACCEPTED, 0, 0, 1, 191)
            rig.take(rig.core.frame(rig.decoder.parse_buffer(ack.pack(codec))[0], sent_s + 0.01))
    assert rig.reply(request).outcome is Outcome.ACCEPTED
    rig.clock.advance(1.0 / RATE_HZ)
    telemetry(rig, north_cm=4.0, vn_cm_s=50.0)
    rig.tick()
    lead_s = 0.005 + LEAD_MS / 1000
    assert rig.core.status()["goal_deg"][0] == pytest.approx(
        PARK[0] - 4.0 - 50.0 * lead_s, abs=0.05
    )


def test_stale_telemetry_holds_and_says_why():
    rig = world_rig(max_age_ms=100.0)
    telemetry(rig)
    world_goto(rig, PARK)
    rig.ack_all(rig.sent)
    before = rig.core.status()["goal_deg"]
    rig.clock.advance(0.5)
    rig.tick()
    world = rig.core.status()["world"]
    assert rig.core.status()["goal_deg"] == before
    assert "old" in world["reason"] and world["telemetry_age_ms"] == pytest.approx(500, abs=1)


def test_out_of_reach_it_holds_the_last_reachable_pose_and_follows_again_when_back():
    rig = world_rig()
    telemetry(rig)
    world_goto(rig, PARK)
    rig.ack_all(rig.sent)
    held = rig.core.status()["goal_deg"]
    rig.clock.advance(1.0 / RATE_HZ)
    telemetry(rig, north_cm=-2000.0)  # the target now 2000 cm ahead: the fake solver fails
    rig.tick()
    status = rig.core.status()
    assert status["goal_deg"] == held
    assert status["world"]["reachable"] is False and "out of reach" in status["world"]["reason"]
    rig.clock.advance(1.0 / RATE_HZ)
    telemetry(rig, north_cm=-1.0)
    rig.tick()
    status = rig.core.status()
    assert status["world"]["reachable"] is True
    assert status["goal_deg"][0] == pytest.approx(PARK[0] + 1.0, abs=0.05)


def test_a_base_frame_target_or_a_stop_ends_the_hold():
    rig = world_rig()
    telemetry(rig)
    world_goto(rig, PARK)
    rig.ack_all(rig.sent)
    rig.request("stop")
    assert rig.core.status()["world"]["following"] is False
    rig.clock.advance(1.0 / RATE_HZ)
    telemetry(rig, north_cm=5.0)
    rig.sent.clear()
    rig.tick()
    assert not [c for c in rig.sent if c.command == SERVO]


def test_status_gives_the_hand_in_the_world():
    rig = world_rig()
    telemetry(rig, north_cm=100.0, yaw_rad=math.pi / 2)
    hand = rig.core.status()["world"]["hand_ned"]
    base = rig.config.arm.fk(rig.core.status()["current_deg"])
    # Yawed to the east: the base's x is the world's east, its y the world's south.
    assert hand["x_cm"] == pytest.approx(100.0 - base.y_cm, abs=1e-3)
    assert hand["y_cm"] == pytest.approx(base.x_cm, abs=1e-3)  # float32 on the wire
    assert hand["z_cm"] == pytest.approx(base.z_cm + MOUNT_Z_CM, abs=1e-3)
