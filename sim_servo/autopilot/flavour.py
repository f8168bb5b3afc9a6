"""What differs between the firmwares: one flavour object per firmware.

The parts of the autopilot ask their flavour (:class:`ArduPilot` or :class:`Px4`) wherever the
two firmwares behave differently — the parameter names and how values are carried, when a
received frame is handled, how frames leave, routing, what an output shows, arming and safety,
the extra commands and streams — instead of testing the flavour's name.

In short, PX4 as measured on PX4 SITL (main of 2026-03, SIH quadrotor) against ArduCopter:
HEARTBEAT with MAV_AUTOPILOT_PX4 and ``MAV_MODE_FLAG_SAFETY_ARMED`` while armed; parameters
INT32, sent bytewise, ``PWM_MAIN_FUNCn`` 0 by default except motors 1–4; DO_SET_SERVO
UNSUPPORTED, DO_SET_ACTUATOR and arming instead, on the commander's cycle; SYSTEM_TIME at 1 Hz
and no SERVO_OUTPUT_RAW floor; frames handled on arrival and sent on each link's loop pass;
outputs dead until armed or prearmed, no safety switch, no Lua scripting.
"""

from __future__ import annotations

import math
import struct
from abc import ABC, abstractmethod
from collections.abc import Callable
from typing import TYPE_CHECKING

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from sim_servo.autopilot.params import Param, ParamTable
from sim_servo.config import (
    ARDUPILOT_PWM_MAX_US,
    ARDUPILOT_PWM_MIN_US,
    ARDUPILOT_PWM_TRIM_US,
    OUTPUT_COUNT,
    PX4_ACTUATOR_SET_COUNT,
    PX4_ACTUATOR_SET_FIRST_FUNCTION,
    PX4_DISARMED_PWM_US,
    PX4_MOTOR_FUNCTIONS,
    PX4_PREARM_DELAY_S,
    PX4_PREARM_MODES,
    PX4_PWM_MAX_US,
    PX4_PWM_MIN_US,
    SimConfig,
)
from sim_servo.errors import SimConfigError
from sim_servo.linktiming import LinkOutput, LoopLinkOutput

if TYPE_CHECKING:
    from sim_servo.autopilot.commands import Command
    from sim_servo.autopilot.outputs import Outputs
    from sim_servo.autopilot.routing import Router
    from sim_servo.autopilot.state import AutopilotState
    from sim_servo.autopilot.wire import Wire

CommandHandler = Callable[["Command", float], int]

INT32_RANGE = (-(2**31), 2**31 - 1)
#: PX4: the commands its commander handles, answered on the commander's next cycle.
PX4_COMMANDER_COMMANDS = frozenset(
    {mavlink.MAV_CMD_COMPONENT_ARM_DISARM, mavlink.MAV_CMD_DO_SET_ACTUATOR}
)
#: PX4's defaults: forwarding on for instance 0 (TELEM1), off for the others.
PX4_FORWARD_DEFAULTS = {"MAV_0_FORWARD": 1, "MAV_1_FORWARD": 0}


class Flavour(ABC):
    """The rules one firmware has its own way."""

    #: The ``flavour`` setting's name for it.
    name: str
    #: HEARTBEAT's ``autopilot``.
    autopilot_type: int
    #: The stream this firmware has and the other has not.
    own_stream_id: int
    #: Whether the outputs are driven to their idle PWM at boot (the horns go there).
    drives_outputs_at_boot: bool

    # -- parameters --------------------------------------------------------------------------

    @abstractmethod
    def default_params(self, config: SimConfig) -> dict[str, Param]:
        """The parameter table at its defaults, in index order (functions from ``config``)."""

    @abstractmethod
    def check_param(self, name: str, value: int) -> None:
        """Raise :class:`SimConfigError` for a configured value the firmware refuses."""

    @abstractmethod
    def function_param(self, output: int) -> str: ...

    @abstractmethod
    def limit_params(self, output: int) -> tuple[str, str]: ...

    @abstractmethod
    def encode_param_value(self, param: Param) -> float:
        """PARAM_VALUE's ``param_value`` for ``param``."""

    @abstractmethod
    def decode_param_value(self, param: Param, value: float) -> int | None:
        """PARAM_SET's ``param_value`` as the parameter's value (None: ignored)."""

    @abstractmethod
    def param_set_index(self, names: list[str], name: str) -> int:
        """The ``param_index`` of the PARAM_VALUE that answers a PARAM_SET of ``name``."""

    # -- links and routing -------------------------------------------------------------------

    @abstractmethod
    def new_link_output(self, config: SimConfig, boot_s: float) -> LinkOutput | LoopLinkOutput:
        """A link's outgoing side: when its frames leave."""

    @abstractmethod
    def rx_due_s(self, state: AutopilotState, now_s: float) -> float:
        """When a frame received at ``now_s`` is handled."""

    @abstractmethod
    def make_router(self, state: AutopilotState, wire: Wire, params: ParamTable) -> Router: ...

    # -- outputs -----------------------------------------------------------------------------

    @abstractmethod
    def armed_at_start(self, config: SimConfig) -> bool: ...

    @abstractmethod
    def outputs_live(self, outputs: Outputs) -> bool:
        """Whether the outputs (as a whole) are live: not held by disarm or safety."""

    @abstractmethod
    def live(self, outputs: Outputs, output: int) -> bool:
        """Whether ``output`` has pulses (outside a reboot)."""

    @abstractmethod
    def output_us(self, outputs: Outputs, output: int) -> tuple[int, int]:
        """(reported, physical) PWM of ``output`` in the current state (outside a reboot)."""

    @abstractmethod
    def safety_at_boot(self, params: ParamTable) -> bool:
        """Whether the safety switch is on at each boot."""

    @abstractmethod
    def prearm_due_s(self, params: ParamTable, boot_s: float) -> float | None:
        """When this boot prearms (None: never)."""

    #: Whether the firmware arms and disarms (MAV_CMD_COMPONENT_ARM_DISARM, the query ``arm``).
    arms: bool
    #: Whether it has a safety switch (the queries ``safety_on`` / ``safety_off``).
    has_safety_switch: bool

    # -- commands ----------------------------------------------------------------------------

    @abstractmethod
    def command_handlers(self, outputs: Outputs) -> dict[int, CommandHandler]:
        """The output commands this firmware has."""

    @abstractmethod
    def commander_due_s(
        self, config: SimConfig, command: int, now_s: float, boot_s: float
    ) -> float | None:
        """When a command is acted on and answered (None: at once)."""

    #: Whether armbridge's Lua bridge script can run (ArduPilot's scripting).
    runs_lua: bool


class ArduPilot(Flavour):
    """ArduCopter (source files in ArduPilot/ardupilot)."""

    name = "ardupilot"
    autopilot_type = mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA
    own_stream_id = mavlink.MAVLINK_MSG_ID_SYS_STATUS
    drives_outputs_at_boot = False
    arms = False
    has_safety_switch = True
    runs_lua = True

    def default_params(self, config: SimConfig) -> dict[str, Param]:
        params: dict[str, Param] = {}
        int16 = mavlink.MAV_PARAM_TYPE_INT16
        for n in range(1, OUTPUT_COUNT + 1):
            for suffix, value in (
                ("FUNCTION", config.functions[n]),
                ("MIN", ARDUPILOT_PWM_MIN_US),
                ("MAX", ARDUPILOT_PWM_MAX_US),
                ("TRIM", ARDUPILOT_PWM_TRIM_US),
            ):
                name = f"SERVO{n}_{suffix}"
                params[name] = Param(name, value, int16, -32768, 32767)
        # AP_BoardConfig: the safety switch's state at boot (boards default 1; off here so a
        # bench vehicle's outputs are live) and the outputs it leaves alone.
        params["BRD_SAFETY_DEFLT"] = Param(
            "BRD_SAFETY_DEFLT", 0, mavlink.MAV_PARAM_TYPE_INT8, -128, 127
        )
        params["BRD_SAFETY_MASK"] = Param(
            "BRD_SAFETY_MASK", 0, mavlink.MAV_PARAM_TYPE_INT32, *INT32_RANGE
        )
        return params

    def check_param(self, name: str, value: int) -> None:
        pass  # the parameters' type ranges are the only limits

    def function_param(self, output: int) -> str:
        return f"SERVO{output}_FUNCTION"

    def limit_params(self, output: int) -> tuple[str, str]:
        return f"SERVO{output}_MIN", f"SERVO{output}_MAX"

    def encode_param_value(self, param: Param) -> float:
        return float(param.value)

    def decode_param_value(self, param: Param, value: float) -> int | None:
        if not math.isfinite(value):
            return None
        # GCS_Param: add 0.01 away from zero before truncating, then constrain to the type.
        nudged = value + (0.01 if value >= 0 else -0.01)
        return int(min(max(nudged, param.low), param.high))

    def param_set_index(self, names: list[str], name: str) -> int:
        return -1

    def new_link_output(self, config: SimConfig, boot_s: float) -> LinkOutput | LoopLinkOutput:
        return LinkOutput(config.link_timing)

    def rx_due_s(self, state: AutopilotState, now_s: float) -> float:
        # ArduPilot reads its links once per main-loop pass (GCS::update_receive), so a frame
        # waits for the next pass before it is handled and answered.
        return state.next_tick_s(now_s)

    def make_router(self, state: AutopilotState, wire: Wire, params: ParamTable) -> Router:
        from sim_servo.autopilot.routing import ArduPilotRouter

        return ArduPilotRouter(state, wire)

    def armed_at_start(self, config: SimConfig) -> bool:
        return False

    def outputs_live(self, outputs: Outputs) -> bool:
        return not outputs.safety_on

    def live(self, outputs: Outputs, output: int) -> bool:
        return not outputs.safety_on or bool(outputs.safety_mask >> (output - 1) & 1)

    def output_us(self, outputs: Outputs, output: int) -> tuple[int, int]:
        # SERVO_OUTPUT_RAW reads back what the output driver was told, while the safety switch
        # keeps an output out of BRD_SAFETY_MASK without pulses.
        reported = outputs.commanded_us[output]
        return reported, reported if outputs.live(output) else 0

    def safety_at_boot(self, params: ParamTable) -> bool:
        return params["BRD_SAFETY_DEFLT"].value != 0

    def prearm_due_s(self, params: ParamTable, boot_s: float) -> float | None:
        return None

    def command_handlers(self, outputs: Outputs) -> dict[int, CommandHandler]:
        return {mavlink.MAV_CMD_DO_SET_SERVO: outputs.do_set_servo}

    def commander_due_s(
        self, config: SimConfig, command: int, now_s: float, boot_s: float
    ) -> float | None:
        return None


class Px4(Flavour):
    """PX4 as measured on SITL (main of 2026-03, SIH quadrotor)."""

    name = "px4"
    autopilot_type = mavlink.MAV_AUTOPILOT_PX4
    own_stream_id = mavlink.MAVLINK_MSG_ID_ACTUATOR_OUTPUT_STATUS
    drives_outputs_at_boot = True
    arms = True
    has_safety_switch = False
    runs_lua = False

    def default_params(self, config: SimConfig) -> dict[str, Param]:
        params: dict[str, Param] = {}
        int32 = mavlink.MAV_PARAM_TYPE_INT32
        for n in range(1, OUTPUT_COUNT + 1):
            for prefix, value in (
                ("PWM_MAIN_FUNC", config.functions[n]),
                ("PWM_MAIN_MIN", PX4_PWM_MIN_US),
                ("PWM_MAIN_MAX", PX4_PWM_MAX_US),
                ("PWM_MAIN_DIS", PX4_DISARMED_PWM_US),
            ):
                name = f"{prefix}{n}"
                params[name] = Param(name, value, int32, *INT32_RANGE)
        for name, value in (("COM_PREARM_MODE", 0), *PX4_FORWARD_DEFAULTS.items()):
            params[name] = Param(name, value, int32, *INT32_RANGE)
        return params

    def check_param(self, name: str, value: int) -> None:
        if name == "COM_PREARM_MODE" and value not in PX4_PREARM_MODES:
            raise SimConfigError(f"COM_PREARM_MODE={value}; valid: {list(PX4_PREARM_MODES)}")

    def function_param(self, output: int) -> str:
        return f"PWM_MAIN_FUNC{output}"

    def limit_params(self, output: int) -> tuple[str, str]:
        return f"PWM_MAIN_MIN{output}", f"PWM_MAIN_MAX{output}"

    def encode_param_value(self, param: Param) -> float:
        # PX4 sends integer parameters bytewise: the int32's bits read as a float.
        return float(struct.unpack("<f", struct.pack("<i", param.value))[0])

    def decode_param_value(self, param: Param, value: float) -> int | None:
        return int(struct.unpack("<i", struct.pack("<f", value))[0])

    def param_set_index(self, names: list[str], name: str) -> int:
        return names.index(name)

    def new_link_output(self, config: SimConfig, boot_s: float) -> LinkOutput | LoopLinkOutput:
        return LoopLinkOutput(config.px4_timing.mavlink_loop_ms / 1000.0, boot_s)

    def rx_due_s(self, state: AutopilotState, now_s: float) -> float:
        return now_s  # PX4's receiver thread handles a frame as it is read

    def make_router(self, state: AutopilotState, wire: Wire, params: ParamTable) -> Router:
        from sim_servo.autopilot.routing import Px4Router

        return Px4Router(state, wire, params)

    def armed_at_start(self, config: SimConfig) -> bool:
        return config.armed

    def outputs_live(self, outputs: Outputs) -> bool:
        return outputs.armed or outputs.prearmed

    def live(self, outputs: Outputs, output: int) -> bool:
        return outputs.armed or outputs.prearmed

    def output_us(self, outputs: Outputs, output: int) -> tuple[int, int]:
        """PX4 reports what it outputs: the disarmed PWM (PWM_MAIN_DISn) unless live; live, an
        actuator-set output shows its slot (NaN: never set, still disarmed), a motor its
        minimum once armed."""
        params = outputs.params
        disarmed = params[f"PWM_MAIN_DIS{output}"].value
        pwm = disarmed
        if outputs.live(output):
            function = params.function(output)
            low, high = params.pwm_limits(output)
            slot = function - PX4_ACTUATOR_SET_FIRST_FUNCTION
            if 0 <= slot < PX4_ACTUATOR_SET_COUNT:
                value = outputs.actuator_values[slot]
                if not math.isnan(value):
                    pwm = min(max(px4_actuator_pwm_us(value), low), high)
            elif function in PX4_MOTOR_FUNCTIONS.values() and outputs.armed:
                pwm = low  # motors idle at their minimum once armed
        return pwm, pwm

    def safety_at_boot(self, params: ParamTable) -> bool:
        return False

    def prearm_due_s(self, params: ParamTable, boot_s: float) -> float | None:
        """``COM_PREARM_MODE`` 1 (safety button) is mode 2 here: the simulated PX4 has no
        safety button, as SITL."""
        if params["COM_PREARM_MODE"].value not in (1, 2):
            return None
        return boot_s + PX4_PREARM_DELAY_S

    def command_handlers(self, outputs: Outputs) -> dict[int, CommandHandler]:
        return {
            mavlink.MAV_CMD_DO_SET_ACTUATOR: outputs.do_set_actuator,
            mavlink.MAV_CMD_COMPONENT_ARM_DISARM: outputs.arm_disarm,
        }

    def commander_due_s(
        self, config: SimConfig, command: int, now_s: float, boot_s: float
    ) -> float | None:
        period_s = config.px4_timing.commander_period_ms / 1000.0
        if command not in PX4_COMMANDER_COMMANDS or period_s <= 0.0:
            return None
        # Commander.cpp handles it (and answers) on its next cycle.
        cycles = math.floor(round((now_s - boot_s) / period_s, 9)) + 1
        return boot_s + cycles * period_s


FLAVOURS: dict[str, type[Flavour]] = {"ardupilot": ArduPilot, "px4": Px4}


def flavour_for(config: SimConfig) -> Flavour:
    """The flavour object for ``config.flavour``."""
    try:
        return FLAVOURS[config.flavour]()
    except KeyError:
        raise SimConfigError(f"flavour={config.flavour!r}; valid: {list(FLAVOURS)}") from None


def px4_actuator_pwm_us(value: float) -> int:
    """PX4's PWM for an actuator value: 1500 + 500·v rounded half away from zero (measured on
    SITL, whose outputs span 1000–2000); the caller clamps it to the output's min/max."""
    exact = 1500.0 + 500.0 * min(max(value, -1e6), 1e6)
    return int(math.copysign(math.floor(abs(exact) + 0.5), exact))
