"""``armbridge doctor``: the verdicts from what the autopilot said (pure): a joint on a motor
output is named with the parameter to change; a correct setup passes every item. Against the
simulator: ``test_doctor_sim.py``."""

from __future__ import annotations

import dataclasses
import json

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from companion.daemon.cli import main
from companion.daemon.config import parse_config
from companion.daemon.doctor import Findings, Verdict, evaluate, param_names

URL = {"url": "udpout:127.0.0.1:14550"}
ARDUPILOT = (1, 1, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA)
PX4 = (1, 1, mavlink.MAV_AUTOPILOT_PX4)


def config(dialect="ardupilot", outputs=(9, 10, 11, 12, 13, 14), **link):
    return parse_config(
        {
            "link": {**URL, "dialect": dialect, **link},
            "control": {"socket": ""},
            "joint": [{"output": o} for o in outputs],
        }
    )


def ardupilot_params(functions=None, low=1000, high=2000):
    params = {}
    for n in range(1, 17):
        params[f"SERVO{n}_FUNCTION"] = float((functions or {}).get(n, 33 if n <= 4 else 0))
        params[f"SERVO{n}_MIN"], params[f"SERVO{n}_MAX"] = float(low), float(high)
    return params


STREAMING = {"SERVO_OUTPUT_RAW": (0, True), "ACTUATOR_OUTPUT_STATUS": (0, True)}


def by_verdict(checks, verdict):
    return [c for c in checks if c.verdict is verdict]


def test_a_joint_on_a_motor_output_fails_naming_the_parameter_and_the_fix():
    cfg = config(outputs=(1, 10, 11, 12, 13, 14))
    found = Findings("u", autopilot=ARDUPILOT, params=ardupilot_params(), streams=STREAMING)
    failed = by_verdict(evaluate(cfg, found), Verdict.FAIL)
    assert [c.item for c in failed] == ["joint 1 (q1) on output 1"]
    assert "SERVO1_FUNCTION = 33 (a motor)" in failed[0].detail
    assert failed[0].fix is not None and failed[0].fix.startswith("param set SERVO1_FUNCTION 0")


def test_ardupilot_rc_passthrough_and_a_narrow_range_are_warnings():
    params = ardupilot_params({9: 1}, low=1100, high=1900)
    found = Findings("u", autopilot=ARDUPILOT, params=params, streams=STREAMING)
    checks = evaluate(config(), found)
    warned = {c.item: c for c in by_verdict(checks, Verdict.WARN)}
    assert "RC pass-through" in warned["joint 1 (q1) on output 9"].detail
    assert warned["joint 2 (q2) on output 10 range"].fix == (
        "param set SERVO10_MIN 1000; param set SERVO10_MAX 2000"
    )
    assert not by_verdict(checks, Verdict.FAIL)


def test_px4_functions_must_be_the_actuator_set_in_joint_order_and_limits_the_calibration():
    cfg = config("px4")
    params: dict[str, float | None] = {name: None for name in param_names(cfg, "px4")}
    for k, n in enumerate(range(9, 15)):
        params[f"PWM_MAIN_FUNC{n}"] = float(301 + k)
        params[f"PWM_MAIN_MIN{n}"], params[f"PWM_MAIN_MAX{n}"] = 1000.0, 2000.0
    params["PWM_MAIN_FUNC10"] = 0.0  # PX4's default: unmapped
    params["PWM_MAIN_MIN12"] = 1100.0
    found = Findings("u", autopilot=PX4, params=params, streams=STREAMING)
    failed = {c.item: c for c in by_verdict(evaluate(cfg, found), Verdict.FAIL)}
    assert failed["joint 2 (q2) on output 10"].fix == "param set PWM_MAIN_FUNC10 302"
    assert failed["joint 4 (q4) on output 12 range"].fix == (
        "param set PWM_MAIN_MIN12 1000; param set PWM_MAIN_MAX12 2000"
    )
    assert len(failed) == 2


def test_no_autopilot_and_a_wrong_dialect_fail_first():
    silent = evaluate(config(), Findings("udpout:x:1", listened_s=10.0))
    assert [(c.item, c.verdict) for c in silent] == [("link", Verdict.FAIL)]
    assert "no autopilot HEARTBEAT on udpout:x:1 in 10 s" in silent[0].detail
    wrong = evaluate(config("px4"), Findings("u", autopilot=ARDUPILOT, params={}))
    assert wrong[-1].item == "dialect" and wrong[-1].fix == 'set link.dialect = "ardupilot"'


def test_an_autopilot_signing_from_the_future_fails_signing_with_the_fix_not_the_link():
    # Its HEARTBEAT is refused, so no autopilot is heard: the cause is the clock, not the cable.
    problem = "the autopilot 1/1 signs 7.0 days ahead of our clock (...)"
    found = Findings("u", listened_s=10.0, signing_rejections=12, signing_problem=problem)
    [check] = evaluate(config(), found)
    assert (check.item, check.verdict, check.detail) == ("signing", Verdict.FAIL, problem)
    assert check.fix is not None and "SETUP_SIGNING" in check.fix and "set it" in check.fix


def test_the_lua_bridge_and_a_serial_links_budget_are_checked():
    cfg = config("ardupilot-lua", url="/dev/ttyAMA0,57600")
    params = ardupilot_params()
    answered = Findings("u", autopilot=ARDUPILOT, params=params, streams=STREAMING, lua_probe=0)
    checks = {c.item: c for c in evaluate(cfg, answered)}
    assert checks["lua bridge"].verdict is Verdict.PASS
    assert checks["link budget"].verdict is Verdict.PASS  # one 44 B frame fits 20 Hz at 57 600
    unsupported = dataclasses.replace(answered, lua_probe=mavlink.MAV_RESULT_UNSUPPORTED)
    lua = {c.item: c for c in evaluate(cfg, unsupported)}["lua bridge"]
    assert lua.verdict is Verdict.FAIL and "UNSUPPORTED" in lua.detail
    assert lua.fix is not None and "SCR_ENABLE = 1" in lua.fix
    six = config(
        "ardupilot",
        url="/dev/ttyAMA0,57600",
    )
    slow = {c.item: c for c in evaluate(six, answered)}  # 264 B at 20 Hz do not fit 57 600
    assert (
        slow["link budget"].verdict is Verdict.WARN and "ardupilot-lua" in slow["link budget"].fix
    )
    udp = {c.item for c in evaluate(config(), answered)}
    assert "link budget" not in udp and "lua bridge" not in udp


def test_a_correct_px4_setup_passes_the_vehicle_checks():
    cfg = parse_config(
        {
            "link": {**URL, "dialect": "px4"},
            "arm": {"park_deg": [0, 90, 0, 0, 0, 0]},
            "control": {"socket": ""},
        }
    )
    park = cfg.calibration.angles_to_pwm_us(cfg.park_deg)
    params: dict[str, float | None] = {"COM_PREARM_MODE": 2.0, "MAV_0_FORWARD": 1.0}
    params["MAV_1_FORWARD"] = 1.0
    for k, n in enumerate(range(9, 15)):
        params[f"PWM_MAIN_FUNC{n}"] = float(301 + k)
        params[f"PWM_MAIN_MIN{n}"], params[f"PWM_MAIN_MAX{n}"] = 1000.0, 2000.0
        params[f"PWM_MAIN_DIS{n}"] = float(park[n])
    found = Findings("u", autopilot=PX4, params=params, streams=STREAMING)
    checks = evaluate(cfg, found)
    assert {c.item: c.verdict for c in checks if c.verdict is not Verdict.PASS} == {
        "signing": Verdict.WARN,
        "routing": Verdict.WARN,
    }
    assert "joint 1 (q1) on output 9 disarmed" in {c.item for c in checks}


def _closed_tcp_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]  # closed again on exit: a connect is refused


@pytest.mark.parametrize("json_out", [False, True])
@pytest.mark.parametrize(
    "url, fix",
    [
        ("{tmp}/ttyNOPE,57600", "is the flight controller plugged in"),
        ("tcp:127.0.0.1:{port}", "listening on 127.0.0.1:"),
    ],
)
def test_a_link_that_cannot_be_opened_is_a_finding_with_its_fix(
    tmp_path, capsys, url, fix, json_out
):
    url = url.format(tmp=tmp_path, port=_closed_tcp_port())
    path = tmp_path / "armbridge.toml"
    path.write_text(
        f'[link]\nurl = "{url}"\ndialect = "ardupilot"\n[control]\nsocket = ""\n',
        encoding="utf-8",
    )
    argv = ["doctor", "--config", str(path), "--timeout-s", "1", "--listen-s", "0.1"]
    assert main([*argv, "--json"] if json_out else argv) == 1
    out = capsys.readouterr().out
    if json_out:
        (check,) = json.loads(out)["checks"]
        assert check["item"] == "link" and check["verdict"] == "FAIL"
        assert fix in check["fix"]
    else:
        assert "FAIL  link: cannot" in out and fix in out
