"""The I/O loop in-process: one exchange over UDP, stop(), and a protocol failure ending it."""

import socket
import threading

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from sim_servo.autopilot import SimAutopilot
from sim_servo.config import SimConfig
from sim_servo.endpoints import UdpEndpoint
from sim_servo.eventlog import EventLog
from sim_servo.query import query
from sim_servo.server import SimServer


def start(tmp_path, autopilot_cls=SimAutopilot):
    events = EventLog(None)
    endpoint = UdpEndpoint("127.0.0.1", 0)
    import time

    now = time.monotonic()
    autopilot = autopilot_cls(SimConfig(), now_s=now, emit=events)
    server = SimServer(
        autopilot, endpoint, events, query_path=str(tmp_path / "q.sock"), start_s=now
    )
    result = {}
    thread = threading.Thread(target=lambda: result.setdefault("rc", server.run()), daemon=True)
    thread.start()
    return server, endpoint, events, thread, result


def test_exchange_query_and_stop(tmp_path):
    server, endpoint, _, thread, result = start(tmp_path)
    _, host, port = endpoint.url.split(":")
    mav, dec = mavlink.MAVLink(None, 255, 190), mavlink.MAVLink(None)
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as client:
        client.settimeout(5)
        client.sendto(
            mav.command_long_encode(1, 1, 183, 0, 9, 1234, 0, 0, 0, 0, 0).pack(mav),
            (host, int(port)),
        )
        got = []
        while not any(m.get_type() == "COMMAND_ACK" for m in got):
            got += dec.parse_buffer(client.recvfrom(4096)[0]) or []
    state = query(tmp_path / "q.sock", "state")
    assert state["outputs"]["9"]["pwm_us"] == 1234 and state["link"]["closed"] is False
    assert any(e["event"] == "ack" for e in query(tmp_path / "q.sock", "events")["events"])
    server.stop()
    thread.join(5)
    assert result["rc"] == 0 and endpoint.closed
    assert not (tmp_path / "q.sock").exists()


class Broken(SimAutopilot):
    def receive(self, data, now_s):
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
