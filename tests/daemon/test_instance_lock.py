"""One ``armbridge run`` per config: the lock in-process, then two real daemons on one config."""

from __future__ import annotations

import os
import socket
import subprocess
import sys

import pytest

from companion.daemon.instance_lock import AlreadyRunning, InstanceLock, lock_path
from devkit.daemon_process import ROOT

# -- the lock, in-process (flock locks belong to an open file description: a second open in
# the same process conflicts like a second process would) --------------------------------------


def test_the_holder_writes_its_pid_and_a_second_taker_is_refused_naming_it(tmp_path):
    path = tmp_path / "control.sock.lock"
    with InstanceLock(path):
        assert path.read_text() == f"{os.getpid()}\n"
        with pytest.raises(AlreadyRunning) as refused:
            InstanceLock(path).acquire()
        assert refused.value.pid == os.getpid()
        assert f"already running (pid {os.getpid()}" in str(refused.value)
        assert path.read_text() == f"{os.getpid()}\n"  # the refused one changed nothing
    with InstanceLock(path):  # released: the next one takes it (a stale pid is overwritten)
        pass
    assert path.exists()  # never deleted


def test_a_stale_longer_pid_is_replaced_not_overlaid(tmp_path):
    path = tmp_path / "x.lock"
    path.write_text("123456789\n")
    with InstanceLock(path):
        assert path.read_text() == f"{os.getpid()}\n"


def test_a_holder_that_has_not_written_its_pid_yet_is_named_unknown(tmp_path):
    path = tmp_path / "x.lock"
    with InstanceLock(path):
        path.write_text("")
        with pytest.raises(AlreadyRunning, match=r"already running \(pid unknown"):
            InstanceLock(path).acquire()


def test_a_symlink_or_a_directory_at_the_lock_path_is_refused(tmp_path):
    victim = tmp_path / "victim"
    victim.write_text("keep me\n")
    (tmp_path / "link.lock").symlink_to(victim)
    with pytest.raises(OSError):
        InstanceLock(tmp_path / "link.lock").acquire()
    assert victim.read_text() == "keep me\n"
    (tmp_path / "dir.lock").mkdir()
    with pytest.raises(OSError):
        InstanceLock(tmp_path / "dir.lock").acquire()


def test_the_lock_sits_beside_the_socket_or_else_is_named_after_the_configs_real_path(
    tmp_path,
):
    assert lock_path("a.toml", "/run/armbridge/control.sock") == (tmp_path / "x").parent.joinpath(
        "/run/armbridge/control.sock.lock"
    )
    config = tmp_path / "armbridge.toml"
    config.write_text("")
    (tmp_path / "alias.toml").symlink_to(config)
    env = {"RUNTIME_DIRECTORY": "/run/armbridge"}
    named = lock_path(config, None, env)
    assert named.parent == tmp_path.parent.joinpath("/run/armbridge")
    assert named.name.startswith("armbridge-") and named.suffix == ".lock"
    assert lock_path(tmp_path / "alias.toml", None, env) == named  # same file, same lock
    assert lock_path(tmp_path / "other.toml", None, env) != named
    assert lock_path(config, None, {"XDG_RUNTIME_DIR": "/run/user/1000"}).parent == (
        tmp_path.parent.joinpath("/run/user/1000")
    )


# -- two real daemons ---------------------------------------------------------------------------


#: How long each command may take to exit: it pays the imports only (about a second), but on a
#: machine loaded by other processes they were seen to take over 20 s.
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
