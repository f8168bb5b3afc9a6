import os
import select
import socket
import time

import pytest
import serial

from firmware_interface.errors import InvalidUrl, TransportError
from firmware_interface.transport import (
    OPENERS,
    TransportSpec,
    UdpInTransport,
    open_transport,
    parse_url,
)


@pytest.mark.parametrize(
    "url, spec",
    [
        ("/dev/ttyACM0,921600", TransportSpec("serial", "/dev/ttyACM0", baud=921600)),
        ("serial:///dev/ttyACM0?baud=57600", TransportSpec("serial", "/dev/ttyACM0", baud=57600)),
        ("COM3,115200", TransportSpec("serial", "COM3", baud=115200)),
        ("udpin:0.0.0.0:14550", TransportSpec("udpin", "0.0.0.0", port=14550)),
        ("udp:127.0.0.1:0", TransportSpec("udpin", "127.0.0.1", port=0)),
        ("udpout:192.168.1.10:14550", TransportSpec("udpout", "192.168.1.10", port=14550)),
        ("tcp:127.0.0.1:5760", TransportSpec("tcp", "127.0.0.1", port=5760)),
        # MAVSDK's forms
        ("udp://:14540", TransportSpec("udpin", "0.0.0.0", port=14540)),
        ("udpin://0.0.0.0:14540", TransportSpec("udpin", "0.0.0.0", port=14540)),
        ("udpin://:14540", TransportSpec("udpin", "0.0.0.0", port=14540)),
        ("udpout://10.41.1.1:14540", TransportSpec("udpout", "10.41.1.1", port=14540)),
        ("tcp://127.0.0.1:5760", TransportSpec("tcp", "127.0.0.1", port=5760)),
        ("serial:///dev/ttyACM0:921600", TransportSpec("serial", "/dev/ttyACM0", baud=921600)),
    ],
)
def test_parse_url_accepts_the_usual_forms(url, spec):
    assert parse_url(url) == spec


@pytest.mark.parametrize(
    "url, why",
    [
        ("bluetooth:aa:bb", "unknown scheme 'bluetooth'"),
        ("/dev/ttyACM0", "not a recognised form"),
        ("/dev/ttyACM0,fast", "baud='fast' is not an integer"),
        ("/dev/ttyACM0,0", r"baud=0 outside \[1, 12000000\]"),
        ("serial:///dev/ttyACM0", r"missing \?baud=N"),
        ("udpout:127.0.0.1:0", r"port=0 outside \[1, 65535\] for udpout"),
        ("tcp:127.0.0.1:70000", r"port=70000 outside"),
        ("tcp:5760", "needs HOST:PORT"),
        ("tcp://:5760", "needs HOST:PORT"),
        ("udpout://:14540", "needs HOST:PORT"),
        ("serial:///dev/ttyACM0:fast", r"missing \?baud=N"),
        ("serial://:921600", "no serial device"),
        ("", "empty"),
    ],
)
def test_parse_url_refuses_with_reason_and_valid_forms(url, why):
    with pytest.raises(InvalidUrl, match=why) as info:
        parse_url(url)
    assert "valid forms:" in str(info.value) and "udpout:HOST:PORT" in str(info.value)


def test_every_parsed_kind_has_an_opener():
    assert set(OPENERS) == {"serial", "udpin", "udpout", "tcp"}


def read_until(transport, n, timeout_s=5.0):
    deadline = time.monotonic() + timeout_s
    data = b""
    while len(data) < n and time.monotonic() < deadline:
        data += transport.read(0.05)
    return data


def test_udp_in_and_out_talk_to_each_other():
    with open_transport("udpin:127.0.0.1:0") as server:
        assert isinstance(server, UdpInTransport)
        host, port = server.local_address
        assert port != 0
        server.write(b"dropped: no peer yet")  # must not raise
        with open_transport(f"udpout:{host}:{port}") as client:
            client.write(b"hello")
            assert read_until(server, 5) == b"hello"
            # A datagram never chooses the peer by itself: the link does, after decoding.
            assert server.peer is None
            server.set_peer(client.local_address)
            server.write(b"reply")
            assert read_until(client, 5) == b"reply"
            assert client.read(0.0) == b""


def test_tcp_client_reads_writes_and_reports_peer_close():
    with socket.create_server(("127.0.0.1", 0)) as listener:
        port = listener.getsockname()[1]
        with open_transport(f"tcp:127.0.0.1:{port}") as client:
            conn, _ = listener.accept()
            with conn:
                client.write(b"ping")
                assert conn.recv(16) == b"ping"
                conn.sendall(b"pong")
                assert read_until(client, 4) == b"pong"
            with pytest.raises(TransportError, match="closed by peer"):
                read_until(client, 1)


def test_tcp_connect_refused_keeps_the_os_error():
    with socket.create_server(("127.0.0.1", 0)) as listener:
        port = listener.getsockname()[1]
    with pytest.raises(TransportError) as info:
        open_transport(f"tcp:127.0.0.1:{port}")
    assert isinstance(info.value.__cause__, OSError)


@pytest.fixture
def pty_pair():
    master, slave = os.openpty()
    path = os.ttyname(slave)
    yield master, path
    for fd in (master, slave):
        try:
            os.close(fd)
        except OSError:
            pass


def test_serial_over_a_pty_both_ways(pty_pair):
    master, path = pty_pair
    with open_transport(f"serial://{path}?baud=115200") as port:
        os.write(master, b"\xfe\x01abc")
        assert read_until(port, 5) == b"\xfe\x01abc"
        port.write(b"xyz")
        ready, _, _ = select.select([master], [], [], 5.0)
        assert ready and os.read(master, 16) == b"xyz"


def test_serial_read_fails_cleanly_when_the_pty_vanishes(pty_pair):
    master, path = pty_pair
    port = open_transport(f"{path},57600")
    try:
        os.close(master)
        with pytest.raises(TransportError, match="read from") as info:
            read_until(port, 1)
        assert isinstance(info.value.__cause__, (serial.SerialException, OSError, TypeError))
    finally:
        port.close()


def test_missing_serial_device_is_a_transport_error_with_cause(tmp_path):
    with pytest.raises(TransportError, match="cannot open serial port") as info:
        open_transport(f"{tmp_path / 'ttyNOPE'},57600")
    assert isinstance(info.value.__cause__, serial.SerialException)
