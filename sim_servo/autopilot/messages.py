"""MAVLink names and fields as the event log writes them (JSON-ready)."""

from __future__ import annotations

import math
from typing import Any

from pymavlink.dialects.v20 import ardupilotmega as mavlink


def param_id(raw: Any) -> str:
    """A PARAM_* ``param_id`` as text (up to its first NUL)."""
    text = raw.decode("ascii", "replace") if isinstance(raw, bytes | bytearray) else str(raw)
    return text.split("\x00", 1)[0]


def message_fields(msg: mavlink.MAVLink_message) -> dict[str, Any]:
    """A message's fields, JSON-ready: text up to its NUL, NaN and infinities as strings."""
    fields = {}
    for name in msg.get_fieldnames():
        value = getattr(msg, name)
        if isinstance(value, bytes | bytearray):
            value = value.decode("ascii", "replace").split("\x00", 1)[0]
        elif isinstance(value, float) and not math.isfinite(value):
            value = str(value)  # JSON has no NaN / inf
        elif isinstance(value, list):
            value = [str(v) if isinstance(v, float) and not math.isfinite(v) else v for v in value]
        fields[name] = value
    return fields


def command_name(command: int) -> str:
    entry = mavlink.enums["MAV_CMD"].get(command)
    return entry.name if entry is not None else str(command)


def result_name(result: int) -> str:
    return mavlink.enums["MAV_RESULT"][result].name


def message_name(msg_id: int) -> str:
    return mavlink.mavlink_map[msg_id].msgname
