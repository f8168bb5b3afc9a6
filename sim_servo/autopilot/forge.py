"""A test fault: frames forged as if from the autopilot, on the companion's link.

A MAVLink 1/2 link without signing has no way to tell who sent a frame: anything that can put
bytes on it (a second radio on the same channel, a program on a shared serial bus or network)
can send frames with the autopilot's system and component ids. :meth:`Forger.start` (the query
``forge``) plays such a sender: from now, every ``interval_s`` for ``for_s`` seconds (0: once),
one forged frame goes out on the companion's link (link 0) only, the same way out as the
autopilot's own frames (its link timing, no faults), from a codec of its own (the forger's own
sequence numbers, never signed: it has no key). It carries the autopilot's (system, component)
and says what the asker chose:

* ``SERVO_OUTPUT_RAW``: ``pwm_us`` (output → PWM, outputs 1–16); the outputs not named show
  what the autopilot reports now; ``time_usec`` the autopilot's time since boot;
* ``SYS_STATUS``: ``safety_on`` (default false): the motor outputs "enabled" unless it is
  true, as the autopilot's own SYS_STATUS says of its safety switch;
* ``SYSTEM_TIME``: ``time_boot_ms`` (default 0: what a rebooted autopilot would send; any value
  below the autopilot's own is a time going back), ``time_unix_usec`` the autopilot's.

Nothing in the autopilot changes: its outputs, streams and state are what they were. It goes
on through a reboot (a forger is not the autopilot). A new ``forge`` replaces one still going.
The ``fault`` event ``forge`` says what was asked (``msg``, ``fields``, ``for_s``,
``interval_s``); the counter ``forged`` counts the frames.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from sim_servo.autopilot.state import AutopilotState
from sim_servo.autopilot.wire import Wire
from sim_servo.config import OUTPUT_COUNT

#: The messages a forger can send.
FORGEABLE = ("SERVO_OUTPUT_RAW", "SYS_STATUS", "SYSTEM_TIME")
#: Bounds of a forgery: how long it lasts and how often a frame goes.
MAX_FOR_S = 600.0
MIN_INTERVAL_S = 0.001
DEFAULT_INTERVAL_S = 0.01
#: The companion's link: forged frames go there only.
COMPANION_LINK = 0


@dataclass
class Forgery:
    """One forgery: what to say, until when, how often; the next frame's time."""

    msg: str
    fields: dict[str, Any]
    until_s: float
    interval_s: float
    next_s: float
    sent: int = field(default=0)


def parse_forgery(request: Mapping[str, Any], now_s: float) -> Forgery:
    """A forgery from the query's JSON object (``msg``, ``for_s``, ``interval_s`` and the
    message's own fields, see the module docstring); ``ValueError`` naming the field."""
    msg = str(request.get("msg", "")).upper()
    if msg not in FORGEABLE:
        raise ValueError(f"msg={request.get('msg')!r}; valid: {list(FORGEABLE)}")
    for_s = _number(request.get("for_s", 0.0), "for_s", 0.0, MAX_FOR_S)
    interval_s = _number(
        request.get("interval_s", DEFAULT_INTERVAL_S), "interval_s", MIN_INTERVAL_S, MAX_FOR_S
    )
    fields: dict[str, Any] = {}
    if msg == "SERVO_OUTPUT_RAW":
        pwm_us = request.get("pwm_us", {})
        if not isinstance(pwm_us, Mapping):
            raise ValueError(f"pwm_us={pwm_us!r} must map outputs to PWMs")
        shown = {}
        for output, pwm in pwm_us.items():
            number = int(_number(output, "pwm_us output", 1, OUTPUT_COUNT))
            shown[number] = int(_number(pwm, f"pwm_us[{output}]", 0, 65535))
        fields["pwm_us"] = shown
    elif msg == "SYS_STATUS":
        safety_on = request.get("safety_on", False)
        if not isinstance(safety_on, bool):
            raise ValueError(f"safety_on={safety_on!r} must be true or false")
        fields["safety_on"] = safety_on
    else:
        fields["time_boot_ms"] = int(
            _number(request.get("time_boot_ms", 0), "time_boot_ms", 0, 2**32 - 1)
        )
    return Forgery(msg, fields, now_s + for_s, interval_s, now_s)


def _number(value: Any, name: str, low: float, high: float) -> float:
    try:
        number = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name}={value!r} is not a number") from None
    if not (math.isfinite(number) and low <= number <= high):
        raise ValueError(f"{name}={value!r} outside [{low}, {high}]")
    return number


class Forger:
    """The forger on the companion's link. ``reported_us`` reads what the autopilot reports per
    output now (the outputs a forged SERVO_OUTPUT_RAW does not name)."""

    def __init__(
        self,
        state: AutopilotState,
        wire: Wire,
        reported_us: Callable[[], Mapping[int, int]],
    ) -> None:
        self._state = state
        self._wire = wire
        self._reported_us = reported_us
        config = state.config
        self.encoder = mavlink.MAVLink(
            None, srcSystem=config.system_id, srcComponent=config.component_id
        )
        self.forgery: Forgery | None = None

    def start(self, request: Mapping[str, Any], now_s: float) -> Forgery:
        """Start forging now (replacing a forgery still going); ``ValueError`` for a request
        that names no forgeable message or a field out of range."""
        forgery = parse_forgery(request, now_s)
        self.forgery = forgery
        self._state.emit(
            now_s,
            "fault",
            fault="forge",
            msg=forgery.msg,
            fields={k: _jsonable(v) for k, v in forgery.fields.items()},
            for_s=round(forgery.until_s - now_s, 6),
            interval_s=forgery.interval_s,
        )
        return forgery

    def next_events_s(self) -> list[float]:
        return [] if self.forgery is None else [self.forgery.next_s]

    def run(self, now_s: float) -> None:
        """Send the forged frame due by ``now_s`` (one: behind by more than an interval, the
        cadence restarts from now)."""
        forgery = self.forgery
        if forgery is None or forgery.next_s > now_s:
            return
        frame = self._message(forgery, now_s).pack(self.encoder)
        self.encoder.seq = (self.encoder.seq + 1) % 256
        self._wire.write_routed(frame, COMPANION_LINK, now_s, 0.0)
        self._state.stats["forged"] += 1
        forgery.sent += 1
        forgery.next_s += forgery.interval_s
        if forgery.next_s <= now_s:
            forgery.next_s = now_s + forgery.interval_s
        if forgery.next_s > forgery.until_s:
            self.forgery = None

    def _message(self, forgery: Forgery, now_s: float) -> mavlink.MAVLink_message:
        state, enc = self._state, self.encoder
        boot_us = state.time_boot_us(now_s)
        if forgery.msg == "SERVO_OUTPUT_RAW":
            shown = {**self._reported_us(), **forgery.fields["pwm_us"]}
            values = [shown.get(o, 0) & 0xFFFF for o in range(1, OUTPUT_COUNT + 1)]
            return enc.servo_output_raw_encode(boot_us & 0xFFFFFFFF, 0, *values)
        if forgery.msg == "SYS_STATUS":
            motors = mavlink.MAV_SYS_STATUS_SENSOR_MOTOR_OUTPUTS
            enabled = 0 if forgery.fields["safety_on"] else motors
            return enc.sys_status_encode(motors, enabled, motors, 0, 0, -1, -1, 0, 0, 0, 0, 0, 0)
        return enc.system_time_encode(state.time_unix_us(now_s), forgery.fields["time_boot_ms"])


def _jsonable(value: Any) -> Any:
    if isinstance(value, dict):
        return {str(k): v for k, v in value.items()}
    return value
