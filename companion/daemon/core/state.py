"""The state the core's parts share, and who writes what.

:class:`ArmState` holds what more than one part reads: the acknowledged pose and PWMs, the
refused outputs, a step still to confirm, the updates in flight, the link, the counters. Each
field names the part that writes it; the others only read it.
"""

from __future__ import annotations

import collections
import math
from dataclasses import dataclass, field
from typing import Any

from companion.daemon.requests import Reply, Request
from firmware_interface.updates import ServoCommand, UpdateTracker

#: The counters status shows, each incremented by the part named.
COUNTER_NAMES = (
    "targets",  # the dispatcher: goto requests taken
    "solved",  # motion, world: solves run
    "accepted",  # status (answers): by outcome
    "denied",
    "failed",
    "temporarily_rejected",
    "cancelled",
    "servo_updates",  # updates: acknowledged in full
    "servo_errors",  # updates: ended unanswered or miscounted
    "refused_outputs",  # updates
    "foreign_frames",  # the dispatcher: frames from another system
    "forged_frames",  # watch: frames from the autopilot's ids that contradict its own
    "autopilot_reboots",  # watch
    "internal_errors",  # the dispatcher
    "keepout_refusals",  # keep-out gate
    "foreign_commands",  # the outputs' truth: an output set by another sender
)


@dataclass(eq=False)
class AwaitingFirstStep:
    """An accepted target waiting for its first step to be acknowledged."""

    request: Request
    reply: Reply  # what it will be answered once its first step is acknowledged


@dataclass(eq=False)
class Flight:
    """An update on its way: the joints it moves to, and its ACK accounting.

    All its commands go out at once (``tracker`` counts their ACKs). Those whose fate that
    leaves unknown are then sent **one at a time** (``pending``), each waiting for its own ACK
    (unambiguous) and re-sent up to ``command_retries`` times: on a lossy link a lost frame
    then costs one command's round trip, not the whole update's.
    """

    step_deg: tuple[float, ...]
    pwm_by_output: dict[int, int]  # the whole step (outputs already there are not sent)
    sent_outputs: frozenset[int]
    tracker: UpdateTracker
    sent_s: float
    waiting: list[AwaitingFirstStep] = field(default_factory=list)  # first step is this one
    timeout_s: float = 0.5  # per attempt
    pending: list[ServoCommand] = field(default_factory=list)  # still to confirm, in order
    attempt: int = 0  # sends of the command being confirmed one at a time (0: the batch)
    accepted: dict[int, int] = field(default_factory=dict)
    refused: dict[int, str] = field(default_factory=dict)
    #: The steps of updates ahead of it that ended unanswered (the outputs may hold them).
    folded: list[tuple[float, ...]] = field(default_factory=list)
    seq: int = 0  # updates sent before it since the start
    #: Its outcome is taken, the commands to confirm one at a time wait for the outputs' truth
    #: to allow them (see ``OutputsTruth.may_confirm``).
    deferred: bool = False


@dataclass(eq=False)
class ArmState:
    """What the parts share (see the module docstring); each field says who writes it."""

    #: The arm's outputs, in joint order (the dispatcher, from the settings).
    outputs: tuple[int, ...]
    #: Per joint: the acknowledged angle (before any ACK: the assumed start pose). Updates
    #: write it as steps are acknowledged; PX4's outputs where a readback shows the joint
    #: (nothing acknowledged yet, or an output found not live).
    position: list[float]
    #: A readback placed a joint (the outputs' truth: at the start, or set by another sender),
    #: so :attr:`position` says where the outputs are even before anything of ours was sent.
    placed_by_readback: bool = False
    #: Per joint, the lowest and the highest angle the pose file said the outputs may hold
    #: (None: nothing restored, or every output acknowledged since). Until the outputs are
    #: sent to the middle it is what they may hold (a joint placed by a readback since: where
    #: it shows), and the file keeps it (a safety switch may hold them anywhere in it).
    restored: tuple[list[float], list[float]] | None = None
    #: Per output, the PWM the autopilot accepted (updates; cleared by watch on a loss, and
    #: by PX4's outputs for one found not live).
    acked_pwm: dict[int, int] = field(default_factory=dict)
    #: Outputs the autopilot refused, with its reason (updates).
    refused: dict[int, str] = field(default_factory=dict)
    #: A step sent whose outputs are not all confirmed: re-sent before moving on, and at once
    #: (``resend_at_once``) after a link loss or a reboot. Updates write it; the outputs' truth
    #: sets the pose to re-send after a loss.
    unconfirmed: tuple[float, ...] | None = None
    resend_at_once: bool = False
    #: Updates on their way, oldest first (updates; cleared by watch on a loss).
    flights: collections.deque[Flight] = field(default_factory=collections.deque)
    #: When the last update went out (-inf: none yet), and how many went out (updates).
    last_step_s: float = -math.inf
    updates_sent: int = 0
    #: The link to the pinned autopilot is up (watch).
    link_up: bool = False
    #: The source of the ``stop`` the arm holds for until a ``resume`` (None: not stopped).
    #: The dispatcher sets and clears it; a reload keeps it, a restart starts without.
    stopped_by: tuple[Any, ...] | None = None
    counters: dict[str, int] = field(default_factory=lambda: dict.fromkeys(COUNTER_NAMES, 0))

    def settled(self) -> bool:
        """Nothing in flight or to confirm, and every output acknowledged (or refused)."""
        return (
            self.unconfirmed is None
            and not self.flights
            and all(o in self.acked_pwm or o in self.refused for o in self.outputs)
        )

    def commanded(self) -> tuple[float, ...]:
        """The step commanded last: what the outputs will hold once the updates land."""
        return self.flights[-1].step_deg if self.flights else tuple(self.position)

    @property
    def ever_sent(self) -> bool:
        return self.last_step_s > -math.inf
