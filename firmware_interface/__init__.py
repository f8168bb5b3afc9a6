"""Companion ↔ flight-controller interface: joint→PWM calibration and a MAVLink 2 link.

Typical use by the daemon::

    calibration = default_calibration()                     # or calibration_from_ranges(...)
    with MavlinkLink.open("/dev/ttyACM0,921600") as link:
        link.wait_for_autopilot(timeout_s=10.0)
        commands = CommandSender(link, timeout_s=0.5, retries=2)
        servos = make_servo_dialect("ardupilot", commands, calibration)
        servos.send_angles([0, 90, 0, 0, 0, 10])
"""

from firmware_interface.calibration import (
    TABLE2_RANGES_DEG,
    ArmCalibration,
    JointCalibration,
    calibration_from_ranges,
    default_calibration,
)
from firmware_interface.commands import CommandOutcome, CommandSender
from firmware_interface.errors import (
    AngleOutOfRange,
    CalibrationError,
    CommandRejected,
    ConfigurationError,
    FirmwareInterfaceError,
    InvalidUrl,
    LinkClosed,
    LinkError,
    LinkTimeout,
    NonFiniteAngle,
    PwmOutOfRange,
    ServoOutputUnavailable,
    SettingError,
    SigningStateError,
    TransportError,
)
from firmware_interface.link import (
    AutopilotInfo,
    LinkConfig,
    LinkState,
    LinkStats,
    MavlinkLink,
)
from firmware_interface.link_budget import LinkBudget, UpdateCost, link_budget, update_cost
from firmware_interface.readback import OutputReadback
from firmware_interface.servo import (
    SERVO_DIALECTS,
    ArduPilotLuaServoDialect,
    ArduPilotServoDialect,
    Px4ServoDialect,
    ServoDialect,
    make_servo_dialect,
)
from firmware_interface.signing import SigningConfig, load_key
from firmware_interface.transport import Transport, open_transport, parse_url

__all__ = [
    "TABLE2_RANGES_DEG",
    "ArmCalibration",
    "JointCalibration",
    "calibration_from_ranges",
    "default_calibration",
    "CommandOutcome",
    "CommandSender",
    "AngleOutOfRange",
    "CalibrationError",
    "CommandRejected",
    "ConfigurationError",
    "FirmwareInterfaceError",
    "InvalidUrl",
    "LinkClosed",
    "LinkError",
    "LinkTimeout",
    "NonFiniteAngle",
    "PwmOutOfRange",
    "SettingError",
    "ServoOutputUnavailable",
    "SigningStateError",
    "TransportError",
    "AutopilotInfo",
    "LinkConfig",
    "LinkState",
    "LinkStats",
    "MavlinkLink",
    "LinkBudget",
    "UpdateCost",
    "link_budget",
    "update_cost",
    "OutputReadback",
    "SERVO_DIALECTS",
    "ArduPilotLuaServoDialect",
    "ArduPilotServoDialect",
    "Px4ServoDialect",
    "ServoDialect",
    "make_servo_dialect",
    "SigningConfig",
    "load_key",
    "Transport",
    "open_transport",
    "parse_url",
]
