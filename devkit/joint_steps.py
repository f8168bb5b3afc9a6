"""Joint steps faster than the speed limit, from what the servos physically received.

Pure functions over the simulator's event log (``start``, ``output`` and ``servo`` events, see
:mod:`sim_servo.eventlog`), used by ``bench/output_cycles.py`` and ``bench/state_cycles.py`` and
tested on hand-made timelines.

**A fast step.** Per output, each change of the physical pulse is a step of the joint from the
angle of the last pulse before it to the angle of the new one (angles through the joint's
calibration). It is *fast* when

    |Δangle| > joint_speed_deg_s / rate_hz + quantum_deg

i.e. more than one control tick's step (the most the daemon ever sends at once: its step is
``joint_speed_deg_s × min(1 / rate_hz, time since its previous step)``) plus one PWM quantum
(the joint's degrees per µs: a step is rounded to whole µs). ``Δt`` (the time since the output's
previous physical change) does not widen the allowance: a servo held for seconds and then given
a new pulse moves there at its own slew rate, so a jump after a long hold (the disarmed PWM to a
stored value when PX4 arms; a stored value when ArduPilot's safety switch is released) is as
fast as one after a tick. The looser reading, allowance ``joint_speed_deg_s × max(Δt, 1 /
rate_hz)`` (a jump spread over the time since the previous change), is also given per step
(``loose``), for comparison.

**No pulses** (PWM 0: an ArduPilot output held by its safety switch, any output during a
reboot): the servo holds where it was, so a change to 0 is no step, and the next pulse is
compared with the last pulse before the gap. **Changes at the same instant** (two commands
carried out in one pass of the autopilot, e.g. PX4's commander cycle): only the last went out,
the ones before it lasted no time at all and are no step. **A pulse outside the servo's
calibrated range** (:func:`undriven_outside`: PX4 SITL's disarmed 900 µs) counts as no pulses.
The first pulse an output ever gets has nothing to compare with (ArduPilot outputs start
without pulses, the servo wherever it was left): it is returned apart, never counted as fast.

**Whose step** (:func:`step_kind`). The daemon's: its own commands, and the outputs coming alive
(arm, prearm, the safety switch released, a mask or a boot) with a value the daemon stored. A
foreign sender's: a command from another link than the companion's (the simulator tags it with
``src``), or coming alive with a value such a command stored (the last ``servo`` event of the
output before the step was tagged). The autopilot's own: PX4 driving an output to its disarmed
PWM (disarm, kill, prearm off, reboot). **A race** (counted apart from both): the daemon's
command from a PWM a foreign command set less than ``race_window_s`` before (until a readback
first showed the foreign PWM, and a hop): no readback could have shown the daemon that command
yet, so its step was computed from the PWM before it; later ones are the daemon's (a readback
showing a foreign PWM holds the motion until it is believed, and the joint is then taken where
it shows). **A reboot race**
(also apart): the autopilot rebooted within ``belief_window_s`` of the foreign command, before
its readbacks could be believed (two over more than an interval, and the autopilot's clock
heard after them): after the reboot the outputs carry no pulses, and what the daemon re-sends
was computed without the foreign PWM, which it cannot tell from frames forged while an
autopilot reboots. **A dead-time race** (apart too): PX4's outputs went to the disarmed PWM
and came alive again within ``dead_window_s`` (a kill, then an arm at once), before the
readbacks could show them dead and the daemon store a marker there; they came back to within
a step of the pulse they had before, as PX4 brings out what it stored (a daemon holding still
would see the same jump). **A marker race** (apart too, :func:`marker_race`): the daemon's
command that reached PX4 while its outputs were dead, or before a readback could show the
daemon they had come alive again (the first such readback, and a hop), and that its commander
carried out after they came alive: sent for dead outputs (the marker next to the disarmed
PWM, which brings outputs that stay dead alive within a step), it moved live ones.

**A limit that changes** (:class:`SpeedLimits`). A reload changes ``joint_speed_deg_s`` at an
instant known only within a window (the signal sent … the daemon said it applied it): a step in
the window is judged against the higher of the two limits (either may be in force) and, apart,
against the lower; elsewhere against the limit in force. A value stored earlier coming out, and
the first pulse after no pulses, are judged by the limit when it was stored (when the pulses
stopped) too: they move the joint by at most a step of the motion that was interrupted.
"""

from __future__ import annotations

import bisect
import dataclasses
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

#: The kinds of :func:`step_kind`: the daemon's, a foreign sender's, the autopilot's own.
DAEMON_COMMAND = "daemon: command"
DAEMON_ALIVE = "daemon: coming alive"
FOREIGN_COMMAND = "foreign: command"
FOREIGN_ALIVE = "foreign: coming alive"
AUTOPILOT = "foreign: autopilot to its disarmed PWM"
RACE = "race: the daemon's command before a readback could show a foreign one"
RACE_REBOOT = "race: a reboot before the readbacks could confirm a foreign command"
RACE_DEAD = "race: the outputs alive again before a readback could show them dead"
MARKER_RACE = "race: the outputs alive again before the daemon's command for them dead took effect"
DAEMON_KINDS = (DAEMON_COMMAND, DAEMON_ALIVE)
FOREIGN_KINDS = (FOREIGN_COMMAND, FOREIGN_ALIVE, AUTOPILOT)
#: Causes of an output change that bring stored values out (the outputs coming alive).
ALIVE_CAUSES = frozenset({"arm", "prearm", "param", "mask", "safety_off", "boot"})


@dataclass(frozen=True)
class Change:
    """One change of an output's physical pulse (``pwm_us`` 0: no pulses), and why."""

    t_s: float
    pwm_us: int
    cause: str
    #: A command's sender when it came from another link than the companion's (``src``).
    source: tuple[int, int] | None = None


@dataclass(frozen=True)
class JointStep:
    """A physical step of one joint (see the module docstring)."""

    output: int
    t_s: float
    from_us: int
    to_us: int
    step_deg: float  # |Δangle|
    dt_s: float  # since the output's previous physical change (a change to 0 included)
    allowed_deg: float  # joint_speed_deg_s / rate_hz + quantum_deg
    cause: str  # the simulator's cause of the change: command, arm, prearm, safety_off ...
    source: tuple[int, int] | None = None  # a foreign command's sender
    #: |Δangle| from the pulse before ``from_us`` (None: none): a step coming alive after a
    #: short dead time, compared with where the joint was before it (:data:`RACE_DEAD`).
    back_deg: float | None = None
    #: The first pulse after no pulses (a safety switch, a reboot): when the pulses stopped
    #: (None: no gap before this step), see :func:`judge`.
    gap_from_s: float | None = None
    #: The pulse before ``from_us`` (None: none), and the cause of the change to ``from_us``.
    before_us: int | None = None
    from_cause: str | None = None

    @property
    def fast(self) -> bool:
        return self.step_deg > self.allowed_deg

    def loose(self, joint_speed_deg_s: float, rate_hz: float, quantum_deg: float) -> bool:
        """Fast even against ``joint_speed_deg_s × max(Δt, 1 / rate_hz) + quantum_deg``."""
        return self.step_deg > joint_speed_deg_s * max(self.dt_s, 1.0 / rate_hz) + quantum_deg


def undriven_outside(changes: Sequence[Change], low_us: int, high_us: int) -> list[Change]:
    """``changes`` with every pulse outside ``[low_us, high_us]`` (the servo's calibrated
    range) taken as no pulses (0): such a PWM (PX4 SITL's disarmed 900 µs below 1000–2000)
    says nothing of where the joint is, so it is compared as a gap: the next pulse in the range
    with the last one before it."""
    out: list[Change] = []
    for change in changes:
        pwm = change.pwm_us if low_us <= change.pwm_us <= high_us else 0
        if out and out[-1].pwm_us == pwm:
            continue  # 900 → 0 after 0: no change at all
        out.append(dataclasses.replace(change, pwm_us=pwm))
    return out


def output_changes(events: Iterable[Mapping[str, Any]]) -> dict[int, list[Change]]:
    """Each output's physical pulse over time from the log: the ``start`` event's
    ``outputs_us`` (cause ``start``), then each ``output`` event. Raises ``ValueError`` when an
    ``output`` event does not follow on from the one before (a log that lost lines)."""
    changes: dict[int, list[Change]] = {}
    for event in events:
        if event["event"] == "start" and "outputs_us" in event:
            for output, pwm in event["outputs_us"].items():
                changes[int(output)] = [Change(float(event["t_s"]), int(pwm), "start")]
        elif event["event"] == "output":
            output = int(event["output"])
            history = changes.setdefault(output, [])
            if history and history[-1].pwm_us != event["from_us"]:
                raise ValueError(
                    f"output {output}: event at t_s={event['t_s']} goes from "
                    f"{event['from_us']} µs but the log had it at {history[-1].pwm_us} µs"
                )
            source = tuple(event["src"]) if event.get("src") else None
            history.append(
                Change(
                    float(event["t_s"]),
                    int(event["pwm_us"]),
                    str(event["cause"]),
                    (int(source[0]), int(source[1])) if source else None,
                )
            )
    return changes


def joint_steps(
    output: int,
    changes: Iterable[Change],
    to_angle_deg: Callable[[int], float],
    *,
    joint_speed_deg_s: float,
    rate_hz: float,
    quantum_deg: float,
) -> tuple[list[JointStep], list[Change]]:
    """``output``'s physical steps (every change to a pulse, compared with the last pulse before
    it) and its first pulses (nothing to compare with). ``to_angle_deg`` maps a PWM (µs, > 0)
    to the joint's angle."""
    if not (joint_speed_deg_s > 0 and rate_hz > 0 and quantum_deg >= 0):
        raise ValueError(
            f"joint_speed_deg_s={joint_speed_deg_s!r} and rate_hz={rate_hz!r} must be > 0, "
            f"quantum_deg={quantum_deg!r} >= 0"
        )
    allowed_deg = joint_speed_deg_s / rate_hz + quantum_deg
    steps: list[JointStep] = []
    first: list[Change] = []
    pulse: int | None = None  # the last pulse (> 0): where the servo holds
    pulse_cause: str | None = None  # the cause of the change to it
    before: int | None = None  # the pulse before it
    previous_s: float | None = None
    stopped_s: float | None = None  # when the pulses stopped (None: they go on)
    ordered = list(changes)
    for k, change in enumerate(ordered):
        if k + 1 < len(ordered) and ordered[k + 1].t_s == change.t_s:
            continue  # another change at the same instant: this one never went out
        dt_s = change.t_s - previous_s if previous_s is not None else float("inf")
        previous_s = change.t_s
        if change.pwm_us == 0:
            if stopped_s is None:
                stopped_s = change.t_s
            continue  # no pulses: the servo holds
        gap_from_s, stopped_s = stopped_s, None
        if pulse is None:
            first.append(change)
        elif change.pwm_us != pulse:
            steps.append(
                JointStep(
                    output=output,
                    t_s=change.t_s,
                    from_us=pulse,
                    to_us=change.pwm_us,
                    step_deg=abs(to_angle_deg(change.pwm_us) - to_angle_deg(pulse)),
                    dt_s=dt_s,
                    allowed_deg=allowed_deg,
                    cause=change.cause,
                    source=change.source,
                    back_deg=None
                    if before is None
                    else abs(to_angle_deg(change.pwm_us) - to_angle_deg(before)),
                    gap_from_s=gap_from_s,
                    before_us=before,
                    from_cause=pulse_cause,
                )
            )
        if change.pwm_us != pulse:
            before = pulse
            pulse_cause = change.cause
        pulse = change.pwm_us
    return steps, first


def stored_by_foreign(events: Iterable[Mapping[str, Any]]) -> dict[int, list[tuple[float, bool]]]:
    """Per output, each command that gave it a new PWM (``servo`` events) in log order:
    ``(t_s, whether a foreign sender gave it)``. A command that gives the PWM it already had
    is left out: the value is still the earlier sender's (the daemon re-sending what a ground
    station stored does not make it the daemon's)."""
    stored: dict[int, list[tuple[float, bool]]] = {}
    last_pwm: dict[int, int] = {}
    for event in events:
        if event["event"] == "servo":
            output, pwm = int(event["output"]), int(event["pwm_us"])
            if last_pwm.get(output) == pwm:
                continue
            last_pwm[output] = pwm
            stored.setdefault(output, []).append((float(event["t_s"]), bool(event.get("src"))))
    return stored


def commands_received(events: Iterable[Mapping[str, Any]]) -> dict[int, dict[float, float]]:
    """Per output, for each ``servo`` event that says when its command arrived (PX4's
    commander acts on it later: ``received_t_s``), its time to that arrival."""
    received: dict[int, dict[float, float]] = {}
    for event in events:
        if event["event"] == "servo" and event.get("received_t_s") is not None:
            by_t = received.setdefault(int(event["output"]), {})
            by_t[float(event["t_s"])] = float(event["received_t_s"])
    return received


def marker_race(
    step: JointStep,
    *,
    disarmed_us: int | None,
    received_s: float | None,
    shown: Sequence[tuple[float, int]],
    hop_s: float,
) -> bool:
    """Whether ``step``, the daemon's command right after its output came alive from PX4's
    disarmed PWM (``disarmed_us``), reached PX4 (``received_s``) before a readback could show
    the daemon that it had: the first at or after it came alive to show ``step.from_us``
    (``shown``, from :func:`readbacks_shown`), and ``hop_s`` (:data:`MARKER_RACE`)."""
    if (
        disarmed_us is None
        or received_s is None
        or step.cause != "command"
        or step.source is not None
        or step.before_us != disarmed_us
        or step.from_cause not in ALIVE_CAUSES
    ):
        return False
    shown_s = first_shown_after(shown, step.from_us, step.t_s - step.dt_s)
    return shown_s is None or received_s < shown_s + hop_s


def readbacks_shown(events: Iterable[Mapping[str, Any]]) -> dict[int, list[tuple[float, int]]]:
    """Per output, when a streamed readback first showed each new PWM (the simulator's
    ``readback`` events), in log order: ``(t_s, pwm_us)``."""
    shown: dict[int, list[tuple[float, int]]] = {}
    for event in events:
        if event["event"] == "readback":
            for output, pwm in event["pwm_us"].items():
                shown.setdefault(int(output), []).append((float(event["t_s"]), int(pwm)))
    return shown


def first_shown_after(shown: Sequence[tuple[float, int]], pwm_us: int, t_s: float) -> float | None:
    """When a readback first showed ``pwm_us`` at or after ``t_s`` (from :func:`readbacks_shown`;
    None: none did)."""
    k = bisect.bisect_left([t for t, _ in shown], t_s)
    return next((t for t, pwm in shown[k:] if pwm == pwm_us), None)


def foreign_stored_at(stored: Sequence[tuple[float, bool]], t_s: float) -> bool:
    """Whether the last command at or before ``t_s`` (from :func:`stored_by_foreign`) was a
    foreign sender's."""
    k = bisect.bisect_right([t for t, _ in stored], t_s)
    return k > 0 and stored[k - 1][1]


def stored_before(stored: Sequence[tuple[float, bool]], t_s: float) -> float | None:
    """When the last command at or before ``t_s`` (from :func:`stored_by_foreign`) was given
    (None: none)."""
    k = bisect.bisect_right([t for t, _ in stored], t_s)
    return stored[k - 1][0] if k > 0 else None


def foreign_command_before(stored: Sequence[tuple[float, bool]], t_s: float) -> float | None:
    """How long before ``t_s`` the last command strictly before it was given, if a foreign
    sender gave it (from :func:`stored_by_foreign`; None: the daemon's, or none)."""
    k = bisect.bisect_left([t for t, _ in stored], t_s)
    if k == 0 or not stored[k - 1][1]:
        return None
    return t_s - stored[k - 1][0]


def step_kind(
    step: JointStep,
    *,
    disarmed_us: int | None,
    stored_foreign: bool,
    foreign_before_s: float | None = None,
    race_window_s: float = 0.0,
    reboot_cut_short: bool = False,
    dead_window_s: float = 0.0,
    back_allowed_deg: float | None = None,
    marker_raced: bool = False,
) -> str:
    """Whose step ``step`` is (module docstring): one of :data:`DAEMON_KINDS`,
    :data:`FOREIGN_KINDS` or a race (:data:`RACE`, :data:`RACE_REBOOT`, :data:`RACE_DEAD`,
    :data:`MARKER_RACE`). ``disarmed_us``: PX4's
    disarmed PWM (None on ArduPilot); ``stored_foreign``: the output's stored value came from
    a foreign command; ``foreign_before_s``: the command before this one was a foreign
    sender's, this long before
    (:func:`foreign_command_before`); ``race_window_s``: a daemon command less than this after
    it is a race (the time until a readback first showed the foreign PWM, and a hop);
    ``reboot_cut_short``: the autopilot rebooted so soon after
    that foreign command that its readbacks could not be believed before the outputs lost their
    pulses (the daemon then cannot tell it from frames forged while the autopilot reboots:
    :data:`RACE_REBOOT`); ``dead_window_s``: outputs back from PX4's disarmed PWM this soon
    after going there, to within a step of where they were before, were dead for less than
    the readbacks need to show it (:data:`RACE_DEAD`); "a step" is ``back_allowed_deg`` (the
    limit in force, e.g. after a reload; default ``step.allowed_deg``); ``marker_raced``: the
    daemon's command took effect on outputs alive again before it could know
    (:func:`marker_race`, :data:`MARKER_RACE`)."""
    if step.cause == "command":
        if step.source is not None:
            return FOREIGN_COMMAND
        if foreign_before_s is not None and foreign_before_s <= race_window_s:
            return RACE
        if foreign_before_s is not None and reboot_cut_short:
            return RACE_REBOOT
        if marker_raced:
            return MARKER_RACE
        return DAEMON_COMMAND
    if disarmed_us is not None and step.to_us == disarmed_us:
        return AUTOPILOT
    if step.cause in ALIVE_CAUSES:
        if stored_foreign:
            return FOREIGN_ALIVE
        if (
            disarmed_us is not None
            and step.from_us == disarmed_us
            and step.dt_s <= dead_window_s
            and step.back_deg is not None
            and step.back_deg
            <= (step.allowed_deg if back_allowed_deg is None else back_allowed_deg)
        ):
            return RACE_DEAD
        return DAEMON_ALIVE
    return AUTOPILOT


@dataclass(frozen=True)
class Reload:
    """A change of ``joint_speed_deg_s`` from ``old`` to ``new``, applied at some instant in
    ``[start_s, end_s]``."""

    start_s: float
    end_s: float
    old: float
    new: float


@dataclass
class SpeedLimits:
    """The joint speed limit over time: ``base`` until the first reload, each reload's ``new``
    after its window (reloads in time order; windows may overlap: reloads sent in quick
    succession)."""

    base: float
    reloads: list[Reload] = field(default_factory=list)

    def at(self, t_s: float) -> tuple[float, float]:
        """(lower, higher) limit that may be in force at ``t_s``: equal outside a window; in
        one or more, any of their old and new limits."""
        speed = self.base
        may_be: set[float] = set()
        for reload in self.reloads:
            if t_s < reload.start_s:
                break
            if t_s <= reload.end_s:
                may_be |= {reload.old, reload.new}
            speed = reload.new
        if not may_be:
            return speed, speed
        return min(may_be), max(may_be)


def judge(
    step: JointStep,
    limits: SpeedLimits,
    *,
    rate_hz: float,
    quantum_deg: float,
    stored_s: float | None = None,
) -> tuple[bool, bool]:
    """(fast against the limit that may be in force — the higher in a reload window —, fast
    against the lower one): ``|Δangle| > speed / rate_hz + quantum_deg``. A step that brings
    out a stored value (outputs coming alive: ``stored_s``, when it was stored) is judged by
    the limit in force then too, the higher of the two: a safety switch that held a joint
    mid-motion releases it by up to a step of the motion it interrupted, whatever limit a
    reload set while it was held. So is the first pulse after no pulses (``step.gap_from_s``):
    where the servo stopped is known only to within the poses the daemon sent before it
    stopped (a switch gone on unseen, forged SYS_STATUS, a reboot: the daemon re-sends the
    middle of that band), at most a step of the motion it interrupted from the truth."""
    lower, higher = limits.at(step.t_s)
    if stored_s is not None and step.cause != "command":
        higher = max(higher, limits.at(stored_s)[1])
    if step.gap_from_s is not None:
        higher = max(higher, limits.at(step.gap_from_s)[1])
    return (
        step.step_deg > higher / rate_hz + quantum_deg,
        step.step_deg > lower / rate_hz + quantum_deg,
    )
