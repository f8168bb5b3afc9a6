"""``armbridge doctor``: a preflight of the flight controller against the config, item by item,
each failure with the exact fix.

It opens the configured link itself (the service must be stopped: a serial port has one reader;
the instance lock tells), waits for the autopilot, then:

* **outputs**: for each joint, the output's function parameter, read with PARAM_REQUEST_READ —
  ArduPilot ``SERVOn_FUNCTION`` must be 0 (DO_SET_SERVO is refused on any other function but RC
  pass-through, 1 and 51–66, which the RC input then fights); PX4 ``PWM_MAIN_FUNCn`` (or
  ``PWM_AUX_FUNCn`` on boards with an IO processor) must be 301–306 "Peripheral via Actuator Set
  k" in joint order. On PX4 only a disabled output (0) or one of the actuator-set functions gets
  its function set; any other (a motor 101–112, a servo 201+, landing gear, a constant output,
  ...) is the vehicle's: the joint moves to a free output, one of those read as 0 (every
  output's function is read for that), and the vehicle's function stays.
* **limits**: the PWM limits against the calibration: PX4 maps −1…1 onto
  ``PWM_MAIN_MINn``…``PWM_MAIN_MAXn``, so they must equal the joint's
  ``pwm_min_us``/``pwm_max_us``; ArduPilot does not clamp DO_SET_SERVO, but its own outputs
  (trim at boot, failsafe) use ``SERVOn_MIN``/``MAX``, so the calibration should lie within
  them (a warning). PX4's ``PWM_MAIN_DISn`` is where a joint goes whenever the outputs are not
  live (boot, disarm, kill): the park PWM, or at least within the calibration. A build without
  these parameters for an output (some SITL builds: never answered) uses its output driver's
  own, 1000–2000 µs and disarmed 900 µs on PX4 SITL: doctor names the missing ones and judges
  those values instead.
* **forwarding** (PX4): a frame passes only from an instance that forwards to one that forwards
  (``MAV_n_FORWARD``). Doctor cannot tell which instance its link is (a serial port is named on
  the autopilot's side; SITL starts its instances with forwarding whatever the parameters say),
  so a HEARTBEAT of another system heard here shows forwarding works and the parameters are not
  doubted; without one, the ones that are off are named in the routing item's fix, never a
  warning of their own.
* **readback**: SERVO_OUTPUT_RAW (and PX4's ACTUATOR_OUTPUT_STATUS) can be streamed: asked with
  MAV_CMD_SET_MESSAGE_INTERVAL, acknowledged, and seen; set back to the default rate after.
* **signing**: off (a warning: anyone on the link may move the arm), or on and the autopilot's
  frames verify and it answers our signed requests.
* **routing**: a ground station heard here through the autopilot (a warning when none is: it may
  simply be off). A USER_1 we sent ourselves cannot prove the route: ArduPilot never forwards a
  frame back out of the link it came in on; the ground station's HEARTBEAT arriving here does
  prove its frames reach us.

The verdicts are computed by :func:`evaluate` from :class:`Findings` (pure: tested without a
link); :func:`gather` does the talking. Exit codes (``armbridge doctor``): 0 nothing failed
(warnings allowed), 1 an item failed, 2 a bad config, 3 the service holds the link.
"""

from __future__ import annotations

import enum
import math
import struct
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from companion.daemon.config import DaemonConfig, link_budget_of, link_config
from firmware_interface import JointCalibration, LinkConfig, LinkError, MavlinkLink
from firmware_interface.errors import InvalidUrl
from firmware_interface.link import MessageQueue
from firmware_interface.lua_bridge import MAV_CMD_USER_2, sender_fix
from firmware_interface.signing import LOCKOUT_FIX
from firmware_interface.transport import parse_url

__all__ = ["Check", "Findings", "Verdict", "evaluate", "gather", "format_report", "param_names"]

#: MAV_CMD_DO_SET_SERVO works on these ArduPilot output functions (AP_ServoRelayEvents.cpp).
ARDUPILOT_SERVO_FUNCTIONS = frozenset({0, 1, *range(51, 67)})
PX4_FIRST_ACTUATOR_FUNCTION = 301
PX4_ACTUATOR_SET_SIZE = 6
PX4_ACTUATOR_FUNCTIONS = range(
    PX4_FIRST_ACTUATOR_FUNCTION, PX4_FIRST_ACTUATOR_FUNCTION + PX4_ACTUATOR_SET_SIZE
)
#: PX4 output functions (``PWM_MAIN_FUNCn``; src/lib/mixer_module/output_functions.yaml).
PX4_FUNCTION_NAMES = {
    0: "Disabled",
    1: "Constant Min",
    2: "Constant Max",
    400: "Landing Gear",
    401: "Parachute",
    402: "RC Roll",
    403: "RC Pitch",
    404: "RC Throttle",
    405: "RC Yaw",
    406: "RC Flaps",
    420: "Gimbal Roll",
    421: "Gimbal Pitch",
    422: "Gimbal Yaw",
    430: "Gripper",
    440: "Landing Gear Wheel",
}
#: Numbered PX4 functions: (first, last, name); the number is the function's minus first, plus 1.
PX4_FUNCTION_RANGES = (
    (101, 112, "Motor"),
    (201, 215, "Servo"),
    (301, 306, "Peripheral via Actuator Set"),
    (407, 412, "RC AUX"),
    (2000, 2031, "Camera Trigger"),
    (2032, 2063, "Camera Capture"),
    (2064, 2095, "PPS Input"),
)
#: PX4's output driver's own range and disarmed PWM (µs), for a build without
#: ``PWM_MAIN_MINn``/``MAXn``/``DISn``: PX4 SITL's (pwm_out_sim: 1000–2000, disarmed 900,
#: as measured on SITL).
PX4_BUILTIN_PWM_US = (1000, 2000)
PX4_BUILTIN_DISARMED_US = 900
#: The outputs whose function doctor reads on PX4 (SITL and FMU boards: PWM_MAIN_FUNC1..16;
#: boards with an IO processor: PWM_MAIN_FUNC1..8 and PWM_AUX_FUNC1..8).
PX4_SCANNED_OUTPUTS = 16
#: Readback streams doctor asks for, per autopilot.
READBACK = {
    "ardupilot": ("SERVO_OUTPUT_RAW",),
    "px4": ("SERVO_OUTPUT_RAW", "ACTUATOR_OUTPUT_STATUS"),
}
STREAM_IDS = {
    "SERVO_OUTPUT_RAW": mavlink.MAVLINK_MSG_ID_SERVO_OUTPUT_RAW,
    "ACTUATOR_OUTPUT_STATUS": mavlink.MAVLINK_MSG_ID_ACTUATOR_OUTPUT_STATUS,
}
STREAM_RATE_HZ = 10.0


class Verdict(enum.Enum):
    PASS = "PASS"
    WARN = "WARN"
    FAIL = "FAIL"
    SKIP = "SKIP"


@dataclass(frozen=True)
class Check:
    """One item: what was checked, the verdict, what was found and (unless it passed) the fix."""

    item: str
    verdict: Verdict
    detail: str
    fix: str | None = None

    def as_dict(self) -> dict[str, Any]:
        return {
            "item": self.item,
            "verdict": self.verdict.value,
            "detail": self.detail,
            "fix": self.fix,
        }


@dataclass
class Findings:
    """What :func:`gather` read from the autopilot (every field may be missing)."""

    url: str
    #: ``(system, component, MAV_AUTOPILOT)`` of the autopilot heard, or None.
    autopilot: tuple[int, int, int] | None = None
    heard_after_s: float | None = None
    #: Parameter name → value (None: asked, never answered: no such parameter, or lost).
    params: dict[str, float | None] = field(default_factory=dict)
    #: Stream name → (MAV_RESULT of the interval request or None, seen after it).
    streams: dict[str, tuple[int | None, bool]] = field(default_factory=dict)
    #: ``(system, component)`` of ground stations heard through the autopilot.
    ground_stations: set[tuple[int, int]] = field(default_factory=set)
    #: ``(system, component)`` of HEARTBEATs of other systems than the autopilot's (and ours)
    #: heard here: frames the autopilot forwarded to this link (or a router in between sent).
    others: set[tuple[int, int]] = field(default_factory=set)
    #: ardupilot-lua: the MAV_RESULT the bridge script's probe got (None: no answer).
    lua_probe: int | None = None
    signing_on: bool = False
    #: Signed frames refused (bad signature, replayed, future): from anyone, the autopilot or
    #: others routed through it.
    signing_rejections: int = 0
    #: The autopilot signs far ahead of our clock (``MavlinkLink.signing_problem``), or None.
    signing_problem: str | None = None
    listened_s: float = 0.0
    #: Why the link could not be opened (None: it was): nothing else was read.
    open_error: str | None = None


def flavour(findings: Findings) -> str | None:
    if findings.autopilot is None:
        return None
    kind = findings.autopilot[2]
    if kind == mavlink.MAV_AUTOPILOT_PX4:
        return "px4"
    if kind == mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA:
        return "ardupilot"
    return "other"


def param_names(config: DaemonConfig, autopilot: str) -> list[str]:
    """Every parameter :func:`evaluate` reads for ``autopilot`` ("ardupilot" or "px4")."""
    names: list[str] = []
    for joint in config.calibration.joints:
        n = joint.output
        if autopilot == "ardupilot":
            names += [f"SERVO{n}_FUNCTION", f"SERVO{n}_MIN", f"SERVO{n}_MAX"]
        else:
            for prefix in _px4_prefixes(n):
                i = _px4_index(prefix, n)
                names += [f"{prefix}_{p}{i}" for p in ("FUNC", "MIN", "MAX", "DIS")]
    if autopilot == "px4":
        # Every output's function: where a joint sits on the vehicle's, the free ones to offer.
        for n in range(1, PX4_SCANNED_OUTPUTS + 1):
            names += [f"{prefix}_FUNC{_px4_index(prefix, n)}" for prefix in _px4_prefixes(n)]
    names += _VEHICLE_PARAMS[autopilot]
    return names


#: PX4's MAVLink forwarding on the first instances (TELEM1, TELEM2: ours is likely one of them).
_PX4_FORWARD_PARAMS = ("MAV_0_FORWARD", "MAV_1_FORWARD")
#: The vehicle-wide parameters read: ArduPilot's safety switch; PX4's prearm mode and forwarding.
_VEHICLE_PARAMS = {
    "ardupilot": ["BRD_SAFETY_DEFLT", "BRD_SAFETY_MASK"],
    "px4": ["COM_PREARM_MODE", *_PX4_FORWARD_PARAMS],
}


def _px4_prefixes(output: int) -> tuple[str, ...]:
    """PX4 names output n ``PWM_MAIN_*n`` (SITL and FMU-only boards: 1–16); boards with an IO
    processor have 8 MAIN and the FMU's as ``PWM_AUX_*1..8``."""
    return ("PWM_MAIN", "PWM_AUX") if output > 8 else ("PWM_MAIN",)


def _px4_index(prefix: str, output: int) -> int:
    return output - 8 if prefix == "PWM_AUX" else output


def evaluate(config: DaemonConfig, findings: Findings) -> list[Check]:
    """The verdicts, item by item, from what was found."""
    checks: list[Check] = []
    kind = flavour(findings)
    if findings.open_error is not None:
        checks.append(Check("link", Verdict.FAIL, findings.open_error, _open_fix(findings.url)))
        return checks
    if findings.autopilot is None and findings.signing_problem is not None:
        checks.append(_signing_clock(findings.signing_problem))
        return checks
    if findings.autopilot is None:
        refused = (
            f" ({findings.signing_rejections} signed frames refused: the same key on both "
            "ends? MAVProxy: signing setup KEY)"
            if findings.signing_rejections
            else ""
        )
        checks.append(
            Check(
                "link",
                Verdict.FAIL,
                f"no autopilot HEARTBEAT on {findings.url} in {findings.listened_s:.0f} s"
                + refused,
                "check the cable, the port and baud in link.url, and that the flight controller "
                "sends MAVLink on that port (ArduPilot SERIALn_PROTOCOL = 2; PX4 MAV_n_CONFIG)",
            )
        )
        return checks
    system, component, _ = findings.autopilot
    name = {"px4": "PX4", "ardupilot": "ArduPilot"}.get(
        kind or "", f"autopilot type {findings.autopilot[2]}"
    )
    checks.append(
        Check(
            "link",
            Verdict.PASS,
            f"{name} {system}/{component} heard after {findings.heard_after_s or 0:.1f} s",
        )
    )
    dialect = config.link.dialect
    if kind == "other" or (kind is not None and not dialect.startswith(kind)):
        checks.append(
            Check(
                "dialect",
                Verdict.FAIL,
                f'link.dialect = "{dialect}" but the autopilot is {name}',
                f'set link.dialect = "{kind}"'
                if kind != "other"
                else "armbridge supports ArduPilot and PX4",
            )
        )
        return checks
    if kind == "ardupilot":
        checks += _ardupilot_outputs(config, findings.params)
        checks += _ardupilot_safety(config, findings.params)
    else:
        checks += _px4_outputs(config, findings.params)
        checks += _px4_vehicle(config, findings.params)
        checks += _px4_forwarding(findings)
    checks += _streams(findings, kind or "ardupilot")
    if dialect == "ardupilot-lua":
        checks.append(_lua_script(config, findings))
    budget = _link_budget(config)
    if budget is not None:
        checks.append(budget)
    checks.append(_signing(config, findings))
    checks.append(_routing(findings, kind))
    return checks


def _open_fix(url: str) -> str:
    """What to do when ``link.url`` could not be opened, by its kind."""
    try:
        spec = parse_url(url)
    except InvalidUrl as exc:  # check-config refuses it first; stay safe
        return str(exc)
    if spec.kind == "serial":
        return (
            f"is the flight controller plugged in and is {spec.address} its port? "
            "(ls -l /dev/serial/by-id/; the user needs the dialout group; nothing else may "
            "hold the port, e.g. ModemManager or a ground station)"
        )
    if spec.kind == "tcp":
        return (
            f"is the autopilot (or SITL) listening on {spec.address}:{spec.port}? Check the "
            "host and port in link.url"
        )
    if spec.kind == "udpin":
        return (
            f"{spec.address}:{spec.port} cannot be listened on: another program holds the port "
            "(the daemon, MAVProxy, mavlink-router), or the host is not an address of this "
            "machine (udpin:0.0.0.0:PORT listens on every interface)"
        )
    return f"check the host and port in link.url ({url})"


def _joint_label(index: int, name: str, output: int) -> str:
    return f"joint {index + 1} ({name}) on output {output}"


def _value(params: dict[str, float | None], key: str) -> int | None:
    value = params.get(key)
    return None if value is None or not math.isfinite(value) else round(value)


def _ardupilot_outputs(config: DaemonConfig, params: dict[str, float | None]) -> list[Check]:
    checks = []
    for index, joint in enumerate(config.calibration.joints):
        n = joint.output
        label = _joint_label(index, joint.name, n)
        function = _value(params, f"SERVO{n}_FUNCTION")
        if function is None:
            checks.append(
                Check(
                    label,
                    Verdict.FAIL,
                    f"SERVO{n}_FUNCTION not answered",
                    "check the output number",
                )
            )
            continue
        if function == 0:
            checks.append(Check(label, Verdict.PASS, f"SERVO{n}_FUNCTION = 0 (disabled: ours)"))
        elif function in ARDUPILOT_SERVO_FUNCTIONS:
            checks.append(
                Check(
                    label,
                    Verdict.WARN,
                    f"SERVO{n}_FUNCTION = {function} (RC pass-through): the RC input moves it too",
                    f"param set SERVO{n}_FUNCTION 0",
                )
            )
        else:
            what = " (a motor)" if 33 <= function <= 40 or 82 <= function <= 85 else ""
            checks.append(
                Check(
                    label,
                    Verdict.FAIL,
                    f"SERVO{n}_FUNCTION = {function}{what}: ArduPilot refuses DO_SET_SERVO on it "
                    f'("ServoRelayEvent: Channel {n} is already in use")',
                    f"map joint {index + 1} to a free output (joint.output = an output whose "
                    "SERVOn_FUNCTION is 0); leave this output's function as it is"
                    + (
                        ""
                        if what
                        else f" unless nothing on the vehicle uses it (then SERVO{n}_FUNCTION 0)"
                    ),
                )
            )
        low, high = _value(params, f"SERVO{n}_MIN"), _value(params, f"SERVO{n}_MAX")
        pwm = (joint.pwm_min_us, joint.pwm_max_us)
        if low is None or high is None:
            continue
        if low <= min(pwm) and max(pwm) <= high:
            checks.append(
                Check(
                    f"{label} range",
                    Verdict.PASS,
                    f"{min(pwm)}-{max(pwm)} us within SERVO{n}_MIN/MAX {low}-{high}",
                )
            )
        else:
            checks.append(
                Check(
                    f"{label} range",
                    Verdict.WARN,
                    f"calibration {min(pwm)}-{max(pwm)} us outside SERVO{n}_MIN/MAX {low}-{high} "
                    "(DO_SET_SERVO is not clamped, but the autopilot's own outputs use these)",
                    f"param set SERVO{n}_MIN {min(pwm)}; param set SERVO{n}_MAX {max(pwm)}",
                )
            )
    return checks


def _px4_function_name(function: int) -> str:
    """PX4's name for an output function: "Motor 1", "Servo 3", "Landing Gear"."""
    name = PX4_FUNCTION_NAMES.get(function)
    if name is not None:
        return name
    for first, last, stem in PX4_FUNCTION_RANGES:
        if first <= function <= last:
            return f"{stem} {function - first + 1}"
    return "unknown to doctor"


def _px4_prefix(params: dict[str, float | None], output: int) -> str | None:
    """The prefix of the output's parameters, the one whose function was answered: PWM_MAIN,
    or for outputs 9-16 on a board with an IO processor PWM_AUX; None: neither was."""
    for prefix in _px4_prefixes(output):
        if _value(params, f"{prefix}_FUNC{_px4_index(prefix, output)}") is not None:
            return prefix
    return None


def _px4_param(prefix: str, kind: str, output: int) -> str:
    """``_px4_param("PWM_AUX", "DIS", 9)`` → PWM_AUX_DIS1."""
    return f"{prefix}_{kind}{_px4_index(prefix, output)}"


def _px4_vehicles(params: dict[str, float | None], output: int) -> bool:
    """Whether the output's function was read and is neither 0 nor an actuator-set function:
    the vehicle's (a motor, a control surface, ...), whose limits and disarmed PWM are its own."""
    prefix = _px4_prefix(params, output)
    if prefix is None:
        return False
    function = _value(params, _px4_param(prefix, "FUNC", output))
    return function not in (0, *PX4_ACTUATOR_FUNCTIONS)


def _px4_free_outputs(config: DaemonConfig, params: dict[str, float | None]) -> list[int]:
    """Outputs no joint uses whose function was read as 0 (Disabled), lowest first."""
    used = set(config.calibration.outputs)
    free = []
    for n in range(1, max(PX4_SCANNED_OUTPUTS, *used) + 1):
        prefix = _px4_prefix(params, n)
        if (
            n not in used
            and prefix is not None
            and _value(params, _px4_param(prefix, "FUNC", n)) == 0
        ):
            free.append(n)
    return free


def _px4_outputs(config: DaemonConfig, params: dict[str, float | None]) -> list[Check]:
    """Joint k must sit on an output of function 300 + k ("Peripheral via Actuator Set k").
    A disabled output (0), or one of the actuator-set functions (the daemon's: it sends all six
    slots in each update), gets the function set. Any other function is the vehicle's (a motor,
    a control surface, landing gear, a constant output, ...): the joint moves to a free output
    (function 0, named when doctor read one), the output's function is never changed."""
    checks = []
    free = _px4_free_outputs(config, params)
    for index, joint in enumerate(config.calibration.joints):
        n = joint.output
        label = _joint_label(index, joint.name, n)
        prefix = _px4_prefix(params, n)
        if prefix is None:
            names = " or ".join(_px4_param(p, "FUNC", n) for p in _px4_prefixes(n))
            checks.append(
                Check(label, Verdict.FAIL, f"{names} not answered", "check the output number")
            )
            continue
        func_name = _px4_param(prefix, "FUNC", n)
        function = _value(params, func_name)
        want = PX4_FIRST_ACTUATOR_FUNCTION + index
        if index >= PX4_ACTUATOR_SET_SIZE:
            checks.append(
                Check(
                    label,
                    Verdict.FAIL,
                    "PX4 has 6 actuator-set outputs; this is joint 7+",
                    "use at most 6 joints",
                )
            )
        elif function == want:
            checks.append(
                Check(
                    label,
                    Verdict.PASS,
                    f"{func_name} = {want} (Peripheral via Actuator Set {index + 1})",
                )
            )
        elif function == 0 or function in PX4_ACTUATOR_FUNCTIONS:
            checks.append(
                Check(
                    label,
                    Verdict.FAIL,
                    f"{func_name} = {function} ({_px4_function_name(function or 0)}): joint "
                    f"{index + 1} is sent as actuator set slot {index + 1}, which drives only an "
                    f"output of function {want}",
                    f"param set {func_name} {want}",
                )
            )
        else:
            checks.append(
                Check(
                    label,
                    Verdict.FAIL,
                    f"{func_name} = {function} ({_px4_function_name(function or 0)}): the "
                    f"output is the vehicle's; joint {index + 1} drives only an output of "
                    f"function {want}",
                    _px4_move_fix(index, want, free, params),
                )
            )
            continue  # its limits are the vehicle's, not to be set to the arm's
        checks.append(_px4_range(index, joint, prefix, params))
    return checks


def _px4_range(
    index: int, joint: JointCalibration, prefix: str, params: dict[str, float | None]
) -> Check:
    """PX4 maps −1…1 onto the output's MIN…MAX; a build without them (some SITL builds) uses
    its output driver's own, 1000–2000 µs."""
    n = joint.output
    i = _px4_index(prefix, n)
    label = f"{_joint_label(index, joint.name, n)} range"
    names = (_px4_param(prefix, "MIN", n), _px4_param(prefix, "MAX", n))
    read = [_value(params, name) for name in names]
    missing = [name for name, value in zip(names, read, strict=True) if value is None]
    low, high = (PX4_BUILTIN_PWM_US[k] if value is None else value for k, value in enumerate(read))
    pwm = (min(joint.pwm_min_us, joint.pwm_max_us), max(joint.pwm_min_us, joint.pwm_max_us))
    if missing:
        own = [
            f"{what} ({PX4_BUILTIN_PWM_US[k]} us on SITL)"
            for k, what in enumerate(("minimum", "maximum"))
            if read[k] is None
        ]
        found = (
            f"{', '.join(missing)} not answered (no such parameter in this build): PX4 uses its "
            f"output driver's own {' and '.join(own)} and maps -1..1 onto {low}-{high} us"
        )
    else:
        found = f"{prefix}_MIN/MAX{i} = {low}/{high}"
    if (low, high) == pwm:
        return Check(label, Verdict.PASS, f"{found} = the calibration")
    if missing:
        fix = (
            f"calibrate joint {index + 1} over {low}-{high} us (pwm_min_us, pwm_max_us, with "
            f"angle_min_deg/angle_max_deg widened to match), or use a PX4 build that has "
            f"{' and '.join(missing)}"
        )
    else:
        fix = f"param set {names[0]} {pwm[0]}; param set {names[1]} {pwm[1]}"
    return Check(
        label,
        Verdict.FAIL,
        f"{found}, but the calibration is {pwm[0]}-{pwm[1]} us: "
        + ("" if missing else "PX4 maps -1..1 onto MIN..MAX, so ")
        + "every angle would land elsewhere",
        fix,
    )


def _px4_move_fix(index: int, want: int, free: list[int], params: dict[str, float | None]) -> str:
    """Move joint ``index`` to the first of ``free`` (taken from it) and give it its function;
    the output it leaves keeps its own."""
    if not free:
        return (
            f"map joint {index + 1} to an output whose function is 0 (Disabled) (joint.output), "
            f"then param set PWM_MAIN_FUNCn {want} there; leave this output's function as it is"
        )
    offered = ", ".join(map(str, free))
    target = free.pop(0)
    name = _px4_param(_px4_prefix(params, target) or "PWM_MAIN", "FUNC", target)
    return (
        f"map joint {index + 1} to a free output, e.g. joint.output = {target}, then param set "
        f"{name} {want}; leave this output's function as it is "
        f"(free (function 0): {offered})"
    )


def _ardupilot_safety(config: DaemonConfig, params: dict[str, float | None]) -> list[Check]:
    """A safety switch keeps outputs outside BRD_SAFETY_MASK without pulses; what was sent
    meanwhile goes out in one step when it is switched off. The daemon holds the arm then."""
    default, mask = _value(params, "BRD_SAFETY_DEFLT"), _value(params, "BRD_SAFETY_MASK")
    if default is None:
        return []
    outside = [o for o in config.calibration.outputs if not (mask or 0) >> (o - 1) & 1]
    if default == 0 or not outside:
        why = "no safety switch" if default == 0 else "the arm's outputs are in BRD_SAFETY_MASK"
        return [Check("safety switch", Verdict.PASS, why)]
    wanted = (mask or 0) | sum(1 << (o - 1) for o in config.calibration.outputs)
    return [
        Check(
            "safety switch",
            Verdict.WARN,
            f"BRD_SAFETY_DEFLT = {default} and output(s) {', '.join(map(str, outside))} not in "
            f"BRD_SAFETY_MASK = {mask}: the arm holds until the switch is pressed",
            f"param set BRD_SAFETY_MASK {wanted} (the arm's outputs stay live with the switch on)",
        )
    ]


def _px4_vehicle(config: DaemonConfig, params: dict[str, float | None]) -> list[Check]:
    """PX4: outputs dead until armed unless prearmed (COM_PREARM_MODE 2); the disarmed PWM is
    where a joint goes at boot, disarm and kill (the park PWM is the safe choice)."""
    checks = []
    prearm = _value(params, "COM_PREARM_MODE")
    if prearm is not None:
        if prearm == 2:
            checks.append(
                Check("prearm", Verdict.PASS, "COM_PREARM_MODE = 2: outputs live 5 s after boot")
            )
        else:
            checks.append(
                Check(
                    "prearm",
                    Verdict.WARN,
                    f"COM_PREARM_MODE = {prearm}: the arm's outputs stay at the disarmed PWM "
                    "until the vehicle arms (the daemon holds and says so)",
                    "param set COM_PREARM_MODE 2 (the arm moves while disarmed)",
                )
            )
    park_pwm = (
        config.calibration.angles_to_pwm_us(config.park_deg) if config.park_deg is not None else {}
    )
    for index, joint in enumerate(config.calibration.joints):
        n = joint.output
        if _px4_vehicles(params, n):
            continue  # the joint must move (an output item says so): its disarmed PWM is not ours
        # The output's prefix is the one its function was read with (else its DIS, if any).
        prefix = _px4_prefix(params, n) or next(
            (p for p in _px4_prefixes(n) if _value(params, _px4_param(p, "DIS", n)) is not None),
            None,
        )
        if prefix is None:
            continue  # no such output (the output item says so)
        checks.append(_px4_disarmed(index, joint, prefix, params, park_pwm.get(n)))
    return checks


def _px4_disarmed(
    index: int,
    joint: JointCalibration,
    prefix: str,
    params: dict[str, float | None],
    park: int | None,
) -> Check:
    """Where the joint goes whenever the outputs are not live: ``PWM_MAIN_DISn``, or in a build
    without it the output driver's own disarmed PWM (900 µs on PX4 SITL). Outside the
    calibration, or not the park PWM, it is a jump at boot, disarm and kill."""
    n = joint.output
    name = _px4_param(prefix, "DIS", n)
    read = _value(params, name)
    dis = PX4_BUILTIN_DISARMED_US if read is None else read
    found = (
        f"{name} not answered (no such parameter in this build): the output driver's own "
        f"disarmed PWM applies, {dis} us on PX4 SITL"
        if read is None
        else f"{name} = {dis}"
    )
    label = f"{_joint_label(index, joint.name, n)} disarmed"
    low, high = sorted((joint.pwm_min_us, joint.pwm_max_us))
    inside = low <= dis <= high
    if park is not None and dis == park:
        return Check(label, Verdict.PASS, f"{found} = the park PWM")
    if park is None and inside:
        return Check(label, Verdict.PASS, f"{found}, within the calibration")
    target = park if park is not None else joint.pwm_min_us
    where = "" if inside else f", outside the calibration {low}-{high} us"
    fix = f"param set {name} {target}"
    return Check(
        label,
        Verdict.WARN,
        f"{found}{where}: at boot, disarm and kill the joint jumps there"
        + ("" if park is None else f" (park is {park} us)"),
        fix
        if read is not None
        else f"{fix} on a PX4 build that has it; this one has no disarmed PWM to set for the "
        "output",
    )


def _px4_forwarding_off(params: dict[str, float | None]) -> list[str]:
    return [name for name in _PX4_FORWARD_PARAMS if _value(params, name) == 0]


def _px4_forwarding(findings: Findings) -> list[Check]:
    """PX4 forwards a frame only from an instance that forwards to one that forwards
    (``MAV_n_FORWARD``, read at boot). Which instance this link is doctor cannot tell: a serial
    port is named on the autopilot's side, and SITL starts its instances with forwarding
    (``mavlink start -f``) whatever the parameters say. So what was heard decides: a HEARTBEAT of
    another system here (a ground station, another vehicle) came through forwarding on this
    link's instance (or a router between doctor and the autopilot sent it, which routes as
    well), and the parameters are not doubted then. Without one the parameters alone are no
    finding of their own: the routing item's fix names those that are off."""
    params = findings.params
    off = _px4_forwarding_off(params)
    heard = sorted(findings.ground_stations | findings.others)
    if heard:
        who = ", ".join(f"{s}/{c}" for s, c in heard)
        note = (
            f" ({', '.join(off)} = 0: not this link's instance, set since boot (it takes effect "
            "at a reboot), or an instance started with forwarding, as SITL's are)"
            if off
            else ""
        )
        return [
            Check(
                "forwarding",
                Verdict.PASS,
                f"works: HEARTBEATs of {who} reach this link through the autopilot{note}",
            )
        ]
    if not off and any(_value(params, name) is not None for name in _PX4_FORWARD_PARAMS):
        on = ", ".join(name for name in _PX4_FORWARD_PARAMS if _value(params, name) is not None)
        return [Check("forwarding", Verdict.PASS, f"{on} = 1")]
    return []


def _streams(findings: Findings, kind: str) -> list[Check]:
    checks = []
    for name in READBACK.get(kind, ()):
        result, seen = findings.streams.get(name, (None, False))
        item = f"readback {name}"
        if seen:
            checks.append(Check(item, Verdict.PASS, "streams when asked"))
        elif result not in (None, mavlink.MAV_RESULT_ACCEPTED):
            checks.append(
                Check(
                    item,
                    Verdict.FAIL,
                    f"SET_MESSAGE_INTERVAL answered {_result(result)}",
                    "update the firmware",
                )
            )
        else:
            checks.append(
                Check(
                    item,
                    Verdict.WARN if name == "ACTUATOR_OUTPUT_STATUS" else Verdict.FAIL,
                    "asked for, never seen" + ("" if result is not None else " (no ACK either)"),
                    "check the port's MAVLink stream settings and bandwidth",
                )
            )
    return checks


def _lua_script(config: DaemonConfig, findings: Findings) -> Check:
    result = findings.lua_probe
    # The probe carries no PWM: the script refuses it (FAILED, nothing set); ArduPilot without
    # the script answers UNSUPPORTED.
    if result in (mavlink.MAV_RESULT_ACCEPTED, mavlink.MAV_RESULT_FAILED):
        return Check("lua bridge", Verdict.PASS, "the script answers MAV_CMD_USER_2")
    if result == mavlink.MAV_RESULT_DENIED:
        s = config.link
        system = s.system_id or (findings.autopilot[0] if findings.autopilot else "?")
        return Check(
            "lua bridge",
            Verdict.FAIL,
            f"the script answers MAV_CMD_USER_2 but refuses our ids {system}/{s.component_id} "
            "(DENIED): it obeys another sender",
            sender_fix(s.system_id, s.component_id),
        )
    where = (
        "copy the script (python -c 'import firmware_interface.lua_bridge as m; "
        "print(m.script_path())') to APM/scripts on the SD card, set SCR_ENABLE = 1, reboot"
    )
    if result is None:
        return Check("lua bridge", Verdict.FAIL, "MAV_CMD_USER_2 got no answer", where)
    return Check(
        "lua bridge",
        Verdict.FAIL,
        f"MAV_CMD_USER_2 answered {_result(result)}: the script is not running",
        where,
    )


def _link_budget(config: DaemonConfig) -> Check | None:
    """A serial link's bytes per update x rate_hz against its baud (None: not serial)."""
    budget = link_budget_of(config)
    if budget.baud is None:
        return None
    verdict = Verdict.PASS if budget.fits else Verdict.WARN
    fix = (
        None
        if budget.fits
        else "a faster baud, a lower control.rate_hz, or "
        + (" / ".join(budget.alternatives) or "fewer joints")
    )
    return Check("link budget", verdict, budget.message, fix)


def _signing(config: DaemonConfig, findings: Findings) -> Check:
    if config.link.signing is None:
        return Check(
            "signing",
            Verdict.WARN,
            "off: anyone who can send a frame on this link may move the arm",
            "set link.signing_key (and the same key on the autopilot) — see docs/signing.md",
        )
    if not findings.params or all(v is None for v in findings.params.values()):
        return Check(
            "signing",
            Verdict.FAIL,
            "on, but the autopilot answered none of our signed requests",
            "load the same key on the autopilot, or check its signing state",
        )
    return Check("signing", Verdict.PASS, "on; the autopilot's frames verify and it answers ours")


def _signing_clock(problem: str) -> Check:
    """The autopilot's frames are signed far ahead of our clock: its HEARTBEAT is refused (so
    no autopilot is heard), and after its restart it refuses ours."""
    return Check("signing", Verdict.FAIL, problem, LOCKOUT_FIX)


def _routing(findings: Findings, kind: str | None) -> Check:
    if findings.ground_stations:
        who = ", ".join(f"{s}/{c}" for s, c in sorted(findings.ground_stations))
        return Check("routing", Verdict.PASS, f"ground station {who} heard through the autopilot")
    off = _px4_forwarding_off(findings.params) if kind == "px4" else []
    forwarding = (
        f"; PX4 forwards only between instances that both forward, and {', '.join(off)} = 0: "
        + ", ".join(f"param set {name} 1" for name in off)
        + (
            " if that is its instance (ours forwards: others are heard), then reboot"
            if findings.others
            else " if that is its instance or ours, then reboot"
        )
        if off
        else ""
    )
    return Check(
        "routing",
        Verdict.WARN,
        f"no ground station heard through the autopilot in {findings.listened_s:.0f} s",
        "if one is connected, its USER_1 targets will not reach us: connect it to another "
        "autopilot port, not behind the same MAVProxy as us (docs/mavlink-targets.md: "
        "where the daemon sits)" + forwarding,
    )


def _result(result: int | None) -> str:
    if result is None:
        return "nothing"
    entry = mavlink.enums["MAV_RESULT"].get(result)
    return entry.name.removeprefix("MAV_RESULT_") if entry else str(result)


# -- talking to the autopilot ----------------------------------------------------------------


def decode_param(msg: Any, autopilot: str) -> float:
    """A PARAM_VALUE's value: PX4 sends integer types bytewise (the int's bits as a float)."""
    integer_types = (
        mavlink.MAV_PARAM_TYPE_INT8,
        mavlink.MAV_PARAM_TYPE_INT16,
        mavlink.MAV_PARAM_TYPE_INT32,
        mavlink.MAV_PARAM_TYPE_UINT8,
        mavlink.MAV_PARAM_TYPE_UINT16,
        mavlink.MAV_PARAM_TYPE_UINT32,
    )
    if autopilot == "px4" and msg.param_type in integer_types:
        return float(struct.unpack("<i", struct.pack("<f", msg.param_value))[0])
    return float(msg.param_value)


def _param_id(raw: Any) -> str:
    text = raw.decode("ascii", "replace") if isinstance(raw, bytes) else str(raw)
    return text.rstrip("\0")


def gather(
    config: DaemonConfig,
    *,
    timeout_s: float = 10.0,
    listen_s: float = 3.0,
    open_link: Callable[[str, LinkConfig], MavlinkLink] | None = None,
    clock: Callable[[], float] = time.monotonic,
) -> Findings:
    """Open the link, wait at most ``timeout_s`` for the autopilot, read what :func:`evaluate`
    needs, listen at least ``listen_s`` for a ground station; close the link."""
    s = config.link
    opener = open_link or (lambda url, cfg: MavlinkLink.open(url, cfg, clock=clock))
    findings = Findings(url=s.url, signing_on=s.signing is not None)
    started = clock()
    try:
        link = opener(s.url, link_config(s))
    except LinkError as exc:  # no such device, refused, address in use: a finding, no traceback
        findings.open_error = str(exc)
        return findings
    try:
        with link.messages(
            ["HEARTBEAT", "PARAM_VALUE", "COMMAND_ACK", *STREAM_IDS], maxsize=4096
        ) as inbox:
            try:
                info = link.wait_for_autopilot(timeout_s)
            except LinkError:  # LinkTimeout, or the link ended: nothing heard
                findings.listened_s = clock() - started
                stats = link.stats
                findings.signing_rejections = (
                    stats.rejected_bad_signature + stats.rejected_replay + stats.rejected_future
                )
                findings.signing_problem = link.signing_problem
                return findings
            findings.autopilot = (info.system_id, info.component_id, info.autopilot)
            findings.heard_after_s = clock() - started
            kind = flavour(findings)
            if kind in ("ardupilot", "px4"):
                names = param_names(config, kind)
                # PX4's PWM_AUX_* only where PWM_MAIN_* is not there (boards with an IO
                # processor); an unknown name is never answered, so asking costs the timeout.
                main = [n for n in names if not n.startswith("PWM_AUX_")]
                _read_params(link, inbox, main, kind, findings, clock)
                aux = [
                    n
                    for n in names
                    if n.startswith("PWM_AUX_") and findings.params.get(_main_of(n)) is None
                ]
                if aux:
                    _read_params(link, inbox, aux, kind, findings, clock)
                _try_streams(link, inbox, READBACK[kind], findings, clock)
                if config.link.dialect == "ardupilot-lua":
                    findings.lua_probe = _probe_lua(link, inbox, config, findings, clock)
            _drain_until(inbox, started + max(listen_s, 0.0), findings, clock)
            findings.others.discard((s.system_id or 0, s.component_id))  # our own, if echoed
            findings.listened_s = clock() - started
            stats = link.stats
            findings.signing_rejections = (
                stats.rejected_bad_signature + stats.rejected_replay + stats.rejected_future
            )
    finally:
        link.close()
    return findings


def _note(msg: Any, findings: Findings) -> None:
    """What every incoming frame may tell, whatever we wait for: a ground station, another
    system (either came through the autopilot's forwarding)."""
    if msg.get_type() != "HEARTBEAT":
        return
    source = (msg.get_srcSystem(), msg.get_srcComponent())
    if msg.type == mavlink.MAV_TYPE_GCS:
        findings.ground_stations.add(source)
    if findings.autopilot is not None and source[0] != findings.autopilot[0]:
        findings.others.add(source)


def _drain_until(
    inbox: MessageQueue, until_s: float, findings: Findings, clock: Callable[[], float]
) -> list[Any]:
    seen: list[Any] = []
    while True:
        remaining = until_s - clock()
        if remaining <= 0:
            return seen
        msg = inbox.get_nowait() or _wait_one(inbox, min(remaining, 0.1))
        if msg is None:
            continue
        _note(msg, findings)
        seen.append(msg)


def _main_of(aux_name: str) -> str:
    """PWM_AUX_FUNC3 → PWM_MAIN_FUNC11: the same output's PWM_MAIN name."""
    stem = aux_name.removeprefix("PWM_AUX_").rstrip("0123456789")
    index = int(aux_name[len("PWM_AUX_") + len(stem) :])
    return f"PWM_MAIN_{stem}{index + 8}"


def _wait_one(inbox: MessageQueue, timeout_s: float) -> Any:
    try:
        return inbox.get(timeout_s)
    except LinkError:  # LinkTimeout: nothing this slice
        return None


def _read_params(
    link: MavlinkLink,
    inbox: MessageQueue,
    names: Iterable[str],
    kind: str,
    findings: Findings,
    clock: Callable[[], float],
) -> None:
    """PARAM_REQUEST_READ by name, all at once, then again for the unanswered (3 rounds of
    0.7 s). A name the autopilot lacks is never answered (ArduPilot, PX4): it stays None."""
    wanted = list(dict.fromkeys(names))
    for name in wanted:
        findings.params[name] = None
    system, component = link.target
    for _round in range(3):
        missing = [n for n in wanted if findings.params[n] is None]
        if not missing:
            return
        for name in missing:
            link.send(link.mav.param_request_read_encode(system, component, name.encode(), -1))
        deadline = clock() + 0.7
        while clock() < deadline and any(findings.params[n] is None for n in missing):
            for msg in _drain_until(inbox, min(deadline, clock() + 0.05), findings, clock):
                if msg.get_type() == "PARAM_VALUE":
                    name = _param_id(msg.param_id)
                    if name in findings.params:
                        findings.params[name] = decode_param(msg, kind)


def _try_streams(
    link: MavlinkLink,
    inbox: MessageQueue,
    names: Iterable[str],
    findings: Findings,
    clock: Callable[[], float],
) -> None:
    system, component = link.target
    for name in names:
        msg_id = STREAM_IDS[name]
        link.send(
            link.mav.command_long_encode(
                system,
                component,
                mavlink.MAV_CMD_SET_MESSAGE_INTERVAL,
                0,
                msg_id,
                1e6 / STREAM_RATE_HZ,
                0,
                0,
                0,
                0,
                0,
            )
        )
        result: int | None = None
        seen = False
        deadline = clock() + 1.5
        while clock() < deadline and not (seen and result is not None):
            for msg in _drain_until(inbox, min(deadline, clock() + 0.1), findings, clock):
                if msg.get_type() == name:
                    seen = True
                elif (
                    msg.get_type() == "COMMAND_ACK"
                    and msg.command == mavlink.MAV_CMD_SET_MESSAGE_INTERVAL
                ):
                    result = msg.result
        findings.streams[name] = (result, seen)
        # Back to the autopilot's default rate (interval 0); the daemon asks for its own.
        link.send(
            link.mav.command_long_encode(
                system, component, mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, 0, msg_id, 0, 0, 0, 0, 0, 0
            )
        )


def _probe_lua(
    link: MavlinkLink,
    inbox: MessageQueue,
    config: DaemonConfig,
    findings: Findings,
    clock: Callable[[], float],
) -> int | None:
    """MAV_CMD_USER_2 with every PWM NaN ("leave that output alone"), sent with the daemon's
    own ids (the link is opened as ``run`` opens it): the bridge script refuses it, FAILED
    ("no PWM"), setting nothing, or answers DENIED if it obeys another sender; without the
    script ArduPilot answers UNSUPPORTED itself."""
    system, component = link.target
    first = min(config.calibration.outputs)
    nan = math.nan
    link.send(
        link.mav.command_long_encode(
            system, component, MAV_CMD_USER_2, 0, nan, nan, nan, nan, nan, nan, float(first)
        )
    )
    deadline = clock() + 1.5  # the script answers within ~12 ms; allow for a slow link
    while clock() < deadline:
        for msg in _drain_until(inbox, min(deadline, clock() + 0.1), findings, clock):
            if msg.get_type() == "COMMAND_ACK" and msg.command == MAV_CMD_USER_2:
                return int(msg.result)
    return None


def format_report(findings: Findings, checks: list[Check]) -> str:
    """The report for people: one line per item, the fix below each one that did not pass."""
    lines = [f"armbridge doctor: {findings.url}"]
    for c in checks:
        lines.append(f"  {c.verdict.value:4}  {c.item}: {c.detail}")
        if c.fix and c.verdict is not Verdict.PASS:
            lines.append(f"        fix: {c.fix}")
    counts = {v: sum(c.verdict is v for c in checks) for v in Verdict}
    lines.append(
        f"{counts[Verdict.FAIL]} failed, {counts[Verdict.WARN]} warnings, "
        f"{counts[Verdict.PASS]} passed"
    )
    return "\n".join(lines)
