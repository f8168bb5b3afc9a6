"""What the core asks its driver to do: send a command, read a parameter, answer a request."""

from __future__ import annotations

from dataclasses import dataclass

from companion.daemon.requests import Reply, Request


@dataclass(frozen=True)
class SendCommand:
    """A COMMAND_LONG to the autopilot ``target`` (system, component)."""

    target: tuple[int, int]
    command: int
    params: tuple[float, ...]
    confirmation: int = 0


@dataclass(frozen=True)
class ReadParam:
    """A PARAM_REQUEST_READ of ``name`` to the autopilot ``target``."""

    target: tuple[int, int]
    name: str


@dataclass(frozen=True)
class Answer:
    """Answer ``request`` with ``reply`` (the edge sets its future)."""

    request: Request
    reply: Reply


Action = SendCommand | ReadParam | Answer
