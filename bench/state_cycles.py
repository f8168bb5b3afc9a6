"""Random cycles of the daemon's own restarts and reloads, a ground station's servo commands and
forged frames, among the autopilot's arming and safety events, against moving targets.

    python -m bench.state_cycles [--cycles 150] [--flavour px4|ardupilot|both] [--seed 0]
                                 [--events NAME,...] [--px4-disarmed-us 1000]
                                 [--answer-bound-s 5] [--daemon-root DIR]
                                 [--min-dwell-s 0.03] [--max-dwell-s 1.0]
                                 [--markdown bench/results/state_cycles.md] [--keep-logs DIR]

The stack and the method are those of ``bench/output_cycles.py`` (read its docstring): the
daemon and the simulated flight controller as subprocesses on UDP loopback, shipped daemon
defaults (``control.rate_hz`` 20, ``arm.joint_speed_deg_s`` 60 at start), a vehicle set up for
the arm (PX4 armed, ``COM_PREARM_MODE`` 2; ArduPilot's safety switch off at boot, the arm's
outputs in ``BRD_SAFETY_MASK`` at start); each cycle, seeded: an event with probability 0.6, a
target (``goto``, not waited for) with probability 0.7, a dwell drawn log-uniformly in [min,
max] while the daemon's ``status`` and the simulator's ``state`` are polled every 20 ms. The
simulator's event log is the physical truth.

**Events** (weights in ``EVENTS``; ``--events`` keeps some only), on top of output_cycles' own
(PX4 ``arm``, ``disarm``, ``kill``, ``prearm_on`` / ``prearm_off``, ``reboot``; ArduPilot
``safety_on`` / ``safety_off``, ``mask_arm`` / ``mask_none``, ``reboot``):

* ``daemon_kill`` / ``daemon_restart``: a target is sent and, 0.05–0.4 s later (the arm on its
  way, away from park), the daemon is killed (SIGKILL, as a crash) or stopped (SIGTERM, its exit
  waited for, as ``systemctl restart``), then started again on the same config; the bench waits
  until it answers and hears the autopilot. Gotos a killed daemon never answered are *lost*.
* ``reload``: the config's ``arm.joint_speed_deg_s`` rewritten to another of 20, 30 … 120 °/s,
  then SIGHUP; the bench waits (at most ``--answer-bound-s``) for the daemon's ``reloaded`` log
  line. The limit a step is judged by follows the config in force (below).
* ``foreign_servo``: a ground station (system 255, component 190, on the simulator's
  ground-station link) sends MAV_CMD_DO_SET_SERVO to one arm output: 2000 µs or a PWM drawn in
  1000–2000. ArduPilot applies it (the output's function is 0); PX4 answers UNSUPPORTED.
* ``foreign_actuator`` (PX4): the same ground station's MAV_CMD_DO_SET_ACTUATOR setting one
  joint's slot (1.0, i.e. 2000 µs, or a value drawn in −1…1), the others NaN (unchanged).
* ``forge_readback``: SERVO_OUTPUT_RAW forged as if from the autopilot on the daemon's link
  (the simulator's ``forge`` fault: frames with the autopilot's ids, unsigned, on the companion's
  link only) every 10 ms for 0.02–0.5 s, showing the arm's outputs elsewhere: PWMs drawn in
  1000–2000 or (PX4, half the time) all at the disarmed PWM, as if dead.
* ``forge_safety`` (ArduPilot): the arm's outputs taken out of ``BRD_SAFETY_MASK`` if they are
  in it (a ``mask_none`` first, logged as one: the switch must hold them), the real switch on
  (if it is off), then SYS_STATUS forged every 10 ms for 0.5–2 s saying it is off, and a target
  sent. What the daemon stores meanwhile comes out when a later ``safety_off`` releases the
  switch.
* ``forge_time``: one SYSTEM_TIME forged with ``time_boot_ms`` drawn below the autopilot's own
  (the clock going back: a reboot that did not happen).

``--px4-disarmed-us 900`` sets ``PWM_MAIN_DISn`` of the arm's outputs (PX4 SITL's default; the
arm's range is 1000–2000): the disarmed PWM lies outside the joints' range.

**Joint steps faster than the limit**: every physical change of the six arm outputs in the
simulator's log, through the daemon's calibration (extended beyond the range, as output_cycles),
by :mod:`devkit.joint_steps`: fast when more than ``joint_speed_deg_s / rate_hz`` plus one PWM
quantum. Whose step (:func:`devkit.joint_steps.step_kind`): the **daemon**'s — its commands, and
outputs coming alive with values it stored — or **foreign** — a ground station's command (the
simulator tags its events with the sender), outputs coming alive with a value such a command
stored, and PX4 itself driving its outputs to the disarmed PWM. The daemon's next command after
a foreign one (jumping back from the foreign PWM) is the daemon's, unless it went out less than
``RACE_HOP_S`` after the first readback that showed the foreign PWM left the simulator (its
``readback`` events): then that readback could not have reached the daemon yet, and it is
counted apart as a **race**; so is one after
an autopilot reboot less than ``BELIEF_WINDOW_S`` after the foreign command (its readbacks
could not be believed before it: a **reboot race**), and PX4's outputs coming alive
``DEAD_WINDOW_S`` or less after going to the disarmed PWM, back to within a step of where they
were (dead too briefly for the readbacks to show it: a **dead-time race**). The target is 0
daemon steps. **The limit around a reload**: in force from the moment the daemon applied it,
which lies between the SIGHUP and the ``reloaded`` line seen in its log plus two control periods
(the command in flight); in that window a step is judged against the higher of the old and new
limits, and the steps over the lower one only are counted apart ("reload window"). Outputs
coming alive bring out a value stored earlier: such a step is judged by the higher of the
limits in force when it was stored and at the release (a safety switch held the joint
mid-motion; the rewind stored a pose within the band of that motion's steps). So is the first
pulse after no pulses, by the limits when the pulses stopped and at the step (the servo stopped
somewhere in the band of the steps sent before: a switch seen late, forged SYS_STATUS; after a
reboot the daemon re-sends the band's middle, at most a step of that motion from the truth).
The steps over the lower limit only, in any of these, are counted apart ("over the lower limit
only"). A killed or restarted daemon's successor reads the config in force.

**Gotos answered**: each ``goto`` goes on a control connection of its own (a pool: a connection
answers one request at a time, so a goto never waits behind another's answer); answered within
``--answer-bound-s`` (5 s), late, never (the daemon alive at the end, after 10 s more), or lost
(its daemon killed first), by the event before it.

**Status** ``outputs_live`` against the simulator's truth as output_cycles measures it (the
time from an event until a poll finds them equal; a restart's from when the new daemon answers).
Of the time they disagree, the part where the outputs were live and the daemon said only that
it does not know (``not_live`` reasons "not known live …", "safety switch unknown …": readbacks
or a switch undecided, not a verdict) is given apart.

The run's headline figures are per flavour and event kind: the daemon's fast steps after each
kind (the last event before the step), unanswered gotos, status over its bound.
"""

from __future__ import annotations

import argparse
import bisect
import functools
import math
import os
import platform
import select
import shutil
import subprocess
import time
from collections import Counter, defaultdict
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from bench.loopback import Stack, load_average
from bench.output_cycles import (
    ARM_MASK,
    ARM_OUTPUTS,
    JOINT_SPEED_DEG_S,
    MARGIN_S,
    POLL_S,
    RATE_HZ,
    Agreement,
    bound_s,
    joint_angle,
    over_bound_lines,
    quantum_deg,
    random_poses,
    set_param,
    sim_live,
)
from bench.report import md_table, write_markdown
from companion.kinematics.arm import Arm, Pose
from devkit.control_client import ControlConnection
from devkit.daemon_process import NOT_SERVING
from devkit.joint_steps import (
    AUTOPILOT,
    DAEMON_ALIVE,
    DAEMON_COMMAND,
    DAEMON_KINDS,
    FOREIGN_ALIVE,
    FOREIGN_COMMAND,
    JointStep,
    Reload,
    SpeedLimits,
    commands_received,
    first_shown_after,
    foreign_command_before,
    foreign_stored_at,
    joint_steps,
    judge,
    marker_race,
    output_changes,
    readbacks_shown,
    step_kind,
    stored_before,
    stored_by_foreign,
    undriven_outside,
)
from firmware_interface.calibration import default_calibration
from sim_servo.config import PX4_DISARMED_PWM_US
from sim_servo.gcs import GroundStation

ROOT = Path(__file__).resolve().parent.parent
EVENT_P = 0.6
TARGET_P = 0.7
#: Events and their weights per flavour (output_cycles' own, then this bench's).
EVENTS = {
    "px4": {
        "arm": 2, "disarm": 2, "kill": 2, "prearm_on": 1, "prearm_off": 1, "reboot": 1,
        "daemon_kill": 2, "daemon_restart": 1, "reload": 2, "foreign_servo": 1,
        "foreign_actuator": 2, "forge_readback": 2, "forge_time": 1,
    },
    "ardupilot": {
        "safety_on": 2, "safety_off": 2, "mask_arm": 1, "mask_none": 1, "reboot": 1,
        "daemon_kill": 2, "daemon_restart": 1, "reload": 2, "foreign_servo": 2,
        "forge_readback": 2, "forge_safety": 2, "forge_time": 1,
    },
}  # fmt: skip
#: The daemon's reasons for an output that mean "not known live" rather than "not live".
UNKNOWN_PREFIXES = ("not known live", "safety switch unknown")
#: The joint speeds a reload draws from (°/s).
RELOAD_SPEEDS = tuple(range(20, 121, 10))
#: A forger's frame interval.
FORGE_INTERVAL_S = 0.01
#: A daemon command from a PWM a foreign command set is a race (``devkit.joint_steps.RACE``)
#: when it reached the simulator less than this after the first readback showing that PWM left
#: it: the readback's way to the daemon (held up to 4.8 ms, ``[link_timing]``) and the command's
#: way back. So is one PX4's commander carried out on outputs alive again from the disarmed
#: PWM, that reached it less than this after the first readback showing them alive
#: (``devkit.joint_steps.MARKER_RACE``).
RACE_HOP_S = 0.01
#: The most that can take at 50 Hz (a readback interval and a hop): a log without ``readback``
#: events is judged with it.
RACE_WINDOW_S = 0.02 + RACE_HOP_S
#: A foreign command the autopilot's reboot followed this soon (``devkit.joint_steps.RACE_REBOOT``):
#: the race window, the span of two readbacks over more than an interval (1.25 × 20 ms), and the
#: round trip of the SYSTEM_TIME asked for then.
BELIEF_WINDOW_S = RACE_WINDOW_S + 1.25 * 0.02 + 0.01
#: PX4's outputs dead (at the disarmed PWM) for less than this before coming alive again
#: (``devkit.joint_steps.RACE_DEAD``): the first readback showing them dead (an interval), the
#: ones it takes to believe it (over more than an interval: the third, two more) and a hop.
DEAD_WINDOW_S = 3 * 0.02 + 0.01
#: The window after the ``reloaded`` log line in which the old limit may still be in force.
RELOAD_MARGIN_PERIODS = 2
#: At most this many control connections for gotos at once (each answers one at a time).
MAX_CONNECTIONS = 8
#: The ground station's ids (MAVProxy's), another system than the autopilot's and the daemon's.
FOREIGN_IDS = (255, 190)
#: After the last cycle, how long the gotos still unanswered are waited for.
FINAL_WAIT_S = 10.0


@dataclass
class Goto:
    """One goto: when it left, what came before it, its answer."""

    sent_s: float
    after: str
    answered_s: float | None = None
    outcome: str | None = None
    lost: bool = False  # its daemon was killed (or died) before answering


@dataclass
class ReloadRecord:
    sent_s: float
    old: float
    new: float
    seen_s: float | None = None  # the ``reloaded`` log line seen (None: not within the bound)
    refused: bool = False


@dataclass
class Run:
    flavour: str
    cycles: int
    disarmed_us: int | None
    events: Counter = field(default_factory=Counter)
    timeline: list[tuple[float, str]] = field(default_factory=list)
    agreements: list[Agreement] = field(default_factory=list)
    gotos: list[Goto] = field(default_factory=list)
    reloads: list[ReloadRecord] = field(default_factory=list)
    foreign_results: Counter = field(default_factory=Counter)
    restart_s: list[float] = field(default_factory=list)
    daemon_deaths: list[str] = field(default_factory=list)
    steps: list[JointStep] = field(default_factory=list)
    kinds: list[str] = field(default_factory=list)
    verdicts: list[tuple[bool, bool]] = field(default_factory=list)
    first_pulses: int = 0
    sim_t0: float = 0.0
    disagree_s: float = 0.0
    #: ... of which the daemon said "not known live" (not a verdict: the readbacks or the
    #: switch undecided) while the outputs were live.
    unknown_s: float = 0.0
    polled_s: float = 0.0
    wall_s: float = 0.0
    load_before: str = ""


class GotoPool:
    """Gotos on the control socket, each on a connection with nothing pending (up to
    ``MAX_CONNECTIONS``, then the one waiting longest); answers matched in order per
    connection."""

    def __init__(self, path: str, record: list[Goto]) -> None:
        self.path = path
        self.record = record
        self._pending: dict[ControlConnection, list[Goto]] = {}

    def send(self, pose: Pose, after: str) -> Goto:
        idle = [c for c, waiting in self._pending.items() if not waiting]
        if idle:
            client = idle[0]
        elif len(self._pending) < MAX_CONNECTIONS:
            client = ControlConnection(self.path)
            self._pending[client] = []
        else:
            client = min(self._pending, key=lambda c: self._pending[c][0].sent_s)
        goto = Goto(time.monotonic(), after)
        self._pending[client].append(goto)
        self.record.append(goto)
        try:
            goto.sent_s = client.send({"cmd": "goto", "pose": list(pose.as_tuple())})
        except OSError:  # the daemon died: found by the next status poll
            self._drop(client)
        return goto

    def waiting(self) -> int:
        return sum(len(w) for w in self._pending.values())

    def poll(self, timeout_s: float) -> None:
        """Take the answers that arrive within ``timeout_s`` (at least one look)."""
        busy = [c for c, waiting in self._pending.items() if waiting]
        if not busy:
            time.sleep(max(timeout_s, 0.0))
            return
        ready, _, _ = select.select(busy, [], [], max(timeout_s, 0.0))
        for client in ready:
            try:
                client.receive()
            except (ConnectionError, OSError):
                self._drop(client)
                continue
            now = time.monotonic()
            while (reply := client.buffered_reply()) is not None:
                goto = self._pending[client].pop(0)
                goto.answered_s, goto.outcome = now, str(reply.get("outcome", "error"))

    def _drop(self, client: ControlConnection) -> None:
        for goto in self._pending.pop(client, []):
            goto.lost = True
        client.close()

    def close(self, wait_s: float = 1.0) -> None:
        """The daemon stopped or died: take what it answered before it went (a SIGTERM answers
        every waiting request), then every goto still waiting is lost."""
        deadline = time.monotonic() + wait_s
        while self.waiting() and time.monotonic() < deadline:
            self.poll(min(0.05, deadline - time.monotonic()))
        for client in list(self._pending):
            self._drop(client)


def git(*args: str, cwd: Path = ROOT) -> str:
    try:
        out = subprocess.run(
            ["git", *args], cwd=cwd, capture_output=True, text=True, timeout=10, check=True
        )
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    return out.stdout.strip()


class Cycles:
    """One flavour's run: the stack, the clients, the events."""

    def __init__(self, flavour: str, args: argparse.Namespace) -> None:
        self.flavour = flavour
        self.args = args
        self.rng = np.random.default_rng([args.seed, 0 if flavour == "px4" else 1])
        self.poses = random_poses(Arm.default(), self.rng, 2 * args.cycles)
        self._next_pose = 0
        weights = {k: v for k, v in EVENTS[flavour].items() if k in args.events}
        self.names = list(weights)
        self.weights = np.array([weights[n] for n in self.names], dtype=float)
        self.weights /= self.weights.sum()
        disarmed = args.px4_disarmed_us if flavour == "px4" else None
        self.run = Run(flavour, args.cycles, disarmed, load_before=load_average())
        self.speed = JOINT_SPEED_DEG_S
        self.pending: Agreement | None = None
        #: ArduPilot: whether the arm's outputs are in BRD_SAFETY_MASK (they are at start).
        self.mask_has_arm = flavour == "ardupilot"

    # -- the stack --------------------------------------------------------------------------

    def sim_args(self) -> list[str]:
        if self.flavour == "ardupilot":
            return ["--param", f"BRD_SAFETY_MASK={ARM_MASK}"]
        if self.args.px4_disarmed_us == PX4_DISARMED_PWM_US:
            return []
        return [
            arg
            for output in ARM_OUTPUTS
            for arg in ("--param", f"PWM_MAIN_DIS{output}={self.args.px4_disarmed_us}")
        ]

    def execute(self) -> Run:
        args, run = self.args, self.run
        daemon = {
            "solver": {"seed": args.seed},
            "control": {"rate_hz": RATE_HZ},
            "arm": {"joint_speed_deg_s": JOINT_SPEED_DEG_S},
        }
        with Stack(
            dialect=self.flavour,
            daemon=daemon,
            sim_args=self.sim_args(),
            daemon_root=args.daemon_root,
            # A daemon of today keeps where the outputs were left, as on a board; an older one
            # (--daemon-root) may not know the setting.
            keep_pose=args.daemon_root is None,
        ) as stack:
            assert stack.sim is not None
            self.stack, self.sim = stack, stack.sim
            self.gotos = GotoPool(stack.control_path, run.gotos)
            self.gcs = GroundStation(stack.gcs_url)
            t_start = time.monotonic()
            try:
                for _ in range(args.cycles):
                    self.cycle()
                if self.pending is not None:
                    run.agreements.append(self.pending)
                run.wall_s = time.monotonic() - t_start
                deadline = time.monotonic() + FINAL_WAIT_S
                while self.gotos.waiting() and time.monotonic() < deadline:
                    self.gotos.poll(0.1)
            finally:
                self.gotos.close(0.0)
                self.gcs.close()
            events = stack.stop()
            if args.keep_logs is not None:
                self.keep_logs(stack)
        run.sim_t0 = next(e["monotonic_s"] for e in events if e["event"] == "start")
        self.count_steps(events)
        return run

    def keep_logs(self, stack: Stack) -> None:
        directory = self.args.keep_logs
        directory.mkdir(parents=True, exist_ok=True)
        logs = [*stack.old_daemon_logs, stack.daemon_log]
        for k, path in enumerate(logs):
            if path.exists():
                shutil.copy(path, directory / f"{self.flavour}-daemon-{k}.log")
        if stack.event_log.exists():
            shutil.copy(stack.event_log, directory / f"{self.flavour}-sim.jsonl")

    # -- one cycle --------------------------------------------------------------------------

    def pose(self) -> Pose:
        pose = self.poses[self._next_pose % len(self.poses)]
        self._next_pose += 1
        return pose

    def last_event(self) -> str:
        return self.run.timeline[-1][1] if self.run.timeline else "start"

    def cycle(self) -> None:
        run, rng = self.run, self.rng
        if self.names and rng.random() < EVENT_P:
            event = str(rng.choice(self.names, p=self.weights))
            if self.pending is not None:
                run.agreements.append(self.pending)  # censored: the next event came first
                self.pending = None
            state = self.sim.state()
            before = sim_live(state)
            run.timeline.append((time.monotonic(), event))  # before it acts
            run.events[event] += 1
            acted_s = self.act(event)
            self.pending = Agreement(event, acted_s, before)
        if rng.random() < TARGET_P:
            self.gotos.send(self.pose(), self.last_event())
        dwell_s = math.exp(
            rng.uniform(math.log(self.args.min_dwell_s), math.log(self.args.max_dwell_s))
        )
        self.dwell(dwell_s)

    def dwell(self, dwell_s: float) -> None:
        """Poll the answers, the daemon's status and the simulator's state for ``dwell_s``."""
        run = self.run
        end_s = time.monotonic() + dwell_s
        last_poll_s: float | None = None
        last_agree = True
        last_unknown = False
        while (now := time.monotonic()) < end_s:
            self.gotos.poll(min(POLL_S, end_s - now))
            if time.monotonic() - (last_poll_s or 0.0) < POLL_S:
                continue
            truth = sim_live(self.sim.state())
            said_status = self.daemon_live()
            if said_status is None:
                continue  # it died: restarted, its polls start over
            said, unknown = said_status
            polled = time.monotonic()
            if last_poll_s is not None:
                run.polled_s += polled - last_poll_s
                if not last_agree:
                    run.disagree_s += polled - last_poll_s
                    if last_unknown:
                        run.unknown_s += polled - last_poll_s
            last_poll_s, last_agree = polled, truth == said
            last_unknown = truth and unknown
            pending = self.pending
            if pending is not None and pending.poll(polled, truth, said, bound_s(run.flavour)):
                run.agreements.append(pending)
                self.pending = None

    def daemon_live(self) -> tuple[bool, bool] | None:
        """The daemon's ``outputs_live``, and whether every output it says is not live is only
        not known to be (:data:`UNKNOWN_PREFIXES`); None when it died (it is then started
        again)."""
        try:
            status = self.stack.status()
            reasons = status["not_live"].values()
            unknown = bool(reasons) and all(r.startswith(UNKNOWN_PREFIXES) for r in reasons)
            return bool(status["outputs_live"]), unknown
        except NOT_SERVING:
            assert self.stack.daemon is not None
            code = self.stack.daemon.proc.poll()
            if code is None:
                raise
            self.run.daemon_deaths.append(f"exit {code} after {self.last_event()}")
            self.run.timeline.append((time.monotonic(), "daemon_died"))
            self.restart("kill")
            return None

    # -- the events -------------------------------------------------------------------------

    def act(self, event: str) -> float:
        """Carry out ``event``; the monotonic time its agreement is measured from."""
        sim = self.sim
        if event in ("arm", "disarm"):
            sim.arm(event == "arm")
        elif event == "kill":
            sim.kill_switch()
        elif event in ("safety_on", "safety_off"):
            sim.safety(event == "safety_on")
        elif event in ("prearm_on", "prearm_off"):
            set_param(self.gcs, self.flavour, "COM_PREARM_MODE", 2 if event == "prearm_on" else 0)
        elif event in ("mask_arm", "mask_none"):
            set_param(
                self.gcs, self.flavour, "BRD_SAFETY_MASK", ARM_MASK if event == "mask_arm" else 0
            )
            self.mask_has_arm = event == "mask_arm"
        elif event == "reboot":
            sim.reboot()
        elif event in ("daemon_kill", "daemon_restart"):
            self.gotos.send(self.pose(), event)  # under way when it stops
            self.dwell(float(self.rng.uniform(0.05, 0.4)))
            return self.restart("kill" if event == "daemon_kill" else "term")
        elif event == "reload":
            self.reload()
        elif event == "foreign_servo":
            self.foreign_servo()
        elif event == "foreign_actuator":
            self.foreign_actuator()
        elif event == "forge_readback":
            self.forge_readback()
        elif event == "forge_safety":
            self.forge_safety()
        elif event == "forge_time":
            boot_ms = int(sim.state()["time_boot_ms"])
            sim.forge("SYSTEM_TIME", time_boot_ms=int(self.rng.integers(0, max(boot_ms, 1))))
        else:
            raise ValueError(f"event={event!r}; valid: {self.names}")
        return time.monotonic()

    def restart(self, how: str) -> float:
        """Stop the daemon (``kill`` / ``term``), take what it answered, start it again; the
        monotonic time the new one answered and heard the autopilot."""
        t0 = time.monotonic()
        self.stack.stop_daemon(how)
        self.gotos.close()  # what the old one answered, the rest lost
        ready_s = self.stack.start_daemon()
        self.gotos = GotoPool(self.stack.control_path, self.run.gotos)
        self.run.restart_s.append(ready_s - t0)
        return ready_s

    def reload(self) -> None:
        choices = [s for s in RELOAD_SPEEDS if s != self.speed]
        new = float(self.rng.choice(choices))
        log_path = self.stack.daemon_log
        seen = log_path.read_text(errors="replace").count("reloaded ")
        refused = log_path.read_text(errors="replace").count("reload refused")
        record = ReloadRecord(time.monotonic(), self.speed, new)
        self.run.reloads.append(record)
        self.stack.reload_daemon({"arm": {"joint_speed_deg_s": new}})
        self.speed = new
        deadline = record.sent_s + self.args.answer_bound_s
        while time.monotonic() < deadline:
            self.gotos.poll(0.005)
            text = log_path.read_text(errors="replace")
            if text.count("reloaded ") > seen:
                record.seen_s = time.monotonic()
                return
            if text.count("reload refused") > refused:
                record.refused = True
                return

    def foreign_pwm(self) -> int:
        return 2000 if self.rng.random() < 0.5 else int(self.rng.integers(1000, 2001))

    def foreign_command(self, command: int, params: list[float]) -> None:
        """``command`` from the ground station to the autopilot; its ACK waited for (0.5 s)."""
        self.gcs.send(self.gcs.mav.command_long_encode(1, 1, command, 0, *params))
        ack = self.gcs.wait_for(
            lambda m: m.get_type() == "COMMAND_ACK" and m.command == command, 0.5
        )
        name = mavlink.enums["MAV_CMD"][command].name.removeprefix("MAV_CMD_")
        result = "no ACK" if ack is None else mavlink.enums["MAV_RESULT"][ack.result].name
        self.run.foreign_results[f"{name} {result.removeprefix('MAV_RESULT_')}"] += 1

    def foreign_servo(self) -> None:
        output = int(self.rng.choice(ARM_OUTPUTS))
        pwm = self.foreign_pwm()
        self.foreign_command(mavlink.MAV_CMD_DO_SET_SERVO, [output, pwm, 0, 0, 0, 0, 0])

    def foreign_actuator(self) -> None:
        slot = int(self.rng.integers(0, len(ARM_OUTPUTS)))
        value = 1.0 if self.rng.random() < 0.5 else float(self.rng.uniform(-1.0, 1.0))
        params = [math.nan] * 6 + [0.0]
        params[slot] = value
        self.foreign_command(mavlink.MAV_CMD_DO_SET_ACTUATOR, params)

    def forge_safety(self) -> None:
        """The switch on, holding the arm's outputs; SYS_STATUS forged saying it is off."""
        sim, run = self.sim, self.run
        if self.mask_has_arm:  # the switch would not hold them: a mask_none first
            run.timeline[-1] = (run.timeline[-1][0], "mask_none")
            run.events["mask_none"] += 1
            self.act("mask_none")
            self.dwell(0.3)  # the output driver takes the mask at its next tick
            run.timeline.append((time.monotonic(), "forge_safety"))
        if not sim.state()["safety_on"]:
            sim.safety(True)
        for_s = float(self.rng.uniform(0.5, 2.0))
        sim.forge("SYS_STATUS", safety_on=False, for_s=for_s, interval_s=FORGE_INTERVAL_S)
        self.gotos.send(self.pose(), "forge_safety")

    def forge_readback(self) -> None:
        rng = self.rng
        if self.run.disarmed_us is not None and rng.random() < 0.5:
            shown = dict.fromkeys(ARM_OUTPUTS, self.run.disarmed_us)
        else:
            shown = {o: int(rng.integers(1000, 2001)) for o in ARM_OUTPUTS}
        for_s = math.exp(rng.uniform(math.log(0.02), math.log(0.5)))
        self.sim.forge(
            "SERVO_OUTPUT_RAW",
            pwm_us={str(o): pwm for o, pwm in shown.items()},
            for_s=for_s,
            interval_s=FORGE_INTERVAL_S,
        )

    # -- counting ---------------------------------------------------------------------------

    def count_steps(self, events: list[dict[str, Any]]) -> None:
        run = self.run
        limits = SpeedLimits(
            JOINT_SPEED_DEG_S,
            [
                Reload(
                    r.sent_s - run.sim_t0,
                    (r.seen_s if r.seen_s is not None else math.inf)
                    - run.sim_t0
                    + RELOAD_MARGIN_PERIODS / RATE_HZ,
                    r.old,
                    r.new,
                )
                for r in run.reloads
                if not r.refused
            ],
        )
        calibration = default_calibration(ARM_OUTPUTS)
        changes = output_changes(events)
        stored = stored_by_foreign(events)
        readbacks = readbacks_shown(events)
        received = commands_received(events)
        reboots_s = sorted(
            e["t_s"] for e in events if e["event"] == "fault" and e.get("fault") == "reboot"
        )
        for output in ARM_OUTPUTS:
            joint = calibration.for_output(output)
            quantum = quantum_deg(joint)
            steps, first = joint_steps(
                output,
                undriven_outside(changes.get(output, []), joint.pwm_min_us, joint.pwm_max_us),
                functools.partial(joint_angle, joint),
                joint_speed_deg_s=JOINT_SPEED_DEG_S,
                rate_hz=RATE_HZ,
                quantum_deg=quantum,
            )
            run.first_pulses += len(first)
            for step in steps:
                run.steps.append(step)
                before_s = foreign_command_before(stored.get(output, []), step.t_s)
                race_window_s = RACE_WINDOW_S
                if before_s is not None and readbacks:
                    shown_s = first_shown_after(
                        readbacks.get(output, []), step.from_us, step.t_s - before_s
                    )
                    race_window_s = (
                        math.inf
                        if shown_s is None
                        else shown_s - (step.t_s - before_s) + RACE_HOP_S
                    )
                in_force_deg_s = limits.at(step.t_s)[1]
                run.kinds.append(
                    step_kind(
                        step,
                        disarmed_us=run.disarmed_us,
                        stored_foreign=foreign_stored_at(stored.get(output, []), step.t_s),
                        foreign_before_s=before_s,
                        race_window_s=race_window_s,
                        reboot_cut_short=before_s is not None
                        and reboot_within(reboots_s, step.t_s - before_s, BELIEF_WINDOW_S),
                        dead_window_s=DEAD_WINDOW_S,
                        back_allowed_deg=in_force_deg_s / RATE_HZ + quantum,
                        marker_raced=marker_race(
                            step,
                            disarmed_us=run.disarmed_us,
                            received_s=received.get(output, {}).get(step.t_s),
                            shown=readbacks.get(output, []),
                            hop_s=RACE_HOP_S,
                        ),
                    )
                )
                run.verdicts.append(
                    judge(
                        step,
                        limits,
                        rate_hz=RATE_HZ,
                        quantum_deg=quantum,
                        stored_s=stored_before(stored.get(output, []), step.t_s),
                    )
                )


def reboot_within(reboots_s: Sequence[float], t_s: float, window_s: float) -> bool:
    """Whether one of ``reboots_s`` (sorted) lies in ``[t_s, t_s + window_s]``."""
    k = bisect.bisect_left(reboots_s, t_s)
    return k < len(reboots_s) and reboots_s[k] <= t_s + window_s


# -- the report -------------------------------------------------------------------------------


def event_before(run: Run, t_monotonic: float) -> tuple[str, float]:
    """The last event at or before ``t_monotonic`` and how long before it ("start", inf: none)."""
    before = [(t, e) for t, e in run.timeline if t <= t_monotonic]
    if not before:
        return "start", math.inf
    t, event = before[-1]
    return event, t_monotonic - t


def events_before(run: Run, step: JointStep, *, detail: bool = False) -> str:
    """The last two events before ``step`` (with how long before it, in detail)."""
    t = run.sim_t0 + step.t_s
    before = [(t_e, e) for t_e, e in run.timeline if t_e <= t][-2:]
    if detail:
        return " then ".join(f"{e} ({t - t_e:.2f} s before)" for t_e, e in before)
    return " then ".join(e for _, e in before) or "start"


def fast_daemon_steps(run: Run) -> list[tuple[JointStep, str]]:
    """The daemon's steps fast against the limit that may be in force, with their kind."""
    return [
        (s, k)
        for s, k, (fast, _) in zip(run.steps, run.kinds, run.verdicts, strict=True)
        if fast and k in DAEMON_KINDS
    ]


def _ms(values: list[float], q: float) -> float:
    return float(np.percentile(np.array(values) * 1e3, q)) if values else math.nan


def header(args: argparse.Namespace, runs: list[Run]) -> list[str]:
    """The title and the run's settings (write_markdown adds command, commit, date, machine)."""
    if args.daemon_root is None:
        last = git("log", "-1", "--format=%h %cs", "--", "companion")
        daemon = f"the daemon, `companion/`, as of {last}"
    else:
        found = git("log", "-1", "--format=%h %cs", cwd=args.daemon_root)
        daemon = f"the daemon from `{args.daemon_root}`" + (
            f", commit {found}" if found != "unknown" else " (not a git checkout)"
        )
    loads = "; ".join(f"{r.flavour} {r.load_before}" for r in runs)
    return [
        f"# State cycles ({args.cycles} cycles a flavour, seed {args.seed})",
        "",
        f"Run on {daemon} ({platform.node() or 'unknown host'}, pid {os.getpid()}); load "
        f"average before each flavour: {loads}.",
        "",
        f"Daemon rate {RATE_HZ:g} Hz, joint speed {JOINT_SPEED_DEG_S:g} °/s at start (reloads "
        f"draw {RELOAD_SPEEDS[0]}–{RELOAD_SPEEDS[-1]} °/s); a step is fast above "
        "speed / rate + one PWM quantum; dwell "
        f"{args.min_dwell_s}–{args.max_dwell_s} s log-uniform; PX4 disarmed PWM "
        f"{args.px4_disarmed_us} µs; gotos answered within {args.answer_bound_s:g} s.",
    ]


def report(runs: list[Run], args: argparse.Namespace) -> list[str]:
    lines = header(args, runs)
    lines += ["", "## Joint steps faster than the limit", ""] + steps_table(runs)
    lines += ["", "## By event kind", ""] + by_event_table(runs, args.answer_bound_s)
    lines += ["", "## Gotos", ""] + gotos_table(runs, args.answer_bound_s)
    lines += ["", "## Status `outputs_live` against the simulator", ""] + status_table(runs)
    for r in runs:
        lines += ["", f"## {r.flavour}: details", ""] + details(r, args.answer_bound_s)
    return lines


def steps_table(runs: list[Run]) -> list[str]:
    rows = []
    for r in runs:
        fast = Counter(k for k, (f, _) in zip(r.kinds, r.verdicts, strict=True) if f)
        window = sum(
            1
            for k, (f, low) in zip(r.kinds, r.verdicts, strict=True)
            if low and not f and k in DAEMON_KINDS
        )
        daemon = [s.step_deg for s, _ in fast_daemon_steps(r)]
        rows.append([
            r.flavour, len(r.steps), fast[DAEMON_COMMAND], fast[DAEMON_ALIVE],
            max(daemon, default=0.0), window, fast[FOREIGN_COMMAND], fast[FOREIGN_ALIVE],
            fast[AUTOPILOT], r.first_pulses,
        ])  # fmt: skip
    return [
        "Every physical change of the six arm outputs; the daemon's own are the target (0).",
        "",
        *md_table(
            [
                "flavour",
                "physical changes",
                "daemon: commands",
                "daemon: coming alive",
                "largest daemon step (°)",
                "daemon, over the lower limit only (a reload between)",
                "foreign: commands",
                "foreign: coming alive",
                "foreign: autopilot to its disarmed PWM",
                "first pulses",
            ],
            rows,
        ),
    ]


def by_event_table(runs: list[Run], answer_bound_s: float) -> list[str]:
    rows = []
    for r in runs:
        fast_after: dict[str, list[float]] = defaultdict(list)
        for step, _ in fast_daemon_steps(r):
            fast_after[event_before(r, r.sim_t0 + step.t_s)[0]].append(step.step_deg)
        gotos_after: dict[str, list[Goto]] = defaultdict(list)
        for goto in r.gotos:
            gotos_after[goto.after].append(goto)
        over = Counter(
            a.event
            for a in r.agreements
            if (a.latency_s if a.latency_s is not None else a.dwell_s) > bound_s(r.flavour)
        )
        counts = {"start": 1, **r.events, "daemon_died": len(r.daemon_deaths)}
        for kind in ["start", *EVENTS[r.flavour], "daemon_died"]:
            gotos = gotos_after.get(kind, [])
            fast = fast_after.get(kind, [])
            if not counts.get(kind) and not gotos and not fast:
                continue
            rows.append([
                r.flavour, kind, counts.get(kind, 0), len(fast), max(fast, default=0.0),
                len(gotos), sum(1 for g in gotos if _unanswered(g, answer_bound_s)),
                sum(1 for g in gotos if g.lost), over[kind],
            ])  # fmt: skip
    return [
        "The daemon's fast steps and the gotos counted after the last event before them "
        "(`start`: before any); status over its bound as output_cycles counts it.",
        "",
        *md_table(
            [
                "flavour",
                "event",
                "events",
                "daemon fast steps after it",
                "largest (°)",
                "gotos after it",
                "unanswered within the bound",
                "of which lost in a kill",
                "status over its bound",
            ],
            rows,
        ),
    ]


def gotos_table(runs: list[Run], answer_bound_s: float) -> list[str]:
    rows = []
    for r in runs:
        answered = [g for g in r.gotos if g.answered_s is not None]
        took = [g.answered_s - g.sent_s for g in answered if g.answered_s is not None]
        late = sum(1 for t in took if t > answer_bound_s)
        outcomes = Counter(g.outcome for g in answered)
        rows.append([
            r.flavour, len(r.gotos), len(took) - late, late,
            sum(1 for g in r.gotos if g.answered_s is None and not g.lost),
            sum(1 for g in r.gotos if g.lost), _ms(took, 50), _ms(took, 99),
            max(took, default=math.nan) * 1e3,
            ", ".join(f"{k} {v}" for k, v in sorted(outcomes.items())),
        ])  # fmt: skip
    return md_table(
        [
            "flavour",
            "sent",
            "answered within the bound",
            "late",
            "never (daemon alive)",
            "lost in a kill",
            "p50 ms",
            "p99 ms",
            "max ms",
            "outcomes",
        ],
        rows,
    )


def status_table(runs: list[Run]) -> list[str]:
    rows = []
    for r in runs:
        agreed = [a.latency_s for a in r.agreements if a.latency_s is not None]
        censored = [a for a in r.agreements if a.latency_s is None]
        bound = bound_s(r.flavour)
        over = sum(1 for v in agreed if v > bound) + sum(1 for a in censored if a.dwell_s > bound)
        rows.append([
            r.flavour, bound * 1e3, len(r.agreements), _ms(agreed, 50), _ms(agreed, 99),
            max(agreed, default=math.nan) * 1e3, over,
            sum(1 for a in r.agreements if a.said_live_late),
            sum(1 for a in censored if a.dwell_s <= bound),
            100.0 * r.disagree_s / r.polled_s if r.polled_s else math.nan,
            100.0 * r.unknown_s / r.polled_s if r.polled_s else math.nan,
        ])  # fmt: skip
    return [
        f"Bound: the flavour's readback period + {MARGIN_S * 1e3:.0f} ms.",
        "",
        *md_table(
            [
                "flavour",
                "bound ms",
                "events",
                "agree p50 ms",
                "p99 ms",
                "max ms",
                "over the bound",
                "of which said live while not (past the bound)",
                "next event first (dwell under the bound)",
                "time disagreeing %",
                "of which live but said not known live %",
            ],
            rows,
        ),
    ]


def details(r: Run, answer_bound_s: float) -> list[str]:
    lines = [
        f"{r.wall_s:.0f} s; events "
        + ", ".join(f"{k} {v}" for k, v in sorted(r.events.items()))
        + "."
    ]
    if r.restart_s:
        lines.append(
            f"Restarts: {len(r.restart_s)}, the new daemon answering and linked after "
            f"{np.median(r.restart_s):.1f} s median ({max(r.restart_s):.1f} s max)."
        )
    if r.daemon_deaths:
        lines.append("The daemon died on its own: " + "; ".join(r.daemon_deaths) + ".")
    if r.reloads:
        seen = [x.seen_s - x.sent_s for x in r.reloads if x.seen_s is not None]
        unseen = sum(1 for x in r.reloads if x.seen_s is None and not x.refused)
        lines.append(
            f"Reloads: {len(r.reloads)} ("
            + ", ".join(f"{x.old:g}→{x.new:g}" for x in r.reloads)
            + f" °/s); logged as applied after {_ms(seen, 50):.0f} ms median, "
            f"{max(seen, default=math.nan) * 1e3:.0f} ms max; {unseen} not logged within the "
            f"bound, {sum(1 for x in r.reloads if x.refused)} refused."
        )
    if r.foreign_results:
        lines.append(
            "The ground station's commands: "
            + ", ".join(f"{k} {v}" for k, v in sorted(r.foreign_results.items()))
            + "."
        )
    foreign = Counter(
        k for k, (f, _) in zip(r.kinds, r.verdicts, strict=True) if f and k not in DAEMON_KINDS
    )
    if foreign:
        lines.append(
            "Foreign fast steps: " + ", ".join(f"{k} {v}" for k, v in sorted(foreign.items())) + "."
        )
    fast = fast_daemon_steps(r)
    if fast:
        pairs = Counter(events_before(r, step) for step, _ in fast)
        lines.append(
            "The daemon's fast steps by the two events before them: "
            + ", ".join(f"{k} {v}" for k, v in sorted(pairs.items()))
            + "."
        )
        lines += ["", "The daemon's largest fast steps:", ""]
    for step, kind in sorted(fast, key=lambda sk: -sk[0].step_deg)[:12]:
        context = events_before(r, step, detail=True)
        lines.append(
            f"- output {step.output} t={step.t_s:.3f} s: {step.from_us} → {step.to_us} µs "
            f"({step.step_deg:.1f}°, {kind}, cause {step.cause}, {step.dt_s:.3f} s after its "
            f"previous change; after {context or 'no event'})"
        )
    late = [g for g in r.gotos if _unanswered(g, answer_bound_s)]
    if late:
        lines += ["", "Gotos not answered within the bound:", ""]
    for g in late[:12]:
        if g.answered_s is not None:
            took = f"answered {g.outcome} after {g.answered_s - g.sent_s:.1f} s"
        else:
            took = "lost in a kill" if g.lost else "never answered"
        lines.append(f"- sent at {g.sent_s - r.sim_t0:.3f} s after {g.after}: {took}")
    claims = over_bound_lines(
        r.agreements, r.timeline, r.sim_t0, bound_s(r.flavour), false_claims_only=True
    )
    if claims:
        lines += ["", "Status said live while the outputs were not, past the bound:", "", *claims]
    return lines


def _unanswered(goto: Goto, bound_s_: float) -> bool:
    return goto.answered_s is None or goto.answered_s - goto.sent_s > bound_s_


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--cycles", type=int, default=150, help="per flavour")
    parser.add_argument("--flavour", choices=["px4", "ardupilot", "both"], default="both")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--events",
        help="comma-separated event names to draw from (default: all of the flavour's); "
        "names a flavour lacks are ignored for it",
    )
    parser.add_argument(
        "--px4-disarmed-us",
        type=int,
        default=PX4_DISARMED_PWM_US,
        help=f"PX4's PWM_MAIN_DISn on the arm's outputs (default {PX4_DISARMED_PWM_US}; "
        "PX4 SITL's is 900)",
    )
    parser.add_argument(
        "--daemon-root",
        type=Path,
        help="run the daemon from this checkout (another version of it; default this one)",
    )
    parser.add_argument("--answer-bound-s", type=float, default=5.0)
    parser.add_argument("--min-dwell-s", type=float, default=0.03)
    parser.add_argument("--max-dwell-s", type=float, default=1.0)
    parser.add_argument("--markdown", type=Path, default=ROOT / "bench/results/state_cycles.md")
    parser.add_argument(
        "--keep-logs", type=Path, help="copy the daemons' logs and the simulator's events here"
    )
    args = parser.parse_args()
    if not 0 < args.min_dwell_s <= args.max_dwell_s:
        parser.error("need 0 < --min-dwell-s <= --max-dwell-s")
    if args.cycles < 1:
        parser.error(f"--cycles={args.cycles} must be >= 1")
    if not 500 <= args.px4_disarmed_us <= 2500:
        parser.error(f"--px4-disarmed-us={args.px4_disarmed_us} outside [500, 2500]")
    if not args.answer_bound_s > 0:
        parser.error(f"--answer-bound-s={args.answer_bound_s} must be > 0")
    known = {name for events in EVENTS.values() for name in events}
    if args.events is None:
        args.events = known
    else:
        args.events = {name.strip() for name in args.events.split(",") if name.strip()}
        if unknown := args.events - known:
            parser.error(f"--events: unknown {sorted(unknown)}; valid: {sorted(known)}")
    flavours = ["px4", "ardupilot"] if args.flavour == "both" else [args.flavour]
    runs = [Cycles(f, args).execute() for f in flavours]
    text = "\n".join(report(runs, args)) + "\n"
    print(text)
    write_markdown(args.markdown, text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
