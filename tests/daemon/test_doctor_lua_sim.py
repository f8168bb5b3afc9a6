"""``armbridge doctor`` probing the Lua bridge of the simulated flight controller (``--lua-script``,
which answers as the shipped script): the probe goes out with the daemon's own ids, so a script
that obeys them passes, and one that obeys another sender is named with the parameters to set."""

from __future__ import annotations

import json

import pytest

from companion.daemon.cli import main
from devkit.config import write_config

pytestmark = pytest.mark.slow


def lua_check(tmp_path, capsys, url: str, name: str, **link) -> dict:
    path = write_config(
        tmp_path / f"{name}.toml",
        {
            "link": {"url": url, "dialect": "ardupilot-lua", **link},
            "control": {"socket": ""},
        },
    )
    main(["doctor", "--config", str(path), "--json", "--listen-s", "0.5"])
    checks = json.loads(capsys.readouterr().out)["checks"]
    return next(c for c in checks if c["item"] == "lua bridge")


def test_doctor_probes_the_lua_bridge_as_the_daemon(tmp_path, sims, capsys):
    sim = sims("--udp", "127.0.0.1:0", "--lua-script")
    ours = lua_check(tmp_path, capsys, sim.url, "default")  # 1/191, the script's default
    assert ours["verdict"] == "PASS", ours
    other = lua_check(tmp_path, capsys, sim.url, "other", component_id=195)
    assert other["verdict"] == "FAIL", other
    assert "refuses our ids 1/195 (DENIED)" in other["detail"]
    assert "set ARMB_SYSID = 0 (the vehicle's own system id) and ARMB_COMPID = 195" in other["fix"]
