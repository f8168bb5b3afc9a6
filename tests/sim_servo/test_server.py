"""The I/O loop in-process: one exchange over UDP, routing between the companion's and the ground
station's links, stop(), and a protocol failure ending it."""

import socket
import threading
import time

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from devkit.mavlink_peer import MavPeer
from sim_servo.autopilot import SimAutopilot
from sim_servo.config import SimConfig
from sim_servo.endpoints import UdpEndpoint
from sim_servo.eventlog import EventLog
from sim_servo.query import query
from sim_servo.server import SimServer


def start(tmp_path, autopilot_cls=SimAutopilot, gcs=None, config=None):
    events = EventLog(None)
    endpoint = UdpEndpoint("127.0.0.1", 0)
    now = time.monotonic()
    autopilot = autopilot_cls(config or SimConfig(), now_s=now, emit=events)
    server = SimServer(
        autopilot, endpoint, events, gcs=gcs, query_path=str(tmp_path / "q.sock"), start_s=now
    )
    result = {}
    thread = threading.Thread(target=lambda: result.setdefault("rc", server.run()), daemon=True)
    thread.start()
    return server, endpoint, events, thread, result


def test_exchange_query_and_stop(tmp_path):
    server, endpoint, _, thread, result = start(tmp_path)
    with MavPeer.connect(endpoint.url) as client:
        client.command(183, 9, 1234)
        client.next_message(lambda m: m.get_type() == "COMMAND_ACK")
    state = query(tmp_path / "q.sock", "state")
    assert state["outputs"]["9"]["pwm_us"] == 1234 and state["link"]["closed"] is False
    assert any(e["event"] == "ack" for e in query(tmp_path / "q.sock", "events")["events"])
    server.stop()
    thread.join(5)
    assert result["rc"] == 0 and endpoint.closed
    assert not (tmp_path / "q.sock").exists()


def test_frames_are_routed_between_the_companion_and_the_ground_station(tmp_path):
    gcs_endpoint = UdpEndpoint("127.0.0.1", 0)
    server, endpoint, _, thread, result = start(tmp_path, gcs=gcs_endpoint)
    with (
        MavPeer.connect(endpoint.url, system_id=1, component_id=191) as companion,
        MavPeer.connect(gcs_endpoint.url) as gcs,
    ):
        gcs.send_heartbeat(8, 6)
        # The autopilot's heartbeat tells us it has heard (and routes to) the ground station.
        gcs.next_message(lambda m: m.get_type() == "HEARTBEAT")
        companion.send_heartbeat(8, 18)
        gcs.next_message(lambda m: m.get_srcComponent() == 191)
        gcs.command(mavlink.MAV_CMD_USER_1, 1, 2, 3, 4, 5, 6, target=(1, 191))
        got = companion.next_message(lambda m: m.get_type() == "COMMAND_LONG")
        assert got.get_srcSystem() == 255 and (got.param1, got.param6) == (1.0, 6.0)
        companion.send(companion.mav.command_ack_encode(mavlink.MAV_CMD_USER_1, 0, 0, 0, 255, 190))
        got = gcs.ack(mavlink.MAV_CMD_USER_1)
        assert got.get_srcComponent() == 191
    state = query(tmp_path / "q.sock", "state")
    assert state["stats"]["routed"] >= 3 and state["gcs_link"]["closed"] is False
    server.stop()
    thread.join(5)
    assert result["rc"] == 0 and endpoint.closed and gcs_endpoint.closed


class Broken(SimAutopilot):
    def receive(self, data, now_s, channel=0):
        raise RuntimeError("protocol bug")


def test_protocol_exception_ends_the_loop_with_status_1(tmp_path):
    server, endpoint, events, thread, result = start(tmp_path, Broken)
    _, host, port = endpoint.url.split(":")
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as client:
        client.sendto(b"\xfd\x00", (host, int(port)))
    thread.join(5)
    assert result["rc"] == 1
    error = [e for e in events.recent if e["event"] == "error"][0]
    assert "protocol bug" in error["error"]


def test_arming_and_safety_queries(tmp_path):
    px4 = SimConfig(flavour="px4", functions={9: 301})
    server, _, _, thread, result = start(tmp_path, config=px4)
    path = tmp_path / "q.sock"
    assert query(path, "state")["armed"] is False
    assert query(path, "arm") == {"ok": True}
    assert query(path, "state")["armed"] is True
    assert query(path, "kill") == {"ok": True}
    state = query(path, "state")
    assert state["armed"] is False and state["outputs"]["9"]["pwm_us"] == 1000
    assert query(path, "safety_on") == {"ok": False}  # PX4 has none here
    causes = [e.get("cause") for e in query(path, "events")["events"] if e["event"] == "arming"]
    assert causes == ["query", "kill"]
    server.stop()
    thread.join(5)
    assert result["rc"] == 0
    server, _, _, thread, result = start(tmp_path)  # ArduPilot
    assert query(path, "safety_on") == {"ok": True} and query(path, "state")["safety_on"] is True
    assert query(path, "arm") == {"ok": False}
    server.stop()
    thread.join(5)


def test_the_forge_query_sends_a_forged_frame_to_the_companion(tmp_path):
    server, endpoint, _, thread, result = start(tmp_path)
    path = tmp_path / "q.sock"
    with MavPeer.connect(endpoint.url, system_id=1, component_id=191) as companion:
        companion.send_heartbeat(8, 18)  # the UDP endpoint answers its last sender
        companion.next_message(lambda m: m.get_type() == "HEARTBEAT")
        request = '{"query": "forge", "msg": "SYSTEM_TIME", "time_boot_ms": 3}'
        assert query(path, request) == {"ok": True}
        got = companion.next_message(lambda m: m.get_type() == "SYSTEM_TIME")
        assert got.time_boot_ms == 3 and (got.get_srcSystem(), got.get_srcComponent()) == (1, 1)
    assert "msg='NOPE'" in query(path, '{"query": "forge", "msg": "NOPE"}')["error"]
    assert "msg=None" in query(path, "forge")["error"]
    assert query(path, "state")["stats"]["forged"] == 1
    server.stop()
    thread.join(5)
    assert result["rc"] == 0
