"""Random arm/disarm/prearm/kill/reboot and safety-switch cycles against moving targets.

    python -m bench.output_cycles [--cycles 1000] [--flavour px4|ardupilot|both] [--seed 0]
                                  [--min-dwell-s 0.03] [--max-dwell-s 1.0]
                                  [--markdown bench/results/output_cycles.md] [--keep-logs DIR]

The daemon and the simulated flight controller run as subprocesses on UDP loopback (see
``bench/loopback.py``), shipped daemon defaults (``control.rate_hz`` 20, ``arm.joint_speed_deg_s``
60) and a vehicle set up for the arm (``--ready``: PX4 armed, ``COM_PREARM_MODE`` 2; the
disarmed PWM ``PWM_MAIN_DISn`` left at its default, 1000 µs; ArduPilot's safety switch off at
boot, the arm's outputs in ``BRD_SAFETY_MASK`` at start). Each cycle, seeded:

* with probability 0.6 an **event**: PX4 ``arm``, ``disarm``, ``kill`` (query socket),
  ``prearm_on`` / ``prearm_off`` (``COM_PREARM_MODE`` 2 / 0 by PARAM_SET from the ground
  station's link: the simulator applies it at once, prearmed from 5 s after boot), ``reboot``;
  ArduPilot ``safety_on`` / ``safety_off`` (query socket), ``reboot``, and
  ``mask_arm`` / ``mask_none`` (``BRD_SAFETY_MASK`` with or without the arm's outputs by
  PARAM_SET, the switch on or off: its output driver takes a new mask at its next 10 Hz tick,
  as ArduPilot's does). Reboots are drawn half as often as the others;
* with probability 0.7 a **target**: a random reachable pose (forward kinematics of joints drawn
  within 90 % of their limits), ``goto`` on the control socket, not waited for;
* a **dwell** drawn log-uniformly in [min, max] (default 0.03–1 s), during which the daemon's
  ``status`` and the simulator's ``state`` are polled every 20 ms.

**Joint steps faster than the limit** come from the simulator's event log alone (what each servo
physically received: :func:`devkit.joint_steps.output_changes`), through the daemon's
calibration (PWM → angle), by :func:`devkit.joint_steps.joint_steps`: a physical change of
more than ``joint_speed_deg_s / rate_hz`` (one control tick's step, 3° by default) plus one PWM
quantum, whatever the time since the output's previous change (a jump after a hold is a jump);
pulses stopping (0) are no step, and the next pulse is compared with the last one before. They
are split by the simulator's cause of the change: *the autopilot to its disarmed PWM* (PX4
disarm, kill, prearm off, reboot: PX4 itself drives the outputs to ``PWM_MAIN_DISn``; ``doctor``
asks for the park PWM there), *coming alive* (arm, prearm, safety off, boot: the stored values
appear at once) and *commands* (the daemon's own updates). The last two are the daemon's
responsibility (the target: 0), except PX4's outputs coming alive ``DEAD_WINDOW_S`` or less
after going dead, back to within a step of where they were (a kill, then an arm at once): dead
too briefly for the readbacks to show it, counted apart as a race; and a daemon command PX4's
commander carried out on outputs alive again from the disarmed PWM, that reached it less than
``MARKER_HOP_S`` after the first readback showing them alive (the marker sent for outputs the
readbacks showed dead): counted apart as a race too, with its largest step. The count under
the looser reading (allowance ``joint_speed_deg_s × max(Δt, 1 / rate_hz)``, Δt since the
output's previous change) is given too.

**Status "outputs live" against the simulator's truth.** After each event, the time from the
event (the query answered, or the PARAM_SET sent) until a poll finds the daemon's
``outputs_live`` equal to the simulator's (every arm output ``live`` in its ``state``). An event
followed by the next one before they agree is *censored* at its dwell: counted as over the bound
when the dwell already exceeded it, and apart otherwise. The bound is one readback period
(``READBACK_FAST_INTERVAL_S``, 0.02 s, on PX4, whose outputs' truth is the readback;
``READBACK_INTERVAL_S``, 0.1 s, on ArduPilot, whose is SYS_STATUS every 25 ms) plus a margin of
50 ms (the 20 ms poll, the stream's phase and the loopback hops). On PX4 a dead output is seen
at the first readback after the event, a live one at the first that shows its marker
(``MARKER_OFFSET_US``); at the start, after a reboot or a loss, a readback settled
``READBACK_SETTLE_S`` (0.15 s) after the marker's ACK, twice, tells that it is not live. Of the
events over the bound, those where a poll past the bound found the status saying live while the
outputs were not are counted apart ("said live while not"): a false claim, where "not known
live" while they are live (readbacks that contradict each other, a restart) is caution.
"""

from __future__ import annotations

import argparse
import math
import shutil
import struct
import time
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from bench.loopback import ControlSocketInput, Stack, load_average
from bench.report import machine, md_table, write_markdown
from companion.daemon.core import READBACK_FAST_INTERVAL_S, READBACK_INTERVAL_S
from companion.kinematics.arm import Arm, Pose
from devkit.joint_steps import (
    ALIVE_CAUSES,
    JointStep,
    commands_received,
    joint_steps,
    marker_race,
    output_changes,
    readbacks_shown,
)
from firmware_interface.calibration import JointCalibration, default_calibration
from sim_servo.config import PX4_DISARMED_PWM_US
from sim_servo.gcs import GroundStation

ROOT = Path(__file__).resolve().parent.parent
#: The daemon's readback period per flavour on a fast link (SERVO_OUTPUT_RAW: PX4's outputs'
#: truth; ArduPilot's comes from SYS_STATUS, every 25 ms, and the readback every 100 ms), and
#: the margin allowed on top of it for the status to agree with the simulator.
READBACK_PERIOD_S = {"px4": READBACK_FAST_INTERVAL_S, "ardupilot": READBACK_INTERVAL_S}
MARGIN_S = 0.05
#: PX4's outputs dead for less than this are not seen by the readbacks (the first showing them
#: dead, the third to believe it, a hop): see :func:`category`.
DEAD_WINDOW_S = 3 * READBACK_FAST_INTERVAL_S + 0.01
#: A daemon command PX4's commander carried out on outputs alive again from the disarmed PWM,
#: that reached it less than this after the first readback showing them alive: the readback's
#: way to the daemon and the command's way back (``devkit.joint_steps.MARKER_RACE``).
MARKER_HOP_S = 0.01
POLL_S = 0.02
EVENT_P = 0.6
TARGET_P = 0.7
#: Daemon settings (the shipped defaults, written out: the step bound depends on them).
RATE_HZ = 20.0
JOINT_SPEED_DEG_S = 60.0
ARM_OUTPUTS = (9, 10, 11, 12, 13, 14)
#: Events and their weights per flavour.
EVENTS = {
    "px4": {"arm": 2, "disarm": 2, "kill": 2, "prearm_on": 2, "prearm_off": 2, "reboot": 1},
    "ardupilot": {"safety_on": 2, "safety_off": 2, "mask_arm": 1, "mask_none": 1, "reboot": 1},
}
#: BRD_SAFETY_MASK with the arm's outputs (9–14: bits 8–13).
ARM_MASK = sum(1 << (o - 1) for o in ARM_OUTPUTS)


@dataclass
class Agreement:
    """One event's wait for the daemon's status to agree with the simulator."""

    event: str
    t_s: float
    truth_before: bool | None
    latency_s: float | None = None  # None: not agreed before the next event (censored)
    dwell_s: float = 0.0
    truth_changed: bool = False
    #: A poll later than the bound found the status saying live while the outputs were not
    #: (the other way round, "not known live" while live, is caution, not a false claim).
    said_live_late: bool = False

    def poll(self, polled_s: float, truth: bool, said: bool, bound_s: float) -> bool:
        """A poll at ``polled_s`` found the simulator's ``truth`` and the daemon's ``said``:
        whether they agree, the first time (the wait is over)."""
        self.dwell_s = polled_s - self.t_s
        self.truth_changed |= truth != self.truth_before
        if said and not truth and self.dwell_s > bound_s:
            self.said_live_late = True
        if truth == said and self.latency_s is None:
            self.latency_s = self.dwell_s
            return True
        return False


@dataclass
class Run:
    flavour: str
    cycles: int
    events: Counter = field(default_factory=Counter)
    outcomes: Counter = field(default_factory=Counter)
    agreements: list[Agreement] = field(default_factory=list)
    steps: list[JointStep] = field(default_factory=list)
    #: (output, t_s) of the steps that are marker races (see :func:`category`).
    marker_raced: set[tuple[int, float]] = field(default_factory=set)
    first_pulses: int = 0
    #: (monotonic s, event) of every event, and the simulator's t_s 0 on CLOCK_MONOTONIC.
    timeline: list[tuple[float, str]] = field(default_factory=list)
    sim_t0: float = 0.0
    disagree_s: float = 0.0
    polled_s: float = 0.0
    wall_s: float = 0.0
    load_before: str = ""


def joint_angle(joint: JointCalibration, pwm_us: int) -> float:
    """The calibration's linear map, extended beyond the servo's range (a disarmed PWM may lie
    outside it): the angle the joint physically goes to."""
    fraction = (pwm_us - joint.trim_us - joint.pwm_min_us) / (joint.pwm_max_us - joint.pwm_min_us)
    if joint.reversed:
        fraction = 1.0 - fraction
    return joint.angle_min_deg + fraction * (joint.angle_max_deg - joint.angle_min_deg)


def quantum_deg(joint: JointCalibration) -> float:
    return (joint.angle_max_deg - joint.angle_min_deg) / (joint.pwm_max_us - joint.pwm_min_us)


def category(step: JointStep, run: Run) -> str:
    """Whose step it is: ``command`` (the daemon's update), ``alive`` (stored values coming out),
    ``disarmed`` (PX4 driving its outputs to the disarmed PWM), ``dead_race`` (PX4's outputs
    alive again within ``DEAD_WINDOW_S`` of going dead, back to within a step of where they were:
    dead too briefly for the readbacks to show it, see ``devkit.joint_steps.RACE_DEAD``),
    ``marker_race`` (the daemon's command for outputs the readbacks showed dead, carried out
    after they came alive, before a readback could show it: ``devkit.joint_steps.MARKER_RACE``)."""
    flavour = run.flavour
    if step.cause == "command":
        if (step.output, step.t_s) in run.marker_raced:
            return "marker_race"
        return "command"
    if flavour == "px4" and step.to_us == PX4_DISARMED_PWM_US and step.cause not in ("arm",):
        return "disarmed"
    if step.cause not in ALIVE_CAUSES:
        return "disarmed"
    if (
        flavour == "px4"
        and step.from_us == PX4_DISARMED_PWM_US
        and step.dt_s <= DEAD_WINDOW_S
        and step.back_deg is not None
        and step.back_deg <= step.allowed_deg
    ):
        return "dead_race"
    return "alive"


def random_poses(arm: Arm, rng: np.random.Generator, count: int) -> list[Pose]:
    """Reachable poses: forward kinematics of joints drawn within 90 % of their limits."""
    low = np.array([j.min_rad for j in arm.joints])
    high = np.array([j.max_rad for j in arm.joints])
    mid, half = (low + high) / 2, (high - low) / 2 * 0.9
    q_rad = rng.uniform(mid - half, mid + half, size=(count, len(arm.joints)))
    return [Pose.from_matrix(t) for t in arm.fk_batch(q_rad)]


def param_value(flavour: str, value: int) -> float:
    """PARAM_SET's float for an integer parameter: PX4 sends INT32 bytewise."""
    if flavour == "px4":
        return float(struct.unpack("<f", struct.pack("<i", value))[0])
    return float(value)


def _param_id(raw: Any) -> str:
    text = raw.decode("ascii", "replace") if isinstance(raw, bytes | bytearray) else str(raw)
    return text.rstrip("\0")


def set_param(gcs: GroundStation, flavour: str, name: str, value: int) -> None:
    """PARAM_SET from the ground station; returns once a PARAM_VALUE says it is set (sent
    again every 0.5 s: a rebooting autopilot is deaf). Only one with the value set will do:
    the autopilot sends PARAM_VALUE on every link, so the daemon's own read of the parameter
    may have left an answer with the old value waiting here."""
    msg = gcs.mav.param_set_encode(
        1, 1, name.encode(), param_value(flavour, value), mavlink.MAV_PARAM_TYPE_INT32
    )
    for _ in range(10):
        gcs.send(msg)
        answer = gcs.wait_for(
            lambda m: (
                m.get_type() == "PARAM_VALUE"
                and _param_id(m.param_id) == name
                and m.param_value == msg.param_value
            ),
            0.5,
        )
        if answer is not None:
            return
    raise TimeoutError(f"no PARAM_VALUE for {name} within 5 s")


def sim_live(state: dict[str, Any]) -> bool:
    """The simulator's truth: every arm output live (pulses that follow its commands)."""
    return all(state["outputs"][str(o)]["live"] for o in ARM_OUTPUTS)


def run_flavour(flavour: str, args: argparse.Namespace) -> Run:
    rng = np.random.default_rng([args.seed, 0 if flavour == "px4" else 1])
    arm = Arm.default()
    poses = random_poses(arm, rng, args.cycles)
    names = list(EVENTS[flavour])
    weights = np.array([EVENTS[flavour][n] for n in names], dtype=float)
    weights /= weights.sum()
    daemon = {
        "solver": {"seed": args.seed},
        "control": {"rate_hz": RATE_HZ},
        "arm": {"joint_speed_deg_s": JOINT_SPEED_DEG_S},
    }
    out = Run(flavour, args.cycles, load_before=load_average())
    # ArduPilot starts with the arm's outputs in BRD_SAFETY_MASK (what doctor asks for), so the
    # daemon reads that at start; mask_none then takes them out.
    sim_args = () if flavour == "px4" else ("--param", f"BRD_SAFETY_MASK={ARM_MASK}")
    with Stack(dialect=flavour, daemon=daemon, sim_args=sim_args) as stack:
        assert stack.sim is not None
        sim = stack.sim
        source = ControlSocketInput(stack)
        gcs = GroundStation(stack.gcs_url)

        def act(event: str) -> None:
            if event in ("arm", "disarm"):
                sim.arm(event == "arm")
            elif event == "kill":
                sim.kill_switch()
            elif event in ("safety_on", "safety_off"):
                sim.safety(event == "safety_on")
            elif event in ("prearm_on", "prearm_off"):
                set_param(gcs, flavour, "COM_PREARM_MODE", 2 if event == "prearm_on" else 0)
            elif event in ("mask_arm", "mask_none"):
                set_param(gcs, flavour, "BRD_SAFETY_MASK", ARM_MASK if event == "mask_arm" else 0)
            elif event == "reboot":
                sim.reboot()
            else:
                raise ValueError(f"event={event!r}; valid: {names}")

        pending: Agreement | None = None
        sent = 0
        t_start = time.monotonic()
        for k in range(args.cycles):
            if rng.random() < EVENT_P:
                event = str(rng.choice(names, p=weights))
                if pending is not None:
                    out.agreements.append(pending)  # censored: the next event came first
                state = sim.state()
                before = sim_live(state)
                out.timeline.append((time.monotonic(), event))  # before it acts
                act(event)
                pending = Agreement(event, time.monotonic(), before)
                out.events[event] += 1
            if rng.random() < TARGET_P:
                source.send(poses[k].as_tuple())
                sent += 1
            dwell_s = math.exp(rng.uniform(math.log(args.min_dwell_s), math.log(args.max_dwell_s)))
            end_s = time.monotonic() + dwell_s
            last_poll_s: float | None = None
            last_agree = True
            while (now := time.monotonic()) < end_s:
                for answer in source.poll(min(POLL_S, end_s - now)):
                    out.outcomes[answer["outcome"]] += 1
                if time.monotonic() - (last_poll_s or 0.0) < POLL_S:
                    continue
                truth = sim_live(sim.state())
                said = bool(stack.status()["outputs_live"])
                polled = time.monotonic()
                if last_poll_s is not None:
                    out.polled_s += polled - last_poll_s
                    if not last_agree:
                        out.disagree_s += polled - last_poll_s
                last_poll_s, last_agree = polled, truth == said
                if pending is not None and pending.poll(polled, truth, said, bound_s(flavour)):
                    out.agreements.append(pending)
                    pending = None
        if pending is not None:
            out.agreements.append(pending)
        out.wall_s = time.monotonic() - t_start
        # The last answers (a goto waits for its first step at most a few seconds).
        deadline = time.monotonic() + 10.0
        while sum(out.outcomes.values()) < sent and time.monotonic() < deadline:
            for answer in source.poll(0.1):
                out.outcomes[answer["outcome"]] += 1
        out.outcomes["unanswered"] = sent - sum(out.outcomes.values())
        source.close()
        gcs.close()
        events = stack.stop()
        if args.keep_logs is not None:
            args.keep_logs.mkdir(parents=True, exist_ok=True)
            for path, name in ((stack.daemon_log, "daemon"), (stack.event_log, "sim")):
                if path.exists():
                    shutil.copy(path, args.keep_logs / f"{flavour}-{name}{path.suffix}")
    out.sim_t0 = next(e["monotonic_s"] for e in events if e["event"] == "start")
    calibration = default_calibration(ARM_OUTPUTS)
    changes = output_changes(events)
    readbacks = readbacks_shown(events)
    received = commands_received(events)
    for output in ARM_OUTPUTS:
        joint = calibration.for_output(output)
        steps, first = joint_steps(
            output,
            changes.get(output, []),
            lambda pwm, joint=joint: joint_angle(joint, pwm),
            joint_speed_deg_s=JOINT_SPEED_DEG_S,
            rate_hz=RATE_HZ,
            quantum_deg=quantum_deg(joint),
        )
        out.steps += steps
        out.marker_raced |= {
            (output, step.t_s)
            for step in steps
            if marker_race(
                step,
                disarmed_us=PX4_DISARMED_PWM_US if flavour == "px4" else None,
                received_s=received.get(output, {}).get(step.t_s),
                shown=readbacks.get(output, []),
                hop_s=MARKER_HOP_S,
            )
        }
        out.first_pulses += len(first)
    return out


def events_before(run: Run, step: JointStep, *, detail: bool = False) -> str:
    """The last two events before ``step`` (with how long before it, in detail)."""
    t = run.sim_t0 + step.t_s
    before = [(t_e, e) for t_e, e in run.timeline if t_e <= t][-2:]
    if not detail:
        return " then ".join(e for _, e in before) or "none"
    return " then ".join(f"{e} ({t - t_e:.2f} s before)" for t_e, e in before) or "no event"


def event_gap(run: Run, step: JointStep) -> float:
    """The time between the last two events before ``step`` (inf with fewer than two)."""
    t = run.sim_t0 + step.t_s
    before = [t_e for t_e, _ in run.timeline if t_e <= t][-2:]
    return before[1] - before[0] if len(before) == 2 else math.inf


def _ms(values: list[float], q: float) -> float:
    return float(np.percentile(np.array(values) * 1e3, q)) if values else math.nan


def bound_s(flavour: str) -> float:
    return READBACK_PERIOD_S[flavour] + MARGIN_S


def over_bound_lines(
    agreements: Sequence[Agreement],
    timeline: Sequence[tuple[float, str]],
    sim_t0: float,
    bound: float,
    *,
    false_claims_only: bool = False,
) -> list[str]:
    """A line for each event whose status took longer than ``bound`` to agree (or, with
    ``false_claims_only``, said live while the outputs were not past it)."""
    lines = []
    events = [e for _, e in timeline]
    times = [t for t, _ in timeline]
    for a in agreements:
        took = a.latency_s if a.latency_s is not None else a.dwell_s
        if took <= bound or (false_claims_only and not a.said_live_late):
            continue
        k = max(i for i, t in enumerate(times) if t <= a.t_s)
        before = f"{events[k - 1]} {a.t_s - times[k - 1]:.2f} s before" if k else "none"
        lines.append(
            f"- {a.event} at {a.t_s - sim_t0:.3f} s (sim clock): "
            + (
                f"agreed after {took * 1e3:.0f} ms"
                if a.latency_s is not None
                else f"not agreed in its {took * 1e3:.0f} ms dwell"
            )
            + f"; truth before {'live' if a.truth_before else 'not live'}"
            + f"{', changed' if a.truth_changed else ''}"
            + ("; said live while not" if a.said_live_late else "")
            + f"; event before: {before}"
        )
    return lines


def report(runs: list[Run], args: argparse.Namespace) -> list[str]:
    lines = [
        f"# Output cycles ({args.cycles} cycles a flavour, seed {args.seed})",
        "",
        f"{machine()}; dwell {args.min_dwell_s}–{args.max_dwell_s} s log-uniform; daemon "
        f"rate {RATE_HZ:g} Hz, joint speed {JOINT_SPEED_DEG_S:g} °/s (a step of at most "
        f"{JOINT_SPEED_DEG_S / RATE_HZ:g}° + one PWM quantum).",
        "",
        "Joint steps faster than the limit (every physical change of the six arm outputs):",
        "",
    ]
    rows = []
    for r in runs:
        fast = [s for s in r.steps if s.fast]
        by = Counter(category(s, r) for s in fast)
        loose = sum(
            1
            for s in r.steps
            if category(s, r) in ("command", "alive")
            and s.loose(JOINT_SPEED_DEG_S, RATE_HZ, s.allowed_deg - JOINT_SPEED_DEG_S / RATE_HZ)
        )
        worst = max(
            (s.step_deg for s in r.steps if category(s, r) in ("command", "alive")),
            default=0.0,
        )
        worst_race = max(
            (s.step_deg for s in r.steps if category(s, r) == "marker_race"), default=0.0
        )
        rows.append([
            r.flavour, len(r.steps), by["command"], by["alive"], loose, worst, by["dead_race"],
            by["marker_race"], worst_race, by["disarmed"], r.first_pulses,
        ])  # fmt: skip
    lines += md_table(
        [
            "flavour",
            "physical changes",
            "fast: commands",
            "fast: coming alive",
            "loose reading (daemon's)",
            "largest daemon-side step (°)",
            "race: alive again before a readback could show them dead",
            "race: alive again before the daemon's command for them dead took effect",
            "largest such race (°)",
            "autopilot to its disarmed PWM",
            "first pulses",
        ],
        rows,
    )
    lines += [
        "",
        "Status `outputs_live` against the simulator (bound: the flavour's readback period "
        f"+ {MARGIN_S * 1e3:.0f} ms):",
        "",
    ]
    rows = []
    for r in runs:
        agreed = [a.latency_s for a in r.agreements if a.latency_s is not None]
        changed = [a.latency_s for a in r.agreements if a.latency_s is not None and a.truth_changed]
        censored = [a for a in r.agreements if a.latency_s is None]
        bound = bound_s(r.flavour)
        over = sum(1 for v in agreed if v > bound) + sum(1 for a in censored if a.dwell_s > bound)
        rows.append([
            r.flavour, bound * 1e3, len(r.agreements), len(changed), _ms(agreed, 50),
            _ms(agreed, 99),
            max(agreed, default=math.nan) * 1e3, _ms(changed, 99),
            max(changed, default=math.nan) * 1e3, over,
            sum(1 for a in r.agreements if a.said_live_late),
            sum(1 for a in censored if a.dwell_s <= bound),
            100.0 * r.disagree_s / r.polled_s if r.polled_s else math.nan,
        ])  # fmt: skip
    lines += md_table(
        [
            "flavour",
            "bound ms",
            "events",
            "truth changed",
            "agree p50 ms",
            "p99 ms",
            "max ms",
            "truth changed: p99 ms",
            "max ms",
            "over the bound",
            "of which said live while not (past the bound)",
            "next event first (dwell under the bound)",
            "time disagreeing %",
        ],
        rows,
    )
    for r in runs:
        fast = [s for s in r.steps if s.fast and category(s, r) in ("command", "alive")]
        lines += [
            "",
            f"**{r.flavour}**: {r.wall_s:.0f} s; load before {r.load_before}; events "
            + ", ".join(f"{k} {v}" for k, v in sorted(r.events.items()))
            + "; goto answers "
            + ", ".join(f"{k} {v}" for k, v in sorted(r.outcomes.items())),
        ]
        by_event: dict[str, list[float]] = {}
        for a in r.agreements:
            if a.latency_s is not None and a.truth_changed:
                by_event.setdefault(a.event, []).append(a.latency_s)
        if by_event:
            lines.append(
                "agreement where the truth changed, by event (count, p50 / max ms): "
                + "; ".join(
                    f"{k} {len(v)}, {_ms(v, 50):.0f} / {max(v) * 1e3:.0f}"
                    for k, v in sorted(by_event.items())
                )
            )
        slow_by_event = Counter(
            a.event for a in r.agreements if (a.latency_s or a.dwell_s) > bound_s(r.flavour)
        )
        if slow_by_event:
            lines.append(
                "over the bound by event: "
                + ", ".join(f"{k} {v}" for k, v in sorted(slow_by_event.items()))
            )
            lines += over_bound_lines(r.agreements, r.timeline, r.sim_t0, bound_s(r.flavour))
        commands = sorted(s.step_deg for s in fast if s.cause == "command")
        if commands:
            lines.append(
                f"fast command steps: {len(commands)}, median {commands[len(commands) // 2]:.1f}°, "
                f"largest {commands[-1]:.1f}°"
            )
        if fast:
            pairs = Counter(events_before(r, s) for s in fast)
            gaps: dict[str, float] = {}
            for s in fast:
                gaps[events_before(r, s)] = max(gaps.get(events_before(r, s), 0.0), event_gap(r, s))
            lines.append(
                "fast daemon-side steps by the two events before them (the longest time between "
                "those two events): "
                + ", ".join(f"{k} {v} ({gaps[k]:.2f} s)" for k, v in sorted(pairs.items()))
            )
        for s in sorted(fast, key=lambda s: -s.step_deg)[:10]:
            lines.append(
                f"- output {s.output} t={s.t_s:.3f} s: {s.from_us} → {s.to_us} µs "
                f"({s.step_deg:.1f}°, cause {s.cause}, {s.dt_s:.3f} s after its previous change; "
                f"after {events_before(r, s, detail=True)})"
            )
        raced = [s for s in r.steps if s.fast and category(s, r) == "marker_race"]
        if raced:
            lines.append(
                "races: the daemon's command for outputs shown dead, carried out after they came "
                "alive (the largest):"
            )
        for s in sorted(raced, key=lambda s: -s.step_deg)[:5]:
            lines.append(
                f"- output {s.output} t={s.t_s:.3f} s: {s.from_us} → {s.to_us} µs "
                f"({s.step_deg:.1f}°, {s.dt_s:.3f} s after they came alive; "
                f"after {events_before(r, s, detail=True)})"
            )
    return lines


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--cycles", type=int, default=1000, help="per flavour")
    parser.add_argument("--flavour", choices=["px4", "ardupilot", "both"], default="both")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--min-dwell-s", type=float, default=0.03)
    parser.add_argument("--max-dwell-s", type=float, default=1.0)
    parser.add_argument("--markdown", type=Path, default=ROOT / "bench/results/output_cycles.md")
    parser.add_argument(
        "--keep-logs", type=Path, help="copy the daemon's log and the simulator's events here"
    )
    args = parser.parse_args()
    if not 0 < args.min_dwell_s <= args.max_dwell_s:
        parser.error("need 0 < --min-dwell-s <= --max-dwell-s")
    if args.cycles < 1:
        parser.error(f"--cycles={args.cycles} must be >= 1")
    flavours = ["px4", "ardupilot"] if args.flavour == "both" else [args.flavour]
    runs = [run_flavour(f, args) for f in flavours]
    text = "\n".join(report(runs, args)) + "\n"
    print(text)
    write_markdown(args.markdown, text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
