"""The systemd unit file carries what the daemon relies on."""

from __future__ import annotations

from pathlib import Path

UNIT = Path(__file__).resolve().parents[2] / "packaging" / "armbridge.service"


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
    assert "run --config" in s["ExecStart"][0]


def test_unit_sandboxing_keeps_the_serial_port_reachable():
    s = settings()
    assert s["DynamicUser"] == ["yes"]
    assert s["SupplementaryGroups"] == ["dialout"]
    assert any(v.startswith("/dev/") for v in s["DeviceAllow"])
    assert "PrivateDevices" not in s
    assert s["StateDirectory"] == ["armbridge"]
    assert "NUMBA_CACHE_DIR=/var/cache/armbridge" in s["Environment"]
