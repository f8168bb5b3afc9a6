"""The control socket's JSON-lines protocol, against a daemon whose autopilot is silent."""

from __future__ import annotations

import json
import os
import socket
import stat

import pytest

from companion.daemon.config import parse_config
from companion.daemon.control_socket import ControlServer, request
from companion.daemon.service import ArmDaemon


@pytest.fixture
def daemon():
    silent = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)  # an autopilot that never talks
    silent.bind(("127.0.0.1", 0))
    daemon = ArmDaemon(
        parse_config(
            {
                "link": {"url": f"udpout:127.0.0.1:{silent.getsockname()[1]}"},
                "arm": {"park_deg": [0, 90, 0, 0, 0, 0]},
            }
        )
    )
    daemon.start()
    yield daemon
    daemon.close()
    silent.close()


@pytest.fixture
def server(tmp_path, daemon):
    srv = ControlServer(tmp_path / "control.sock", daemon)
    yield srv
    srv.close()


def test_the_socket_path_appears_only_once_it_listens(tmp_path, daemon, monkeypatch):
    """A client that sees the path can connect: it was bound under another name, listened,
    and only then renamed onto the path (which replaces a stale file)."""
    path = tmp_path / "control.sock"
    path.write_text("stale")
    at_rename = []
    real_rename = os.rename

    def rename(src, dst):
        with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as probe:
            probe.connect(src)  # ECONNREFUSED if it were not listening yet
        at_rename.append((os.path.dirname(src), dst, path.read_text()))
        real_rename(src, dst)

    monkeypatch.setattr(os, "rename", rename)
    srv = ControlServer(path, daemon)
    try:
        assert at_rename == [(str(tmp_path), str(path), "stale")]
        assert stat.S_ISSOCK(path.stat().st_mode)
        assert sorted(p.name for p in tmp_path.iterdir()) == ["control.sock"]
        assert request(path, {"cmd": "status"})["ok"]
    finally:
        srv.close()
    assert not path.exists()


def raw(srv, *lines: bytes) -> list[dict]:
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as sock:
        sock.settimeout(5)
        sock.connect(srv.path)
        sock.sendall(b"".join(line + b"\n" for line in lines))
        buffer = b""
        while buffer.count(b"\n") < len(lines):
            buffer += sock.recv(65536)
    return [json.loads(x) for x in buffer.splitlines()]


def test_status_and_several_requests_on_one_connection(server):
    replies = raw(server, b'{"cmd": "status"}', b'{"cmd": "stop"}', b'{"cmd": "status"}')
    assert [r["ok"] for r in replies] == [True, True, True]
    assert replies[0]["status"]["link"] == "waiting"
    assert replies[1]["outcome"] == "accepted"


@pytest.mark.parametrize(
    ("line", "words"),
    [
        (b"not json", "not JSON"),
        (b"[1, 2]", '"cmd"'),
        (b'{"cmd": "dance"}', "unknown cmd"),
        (b'{"cmd": "trajectory", "points": [[0, 1, 2]]}', "points must be"),
    ],
)
def test_malformed_requests_get_an_error_not_a_crash(server, line, words):
    (reply,) = raw(server, line)
    assert reply["ok"] is False and words in reply["error"]
    assert request(server.path, {"cmd": "status"})["ok"]  # still serving


def test_invalid_target_is_denied_even_with_the_link_down(server):
    reply = request(server.path, {"cmd": "goto", "pose": [1, 2, float("nan"), 0, 0, 0]})
    assert (reply["ok"], reply["outcome"]) == (False, "denied")
    assert "Pose.z_cm" in reply["message"]


def test_valid_target_with_the_autopilot_silent_is_temporarily_rejected(server):
    reply = request(server.path, {"cmd": "goto", "pose": [45, 10, 20, 0, 45, 0]})
    assert (reply["ok"], reply["outcome"]) == (False, "temporarily_rejected")
    assert request(server.path, {"cmd": "park"})["outcome"] == "temporarily_rejected"


def test_a_request_its_client_gave_up_on_is_never_carried_out(tmp_path):
    # A goto whose client was told "no answer" used to wait in an unbounded queue and move the
    # arm 55 s later. Here the control thread never runs (the daemon is not started): after
    # the reply timeout the request is taken back, answered cancelled, and gone.
    daemon = ArmDaemon(parse_config({"link": {"url": "udpout:127.0.0.1:9"}}))
    srv = ControlServer(tmp_path / "c.sock", daemon, reply_timeout_s=0.2)
    try:
        reply = srv.handle_line(b'{"cmd": "goto", "pose": [45, 10, 20, 0, 45, 0]}')
        assert reply["ok"] is False and reply["outcome"] == "cancelled", reply
        assert daemon.intake.take() == []
    finally:
        srv.close()
