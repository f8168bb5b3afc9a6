"""Exceptions raised by ``sim_servo``: one base, layered by concern.

SimError
├── SimConfigError     (also a ValueError: a bad flag, TOML field or value)
│   └── SimFieldError  (one named field; also a tomlfields.FieldError)
├── ServoPwmOutOfRange (also a ValueError: a horn position outside its joint's PWM range)
└── SimIOError         (a socket / pty failure; the OS error is the ``__cause__``)
"""

from __future__ import annotations

from tomlfields import FieldError


class SimError(Exception):
    """Base of every error raised by the simulator."""


class SimConfigError(SimError, ValueError):
    """A setting is invalid; the message names the value and the allowed range."""


class SimFieldError(SimConfigError, FieldError):
    """One setting is invalid: ``SimFieldError(source, field, problem)``, ``field`` dotted as in
    the TOML file (``arm.pwm_min_us``, ``vehicle.mount.xyz_cm[2]``), ``source`` the file
    (``""`` for a value built in code)."""


class ServoPwmOutOfRange(SimError, ValueError):
    """A servo's pulse width (µs) is outside its joint's PWM range: the joint has no angle."""


class SimIOError(SimError):
    """An endpoint (socket, pty, query socket) failed."""
