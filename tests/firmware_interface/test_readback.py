import threading

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from devkit.mavlink_peer import ScriptedPeer, UdpEndpoint
from devkit.timing import FakeClock
from firmware_interface.commands import CommandSender
from firmware_interface.errors import ConfigurationError, LinkTimeout
from firmware_interface.link import LinkConfig, MavlinkLink
from firmware_interface.readback import OutputReadback


@pytest.fixture
def setup():
    clock = FakeClock()
    peer = ScriptedPeer(UdpEndpoint(), system_id=42)
    link = MavlinkLink.open(
        f"udpout:127.0.0.1:{peer.endpoint.port}", LinkConfig(heartbeat_rate_hz=20.0), clock=clock
    )
    peer.wait_for_messages("HEARTBEAT")
    peer.send_heartbeat()
    link.wait_for_autopilot(timeout_s=5.0)
    readback = OutputReadback(link)
    sender = CommandSender(link, timeout_s=2.0)
    yield peer, readback, sender, clock
    readback.close()
    sender.close()
    link.close()
    peer.close()


def servo_output_raw(peer, port=0, **channels):
    values = [channels.get(f"servo{i}_raw", 0) for i in range(1, 17)]
    return peer.mav.servo_output_raw_encode(0, port, *values)


def test_request_sets_the_message_interval(setup):
    peer, readback, sender, _ = setup
    readback.request(sender, rate_hz=20.0)
    (cmd,) = peer.messages("COMMAND_LONG")
    assert cmd.command == mavlink.MAV_CMD_SET_MESSAGE_INTERVAL
    assert (cmd.param1, cmd.param2) == (36.0, 50_000.0)
    with pytest.raises(ConfigurationError, match="rate_hz=0 outside"):
        readback.request(sender, rate_hz=0)


def test_confirms_outputs_9_to_16_from_servo_output_raw(setup):
    peer, readback, _, _ = setup
    peer.send(servo_output_raw(peer, port=1, servo9_raw=1111))  # other port: ignored
    peer.send(servo_output_raw(peer, servo9_raw=1500, servo14_raw=1900, servo16_raw=1234))
    readback.wait_for({9: 1500, 14: 1900, 16: 1234}, timeout_s=5.0)
    assert readback.latest_pwm_us(9) == 1500


def test_actuator_output_status_counts_from_output_1(setup):
    peer, readback, _, _ = setup
    peer.send(peer.mav.actuator_output_status_encode(0, 3, [1000.0, 1500.0, 2000.0] + [0.0] * 29))
    readback.wait_for({1: 1000, 2: 1500, 3: 2000}, timeout_s=5.0)
    assert readback.latest_pwm_us(4) is None


def test_mismatch_times_out_by_the_link_clock_naming_outputs(setup):
    peer, readback, _, clock = setup
    peer.send(servo_output_raw(peer, servo9_raw=1400))
    readback.wait_for({9: 1400}, timeout_s=5.0)
    done = threading.Event()

    def tick():  # time passes only on the fake clock
        while not done.is_set():
            clock.advance(0.25)
            done.wait(0.005)

    ticker = threading.Thread(target=tick)
    ticker.start()
    try:
        with pytest.raises(LinkTimeout, match="output 9: want 1500, got 1400"):
            readback.wait_for({9: 1500}, timeout_s=1.0, tolerance_us=5)
        readback.wait_for({9: 1404}, timeout_s=1.0, tolerance_us=5)  # within tolerance
    finally:
        done.set()
        ticker.join()
