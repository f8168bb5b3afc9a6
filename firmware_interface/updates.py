"""A servo update in flight: its commands sent back-to-back, its COMMAND_ACKs accounted for.

Pure logic (no I/O, no clock of its own): the daemon's control core sends every command of an
update at once and feeds the tracker what comes back. Measured on real ArduCopter (SITL, TCP):
six DO_SET_SERVO sent back-to-back and then the six ACKs collected took 3.2 ms (median), against
32.2 ms sent one at a time, each waiting for its ACK.

COMMAND_ACK carries no sequence number and no output number, so ACKs are **counted**: the
autopilot handles one link's frames in order and answers each at once, so with every ACK of the
update in, the k-th ACK answers the k-th command. A refusal on ArduPilot comes with a STATUSTEXT
"ServoRelayEvent: Channel N is already in use" one main-loop pass later, which names the output
and is checked against the position. When the count cannot be trusted the tracker says so
instead of guessing:

* fewer ACKs than commands by the deadline: every output of the update is **unknown** (any of
  them may have moved); the caller re-sends the same values (DO_SET_SERVO is idempotent);
* more ACKs than commands, or a STATUSTEXT naming an output whose ACK said ACCEPTED: the
  accounting was disturbed (a late ACK of an earlier attempt, or a forged one): unknown too;
* TEMPORARILY_REJECTED / IN_PROGRESS answers are not final: the output is unknown.

What this cannot catch: an ACK of an earlier attempt arriving late *and* one of this attempt's
commands lost, in the same update, can complete the count with the wrong ACK. Both attempts
carry the same values, so it matters only if the earlier attempt's command was lost too.

Two updates on their way at once (the daemon's core sends the next step behind the one in
flight) are counted the same way, in order: the oldest tracker short of ACKs takes the next
one. A command of the first lost, the second's first ACK completes the first's count, and the
second comes up one short: it ends unknown and is confirmed one command at a time. The second
carries every output the first sent, so its outcome is what the outputs hold; until it comes,
the first's verdict may name, for one output, the PWM of a command that was lost.
"""

from __future__ import annotations

import enum
import re
from collections.abc import Sequence
from dataclasses import dataclass, field

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from firmware_interface.commands import result_name
from firmware_interface.lua_bridge import MAV_CMD_USER_2, SENDER_DENIED

#: "ServoRelayEvent: Channel 14 is already in use" (AP_ServoRelayEvents.cpp).
_CHANNEL_IN_USE = re.compile(r"Channel\s+(\d+)\s+is already in use")
#: Results that say "not done, and it will not be": the output is refused.
_REFUSALS = frozenset(
    {mavlink.MAV_RESULT_DENIED, mavlink.MAV_RESULT_UNSUPPORTED, mavlink.MAV_RESULT_FAILED}
)


@dataclass(frozen=True)
class ServoCommand:
    """One COMMAND_LONG of a servo update and the ``{output: pwm_us}`` it sets."""

    command: int
    params: tuple[float, ...]  # 7 params
    pwm_by_output: tuple[tuple[int, int], ...]

    @property
    def outputs(self) -> tuple[int, ...]:
        return tuple(output for output, _ in self.pwm_by_output)


class UpdateState(enum.Enum):
    WAITING = "waiting"
    DONE = "done"  # every output has a verdict (accepted or refused)
    UNKNOWN = "unknown"  # timed out or disturbed: the outputs' state is not known


@dataclass(frozen=True)
class UpdateOutcome:
    """How an update ended, per output."""

    state: UpdateState
    accepted: dict[int, int] = field(default_factory=dict)  # output → pwm_us acknowledged
    refused: dict[int, str] = field(default_factory=dict)  # output → the autopilot's reason
    unknown: tuple[int, ...] = ()
    reason: str = ""  # why the outputs are unknown


class UpdateTracker:
    """ACK accounting for one attempt of one update (see the module docstring).

    ``sent_s``: when the last command went out; ``timeout_s``: how long to wait for all ACKs;
    ``grace_s``: after a refusal, how long to wait for the STATUSTEXT that names the output
    (ArduPilot sends it one main-loop pass after the ACK) and for an ACK too many.
    """

    def __init__(
        self,
        commands: Sequence[ServoCommand],
        *,
        sent_s: float,
        timeout_s: float,
        grace_s: float = 0.05,
    ) -> None:
        if not commands:
            raise ValueError("an update has at least one command")
        self.commands = tuple(commands)
        self.command_ids = frozenset(c.command for c in self.commands)
        self.deadline_s = sent_s + timeout_s
        self.grace_s = grace_s
        self._results: list[int] = []
        self._extra = 0
        self._complete_s: float | None = None
        self._named: dict[int, str] = {}  # output → STATUSTEXT naming it

    def on_ack(self, command: int, result: int, now_s: float) -> bool:
        """Count an ACK from the autopilot; False if it is not for this update's command."""
        if command not in self.command_ids or result == mavlink.MAV_RESULT_IN_PROGRESS:
            return False
        if len(self._results) == len(self.commands):
            self._extra += 1
        else:
            self._results.append(result)
            if len(self._results) == len(self.commands):
                self._complete_s = now_s
        return True

    @property
    def acks_missing(self) -> int:
        """ACKs still to come before the count is complete (0 once it is)."""
        return len(self.commands) - len(self._results)

    @property
    def complete(self) -> bool:
        """Every command has its ACK (its verdict may still wait out the grace period)."""
        return self._complete_s is not None

    @property
    def complete_s(self) -> float | None:
        """When the ACK that completed the count came (None until it did)."""
        return self._complete_s

    def on_statustext(self, text: str) -> None:
        match = _CHANNEL_IN_USE.search(text)
        if match is not None:
            self._named[int(match.group(1))] = text

    def next_event_s(self) -> float:
        """When :meth:`poll` may next change its answer without new input."""
        if self._complete_s is not None:
            return self._complete_s + self.grace_s
        return self.deadline_s

    def poll(self, now_s: float) -> UpdateOutcome | None:
        """The outcome once known, else None."""
        n = len(self.commands)
        if self._complete_s is None:
            if now_s < self.deadline_s:
                return None
            return self._unknown(f"{len(self._results)} of {n} COMMAND_ACKs by the deadline")
        all_accepted = all(r == mavlink.MAV_RESULT_ACCEPTED for r in self._results)
        if all_accepted and not self._extra and not self._named:
            return self._resolve()
        if now_s < self._complete_s + self.grace_s:
            return None  # a refusal's STATUSTEXT, or an ACK too many, may still come
        if self._extra:
            return self._unknown(f"{n + self._extra} COMMAND_ACKs for {n} commands")
        return self._resolve()

    def _resolve(self) -> UpdateOutcome:
        accepted: dict[int, int] = {}
        refused: dict[int, str] = {}
        unknown: list[int] = []
        for command, result in zip(self.commands, self._results, strict=True):
            for output, pwm in command.pwm_by_output:
                if result == mavlink.MAV_RESULT_ACCEPTED:
                    if output in self._named:
                        return self._unknown(
                            f"the autopilot refused output {output} but its ACK said ACCEPTED"
                        )
                    accepted[output] = pwm
                elif command.command == MAV_CMD_USER_2 and result == mavlink.MAV_RESULT_DENIED:
                    # The Lua bridge's answer to a sender it does not obey: not the output's
                    # fault, nor fixed on the output.
                    refused[output] = f"{result_name(result)} ({SENDER_DENIED})"
                elif result in _REFUSALS:
                    said = self._named.get(output)
                    refused[output] = result_name(result) + (f" ({said!r})" if said else "")
                else:
                    unknown.append(output)
        if unknown:
            return UpdateOutcome(
                UpdateState.UNKNOWN, accepted, refused, tuple(unknown), "answer not final"
            )
        return UpdateOutcome(UpdateState.DONE, accepted, refused)

    def _unknown(self, reason: str) -> UpdateOutcome:
        outputs = tuple(o for c in self.commands for o in c.outputs)
        return UpdateOutcome(UpdateState.UNKNOWN, unknown=outputs, reason=reason)
