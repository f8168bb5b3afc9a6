"""Server-side endpoints: UDP, TCP, pty (raw, no echo), hang-up."""

import os
import select
import socket
import termios
import time

import pytest

from sim_servo.endpoints import (
    PtyEndpoint,
    TcpEndpoint,
    UdpEndpoint,
    UdpOutEndpoint,
    parse_host_port,
)
from sim_servo.errors import SimIOError


def pump(endpoint, timeout_s=5.0) -> bytes:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        readable, _, _ = select.select(endpoint.fds(), [], [], 0.05)
        for fd in readable:
            data = endpoint.read_ready(fd)
            if data:
                return data
    raise AssertionError("nothing received")


def test_udp_replies_to_last_sender_and_hangs_up():
    endpoint = UdpEndpoint("127.0.0.1", 0)
    try:
        endpoint.write(b"early")  # no peer yet: dropped, counted
        assert endpoint.dropped_writes == 1
        _, host, port = endpoint.url.split(":")
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as client:
            client.settimeout(5)
            client.sendto(b"hello", (host, int(port)))
            assert pump(endpoint) == b"hello"
            endpoint.write(b"reply")
            assert client.recvfrom(100)[0] == b"reply"
        endpoint.close()
        assert endpoint.closed and endpoint.fds() == []
        endpoint.write(b"late")
        endpoint.close()
    finally:
        endpoint.close()


def test_tcp_accepts_a_client_and_the_next_one():
    endpoint = TcpEndpoint("127.0.0.1", 0)
    try:
        _, host, port = endpoint.url.split(":")
        for payload in (b"first", b"second"):
            with socket.create_connection((host, int(port)), timeout=5) as client:
                pump_after_accept(endpoint)
                client.sendall(payload)
                assert pump(endpoint) == payload
                endpoint.write(b"ack")
                assert client.recv(10) == b"ack"
    finally:
        endpoint.close()


def pump_after_accept(endpoint) -> bytes:
    readable, _, _ = select.select(endpoint.fds(), [], [], 5)
    for fd in readable:
        endpoint.read_ready(fd)
    return b""


def test_pty_is_raw_and_does_not_echo():
    endpoint = PtyEndpoint()
    try:
        assert endpoint.url == f"{endpoint.path},115200"
        fd = os.open(endpoint.path, os.O_RDWR | os.O_NOCTTY)
        try:
            attrs = termios.tcgetattr(fd)
            assert not attrs[3] & termios.ECHO and not attrs[3] & termios.ICANON
            frame = bytes(range(256))
            os.write(fd, frame)
            got = b""
            while len(got) < len(frame):
                got += pump(endpoint)
            assert got == frame  # nothing translated
            endpoint.write(b"\r\n\x03")
            assert os.read(fd, 10) == b"\r\n\x03"
            readable, _, _ = select.select(endpoint.fds(), [], [], 0.1)
            assert readable == []  # our own write was not echoed back to us
        finally:
            os.close(fd)
    finally:
        endpoint.close()


def test_pty_hangup_fails_the_other_side():
    endpoint = PtyEndpoint()
    fd = os.open(endpoint.path, os.O_RDWR | os.O_NOCTTY)
    try:
        endpoint.close()
        readable, _, _ = select.select([fd], [], [], 5)
        assert readable  # hung up: readable at once ...
        try:
            assert os.read(fd, 1) == b""  # ... and reads end-of-file (pyserial raises) or EIO
        except OSError:
            pass
    finally:
        os.close(fd)


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("localhost", "must be HOST:PORT"),
        ("h:x", "is not an integer"),
        ("h:70000", "outside"),
    ],
)
def test_parse_host_port_errors(text, message):
    with pytest.raises(SimIOError, match=message):
        parse_host_port(text, "--udp")


def test_bind_failure_is_a_sim_error():
    with pytest.raises(SimIOError, match="cannot bind"):
        UdpEndpoint("192.0.2.1", 0)  # TEST-NET address not on this machine


def test_pty_link_follows_the_device_through_a_hangup_and_reopen(tmp_path):
    link = tmp_path / "ttyFC"
    endpoint = PtyEndpoint(str(link))
    try:
        assert endpoint.url == f"{link},115200"
        first = endpoint.path
        assert os.readlink(link) == first
        endpoint.close()  # unplugged: the stable name goes, as udev removes it
        assert not os.path.lexists(link) and endpoint.closed
        endpoint.reopen()  # re-enumerated: a new pty behind the same name
        assert not endpoint.closed and os.readlink(link) == endpoint.path
        assert endpoint.url == f"{link},115200"
        fd = os.open(link, os.O_RDWR | os.O_NOCTTY)
        try:
            os.write(fd, b"\xfd\x01")
            assert pump(endpoint) == b"\xfd\x01"
        finally:
            os.close(fd)
    finally:
        endpoint.close()
    assert not os.path.lexists(link)


def test_pty_link_never_replaces_a_regular_file(tmp_path):
    precious = tmp_path / "notes.txt"
    precious.write_text("keep me")
    with pytest.raises(SimIOError, match="exists and is not a symlink"):
        PtyEndpoint(str(precious))
    assert precious.read_text() == "keep me"


def test_only_a_pty_reopens():
    endpoint = UdpEndpoint("127.0.0.1", 0)
    try:
        with pytest.raises(SimIOError, match="cannot reopen"):
            endpoint.reopen()
    finally:
        endpoint.close()


def test_udpout_sends_first_then_answers_the_first_sender_only():
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as companion:
        companion.bind(("127.0.0.1", 0))
        companion.settimeout(5)
        port = companion.getsockname()[1]
        endpoint = UdpOutEndpoint("127.0.0.1", port)
        try:
            assert endpoint.url == f"udpin:127.0.0.1:{port}"
            endpoint.write(b"heartbeat")  # sent before anyone spoke to us: a companion's udpin
            data, sender = companion.recvfrom(100)
            assert data == b"heartbeat" and sender == tuple(endpoint.local)
            companion.sendto(b"command", sender)
            assert pump(endpoint) == b"command"
            with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as other:
                other.settimeout(5)
                other.sendto(b"intruder", sender)
                assert pump(endpoint) == b"intruder"  # read, but it does not move the peer
                endpoint.write(b"ack")
                assert companion.recvfrom(100)[0] == b"ack"
                with pytest.raises(TimeoutError):
                    other.settimeout(0.05)
                    other.recvfrom(100)
        finally:
            endpoint.close()
        assert endpoint.closed
        endpoint.write(b"late")
        assert endpoint.dropped_writes == 1


def test_udpout_to_nobody_counts_instead_of_raising():
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as gone:
        gone.bind(("127.0.0.1", 0))
        port = gone.getsockname()[1]
    endpoint = UdpOutEndpoint("127.0.0.1", port)  # nobody listens there any more
    try:
        for _ in range(3):  # the ICMP refusal of one may surface on the next send
            endpoint.write(b"heartbeat")
        assert endpoint.dropped_writes <= 3 and not endpoint.closed
    finally:
        endpoint.close()
