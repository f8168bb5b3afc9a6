"""The "udpin hijack": the daemon listens (``udpin``); the autopilot sends to it first
(ArduPilot's ``udpclient``); an attacker on the same network sends a 1-byte datagram every
2 ms and valid unsigned frames from another system id. Today's udpin sent to the last sender:
the servo commands went to the attacker. Target: 0 to the attacker, all to the autopilot.

The daemon runs in-process (``ArmDaemon``, the code ``armbridge run`` drives) on real loopback
sockets; the park pose needs no solve, so no solver warm-up.
"""

from __future__ import annotations

import socket
import threading

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from companion.daemon.config import parse_config
from companion.daemon.service import ArmDaemon, Outcome
from devkit.mavlink_peer import ScriptedPeer, UdpClientEndpoint
from devkit.timing import wait_until

PARK_DEG = [10, 80, 10, 5, 5, 5]


class Attacker:
    """Sends ``b"\\x00"`` every 2 ms to ``target``, and every 20th time an unsigned HEARTBEAT
    (claiming to be an autopilot) and a COMMAND_LONG from system 66; counts what it receives."""

    def __init__(self, target: tuple[str, int]) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.target = target
        self.received = 0
        self.sent = 0
        self._stop = threading.Event()
        codec = mavlink.MAVLink(None, 66, 1)
        self._frames = [
            codec.heartbeat_encode(
                mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA, 0, 0, 4
            ).pack(codec),
            codec.command_long_encode(1, 191, mavlink.MAV_CMD_USER_1, 0, 1, 2, 3, 0, 0, 0, 0).pack(
                codec
            ),
        ]
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        self.sock.settimeout(0.002)  # the 2 ms cadence, and a receive at each step
        while not self._stop.is_set():
            self.sock.sendto(b"\x00", self.target)
            self.sent += 1
            if self.sent % 20 == 0:
                for frame in self._frames:
                    self.sock.sendto(frame, self.target)
            try:
                self.received += len(self.sock.recv(65535))
            except TimeoutError:
                pass

    def close(self) -> None:
        self._stop.set()
        self._thread.join()
        self.sock.close()


def test_udpin_hijack_sends_nothing_to_the_attacker_and_everything_to_the_autopilot():
    daemon = ArmDaemon(
        parse_config({"link": {"url": "udpin:127.0.0.1:0"}, "arm": {"park_deg": PARK_DEG}})
    )
    daemon.start()
    assert daemon.link is not None and daemon.link.transport is not None
    address = daemon.link.transport.local_address
    autopilot = ScriptedPeer(UdpClientEndpoint(address))
    attacker = None
    try:
        autopilot.send_heartbeat()
        assert wait_until(lambda: daemon.status()["link"] == "up")
        attacker = Attacker(address)
        assert wait_until(lambda: attacker.sent >= 100)  # 0.2 s of attack before the target
        autopilot.send_heartbeat()
        reply = daemon.submit("park").result(10.0)
        assert reply.outcome is Outcome.ACCEPTED, reply.message
        assert wait_until(lambda: not daemon.status()["moving"])
        autopilot.send_heartbeat()
        servo = [
            m
            for m in autopilot.messages("COMMAND_LONG")
            if m.command == mavlink.MAV_CMD_DO_SET_SERVO
        ]
        assert sorted(int(m.param1) for m in servo) == [9, 10, 11, 12, 13, 14]
        status = daemon.status()
        assert status["counters"]["servo_errors"] == 0
        assert status["link_counters"]["rx_foreign_address"] > 0
        assert status["link_counters"]["peer_changes"] == 1
        attacker.close()
        assert attacker.received == 0, f"{attacker.received} bytes went to the attacker"
    finally:
        if attacker is not None:
            attacker.close()
        daemon.close()
        autopilot.close()
