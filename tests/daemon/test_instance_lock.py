"""One ``armbridge run`` per config: the lock, in-process. Two real daemons on one config:
``test_instance_lock_daemons.py``."""

from __future__ import annotations

import os

import pytest

from companion.daemon.instance_lock import AlreadyRunning, InstanceLock, lock_path

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
