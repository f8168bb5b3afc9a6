"""Who may use the control socket, and what it may replace: mode 0660 in its group
whatever the umask, peer credentials checked, nothing deleted but our own stale socket.

The tests that connect as another user fork a child that drops to ``nobody`` (uid 65534): they
need root, and skip otherwise."""

from __future__ import annotations

import errno
import grp
import json
import os
import re
import shutil
import socket
import stat
import tempfile
import warnings
from collections.abc import Iterator, Sequence
from pathlib import Path

import pytest

from companion.daemon.config import parse_config
from companion.daemon.control_socket import ControlServer, ControlSocketError, request
from companion.daemon.service import ArmDaemon
from devkit.timing import wait_until

NOBODY = 65534
#: A group that exists on any Debian-like system and is not root's primary group.
OTHER_GROUP = "dialout"
needs_root = pytest.mark.skipif(
    os.geteuid() != 0, reason="connecting as another user needs root (setuid in a child)"
)


@pytest.fixture
def daemon():
    return ArmDaemon(parse_config({"link": {"url": "udpout:127.0.0.1:9"}}))


@pytest.fixture
def public_dir() -> Iterator[Path]:
    """A directory everyone may enter (pytest's tmp_path is 0700: nobody could not reach a
    socket there whatever its mode)."""
    directory = Path(tempfile.mkdtemp(prefix="armbridge-sock-"))
    directory.chmod(0o755)
    yield directory
    shutil.rmtree(directory)


def umask_0_server(path: Path, daemon: ArmDaemon, **kwargs) -> ControlServer:
    """A server started under umask 000, the umask that made the old socket 0777."""
    old = os.umask(0)
    try:
        return ControlServer(path, daemon, **kwargs)
    finally:
        os.umask(old)


def as_nobody(path: Path, line: bytes, groups: Sequence[int] = ()) -> dict:
    """Connect to ``path`` as uid/gid ``nobody`` with supplementary ``groups`` (a forked child)
    and send ``line``: ``{"errno": name}`` if the connect failed, else ``{"reply": bytes}``,
    everything received until the server closed or 5 s passed."""
    read_end, write_end = os.pipe()
    with warnings.catch_warnings():
        # Python 3.12+ warns about fork() with threads running: the child only makes system
        # calls and leaves with os._exit, never touching a lock another thread could hold.
        warnings.simplefilter("ignore", DeprecationWarning)
        pid = os.fork()
    if pid == 0:  # pragma: no cover - the child
        code = 1
        try:
            os.close(read_end)
            os.setgroups(list(groups))
            os.setgid(NOBODY)
            os.setuid(NOBODY)
            sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
            sock.settimeout(5.0)
            try:
                sock.connect(str(path))
            except OSError as exc:
                try:  # and what the client (armbridge status) says about it
                    request(path, {"cmd": "status"}, timeout_s=5.0)
                except OSError as client_exc:
                    said = str(client_exc)
                result = {"errno": errno.errorcode[exc.errno], "client": said}
                os.write(write_end, json.dumps(result).encode())
            else:
                try:
                    sock.sendall(line + b"\n")
                except OSError:  # a refused peer may find the connection closed already
                    pass
                data = b""
                try:
                    while chunk := sock.recv(65536):  # to the end, or the timeout
                        data += chunk
                        if b"\n" in data and not data.startswith(b'{"ok": false'):
                            break  # served: it would keep the connection open
                except (TimeoutError, ConnectionResetError):
                    pass
                os.write(write_end, json.dumps({"reply": data.decode()}).encode())
            code = 0
        except BaseException as exc:
            os.write(write_end, json.dumps({"child": repr(exc)}).encode())
        finally:
            os._exit(code)
    os.close(write_end)
    with os.fdopen(read_end, "rb") as pipe:
        out = pipe.read()
    _, status = os.waitpid(pid, 0)
    result = json.loads(out or b"{}")
    assert os.waitstatus_to_exitcode(status) == 0, f"the child failed: {result}"
    if "reply" in result:
        result["reply"] = result["reply"].encode()
    return result


@needs_root
def test_the_socket_is_0660_in_its_group_whatever_the_umask(public_dir, daemon):
    srv = umask_0_server(public_dir / "c.sock", daemon, group=OTHER_GROUP)
    try:
        st = os.stat(srv.path)
        assert stat.S_IMODE(st.st_mode) == 0o660
        assert st.st_gid == grp.getgrnam(OTHER_GROUP).gr_gid
    finally:
        srv.close()


def test_the_default_group_is_the_daemons_primary_group(tmp_path, daemon):
    srv = ControlServer(tmp_path / "c.sock", daemon)
    try:
        st = os.stat(srv.path)
        assert (stat.S_IMODE(st.st_mode), st.st_gid) == (0o660, os.getegid())
        assert srv.group_name == grp.getgrgid(os.getegid()).gr_name
    finally:
        srv.close()


def test_the_configured_group_comes_from_the_config(tmp_path):
    group = grp.getgrgid(os.getegid()).gr_name
    config = parse_config(
        {
            "link": {"url": "udpout:127.0.0.1:9"},
            "control": {"socket": str(tmp_path / "c.sock"), "socket_group": group},
        }
    )
    srv = ControlServer(config.control_socket, ArmDaemon(config))
    try:
        assert (srv.group_name, srv.gid) == (group, os.getegid())
    finally:
        srv.close()


@needs_root
def test_a_user_outside_the_group_cannot_connect(public_dir, daemon):
    srv = umask_0_server(public_dir / "c.sock", daemon)
    try:
        result = as_nobody(public_dir / "c.sock", b'{"cmd": "status"}')
        assert result["errno"] == "EACCES"
        group = grp.getgrgid(os.getegid()).gr_name
        assert f"(mode 0660, group {group}): the daemon's operators are" in result["client"]
    finally:
        srv.close()


@needs_root
def test_a_peer_outside_the_group_is_refused_by_its_credentials(public_dir, daemon):
    """Even with the file mode opened up (by mistake, or through a path we do not control),
    the peer's credentials decide: one line saying why, then the connection closes, and
    nothing reaches the daemon."""
    srv = ControlServer(public_dir / "c.sock", daemon)
    try:
        os.chmod(srv.path, 0o666)
        result = as_nobody(public_dir / "c.sock", b'{"cmd": "stop"}')
        (line,) = result["reply"].splitlines()
        error = json.loads(line)["error"]
        assert error.startswith("permission denied: uid 65534") and "socket_group" in error
        assert daemon.intake.take() == []
        assert wait_until(lambda: srv.connections == 0)
        assert request(srv.path, {"cmd": "status"})["ok"]
    finally:
        srv.close()


@needs_root
def test_a_member_of_the_group_is_served(public_dir, daemon):
    """Membership through a supplementary group (SO_PEERGROUPS), not the primary one."""
    gid = grp.getgrnam(OTHER_GROUP).gr_gid
    srv = ControlServer(public_dir / "c.sock", daemon, group=OTHER_GROUP)
    try:
        result = as_nobody(public_dir / "c.sock", b'{"cmd": "status"}', groups=[gid])
        reply = json.loads(result["reply"].splitlines()[0])
        assert reply["ok"] and "status" in reply
    finally:
        srv.close()


@pytest.mark.parametrize("kind", ["regular file", "directory", "symbolic link", "FIFO"])
def test_what_is_not_a_socket_is_never_replaced(tmp_path, daemon, kind):
    path = tmp_path / "c.sock"
    if kind == "regular file":
        path.write_text("precious")
    elif kind == "directory":
        path.mkdir()
    elif kind == "symbolic link":
        (tmp_path / "target").write_text("precious")
        path.symlink_to(tmp_path / "target")
    else:
        os.mkfifo(path)
    before = os.lstat(path)
    with pytest.raises(ControlSocketError) as info:
        ControlServer(path, daemon)
    assert info.value.strerror.startswith(f"{path} exists and is not a socket (a {kind})")
    after = os.lstat(path)
    assert (after.st_ino, after.st_mode) == (before.st_ino, before.st_mode)
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(
        ["c.sock"] + (["target"] if kind == "symbolic link" else [])
    )


def test_a_second_server_on_a_live_socket_is_refused(tmp_path, daemon):
    first = ControlServer(tmp_path / "c.sock", daemon)
    try:
        inode = os.stat(first.path).st_ino
        with pytest.raises(ControlSocketError) as info:
            ControlServer(tmp_path / "c.sock", daemon)
        assert "another daemon listens on" in info.value.strerror
        assert os.stat(first.path).st_ino == inode
        assert request(first.path, {"cmd": "status"})["ok"]
    finally:
        first.close()


def test_a_stale_socket_is_replaced(tmp_path, daemon):
    stale = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    stale.bind(str(tmp_path / "c.sock"))
    stale.close()  # the file stays, nobody listens: a killed daemon's
    srv = ControlServer(tmp_path / "c.sock", daemon)
    try:
        assert request(srv.path, {"cmd": "status"})["ok"]
    finally:
        srv.close()
    assert not (tmp_path / "c.sock").exists()


def test_closing_removes_only_its_own_socket(tmp_path, daemon):
    """If the path was replaced while we ran (by someone else), close leaves it alone."""
    srv = ControlServer(tmp_path / "c.sock", daemon)
    os.rename(tmp_path / "c.sock", tmp_path / "moved.sock")
    (tmp_path / "c.sock").write_text("someone else's")
    srv.close()
    assert (tmp_path / "c.sock").read_text() == "someone else's"


def test_the_permission_hint_names_the_directorys_group_when_the_socket_cannot_be_seen(tmp_path):
    """The service's /run/armbridge is 0750: a user outside its group cannot even stat the
    socket, so the hint comes from the directory (found by the clean-rootfs install test)."""
    from companion.daemon.client import _permission_hint

    directory = tmp_path / "run"
    directory.mkdir()
    group = grp.getgrgid(directory.stat().st_gid).gr_name
    hint = _permission_hint(directory / "control.sock")
    assert f"group {group!r}" in hint and "ask to be added" in hint


@pytest.mark.parametrize(
    ("mode", "owner", "says"),
    [
        (0o770, None, "writable by its group or others (mode 0770)"),
        (0o757, None, "writable by its group or others (mode 0757)"),
        (0o750, 65534, "belongs to uid 65534"),
    ],
)
def test_a_socket_directory_another_user_could_write_is_refused(
    tmp_path, daemon, mode, owner, says
):
    directory = tmp_path / "run"
    directory.mkdir()
    directory.chmod(mode)
    if owner is not None:
        if os.geteuid() != 0:
            pytest.skip("giving a directory to another user needs root")
        os.chown(directory, owner, -1)
    with pytest.raises(ControlSocketError, match=re.escape(says)):
        ControlServer(directory / "c.sock", daemon)
    assert not (directory / "c.sock").exists()


def test_a_sticky_shared_directory_is_accepted(tmp_path, daemon):
    directory = tmp_path / "shared"
    directory.mkdir()
    directory.chmod(0o1777)  # as /tmp: nobody may rename or remove another's entries
    srv = ControlServer(directory / "c.sock", daemon)
    try:
        assert request(srv.path, {"cmd": "status"})["ok"]
    finally:
        srv.close()


def test_the_mode_is_never_set_through_a_link_swapped_in_for_the_socket(tmp_path):
    from companion.daemon.control_socket import _set_mode_and_group

    secret = tmp_path / "secret"
    secret.write_text("root only")
    secret.chmod(0o600)
    swapped = tmp_path / ".c.sock.123"
    swapped.symlink_to(secret)  # where the socket was bound a moment before
    with pytest.raises(ControlSocketError, match="no longer the socket"):
        _set_mode_and_group(str(swapped), os.getegid(), "g")
    assert stat.S_IMODE(secret.stat().st_mode) == 0o600
