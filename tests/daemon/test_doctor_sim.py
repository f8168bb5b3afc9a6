"""``armbridge doctor`` against the simulated flight controller, a subprocess: ArduPilot's
checks pass, PX4's default setup is named with its fix."""

from __future__ import annotations

import json
import threading

import pytest

from companion.daemon.cli import main
from companion.daemon.config import parse_config
from devkit.config import write_config
from devkit.sim_process import SimProcess
from sim_servo.gcs import GroundStation

pytestmark = pytest.mark.slow

URL = {"url": "udpout:127.0.0.1:14550"}


def config(dialect="ardupilot", outputs=(9, 10, 11, 12, 13, 14), **link):
    return parse_config(
        {
            "link": {**URL, "dialect": dialect, **link},
            "control": {"socket": ""},
            "joint": [{"output": o} for o in outputs],
        }
    )


def test_doctor_against_the_simulator(tmp_path, sims, capsys):
    key = bytes(range(32))
    (tmp_path / "k.key").write_bytes(key)
    (tmp_path / "k.key").chmod(0o600)
    sim = sims(
        "--udp", "127.0.0.1:0", "--gcs", "127.0.0.1:0", "--signing-key", str(tmp_path / "k.key")
    )

    def link(run):  # a state file per run: each starts from the wall clock, as on first use
        return {
            "url": sim.url,
            "signing_key": str(tmp_path / "k.key"),
            "signing_state": str(tmp_path / f"state{run}"),
        }

    done = threading.Event()

    def ground_station() -> None:  # a ground station on its own port, as QGroundControl
        with GroundStation(sim.gcs_url, signing_key=key) as gcs:
            while not done.wait(0.2):
                gcs.heartbeat()

    thread = threading.Thread(target=ground_station, daemon=True)
    thread.start()
    try:
        motor = write_config(
            tmp_path / "motor.toml",
            {
                "link": link(1),
                "control": {"socket": str(tmp_path / "c.sock")},
                "joint": [{"output": o} for o in (1, 10, 11, 12, 13, 14)],
            },
        )
        assert main(["doctor", "--config", str(motor), "--timeout-s", "5", "--listen-s", "1"]) == 1
        out = capsys.readouterr().out
        assert "FAIL  joint 1 (q1) on output 1: SERVO1_FUNCTION = 33 (a motor)" in out, out
        assert "fix: map joint 1 to a free output" in out

        # ArduPilot's SERVOn_MIN/MAX defaults are 1100/1900: a calibration within them.
        joints = [{"output": o, "pwm_min_us": 1100, "pwm_max_us": 1900} for o in range(9, 15)]
        good = write_config(
            tmp_path / "good.toml",
            {"link": link(2), "control": {"socket": str(tmp_path / "c.sock")}, "joint": joints},
        )
        assert main(["doctor", "--config", str(good), "--json", "--listen-s", "1"]) == 0
        checks = json.loads(capsys.readouterr().out)["checks"]
        assert {c["verdict"] for c in checks} == {"PASS"}, [
            c for c in checks if c["verdict"] != "PASS"
        ]
        items = [c["item"] for c in checks]
        assert items[0] == "link" and "readback SERVO_OUTPUT_RAW" in items
        assert "signing" in items and "routing" in items
    finally:
        done.set()
        thread.join(timeout=5)


def test_doctor_names_px4s_default_setup_and_its_fix(tmp_path, capsys):
    """PX4 as it comes (arm outputs on function 0, COM_PREARM_MODE 0, TELEM2 not
    forwarding): doctor names each parameter with the value to set."""
    with SimProcess(
        tmp_path / "sim",
        "--udp",
        "127.0.0.1:0",
        "--flavour",
        "px4",
        "--param",
        "PWM_MAIN_DIS9=900",  # PX4 SITL's disarmed PWM
        ready=False,
    ) as sim:
        path = write_config(
            tmp_path / "px4.toml",
            {"link": {"url": sim.url, "dialect": "px4"}, "control": {"socket": ""}},
        )
        assert main(["doctor", "--config", str(path), "--listen-s", "0.5"]) == 1
    out = capsys.readouterr().out
    assert (
        "fix: param set PWM_MAIN_FUNC9 301" in out and "fix: param set PWM_MAIN_FUNC14 306" in out
    )
    assert "fix: param set COM_PREARM_MODE 2" in out
    assert "PWM_MAIN_DIS9 = 900, outside the calibration 1000-2000 us" in out, out
    assert "fix: param set PWM_MAIN_DIS9 1000" in out
    # Nothing heard through the autopilot: the forwarding that is off is named in the routing
    # item's fix, not a warning of its own (which instance is ours doctor cannot tell).
    assert "WARN  forwarding" not in out
    assert "WARN  routing" in out and "param set MAV_1_FORWARD 1" in out
