"""devkit's MAVLink peer: a ground station (on firmware_interface's UDP transport) against the
scripted autopilot, over loopback."""

from __future__ import annotations

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from devkit.mavlink_peer import MavPeer, PtyEndpoint, ScriptedPeer, UdpEndpoint


@pytest.fixture
def pair():
    autopilot = ScriptedPeer(UdpEndpoint())
    gcs = MavPeer.connect(f"udpout:127.0.0.1:{autopilot.endpoint.port}")
    yield gcs, autopilot
    gcs.close()
    autopilot.close()


def is_ack(command: int):
    return lambda m: m.get_type() == "COMMAND_ACK" and m.command == command


def test_a_command_is_answered_and_the_cursor_passes_over_the_rest(pair):
    gcs, autopilot = pair
    autopilot.failed_outputs = {9: "ServoRelayEvent: Channel 9 is already in use"}
    sent_s = gcs.command(mavlink.MAV_CMD_DO_SET_SERVO, 9, 1500)
    ack = gcs.ack(mavlink.MAV_CMD_DO_SET_SERVO)
    assert ack.result == mavlink.MAV_RESULT_FAILED and gcs.arrival_s(ack) >= sent_s
    text = gcs.next_message(lambda m: m.get_type() == "STATUSTEXT")
    assert text.text.startswith("ServoRelayEvent")
    command = autopilot.wait_for_messages("COMMAND_LONG")[0]
    assert (command.get_srcSystem(), command.get_srcComponent()) == (255, 190)
    assert (command.param1, command.param2) == (9.0, 1500.0)

    gcs.command(mavlink.MAV_CMD_DO_SET_SERVO, 10, 1500)
    assert gcs.ack(mavlink.MAV_CMD_DO_SET_SERVO).result == mavlink.MAV_RESULT_ACCEPTED
    autopilot.send_heartbeat()
    assert gcs.wait_for(lambda: bool(gcs.messages("HEARTBEAT")))
    gcs.drain()  # the heartbeat is passed over: the next one is waited for
    with pytest.raises(TimeoutError):
        gcs.next_message(lambda m: m.get_type() == "HEARTBEAT", timeout_s=0.2)
    assert [m for _, m in gcs.log] == gcs.received


def test_signed_peers_understand_each_other_and_an_unsigned_frame_is_refused():
    key = bytes(range(32))
    with (
        ScriptedPeer(UdpEndpoint(), signing_key=key) as autopilot,
        MavPeer.connect(f"udpout:127.0.0.1:{autopilot.endpoint.port}", signing_key=key) as gcs,
        MavPeer.connect(f"udpout:127.0.0.1:{autopilot.endpoint.port}") as unsigned,
    ):
        gcs.command(mavlink.MAV_CMD_DO_SET_SERVO, 9, 1500)
        assert gcs.ack(mavlink.MAV_CMD_DO_SET_SERVO).get_signed()
        unsigned.command(mavlink.MAV_CMD_DO_SET_SERVO, 9, 1500)
        assert autopilot.wait_for(lambda: bool(autopilot.bad_frames))
        assert len(autopilot.messages("COMMAND_LONG")) == 1


def test_a_link_that_ends_ends_the_wait_with_connection_error():
    autopilot = PtyEndpoint()
    gcs = MavPeer.connect(f"{autopilot.path},115200")
    try:
        autopilot.close()
        with pytest.raises(ConnectionError):
            gcs.next_message(lambda m: True, timeout_s=5.0)
        assert gcs.error is not None
    finally:
        gcs.close()
