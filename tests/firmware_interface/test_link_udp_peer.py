"""Where a ``udpin`` link sends, and what one datagram can do to the next.

The autopilot is a :class:`ScriptedPeer` that sends first (ArduPilot's ``udpclient``); an
attacker on loopback sends garbage and valid frames from other ids. Real sockets, bounded waits.
"""

from __future__ import annotations

import socket
import time

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from devkit.mavlink_peer import ScriptedPeer, UdpClientEndpoint, UdpEndpoint
from devkit.timing import FakeClock, wait_until
from firmware_interface.link import PEER_HOLD_S, LinkConfig, LinkState, MavlinkLink
from firmware_interface.signing import SigningConfig, wall_to_ticks

KEY = bytes(range(32))


def frame(msg_of, system: int, component: int, key: bytes | None = None, timestamp: int = 0):
    """One frame from ``system/component``, built by ``msg_of(codec)``; signed with ``key``."""
    codec = mavlink.MAVLink(None, system, component)
    if key is not None:
        codec.signing.secret_key = key
        codec.signing.sign_outgoing = True
        codec.signing.timestamp = timestamp
    return msg_of(codec).pack(codec)


def autopilot_heartbeat(codec):
    return codec.heartbeat_encode(
        mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA, 0, 0, 4
    )


def open_udpin(clock=None, signing=None) -> MavlinkLink:
    kwargs = {"clock": clock} if clock is not None else {}
    return MavlinkLink.open(
        "udpin:127.0.0.1:0", LinkConfig(heartbeat_rate_hz=50.0, signing=signing), **kwargs
    )


@pytest.fixture
def attacker():
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))
    yield sock
    sock.close()


def test_udpin_peer_is_never_moved_by_garbage_or_frames_from_other_ids(attacker):
    link = open_udpin()
    peer = ScriptedPeer(UdpClientEndpoint(link.transport.local_address))
    try:
        peer.send_heartbeat()
        link.wait_for_autopilot(5.0)
        assert wait_until(lambda: link.transport.peer == ("127.0.0.1", peer.endpoint.port))
        target = link.transport.local_address
        # Garbage, then an "autopilot" HEARTBEAT and a STATUSTEXT from system 66: all valid
        # MAVLink, none from the pinned autopilot 1/1. Today's udpin sent to the last sender.
        for _ in range(20):
            attacker.sendto(b"\x00", target)
        attacker.sendto(frame(autopilot_heartbeat, 66, 1), target)
        attacker.sendto(frame(lambda c: c.statustext_encode(4, b"hijack"), 66, 1), target)
        assert wait_until(lambda: link.stats.rx_foreign_address >= 2)
        before = len(peer.messages("HEARTBEAT"))
        assert wait_until(lambda: len(peer.messages("HEARTBEAT")) >= before + 3)
        attacker.setblocking(False)
        with pytest.raises(BlockingIOError):
            attacker.recv(65535)  # not one byte came to the attacker
        assert link.transport.peer == ("127.0.0.1", peer.endpoint.port)
        assert link.autopilot.system_id == 1 and link.stats.peer_changes == 1
    finally:
        link.close()
        peer.close()


def test_udpin_sends_its_heartbeat_as_soon_as_it_knows_the_autopilot():
    """The autopilot learns our route from our first frame: it comes at once, not at the next
    1 Hz beat (PX4 dropped a ground station's USER_1 sent right after we were up)."""
    link = MavlinkLink.open("udpin:127.0.0.1:0", LinkConfig(heartbeat_rate_hz=0.1))
    peer = ScriptedPeer(UdpClientEndpoint(link.transport.local_address))
    try:
        assert wait_until(lambda: link.stats.tx_messages >= 1)  # the first beat, to no one
        sent_s = time.monotonic()
        peer.send_heartbeat()
        [heartbeat] = peer.wait_for_messages("HEARTBEAT", timeout_s=5.0)
        assert heartbeat.get_srcComponent() == 191
        assert time.monotonic() - sent_s < 5.0  # the next beat was 10 s away
    finally:
        link.close()
        peer.close()


def test_udpin_follows_the_autopilot_to_a_new_port_only_once_the_old_one_fell_silent(attacker):
    clock = FakeClock()
    link = open_udpin(clock)
    first = ScriptedPeer(UdpClientEndpoint(link.transport.local_address))
    try:
        first.send_heartbeat()
        link.wait_for_autopilot(5.0)
        assert wait_until(lambda: link.transport.peer is not None)
        # Another address with the autopilot's own ids (unsigned: anyone can forge them) while
        # the autopilot is alive: refused.
        attacker.sendto(frame(autopilot_heartbeat, 1, 1), link.transport.local_address)
        assert wait_until(lambda: link.stats.rx_foreign_address == 1)
        assert link.transport.peer == ("127.0.0.1", first.endpoint.port)
        # The autopilot rebooted and came back from another port: followed once the old
        # address has been silent for PEER_HOLD_S.
        clock.advance(PEER_HOLD_S + 0.1)
        second = ScriptedPeer(UdpClientEndpoint(link.transport.local_address))
        try:
            second.send_heartbeat()
            assert wait_until(lambda: link.transport.peer == ("127.0.0.1", second.endpoint.port))
            assert second.wait_for_messages("HEARTBEAT")
            assert link.stats.peer_changes == 2
        finally:
            second.close()
    finally:
        link.close()
        first.close()


def test_signed_udpin_moves_its_peer_only_for_a_correctly_signed_autopilot_frame(
    attacker, tmp_path
):
    clock = FakeClock()
    signing = SigningConfig(KEY, state_path=tmp_path / "signing.state")
    link = open_udpin(clock, signing)
    peer = ScriptedPeer(UdpClientEndpoint(link.transport.local_address), signing_key=KEY)
    # An autopilot whose clock is a second behind ours: its first frames are older than our
    # start and refused, but they tell us where it is; it adopts our timestamp once it hears us.
    peer.mav.signing.timestamp = wall_to_ticks(time.time() - 1.0)
    try:
        peer.send_heartbeat()
        assert wait_until(lambda: link.stats.rejected_replay >= 1)
        assert peer.wait_for_messages("HEARTBEAT")
        peer.send_heartbeat()
        link.wait_for_autopilot(5.0)
        assert wait_until(lambda: link.transport.peer is not None)
        clock.advance(PEER_HOLD_S + 0.1)  # the autopilot "silent": only a signed frame may move us
        target = link.transport.local_address
        attacker.sendto(frame(autopilot_heartbeat, 1, 1), target)  # unsigned
        attacker.sendto(frame(autopilot_heartbeat, 1, 1, bytes(32), 2**40), target)  # wrong key
        # RADIO_STATUS is let through unsigned (as ArduPilot does): it must not move the peer.
        attacker.sendto(frame(lambda c: c.radio_status_encode(0, 0, 0, 0, 0, 0, 0), 1, 1), target)
        assert wait_until(
            lambda: link.stats.rejected_unsigned >= 1 and link.stats.rejected_bad_signature >= 1
        )
        assert wait_until(lambda: link.stats.rx_foreign_address >= 1)
        assert link.transport.peer == ("127.0.0.1", peer.endpoint.port)
        assert link.stats.peer_changes == 1  # the provisional choice, then confirmed
    finally:
        link.close()
        peer.close()


def test_a_partial_frame_at_the_end_of_a_datagram_does_not_swallow_the_next_one():
    endpoint = UdpEndpoint()
    peer = ScriptedPeer(endpoint)
    link = MavlinkLink.open(f"udpout:127.0.0.1:{endpoint.port}", LinkConfig(heartbeat_rate_hz=50))
    try:
        assert peer.wait_for(lambda: endpoint.peer is not None)
        # A MAVLink 2 start byte and a length: today's decoder then took the next datagram's
        # bytes as this frame's body, and the autopilot's HEARTBEAT was lost.
        endpoint.write(b"\xfd\x40")
        peer.send_heartbeat()
        assert link.wait_for_autopilot(5.0)
        assert link.state is LinkState.UP
    finally:
        link.close()
        peer.close()
