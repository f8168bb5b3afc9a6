"""The control socket's JSON-lines protocol, against a daemon whose autopilot is silent."""

from __future__ import annotations

import json
import os
import socket
import stat
import threading
import time

import pytest

from companion.daemon.config import parse_config
from companion.daemon.control_socket import ControlServer, request
from companion.daemon.requests import Reply
from companion.daemon.service import ArmDaemon, Outcome
from devkit.control_client import ControlConnection
from devkit.timing import wait_until


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
    """A client that sees the path can connect: it was bound under another name, given its
    mode, listened, and only then renamed onto the path (which replaces a stale socket)."""
    path = tmp_path / "control.sock"
    stale = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    stale.bind(str(path))  # a socket file nobody listens on: a killed daemon's
    stale.close()
    stale_inode = path.stat().st_ino
    at_rename = []
    real_rename = os.rename

    def rename(src, dst):
        with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as probe:
            probe.connect(src)  # ECONNREFUSED if it were not listening yet
        at_rename.append(
            (os.path.dirname(src), dst, path.stat().st_ino, stat.S_IMODE(os.stat(src).st_mode))
        )
        real_rename(src, dst)

    monkeypatch.setattr(os, "rename", rename)
    srv = ControlServer(path, daemon)
    try:
        assert at_rename == [(str(tmp_path), str(path), stale_inode, 0o660)]
        assert stat.S_ISSOCK(path.stat().st_mode) and path.stat().st_ino != stale_inode
        assert sorted(p.name for p in tmp_path.iterdir()) == ["control.sock"]
        assert request(path, {"cmd": "status"})["ok"]
    finally:
        srv.close()
    assert not path.exists()


def raw(srv, *lines: bytes) -> list[dict]:
    """Send ``lines`` on one connection; the replies that come before it closes (up to one a
    line)."""
    replies = []
    with ControlConnection(srv.path, timeout_s=5) as conn:
        conn.send_raw(b"".join(line + b"\n" for line in lines))
        while len(replies) < len(lines):
            try:
                replies.append(conn.reply())
            except ConnectionError:  # closed (or reset, our unread bytes in its buffer)
                break
    return replies


def test_status_and_several_requests_on_one_connection(server):
    replies = raw(server, b'{"cmd": "status"}', b'{"cmd": "stop"}', b'{"cmd": "status"}')
    assert [r["ok"] for r in replies] == [True, True, True]
    assert replies[0]["status"]["link"] == "waiting"
    assert replies[1]["outcome"] == "accepted"


def test_a_stop_holds_until_a_resume_and_a_goto_the_link_refuses_keeps_it(server):
    assert request(server.path, {"cmd": "stop"})["message"] == "holding until resume"
    status = request(server.path, {"cmd": "status"})["status"]
    assert status["stopped"] is True and status["stopped_by"].startswith("socket ")
    # The autopilot is silent: this goto is not carried out, so the arm stays stopped.
    reply = request(server.path, {"cmd": "goto", "pose": [45, 10, 20, 0, 45, 0]})
    assert reply["outcome"] == "temporarily_rejected"
    assert request(server.path, {"cmd": "status"})["status"]["stopped"] is True
    assert request(server.path, {"cmd": "resume"})["message"] == "resumed"
    status = request(server.path, {"cmd": "status"})["status"]
    assert (status["stopped"], status["stopped_by"]) == (False, None)


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
    reply = request(server.path, {"cmd": "goto", "pose": [1, 2, True, 0, 0, 0]})
    assert (reply["ok"], reply["outcome"]) == (False, "denied")
    assert "Pose.z_cm" in reply["message"]
    # NaN is not JSON: refused by the parser before the daemon sees it.
    reply = request(server.path, {"cmd": "goto", "pose": [1, 2, float("nan"), 0, 0, 0]})
    assert reply == {"ok": False, "error": "refused: NaN is not a JSON number"}


def test_valid_target_with_the_autopilot_silent_is_temporarily_rejected(server):
    reply = request(server.path, {"cmd": "goto", "pose": [45, 10, 20, 0, 45, 0]})
    assert (reply["ok"], reply["outcome"]) == (False, "temporarily_rejected")
    assert request(server.path, {"cmd": "park"})["outcome"] == "temporarily_rejected"


@pytest.fixture
def unstarted():
    """A daemon whose control thread never runs: requests wait in its intake until the test
    answers them (or the socket withdraws them)."""
    return ArmDaemon(parse_config({"link": {"url": "udpout:127.0.0.1:9"}}))


def test_a_request_its_client_gave_up_on_is_never_carried_out(tmp_path, unstarted):
    # A goto whose client was told "no answer" must not wait in a queue and move the arm long
    # after. Here the control thread never runs: after the reply timeout the request is taken
    # back, answered cancelled, and gone.
    srv = ControlServer(tmp_path / "c.sock", unstarted, reply_timeout_s=0.2)
    try:
        (reply,) = raw(srv, b'{"cmd": "goto", "pose": [45, 10, 20, 0, 45, 0]}')
        assert reply["ok"] is False and reply["outcome"] == "cancelled", reply
        assert "no answer within 0.2 s" in reply["message"]
        assert unstarted.intake.take() == []
    finally:
        srv.close()


def test_a_request_whose_client_went_away_is_withdrawn(tmp_path, unstarted):
    """The client closes while its goto waits: the goto is taken back at once (it would
    otherwise move the arm for nobody) instead of after the reply timeout."""
    srv = ControlServer(tmp_path / "c.sock", unstarted, reply_timeout_s=60.0)
    try:
        with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as sock:
            sock.connect(srv.path)
            sock.sendall(b'{"cmd": "goto", "pose": [45, 10, 20, 0, 45, 0]}\n')
            assert wait_until(lambda: srv.waiting == 1)
        assert wait_until(lambda: srv.connections == 0)
        assert unstarted.intake.take() == []
    finally:
        srv.close()


def test_a_waiting_request_holds_up_neither_other_connections_nor_its_order(tmp_path, unstarted):
    """One thread serves everyone: while one connection's park waits for the daemon, another
    connection is answered; the waiting connection's next request is answered after its park,
    in order, and a half-closed client (done sending) still gets both answers."""
    srv = ControlServer(tmp_path / "c.sock", unstarted)
    try:
        with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as sock:
            sock.settimeout(5)
            sock.connect(srv.path)
            sock.sendall(b'{"cmd": "park"}\n{"cmd": "status"}')  # the last line without "\n"
            sock.shutdown(socket.SHUT_WR)
            assert wait_until(lambda: srv.waiting == 1)
            assert request(srv.path, {"cmd": "status"})["ok"]  # not held up
            (park,) = unstarted.intake.take()
            park.answer(Reply(Outcome.ACCEPTED, "parked"))
            lines = b""
            while chunk := sock.recv(65536):
                lines += chunk
        replies = [json.loads(x) for x in lines.splitlines()]
        assert [r.get("message") for r in replies] == ["parked", None]
        assert replies[1]["ok"] and "status" in replies[1]
    finally:
        srv.close()


def test_one_thread_serves_every_connection(tmp_path, unstarted):
    srv = ControlServer(tmp_path / "c.sock", unstarted)
    before = threading.active_count()
    socks = [socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) for _ in range(20)]
    try:
        for sock in socks:
            sock.connect(srv.path)
        assert wait_until(lambda: srv.connections == 20)
        assert threading.active_count() == before
    finally:
        for sock in socks:
            sock.close()
        srv.close()


def test_requests_sent_before_close_are_answered(tmp_path, unstarted):
    """Shutdown closes the daemon first (it answers everything at once), then the socket: a
    request already sent, whether its connection was accepted yet or still in the kernel's
    backlog, gets its answer before the connection closes."""
    unstarted.close()
    srv = ControlServer(tmp_path / "c.sock", unstarted)
    socks = [socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) for _ in range(8)]
    try:
        for sock in socks:
            sock.settimeout(5)
            sock.connect(srv.path)
            sock.sendall(b'{"cmd": "goto", "pose": [45, 10, 20, 0, 45, 0]}\n')
        srv.close()
        for sock in socks:
            reply = json.loads(sock.recv(65536).split(b"\n")[0])
            assert (reply["outcome"], reply["message"]) == (
                "temporarily_rejected",
                "daemon stopping",
            )
            assert sock.recv(65536) == b""
    finally:
        for sock in socks:
            sock.close()


def test_a_close_landing_mid_round_still_reads_what_was_sent(tmp_path, unstarted):
    """A close that lands between a round's wait and its service of the connections: a
    connection accepted before its request came is not closed unread in that round (the
    client would see a reset, not its answer); the last round reads and answers it."""
    unstarted.close()
    srv = ControlServer(tmp_path / "c.sock", unstarted)
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    sock.settimeout(5)
    real_guarded = srv._guarded
    try:
        sock.connect(srv.path)
        wait_until(lambda: srv.connections == 1, timeout_s=5)

        def close_before_service(conn, work, *args):
            if work.__name__ == "_service" and not srv._stopping.is_set():
                sock.sendall(b'{"cmd": "goto", "pose": [45, 10, 20, 0, 45, 0]}\n')
                srv._flush_deadline = time.monotonic() + 5.0
                srv._stopping.set()  # what close() does, after the round looked
            return real_guarded(conn, work, *args)

        srv._guarded = close_before_service
        srv._wake()
        reply = json.loads(sock.recv(65536).split(b"\n")[0])
        assert (reply["outcome"], reply["message"]) == ("temporarily_rejected", "daemon stopping")
        assert sock.recv(65536) == b""
    finally:
        srv.close()
        sock.close()


def test_a_bug_in_the_loop_is_logged_and_the_socket_keeps_serving(
    tmp_path, unstarted, monkeypatch, caplog
):
    """A failure of the accept loop itself is logged and the next round serves again (the
    socket must not die while MAVLink still moves the arm)."""
    srv = ControlServer(tmp_path / "c.sock", unstarted)
    real_accept = srv._accept
    failed = []

    def accept_once_failing():
        if not failed:
            failed.append(True)
            raise RuntimeError("a bug")
        real_accept()

    monkeypatch.setattr(srv, "_accept", accept_once_failing)
    try:
        assert request(srv.path, {"cmd": "status"})["ok"]
        assert failed and srv.alive
        assert "the control socket's loop failed (1 in a row)" in caplog.text
    finally:
        srv.close()
    assert not srv.alive
