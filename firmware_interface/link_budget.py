"""What one servo update costs on the link, and whether ``rate_hz`` of them fit a serial line.

On a serial link the bytes, not the round trips, set an update's time. A target's first update
must be acknowledged within its control period (the daemon may send the next step behind an
update in flight, but a stream of one target a period falls behind when each takes longer),
so an update fits the control rate when

    bytes to the FC x 10 / baud + the FC's answer time + one ACK's bytes x 10 / baud <= 1 / rate_hz

(8N1: 10 bits a byte; the ACKs of earlier commands travel back while later commands are still
going out, so only the last one's bytes come on top). The FC's answer time is the *worst*
measured, so a fit holds for every update, not the median one:

* ``ardupilot``: six DO_SET_SERVO back-to-back answered in 3.2 ms median, 6.0 ms max
  (ArduCopter 4.7.0-dev SITL);
* ``ardupilot-lua``: the Lua bridge script answers in 8.9 ms median, 11.5 ms max (same SITL);
* ``px4``: DO_SET_ACTUATOR answered in 5.8 ms median, 13.0 ms max (PX4 main of 2026-03,
  SITL with the SIH quadrotor; the p90 was 10.8 ms).

UDP and TCP links have no such byte budget here (their bandwidth is orders of magnitude above
an arm's needs): :func:`link_budget` says so and everything fits. Pure: no I/O, no clock.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from firmware_interface.calibration import ArmCalibration
from firmware_interface.errors import ConfigurationError
from firmware_interface.servo import SERVO_DIALECTS
from firmware_interface.transport import parse_url

#: 8N1: start bit, eight data bits, stop bit.
BITS_PER_BYTE = 10
#: The flight controller's answer time per update (ms): (median, max), see the module docstring.
FC_ANSWER_MS: Mapping[str, tuple[float, float]] = {
    "ardupilot": (3.2, 6.0),
    "ardupilot-lua": (8.9, 11.5),
    "px4": (5.8, 13.0),
}
#: Dialects an autopilot speaks: the alternatives offered are the same autopilot's.
AUTOPILOT_OF: Mapping[str, str] = {
    "ardupilot": "ardupilot",
    "ardupilot-lua": "ardupilot",
    "px4": "px4",
}
#: MAVLink 2 signing appends 13 bytes to every frame.
SIGNATURE_BYTES = 13
#: Our sender ids (the daemon's defaults) and the autopilot's; they do not change frame sizes.
_COMPANION = (1, mavlink.MAV_COMP_ID_ONBOARD_COMPUTER)
_AUTOPILOT = (1, 1)


@dataclass(frozen=True)
class UpdateCost:
    """One update of every joint in one dialect: frames, bytes each way, and its time (ms) on
    a serial line of ``baud`` (None: not a serial link, bytes not counted)."""

    dialect: str
    frames: int
    to_fc_bytes: int
    ack_bytes: int  # one COMMAND_ACK
    baud: int | None
    wire_ms: float  # the commands' bytes, then the last ACK's
    answer_ms: float  # the FC's worst answer time
    median_ms: float  # wire + the FC's median answer time

    @property
    def update_ms(self) -> float:
        """Target → last ACK at worst: wire time + the FC's worst answer time."""
        return self.wire_ms + self.answer_ms

    def max_rate_hz(self) -> float:
        return 1000.0 / self.update_ms if self.update_ms > 0 else float("inf")


@dataclass(frozen=True)
class LinkBudget:
    """The verdict for one config: ``fits`` when ``dialect``'s update fits the control period;
    ``alternatives`` the same autopilot's other dialects that would (fastest first);
    ``costs`` those dialects' (and ours) update costs; ``message`` says it all
    in one line for ``check-config`` / ``doctor``."""

    url: str
    baud: int | None
    rate_hz: float
    dialect: str
    costs: Mapping[str, UpdateCost]
    fits: bool
    alternatives: tuple[str, ...]
    message: str


def _frame_bytes(payload_msg: mavlink.MAVLink_message, sender: tuple[int, int]) -> int:
    codec = mavlink.MAVLink(None, *sender)
    return len(payload_msg.pack(codec))


def update_cost(
    dialect: str, calibration: ArmCalibration, baud: int | None, *, signed: bool = False
) -> UpdateCost:
    """The cost of one update of every joint in ``calibration`` (all PWM at mid-range; the
    values do not change a frame's size: params are 4-byte floats)."""
    try:
        factory = SERVO_DIALECTS[dialect]
    except KeyError:
        raise ConfigurationError(
            f"unknown servo dialect {dialect!r}; valid: {sorted(SERVO_DIALECTS)}"
        ) from None
    planner = factory(None, calibration)
    pwm = {j.output: (j.pwm_min_us + j.pwm_max_us) // 2 for j in calibration.joints}
    extra = SIGNATURE_BYTES if signed else 0
    codec = mavlink.MAVLink(None, *_COMPANION)
    frames = to_fc = ack = 0
    for command, params in planner.command_params(pwm):
        msg = codec.command_long_encode(*_AUTOPILOT, command, 0, *params)
        to_fc += _frame_bytes(msg, _COMPANION) + extra
        answer = codec.command_ack_encode(command, 0, 0, 0, *_COMPANION)
        ack = max(ack, _frame_bytes(answer, _AUTOPILOT) + extra)
        frames += 1
    median_answer_ms, max_answer_ms = FC_ANSWER_MS[dialect]
    wire_ms = 0.0 if baud is None else (to_fc + ack) * BITS_PER_BYTE / baud * 1000.0
    return UpdateCost(
        dialect, frames, to_fc, ack, baud, wire_ms, max_answer_ms, wire_ms + median_answer_ms
    )


def link_budget(
    url: str,
    dialect: str,
    calibration: ArmCalibration,
    rate_hz: float,
    *,
    signed: bool = False,
) -> LinkBudget:
    """Whether ``rate_hz`` updates of ``dialect`` fit the link ``url`` (see the module
    docstring); on a serial link that cannot carry them, which dialect would."""
    if not rate_hz > 0:
        raise ConfigurationError(f"rate_hz={rate_hz!r} must be > 0")
    spec = parse_url(url)
    baud = spec.baud if spec.kind == "serial" else None
    ours = update_cost(dialect, calibration, baud, signed=signed)
    costs = {dialect: ours}
    for name in SERVO_DIALECTS:
        if name != dialect and AUTOPILOT_OF.get(name) == AUTOPILOT_OF.get(dialect):
            try:
                costs[name] = update_cost(name, calibration, baud, signed=signed)
            except ConfigurationError:  # cannot drive this arm (px4: more than six joints)
                continue
    period_ms = 1000.0 / rate_hz
    if baud is None:
        return LinkBudget(
            url, None, rate_hz, dialect, costs, True, (),
            f"{spec.kind} link: no serial byte budget; {dialect} at {rate_hz:g} Hz",
        )  # fmt: skip
    fitting = sorted(
        (c for c in costs.values() if c.update_ms <= period_ms), key=lambda c: c.update_ms
    )
    fits = ours.update_ms <= period_ms
    alternatives = tuple(c.dialect for c in fitting if c.dialect != dialect)
    head = (
        f"{dialect} at {baud} baud: {ours.frames} frame(s), {ours.to_fc_bytes} B to the FC, "
        f"up to {ours.update_ms:.1f} ms per update ({ours.wire_ms:.1f} ms of bytes + "
        f"{ours.answer_ms:.1f} ms on the FC)"
    )
    if fits:
        message = f"{head}: fits control.rate_hz={rate_hz:g} ({period_ms:.1f} ms)"
    else:
        message = (
            f"{head}: does not fit control.rate_hz={rate_hz:g} ({period_ms:.1f} ms); "
            f"at most {ours.max_rate_hz():.1f} Hz. "
        )
        if fitting:
            message += "Would fit: " + ", ".join(
                f"dialect = {c.dialect!r} (up to {c.update_ms:.1f} ms)" for c in fitting
            )
        else:
            best = min(costs.values(), key=lambda c: c.update_ms)
            message += (
                f"No dialect fits; fastest {best.dialect!r} up to {best.max_rate_hz():.1f} Hz: "
                "lower control.rate_hz or raise the baud rate"
            )
    return LinkBudget(url, baud, rate_hz, dialect, costs, fits, alternatives, message)
