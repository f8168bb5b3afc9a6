"""The autopilot watch: which autopilot we talk to, whether it is there, whether it rebooted.

* **A pinned autopilot**: its ids come from the config or from the first autopilot HEARTBEAT,
  and never change; frames from anyone else are counted and ignored.
* **An autopilot reboot** (SYSTEM_TIME ``time_boot_ms`` going backwards, or falling behind the
  time elapsed, whatever the gap) is a link loss: the outputs' state is unknown, and every
  output is re-sent before moving on. A reboot silences the autopilot (REBOOT_SILENCE_S at
  least): with that silence before it, one SYSTEM_TIME is evidence enough; without, a second
  signal is needed: the new clock's SYSTEM_TIMEs for REBOOT_CONFIRM_S with none of the old
  clock's among them (a frame forged as the autopilot's on an unsigned link, alone, never
  drops the outputs' state; a forger interleaving with the autopilot's own stream is told
  apart and logged).
* **Link lost**: hold (nothing is sent), answer waiting targets TEMPORARILY_REJECTED (and drop
  their goal); when it is back, re-send every output at the acknowledged pose, then carry on
  towards the goal of a target that was already ACCEPTED.
* **Silences**: a stream that stopped, or an autopilot that speaks again after a gap, may mean
  a reboot that forgot the streams asked for: every stream is asked for again.
"""

from __future__ import annotations

import logging
from typing import TYPE_CHECKING, Any

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from companion.daemon.core.actions import Action, ReadParam, SendCommand
from companion.daemon.core.settings import SYSTEM_TIME_INTERVAL_S

if TYPE_CHECKING:
    from companion.daemon.core.dispatcher import ControlCore

log = logging.getLogger("armbridge")

#: A SYSTEM_TIME stream that fell silent this long is asked for again (a rebooted autopilot
#: forgets the intervals it was asked for), and the outputs are re-sent in case it rebooted.
SYSTEM_TIME_SILENT_S = 1.0
#: ``time_boot_ms`` behind the time since the previous SYSTEM_TIME by more than this is a
#: reboot (less: a frame delayed on its way).
REBOOT_LAG_MS = 750
#: The same, for the first SYSTEM_TIME after the stream fell silent (a rebooted autopilot
#: forgets the interval it was asked for). Silence and lag together are the evidence: a reboot
#: costs at least its gap (0.36 s measured), but one soon after the previous boot may lag by
#: little more, under REBOOT_LAG_MS (seen: up 0.22 s, rebooted, 0.58 s behind).
REBOOT_LAG_AFTER_SILENCE_MS = 250
#: A SYSTEM_TIME this long after the one before counts as after a silence (above), whether or
#: not the silence was noticed first: a stream asked for again early (a silent SYS_STATUS, see
#: SYS_STATUS_SILENT_S) comes back before SYSTEM_TIME_SILENT_S. Twice the interval asked:
#: shorter than any reboot's gap plus the time to ask the stream again.
SYSTEM_TIME_GAP_S = 2 * SYSTEM_TIME_INTERVAL_S
#: ``time_boot_ms`` going back by more than this is a reboot (smaller: frames reordered).
REBOOT_BACKSTEP_MS = 100
#: A reboot silences the autopilot at least this long (0.36 s measured on the simulator,
#: seconds on ArduPilot and PX4 SITL): the largest gap between its frames (by arrival) since
#: the SYSTEM_TIME before, if this long, makes a SYSTEM_TIME that says it rebooted evidence
#: enough.
REBOOT_SILENCE_S = 0.3
#: Without that silence, the new clock must go on for this long (more than a SYSTEM_TIME
#: interval) with no SYSTEM_TIME of the old clock among its frames.
REBOOT_CONFIRM_S = 1.5 * SYSTEM_TIME_INTERVAL_S


def is_reboot(
    previous_ms: int, previous_s: float, boot_ms: int, at_s: float, *, after_silence: bool
) -> bool:
    """Whether a SYSTEM_TIME saying ``boot_ms`` at ``at_s`` after one saying ``previous_ms`` at
    ``previous_s`` shows a reboot: backwards, or far behind where the time since the last one
    says it should be (a reboot soon after the previous boot may not take time_boot_ms below
    its old value by the time the stream, asked for again, comes back)."""
    lag_ms = REBOOT_LAG_AFTER_SILENCE_MS if after_silence else REBOOT_LAG_MS
    return (
        boot_ms + REBOOT_BACKSTEP_MS < previous_ms
        or boot_ms < previous_ms + (at_s - previous_s) * 1000.0 - lag_ms
    )


class AutopilotWatch:
    """Pinning, the link's state, reboots, silences, the streams asked for."""

    def __init__(self, core: ControlCore) -> None:
        self._core = core
        #: The autopilot's (system, component): configured parts are fixed, the rest latched
        #: from the first autopilot HEARTBEAT that matches them.
        self.pinned: tuple[int, int] | None = None
        #: The pinned autopilot answered one of our commands since the link came up: it has
        #: heard us, so it routes a ground station's targets to us (ArduPilot answers them
        #: UNSUPPORTED, PX4 drops them, for a component it has not heard).
        self._heard_us = False
        #: Armed, from its HEARTBEAT (None: no HEARTBEAT yet). Shown, not relied on: PX4's
        #: prearmed outputs are live while disarmed.
        self.armed: bool | None = None
        #: Its uptime by the last SYSTEM_TIME, and when that came.
        self.boot_ms: int | None = None
        self._boot_seen_s = 0.0
        self._system_time_s: float | None = None  # when the last SYSTEM_TIME came
        #: When every stream was last asked for.
        self.streams_asked_s = -float("inf")
        self._autopilot_heard_s: float | None = None  # the last frame from the pinned one
        self._autopilot_streaming = False  # its frames came within AUTOPILOT_GAP_INTERVALS
        #: By arrival: the pinned autopilot's last frame, and the largest gap between its
        #: frames since the last SYSTEM_TIME (see REBOOT_SILENCE_S).
        self._arrived_s: float | None = None
        self._largest_gap_s = 0.0
        #: A SYSTEM_TIME that said it rebooted, with no silence before it: (its time_boot_ms,
        #: when it arrived), until the second signal (REBOOT_CONFIRM_S) or the old clock.
        self._reboot_suspected: tuple[int, float] | None = None

    @property
    def reboot_suspected(self) -> bool:
        """A SYSTEM_TIME said the autopilot rebooted, and the second signal is awaited: what
        its outputs hold is unknown until then, so nothing is sent (a step re-sent over what
        another sender set since its boot would jump)."""
        return self._reboot_suspected is not None

    @property
    def heard_us_on_link(self) -> bool:
        """The autopilot answered us on a link that is up."""
        return self._core.state.link_up and self._heard_us

    def heard_us(self) -> None:
        """It answered one of our commands: it knows our route."""
        self._heard_us = True

    # -- frames -----------------------------------------------------------------------------

    def on_heartbeat(self, actions: list[Action], source: tuple[int, int], msg: Any) -> None:
        """An autopilot's HEARTBEAT (see ``is_autopilot_heartbeat``)."""
        if self.pinned is None:
            self.pin(source)
        elif source != self.pinned:
            self._core.state.counters["foreign_frames"] += 1
            return
        if source == self.pinned:
            self.armed = bool(msg.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED)
            self.after_silence(actions)

    def pin(self, source: tuple[int, int]) -> None:
        pin = self._core.settings.pin
        if all(want in (None, got) for want, got in zip(pin, source, strict=True)):
            self.pinned = source
            log.info("autopilot %d/%d pinned", *source)

    def set_link(self, actions: list[Action], up: bool) -> None:
        state = self._core.state
        if up == state.link_up:
            return
        state.link_up = up
        self._heard_us = False  # until it answers the streams' requests sent on link-up
        if not up:
            log.warning("autopilot link lost: holding, no servo commands")
            self.lose_outputs(actions, "autopilot link lost")
        else:
            if state.ever_sent:
                log.info("autopilot link up: re-sending every output before moving on")
            self.ask_for_streams(actions)

    def lose_outputs(self, actions: list[Action], reason: str) -> None:
        """The autopilot's outputs are unknown (link lost, reboot): re-send them all at the
        acknowledged pose before moving on; targets waiting are TEMPORARILY_REJECTED."""
        core, state = self._core, self._core.state
        flights = list(state.flights)
        state.flights.clear()
        core.motion.reject_waiting(actions, flights, reason)
        state.acked_pwm.clear()
        state.refused.clear()  # asked again: it may have been fixed meanwhile
        core.world.telemetry.reset()
        core.outputs.lost(flights)

    def ask_for_streams(self, actions: list[Action]) -> None:
        """Ask for every stream the core reads (an autopilot forgets them when it reboots):
        SYSTEM_TIME (reboots), SERVO_OUTPUT_RAW (what the outputs do), the firmware's own
        (ArduPilot's SYS_STATUS), the telemetry; and the parameters its outputs' truth reads."""
        if self.pinned is None:
            return
        core = self._core
        now = core.clock()
        self.streams_asked_s = now
        core.outputs.streams_asked(now)
        for msg_id, interval_s in core.settings.streams:
            actions.append(
                SendCommand(
                    self.pinned,
                    mavlink.MAV_CMD_SET_MESSAGE_INTERVAL,
                    (
                        float(msg_id),
                        -1.0 if interval_s < 0 else interval_s * 1e6,
                        0.0,
                        0.0,
                        0.0,
                        0.0,
                        0.0,
                    ),  # fmt: skip
                )
            )
        for name in core.outputs.params_to_read():
            actions.append(ReadParam(self.pinned, name))

    def arrived(self, at_s: float) -> None:
        """A frame from the pinned autopilot arrived at ``at_s``."""
        if self._arrived_s is not None:
            self._largest_gap_s = max(self._largest_gap_s, at_s - self._arrived_s)
        self._arrived_s = at_s

    def on_system_time(self, actions: list[Action], boot_ms: int, received_s: float) -> None:
        """A SYSTEM_TIME from the pinned autopilot, arrived at ``received_s``: a reboot shows
        in ``time_boot_ms``. Its arrival dates it, not when this thread takes it: a control
        thread that stalls (a loaded machine) would otherwise see ``time_boot_ms`` fall behind
        the time elapsed, a reboot that did not happen. A reboot with no silence before it
        needs a second signal (module docstring)."""
        silence_s, self._largest_gap_s = self._largest_gap_s, 0.0
        previous, previous_s = self.boot_ms, self._boot_seen_s
        if previous is None:
            self._take_time(boot_ms, received_s)
            self._core.outputs.clock_heard(received_s)
            return
        after_silence = self._system_time_s is None or received_s - previous_s > SYSTEM_TIME_GAP_S
        suspected = self._reboot_suspected
        if not is_reboot(previous, previous_s, boot_ms, received_s, after_silence=after_silence):
            if suspected is not None:  # the old clock goes on: that one was not the autopilot's
                self._reboot_suspected = None
                self._core.state.counters["forged_frames"] += 1
                log.warning(
                    "SYSTEM_TIME from two clocks (time_boot_ms %d, then %d): frames forged as "
                    "the autopilot's? Not taken as a reboot",
                    suspected[0],
                    boot_ms,
                )
            self._take_time(boot_ms, received_s)
            self._core.outputs.clock_heard(received_s)
            return
        if silence_s < REBOOT_SILENCE_S:
            if suspected is None or is_reboot(
                suspected[0], suspected[1], boot_ms, received_s, after_silence=False
            ):
                if suspected is None:
                    log.info(
                        "SYSTEM_TIME says the autopilot rebooted (time_boot_ms %d → %d) with no "
                        "silence before it: waiting for a second signal",
                        previous,
                        boot_ms,
                    )
                self._reboot_suspected = (boot_ms, received_s)
                return
            if received_s - suspected[1] < REBOOT_CONFIRM_S:
                return  # the new clock goes on, not long enough yet
        self._reboot_suspected = None
        self._take_time(boot_ms, received_s)
        self._rebooted(actions, previous, boot_ms)

    def _take_time(self, boot_ms: int, received_s: float) -> None:
        self.boot_ms, self._boot_seen_s = boot_ms, received_s
        self._system_time_s = received_s

    def _rebooted(self, actions: list[Action], previous_ms: int, boot_ms: int) -> None:
        """The autopilot rebooted: its outputs, our route and its parameters are forgotten."""
        self._core.state.counters["autopilot_reboots"] += 1
        log.warning(
            "autopilot rebooted (time_boot_ms %d → %d): re-sending every output",
            previous_ms,
            boot_ms,
        )
        # It forgot our route (until it answers us again) and reads its parameters anew.
        self._heard_us = False
        self._core.outputs.rebooted()
        self.lose_outputs(actions, "autopilot rebooted")
        self.ask_for_streams(actions)
        motion = self._core.motion
        if not self._core.config.resume_after_reboot and (
            motion.goal is not None or motion.trajectory
        ):
            # What was accepted before it is not carried out on its own after it: a vehicle
            # whose autopilot crashed and restarted may be somewhere else by now.
            log.warning(
                "autopilot rebooted: the arm's goal is dropped (send it again; "
                "control.resume_after_reboot = true goes on towards it)"
            )
            if motion.trajectory:
                motion.trajectory_aborted = "autopilot rebooted"
            motion.goal = None
            motion.trajectory.clear()
            self._core.world.drop()

    def after_silence(self, actions: list[Action]) -> None:
        """A frame from the pinned autopilot after it was silent for AUTOPILOT_GAP_INTERVALS
        of the fastest stream we asked for: it may have rebooted (and forgotten our streams),
        so they are asked for again at once. The SYSTEM_TIME that comes back says whether it
        did, and SYS_STATUS where its safety switch is, without waiting for a silence rule."""
        core = self._core
        now = core.clock()
        heard, self._autopilot_heard_s = self._autopilot_heard_s, now
        gap_s = core.settings.autopilot_gap_s
        if heard is None:
            return
        if now - heard <= gap_s:
            self._autopilot_streaming = True
            return
        # Only after its streams flowed: an autopilot that only beats (streams not asked yet,
        # or not supported) is not asked again at every HEARTBEAT.
        was_streaming, self._autopilot_streaming = self._autopilot_streaming, False
        if not (core.state.link_up and was_streaming):
            return
        # Silent long enough for SYSTEM_TIME's own rule: that first (no output taken for
        # granted), as the next tick would have done.
        self._watch_system_time(actions, now)
        if now - self.streams_asked_s < gap_s:
            return  # just asked
        log.info("the autopilot speaks again after %.2f s: asking for every stream", now - heard)
        self.ask_for_streams(actions)

    # -- ticks ------------------------------------------------------------------------------

    def watch(self, actions: list[Action], now: float) -> None:
        """The streams' silences (each tick while the link is up)."""
        self._watch_system_time(actions, now)
        if self._core.outputs.streams_silent(now):
            self.ask_for_streams(actions)

    def _watch_system_time(self, actions: list[Action], now: float) -> None:
        heard = self._system_time_s
        if now - self.streams_asked_s < SYSTEM_TIME_SILENT_S:
            return
        if heard is None:
            if now - self.streams_asked_s >= 5 * SYSTEM_TIME_SILENT_S:
                self.ask_for_streams(actions)  # never answered yet: ask now and then
            return
        if now - heard < SYSTEM_TIME_SILENT_S:
            return
        # The stream stopped while the autopilot still beats: it may have rebooted and
        # forgotten the interval. Ask again, and take no output for granted: every output is
        # re-sent at the acknowledged pose now, even with the arm still (a reboot left them
        # at their boot values), then the motion goes on.
        log.info("SYSTEM_TIME stopped: asking again and re-sending every output")
        self._system_time_s = None
        state = self._core.state
        state.acked_pwm.clear()
        self._core.outputs.went_quiet(state.flights, now)
        self.ask_for_streams(actions)
