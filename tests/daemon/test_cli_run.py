"""``armbridge run`` as a subprocess, driven by the CLI's client verbs: a service's life
(READY, a goto, SIGTERM), a goto waiting at SIGTERM, a serial device not plugged in yet."""

from __future__ import annotations

import json
import math
import os
import signal
import socket
import time

import pytest

from companion.daemon.cli import main
from companion.daemon.control_socket import request
from companion.kinematics.arm import Arm
from devkit.control_client import ControlConnection
from devkit.timing import wait_until

pytestmark = pytest.mark.slow

WAIT_S = 15.0


@pytest.mark.slow
def test_run_as_a_service_ready_goto_sigterm(tmp_path, sims, daemons, capsys):
    """The daemon as systemd runs it: READY=1 once it serves (saying what it waits for), the
    link up once the autopilot is heard, targets over the control socket, SIGTERM → park →
    STOPPING=1 → exit 0 within a second."""
    notify = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    notify.bind(str(tmp_path / "notify.sock"))
    notify.settimeout(WAIT_S)
    sim = sims("--udp", "127.0.0.1:0")
    env = {**os.environ, "NOTIFY_SOCKET": str(tmp_path / "notify.sock"), "WATCHDOG_USEC": "2000000"}
    # The harness returns once the control socket answers; the notifications wait in `notify`.
    daemon = daemons(
        {"link": {"url": sim.url}, "arm": {"park_deg": [0, 90, 0, 0, 0, 0], "park_on_stop": True}},
        env=env,
    )
    control = daemon.control_path
    config = daemon.config_path
    try:
        messages = []
        while not any(m.startswith(b"READY=1") for m in messages):
            messages.append(notify.recv(4096))  # each recv bounded by the socket timeout
        assert messages[-1] == b"READY=1\nSTATUS=waiting for the autopilot heartbeat on " + (
            sim.url.encode()
        )
        assert any(m.startswith(b"EXTEND_TIMEOUT_USEC=") for m in messages)
        assert wait_until(lambda: request(control, {"cmd": "status"})["status"]["link"] == "up")
        _cli_clients_against_a_live_daemon(str(control), tmp_path, capsys)
        reply = request(
            control, {"cmd": "goto", "pose": [62.14, 22.25, -3.32, 17.24, -1.47, 19.70]}
        )
        assert reply["ok"] and reply["outcome"] == "accepted", reply
        assert (
            request(control, {"cmd": "goto", "pose": [-20, 3, 40, 0, 10, 15]})["outcome"]
            == "failed"
        )
        status = request(control, {"cmd": "status"})["status"]
        assert status["link"] == "up" and status["counters"]["failed"] == 1
        assert "goto (62.14, 22.25, -3.32, 17.24, -1.47, 19.70) from socket" in daemon.log()
        notify.settimeout(3.0)
        assert any(notify.recv(4096) == b"WATCHDOG=1" for _ in range(20))
        # SIGHUP: a new budget applies at once; a new link URL needs a restart and is kept.
        config.write_text(
            config.read_text()
            .replace("[arm]", "[solver]\nbudget_ms = 5.0\n[arm]")
            .replace("udpout:127.0.0.1:", "udpout:127.0.0.2:")
        )
        daemon.proc.send_signal(signal.SIGHUP)
        seen = []
        while not (
            b"RELOADING=1" in seen
            and any(m.startswith(b"READY=1") for m in seen[seen.index(b"RELOADING=1") :])
        ):
            seen.append(notify.recv(4096))  # each recv bounded by the socket timeout
        assert request(control, {"cmd": "status"})["status"]["link"] == "up"
        started = time.monotonic()
        daemon.proc.send_signal(signal.SIGTERM)
        assert daemon.proc.wait(timeout=5) == 0
        assert time.monotonic() - started < 1.5
        rest = []
        notify.settimeout(0.5)
        try:
            while True:
                rest.append(notify.recv(4096))
        except TimeoutError:
            pass
        assert any(m.startswith(b"STOPPING=1") for m in rest)
        log = daemon.log()
        assert "stopping (parking)" in log
        assert "reload: link changed: restart the daemon to apply it" in log
        assert "reloaded" in log
    finally:
        notify.close()


def _cli_clients_against_a_live_daemon(control: str, tmp_path, capsys) -> None:
    """``goto --wait``, ``trajectory FILE --wait`` and ``status`` (for people and ``--json``)."""
    arm = Arm.default()
    park = [0, 90, 0, 0, 0, 0]  # where the daemon starts: short moves from there
    near = [[g + k * d for g, d in zip(park, (2, -2, 2, 1, 2, 1), strict=True)] for k in (1, 2)]
    there = arm.fk(near[0])
    capsys.readouterr()
    assert main(["goto", *map(str, there.as_tuple()), "--socket", control, "--wait", "-q"]) == 0
    out = capsys.readouterr().out
    assert '"outcome": "accepted"' in out and "still: hand" in out
    path = tmp_path / "path.csv"
    rows = [(0.0, there), (0.2, arm.fk(near[1]))]
    path.write_text(
        "# a short path\nt_s,x_cm,y_cm,z_cm,roll_deg,pitch_deg,yaw_deg\n"
        + "".join(f"{t},{','.join(map(str, pose.as_tuple()))}\n" for t, pose in rows)
    )
    assert main(["trajectory", str(path), "--socket", control, "--wait"]) == 0
    assert "trajectory of 2 points" in capsys.readouterr().out
    assert main(["status", "--socket", control]) == 0
    human = capsys.readouterr().out
    assert human.startswith("link up  autopilot 1/1") and "hand " in human
    assert human.count("acknowledged") >= 6 and "last target" in human
    assert main(["status", "--json", "--socket", control]) == 0
    hand = json.loads(capsys.readouterr().out)["status"]["hand"]
    final = arm.fk(near[1])  # where the trajectory ends, up to PWM steps
    assert list(hand) == ["x_cm", "y_cm", "z_cm", "roll_deg", "pitch_deg", "yaw_deg"]
    assert math.dist(list(hand.values())[:3], final.as_tuple()[:3]) < 0.2, hand
    assert f"x {hand['x_cm']:8.2f} cm" in human


@pytest.mark.slow
def test_a_goto_waiting_at_sigterm_is_answered(sims, daemons):
    """Every request gets one answer, also at shutdown: a goto whose servo update is still
    unconfirmed (the autopilot applies DO_SET_SERVO but withholds the ACKs) when SIGTERM comes
    gets a reply line on its connection, whatever the outcome."""
    sim = sims("--udp", "127.0.0.1:0", "--withhold-ack", "DO_SET_SERVO")
    daemon = daemons(
        {"link": {"url": sim.url}, "arm": {"park_deg": [0, 90, 0, 0, 0, 0], "park_on_stop": True}}
    )
    daemon.wait_link("up")
    with ControlConnection(daemon.control_path, timeout_s=WAIT_S) as conn:
        pose = [62.14, 22.25, -3.32, 17.24, -1.47, 19.70]
        conn.send({"cmd": "goto", "pose": pose})
        # Its update reached the autopilot, whose ACKs will not come (FAILED only after
        # (1 + command_retries) × command_timeout_s = 1.5 s): SIGTERM now.
        assert wait_until(lambda: sim.events("servo"), WAIT_S)
        daemon.proc.send_signal(signal.SIGTERM)
        assert daemon.proc.wait(timeout=5) == 0
        try:
            reply = conn.reply()
        except ConnectionError as exc:
            raise AssertionError(f"no answer, the connection ended: {exc}") from exc
    assert reply["outcome"] in ("cancelled", "failed")
    # Parking goes at the speed limit, a step once the one before is confirmed: with every
    # ACK withheld it stops (no jump to park), says so, and the daemon exits within its bound.
    assert "not parked" in daemon.log()
    assert "Traceback" not in daemon.log()


@pytest.mark.slow
def test_run_without_its_serial_device_serves_and_waits_for_it(tmp_path, daemons):
    """The flight controller's port is missing (unplugged, not enumerated yet): the daemon
    serves its socket, says what it waits for, and opens the port once it appears."""
    device = tmp_path / "ttyACM9"
    daemon = daemons({"link": {"url": f"{device},115200"}})
    daemon.wait_link("waiting")  # (the socket serves a moment before the link is opened)
    assert daemon.status()["link_waiting_for"] == str(device)
    assert f"waiting for {device} to appear" in daemon.log()
    master, slave = os.openpty()  # the board enumerates the flight controller
    try:
        device.symlink_to(os.ttyname(slave))
        assert wait_until(lambda: daemon.status()["link_waiting_for"] is None, WAIT_S)
        assert daemon.status()["link_counters"]["reconnects"] == 1
    finally:
        daemon.stop()
        os.close(master)
        os.close(slave)
