"""The armbridge service: targets in, servo PWM out.

Modules: :mod:`~companion.daemon.service` (``ArmDaemon``: the control loop and safety rules),
:mod:`~companion.daemon.requests` (requests, outcomes, replies, payload parsing),
:mod:`~companion.daemon.config` (the TOML config and its validation),
:mod:`~companion.daemon.control_socket` (the JSON-lines control socket) and
:mod:`~companion.daemon.client` (its client),
:mod:`~companion.daemon.motion` (joint speed limit), :mod:`~companion.daemon.systemd`
(sd_notify), :mod:`~companion.daemon.run` (``armbridge run``), :mod:`~companion.daemon.demo`
(``armbridge demo``), :mod:`~companion.daemon.cli` (the ``armbridge`` command).

The public API is listed in ``__all__``. Nothing is imported until a name is used, so that the
command line starts without loading the solver.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from companion.daemon.cli import main
    from companion.daemon.client import request
    from companion.daemon.config import DaemonConfig, load_config, parse_config
    from companion.daemon.requests import Outcome, Reply
    from companion.daemon.service import ArmDaemon

_WHERE = {
    "ArmDaemon": "service",
    "DaemonConfig": "config",
    "Outcome": "requests",
    "Reply": "requests",
    "load_config": "config",
    "main": "cli",
    "parse_config": "config",
    "request": "client",
}
__all__ = [
    "ArmDaemon",
    "DaemonConfig",
    "Outcome",
    "Reply",
    "load_config",
    "main",
    "parse_config",
    "request",
]


def __getattr__(name: str) -> Any:
    if name not in _WHERE:
        raise AttributeError(f"module 'companion.daemon' has no attribute {name!r}")
    return getattr(importlib.import_module(f"companion.daemon.{_WHERE[name]}"), name)
