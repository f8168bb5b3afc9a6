"""The Unix-socket query protocol."""

import json
import socket
import threading

import pytest

from sim_servo.errors import SimIOError
from sim_servo.query import QueryServer, query


@pytest.fixture
def server(tmp_path):
    path = tmp_path / "q.sock"
    srv = QueryServer(path, lambda request, args: {"answer": request})
    stop = threading.Event()

    def loop():
        import select

        while not stop.is_set():
            readable, _, _ = select.select(srv.fds(), [], [], 0.02)
            for fd in readable:
                srv.handle(fd)

    thread = threading.Thread(target=loop, daemon=True)
    thread.start()
    yield path
    stop.set()
    thread.join(5)
    srv.close()


def test_word_and_json_requests(server):
    assert query(server, "state") == {"answer": "state"}
    assert query(server, '{"query": "events"}') == {"answer": "events"}
    assert "unknown query 'nope'" in query(server, "nope")["error"]
    for request in ("pause_heartbeat", "resume_heartbeat", "reboot"):
        assert query(server, request) == {"answer": request}


def test_several_requests_on_one_connection(server):
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as sock:
        sock.settimeout(5)
        sock.connect(str(server))
        sock.sendall(b"ping\nstate\n")
        data = b""
        while data.count(b"\n") < 2:
            data += sock.recv(4096)
    assert [json.loads(line)["answer"] for line in data.splitlines()] == ["ping", "state"]


def test_no_server(tmp_path):
    with pytest.raises(SimIOError, match="failed"):
        query(tmp_path / "absent.sock", timeout_s=0.5)


def test_stale_socket_file_is_replaced(tmp_path):
    path = tmp_path / "q.sock"
    path.write_text("")
    srv = QueryServer(path, lambda r, args: {})
    srv.close()
    assert not path.exists()
