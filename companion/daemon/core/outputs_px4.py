"""PX4's outputs' truth: its readback (SERVO_OUTPUT_RAW) says whether each output is live.

PX4 shows the PWM it outputs (the disarmed PWM until armed or prearmed), so an output that does
not show what it acknowledged, READBACK_MISMATCHES times in a row once settled, is not live:
the joint is where the readback says, and the motion holds. One found dead holds a marker
(``MARKER_OFFSET_US`` from its disarmed PWM), so coming alive moves it 2 µs and shows at the
next readback. Coming alive never moves a joint faster than the speed limit: while the outputs
are not known to be live, one speed-limited step at a time, each once the readback's verdict
on the one before is in.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from typing import TYPE_CHECKING

from companion.daemon.core.outputs import (
    READBACK_TOLERANCE_US,
    OutputsTruth,
)

if TYPE_CHECKING:
    from companion.daemon.core.actions import Action
    from companion.daemon.core.dispatcher import ControlCore
    from companion.daemon.core.state import Flight

log = logging.getLogger("armbridge")

#: An output found not live (showing its disarmed PWM) is told to hold a PWM this far from it,
#: towards the middle of its range: the "marker". It moves the joint by that much when the
#: output comes alive (arm, prearm), which the next readback then shows: live again is seen
#: within one readback, where a readback of the disarmed PWM itself could not tell storage
#: from output. The same at the start and after a reboot or a loss, with the arm still: the
#: PWM the output shows, plus the offset, tells whether it is live.
MARKER_OFFSET_US = 2
#: Where no marker fits (a range too narrow for it), one speed-limited step towards the goal at
#: this interval shows whether the outputs came alive instead.
PROBE_INTERVAL_S = 1.0
#: Outputs not yet known to be live: the next step waits for the readback's verdict on the one
#: before (shown: live; not shown READBACK_MISMATCHES times: not live), at most this long (a
#: readback stream that stopped must not stop the arm for good).
VERDICT_TIMEOUT_S = 2.0
assert MARKER_OFFSET_US > READBACK_TOLERANCE_US  # a marker shown is told from the disarmed PWM
#: For status: a readback stream silent this many intervals says nothing of the outputs any
#: more (a reboot: they are at the disarmed PWM; seen 44 ms after it at 50 Hz, against 66 with
#: 3 intervals, in bench.output_cycles; one lost frame makes a 40 ms gap, not more); silent
#: READBACK_SILENT_S (at least this many intervals), every stream is asked for again (a
#: rebooted PX4 forgot them).
READBACK_STALE_INTERVALS = 2


def marker_pwm_candidates(shown_us: int, middle_us: float, nearest_us: int) -> list[int]:
    """The PWMs to try, in order, as the marker of an output showing ``shown_us``:
    MARKER_OFFSET_US towards ``middle_us``, then away from it, then ``nearest_us``."""
    towards = 1 if shown_us <= middle_us else -1
    return [
        shown_us + towards * MARKER_OFFSET_US,
        shown_us - towards * MARKER_OFFSET_US,
        nearest_us,
    ]


class Px4Outputs(OutputsTruth):
    """PX4: the readback says which outputs are live (see the module docstring)."""

    CLOCK_INTO_RUN = True

    def __init__(self, core: ControlCore) -> None:
        super().__init__(core)
        #: Outputs whose readback does not show what they acknowledged → the reason, and the
        #: PWM they showed then (the disarmed PWM): a readback of that PWM proves nothing.
        self._not_live: dict[int, str] = {}
        self._dead_pwm: dict[int, int] = {}
        #: ... how many updates had been sent when each was found not live (those sent before
        #: it store no pose of its: its hold goes out behind them), and the PWM it is told to
        #: hold meanwhile (its marker, ``MARKER_OFFSET_US`` from the disarmed PWM; or, with no
        #: room for one, the PWM nearest it: then probes, ``PROBE_INTERVAL_S``).
        self._dead_seq: dict[int, int] = {}
        self._held_pwm: dict[int, int] = {}
        #: Outputs whose latest settled readback showed what they acknowledged (live).
        self._confirmed: set[int] = set()
        #: Store the pose the outputs show now (an output was found not live).
        self._store_hold_now = False
        #: Outputs with nothing of ours acknowledged since the start, a loss or a reboot: the
        #: PWM the readbacks show steadily (see :meth:`_judge_start`).
        self._start_shown: dict[int, int] = {}

    # -- frames -----------------------------------------------------------------------------

    def on_sys_status(self, actions: list[Action], safety_on: bool, at_s: float) -> None:
        self.safety_on = safety_on  # shown, not relied on

    def _check_readback(self) -> None:
        """PX4 shows the PWM it outputs: an output that does not show what it acknowledged,
        READBACK_MISMATCHES times in a row once settled, is not live (the joint is where the
        readback says; the motion holds)."""
        core, state = self._core, self._core.state
        now = core.clock()
        outputs = state.outputs
        joint_of = {o: i for i, o in enumerate(outputs)}
        for output in outputs:
            shown = self.shown.get(output)
            acked = state.acked_pwm.get(output)
            if shown is None:
                continue
            if acked is None:
                if (
                    not state.flights
                    and output not in self._ack_history
                    and output not in self._not_live
                ):
                    self._judge_start(joint_of[output], output, shown)
                continue
            shown_ok, settled = self._expected_pwms(output, now)
            # PX4 applies a command on its output cycle and answers it on its commander's: a
            # readback in between shows a step on its way, not acknowledged yet. It is ours,
            # so the output is live.
            on_its_way = {
                f.pwm_by_output[output] for f in state.flights if output in f.pwm_by_output
            }
            if any(abs(shown - pwm) <= READBACK_TOLERANCE_US for pwm in shown_ok | on_its_way):
                self._agrees(output)
                self._shown_ack(output, shown)
                dead_pwm = self._dead_pwm.get(output)
                if dead_pwm is not None and abs(shown - dead_pwm) <= READBACK_TOLERANCE_US:
                    continue  # the hold at the disarmed PWM: shown either way, proves nothing
                self._confirmed.add(output)
                self._dead_pwm.pop(output, None)
                self._dead_seq.pop(output, None)
                self._held_pwm.pop(output, None)
                if self._not_live.pop(output, None) is not None:
                    log.info("output %d live again (shows %d us)", output, shown)
                continue
            if not settled:
                continue  # acknowledged too lately to be shown yet
            # An output that stops showing what it acknowledged was disarmed, killed or
            # rebooted, once the readbacks say so for long enough to be believed (a forged
            # readback alone never moves a live output to a marker).
            dead_pwm = self._dead_pwm.get(output)
            if (
                output in self._not_live
                and acked == self._held_pwm.get(output)
                and dead_pwm is not None
                and abs(shown - dead_pwm) <= READBACK_TOLERANCE_US
            ):
                self._agrees(output)
                continue  # still dead, told to hold its marker (or the last PWM known)
            # Live showing another PWM, or dead showing one other than it did (another
            # sender's value stored meanwhile, brought out at arming; a new disarmed PWM): once
            # believed, the joint is there, and its marker is taken from there. Believed with
            # the autopilot's clock heard going on after the readbacks: while PX4 reboots,
            # silent, forged frames are the only readbacks there are.
            if not self._disagrees(output, self.shown_s, clock_after=True):
                continue
            self._confirmed.discard(output)
            reason = (
                f"output {output} shows {shown} us, not the {acked} us acknowledged "
                "(disarmed, the outputs not armed, or set by another sender)"
            )
            log.warning("%s: holding the arm where it is", reason)
            self._not_live[output] = reason
            self._dead_pwm[output] = shown
            self._dead_seq[output] = state.updates_sent
            # The joint is where the output puts it. Its marker is stored at once (PX4 would
            # apply what we stored in one step when the outputs come alive): it moves the
            # joint by MARKER_OFFSET_US then, and the readback shows it. Where the output shows
            # a PWM outside the servo's range, the joint is where it was: the middle of what
            # it may hold is held.
            i = joint_of[output]
            if self.in_range(output, shown):
                state.position[i] = self._marker_deg(output, shown)
            else:
                state.position[i] = self._last_live_middle_deg(output, state.position[i])
            self._held_pwm[output] = core.config.calibration.for_output(output).angle_to_pwm_us(
                state.position[i]
            )
            state.acked_pwm.pop(output, None)
            self._ack_history.pop(output, None)
            self._forget_shown_acks(output)
            self._agrees(output)
            self._store_hold_now = True

    def _judge_start(self, i: int, output: int, shown: int) -> None:
        """Nothing of ours acknowledged since the start, a loss or a reboot (nor on its way):
        the joint is where the readbacks show, once they show one PWM steadily
        (:meth:`_shown_steadily`: a forged frame alone never places it, nor its marker).
        (A PWM outside the servo's range, such as PX4 SITL's disarmed 900 us, says nothing
        of where it is.) A frame showing another PWM takes that back until the readbacks
        settle again."""
        start = self._start_shown.get(output)
        if start is not None and abs(start - shown) <= READBACK_TOLERANCE_US:
            return
        self._start_shown.pop(output, None)
        if not self._shown_steadily(output, shown):
            return
        self._forget_steady(output)
        self._start_shown[output] = shown
        if self.in_range(output, shown):
            self._start_at(i, self.angle_shown(output, shown))

    # -- losses -----------------------------------------------------------------------------

    def _forget_liveness(self, now: float) -> None:
        """A loss or a (possible) reboot: what was stored is gone (a rebooted PX4 holds
        nothing), so whether each output is live is unknown again until its marker, sent
        anew, shows or does not (status: not known live)."""
        self._ack_history.clear()
        self._forget_shown_acks()
        self._confirmed.clear()
        self._not_live.clear()
        self._dead_pwm.clear()
        self._dead_seq.clear()
        self._held_pwm.clear()
        self._start_shown.clear()
        self._steady_seen.clear()
        self._store_hold_now = False
        self.safety_on = None
        self._readback_since_s = now

    def lost(self, flights: Sequence[Flight]) -> None:
        self._mismatches.clear()
        self._doubt_until_s.clear()
        self._forget_liveness(self._core.clock())
        # PX4 applies what it stores in one step once its outputs are live: re-sending the
        # pose of before would jump from wherever the outputs are now (the disarmed PWM after
        # a reboot). The joints are where the next readback says; the motion goes on from
        # there at the speed limit.
        self._core.state.unconfirmed = None

    def went_quiet(self, flights: Sequence[Flight], now: float) -> None:
        # Never re-send a stale pose (see lost): the readback says where the joints are.
        self._forget_liveness(now)

    # -- the motion's questions --------------------------------------------------------------

    def take_hold(self) -> bool:
        # Outputs found not live: their markers stored now, behind whatever is on its way (PX4
        # takes the frames in order), before a re-arm would bring out the pose stored before.
        hold, self._store_hold_now = self._store_hold_now, False
        return hold

    @property
    def hold_wanted(self) -> bool:
        return self._store_hold_now

    def may_move(self, actions: list[Action], now: float) -> bool:
        if not self._readback_seen(now) or self._unsteady() or self._disarmed_out_of_range():
            return False
        state = self._core.state
        if self._confirmed.issuperset(state.outputs):
            return True
        # Outputs not known to be live: one speed-limited step at a time, the next only once
        # the readback showed it (found not live: once it shows its marker, or with no marker,
        # once a PROBE_INTERVAL_S): if they come alive meanwhile, they jump by at most that one
        # step.
        if self._not_live:
            return not (self._markers_held() or now - state.last_step_s < PROBE_INTERVAL_S)
        if self._unmarked_unknown() or self._armed_out_of_range():
            # The start, a loss or a reboot: the markers say whether the outputs are live,
            # moving each joint by MARKER_OFFSET_US; the motion waits for that. (A motion step
            # could leave an output at the disarmed PWM it shows, and a readback of that would
            # prove nothing.) (hold: 2 us from what the outputs show, no keep-out path to
            # check; a disarmed PWM inside a volume would refuse it at every tick.)
            self._core.updates.send_step(actions, self._marker_pose(), now, hold=True)
            return False
        if (
            any(o in state.acked_pwm for o in state.outputs if o not in self._confirmed)
            and now - state.last_step_s < VERDICT_TIMEOUT_S
        ):
            return False  # the readback's verdict on the step before is not in yet
        return True

    def in_doubt(self, now: float) -> bool:
        # Readbacks that disagreed long enough wait for the autopilot's clock (asked for at
        # once) before they are believed: the motion holds until then too, past the doubt's
        # own intervals (a step sent meanwhile would be stored into outputs that may be dead,
        # and come out in one move with the next).
        return super().in_doubt(now) or any(
            met_s >= self._clock_heard_s for met_s in self._span_met_s.values()
        )

    def may_pipeline(self) -> bool:
        return not self._store_hold_now and self._confirmed.issuperset(self._core.state.outputs)

    def overtaken(self, seq: int) -> set[int]:
        # Outputs found not live since that update went out hold their markers, stored behind
        # it: what it stored there is no pose of theirs (nor of the joints').
        return {
            o for o, dead_seq in self._dead_seq.items() if seq < dead_seq and o in self._not_live
        }

    def dead(self) -> dict[int, str]:
        dead = dict(self._not_live)
        for output in self._disarmed_out_of_range():
            # Live (prearmed) or not, PX4 shows its disarmed PWM while nothing is stored: which
            # is unknown.
            dead[output] = (
                f"not known live (output {output} shows {self.shown[output]} us, outside its "
                "range, and nothing of ours is stored since the start: the arm moves once "
                "armed, from where the outputs then show)"
            )
        return dead

    def _unplaced(self) -> list[int]:
        """Outputs with nothing of ours acknowledged since the start, a loss or a reboot, nor
        on its way, that readbacks show (not found dead), in order."""
        state = self._core.state
        ahead = {o for f in state.flights for o in f.sent_outputs}
        return [
            o
            for o in state.outputs
            if o in self.shown
            and o not in self._ack_history
            and o not in ahead
            and o not in self._not_live
        ]

    def _unsteady(self) -> list[int]:
        """Outputs not placed yet (:meth:`_unplaced`) whose readbacks have not shown one PWM
        steadily (:meth:`_judge_start`: forged frames between the autopilot's own, or a
        change): the motion waits (nothing is sent before where the joint is is known)."""
        return [o for o in self._unplaced() if o not in self._start_shown]

    def _disarmed_out_of_range(self) -> list[int]:
        """Outputs not placed yet (:meth:`_unplaced`) whose readbacks steadily show a PWM
        outside their servo's range (PX4 SITL's disarmed 900 us), while the vehicle is not
        armed: where the joint is is unknown, and PX4 shows what it stores (an earlier
        daemon's pose) once armed. Nothing is sent meanwhile: a step stored now would come out
        in one move at arming, from wherever the joint is."""
        if self._core.watch.armed:
            return []
        return [
            o
            for o in self._unplaced()
            if (start := self._start_shown.get(o)) is not None and not self.in_range(o, start)
        ]

    def unknown(self, now: float) -> dict[int, str]:
        """While the readback is silent for READBACK_STALE_INTERVALS; each output until a
        readback showed what it stored since the start, a loss or a reboot (its marker, or a
        step); and one whose readback disagrees until the next say whether to believe it."""
        outputs = self._core.state.outputs
        if self.shown_s == -math.inf:
            return dict.fromkeys(outputs, "not known live (no SERVO_OUTPUT_RAW yet)")
        silence = self.readback_silence(now, READBACK_STALE_INTERVALS)
        if silence is not None:
            return dict.fromkeys(outputs, silence)
        why = (
            "not known live yet (no readback has shown what it stores since the start, "
            "a loss or a reboot)"
        )
        unknown = {o: why for o in outputs if o not in self._confirmed}
        for output in self._unsteady():
            unknown[output] = (
                f"not known live yet (output {output} shows {self.shown[output]} us; the "
                "readbacks have not shown one PWM steadily yet)"
            )
        # A readback shows another PWM than acknowledged: not known live until the next ones
        # say whether to believe it (the motion holds meanwhile; the outputs may be dead).
        for output, until_s in self._doubt_until_s.items():
            if now < until_s:
                unknown.setdefault(
                    output,
                    f"not known live (output {output} shows {self.shown.get(output)} us, not "
                    "what it acknowledged)",
                )
        return unknown

    def streams_silent(self, now: float) -> bool:
        """A readback stream (once seen) silent for READBACK_SILENT_S: a rebooted PX4 forgot
        the streams."""
        return self.readback_stream_silent(now, READBACK_STALE_INTERVALS)

    def refusal_advice(self, refused: dict[int, str]) -> tuple[str, str]:
        first = min(refused)
        more = f"+{len(refused) - 1}" if len(refused) > 1 else ""
        return "", f"Arm: output {first}{more} refused by the autopilot"

    # -- helpers ----------------------------------------------------------------------------

    def _unmarked_unknown(self) -> bool:
        """An output with nothing acknowledged since the start, a loss or a reboot, and none on
        its way (its liveness unknown: a marker would tell), its readbacks steadily showing a
        PWM in its servo's range. One showing a PWM outside it gets no marker: nothing is sent
        before a target unless it is where the outputs show, and that PWM says nothing of where
        the joint is."""
        state = self._core.state
        ahead = {o for f in state.flights for o in f.sent_outputs}
        return any(
            o not in state.acked_pwm
            and o not in ahead
            and (start := self._start_shown.get(o)) is not None
            and self.in_range(o, start)
            for o in state.outputs
        )

    def _armed_out_of_range(self) -> bool:
        """Armed, with a target, an output with nothing of ours stored since the start, a loss
        or a reboot shows a PWM outside its servo's range: its joint is where its last pulse
        left it, known to within the poses held (the middle of a band: see
        :meth:`_last_live_middle_deg`, ``pose_file``). Its first update is that pose alone,
        within half the band of the joint (:meth:`_marker_pose` keeps it where it is held),
        and the motion's steps go from there once a readback showed it; a step sent at once
        would go up to half the band past the limit."""
        core = self._core
        return (
            core.watch.armed is True
            and core.motion.goal is not None
            and any(
                (start := self._start_shown.get(o)) is not None and not self.in_range(o, start)
                for o in self._unplaced()
            )
        )

    def _marker_pose(self) -> tuple[float, ...]:
        """The pose with each output that has nothing acknowledged at its marker (from the PWM
        the readbacks steadily show), the others where they are."""
        state = self._core.state
        pose = list(state.position)
        for i, output in enumerate(state.outputs):
            start = self._start_shown.get(output)
            if output not in state.acked_pwm and start is not None and self.in_range(output, start):
                pose[i] = self._marker_deg(output, start)
        return tuple(pose)

    def _last_live_middle_deg(self, output: int, position_deg: float) -> float:
        """Where the joint of an output just found dead, showing a PWM outside its servo's
        range (which says nothing of where it is), may be: at the PWM a readback last showed
        it hold live, or at any acknowledged since (a step applied just before the outputs
        died; the motion holds from the first readback that disagreed, so those are the steps
        sent before it: one at most when the readback is faster than the control rate). The
        middle of those angles, half their spread from each: a joint held there, or stepped
        from there once armed, moves by no more than that, whichever it holds."""
        shown_s = self._shown_ack_s.get(output, -math.inf)
        angles = [
            self.angle_shown(output, pwm)
            for t, pwm in self._ack_history.get(output, ())
            if t >= shown_s
        ]
        if not angles:
            return position_deg
        return (min(angles) + max(angles)) / 2

    def _markers_held(self) -> bool:
        """Every output not live holds a PWM the readback tells from the one it shows (a
        marker): the next readback shows when they come alive, no probe needed."""
        return all(
            abs(self._held_pwm[o] - self._dead_pwm[o]) > READBACK_TOLERANCE_US
            for o in self._not_live
        )

    def _marker_deg(self, output: int, shown_us: int) -> float:
        """The angle an output showing ``shown_us`` (not live, or not known to be) is told to
        hold: its marker (``MARKER_OFFSET_US`` from it, towards the middle of the range: the
        readback tells it from ``shown_us``) or, with no room for one, the angle nearest
        ``shown_us``. ``shown_us`` lies in the servo's range (outside it, the joint holds the
        last PWM known instead)."""
        config = self._core.config
        joint = config.calibration.for_output(output)
        limits = config.arm.joints[self._core.state.outputs.index(output)]
        low_deg = max(joint.angle_min_deg, math.degrees(limits.min_rad))
        high_deg = min(joint.angle_max_deg, math.degrees(limits.max_rad))
        nearest = self.angle_shown(output, shown_us)
        candidates = marker_pwm_candidates(
            shown_us, (joint.pwm_min_us + joint.pwm_max_us) / 2, joint.angle_to_pwm_us(nearest)
        )
        for pwm in candidates:
            if abs(pwm - shown_us) <= READBACK_TOLERANCE_US:
                continue
            if not joint.pwm_min_us <= pwm <= joint.pwm_max_us:
                continue
            angle = joint.pwm_us_to_angle_deg(pwm)
            if low_deg <= angle <= high_deg and joint.angle_to_pwm_us(angle) == pwm:
                return angle
        return nearest
