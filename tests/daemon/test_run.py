"""``armbridge run``'s SIGHUP path, in-process: a re-read config goes through load_config's
bounds before ``ArmDaemon.reload`` ever sees it."""

from __future__ import annotations

import logging
import os
import signal
import time

import pytest

from companion.daemon.config import load_config
from companion.daemon.control_socket import ControlServer
from companion.daemon.run import HeartbeatWait, SignalFlags, reload_config
from companion.daemon.service import ArmDaemon

GOOD = '[link]\nurl = "udpout:127.0.0.1:14550"\n[control]\nrate_hz = 20.0\n'


class RecordingDaemon(ArmDaemon):
    """An ArmDaemon (never started: no link) that records what reload is given."""

    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.reloaded = []

    def reload(self, new):
        self.reloaded.append(new)
        return super().reload(new)


@pytest.fixture
def daemon_and_path(tmp_path):
    path = tmp_path / "armbridge.toml"
    path.write_text(GOOD)
    return RecordingDaemon(load_config(path)), path


@pytest.mark.parametrize(
    ("edit", "field"),
    [
        (lambda t: t.replace("rate_hz = 20.0", "rate_hz = 1e-10"), "control.rate_hz"),
        (lambda t: t + "[solver]\nbudget_ms = 1e300\n", "solver.budget_ms"),
        (lambda t: t + "[arm]\njoint_speed_deg_s = 1e6\n", "arm.joint_speed_deg_s"),
        (
            lambda t: t.replace("[control]", "command_timeout_s = 1e300\n[control]"),
            "link.command_timeout_s",
        ),
        (
            lambda t: (
                t
                + "[arm]\npark_deg = [0, 170, 0, 0, 0, 0]\n"
                + "".join(f"[[joint]]\noutput = {o}\n" for o in range(9, 15)).replace(
                    "output = 10\n", "output = 10\ntrim_us = 100\n"
                )
            ),
            "joint[2].trim_us",
        ),
    ],
    ids=["rate", "budget", "joint-speed", "command-timeout", "trim"],
)
def test_an_out_of_bounds_reload_never_reaches_the_daemon(daemon_and_path, caplog, edit, field):
    daemon, path = daemon_and_path
    running = daemon.config
    path.write_text(edit(GOOD))
    with caplog.at_level(logging.ERROR, logger="armbridge"):
        assert reload_config(daemon, str(path)) is False
    assert daemon.reloaded == [] and daemon.config is running
    assert f": {field}: " in caplog.text and "keeping the running config" in caplog.text


def test_an_in_bounds_reload_is_applied(daemon_and_path):
    daemon, path = daemon_and_path
    path.write_text(GOOD.replace("rate_hz = 20.0", "rate_hz = 400"))
    assert reload_config(daemon, str(path)) is True
    assert len(daemon.reloaded) == 1 and daemon.config.rate_hz == 400


def test_the_wait_for_the_autopilot_is_logged_at_doubling_intervals(caplog):
    """No flight controller yet: a warning at 5 s, then at 10, 20, 40 s... and one line when
    it is heard; nothing after that."""
    wait = HeartbeatWait("udpout:127.0.0.1:14550", started_s=100.0)
    with caplog.at_level(logging.INFO, logger="armbridge"):
        for t in range(0, 60):
            wait.update(False, 100.0 + t)
        wait.update(True, 160.5)
        wait.update(False, 200.0)
        wait.update(True, 300.0)
    lines = [r.getMessage() for r in caplog.records]
    waits = [line for line in lines if "no heartbeat" in line]
    assert [w.split(" after ")[1].split(" s")[0] for w in waits] == ["5", "10", "20", "40"]
    assert "udpout:127.0.0.1:14550" in waits[0] and "armbridge doctor" in waits[0]
    assert lines[-1] == "autopilot link up after 60.5 s" and wait.heard


def test_sighup_applies_the_sockets_limits_and_keeps_its_path(tmp_path, caplog):
    """[control] on SIGHUP: max_connections and idle_timeout_s reach the running server; a new
    socket path or group needs a restart (kept, and said)."""
    socket_path = tmp_path / "c.sock"
    path = tmp_path / "armbridge.toml"
    path.write_text(GOOD + f'socket = "{socket_path}"\n')
    daemon = ArmDaemon(load_config(path))
    server = ControlServer(str(socket_path), daemon)
    try:
        assert (server.max_connections, server.idle_timeout_s) == (32, 30.0)
        path.write_text(
            GOOD
            + f'socket = "{tmp_path / "other.sock"}"\nmax_connections = 4\nidle_timeout_s = 2\n'
        )
        with caplog.at_level(logging.WARNING):
            assert reload_config(daemon, str(path), server)
        assert (server.max_connections, server.idle_timeout_s) == (4, 2.0)
        assert daemon.config.control_socket == str(socket_path)
        assert "control.socket changed: restart the daemon to apply it" in caplog.text
    finally:
        server.close()


def test_signal_flags_wake_the_main_loop_without_a_lock_in_the_handler():

    flags = SignalFlags()
    previous = signal.signal(signal.SIGHUP, flags.on_reload)
    try:
        t0 = time.monotonic()
        os.kill(os.getpid(), signal.SIGHUP)
        flags.wait(5.0)  # returns at once: the flag is set, or the pipe woke it
        assert flags.reload and not flags.stop
        assert time.monotonic() - t0 < 4.0
        flags.reload = False
        t0 = time.monotonic()
        flags.wait(0.05)  # nothing came: the timeout
        assert time.monotonic() - t0 >= 0.04
    finally:
        signal.signal(signal.SIGHUP, previous)
        flags.close()
