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
    # Never "disable the motor": the joint moves to a free output.
    assert failed[0].fix is not None and failed[0].fix.startswith("map joint 1 to a free output")
    assert "SERVO1_FUNCTION 0" not in failed[0].fix


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


def lua_check(cfg, result):
    found = Findings(
        "u", autopilot=(7, 1, ARDUPILOT[2]), params=ardupilot_params(), lua_probe=result
    )
    return {c.item: c for c in evaluate(cfg, found)}["lua bridge"]


def test_the_lua_bridges_answers_to_the_probe():
    cfg = config("ardupilot-lua")
    # The probe has no PWM: the script refuses it (FAILED), which proves it runs.
    assert lua_check(cfg, mavlink.MAV_RESULT_FAILED).verdict is Verdict.PASS
    denied = lua_check(cfg, mavlink.MAV_RESULT_DENIED)
    assert denied.verdict is Verdict.FAIL
    assert "refuses our ids 7/191" in denied.detail  # the vehicle's system id, learned
    assert denied.fix is not None
    assert "set ARMB_SYSID = 0 (the vehicle's own system id) and ARMB_COMPID = 191" in denied.fix
    own = lua_check(
        config("ardupilot-lua", system_id=200, component_id=42), mavlink.MAV_RESULT_DENIED
    )
    assert "refuses our ids 200/42" in own.detail
    assert own.fix is not None and "set ARMB_SYSID = 200 and ARMB_COMPID = 42" in own.fix


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


def px4_params(functions=None, **extra):
    """A PX4 answer: PWM_MAIN_FUNC1..16 (motors 1-4, the arm's actuator set on 9-14, the rest
    disabled, as ``functions`` overrides; None: not answered), the arm's limits 1000-2000 and
    disarmed 1500, prearm and forwarding on."""
    params: dict[str, float | None] = {"COM_PREARM_MODE": 2.0, "MAV_0_FORWARD": 1.0}
    params["MAV_1_FORWARD"] = 1.0
    defaults = {**{n: 100 + n for n in range(1, 5)}, **{n: 292 + n for n in range(9, 15)}}
    for n in range(1, 17):
        function = {**defaults, **(functions or {})}.get(n, 0)
        params[f"PWM_MAIN_FUNC{n}"] = None if function is None else float(function)
    for n in range(9, 15):
        params[f"PWM_MAIN_MIN{n}"], params[f"PWM_MAIN_MAX{n}"] = 1000.0, 2000.0
        params[f"PWM_MAIN_DIS{n}"] = 1500.0
    params.update(extra)
    return params


def test_px4_a_joint_on_a_motor_or_another_function_is_moved_never_the_function_changed():
    """Only a disabled output (or one of the arm's own actuator-set outputs) gets its function
    set; a motor, a control surface, landing gear or a constant output is the vehicle's: the
    joint moves to a free output, named with its parameter."""
    cfg = config("px4", outputs=(1, 10, 11, 12, 13, 14))
    params = px4_params({9: 0, 11: 304, 12: 400, 15: 0})
    found = Findings("u", autopilot=PX4, params=params, streams=STREAMING)
    failed = {c.item: c for c in by_verdict(evaluate(cfg, found), Verdict.FAIL)}
    motor = failed["joint 1 (q1) on output 1"]
    assert "PWM_MAIN_FUNC1 = 101 (Motor 1)" in motor.detail
    assert motor.fix is not None and "PWM_MAIN_FUNC1 " not in motor.fix
    assert "joint.output = 5" in motor.fix and "param set PWM_MAIN_FUNC5 301" in motor.fix
    assert "free (function 0): 5, 6, 7, 8, 9, 15, 16" in motor.fix
    # Another of the arm's actuator-set functions: ours, set to this joint's.
    assert failed["joint 3 (q3) on output 11"].fix == "param set PWM_MAIN_FUNC11 303"
    gear = failed["joint 4 (q4) on output 12"]
    assert "PWM_MAIN_FUNC12 = 400 (Landing Gear)" in gear.detail
    assert gear.fix is not None and "PWM_MAIN_FUNC12 " not in gear.fix
    # The next free output, not the one offered to joint 1.
    assert "joint.output = 6" in gear.fix and "param set PWM_MAIN_FUNC6 304" in gear.fix
    assert len(failed) == 3
    # A board with an IO processor: output 9 is PWM_AUX_FUNC1, a control surface there.
    aux = {f"PWM_MAIN_FUNC{n}": None for n in range(9, 17)}
    functions = [201, 302, 303, 304, 305, 306, 0, 0]
    aux |= {f"PWM_AUX_FUNC{k}": float(f) for k, f in enumerate(functions, 1)}
    io = Findings("u", autopilot=PX4, params=px4_params(**aux), streams=STREAMING)
    servo = {c.item: c for c in evaluate(config("px4"), io)}
    surface = servo["joint 1 (q1) on output 9"]
    assert surface.verdict is Verdict.FAIL and "PWM_AUX_FUNC1 = 201 (Servo 1)" in surface.detail
    assert surface.fix is not None and "PWM_AUX_FUNC1 " not in surface.fix
    assert "joint.output = 5" in surface.fix and "8, 15, 16" in surface.fix
    # Nothing free that doctor read: the fix says what to look for.
    busy = px4_params({n: 1 for n in (5, 6, 7, 8, 9, 15, 16)})
    full = Findings("u", autopilot=PX4, params=busy, streams=STREAMING)
    none_free = {c.item: c for c in evaluate(cfg, full)}
    fix = none_free["joint 1 (q1) on output 1"].fix
    assert fix is not None and "PWM_MAIN_FUNC1 " not in fix and "function is 0" in fix


def test_px4_forwarding_seen_working_is_not_doubted_from_its_parameters():
    """SITL starts its MAVLink instances with forwarding (``-f``) whatever MAV_n_FORWARD say,
    and doctor cannot tell which instance its link is: frames of another system heard here show
    forwarding works; without them the parameters are only a hint in the routing item."""
    cfg = config("px4")
    params = px4_params(MAV_1_FORWARD=0.0)
    for heard in ({"ground_stations": {(255, 190)}}, {"others": {(2, 1)}}):
        found = Findings("u", autopilot=PX4, params=params, streams=STREAMING, **heard)
        checks = {c.item: c for c in evaluate(cfg, found)}
        assert checks["forwarding"].verdict is Verdict.PASS, checks["forwarding"]
        assert "MAV_1_FORWARD = 0" in checks["forwarding"].detail
    silent = Findings("u", autopilot=PX4, params=params, streams=STREAMING, listened_s=3.0)
    checks = evaluate(cfg, silent)
    assert "forwarding" not in {c.item for c in checks}
    routing = {c.item: c for c in checks}["routing"]
    assert routing.verdict is Verdict.WARN
    assert routing.fix is not None and "param set MAV_1_FORWARD 1" in routing.fix
    assert "reboot" in routing.fix


def test_px4_limits_that_do_not_exist_are_named_with_what_the_outputs_do_instead():
    """A build without per-output limits: PX4 uses its built-in 1000-2000 us and a disarmed
    900 us (SITL's), which is outside a 1000-2000 calibration: the joint goes there."""
    missing = {f"PWM_MAIN_{p}{n}": None for p in ("MIN", "MAX", "DIS") for n in range(9, 15)}
    found = Findings("u", autopilot=PX4, params=px4_params(**missing), streams=STREAMING)
    checks = {c.item: c for c in evaluate(config("px4"), found)}
    limits = checks["joint 1 (q1) on output 9 range"]
    assert limits.verdict is Verdict.PASS
    assert "PWM_MAIN_MIN9, PWM_MAIN_MAX9 not answered" in limits.detail
    assert "1000-2000" in limits.detail
    disarmed = checks["joint 1 (q1) on output 9 disarmed"]
    assert disarmed.verdict is Verdict.WARN
    assert "PWM_MAIN_DIS9 not answered" in disarmed.detail and "900 us" in disarmed.detail
    assert disarmed.fix is not None and "param set PWM_MAIN_DIS9 1000" in disarmed.fix
    narrow = parse_config(
        {
            "link": {**URL, "dialect": "px4"},
            "arm": {"park_deg": [0, 90, 0, 0, 0, 0]},
            "control": {"socket": ""},
            "joint": [{"output": o, "pwm_min_us": 1100, "pwm_max_us": 1900} for o in range(9, 15)],
        }
    )
    park = narrow.calibration.angles_to_pwm_us(narrow.park_deg)
    checks = {c.item: c for c in evaluate(narrow, found)}
    assert checks["joint 2 (q2) on output 10 range"].verdict is Verdict.FAIL
    assert "1000-2000" in checks["joint 2 (q2) on output 10 range"].detail
    assert f"param set PWM_MAIN_DIS10 {park[10]}" in (
        checks["joint 2 (q2) on output 10 disarmed"].fix or ""
    )
    # Newer PX4 SITL has the parameters, and PWM_MAIN_DISn is 900 there: the same finding.
    sitl = px4_params(**{f"PWM_MAIN_DIS{n}": 900.0 for n in range(9, 15)})
    found = Findings("u", autopilot=PX4, params=sitl, streams=STREAMING)
    disarmed = {c.item: c for c in evaluate(narrow, found)}["joint 3 (q3) on output 11 disarmed"]
    assert disarmed.verdict is Verdict.WARN and "900" in disarmed.detail
    assert disarmed.fix == f"param set PWM_MAIN_DIS11 {park[11]}"


def test_heartbeats_of_other_systems_are_noted_as_forwarded_to_us():
    from companion.daemon.doctor import _note

    encoder = mavlink.MAVLink(None)

    def heartbeat(system, component, kind=mavlink.MAV_TYPE_ONBOARD_CONTROLLER):
        encoder.srcSystem, encoder.srcComponent = system, component
        msg = encoder.heartbeat_encode(kind, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0)
        msg.pack(encoder)
        return mavlink.MAVLink(None).decode(msg.get_msgbuf())

    found = Findings("u", autopilot=PX4)
    for msg in (
        heartbeat(255, 190, mavlink.MAV_TYPE_GCS),
        heartbeat(2, 1, mavlink.MAV_TYPE_QUADROTOR),
        heartbeat(1, 100),  # a camera of the autopilot's own system: not evidence
        heartbeat(1, 1, mavlink.MAV_TYPE_QUADROTOR),
    ):
        _note(msg, found)
    assert found.ground_stations == {(255, 190)}
    assert found.others == {(255, 190), (2, 1)}
