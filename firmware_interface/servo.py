"""Servo commands for the arm, in two autopilot dialects behind one interface.

* ``ardupilot``: one COMMAND_LONG ``MAV_CMD_DO_SET_SERVO`` (183) per joint — param1 = output
  number (1-based), param2 = PWM µs. :meth:`ServoDialect.send_pwm` sends them one at a time,
  each waiting for its ACK (ACKs carry no sequence number, see
  :mod:`firmware_interface.commands`); the daemon instead sends an update's commands
  back-to-back (:meth:`ServoDialect.plan`) and counts the ACKs
  (:mod:`firmware_interface.updates`). ArduPilot accepts it only on
  outputs whose ``SERVOn_FUNCTION`` is 0, 1 or 51–66; otherwise it sends the STATUSTEXT
  "ServoRelayEvent: Channel N is already in use" and ``MAV_RESULT_FAILED``
  (AP_ServoRelayEvents.cpp), which we raise as :class:`ServoOutputUnavailable`.
  ArduPilot does not clamp the PWM: :meth:`ArmCalibration.check_pwm_us` is the gate.
  With ``skip_unchanged`` an update leaves out the outputs whose PWM the autopilot has already
  acknowledged (ArduPilot holds a DO_SET_SERVO value until the next one): each output left out
  saves a round trip, about 2.5 ms against a 400 Hz main loop.
* ``px4``: one COMMAND_LONG ``MAV_CMD_DO_SET_ACTUATOR`` (187) with params 1–6 = the joints,
  in joint order, normalised to −1…1 over [pwm_min_us, pwm_max_us]; param7 = 0 (actuator set
  1–6). Joint k drives the output whose function is "Peripheral via Actuator Set k" (301…306).
  PX4 copies all six params at once (FunctionActuatorSet.hpp) and NaN turns an output off, so
  every joint must be commanded in each update; with fewer than six joints the spare slots are
  NaN. ``skip_unchanged`` changes nothing here.
* ``ardupilot-lua``: ArduPilot with the Lua bridge we ship (:mod:`firmware_interface.lua_bridge`,
  ``lua/armbridge_servo.lua`` on the SD card): one COMMAND_LONG ``MAV_CMD_USER_2`` (31011) sets
  up to six consecutive outputs, params 1–6 = PWM µs (NaN: leave that output alone), param7 =
  the first output; the script checks every output's SERVOn_FUNCTION (must be 0) and
  SERVOn_MIN/MAX before it sets any and answers one COMMAND_ACK: ACCEPTED, or FAILED with
  nothing set; it obeys only the companion's ids (its ``ARMB_SYSID`` / ``ARMB_COMPID``
  parameters) and answers anyone else DENIED, raised naming what to set. One 44-byte frame per
  update instead of six (264 B): the choice on 57 600 / 115 200 baud links, where the bytes,
  not the round trips, set the latency. Outputs are
  grouped in windows of six from the lowest (the default 9–14 is one frame); outputs further
  apart cost one frame per window, one ACK each. A window whose outputs all hold their value
  already is left out of an update.
"""

from __future__ import annotations

import abc
import math
import re
from collections.abc import Callable, Mapping, Sequence

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from firmware_interface.calibration import ArmCalibration
from firmware_interface.commands import CommandSender
from firmware_interface.errors import CommandRejected, ConfigurationError, ServoOutputUnavailable
from firmware_interface.lua_bridge import LUA_SLOTS, MAV_CMD_USER_2, sender_fix
from firmware_interface.updates import ServoCommand

PX4_ACTUATOR_SLOTS = 6
#: One COMMAND_LONG: the MAV_CMD id and its seven params.
CommandParams = tuple[int, tuple[float, ...]]


class ServoDialect(abc.ABC):
    """Moves the arm's servos through one autopilot's command set."""

    name: str
    #: True where each output is its own command (ardupilot), False for one command for all.
    per_output: bool

    def __init__(self, commands: CommandSender | None, calibration: ArmCalibration) -> None:
        self.commands = commands  # None: plan updates only (the daemon sends them itself)
        self.calibration = calibration

    def plan(
        self, pwm_by_output: Mapping[int, int], acked_pwm_us: Mapping[int, int] | None = None
    ) -> list[ServoCommand]:
        """The commands of one update, to be sent back-to-back (see
        :mod:`firmware_interface.updates`). Every value is checked against its output's range
        first. ``acked_pwm_us``: what the autopilot is known to hold; where the dialect sets
        outputs one by one (ardupilot), outputs already at their value are left out."""
        self.calibration.check_pwm_us(pwm_by_output)
        acked = acked_pwm_us or {}
        wanted = {
            o: p for o, p in pwm_by_output.items() if not self.per_output or acked.get(o) != p
        }
        if not wanted:
            return []
        if not self.per_output:  # one command sets every output
            setting = tuple(sorted(pwm_by_output.items()))
            return [ServoCommand(c, tuple(p), setting) for c, p in self.command_params(wanted)]
        return [
            ServoCommand(c, tuple(p), ((int(p[0]), wanted[int(p[0])]),))
            for c, p in self.command_params(wanted)
        ]

    def send_angles(self, angles_deg: Sequence[float] | Mapping[str, float]) -> dict[int, int]:
        """Convert joint angles (degrees) through the calibration and send them.
        Returns the ``{output: pwm_us}`` that was commanded."""
        pwm_by_output = self.calibration.angles_to_pwm_us(angles_deg)
        self.send_pwm(pwm_by_output)
        return pwm_by_output

    def _sender(self) -> CommandSender:
        if self.commands is None:
            raise ConfigurationError(
                f"{self.name} dialect built without a CommandSender: plan only"
            )
        return self.commands

    def send_pwm(self, pwm_by_output: Mapping[int, int], *, skip_unchanged: bool = False) -> None:
        """Send ``{output: pwm_us}`` and wait until the autopilot acknowledged all of it.
        Every value is checked against its output's range before anything is sent.

        ``skip_unchanged``: where the dialect sends outputs one by one (ardupilot), leave out
        those the autopilot already acknowledged at this PWM. Leave it off to re-send
        everything, e.g. when the autopilot may have lost its state (link back after a loss).
        """
        self.calibration.check_pwm_us(pwm_by_output)
        self._send_checked(dict(pwm_by_output), skip_unchanged)

    @abc.abstractmethod
    def command_params(self, pwm_by_output: Mapping[int, int]) -> list[CommandParams]:
        """The ``(MAV_CMD, params)`` pairs one update sends, in order (for sending and sizing)."""

    @abc.abstractmethod
    def _send_checked(self, pwm_by_output: dict[int, int], skip_unchanged: bool) -> None: ...


class ArduPilotServoDialect(ServoDialect):
    """One DO_SET_SERVO per output, each acknowledged before the next is sent."""

    name = "ardupilot"
    per_output = True

    def __init__(self, commands: CommandSender | None, calibration: ArmCalibration) -> None:
        super().__init__(commands, calibration)
        self._acked_pwm_us: dict[int, int] = {}  # per output, the PWM last ACCEPTED

    def command_params(self, pwm_by_output: Mapping[int, int]) -> list[CommandParams]:
        return [
            (mavlink.MAV_CMD_DO_SET_SERVO, (float(output), float(pwm), 0.0, 0.0, 0.0, 0.0, 0.0))
            for output, pwm in pwm_by_output.items()
        ]

    def _send_checked(self, pwm_by_output: dict[int, int], skip_unchanged: bool) -> None:
        if skip_unchanged:
            pwm_by_output = {
                output: pwm
                for output, pwm in pwm_by_output.items()
                if self._acked_pwm_us.get(output) != pwm
            }
        for command, params in self.command_params(pwm_by_output):
            output, pwm = int(params[0]), int(params[1])
            # Unknown until acknowledged: a timeout may or may not have moved the servo.
            self._acked_pwm_us.pop(output, None)
            try:
                self._sender().command_long(command, params)
            except CommandRejected as exc:
                if exc.result != mavlink.MAV_RESULT_FAILED:
                    raise
                raise ServoOutputUnavailable(
                    f"servo output {output} refused DO_SET_SERVO pwm_us={pwm} "
                    f"({exc.result_name}); autopilot said: {exc.statustext!r}. "
                    f"Set SERVO{output}_FUNCTION to 0 (disabled) on the flight controller.",
                    command=command,
                    result=exc.result,
                    result_name=exc.result_name,
                    output=output,
                    statustext=exc.statustext,
                ) from exc
            self._acked_pwm_us[output] = pwm


class Px4ServoDialect(ServoDialect):
    """One DO_SET_ACTUATOR carrying all joints as −1…1 values."""

    name = "px4"
    per_output = False

    def __init__(self, commands: CommandSender | None, calibration: ArmCalibration) -> None:
        if len(calibration) > PX4_ACTUATOR_SLOTS:
            raise ConfigurationError(
                f"px4 dialect drives at most {PX4_ACTUATOR_SLOTS} joints "
                f"(Actuator Set 1–6), calibration has {len(calibration)}"
            )
        super().__init__(commands, calibration)

    def command_params(self, pwm_by_output: Mapping[int, int]) -> list[CommandParams]:
        missing = [j.name for j in self.calibration.joints if j.output not in pwm_by_output]
        if missing:
            raise ConfigurationError(
                f"px4 DO_SET_ACTUATOR sets all joints at once; missing {missing}"
            )
        values = [j.pwm_us_to_normalized(pwm_by_output[j.output]) for j in self.calibration.joints]
        values += [math.nan] * (PX4_ACTUATOR_SLOTS - len(values))
        return [(mavlink.MAV_CMD_DO_SET_ACTUATOR, (*values, 0.0))]

    def _send_checked(self, pwm_by_output: dict[int, int], skip_unchanged: bool) -> None:
        for command, params in self.command_params(pwm_by_output):
            self._sender().command_long(command, params)


#: "Channel 12 is already in use", as the Lua bridge (and ArduPilot itself) words a refusal.
_CHANNEL_IN_USE = re.compile(r"Channel\s+(\d+)\s+is already in use")


class ArduPilotLuaServoDialect(ServoDialect):
    """One MAV_CMD_USER_2 per window of up to six outputs, for the shipped Lua bridge."""

    name = "ardupilot-lua"
    per_output = False

    @staticmethod
    def windows(outputs: Sequence[int]) -> list[tuple[int, ...]]:
        """The outputs grouped as one command each: from the lowest, up to six in a row."""
        groups: list[tuple[int, ...]] = []
        for output in sorted(outputs):
            if groups and output < groups[-1][0] + LUA_SLOTS:
                groups[-1] = (*groups[-1], output)
            else:
                groups.append((output,))
        return groups

    def command_params(self, pwm_by_output: Mapping[int, int]) -> list[CommandParams]:
        params: list[CommandParams] = []
        for window in self.windows(list(pwm_by_output)):
            first = window[0]
            slots = [math.nan] * LUA_SLOTS
            for output in window:
                slots[output - first] = float(pwm_by_output[output])
            params.append((MAV_CMD_USER_2, (*slots, float(first))))
        return params

    def plan(
        self, pwm_by_output: Mapping[int, int], acked_pwm_us: Mapping[int, int] | None = None
    ) -> list[ServoCommand]:
        self.calibration.check_pwm_us(pwm_by_output)
        acked = acked_pwm_us or {}
        planned: list[ServoCommand] = []
        for command, params in self.command_params(pwm_by_output):
            first = int(params[6])
            setting = tuple(
                (first + slot, int(pwm))
                for slot, pwm in enumerate(params[:6])
                if not math.isnan(pwm)
            )
            if all(acked.get(output) == pwm for output, pwm in setting):
                continue  # the autopilot holds every value of this window already
            planned.append(ServoCommand(command, tuple(params), setting))
        return planned

    def _send_checked(self, pwm_by_output: dict[int, int], skip_unchanged: bool) -> None:
        for command in self.plan(pwm_by_output):
            try:
                self._sender().command_long(command.command, command.params)
            except CommandRejected as exc:
                if exc.result == mavlink.MAV_RESULT_DENIED:
                    link = self._sender().link
                    raise CommandRejected(
                        f"servo outputs {list(command.outputs)}: the Lua bridge refused our "
                        f"commands ({exc.result_name}, none set) as from "
                        f"{link.system_id}/{link.config.component_id}; "
                        f"{sender_fix(link.config.system_id, link.config.component_id)}",
                        command=exc.command,
                        result=exc.result,
                        result_name=exc.result_name,
                        statustext=exc.statustext,
                    ) from exc
                if exc.result != mavlink.MAV_RESULT_FAILED:
                    raise
                named = _CHANNEL_IN_USE.search(exc.statustext or "")
                output = int(named.group(1)) if named else command.outputs[0]
                raise ServoOutputUnavailable(
                    f"servo outputs {list(command.outputs)} refused by the Lua bridge "
                    f"({exc.result_name}, none set); autopilot said: {exc.statustext!r}. "
                    f"Check SERVO{output}_FUNCTION = 0 and SERVO{output}_MIN/MAX on the "
                    f"flight controller.",
                    command=command.command,
                    result=exc.result,
                    result_name=exc.result_name,
                    output=output,
                    statustext=exc.statustext,
                ) from exc


#: The dialects by name; an unknown name is refused with this list.
SERVO_DIALECTS: dict[str, Callable[[CommandSender | None, ArmCalibration], ServoDialect]] = {
    "ardupilot": ArduPilotServoDialect,
    "px4": Px4ServoDialect,
    "ardupilot-lua": ArduPilotLuaServoDialect,
}


def make_servo_dialect(
    name: str, commands: CommandSender | None, calibration: ArmCalibration
) -> ServoDialect:
    """Build the dialect called ``name`` (``ardupilot``, ``px4``, ``ardupilot-lua``); without
    ``commands`` it only plans updates (:meth:`ServoDialect.plan`)."""
    try:
        factory = SERVO_DIALECTS[name]
    except KeyError:
        raise ConfigurationError(
            f"unknown servo dialect {name!r}; valid: {sorted(SERVO_DIALECTS)}"
        ) from None
    return factory(commands, calibration)
