"""Exceptions of the arm side of the bridge, all under one base.

``ArmError`` is the root; callers that only want "anything the arm code refused" catch it.
Configuration problems are also ``ValueError`` so that plain ``except ValueError`` still works.
"""

from __future__ import annotations

from tomlfields import FieldError


class ArmError(Exception):
    """Base of every error raised by :mod:`companion`."""


class ConfigError(ArmError, FieldError):
    """A configuration file (arm description or daemon config) is malformed.

    ``source`` names the file (or ``"<dict>"``), ``field`` the offending field in dotted form
    (``joint[2].min_deg``), and the message states the allowed values.
    """


class ArmConfigError(ConfigError):
    """An arm description (TOML file or dict) is malformed."""


class KinematicsError(ArmError):
    """Base for kinematic failures (unreachable targets, limit violations)."""


class JointLimitError(KinematicsError, ValueError):
    """A joint angle lies outside its allowed range."""


class UnreachableTarget(KinematicsError):
    """No joint configuration within the limits reaches the target within tolerance."""
