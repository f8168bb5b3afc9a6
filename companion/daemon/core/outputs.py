"""The outputs' truth: what the autopilot's outputs really do (an ACK proves nothing).

One interface, :class:`OutputsTruth`, and one class per firmware: PX4's readback
(:mod:`.outputs_px4`) and ArduPilot's safety switch (:mod:`.outputs_ardupilot`). The rest of
the core asks it ("may the motion go on?", "may I step to this pose?", "what is dead?", "what
is unknown for status?", "a loss happened", "a readback came") and never asks which firmware
it talks to.
"""

from __future__ import annotations

import abc
import collections
import logging
import math
from collections.abc import Sequence
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from companion.daemon.core.actions import Action
    from companion.daemon.core.dispatcher import ControlCore
    from companion.daemon.core.state import Flight

log = logging.getLogger("armbridge")

#: With no readback this long after the start (or, on PX4, a loss or a reboot), move without it
#: (and say so).
READBACK_WAIT_S = 2.0
#: A readback stream (once seen) silent this long (and at least its firmware's stale intervals)
#: is asked for again with every stream: a rebooted autopilot forgot them, and its reboot is then
#: seen from the SYSTEM_TIME that comes back rather than after SYSTEM_TIME_SILENT_S.
READBACK_SILENT_S = 0.5
#: A readback PWM within this of the acknowledged one is "the same" (PX4 rounds its mapping).
READBACK_TOLERANCE_US = 1
#: A readback this long after an output's ACK shows what the output does with that command
#: (the autopilot applies it on its next output cycle, a few ms; the stream adds up to its
#: interval, see :meth:`OutputsTruth.settle_s`).
READBACK_SETTLE_S = 0.15
#: An output's readback disagrees with what it acknowledged only after this many readbacks in
#: a row show the same other PWM, spanning more than the stream's interval (by arrival) with
#: none showing anything else between: the autopilot's own readback falls inside that span,
#: so frames forged as the autopilot's (an unsigned link), however many, are contradicted by
#: it and never make the daemon command the outputs somewhere on their word alone. (Frames
#: that show two PWMs by turns believe neither: the motion holds until one PWM alone is
#: shown; counting each PWM apart let a forger's frames, spread over the span, be believed
#: beside the autopilot's own.) The same rule takes an output where it shows when nothing of
#: ours is acknowledged (:meth:`OutputsTruth._shown_steadily`).
READBACK_MISMATCHES = 2
READBACK_SPAN_INTERVALS = 1.25
#: Meanwhile (a settled readback disagreed, not believed yet) the motion holds: no step goes
#: out on a belief the next readbacks may overturn; until this many intervals after the last
#: readback that disagreed (frames that agree between do not end it: with a forger on the
#: link, some of them are his).
READBACK_DOUBT_INTERVALS = 2.0

#: A readback that starts to disagree asks the autopilot for a SYSTEM_TIME at once (its clock
#: going on is what a belief waits for, see ``OutputsTruth._disagrees``), at most once in this
#: many readback intervals.
CLOCK_PROBE_INTERVALS = 2.0

#: A band of poses: per joint, the lowest and the highest angle.
Band = tuple[list[float], list[float]]


def band_of(poses: Sequence[Sequence[float]]) -> Band:
    """Per joint, the lowest and the highest angle of ``poses``."""
    return (
        [min(p[i] for p in poses) for i in range(len(poses[0]))],
        [max(p[i] for p in poses) for i in range(len(poses[0]))],
    )


def middle(band: Band) -> tuple[float, ...]:
    """Per joint, the middle of a band (within half its width of every angle in it)."""
    return tuple((lo + hi) / 2 for lo, hi in zip(*band, strict=True))


class OutputsTruth(abc.ABC):
    """What one firmware says of its outputs, and what the motion may do about it."""

    #: Readbacks that disagree with what an output acknowledged are believed with the
    #: autopilot's clock heard a readback interval or more into their run (asked for at the
    #: run's second frame), not only after the run is long enough: it was there then, so one
    #: of its own readbacks fell in the run and showed the same (else the run would have
    #: broken), and it did not reboot under frames forged alone. PX4: an output found dead
    #: gets its marker without the probe's round trip after the span (outputs alive again
    #: within that, prearm off and on, would come back to the marker in one step).
    CLOCK_INTO_RUN = False

    def __init__(self, core: ControlCore) -> None:
        self._core = core
        #: The last SERVO_OUTPUT_RAW: output → PWM shown, and when it arrived.
        self.shown: dict[int, int] = {}
        self.shown_s = -math.inf
        #: The safety switch by the last SYS_STATUS (None: none since the start, a loss or a
        #: reboot); shown in status.
        self.safety_on: bool | None = None
        #: The motion moves only after a readback newer than this (the start; PX4: a loss or a
        #: reboot too), or READBACK_WAIT_S after it with none (a firmware that does not stream
        #: it): the joints are where the outputs show, not at an assumed pose.
        self._readback_since_s = core.clock()
        self._readback_warned = False
        #: Per output, the PWMs acknowledged lately with when (a readback may still show any of
        #: those from the last :meth:`settle_s`); no entry: nothing acknowledged since the
        #: start, a loss or a reboot.
        self._ack_history: dict[int, collections.deque[tuple[float, int]]] = {}
        #: Per output, when the newest of its ACKs a readback showed was given (the readback
        #: cannot show the ones before it any more; no entry: none shown since its history
        #: began).
        self._shown_ack_s: dict[int, float] = {}
        #: Per output: a PWM of ours on its way that a readback showed before its ACK came
        #: (the output took it): that ACK, when it comes, is one the readback showed.
        self._shown_before_ack: dict[int, int] = {}
        #: Per output: the PWM settled readbacks in a row showed instead of the acknowledged
        #: one (within READBACK_TOLERANCE_US), when the first of them arrived, and how many.
        self._mismatches: dict[int, tuple[int, float, int]] = {}
        #: Per output with nothing of ours acknowledged: the PWM readbacks in a row showed (within
        #: READBACK_TOLERANCE_US), when the first of them arrived, and how many (see
        #: :meth:`_shown_steadily`).
        self._steady_seen: dict[int, tuple[int, float, int]] = {}
        #: Per output: when its readbacks first disagreed long enough (waiting for the
        #: autopilot's clock, see :meth:`_clock_after`).
        self._span_met_s: dict[int, float] = {}
        #: Per output: the motion holds until then (a settled readback disagreed lately, see
        #: READBACK_DOUBT_INTERVALS), unless the readbacks were believed first.
        self._doubt_until_s: dict[int, float] = {}
        #: The last output found set by another sender, for status: output, PWM shown, PWM
        #: acknowledged before, when it was seen (None: none since the start).
        self.foreign_command: dict[str, float] | None = None
        #: When the last SYSTEM_TIME that continued the autopilot's clock arrived (see
        #: :meth:`_disagrees`: a readback is believed only with the autopilot heard after it).
        self._clock_heard_s = -math.inf
        #: A readback started to disagree: ask for a SYSTEM_TIME (see :meth:`take_clock_probe`).
        self._probe_wanted = False
        self._probe_sent_s = -math.inf

    # -- frames -----------------------------------------------------------------------------

    def on_readback(self, shown: dict[int, int], received_s: float) -> None:
        """A SERVO_OUTPUT_RAW showing ``shown`` (output → PWM), arrived at ``received_s``."""
        self.shown = shown
        # When it arrived (the control thread may take it later): the readback's silence
        # is the link's, not this thread's.
        self.shown_s = received_s
        self._check_readback()

    def _check_readback(self) -> None:  # noqa: B027
        """What the readback just shown says of the outputs (default: nothing)."""

    def settle_s(self) -> float:
        """How long after an ACK a readback surely shows it: READBACK_SETTLE_S, or one and a
        half of the readback's intervals on a slower stream."""
        return max(READBACK_SETTLE_S, 1.5 * self._core.settings.readback_interval_s)

    def _expected_pwms(self, output: int, now: float) -> tuple[set[int], bool]:
        """The PWMs a readback at ``now`` may show for ``output`` if it does what it
        acknowledged: the last one acknowledged at least :meth:`settle_s` ago and any
        acknowledged since (the readback lags by up to that); and whether that older one
        exists (settled: a readback showing none of them then disagrees; before, it may just
        lag)."""
        history = self._ack_history.get(output)
        if not history:
            return set(), False
        # A readback shows the output's PWMs in order: once one showed an ACK, the ACKs before
        # it are behind the output (one showing them again is another sender's).
        shown_s = self._shown_ack_s.get(output, -math.inf)
        cutoff = now - self.settle_s() + 1e-9
        recent = {pwm for t, pwm in history if t >= max(cutoff, shown_s)}
        older = [pwm for t, pwm in history if shown_s <= t < cutoff]
        return recent | set(older[-1:]), bool(older) or shown_s > -math.inf

    def _shown_ack(self, output: int, shown: int) -> None:
        """A readback showed ``shown``, one of ``output``'s ACKs the readback may still show:
        the oldest of those with that PWM is where the output is now (see
        :meth:`_expected_pwms`)."""
        history = self._ack_history.get(output) or ()
        shown_s = self._shown_ack_s.get(output, -math.inf)
        for t, pwm in history:
            if t >= shown_s and abs(pwm - shown) <= READBACK_TOLERANCE_US:
                self._shown_ack_s[output] = t
                self._shown_before_ack.pop(output, None)
                return
        # Not acknowledged yet: a step on its way, shown before its ACK. Without this, its ACK
        # would leave the readback free to show the PWM before it again, and a ground station
        # setting that PWM just then went unseen (the next step moved the joint from it).
        for flight in self._core.state.flights:
            on_its_way = flight.pwm_by_output.get(output)
            if on_its_way is not None and abs(on_its_way - shown) <= READBACK_TOLERANCE_US:
                self._shown_before_ack[output] = shown
                return

    def _forget_shown_acks(self, output: int | None = None) -> None:
        """Which ACKs the readback showed, for ``output`` (None: every output)."""
        if output is None:
            self._shown_ack_s.clear()
            self._shown_before_ack.clear()
        else:
            self._shown_ack_s.pop(output, None)
            self._shown_before_ack.pop(output, None)

    def clock_heard(self, at_s: float) -> None:
        """A SYSTEM_TIME that continues the autopilot's clock arrived at ``at_s``."""
        self._clock_heard_s = at_s
        if self.shown_s > -math.inf and any(met_s < at_s for met_s in self._span_met_s.values()):
            # Readbacks waited for this (their span met): judged again now, not a readback
            # later. (The frame already counted counts again; a belief still needs frames
            # spanning READBACK_SPAN_INTERVALS, so that believes nothing sooner than it should.)
            self._check_readback()

    def take_clock_probe(self, now: float) -> bool:
        """Whether to ask the autopilot for a SYSTEM_TIME now (a readback started to disagree,
        ArduPilot's SYS_STATUS said "off" after "on"; at most once in CLOCK_PROBE_INTERVALS
        readback intervals): its answer, a round trip later, says it is there and did not
        reboot, rather than the stream's next frame up to its interval later. Asked once:
        True clears it."""
        if not self._probe_wanted:
            return False
        interval_s = CLOCK_PROBE_INTERVALS * self._core.settings.readback_interval_s
        if now - self._probe_sent_s < interval_s:
            return False
        self._probe_wanted = False
        self._probe_sent_s = now
        return True

    def _disagrees(self, output: int, at_s: float, *, clock_after: bool = False) -> bool:
        """Another settled readback not showing what ``output`` acknowledged, arrived at
        ``at_s``: whether the readbacks now disagree with it for long enough to be believed
        (READBACK_MISMATCHES showing the same PWM over READBACK_SPAN_INTERVALS of the stream,
        none showing another between).
        ``clock_after``: and a SYSTEM_TIME continuing the autopilot's clock came after they
        did (:meth:`_clock_after`)."""
        # The same PWM in a row: frames forged with another PWM between the autopilot's own
        # (a dead output's) start the count again, and a PWM is believed only where every
        # frame of the span showed it, the autopilot's own among them.
        shown = self.shown.get(output, 0)
        seen = self._mismatches.get(output)
        if seen is None or abs(seen[0] - shown) > READBACK_TOLERANCE_US:
            seen = (shown, at_s, 0)
            self._span_met_s.pop(output, None)
        pwm, since_s, count = seen
        count += 1
        self._mismatches[output] = (pwm, since_s, count)
        interval_s = self._core.settings.readback_interval_s
        if clock_after and self.CLOCK_INTO_RUN and count == 2:
            self._probe_wanted = True  # answered before the span is met: no wait then
        believed = count >= READBACK_MISMATCHES and at_s - since_s >= (
            READBACK_SPAN_INTERVALS * interval_s
        )
        if believed and clock_after:
            if self.CLOCK_INTO_RUN and self._clock_heard_s >= since_s + interval_s:
                believed = True
            else:
                believed = self._clock_after(output, at_s)
        if believed:
            self._doubt_until_s.pop(output, None)
        else:
            self._doubt_until_s[output] = at_s + READBACK_DOUBT_INTERVALS * interval_s
        return believed

    def _shown_steadily(self, output: int, shown: int) -> bool:
        """``output``, with nothing of ours acknowledged, shows ``shown``: whether readbacks
        showed it (within the tolerance) READBACK_MISMATCHES times in a row over more than
        READBACK_SPAN_INTERVALS of the stream, and the autopilot's clock went on after (as
        :meth:`_disagrees`: a forged frame alone is never believed). Until then the motion
        holds (:meth:`_hold_for`)."""
        at_s = self.shown_s
        seen = self._steady_seen.get(output)
        if seen is None or abs(seen[0] - shown) > READBACK_TOLERANCE_US:
            self._steady_seen[output] = (shown, at_s, 1)
            self._span_met_s.pop(output, None)
            self._hold_for(output, at_s)
            return False
        pwm, since_s, count = seen
        self._steady_seen[output] = (pwm, since_s, count + 1)
        interval_s = self._core.settings.readback_interval_s
        believed = (
            count + 1 >= READBACK_MISMATCHES
            and at_s - since_s >= READBACK_SPAN_INTERVALS * interval_s
            and self._clock_after(output, at_s)
        )
        if believed:
            self._doubt_until_s.pop(output, None)
            self._span_met_s.pop(output, None)
        else:
            self._hold_for(output, at_s)
        return believed

    def _judging(self, now: float) -> bool:
        """Readbacks are being judged by :meth:`_shown_steadily` (an output with nothing of
        ours acknowledged shows a PWM not believed yet): the motion waits, unless the last
        run of them began READBACK_WAIT_S ago (a stream that stopped must not stop the arm for
        good; one whose frames keep changing, a forger's among them, holds it)."""
        return any(now - since_s < READBACK_WAIT_S for _, since_s, _ in self._steady_seen.values())

    def _forget_steady(self, output: int) -> None:
        """``output``'s readbacks are no longer to be judged by :meth:`_shown_steadily`."""
        if self._steady_seen.pop(output, None) is not None:
            self._span_met_s.pop(output, None)

    def _hold_for(self, output: int, at_s: float) -> None:
        """A readback arrived at ``at_s`` shows ``output`` somewhere not believed yet: the
        motion holds until the next readbacks say, and the autopilot is asked whether it is
        there (its clock)."""
        interval_s = self._core.settings.readback_interval_s
        self._doubt_until_s[output] = at_s + READBACK_DOUBT_INTERVALS * interval_s

    def _clock_after(self, output: int, at_s: float) -> bool:
        """The readbacks of ``output`` disagree long enough (the span is complete at ``at_s``
        or was earlier): whether a SYSTEM_TIME continuing the autopilot's clock has come
        since (if not, one is asked for). Then the autopilot did not reboot during the span:
        its own readbacks flowed, fell inside it, and disagreed too. While it reboots, silent,
        forged frames are all the readbacks there are, and none of its own contradicts them."""
        met_s = self._span_met_s.setdefault(output, at_s)
        if self._clock_heard_s > met_s:
            return True
        self._probe_wanted = True
        return False

    def in_doubt(self, now: float) -> bool:
        """A settled readback disagreed with what an output acknowledged, and the readbacks
        have not said yet whether to believe it (the motion holds meanwhile)."""
        return any(now < until_s for until_s in self._doubt_until_s.values())

    def _agrees(self, output: int) -> None:
        """A readback showed what ``output`` acknowledged (or a step on its way)."""
        self._mismatches.pop(output, None)
        self._span_met_s.pop(output, None)

    def _readback_seen(self, now: float) -> bool:
        """A readback since :attr:`_readback_since_s` tells where the joints are; without one
        for READBACK_WAIT_S, go on from the pose assumed (and say so once)."""
        if self.shown_s >= self._readback_since_s:
            return True
        if now - self._readback_since_s < READBACK_WAIT_S:
            return False
        if not self._readback_warned:
            self._readback_warned = True
            log.warning(
                "no SERVO_OUTPUT_RAW from the autopilot in %.0f s: moving from the pose last "
                "acknowledged (or the park pose); outputs may jump to it",
                READBACK_WAIT_S,
            )
        return True

    def _start_at(self, i: int, angle: float) -> None:
        """Joint ``i`` is at ``angle`` (its output shows it: at the start, or set by another
        sender), and a pose still to re-send (``pose_file``, a loss) keeps it there."""
        state = self._core.state
        state.position[i] = angle
        state.placed_by_readback = True
        if state.restored is not None:
            state.restored[0][i] = state.restored[1][i] = angle
        if state.unconfirmed is not None:
            unconfirmed = list(state.unconfirmed)
            unconfirmed[i] = angle
            state.unconfirmed = tuple(unconfirmed)

    def in_range(self, output: int, pwm_us: int) -> bool:
        """Whether ``pwm_us`` lies in ``output``'s servo range (a disarmed PWM may not)."""
        joint = self._core.config.calibration.for_output(output)
        return joint.pwm_min_us <= pwm_us <= joint.pwm_max_us

    def angle_shown(self, output: int, pwm_us: int) -> float:
        """The joint angle an output's PWM means, within the calibration and the arm's limits."""
        config = self._core.config
        joint = config.calibration.for_output(output)
        pwm = min(max(pwm_us, joint.pwm_min_us), joint.pwm_max_us)
        angle = joint.pwm_us_to_angle_deg(pwm)
        limits = config.arm.joints[self._core.state.outputs.index(output)]
        return min(max(angle, math.degrees(limits.min_rad)), math.degrees(limits.max_rad))

    @abc.abstractmethod
    def on_sys_status(self, actions: list[Action], safety_on: bool, at_s: float) -> None:
        """A SYS_STATUS saying where the safety switch is, arrived at ``at_s``."""

    def on_param(  # noqa: B027
        self, actions: list[Action], name: str, value: float, at_s: float
    ) -> None:
        """A PARAM_VALUE from the pinned autopilot, arrived at ``at_s`` (default: none is
        read)."""

    def params_to_read(self) -> list[str]:
        """Parameters to read whenever the streams are asked for (default: none)."""
        return []

    def streams_asked(self, now: float) -> None:  # noqa: B027
        """Every stream was just asked for."""

    def rebooted(self) -> None:  # noqa: B027
        """The autopilot rebooted (before :meth:`lost`)."""

    # -- losses -----------------------------------------------------------------------------

    @abc.abstractmethod
    def lost(self, flights: Sequence[Flight]) -> None:
        """The link was lost or the autopilot rebooted; ``flights`` (no longer tracked) were on
        their way. Forget what the outputs were known to do, and set the pose to re-send."""

    @abc.abstractmethod
    def went_quiet(self, flights: Sequence[Flight], now: float) -> None:
        """SYSTEM_TIME stopped (a possible reboot); ``flights`` are still on their way."""

    # -- the motion's questions --------------------------------------------------------------

    def take_hold(self) -> bool:
        """Whether the outputs must be told to hold the acknowledged pose now, before anything
        else (asked once: True clears it)."""
        return False

    @property
    def hold_wanted(self) -> bool:
        """:meth:`take_hold` would say True."""
        return False

    @abc.abstractmethod
    def may_move(self, actions: list[Action], now: float) -> bool:
        """Whether the next update may go out (nothing in flight); may send one itself."""

    def may_confirm(self, now: float) -> bool:
        """Whether a command of an update left unknown may be confirmed alone now (default:
        yes)."""
        return True

    def unanswered(self, now: float) -> None:  # noqa: B027
        """Not one ACK came for an update: the autopilot may have gone silent (default:
        nothing to do)."""

    def may_pipeline(self) -> bool:
        """Whether a step may go out behind the update in flight (outputs known live)."""
        return True

    def may_step_to(self, step: tuple[float, ...]) -> bool:
        """Whether a motion step to ``step`` may go out now."""
        return True

    def may_hold(self) -> list[tuple[float, ...]]:
        """Poses the outputs may hold beside the acknowledged one and the steps on their way
        (the ends of a band; default: none)."""
        return []

    def stepped_to(self, step: tuple[float, ...]) -> None:  # noqa: B027
        """An update to ``step`` went out."""

    def acknowledged(self, output: int, pwm: int, now: float) -> None:
        """``output`` acknowledged ``pwm`` at ``now``. The readbacks may lag behind it, so a
        run of them disagreeing starts again, unless the PWM they show is none that output
        ever acknowledged (the disarmed PWM of outputs that died under a step): a lag never
        shows that, and the run goes on (restarting it would keep a dead output's marker a
        readback interval longer from going out)."""
        history = self._ack_history.setdefault(output, collections.deque(maxlen=64))
        history.append((now, pwm))
        early = self._shown_before_ack.get(output)
        if early is not None and abs(early - pwm) <= READBACK_TOLERANCE_US:
            del self._shown_before_ack[output]
            self._shown_ack_s[output] = now
        run = self._mismatches.get(output)
        if run is not None and all(
            abs(run[0] - acked) > READBACK_TOLERANCE_US for _, acked in history
        ):
            return
        self._agrees(output)

    def all_acknowledged(self) -> None:  # noqa: B027
        """Every output holds what it acknowledged."""

    def overtaken(self, seq: int) -> set[int]:
        """Outputs whose ACKs in the update numbered ``seq`` say nothing of their pose (a
        hold was stored behind it)."""
        return set()

    @abc.abstractmethod
    def dead(self) -> dict[int, str]:
        """The arm's outputs that are not live now, with the reason."""

    @abc.abstractmethod
    def unknown(self, now: float) -> dict[int, str]:
        """For status, the arm's outputs not known to be live, with the reason."""

    def readback_stream_silent(self, now: float, intervals: float) -> bool:
        """Whether the readback stream (once seen) has been silent for READBACK_SILENT_S, and
        at least ``intervals`` of its intervals, since it was last heard or the streams were
        last asked for (said in the log once a silence)."""
        if self.shown_s == -math.inf:
            return False
        silent_s = max(READBACK_SILENT_S, intervals * self._core.settings.readback_interval_s)
        if now - max(self.shown_s, self._core.watch.streams_asked_s) < silent_s:
            return False
        silent_for_s = now - self.shown_s
        # Said once a silence (a stream that never comes back is asked for every 0.5 s).
        say = log.info if silent_for_s < 2 * silent_s else log.debug
        say("no SERVO_OUTPUT_RAW for %.2f s: asking for every stream again", silent_for_s)
        return True

    def readback_silence(self, now: float, intervals: float) -> str | None:
        """Why status cannot say the outputs are live: the readback stream, once heard, silent
        for more than ``intervals`` of its intervals (an autopilot that reboots sends nothing;
        frames forged as its own may still say its outputs are live). None: it is not."""
        silent_s = now - self.shown_s
        if (
            self.shown_s > -math.inf
            and silent_s > intervals * self._core.settings.readback_interval_s
        ):
            return f"not known live (no SERVO_OUTPUT_RAW for {silent_s * 1e3:.0f} ms)"
        return None

    @abc.abstractmethod
    def streams_silent(self, now: float) -> bool:
        """Whether the stream this firmware's truth comes from fell silent long enough to ask
        for every stream again (logged)."""

    @abc.abstractmethod
    def refusal_advice(self, refused: dict[int, str]) -> tuple[str, str]:
        """What to do about refused outputs: (a hint for the log and reply, a short line)."""
