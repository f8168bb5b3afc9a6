"""Read back the outputs the autopilot actually applied, to confirm a servo command.

ArduPilot reports them in SERVO_OUTPUT_RAW (36): port 0 carries outputs 1–16 (9–16 only in
MAVLink 2). PX4 reports ACTUATOR_OUTPUT_STATUS (375): ``actuator[i]`` is output i+1 for the
first ``active`` outputs. Ask for a stream with :meth:`OutputReadback.request`
(MAV_CMD_SET_MESSAGE_INTERVAL, 511, interval in µs).
"""

from __future__ import annotations

import threading
from collections.abc import Mapping

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from firmware_interface.commands import CommandOutcome, CommandSender
from firmware_interface.errors import ConfigurationError, LinkError, LinkTimeout
from firmware_interface.link import MavlinkLink, MavMessage

SERVO_OUTPUT_RAW_OUTPUTS = 16


class OutputReadback:
    """Keeps the latest reported value of every output of the link's autopilot."""

    def __init__(self, link: MavlinkLink) -> None:
        self.link = link
        self._cond = threading.Condition()
        self._pwm_us: dict[int, float] = {}
        self._subscription = link.subscribe(
            self._on_message, ["SERVO_OUTPUT_RAW", "ACTUATOR_OUTPUT_STATUS"]
        )

    def close(self) -> None:
        self._subscription.cancel()

    def request(
        self, commands: CommandSender, rate_hz: float = 10.0, message: str = "SERVO_OUTPUT_RAW"
    ) -> CommandOutcome:
        """Ask the autopilot to stream ``message`` at ``rate_hz``."""
        ids = {
            "SERVO_OUTPUT_RAW": mavlink.MAVLINK_MSG_ID_SERVO_OUTPUT_RAW,
            "ACTUATOR_OUTPUT_STATUS": mavlink.MAVLINK_MSG_ID_ACTUATOR_OUTPUT_STATUS,
        }
        if message not in ids:
            raise ConfigurationError(f"message={message!r}; valid: {sorted(ids)}")
        if not 0 < rate_hz <= 1000:
            raise ConfigurationError(f"rate_hz={rate_hz!r} outside (0, 1000]")
        return commands.command_long(
            mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, (ids[message], 1e6 / rate_hz)
        )

    def _on_message(self, msg: MavMessage) -> None:
        try:
            if msg.get_srcSystem() != self.link.target[0]:
                return
        except LinkError:  # no autopilot known yet
            return
        values: dict[int, float] = {}
        if msg.get_type() == "SERVO_OUTPUT_RAW":
            if msg.port != 0:
                return
            for output in range(1, SERVO_OUTPUT_RAW_OUTPUTS + 1):
                values[output] = getattr(msg, f"servo{output}_raw")
        else:
            for index in range(min(msg.active, len(msg.actuator))):
                values[index + 1] = msg.actuator[index]
        with self._cond:
            self._pwm_us.update(values)
            self._cond.notify_all()

    def latest_pwm_us(self, output: int) -> float | None:
        """The last value reported for ``output`` (µs for PWM outputs), or None."""
        with self._cond:
            return self._pwm_us.get(output)

    def wait_for(
        self, expected_pwm_us: Mapping[int, int], timeout_s: float, tolerance_us: float = 0.0
    ) -> None:
        """Wait until every output reports its expected PWM (± ``tolerance_us``), at most
        ``timeout_s`` by the link's clock; raises :class:`LinkTimeout` naming the mismatches."""
        clock = self.link.clock
        deadline = clock() + timeout_s

        def mismatches() -> dict[int, float | None]:
            return {
                output: self._pwm_us.get(output)
                for output, want in expected_pwm_us.items()
                if self._pwm_us.get(output) is None
                or abs(self._pwm_us[output] - want) > tolerance_us
            }

        with self._cond:
            while bad := mismatches():
                if clock() >= deadline or self.link.closed:
                    detail = ", ".join(
                        f"output {o}: want {expected_pwm_us[o]}, got {v}"
                        for o, v in sorted(bad.items())
                    )
                    raise LinkTimeout(
                        f"outputs not confirmed within timeout_s={timeout_s}: {detail}"
                    )
                self._cond.wait(0.01)
