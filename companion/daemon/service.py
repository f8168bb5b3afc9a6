"""The companion daemon: target in, deadline-bounded IK, speed-limited safe PWM out.

Threads and who owns what:

* the link's reader thread (firmware_interface) only *enqueues*: a MAVLink COMMAND_LONG
  ``MAV_CMD_USER_1`` addressed to us becomes a request on the control queue;
* the control socket's thread (:mod:`companion.daemon.control_socket`) only enqueues too;
* the **control thread** (this module) owns all arm state. It takes requests (validate →
  solve → accept or refuse), and on every tick at ``rate_hz`` moves the commanded joints
  towards the goal by at most ``joint_speed_deg_s / rate_hz`` and sends the servo commands.
  An accepted target does not wait for the next tick: its first step goes out at once, at most
  ``joint_speed_deg_s`` × the time since the previous step, and the ticks restart from there.
  It blocks only on its own ACKs, which the reader thread delivers.

Safety rules, in this order:

1. A target must be six finite numbers, or it is DENIED. With the autopilot link down it is
   TEMPORARILY_REJECTED. If the solution misses the tolerances it is FAILED, and nothing moves.
2. Every PWM goes through the calibration, which refuses anything outside a servo's range.
   The dialect checks it again before sending. Nothing is ever clamped into range silently.
3. A servo update that goes unanswered (after the CommandSender's retries) during an accepted
   motion is sent again on the next tick, up to ``UPDATE_ATTEMPTS`` updates in a row; a
   rejected command stops the motion at once.
4. Autopilot link lost: stop commanding and hold. When it comes back, re-send the current PWMs
   first, then carry on.
5. The arm is assumed to start at the park pose (or mid-range if none is set). Nothing is sent
   until the first target, and never faster than the joint speed limit from there.

MAVLink target input (document for ground stations): COMMAND_LONG ``MAV_CMD_USER_1`` (31010) to
our system / component id, params 1–6 = x_cm, y_cm, z_cm, roll_deg, pitch_deg, yaw_deg (param
7 ignored). Answer: COMMAND_ACK ``ACCEPTED`` once the first servo commands towards it are out,
``DENIED`` for non-finite params, ``FAILED`` when it is out of reach (with a STATUSTEXT giving
both errors) or the servos refused, ``TEMPORARILY_REJECTED`` while the autopilot link is down.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import queue
import threading
import time
from collections.abc import Callable, Sequence
from concurrent.futures import Future
from typing import Any

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from companion import ik
from companion.daemon.config import DaemonConfig
from companion.daemon.motion import limit_step
from companion.daemon.requests import (
    MAV_CMD_USER_1,
    MAV_RESULT,
    STATUSTEXT_MAX,
    Outcome,
    Reply,
    Request,
    as_pose,
    parse_trajectory,
)
from companion.kinematics.arm import Pose
from firmware_interface import (
    CalibrationError,
    CommandSender,
    LinkConfig,
    LinkError,
    LinkState,
    LinkTimeout,
    MavlinkLink,
    ServoDialect,
    make_servo_dialect,
)

__all__ = ["ArmDaemon", "Outcome", "Reply"]

log = logging.getLogger("armbridge")

#: An accepted motion survives this many servo updates in a row that went unanswered (each
#: already retried by the CommandSender); then it is abandoned.
UPDATE_ATTEMPTS = 3


class ArmDaemon:
    """The bridge between targets and servos; see the module docstring.

    ``start()`` opens the link and starts the control thread; ``close()`` stops both (after an
    optional park). ``clock`` paces the control ticks (monotonic seconds).
    """

    def __init__(self, config: DaemonConfig, *, clock: Callable[[], float] = time.monotonic):
        self.config = config
        self.clock = clock
        self._queue: queue.Queue[Request | None] = queue.Queue()
        self._lock = threading.Lock()  # guards _status
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.link: MavlinkLink | None = None
        self._sender: CommandSender | None = None
        self._dialect: ServoDialect | None = None
        self._last_tick = clock()
        self._last_step_s = -math.inf  # when the last step was sent (for the speed limit)
        arm = config.arm
        start = config.park_deg or tuple(
            math.degrees((j.min_rad + j.max_rad) / 2) for j in arm.joints
        )
        self._current: tuple[float, ...] = tuple(start)
        self._goal: tuple[float, ...] | None = None
        self._pending: list[Request] = []  # accepted, waiting for their first servo commands
        self._trajectory: list[tuple[float, Pose]] = []
        self._trajectory_t0 = 0.0
        self._last_pwm: dict[int, int] | None = None
        self._holding = False
        self._unanswered_updates = 0  # servo updates in a row that got no ACK
        self._counters = {
            "targets": 0,
            "accepted": 0,
            "denied": 0,
            "failed": 0,
            "temporarily_rejected": 0,
            "servo_updates": 0,
            "servo_errors": 0,
            "not_for_us": 0,
            "internal_errors": 0,
        }
        self._last_target: dict[str, Any] | None = None
        # The newest accepted target's timing until its first servo update is out (see status).
        self._timing_pending: dict[str, float] | None = None

    # -- life cycle -------------------------------------------------------------------------

    def start(self) -> None:
        s = self.config.link
        self.link = MavlinkLink.open(
            s.url,
            LinkConfig(
                system_id=s.system_id,
                component_id=s.component_id,
                target_system=s.target_system,
                target_component=s.target_component,
                loss_timeout_s=s.loss_timeout_s,
                signing=s.signing,
            ),
        )
        self._sender = CommandSender(
            self.link, timeout_s=s.command_timeout_s, retries=s.command_retries
        )
        self._dialect = make_servo_dialect(s.dialect, self._sender, self.config.calibration)
        self.link.subscribe(self._on_command_long, ["COMMAND_LONG"])
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
        """The control thread is alive and ticked within the last two periods (for the
        watchdog)."""
        alive = self._thread is not None and self._thread.is_alive()
        return alive and self.clock() - self._last_tick < 2.0 / self.config.rate_hz + 1.0

    def close(self, *, park: bool = False, timeout_s: float = 0.8) -> None:
        """Stop the control thread (parking first if asked) and close the link."""
        if park and self.config.park_deg is not None and self._thread is not None:
            self.submit("park", direct=True).result(timeout=timeout_s)
        self._stop.set()
        self._queue.put(None)
        if self._thread is not None:
            self._thread.join(timeout=timeout_s)
        if self._sender is not None:
            self._sender.close()
        if self.link is not None:
            self.link.close()

    def reload(self, new: DaemonConfig) -> list[str]:
        """Apply a re-read config (SIGHUP). Solver, motion, park and rate settings take effect
        at once. Link, arm and calibration changes need a restart: they are kept as they were
        and named in the returned warnings, and so is a new park pose they cannot reach."""
        old = self.config
        warnings = [
            f"{name} changed: restart the daemon to apply it"
            for name, old_value, new_value in (
                ("link", old.link, new.link),
                ("arm", old.arm, new.arm),
                ("calibration", old.calibration, new.calibration),
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
            new, link=old.link, arm=old.arm, calibration=old.calibration, park_deg=park_deg
        )
        for warning in warnings:
            log.warning("reload: %s", warning)
        log.info("reloaded %s", new.source)
        return warnings

    # -- requests (any thread) --------------------------------------------------------------

    def submit(self, kind: str, payload: Any = None, *, direct: bool = False) -> Future:
        """Queue a request for the control thread; the future resolves to a :class:`Reply`.

        ``goto``: a Pose or 6 numbers. ``trajectory``: ``[(t_s, pose), ...]`` relative to now.
        ``park``, ``stop``: no payload. ``direct`` (park only) skips the speed limit: used on
        shutdown, when there is no time to creep.
        """
        if kind not in ("goto", "trajectory", "park", "stop"):
            raise ValueError(f"unknown request {kind!r}; valid: goto, trajectory, park, stop")
        request = Request(kind, payload, direct, received_s=self.clock())
        if self._stop.is_set():
            request.future.set_result(Reply(Outcome.TEMPORARILY_REJECTED, "daemon stopping"))
        else:
            self._queue.put(request)
        return request.future

    def status(self) -> dict[str, Any]:
        """A snapshot: link state, joints, last target, counters (thread-safe)."""
        link = self.link
        with self._lock:
            return {
                "link": link.state.value if link is not None else "closed",
                "holding": self._holding,
                "current_deg": list(self._current),
                "goal_deg": list(self._goal) if self._goal is not None else None,
                "moving": self._goal is not None and self._goal != self._current,
                "last_pwm_us": dict(self._last_pwm) if self._last_pwm else None,
                "last_target": self._last_target,
                "trajectory_points_left": len(self._trajectory),
                "counters": dict(self._counters),
            }

    # -- MAVLink input (reader thread: enqueue only) ------------------------------------------

    def _on_command_long(self, msg: Any) -> None:
        if msg.command != MAV_CMD_USER_1:
            return
        link = self.link
        assert link is not None
        if msg.target_system != link.system_id or msg.target_component != link.config.component_id:
            with self._lock:
                self._counters["not_for_us"] += 1
            return
        source = (msg.get_srcSystem(), msg.get_srcComponent())
        params = (msg.param1, msg.param2, msg.param3, msg.param4, msg.param5, msg.param6)
        future = self.submit("goto", params)
        future.add_done_callback(lambda f: self._answer_mavlink(source, f.result()))

    def _answer_mavlink(self, source: tuple[int, int], reply: Reply) -> None:
        link = self.link
        if link is None:
            return
        try:
            if reply.outcome is not Outcome.ACCEPTED:
                severity = (
                    mavlink.MAV_SEVERITY_WARNING
                    if reply.outcome is Outcome.FAILED
                    else mavlink.MAV_SEVERITY_NOTICE
                )
                text = reply.message[:STATUSTEXT_MAX].encode("ascii", "replace")
                link.send(link.mav.statustext_encode(severity, text))
            link.send(
                link.mav.command_ack_encode(
                    MAV_CMD_USER_1, MAV_RESULT[reply.outcome], 0, 0, source[0], source[1]
                )
            )
        except LinkError as exc:
            log.warning("could not answer %d/%d: %s", *source, exc)

    # -- control thread ---------------------------------------------------------------------

    def _run(self) -> None:
        next_tick = self.clock()
        while not self._stop.is_set():
            period = 1.0 / self.config.rate_hz  # re-read: SIGHUP may change it
            timeout = max(0.0, next_tick - self.clock())
            try:
                request = self._queue.get(timeout=timeout)
            except queue.Empty:
                request = None
            if request is not None:
                try:
                    self._handle(request)
                except Exception as exc:  # a bug must not kill the loop that guards the servos
                    self._internal_error(f"{request.kind} request", exc)
                    self._finish(request, Reply(Outcome.FAILED, f"internal error: {exc!r}"))
            now = self.clock()
            # A newly accepted target does not wait for the next tick: its first step goes out
            # now (sized by the time since the last step, see _tick), and the ticks restart
            # from here. Unless more requests are already waiting: a burst is handled first
            # and its latest goal gets one update, so a flood of targets cannot turn into a
            # flood of servo updates (each update also waits for its ACKs: the link's pace).
            immediate = now < next_tick and bool(self._pending) and self._queue.empty()
            if now >= next_tick or immediate:
                try:
                    self._tick(now, period)
                except Exception as exc:
                    self._internal_error("control tick", exc)
                next_tick = now + period if immediate else max(next_tick + period, now)
        for request in self._pending:
            request.future.set_result(Reply(Outcome.FAILED, "daemon stopped before moving"))

    def _internal_error(self, where: str, exc: Exception) -> None:
        """Something unexpected failed: log it with its traceback, stop moving and hold (the
        servos keep their last PWM), and carry on serving."""
        log.exception("internal error in %s, holding: %r", where, exc)
        self._trajectory.clear()
        self._set_goal(None)
        for request in self._pending:
            self._finish(request, Reply(Outcome.FAILED, f"internal error: {exc!r}"))
        self._pending.clear()
        with self._lock:
            self._counters["internal_errors"] += 1

    def _count(self, outcome: Outcome) -> None:
        with self._lock:
            self._counters[outcome.value] += 1

    def _finish(self, request: Request, reply: Reply) -> None:
        if reply.outcome is not Outcome.ACCEPTED:
            self._count(reply.outcome)
            log.info("%s refused (%s): %s", request.kind, reply.outcome.value, reply.message)
        if not request.future.done():
            request.future.set_result(reply)

    def _link_up(self) -> bool:
        return self.link is not None and self.link.poll_state() is LinkState.UP

    def _handle(self, request: Request) -> None:
        if request.kind == "stop":
            self._trajectory.clear()
            self._set_goal(None)
            self._finish(request, Reply(Outcome.ACCEPTED, "holding"))
            return
        # Validate first: an invalid request is DENIED whatever the link does.
        if request.kind == "goto":
            with self._lock:
                self._counters["targets"] += 1
        try:
            parsed = self._parse(request)
        except (TypeError, ValueError) as exc:
            self._finish(request, Reply(Outcome.DENIED, str(exc)))
            return
        if not self._link_up():
            self._finish(request, Reply(Outcome.TEMPORARILY_REJECTED, "autopilot link down"))
            return
        self._trajectory.clear()
        if request.kind == "park":
            if request.direct:
                self._set_current(parsed)
            self._accept(request, parsed, "parking")
        elif request.kind == "trajectory":
            self._trajectory = parsed
            self._trajectory_t0 = self.clock()
            self._finish(request, Reply(Outcome.ACCEPTED, f"trajectory of {len(parsed)} points"))
        else:
            self._goto(request, parsed, request.received_s)

    def _parse(self, request: Request) -> Any:
        """The request's validated payload; ValueError says what is wrong with it."""
        if request.kind == "park":
            if self.config.park_deg is None:
                raise ValueError("no park_deg configured")
            return self.config.park_deg
        if request.kind == "trajectory":
            return parse_trajectory(request.payload)
        try:
            return as_pose(request.payload)
        except ValueError as exc:
            raise ValueError(f"invalid target: {exc}") from exc

    def _goto(self, request: Request | None, pose: Pose, received_s: float) -> bool:
        start = self._goal if self._goal is not None else self._current
        result = ik.solve(
            self.config.arm,
            pose,
            budget_ms=self.config.budget_ms,
            seed=self.config.seed,
            q_start_deg=start,
            tol_pos_cm=self.config.tol_pos_cm,
            tol_ori_deg=self.config.tol_ori_deg,
        )
        timing = {"received_s": received_s, "solved_s": self.clock()}
        with self._lock:
            self._last_target = {
                "pose": list(pose.as_tuple()),
                "converged": result.converged,
                "pos_err_cm": result.pos_err_cm,
                "ori_err_deg": result.ori_err_deg,
                "solve_ms": result.elapsed_ms,
                "timing": timing,
            }
        if not result.converged:
            reply = Reply(
                Outcome.FAILED,
                f"unreachable: pos {result.pos_err_cm:.2f}cm ori {result.ori_err_deg:.1f}deg",
                result,
            )
            if request is not None:
                self._finish(request, reply)
            else:
                log.warning("trajectory point refused: %s", reply.message)
            return False
        try:
            self.config.calibration.angles_to_pwm_us(result.q_deg)
        except CalibrationError as exc:  # the config check makes this unreachable; stay safe
            if request is not None:
                self._finish(request, Reply(Outcome.FAILED, f"calibration refused: {exc}", result))
            return False
        if request is not None:
            self._accept(request, result.q_deg, "moving", result, timing)
        else:
            self._set_goal(result.q_deg)
        self._timing_pending = timing
        return True

    def _accept(
        self,
        request: Request,
        goal: Sequence[float],
        message: str,
        result: ik.IKResult | None = None,
        timing: dict[str, float] | None = None,
    ) -> None:
        self._set_goal(tuple(goal))
        request.accepted = Reply(Outcome.ACCEPTED, message, result, timing)
        self._pending.append(request)

    def _set_goal(self, goal: Sequence[float] | None) -> None:
        with self._lock:
            self._goal = tuple(goal) if goal is not None else None

    def _set_current(self, current: Sequence[float]) -> None:
        with self._lock:
            self._current = tuple(current)

    def _due_trajectory_point(self, now: float) -> None:
        due = [p for p in self._trajectory if p[0] <= now - self._trajectory_t0]
        if not due:
            return
        self._trajectory = self._trajectory[len(due) :]
        if not self._goto(None, due[-1][1], now):
            log.warning("trajectory aborted: a point is out of reach")
            self._trajectory.clear()

    def _tick(self, now: float, period: float) -> None:
        self._last_tick = now
        if not self._link_up():
            if not self._holding and self._last_pwm is not None:
                log.warning("autopilot link lost: holding, no servo commands")
            with self._lock:
                self._holding = True
            for request in self._pending:
                self._finish(request, Reply(Outcome.TEMPORARILY_REJECTED, "autopilot link lost"))
            self._pending.clear()
            return
        if self._holding:
            with self._lock:
                self._holding = False
            if self._last_pwm is not None:
                log.info("autopilot link back: re-sending current PWMs")
                # Everything, not only what changed: the autopilot may have restarted meanwhile.
                if not self._send(self._last_pwm, skip_unchanged=False):
                    return
        if self._trajectory:
            self._due_trajectory_point(now)
        goal = self._goal
        if goal is None or (
            goal == self._current and self._last_pwm is not None and not self._pending
        ):
            return
        # The speed limit holds whenever a step goes out: at most the joint speed times the
        # time since the last step, and never more than one period's worth.
        max_step_deg = self.config.joint_speed_deg_s * min(period, now - self._last_step_s)
        if not max_step_deg > 0:
            return
        step = limit_step(self._current, goal, max_step_deg)
        try:
            pwm = self.config.calibration.angles_to_pwm_us(step)
        except CalibrationError as exc:  # unreachable by construction; refuse, never clamp
            log.error("calibration refused a step, holding: %s", exc)
            self._set_goal(None)
            return
        first_out_s = self.clock()
        if self._send(pwm):
            self._last_step_s = now
            self._set_current(step)
            out = {"first_out_s": first_out_s, "acked_s": self.clock()}
            self._record_first_out(out)
            for request in self._pending:
                reply = request.accepted
                assert reply is not None  # set by _accept before the request joins _pending
                if reply.timing is not None:
                    reply = dataclasses.replace(reply, timing={**reply.timing, **out})
                self._finish(request, reply)
                self._count(Outcome.ACCEPTED)
            self._pending.clear()

    def _record_first_out(self, out: dict[str, float]) -> None:
        """Completes the timing of the newest target once its first servo update is acked."""
        pending, self._timing_pending = self._timing_pending, None
        if pending is None:
            return
        with self._lock:
            last = self._last_target
            if last is not None and last["timing"] is pending:
                self._last_target = {**last, "timing": {**pending, **out}}

    def _send(self, pwm: dict[int, int], *, skip_unchanged: bool = True) -> bool:
        """Send a servo update (ardupilot: only the outputs whose PWM changed since the
        autopilot acknowledged them, unless ``skip_unchanged`` is off); False if it failed."""
        assert self._dialect is not None
        try:
            self._dialect.send_pwm(pwm, skip_unchanged=skip_unchanged)
        except (LinkError, CalibrationError) as exc:
            with self._lock:
                self._counters["servo_errors"] += 1
            self._unanswered_updates += 1
            if (
                isinstance(exc, LinkTimeout)
                and not self._pending
                and self._unanswered_updates < UPDATE_ATTEMPTS
            ):
                # An accepted motion is not abandoned for one lost answer: the next tick sends
                # the update again (a rejection, or a refused PWM, stops at once).
                log.warning(
                    "servo update unanswered (%d of %d), trying again: %s",
                    self._unanswered_updates,
                    UPDATE_ATTEMPTS,
                    exc,
                )
                return False
            self._unanswered_updates = 0
            log.error("servo command failed, stopping motion: %s", exc)
            self._set_goal(None)
            for request in self._pending:
                self._finish(request, Reply(Outcome.FAILED, f"servo command failed: {exc}"))
            self._pending.clear()
            return False
        self._unanswered_updates = 0
        with self._lock:
            self._last_pwm = dict(pwm)
            self._counters["servo_updates"] += 1
        return True
