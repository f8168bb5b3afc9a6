"""The daemon's control logic as a state machine: events in, actions out, no I/O.

:class:`ControlCore` owns the arm's state. It is driven by one thread (the daemon's control
thread, :mod:`companion.daemon.service`) with three events — a request taken from the intake
(:meth:`~ControlCore.request`), a frame from the autopilot (:meth:`~ControlCore.frame`), a tick
(:meth:`~ControlCore.tick`) — and returns the actions to carry out: commands to send to the
autopilot (:class:`SendCommand`) and answers to requests (:class:`Answer`). Time comes from the
injected clock, the solver is injected too, so every rule below is an in-process test with a
fake clock.

Rules:

* **Status is what the autopilot acknowledged.** Per output, the PWM the autopilot ACCEPTED;
  per joint, the angle whose PWM it accepted. Motion steps from there, so a partial update can
  neither break the speed limit nor make the status lie.
* **Pipelined updates.** An update's commands go out back-to-back and its ACKs are counted
  (:mod:`firmware_interface.updates`). The next step may go out behind the update in flight
  (at most ``PIPELINE_DEPTH`` on their way), re-sending every output the one ahead sent, so
  when the one ahead ends unanswered the one behind decides. When the outputs' state is
  unknown (ACKs missing), the same values are re-sent (``command_retries`` more times at
  once), and the arm does not move on before they are confirmed. An update that stays unknown
  fails the targets waiting on it; ``UPDATE_ATTEMPTS`` of them in a row abandon the motion.
* **A refused output stops the motion** with the autopilot's reason; what did move is reported
  as moved.
* **Every request gets one answer**: ``goto`` ACCEPTED once its first step is acknowledged,
  FAILED (out of reach, refused, unanswered), DENIED (malformed), TEMPORARILY_REJECTED (no
  autopilot), CANCELLED (superseded or stopped before its first step went out). A target whose
  first step is already on its way is not cancelled: it is answered with what happened.
* **A pinned autopilot**: its ids come from the config or from the first autopilot HEARTBEAT,
  and never change; ACKs, STATUSTEXTs and SYSTEM_TIMEs from anyone else are counted and ignored.
* **An autopilot reboot** (SYSTEM_TIME ``time_boot_ms`` going backwards, or falling behind the
  time elapsed, whatever the gap) is a link loss: the outputs' state is unknown, and every
  output is re-sent before moving on.
* **Link lost**: hold (nothing is sent), answer waiting targets TEMPORARILY_REJECTED (and drop
  their goal); when it is back, re-send every output at the acknowledged pose, then carry on
  towards the goal of a target that was already ACCEPTED.
* **The outputs tell the truth** (an ACK proves nothing): PX4's readback says whether each
  output is live; one found dead holds a marker (``MARKER_OFFSET_US`` from its disarmed PWM),
  so coming alive moves it 2 µs and shows at the next readback; ArduPilot's SYS_STATUS says
  where its safety switch is, and what the outputs may hold meanwhile stays within a step
  (``SAFETY_STEPS_AHEAD``). Coming alive never moves a joint faster than the speed limit.
"""

from __future__ import annotations

import collections
import dataclasses
import logging
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from companion.daemon.config import DaemonConfig
from companion.daemon.motion import limit_step
from companion.daemon.requests import (
    MOTION_KINDS,
    Outcome,
    Reply,
    Request,
    Target,
    as_target,
    parse_trajectory,
)
from companion.daemon.telemetry import VehicleTelemetry
from companion.ik.keepout import ClearVerdict, solve_clear
from companion.ik.solver import TargetMode
from companion.kinematics.arm import Pose
from companion.kinematics.collision import KeepOut
from companion.kinematics.vehicle import base_to_world, matrix_to_base
from firmware_interface import CalibrationError, make_servo_dialect
from firmware_interface.commands import command_name
from firmware_interface.link import is_autopilot_heartbeat
from firmware_interface.transport import parse_url
from firmware_interface.updates import ServoCommand, UpdateOutcome, UpdateState, UpdateTracker

log = logging.getLogger("armbridge")

#: An accepted motion survives this many unanswered updates in a row (each already re-sent
#: ``command_retries`` times); then it is abandoned.
UPDATE_ATTEMPTS = 3
#: SYSTEM_TIME is asked for at this interval, for reboot detection.
SYSTEM_TIME_INTERVAL_S = 0.25
#: A SYSTEM_TIME stream that fell silent this long is asked for again (a rebooted autopilot
#: forgets the intervals it was asked for), and the outputs are re-sent in case it rebooted.
SYSTEM_TIME_SILENT_S = 1.0
#: At shutdown, the park update's commands are sent again after this long without an ACK.
SHUTDOWN_RETRY_S = 0.1
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
#: The outputs' readback (SERVO_OUTPUT_RAW) is asked for at this interval: the truth of what the
#: outputs do (issue 20). ArduPilot streams it at most every 20 ms.
READBACK_INTERVAL_S = 0.1
#: PX4 on a link with room for it: a readback this often sees outputs go dead (disarm, kill)
#: sooner, so the hold at the disarmed PWM is stored before a quick re-arm would apply the
#: pose stored before (bench.output_cycles: every fast PX4 step came from a re-arm inside the
#: window in which the disarm was not seen yet), and sees them come alive within 20 ms (the
#: marker, ``MARKER_OFFSET_US``). 50 Hz, ArduPilot's cap for this stream: 49-byte frames,
#: 2.5 kB/s on the link, ~0.2 % of a core in the daemon.
READBACK_FAST_INTERVAL_S = 0.02
#: ArduPilot on a serial line below SLOW_LINK_BAUD: the readback only feeds status there (its
#: safety switch comes from SYS_STATUS), and at 10 Hz its 49-byte frames (4.3 ms each at
#: 115 200 baud) would delay an update's ACK behind them one time in twenty.
READBACK_SLOW_LINK_INTERVAL_S = 1.0
SLOW_LINK_BAUD = 230_400
#: ArduPilot's SYS_STATUS (its safety switch: MAV_SYS_STATUS_SENSOR_MOTOR_OUTPUTS enabled means
#: the switch is off) is asked for at this interval (on a serial line below SLOW_LINK_BAUD, the
#: slower one): the switch is seen that late, and the steps sent meanwhile are stored without
#: pulses, so what the arm may have moved then is undone while it is on (see ``_rewind``). Twice
#: a control tick (20 Hz) on a fast link, so that SAFETY_STEPS_AHEAD seldom holds a step back.
SYS_STATUS_INTERVAL_S = 0.025
SYS_STATUS_SLOW_LINK_INTERVAL_S = 0.25
#: ArduPilot: since the last SYS_STATUS that said the switch is off, the switch may have gone on
#: (and even off again, unseen) at any moment, holding each output at the pose acknowledged then
#: or at any step sent since (or on its way then), and storing every later one for its release.
#: Those poses are kept within a band this many control ticks' steps (``joint_speed_deg_s /
#: rate_hz``) wide per joint (a step that would widen it waits for the next SYS_STATUS): with
#: one, the release moves a joint by at most a step whatever it stored, and the middle of the
#: band, where the rewind (``_rewind``) and a re-send after a loss or a reboot send the outputs,
#: is within half a step of anything they may hold. A SYS_STATUS stream that falls silent stops
#: the arm within the band (never narrower than SAFETY_BAND_MIN_S of motion, below). On a slow
#: serial line (SYS_STATUS every 0.25 s) the
#: band is the steps of one SYS_STATUS interval, not to slow the arm: a release there may move a
#: joint by more than a step.
SAFETY_STEPS_AHEAD = 1
#: ... and at least this long of motion at ``joint_speed_deg_s`` (one step at the default 20 Hz
#: control): two SYS_STATUS intervals, so that the band, which holds a step on its way when a
#: SYS_STATUS comes, never slows the arm. Above 20 Hz control a release may then move a joint
#: by this much motion (3 degrees at 60 deg/s), more than one of its shorter steps: held whole
#: to one step at 50 Hz, the arm fell behind a hovering vehicle (world error p99 1.9-4.7 cm
#: against 0.3-0.6, ``bench.world_hold``).
SAFETY_BAND_MIN_S = 0.05
#: ArduPilot: nothing moves until a SYS_STATUS said where the safety switch is (at start, after
#: a loss or a reboot: ArduPilot boots with it on, ``BRD_SAFETY_DEFLT``, and what is sent then
#: is stored and goes out in one step at its release); with none this long after asking, the
#: arm moves without knowing (and says so once).
SYS_STATUS_WAIT_S = 2.0
#: ArduPilot: a SYS_STATUS stream silent for this many intervals says nothing of the switch
#: any more: status shows the outputs as not known to be live (a reboot: they are not).
SYS_STATUS_STALE_INTERVALS = 4
#: ... and silent this long (at least SYS_STATUS_STALE_INTERVALS), every stream is asked for
#: again (a rebooted ArduPilot forgot them; one asked while it reboots is lost), so a reboot is
#: seen from the SYSTEM_TIME that comes back rather than after SYSTEM_TIME_SILENT_S.
SYS_STATUS_SILENT_S = 0.5
#: A readback this long after an output's ACK shows what the output does with that command
#: (PX4 applies it on its next output cycle, a few ms; the stream adds up to its interval).
READBACK_SETTLE_S = 0.15
#: This many such readbacks in a row not showing the acknowledged PWM: the output is not live.
READBACK_MISMATCHES = 2
#: PX4: an output found not live (showing its disarmed PWM) is told to hold a PWM this far
#: from it, towards the middle of its range: the "marker". It moves the joint by that much
#: when the output comes alive (arm, prearm), which the next readback then shows: live again
#: is seen within one readback, where a readback of the disarmed PWM itself could not tell
#: storage from output. The same at the start and after a reboot or a loss, with the arm
#: still: the PWM the output shows, plus the offset, tells whether it is live.
MARKER_OFFSET_US = 2
#: PX4: where no marker fits (a range too narrow for it), one speed-limited step towards the
#: goal at this interval shows whether the outputs came alive instead.
PROBE_INTERVAL_S = 1.0
#: PX4, outputs not yet known to be live: the next step waits for the readback's verdict on
#: the one before (shown: live; not shown READBACK_MISMATCHES times: not live), at most this
#: long (a readback stream that stopped must not stop the arm for good).
VERDICT_TIMEOUT_S = 2.0
#: A readback PWM within this of the acknowledged one is "the same" (PX4 rounds its mapping).
READBACK_TOLERANCE_US = 1
assert MARKER_OFFSET_US > READBACK_TOLERANCE_US  # a marker shown is told from the disarmed PWM
#: PX4, for status: a readback stream silent this many intervals says nothing of the outputs
#: any more (a reboot: they are at the disarmed PWM; seen 44 ms after it at 50 Hz, against 66
#: with 3 intervals, in bench.output_cycles; one lost frame makes a 40 ms gap, not more);
#: silent READBACK_SILENT_S (at least this many intervals), every stream is asked for again
#: (a rebooted PX4 forgot them).
READBACK_STALE_INTERVALS = 2
READBACK_SILENT_S = 0.5
#: A frame from the autopilot after this many intervals of the fastest stream asked for with
#: nothing from it, where its frames came that often before: every stream is asked for again
#: at once (see ``_after_silence``).
AUTOPILOT_GAP_INTERVALS = 4
#: PX4: with no readback this long after the link came up, move without it (and say so).
READBACK_WAIT_S = 2.0
#: Updates on their way at once: one, and the next step behind it (see ``_pipeline``). The
#: next step after that waits: a deeper pipe would only queue stale steps.
PIPELINE_DEPTH = 2

#: (pose, q_start_deg or None for a cold start, mode, budget_ms or None for the configured
#: one, seed= keyword: None for the configured one) → ik.IKResult
Solve = Callable[..., Any]
#: A world-frame target is solved again every control tick in at most this share of the
#: period (warm, it converges in ~0.1 ms; an unreachable one costs the whole of it).
WORLD_SOLVE_SHARE = 0.1
#: A stream asked to stop (SET_MESSAGE_INTERVAL param2 = -1).
STOP_STREAM = -1.0


def stream_intervals_s(*, ardupilot: bool, url: str) -> tuple[float, float]:
    """(SERVO_OUTPUT_RAW, SYS_STATUS) intervals for a link: slower on a serial line below
    :data:`SLOW_LINK_BAUD`, where every byte up delays the ACKs behind it."""
    spec = parse_url(url)
    slow_serial = spec.kind == "serial" and (spec.baud or 0) < SLOW_LINK_BAUD
    if ardupilot:
        readback_s = READBACK_SLOW_LINK_INTERVAL_S if slow_serial else READBACK_INTERVAL_S
    else:
        readback_s = READBACK_INTERVAL_S if slow_serial else READBACK_FAST_INTERVAL_S
    sys_status_s = SYS_STATUS_SLOW_LINK_INTERVAL_S if slow_serial else SYS_STATUS_INTERVAL_S
    return readback_s, sys_status_s


def stream_requests(
    *,
    ardupilot: bool,
    readback_interval_s: float,
    sys_status_interval_s: float,
    world_telemetry_hz: float | None,
) -> list[tuple[int, float]]:
    """The streams the core asks for (message id, interval in s; :data:`STOP_STREAM`: stop):
    SYSTEM_TIME (reboots), SERVO_OUTPUT_RAW (what the outputs do), from ArduPilot SYS_STATUS
    (its safety switch), and ATTITUDE / LOCAL_POSITION_NED at ``world_telemetry_hz`` when
    world targets are on (None: off). Also what ``bench/serial_links.py``'s line model asks."""
    streams = [
        (mavlink.MAVLINK_MSG_ID_SYSTEM_TIME, SYSTEM_TIME_INTERVAL_S),
        (mavlink.MAVLINK_MSG_ID_SERVO_OUTPUT_RAW, readback_interval_s),
    ]
    if ardupilot:
        streams.append((mavlink.MAVLINK_MSG_ID_SYS_STATUS, sys_status_interval_s))
    if world_telemetry_hz is not None:
        streams += [
            (mavlink.MAVLINK_MSG_ID_ATTITUDE, 1.0 / world_telemetry_hz),
            (mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED, 1.0 / world_telemetry_hz),
        ]
    elif not ardupilot:
        # PX4 streams them unasked on a companion's (ONBOARD) link, 100 and 30 Hz: half a
        # 115 200-baud line, in the way of every ACK. Unread here, they are stopped (on this
        # link only: a ground station's has its own).
        streams += [
            (mavlink.MAVLINK_MSG_ID_ATTITUDE, STOP_STREAM),
            (mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED, STOP_STREAM),
        ]
    return streams


def _band_of(poses: Sequence[Sequence[float]]) -> tuple[list[float], list[float]]:
    """Per joint, the lowest and the highest angle of ``poses``."""
    return (
        [min(p[i] for p in poses) for i in range(len(poses[0]))],
        [max(p[i] for p in poses) for i in range(len(poses[0]))],
    )


def _middle(band: tuple[list[float], list[float]]) -> tuple[float, ...]:
    """Per joint, the middle of a band (within half its width of every angle in it)."""
    return tuple((lo + hi) / 2 for lo, hi in zip(*band, strict=True))


#: Before any update's round trip was measured, the link's one-way latency is taken as this.
WORLD_DEFAULT_ONE_WAY_S = 0.005


@dataclass(frozen=True)
class SendCommand:
    """A COMMAND_LONG to the autopilot ``target`` (system, component)."""

    target: tuple[int, int]
    command: int
    params: tuple[float, ...]
    confirmation: int = 0


@dataclass(frozen=True)
class ReadParam:
    """A PARAM_REQUEST_READ of ``name`` to the autopilot ``target``."""

    target: tuple[int, int]
    name: str


@dataclass(frozen=True)
class Answer:
    """Answer ``request`` with ``reply`` (the edge sets its future)."""

    request: Request
    reply: Reply


Action = SendCommand | ReadParam | Answer


@dataclass(eq=False)
class _Waiting:
    """An accepted target waiting for its first step to be acknowledged."""

    request: Request
    reply: Reply  # what it will be answered once its first step is acknowledged


@dataclass(eq=False)
class _InFlight:
    """The update on its way: the joints it moves to, and its ACK accounting.

    All its commands go out at once (``tracker`` counts their ACKs). Those whose fate that
    leaves unknown are then sent **one at a time** (``pending``), each waiting for its own ACK
    (unambiguous) and re-sent up to ``command_retries`` times: on a lossy link a lost frame
    then costs one command's round trip, not the whole update's.
    """

    step_deg: tuple[float, ...]
    pwm_by_output: dict[int, int]  # the whole step (outputs already there are not sent)
    sent_outputs: frozenset[int]
    tracker: UpdateTracker
    sent_s: float
    waiting: list[_Waiting] = field(default_factory=list)  # targets whose first step this is
    timeout_s: float = 0.5  # per attempt
    pending: list[ServoCommand] = field(default_factory=list)  # still to confirm, in order
    attempt: int = 0  # sends of the command being confirmed one at a time (0: the batch)
    accepted: dict[int, int] = field(default_factory=dict)
    refused: dict[int, str] = field(default_factory=dict)
    #: The steps of updates ahead of it that ended unanswered (the outputs may hold them).
    folded: list[tuple[float, ...]] = field(default_factory=list)
    seq: int = 0  # updates sent before it since the start


class ControlCore:
    """See the module docstring. Not thread-safe: one thread drives it."""

    def __init__(
        self,
        config: DaemonConfig,
        *,
        solve: Solve,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.config = config
        self.clock = clock
        self._solve = solve
        self._dialect = make_servo_dialect(config.link.dialect, None, config.calibration)
        self._outputs = tuple(j.output for j in config.calibration.joints)
        arm = config.arm
        start = config.park_deg or tuple(
            math.degrees((j.min_rad + j.max_rad) / 2) for j in arm.joints
        )
        #: Per joint: the acknowledged angle (before any ACK: the assumed start pose).
        self._position: list[float] = [float(a) for a in start]
        self._acked_pwm: dict[int, int] = {}
        self._refused: dict[int, str] = {}
        #: A step sent whose outputs are not all confirmed: re-sent before moving on, and at
        #: once (``_resend_now``) after a link loss or a reboot.
        self._unconfirmed: tuple[float, ...] | None = None
        self._resend_now = False
        self._goal: tuple[float, ...] | None = None
        self._trajectory: list[tuple[float, Pose]] = []
        self._trajectory_t0 = 0.0
        self._waiting: list[_Waiting] = []  # accepted, first step not sent yet
        #: Updates on their way, oldest first: at most PIPELINE_DEPTH (see _maybe_send).
        self._flights: collections.deque[_InFlight] = collections.deque()
        self._unanswered = 0
        self._last_step_s = -math.inf
        self._next_tick_s = clock()
        self._link_up = False
        #: The pinned autopilot answered one of our commands since the link came up: it has
        #: heard us, so it routes a ground station's targets to us (ArduPilot answers them
        #: UNSUPPORTED, PX4 drops them, for a component it has not heard).
        self._heard_us = False
        #: The autopilot's (system, component): configured parts are fixed, the rest latched
        #: from the first autopilot HEARTBEAT that matches them.
        self._pin_config = (config.link.target_system, config.link.target_component)
        self._pinned: tuple[int, int] | None = None
        self._boot_ms: int | None = None
        self._boot_seen_s = 0.0  # when _boot_ms came
        self._system_time_s: float | None = None  # when the last SYSTEM_TIME came
        self._system_time_asked_s = -math.inf
        self._autopilot_heard_s: float | None = None  # the last frame from the pinned one
        self._autopilot_streaming = False  # its frames came within AUTOPILOT_GAP_INTERVALS
        # -- the outputs' truth (issue 20) --
        #: The last SERVO_OUTPUT_RAW: output → PWM shown, and when it came.
        self._readback: dict[int, int] = {}
        self._readback_s = -math.inf
        #: PX4 moves only after a readback newer than this (start, link loss, reboot), or
        #: READBACK_WAIT_S after it with none (a firmware that does not stream it).
        self._readback_since_s = clock()
        self._readback_warned = False
        self._readback_interval_s, self._sys_status_interval_s = stream_intervals_s(
            ardupilot=self._is_ardupilot, url=config.link.url
        )
        #: See ``_after_silence``: AUTOPILOT_GAP_INTERVALS of the fastest stream asked for.
        fastest_s = min(self._readback_interval_s, SYSTEM_TIME_INTERVAL_S)
        if self._is_ardupilot:
            fastest_s = min(fastest_s, self._sys_status_interval_s)
        self._autopilot_gap_s = AUTOPILOT_GAP_INTERVALS * fastest_s
        #: Per output, the PWMs acknowledged lately with when (a readback may still show any of
        #: those from the last READBACK_SETTLE_S); no entry: nothing acknowledged since the
        #: start, a loss or a reboot.
        self._ack_history: dict[int, collections.deque[tuple[float, int]]] = {}
        #: Per output: readbacks in a row, settled after its ACK, not showing the acked PWM.
        self._mismatches: dict[int, int] = {}
        #: PX4: outputs whose readback does not show what they acknowledged → the reason, and
        #: the PWM they showed then (the disarmed PWM): a readback of that PWM proves nothing.
        self._not_live: dict[int, str] = {}
        self._dead_pwm: dict[int, int] = {}
        #: ... how many updates had been sent when each was found not live (those sent before
        #: it store no pose of its: its hold goes out behind them), and the PWM it is told to
        #: hold meanwhile (its marker, ``MARKER_OFFSET_US`` from the disarmed PWM; or, with no
        #: room for one, the PWM nearest it: then probes, ``PROBE_INTERVAL_S``).
        self._dead_seq: dict[int, int] = {}
        self._updates_sent = 0
        self._held_pwm: dict[int, int] = {}
        #: PX4: outputs whose latest settled readback showed what they acknowledged (live).
        self._confirmed: set[int] = set()
        #: PX4: store the pose the outputs show now (an output was found not live).
        self._hold_now = False
        #: ArduPilot: the safety switch (None: no SYS_STATUS yet) and BRD_SAFETY_MASK (None:
        #: not read yet; then no output is assumed to be in it).
        self._safety_on: bool | None = None
        self._safety_mask: int | None = None
        #: ArduPilot: per joint, the lowest and highest angle the outputs may hold since the
        #: last SYS_STATUS that said the switch was off (see ``SAFETY_STEPS_AHEAD``; None: no
        #: such SYS_STATUS since the start, a loss or a reboot), and the band's allowed width;
        #: the pose to send the dead outputs back to once the switch was seen on (``_rewind``).
        #: A loss or a reboot forgets them (a rebooted ArduPilot comes back with its switch at
        #: BRD_SAFETY_DEFLT).
        self._band: tuple[list[float], list[float]] | None = None
        #: ArduPilot, after a loss or a reboot until every output is acknowledged again: the
        #: band of poses the outputs may hold from before it (the re-send among them).
        self._loss_band: tuple[list[float], list[float]] | None = None
        step_deg = config.joint_speed_deg_s / config.rate_hz
        steps = SAFETY_STEPS_AHEAD
        if self._sys_status_interval_s > SYS_STATUS_INTERVAL_S:  # a slow serial line
            steps = max(steps, math.ceil(self._sys_status_interval_s * config.rate_hz - 1e-9))
        self._band_deg = max(step_deg * steps, config.joint_speed_deg_s * SAFETY_BAND_MIN_S)
        #: A motion step waited for a SYS_STATUS (the band): it goes out when one comes.
        self._band_held = False
        self._rewind_to: tuple[float, ...] | None = None
        self._sys_status_asked_s = clock()
        self._sys_status_s: float | None = None  # when the last SYS_STATUS came (None: none)
        #: A SYS_STATUS came from this autopilot once: it streams them, so the arm never moves
        #: without one (a stream lost in a reboot is asked for again instead).
        self._sys_status_ever = False
        self._sys_status_warned = False
        #: PX4: armed, from its HEARTBEAT (None: no HEARTBEAT yet). Shown, not relied on:
        #: prearmed outputs are live while disarmed.
        self._armed: bool | None = None
        self.counters = {
            "targets": 0,
            "solved": 0,
            "accepted": 0,
            "denied": 0,
            "failed": 0,
            "temporarily_rejected": 0,
            "cancelled": 0,
            "servo_updates": 0,
            "servo_errors": 0,
            "refused_outputs": 0,
            "foreign_frames": 0,
            "autopilot_reboots": 0,
            "internal_errors": 0,
            "keepout_refusals": 0,
        }
        self.last_target: dict[str, Any] | None = None
        self._hand_at: tuple[tuple[float, ...], dict[str, float]] | None = None
        #: (kind, source) → (when its last "accepted" line was logged, how many since)
        self._accept_log: dict[tuple[str, Any], tuple[float, int]] = {}
        # -- keep-out volumes (issue 18), prepared once per config --
        self._keepout_of: DaemonConfig | None = None
        self._keepout_obj: KeepOut | None = None
        # -- world-frame targets (issue 18) --
        self._telemetry = VehicleTelemetry()
        #: The target held in the world (None: none), and what following it last found.
        self._world: Target | None = None
        self._world_note: dict[str, Any] = {}
        self._world_matrix: tuple[Target, Any] | None = None  # the target's 4×4, once
        #: Recent updates' round trips (s), for the link's one-way latency.
        self._round_trips: collections.deque[float] = collections.deque(maxlen=32)
        self._mount_cache: tuple[Any, Any] | None = None

    # -- events -----------------------------------------------------------------------------

    def request(self, request: Request) -> list[Action]:
        """A request taken from the intake (``goto``, ``trajectory``, ``park``, ``stop``)."""
        actions: list[Action] = []
        if request.answered:  # withdrawn or answered meanwhile: never carried out
            return actions
        if request.kind == "stop":
            self._stop_motion(actions, Reply(Outcome.CANCELLED, "stopped before it moved"))
            self._answer(actions, request, Reply(Outcome.ACCEPTED, "holding"))
            return actions
        if request.kind == "goto":
            self.counters["targets"] += 1
        try:
            parsed = self._parse(request)
        except (TypeError, ValueError, OverflowError) as exc:
            self._answer(actions, request, Reply(Outcome.DENIED, str(exc)))
            return actions
        if not self._link_up:
            self._answer(
                actions, request, Reply(Outcome.TEMPORARILY_REJECTED, "autopilot link down")
            )
            return actions
        superseded = Reply(Outcome.CANCELLED, f"superseded by a {request.kind}")
        if request.kind == "park":
            self._stop_motion(actions, superseded)
            if request.direct:
                self._send_direct(actions, tuple(parsed))
            self._accept(actions, request, tuple(parsed), Reply(Outcome.ACCEPTED, "parking"))
        elif request.kind == "trajectory":
            self._stop_motion(actions, superseded)
            self._trajectory = parsed
            self._trajectory_t0 = self.clock()
            self._answer(
                actions, request, Reply(Outcome.ACCEPTED, f"trajectory of {len(parsed)} points")
            )
            self._due_trajectory_point(actions)
        else:
            self._goto(actions, request, parsed)
        self._maybe_send(actions, immediate=True)
        return actions

    def frame(self, msg: Any, received_s: float | None = None) -> list[Action]:
        """A frame from the link (see ``service.CORE_FRAMES``), received at ``received_s``
        (default: now; the vehicle's telemetry is dated from it)."""
        actions: list[Action] = []
        kind = msg.get_type()
        source = (msg.get_srcSystem(), msg.get_srcComponent())
        if kind == "HEARTBEAT":
            if not is_autopilot_heartbeat(msg):
                return actions
            if self._pinned is None:
                self._pin(source)
            elif source != self._pinned:
                self.counters["foreign_frames"] += 1
                return actions
            if source == self._pinned:
                self._armed = bool(msg.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED)
                self._after_silence(actions)
            return actions
        if source != self._pinned:
            self.counters["foreign_frames"] += 1
            return actions
        self._after_silence(actions)
        if kind == "COMMAND_ACK":
            if msg.target_component in (0, self.config.link.component_id):
                self._heard_us = True  # it answered us: it knows our route
                # Counted in order: the oldest update still short of ACKs takes it (the
                # autopilot answers one link's commands in the order they came); once all
                # are complete, the newest counts it as one too many.
                at_s = self.clock() if received_s is None else received_s
                for flight in self._flights:
                    if not flight.tracker.complete or flight is self._flights[-1]:
                        flight.tracker.on_ack(msg.command, msg.result, at_s)
                        break
                self._poll_update(actions)
        elif kind == "STATUSTEXT":
            text = msg.text
            if isinstance(text, bytes | bytearray):
                text = text.decode("ascii", "replace")
            for flight in self._flights:
                flight.tracker.on_statustext(str(text))
        elif kind == "SYSTEM_TIME":
            self._on_system_time(actions, int(msg.time_boot_ms))
        elif kind == "SERVO_OUTPUT_RAW":
            self._on_readback(msg, self.clock() if received_s is None else received_s)
            if self._hold_now:
                self._maybe_send(actions, immediate=True)
        elif kind == "SYS_STATUS":
            enabled = msg.onboard_control_sensors_enabled
            self._on_sys_status(actions, not enabled & mavlink.MAV_SYS_STATUS_SENSOR_MOTOR_OUTPUTS)
        elif kind in ("ATTITUDE", "LOCAL_POSITION_NED"):
            self._telemetry.on_frame(msg, self.clock() if received_s is None else received_s)
        elif kind == "PARAM_VALUE" and _param_name(msg.param_id) == "BRD_SAFETY_MASK":
            # From the pinned autopilot, but a frame forged as it (no signing) may say NaN.
            value = msg.param_value
            self._safety_mask = int(value) if math.isfinite(value) and value >= 0 else None
        return actions

    def tick(self, link_up: bool, autopilot: tuple[int, int] | None = None) -> list[Action]:
        """Periodic work; call at least every :meth:`next_wake_s`, and whenever the link's
        state may have changed. ``autopilot``: the ids the link latched, if it did (it hears
        the first HEARTBEAT a moment before this core does)."""
        actions: list[Action] = []
        now = self.clock()
        if self._pinned is None and autopilot is not None:
            self._pin(autopilot)
        # The link may report UP a moment before its HEARTBEAT reached us: pinned first.
        self._set_link(actions, link_up and self._pinned is not None)
        due = now >= self._next_tick_s
        if due:  # also while the link is down: the next wake is a period away, not now
            period = 1.0 / self.config.rate_hz
            self._next_tick_s = max(self._next_tick_s + period, now)
        if not self._link_up:
            return actions
        self._poll_update(actions)
        self._watch_system_time(actions, now)
        self._watch_sys_status(actions, now)
        self._watch_readback(actions, now)
        if due:
            if self._trajectory:
                self._due_trajectory_point(actions)
            elif self._world is not None:
                self._follow_world()
            self._maybe_send(actions, immediate=False)
        return actions

    def next_wake_s(self) -> float:
        """When :meth:`tick` next has something to do (daemon clock)."""
        wake = self._next_tick_s
        for flight in self._flights:
            wake = min(wake, flight.tracker.next_event_s())
        return wake

    def acks_to_progress(self) -> int:
        """How many more servo COMMAND_ACKs may arrive before one of them changes anything:
        the oldest update short of ACKs decides nothing until its count is complete
        (:meth:`UpdateTracker.poll`); 1 when none is short (the driver may then wake for
        each)."""
        for flight in self._flights:
            if not flight.tracker.complete:
                return max(1, flight.tracker.acks_missing)
        return 1

    def ack_wake_wanted(self) -> bool:
        """Whether the ACK that completes an update (:meth:`acks_to_progress`) must be taken
        at once: nothing is in flight (an ACK then is one too many), a request waits on an
        update in flight (its answer) or to go out behind it, or an update is being confirmed
        one command at a time. Otherwise it changes nothing before the next tick, which takes
        it first (an update's time is its last ACK's reception, not when it is taken), and the
        driver need not wake for it: following a world target or a trajectory, one wake a
        tick fewer."""
        if self._waiting or not self._flights:
            return True
        return any(f.waiting or f.pending or f.attempt for f in self._flights)

    def shutdown(self, *, park: bool) -> list[Action]:
        """Stop: answer everything waiting, and send the park pose directly if asked."""
        actions: list[Action] = []
        self._stop_motion(actions, Reply(Outcome.CANCELLED, "daemon stopping"))
        if park and self.config.park_deg is not None and self._link_up:
            # Little time is left: a lost frame is sent again after SHUTDOWN_RETRY_S, not
            # after command_timeout_s.
            timeout_s = min(self.config.link.command_timeout_s, SHUTDOWN_RETRY_S)
            self._send_direct(actions, tuple(self.config.park_deg), force=True, timeout_s=timeout_s)
        return actions

    @property
    def link_up(self) -> bool:
        return self._link_up

    def brief(self) -> tuple[bool, int, int, int]:
        """A few figures of :meth:`status`, cheap enough to take every step: whether the
        autopilot answered us on a link that is up, and the targets accepted, failed and
        denied."""
        counters = self.counters
        return (
            self._link_up and self._heard_us,
            counters["accepted"],
            counters["failed"],
            counters["denied"],
        )

    def finish(self) -> list[Action]:
        """The daemon exits now: whatever still waits on an update is answered."""
        actions: list[Action] = []
        for flight in self._flights:
            for w in flight.waiting:
                self._answer(actions, w.request, Reply(Outcome.FAILED, "daemon stopped"))
        self._flights.clear()
        return actions

    def internal_error(self, reply: Reply) -> list[Action]:
        """A bug under the driving thread: stop moving, hold (the servos keep their last
        PWM), answer every waiting target with ``reply``; the outputs of an update in flight
        are re-sent before anything moves again."""
        actions: list[Action] = []
        self.counters["internal_errors"] += 1
        flights = list(self._flights)
        self._flights.clear()
        for inflight in flights:
            for w in inflight.waiting:
                self._answer(actions, w.request, reply)
            for output in inflight.sent_outputs:
                self._acked_pwm.pop(output, None)
        if flights:
            self._unconfirmed = tuple(self._position)
        self._stop_motion(actions, reply)
        return actions

    def parked(self) -> bool:
        """Every output acknowledged at the park pose."""
        park = self.config.park_deg
        return park is not None and self._settled() and tuple(self._position) == tuple(park)

    @property
    def idle(self) -> bool:
        """No update in flight."""
        return not self._flights

    # -- requests ---------------------------------------------------------------------------

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

    def _goto(self, actions: list[Action], request: Request | None, target: Target) -> bool:
        pose = target.pose
        if target.frame != "base":
            refusal = self._world_refusal(target)
            in_base = None if refusal is not None else self._world_in_base(target)
            if in_base is None:
                if request is not None:
                    self._answer(
                        actions,
                        request,
                        refusal or Reply(Outcome.TEMPORARILY_REJECTED, self._world_note["reason"]),
                    )
                return False
            pose = in_base
        start = self._goal if self._goal is not None else tuple(self._position)
        result, failure = self._solve_target(pose, start, target.mode, None)
        self.counters["solved"] += 1
        timing = {
            "received_s": request.received_s if request is not None else self.clock(),
            "solved_s": self.clock(),
        }
        self.last_target = {
            "pose": list(pose.as_tuple()),
            "mode": target.mode,
            "converged": result is not None and result.converged,
            "pos_err_cm": None if result is None else result.pos_err_cm,
            "ori_err_deg": None if result is None else result.ori_err_deg,
            "solve_ms": None if result is None else result.elapsed_ms,
            "timing": timing,
        }
        if failure is None and result is not None and not result.converged:
            failure = f"unreachable: pos {result.pos_err_cm:.2f}cm ori {result.ori_err_deg:.1f}deg"
        if failure is None and result is not None:
            hit = self._keepout_hit(result.q_deg)  # solve_clear's answer, checked once more
            if hit is not None:
                self.counters["keepout_refusals"] += 1
                failure = f"keep-out: the solution {hit}"
        if failure is not None or result is None:
            reply = Reply(Outcome.FAILED, failure or "no solution", result)
            if request is not None:
                self._answer(actions, request, reply)
            else:
                log.warning("trajectory point refused: %s", reply.message)
            return False
        try:
            self.config.calibration.angles_to_pwm_us(result.q_deg)
        except CalibrationError as exc:  # the config check makes this unreachable; stay safe
            if request is not None:
                self._answer(
                    actions, request, Reply(Outcome.FAILED, f"calibration refused: {exc}", result)
                )
            return False
        if request is None:
            self._goal = tuple(result.q_deg)
        else:
            superseded = Reply(Outcome.CANCELLED, "superseded by a newer target")
            self._stop_motion(actions, superseded)
            message = "moving" if target.frame == "base" else "moving; held in LOCAL_NED"
            self._accept(
                actions, request, result.q_deg, Reply(Outcome.ACCEPTED, message, result, timing)
            )
            if target.frame != "base":
                self._world = target
                self._world_note = {"reachable": True, "reason": None}
        return True

    def _accept(
        self, actions: list[Action], request: Request, goal: Sequence[float], reply: Reply
    ) -> None:
        self._goal = tuple(float(g) for g in goal)
        if tuple(self._position) == self._goal and self._settled():
            self._answer(actions, request, reply)  # already there: nothing to send
            return
        dead = self._dead_outputs()
        if dead:
            # Its first step would wait for outputs that may stay dead for hours: the answer
            # comes now, and says the arm moves once they are live.
            self._answer(actions, request, _not_live_reply(reply, dead))
            return
        self._waiting.append(_Waiting(request, reply))

    def _stop_motion(self, actions: list[Action], reply: Reply) -> None:
        """Forget the goal; targets whose first step has not gone out get ``reply``. Those
        already on their way are answered when their update resolves."""
        self._goal = None
        self._trajectory.clear()
        self._world = None
        for w in self._waiting:
            self._answer(actions, w.request, reply)
        self._waiting.clear()

    def _due_trajectory_point(self, actions: list[Action]) -> None:
        elapsed = self.clock() - self._trajectory_t0
        due = [p for p in self._trajectory if p[0] <= elapsed]
        if not due:
            return
        self._trajectory = self._trajectory[len(due) :]
        if not self._goto(actions, None, Target(due[-1][1])):
            log.warning("trajectory aborted: a point is out of reach")
            self._trajectory.clear()

    # -- updates ----------------------------------------------------------------------------

    def _settled(self) -> bool:
        return (
            self._unconfirmed is None
            and not self._flights
            and all(o in self._acked_pwm or o in self._refused for o in self._outputs)
        )

    def _maybe_send(self, actions: list[Action], *, immediate: bool) -> None:
        """Start the next update if one is due. ``immediate``: only if a newly accepted target
        waits (its first step does not wait for the next tick).

        With an update in flight, the next one may go out behind it (``_pipeline``), so a
        target does not wait out the round trip of the step before it (on a 115 200-baud line
        an update takes 13–21 ms of a 20 ms slot)."""
        if not self._link_up:
            return
        if self._hold_now and not self._is_ardupilot:
            # PX4 outputs found not live: their markers stored now, behind whatever is on its
            # way (PX4 takes the frames in order), before a re-arm would bring out the pose
            # stored before.
            self._hold_now = False
            self._unconfirmed = None
            self._send_step(
                actions, tuple(self._position), self.clock(), everything=True, hold=True
            )
            return
        if immediate and not self._waiting:
            return
        if self._flights:
            self._pipeline(actions)
            return
        now = self.clock()
        if not self._outputs_known(now):
            return
        if self._is_ardupilot:
            if not self._safety_known(now):
                return
            dead = self._dead_outputs()
            if dead and self._rewind_to is not None:
                self._rewind(actions, dead, now)
            if dead:
                # The safety switch: whatever is sent is applied at once when it goes off.
                return
        else:
            if not self._confirmed.issuperset(self._outputs):
                # Outputs not known to be live: one speed-limited step at a time, the next only
                # once the readback showed it (found not live: once it shows its marker, or
                # with no marker, once a PROBE_INTERVAL_S): if they come alive meanwhile, they
                # jump by at most that one step.
                if self._not_live:
                    if self._markers_held() or now - self._last_step_s < PROBE_INTERVAL_S:
                        return
                elif self._unmarked_unknown():
                    # The start, a loss or a reboot: the markers say whether the outputs are
                    # live, moving each joint by MARKER_OFFSET_US; the motion waits for that.
                    # (A motion step could leave an output at the disarmed PWM it shows, and
                    # a readback of that would prove nothing.)
                    # (hold: 2 us from what the outputs show, no keep-out path to check; a
                    # disarmed PWM inside a volume would refuse it at every tick.)
                    self._send_step(actions, self._marker_pose(), now, hold=True)
                    return
                elif (
                    any(o in self._acked_pwm for o in self._outputs if o not in self._confirmed)
                    and now - self._last_step_s < VERDICT_TIMEOUT_S
                ):
                    return  # the readback's verdict on the step before is not in yet
        if self._unconfirmed is not None:
            if not (self._resend_now or self._goal is not None or self._waiting):
                return  # an unanswered step is tried again when there is somewhere to go
            self._resend_now = False
            step = self._unconfirmed
        else:
            goal = self._goal
            if goal is None or (goal == tuple(self._position) and self._settled()):
                return
            period = 1.0 / self.config.rate_hz
            max_step_deg = self.config.joint_speed_deg_s * min(period, now - self._last_step_s)
            if not max_step_deg > 0:
                return
            step = limit_step(self._position, goal, max_step_deg)
            if not self._may_step_to(step):
                return  # no SYS_STATUS said the switch is off since the steps before
        self._send_step(actions, step, now)

    def _unmarked_unknown(self) -> bool:
        """PX4: an output with nothing acknowledged since the start, a loss or a reboot, and
        none on its way (its liveness unknown: a marker would tell)."""
        ahead = {o for f in self._flights for o in f.sent_outputs}
        return any(
            o not in self._acked_pwm and o not in ahead and o in self._readback
            for o in self._outputs
        )

    def _marker_pose(self) -> tuple[float, ...]:
        """The pose with each output that has nothing acknowledged at its marker (from the PWM
        the readback shows), the others where they are."""
        pose = list(self._position)
        for i, output in enumerate(self._outputs):
            shown = self._readback.get(output)
            if output not in self._acked_pwm and shown is not None:
                pose[i] = self._marker_deg(output, shown)
        return tuple(pose)

    def _pipeline(self, actions: list[Action]) -> None:
        """Send the next step behind the update in flight, without waiting for its ACKs.

        Only in the plain case: one update in flight (PIPELINE_DEPTH), in its first attempt,
        every output acknowledged before it (none unknown after a loss, a reboot or an update
        that ended unanswered), every output live (and, on PX4, confirmed live by the
        readback).
        The step is computed from the one in flight (as if acknowledged) at the speed limit,
        and it **re-sends every output the updates ahead of it sent**, at its own values: the
        ACKs are counted in order (:mod:`firmware_interface.updates`), so if one ahead ends
        unanswered or miscounted, this one's outcome alone says where those outputs are
        (see :meth:`_poll_update`)."""
        last = self._flights[-1]
        if (
            len(self._flights) >= PIPELINE_DEPTH
            or last.attempt
            or last.pending
            or self._unconfirmed is not None
            or not self._acked_pwm.keys() >= set(self._outputs)
            or self._dead_outputs()
        ):
            return
        now = self.clock()
        if last.tracker.poll(now) is not None:
            return  # its verdict is in (or its time is up): resolved first, then we go on
        if not self._is_ardupilot and (
            self._hold_now or not self._confirmed.issuperset(self._outputs)
        ):
            return
        goal = self._goal
        if goal is None or goal == last.step_deg:
            return
        period = 1.0 / self.config.rate_hz
        max_step_deg = self.config.joint_speed_deg_s * min(period, now - self._last_step_s)
        if not max_step_deg > 0:
            return
        step = limit_step(last.step_deg, goal, max_step_deg)
        if not self._may_step_to(step):
            return
        ahead = {o for f in self._flights for o in f.sent_outputs}
        base = {o: pwm for o, pwm in self._acked_pwm.items() if o not in ahead}
        self._send_step(actions, step, now, base_pwm=base)

    def _on_sys_status(self, actions: list[Action], safety_on: bool) -> None:
        """ArduPilot's safety switch, as a SYS_STATUS says (see ``SAFETY_STEPS_AHEAD``)."""
        self._sys_status_s = self.clock()
        self._sys_status_ever = True
        if not self._is_ardupilot:
            self._safety_on = safety_on
            return
        if safety_on != self._safety_on:
            log.warning("safety switch %s", "on: outputs not live" if safety_on else "off")
            if safety_on and self._band is not None:
                self._rewind_to = self._band_middle()
            elif not safety_on:
                self._rewind_to = None
        self._safety_on = safety_on
        if safety_on:
            return
        # Off now: the outputs hold what was acknowledged, or a step still on its way (or one
        # whose update ended unanswered: it is sent again before anything else).
        poses = [f.step_deg for f in self._flights]
        if self._unconfirmed is not None:
            poses.append(self._unconfirmed)
        if self._loss_band is not None:  # what they held before is unknown: that band
            poses += [tuple(self._loss_band[0]), tuple(self._loss_band[1])]
        else:
            poses.append(tuple(self._position))
        self._band = _band_of(poses)
        if self._band_held and self._link_up:
            self._band_held = False
            self._maybe_send(actions, immediate=False)  # the step held back for this

    def _band_middle(self) -> tuple[float, ...]:
        assert self._band is not None
        return _middle(self._band)

    def _may_step_to(self, step: tuple[float, ...]) -> bool:
        """ArduPilot: a motion step to ``step`` keeps the poses the outputs may hold since the
        last SYS_STATUS that said the switch is off within ``SAFETY_STEPS_AHEAD`` (always true
        when none came since the start, a loss or a reboot: see ``_safety_known``)."""
        if not self._is_ardupilot or self._band is None:
            return True
        low, high = self._band
        width = self._band_deg + 1e-9
        ok = all(
            max(hi, a) - min(lo, a) <= width for lo, hi, a in zip(low, high, step, strict=True)
        )
        self._band_held = not ok
        return ok

    def _stepped_to(self, step: tuple[float, ...]) -> None:
        """A step to ``step`` went out: the outputs may hold it (ArduPilot's band)."""
        if self._band is None:
            return
        low, high = self._band
        for i, a in enumerate(step):
            low[i], high[i] = min(low[i], a), max(high[i], a)

    def _forget_safety(self) -> None:
        """ArduPilot, a loss or a (possible) reboot: the switch is unknown until a SYS_STATUS
        says (it boots at BRD_SAFETY_DEFLT), and no pose from before is rewound to."""
        self._safety_on = None
        self._sys_status_s = None
        self._band = self._rewind_to = None

    def _resend_pose(self, flights: Sequence[_InFlight]) -> tuple[float, ...]:
        """ArduPilot, after a loss or a reboot: the pose to send every output to again, within
        one step of anything they may hold. The switch seen on: the pose they were sent back to
        (nothing moved since). Else the middle of the band of poses they may hold since the
        last SYS_STATUS that said off (``SAFETY_STEPS_AHEAD``: the switch may have gone on
        since), or with none, the oldest step that was on its way (they hold it, the
        acknowledged pose, or the step behind it)."""
        if self._safety_on is True and self._rewind_to is not None:
            return self._rewind_to  # seen on, not sent back yet
        if self._safety_on is not True and self._band is not None:
            return self._band_middle()
        if self._loss_band is not None:  # lost again before the re-send was acknowledged
            return _middle(self._loss_band)
        return flights[0].step_deg if flights else tuple(self._position)

    def _forget_outputs(self, flights: Sequence[_InFlight]) -> tuple[float, ...] | None:
        """ArduPilot, a loss or a (possible) reboot: what the outputs may hold is kept as
        ``_loss_band``, the switch forgotten; the pose to send them to again (None: nothing
        was ever sent)."""
        if not (flights or self._last_step_s > -math.inf):
            self._forget_safety()
            return None
        resend = self._resend_pose(flights)
        if self._band is not None:
            poses = [tuple(self._band[0]), tuple(self._band[1])]
        elif self._loss_band is not None:
            poses = [tuple(self._loss_band[0]), tuple(self._loss_band[1])]
        else:
            poses = [tuple(self._position)] + [f.step_deg for f in flights]
        self._loss_band = _band_of([*poses, resend])
        self._forget_safety()
        return resend

    def _rewind(self, actions: list[Action], dead: dict[int, str], now: float) -> None:
        """ArduPilot, the safety switch seen on: it went on at some moment since the SYS_STATUS
        before, and its outputs have held since then what they had; the steps sent meanwhile
        are stored and would go out in one step at its release. The dead outputs are sent back
        to the pose commanded at that SYS_STATUS (within one SYS_STATUS interval of motion of
        what they hold), and the motion goes on from there once the switch is off."""
        rewind, self._rewind_to = self._rewind_to, None
        assert rewind is not None
        current = list(self._position)
        step = tuple(
            rewind[i] if output in dead else current[i] for i, output in enumerate(self._outputs)
        )
        if step != tuple(current) or not self._settled():
            log.info("safety switch on: the held outputs sent back to where they stopped")
            self._send_step(actions, step, now)

    def _safety_known(self, now: float) -> bool:
        """ArduPilot: a SYS_STATUS said where the safety switch is since the start, the last
        loss or reboot (or none came for SYS_STATUS_WAIT_S, which is said once)."""
        if self._safety_on is not None:
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

    def _outputs_known(self, now: float) -> bool:
        """PX4: a readback since the start, link loss or reboot tells where the joints are;
        without one for READBACK_WAIT_S, go on from the acknowledged pose (and say so once)."""
        if self._is_ardupilot or self._readback_s >= self._readback_since_s:
            return True
        if now - self._readback_since_s < READBACK_WAIT_S:
            return False
        if not self._readback_warned:
            self._readback_warned = True
            log.warning(
                "no SERVO_OUTPUT_RAW from the autopilot in %.0f s: moving from the pose last "
                "acknowledged; outputs that come alive later may jump to it",
                READBACK_WAIT_S,
            )
        return True

    def _send_step(
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
        acknowledged PWMs) already holds are left out, unless ``everything``. ``hold``: PX4's
        outputs told to hold their markers (found not live, or not known to be): no keep-out
        path from the step commanded last (the outputs are where the readback shows them, and
        the marker is within MARKER_OFFSET_US of it)."""
        if base_pwm is None:
            base_pwm = self._acked_pwm
        try:
            pwm = self.config.calibration.angles_to_pwm_us(step)
            commands = self._dialect.plan(pwm, None if everything else base_pwm)
        except CalibrationError as exc:  # unreachable by construction; refuse, never clamp
            log.error("calibration refused a step, holding: %s", exc)
            self._fail_motion(actions, f"calibration refused a step: {exc}")
            return
        keepout = None if hold else self._keepout()
        if keepout is not None:
            # The motion from the step commanded last (what the outputs will hold) to this one,
            # proven clear of every volume, or not sent. As the servos get it: each angle
            # through its PWM rounded to whole µs (a 60 cm link moves up to ~0.05 cm with the
            # rounding), and each command's outputs changing in the order sent (ArduPilot: one
            # output a command, so not the straight line; at 180 deg/s and 100 Hz its corners
            # came 0.09 cm into the margin in bench.keepout_daemon).
            before = self._flights[-1].step_deg if self._flights else tuple(self._position)
            path = self._output_path(self._as_sent_rad(before), self._as_sent_rad(step), commands)
            collision = keepout.check_path(path)
            if collision is not None:
                self.counters["keepout_refusals"] += 1
                log.error("keep-out: a step refused, holding: %s", collision.reason)
                self._fail_motion(actions, f"keep-out: {collision.reason}")
                return
        waiting, self._waiting = self._waiting, []
        if not commands:  # every output already holds this step
            if self._flights:  # (behind an update: it already carries this step)
                self._flights[-1].waiting.extend(waiting)
                return
            self._position = list(step)
            self._unconfirmed = None
            for w in waiting:
                self._answer(actions, w.request, w.reply)
            return
        if timeout_s is None:
            timeout_s = self.config.link.command_timeout_s
        tracker = UpdateTracker(commands, sent_s=now, timeout_s=timeout_s)
        sent = frozenset(o for c in commands for o in c.outputs)
        self._flights.append(
            _InFlight(step, pwm, sent, tracker, now, waiting, timeout_s, seq=self._updates_sent)
        )
        self._updates_sent += 1
        self._last_step_s = now
        self._stepped_to(step)
        self._emit(actions, commands, 0)

    def _send_direct(
        self,
        actions: list[Action],
        step: tuple[float, ...],
        *,
        force: bool = False,
        timeout_s: float | None = None,
    ) -> None:
        """Everything to ``step`` at once, past the speed limit (park on shutdown)."""
        # Their answers would be counted into this update; the autopilot handles frames in
        # order, so the direct step lands last whatever happens to those in flight.
        for flight in self._flights:
            for w in flight.waiting:
                self._answer(
                    actions,
                    w.request,
                    Reply(Outcome.FAILED, "interrupted by a park before it was confirmed"),
                )
            for o in flight.sent_outputs:
                self._acked_pwm.pop(o, None)
        self._flights.clear()
        self._unconfirmed = None
        self._send_step(actions, step, self.clock(), everything=force, timeout_s=timeout_s)

    def _emit(self, actions: list[Action], commands: list[ServoCommand], attempt: int) -> None:
        assert self._pinned is not None  # the link is up only once an autopilot was heard
        for c in commands:
            actions.append(SendCommand(self._pinned, c.command, c.params, attempt))

    def _poll_update(self, actions: list[Action]) -> None:
        now = self.clock()
        while self._flights:
            inflight = self._flights[0]
            outcome = inflight.tracker.poll(now)
            if outcome is None:
                return
            if len(self._flights) > 1 and (outcome.unknown or outcome.state is UpdateState.UNKNOWN):
                self._fold_into_next(actions, inflight, outcome.reason)
                continue
            if len(self._flights) > 1:
                inflight.accepted.update(outcome.accepted)
                inflight.refused.update(outcome.refused)
                self._resolve_update(actions, inflight, now)
                continue
            self._poll_last(actions, inflight, outcome, now)
            return

    def _fold_into_next(self, actions: list[Action], inflight: _InFlight, reason: str) -> None:
        """An update with one behind it ended unanswered (or miscounted): the one behind
        re-sent every output it sent, so its outcome will say where they are. Until then they
        are unknown; the targets whose first step it was wait on the one behind."""
        self._flights.popleft()
        log.info("servo update unconfirmed (%s); the update behind it decides", reason)
        for output in inflight.sent_outputs:
            self._acked_pwm.pop(output, None)
        self._flights[0].waiting[:0] = inflight.waiting
        self._flights[0].folded[:0] = [*inflight.folded, inflight.step_deg]
        self.counters["servo_errors"] += 1

    def _poll_last(
        self, actions: list[Action], inflight: _InFlight, outcome: UpdateOutcome, now: float
    ) -> None:
        """The outcome of the only update in flight: resolve it, or confirm what it left
        unknown one command at a time."""
        inflight.accepted.update(outcome.accepted)
        inflight.refused.update(outcome.refused)
        unknown = set(outcome.unknown)
        commands = inflight.tracker.commands
        if unknown:
            # Each command is sent at most 1 + command_retries times: once in the batch, then
            # alone until its ACK comes.
            retry = [c for c in commands if unknown.intersection(c.outputs)]
            if inflight.folded and inflight.attempt < self.config.link.command_retries:
                retry = self._retry_between(inflight, unknown) or retry
            if inflight.attempt < self.config.link.command_retries:
                inflight.pending = retry + inflight.pending
                inflight.attempt += 1
            else:
                names = sorted({command_name(c.command) for c in retry})
                outputs = sorted(o for c in retry for o in c.outputs)
                reason = (
                    f"no COMMAND_ACK for {', '.join(names)} to output(s) "
                    f"{', '.join(map(str, outputs))} after {inflight.attempt + 1} attempts of "
                    f"timeout_s={self.config.link.command_timeout_s:g}"
                )
                self._resolve_update(actions, inflight, now, unknown=reason)
                return
            log.info("servo update unconfirmed (%s), confirming one at a time", outcome.reason)
        elif inflight.pending:
            inflight.attempt = 1
        if inflight.pending:
            command = inflight.pending.pop(0)
            inflight.tracker = UpdateTracker([command], sent_s=now, timeout_s=inflight.timeout_s)
            self._emit(actions, [command], inflight.attempt)
            return
        self._resolve_update(actions, inflight, now)

    def _folded_poses(self, inflight: _InFlight) -> list[tuple[float, ...]]:
        """What outputs left unknown by ``inflight`` may hold: the acknowledged pose, a step
        folded into it, or its own step (each a step from the one before)."""
        return [tuple(self._position), *inflight.folded, inflight.step_deg]

    def _retry_between(self, inflight: _InFlight, unknown: set[int]) -> list[ServoCommand]:
        """An update with the steps of updates ahead of it folded into it left ``unknown``
        outputs: they hold the acknowledged pose, one of those steps or this one (two steps
        apart at most). They are confirmed at the middle of those poses, within one step of
        each, rather than at this step; the flight's step becomes that (the outputs it
        confirmed keep theirs)."""
        poses = self._folded_poses(inflight)
        middle = _middle(_band_of(poses))
        step = tuple(
            middle[i] if output in unknown else inflight.step_deg[i]
            for i, output in enumerate(self._outputs)
        )
        try:
            pwm = self.config.calibration.angles_to_pwm_us(step)
            commands = self._dialect.plan(pwm, None)
        except CalibrationError:  # within the hull of steps already checked: unreachable
            return []
        keepout = self._keepout()
        if keepout is not None:
            # The middle was never a commanded step: the motion to it from every pose the
            # outputs may hold is proven clear, or the step's own commands are tried again.
            target = self._as_sent_rad(step)
            for held in poses:
                path = self._output_path(self._as_sent_rad(held), target, commands)
                if keepout.check_path(path) is not None:
                    return []
        inflight.step_deg, inflight.pwm_by_output, inflight.folded = step, pwm, []
        self._stepped_to(step)
        return [c for c in commands if unknown.intersection(c.outputs)]

    def _resolve_update(
        self, actions: list[Action], inflight: _InFlight, now: float, *, unknown: str = ""
    ) -> None:
        """Every command of the update has its verdict (or ``unknown`` says why not)."""
        assert self._flights and self._flights[0] is inflight
        self._flights.popleft()
        joint_of = {o: i for i, o in enumerate(self._outputs)}
        # PX4 outputs found not live since this update went out hold their markers, stored
        # behind it: what it stored there is no pose of theirs (nor of the joints').
        overtaken = {
            o for o, seq in self._dead_seq.items() if inflight.seq < seq and o in self._not_live
        }
        for output, pwm in inflight.accepted.items():
            if output in overtaken:
                continue
            self._acked_pwm[output] = pwm
            self._ack_history.setdefault(output, collections.deque(maxlen=64)).append((now, pwm))
            self._mismatches[output] = 0
            self._refused.pop(output, None)
            self._position[joint_of[output]] = inflight.step_deg[joint_of[output]]
        settled = set(inflight.accepted) | set(inflight.refused)
        for output in inflight.sent_outputs - settled:
            self._acked_pwm.pop(output, None)
        timing = {"first_out_s": inflight.sent_s, "acked_s": now}
        if inflight.refused:
            self._unconfirmed = None
            self._unanswered = 0
            self._refused.update(inflight.refused)
            self.counters["refused_outputs"] += len(inflight.refused)
            reason = "; ".join(
                f"servo output {o} refused by the autopilot: {why}"
                for o, why in sorted(inflight.refused.items())
            )
            hint = " ".join(
                f"Set SERVO{o}_FUNCTION = 0 on the flight controller."
                for o in sorted(inflight.refused)
                if self._is_ardupilot
            )
            log.error("%s; motion stopped. %s", reason, hint)
            first = min(inflight.refused)
            more = f"+{len(inflight.refused) - 1}" if len(inflight.refused) > 1 else ""
            brief = (
                f"Arm: set SERVO{first}_FUNCTION=0{more} (output in use)"
                if self._is_ardupilot
                else f"Arm: output {first}{more} refused by the autopilot"
            )
            for w in inflight.waiting:
                reply = Reply(Outcome.FAILED, f"{reason}. {hint}".strip(), brief=brief)
                self._answer(actions, w.request, reply)
            self._fail_motion(actions, reason)
            return
        if not unknown:
            self._unconfirmed = None
            self._unanswered = 0
            if all(o in self._acked_pwm or o in self._refused for o in self._outputs):
                self._loss_band = None  # they hold what was acknowledged
            self.counters["servo_updates"] += 1  # acknowledged in full
            if inflight.attempt == 0:
                done_s = inflight.tracker.complete_s
                self._round_trips.append((now if done_s is None else done_s) - inflight.sent_s)
            self._record_first_out(timing)
            dead = self._dead_outputs()
            for w in inflight.waiting:
                reply = w.reply
                if reply.timing is not None:
                    reply = dataclasses.replace(reply, timing={**reply.timing, **timing})
                if dead:
                    reply = _not_live_reply(reply, dead)
                self._answer(actions, w.request, reply)
            self._maybe_send(actions, immediate=True)
            return
        # Some outputs may or may not have moved: they hold the acknowledged pose, this step
        # or one folded into it (each a step from the one before). A pose within one step of
        # every one of them is sent before moving on: this step, or with steps folded into it,
        # the middle of them all.
        if inflight.folded:
            self._unconfirmed = _middle(_band_of(self._folded_poses(inflight)))
        else:
            self._unconfirmed = inflight.step_deg
        self.counters["servo_errors"] += 1
        self._unanswered += 1
        message = f"servo update unanswered: {unknown}"
        if inflight.waiting or self._unanswered >= UPDATE_ATTEMPTS:
            log.error("%s; motion stopped", message)
            for w in inflight.waiting:
                self._answer(actions, w.request, Reply(Outcome.FAILED, message))
            self._fail_motion(actions, message)
            self._unanswered = 0
        else:
            log.warning(
                "%s (%d of %d), trying again on the next tick",
                message,
                self._unanswered,
                UPDATE_ATTEMPTS,
            )

    def _fail_motion(self, actions: list[Action], reason: str) -> None:
        self._stop_motion(actions, Reply(Outcome.FAILED, f"motion stopped: {reason}"))

    def _record_first_out(self, timing: dict[str, float]) -> None:
        last = self.last_target
        if last is not None and "first_out_s" not in last["timing"]:
            self.last_target = {**last, "timing": {**last["timing"], **timing}}

    # -- the autopilot ----------------------------------------------------------------------

    def _pin(self, source: tuple[int, int]) -> None:
        if all(want in (None, got) for want, got in zip(self._pin_config, source, strict=True)):
            self._pinned = source
            log.info("autopilot %d/%d pinned", *source)

    def _set_link(self, actions: list[Action], up: bool) -> None:
        if up == self._link_up:
            return
        self._link_up = up
        self._heard_us = False  # until it answers the SYSTEM_TIME request sent on link-up
        if not up:
            log.warning("autopilot link lost: holding, no servo commands")
            self._lose_outputs(actions, "autopilot link lost")
        else:
            if self._last_step_s > -math.inf:
                log.info("autopilot link up: re-sending every output before moving on")
            self._ask_system_time(actions)

    def _lose_outputs(self, actions: list[Action], reason: str) -> None:
        """The autopilot's outputs are unknown (link lost, reboot): re-send them all at the
        acknowledged pose before moving on; targets waiting are TEMPORARILY_REJECTED."""
        flights = list(self._flights)
        self._flights.clear()
        rejected = Reply(Outcome.TEMPORARILY_REJECTED, reason)
        unanswered = [w for f in flights for w in f.waiting] + self._waiting
        for w in unanswered:
            self._answer(actions, w.request, rejected)
        self._waiting.clear()
        if unanswered:  # the goal is theirs: never carried out after that answer
            self._goal = None
            self._trajectory.clear()
        self._acked_pwm.clear()
        self._ack_history.clear()
        self._mismatches.clear()
        self._confirmed.clear()
        self._forget_liveness()
        self._telemetry.reset()
        resend = self._forget_outputs(flights)  # ArduPilot: the switch unknown (boots on)
        self._readback_since_s = self.clock()
        if not self._is_ardupilot:
            # PX4 applies what it stores in one step once its outputs are live: re-sending the
            # pose of before would jump from wherever the outputs are now (the disarmed PWM
            # after a reboot). The joints are where the next readback says; the motion goes on
            # from there at the speed limit.
            self._unconfirmed = None
            return
        if resend is not None:
            # The outputs hold what they were last told (see _resend_pose): sent again within
            # one step of it.
            self._unconfirmed = resend
            self._resend_now = True

    def _ask_system_time(self, actions: list[Action]) -> None:
        """Ask for every stream the core reads (an autopilot forgets them when it reboots):
        SYSTEM_TIME (reboots), SERVO_OUTPUT_RAW (what the outputs do) and, from ArduPilot,
        SYS_STATUS (its safety switch) and BRD_SAFETY_MASK."""
        if self._pinned is None:
            return
        self._system_time_asked_s = self.clock()
        streams = stream_requests(
            ardupilot=self._is_ardupilot,
            readback_interval_s=self._readback_interval_s,
            sys_status_interval_s=self._sys_status_interval_s,
            world_telemetry_hz=self.config.world.telemetry_hz
            if self.config.world.enabled
            else None,
        )
        if self._is_ardupilot:
            self._sys_status_asked_s = self.clock()
        for msg_id, interval_s in streams:
            actions.append(
                SendCommand(
                    self._pinned,
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
        if self._is_ardupilot and self._safety_mask is None:
            actions.append(ReadParam(self._pinned, "BRD_SAFETY_MASK"))

    @property
    def _is_ardupilot(self) -> bool:
        return self.config.link.dialect.startswith("ardupilot")

    # -- the outputs' truth (issue 20) -------------------------------------------------------

    def _on_readback(self, msg: Any, received_s: float) -> None:
        """A SERVO_OUTPUT_RAW: what each output does. PX4 shows the PWM it outputs (the
        disarmed PWM until armed or prearmed), so a PX4 output that does not show what it
        acknowledged, READBACK_MISMATCHES times in a row once settled, is not live: the joint
        is where the readback says, and the motion holds (see :meth:`_maybe_send`). ArduPilot
        shows what it was told even with the safety switch on: SYS_STATUS says that."""
        now = self.clock()
        self._readback = {
            n: int(v)
            for n in range(1, 17)
            if (v := getattr(msg, f"servo{n}_raw", 0)) and msg.port == 0
        }
        # When it arrived (the control thread may take it later): the readback's silence
        # (status, READBACK_STALE_INTERVALS) is the link's, not this thread's.
        self._readback_s = received_s
        if self._is_ardupilot:
            return
        joint_of = {o: i for i, o in enumerate(self._outputs)}
        for output in self._outputs:
            shown = self._readback.get(output)
            acked = self._acked_pwm.get(output)
            if shown is None:
                continue
            if acked is None:
                if not self._flights and output not in self._ack_history:
                    # Nothing of ours acknowledged yet (start, reboot): the joint is where the
                    # output puts it, not at the assumed start pose.
                    self._position[joint_of[output]] = self._angle_shown(output, shown)
                continue
            shown_ok, settled = self._expected_pwms(output, now)
            # PX4 applies a command on its output cycle and answers it on its commander's: a
            # readback in between shows a step on its way, not acknowledged yet. It is ours,
            # so the output is live.
            on_its_way = {
                f.pwm_by_output[output] for f in self._flights if output in f.pwm_by_output
            }
            if any(abs(shown - pwm) <= READBACK_TOLERANCE_US for pwm in shown_ok | on_its_way):
                self._mismatches[output] = 0
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
            # A live output that stops showing what it acknowledged long ago was disarmed,
            # killed or rebooted: no second look (PX4 would apply our stored pose at once on
            # a quick re-arm). After a new command, READBACK_MISMATCHES (the readback lags).
            needed = 1 if output in self._confirmed else READBACK_MISMATCHES
            self._confirmed.discard(output)
            if output in self._not_live and acked == self._held_pwm.get(output):
                continue  # told to hold its marker (or the PWM nearest the disarmed one)
            self._mismatches[output] = self._mismatches.get(output, 0) + 1
            if self._mismatches[output] < needed:
                continue
            if output not in self._not_live:
                reason = (
                    f"output {output} shows {shown} us, not the {acked} us acknowledged "
                    "(disarmed, or the outputs not armed)"
                )
                log.warning("%s: holding the arm where it is", reason)
                self._not_live[output] = reason
            self._dead_pwm[output] = shown
            self._dead_seq[output] = self._updates_sent
            # The joint is where the output puts it. Its marker is stored at once (PX4 would
            # apply what we stored in one step when the outputs come alive): it moves the
            # joint by MARKER_OFFSET_US then, and the readback shows it.
            held_deg = self._marker_deg(output, shown)
            self._position[joint_of[output]] = held_deg
            self._held_pwm[output] = self.config.calibration.for_output(output).angle_to_pwm_us(
                held_deg
            )
            self._acked_pwm.pop(output, None)
            self._ack_history.pop(output, None)
            self._mismatches[output] = 0
            self._hold_now = True

    def _forget_liveness(self) -> None:
        """PX4, a loss or a (possible) reboot: what was stored is gone (a rebooted PX4 holds
        nothing), so whether each output is live is unknown again until its marker, sent
        anew, shows or does not (status: not known live)."""
        self._not_live.clear()
        self._dead_pwm.clear()
        self._dead_seq.clear()
        self._held_pwm.clear()
        self._hold_now = False

    def _markers_held(self) -> bool:
        """PX4: every output not live holds a PWM the readback tells from the one it shows
        (a marker): the next readback shows when they come alive, no probe needed."""
        return all(
            abs(self._held_pwm[o] - self._dead_pwm[o]) > READBACK_TOLERANCE_US
            for o in self._not_live
        )

    def _marker_deg(self, output: int, shown_us: int) -> float:
        """The angle an output showing ``shown_us`` (not live, or not known to be) is told to
        hold: its marker (``MARKER_OFFSET_US`` from it, towards the middle of the range: the
        readback tells it from ``shown_us``; for a disarmed PWM outside the servo's range, the
        nearest end of the range) or, with no room for one, the angle nearest ``shown_us``."""
        joint = self.config.calibration.for_output(output)
        limits = self.config.arm.joints[self._outputs.index(output)]
        low_deg = max(joint.angle_min_deg, math.degrees(limits.min_rad))
        high_deg = min(joint.angle_max_deg, math.degrees(limits.max_rad))
        middle_us = (joint.pwm_min_us + joint.pwm_max_us) / 2
        towards = 1 if shown_us <= middle_us else -1
        nearest = self._angle_shown(output, shown_us)
        candidates = [shown_us + towards * MARKER_OFFSET_US, shown_us - towards * MARKER_OFFSET_US]
        candidates.append(joint.angle_to_pwm_us(nearest))
        for pwm in candidates:
            if abs(pwm - shown_us) <= READBACK_TOLERANCE_US:
                continue
            if not joint.pwm_min_us <= pwm <= joint.pwm_max_us:
                continue
            angle = joint.pwm_us_to_angle_deg(pwm)
            if low_deg <= angle <= high_deg and joint.angle_to_pwm_us(angle) == pwm:
                return angle
        return nearest

    def _expected_pwms(self, output: int, now: float) -> tuple[set[int], bool]:
        """The PWMs a readback at ``now`` may show for ``output`` if it is live: the last one
        acknowledged at least READBACK_SETTLE_S ago and any acknowledged since (the readback
        lags by up to that); and whether that older one exists (settled: a readback showing
        none of them then says the output is not live; before, it may just lag)."""
        history = self._ack_history.get(output)
        if not history:
            return set(), False
        cutoff = now - READBACK_SETTLE_S + 1e-9
        recent = {pwm for t, pwm in history if t >= cutoff}
        older = [pwm for t, pwm in history if t < cutoff]
        return recent | set(older[-1:]), bool(older)

    def _angle_shown(self, output: int, pwm_us: int) -> float:
        """The joint angle an output's PWM means, within the calibration and the arm's limits
        (a disarmed PWM may lie outside the servo's range)."""
        joint = self.config.calibration.for_output(output)
        pwm = min(max(pwm_us, joint.pwm_min_us), joint.pwm_max_us)
        angle = joint.pwm_us_to_angle_deg(pwm)
        limits = self.config.arm.joints[self._outputs.index(output)]
        return min(max(angle, math.degrees(limits.min_rad)), math.degrees(limits.max_rad))

    def _dead_outputs(self) -> dict[int, str]:
        """The arm's outputs that are not live now, with the reason."""
        if self._is_ardupilot:
            if not self._safety_on:
                return {}
            mask = self._safety_mask or 0
            return {
                o: f"safety switch on (output {o} not in BRD_SAFETY_MASK)"
                for o in self._outputs
                if not mask >> (o - 1) & 1
            }
        return dict(self._not_live)

    def _unknown_outputs(self) -> dict[int, str]:
        """For status, the arm's outputs not known to be live. ArduPilot: while its SYS_STATUS
        stream (once seen) is silent for SYS_STATUS_STALE_INTERVALS (a reboot, a loss) or has
        not said where the switch is since a loss or a reboot. PX4: while the readback is
        silent for READBACK_STALE_INTERVALS, and each output until a readback showed what it
        stored since the start, a loss or a reboot (its marker, or a step)."""
        if not self._is_ardupilot:
            if self._readback_s == -math.inf:
                return dict.fromkeys(self._outputs, "not known live (no SERVO_OUTPUT_RAW yet)")
            silent_s = self.clock() - self._readback_s
            if silent_s > READBACK_STALE_INTERVALS * self._readback_interval_s:
                why = f"not known live (no SERVO_OUTPUT_RAW for {silent_s * 1e3:.0f} ms)"
                return dict.fromkeys(self._outputs, why)
            why = (
                "not known live yet (no readback has shown what it stores since the start, "
                "a loss or a reboot)"
            )
            return {o: why for o in self._outputs if o not in self._confirmed}
        if not self._sys_status_ever:
            return {}
        if self._sys_status_s is None or self._safety_on is None:
            why = "safety switch unknown (no SYS_STATUS since the link came back or a reboot)"
        else:
            silent_s = self.clock() - self._sys_status_s
            if silent_s <= SYS_STATUS_STALE_INTERVALS * self._sys_status_interval_s:
                return {}
            why = f"safety switch unknown (no SYS_STATUS for {silent_s * 1e3:.0f} ms)"
        return dict.fromkeys(self._outputs, why)

    def _on_system_time(self, actions: list[Action], boot_ms: int) -> None:
        previous, previous_s = self._boot_ms, self._boot_seen_s
        now = self.clock()
        after_silence = previous is not None and (
            self._system_time_s is None or now - previous_s > SYSTEM_TIME_GAP_S
        )
        self._boot_ms, self._boot_seen_s = boot_ms, now
        self._system_time_s = now
        # Backwards, or far behind where the time since the last one says it should be: a
        # reboot soon after the previous boot may not take time_boot_ms below its old value
        # by the time the stream, asked for again, comes back.
        lag_ms = REBOOT_LAG_AFTER_SILENCE_MS if after_silence else REBOOT_LAG_MS
        if previous is not None and (
            boot_ms + REBOOT_BACKSTEP_MS < previous
            or boot_ms < previous + (now - previous_s) * 1000.0 - lag_ms
        ):
            self.counters["autopilot_reboots"] += 1
            log.warning(
                "autopilot rebooted (time_boot_ms %d → %d): re-sending every output",
                previous,
                boot_ms,
            )
            # It forgot our route (until it answers us again) and reads BRD_SAFETY_MASK
            # anew at boot: a new mask applies only then.
            self._heard_us = False
            self._safety_mask = None
            self._lose_outputs(actions, "autopilot rebooted")
            self._ask_system_time(actions)

    def _watch_sys_status(self, actions: list[Action], now: float) -> None:
        """ArduPilot: a SYS_STATUS stream that fell silent holds the arm (``SAFETY_STEPS_AHEAD``;
        after a loss or a reboot, until one says where the switch is); every SYS_STATUS_SILENT_S
        of silence, every stream is asked for again (a request lost in a reboot)."""
        if not self._is_ardupilot or not self._sys_status_ever:
            return
        heard = -math.inf if self._sys_status_s is None else self._sys_status_s
        silent_s = max(
            SYS_STATUS_SILENT_S, SYS_STATUS_STALE_INTERVALS * self._sys_status_interval_s
        )
        if now - max(heard, self._sys_status_asked_s) < silent_s:
            return
        # Said once a silence (a stream that never comes back is asked for every 0.5 s).
        say = log.info if now - heard < 2 * silent_s else log.debug
        say("no SYS_STATUS for %.2f s: asking for every stream again", now - heard)
        self._ask_system_time(actions)

    def _after_silence(self, actions: list[Action]) -> None:
        """A frame from the pinned autopilot after it was silent for AUTOPILOT_GAP_INTERVALS
        of the fastest stream we asked for: it may have rebooted (and forgotten our streams),
        so they are asked for again at once. The SYSTEM_TIME that comes back says whether it
        did, and SYS_STATUS where its safety switch is, without waiting for a silence rule."""
        now = self.clock()
        heard, self._autopilot_heard_s = self._autopilot_heard_s, now
        gap_s = self._autopilot_gap_s
        if heard is None:
            return
        if now - heard <= gap_s:
            self._autopilot_streaming = True
            return
        # Only after its streams flowed: an autopilot that only beats (streams not asked yet,
        # or not supported) is not asked again at every HEARTBEAT.
        was_streaming, self._autopilot_streaming = self._autopilot_streaming, False
        if not (self._link_up and was_streaming):
            return
        # Silent long enough for SYSTEM_TIME's own rule: that first (no output taken for
        # granted), as the next tick would have done.
        self._watch_system_time(actions, now)
        if now - self._system_time_asked_s < gap_s:
            return  # just asked
        log.info("the autopilot speaks again after %.2f s: asking for every stream", now - heard)
        self._ask_system_time(actions)

    def _watch_readback(self, actions: list[Action], now: float) -> None:
        """PX4: a readback stream (once seen) silent for READBACK_SILENT_S: every stream is
        asked for again (a rebooted PX4 forgot them), so the reboot is seen from the
        SYSTEM_TIME that comes back rather than after SYSTEM_TIME_SILENT_S."""
        if self._is_ardupilot or self._readback_s == -math.inf:
            return
        silent_s = max(READBACK_SILENT_S, READBACK_STALE_INTERVALS * self._readback_interval_s)
        if now - max(self._readback_s, self._system_time_asked_s) < silent_s:
            return
        silent_for_s = now - self._readback_s
        # Said once a silence (a stream that never comes back is asked for every 0.5 s).
        say = log.info if silent_for_s < 2 * silent_s else log.debug
        say("no SERVO_OUTPUT_RAW for %.2f s: asking for every stream again", silent_for_s)
        self._ask_system_time(actions)

    def _watch_system_time(self, actions: list[Action], now: float) -> None:
        heard = self._system_time_s
        if now - self._system_time_asked_s < SYSTEM_TIME_SILENT_S:
            return
        if heard is None:
            if now - self._system_time_asked_s >= 5 * SYSTEM_TIME_SILENT_S:
                self._ask_system_time(actions)  # never answered yet: ask now and then
            return
        if now - heard < SYSTEM_TIME_SILENT_S:
            return
        # The stream stopped while the autopilot still beats: it may have rebooted and
        # forgotten the interval. Ask again, and take no output for granted: every output is
        # re-sent at the acknowledged pose now, even with the arm still (a reboot left them
        # at their boot values), then the motion goes on.
        log.info("SYSTEM_TIME stopped: asking again and re-sending every output")
        self._system_time_s = None
        resend = self._forget_outputs(self._flights)  # it may have rebooted, switch on
        self._acked_pwm.clear()
        self._ack_history.clear()
        self._confirmed.clear()
        self._forget_liveness()
        if not self._is_ardupilot:
            # PX4 (see _lose_outputs): never re-send a stale pose; the readback says where.
            self._readback_since_s = now
        elif not self._flights and self._last_step_s > -math.inf:
            self._unconfirmed = resend
            self._resend_now = True
        self._ask_system_time(actions)

    # -- keep-out volumes (issue 18) ---------------------------------------------------------

    def _keepout(self) -> KeepOut | None:
        """The config's keep-out volumes, prepared (None: none configured)."""
        config = self.config
        if self._keepout_of is not config:
            self._keepout_of = config
            self._keepout_obj = config.keepout_check() if config.keepout else None
        return self._keepout_obj

    def _solve_target(
        self, pose: Pose, start: Sequence[float], mode: str, budget_ms: float | None
    ) -> tuple[Any, str | None]:
        """Solve a target: ``(result, None)``, or ``(result or None, why it is refused)``.

        Without keep-out volumes, the injected solver once, warm from ``start``. With them,
        :func:`~companion.ik.keepout.solve_clear` within the same budget: a target reachable
        clear of every volume is reached (another solution is looked for when the first
        collides; the one taken is steered away from the volumes where the target leaves
        freedom);
        one that is not is refused naming the link and the volume. The motion is judged from
        the step commanded last (where the outputs go next) **straight** to the solution, the
        path the speed limit steps along: a solution whose straight motion would cross a volume
        is not taken (another is looked for), and if every one found would, the target is
        refused naming where along the motion. The daemon does not plan detours round a volume:
        a user who wants one sends a waypoint first (a trajectory)."""
        keepout = self._keepout()
        if keepout is None:
            return self._solve(pose, start, mode, budget_ms), None
        config = self.config
        commanded = self._flights[-1].step_deg if self._flights else tuple(self._position)

        def solver(arm: Any, target: Pose, **kwargs: Any) -> Any:
            return self._solve(
                target,
                kwargs["q_start_deg"],
                kwargs["mode"].value,
                kwargs["budget_ms"],
                seed=kwargs["seed"],
            )

        out = solve_clear(
            keepout,
            pose,
            budget_ms=config.budget_ms if budget_ms is None else budget_ms,
            seed=config.seed,
            q_start_deg=commanded,
            tol_pos_cm=config.tol_pos_cm,
            tol_ori_deg=config.tol_ori_deg,
            mode=TargetMode(mode),
            solver=solver,
            clock=self.clock,  # the core's: a test's fake clock makes the attempts exact
        )
        if out.verdict is ClearVerdict.CLEAR:
            return out.result, None
        why = None if out.collision is None else out.collision.reason
        if out.verdict in (ClearVerdict.COLLIDES, ClearVerdict.MOTION_COLLIDES):
            self.counters["keepout_refusals"] += 1
            what = (
                "the motion to every solution found"
                if out.verdict is ClearVerdict.MOTION_COLLIDES
                else "every solution found"
            )
            return out.refused_answer, f"keep-out: {what} is refused: {why}"
        nearest = out.result
        if nearest is None:
            return None, (
                "unreachable clear of the keep-out volumes within the budget"
                + ("" if why is None else f" ({why})")
            )
        return nearest, (
            f"unreachable: pos {nearest.pos_err_cm:.2f}cm ori {nearest.ori_err_deg:.1f}deg"
        )

    def _keepout_hit(self, q_deg: Sequence[float]) -> str | None:
        """Why a configuration is refused (a link within the margin of a volume), or None."""
        keepout = self._keepout()
        if keepout is None:
            return None
        collision = keepout.check(self._as_sent_rad(q_deg))
        return None if collision is None else f"puts {collision.reason} (at the PWM sent)"

    def _output_path(
        self, before_rad: Any, step_rad: Any, commands: Sequence[ServoCommand]
    ) -> list[Any]:
        """The configurations (rad) the outputs go through from ``before_rad`` to ``step_rad``
        when ``commands`` land in order: each command's outputs change together."""
        index = {output: i for i, output in enumerate(self._outputs)}
        q = np.array(before_rad, float)
        path = [q.copy()]
        for command in commands:
            for output in command.outputs:
                if output in index:
                    q[index[output]] = step_rad[index[output]]
            if not np.array_equal(q, path[-1]):
                path.append(q.copy())
        if not np.array_equal(q, step_rad):  # outputs left out as already there, by the ACKs
            path.append(np.array(step_rad, float))
        return path

    def _as_sent_rad(self, q_deg: Sequence[float]) -> Any:
        """The joints (rad) the servos get for ``q_deg``: each angle through its PWM, rounded
        to whole µs as sent (angles outside the calibration: as they are, never sent)."""
        cal = self.config.calibration
        try:
            pwm = cal.angles_to_pwm_us(q_deg)
        except CalibrationError:
            return np.radians(np.asarray(q_deg, float))
        return np.radians([j.pwm_us_to_angle_deg(pwm[j.output]) for j in cal.joints])

    # -- world-frame targets (issue 18) ------------------------------------------------------

    def _world_refusal(self, target: Target) -> Reply | None:
        if not self.config.world.enabled:
            return Reply(
                Outcome.DENIED,
                f"frame={target.frame!r}: world-frame targets are off ([world] enabled = false)",
            )
        return None

    def _world_in_base(self, target: Target) -> Pose | None:
        """The world target in the arm's base frame when the next step will reach the
        servos (None: no usable telemetry; ``_world_note["reason"]`` says why)."""
        now = self.clock()
        state = self._telemetry.state()
        world = self.config.world
        if state is None:
            self._world_note = {
                "reachable": None,
                "reason": "no vehicle telemetry yet (ATTITUDE and LOCAL_POSITION_NED)",
            }
            return None
        age_ms = 1000.0 * state.age_s(now)
        if age_ms > world.max_age_ms:
            self._world_note = {
                "reachable": None,
                "reason": f"vehicle telemetry {age_ms:.0f} ms old (world.max_age_ms = "
                f"{world.max_age_ms:g}): holding",
            }
            return None
        trips = sorted(self._round_trips)
        one_way_s = trips[len(trips) // 2] / 2.0 if trips else WORLD_DEFAULT_ONE_WAY_S
        apply_s = now + one_way_s + world.lead_ms / 1000.0
        if self._world_matrix is None or self._world_matrix[0] is not target:
            self._world_matrix = (target, target.pose.as_matrix())  # held for many ticks
        return matrix_to_base(self._world_matrix[1], state.predict(apply_s), self._mount_matrix())

    def _mount_matrix(self) -> Any:
        """``T_body_base`` of the config's mount, built once per mount (40 µs a tick)."""
        mount = self.config.mount
        if self._mount_cache is None or self._mount_cache[0] is not mount:
            self._mount_cache = (mount, mount.matrix)
        return self._mount_cache[1]

    def _follow_world(self) -> None:
        """Each tick: the held world target solved again (warm) for where the vehicle will be.
        Out of reach, or with no fresh telemetry, the arm holds its last goal and status says
        why; it follows again once the target is back within reach."""
        target = self._world
        assert target is not None
        pose = self._world_in_base(target)
        if pose is None:
            return
        start = self._goal if self._goal is not None else tuple(self._position)
        budget_ms = min(self.config.budget_ms, 1000.0 * WORLD_SOLVE_SHARE / self.config.rate_hz)
        result, refusal = self._solve_target(pose, start, target.mode, budget_ms)
        self.counters["solved"] += 1
        if refusal is None and result is not None and result.converged:
            hit = self._keepout_hit(result.q_deg)
            refusal = None if hit is None else f"keep-out: the solution {hit}"
        if refusal is not None or result is None:
            self._world_note = {
                "reachable": False,
                "reason": f"{refusal or 'no solution'}; holding the last clear pose",
            }
            return
        if result.converged:
            self._goal = tuple(float(q) for q in result.q_deg)
            self._world_note = {"reachable": True, "reason": None, "solve_ms": result.elapsed_ms}
            return
        if self._world_note.get("reachable") is not False:
            log.warning(
                "world target out of reach (pos %.2f cm, ori %.1f deg): holding the last "
                "reachable pose",
                result.pos_err_cm,
                result.ori_err_deg,
            )
        self._world_note = {
            "reachable": False,
            "reason": f"out of reach: pos {result.pos_err_cm:.2f} cm ori "
            f"{result.ori_err_deg:.1f} deg; holding the last reachable pose",
        }

    def _world_status(self, position: tuple[float, ...]) -> dict[str, Any]:
        world = self.config.world
        out: dict[str, Any] = {"enabled": world.enabled}
        if not world.enabled:
            return out
        now = self.clock()
        state = self._telemetry.state()
        out["telemetry_age_ms"] = None if state is None else 1000.0 * state.age_s(now)
        out["target"] = (
            None
            if self._world is None
            else {"pose": list(self._world.pose.as_tuple()), "mode": self._world.mode}
        )
        out["following"] = self._world is not None
        out.update(self._world_note if self._world is not None else {})
        if state is not None and self._hand_at is not None and self._hand_at[0] == position:
            hand = base_to_world(Pose(**self._hand_at[1]), state.predict(now), self._mount_matrix())
            out["hand_ned"] = dict(zip(POSE_KEYS, hand.as_tuple(), strict=True))
        return out

    # -- answers and status -----------------------------------------------------------------

    def _answer(self, actions: list[Action], request: Request, reply: Reply) -> None:
        actions.append(Answer(request, reply))
        if reply.outcome is Outcome.ACCEPTED:
            self._log_accepted(request, reply)
        if request.kind != "stop":
            self.counters[reply.outcome.value] += 1

    def _log_accepted(self, request: Request, reply: Reply) -> None:
        """One line per request carried out (refusals are summarised by the intake), but a
        stream of targets (50 Hz from a ground station) at most one line per second per kind
        and source, saying how many it stood for: the journal of a board on an SD card."""
        key = (request.kind, request.source)
        now = self.clock()
        last_s, skipped = self._accept_log.get(key, (-math.inf, 0))
        if request.kind in MOTION_KINDS and now - last_s < ACCEPT_LOG_INTERVAL_S:
            self._accept_log[key] = (last_s, skipped + 1)
            return
        if len(self._accept_log) >= 256:  # bounded: sources come and go
            self._accept_log.clear()
        self._accept_log[key] = (now, 0)
        target = ""
        if request.kind == "goto" and self.last_target is not None:
            target = " (" + ", ".join(f"{v:.2f}" for v in self.last_target["pose"]) + ")"
            if self.last_target.get("mode", "pose") != "pose":
                target += f" {self.last_target['mode']}"
        more = f" (and {skipped} more since the last line)" if skipped else ""
        log.info(
            "%s%s from %s accepted: %s%s",
            request.kind,
            target,
            _source(request),
            reply.message,
            more,
        )

    def status(self) -> dict[str, Any]:
        """A JSON-ready snapshot (build it on the driving thread)."""
        dead = {**self._unknown_outputs(), **self._dead_outputs()}
        outputs = {}
        for output in self._outputs:
            if output in self._refused:
                state: dict[str, Any] = {"state": "refused", "reason": self._refused[output]}
            elif output in self._acked_pwm:
                state = {"state": "acknowledged"}
            else:
                state = {"state": "unknown"}
            outputs[output] = {
                "pwm_us": self._acked_pwm.get(output),
                **state,
                "shown_us": self._readback.get(output),
                "live": output not in dead,
            }
        position = tuple(self._position)
        if self._hand_at is None or self._hand_at[0] != position:
            hand = self.config.arm.fk(position)
            self._hand_at = (position, dict(zip(POSE_KEYS, hand.as_tuple(), strict=True)))
        return {
            "autopilot": list(self._pinned) if self._pinned else None,
            # Its uptime by the last SYSTEM_TIME (None until one came): reboots are seen from it.
            "autopilot_boot_ms": self._boot_ms,
            "autopilot_heard_us": self._link_up and self._heard_us,
            "holding": not self._link_up and self._last_step_s > -math.inf,
            "current_deg": list(position),
            # The hand where the acknowledged joints put it (forward kinematics of current_deg).
            "hand": dict(self._hand_at[1]),
            "goal_deg": list(self._goal) if self._goal is not None else None,
            "moving": bool(self._flights)
            or (self._goal is not None and (self._goal != position or not self._settled())),
            "last_pwm_us": dict(self._acked_pwm) or None,
            # What the outputs do (issue 20): not live = disarmed / safety on, with why.
            "outputs_live": not dead,
            "not_live": {str(o): why for o, why in sorted(dead.items())},
            "armed": self._armed,
            "safety_on": self._safety_on,
            "outputs": outputs,
            "last_target": self.last_target,
            "trajectory_points_left": len(self._trajectory),
            # World-frame targets (issue 18): the one held, whether it is within reach, the
            # telemetry's age, the hand in LOCAL_NED by the acknowledged joints.
            "world": self._world_status(position),
            "counters": dict(self.counters),
        }


#: At most one "accepted" log line per second per kind and source for motion requests.
ACCEPT_LOG_INTERVAL_S = 1.0

#: The keys of a pose in status and replies, in ``Pose`` order.
POSE_KEYS = ("x_cm", "y_cm", "z_cm", "roll_deg", "pitch_deg", "yaw_deg")


def _source(request: Request) -> str:
    """Who asked, for a log line: ``mavlink 255/190``, ``socket 3``."""
    kind, *ids = request.source or ("unknown",)
    return f"{kind} {'/'.join(str(i) for i in ids)}".strip()


def _not_live_reply(reply: Reply, dead: dict[int, str]) -> Reply:
    first = dead[min(dead)]
    more = f" (+{len(dead) - 1} more)" if len(dead) > 1 else ""
    return dataclasses.replace(
        reply,
        message=f"{reply.message}; outputs not live: {first}{more}: the arm moves when they are",
    )


def _param_name(raw: Any) -> str:
    text = raw.decode("ascii", "replace") if isinstance(raw, bytes | bytearray) else str(raw)
    return text.rstrip("\0")
