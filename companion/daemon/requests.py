"""What the daemon is asked and what it answers: requests, outcomes, replies, and the parsing
of their payloads (a pose, a trajectory). No I/O and no state: :mod:`companion.daemon.service`
queues :class:`Request` objects from every input (MAVLink ``MAV_CMD_USER_1`` and
``MAV_CMD_DO_PAUSE_CONTINUE``, the control socket, the CLI) and answers each with exactly one
:class:`Reply`.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Sequence
from concurrent.futures import Future, InvalidStateError
from dataclasses import dataclass, field
from enum import Enum
from typing import TYPE_CHECKING, Any

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from companion.kinematics import Pose

if TYPE_CHECKING:  # the solver (numba) is not needed to parse or answer a request
    from companion import ik

MAV_CMD_USER_1 = mavlink.MAV_CMD_USER_1  # 31010: our "move the hand to" command
#: 193: ``stop`` (param1 = 0, "pause") and ``resume`` (param1 = 1, "continue") over MAVLink,
#: addressed to our component (a ground station's pause button addresses the autopilot's).
MAV_CMD_DO_PAUSE_CONTINUE = mavlink.MAV_CMD_DO_PAUSE_CONTINUE
#: MAV_CMD_DO_PAUSE_CONTINUE's param1 → the request kind.
MAVLINK_PAUSE_KINDS = {0.0: "stop", 1.0: "resume"}
STATUSTEXT_MAX = 50  # characters in a MAVLink STATUSTEXT
#: common.xml's MAV_RESULT_CANCELLED (6); the pymavlink release we pin predates it.
MAV_RESULT_CANCELLED = getattr(mavlink, "MAV_RESULT_CANCELLED", 6)


class Outcome(Enum):
    """How a target request ended; maps onto MAV_RESULT for MAVLink clients."""

    ACCEPTED = "accepted"
    DENIED = "denied"
    FAILED = "failed"
    TEMPORARILY_REJECTED = "temporarily_rejected"
    CANCELLED = "cancelled"  # superseded by a newer target, or stopped before it moved


MAV_RESULT = {
    Outcome.ACCEPTED: mavlink.MAV_RESULT_ACCEPTED,
    Outcome.DENIED: mavlink.MAV_RESULT_DENIED,
    Outcome.FAILED: mavlink.MAV_RESULT_FAILED,
    Outcome.TEMPORARILY_REJECTED: mavlink.MAV_RESULT_TEMPORARILY_REJECTED,
    Outcome.CANCELLED: MAV_RESULT_CANCELLED,
}
#: The request kinds; ``goto`` and ``trajectory`` are motion targets (the newest one wins).
#: ``stop`` holds the arm until a ``resume`` (or, from the operator's own inputs, a new target
#: or park): see :attr:`Request.local`.
KINDS = ("goto", "trajectory", "park", "stop", "resume")
MOTION_KINDS = frozenset({"goto", "trajectory"})
#: The inputs anyone on the vehicle's link reaches (:attr:`Request.local`).
REMOTE_ORIGINS = frozenset({"mavlink", "unknown"})
#: The kinds that say whether the arm may move at all: not targets, not counted as such.
LATCH_KINDS = frozenset({"stop", "resume"})


@dataclass(frozen=True)
class Reply:
    """The answer to one request: an outcome, a one-line reason, the solve if there was one.

    ``timing`` (targets only): daemon-clock seconds (``time.monotonic`` unless a clock was
    injected; CLOCK_MONOTONIC is system-wide on Linux, so comparable across processes):
    ``received_s`` (handed to the daemon by its input thread), ``solved_s`` (solve returned),
    and once accepted ``first_out_s`` (its first servo update started) and ``acked_s`` (the
    autopilot acknowledged all of that update). ``status()["last_target"]["timing"]`` has the
    same for the newest target.
    """

    outcome: Outcome
    message: str
    solve: ik.IKResult | None = None
    timing: dict[str, float] | None = None
    #: For a ground station's STATUSTEXT (50 characters): the essentials first. None: the
    #: message, shortened at a word.
    brief: str | None = None

    def statustext(self) -> str:
        """At most :data:`STATUSTEXT_MAX` ASCII characters, cut at a word with ``...``."""
        text = (self.brief or self.message).encode("ascii", "replace").decode()
        if len(text) <= STATUSTEXT_MAX:
            return text
        cut = text[: STATUSTEXT_MAX - 3]
        if " " in cut[STATUSTEXT_MAX // 2 :]:
            cut = cut[: cut.rindex(" ")]
        return cut.rstrip(" ,;:.") + "..."

    def as_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {"outcome": self.outcome.value, "message": self.message}
        if self.timing is not None:
            out["timing"] = dict(self.timing)
        if self.solve is not None:
            out["solve"] = {
                "q_deg": list(self.solve.q_deg),
                "pos_err_cm": self.solve.pos_err_cm,
                "ori_err_deg": self.solve.ori_err_deg,
                "elapsed_ms": self.solve.elapsed_ms,
                "converged": self.solve.converged,
            }
        return out


@dataclass(eq=False)
class Request:
    """One request, with the future its :class:`Reply` is set on (exactly once)."""

    kind: str  # goto | trajectory | park | stop | resume
    payload: Any
    direct: bool = False
    received_s: float = 0.0  # daemon clock when submitted
    source: tuple[Any, ...] = ("local",)  # who sent it: ("mavlink", sys, comp), ("socket", n) …
    future: Future = field(default_factory=Future)
    #: Set once the control thread took it from the intake (or it was answered there).
    taken: threading.Event = field(default_factory=threading.Event)

    @property
    def answered(self) -> bool:
        return self.future.done()

    @property
    def origin(self) -> str:
        """The input it came from: ``mavlink``, ``socket``, ``local`` (in-process) ..."""
        return str(self.source[0]) if self.source else "unknown"

    @property
    def local(self) -> bool:
        """From the operator's side of the daemon (the control socket, whose permissions say
        who may connect, or in-process), not from the MAVLink link, where a system id proves
        nothing unless the link is signed."""
        return local_source(self.source)

    def answer(self, reply: Reply) -> bool:
        """Set the reply unless one was set already (from any thread); True if this one was."""
        try:
            self.future.set_result(reply)
        except InvalidStateError:
            return False
        return True


def local_source(source: tuple[Any, ...] | None) -> bool:
    """Whether a request's ``source`` is on the operator's side (:attr:`Request.local`)."""
    return source is not None and len(source) > 0 and str(source[0]) not in REMOTE_ORIGINS


def source_name(source: tuple[Any, ...] | None) -> str:
    """Who asked, for people: ``mavlink 255/190``, ``socket 3``."""
    kind, *ids = source or ("unknown",)
    return f"{kind} {'/'.join(str(i) for i in ids)}".strip()


def stopped_reply(stopped_by: tuple[Any, ...]) -> Reply:
    """The answer to a target from the link while a ``stop`` from ``stopped_by`` holds the arm.

    A stop from the link is released by a ``resume`` from the link; one from the companion (the
    control socket, the CLI) only from the companion: a ground station that keeps retrying, or
    anyone sending from forged system ids, cannot move the arm the operator stopped there."""
    if local_source(stopped_by):
        return Reply(
            Outcome.DENIED,
            f"stopped from the companion ({source_name(stopped_by)}): it resumes there "
            "(armbridge resume, or a new target on its control socket)",
            brief="stopped on the companion: resume there",
        )
    return Reply(
        Outcome.DENIED,
        f"stopped by {source_name(stopped_by)}: send resume "
        "(MAV_CMD_DO_PAUSE_CONTINUE, param1 = 1)",
        brief="stopped: send resume",
    )


def as_pose(value: Any) -> Pose:
    """A :class:`Pose` from a Pose or six numbers; ``ValueError`` names what is wrong."""
    if isinstance(value, Pose):
        return value
    if isinstance(value, str | bytes | bytearray) or not isinstance(value, Sequence):
        raise ValueError(
            f"a pose is 6 numbers (x_cm, y_cm, z_cm, roll_deg, pitch_deg, yaw_deg), got {value!r}"
        )
    return Pose.from_sequence(value)


#: What of a target must be met (the solver's ``TargetMode`` by value): the whole pose; the
#: position only; the position and the hand's z axis pointing along the target orientation's.
TARGET_MODES = ("pose", "position", "position_axis")
#: The frame a target's pose is given in: the arm's base frame, or the world (MAVLink's
#: LOCAL_NED: north-east-down from the autopilot's origin, cm and degrees like every pose
#: here), where the daemon holds the hand while the vehicle moves.
TARGET_FRAMES = ("base", "local_ned")
#: MAV_CMD_USER_1 param7 → (target mode, frame): 0-2 the modes in the base frame; 3-15 are
#: kept for more modes; 16 + mode in LOCAL_NED (16 pose, 17 position, 18 position_axis).
MAVLINK_TARGET_MODES = {
    float(offset + i): (mode, frame)
    for offset, frame in ((0, "base"), (16, "local_ned"))
    for i, mode in enumerate(TARGET_MODES)
}


@dataclass(frozen=True)
class Target:
    """A ``goto``: the pose, what of it must be met (:data:`TARGET_MODES`), and the frame it
    is given in (:data:`TARGET_FRAMES`)."""

    pose: Pose
    mode: str = "pose"
    frame: str = "base"


def as_target(value: Any) -> Target:
    """A :class:`Target` from a Target, a pose (mode ``pose``, base frame), or ``{"pose":
    ..., "mode": ..., "frame": ...}``; ``ValueError`` names what is wrong."""
    if isinstance(value, Target):
        return value
    if isinstance(value, dict):
        mode = value.get("mode", "pose")
        if mode not in TARGET_MODES:
            raise ValueError(
                f"mode={mode!r} is not one of {', '.join(TARGET_MODES)} "
                "(MAV_CMD_USER_1 param7: 0 pose, 1 position, 2 position_axis; +16 in LOCAL_NED)"
            )
        frame = value.get("frame", "base")
        if frame not in TARGET_FRAMES:
            raise ValueError(f"frame={frame!r} is not one of {', '.join(TARGET_FRAMES)}")
        return Target(as_pose(value.get("pose")), mode, frame)
    return Target(as_pose(value))


def mavlink_target_payload(params: Sequence[float], param7: float) -> dict[str, Any]:
    """A USER_1's payload: params 1-6 the pose, param7 the target mode and frame (an unknown
    one is refused by :func:`as_target`, naming it)."""
    known = MAVLINK_TARGET_MODES.get(param7) if math.isfinite(param7) else None
    if known is None:
        return {"pose": tuple(params), "mode": f"param7={param7:g}"}
    mode, frame = known
    return {"pose": tuple(params), "mode": mode, "frame": frame}


#: Points in one trajectory request: the daemon holds them until they are due (40 s of points
#: at 50 Hz).
MAX_TRAJECTORY_POINTS = 2_000
#: The longest a point can be in JSON: seven numbers of at most 24 characters (Python's longest
#: float repr, ``-1.2345678901234567e-300``) with their separators, and its brackets.
POINT_JSON_BYTES = 7 * (24 + 2) + 4


def parse_trajectory(payload: Any) -> list[tuple[float, Pose]]:
    """``[(t_s, pose), ...]`` (a pose: six numbers ``x_cm .. yaw_deg`` or a Pose; the control
    socket turns its rows of seven numbers into these pairs), times never decreasing (points
    at the same time: the last one wins), at most :data:`MAX_TRAJECTORY_POINTS` → the points;
    ``ValueError`` says what is wrong (a point out of order is refused, never re-sorted: a file
    written in the wrong order would otherwise run in an order nobody wrote)."""
    if isinstance(payload, list | tuple) and len(payload) > MAX_TRAJECTORY_POINTS:
        raise ValueError(f"bad trajectory: {len(payload)} points, at most {MAX_TRAJECTORY_POINTS}")
    try:
        points = [(float(t), as_pose(p)) for t, p in payload]
    except (TypeError, ValueError, OverflowError) as exc:
        raise ValueError(f"bad trajectory: {exc}") from exc
    if not points or not all(math.isfinite(t) and t >= 0 for t, _ in points):
        raise ValueError("bad trajectory: times must be finite and >= 0, at least one")
    for i in range(1, len(points)):
        if points[i][0] < points[i - 1][0]:
            raise ValueError(
                f"bad trajectory: point {i}: t_s = {points[i][0]:g} after "
                f"{points[i - 1][0]:g}: times must not go back"
            )
    return points
