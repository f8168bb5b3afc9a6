"""``python -m sim_servo`` as a subprocess: UDP, TCP and pty links, streams, slew, signing,
faults, reboot."""

from __future__ import annotations

import time

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from devkit.mavlink_peer import MavPeer
from devkit.sim_process import SimProcess
from devkit.timing import wait_until
from sim_servo.config import config_from_mapping
from sim_servo.eventlog import world_timeline
from sim_servo.hover import HoverDisturbance


def gcs_client(url: str, signing_key: bytes | None = None) -> MavPeer:
    """A ground station (255/190) on the simulator's link ``url`` (plays the daemon)."""
    client = MavPeer.connect(url, signing_key=signing_key)
    client.wait_s = WAIT_S
    return client


pytestmark = pytest.mark.slow

WAIT_S = 10.0


def is_type(kind: str):
    return lambda m: m.get_type() == kind


def ack_for(command: int):
    return lambda m: m.get_type() == "COMMAND_ACK" and m.command == command


@pytest.fixture
def udp_sim(tmp_path):
    sims: list[SimProcess] = []
    clients: list[MavPeer] = []

    def start(*args: str, signing_key: bytes | None = None) -> tuple[SimProcess, MavPeer]:
        sim = SimProcess(tmp_path / f"sim{len(sims)}", "--udp", "127.0.0.1:0", *args)
        sims.append(sim)
        client = gcs_client(sim.url, signing_key)
        clients.append(client)
        client.send(
            client.mav.heartbeat_encode(
                mavlink.MAV_TYPE_ONBOARD_CONTROLLER, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0
            )
        )
        return sim, client

    yield start
    for client in clients:
        client.close()
    for sim in sims:
        sim.kill()


@pytest.mark.slow
def test_udp_heartbeat_accept_refuse_stream_and_clean_stop(udp_sim):
    sim, client = udp_sim()
    beat = client.next_message(is_type("HEARTBEAT"))
    assert (beat.get_srcSystem(), beat.get_srcComponent()) == (1, 1)
    assert (beat.type, beat.autopilot) == (
        mavlink.MAV_TYPE_QUADROTOR,
        mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA,
    )

    client.command(mavlink.MAV_CMD_DO_SET_SERVO, 9, 1800)
    assert client.next_message(ack_for(183)).result == mavlink.MAV_RESULT_ACCEPTED

    client.command(mavlink.MAV_CMD_DO_SET_SERVO, 2, 1800)
    assert client.next_message(ack_for(183)).result == mavlink.MAV_RESULT_FAILED
    text = client.next_message(is_type("STATUSTEXT"))
    assert text.text == "ServoRelayEvent: Channel 2 is already in use"
    assert text.severity == mavlink.MAV_SEVERITY_INFO

    client.command(mavlink.MAV_CMD_NAV_TAKEOFF)
    assert client.next_message(ack_for(22)).result == mavlink.MAV_RESULT_UNSUPPORTED

    client.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, 36, 50_000)  # 20 Hz
    assert client.next_message(ack_for(511)).result == mavlink.MAV_RESULT_ACCEPTED
    client.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, 30, 20_000)  # ATTITUDE at 50 Hz
    assert client.next_message(ack_for(511)).result == mavlink.MAV_RESULT_ACCEPTED
    attitude = client.next_message(is_type("ATTITUDE"))
    raw = client.next_message(is_type("SERVO_OUTPUT_RAW"))
    assert raw.servo9_raw == 1800 and raw.servo2_raw == 1000
    first = len(client.received)

    def raws() -> list:
        return [m for m in client.received[first:] if m.get_type() == "SERVO_OUTPUT_RAW"]

    assert client.wait_for(lambda: len(raws()) > 30, WAIT_S)  # 1.5 s at 20 Hz
    stamps = [m.time_usec for m in raws()]
    rate_hz = (len(stamps) - 1) / ((stamps[-1] - stamps[0]) / 1e6)
    assert rate_hz == pytest.approx(20, rel=0.1)  # by the sender's own timestamps

    state = sim.state()
    assert state["outputs"]["9"]["pwm_us"] == 1800 and state["peer"] == [255, 190]
    assert sim.stop() == 0
    events = sim.events()
    assert events[0]["event"] == "start" and events[-1]["event"] == "stop"
    commands = [e for e in events if e["event"] == "rx" and e["msg"] == "COMMAND_LONG"]
    assert [e["fields"]["command"] for e in commands] == [183, 183, 22, 511, 511]
    # The moving vehicle: the start event's settings rebuild the motion the frames carried,
    # and the log holds the hand in the world.
    hover = HoverDisturbance.from_config(
        config_from_mapping({"vehicle": events[0]["vehicle"]}).vehicle
    )
    state = hover.state(attitude.time_boot_ms / 1000.0)  # booted at the start
    assert attitude.roll == pytest.approx(state.roll_rad, rel=1e-6, abs=1e-7)
    assert attitude.yawspeed == pytest.approx(state.body_rates()[2], rel=1e-6, abs=1e-7)
    samples = world_timeline(events)
    assert len(samples) >= 25 and all(s.hand is not None for s in samples)


@pytest.mark.slow
def test_udp_slew_timing_and_hand_at_target(udp_sim):
    sim, client = udp_sim("--slew-s-per-60deg", "0.6")  # slow: 1000 µs take ~1.8 s
    client.next_message(is_type("HEARTBEAT"))
    client.command(mavlink.MAV_CMD_DO_SET_SERVO, 9, 1000)  # theta1 → -90°
    client.next_message(ack_for(183))
    sent = time.monotonic()
    state = sim.state()
    assert state["outputs"]["9"]["moving"]
    settled = wait_until(lambda: sim.state()["settled"])
    elapsed = time.monotonic() - sent
    travel_s = 500 * 0.18 / (60 / 0.6)  # 500 µs × 0.18 °/µs at 100 °/s = 0.9 s
    # Only an upper bound on the wall clock (a loaded machine is late, never early to ask);
    # the travel time itself is checked exactly on the simulator's clock below.
    assert elapsed < travel_s + 3.0
    hand = sim.state()["hand"]
    assert settled and hand["angles_deg"]["theta1"] == pytest.approx(-90.0)
    from companion.kinematics.arm import Arm

    expected = Arm.default().fk([-90.0, 90.0, 0.0, 0.0, 0.0, 10.0])
    assert hand["pose"]["y_cm"] == pytest.approx(expected.y_cm, abs=1e-6)
    log_settled = [e for e in sim.events() if e["event"] == "settled"][-1]
    servo = [e for e in sim.events() if e["event"] == "servo"][-1]
    assert log_settled["t_s"] - servo["t_s"] == pytest.approx(travel_s, abs=1e-3)
    assert sim.stop() == 0


@pytest.mark.slow
def test_udp_signing_required(udp_sim, tmp_path):
    key = bytes(range(1, 33))
    key_file = tmp_path / "key.hex"
    key_file.write_text(key.hex() + "\n")
    sim, unsigned = udp_sim("--signing-key", str(key_file))
    unsigned.command(mavlink.MAV_CMD_DO_SET_SERVO, 9, 1600)
    assert wait_until(lambda: sim.state()["stats"]["rejected_signature"] >= 2)
    assert sim.state()["outputs"]["9"]["pwm_us"] == 0
    signed = gcs_client(sim.url, signing_key=key)
    try:
        signed.command(mavlink.MAV_CMD_DO_SET_SERVO, 9, 1600)
        ack = signed.next_message(ack_for(183))
        assert ack.result == mavlink.MAV_RESULT_ACCEPTED and ack.get_signed()
    finally:
        signed.close()
    assert sim.stop() == 0


@pytest.mark.slow
def test_udp_faults_withhold_nack_heartbeat_pause(udp_sim):
    sim, client = udp_sim(
        "--withhold-ack", "DO_SET_SERVO", "--nack-output", "10", "--heartbeat-pause-after", "0"
    )
    client.command(mavlink.MAV_CMD_NAV_TAKEOFF)
    client.next_message(ack_for(22))  # the link works...
    client.command(mavlink.MAV_CMD_DO_SET_SERVO, 9, 1600)
    assert wait_until(lambda: sim.state()["outputs"]["9"]["pwm_us"] == 1600)

    def withheld_came() -> bool:
        return any(
            m.get_type() == "HEARTBEAT" or (m.get_type() == "COMMAND_ACK" and m.command == 183)
            for m in client.received
        )

    client.wait_for(withheld_came, 1.5)  # the window in which neither may come
    kinds = {m.get_type() for _, m in client.log}
    assert "HEARTBEAT" not in kinds  # paused from the start
    assert not any(m.get_type() == "COMMAND_ACK" and m.command == 183 for _, m in client.log)
    assert sim.state()["stats"]["acks_withheld"] == 1
    assert sim.stop() == 0


@pytest.mark.slow
def test_udp_reboot_on_request_silence_then_time_boot_and_sequence_from_zero(udp_sim):
    sim, client = udp_sim("--system-time-rate-hz", "20", "--reboot-gap", "0.5")
    last = client.next_message(lambda m: is_type("SYSTEM_TIME")(m) and m.time_boot_ms > 300)
    start = len(client.received)
    assert sim.reboot()
    assert not sim.reboot()  # already rebooting
    assert wait_until(lambda: len(sim.events("fault", fault="booted")) == 1)
    client.drain()
    client.next_message(is_type("SYSTEM_TIME"))
    seen = len(client.received)
    assert client.wait_for(lambda: len(client.received) >= seen + 6)  # 0.3 s at 20 Hz
    log = client.log[start - 1 :]
    # The first frame after the longest silence is the first one after the reboot.
    pairs = enumerate(zip(log, log[1:], strict=False))
    gap_s, after = max((b[0] - a[0], i + 1) for i, (a, b) in pairs)
    assert gap_s >= 0.45  # 0.5 s on the simulator's clock, less our read jitter
    assert log[after][1].get_seq() == 0
    first = next(m for _, m in log[after:] if m.get_type() == "SYSTEM_TIME")
    assert first.time_boot_ms < 100 < last.time_boot_ms
    assert sim.events("fault", fault="reboot")[0]["gap_s"] == 0.5
    assert sim.state()["stats"]["reboots"] == 1
    assert sim.stop() == 0


@pytest.mark.slow
def test_udp_drop_and_latency(udp_sim):
    sim, client = udp_sim("--latency-ms", "200")
    sent = client.command(mavlink.MAV_CMD_NAV_TAKEOFF)
    arrived = client.arrival_s(client.next_message(ack_for(22)))
    assert arrived - sent >= 0.2
    assert sim.stop() == 0

    sim, client = udp_sim("--drop-out", "1", "--seed", "1")
    client.command(mavlink.MAV_CMD_NAV_TAKEOFF)
    assert wait_until(lambda: sim.state()["stats"]["dropped_out"] >= 2)
    client.wait_for(lambda: bool(client.received), 0.3)  # the window in which none may come
    assert client.log == []
    assert sim.stop() == 0


@pytest.mark.slow
def test_tcp_link(tmp_path):
    sim = SimProcess(tmp_path, "--tcp", "127.0.0.1:0")
    try:
        assert sim.url.startswith("tcp:")
        with gcs_client(sim.url) as client:
            client.command(183, 11, 1400)
            got = client.next_message(is_type("COMMAND_ACK"))
            assert got.result == 0
        assert sim.state()["outputs"]["11"]["pwm_us"] == 1400
        assert sim.stop() == 0
    finally:
        sim.kill()


def _pty_exchange(client: MavPeer, msg, want):
    # The cursor keeps frames read past the one wanted for the next exchange: the STATUSTEXT
    # that follows a FAILED ACK may come in the same read (the simulator's output hold).
    client.send(msg)
    return client.next_message(want)


@pytest.mark.slow
def test_pty_link_and_hangup(tmp_path):
    # The hang-up is asked for (query ``hangup``) after the three exchanges below; it replaces
    # the one scheduled for much later.
    sim = SimProcess(tmp_path, "--pty", "--hangup-after", "600")
    try:
        device, _, baud = sim.url.rpartition(",")
        assert device.startswith("/dev/") and baud == "115200"
        with gcs_client(sim.url) as client:
            mav = client.mav
            beat = _pty_exchange(client, mav.heartbeat_encode(18, 8, 0, 0, 0), is_type("HEARTBEAT"))
            assert beat.autopilot == mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA
            ack = _pty_exchange(
                client, mav.command_long_encode(1, 1, 183, 0, 3, 1500, 0, 0, 0, 0, 0), ack_for(183)
            )
            assert ack.result == mavlink.MAV_RESULT_FAILED
            text = _pty_exchange(
                client, mav.heartbeat_encode(18, 8, 0, 0, 0), is_type("STATUSTEXT")
            )
            assert text.text == "ServoRelayEvent: Channel 3 is already in use"
            assert sim.hangup()
            assert wait_until(lambda: sim.state()["link"]["closed"])
            assert not sim.hangup()  # away for good: no second hang-up
            # Reading the port fails: the peer's reader ends with the transport's error.
            assert wait_until(lambda: client.error is not None)
        assert any(e.get("fault") == "hangup" for e in sim.events())
        assert sim.stop() == 0
    finally:
        sim.kill()
