"""armbridge's Lua bridge script on ArduPilot (``lua_script``): MAV_CMD_USER_2 is answered as
the script answers it, after the script's own delay (:mod:`sim_servo.lua_bridge`); the arm's
outputs get ``SERVOn_MIN`` / ``MAX`` = the arm's PWM range, as the script's install notes ask.
The script's own parameters (``ARMB_SYSID`` / ``ARMB_COMPID``: who is obeyed) are in the
parameter table whenever the script is on (:class:`~sim_servo.autopilot.params.ParamTable`).
"""

from __future__ import annotations

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from sim_servo.autopilot.commands import Command, acknowledge
from sim_servo.autopilot.outputs import Outputs
from sim_servo.autopilot.params import ParamTable
from sim_servo.autopilot.state import AutopilotState
from sim_servo.autopilot.wire import Wire
from sim_servo.lua_bridge import (
    MAV_CMD_USER_2,
    DeniedTexts,
    LuaScriptTiming,
    check_user2,
    refusal_text,
)


class LuaScript:
    """The script: its commands waiting for their answer time, (due, command)."""

    def __init__(
        self,
        state: AutopilotState,
        params: ParamTable,
        outputs: Outputs,
        wire: Wire,
        *,
        now_s: float,
    ) -> None:
        if not state.flavour.runs_lua:
            raise ValueError("lua_script needs flavour='ardupilot'")
        self._state = state
        self._params = params
        self._outputs = outputs
        self._wire = wire
        self._timing = LuaScriptTiming(now_s)
        self._pending: list[tuple[float, Command]] = []
        self._denied_texts = DeniedTexts()
        arm = state.config.arm
        for output in arm.outputs:
            params[f"SERVO{output}_MIN"].value = arm.pwm_min_us
            params[f"SERVO{output}_MAX"].value = arm.pwm_max_us

    def takes(self, command: Command) -> bool:
        return command.command == MAV_CMD_USER_2

    def queue(self, command: Command, now_s: float) -> None:
        self._pending.append((self._timing.answer_s(now_s), command))

    def _param(self, name: str) -> float | None:
        param = self._params.get(name)
        return None if param is None else float(param.value)

    def run(self, now_s: float) -> None:
        """Answer the commands due by ``now_s``."""
        if not self._pending:
            return
        due = [command for at, command in self._pending if at <= now_s]
        self._pending = [entry for entry in self._pending if entry[0] > now_s]
        for command in due:
            verdict = check_user2(
                command.params,
                self._param,
                sender=command.source,
                own_system=self._state.config.system_id,
            )
            if verdict.accepted:
                for output, pwm in verdict.settings.items():
                    self._outputs.apply(output, pwm, now_s)
                result = mavlink.MAV_RESULT_ACCEPTED
            elif verdict.denied:
                if self._denied_texts.due(now_s):
                    self._wire.statustext(
                        mavlink.MAV_SEVERITY_WARNING, refusal_text(verdict), now_s
                    )
                result = mavlink.MAV_RESULT_DENIED
            else:
                # The script sends its text at once (gcs:send_text), before its ACK.
                self._wire.statustext(mavlink.MAV_SEVERITY_WARNING, refusal_text(verdict), now_s)
                result = mavlink.MAV_RESULT_FAILED
            acknowledge(
                self._state,
                self._wire,
                command,
                result,
                now_s,
                name="MAV_CMD_USER_2 (lua)",
                result_param2=verdict.refused_output,
                refused_output=verdict.refused_output,
            )

    def next_events_s(self) -> list[float]:
        return [due for due, _ in self._pending]

    def halt(self, now_s: float) -> None:
        self._pending.clear()
        self._denied_texts.reset()
