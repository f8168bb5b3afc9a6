"""At the daemon (``ArmDaemon`` in-process, a scripted autopilot on loopback): who may
send targets (``link.allowed_senders``), and a signing state that cannot be stored, which must
hold the arm with a clear reason in ``status``."""

from __future__ import annotations

import dataclasses
import errno
import math
import os

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from companion.daemon.config import parse_config
from companion.daemon.service import ArmDaemon, Outcome
from devkit.mavlink_peer import ScriptedPeer, UdpEndpoint
from devkit.timing import wait_until
from firmware_interface.signing import write_state_file

KEY = bytes(range(32))
PARK_DEG = [10, 80, 10, 5, 5, 5]


@pytest.fixture
def autopilot():
    endpoint = UdpEndpoint()
    peer = ScriptedPeer(endpoint)
    yield endpoint, peer
    peer.close()


def start(daemon: ArmDaemon, endpoint, peer) -> ArmDaemon:
    daemon.start()
    assert peer.wait_for(lambda: endpoint.peer is not None)
    peer.send_heartbeat()
    assert wait_until(lambda: daemon.status()["link"] == "up")
    return daemon


def user_1(endpoint, source, params) -> None:
    """A USER_1 to the daemon (1/191) from ``source``, as the autopilot routes it."""
    codec = mavlink.MAVLink(None, *source)
    endpoint.write(
        codec.command_long_encode(1, 191, mavlink.MAV_CMD_USER_1, 0, *params, 0).pack(codec)
    )


def acks_to(peer, source):
    return [
        m for m in peer.messages("COMMAND_ACK") if (m.target_system, m.target_component) == source
    ]


def test_a_sender_outside_allowed_senders_is_denied_with_the_reason(autopilot):
    endpoint, peer = autopilot
    config = parse_config(
        {
            "link": {
                "url": f"udpout:127.0.0.1:{endpoint.port}",
                "allowed_senders": [[255, 190]],
            },
            "arm": {"park_deg": PARK_DEG},
        }
    )
    daemon = start(ArmDaemon(config), endpoint, peer)
    try:
        user_1(endpoint, (66, 190), (45.0, 10.0, 20.0, 0.0, 45.0, 0.0))
        assert peer.wait_for(lambda: acks_to(peer, (66, 190)))
        assert acks_to(peer, (66, 190))[0].result == mavlink.MAV_RESULT_DENIED
        texts = [m.text for m in peer.messages("STATUSTEXT")]
        assert "sender 66/190 not in link.allowed_senders" in texts
        # An allowed sender goes the usual way (here: a NaN is DENIED for what it is).
        user_1(endpoint, (255, 190), (1.0, 2.0, math.nan, 0.0, 0.0, 0.0))
        assert peer.wait_for(lambda: acks_to(peer, (255, 190)))
        assert acks_to(peer, (255, 190))[0].result == mavlink.MAV_RESULT_DENIED
        # A flood from outside the list is answered at the flood rate, not frame for frame.
        for _ in range(200):
            user_1(endpoint, (66, 190), (45.0, 10.0, 20.0, 0.0, 45.0, 0.0))
        assert wait_until(lambda: daemon.status()["counters"]["not_allowed"] == 201)
        counters = daemon.status()["counters"]
        assert counters["flood_unanswered"] > 0
        assert counters["targets"] == 1 and counters["servo_updates"] == 0
    finally:
        daemon.close()


def test_a_signing_state_that_cannot_be_stored_holds_the_arm_and_says_why(tmp_path):
    endpoint = UdpEndpoint()
    peer = ScriptedPeer(endpoint, signing_key=KEY)
    key_file = tmp_path / "signing.key"
    key_file.write_bytes(KEY)
    key_file.chmod(0o600)
    full = {"disk": False}

    def writer(path, reserved_until):
        if full["disk"]:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        write_state_file(path, reserved_until)

    wall = [1_790_000_000.0]
    config = parse_config(
        {
            "link": {
                "url": f"udpout:127.0.0.1:{endpoint.port}",
                "signing_key": str(key_file),
                "signing_state": str(tmp_path / "signing.state"),
            },
            "arm": {"park_deg": PARK_DEG},
        }
    )
    signing = dataclasses.replace(
        config.link.signing, write_state=writer, wall_clock=lambda: wall[0]
    )
    config = dataclasses.replace(config, link=dataclasses.replace(config.link, signing=signing))
    daemon = start(ArmDaemon(config), endpoint, peer)
    try:
        full["disk"] = True
        wall[0] += 45.0  # the next signed frame needs a new reservation
        # The heartbeat thread meets the fault first, and counts it right after.
        assert wait_until(
            lambda: (
                daemon.status()["link"] == "fault"
                and daemon.status()["link_counters"]["signing_state_errors"] >= 1
            )
        )
        assert "No space left on device" in daemon.status()["link_fault"]
        reply = daemon.submit("park").result(10.0)
        assert reply.outcome is Outcome.TEMPORARILY_REJECTED
        assert all(m.command != mavlink.MAV_CMD_DO_SET_SERVO for m in peer.messages("COMMAND_LONG"))
    finally:
        daemon.close()
        peer.close()
