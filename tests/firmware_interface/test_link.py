import os
import socket
import time

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from devkit.mavlink_peer import PtyEndpoint, ScriptedPeer, TcpEndpoint, UdpEndpoint
from devkit.timing import wait_until
from firmware_interface.errors import ConfigurationError, InvalidUrl, LinkClosed, LinkTimeout
from firmware_interface.link import LinkConfig, LinkState, MavlinkLink, _Codec
from firmware_interface.transport import open_transport, parse_url

FAST = dict(heartbeat_rate_hz=20.0, reconnect_initial_s=0.02, reconnect_max_s=0.2)


@pytest.fixture
def udp_peer():
    peer = ScriptedPeer(UdpEndpoint(), system_id=42)
    yield peer
    peer.close()


@pytest.fixture
def udp_link(udp_peer, clock):
    link = MavlinkLink.open(
        f"udpout:127.0.0.1:{udp_peer.endpoint.port}", LinkConfig(**FAST), clock=clock
    )
    yield link
    link.close()


def test_heartbeat_from_start_up_as_onboard_controller(udp_peer, udp_link):
    beat = udp_peer.wait_for_messages("HEARTBEAT")[0]
    assert beat.type == mavlink.MAV_TYPE_ONBOARD_CONTROLLER
    assert beat.autopilot == mavlink.MAV_AUTOPILOT_INVALID
    assert beat.get_srcComponent() == 191
    assert beat.get_srcSystem() == 1  # provisional until the vehicle's id is known
    assert udp_link.state is LinkState.WAITING
    assert udp_peer.bad_frames == []


def test_discovers_the_autopilot_and_adopts_its_system_id(udp_peer, udp_link):
    udp_peer.wait_for_messages("HEARTBEAT")
    # A GCS heartbeat must not be mistaken for the autopilot.
    udp_peer.send_heartbeat(
        autopilot=mavlink.MAV_AUTOPILOT_INVALID, vehicle_type=mavlink.MAV_TYPE_GCS
    )
    udp_peer.send_heartbeat()
    info = udp_link.wait_for_autopilot(timeout_s=5.0)
    assert (info.system_id, info.component_id) == (42, 1)
    assert info.autopilot == mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA
    assert udp_link.target == (42, 1)
    assert udp_link.system_id == 42
    assert udp_link.state is LinkState.UP
    assert udp_peer.wait_for(
        lambda: any(m.get_srcSystem() == 42 for m in udp_peer.messages("HEARTBEAT"))
    )


def test_an_autopilot_heard_before_its_heartbeat_is_asked_for_one(udp_peer, udp_link):
    # A restart: the autopilot's streams flow on (an earlier run asked for them); its 1 Hz
    # HEARTBEAT would come up to a second later. A frame from another component (sent first)
    # asks nothing.
    udp_peer.answers_heartbeat_requests = True
    udp_peer.wait_for_messages("HEARTBEAT")  # ours: the peer knows where we are
    gimbal = mavlink.MAVLink(None, 42, mavlink.MAV_COMP_ID_GIMBAL)
    udp_peer.endpoint.write(gimbal.system_time_encode(0, 1000).pack(gimbal))
    for _ in range(3):
        udp_peer.send(udp_peer.mav.system_time_encode(0, 1000))
    info = udp_link.wait_for_autopilot(timeout_s=5.0)
    assert (info.system_id, info.component_id) == (42, 1)
    asks = [
        m for m in udp_peer.messages("COMMAND_LONG") if m.command == mavlink.MAV_CMD_REQUEST_MESSAGE
    ]
    assert len(asks) == 1  # one per HEARTBEAT_ASK_INTERVAL_S (the fake clock stands still)
    assert (asks[0].target_system, asks[0].target_component, asks[0].param1) == (42, 1, 0)


def test_configured_target_ignores_other_systems(udp_peer, clock):
    config = LinkConfig(target_system=7, system_id=7, **FAST)
    url = f"udpout:127.0.0.1:{udp_peer.endpoint.port}"
    with MavlinkLink.open(url, config, clock=clock) as link:
        udp_peer.wait_for_messages("HEARTBEAT")
        udp_peer.send_heartbeat()  # from system 42
        with pytest.raises(LinkTimeout, match="no autopilot HEARTBEAT within timeout_s=0.2"):
            link.wait_for_autopilot(timeout_s=0.2)
        assert link.autopilot is None
        assert link.target == (7, 1)


def test_link_lost_and_recovered_by_the_fake_clock(udp_peer, udp_link, clock):
    changes = []
    udp_link.on_state_change(changes.append)
    udp_peer.wait_for_messages("HEARTBEAT")
    udp_peer.send_heartbeat()
    udp_link.wait_for_autopilot(timeout_s=5.0)
    assert udp_link.poll_state() is LinkState.UP
    clock.advance(2.9)
    assert udp_link.poll_state() is LinkState.UP
    clock.advance(0.2)  # 3.1 s without a heartbeat: default loss timeout is 3 s
    assert udp_link.poll_state() is LinkState.LOST
    udp_peer.send_heartbeat()
    assert wait_until(lambda: udp_link.state is LinkState.UP)
    assert changes == [LinkState.UP, LinkState.LOST, LinkState.UP]


def test_incoming_commands_queue_and_arbitrary_replies(udp_peer, udp_link):
    udp_peer.wait_for_messages("HEARTBEAT")
    with udp_link.messages(["COMMAND_LONG"]) as inbox:
        udp_peer.send(
            udp_peer.mav.command_long_encode(
                1, 191, mavlink.MAV_CMD_USER_1, 0, 1.5, 0, 0, 0, 0, 0, 0
            )
        )
        cmd = inbox.get(timeout_s=5.0)
        assert cmd.command == mavlink.MAV_CMD_USER_1 and cmd.param1 == 1.5
        assert inbox.get_nowait() is None
    buf = udp_link.send(
        udp_link.mav.command_ack_encode(
            mavlink.MAV_CMD_USER_1, mavlink.MAV_RESULT_ACCEPTED, 0, 0, 42, 1
        )
    )
    assert buf[0] == 0xFD  # MAVLink 2 framing
    ack = udp_peer.wait_for_messages("COMMAND_ACK")[0]
    assert (ack.command, ack.result, ack.target_system) == (mavlink.MAV_CMD_USER_1, 0, 42)


def test_queue_get_times_out(udp_link):
    with udp_link.messages(["COMMAND_LONG"]) as inbox, pytest.raises(LinkTimeout):
        inbox.get(timeout_s=0.01)


def test_garbage_is_counted_not_fatal(udp_peer, udp_link):
    udp_peer.wait_for_messages("HEARTBEAT")
    udp_peer.endpoint.write(b"\x00\x01garbage")
    udp_peer.send_heartbeat()
    udp_link.wait_for_autopilot(timeout_s=5.0)
    assert udp_link.stats.rx_bad_frames >= 1
    assert not udp_link.closed


def test_an_error_in_a_subscriber_ends_the_link_and_is_kept(udp_peer, udp_link):
    def broken(msg):
        raise RuntimeError("bug in handler")

    udp_link.subscribe(broken, ["HEARTBEAT"])
    udp_peer.wait_for_messages("HEARTBEAT")
    udp_peer.send_heartbeat()
    assert wait_until(lambda: udp_link.closed)
    assert isinstance(udp_link.failure, RuntimeError)
    assert udp_link.state is LinkState.CLOSED
    with pytest.raises(LinkClosed) as info:
        udp_link.send(udp_link.mav.heartbeat_encode(18, 8, 0, 0, 4))
    assert info.value.__cause__ is udp_link.failure


def test_a_link_that_ends_as_a_heartbeat_goes_out_ends_the_heartbeat_loop_quietly(
    udp_peer, udp_link
):
    # The reader thread ends the link on an error in protocol code whenever it happens: here
    # between the heartbeat loop's look at the link and its send (made certain by ending it
    # from the encoder). The loop, run here in the test's thread, must just stop.
    udp_peer.wait_for_messages("HEARTBEAT")
    encode = udp_link._encoder.heartbeat_encode

    def ending_meanwhile(*args):
        udp_link.failure = RuntimeError("ended by the reader meanwhile")
        udp_link._stop.set()
        return encode(*args)

    udp_link._encoder.heartbeat_encode = ending_meanwhile
    udp_link._heartbeat_loop()
    assert udp_link.closed and udp_link.state is LinkState.CLOSED


def test_cancelled_subscription_gets_nothing_more(udp_peer, udp_link):
    seen = []
    sub = udp_link.subscribe(seen.append, ["STATUSTEXT"])
    udp_peer.wait_for_messages("HEARTBEAT")
    udp_peer.send_statustext("one")
    assert wait_until(lambda: len(seen) == 1)
    sub.cancel()
    udp_peer.send_statustext("two")
    udp_peer.send_heartbeat()
    udp_link.wait_for_autopilot(timeout_s=5.0)  # ordered after "two" on the same socket
    assert [m.text for m in seen] == ["one"]


def test_a_subscription_added_later_gets_the_next_frames_of_a_type_already_dispatched(
    udp_peer, udp_link
):
    first, second = [], []
    udp_link.subscribe(first.append, ["STATUSTEXT"])
    udp_peer.wait_for_messages("HEARTBEAT")
    udp_peer.send_statustext("one")
    assert wait_until(lambda: len(first) == 1)
    udp_link.subscribe(second.append, ["STATUSTEXT"])
    udp_peer.send_statustext("two")
    assert wait_until(lambda: len(first) == 2)
    assert [m.text for m in second] == ["two"]


def test_udpin_replies_to_whoever_spoke_first():
    with MavlinkLink.open("udpin:127.0.0.1:0", LinkConfig(**FAST)) as link:
        port = link.transport.local_address[1]
        endpoint = UdpEndpoint()
        endpoint.peer = ("127.0.0.1", port)
        peer = ScriptedPeer(endpoint, system_id=3)
        try:
            peer.send_heartbeat()
            assert link.wait_for_autopilot(timeout_s=5.0).system_id == 3
            beat = peer.wait_for_messages("HEARTBEAT")[0]
            assert beat.get_srcSystem() == 3
        finally:
            peer.close()


def test_bad_url_and_config_are_refused_before_any_thread_starts():
    with pytest.raises(InvalidUrl, match="unknown scheme 'ftp'"):
        MavlinkLink.open("ftp:host:1")
    with pytest.raises(ConfigurationError, match=r"component_id=0 outside \[1, 255\]"):
        LinkConfig(component_id=0)
    with pytest.raises(ConfigurationError, match="loss_timeout_s=nan"):
        LinkConfig(loss_timeout_s=float("nan"))


# --- serial over a real pty --------------------------------------------------------------


def test_heartbeat_and_discovery_over_a_pty():
    peer = ScriptedPeer(PtyEndpoint(), system_id=9)
    try:
        with MavlinkLink.open(f"{peer.endpoint.path},115200", LinkConfig(**FAST)) as link:
            peer.wait_for_messages("HEARTBEAT")
            peer.send_heartbeat()
            assert link.wait_for_autopilot(timeout_s=5.0).system_id == 9
            assert peer.bad_frames == []
    finally:
        peer.close()


def test_serial_port_vanishes_and_is_reopened_with_backoff(tmp_path):
    device = tmp_path / "ttyFC"
    first = ScriptedPeer(PtyEndpoint(), system_id=9)
    os.symlink(first.endpoint.path, device)
    link = MavlinkLink.open(f"serial://{device}?baud=921600", LinkConfig(**FAST))
    second = None
    try:
        first.wait_for_messages("HEARTBEAT")
        # The device node goes first, so no reopen can race to the dying port.
        device.unlink()
        first.close()  # the port vanishes
        # The reader counts the error, then drops the port: wait for both, not just the count.
        assert wait_until(lambda: link.stats.transport_errors >= 1 and link.transport is None)
        assert not link.closed
        second = ScriptedPeer(PtyEndpoint(), system_id=9)  # plugged back in
        os.symlink(second.endpoint.path, device)
        second.wait_for_messages("HEARTBEAT")
        second.send_heartbeat()
        assert link.wait_for_autopilot(timeout_s=5.0).system_id == 9
        assert link.stats.reconnects >= 1
    finally:
        link.close()
        if second is not None:
            second.close()


def test_link_is_lost_while_the_port_is_down_and_up_again_only_on_a_fresh_heartbeat(
    tmp_path, clock
):
    # The fake clock never moves, so the last HEARTBEAT stays "recent": only the port tells.
    device = tmp_path / "ttyFC"
    first = ScriptedPeer(PtyEndpoint(), system_id=9)
    os.symlink(first.endpoint.path, device)
    link = MavlinkLink.open(f"{device},115200", LinkConfig(**FAST), clock=clock)
    second = None
    try:
        first.wait_for_messages("HEARTBEAT")
        first.send_heartbeat()
        assert wait_until(lambda: link.state is LinkState.UP)
        first.close()  # unplugged
        device.unlink()
        assert wait_until(lambda: link.stats.transport_errors >= 1)
        assert link.state is LinkState.LOST  # nothing can reach the autopilot now
        second = ScriptedPeer(PtyEndpoint(), system_id=9)  # re-enumerated (maybe rebooted)
        os.symlink(second.endpoint.path, device)
        assert wait_until(lambda: link.stats.reconnects >= 1)
        assert link.state is LinkState.LOST  # not a word from the autopilot on this port yet
        second.send_heartbeat()
        assert wait_until(lambda: link.state is LinkState.UP)
    finally:
        link.close()
        if second is not None:
            second.close()


def test_default_reconnect_backoff_is_bounded_at_half_a_second(tmp_path):
    # A USB serial adapter re-enumerates under its udev name: with the default config the link
    # must try again at least every 0.5 s, or a port that came back would go unused for seconds.
    device = tmp_path / "ttyFC"
    peer = ScriptedPeer(PtyEndpoint(), system_id=9)
    os.symlink(peer.endpoint.path, device)
    spec = parse_url(f"{device},115200")
    attempts: list[float] = []

    def reopen():
        attempts.append(time.monotonic())
        return open_transport(spec)

    link = MavlinkLink(reopen, LinkConfig())
    link.start()
    try:
        device.unlink()
        peer.close()  # unplugged, and it stays away
        assert wait_until(lambda: len(attempts) >= 7, timeout_s=10.0)
        gaps_s = [b - a for a, b in zip(attempts[1:], attempts[2:], strict=False)]
        assert max(gaps_s) < 0.5 + 0.25, gaps_s  # 0.1, 0.2, 0.4, 0.5, 0.5 s (+ scheduling)
        assert not link.closed
    finally:
        link.close()


def test_defaults_match_the_issue():
    config = LinkConfig()
    assert (config.component_id, config.heartbeat_rate_hz, config.loss_timeout_s) == (191, 1.0, 3.0)
    assert config.system_id is None and config.target_system is None and config.signing is None


def test_tcp_peer_closing_is_survived_by_reconnecting():
    with socket.create_server(("127.0.0.1", 0)) as listener:
        port = listener.getsockname()[1]
        listener.settimeout(5.0)
        link = MavlinkLink.open(f"tcp:127.0.0.1:{port}", LinkConfig(**FAST))
        second = None
        try:
            first = ScriptedPeer(TcpEndpoint(listener), system_id=5)
            first.wait_for_messages("HEARTBEAT")
            first.close()  # SITL restarted: the connection drops
            second = ScriptedPeer(TcpEndpoint(listener), system_id=5)  # the link dials again
            second.wait_for_messages("HEARTBEAT")
            second.send_heartbeat()
            assert link.wait_for_autopilot(timeout_s=5.0).system_id == 5
            assert link.stats.reconnects >= 1 and link.stats.transport_errors >= 1
        finally:
            link.close()
            if second is not None:
                second.close()


def test_send_many_writes_its_messages_in_one_datagram(clock):
    # An autopilot reading its link once per main-loop pass then sees a whole servo update in
    # one pass.
    peer = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    peer.bind(("127.0.0.1", 0))
    peer.settimeout(5.0)
    link = MavlinkLink.open(f"udpout:127.0.0.1:{peer.getsockname()[1]}", LinkConfig(**FAST))
    try:
        texts = [b"one", b"two", b"three"]
        link.send_many(link.mav.statustext_encode(6, t) for t in texts)
        decoder = mavlink.MAVLink(None)
        while True:
            datagram, _ = peer.recvfrom(65535)
            msgs = decoder.parse_buffer(datagram) or []
            if msgs and msgs[0].get_type() == "STATUSTEXT":
                break
        assert [m.text for m in msgs] == ["one", "two", "three"]
        assert [m.get_seq() for m in msgs] == [(msgs[0].get_seq() + i) % 256 for i in range(3)]
    finally:
        link.close()
        peer.close()


def _decoded(msgs):
    return [
        (
            m.get_type(),
            getattr(m, "reason", None),
            None if m.get_type() == "BAD_DATA" else m.to_dict(),
        )
        for m in msgs
    ]


def test_a_datagram_decodes_as_pymavlinks_byte_parser_decodes_it():
    """parse_datagram's one-frame shortcut gives what parse_buffer gives: messages, refusals
    and counters, signed frames (and their replay) included."""
    key = bytes(range(32))
    sender = mavlink.MAVLink(None, 1, 1)
    signer = mavlink.MAVLink(None, 1, 1)
    signer.signing.secret_key = key
    signer.signing.sign_outgoing = True
    signer.signing.timestamp = 1000
    forger = mavlink.MAVLink(None, 1, 1)
    forger.signing.secret_key = bytes(32)
    forger.signing.sign_outgoing = True
    forger.signing.timestamp = 5000
    ack = sender.command_ack_encode(183, 0, 0, 0, 1, 191).pack(sender)
    attitude = sender.attitude_encode(1000, 0.1, -0.2, 0.3, 0.01, 0.02, 0.03).pack(sender)
    signed = signer.command_ack_encode(183, 4, 0, 0, 1, 191).pack(signer)
    datagrams = [
        ack,
        attitude,
        ack[:-1] + bytes([ack[-1] ^ 0xFF]),  # bad CRC
        ack + attitude,  # two frames
        ack[:-3],  # cut short
        ack + b"\x00",  # a byte too many
        b"\x00\x01garbage",
        bytes([ack[0], ack[1], 0x02]) + ack[3:],  # an unknown incompat flag
        sender.heartbeat_encode(6, 8, 0, 0, 4).pack(sender, force_mavlink1=True),
    ]
    for unsigned_codec in (False, True):
        fast, slow = (_Codec(None, 1, 191) for _ in range(2))
        cases = list(datagrams)
        if unsigned_codec:
            cases += [signed, signed, forger.command_ack_encode(183, 0, 0, 0, 1, 191).pack(forger)]
            for codec in (fast, slow):
                codec.signing.secret_key = key
        for codec in (fast, slow):
            codec.robust_parsing = True
        for data in cases:
            slow.reset_parser()
            expected = _decoded(slow.parse_buffer(data) or [])
            assert _decoded(fast.parse_datagram(data)) == expected, data
        for counter in ("total_packets_received", "total_receive_errors", "total_bytes_received"):
            assert getattr(fast, counter) == getattr(slow, counter), counter
    # The cases above took both paths, and the signed ones were told apart.
    assert [m.get_type() for m in fast.parse_datagram(signed)] == ["BAD_DATA"]  # replayed


def test_a_missing_serial_device_is_waited_for_only_when_asked(tmp_path):
    from firmware_interface.errors import TransportError

    device = tmp_path / "ttyACM0"
    url = f"{device},115200"
    with pytest.raises(TransportError, match="cannot open serial port"):
        MavlinkLink.open(url)  # doctor: said at once
    link = MavlinkLink.open(url, LinkConfig(reconnect_max_s=0.05), wait_for_device=True)
    master, slave = os.openpty()
    try:
        assert link.waiting_for_device == str(device)
        assert link.state is LinkState.WAITING and link.transport is None
        device.symlink_to(os.ttyname(slave))
        assert wait_until(lambda: link.transport is not None, 10.0)
        assert link.waiting_for_device is None and link.stats.reconnects == 1
    finally:
        link.close()
        os.close(master)
        os.close(slave)


def test_caught_up_waits_until_the_reader_handed_on_what_had_arrived(udp_peer, udp_link):
    # A thread about to act on the autopilot's word (the daemon's first step after a solve,
    # which held the interpreter) first lets the reader hand on every frame that had arrived.
    import threading

    udp_peer.wait_for_messages("HEARTBEAT")
    gate = threading.Event()
    seen: list[int] = []

    def slow(msg) -> None:  # the reader, busy with the first frame
        seen.append(msg.time_boot_ms)
        if len(seen) == 1:
            gate.wait(2.0)

    udp_link.subscribe(slow, ["SYSTEM_TIME"])
    codec = udp_peer.mav
    udp_peer.send(codec.system_time_encode(0, 1))
    assert wait_until(lambda: seen == [1])
    udp_peer.send(codec.system_time_encode(0, 2))
    assert udp_link.caught_up(0.05) is False  # the reader is stuck: the caller goes on
    threading.Timer(0.05, gate.set).start()
    assert udp_link.caught_up(2.0) is True
    assert seen == [1, 2]
