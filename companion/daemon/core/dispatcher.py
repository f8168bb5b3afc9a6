"""The control core's dispatcher: events in, actions out.

:class:`ControlCore` takes the events of the daemon's control thread — a request, a frame, a
tick, a shutdown — and hands each to the part whose rule it is (see the package docstring);
the parts share an :class:`~companion.daemon.core.state.ArmState` and the
:class:`~companion.daemon.core.settings.CoreSettings` derived from the config.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from typing import Any

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from companion.daemon.config import DaemonConfig
from companion.daemon.core.actions import Action, SendCommand
from companion.daemon.core.keepout_gate import KeepoutGate
from companion.daemon.core.motion import Motion
from companion.daemon.core.outputs import OutputsTruth
from companion.daemon.core.outputs_ardupilot import ArduPilotOutputs
from companion.daemon.core.outputs_px4 import Px4Outputs
from companion.daemon.core.settings import CoreSettings
from companion.daemon.core.state import ArmState
from companion.daemon.core.status import StatusAndAnswers
from companion.daemon.core.updates import UpdatePipeline
from companion.daemon.core.watch import AutopilotWatch
from companion.daemon.core.world import WorldTargets
from companion.daemon.requests import (
    LATCH_KINDS,
    Outcome,
    Reply,
    Request,
    as_target,
    local_source,
    parse_trajectory,
    source_name,
    stopped_reply,
)
from firmware_interface.link import is_autopilot_heartbeat

log = logging.getLogger("armbridge")

#: (pose, q_start_deg or None for a cold start, mode, budget_ms or None for the configured
#: one, seed= keyword: None for the configured one) → ik.IKResult
Solve = Callable[..., Any]


def outputs_truth_for(settings: CoreSettings, core: ControlCore) -> OutputsTruth:
    """The outputs' truth of the firmware the link speaks to."""
    return ArduPilotOutputs(core) if settings.ardupilot else Px4Outputs(core)


class ControlCore:
    """See the package docstring. Not thread-safe: one thread drives it."""

    def __init__(
        self,
        config: DaemonConfig,
        *,
        solve: Solve,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self._config = config
        self.settings = CoreSettings.from_config(config)
        self.clock = clock
        #: The injected IK solver (see :data:`Solve`).
        self.solve = solve
        start = config.park_deg or tuple(
            math.degrees((j.min_rad + j.max_rad) / 2) for j in config.arm.joints
        )
        self.state = ArmState(self.settings.outputs, [float(a) for a in start])
        self._next_tick_s = clock()
        self.watch = AutopilotWatch(self)
        self.outputs = outputs_truth_for(self.settings, self)
        self.updates = UpdatePipeline(self)
        self.motion = Motion(self)
        self.keepout = KeepoutGate(self)
        self.world = WorldTargets(self)
        self.answers = StatusAndAnswers(self)
        #: Called once a request is solved, before its first step goes out (the service feeds
        #: the frames that arrived during the solve: a readback showing another sender's
        #: command, arrived meanwhile, is seen before a step could go out over it).
        self.before_first_step: Callable[[], None] | None = None
        #: Frames are being fed in a batch (the service's queue, or those that arrived during a
        #: solve): no step goes out until they all are, so each is weighed against them all (an
        #: ACK early in the queue would otherwise send a step before a readback behind it, which
        #: shows another sender's command, is read). The step a frame asked for is deferred to
        #: :meth:`frames_fed`: True, only for a target waiting; False, any step due.
        self.feeding_frames = False
        self._deferred_step: bool | None = None

    # -- config -----------------------------------------------------------------------------

    @property
    def config(self) -> DaemonConfig:
        return self._config

    def reconfigure(self, config: DaemonConfig) -> None:
        """Take a reloaded config: every value derived from it is computed anew. The link,
        the arm and the calibration need a restart (the service keeps them)."""
        settings = CoreSettings.from_config(config)
        if settings.ardupilot != self.settings.ardupilot or settings.outputs != self.state.outputs:
            raise ValueError(
                f"link.dialect {config.link.dialect!r} or the outputs changed: restart the daemon"
            )
        self._config, self.settings = config, settings
        # The operator's word that the autopilot was fixed: refused outputs are tried again.
        self.state.refused.clear()

    # -- events -----------------------------------------------------------------------------

    def request(self, request: Request) -> list[Action]:
        """A request taken from the intake (``goto``, ``trajectory``, ``park``, ``stop``,
        ``resume``). A ``stop`` holds the arm until a ``resume`` (:meth:`_stop_or_resume`);
        meanwhile the link's targets are DENIED, and one from the companion (the operator's
        own: the control socket, in-process) releases it once carried out."""
        actions: list[Action] = []
        answers, motion = self.answers, self.motion
        if request.answered:  # withdrawn or answered meanwhile: never carried out
            return actions
        if request.kind in LATCH_KINDS:
            answers.answer(actions, request, self._stop_or_resume(actions, request))
            return actions
        if request.kind == "goto":
            self.state.counters["targets"] += 1
        stopped_by = self.state.stopped_by
        if stopped_by is not None and not request.local:
            answers.answer(actions, request, stopped_reply(stopped_by))
            return actions
        try:
            parsed = self._parse(request)
        except (TypeError, ValueError, OverflowError) as exc:
            answers.answer(actions, request, Reply(Outcome.DENIED, str(exc)))
            return actions
        if not self.state.link_up:
            answers.answer(
                actions, request, Reply(Outcome.TEMPORARILY_REJECTED, "autopilot link down")
            )
            return actions
        carried_out = True
        if request.kind == "park":
            motion.stop(actions, Reply(Outcome.CANCELLED, f"superseded by a {request.kind}"))
            if request.direct and not self.state.refused:  # FAILED by accept, unsent
                self.updates.send_direct(actions, tuple(parsed))
            motion.accept(actions, request, tuple(parsed), Reply(Outcome.ACCEPTED, "parking"))
        elif request.kind == "trajectory":
            motion.start_trajectory(actions, request, parsed)
        else:
            carried_out = motion.goto(actions, request, parsed)
        if stopped_by is not None and carried_out:
            self.state.stopped_by = None
            log.info("stop released by the %s from %s", request.kind, source_name(request.source))
        if self.before_first_step is not None:
            self.feeding_frames = True
            try:
                self.before_first_step()
            finally:
                self.feeding_frames = False
            actions += self.frames_fed()
        motion.next_step(actions, immediate=True)
        return actions

    def defer_step(self, immediate: bool) -> None:
        """A frame asked for the next step while frames are fed in a batch: taken once they
        all are (:meth:`frames_fed`)."""
        if self._deferred_step is None or not immediate:
            self._deferred_step = immediate

    def frames_fed(self) -> list[Action]:
        """A batch of frames was fed (see :attr:`feeding_frames`): the step one of them asked
        for, now that every one is weighed."""
        actions: list[Action] = []
        deferred, self._deferred_step = self._deferred_step, None
        if deferred is not None:
            self.motion.next_step(actions, immediate=deferred)
        return actions

    def _stop_or_resume(self, actions: list[Action], request: Request) -> Reply:
        """``stop``: forget the goal and hold until a ``resume``. ``resume``: release a stop,
        unless it came from the companion and the resume from the link (``stopped_reply``)."""
        state = self.state
        stopped_by = state.stopped_by
        if request.kind == "stop":
            self.motion.stop(actions, Reply(Outcome.CANCELLED, "stopped before it moved"))
            if stopped_by is None or (request.local and not local_source(stopped_by)):
                state.stopped_by = request.source  # the companion's stop outranks the link's
            return Reply(Outcome.ACCEPTED, "holding until resume")
        if stopped_by is None:
            return Reply(Outcome.ACCEPTED, "not stopped")
        if local_source(stopped_by) and not request.local:
            return stopped_reply(stopped_by)
        state.stopped_by = None
        log.info("stop released by a resume from %s", source_name(request.source))
        return Reply(Outcome.ACCEPTED, "resumed")

    def frame(self, msg: Any, received_s: float | None = None) -> list[Action]:
        """A frame from the link (see ``service.CORE_FRAMES``), received at ``received_s``
        (default: now; the ACKs, SYSTEM_TIME, the readback and the vehicle's telemetry are
        dated from it)."""
        actions: list[Action] = []
        kind = msg.get_type()
        source = (msg.get_srcSystem(), msg.get_srcComponent())
        watch = self.watch
        at_s = self.clock() if received_s is None else received_s
        if kind == "HEARTBEAT":
            if is_autopilot_heartbeat(msg):
                if source == watch.pinned:
                    watch.arrived(at_s)
                watch.on_heartbeat(actions, source, msg)
            return actions
        if source != watch.pinned:
            self.state.counters["foreign_frames"] += 1
            return actions
        watch.arrived(at_s)
        watch.after_silence(actions)
        if kind == "COMMAND_ACK":
            if msg.target_component in (0, self.config.link.component_id):
                watch.heard_us()
                self.updates.on_ack(msg.command, msg.result, at_s)
                self.updates.poll(actions, at_s)
        elif kind == "STATUSTEXT":
            text = msg.text
            if isinstance(text, bytes | bytearray):
                text = text.decode("ascii", "replace")
            self.updates.on_statustext(str(text))
        elif kind == "SYSTEM_TIME":
            watch.on_system_time(actions, int(msg.time_boot_ms), at_s)
            if self.outputs.hold_wanted:  # readbacks that waited for the clock were believed
                self.motion.next_step(actions, immediate=True)
        elif kind == "SERVO_OUTPUT_RAW":
            shown = {
                n: int(v)
                for n in range(1, 17)
                if (v := getattr(msg, f"servo{n}_raw", 0)) and msg.port == 0
            }
            self.outputs.on_readback(shown, at_s)
            self._probe_clock(actions)
            if self.outputs.hold_wanted:
                self.motion.next_step(actions, immediate=True)
        elif kind == "SYS_STATUS":
            enabled = msg.onboard_control_sensors_enabled
            safety_on = not enabled & mavlink.MAV_SYS_STATUS_SENSOR_MOTOR_OUTPUTS
            self.outputs.on_sys_status(actions, safety_on, at_s)
            self._probe_clock(actions)
        elif kind in ("ATTITUDE", "LOCAL_POSITION_NED"):
            self.world.on_frame(msg, at_s)
        elif kind == "PARAM_VALUE":
            self.outputs.on_param(actions, _param_name(msg.param_id), msg.param_value, at_s)
        return actions

    def _probe_clock(self, actions: list[Action]) -> None:
        """Ask for a SYSTEM_TIME if the outputs' truth waits for the autopilot's clock."""
        pinned = self.watch.pinned
        if (
            pinned is not None
            and self.state.link_up  # nothing is sent while the link is down
            and self.outputs.take_clock_probe(self.clock())
        ):
            actions.append(
                SendCommand(
                    pinned,
                    mavlink.MAV_CMD_REQUEST_MESSAGE,
                    (float(mavlink.MAVLINK_MSG_ID_SYSTEM_TIME), 0, 0, 0, 0, 0, 0),
                )
            )

    def tick(self, link_up: bool, autopilot: tuple[int, int] | None = None) -> list[Action]:
        """Periodic work; call at least every :meth:`next_wake_s`, and whenever the link's
        state may have changed. ``autopilot``: the ids the link latched, if it did (it hears
        the first HEARTBEAT a moment before this core does)."""
        actions: list[Action] = []
        now = self.clock()
        watch = self.watch
        if watch.pinned is None and autopilot is not None:
            watch.pin(autopilot)
        # The link may report UP a moment before its HEARTBEAT reached us: pinned first.
        watch.set_link(actions, link_up and watch.pinned is not None)
        due = now >= self._next_tick_s
        if due:  # also while the link is down: the next wake is a period away, not now
            self._next_tick_s = max(self._next_tick_s + self.settings.period_s, now)
        if not self.state.link_up:
            return actions
        self.updates.poll(actions)
        watch.watch(actions, now)
        if due:
            if self.motion.trajectory:
                self.motion.due_trajectory_point(actions)
            elif self.world.following:
                self.world.follow()
            self.motion.next_step(actions, immediate=False)
        return actions

    def next_wake_s(self) -> float:
        """When :meth:`tick` next has something to do (daemon clock)."""
        return self.updates.next_event_s(self._next_tick_s)

    def acks_to_progress(self) -> int:
        """How many more servo COMMAND_ACKs may arrive before one of them changes anything:
        the oldest update short of ACKs decides nothing until its count is complete
        (:meth:`UpdateTracker.poll`); 1 when none is short (the driver may then wake for
        each)."""
        return self.updates.acks_to_progress()

    def ack_wake_wanted(self) -> bool:
        """Whether the ACK that completes an update (:meth:`acks_to_progress`) must be taken
        at once: nothing is in flight (an ACK then is one too many), a request waits on an
        update in flight (its answer) or to go out behind it, or an update is being confirmed
        one command at a time. Otherwise it changes nothing before the next tick, which takes
        it first (an update's time is its last ACK's reception, not when it is taken), and the
        driver need not wake for it: following a world target or a trajectory, one wake a
        tick fewer."""
        flights = self.state.flights
        if self.motion.has_waiting or not flights:
            return True
        return any(f.waiting or f.pending or f.attempt for f in flights)

    def shutdown(self, *, park: bool) -> list[Action]:
        """Stop: answer everything waiting; with ``park``, the park pose becomes the goal, and
        the arm goes there at the speed limit as long as the driver ticks (see
        ``service.PARK_STOP_S``: what it does not reach by then, it holds)."""
        actions: list[Action] = []
        self.motion.stop(actions, Reply(Outcome.CANCELLED, "daemon stopping"))
        if park and self.config.park_deg is not None and self.state.link_up:
            self.motion.goal = tuple(float(a) for a in self.config.park_deg)
            self.motion.next_step(actions, immediate=False)
        return actions

    def parking(self) -> bool:
        """At shutdown: the park pose is the goal, not reached yet, and the arm can move
        towards it (the link up, the outputs live)."""
        return (
            self.motion.goal is not None
            and not self.parked()
            and self.state.link_up
            and not self.outputs.dead()
        )

    def finish(self) -> list[Action]:
        """The daemon exits now: whatever still waits on an update is answered."""
        actions: list[Action] = []
        for flight in self.state.flights:
            for w in flight.waiting:
                self.answers.answer(actions, w.request, Reply(Outcome.FAILED, "daemon stopped"))
        self.state.flights.clear()
        return actions

    def internal_error(self, reply: Reply) -> list[Action]:
        """A bug under the driving thread: stop moving, hold (the servos keep their last
        PWM), answer every waiting target with ``reply``; the outputs of an update in flight
        are re-sent before anything moves again."""
        actions: list[Action] = []
        state = self.state
        state.counters["internal_errors"] += 1
        flights = list(state.flights)
        state.flights.clear()
        for inflight in flights:
            for w in inflight.waiting:
                self.answers.answer(actions, w.request, reply)
            for output in inflight.sent_outputs:
                state.acked_pwm.pop(output, None)
        if flights:
            state.unconfirmed = tuple(state.position)
        self.motion.stop(actions, reply)
        return actions

    def restore_pose(self, left: tuple[dict[int, int], dict[int, int]]) -> None:
        """Before anything is sent: per output, the lowest and the highest PWM the outputs
        were left at (``pose_file``). The joints are taken at the middle of that band rather
        than at the park pose, and a band wider than a PWM is re-sent there before the first
        target's steps (within half the band of the truth). A readback that shows an output's
        PWM later still wins (the outputs' truth)."""
        state = self.state
        if state.ever_sent:
            return
        low, high = left
        calibration = self.config.calibration
        exact = True
        lows, highs = list(state.position), list(state.position)
        for i, output in enumerate(state.outputs):
            if output in low:
                joint = calibration.for_output(output)
                lows[i], highs[i] = sorted(
                    (
                        joint.pwm_us_to_angle_deg(low[output]),
                        joint.pwm_us_to_angle_deg(high[output]),
                    )
                )
                state.position[i] = (lows[i] + highs[i]) / 2
                exact = exact and low[output] == high[output]
        if not exact:
            state.unconfirmed = tuple(state.position)
            state.restored = (lows, highs)

    def outputs_left(self) -> tuple[dict[int, int], dict[int, int]] | None:
        """Per output, the lowest and the highest PWM the outputs may hold now: the
        acknowledged pose, the steps on their way, one still to confirm, and what the outputs'
        truth says they may hold (ArduPilot's held outputs); for ``pose_file``. None before
        anything was sent or a readback placed a joint (what the outputs were left at is still
        what they hold). A joint placed by a readback is saved even before anything is sent:
        a daemon started later, while the outputs show nothing of it (PX4's disarmed 900 us),
        then starts where the outputs last showed it, not where an earlier daemon left it."""
        state = self.state
        if not (state.ever_sent or state.placed_by_readback):
            return None
        poses = [tuple(state.position), *(f.step_deg for f in state.flights)]
        if state.unconfirmed is not None:
            poses.append(state.unconfirmed)
        if state.restored is not None:
            poses += [tuple(state.restored[0]), tuple(state.restored[1])]
        poses += self.outputs.may_hold()
        calibration = self.config.calibration
        low: dict[int, int] = {}
        high: dict[int, int] = {}
        for i, output in enumerate(state.outputs):
            joint = calibration.for_output(output)
            angles = (min(max(p[i], joint.angle_min_deg), joint.angle_max_deg) for p in poses)
            pwms = [
                min(max(joint.mapped_pwm_us(a), joint.pwm_min_us), joint.pwm_max_us) for a in angles
            ]
            low[output], high[output] = min(pwms), max(pwms)
        return low, high

    # -- reading ----------------------------------------------------------------------------

    @property
    def link_up(self) -> bool:
        return self.state.link_up

    @property
    def counters(self) -> dict[str, int]:
        return self.state.counters

    @property
    def last_target(self) -> dict[str, Any] | None:
        return self.answers.last_target

    def link_and_outcome_counts(self) -> tuple[bool, int, int, int]:
        """The few figures of :meth:`status` cheap enough to take every step: whether the
        autopilot answered us on a link that is up, and the targets accepted, failed and
        denied."""
        counters = self.state.counters
        return (
            self.watch.heard_us_on_link,
            counters["accepted"],
            counters["failed"],
            counters["denied"],
        )

    def status(self) -> dict[str, Any]:
        """A JSON-ready snapshot (build it on the driving thread)."""
        snapshot = self.answers.snapshot()
        # Held by a stop until a resume, and who stopped it (``mavlink 255/190``, ``socket 3``).
        stopped_by = self.state.stopped_by
        snapshot["stopped"] = stopped_by is not None
        snapshot["stopped_by"] = source_name(stopped_by) if stopped_by is not None else None
        return snapshot

    def parked(self) -> bool:
        """Every output acknowledged at the park pose."""
        park = self.config.park_deg
        state = self.state
        return park is not None and state.settled() and tuple(state.position) == tuple(park)

    @property
    def idle(self) -> bool:
        """No update in flight."""
        return not self.state.flights

    def _parse(self, request: Request) -> Any:
        if request.kind == "park":
            if self.config.park_deg is None:
                raise ValueError("no park_deg configured")
            return self.config.park_deg
        if request.kind == "trajectory":
            return parse_trajectory(request.payload)
        try:
            return as_target(request.payload)
        except ValueError as exc:
            raise ValueError(f"invalid target: {exc}") from exc


def _param_name(raw: Any) -> str:
    text = raw.decode("ascii", "replace") if isinstance(raw, bytes | bytearray) else str(raw)
    return text.rstrip("\0")
