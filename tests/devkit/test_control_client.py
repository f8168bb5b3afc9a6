"""devkit's control-socket client against the daemon's real control server (its autopilot
never talks: status and refusals need no link)."""

from __future__ import annotations

import select
import socket

import pytest

from companion.daemon.config import parse_config
from companion.daemon.control_socket import ControlServer
from companion.daemon.service import ArmDaemon
from devkit.control_client import ControlConnection, request


@pytest.fixture
def server(tmp_path):
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as silent:
        silent.bind(("127.0.0.1", 0))
        daemon = ArmDaemon(
            parse_config({"link": {"url": f"udpout:127.0.0.1:{silent.getsockname()[1]}"}})
        )
        daemon.start()
        srv = ControlServer(tmp_path / "c.sock", daemon)
        yield srv
        srv.close()
        daemon.close()


def test_requests_on_one_connection_in_order(server):
    with ControlConnection(server.path, timeout_s=5.0) as conn:
        assert conn.request({"cmd": "status"})["ok"]
        conn.send({"cmd": "status"})
        conn.send_raw(b"not json\n")
        assert conn.reply()["ok"]
        refused = conn.reply()
        assert refused["ok"] is False and refused["error"]
    assert request(server.path, {"cmd": "status"}, timeout_s=5.0)["ok"]


def test_replies_taken_without_waiting(server):
    with ControlConnection(server.path, timeout_s=5.0) as conn:
        assert conn.try_reply() is None  # nothing asked, nothing there
        conn.send({"cmd": "status"})
        conn.send({"cmd": "status"})
        replies = []
        while len(replies) < 2:
            assert select.select([conn], [], [], 5.0)[0], "no reply within 5 s"
            conn.receive()
            while (reply := conn.buffered_reply()) is not None:
                replies.append(reply)
        assert [r["ok"] for r in replies] == [True, True]
