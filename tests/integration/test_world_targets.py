"""World-frame targets end to end: the simulator hovers (a seeded drift and tilt,
streaming ATTITUDE and LOCAL_POSITION_NED); a target in LOCAL_NED keeps the hand where it is in
the world, where holding the pose in the arm's frame would carry it along with the vehicle."""

from __future__ import annotations

import numpy as np
import pytest

from companion.kinematics.arm import Arm
from companion.kinematics.rotations import rpy_to_matrix
from companion.kinematics.vehicle import Mount, base_to_world, transform
from devkit.timing import WAIT_S, wait_until

pytestmark = pytest.mark.slow

HOLD_DEG = (0.0, 70.0, -70.0, 0.0, 0.0, 0.0)  # forward and below: room in every direction
HOME_NED_CM = (0.0, 0.0, -200.0)  # the simulator's default home


def vehicle_matrix(vehicle: dict) -> np.ndarray:
    rotation = rpy_to_matrix(vehicle["roll_rad"], vehicle["pitch_rad"], vehicle["yaw_rad"])
    return transform(rotation, [100.0 * vehicle[k] for k in ("north_m", "east_m", "down_m")])


def test_a_world_target_keeps_the_hand_still_in_the_world_while_the_vehicle_hovers(sims, daemons):
    sim = sims("--udp", "127.0.0.1:0", "--hover-seed", "4", "--vehicle-log-hz", "0")
    daemon = daemons(
        {
            "link": {"url": sim.url},
            "arm": {"joint_speed_deg_s": 180.0},
            "control": {"rate_hz": 50.0},
            "world": {"enabled": True},
        }
    )
    daemon.wait_link("up", WAIT_S)
    assert wait_until(lambda: daemon.status()["world"]["telemetry_age_ms"] is not None, WAIT_S)
    arm, mount = Arm.default(), Mount()
    held = arm.fk(HOLD_DEG)
    world = base_to_world(held, transform(np.eye(3), HOME_NED_CM), mount.matrix)
    # There first, in the arm's frame: from park the arm takes a while.
    reply = daemon.request("goto", pose=list(held.as_tuple()))
    assert reply["outcome"] == "accepted", reply
    assert wait_until(lambda: not daemon.status()["moving"] and sim.state()["settled"], WAIT_S)
    reply = daemon.request("goto", pose=list(world.as_tuple()), mode="position", frame="local_ned")
    assert reply["outcome"] == "accepted", reply
    samples: list[dict] = []

    def sampled() -> bool:  # 1.5 s of the simulator's time, a sample every 50 ms or more
        state = sim.state()
        if state["hand_ned"] is not None and (
            not samples or state["time_boot_ms"] - samples[-1]["time_boot_ms"] >= 50
        ):
            samples.append(state)
        return bool(samples) and samples[-1]["time_boot_ms"] - samples[0]["time_boot_ms"] > 1500

    assert wait_until(sampled, 4 * WAIT_S)
    target_cm = world.position_cm
    followed = [
        100.0
        * np.linalg.norm(
            np.array([s["hand_ned"][k] for k in ("north_m", "east_m", "down_m")])
            - target_cm / 100.0
        )
        for s in samples
    ]
    # Where the hand would be had the arm held its pose relative to the vehicle.
    carried = [
        np.linalg.norm(
            base_to_world(held, vehicle_matrix(s["vehicle"]), mount.matrix).position_cm - target_cm
        )
        for s in samples
    ]
    assert np.median(carried) > 1.0  # the vehicle does move
    assert np.median(followed) < 0.5 * np.median(carried), (followed, carried)
    status = daemon.status()["world"]
    assert status["following"] and status["reachable"], status
