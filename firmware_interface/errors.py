"""Exceptions raised by ``firmware_interface``: one base, layered by concern.

FirmwareInterfaceError
├── CalibrationError          (also a ValueError: bad data, refused before anything is sent)
│   ├── NonFiniteAngle
│   ├── AngleOutOfRange
│   └── PwmOutOfRange
├── ConfigurationError        (also a ValueError: bad settings, URL, key file …)
│   ├── SettingError          (one named field; also a tomlfields.FieldError)
│   └── InvalidUrl
└── LinkError
    ├── TransportError        (serial / socket failure; the OS error is the ``__cause__``)
    ├── LinkClosed            (the link was closed, or ended on an error: see ``__cause__``)
    ├── LinkTimeout           (no autopilot, no ACK within the bound)
    └── CommandRejected       (COMMAND_ACK with a result other than ACCEPTED)
        └── ServoOutputUnavailable  (DO_SET_SERVO FAILED: output in use; carries STATUSTEXT)
"""

from __future__ import annotations

from tomlfields import FieldError


class FirmwareInterfaceError(Exception):
    """Base of every error raised by this package."""


class CalibrationError(FirmwareInterfaceError, ValueError):
    """A joint angle or PWM value was refused by the calibration (never clamped)."""


class NonFiniteAngle(CalibrationError):
    """The angle was NaN or infinite."""


class AngleOutOfRange(CalibrationError):
    """The angle is outside the joint's calibrated range."""


class PwmOutOfRange(CalibrationError):
    """The PWM is outside the servo's [pwm_min_us, pwm_max_us]."""


class ConfigurationError(FirmwareInterfaceError, ValueError):
    """A setting (calibration table, URL, key file, dialect name …) is invalid."""


class SettingError(ConfigurationError, FieldError):
    """One field of a setting is invalid: ``SettingError(source, field, problem)``, where
    ``source`` says whose field it is (``joint 'theta2'``) and ``problem`` gives the value and
    the allowed range."""


class InvalidUrl(ConfigurationError):
    """A link URL could not be parsed; the message lists the accepted forms."""


class LinkError(FirmwareInterfaceError):
    """Something went wrong on the MAVLink link."""


class TransportError(LinkError):
    """The byte transport failed (port vanished, socket error)."""


class LinkClosed(LinkError):
    """The link is closed, or ended because of an error (kept as ``__cause__``)."""


class SigningStateError(LinkError):
    """The signing timestamp could not be persisted: nothing is signed beyond what is stored."""


class LinkTimeout(LinkError):
    """A bounded wait on the link expired."""


class CommandRejected(LinkError):
    """The autopilot answered a command with a result other than MAV_RESULT_ACCEPTED.

    ``command`` is the MAV_CMD id, ``result`` the MAV_RESULT value, ``result_name`` its name,
    ``statustext`` the last STATUSTEXT the target sent while the command was in flight (or None).
    """

    def __init__(
        self,
        message: str,
        *,
        command: int,
        result: int,
        result_name: str,
        statustext: str | None = None,
    ) -> None:
        super().__init__(message)
        self.command = command
        self.result = result
        self.result_name = result_name
        self.statustext = statustext


class ServoOutputUnavailable(CommandRejected):
    """ArduPilot refused DO_SET_SERVO on ``output`` (its SERVOn_FUNCTION is not 0/1/51–66).

    ``statustext`` is the STATUSTEXT the autopilot sent just before the ACK, or None.
    This is a configuration problem on the flight controller, not a transient error.
    """

    def __init__(
        self,
        message: str,
        *,
        command: int,
        result: int,
        result_name: str,
        output: int,
        statustext: str | None,
    ) -> None:
        super().__init__(
            message, command=command, result=result, result_name=result_name, statustext=statustext
        )
        self.output = output
