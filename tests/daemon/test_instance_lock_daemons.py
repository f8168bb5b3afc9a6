"""One ``armbridge run`` per config, with real processes: a second daemon on the same config
exits 2, and the first still answers."""

from __future__ import annotations

import socket
import subprocess
import sys

import pytest

from devkit.daemon_process import ROOT

pytestmark = pytest.mark.slow

#: How long each command may take to exit. It pays the imports only (about a second on a quiet
#: machine), but the whole test takes 22 s at load 5, so 20 s is too short a bound.
EXIT_S = 120.0


@pytest.fixture
def silent_autopilot():
    """A bound UDP port that never answers: the daemon's socket serves while its link waits
    for a heartbeat, so no simulator is needed. Yields the config's ``link`` table."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as peer:
        peer.bind(("127.0.0.1", 0))
        yield {"url": f"udpout:127.0.0.1:{peer.getsockname()[1]}"}


def test_a_second_daemon_on_the_same_config_exits_2_and_the_first_still_answers(
    daemons, silent_autopilot
):
    first = daemons({"link": silent_autopilot})
    socket_inode = first.control_path.stat().st_ino
    cli = [sys.executable, "-m", "companion.daemon.cli"]
    # Side by side (each pays the imports): the second instance, and check-config, which must
    # not take the lock (it works while the daemon runs).
    second, checked = (
        subprocess.Popen(
            cli + args,
            cwd=ROOT,
            stdin=subprocess.DEVNULL,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        for args in (
            ["run", "--config", str(first.config_path)],
            ["check-config", str(first.config_path)],
        )
    )
    try:
        second_out, second_err = second.communicate(timeout=EXIT_S)
        checked_out, checked_err = checked.communicate(timeout=EXIT_S)
    finally:
        for proc in (second, checked):
            proc.kill()
            proc.wait()
    assert second.returncode == 2, second_err
    assert f"already running (pid {first.pid}" in second_err
    assert checked.returncode == 0 and ": OK" in checked_out, checked_err
    # It deleted nothing and bound nothing: the same socket file answers.
    assert first.control_path.stat().st_ino == socket_inode
    assert first.request("status")["ok"] is True
    assert first.proc.poll() is None
