"""Strict, typed reading of TOML tables and settings values, shared by every package.

Every problem raises the caller's :class:`FieldError` subclass as ``error(source, field,
problem)``: ``source`` names the file (``"<dict>"``, ``"flags"``, or ``""`` for a value built in
code), ``field`` the setting in dotted form (``joint[2].min_deg``, ``vehicle.mount.xyz_cm[1]``)
and ``problem`` the bad value with the allowed values or range (``0 outside [1, 255]``). Unknown
keys are refused: a typo must not silently fall back to a default.

This package imports nothing of the project, so ``companion``, ``firmware_interface`` and
``sim_servo`` may all use it; each passes its own error class.
"""

from tomlfields.reader import (
    FieldError,
    Table,
    check_boolean,
    check_integer,
    check_number,
    check_numbers,
    is_int,
    is_real,
    load_toml,
    range_text,
)

__all__ = [
    "FieldError",
    "Table",
    "check_boolean",
    "check_integer",
    "check_number",
    "check_numbers",
    "is_int",
    "is_real",
    "load_toml",
    "range_text",
]
