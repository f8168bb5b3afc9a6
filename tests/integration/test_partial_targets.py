"""Partial targets end to end: a 4-joint arm cannot take every pose, but it can put
its hand at a position, or at a position with its z axis pointing a stated way. A ground
station asks for them with MAV_CMD_USER_1 param7 (0 pose, 1 position, 2 position + pointing),
the control socket with ``"mode"``; the simulated autopilot moves the same arm."""

from __future__ import annotations

import math

import numpy as np
import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from companion.kinematics.arm import Arm, Pose
from devkit.timing import WAIT_S, wait_until
from sim_servo.gcs import GroundStation

pytestmark = pytest.mark.slow

ARM4 = """name = "four-joint"
convention = "standard"
length_unit = "cm"
dof = 4
[[joint]]
name = "yaw"
alpha_deg = 90
a = 0
d = 10
min_deg = -170
max_deg = 170
[[joint]]
name = "shoulder"
alpha_deg = 0
a = 25
d = 0
min_deg = -10
max_deg = 170
[[joint]]
name = "elbow"
alpha_deg = 0
a = 20
d = 0
min_deg = -150
max_deg = 150
[[joint]]
name = "wrist"
alpha_deg = 0
a = 8
d = 0
min_deg = -120
max_deg = 120
"""


def hand_error_cm(hand: dict, pose: Pose) -> float:
    return float(np.linalg.norm(Pose(**hand["pose"]).position_cm - pose.position_cm))


def test_a_four_joint_arm_takes_positions_and_pointing_targets(tmp_path, sims, daemons):
    arm_file = tmp_path / "arm4.toml"
    arm_file.write_text(ARM4)
    arm = Arm.from_toml(arm_file)
    sim = sims(
        "--udp", "127.0.0.1:0", "--gcs", "127.0.0.1:0",
        "--arm", str(arm_file), "--arm-outputs", "9,10,11,12",
    )  # fmt: skip
    daemon = daemons(
        {
            "link": {"url": sim.url, "command_timeout_s": 0.3},
            "arm": {"file": str(arm_file), "joint_speed_deg_s": 720.0},
            "solver": {"seed": 3},
            "control": {"rate_hz": 50.0},
            "joint": [{"output": o} for o in (9, 10, 11, 12)],
        }
    )
    daemon.wait_link("up", WAIT_S)
    reached = arm.fk([30, 60, -40, 20])
    # The same position with an orientation no 4-joint arm of this shape can take.
    twisted = Pose(reached.x_cm, reached.y_cm, reached.z_cm, 35.0, -20.0, 80.0)
    with GroundStation(sim.gcs_url) as gcs:
        assert gcs.connect(WAIT_S)
        ack = gcs.wait_ack(WAIT_S, since_s=gcs.send_target(twisted.as_tuple()))
        assert ack is not None and ack.result == mavlink.MAV_RESULT_FAILED  # the whole pose
        ack = gcs.wait_ack(WAIT_S, since_s=gcs.send_target(twisted.as_tuple(), mode=1))
        assert ack is not None and ack.result == mavlink.MAV_RESULT_ACCEPTED
        ack = gcs.wait_ack(WAIT_S, since_s=gcs.send_target(twisted.as_tuple(), mode=7))
        assert ack is not None and ack.result == mavlink.MAV_RESULT_DENIED
        assert any("param7=7" in t for t in ack.statustexts), ack.statustexts
    assert wait_until(lambda: not daemon.status()["moving"] and sim.state()["settled"], WAIT_S)
    assert hand_error_cm(sim.state()["hand"], twisted) < 0.5  # servo quantisation at ~50 cm
    assert daemon.status()["last_target"]["mode"] == "position"

    # Position and pointing, over the control socket: the hand's z axis along the target's.
    pointing = arm.fk([-45, 80, -60, -30])
    reply = daemon.request("goto", pose=list(pointing.as_tuple()), mode="position_axis")
    assert reply["ok"] and reply["outcome"] == "accepted", reply
    assert wait_until(lambda: not daemon.status()["moving"] and sim.state()["settled"], WAIT_S)
    hand = sim.state()["hand"]
    assert hand_error_cm(hand, pointing) < 0.5
    got = Pose(**hand["pose"])
    cos = float(got.rotation[:, 2] @ pointing.rotation[:, 2])
    assert math.degrees(math.acos(min(1.0, cos))) < 1.0
    bad = daemon.request("goto", pose=list(pointing.as_tuple()), mode="sideways")
    assert bad["outcome"] == "denied" and "mode='sideways'" in bad["message"]
