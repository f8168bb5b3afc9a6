"""The systemd unit carries what the daemon relies on, parses, and is sandboxed (exposure ≤ 3.0
by ``systemd-analyze security --offline=true``, where systemd-analyze exists)."""

from __future__ import annotations

import re
import shutil
import subprocess
from pathlib import Path

import pytest

UNIT = (
    Path(__file__).resolve().parents[2] / "companion" / "daemon" / "examples" / "armbridge.service"
)
#: The bound we hold the unit to; the shipped unit scores 1.7 with systemd 252.
EXPOSURE_MAX = 3.0

analyze = shutil.which("systemd-analyze")
needs_analyze = pytest.mark.skipif(analyze is None, reason="systemd-analyze not installed")


def settings() -> dict[str, list[str]]:
    out: dict[str, list[str]] = {}
    for line in UNIT.read_text().splitlines():
        line = line.strip()
        if line and not line.startswith(("#", "[")) and "=" in line:
            key, value = line.split("=", 1)
            out.setdefault(key, []).append(value)
    return out


def test_unit_is_a_notify_service_with_watchdog_and_restart():
    s = settings()
    assert s["Type"] == ["notify"]
    assert int(s["WatchdogSec"][0]) > 0
    assert s["Restart"] == ["on-failure"]
    assert "run --config /etc/armbridge/armbridge.toml" in s["ExecStart"][0]


def test_the_serial_port_is_reachable_by_class_and_group():
    s = settings()
    assert s["DynamicUser"] == ["yes"]
    assert s["SupplementaryGroups"] == ["dialout"]
    assert "PrivateDevices" not in s  # it would hide the port
    allowed = {v.split()[0] for v in s["DeviceAllow"]}
    assert {"char-ttyACM", "char-ttyUSB", "char-ttyAMA", "char-ttyS"} <= allowed
    assert not any(v.startswith("/dev/") for v in allowed)  # a fixed ttyACM0 broke on ttyACM1
    assert any("modprobe@cdc_acm.service" in v for v in s["Wants"])


def test_operators_reach_the_socket_through_the_armbridge_group():
    s = settings()
    # The static group is the daemon's primary group (the socket's default group); the user's
    # name differs from it, which DynamicUser= requires when no static user of that name exists.
    assert s["Group"] == ["armbridge"] and s["User"] != ["armbridge"]
    assert s["RuntimeDirectory"] == ["armbridge"] and s["RuntimeDirectoryMode"] == ["0750"]
    assert s["UMask"] == ["0077"]
    # `run` never read ARMBRIDGE_SOCKET (only the clients do): the config's control.socket is
    # the one truth, so the unit does not pretend otherwise.
    assert not any("ARMBRIDGE_SOCKET" in v for v in s.get("Environment", []))


def test_state_cache_and_the_signing_key_credential():
    s = settings()
    assert s["StateDirectory"] == ["armbridge"] and s["CacheDirectory"] == ["armbridge"]
    assert "NUMBA_CACHE_DIR=/var/cache/armbridge" in s["Environment"]
    # The config's link.signing_key = "credential:signing.key" reads systemd's copy.
    assert s["LoadCredential"] == ["signing.key:/etc/armbridge/signing.key"]


def test_numbas_jit_is_not_forbidden_writable_executable_memory():
    # llvmlite maps code writable, then executable, even for cached kernels.
    assert settings().get("MemoryDenyWriteExecute", ["no"]) == ["no"]


@needs_analyze
def test_exposure_is_at_most_3():
    done = subprocess.run(
        [analyze, "security", "--offline=true", f"--threshold={EXPOSURE_MAX * 10:.0f}", UNIT],
        capture_output=True,
        text=True,
        timeout=30,
    )
    found = re.search(r"Overall exposure level for armbridge\.service: (\d+\.\d+)", done.stdout)
    assert found, done.stdout + done.stderr
    assert float(found.group(1)) <= EXPOSURE_MAX, done.stdout
    assert done.returncode == 0, done.stdout + done.stderr


@needs_analyze
def test_the_unit_parses():
    done = subprocess.run([analyze, "verify", UNIT], capture_output=True, text=True, timeout=30)
    # Here the package is not installed at /opt/armbridge: that complaint, and no other.
    complaints = [
        line
        for line in done.stderr.splitlines()
        if line and "/opt/armbridge/.venv/bin/armbridge is not executable" not in line
    ]
    assert complaints == [], done.stderr
