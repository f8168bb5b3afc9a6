"""The simulated autopilot running armbridge's Lua bridge (``armbridge_servo.lua``).

With ``lua_script`` on (``--lua-script``, ArduPilot flavour only) the simulator answers
COMMAND_LONG ``MAV_CMD_USER_2`` (31011) as the script does on a flight controller: params 1–6
the PWM of outputs ``param7`` … ``param7 + 5`` (NaN: leave that output alone); every output
checked before any is set (``SERVOn_FUNCTION`` must be 0, the PWM an integer within
``SERVOn_MIN`` … ``SERVOn_MAX``); one COMMAND_ACK, ACCEPTED, or FAILED with nothing set,
``result_param2`` the first refused output (0: the command itself) and a STATUSTEXT saying why.
Only the companion is obeyed: a command whose sender ids are not ``ARMB_SYSID`` /
``ARMB_COMPID`` (the script's own parameters, :data:`SCRIPT_PARAMS`; ``ARMB_SYSID`` 0: the
autopilot's system id) is answered DENIED before anything is checked, and the STATUSTEXT naming
the sender is sent at most once every :data:`DENIED_TEXT_S` (:class:`DeniedTexts`).
The simulator re-implements the rules from the script's description (it may not import
``firmware_interface``); ``tests/sim_servo/test_lua_bridge.py`` runs both on the same cases.

When: ArduPilot hands the frame to the script's queue on the main-loop pass that reads it
(0–2.5 ms at 400 Hz, the autopilot's own inbox), the script picks it up on its next run, every
:data:`SCRIPT_PERIOD_MS` (the scripting thread runs at a lower rate than the main loop), and
answers :data:`SCRIPT_ANSWER_MS` later; the answer then leaves through the link's output, whose
floor (``LinkTimingConfig.output_delay_ms``, 1.0 ms) holds for every frame the autopilot
writes. Fitted to what was measured on ArduCopter 4.7.0-dev SITL (send → ACK median 8.9 ms,
max 11.5 ms): the sum of the two waits has its median at (2.5 + 2.7) / 2 = 2.6 ms and its
maximum at 5.2 ms, so 5.3 + 2.6 + 1.0 = 8.9 and 5.3 + 5.2 + 1.0 = 11.5. That measurement was
over TCP; the TCP-fitted hold, or a serial line's bytes, come on top.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

MAV_CMD_USER_2 = 31011
SCRIPT_PERIOD_MS = 2.7
SCRIPT_ANSWER_MS = 5.3
SLOTS = 6
#: The script drives SERVO1 … SERVO32; a board without SERVOn parameters refuses output n.
MAX_OUTPUT = 32
STATUSTEXT_PREFIX = "armbridge: "
STATUSTEXT_MAX = 50
#: The companion's ids, the only sender obeyed: the parameters the script adds
#: (``param:add_table``, prefix ``ARMB_``) with their defaults, which also apply where the
#: parameters are missing. ``ARMB_SYSID`` 0: the autopilot's own system id; 191:
#: MAV_COMP_ID_ONBOARD_COMPUTER (armbridge's defaults).
SYSID_PARAM = "ARMB_SYSID"
COMPID_PARAM = "ARMB_COMPID"
SCRIPT_PARAMS = {SYSID_PARAM: 0, COMPID_PARAM: 191}
#: A refused sender is said at most this often.
DENIED_TEXT_S = 5.0


@dataclass(frozen=True)
class Verdict:
    """What the script does with one command: ``settings`` (output → PWM) to apply, or a
    refusal naming ``refused_output`` (0: the command itself) and the ``reason``; ``denied``:
    refused for its sender (DENIED), not for its outputs (FAILED)."""

    settings: dict[int, int]
    refused_output: int = 0
    reason: str = ""
    denied: bool = False

    @property
    def accepted(self) -> bool:
        return not self.reason


def _is_integer(x: float) -> bool:
    return math.isfinite(x) and float(x).is_integer()


def companion_ids(param: Callable[[str], float | None], own_system: int) -> tuple[float, float]:
    """The (system, component) ids the script obeys, read from its parameters (``param``: by
    name, None where missing); ``own_system``: the autopilot's system id."""
    sysid = param(SYSID_PARAM)
    compid = param(COMPID_PARAM)
    sysid = SCRIPT_PARAMS[SYSID_PARAM] if sysid is None else sysid
    compid = SCRIPT_PARAMS[COMPID_PARAM] if compid is None else compid
    return (own_system if sysid == 0 else sysid), compid


def check_user2(
    params: Sequence[float],
    param: Callable[[str], float | None],
    *,
    sender: tuple[int, int],
    own_system: int,
) -> Verdict:
    """The script's checks on one MAV_CMD_USER_2 (``params``: its seven params) from
    ``sender`` (system, component) to the autopilot ``own_system``; ``param`` reads a
    parameter by name (None: no such parameter), as ``param:get`` does."""
    if tuple(sender) != companion_ids(param, own_system):
        reason = f"denied {sender[0]}/{sender[1]}: not {SYSID_PARAM}/COMPID"
        return Verdict({}, 0, reason, denied=True)
    first = params[6]
    if not _is_integer(first) or not 1 <= first <= MAX_OUTPUT:
        return Verdict({}, 0, f"param7 first output {first} not 1-{MAX_OUTPUT}")
    settings: dict[int, int] = {}
    for slot in range(SLOTS):
        pwm = params[slot]
        if math.isnan(pwm):
            continue
        output = int(first) + slot
        if output > MAX_OUTPUT:
            return Verdict({}, 0, f"output {output} over {MAX_OUTPUT}")
        function = param(f"SERVO{output}_FUNCTION")
        if function is None:
            return Verdict({}, output, f"SERVO{output}_FUNCTION missing")
        if function != 0:
            return Verdict({}, output, f"Channel {output} is already in use")
        low, high = param(f"SERVO{output}_MIN"), param(f"SERVO{output}_MAX")
        if low is None or high is None:
            return Verdict({}, output, f"SERVO{output}_MIN/MAX missing")
        if not _is_integer(pwm) or not low <= pwm <= high:
            return Verdict({}, output, f"out{output} pwm {pwm} not in {low:.0f}-{high:.0f}")
        settings[output] = int(pwm)
    if not settings:
        return Verdict({}, 0, "no PWM in params 1-6")
    return Verdict(settings)


def refusal_text(verdict: Verdict) -> str:
    """The STATUSTEXT the script sends with a refusal (at most 50 characters)."""
    said = verdict.reason if verdict.denied else verdict.reason + "; none set"
    return (STATUSTEXT_PREFIX + said)[:STATUSTEXT_MAX]


class DeniedTexts:
    """When the script says a denied sender: at the first denial, then only once
    ``every_s`` has passed since it last said one (every denial is answered all the same)."""

    def __init__(self, every_s: float = DENIED_TEXT_S) -> None:
        self._every_s = every_s
        self._said_s: float | None = None

    def due(self, now_s: float) -> bool:
        """Whether a denial at ``now_s`` is said (and if so, it counts as said)."""
        if self._said_s is not None and now_s - self._said_s < self._every_s:
            return False
        self._said_s = now_s
        return True

    def reset(self) -> None:
        """The script restarted (a reboot): the next denial is said."""
        self._said_s = None


class LuaScriptTiming:
    """When the script answers: its runs every ``period_ms`` from ``start_s``; a command handed
    over at ``now_s`` is answered ``answer_ms`` after the next run. Pure: times are given."""

    def __init__(
        self,
        start_s: float,
        *,
        period_ms: float = SCRIPT_PERIOD_MS,
        answer_ms: float = SCRIPT_ANSWER_MS,
    ) -> None:
        if not period_ms > 0 or not answer_ms >= 0:
            raise ValueError(f"period_ms={period_ms} must be > 0, answer_ms={answer_ms} >= 0")
        self._start_s = start_s
        self._period_s = period_ms / 1000.0
        self._answer_s = answer_ms / 1000.0

    def answer_s(self, now_s: float) -> float:
        runs = math.ceil(max(0.0, now_s - self._start_s) / self._period_s - 1e-9)
        return self._start_s + runs * self._period_s + self._answer_s
