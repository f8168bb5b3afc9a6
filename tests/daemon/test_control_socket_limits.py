"""The control socket's limits: connection cap, idle timeout, line length, replies a
client never reads, and the JSON parser's limits. In-process, real Unix sockets; the daemon's
control thread never runs (requests wait in its intake until answered or withdrawn)."""

from __future__ import annotations

import json
import socket
import time

import pytest

from companion.daemon.config import parse_config
from companion.daemon.control_socket import (
    MAX_DEPTH,
    MAX_LINE_BYTES,
    ControlServer,
    parse_request_line,
    request,
)
from companion.daemon.service import ArmDaemon
from devkit.timing import wait_until


@pytest.fixture
def daemon():
    return ArmDaemon(parse_config({"link": {"url": "udpout:127.0.0.1:9"}}))


@pytest.fixture
def serve(tmp_path, daemon):
    """``serve(**kwargs)``: a ControlServer on the unstarted daemon, closed at the end."""
    servers = []

    def start(**kwargs):
        servers.append(ControlServer(tmp_path / f"c{len(servers)}.sock", daemon, **kwargs))
        return servers[-1]

    yield start
    for srv in servers:
        srv.close()


def connect(srv, timeout_s: float = 5.0) -> socket.socket:
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    sock.settimeout(timeout_s)
    sock.connect(srv.path)
    return sock


def read_to_end(sock: socket.socket) -> bytes:
    """Everything the server sends until it closes the connection (bounded by the timeout)."""
    data = b""
    while True:
        try:
            chunk = sock.recv(65536)
        except ConnectionResetError:  # it closed with our unread bytes in its buffer
            return data
        if not chunk:
            return data
        data += chunk


def one_error(data: bytes) -> str:
    (line,) = data.splitlines()
    reply = json.loads(line)
    assert reply["ok"] is False
    return reply["error"]


def test_at_the_cap_a_new_connection_closes_one_that_sent_nothing(serve):
    srv = serve(max_connections=4)
    idle = [connect(srv) for _ in range(4)]
    try:
        assert wait_until(lambda: srv.connections == 4)
        assert request(srv.path, {"cmd": "status"})["ok"]  # the fifth is served
        error = one_error(read_to_end(idle[0]))  # the oldest silent one made room
        assert "closed to make room" in error and "max_connections = 4" in error
        assert srv.connections <= 4
    finally:
        for sock in idle:
            sock.close()


def test_at_the_cap_with_every_connection_waiting_the_newcomer_is_refused(serve, daemon):
    srv = serve(max_connections=2)
    busy = [connect(srv) for _ in range(2)]
    try:
        for sock in busy:
            sock.sendall(b'{"cmd": "park"}\n')  # waits: the control thread never takes it
        assert wait_until(lambda: srv.waiting == 2)
        with connect(srv) as newcomer:
            error = one_error(read_to_end(newcomer))
        assert "too many connections" in error and "max_connections = 2" in error
        assert srv.waiting == 2  # nobody's request was dropped for it
    finally:
        for sock in busy:
            sock.close()


def test_an_idle_connection_is_closed_after_the_idle_timeout(serve):
    srv = serve(idle_timeout_s=0.2)
    started = time.monotonic()
    with connect(srv) as sock:
        error = one_error(read_to_end(sock))
    assert "idle for 0.2 s" in error
    assert 0.2 <= time.monotonic() - started < 5.0
    assert request(srv.path, {"cmd": "status"})["ok"]


def test_a_request_dribbled_a_byte_at_a_time_does_not_hold_a_connection(serve):
    """Slowloris: bytes keep coming, but no request completes within the idle timeout."""
    srv = serve(idle_timeout_s=0.3)
    started = time.monotonic()
    dribble = b'{"cmd": "status", "pad": "' + b"x" * 1000
    sent = 0
    with connect(srv) as sock:
        try:
            while time.monotonic() - started < 5.0:
                sock.send(dribble[sent : sent + 1])
                sent += 1
                time.sleep(0.02)  # the pace of the attack, not a synchronisation
        except (BrokenPipeError, ConnectionResetError):
            pass
        error = one_error(read_to_end(sock))
    assert "without a complete request" in error
    assert time.monotonic() - started < 2.0 and sent > 5


def test_a_line_longer_than_the_limit_is_refused_and_the_connection_closed(serve):
    srv = serve()
    with connect(srv) as sock:
        try:
            sock.sendall(b" " * (1 << 20))  # 1 MiB, no newline
        except (BrokenPipeError, ConnectionResetError):
            pass  # refused before it was all sent
        error = one_error(read_to_end(sock))
    assert f"longer than {MAX_LINE_BYTES} bytes" in error
    assert request(srv.path, {"cmd": "status"})["ok"]


def test_a_trajectory_of_the_most_points_fits_a_line_however_its_numbers_are_written():
    from companion.daemon.control_socket import parse_request_line
    from companion.daemon.requests import MAX_TRAJECTORY_POINTS

    longest = -1.2345678901234567e-300  # the longest float repr json.dumps writes
    points = [[float(i), *[longest] * 6] for i in range(MAX_TRAJECTORY_POINTS)]
    line = json.dumps({"cmd": "trajectory", "points": points}).encode()
    assert len(line) <= MAX_LINE_BYTES
    cmd, payload = parse_request_line(line)
    assert cmd == "trajectory" and len(payload) == MAX_TRAJECTORY_POINTS


def test_a_line_of_exactly_the_limit_is_served(serve):
    srv = serve()
    line = b'{"cmd": "status"}'
    with connect(srv) as sock:
        sock.sendall(line + b" " * (MAX_LINE_BYTES - len(line)) + b"\n")
        reply = json.loads(sock.recv(65536 * 4).split(b"\n")[0])
    assert reply["ok"] and "status" in reply


def test_a_client_that_never_reads_its_replies_is_closed(serve):
    """Requests pile up replies the client never reads: past the cap its requests wait, the
    kernel's buffers fill, and the idle timeout closes it; others are served meanwhile."""
    srv = serve(idle_timeout_s=0.3)
    with connect(srv) as sock:
        sock.setblocking(False)
        lines = b'{"cmd": "status"}\n' * 1000
        try:
            while True:  # until the server stops taking requests and every buffer is full
                sock.send(lines)
        except BlockingIOError:
            pass
        assert request(srv.path, {"cmd": "status"})["ok"]
        assert wait_until(lambda: srv.connections == 0)


@pytest.mark.parametrize(
    ("line", "words"),
    [
        (b'{"cmd": "goto", "pose": ' + b"[" * 30_000 + b"]" * 30_000 + b"}", "nested more than"),
        (b"[" * 33 + b"]" * 33, f"nested more than {MAX_DEPTH} deep"),
        (b'{"cmd": "goto", "pose": [' + b"9" * 5000 + b", 0, 0, 0, 0, 0]}", "5000 digits"),
        (b'{"cmd": "goto", "pose": [-' + b"9" * 21 + b", 0, 0, 0, 0, 0]}", "21 digits"),
        (b'{"cmd": "goto", "pose": [1e999, 0, 0, 0, 0, 0]}', "out of a float's range"),
        (b'{"cmd": "goto", "pose": [NaN, 0, 0, 0, 0, 0]}', "NaN is not a JSON number"),
        (b'{"cmd": "goto", "pose": [-Infinity, 0, 0, 0, 0, 0]}', "-Infinity is not"),
        (
            b'{"cmd": "status", "cmd": "goto", "pose": [45, 10, 20, 0, 45, 0]}',
            "duplicate key 'cmd'",
        ),
        (b'{"cmd": "goto", "pose": [{"a": 1, "a": 2}]}', "duplicate key 'a'"),
    ],
    ids=["deep-30000", "deep-33", "int-5000", "int-21", "1e999", "nan", "-inf", "dup", "dup-inner"],
)
def test_the_parser_refuses_past_its_limits_and_the_server_lives(serve, daemon, line, words):
    srv = serve()
    with connect(srv) as sock:
        sock.sendall(line + b'\n{"cmd": "status"}\n')
        data = b""
        while data.count(b"\n") < 2:
            chunk = sock.recv(65536)
            assert chunk, f"closed after {data!r}"
            data += chunk
    refused, status = (json.loads(x) for x in data.splitlines())
    assert refused["ok"] is False and refused["error"].startswith("refused: ")
    assert words in refused["error"]
    assert status["ok"] and "status" in status
    assert daemon.intake.take() == []  # nothing reached the daemon


def test_the_parser_keeps_what_is_within_its_limits():
    depth = MAX_DEPTH - 1
    assert parse_request_line(
        b'{"cmd": "goto", "pose": ['
        + b"9" * 20
        + b', -1e308, 0.5, 0, 0, 0], "x": "[[[["'
        + b', "y": '
        + b"[" * depth
        + b"]" * depth
        + b"}"
    ) == ("goto", [int("9" * 20), -1e308, 0.5, 0, 0, 0])
    # Brackets inside strings (escaped quotes included) are not nesting.
    assert parse_request_line(b'{"cmd": "status", "s": "\\"' + b"[" * 100 + b'"}') == (
        "status",
        None,
    )
