"""sd_notify against a real datagram socket bound in a temporary directory."""

from __future__ import annotations

import os
import socket
import uuid

import pytest

from companion.daemon.systemd import Notifier


@pytest.fixture
def notify_socket(tmp_path):
    path = tmp_path / "notify.sock"
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(str(path))
    sock.settimeout(2.0)
    yield str(path), sock
    sock.close()


def test_ready_status_watchdog_stopping_bytes(notify_socket):
    path, sock = notify_socket
    with Notifier({"NOTIFY_SOCKET": path}) as n:
        assert n.enabled
        assert n.ready("link up")
        assert sock.recv(4096) == b"READY=1\nSTATUS=link up"
        assert n.watchdog()
        assert sock.recv(4096) == b"WATCHDOG=1"
        assert n.status("solving\nsecond line")
        assert sock.recv(4096) == b"STATUS=solving second line"
        assert n.stopping()
        assert sock.recv(4096) == b"STOPPING=1"


def test_abstract_namespace_socket():
    name = f"armbridge-test-{uuid.uuid4().hex}"
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind("\0" + name)
    sock.settimeout(2.0)
    try:
        with Notifier({"NOTIFY_SOCKET": "@" + name}) as n:
            assert n.ready()
            assert sock.recv(4096) == b"READY=1"
    finally:
        sock.close()


def test_outside_systemd_everything_is_a_no_op():
    with Notifier({}) as n:
        assert not n.enabled
        assert not n.ready() and not n.watchdog() and not n.stopping()
        assert n.watchdog_period_s is None


def test_vanished_socket_is_logged_not_raised(tmp_path, caplog):
    with Notifier({"NOTIFY_SOCKET": str(tmp_path / "gone.sock")}) as n:
        assert not n.ready()
    assert "sd_notify" in caplog.text


@pytest.mark.parametrize(
    ("env", "period"),
    [
        ({"WATCHDOG_USEC": "4000000"}, 4.0),
        ({"WATCHDOG_USEC": "4000000", "WATCHDOG_PID": str(os.getpid())}, 4.0),
        ({"WATCHDOG_USEC": "4000000", "WATCHDOG_PID": "1"}, None),
        ({"WATCHDOG_USEC": "soon"}, None),
        ({"WATCHDOG_USEC": "0"}, None),
        ({}, None),
    ],
)
def test_watchdog_period(env, period):
    with Notifier(env) as n:
        assert n.watchdog_period_s == period
