"""The 16 servo outputs: what the autopilot reports, what each servo physically receives, and
what decides it — the commands, arming and prearm (PX4), the safety switch (ArduPilot).

ArduPilot (GCS_ServoRelay.cpp, AP_ServoRelayEvents.cpp ``do_set_servo``): MAV_CMD_DO_SET_SERVO on
an output outside 1–16 → FAILED; on an output whose SERVOn_FUNCTION is not 0 (disabled), 1 (RC
pass-through) or 51–66 (RC input 1–16) → STATUSTEXT severity INFO "ServoRelayEvent: Channel N is
already in use" (sent from the main loop, so one loop period *after* the ACK) and FAILED;
otherwise the PWM is applied as given (no clamping) and ACCEPTED.

ArduPilot's safety switch (AP_BoardConfig; ``AP_HAL_ChibiOS/RCOutput.cpp`` ``push_local``): on
at each boot when ``BRD_SAFETY_DEFLT`` is 1 (0 here by default, so outputs are live);
:meth:`Outputs.set_safety` flips it. While on, an output whose bit (output − 1) is not in
``BRD_SAFETY_MASK`` sends no pulses; DO_SET_SERVO is still ACCEPTED and SERVO_OUTPUT_RAW still
reports the PWM given (``read()`` returns the stored period); switched off, the stored PWMs go
out in one step. A new ``BRD_SAFETY_MASK`` applies at the next tenth of a second since boot
(``RCOutput::safety_update`` reads it at 10 Hz), a reboot's at once.

PX4: disarmed at boot (``SimConfig.armed``: armed at start); MAV_CMD_COMPONENT_ARM_DISARM param1
1 / 0 arms / disarms (param2 21196: forced, a kill) → ACCEPTED, other values DENIED.
``COM_PREARM_MODE`` 0 (default): never prearmed; 2 (and 1: no safety button here, as SITL):
prearmed from 5 s after each boot; changes apply at once. Outputs are live while armed or
prearmed; otherwise every output shows ``PWM_MAIN_DISn`` (1000 as boards; SITL 900) — at boot,
on disarm and kill, after a reboot. Live, an output on function 301–306 shows its slot of
actuator set 1 (a slot never set since boot is NaN: the disarmed PWM), a motor (101–104) its
minimum once armed. What was stored while dead appears in one step when the outputs come alive.
MAV_CMD_DO_SET_ACTUATOR (Commander.cpp) is ACCEPTED whatever happens: nothing mapped, disarmed,
param7 ≠ 0 (then ignored), values out of range. Param7 0 stores params 1–6 (NaN: slot
unchanged). PWM = 1500 + 500·v rounded half away from zero, clamped to ``PWM_MAIN_MINn`` /
``MAXn``.

The ``output`` event logs every change of what a servo physically receives (with its cause),
``arming`` / ``prearm`` / ``safety`` the state changes, so a bench can check from the log alone
that no joint stepped faster than its limit. A command that came in on another link than the
companion's (a ground station's DO_SET_SERVO or DO_SET_ACTUATOR) tags its ``output`` and
``servo`` events with ``src`` (its sender's system and component) and ``link``: a bench tells
the companion's steps from a foreign sender's.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable
from typing import TYPE_CHECKING, Any

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from sim_servo.autopilot.flavour import px4_actuator_pwm_us
from sim_servo.autopilot.params import ParamTable
from sim_servo.autopilot.state import AutopilotState
from sim_servo.autopilot.wire import Wire
from sim_servo.config import OUTPUT_COUNT, PX4_ACTUATOR_SET_COUNT, PX4_ACTUATOR_SET_FIRST_FUNCTION
from sim_servo.hand import HandModel
from sim_servo.servo import Servo, ServoParams

if TYPE_CHECKING:
    from sim_servo.autopilot.commands import Command

#: SERVOn_FUNCTION values DO_SET_SERVO may drive (AP_ServoRelayEvents.cpp): k_none, k_manual,
#: k_rcin1 … k_rcin16.
ARDUPILOT_FREE_FUNCTIONS = frozenset({0, 1, *range(51, 67)})
STATUSTEXT_IN_USE = "ServoRelayEvent: Channel {output} is already in use"
#: What an output assigned to a function (a motor, disarmed) reports before any command.
IDLE_ASSIGNED_PWM_US = 1000
#: ArduPilot's output driver reads BRD_SAFETY_MASK this often (``RCOutput::safety_update``).
MASK_PERIOD_S = 0.1
#: MAV_CMD_COMPONENT_ARM_DISARM param2 that forces (PX4 skips its checks; here: a kill).
PX4_FORCE_MAGIC = 21196


def foreign_origin(command: Command) -> dict[str, Any]:
    """The fields that tag the events of a command from another link than the companion's
    (link 0): ``src`` (its sender's system and component) and ``link``; none for the
    companion's own commands."""
    if command.channel == 0:
        return {}
    return {"src": list(command.source), "link": command.channel}


def make_servos(state: AutopilotState, hand: HandModel | None, now_s: float) -> dict[int, Servo]:
    """One servo per output, at the configured initial PWM (the hand's joints with their own
    degrees per µs)."""
    config = state.config
    servos: dict[int, Servo] = {}
    for output in range(1, OUTPUT_COUNT + 1):
        deg_per_us = config.servo.deg_per_us
        if hand is not None and output in hand.outputs:
            deg_per_us = hand.deg_per_us(output)
        params = ServoParams(
            slew_s_per_60deg=config.servo.slew_s_per_60deg,
            deg_per_us=deg_per_us,
            deadband_us=config.servo.deadband_us,
            travel_min_us=config.servo.travel_min_us,
            travel_max_us=config.servo.travel_max_us,
        )
        servos[output] = Servo(params, config.servo.initial_us, now_s)
    return servos


class Outputs:
    """The outputs' state. ``before_course_change`` runs before any servo is given a new
    course (the world log's samples due by then keep their horn positions)."""

    def __init__(
        self,
        state: AutopilotState,
        params: ParamTable,
        servos: dict[int, Servo],
        wire: Wire,
        *,
        hand: HandModel | None,
        before_course_change: Callable[[float], None],
        now_s: float,
    ) -> None:
        self._state = state
        self._flavour = state.flavour
        self.params = params
        self.servos = servos
        self._wire = wire
        self._hand = hand
        self._before_course_change = before_course_change
        #: PX4: armed (MAV_CMD_COMPONENT_ARM_DISARM); prearmed (COM_PREARM_MODE, 5 s after boot).
        self.armed = self._flavour.armed_at_start(state.config)
        self.prearmed = False
        #: PX4: actuator set 1–6 as last set by DO_SET_ACTUATOR (NaN: never set since boot).
        self.actuator_values = [math.nan] * PX4_ACTUATOR_SET_COUNT
        #: ArduPilot: the PWM each output was last given (boot values until a command).
        self.commanded_us: dict[int, int] = self._boot_pwm_us()
        #: ArduPilot: the safety switch (BRD_SAFETY_DEFLT at each boot).
        self.safety_on = self._flavour.safety_at_boot(params)
        #: ArduPilot: the BRD_SAFETY_MASK the output driver applies, and when it next reads a
        #: changed one (None: unchanged).
        self.safety_mask = self._mask_param()
        self._mask_due_s: float | None = None
        #: What the autopilot reports (SERVO_OUTPUT_RAW, ACTUATOR_OUTPUT_STATUS) …
        self.pwm_us: dict[int, int] = {}
        #: … and what each servo physically receives (0: no pulses).
        self.output_us: dict[int, int] = {}
        self.pwm_us, self.output_us = self._outputs_now()
        if self._flavour.drives_outputs_at_boot:
            for output, pwm in self.output_us.items():
                self.servos[output].command(pwm, now_s)
        #: Whether a servo may still be moving (a ``settled`` event is due when all stop).
        self.moving = self._flavour.drives_outputs_at_boot

    def _boot_pwm_us(self) -> dict[int, int]:
        """ArduPilot: each output's PWM at boot: none on a disabled output, idle on an
        assigned one."""
        return {
            output: 0 if self.params.function(output) == 0 else IDLE_ASSIGNED_PWM_US
            for output in range(1, OUTPUT_COUNT + 1)
        }

    # -- what is reported, what the servos receive -------------------------------------------

    @property
    def outputs_live(self) -> bool:
        """PX4: armed or prearmed; ArduPilot: the safety switch off (per output: the mask)."""
        return self._flavour.outputs_live(self)

    def live(self, output: int) -> bool:
        return not self._state.rebooting and self._flavour.live(self, output)

    def _outputs_now(
        self, outputs: Iterable[int] | None = None
    ) -> tuple[dict[int, int], dict[int, int]]:
        """(reported, physical) PWM of every output (or of ``outputs``) in the current state.
        During a reboot nothing has pulses."""
        reported: dict[int, int] = {}
        physical: dict[int, int] = {}
        for output in range(1, OUTPUT_COUNT + 1) if outputs is None else outputs:
            reported[output], physical[output] = self._flavour.output_us(self, output)
            if self._state.rebooting:
                physical[output] = 0
        return reported, physical

    def refresh(
        self,
        now_s: float,
        cause: str,
        outputs: Iterable[int] | None = None,
        **origin: Any,
    ) -> None:
        """Bring the reported and physical PWMs up to the current state; every physical change
        moves its servo and is logged as an ``output`` event (what the servo receives).
        ``outputs``: only those changed (a command to one output; the rest of the state is as
        the last full refresh left it). ``origin``: fields every such event carries (a foreign
        command's sender, see :func:`foreign_origin`)."""
        self._before_course_change(now_s)
        reported, physical = self._outputs_now(outputs)
        self.pwm_us = reported if outputs is None else {**self.pwm_us, **reported}
        for output, pwm in physical.items():
            before = self.output_us.get(output)
            if before == pwm:
                continue
            self.output_us[output] = pwm
            servo = self.servos[output]
            servo.command(pwm, now_s)
            self.moving = True
            self._state.emit(
                now_s,
                "output",
                output=output,
                pwm_us=pwm,
                from_us=before,
                cause=cause,
                position_us=round(servo.position_us(now_s), 3),
                **origin,
            )

    def on_param_change(self, now_s: float) -> None:
        """A parameter was set: the prearm mode, functions and limits apply at once, the mask
        at the output driver's next tick."""
        self.run_prearm(now_s)
        if self._mask_param() != self.safety_mask and self._mask_due_s is None:
            since_boot_s = now_s - self._state.boot_s
            ticks = math.floor(since_boot_s / MASK_PERIOD_S + 1e-9) + 1
            self._mask_due_s = self._state.boot_s + ticks * MASK_PERIOD_S
        self.refresh(now_s, "param")

    def _mask_param(self) -> int:
        param = self.params.get("BRD_SAFETY_MASK")
        return 0 if param is None else int(param.value)

    def mask_due_s(self) -> float | None:
        """When the output driver takes a changed BRD_SAFETY_MASK (None: none changed)."""
        return self._mask_due_s

    def run_mask(self, now_s: float) -> None:
        if self._mask_due_s is not None and now_s >= self._mask_due_s:
            self._mask_due_s = None
            if self._mask_param() != self.safety_mask:
                self.safety_mask = self._mask_param()
                self.refresh(now_s, "mask")

    # -- arming, prearm, safety --------------------------------------------------------------

    def prearm_due_s(self) -> float | None:
        """When this boot prearms (None: never, or rebooting)."""
        if self._state.rebooting:
            return None
        return self._flavour.prearm_due_s(self.params, self._state.boot_s)

    def run_prearm(self, now_s: float) -> None:
        due_s = self.prearm_due_s()
        prearmed = due_s is not None and now_s >= due_s
        if prearmed != self.prearmed:
            self.prearmed = prearmed
            self._state.emit(now_s, "prearm", prearmed=prearmed)
            self.refresh(now_s, "prearm")

    def set_armed(self, armed: bool, now_s: float, cause: str = "query") -> bool:
        """PX4: arm or disarm now (``cause`` goes in the event: query, command, kill …); False
        (nothing done) on ArduPilot or while rebooting."""
        if not self._flavour.arms or self._state.rebooting:
            return False
        if armed != self.armed:
            self.armed = armed
            self._state.emit(now_s, "arming", armed=armed, cause=cause)
            self.refresh(now_s, "arm" if armed else cause)
        return True

    def set_safety(self, on: bool, now_s: float, cause: str = "query") -> bool:
        """ArduPilot: engage (``on``) or disengage the safety switch now; False (nothing done)
        on PX4 or while rebooting."""
        if not self._flavour.has_safety_switch or self._state.rebooting:
            return False
        if on != self.safety_on:
            self.safety_on = on
            self._state.emit(now_s, "safety", on=on, cause=cause)
            self.refresh(now_s, "safety_on" if on else "safety_off")
        return True

    # -- commands ----------------------------------------------------------------------------

    def do_set_servo(self, command: Command, now_s: float) -> int:
        """ArduPilot MAV_CMD_DO_SET_SERVO."""
        channel_f, pwm_f = command.params[0], command.params[1]
        # param1/param2 reach do_set_servo as uint8_t / uint16_t (C truncation).
        if not (math.isfinite(channel_f) and math.isfinite(pwm_f)) or not 0 <= channel_f < 256:
            return mavlink.MAV_RESULT_FAILED
        output, pwm = int(channel_f), int(pwm_f) % 65536
        if not 1 <= output <= OUTPUT_COUNT:
            return mavlink.MAV_RESULT_FAILED
        if output in self._state.config.faults.nack_outputs:
            self._state.emit(now_s, "fault", fault="nack_output", output=output, pwm_us=pwm)
            return mavlink.MAV_RESULT_FAILED
        if self.params.function(output) not in ARDUPILOT_FREE_FUNCTIONS:
            self._wire.statustext(
                mavlink.MAV_SEVERITY_INFO, STATUSTEXT_IN_USE.format(output=output), now_s
            )
            return mavlink.MAV_RESULT_FAILED
        self.apply(output, pwm, now_s, **foreign_origin(command))
        return mavlink.MAV_RESULT_ACCEPTED

    def apply(self, output: int, pwm: int, now_s: float, **origin: Any) -> None:
        """An ArduPilot output given ``pwm`` (DO_SET_SERVO, or the Lua bridge's command);
        ``origin``: a foreign sender's fields for the events (:func:`foreign_origin`)."""
        self._before_course_change(now_s)
        self.commanded_us[output] = pwm
        self.refresh(now_s, "command", (output,), **origin)
        self._servo_event(output, pwm, now_s, **origin)
        if self.output_us[output] == pwm:
            # A command re-sends the pulse even when it is unchanged (the servo's own timing).
            self.servos[output].command(pwm, now_s)
            self.moving = True

    def do_set_actuator(self, command: Command, now_s: float) -> int:
        """PX4 MAV_CMD_DO_SET_ACTUATOR (actuator set 1–6); outputs on functions 301–306 show
        their slot once live."""
        if command.params[6] != 0:
            return mavlink.MAV_RESULT_ACCEPTED  # no other set drives functions 301–306
        mapped = {
            output: slot
            for output in range(1, OUTPUT_COUNT + 1)
            if 0
            <= (slot := self.params.function(output) - PX4_ACTUATOR_SET_FIRST_FUNCTION)
            < PX4_ACTUATOR_SET_COUNT
        }
        for output in mapped:
            if output in self._state.config.faults.nack_outputs:
                self._state.emit(now_s, "fault", fault="nack_output", output=output)
                return mavlink.MAV_RESULT_FAILED
        origin = foreign_origin(command)
        given = {s for s in range(PX4_ACTUATOR_SET_COUNT) if not math.isnan(command.params[s])}
        for slot in given:
            self.actuator_values[slot] = command.params[slot]
        self.refresh(now_s, "command", **origin)
        for output, slot in mapped.items():
            value = self.actuator_values[slot]
            if math.isnan(value) or (origin and slot not in given):
                continue  # a foreign command's events name only the slots it set
            low, high = self.params.pwm_limits(output)
            pwm = min(max(px4_actuator_pwm_us(value), low), high)
            received = {}
            if command.received_s is not None:  # (it waited for the commander)
                received["received_t_s"] = self._state.t(command.received_s)
            self._servo_event(
                output, pwm, now_s, value=value, live=self.live(output), **origin, **received
            )
        return mavlink.MAV_RESULT_ACCEPTED

    def arm_disarm(self, command: Command, now_s: float) -> int:
        """PX4 MAV_CMD_COMPONENT_ARM_DISARM: param1 1 arms, 0 disarms (a force, param2 21196,
        disarms at once whatever the state: a kill); anything else DENIED. The outputs go to
        the disarmed PWM on a disarm, to the stored values on an arm (one step)."""
        action = command.params[0]
        if not math.isfinite(action) or round(action) not in (0, 1):
            return mavlink.MAV_RESULT_DENIED
        forced = command.params[1] == PX4_FORCE_MAGIC
        cause = "command" if round(action) == 1 or not forced else "kill"
        self.set_armed(round(action) == 1, now_s, cause=cause)
        return mavlink.MAV_RESULT_ACCEPTED

    def _servo_event(self, output: int, pwm: int, now_s: float, **extra: Any) -> None:
        """A command gave ``output`` the PWM ``pwm`` (what it shows once live)."""
        servo = self.servos[output]
        self._state.emit(
            now_s,
            "servo",
            output=output,
            pwm_us=pwm,
            position_us=round(servo.position_us(now_s), 3),
            target_us=round(servo.target_us, 3),
            arrival_t_s=self._state.t(servo.arrival_s()),
            **{
                k: (None if isinstance(v, float) and math.isnan(v) else v) for k, v in extra.items()
            },
        )

    # -- motion ------------------------------------------------------------------------------

    def positions(self, now_s: float) -> dict[int, float]:
        return {o: round(s.position_us(now_s), 3) for o, s in self.servos.items()}

    def arrival_s(self) -> float | None:
        """When the last moving servo arrives (None: none is moving)."""
        if not self.moving:
            return None
        return max(servo.arrival_s() for servo in self.servos.values())

    def check_settled(self, now_s: float) -> None:
        """The ``settled`` event, stamped when the last servo arrived, with the hand then."""
        if not self.moving or any(servo.moving(now_s) for servo in self.servos.values()):
            return
        self.moving = False
        arrival = max(servo.arrival_s() for servo in self.servos.values())
        self._state.emit(
            arrival,
            "settled",
            positions_us=self.positions(now_s),
            hand=self._hand.state(self.positions(now_s)).as_dict() if self._hand else None,
        )

    # -- reboot ------------------------------------------------------------------------------

    def halt(self, now_s: float) -> None:
        """A reboot starts: disarmed, not prearmed, no pulses (the servos hold where they are)."""
        if self.armed:
            self.armed = False
            self._state.emit(now_s, "arming", armed=False, cause="reboot")
        if self.prearmed:
            self.prearmed = False
            self._state.emit(now_s, "prearm", prearmed=False)
        self.refresh(now_s, "reboot")

    def boot(self, now_s: float) -> None:
        """Back from a reboot: the outputs at their boot values, the safety switch at its
        default."""
        self.commanded_us = self._boot_pwm_us()
        self.actuator_values = [math.nan] * PX4_ACTUATOR_SET_COUNT
        safety_on = self._flavour.safety_at_boot(self.params)
        self.safety_mask, self._mask_due_s = self._mask_param(), None
        if safety_on != self.safety_on:
            self.safety_on = safety_on
            self._state.emit(now_s, "safety", on=safety_on, cause="boot")
        self.refresh(now_s, "boot")
