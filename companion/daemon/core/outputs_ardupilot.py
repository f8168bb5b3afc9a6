"""ArduPilot's outputs' truth: its SYS_STATUS says where its safety switch is.

ArduPilot shows in its readback what it was told even with the safety switch on; SYS_STATUS
(MAV_SYS_STATUS_SENSOR_MOTOR_OUTPUTS enabled: the switch is off) says whether the outputs are
live, and BRD_SAFETY_MASK which outputs the switch leaves live. The readback says where the
joints are at the start (nothing moves before one came, or READBACK_WAIT_S without), and when
another sender (a ground station's servo test) set an output: the joint is where it shows,
the motion goes on from there at the speed limit, and status says so (``foreign_command``).
A SYS_STATUS saying the switch is off while one said it is on less than
SAFETY_ON_STICKY_INTERVALS ago is not believed (frames forged as the autopilot's, on an
unsigned link, alternate with its own), nor one after "on" before the autopilot's clock went
on after it (while it reboots, forged frames are all there is). What the outputs may hold
while the switch is unseen stays within a band a step wide (``SAFETY_STEPS_AHEAD``); once the
switch is seen on, the held outputs are sent back to the middle of that band (the rewind).
Outputs in BRD_SAFETY_MASK stay live with the switch on, but the mask may change at any moment
(a ground station sets it; ArduPilot applies it within MASK_APPLY_S): while the switch is on,
the mask is asked for at every SYS_STATUS, and an answer narrows a joint's band as an "off"
would, to the poses sent since it was asked, once the output has been in every answer for
MASK_APPLY_S.
"""

from __future__ import annotations

import collections
import logging
import math
from collections.abc import Sequence
from typing import TYPE_CHECKING

from companion.daemon.core.actions import ReadParam
from companion.daemon.core.outputs import (
    READBACK_TOLERANCE_US,
    Band,
    OutputsTruth,
    band_of,
    middle,
)

if TYPE_CHECKING:
    from companion.daemon.core.actions import Action
    from companion.daemon.core.dispatcher import ControlCore
    from companion.daemon.core.state import Flight

log = logging.getLogger("armbridge")

#: Nothing moves until a SYS_STATUS said where the safety switch is (at start, after a loss or
#: a reboot: ArduPilot boots with it on, ``BRD_SAFETY_DEFLT``, and what is sent then is stored
#: and goes out in one step at its release); with none this long after asking, the arm moves
#: without knowing (and says so once).
SYS_STATUS_WAIT_S = 2.0
#: A SYS_STATUS stream silent for this many intervals says nothing of the switch any more:
#: status shows the outputs as not known to be live (a reboot: they are not).
SYS_STATUS_STALE_INTERVALS = 4
#: ... and silent this long (at least SYS_STATUS_STALE_INTERVALS), every stream is asked for
#: again (a rebooted ArduPilot forgot them; one asked while it reboots is lost), so a reboot is
#: seen from the SYSTEM_TIME that comes back rather than after SYSTEM_TIME_SILENT_S.
SYS_STATUS_SILENT_S = 0.5
#: For status: a readback stream silent this many intervals says the autopilot is silent (a
#: reboot), whatever SYS_STATUS frames still come (forged as its own, on an unsigned link): its
#: outputs are not known to be live. Three lost frames in a row are not yet a silence.
READBACK_STALE_INTERVALS = 4

SAFETY_MASK_PARAM = "BRD_SAFETY_MASK"
#: ArduPilot's output driver reads BRD_SAFETY_MASK at 10 Hz: a new mask applies within 0.1 s of
#: being set (with a margin here). An output the mask newly frees may still be held that long
#: after an answer says it is in it; one it newly holds is held only after the answer said
#: otherwise, so the pose it holds is among those sent since that answer was asked for.
MASK_APPLY_S = 0.12
#: While the switch is on, BRD_SAFETY_MASK asked for and unanswered this many SYS_STATUS
#: intervals (a lost request or answer) is asked for again.
MASK_ASK_AGAIN_INTERVALS = 4
#: A SYS_STATUS saying the switch is off is believed only this many SYS_STATUS intervals after
#: the last one that said it is on: the autopilot's own stream, saying on, would otherwise be
#: overruled by a frame forged between two of its frames.
SAFETY_ON_STICKY_INTERVALS = 1.5
#: Two SYS_STATUS arriving less than this many intervals apart break the stream's cadence:
#: one of them is not the autopilot's (frames forged as its own, on an unsigned link), and so
#: until SAFETY_ON_STICKY_INTERVALS after the last such frame. Then an "off" says only what no
#: "on" says (see SYS_STATUS_ON_WITHIN_INTERVALS). A forger sending twice an interval or more
#: always comes this close to the autopilot's frames; one sending no more often than the
#: stream, between its frames, is not told apart (signing is the remedy). A link that bunches
#: frames, or a stalled reader, breaks the cadence too: the arm then moves on more slowly,
#: within its band. A release ("off" believed after "on", which the autopilot's own "on"
#: frames and its clock vouch for) narrows the band as a clean "off" does, whatever the
#: cadence: the outputs bring out what they stored.
SYS_STATUS_CADENCE_INTERVALS = 0.4
#: The switch going on shows in the autopilot's next SYS_STATUS, and "on" is believed at once:
#: with none saying on for this many intervals (three of its frames lost in a row), the switch
#: was off that long ago. So with the cadence broken, an "off" (the autopilot's or a forger's)
#: narrows the band to the poses held since this many intervals before it arrived, each step
#: sent since and the pose it was sent from; a clean "off" narrows it to those since
#: SYS_STATUS_AGE_INTERVALS. Only while the readback stream flows: a fade that loses the
#: autopilot's frames loses those too, and "off" frames still coming are a forger's (nothing
#: narrows then, the band only takes in what is sent; one forging the readback too through a
#: fade is not told apart: signing is the remedy).
SYS_STATUS_ON_WITHIN_INTERVALS = SYS_STATUS_STALE_INTERVALS
#: A SYS_STATUS saying off speaks of the moment it left the autopilot, which may be before
#: steps taken since (the control thread takes it later than the reader did, a busy board or
#: a held frame): "off" narrows the band to the poses held since this many intervals before
#: it arrived, each step sent since and the pose it was sent from (without them, the switch
#: going on just before a step was acknowledged left the pose it held out of the band).
SYS_STATUS_AGE_INTERVALS = 0.5
#: The most steps kept for the bands: more than SYS_STATUS_ON_WITHIN_INTERVALS + 1 of
#: SYS_STATUS's slowest interval (0.25 s, a slow serial line) at the highest control rate
#: (400 Hz): 500.
STEPS_KEPT = 1024


def band_allows(band: Band, step: Sequence[float], width_deg: float) -> bool:
    """Whether adding ``step`` to ``band`` keeps it within ``width_deg`` on every joint."""
    low, high = band
    width = width_deg + 1e-9
    return all(max(hi, a) - min(lo, a) <= width for lo, hi, a in zip(low, high, step, strict=True))


def _pinned(pose: tuple[float, ...], i: int, angle: float) -> tuple[float, ...]:
    """``pose`` with joint ``i`` at ``angle``."""
    return (*pose[:i], angle, *pose[i + 1 :])


def widen(band: Band, step: Sequence[float]) -> None:
    """Widen ``band`` (in place) to hold ``step``."""
    low, high = band
    for i, a in enumerate(step):
        low[i], high[i] = min(low[i], a), max(high[i], a)


class ArduPilotOutputs(OutputsTruth):
    """ArduPilot: the safety switch says whether the outputs are live (module docstring)."""

    def __init__(self, core: ControlCore) -> None:
        super().__init__(core)
        #: BRD_SAFETY_MASK (None: not read yet; then no output is assumed to be in it).
        self._safety_mask: int | None = None
        #: The switch on: when BRD_SAFETY_MASK was last asked for, not answered yet (None: no
        #: request outstanding).
        self._mask_asked_s: float | None = None
        #: The switch on: per arm output in every BRD_SAFETY_MASK seen since the switch was
        #: seen on, from when it is surely live (the first such answer's arrival plus
        #: MASK_APPLY_S); an answer to a request asked after that narrows its joint's band.
        self._mask_live_from_s: dict[int, float] = {}
        #: Per arm output a BRD_SAFETY_MASK put in it (none before had it): when that came. The
        #: switch on, it is taken as held MASK_APPLY_S more (ArduPilot applies it within 0.1 s;
        #: what is sent meanwhile is stored, and goes out with the release).
        self._mask_freed_s: dict[int, float] = {}
        self._sys_status_asked_s = core.clock()
        self._sys_status_s: float | None = None  # when the last SYS_STATUS came (None: none)
        #: A SYS_STATUS came from this autopilot once: it streams them, so the arm never moves
        #: without one (a stream lost in a reboot is asked for again instead).
        self._sys_status_ever = False
        self._sys_status_warned = False
        #: Per joint, the lowest and highest angle the outputs may hold since the last
        #: SYS_STATUS that said the switch was off (see ``SAFETY_STEPS_AHEAD``; None: no such
        #: SYS_STATUS since the start, a loss or a reboot). A loss or a reboot forgets it (a
        #: rebooted ArduPilot comes back with its switch at BRD_SAFETY_DEFLT).
        self._held_since_off: Band | None = None
        #: After a loss or a reboot until every output is acknowledged again: the band of
        #: poses the outputs may hold from before it (the re-send among them).
        self._held_before_loss: Band | None = None
        #: A motion step waited for a SYS_STATUS (the band): it goes out when one comes.
        self._step_waits_for_sys_status = False
        #: The pose to send the held outputs back to once the switch was seen on (the rewind).
        self._rewind_to: tuple[float, ...] | None = None
        #: ... for the joints the switch held then (not in BRD_SAFETY_MASK), by index.
        self._rewind_joints: list[int] = []
        #: When a SYS_STATUS last said the switch is on (by arrival).
        self._safety_on_seen_s = -math.inf
        #: The switch unknown (start, loss, reboot): since when SYS_STATUS says it is off, with
        #: none saying on since (None: none said off yet).
        self._off_since_s: float | None = None
        #: When the last SYS_STATUS arrived, and until when an "off" narrows the band only to
        #: what no "on" says (see SYS_STATUS_CADENCE_INTERVALS).
        self._sys_status_at_s = -math.inf
        self._cadence_broken_until_s = -math.inf
        #: Joints taken where another sender put their output, none of our ACKs for it since
        #: (a step on its way from before says nothing of where it is).
        self._taken: set[int] = set()
        #: ... and per output so taken, how many updates had been sent then: the ACKs of those
        #: sent before it say nothing of where it is (see :meth:`overtaken`).
        self._taken_seq: dict[int, int] = {}
        #: Per output, the PWM its readback showed when the first of the ACKs it has was
        #: given (see :meth:`acknowledged`).
        self._shown_before: dict[int, int | None] = {}
        #: The steps sent in the last SYS_STATUS_ON_WITHIN_INTERVALS (and one before): when,
        #: the pose each was sent from, the step (at most STEPS_KEPT: memory stays flat).
        self._steps_sent: collections.deque[tuple[float, tuple[float, ...], tuple[float, ...]]] = (
            collections.deque(maxlen=STEPS_KEPT)
        )

    # -- frames -----------------------------------------------------------------------------

    def on_sys_status(self, actions: list[Action], safety_on: bool, at_s: float) -> None:
        """The safety switch, as a SYS_STATUS arrived at ``at_s`` says (see
        ``SAFETY_STEPS_AHEAD`` and ``SAFETY_ON_STICKY_INTERVALS``)."""
        core = self._core
        self._sys_status_s = core.clock()
        self._sys_status_ever = True
        interval_s = core.settings.sys_status_interval_s
        self._check_cadence(at_s, interval_s)
        if safety_on:
            self._safety_on_seen_s = at_s
            self._off_since_s = None
        elif self.safety_on is None:
            # Unknown since the start, a loss or a reboot (it boots with the switch on): "off"
            # is believed once SYS_STATUS has said so for SAFETY_ON_STICKY_INTERVALS, counted
            # from when the stream was asked for at the earliest, with none saying on: the
            # autopilot's own stream, flowing by then, would have said on (frames forged as
            # its own, while it reboots or before its stream comes back, are all there is).
            if self._off_since_s is None:
                self._off_since_s = at_s
            since_s = max(self._off_since_s, self._sys_status_asked_s)
            if at_s - since_s < SAFETY_ON_STICKY_INTERVALS * interval_s:
                return
        elif at_s - self._safety_on_seen_s < SAFETY_ON_STICKY_INTERVALS * interval_s:
            if self.safety_on is False:
                log.warning(
                    "SYS_STATUS says the safety switch is both on and off (frames forged as "
                    "the autopilot's?): taken as on"
                )
            safety_on = True
        elif self.safety_on:
            # "Off" after "on" is believed once the autopilot's clock went on after the first
            # such frame (asked for now): while it reboots it is silent, and frames forged as
            # its own, at its cadence, are all there is.
            if self._off_since_s is None:
                self._off_since_s = at_s
            if self._clock_heard_s <= self._off_since_s:
                self._probe_wanted = True
                return
        released = safety_on is False and self.safety_on is True
        if safety_on != self.safety_on:
            if safety_on:
                log.warning("safety switch on: outputs not live")
            elif self.safety_on is not None:  # off after on: a board without one never says
                log.info("safety switch off")
            if safety_on and self._held_since_off is not None:
                self._rewind_to = middle(self._held_since_off)
                self._rewind_joints = self._switch_holds()
            elif not safety_on:
                self._rewind_to = None
            if safety_on:
                # What the mask frees counts from answers given since (module docstring).
                self._mask_live_from_s.clear()
                if self._held_since_off is None:  # no "off" since the start: from now on
                    self._held_since_off = band_of(self._poses_since(math.inf))
        self.safety_on = safety_on
        if safety_on:
            self._ask_mask(actions, interval_s)
            return
        # Off now: the outputs hold what was acknowledged, or a step still on its way (or one
        # whose update ended unanswered: it is sent again before anything else), or any step
        # sent since the frame left the autopilot.
        band = self._held_since_off
        if band is None or released or at_s >= self._cadence_broken_until_s:
            # A clean "off", or a release believed (no "on" for SAFETY_ON_STICKY_INTERVALS, the
            # autopilot's clock heard since): the held outputs brought out what they stored.
            self._held_since_off = band_of(
                self._poses_since(at_s - SYS_STATUS_AGE_INTERVALS * interval_s)
            )
        elif self._autopilot_flowing(at_s):
            # Perhaps forged: no "on" for SYS_STATUS_ON_WITHIN_INTERVALS says as much.
            self._held_since_off = band_of(
                self._poses_since(at_s - SYS_STATUS_ON_WITHIN_INTERVALS * interval_s)
            )
        else:
            for pose in self._poses_since(at_s - SYS_STATUS_AGE_INTERVALS * interval_s):
                # (a forger's: nothing narrows)
                widen(band, pose)
        self._step_held_back(actions)

    def _poses_since(self, since_s: float) -> list[tuple[float, ...]]:
        """The poses the outputs may hold of what was sent up to now since ``since_s``: the
        one acknowledged (or the band held before a loss), the steps on their way or to be
        sent again, and each step sent since ``since_s`` with the pose it went from."""
        state = self._core.state
        poses = [f.step_deg for f in state.flights]
        if state.unconfirmed is not None:
            poses.append(state.unconfirmed)
        if self._held_before_loss is not None:  # what they held before is unknown: that band
            poses += [tuple(self._held_before_loss[0]), tuple(self._held_before_loss[1])]
        else:
            poses.append(tuple(state.position))
        for sent_s, base, step in self._steps_sent:
            if sent_s >= since_s:
                poses += [base, step]
        return poses

    def _step_held_back(self, actions: list[Action]) -> None:
        """A band narrowed: the motion step it held back goes out."""
        if self._step_waits_for_sys_status and self._core.state.link_up:
            self._step_waits_for_sys_status = False
            self._core.motion.next_step(actions, immediate=False)

    def _ask_mask(self, actions: list[Action], interval_s: float) -> None:
        """The switch on, every arm output in BRD_SAFETY_MASK as last read: ask for it (one
        request at a time; again after MASK_ASK_AGAIN_INTERVALS unanswered)."""
        core = self._core
        pinned = core.watch.pinned
        if pinned is None or not core.state.link_up or self._safety_mask is None or self.dead():
            return
        now = core.clock()
        asked_s = self._mask_asked_s
        if asked_s is not None and now - asked_s < MASK_ASK_AGAIN_INTERVALS * interval_s:
            return
        self._mask_asked_s = now
        actions.append(ReadParam(pinned, SAFETY_MASK_PARAM))

    def _check_cadence(self, at_s: float, interval_s: float) -> None:
        """A SYS_STATUS arrived at ``at_s``: less than SYS_STATUS_CADENCE_INTERVALS after the
        one before, one of them is not the autopilot's, and so perhaps the "off" frames that
        narrowed the band lately: it takes in again what was held since
        SYS_STATUS_ON_WITHIN_INTERVALS (see the constants)."""
        gap_s = at_s - self._sys_status_at_s
        if gap_s < 0:
            return  # stamped before the one before: says nothing of the cadence
        self._sys_status_at_s = at_s
        if gap_s >= SYS_STATUS_CADENCE_INTERVALS * interval_s:
            return
        self._cadence_broken_until_s = at_s + SAFETY_ON_STICKY_INTERVALS * interval_s
        band = self._held_since_off
        if band is not None:
            for pose in self._poses_since(at_s - SYS_STATUS_ON_WITHIN_INTERVALS * interval_s):
                widen(band, pose)

    def _autopilot_flowing(self, now: float) -> bool:
        """Whether the autopilot's readback stream is heard (not silent for
        READBACK_STALE_INTERVALS): its frames are reaching us, an "on" among them."""
        return (
            self.shown_s > -math.inf
            and self.readback_silence(now, READBACK_STALE_INTERVALS) is None
        )

    def _check_readback(self) -> None:
        """At the start the joints are where the readback shows; later, an output that shows
        something else than what it acknowledged, for long enough to be believed, was set by
        another sender: the joint is where it shows."""
        core, state = self._core, self._core.state
        now = core.clock()
        for i, output in enumerate(state.outputs):
            shown = self.shown.get(output)
            if shown is None or not self.in_range(output, shown):
                # No pulses (an output nothing set since boot), or not a joint's PWM: that
                # contradicts frames that showed one (forged, after a reboot).
                self._forget_steady(output)
                continue
            acked = state.acked_pwm.get(output)
            if acked is None:
                if any(output in f.pwm_by_output for f in state.flights):
                    # Ours on its way (shown before its ACK, or not applied yet): its outcome
                    # says where the output is.
                    self._forget_steady(output)
                    self._doubt_until_s.pop(output, None)
                elif output not in self._steady_seen and self._as_held(i, output, shown):
                    # Where the joint is already taken to be (a PWM believed before, the pose
                    # to re-send): nothing to decide. (Not while another PWM is being judged:
                    # frames showing two by turns believe neither.)
                    self._doubt_until_s.pop(output, None)
                elif not self._shown_steadily(output, shown):
                    pass  # not believed yet: the motion holds until the next readbacks say
                else:
                    self._forget_steady(output)
                    self._place(i, output, shown)
                continue
            self._forget_steady(output)
            expected, settled = self._expected_pwms(output, now)
            if not settled and (before := self._shown_before.get(output)) is not None:
                # Our first ACKs are all recent (a start, a loss, a reboot): the readback may
                # still show what the output held before them, and nothing else.
                expected.add(before)
                settled = True
            on_its_way = {
                f.pwm_by_output[output] for f in state.flights if output in f.pwm_by_output
            }
            if any(abs(shown - pwm) <= READBACK_TOLERANCE_US for pwm in expected | on_its_way):
                self._agrees(output)
                self._shown_ack(output, shown)
                continue
            # Neither what it acknowledged nor a step on its way (an update left unknown among
            # them): another sender's, once believed.
            if not settled or not self._disagrees(output, self.shown_s, clock_after=True):
                continue
            self._agrees(output)
            if not core.motion.moving(tuple(state.position)):
                core.motion.goal = None  # the arm was still: it stays where it was put
            angle = self.angle_shown(output, shown)
            log.warning(
                "output %d shows %d us, not the %d us acknowledged: set by another sender "
                "(a ground station's servo test?); the joint is taken where it shows "
                "(%.1f deg), the motion goes on from there",
                output,
                shown,
                acked,
                angle,
            )
            state.counters["foreign_commands"] += 1
            self.foreign_command = {
                "output": output,
                "shown_us": shown,
                "acknowledged_us": acked,
                "at_s": self.shown_s,
            }
            state.acked_pwm[output] = shown
            self._ack_history.pop(output, None)
            self._forget_shown_acks(output)
            self.acknowledged(output, shown, now)
            self._joint_at(i, angle)

    def _place(self, i: int, output: int, shown: int) -> None:
        """Readbacks steadily show ``output`` (index ``i``), nothing of ours acknowledged, at
        ``shown``: the joint is there."""
        state = self._core.state
        if not state.ever_sent:
            # The start: ArduPilot keeps what its outputs were told (by an earlier daemon)
            # until it reboots; the joint is there, not at the park pose.
            if self._as_held(i, output, shown):
                return
            angle = self.angle_shown(output, shown)
            log.info(
                "output %d shows %d us at the start: the joint is taken there (%.1f deg)",
                output,
                shown,
                angle,
            )
            self._start_at(i, angle)
            if self._held_since_off is not None:  # nothing sent: they hold that
                self._held_since_off = band_of([tuple(state.position)])
        elif not self._as_held(i, output, shown):
            # After a loss or a reboot: another sender set the output since the boot; the pose
            # re-sent keeps it there.
            self._take_shown(i, output, shown)

    def _joint_at(self, i: int, angle: float) -> None:
        """Joint ``i``'s output holds ``angle`` (a readback showed another sender's PWM): the
        joint is there, a pose still to re-send keeps it there, a command of an update left
        unknown is not confirmed over it, a rewind still to come leaves it there, and the
        bands hold it there alone: that is where the output is, or, held by the switch, what
        it stores and brings out at the release (the other sender's step, not ours; a re-send
        at the middle of a band widened to take it in beside what they held moved the joint
        half that width at once)."""
        state = self._core.state
        self._start_at(i, angle)
        self._taken.add(i)
        output = state.outputs[i]
        for flight in state.flights:  # an update left unknown is not confirmed over it
            flight.pending = [c for c in flight.pending if output not in c.outputs]
            flight.step_deg = _pinned(flight.step_deg, i, angle)  # the next step goes from it
        self._taken_seq[output] = state.updates_sent
        # So do the bands, and the steps an "off" or a broken cadence would take in: what they
        # hold of this joint is from before the other sender's step.
        for band in (self._held_before_loss, self._held_since_off):
            if band is not None:
                band[0][i] = band[1][i] = angle
        self._steps_sent = collections.deque(
            (
                (sent_s, _pinned(base, i, angle), _pinned(step, i, angle))
                for sent_s, base, step in self._steps_sent
            ),
            maxlen=self._steps_sent.maxlen,
        )
        if self._rewind_to is not None:  # the switch on: the rewind leaves it there
            rewind = list(self._rewind_to)
            rewind[i] = angle
            self._rewind_to = tuple(rewind)

    def _as_held(self, i: int, output: int, shown: int) -> bool:
        """Whether ``shown`` is the PWM of where joint ``i`` is taken to be (the pose still to
        re-send, else the acknowledged one). Before anything is sent, that PWM exactly: a pose
        restored from the file a PWM off what the output shows, taken as held, put the first
        step a PWM further than a step from where the joint was."""
        state = self._core.state
        angle = (state.unconfirmed or state.position)[i]
        joint = self._core.config.calibration.for_output(output)
        angle = min(max(angle, joint.angle_min_deg), joint.angle_max_deg)
        tolerance_us = READBACK_TOLERANCE_US if state.ever_sent else 0
        return abs(joint.mapped_pwm_us(angle) - shown) <= tolerance_us

    def _take_shown(self, i: int, output: int, shown: int) -> None:
        """The joint of ``output`` (index ``i``) is where its readback shows."""
        state = self._core.state
        angle = self.angle_shown(output, shown)
        if state.position[i] == angle and (
            state.unconfirmed is None or state.unconfirmed[i] == angle
        ):
            return
        log.info("output %d shows %d us: the joint is taken there (%.1f deg)", output, shown, angle)
        self._joint_at(i, angle)

    def on_param(self, actions: list[Action], name: str, value: float, at_s: float) -> None:
        if name != SAFETY_MASK_PARAM:
            return
        # From the pinned autopilot, but a frame forged as it (no signing) may say NaN.
        mask = int(value) if math.isfinite(value) and value >= 0 else None
        outputs = self._core.state.outputs
        was_live = set(o for o in outputs if o not in self.dead())
        before, self._safety_mask = self._safety_mask, mask
        asked_s, self._mask_asked_s = self._mask_asked_s, None
        for output in outputs:
            if mask is not None and mask >> (output - 1) & 1:
                self._mask_live_from_s.setdefault(output, at_s + MASK_APPLY_S)
                if before is None or not before >> (output - 1) & 1:
                    self._mask_freed_s[output] = at_s
            else:
                self._mask_live_from_s.pop(output, None)
                self._mask_freed_s.pop(output, None)
        band = self._held_since_off
        if not self.safety_on or band is None:
            return
        if was_live - set(o for o in outputs if o not in self.dead()):
            # The mask holds an output it left live: it holds one of the poses sent since this
            # was asked for, all within the band; the held outputs go back to its middle.
            log.warning("BRD_SAFETY_MASK changed with the safety switch on: outputs not live")
            self._rewind_to = middle(band)
            self._rewind_joints = self._switch_holds()
            return
        if asked_s is None:
            return  # not ours (a ground station set it): says nothing of when it applied
        narrowed = [
            i
            for i, output in enumerate(outputs)
            if self._mask_live_from_s.get(output, math.inf) <= asked_s
        ]
        if narrowed:
            since = band_of(self._poses_since(asked_s))
            for i in narrowed:
                band[0][i], band[1][i] = since[0][i], since[1][i]
            self._step_held_back(actions)

    def params_to_read(self) -> list[str]:
        return [SAFETY_MASK_PARAM] if self._safety_mask is None else []

    def streams_asked(self, now: float) -> None:
        self._sys_status_asked_s = now

    def rebooted(self) -> None:
        # Set and not applied yet, a mask applies at the boot: it is read anew.
        self._safety_mask = None

    # -- losses -----------------------------------------------------------------------------

    def _forget_safety(self) -> None:
        """A loss or a (possible) reboot: the switch is unknown until a SYS_STATUS says (it
        boots at BRD_SAFETY_DEFLT), and no pose from before is rewound to."""
        self.safety_on = None
        self._sys_status_s = None
        self._off_since_s = None
        self._held_since_off = self._rewind_to = None
        self._mask_asked_s = None
        self._mask_live_from_s.clear()

    def _resend_pose(self, flights: Sequence[Flight]) -> tuple[float, ...]:
        """After a loss or a reboot: the pose to send every output to again, within one step of
        anything they may hold. The switch seen on: the pose they were sent back to (nothing
        moved since). Else the middle of the band of poses they may hold since the last
        SYS_STATUS that said off (``SAFETY_STEPS_AHEAD``: the switch may have gone on since),
        or with none, the oldest step that was on its way (they hold it, the acknowledged
        pose, or the step behind it)."""
        if self.safety_on is True and self._rewind_to is not None:
            # Seen on, not sent back yet: the outputs it held to the rewind; those it left
            # live (BRD_SAFETY_MASK) went on with the motion.
            live = flights[0].step_deg if flights else tuple(self._core.state.position)
            held = self._rewind_joints
            return tuple(
                r if i in held else a
                for i, (r, a) in enumerate(zip(self._rewind_to, live, strict=True))
            )
        if self.safety_on is not True and self._held_since_off is not None:
            return middle(self._held_since_off)
        if self._held_before_loss is not None:  # lost again before the re-send was acknowledged
            return middle(self._held_before_loss)
        return flights[0].step_deg if flights else tuple(self._core.state.position)

    def _forget_outputs(self, flights: Sequence[Flight]) -> tuple[float, ...] | None:
        """A loss or a (possible) reboot: what the outputs may hold is kept as the band held
        before the loss, the switch forgotten; the pose to send them to again (None: nothing
        was ever sent)."""
        state = self._core.state
        self._readback_since_s = self._core.clock()  # where they are: the next readback says
        if not (flights or state.ever_sent):
            self._forget_safety()
            return None
        resend = list(self._resend_pose(flights))
        if self._held_since_off is not None:
            poses = [tuple(self._held_since_off[0]), tuple(self._held_since_off[1])]
        elif self._held_before_loss is not None:
            poses = [tuple(self._held_before_loss[0]), tuple(self._held_before_loss[1])]
        else:
            poses = [tuple(state.position)] + [f.step_deg for f in flights]
        band = band_of([*poses, tuple(resend)])
        for i in self._taken:  # where another sender put it, whatever was on its way before
            resend[i] = band[0][i] = band[1][i] = state.position[i]
        self._held_before_loss = band
        self._forget_safety()
        return tuple(resend)

    def lost(self, flights: Sequence[Flight]) -> None:
        resend = self._forget_outputs(flights)  # the switch unknown (it boots on)
        if resend is not None:
            # The outputs hold what they were last told (see _resend_pose): sent again within
            # one step of it.
            state = self._core.state
            state.unconfirmed = resend
            state.resend_at_once = True

    def went_quiet(self, flights: Sequence[Flight], now: float) -> None:
        resend = self._forget_outputs(flights)  # it may have rebooted, switch on
        if not flights and resend is not None:
            state = self._core.state
            state.unconfirmed = resend
            state.resend_at_once = True

    # -- the motion's questions --------------------------------------------------------------

    def may_move(self, actions: list[Action], now: float) -> bool:
        if not self._readback_seen(now):
            # Where the joints are comes from the first readback since the start, a loss or a
            # reboot (another sender may have set an output meanwhile: the re-send waits).
            return False
        if not self._safety_known(now) or self._judging(now):
            # (Judging: an output shows a PWM not believed yet; moving from where the joint
            # is taken to be now could jump from where it is.)
            return False
        dead = self.dead()
        if dead and self._rewind_to is not None and not self.in_doubt(now):
            # (Not while a readback is in doubt: it may show an output another sender set,
            # which the rewind must not send back over.)
            self._rewind(actions, dead, now)
        # The safety switch: whatever is sent is applied at once when it goes off.
        return not dead

    def may_pipeline(self) -> bool:
        return True

    def overtaken(self, seq: int) -> set[int]:
        # Outputs another sender set, believed after that update went out: its ACKs for them
        # (given before that command, or the readbacks would not have shown it) say nothing
        # of where they are.
        return {o for o, taken_seq in self._taken_seq.items() if seq < taken_seq}

    def may_confirm(self, now: float) -> bool:
        """Confirming an update alone re-sends its commands: not before a readback since it
        went unanswered (another sender may have set an output since a reboot), nor while a
        readback's word is in doubt or the safety switch is unknown."""
        return self._readback_seen(now) and not self.in_doubt(now) and self._safety_known(now)

    def unanswered(self, now: float) -> None:
        self._readback_since_s = now  # where the outputs are: the next readback says

    def may_step_to(self, step: tuple[float, ...]) -> bool:
        """A motion step to ``step`` keeps the poses the outputs may hold since the last
        SYS_STATUS that said the switch is off within ``SAFETY_STEPS_AHEAD`` (always true when
        none came since the start, a loss or a reboot: see ``_safety_known``)."""
        if self._held_since_off is None:
            return True
        width_deg = self._core.settings.safety_band_width_deg
        ok = band_allows(self._held_since_off, step, width_deg)
        self._step_waits_for_sys_status = not ok
        return ok

    def stepped_to(self, step: tuple[float, ...]) -> None:
        """A step to ``step`` went out: the outputs may hold it."""
        state = self._core.state
        now = self._core.clock()
        kept_s = (SYS_STATUS_ON_WITHIN_INTERVALS + 1) * self._core.settings.sys_status_interval_s
        while self._steps_sent and self._steps_sent[0][0] < now - kept_s:
            self._steps_sent.popleft()
        self._steps_sent.append((now, tuple(state.position), step))
        if self._held_since_off is not None:
            widen(self._held_since_off, step)

    def may_hold(self) -> list[tuple[float, ...]]:
        """The ends of the bands the outputs may hold since the switch was last seen off and
        from before a loss or a reboot."""
        return [
            tuple(end)
            for band in (self._held_since_off, self._held_before_loss)
            if band is not None
            for end in band
        ]

    def acknowledged(self, output: int, pwm: int, now: float) -> None:
        if not self._ack_history.get(output):
            self._shown_before[output] = self.shown.get(output)
        self._taken.discard(self._core.state.outputs.index(output))
        super().acknowledged(output, pwm, now)

    def all_acknowledged(self) -> None:
        self._held_before_loss = None  # they hold what was acknowledged

    def dead(self) -> dict[int, str]:
        if not self.safety_on:
            return {}
        mask = self._safety_mask or 0
        dead = {
            o: f"safety switch on (output {o} not in BRD_SAFETY_MASK)"
            for o in self._core.state.outputs
            if not mask >> (o - 1) & 1
        }
        now = self._core.clock()
        for output, freed_s in self._mask_freed_s.items():
            if now < freed_s + MASK_APPLY_S and output not in dead:
                dead[output] = (
                    f"safety switch on (output {output} just put in BRD_SAFETY_MASK: "
                    "ArduPilot frees it within 0.1 s)"
                )
        return dead

    def unknown(self, now: float) -> dict[int, str]:
        """While its SYS_STATUS stream (once seen) is silent for SYS_STATUS_STALE_INTERVALS (a
        reboot, a loss) or has not said where the switch is since a loss or a reboot; and
        while its readback stream (once heard) is silent for READBACK_STALE_INTERVALS: the
        autopilot is silent (a reboot), and SYS_STATUS frames still coming are not its own."""
        if not self._sys_status_ever:
            why = "safety switch unknown (no SYS_STATUS from the autopilot yet)"
            return dict.fromkeys(self._core.state.outputs, why)
        if self._sys_status_s is None or self.safety_on is None:
            why = "safety switch unknown (no SYS_STATUS since the link came back or a reboot)"
        else:
            silent_s = now - self._sys_status_s
            interval_s = self._core.settings.sys_status_interval_s
            if silent_s <= SYS_STATUS_STALE_INTERVALS * interval_s:
                silence = self.readback_silence(now, READBACK_STALE_INTERVALS)
                if silence is None:
                    return {}
                return dict.fromkeys(self._core.state.outputs, silence)
            why = f"safety switch unknown (no SYS_STATUS for {silent_s * 1e3:.0f} ms)"
        return dict.fromkeys(self._core.state.outputs, why)

    def streams_silent(self, now: float) -> bool:
        """A SYS_STATUS stream that fell silent holds the arm (``SAFETY_STEPS_AHEAD``; after a
        loss or a reboot, until one says where the switch is); every SYS_STATUS_SILENT_S of
        silence, every stream is asked for again (a request lost in a reboot). So too after
        READBACK_SILENT_S of a readback stream's silence: SYS_STATUS frames forged as the
        autopilot's while it rebooted would otherwise hide that it forgot every stream, and
        with the readback gone, where another sender put an output since goes unseen."""
        if self.readback_stream_silent(now, READBACK_STALE_INTERVALS):
            return True
        if not self._sys_status_ever:
            return False
        heard = -math.inf if self._sys_status_s is None else self._sys_status_s
        interval_s = self._core.settings.sys_status_interval_s
        silent_s = max(SYS_STATUS_SILENT_S, SYS_STATUS_STALE_INTERVALS * interval_s)
        if now - max(heard, self._sys_status_asked_s) < silent_s:
            return False
        # Said once a silence (a stream that never comes back is asked for every 0.5 s).
        say = log.info if now - heard < 2 * silent_s else log.debug
        say("no SYS_STATUS for %.2f s: asking for every stream again", now - heard)
        return True

    def refusal_advice(self, refused: dict[int, str]) -> tuple[str, str]:
        # The output belongs to something else (a motor, a gimbal): never advise taking it
        # away; the joint moves to a free output (doctor names them).
        if all("ARMB_" in why for why in refused.values()):
            # The Lua bridge refused our ids, not an output: its reason says what to set.
            return "", "Arm: Lua bridge refused our ids (ARMB_SYSID)"
        hint = " ".join(
            f"SERVO{o}_FUNCTION is not 0 on the flight controller: map the joint to a free "
            f"output (joint.output; armbridge doctor names them), or set SERVO{o}_FUNCTION = 0 "
            "only if nothing on the vehicle uses that output."
            for o, why in sorted(refused.items())
            if "ARMB_" not in why
        )
        first = min(refused)
        more = f"+{len(refused) - 1}" if len(refused) > 1 else ""
        return hint, f"Arm: output {first}{more} in use (SERVO{first}_FUNCTION)"

    # -- helpers ----------------------------------------------------------------------------

    def _safety_known(self, now: float) -> bool:
        """A SYS_STATUS said where the safety switch is since the start, the last loss or
        reboot (or none came for SYS_STATUS_WAIT_S, which is said once)."""
        if self.safety_on is not None:
            return True
        if self._sys_status_ever or now - self._sys_status_asked_s < SYS_STATUS_WAIT_S:
            return False  # (an autopilot that sent one sends them: asked again meanwhile)
        if not self._sys_status_warned:
            self._sys_status_warned = True
            log.warning(
                "no SYS_STATUS from the autopilot in %.0f s: moving without knowing its safety "
                "switch (outputs held by it store what is sent, and jump to it at its release)",
                SYS_STATUS_WAIT_S,
            )
        return True

    def _switch_holds(self) -> list[int]:
        """The joints (by index) whose outputs the safety switch holds when on: those not in
        BRD_SAFETY_MASK (all while it is not read)."""
        mask = self._safety_mask or 0
        return [i for i, o in enumerate(self._core.state.outputs) if not mask >> (o - 1) & 1]

    def _rewind(self, actions: list[Action], dead: dict[int, str], now: float) -> None:
        """The safety switch seen on: it went on at some moment since the SYS_STATUS before,
        and its outputs have held since then what they had; the steps sent meanwhile are
        stored and would go out in one step at its release. The dead outputs are sent back to
        the pose commanded at that SYS_STATUS (within one SYS_STATUS interval of motion of
        what they hold), and the motion goes on from there once the switch is off."""
        rewind, self._rewind_to = self._rewind_to, None
        assert rewind is not None
        state = self._core.state
        current = list(state.position)
        step = tuple(
            rewind[i] if output in dead else current[i] for i, output in enumerate(state.outputs)
        )
        if step != tuple(current) or not state.settled():
            log.info("safety switch on: the held outputs sent back to where they stopped")
            self._core.updates.send_step(actions, step, now)
