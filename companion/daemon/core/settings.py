"""What the control core derives from its config, computed in one place.

:meth:`CoreSettings.from_config` is a pure function of a :class:`DaemonConfig`: the outputs,
the servo dialect, the streams asked for and their intervals, the silences that follow from
them, the ArduPilot safety band's width, the keep-out volumes prepared, the mount's matrix. The
core holds one; :meth:`~companion.daemon.core.ControlCore.reconfigure` computes it anew on a
reload, so nothing derived from the config outlives it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from companion.daemon.config import DaemonConfig
from companion.kinematics.collision import KeepOut
from firmware_interface import make_servo_dialect
from firmware_interface.servo import ServoDialect
from firmware_interface.transport import parse_url

#: SYSTEM_TIME is asked for at this interval, for reboot detection.
SYSTEM_TIME_INTERVAL_S = 0.25
#: The outputs' readback (SERVO_OUTPUT_RAW) is asked for at this interval: the truth of what the
#: outputs do. ArduPilot streams it at most every 20 ms.
READBACK_INTERVAL_S = 0.1
#: On a link with room for it: a readback this often sees PX4's outputs go dead (disarm, kill)
#: and an ArduPilot output set by another sender (a ground station's servo test) before the
#: next control step;
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
#: pulses, so what the arm may have moved then is undone while it is on (see the rewind in
#: ``outputs_ardupilot``). Twice a control tick (20 Hz) on a fast link, so that
#: SAFETY_STEPS_AHEAD seldom holds a step back.
SYS_STATUS_INTERVAL_S = 0.025
SYS_STATUS_SLOW_LINK_INTERVAL_S = 0.25
#: ArduPilot: since the last SYS_STATUS that said the switch is off, the switch may have gone on
#: (and even off again, unseen) at any moment, holding each output at the pose acknowledged then
#: or at any step sent since (or on its way then), and storing every later one for its release.
#: Those poses are kept within a band this many control ticks' steps (``joint_speed_deg_s /
#: rate_hz``) wide per joint (a step that would widen it waits for the next SYS_STATUS): with
#: one, the release moves a joint by at most a step whatever it stored, and the middle of the
#: band, where the rewind and a re-send after a loss or a reboot send the outputs, is within
#: half a step of anything they may hold. A SYS_STATUS stream that falls silent stops the arm
#: within the band (never narrower than SAFETY_BAND_MIN_S of motion, below). On a slow serial
#: line (SYS_STATUS every 0.25 s) the band is the steps of one SYS_STATUS interval, not to slow
#: the arm: a release there may move a joint by more than a step.
SAFETY_STEPS_AHEAD = 1
#: ... and at least this long of motion at ``joint_speed_deg_s`` (one step at the default 20 Hz
#: control): two SYS_STATUS intervals, so that the band, which holds a step on its way when a
#: SYS_STATUS comes, never slows the arm. Above 20 Hz control a release may then move a joint
#: by this much motion (3 degrees at 60 deg/s), more than one of its shorter steps: held whole
#: to one step at 50 Hz, the arm fell behind a hovering vehicle (world error p99 1.9-4.7 cm
#: against 0.3-0.6, ``bench.world_hold``).
SAFETY_BAND_MIN_S = 0.05
#: A frame from the autopilot after this many intervals of the fastest stream asked for with
#: nothing from it, where its frames came that often before: every stream is asked for again
#: at once (see ``AutopilotWatch.after_silence``).
AUTOPILOT_GAP_INTERVALS = 4
#: A world-frame target is solved again every control tick in at most this share of the
#: period (warm, it converges in ~0.1 ms; an unreachable one costs the whole of it).
WORLD_SOLVE_SHARE = 0.1
#: A stream asked to stop (SET_MESSAGE_INTERVAL param2 = -1).
STOP_STREAM = -1.0


def is_ardupilot(dialect: str) -> bool:
    """Whether a ``link.dialect`` speaks to ArduPilot (``ardupilot``, ``ardupilot-lua``)."""
    return dialect.startswith("ardupilot")


def stream_intervals_s(*, ardupilot: bool, url: str) -> tuple[float, float]:
    """(SERVO_OUTPUT_RAW, SYS_STATUS) intervals for a link: slower on a serial line below
    :data:`SLOW_LINK_BAUD`, where every byte up delays the ACKs behind it."""
    spec = parse_url(url)
    slow_serial = spec.kind == "serial" and (spec.baud or 0) < SLOW_LINK_BAUD
    if slow_serial:
        readback_s = READBACK_SLOW_LINK_INTERVAL_S if ardupilot else READBACK_INTERVAL_S
    else:
        # Both firmwares: an output set by another sender (ArduPilot) or gone dead (PX4) is
        # seen within a readback, before the next control step goes out.
        readback_s = READBACK_FAST_INTERVAL_S
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


def safety_band_width_deg(
    *, joint_speed_deg_s: float, rate_hz: float, sys_status_interval_s: float
) -> float:
    """ArduPilot: how wide (deg, per joint) the band of poses the outputs may hold since the
    last SYS_STATUS that said the switch is off may grow (see :data:`SAFETY_STEPS_AHEAD`)."""
    step_deg = joint_speed_deg_s / rate_hz
    steps = SAFETY_STEPS_AHEAD
    if sys_status_interval_s > SYS_STATUS_INTERVAL_S:  # a slow serial line
        steps = max(steps, math.ceil(sys_status_interval_s * rate_hz - 1e-9))
    return max(step_deg * steps, joint_speed_deg_s * SAFETY_BAND_MIN_S)


@dataclass(frozen=True, eq=False)
class CoreSettings:
    """Everything the core derives from its config (see the module docstring)."""

    #: The arm's servo outputs, in joint order.
    outputs: tuple[int, ...]
    #: The autopilot speaks ArduPilot (else PX4): chooses the outputs' truth.
    ardupilot: bool
    dialect: ServoDialect
    #: One control tick, and the most a joint moves in one (at ``joint_speed_deg_s``).
    period_s: float
    step_deg: float
    readback_interval_s: float
    sys_status_interval_s: float
    #: The streams asked for (message id, interval s), see :func:`stream_requests`.
    streams: tuple[tuple[int, float], ...]
    #: AUTOPILOT_GAP_INTERVALS of the fastest stream asked for.
    autopilot_gap_s: float
    #: ArduPilot: see :func:`safety_band_width_deg`.
    safety_band_width_deg: float
    #: The (system, component) the autopilot must have (None: any; latched from its HEARTBEAT).
    pin: tuple[int | None, int | None]
    #: The keep-out volumes prepared (None: none configured).
    keepout: KeepOut | None
    #: ``T_body_base`` of the mount (4×4).
    mount_matrix: Any
    #: A world target's solve each tick, at most (ms).
    world_solve_budget_ms: float

    @classmethod
    def from_config(cls, config: DaemonConfig) -> CoreSettings:
        ardupilot = is_ardupilot(config.link.dialect)
        readback_s, sys_status_s = stream_intervals_s(ardupilot=ardupilot, url=config.link.url)
        fastest_s = min(readback_s, SYSTEM_TIME_INTERVAL_S)
        if ardupilot:
            fastest_s = min(fastest_s, sys_status_s)
        world = config.world
        streams = stream_requests(
            ardupilot=ardupilot,
            readback_interval_s=readback_s,
            sys_status_interval_s=sys_status_s,
            world_telemetry_hz=world.telemetry_hz if world.enabled else None,
        )
        return cls(
            outputs=tuple(j.output for j in config.calibration.joints),
            ardupilot=ardupilot,
            dialect=make_servo_dialect(config.link.dialect, None, config.calibration),
            period_s=1.0 / config.rate_hz,
            step_deg=config.joint_speed_deg_s / config.rate_hz,
            readback_interval_s=readback_s,
            sys_status_interval_s=sys_status_s,
            streams=tuple(streams),
            autopilot_gap_s=AUTOPILOT_GAP_INTERVALS * fastest_s,
            safety_band_width_deg=safety_band_width_deg(
                joint_speed_deg_s=config.joint_speed_deg_s,
                rate_hz=config.rate_hz,
                sys_status_interval_s=sys_status_s,
            ),
            pin=(config.link.target_system, config.link.target_component),
            keepout=config.keepout_check() if config.keepout else None,
            mount_matrix=config.mount.matrix,
            world_solve_budget_ms=min(
                config.budget_ms, 1000.0 * WORLD_SOLVE_SHARE / config.rate_hz
            ),
        )
