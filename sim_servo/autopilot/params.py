"""The parameter table and the PARAM_* messages (GCS_Param.cpp; PX4's mavlink_parameters.cpp).

Unknown names get no reply; the answer is PARAM_VALUE, deferred to the next main-loop pass. A
set applies at once, without a reboot; parameters keep their values through a reboot. How a
value is carried and which index a set answers with are the flavour's
(:mod:`sim_servo.autopilot.flavour`): ArduPilot's integer parameters take ``value + 0.01`` (away
from zero) truncated, and a set or a read by name is answered with ``param_index`` −1 (65535 on
the wire, a uint16); PX4 carries an INT32's bytes in the float and answers with the index.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from sim_servo.autopilot.messages import param_id
from sim_servo.autopilot.state import AutopilotState
from sim_servo.errors import SimConfigError
from sim_servo.lua_bridge import SCRIPT_PARAMS

if TYPE_CHECKING:
    from sim_servo.autopilot.wire import Wire


#: The integers a float32 holds exactly: the range given to a script's float parameters.
FLOAT_INTS = (-(2**24), 2**24)


@dataclass
class Param:
    name: str
    value: int
    param_type: int  # MAV_PARAM_TYPE
    low: int
    high: int


class ParamTable(Mapping[str, Param]):
    """The flavour's parameters by name, in their index order, with the configured values;
    parameters keep their values through a reboot."""

    def __init__(self, state: AutopilotState) -> None:
        self._flavour = state.flavour
        config = state.config
        params = self._flavour.default_params(config)
        if config.lua_script:
            # The Lua bridge script's own (param:add_table): a script's parameters are floats
            # (REAL32 on the wire), held here as integers like every parameter.
            for name, default in SCRIPT_PARAMS.items():
                params[name] = Param(name, default, mavlink.MAV_PARAM_TYPE_REAL32, *FLOAT_INTS)
        for name, value in config.params.items():
            param = params.get(name)
            if param is None:
                raise SimConfigError(f"parameter {name!r} unknown to the {config.flavour} flavour")
            if not param.low <= value <= param.high:
                raise SimConfigError(
                    f"parameter {name}={value} outside [{param.low}, {param.high}]"
                )
            self._flavour.check_param(name, value)
            param.value = value
        self._params = params
        #: The names in index order (PARAM_REQUEST_READ by index, PARAM_REQUEST_LIST).
        self.names = list(params)

    def __getitem__(self, name: str) -> Param:
        return self._params[name]

    def __iter__(self) -> Iterator[str]:
        return iter(self._params)

    def __len__(self) -> int:
        return len(self._params)

    def function(self, output: int) -> int:
        """The output's function (SERVOn_FUNCTION, PWM_MAIN_FUNCn)."""
        return self._params[self._flavour.function_param(output)].value

    def pwm_limits(self, output: int) -> tuple[int, int]:
        """The output's (minimum, maximum) PWM in µs."""
        low, high = self._flavour.limit_params(output)
        return self._params[low].value, self._params[high].value


class ParamService:
    """PARAM_SET, PARAM_REQUEST_READ and PARAM_REQUEST_LIST. A set applies at once:
    ``on_change`` brings what depends on parameters (outputs, prearm) up to date."""

    def __init__(
        self,
        state: AutopilotState,
        table: ParamTable,
        wire: Wire,
        on_change: Callable[[float], None],
    ) -> None:
        self._state = state
        self._table = table
        self._wire = wire
        self._on_change = on_change

    def handlers(self) -> dict[str, Callable[[Any, float, int], None]]:
        return {
            "PARAM_SET": self.on_param_set,
            "PARAM_REQUEST_READ": self.on_param_request_read,
            "PARAM_REQUEST_LIST": self.on_param_request_list,
        }

    def _for_us(self, msg: Any) -> bool:
        return bool(msg.target_system in (0, self._state.config.system_id))

    def _param_value(self, param: Param, index: int) -> mavlink.MAVLink_message:
        # param_index is a uint16_t on the wire: ArduPilot's -1 arrives as 65535.
        return self._wire.encoder.param_value_encode(
            param.name.encode(),
            self._state.flavour.encode_param_value(param),
            param.param_type,
            len(self._table),
            index & 0xFFFF,
        )

    def on_param_set(self, msg: Any, now_s: float, channel: int) -> None:
        if not self._for_us(msg):
            return
        name = param_id(msg.param_id)
        param = self._table.get(name)
        if param is None:
            self._state.emit(now_s, "param_unknown", name=name)
            return
        value = self._state.flavour.decode_param_value(param, msg.param_value)
        if value is None:
            return
        old = param.value
        param.value = value
        self._state.emit(now_s, "param_set", name=name, old=old, value=value)
        # Applied at once (PX4: functions, limits, prearm mode; here also BRD_SAFETY_MASK).
        self._on_change(now_s)
        index = self._state.flavour.param_set_index(self._table.names, name)
        self._wire.defer(self._param_value(param, index), now_s)

    def on_param_request_read(self, msg: Any, now_s: float, channel: int) -> None:
        if not self._for_us(msg):
            return
        names = self._table.names
        if msg.param_index == -1:
            name = param_id(msg.param_id)
            index = -1
        elif 0 <= msg.param_index < len(names):
            name = names[msg.param_index]
            index = msg.param_index
        else:
            return
        param = self._table.get(name)
        if param is None:
            self._state.emit(now_s, "param_unknown", name=name)
            return
        self._wire.defer(self._param_value(param, index), now_s)

    def on_param_request_list(self, msg: Any, now_s: float, channel: int) -> None:
        if not self._for_us(msg):
            return
        for index, name in enumerate(self._table.names):
            self._wire.defer(self._param_value(self._table[name], index), now_s)
