"""Motion: the goal, the targets waiting for their first step, the steps at the speed limit,
the trajectory's points.

The arm never jumps: each step moves the joints towards the goal by at most
``joint_speed_deg_s`` for the time since the step before (one control period at most), from
the acknowledged pose, or from the step in flight for a step sent behind it. Every request
gets one answer: ``goto`` ACCEPTED once its first step is acknowledged, FAILED (out of reach,
refused, unanswered), CANCELLED (superseded or stopped before its first step went out). A
target whose first step is already on its way is not cancelled: it is answered with what
happened.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

from companion.daemon.core.actions import Action
from companion.daemon.core.state import AwaitingFirstStep, Flight
from companion.daemon.core.updates import PIPELINE_DEPTH, not_live_reply
from companion.daemon.motion import limit_step
from companion.daemon.requests import Outcome, Reply, Request, Target
from companion.kinematics.arm import Pose
from firmware_interface import CalibrationError

if TYPE_CHECKING:
    from companion.daemon.core.dispatcher import ControlCore

log = logging.getLogger("armbridge")


class Motion:
    """Where the arm goes, and the next step towards it (module docstring)."""

    def __init__(self, core: ControlCore) -> None:
        self._core = core
        #: The joints the motion goes to (None: hold).
        self.goal: tuple[float, ...] | None = None
        #: The trajectory's points still to come: (seconds from its start, pose).
        self.trajectory: list[tuple[float, Pose]] = []
        self._trajectory_t0 = 0.0
        #: Why the daemon abandoned the last trajectory before its end (None: it did not, or
        #: a newer request replaced it): status shows it, ``trajectory --wait`` exits on it.
        self.trajectory_aborted: str | None = None
        self._point_refusal = ""
        #: Accepted targets whose first step has not gone out yet.
        self._waiting: list[AwaitingFirstStep] = []

    # -- requests ---------------------------------------------------------------------------

    @property
    def has_waiting(self) -> bool:
        return bool(self._waiting)

    def take_waiting(self) -> list[AwaitingFirstStep]:
        """The targets waiting for a first step, handed to the update that carries it."""
        waiting, self._waiting = self._waiting, []
        return waiting

    def goto(self, actions: list[Action], request: Request | None, target: Target) -> bool:
        """Solve ``target`` and make it the goal (``request`` None: a trajectory's point)."""
        core = self._core
        world, answers = core.world, core.answers
        pose = target.pose
        if target.frame != "base":
            refusal = world.refusal(target)
            in_base = None if refusal is not None else world.in_base(target)
            if in_base is None:
                if request is not None:
                    answers.answer(
                        actions,
                        request,
                        refusal or Reply(Outcome.TEMPORARILY_REJECTED, world.note["reason"]),
                    )
                return False
            pose = in_base
        start = self.goal if self.goal is not None else tuple(core.state.position)
        result, failure = core.keepout.solve(pose, start, target.mode, None)
        core.state.counters["solved"] += 1
        timing = {
            "received_s": request.received_s if request is not None else core.clock(),
            "solved_s": core.clock(),
        }
        answers.last_target = {
            "pose": list(pose.as_tuple()),
            "mode": target.mode,
            "converged": result is not None and result.converged,
            "pos_err_cm": None if result is None else result.pos_err_cm,
            "ori_err_deg": None if result is None else result.ori_err_deg,
            "solve_ms": None if result is None else result.elapsed_ms,
            "timing": timing,
            # Its answer once given (outcome and message; None: not answered yet, or a
            # trajectory's point, which has none).
            "outcome": None,
            "answer": None,
        }
        answers.last_target_request = request
        if failure is None and result is not None and not result.converged:
            failure = f"unreachable: pos {result.pos_err_cm:.2f}cm ori {result.ori_err_deg:.1f}deg"
        if failure is None and result is not None:
            hit = core.keepout.solution_refusal(result.q_deg)  # solve's answer, checked again
            if hit is not None:
                core.state.counters["keepout_refusals"] += 1
                failure = f"keep-out: {hit}"
        if failure is not None or result is None:
            reply = Reply(Outcome.FAILED, failure or "no solution", result)
            if request is not None:
                answers.answer(actions, request, reply)
            else:
                log.warning("trajectory point refused: %s", reply.message)
                self._point_refusal = reply.message
            return False
        try:
            core.config.calibration.angles_to_pwm_us(result.q_deg)
        except CalibrationError as exc:  # the config check makes this unreachable; stay safe
            if request is not None:
                answers.answer(
                    actions, request, Reply(Outcome.FAILED, f"calibration refused: {exc}", result)
                )
            return False
        if request is None:
            refused = self.refused_reply()
            if refused is not None:
                self._point_refusal = refused.message
                return False
            self.goal = tuple(result.q_deg)
        else:
            superseded = Reply(Outcome.CANCELLED, "superseded by a newer target")
            self.stop(actions, superseded)
            message = "moving" if target.frame == "base" else "moving; held in LOCAL_NED"
            self.accept(
                actions, request, result.q_deg, Reply(Outcome.ACCEPTED, message, result, timing)
            )
            if target.frame != "base":
                world.hold(target)
        return True

    def accept(
        self, actions: list[Action], request: Request, goal: Sequence[float], reply: Reply
    ) -> None:
        """``goal`` is the goal; ``request`` is answered ``reply`` once its first step is
        acknowledged (at once if the arm is there)."""
        core = self._core
        refused = self.refused_reply()
        if refused is not None:  # a step would move the other joints, then fail again
            core.answers.answer(actions, request, refused)
            return
        self.goal = tuple(float(g) for g in goal)
        if tuple(core.state.position) == self.goal and core.state.settled():
            core.answers.answer(actions, request, reply)  # already there: nothing to send
            return
        dead = core.outputs.dead()
        if dead:
            # Its first step would wait for outputs that may stay dead for hours: the answer
            # comes now, and says the arm moves once they are live.
            core.answers.answer(actions, request, not_live_reply(reply, dead))
            return
        self._waiting.append(AwaitingFirstStep(request, reply))

    def refused_reply(self) -> Reply | None:
        """FAILED, if the autopilot refused one of the arm's outputs: remembered until a
        reload, a link loss or a reboot (the fix is made on the autopilot), so a target never
        moves the other joints a step before failing again (a ground station retrying would
        creep the arm)."""
        refused = self._core.state.refused
        if not refused:
            return None
        hint, brief = self._core.outputs.refusal_advice(refused)
        reason = "; ".join(
            f"servo output {o} refused by the autopilot: {why}"
            for o, why in sorted(refused.items())
        )
        return Reply(
            Outcome.FAILED,
            f"{reason}. {hint} Nothing moves until it is fixed and the daemon reloaded "
            "(systemctl reload armbridge) or the autopilot rebooted".replace(".  ", ". "),
            brief=brief,
        )

    def start_trajectory(
        self, actions: list[Action], request: Request, points: list[tuple[float, Pose]]
    ) -> None:
        self.stop(actions, Reply(Outcome.CANCELLED, f"superseded by a {request.kind}"))
        self.trajectory = points
        self.trajectory_aborted = None
        self._trajectory_t0 = self._core.clock()
        self._core.answers.answer(
            actions, request, Reply(Outcome.ACCEPTED, f"trajectory of {len(points)} points")
        )
        self.due_trajectory_point(actions)

    def due_trajectory_point(self, actions: list[Action]) -> None:
        """The latest trajectory point that is due becomes the goal (those before it are
        skipped)."""
        elapsed = self._core.clock() - self._trajectory_t0
        due = [p for p in self.trajectory if p[0] <= elapsed]
        if not due:
            return
        self.trajectory = self.trajectory[len(due) :]
        self._point_refusal = "refused"
        if not self.goto(actions, None, Target(due[-1][1])):
            self.trajectory_aborted = f"the point at t_s={due[-1][0]:g}: {self._point_refusal}"
            log.warning("trajectory aborted: %s", self.trajectory_aborted)
            self.trajectory.clear()

    def stop(self, actions: list[Action], reply: Reply) -> None:
        """Forget the goal; targets whose first step has not gone out get ``reply``. Those
        already on their way are answered when their update resolves."""
        self.goal = None
        self.trajectory.clear()
        self._core.world.drop()
        for w in self._waiting:
            self._core.answers.answer(actions, w.request, reply)
        self._waiting.clear()

    def fail(self, actions: list[Action], reason: str) -> None:
        if self.trajectory:
            self.trajectory_aborted = f"motion stopped: {reason}"
        self.stop(actions, Reply(Outcome.FAILED, f"motion stopped: {reason}"))

    def reject_waiting(self, actions: list[Action], flights: Sequence[Flight], reason: str) -> None:
        """The outputs are unknown (link lost, reboot): every target waiting, on ``flights``
        or for its first step, is TEMPORARILY_REJECTED, and its goal dropped."""
        rejected = Reply(Outcome.TEMPORARILY_REJECTED, reason)
        unanswered = [w for f in flights for w in f.waiting] + self._waiting
        for w in unanswered:
            self._core.answers.answer(actions, w.request, rejected)
        self._waiting.clear()
        if unanswered:  # the goal is theirs: never carried out after that answer
            if self.trajectory:
                self.trajectory_aborted = reason
            self.goal = None
            self.trajectory.clear()

    def moving(self, position: tuple[float, ...]) -> bool:
        state = self._core.state
        return bool(state.flights) or (
            self.goal is not None and (self.goal != position or not state.settled())
        )

    # -- steps ------------------------------------------------------------------------------

    def _max_step_deg(self, now: float) -> float:
        """How far a joint may move in the step going out at ``now``."""
        core = self._core
        since_s = now - core.state.last_step_s
        return core.config.joint_speed_deg_s * min(core.settings.period_s, since_s)

    def next_step(self, actions: list[Action], *, immediate: bool) -> None:
        """Start the next update if one is due. ``immediate``: only if a newly accepted target
        waits (its first step does not wait for the next tick).

        With an update in flight, the next one may go out behind it (:meth:`step_behind`), so
        a target does not wait out the round trip of the step before it (on a 115 200-baud
        line an update takes 13–21 ms of a 20 ms slot)."""
        core = self._core
        state, outputs, updates = core.state, core.outputs, core.updates
        if core.feeding_frames:
            core.defer_step(immediate)
            return
        if not state.link_up or core.watch.reboot_suspected:
            return
        if outputs.take_hold():
            state.unconfirmed = None
            updates.send_step(
                actions, tuple(state.position), core.clock(), everything=True, hold=True
            )
            return
        if immediate and not self._waiting:
            return
        if state.flights:
            self.step_behind(actions)
            return
        now = core.clock()
        if not outputs.may_move(actions, now) or outputs.in_doubt(now):
            return
        if state.unconfirmed is not None:
            if not (state.resend_at_once or self.goal is not None or self._waiting):
                return  # an unanswered step is tried again when there is somewhere to go
            state.resend_at_once = False
            step = state.unconfirmed
        else:
            goal = self.goal
            if goal is None or (goal == tuple(state.position) and state.settled()):
                return
            max_step_deg = self._max_step_deg(now)
            if not max_step_deg > 0:
                return
            step = limit_step(state.position, goal, max_step_deg)
            if not outputs.may_step_to(step):
                return  # e.g. ArduPilot: no SYS_STATUS said the switch is off since the steps
        updates.send_step(actions, step, now)

    def step_behind(self, actions: list[Action]) -> None:
        """Send the next step behind the update in flight, without waiting for its ACKs.

        Only in the plain case: one update in flight (PIPELINE_DEPTH), in its first attempt,
        every output acknowledged before it (none unknown after a loss, a reboot or an update
        that ended unanswered), every output live (and, on PX4, confirmed live by the
        readback). The step is computed from the one in flight (as if acknowledged) at the
        speed limit, and it **re-sends every output the updates ahead of it sent**, at its own
        values: the ACKs are counted in order (:mod:`firmware_interface.updates`), so if one
        ahead ends unanswered or miscounted, this one's outcome alone says where those outputs
        are (see :meth:`UpdatePipeline.poll`)."""
        core = self._core
        state, outputs = core.state, core.outputs
        last = state.flights[-1]
        if (
            len(state.flights) >= PIPELINE_DEPTH
            or last.attempt
            or last.pending
            or state.unconfirmed is not None
            or not state.acked_pwm.keys() >= set(state.outputs)
            or outputs.dead()
        ):
            return
        now = core.clock()
        if last.tracker.poll(now) is not None:
            return  # its verdict is in (or its time is up): resolved first, then we go on
        if not outputs.may_pipeline() or outputs.in_doubt(now):
            return
        goal = self.goal
        if goal is None or goal == last.step_deg:
            return
        # The autopilot may apply this step in the same output cycle as the one in flight (two
        # commands a few ms apart): together they stay within one control step.
        ahead_deg = max(
            (abs(a - b) for a, b in zip(last.step_deg, state.position, strict=True)), default=0.0
        )
        max_step_deg = min(self._max_step_deg(now), core.settings.step_deg - ahead_deg)
        if not max_step_deg > 0:
            return
        step = limit_step(last.step_deg, goal, max_step_deg)
        if not outputs.may_step_to(step):
            return
        ahead = {o for f in state.flights for o in f.sent_outputs}
        base = {o: pwm for o, pwm in state.acked_pwm.items() if o not in ahead}
        core.updates.send_step(actions, step, now, base_pwm=base)

    def retarget(self, goal: Sequence[Any]) -> None:
        """A held target (world frame) solved anew: its solution is the goal."""
        self.goal = tuple(float(q) for q in goal)
