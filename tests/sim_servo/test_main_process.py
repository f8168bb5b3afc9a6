"""``python -m sim_servo`` as a subprocess: UDP, TCP and pty links, streams, slew, signing,
faults, reboot."""

from __future__ import annotations

import select
import socket
import time

import pytest
import serial
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from sim_servo.config import config_from_mapping
from sim_servo.eventlog import world_timeline
from sim_servo.hover import HoverDisturbance
from tests.support.sim_process import SimProcess
from tests.support.timing import wait_until

pytestmark = pytest.mark.slow

WAIT_S = 10.0


class UdpClient:
    """A pymavlink codec over a UDP socket (plays the daemon)."""

    def __init__(self, url: str, signing_key: bytes | None = None) -> None:
        _, host, port = url.split(":")
        self.address = (host, int(port))
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.mav = mavlink.MAVLink(None, 255, 190)
        self.dec = mavlink.MAVLink(None)
        self.dec.robust_parsing = True
        if signing_key is not None:
            self.mav.signing.secret_key = signing_key
            self.mav.signing.sign_outgoing = True
            self.mav.signing.timestamp = 1
            self.dec.signing.secret_key = signing_key
        self.log: list[tuple[float, mavlink.MAVLink_message]] = []

    def send(self, msg) -> float:
        self.sock.sendto(msg.pack(self.mav), self.address)
        return time.monotonic()

    def read(self, timeout_s: float) -> None:
        ready, _, _ = select.select([self.sock], [], [], timeout_s)
        if ready:
            data, _ = self.sock.recvfrom(65535)
            now = time.monotonic()
            for msg in self.dec.parse_buffer(data) or []:
                self.log.append((now, msg))

    def wait_for(self, predicate, timeout_s: float = WAIT_S):
        """The first logged message (from now on) satisfying ``predicate``."""
        start = len(self.log)
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            for _, msg in self.log[start:]:
                if predicate(msg):
                    return msg
            start = len(self.log)
            self.read(0.05)
        raise AssertionError(f"no matching message within {timeout_s} s")

    def command(self, command: int, *params: float) -> float:
        values = list(params) + [0.0] * (7 - len(params))
        return self.send(self.mav.command_long_encode(1, 1, command, 0, *values))

    def close(self) -> None:
        self.sock.close()


def is_type(kind: str):
    return lambda m: m.get_type() == kind


def ack_for(command: int):
    return lambda m: m.get_type() == "COMMAND_ACK" and m.command == command


@pytest.fixture
def udp_sim(tmp_path):
    sims: list[SimProcess] = []
    clients: list[UdpClient] = []

    def start(*args: str, signing_key: bytes | None = None) -> tuple[SimProcess, UdpClient]:
        sim = SimProcess(tmp_path / f"sim{len(sims)}", "--udp", "127.0.0.1:0", *args)
        sims.append(sim)
        client = UdpClient(sim.url, signing_key)
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


def test_udp_heartbeat_accept_refuse_stream_and_clean_stop(udp_sim):
    sim, client = udp_sim()
    beat = client.wait_for(is_type("HEARTBEAT"))
    assert (beat.get_srcSystem(), beat.get_srcComponent()) == (1, 1)
    assert (beat.type, beat.autopilot) == (
        mavlink.MAV_TYPE_QUADROTOR,
        mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA,
    )

    client.command(mavlink.MAV_CMD_DO_SET_SERVO, 9, 1800)
    assert client.wait_for(ack_for(183)).result == mavlink.MAV_RESULT_ACCEPTED

    client.command(mavlink.MAV_CMD_DO_SET_SERVO, 2, 1800)
    assert client.wait_for(ack_for(183)).result == mavlink.MAV_RESULT_FAILED
    text = client.wait_for(is_type("STATUSTEXT"))
    assert text.text == "ServoRelayEvent: Channel 2 is already in use"
    assert text.severity == mavlink.MAV_SEVERITY_INFO

    client.command(mavlink.MAV_CMD_NAV_TAKEOFF)
    assert client.wait_for(ack_for(22)).result == mavlink.MAV_RESULT_UNSUPPORTED

    client.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, 36, 50_000)  # 20 Hz
    assert client.wait_for(ack_for(511)).result == mavlink.MAV_RESULT_ACCEPTED
    client.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, 30, 20_000)  # ATTITUDE at 50 Hz
    assert client.wait_for(ack_for(511)).result == mavlink.MAV_RESULT_ACCEPTED
    attitude = client.wait_for(is_type("ATTITUDE"))
    raw = client.wait_for(is_type("SERVO_OUTPUT_RAW"))
    assert raw.servo9_raw == 1800 and raw.servo2_raw == 1000
    first = len(client.log)
    t0 = time.monotonic()
    while time.monotonic() - t0 < 1.5:
        client.read(0.05)
    stamps = [m.time_usec for _, m in client.log[first:] if m.get_type() == "SERVO_OUTPUT_RAW"]
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


def test_udp_slew_timing_and_hand_at_target(udp_sim):
    sim, client = udp_sim("--slew-s-per-60deg", "0.6")  # slow: 1000 µs take ~1.8 s
    client.wait_for(is_type("HEARTBEAT"))
    client.command(mavlink.MAV_CMD_DO_SET_SERVO, 9, 1000)  # theta1 → -90°
    client.wait_for(ack_for(183))
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


def test_udp_signing_required(udp_sim, tmp_path):
    key = bytes(range(1, 33))
    key_file = tmp_path / "key.hex"
    key_file.write_text(key.hex() + "\n")
    sim, unsigned = udp_sim("--signing-key", str(key_file))
    unsigned.command(mavlink.MAV_CMD_DO_SET_SERVO, 9, 1600)
    assert wait_until(lambda: sim.state()["stats"]["rejected_signature"] >= 2)
    assert sim.state()["outputs"]["9"]["pwm_us"] == 0
    signed = UdpClient(sim.url, signing_key=key)
    try:
        signed.command(mavlink.MAV_CMD_DO_SET_SERVO, 9, 1600)
        ack = signed.wait_for(ack_for(183))
        assert ack.result == mavlink.MAV_RESULT_ACCEPTED and ack.get_signed()
    finally:
        signed.close()
    assert sim.stop() == 0


def test_udp_faults_withhold_nack_heartbeat_pause(udp_sim):
    sim, client = udp_sim(
        "--withhold-ack", "DO_SET_SERVO", "--nack-output", "10", "--heartbeat-pause-after", "0"
    )
    client.command(mavlink.MAV_CMD_NAV_TAKEOFF)
    client.wait_for(ack_for(22))  # the link works...
    client.command(mavlink.MAV_CMD_DO_SET_SERVO, 9, 1600)
    assert wait_until(lambda: sim.state()["outputs"]["9"]["pwm_us"] == 1600)
    deadline = time.monotonic() + 1.5
    while time.monotonic() < deadline:
        client.read(0.05)
    kinds = {m.get_type() for _, m in client.log}
    assert "HEARTBEAT" not in kinds  # paused from the start
    assert not any(m.get_type() == "COMMAND_ACK" and m.command == 183 for _, m in client.log)
    assert sim.state()["stats"]["acks_withheld"] == 1
    assert sim.stop() == 0


def test_udp_reboot_on_request_silence_then_time_boot_and_sequence_from_zero(udp_sim):
    sim, client = udp_sim("--system-time-rate-hz", "20", "--reboot-gap", "0.5")
    last = client.wait_for(lambda m: is_type("SYSTEM_TIME")(m) and m.time_boot_ms > 300)
    start = len(client.log)
    assert sim.reboot()
    assert not sim.reboot()  # already rebooting
    assert wait_until(lambda: len(sim.events("fault", fault="booted")) == 1)
    client.wait_for(is_type("SYSTEM_TIME"))
    deadline = time.monotonic() + 0.3
    while time.monotonic() < deadline:
        client.read(0.05)
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


def test_udp_drop_and_latency(udp_sim):
    sim, client = udp_sim("--latency-ms", "200")
    sent = client.command(mavlink.MAV_CMD_NAV_TAKEOFF)
    client.wait_for(ack_for(22))
    arrived = client.log[-1][0]
    assert arrived - sent >= 0.2
    assert sim.stop() == 0

    sim, client = udp_sim("--drop-out", "1", "--seed", "1")
    client.command(mavlink.MAV_CMD_NAV_TAKEOFF)
    assert wait_until(lambda: sim.state()["stats"]["dropped_out"] >= 2)
    client.read(0.3)
    assert client.log == []
    assert sim.stop() == 0


def test_tcp_link(tmp_path):
    sim = SimProcess(tmp_path, "--tcp", "127.0.0.1:0")
    try:
        _, host, port = sim.url.split(":")
        with socket.create_connection((host, int(port)), timeout=WAIT_S) as sock:
            mav, dec = mavlink.MAVLink(None, 255, 190), mavlink.MAVLink(None)
            sock.sendall(mav.command_long_encode(1, 1, 183, 0, 11, 1400, 0, 0, 0, 0, 0).pack(mav))
            got = []
            deadline = time.monotonic() + WAIT_S
            while not any(m.get_type() == "COMMAND_ACK" for m in got):
                assert time.monotonic() < deadline, "no ACK over TCP"
                got += dec.parse_buffer(sock.recv(4096)) or []
            assert [m for m in got if m.get_type() == "COMMAND_ACK"][0].result == 0
        assert sim.state()["outputs"]["11"]["pwm_us"] == 1400
        assert sim.stop() == 0
    finally:
        sim.kill()


def _pty_exchange(port: serial.Serial, mav, dec, msg, want, timeout_s=WAIT_S):
    # Frames read past the one wanted are kept for the next exchange: the STATUSTEXT that
    # follows a FAILED ACK may come in the same read (the simulator's output hold).
    backlog = dec.__dict__.setdefault("backlog", [])
    port.write(msg.pack(mav))
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        backlog += dec.parse_buffer(port.read(port.in_waiting or 1)) or []
        for i, m in enumerate(backlog):
            if want(m):
                del backlog[: i + 1]
                return m
    raise AssertionError("no reply over the pty")


def test_pty_link_and_hangup(tmp_path):
    # The hang-up is asked for (query ``hangup``) after the three exchanges below; it replaces
    # the one scheduled for much later.
    sim = SimProcess(tmp_path, "--pty", "--hangup-after", "600")
    try:
        device, _, baud = sim.url.rpartition(",")
        assert device.startswith("/dev/") and baud == "115200"
        with serial.Serial(device, int(baud), timeout=0.05) as port:
            mav, dec = mavlink.MAVLink(None, 255, 190), mavlink.MAVLink(None)
            beat = _pty_exchange(
                port, mav, dec, mav.heartbeat_encode(18, 8, 0, 0, 0), is_type("HEARTBEAT")
            )
            assert beat.autopilot == mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA
            ack = _pty_exchange(
                port,
                mav,
                dec,
                mav.command_long_encode(1, 1, 183, 0, 3, 1500, 0, 0, 0, 0, 0),
                ack_for(183),
            )
            assert ack.result == mavlink.MAV_RESULT_FAILED
            text = _pty_exchange(
                port, mav, dec, mav.heartbeat_encode(18, 8, 0, 0, 0), is_type("STATUSTEXT")
            )
            assert text.text == "ServoRelayEvent: Channel 3 is already in use"
            assert sim.hangup()
            assert wait_until(lambda: sim.state()["link"]["closed"])
            assert not sim.hangup()  # away for good: no second hang-up

            def read_fails() -> bool:
                try:
                    port.read(1)
                except (serial.SerialException, OSError):
                    return True
                return False

            assert wait_until(read_fails)
        assert any(e.get("fault") == "hangup" for e in sim.events())
        assert sim.stop() == 0
    finally:
        sim.kill()
