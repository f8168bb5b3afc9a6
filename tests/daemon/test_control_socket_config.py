"""The ``[control]`` socket fields: a relative socket path counts from the config's
directory like every other path, and ``check-config`` refuses what ``run`` would."""

from __future__ import annotations

import os
import socket
import stat
from pathlib import Path

import pytest

from companion.daemon.cli import main
from companion.daemon.config import load_config, parse_config
from companion.daemon.run import _make_socket_directory
from companion.errors import ConfigError

URL = {"url": "udpout:127.0.0.1:9"}


def write(directory: Path, control: str) -> Path:
    directory.mkdir(parents=True, exist_ok=True)
    path = directory / "armbridge.toml"
    path.write_text(f'[link]\nurl = "udpout:127.0.0.1:9"\n[control]\n{control}\n')
    return path


def test_a_relative_socket_path_counts_from_the_config_files_directory(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # not where the config is
    path = write(tmp_path / "etc", 'socket = "run/control.sock"')
    (tmp_path / "etc" / "run").mkdir()
    assert load_config(path).control_socket == str(tmp_path / "etc" / "run" / "control.sock")


def test_check_config_refuses_a_file_that_is_not_a_socket(tmp_path, capsys):
    (tmp_path / "control.sock").write_text("precious")
    path = write(tmp_path, 'socket = "control.sock"')
    assert main(["check-config", str(path)]) == 2
    err = capsys.readouterr().err
    assert ": control.socket: " in err and "is not a socket (a regular file)" in err
    assert (tmp_path / "control.sock").read_text() == "precious"


def test_check_config_accepts_a_socket_at_the_path(tmp_path):
    """A stale socket, or the running daemon's own (a SIGHUP reload reads the same config)."""
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as sock:
        sock.bind(str(tmp_path / "control.sock"))
        path = write(tmp_path, 'socket = "control.sock"')
        assert load_config(path).control_socket == str(tmp_path / "control.sock")


def test_check_config_refuses_a_missing_directory(tmp_path):
    path = write(tmp_path, 'socket = "no-such-dir/below/control.sock"')
    with pytest.raises(ConfigError) as info:
        load_config(path)
    assert info.value.field == "control.socket" and "does not exist" in str(info.value)


def test_run_makes_a_missing_last_directory(tmp_path):
    """As RuntimeDirectory= would: check-config passes it, and run makes it (0750)."""
    config = load_config(write(tmp_path, 'socket = "rundir/control.sock"'))
    assert not (tmp_path / "rundir").exists()
    _make_socket_directory(config)
    assert (tmp_path / "rundir").is_dir()
    assert stat.S_IMODE((tmp_path / "rundir").stat().st_mode) == 0o750 & ~_umask()
    _make_socket_directory(config)  # already there: nothing to do


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def test_an_empty_socket_means_none(tmp_path):
    assert load_config(write(tmp_path, 'socket = ""')).control_socket is None


def test_a_missing_runtime_directory_under_run_passes(tmp_path):
    """systemd's RuntimeDirectory= makes /run/NAME when the service starts."""
    assert not os.path.exists("/run/armbridge-test-nonexistent")
    config = parse_config(
        {"link": URL, "control": {"socket": "/run/armbridge-test-nonexistent/c.sock"}}
    )
    assert config.control_socket == "/run/armbridge-test-nonexistent/c.sock"


@pytest.mark.parametrize(
    ("control", "field", "words"),
    [
        ({"socket": "/tmp/c.sock", "socket_group": "no-such-group-x"}, "socket_group", "no group"),
        ({"socket": "/tmp/c.sock", "max_connections": 0}, "max_connections", "[1, 256]"),
        ({"socket": "/tmp/c.sock", "max_connections": 257}, "max_connections", "[1, 256]"),
        ({"socket": "/tmp/c.sock", "idle_timeout_s": 0.05}, "idle_timeout_s", "[0.1, 3600]"),
        ({"socket": "", "idle_timeout_s": 5.0}, "idle_timeout_s", "there is no socket"),
    ],
)
def test_socket_settings_are_bounded(control, field, words):
    with pytest.raises(ConfigError) as info:
        parse_config({"link": URL, "control": control})
    assert info.value.field == f"control.{field}" and words in str(info.value)


def test_socket_settings_defaults():
    config = parse_config({"link": URL, "control": {"socket": "/tmp/c.sock"}})
    assert (
        config.control_socket_group,
        config.control_max_connections,
        config.control_idle_timeout_s,
    ) == (None, 32, 30.0)
