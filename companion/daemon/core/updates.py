"""The update pipeline: servo updates in flight, their ACKs counted in order, confirmed.

An update's commands go out back-to-back and its ACKs are counted
(:mod:`firmware_interface.updates`). The next step may go out behind the update in flight (at
most ``PIPELINE_DEPTH`` on their way), re-sending every output the one ahead sent, so when the
one ahead ends unanswered the one behind decides. When the outputs' state is unknown (ACKs
missing), the commands left unknown are re-sent one at a time (``command_retries`` more
times), and the arm does not move on before they are confirmed. An update that stays unknown
fails the targets waiting on it; ``UPDATE_ATTEMPTS`` of them in a row abandon the motion. A
refused output stops the motion with the autopilot's reason.
"""

from __future__ import annotations

import collections
import dataclasses
import logging
from typing import TYPE_CHECKING

from companion.daemon.core.actions import Action, SendCommand
from companion.daemon.core.outputs import band_of, middle
from companion.daemon.core.state import Flight
from companion.daemon.requests import Outcome, Reply
from firmware_interface import CalibrationError
from firmware_interface.commands import command_name
from firmware_interface.updates import ServoCommand, UpdateOutcome, UpdateState, UpdateTracker

if TYPE_CHECKING:
    from companion.daemon.core.dispatcher import ControlCore

log = logging.getLogger("armbridge")

#: An accepted motion survives this many unanswered updates in a row (each already re-sent
#: ``command_retries`` times); then it is abandoned.
UPDATE_ATTEMPTS = 3
#: Updates on their way at once: one, and the next step behind it (see
#: ``Motion.step_behind``). The next step after that waits: a deeper pipe would only queue
#: stale steps.
PIPELINE_DEPTH = 2


class UpdatePipeline:
    """Sends steps as updates and resolves them from their ACKs (module docstring)."""

    def __init__(self, core: ControlCore) -> None:
        self._core = core
        #: Unanswered updates in a row (UPDATE_ATTEMPTS).
        self._unanswered = 0
        #: Recent updates' round trips (s), for the link's one-way latency.
        self.round_trips: collections.deque[float] = collections.deque(maxlen=32)

    # -- ACKs -------------------------------------------------------------------------------

    def on_ack(self, command: int, result: int, at_s: float) -> None:
        """A COMMAND_ACK to us. Counted in order: the oldest update still short of ACKs takes
        it (the autopilot answers one link's commands in the order they came); once all are
        complete, the newest counts it as one too many."""
        flights = self._core.state.flights
        for flight in flights:
            if not flight.tracker.complete or flight is flights[-1]:
                flight.tracker.on_ack(command, result, at_s)
                break

    def on_statustext(self, text: str) -> None:
        for flight in self._core.state.flights:
            flight.tracker.on_statustext(text)

    def acks_to_progress(self) -> int:
        """See :meth:`ControlCore.acks_to_progress`."""
        for flight in self._core.state.flights:
            if not flight.tracker.complete:
                return max(1, flight.tracker.acks_missing)
        return 1

    def next_event_s(self, wake_s: float) -> float:
        for flight in self._core.state.flights:
            wake_s = min(wake_s, flight.tracker.next_event_s())
        return wake_s

    def one_way_s(self) -> float | None:
        """The link's one-way latency: half the median round trip (None: none measured)."""
        trips = sorted(self.round_trips)
        return trips[len(trips) // 2] / 2.0 if trips else None

    # -- sending ----------------------------------------------------------------------------

    def send_step(
        self,
        actions: list[Action],
        step: tuple[float, ...],
        now: float,
        *,
        everything: bool = False,
        timeout_s: float | None = None,
        base_pwm: dict[int, int] | None = None,
        hold: bool = False,
    ) -> None:
        """Send the update to ``step``; outputs whose PWM ``base_pwm`` (default: the
        acknowledged PWMs) already holds are left out, unless ``everything``. ``hold``: the
        outputs told to hold markers (PX4, found not live or not known to be): no keep-out path
        from the step commanded last (the outputs are where the readback shows them, and the
        marker is within MARKER_OFFSET_US of it)."""
        core, state = self._core, self._core.state
        if base_pwm is None:
            base_pwm = state.acked_pwm
        try:
            pwm = core.config.calibration.angles_to_pwm_us(step)
            commands = core.settings.dialect.plan(pwm, None if everything else base_pwm)
        except CalibrationError as exc:  # unreachable by construction; refuse, never clamp
            log.error("calibration refused a step, holding: %s", exc)
            core.motion.fail(actions, f"calibration refused a step: {exc}")
            return
        if not hold:
            # The motion from the step commanded last (what the outputs will hold) to this one,
            # proven clear of every volume, or not sent.
            refusal = core.keepout.step_refusal([state.commanded()], step, commands)
            if refusal is not None:
                state.counters["keepout_refusals"] += 1
                log.error("keep-out: a step refused, holding: %s", refusal)
                core.motion.fail(actions, f"keep-out: {refusal}")
                return
        waiting = core.motion.take_waiting()
        if not commands:  # every output already holds this step
            if state.flights:  # (behind an update: it already carries this step)
                state.flights[-1].waiting.extend(waiting)
                return
            state.position = list(step)
            state.unconfirmed = None
            for w in waiting:
                core.answers.answer(actions, w.request, w.reply)
            return
        if timeout_s is None:
            timeout_s = core.config.link.command_timeout_s
        tracker = UpdateTracker(commands, sent_s=now, timeout_s=timeout_s)
        sent = frozenset(o for c in commands for o in c.outputs)
        state.flights.append(
            Flight(step, pwm, sent, tracker, now, waiting, timeout_s, seq=state.updates_sent)
        )
        state.updates_sent += 1
        state.last_step_s = now
        core.outputs.stepped_to(step)
        self._emit(actions, commands, 0)

    def send_direct(
        self,
        actions: list[Action],
        step: tuple[float, ...],
        *,
        force: bool = False,
        timeout_s: float | None = None,
    ) -> None:
        """Everything to ``step`` at once, past the speed limit (park on shutdown)."""
        core, state = self._core, self._core.state
        # Their answers would be counted into this update; the autopilot handles frames in
        # order, so the direct step lands last whatever happens to those in flight.
        for flight in state.flights:
            for w in flight.waiting:
                core.answers.answer(
                    actions,
                    w.request,
                    Reply(Outcome.FAILED, "interrupted by a park before it was confirmed"),
                )
            for o in flight.sent_outputs:
                state.acked_pwm.pop(o, None)
        state.flights.clear()
        state.unconfirmed = None
        self.send_step(actions, step, core.clock(), everything=force, timeout_s=timeout_s)

    def _emit(self, actions: list[Action], commands: list[ServoCommand], attempt: int) -> None:
        pinned = self._core.watch.pinned
        assert pinned is not None  # the link is up only once an autopilot was heard
        for c in commands:
            actions.append(SendCommand(pinned, c.command, c.params, attempt))

    # -- resolving --------------------------------------------------------------------------

    def poll(self, actions: list[Action], at_s: float | None = None) -> None:
        """Resolve the updates in flight whose outcome is in, oldest first, as of ``at_s``
        (default: now). An ACK's handler passes its arrival: a control thread that stalled
        takes the queued frames late, and judged at its own late time an update whose other
        ACKs wait in the queue behind this one would be taken as unanswered."""
        state = self._core.state
        now = self._core.clock() if at_s is None else at_s
        if self._core.watch.reboot_suspected:
            return  # its verdict first: a reboot clears them, the old clock going on resumes
        while state.flights:
            inflight = state.flights[0]
            outcome = inflight.tracker.poll(now)
            if outcome is None:
                return
            if len(state.flights) > 1 and (outcome.unknown or outcome.state is UpdateState.UNKNOWN):
                self._hand_over_to_the_update_behind(inflight, outcome.reason)
                continue
            if len(state.flights) > 1:
                inflight.accepted.update(outcome.accepted)
                inflight.refused.update(outcome.refused)
                self._resolve(actions, inflight, now)
                continue
            self._resolve_or_confirm_one_by_one(actions, inflight, outcome, now)
            return

    def _hand_over_to_the_update_behind(self, inflight: Flight, reason: str) -> None:
        """An update with one behind it ended unanswered (or miscounted): the one behind
        re-sent every output it sent, so its outcome will say where they are. Until then they
        are unknown; the targets whose first step it was wait on the one behind."""
        state = self._core.state
        state.flights.popleft()
        log.info("servo update unconfirmed (%s); the update behind it decides", reason)
        for output in inflight.sent_outputs:
            state.acked_pwm.pop(output, None)
        state.flights[0].waiting[:0] = inflight.waiting
        state.flights[0].folded[:0] = [*inflight.folded, inflight.step_deg]
        state.counters["servo_errors"] += 1

    def _resolve_or_confirm_one_by_one(
        self, actions: list[Action], inflight: Flight, outcome: UpdateOutcome, now: float
    ) -> None:
        """The outcome of the only update in flight: resolve it, or confirm what it left
        unknown one command at a time."""
        core = self._core
        if inflight.deferred:  # its outcome was taken: the confirmations wait
            self._confirm_next(actions, inflight, now)
            return
        link = core.config.link
        inflight.accepted.update(outcome.accepted)
        inflight.refused.update(outcome.refused)
        unknown = set(outcome.unknown)
        commands = inflight.tracker.commands
        tracker = inflight.tracker
        if unknown and tracker.acks_missing == len(tracker.commands):
            # Not one ACK: the autopilot may have gone silent (a reboot, with frames forged as
            # its own filling the silence): every stream is asked for again, and the outputs'
            # truth says when the confirmations may go out (a readback since, on ArduPilot).
            log.info("servo update unanswered (%s): asking for every stream again", outcome.reason)
            core.outputs.unanswered(now)
            core.watch.ask_for_streams(actions)
        if unknown:
            # Each command is sent at most 1 + command_retries times: once in the batch, then
            # alone until its ACK comes.
            retry = [c for c in commands if unknown.intersection(c.outputs)]
            if inflight.folded and inflight.attempt < link.command_retries:
                retry = self._retry_between(inflight, unknown) or retry
            if inflight.attempt < link.command_retries:
                inflight.pending = retry + inflight.pending
                inflight.attempt += 1
            else:
                names = sorted({command_name(c.command) for c in retry})
                outputs = sorted(o for c in retry for o in c.outputs)
                reason = (
                    f"no COMMAND_ACK for {', '.join(names)} to output(s) "
                    f"{', '.join(map(str, outputs))} after {inflight.attempt + 1} attempts of "
                    f"timeout_s={link.command_timeout_s:g}"
                )
                self._resolve(actions, inflight, now, unknown=reason)
                return
            log.info("servo update unconfirmed (%s), confirming one at a time", outcome.reason)
        elif inflight.pending:
            inflight.attempt = 1
        self._confirm_next(actions, inflight, now)

    def _confirm_next(self, actions: list[Action], inflight: Flight, now: float) -> None:
        """Send the next command to confirm alone, once the outputs' truth allows it (else
        the flight waits, ``deferred``), or resolve the update when none is left."""
        if inflight.pending:
            if not self._core.outputs.may_confirm(now):
                inflight.deferred = True
                return
            inflight.deferred = False
            command = inflight.pending.pop(0)
            inflight.tracker = UpdateTracker([command], sent_s=now, timeout_s=inflight.timeout_s)
            self._emit(actions, [command], inflight.attempt)
            return
        inflight.deferred = False
        self._resolve(actions, inflight, now)

    def _poses_left_unknown(self, inflight: Flight) -> list[tuple[float, ...]]:
        """What outputs left unknown by ``inflight`` may hold: the acknowledged pose, a step
        folded into it, or its own step (each a step from the one before)."""
        return [tuple(self._core.state.position), *inflight.folded, inflight.step_deg]

    def _retry_between(self, inflight: Flight, unknown: set[int]) -> list[ServoCommand]:
        """An update with the steps of updates ahead of it folded into it left ``unknown``
        outputs: they hold the acknowledged pose, one of those steps or this one (two steps
        apart at most). They are confirmed at the middle of those poses, within one step of
        each, rather than at this step; the flight's step becomes that (the outputs it
        confirmed keep theirs)."""
        core = self._core
        poses = self._poses_left_unknown(inflight)
        mid = middle(band_of(poses))
        step = tuple(
            mid[i] if output in unknown else inflight.step_deg[i]
            for i, output in enumerate(core.state.outputs)
        )
        try:
            pwm = core.config.calibration.angles_to_pwm_us(step)
            commands = core.settings.dialect.plan(pwm, None)
        except CalibrationError:  # within the hull of steps already checked: unreachable
            return []
        # The middle was never a commanded step: the motion to it from every pose the outputs
        # may hold is proven clear, or the step's own commands are tried again.
        if core.keepout.step_refusal(poses, step, commands) is not None:
            return []
        inflight.step_deg, inflight.pwm_by_output, inflight.folded = step, pwm, []
        core.outputs.stepped_to(step)
        return [c for c in commands if unknown.intersection(c.outputs)]

    def _resolve(
        self, actions: list[Action], inflight: Flight, now: float, *, unknown: str = ""
    ) -> None:
        """Every command of the update has its verdict (or ``unknown`` says why not)."""
        core, state = self._core, self._core.state
        outputs_truth = core.outputs
        assert state.flights and state.flights[0] is inflight
        state.flights.popleft()
        joint_of = {o: i for i, o in enumerate(state.outputs)}
        overtaken = outputs_truth.overtaken(inflight.seq)
        for output, pwm in inflight.accepted.items():
            if output in overtaken:
                continue
            state.acked_pwm[output] = pwm
            outputs_truth.acknowledged(output, pwm, now)
            state.refused.pop(output, None)
            state.position[joint_of[output]] = inflight.step_deg[joint_of[output]]
        settled = set(inflight.accepted) | set(inflight.refused)
        for output in inflight.sent_outputs - settled:
            state.acked_pwm.pop(output, None)
        timing = {"first_out_s": inflight.sent_s, "acked_s": now}
        if inflight.refused:
            state.unconfirmed = None
            self._unanswered = 0
            state.refused.update(inflight.refused)
            state.counters["refused_outputs"] += len(inflight.refused)
            reason = "; ".join(
                f"servo output {o} refused by the autopilot: {why}"
                for o, why in sorted(inflight.refused.items())
            )
            hint, brief = outputs_truth.refusal_advice(inflight.refused)
            log.error("%s; motion stopped. %s", reason, hint)
            for w in inflight.waiting:
                reply = Reply(Outcome.FAILED, f"{reason}. {hint}".strip(), brief=brief)
                core.answers.answer(actions, w.request, reply)
            core.motion.fail(actions, reason)
            return
        if not unknown:
            state.unconfirmed = None
            self._unanswered = 0
            if all(o in state.acked_pwm or o in state.refused for o in state.outputs):
                state.restored = None  # they hold what was acknowledged
                outputs_truth.all_acknowledged()
            state.counters["servo_updates"] += 1  # acknowledged in full
            if inflight.attempt == 0:
                done_s = inflight.tracker.complete_s
                self.round_trips.append((now if done_s is None else done_s) - inflight.sent_s)
            core.answers.record_first_out(timing)
            dead = outputs_truth.dead()
            for w in inflight.waiting:
                reply = w.reply
                if reply.timing is not None:
                    reply = dataclasses.replace(reply, timing={**reply.timing, **timing})
                if dead:
                    reply = not_live_reply(reply, dead)
                core.answers.answer(actions, w.request, reply)
            core.motion.next_step(actions, immediate=True)
            return
        # Some outputs may or may not have moved: they hold the acknowledged pose, this step
        # or one folded into it (each a step from the one before). A pose within one step of
        # every one of them is sent before moving on: this step, or with steps folded into it,
        # the middle of them all.
        if inflight.folded:
            state.unconfirmed = middle(band_of(self._poses_left_unknown(inflight)))
        else:
            state.unconfirmed = inflight.step_deg
        state.counters["servo_errors"] += 1
        self._unanswered += 1
        message = f"servo update unanswered: {unknown}"
        if inflight.waiting or self._unanswered >= UPDATE_ATTEMPTS:
            log.error("%s; motion stopped", message)
            for w in inflight.waiting:
                core.answers.answer(actions, w.request, Reply(Outcome.FAILED, message))
            core.motion.fail(actions, message)
            self._unanswered = 0
        else:
            log.warning(
                "%s (%d of %d), trying again on the next tick",
                message,
                self._unanswered,
                UPDATE_ATTEMPTS,
            )


def not_live_reply(reply: Reply, dead: dict[int, str]) -> Reply:
    """``reply`` saying the arm moves once the ``dead`` outputs are live."""
    first = dead[min(dead)]
    more = f" (+{len(dead) - 1} more)" if len(dead) > 1 else ""
    return dataclasses.replace(
        reply,
        message=f"{reply.message}; outputs not live: {first}{more}: the arm moves when they are",
    )
