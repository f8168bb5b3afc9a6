"""COMMAND_LONG and COMMAND_INT: acted on when routing says they are ours, answered with a
COMMAND_ACK addressed to the sender, on the link the command came from only.

GCS_Common.cpp ``handle_command_long`` checks no target itself, so a command for a component
never heard gets our answer. A command no part handles → UNSUPPORTED. On PX4 the commander's
commands (arming, DO_SET_ACTUATOR) wait in a queue for its next cycle
(:class:`~sim_servo.config.Px4TimingConfig`); the Lua bridge's MAV_CMD_USER_2 waits for the
script (:mod:`sim_servo.autopilot.lua`). The handlers live with what they act on: outputs,
streams.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from sim_servo.autopilot.messages import command_name, result_name
from sim_servo.autopilot.state import AutopilotState
from sim_servo.autopilot.wire import Wire

if TYPE_CHECKING:
    from sim_servo.autopilot.lua import LuaScript


@dataclass(frozen=True)
class Command:
    """A COMMAND_LONG or COMMAND_INT, normalised (``params`` has 7 floats)."""

    command: int
    params: tuple[float, ...]
    source: tuple[int, int]
    channel: int = 0
    #: When it arrived (set when it waits for PX4's commander: it acts later).
    received_s: float | None = None


#: Acts on a command at a time; the MAV_RESULT.
CommandHandler = Callable[[Command, float], int]


def acknowledge(
    state: AutopilotState,
    wire: Wire,
    command: Command,
    result: int,
    now_s: float,
    *,
    name: str,
    result_param2: int = 0,
    **extra: Any,
) -> None:
    """Log the ``ack`` event and send the COMMAND_ACK, unless the faults withhold it."""
    faults = state.config.faults
    withheld = faults.withhold_all_acks or command.command in faults.withhold_ack_commands
    state.emit(
        now_s,
        "ack",
        command=command.command,
        command_name=name,
        result=result,
        result_name=result_name(result),
        withheld=withheld,
        **extra,
    )
    if withheld:
        state.stats["acks_withheld"] += 1
        return
    state.stats["acks"] += 1
    # On the link the command came from only (GCS_Common.cpp: sent on ``chan``).
    ack = wire.encoder.command_ack_encode(
        command.command, result, 0, result_param2, *command.source
    )
    wire.send(ack, now_s, command.channel)


class Commands:
    """The command handlers by MAV_CMD, the PX4 commander's queue."""

    def __init__(
        self,
        state: AutopilotState,
        wire: Wire,
        handlers: dict[int, CommandHandler],
        lua: LuaScript | None,
    ) -> None:
        self._state = state
        self._wire = wire
        self._handlers = handlers
        self._lua = lua
        #: PX4: the commander's queue of commands waiting for its next cycle, (due, command).
        self._commander: list[tuple[float, Command]] = []

    def message_handlers(self) -> dict[str, Callable[[Any, float, int], None]]:
        return {"COMMAND_LONG": self.on_command_long, "COMMAND_INT": self.on_command_int}

    def on_command_long(self, msg: Any, now_s: float, channel: int) -> None:
        params = (
            msg.param1,
            msg.param2,
            msg.param3,
            msg.param4,
            msg.param5,
            msg.param6,
            msg.param7,
        )
        self._take(_command(msg, params, channel), now_s)

    def on_command_int(self, msg: Any, now_s: float, channel: int) -> None:
        params = (msg.param1, msg.param2, msg.param3, msg.param4, float(msg.x), float(msg.y), msg.z)
        self._take(_command(msg, params, channel), now_s)

    def _take(self, command: Command, now_s: float) -> None:
        if self._lua is not None and self._lua.takes(command):
            self._lua.queue(command, now_s)
            return
        state = self._state
        due_s = state.flavour.commander_due_s(state.config, command.command, now_s, state.boot_s)
        if due_s is not None:
            self._commander.append((due_s, dataclasses.replace(command, received_s=now_s)))
            return
        self.execute(command, now_s)

    def run_commander(self, now_s: float) -> None:
        due = [command for at, command in self._commander if at <= now_s]
        self._commander = [entry for entry in self._commander if entry[0] > now_s]
        for command in due:
            self.execute(command, now_s)

    def execute(self, command: Command, now_s: float) -> None:
        """Act on ``command`` now and answer it."""
        handler = self._handlers.get(command.command)
        result = handler(command, now_s) if handler is not None else mavlink.MAV_RESULT_UNSUPPORTED
        acknowledge(
            self._state, self._wire, command, result, now_s, name=command_name(command.command)
        )

    def next_events_s(self) -> list[float]:
        return [due for due, _ in self._commander]

    def halt(self, now_s: float) -> None:
        self._commander.clear()


def _command(msg: Any, params: tuple[float, ...], channel: int) -> Command:
    return Command(msg.command, params, (msg.get_srcSystem(), msg.get_srcComponent()), channel)
