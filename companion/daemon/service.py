"""The companion daemon: target in, deadline-bounded IK, speed-limited safe PWM out.

This module is the edge around :class:`~companion.daemon.core.ControlCore` (the rules live
there): it owns the threads, the link and the clock.

* the link's **reader thread** (firmware_interface) never waits on anything: a MAVLink
  COMMAND_LONG ``MAV_CMD_USER_1`` or ``MAV_CMD_DO_PAUSE_CONTINUE`` addressed to us goes to the
  :class:`~companion.daemon.intake.Intake` (bounded, newest target wins, per-source rate
  limits), and the frames the core needs
  (HEARTBEAT, COMMAND_ACK, STATUSTEXT, SYSTEM_TIME) into a bounded queue;
* the control socket's threads hand their requests to the intake too;
* the **control thread** is the only one that touches the core. It wakes when something
  arrives that cannot wait for its next pass (a request, a frame that may change what is sent
  or answered now; not the telemetry, the ACKs of an update nobody waits on, nor, with its
  next pass near, the streams) or when the core asks (its next tick, an ACK deadline), feeds
  the core the frames, the link state and the requests, and carries out what the core
  returns: commands to the autopilot, answers to requests. It never blocks on the autopilot.

MAVLink target input (document for ground stations): COMMAND_LONG ``MAV_CMD_USER_1`` (31010) to
our system / component id, params 1–6 = x_cm, y_cm, z_cm, roll_deg, pitch_deg, yaw_deg (param
7 ignored). Answer: COMMAND_ACK ``ACCEPTED`` once the autopilot acknowledged the first servo
commands towards it, ``DENIED`` for non-finite params, ``FAILED`` when it is out of reach (with a
STATUSTEXT giving both errors) or the servos refused, ``TEMPORARILY_REJECTED`` while the
autopilot link is down or over the per-source rate limit, ``CANCELLED`` when a newer target or a
stop replaced it before it moved. With ``link.allowed_senders`` set, a target from a (system,
component) not in it is answered ``DENIED`` (with a STATUSTEXT naming the sender and the
setting), counted in ``not_allowed``, never queued; those answers share the flood limit of
rate-limited refusals (beyond it: unanswered, counted in ``flood_unanswered``).

MAVLink stop and resume: COMMAND_LONG ``MAV_CMD_DO_PAUSE_CONTINUE`` (193) to our system /
component id, param1 = 0 ``stop``, 1 ``resume`` (anything else ``DENIED``); answered with a
COMMAND_ACK of that command. After a stop the arm holds until a resume: every ``USER_1`` is
answered ``DENIED`` ("stopped: send resume") meanwhile. A stop from the companion (the control
socket) is released only from there; a resume from the link is then ``DENIED`` too. Stops and
resumes are never rate limited (the intake coalesces them); their answers share the flood
limit above. ``link.allowed_senders`` applies to them as to targets.

Shutdown (:meth:`ArmDaemon.close`): the intake refuses new requests and answers the waiting ones,
the core answers its own, parks if asked (at the speed limit, as any motion, for at most
``park_wait_s``: :data:`PARK_STOP_S` by default, inside the unit's ``TimeoutStopSec=5``; where
the arm is not parked by then, it holds), and the link closes. It never raises and is bounded
in time whatever the backlog or the autopilot does.
"""

from __future__ import annotations

import collections
import dataclasses
import logging
import threading
import time
from collections.abc import Callable, Sequence
from concurrent.futures import Future
from typing import Any

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from companion import ik
from companion.daemon.config import DaemonConfig, link_config
from companion.daemon.core import Action, Answer, ControlCore, ReadParam, SendCommand
from companion.daemon.intake import RATE_LIMITED, Intake, RefusalLog, TokenBucket
from companion.daemon.requests import (
    KINDS,
    MAV_CMD_DO_PAUSE_CONTINUE,
    MAV_CMD_USER_1,
    MAV_RESULT,
    MAVLINK_PAUSE_KINDS,
    Outcome,
    Reply,
    Request,
    as_target,
    mavlink_target_payload,
    parse_trajectory,
)
from companion.kinematics.arm import Pose
from firmware_interface import LinkError, LinkState, MavlinkLink
from firmware_interface.signing import lockout_message

__all__ = ["ArmDaemon", "Outcome", "Reply"]

log = logging.getLogger("armbridge")

#: A thread asking for status waits this long at most for the control thread to build a fresh
#: snapshot (it builds one at the end of its step); past it, the last one is served.
STATUS_WAIT_S = 0.25
#: With ``park_on_stop``, the arm goes to park at the speed limit for at most this long at
#: shutdown (the shipped unit's TimeoutStopSec=5 leaves the rest for the link to close): 180
#: deg at the default 60 deg/s.
PARK_STOP_S = 3.0
#: Frames waiting for the control thread; beyond this the oldest is dropped (and counted).
FRAME_QUEUE_MAX = 1024
#: ``_acks_wake_at`` when no ACCEPTED ACK needs to wake the control thread.
NO_WAKE = float("inf")
#: The frame types the core reads.
CORE_FRAMES = (
    "HEARTBEAT",
    "COMMAND_ACK",
    "STATUSTEXT",
    "SYSTEM_TIME",
    "SERVO_OUTPUT_RAW",
    "SYS_STATUS",
    "PARAM_VALUE",
)
#: The vehicle's telemetry, read with ``[world]`` on. PX4 streams them on a
#: companion's link unasked (100 and 30 Hz): they do not wake the control thread, which
#: takes them on its next pass (at least every control period).
TELEMETRY_FRAMES = ("ATTITUDE", "LOCAL_POSITION_NED")
#: The streams the core asks for at fixed intervals (SERVO_OUTPUT_RAW every 20 or 100 ms,
#: ArduPilot's SYS_STATUS 25 ms, SYSTEM_TIME 250 ms): what they tell matters from the next
#: tick on (the control thread feeds the frames before each tick), so one wakes the control
#: thread only when its next pass is more than ``STREAM_WAKE_S`` away.
STREAM_FRAMES = ("SERVO_OUTPUT_RAW", "SYS_STATUS", "SYSTEM_TIME")
STREAM_WAKE_S = 0.025
#: PX4's readback is how the core sees outputs die (disarm, kill): one whose PWMs differ from
#: the one before wakes the control thread at once, so the hold is stored before a quick
#: re-arm would bring out the pose stored before (the same PWMs again wake nothing).
READBACK_FIELDS = tuple(f"servo{n}_raw" for n in range(1, 17))
#: The control thread waits at most this long between passes.
MAX_WAIT_S = 0.05
#: STATUSTEXTs explaining refused MAVLink targets: at most this many a second (burst 5).
STATUSTEXT_RATE_HZ = 2.0
#: Per source, at most this many motion targets a second (burst ``SOURCE_BURST``): a ground
#: station streaming targets at 50 Hz stays well inside it.
SOURCE_RATE_HZ = 100.0
SOURCE_BURST = 20.0
#: A MAVLink source over its rate limit gets at most this many TEMPORARILY_REJECTED ACKs a
#: second; the rest of its flood goes unanswered (counted in ``flood_unanswered``): answering
#: 5 000 frames a second would turn the daemon into the flood's amplifier on the link to the
#: autopilot, and cost the reader thread the time it needs for the autopilot's own frames.
FLOOD_ANSWERS_HZ = 2 * SOURCE_RATE_HZ
#: Sources whose flood answers are counted (least recently used beyond it forgotten).
FLOOD_SOURCES_MAX = 256


class ArmDaemon:
    """The bridge between targets and servos; see the module docstring.

    ``start()`` opens the link and starts the control thread; ``close()`` stops both (after an
    optional park). ``clock`` paces everything (monotonic seconds).
    """

    def __init__(
        self,
        config: DaemonConfig,
        *,
        clock: Callable[[], float] = time.monotonic,
        park_wait_s: float = PARK_STOP_S,
    ) -> None:
        self.config = config
        self.clock = clock
        self.park_wait_s = park_wait_s
        self._wake = threading.Event()
        self.intake = Intake(
            clock=clock,
            rate_hz=SOURCE_RATE_HZ,
            burst=SOURCE_BURST,
            refusals=RefusalLog(clock=clock),
            wake=self._wake,
        )
        self._core = ControlCore(config, solve=self._solve, clock=clock)
        self._core.before_first_step = self._frames_before_step
        self._frames: collections.deque[Any] = collections.deque()
        self._frames_lock = threading.Lock()
        # ACCEPTED COMMAND_ACKs queued for the core and taken by it (under _frames_lock): the
        # reader wakes the control thread only once the queue holds the ACK that completes the
        # oldest update's count (_arm_ack_wake); the ones before it decide nothing, and
        # ArduPilot answers an update's six DO_SET_SERVO with six frames.
        self._acks_queued = 0
        self._acks_fed = 0
        self._acks_wake_at: float = 1
        # When the control thread's next pass is due at the latest (it waits until then);
        # a stream frame wakes it only if that is far (STREAM_WAKE_S).
        self._next_pass_s = -float("inf")
        self._readback_wakes = config.link.dialect == "px4"
        self._last_readback: tuple[int, ...] = ()
        # The status snapshot is built on the control thread when some thread asked for one
        # (generations: asked, built): nobody asking, it costs nothing (it was a quarter of
        # the control thread's CPU at 50 Hz with world targets on, rebuilt every 20 ms).
        self._status_cond = threading.Condition()
        self._status_asked = 0
        self._status_built = 0
        self._counts_lock = threading.Lock()
        # Counted here, added to the core's counters in status(): refused before the core.
        self._counts = {
            "not_for_us": 0,
            "not_allowed": 0,
            "frames_dropped": 0,
            "denied": 0,
            "targets": 0,
            "flood_unanswered": 0,
        }
        self._flood_answers: collections.OrderedDict[tuple[int, int], TokenBucket] = (
            collections.OrderedDict()
        )
        self._status: dict[str, Any] = self._core.status()
        # What the service's main loop reports to systemd twice a second (brief()), published
        # by the control thread after each step: that loop then never wakes it for a snapshot.
        self._brief = self._core.link_and_outcome_counts()
        #: Given where the outputs may be (``ControlCore.outputs_left``) by the control thread
        #: whenever it changed (``run``: the pose file's writer; it must not block).
        self.pose_sink: Callable[[tuple[dict[int, int], dict[int, int]]], None] | None = None
        self._left: tuple[dict[int, int], dict[int, int]] | None = None
        self._closing: bool | None = None  # set by close(): park or not
        self._new_config: DaemonConfig | None = None
        self._thread: threading.Thread | None = None
        self.link: MavlinkLink | None = None
        self._last_tick = clock()
        self._statustexts = TokenBucket(STATUSTEXT_RATE_HZ, 5.0, clock())

    # -- life cycle -------------------------------------------------------------------------

    def restore_pose(self, left: tuple[dict[int, int], dict[int, int]]) -> None:
        """Before :meth:`start`: per output, the lowest and highest PWM the outputs were left
        at (see ``pose_file``)."""
        self._core.restore_pose(left)

    def start(self) -> None:
        s = self.config.link
        # A serial flight controller not plugged in yet is waited for, as a silent UDP one is:
        # the socket serves meanwhile and status says what the link waits for.
        self.link = MavlinkLink.open(s.url, link_config(s), clock=self.clock, wait_for_device=True)
        self.link.subscribe(self._on_command_long, ["COMMAND_LONG"])
        self.link.subscribe(
            self._on_frame,
            CORE_FRAMES + (TELEMETRY_FRAMES if self.config.world.enabled else ()),
        )
        self._thread = threading.Thread(target=self._run, name="armbridge-control", daemon=True)
        self._thread.start()
        log.info(
            "started: link %s (%s), arm %s, %g Hz, budget %g ms",
            s.url,
            s.dialect,
            self.config.arm.name,
            self.config.rate_hz,
            self.config.budget_ms,
        )

    def wait_for_autopilot(self, timeout_s: float) -> bool:
        """True once an autopilot HEARTBEAT was heard (bounded wait)."""
        assert self.link is not None
        try:
            self.link.wait_for_autopilot(timeout_s)
        except LinkError:
            return False
        return True

    @property
    def healthy(self) -> bool:
        """The control thread is alive and went round its loop within the last two periods
        (for the watchdog)."""
        alive = self._thread is not None and self._thread.is_alive()
        return alive and self.clock() - self._last_tick < 2.0 / self.config.rate_hz + 1.0

    def close(self, *, park: bool = False, timeout_s: float | None = None) -> None:
        """Stop: refuse and answer every request, park at the speed limit if asked (and
        configured), close the link. Never raises; returns within about ``timeout_s`` (default:
        0.7 s, plus ``park_wait_s`` when parking) plus the link's close."""
        if timeout_s is None:
            timeout_s = 0.7 + (self.park_wait_s if park else 0.0)
        stopping = Reply(Outcome.TEMPORARILY_REJECTED, "daemon stopping")
        self.intake.close(stopping, Reply(Outcome.CANCELLED, "daemon stopping"))
        self._closing = park
        self._wake.set()
        if self._thread is not None:
            self._thread.join(timeout=timeout_s)
            if self._thread.is_alive():
                log.error("control thread did not stop within %.1f s", timeout_s)
        if self.link is not None:
            self.link.close()

    def reload(self, new: DaemonConfig) -> list[str]:
        """Apply a re-read config (SIGHUP). Solver, motion, park and rate settings take effect
        at once (the control socket's limits too: ``run`` hands them to its server; the
        ``[world]`` settings but ``enabled``). Link, arm, calibration, the socket's path and
        group and ``world.enabled`` need a restart: they are kept as they were
        and named in the returned warnings, and so is a new park pose they cannot reach."""
        old = self.config
        warnings = [
            f"{name} changed: restart the daemon to apply it"
            for name, old_value, new_value in (
                ("link", old.link, new.link),
                ("arm", old.arm, new.arm),
                ("calibration", old.calibration, new.calibration),
                ("control.socket", old.control_socket, new.control_socket),
                ("control.socket_group", old.control_socket_group, new.control_socket_group),
                ("world.enabled", old.world.enabled, new.world.enabled),
            )
            if old_value != new_value
        ]
        park_deg = new.park_deg
        if park_deg is not None and (new.arm != old.arm or new.calibration != old.calibration):
            # load_config proved the new park against the new arm and calibration; the running
            # ones are the old, and a park they refuse would fail when it is asked for.
            try:
                old.arm.check_limits(park_deg)
                old.calibration.angles_to_pwm_us(park_deg)
            except ValueError as exc:
                warnings.append(
                    f"park_deg {list(park_deg)} does not fit the running arm and calibration "
                    f"({exc}): kept {list(old.park_deg) if old.park_deg else None}"
                )
                park_deg = old.park_deg
        self.config = dataclasses.replace(
            new,
            link=old.link,
            arm=old.arm,
            calibration=old.calibration,
            park_deg=park_deg,
            control_socket=old.control_socket,
            control_socket_group=old.control_socket_group,
            # The telemetry streams are asked for, and their frames subscribed to, at start.
            world=dataclasses.replace(new.world, enabled=old.world.enabled),
        )
        self._new_config = self.config
        self._wake.set()
        for warning in warnings:
            log.warning("reload: %s", warning)
        applied = _changed_fields(old, self.config)
        log.info(
            "reloaded %s: %s",
            new.source,
            ", ".join(applied) + " applied" if applied else "nothing to apply",
        )
        return warnings

    # -- requests (any thread) --------------------------------------------------------------

    def submit(
        self,
        kind: str,
        payload: Any = None,
        *,
        direct: bool = False,
        source: tuple[Any, ...] = ("local",),
    ) -> Future:
        """Hand a request to the intake; the future resolves to a :class:`Reply` (always, and
        once).

        ``goto``: a Pose or 6 numbers. ``trajectory``: ``[(t_s, pose), ...]`` relative to now.
        ``park``, ``stop``, ``resume``: no payload. ``direct`` (park only) skips the speed
        limit.
        ``source`` identifies the sender for the rate limits.
        """
        return self.submit_request(self.new_request(kind, payload, direct=direct, source=source))

    def new_request(
        self,
        kind: str,
        payload: Any = None,
        *,
        direct: bool = False,
        source: tuple[Any, ...] = ("local",),
    ) -> Request:
        if kind not in KINDS:
            raise ValueError(f"unknown request {kind!r}; valid: {', '.join(KINDS)}")
        return Request(kind, payload, direct, received_s=self.clock(), source=source)

    def submit_request(self, request: Request) -> Future:
        # A malformed target is DENIED here, at once: it must not displace a valid one waiting.
        try:
            if request.kind == "goto":
                as_target(request.payload)
            elif request.kind == "trajectory":
                parse_trajectory(request.payload)
        except (TypeError, ValueError, OverflowError) as exc:
            with self._counts_lock:
                self._counts["denied"] += 1
                self._counts["targets"] += request.kind == "goto"
            reply = Reply(Outcome.DENIED, f"invalid {request.kind}: {exc}")
            request.taken.set()
            request.answer(reply)
            self.intake.refusals.note(request.kind, Outcome.DENIED, reply.message)
            return request.future
        self.intake.submit(request)
        return request.future

    def answer_bound_s(self) -> float:
        """How long after the control thread took a request its answer may take, at most: its
        solve, the update in flight before it, and its own first update, each command of which
        is given ``command_retries + 1`` attempts of ``command_timeout_s``."""
        link = self.config.link
        update_s = (
            (link.command_retries + 1) * link.command_timeout_s * len(self.config.calibration)
        )
        return self.config.budget_ms / 1000.0 + 2 * update_s + 1.0

    def withdraw(self, request: Request) -> bool:
        """Take back a request its sender gave up on, if the control thread has not taken it
        yet; True if so (the caller answers it). Otherwise its answer is on its way."""
        return self.intake.withdraw(request)

    def status(self) -> dict[str, Any]:
        """A snapshot: link state, joints, per-output state, last target, counters (any
        thread). Built fresh by the control thread for the caller (waiting at most
        ``STATUS_WAIT_S`` for the end of its step), so it counts every answer given before the
        call; on the control thread itself (an answer's callback), built at once."""
        self._refresh_status()
        link = self.link
        status = dict(self._status)
        counters = dict(status["counters"])
        counters["cancelled"] += self.intake.counters["cancelled"]
        counters["rate_limited"] = self.intake.counters["rate_limited"]
        with self._counts_lock:
            early = dict(self._counts)
        counters["denied"] += early.pop("denied")
        counters["targets"] += early.pop("targets")
        counters.update(early)
        status["counters"] = counters
        status["link"] = link.state.value if link is not None else "closed"
        # Why the link cannot be used although it may be up (e.g. the signing state cannot be
        # stored), and its counters (signatures refused, foreign datagrams ...).
        status["link_fault"] = link.fault if link is not None else None
        # The serial device the link waits for (not plugged in yet), or None.
        status["link_waiting_for"] = link.waiting_for_device if link is not None else None
        # The autopilot signs far ahead of our clock (each side refuses the other), with the fix.
        problem = link.signing_problem if link is not None else None
        status["link_signing_problem"] = lockout_message(problem) if problem else None
        status["link_counters"] = dataclasses.asdict(link.stats) if link is not None else None
        return status

    def brief(self) -> dict[str, Any]:
        """A few figures of :meth:`status` as of the control thread's last step (at most a
        control period old), without asking it for a snapshot: ``link`` (its state),
        ``autopilot_heard_us``, and the targets ``accepted`` and ``refused`` (failed or
        denied, also those denied before the core)."""
        heard_us, accepted, failed, denied = self._brief
        with self._counts_lock:
            denied += self._counts["denied"]
        link = self.link
        return {
            "link": link.state.value if link is not None else "closed",
            "autopilot_heard_us": heard_us,
            "accepted": accepted,
            "refused": failed + denied,
        }

    def _refresh_status(self) -> None:
        thread = self._thread
        if thread is None or self._closing is not None or not thread.is_alive():
            return  # not started, stopping or stopped: the last snapshot is the final one
        if threading.current_thread() is thread:
            self._status = self._core.status()
            return
        with self._status_cond:
            self._status_asked += 1
            wanted = self._status_asked
        self._wake.set()
        with self._status_cond:
            self._status_cond.wait_for(lambda: self._status_built >= wanted, STATUS_WAIT_S)

    # -- link input (reader thread: never waits) ----------------------------------------------

    def _on_command_long(self, msg: Any) -> None:
        command = msg.command
        if command != MAV_CMD_USER_1 and command != MAV_CMD_DO_PAUSE_CONTINUE:
            return
        link = self.link
        assert link is not None
        if msg.target_system != link.system_id or msg.target_component != link.config.component_id:
            with self._counts_lock:
                self._counts["not_for_us"] += 1
            return
        source = (msg.get_srcSystem(), msg.get_srcComponent())
        allowed = self.config.link.allowed_senders
        if allowed is not None and source not in allowed:
            with self._counts_lock:
                self._counts["not_allowed"] += 1
            reply = Reply(
                Outcome.DENIED,
                f"sender {source[0]}/{source[1]} not in link.allowed_senders",
            )
            self.intake.refusals.note("goto", Outcome.DENIED, reply.message)
            if self._flood_answer_allowed(source):
                self._answer_mavlink(source, reply, command)
            else:
                with self._counts_lock:
                    self._counts["flood_unanswered"] += 1
            return
        if command == MAV_CMD_DO_PAUSE_CONTINUE:
            self._on_pause_continue(msg, source)
            return
        params = (msg.param1, msg.param2, msg.param3, msg.param4, msg.param5, msg.param6)
        payload = mavlink_target_payload(params, msg.param7)
        request = self.new_request("goto", payload, source=("mavlink", *source))
        request.future.add_done_callback(lambda f: self._answer_mavlink(source, f.result()))
        self.intake.submit(request)

    def _on_pause_continue(self, msg: Any, source: tuple[int, int]) -> None:
        """MAV_CMD_DO_PAUSE_CONTINUE to us: param1 0 ``stop``, 1 ``resume``. Never rate
        limited (the intake coalesces them); each is carried out, and answered within the
        flood limit of answers."""
        kind = MAVLINK_PAUSE_KINDS.get(msg.param1)
        answered = self._flood_answer_allowed(source)
        if not answered:
            with self._counts_lock:
                self._counts["flood_unanswered"] += 1
        if kind is None:
            reply = Reply(
                Outcome.DENIED,
                f"MAV_CMD_DO_PAUSE_CONTINUE param1 = {msg.param1:g}: 0 stops, 1 resumes",
            )
            self.intake.refusals.note("stop", Outcome.DENIED, reply.message)
            if answered:
                self._answer_mavlink(source, reply, MAV_CMD_DO_PAUSE_CONTINUE)
            return
        request = self.new_request(kind, source=("mavlink", *source))
        if answered:
            request.future.add_done_callback(
                lambda f: self._answer_mavlink(source, f.result(), MAV_CMD_DO_PAUSE_CONTINUE)
            )
        self.intake.submit(request)

    def _on_frame(self, msg: Any) -> None:
        kind = msg.get_type()
        counted = kind == "COMMAND_ACK" and msg.result == mavlink.MAV_RESULT_ACCEPTED
        now = self.clock()
        with self._frames_lock:
            if len(self._frames) >= FRAME_QUEUE_MAX:
                self._acks_fed += self._frames.popleft()[2]
                with self._counts_lock:
                    self._counts["frames_dropped"] += 1
            self._frames.append((now, msg, counted))
            if counted:
                self._acks_queued += 1
                wake = self._acks_queued >= self._acks_wake_at
            elif kind in STREAM_FRAMES:
                wake = self._next_pass_s - now > STREAM_WAKE_S
                if kind == "SERVO_OUTPUT_RAW" and self._readback_wakes:
                    shown = tuple(getattr(msg, f, 0) for f in READBACK_FIELDS)
                    wake = wake or shown != self._last_readback
                    self._last_readback = shown
            else:
                wake = kind not in TELEMETRY_FRAMES
        if wake:
            self._wake.set()

    def _answer_mavlink(
        self, source: tuple[int, int], reply: Reply, command: int = MAV_CMD_USER_1
    ) -> None:
        link = self.link
        if link is None:
            return
        if reply.message.startswith(RATE_LIMITED) and not self._flood_answer_allowed(source):
            with self._counts_lock:
                self._counts["flood_unanswered"] += 1
            return
        try:
            if reply.outcome in (Outcome.FAILED, Outcome.DENIED) and self._statustexts.take(
                self.clock()
            ):
                severity = (
                    mavlink.MAV_SEVERITY_WARNING
                    if reply.outcome is Outcome.FAILED
                    else mavlink.MAV_SEVERITY_NOTICE
                )
                link.send(link.mav.statustext_encode(severity, reply.statustext().encode()))
            link.send(
                link.mav.command_ack_encode(
                    command, MAV_RESULT[reply.outcome], 0, 0, source[0], source[1]
                )
            )
        except LinkError as exc:
            log.warning("could not answer %d/%d: %s", *source, exc)

    def _flood_answer_allowed(self, source: tuple[int, int]) -> bool:
        """Runs on the reader thread only."""
        now = self.clock()
        bucket = self._flood_answers.get(source)
        if bucket is None:
            bucket = TokenBucket(FLOOD_ANSWERS_HZ, FLOOD_ANSWERS_HZ / 10, now)
            self._flood_answers[source] = bucket
            if len(self._flood_answers) > FLOOD_SOURCES_MAX:
                self._flood_answers.popitem(last=False)
        else:
            self._flood_answers.move_to_end(source)
        return bucket.take(now)

    # -- control thread ---------------------------------------------------------------------

    def _solve(
        self,
        pose: Pose,
        q_start_deg: Sequence[float] | None,
        mode: str = "pose",
        budget_ms: float | None = None,
        *,
        seed: int | None = None,
    ) -> ik.IKResult:
        config = self.config
        budget_ms = config.budget_ms if budget_ms is None else budget_ms
        return ik.solve(
            config.arm,
            pose,
            budget_ms=budget_ms,
            # The budget is CPU time; however busy the board, a solve ends within the control
            # period (or the budget, if that is longer).
            ceiling_ms=max(budget_ms, 1000.0 / config.rate_hz),
            seed=config.seed if seed is None else seed,
            q_start_deg=q_start_deg,
            tol_pos_cm=config.tol_pos_cm,
            tol_ori_deg=config.tol_ori_deg,
            mode=ik.TargetMode(mode),
            settings=config.search_settings,
        )

    def _run(self) -> None:
        core = self._core
        while self._closing is None:
            now = self.clock()
            next_pass_s = min(core.next_wake_s(), now + MAX_WAIT_S)
            self._next_pass_s = next_pass_s
            self._wake.wait(max(0.0, next_pass_s - now))
            self._wake.clear()
            if self._closing is None:
                self._guarded("control loop", None, self._step)
                self._arm_ack_wake()
            self._last_tick = self.clock()
        self._guarded("shutdown", None, self._shutdown)

    def _step(self) -> None:
        core = self._core
        if self._new_config is not None:
            new_config, self._new_config = self._new_config, None
            core.reconfigure(new_config)
        # Requests first, then the frames: every frame that arrived before a request (the
        # autopilot's first HEARTBEAT, say) is then seen before it.
        requests = self.intake.take()
        self._feed_frames()
        self._carry_out(self._tick())
        for request in requests:
            self._guarded(f"{request.kind} request", request, _bind(self._request, request))
            self._feed_frames()  # ACKs that came in during a solve
        self._brief = core.link_and_outcome_counts()
        if self.pose_sink is not None:
            left = core.outputs_left()
            if left is not None and left != self._left:
                self._left = left
                self.pose_sink(left)
        # The snapshot other threads asked for (status()), once for all of them.
        with self._status_cond:
            asked = self._status_asked
        if asked > self._status_built:
            self._status = core.status()
            with self._status_cond:
                self._status_built = asked
                self._status_cond.notify_all()

    def _arm_ack_wake(self) -> None:
        """The ACK count at which the reader wakes us (any other ACK, and every other frame
        the core reads but the telemetry and, with our next pass near, the streams, wakes us
        at once); wakes us now if it is queued.
        When the core does not need the completing ACK before its next tick
        (:meth:`ControlCore.ack_wake_wanted`), no ACCEPTED ACK wakes us: that tick takes them."""
        core = self._core
        with self._frames_lock:
            self._acks_wake_at = (
                self._acks_fed + core.acks_to_progress() if core.ack_wake_wanted() else NO_WAKE
            )
            due = self._acks_queued >= self._acks_wake_at
        if due:
            self._wake.set()

    def _request(self, request: Request) -> None:
        self._carry_out(self._core.request(request))

    def _frames_before_step(self) -> None:
        """A request was solved: the frames that arrived meanwhile go to the core before its
        first step (the solve held the interpreter, so the reader may not have queued them
        yet: it is given up to CATCH_UP_S to)."""
        link = self.link
        if link is not None:
            link.caught_up()
        self._feed_frames()

    def _feed_frames(self) -> None:
        """Feed the queued frames to the core as one batch: a step one of them asks for goes
        out once all are fed (``ControlCore.feeding_frames``; within a request's, the request
        takes it)."""
        core = self._core
        within = core.feeding_frames
        core.feeding_frames = True
        try:
            while True:
                with self._frames_lock:
                    if not self._frames:
                        break
                    received_s, msg, counted = self._frames.popleft()
                    self._acks_fed += counted
                self._carry_out(core.frame(msg, received_s))
        finally:
            core.feeding_frames = within
        if not within:
            self._carry_out(core.frames_fed())

    def _tick(self) -> list[Action]:
        link = self.link
        if link is None:
            return self._core.tick(False)
        autopilot = link.autopilot
        pinned = (autopilot.system_id, autopilot.component_id) if autopilot else None
        return self._core.tick(link.poll_state() is LinkState.UP, pinned)

    def _carry_out(self, actions: list[Action]) -> None:
        # The commands go first, all in one write (one datagram): the autopilot then reads an
        # update's commands in one main-loop pass. Answers after: ACCEPTED comes from the
        # core only once the autopilot acknowledged, so nothing is answered early.
        commands = [a for a in actions if isinstance(a, SendCommand)]
        link = self.link
        if commands and link is not None:
            try:
                link.send_many(
                    link.mav.command_long_encode(*c.target, c.command, c.confirmation, *c.params)
                    for c in commands
                )
            except LinkError as exc:
                # The update then goes unanswered and the core treats it so; a transport
                # error also drops the link to LOST, which makes the core hold.
                log.warning("servo commands not sent: %s", exc)
        for read in (a for a in actions if isinstance(a, ReadParam)):
            if link is None:
                break
            try:
                link.send(link.mav.param_request_read_encode(*read.target, read.name.encode(), -1))
            except LinkError as exc:
                log.warning("%s not asked for: %s", read.name, exc)
        # A client that asks for status once answered sees its request counted: status()
        # waits for a snapshot built after it asked (on this thread: builds one at once).
        for action in (a for a in actions if isinstance(a, Answer)):
            reply = action.reply
            if action.request.answer(reply) and reply.outcome is not Outcome.ACCEPTED:
                self.intake.refusals.note(action.request.kind, reply.outcome, reply.message)

    def _guarded(self, where: str, request: Request | None, work: Callable[[], None]) -> None:
        """Run ``work``; a bug in it must not kill the thread that guards the servos: it is
        logged, the motion stops (the servos keep their last PWM), ``request`` is answered."""
        try:
            work()
        except Exception as exc:
            log.exception("internal error in %s, holding: %r", where, exc)
            reply = Reply(Outcome.FAILED, f"internal error: {exc!r}")
            try:
                self._carry_out(self._core.internal_error(reply))
            except Exception:
                log.exception("internal error while recovering")
            if request is not None:
                try:  # as _carry_out does: the snapshot first, so it counts the error
                    self._status = self._core.status()
                except Exception:
                    log.exception("internal error while recovering")
                request.answer(reply)

    def _shutdown(self) -> None:
        core = self._core
        park = bool(self._closing) and self.config.park_deg is not None
        self._carry_out(core.shutdown(park=park))
        deadline = self.clock() + (self.park_wait_s if park else 0.0)
        while (not core.idle or (park and core.parking())) and self.clock() < deadline:
            with self._frames_lock:  # the ACK that completes a step wakes us (it is waited for)
                self._acks_wake_at = self._acks_fed + core.acks_to_progress()
            self._wake.wait(min(0.01, max(0.0, deadline - self.clock())))
            self._wake.clear()
            self._feed_frames()
            self._carry_out(self._tick())
        if park:
            if core.parked():
                log.info("parked")
            elif not core.link_up:
                log.warning("not parked: the autopilot link is down")
            elif core.outputs.dead():
                log.warning("not parked: the outputs are not live")
            else:
                log.warning(
                    "not parked within %.1f s at the speed limit: the arm holds where it got",
                    self.park_wait_s,
                )
        self._carry_out(core.finish())
        self._status = core.status()


def _bind(work: Callable[[Request], None], request: Request) -> Callable[[], None]:
    return lambda: work(request)


def _changed_fields(old: DaemonConfig, new: DaemonConfig) -> list[str]:
    """The config's fields a reload changed, as ``name old → new`` (sections by name only)."""
    changed = []
    for f in dataclasses.fields(old):
        before, after = getattr(old, f.name), getattr(new, f.name)
        if f.name == "source" or before == after:
            continue
        simple = isinstance(before, int | float | str | bool | type(None))
        changed.append(f"{f.name} {before!r} → {after!r}" if simple else f.name)
    return changed
