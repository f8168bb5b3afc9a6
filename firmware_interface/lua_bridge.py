"""The ArduPilot Lua bridge we ship (``lua/armbridge_servo.lua``): where it is, and its command.

The script runs on the flight controller (ArduPilot 4.5+, ``SCR_ENABLE = 1``, the file in the SD
card's ``APM/scripts/``) and sets up to :data:`LUA_SLOTS` consecutive servo outputs from one
COMMAND_LONG :data:`MAV_CMD_USER_2`: params 1–6 = PWM µs (NaN: leave the output alone),
param 7 = the first output (1-based). It answers one COMMAND_ACK per command: ACCEPTED, or
FAILED with nothing set (``result_param2`` = the first refused output, 0 for the command itself).
It obeys one sender, the companion: :data:`SYSID_PARAM` / :data:`COMPID_PARAM`, parameters the
script adds itself (defaults 0, the vehicle's own system id, and 191: armbridge's defaults);
anyone else gets DENIED and nothing is set (:func:`sender_fix` says what to set).
The script's own header comment is the full description; the ``ardupilot-lua`` servo dialect
(:mod:`firmware_interface.servo`) speaks it.
"""

from __future__ import annotations

from importlib import resources
from pathlib import Path

#: MAV_CMD_USER_2: blocked from ArduPilot's own handling by the script (``block_command``).
MAV_CMD_USER_2 = 31011
#: Outputs one command sets (params 1–6).
LUA_SLOTS = 6
#: The highest output the script drives (SERVO1 … SERVO32).
LUA_MAX_OUTPUT = 32
SCRIPT_NAME = "armbridge_servo.lua"
#: The script's parameters naming the one sender it obeys: system id (0: the vehicle's own)
#: and component id.
SYSID_PARAM = "ARMB_SYSID"
COMPID_PARAM = "ARMB_COMPID"
#: Why a DENIED answer came, where our ids are not at hand.
SENDER_DENIED = (
    f"the Lua bridge obeys only the sender {SYSID_PARAM} / {COMPID_PARAM} name: set them to "
    f"this companion's link.system_id (0: the vehicle's own) and link.component_id"
)


def sender_fix(system_id: int | None, component_id: int) -> str:
    """What to set on the flight controller when the script answers DENIED to us: our
    ``system_id`` (None: the vehicle's own, which we take unless configured: 0) and
    ``component_id``."""
    sysid = "0 (the vehicle's own system id)" if system_id is None else str(system_id)
    return (
        f"set {SYSID_PARAM} = {sysid} and {COMPID_PARAM} = {component_id} on the flight "
        f"controller: the Lua bridge obeys only the sender they name"
    )


def script_path() -> Path:
    """The installed script's path (copy it to ``APM/scripts/`` on the SD card)."""
    return Path(str(resources.files("firmware_interface").joinpath("lua", SCRIPT_NAME)))


def script_text() -> str:
    """The script's source."""
    return resources.files("firmware_interface").joinpath("lua", SCRIPT_NAME).read_text("utf-8")
