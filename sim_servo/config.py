"""Simulator settings: flavour, identity, output function table, servo model, arm, faults.

Settings come from a TOML file (``--config``, schema in ``docs/simulator.md`` and
``sim_servo/examples/quad_arm.toml``) and are then overridden by command-line flags. Every value
is validated here, once; the message names the field, the value and the allowed range.

Output functions use each flavour's own numbers:

* ``ardupilot``: ``SERVOn_FUNCTION`` — 0 disabled, 1 RC pass-through, 33–36 motors 1–4,
  51–66 RC input 1–16 … A quad's defaults are outputs 1–4 = 33–36, the rest 0.
* ``px4``: ``PWM_MAIN_FUNCn`` — 0 disabled, 101–104 motors 1–4, 301–306 "Peripheral via
  Actuator Set 1–6". The defaults are outputs 1–4 = 101–104 and every other output 0, as PX4
  ships them (``PWM_MAIN_FUNC5..16`` = 0): the arm's outputs must be set to 301–306.

A *ready* vehicle (:func:`ready_setup`, the flag ``--ready``, what the test helpers and the
benches start) is one set up as ``docs/px4.md`` and ``docs/ardupilot.md`` say: PX4 — the
arm's outputs on functions 301–306 in joint order, ``COM_PREARM_MODE`` 2, forwarding on both
links (``MAV_0_FORWARD`` / ``MAV_1_FORWARD`` 1) and armed at start (so its outputs are live at
once, not 5 s after boot; after a reboot it comes back disarmed and prearms 5 s later, as real
PX4 does); ArduPilot — nothing to do (the safety switch is off by default).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

import tomlfields
from sim_servo.errors import SimConfigError, SimFieldError
from tomlfields import Table, check_boolean, check_integer, check_number, check_numbers, is_int

FLAVOURS = ("ardupilot", "px4")
#: SERVO1…SERVO16: the outputs SERVO_OUTPUT_RAW port 0 reports.
OUTPUT_COUNT = 16
#: ArduPilot SRV_Channel parameter defaults (SERVOn_MIN / MAX / TRIM).
ARDUPILOT_PWM_MIN_US = 1100
ARDUPILOT_PWM_MAX_US = 1900
ARDUPILOT_PWM_TRIM_US = 1500
#: PX4 PWM_MAIN_MINn / MAXn defaults.
PX4_PWM_MIN_US = 1000
PX4_PWM_MAX_US = 2000
#: The arm's outputs by default: the six after a quad's motors (the daemon's default too).
DEFAULT_ARM_OUTPUTS = (9, 10, 11, 12, 13, 14)
#: The PWM range (µs) each arm joint sweeps by default.
DEFAULT_ARM_PWM_MIN_US = 1000
DEFAULT_ARM_PWM_MAX_US = 2000
#: Bounds for an arm joint's PWM range (µs): hobby servos live well inside them.
ARM_PWM_LIMIT_MIN_US = 500
ARM_PWM_LIMIT_MAX_US = 2500
ARDUPILOT_MOTOR_FUNCTIONS = {1: 33, 2: 34, 3: 35, 4: 36}
PX4_MOTOR_FUNCTIONS = {1: 101, 2: 102, 3: 103, 4: 104}
PX4_ACTUATOR_SET_FIRST_FUNCTION = 301
PX4_ACTUATOR_SET_COUNT = 6
#: Measured on ArduCopter 4.7.0-dev SITL: SERVO_OUTPUT_RAW never faster than 50 Hz, whatever
#: SET_MESSAGE_INTERVAL asked for.
ARDUPILOT_SERVO_OUTPUT_MIN_INTERVAL_MS = 20
#: SYSTEM_TIME before any SET_MESSAGE_INTERVAL. ArduCopter: in the EXTRA3 stream, whose
#: SRn_EXTRA3 default is 0 on Copter (GCS_MAVLink_Parameters.cpp), so off. PX4: 1 Hz in the
#: ONBOARD mode of a companion link (mavlink_main.cpp ``configure_streams_to_default``).
DEFAULT_SYSTEM_TIME_RATE_HZ = {"ardupilot": 0.0, "px4": 1.0}
#: A real flight controller's reboot measured at 0.36 s without a frame.
DEFAULT_REBOOT_GAP_S = 0.36
#: PX4 ``PWM_MAIN_DISn`` default on boards (SITL has 900): the PWM of an output while it is not
#: live (disarmed and not prearmed), at boot and after a kill or a reboot.
PX4_DISARMED_PWM_US = 1000
#: ATTITUDE and LOCAL_POSITION_NED before any SET_MESSAGE_INTERVAL (see :mod:`sim_servo.hover`).
#: ArduCopter: in the EXTRA1 and POSITION streams, whose SRn_EXTRA1 / SRn_POSITION defaults are
#: 0 on Copter (GCS_MAVLink_Parameters.cpp), so off until asked. PX4: 100 Hz and 30 Hz in the
#: ONBOARD mode of a companion link (mavlink_main.cpp ``configure_streams_to_default``).
DEFAULT_ATTITUDE_RATE_HZ = {"ardupilot": 0.0, "px4": 100.0}
DEFAULT_LOCAL_POSITION_RATE_HZ = {"ardupilot": 0.0, "px4": 30.0}
#: PX4 ``COM_PREARM_MODE``: 0 disabled (default), 1 safety button, 2 always.
PX4_PREARM_MODES = (0, 1, 2)
#: Measured on PX4 SITL: with ``COM_PREARM_MODE`` 2 the outputs come alive 5 s after boot.
PX4_PREARM_DELAY_S = 5.0
#: The autopilot's HEARTBEAT rate. Real ones send 1 Hz. Below 0.1 Hz (one every 10 s) any
#: peer takes the link for lost (the daemon waits at most 60 s, most far less): a silent
#: autopilot is the fault ``heartbeat_pause_after_s`` models. Above 100 Hz it floods the link.
HEARTBEAT_RATE_HZ = (0.1, 100.0)
#: The main loop's rate (ArduCopter's is 400 Hz). Below 1 Hz every command waits seconds for
#: its pass; above 10 kHz the loop does nothing but spin.
LOOP_RATE_HZ = (1.0, 10_000.0)


# Every value is checked by the shared reader (tomlfields), raising SimFieldError named by its
# dotted TOML field; a value built in code has no source, and config_from_mapping adds the file.


def _real(value: Any, field: str, low: float, high: float) -> float:
    """A finite number in ``[low, high]``."""
    return check_number(value, field, min_value=low, max_value=high, error=SimFieldError)


def _positive(value: Any, field: str, high: float) -> float:
    """A finite number in ``(0, high]``."""
    return check_number(value, field, max_value=high, positive=True, error=SimFieldError)


def _int(value: Any, field: str, low: int, high: int) -> int:
    """An integer in ``[low, high]``."""
    return check_integer(value, field, min_value=low, max_value=high, error=SimFieldError)


def _bool(value: Any, field: str) -> bool:
    return check_boolean(value, field, error=SimFieldError)


def _optional_real(value: Any, field: str, low: float, high: float) -> float | None:
    return None if value is None else _real(value, field, low, high)


def _triple(value: Any, field: str, low: float, high: float) -> tuple[float, float, float]:
    x, y, z = check_numbers(
        value, field, length=3, min_value=low, max_value=high, error=SimFieldError
    )
    return (x, y, z)


@dataclass(frozen=True)
class ServoConfig:
    """The servo model shared by every output.

    ``slew_s_per_60deg`` is the datasheet speed (0.12 s/60° for a typical hobby servo);
    ``deadband_us`` the command change the servo ignores; ``deg_per_us`` how far the horn turns
    per µs on outputs that drive no arm joint (arm outputs use their joint's angle span over
    its PWM span, see :class:`ArmConfig`); the horn stops at ``[travel_min_us, travel_max_us]``;
    it starts at ``initial_us``.
    """

    slew_s_per_60deg: float = 0.12
    deadband_us: float = 1.0
    deg_per_us: float = 0.09
    travel_min_us: float = 500.0
    travel_max_us: float = 2500.0
    initial_us: float = 1500.0

    def __post_init__(self) -> None:
        _real(self.slew_s_per_60deg, "servo.slew_s_per_60deg", 0.0, 60.0)
        _real(self.deadband_us, "servo.deadband_us", 0.0, 100.0)
        _positive(self.deg_per_us, "servo.deg_per_us", 10.0)
        _real(self.travel_min_us, "servo.travel_min_us", 0.0, 5000.0)
        _real(self.travel_max_us, "servo.travel_max_us", 0.0, 5000.0)
        if not self.travel_min_us < self.travel_max_us:
            raise SimFieldError(
                "",
                "servo.travel_min_us",
                f"{self.travel_min_us!r} must be below servo.travel_max_us = "
                f"{self.travel_max_us!r}",
            )
        _real(self.initial_us, "servo.initial_us", self.travel_min_us, self.travel_max_us)


@dataclass(frozen=True)
class LinkTimingConfig:
    """When the autopilot's frames leave, on every link: a model fitted to ArduCopter SITL.

    Measured on ArduCopter 4.7.0-dev SITL over TCP on loopback with a pymavlink client (the
    figures ``python -m bench.sim_calibration`` compares against): one DO_SET_SERVO round trip
    5.7 ms median (5.3–6.1); six one after another, each waiting for its ACK, 32.2 ms in all;
    six back-to-back, then their six ACKs, 3.2 ms median (6.0 max). A burst beats a single
    round trip, so the time is not spent handling the command; the model, on top of the 400 Hz
    main-loop pass that handles each frame:

    * every frame the autopilot writes to a link leaves ``output_delay_ms`` after it was
      produced at the earliest (the burst's floor);
    * then it is *held*, as a receiver's delayed ACK is: released when the next frame arrives
      from that link, or ``hold_ms`` after the first frame that arrived on the link since it
      was last quiet (``hold_ms`` after the frame was produced if none did), or at once when
      ``burst_frames`` frames have arrived on the link within that window (TCP acknowledges at
      least every second segment at once).

    So a lone command's answer leaves ``hold_ms`` after the command arrived, whatever the loop
    phase, and a burst's answers leave ``output_delay_ms`` after the pass that handled them.
    The model's own figures (no I/O cost): one round trip ``hold_ms`` (4.8 ms), six in sequence
    6 × 4.8 = 28.8 ms, a burst of six 0–2.5 ms + ``output_delay_ms`` (median 2.25 ms). The
    defaults were fitted with ``python -m bench.sim_calibration`` (this simulator as a process,
    a Python client, a loaded 2-core machine), which adds 0.5–1 ms per exchange: it measures
    about 5.6, 33 and 4.7–5.3 ms. The burst stays above SITL's there, because handling six
    commands costs this Python simulator 0.6–1.2 ms, more than ``output_delay_ms``. Fitted,
    not derived: which part of SITL holds the frames was not identified. Serial links could not
    be measured here; the same model applies to UDP, TCP and pty. ``hold_ms`` and
    ``output_delay_ms`` 0 (:meth:`instant`) give the old timing: frames leave on the pass that
    produced them.
    """

    output_delay_ms: float = 1.0
    hold_ms: float = 4.8
    burst_frames: int = 2

    def __post_init__(self) -> None:
        _real(self.output_delay_ms, "link_timing.output_delay_ms", 0.0, 1000.0)
        _real(self.hold_ms, "link_timing.hold_ms", 0.0, 1000.0)
        _int(self.burst_frames, "link_timing.burst_frames", 1, 1000)

    @classmethod
    def instant(cls) -> LinkTimingConfig:
        """No delay, no hold: frames leave on the main-loop pass that produced them."""
        return cls(output_delay_ms=0.0, hold_ms=0.0)


@dataclass(frozen=True)
class Px4TimingConfig:
    """When the PX4 flavour answers and forwards: a model fitted to PX4 SITL (main of 2026-03,
    SIH quadrotor, UDP on loopback, a pymavlink client).

    Measured there: MAV_CMD_DO_SET_ACTUATOR → COMMAND_ACK median 5.8 ms, p90 10.8, max 13.0; a
    ground station's MAV_CMD_USER_1 through PX4 to the companion and its COMMAND_ACK back
    through PX4: median 17.9–18.4 ms, max 22.5. The model (replacing ArduPilot's delay-and-hold
    :class:`LinkTimingConfig`, which this flavour does not use):

    * a received frame is handled at once (PX4's receiver thread, not a main-loop pass);
    * a command the commander handles (MAV_CMD_COMPONENT_ARM_DISARM, MAV_CMD_DO_SET_ACTUATOR)
      takes effect and is answered on the commander's next cycle, every
      ``commander_period_ms`` (10 ms, PX4's 100 Hz commander) from boot;
    * a frame routed from one link to another leaves ``forward_delay_ms`` later at the earliest;
    * every frame leaves on its link's next MAVLink main-loop pass, every ``mavlink_loop_ms``
      from boot (1.5 ms, PX4's shortest main-loop delay).

    So an ACK takes 0–10 ms + 0–1.5 ms (the model's own median 5.75 ms, p90 9.8, max 11.5) and
    each routed hop ``forward_delay_ms`` + 0–1.5 ms. As a process on a loaded 2-core machine
    (load 2–4) ``python -m bench.px4_calibration`` measured the ACK at 7.4–9.4 ms median, the
    Python simulator's wake-ups adding 1.5–3.5 ms (ArduPilot's single round trip, one wake-up,
    gained 0.7–1.5 ms in the same conditions): the simulator's median is above SITL's, its p90
    and max near them. ``forward_delay_ms`` (2.5) was fitted to the ground station's round
    trip through the daemon with ``python -m bench.latency --dialects ardupilot px4``: px4 → ACK
    median 19.9 ms at load 4 (SITL 17.9–18.4); which part of PX4 delays a forwarded frame was
    not identified. All 0 (:meth:`instant`): frames are handled and leave at once.
    """

    commander_period_ms: float = 10.0
    mavlink_loop_ms: float = 1.5
    forward_delay_ms: float = 2.5

    def __post_init__(self) -> None:
        _real(self.commander_period_ms, "px4_timing.commander_period_ms", 0.0, 1000.0)
        _real(self.mavlink_loop_ms, "px4_timing.mavlink_loop_ms", 0.0, 1000.0)
        _real(self.forward_delay_ms, "px4_timing.forward_delay_ms", 0.0, 1000.0)

    @classmethod
    def instant(cls) -> Px4TimingConfig:
        """No commander cycle, no main-loop wait, no forwarding delay."""
        return cls(commander_period_ms=0.0, mavlink_loop_ms=0.0, forward_delay_ms=0.0)


@dataclass(frozen=True)
class FaultConfig:
    """Fault injection; every field off by default. Probabilities are per frame, in [0, 1]."""

    drop_in: float = 0.0
    drop_out: float = 0.0
    corrupt_in: float = 0.0
    corrupt_out: float = 0.0
    latency_ms: float = 0.0
    jitter_ms: float = 0.0
    heartbeat_pause_after_s: float | None = None
    heartbeat_pause_for_s: float | None = None  # None: for ever
    withhold_ack_commands: frozenset[int] = frozenset()
    withhold_all_acks: bool = False
    nack_outputs: frozenset[int] = frozenset()
    hangup_after_s: float | None = None
    hangup_for_s: float | None = None  # None: the port never comes back
    reboot_after_s: float | None = None
    reboot_gap_s: float = DEFAULT_REBOOT_GAP_S
    seed: int = 0

    def __post_init__(self) -> None:
        for name in ("drop_in", "drop_out", "corrupt_in", "corrupt_out"):
            _real(getattr(self, name), f"faults.{name}", 0.0, 1.0)
        _real(self.latency_ms, "faults.latency_ms", 0.0, 60_000.0)
        _real(self.jitter_ms, "faults.jitter_ms", 0.0, 60_000.0)
        for name in (
            "heartbeat_pause_after_s",
            "heartbeat_pause_for_s",
            "hangup_after_s",
            "hangup_for_s",
            "reboot_after_s",
        ):
            _optional_real(getattr(self, name), f"faults.{name}", 0.0, 1e6)
        _real(self.reboot_gap_s, "faults.reboot_gap_s", 0.0, 600.0)
        _bool(self.withhold_all_acks, "faults.withhold_all_acks")
        for command in self.withhold_ack_commands:
            _int(command, "faults.withhold_ack", 0, 65535)
        for output in self.nack_outputs:
            _int(output, "faults.nack_outputs", 1, OUTPUT_COUNT)
        _int(self.seed, "faults.seed", 0, 2**63 - 1)
        object.__setattr__(self, "withhold_ack_commands", frozenset(self.withhold_ack_commands))
        object.__setattr__(self, "nack_outputs", frozenset(self.nack_outputs))


@dataclass(frozen=True)
class MountConfig:
    """Where the arm's base sits on the vehicle: the base frame in the body frame FRD (x
    forward, y right, z down, origin at the autopilot's body origin). ``xyz_cm`` is the base
    origin in body FRD (cm); ``rpy_deg`` the base frame's orientation, roll/pitch/yaw with
    ``R = Rz(yaw) · Ry(pitch) · Rx(roll)`` (as :class:`companion.kinematics.Pose`). The default:
    an arm hanging under a quadrotor, 10 cm below the body origin, its axes the body's (its +z
    points down)."""

    xyz_cm: tuple[float, float, float] = (0.0, 0.0, 10.0)
    rpy_deg: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def __post_init__(self) -> None:
        xyz_cm = _triple(self.xyz_cm, "vehicle.mount.xyz_cm", -500.0, 500.0)
        object.__setattr__(self, "xyz_cm", xyz_cm)
        rpy_deg = _triple(self.rpy_deg, "vehicle.mount.rpy_deg", -360.0, 360.0)
        object.__setattr__(self, "rpy_deg", rpy_deg)


@dataclass(frozen=True)
class VehicleConfig:
    """The vehicle's motion in LOCAL_NED: a seeded hover disturbance (:mod:`sim_servo.hover`).

    With ``hover`` the vehicle drifts around ``home_ned_m`` (north, east, down in m from the
    autopilot's origin; −2: 2 m up) by at most ``drift_cm`` north and east and ``heave_cm``
    down, tilts by at most ``tilt_deg`` in roll and pitch and wanders by at most ``yaw_deg``
    around ``home_yaw_deg``: each a sum of ``components`` sinusoids whose periods are drawn in
    [``period_min_s``, ``period_max_s``] (yaw: [``yaw_period_min_s``, ``yaw_period_max_s``]),
    amplitudes and phases from ``seed``. Without it the vehicle holds ``home_ned_m`` level.
    ``log_rate_hz``: a ``vehicle`` event (vehicle state, the hand in the world) that often in
    the event log (0: none). ``mount``: :class:`MountConfig`.
    """

    hover: bool = True
    seed: int = 0
    drift_cm: float = 10.0
    heave_cm: float = 5.0
    tilt_deg: float = 5.0
    yaw_deg: float = 5.0
    period_min_s: float = 1.0
    period_max_s: float = 5.0
    yaw_period_min_s: float = 8.0
    yaw_period_max_s: float = 20.0
    components: int = 3
    home_ned_m: tuple[float, float, float] = (0.0, 0.0, -2.0)
    home_yaw_deg: float = 0.0
    log_rate_hz: float = 25.0
    mount: MountConfig = field(default_factory=MountConfig)

    def __post_init__(self) -> None:
        _bool(self.hover, "vehicle.hover")
        _int(self.seed, "vehicle.seed", 0, 2**63 - 1)
        _real(self.drift_cm, "vehicle.drift_cm", 0.0, 500.0)
        _real(self.heave_cm, "vehicle.heave_cm", 0.0, 500.0)
        _real(self.tilt_deg, "vehicle.tilt_deg", 0.0, 45.0)
        _real(self.yaw_deg, "vehicle.yaw_deg", 0.0, 180.0)
        for low_name, high_name in (
            ("period_min_s", "period_max_s"),
            ("yaw_period_min_s", "yaw_period_max_s"),
        ):
            low = _real(getattr(self, low_name), f"vehicle.{low_name}", 0.05, 3600.0)
            high = _real(getattr(self, high_name), f"vehicle.{high_name}", 0.05, 3600.0)
            if low > high:
                raise SimFieldError(
                    "",
                    f"vehicle.{low_name}",
                    f"{getattr(self, low_name)!r} must not exceed vehicle.{high_name} = "
                    f"{getattr(self, high_name)!r}",
                )
        _int(self.components, "vehicle.components", 1, 16)
        home_ned_m = _triple(self.home_ned_m, "vehicle.home_ned_m", -1e6, 1e6)
        object.__setattr__(self, "home_ned_m", home_ned_m)
        _real(self.home_yaw_deg, "vehicle.home_yaw_deg", -360.0, 360.0)
        _real(self.log_rate_hz, "vehicle.log_rate_hz", 0.0, 1000.0)
        if not isinstance(self.mount, MountConfig):
            raise SimConfigError(f"vehicle mount={self.mount!r} must be a MountConfig")

    def as_dict(self) -> dict[str, Any]:
        """The settings as TOML / JSON data (the ``start`` event carries them)."""
        data = {name: getattr(self, name) for name in self.__dataclass_fields__ if name != "mount"}
        data["home_ned_m"] = list(self.home_ned_m)
        data["mount"] = {"xyz_cm": list(self.mount.xyz_cm), "rpy_deg": list(self.mount.rpy_deg)}
        return data


@dataclass(frozen=True)
class ArmConfig:
    """Which arm the servos move and how its joints map onto outputs (the simulator's servo model).

    ``arm_file`` None is the default paper arm. Joint ``theta1``, ``theta2``, … (arm order) is on
    ``outputs[0]``, ``outputs[1]``, …; its servo sweeps the joint's limits (degrees, from the arm)
    linearly over ``[pwm_min_us, pwm_max_us]`` (µs, integers in [500, 2500]), from the upper limit
    down for a joint named in ``reversed_joints``. ``trims_us`` (joint name → integer µs, at most
    half the PWM span either way) shifts a joint's sweep along the pulse axis. A horn outside
    ``[pwm_min_us, pwm_max_us]`` gives no angle. :mod:`sim_servo.hand` implements it; joint names
    are checked against the arm there.
    """

    arm_file: Path | None = None
    outputs: tuple[int, ...] = DEFAULT_ARM_OUTPUTS
    pwm_min_us: int = DEFAULT_ARM_PWM_MIN_US
    pwm_max_us: int = DEFAULT_ARM_PWM_MAX_US
    reversed_joints: tuple[str, ...] = ()
    trims_us: Mapping[str, int] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if not isinstance(self.outputs, list | tuple):
            raise SimFieldError(
                "", "arm.outputs", f"must be a list of output numbers, got {self.outputs!r}"
            )
        outputs = tuple(self.outputs)
        for i, output in enumerate(outputs):
            _int(output, f"arm.outputs[{i}]", 1, OUTPUT_COUNT)
        if len(set(outputs)) != len(outputs):
            raise SimFieldError("", "arm.outputs", f"{list(outputs)} repeat an output")
        object.__setattr__(self, "outputs", outputs)
        for name in ("pwm_min_us", "pwm_max_us"):
            check_integer(
                getattr(self, name),
                f"arm.{name}",
                min_value=ARM_PWM_LIMIT_MIN_US,
                max_value=ARM_PWM_LIMIT_MAX_US,
                unit="µs",
                error=SimFieldError,
            )
        if not self.pwm_min_us < self.pwm_max_us:
            raise SimFieldError(
                "",
                "arm.pwm_min_us",
                f"{self.pwm_min_us} must be below arm.pwm_max_us = {self.pwm_max_us}",
            )
        # A bare string would otherwise be taken as a list of one-letter joint names.
        if not isinstance(self.reversed_joints, list | tuple | set | frozenset):
            raise SimFieldError(
                "", "arm.reversed", f"must be a list of joint names, got {self.reversed_joints!r}"
            )
        for name in self.reversed_joints:
            if not isinstance(name, str):
                raise SimFieldError("", "arm.reversed", f"{name!r} is not a joint name")
        object.__setattr__(self, "reversed_joints", tuple(self.reversed_joints))
        if not isinstance(self.trims_us, Mapping):
            raise SimFieldError(
                "",
                "arm.trims_us",
                f"must be a table of joint name = trim in µs, got {self.trims_us!r}",
            )
        # Beyond half the span the joint's mid-range (its neutral) would leave the PWM range.
        half_span_us = (self.pwm_max_us - self.pwm_min_us) // 2
        for name, trim_us in self.trims_us.items():
            if not isinstance(name, str):
                raise SimFieldError("", "arm.trims_us", f"key {name!r} is not a joint name")
            check_integer(
                trim_us,
                f"arm.trims_us.{name}",
                min_value=-half_span_us,
                max_value=half_span_us,
                unit="µs",
                error=SimFieldError,
            )
        object.__setattr__(self, "trims_us", dict(self.trims_us))


@dataclass(frozen=True)
class SimConfig:
    """Everything the simulated autopilot needs. ``functions`` maps output (1–16) → function."""

    flavour: str = "ardupilot"
    system_id: int = 1
    component_id: int = 1
    functions: Mapping[int, int] = field(default_factory=dict)
    servo: ServoConfig = field(default_factory=ServoConfig)
    arm: ArmConfig = field(default_factory=ArmConfig)
    faults: FaultConfig = field(default_factory=FaultConfig)
    vehicle: VehicleConfig = field(default_factory=VehicleConfig)
    link_timing: LinkTimingConfig = field(default_factory=LinkTimingConfig)
    px4_timing: Px4TimingConfig = field(default_factory=Px4TimingConfig)
    signing_key: bytes | None = None
    #: Parameter values at start (name → value), over the flavour's defaults; names are checked
    #: by the autopilot (:class:`~sim_servo.autopilot.SimAutopilot`), which knows them.
    params: Mapping[str, int] = field(default_factory=dict)
    #: PX4: armed at start (a pilot armed it). A reboot comes back disarmed, as PX4 does.
    armed: bool = False
    servo_output_rate_hz: float = 0.0
    #: SERVO_OUTPUT_RAW's shortest interval, whatever is asked; None: the flavour's (ArduPilot
    #: 20 ms, PX4 none).
    servo_output_min_interval_ms: int | None = None
    #: SYSTEM_TIME before any SET_MESSAGE_INTERVAL; None: the flavour's (ArduPilot 0, PX4 1 Hz).
    system_time_rate_hz: float | None = None
    #: ATTITUDE / LOCAL_POSITION_NED before any SET_MESSAGE_INTERVAL; None: the flavour's
    #: (ArduPilot 0, PX4 100 / 30 Hz).
    attitude_rate_hz: float | None = None
    local_position_rate_hz: float | None = None
    heartbeat_rate_hz: float = 1.0
    loop_rate_hz: float = 400.0
    #: Answer MAV_CMD_USER_2 as armbridge's Lua bridge script does (ArduPilot only).
    lua_script: bool = False

    def __post_init__(self) -> None:
        if not isinstance(self.flavour, str) or self.flavour not in FLAVOURS:
            raise SimFieldError(
                "", "flavour", f"{self.flavour!r} is not one of {', '.join(FLAVOURS)}"
            )
        if _bool(self.lua_script, "lua_script") and self.flavour != "ardupilot":
            raise SimFieldError(
                "", "lua_script", f"true needs flavour = 'ardupilot', not {self.flavour!r}"
            )
        _int(self.system_id, "system_id", 1, 255)
        _int(self.component_id, "component_id", 1, 255)
        functions = default_functions(self.flavour, self.arm.outputs)
        for output, function in dict(self.functions).items():
            if not is_int(output) or not 1 <= output <= OUTPUT_COUNT:
                raise SimFieldError(
                    "", f"outputs.{output}", f"output number {output!r} outside [1, {OUTPUT_COUNT}]"
                )
            functions[output] = _int(function, f"outputs.{output}", 0, 65535)
        object.__setattr__(self, "functions", functions)
        if not isinstance(self.params, Mapping):
            raise SimFieldError(
                "", "params", f"must be a table of name = integer, got {self.params!r}"
            )
        for name, value in self.params.items():
            if not isinstance(name, str) or not name:
                raise SimFieldError("", "params", f"parameter name {name!r} is not a name")
            _int(value, f"params.{name}", -(2**31), 2**31 - 1)
        object.__setattr__(self, "params", dict(self.params))
        _bool(self.armed, "armed")
        if self.signing_key is not None and (
            not isinstance(self.signing_key, bytes) or len(self.signing_key) != 32
        ):
            raise SimFieldError("", "signing_key", "must be 32 bytes")
        _real(self.servo_output_rate_hz, "servo_output_rate_hz", 0.0, 1000.0)
        if self.servo_output_min_interval_ms is not None:
            _int(self.servo_output_min_interval_ms, "servo_output_min_interval_ms", 0, 60_000)
        _optional_real(self.system_time_rate_hz, "system_time_rate_hz", 0.0, 1000.0)
        _optional_real(self.attitude_rate_hz, "attitude_rate_hz", 0.0, 1000.0)
        _optional_real(self.local_position_rate_hz, "local_position_rate_hz", 0.0, 1000.0)
        if not isinstance(self.vehicle, VehicleConfig):
            raise SimConfigError(f"vehicle={self.vehicle!r} must be a VehicleConfig")
        _real(self.heartbeat_rate_hz, "heartbeat_rate_hz", *HEARTBEAT_RATE_HZ)
        _real(self.loop_rate_hz, "loop_rate_hz", *LOOP_RATE_HZ)

    @property
    def servo_output_floor_ms(self) -> int:
        """SERVO_OUTPUT_RAW's shortest interval in force (the flavour's when not set)."""
        if self.servo_output_min_interval_ms is not None:
            return self.servo_output_min_interval_ms
        return ARDUPILOT_SERVO_OUTPUT_MIN_INTERVAL_MS if self.flavour == "ardupilot" else 0

    @property
    def system_time_default_hz(self) -> float:
        """SYSTEM_TIME's rate before any SET_MESSAGE_INTERVAL (the flavour's when not set)."""
        if self.system_time_rate_hz is not None:
            return self.system_time_rate_hz
        return DEFAULT_SYSTEM_TIME_RATE_HZ[self.flavour]

    @property
    def attitude_default_hz(self) -> float:
        """ATTITUDE's rate before any SET_MESSAGE_INTERVAL (the flavour's when not set)."""
        if self.attitude_rate_hz is not None:
            return self.attitude_rate_hz
        return DEFAULT_ATTITUDE_RATE_HZ[self.flavour]

    @property
    def local_position_default_hz(self) -> float:
        """LOCAL_POSITION_NED's rate before any SET_MESSAGE_INTERVAL (the flavour's when not
        set)."""
        if self.local_position_rate_hz is not None:
            return self.local_position_rate_hz
        return DEFAULT_LOCAL_POSITION_RATE_HZ[self.flavour]


def default_functions(flavour: str, arm_outputs: tuple[int, ...]) -> dict[int, int]:
    """The output function table of a quad carrying the arm, for ``flavour``."""
    functions = dict.fromkeys(range(1, OUTPUT_COUNT + 1), 0)
    if flavour == "ardupilot":
        functions.update(ARDUPILOT_MOTOR_FUNCTIONS)
    elif flavour == "px4":
        # PWM_MAIN_FUNC5..16 ship as 0: the arm's outputs are not mapped until someone sets
        # them (ready_setup() does).
        functions.update(PX4_MOTOR_FUNCTIONS)
    else:
        raise SimConfigError(f"flavour={flavour!r}; valid: {list(FLAVOURS)}")
    return functions


def ready_setup(flavour: str, arm_outputs: tuple[int, ...]) -> dict[str, Any]:
    """The settings (TOML keys) of a vehicle set up for the arm: PX4 — the arm's outputs on
    functions 301–306 in joint order, ``COM_PREARM_MODE`` 2, forwarding on both links, armed
    at start; ArduPilot — none (its safety switch is off by default)."""
    if flavour == "ardupilot":
        return {}
    if flavour != "px4":
        raise SimConfigError(f"flavour={flavour!r}; valid: {list(FLAVOURS)}")
    outputs = {
        str(output): PX4_ACTUATOR_SET_FIRST_FUNCTION + index
        for index, output in enumerate(arm_outputs[:PX4_ACTUATOR_SET_COUNT])
    }
    params = {"COM_PREARM_MODE": 2, "MAV_0_FORWARD": 1, "MAV_1_FORWARD": 1}
    return {"outputs": outputs, "params": params, "armed": True}


def load_key(path: str | Path) -> bytes:
    """A 32-byte signing key from a file: 32 raw bytes or 64 hex digits."""
    try:
        data = Path(path).read_bytes()
    except OSError as exc:
        raise SimConfigError(f"cannot read signing key file {str(path)!r}: {exc}") from exc
    if len(data) == 32:
        return data
    text = data.strip()
    if len(text) == 64:
        try:
            return bytes.fromhex(text.decode("ascii"))
        except (UnicodeDecodeError, ValueError):
            pass
    raise SimConfigError(
        f"signing key file {str(path)!r} holds {len(data)} bytes; expected 32 raw bytes or 64 hex "
        "digits"
    )


_TOP_KEYS = {
    "flavour",
    "system_id",
    "component_id",
    "servo_output_rate_hz",
    "servo_output_min_interval_ms",
    "system_time_rate_hz",
    "attitude_rate_hz",
    "local_position_rate_hz",
    "heartbeat_rate_hz",
    "loop_rate_hz",
    "lua_script",
    "signing_key_file",
    "vehicle",
    "armed",
    "params",
    "px4_timing",
    "outputs",
    "servo",
    "arm",
    "faults",
    "link_timing",
}
_FAULT_KEYS = {
    "drop_in",
    "drop_out",
    "corrupt_in",
    "corrupt_out",
    "latency_ms",
    "jitter_ms",
    "heartbeat_pause_after_s",
    "heartbeat_pause_for_s",
    "withhold_ack",
    "nack_outputs",
    "hangup_after_s",
    "hangup_for_s",
    "reboot_after_s",
    "reboot_gap_s",
    "seed",
}
_ARM_KEYS = {"file", "outputs", "pwm_min_us", "pwm_max_us", "reversed", "trims_us"}


def parse_withhold(values: list[Any] | str, source: str = "") -> tuple[frozenset[int], bool]:
    """``"all"`` or a list of command ids / names (``DO_SET_SERVO``, ``183``)."""
    from pymavlink.dialects.v20 import ardupilotmega as mavlink

    if values == "all" or (isinstance(values, list) and "all" in values):
        return frozenset(), True
    commands = set()
    for value in values if isinstance(values, list) else [values]:
        if isinstance(value, int) and not isinstance(value, bool):
            commands.add(value)
            continue
        text = str(value).strip().upper()
        if text.isdigit():
            commands.add(int(text))
            continue
        name = text if text.startswith("MAV_CMD_") else f"MAV_CMD_{text}"
        number = getattr(mavlink, name, None)
        if not isinstance(number, int):
            raise SimFieldError(
                source,
                "faults.withhold_ack",
                f"{value!r} is not a command id, MAV_CMD name or 'all'",
            )
        commands.add(number)
    return frozenset(commands), False


def config_from_mapping(
    data: Mapping[str, Any], source: str = "<dict>", base_dir: Path | None = None
) -> SimConfig:
    """Build a :class:`SimConfig` from the TOML structure; paths are relative to ``base_dir``.
    Every refusal is a :class:`SimFieldError` naming ``source`` and the dotted field."""
    try:
        return _config_from_mapping(
            Table(data, source, allowed=_TOP_KEYS, error=SimFieldError), base_dir
        )
    except SimFieldError as exc:
        # The settings classes check their own values, before the file is known.
        raise exc if exc.source else exc.at(source) from None


def _fields(cls: Any) -> tuple[str, ...]:
    return tuple(f.name for f in fields(cls))


def _config_from_mapping(root: Table, base_dir: Path | None) -> SimConfig:
    kwargs: dict[str, Any] = {}
    for key in (
        "flavour",
        "system_id",
        "component_id",
        "servo_output_rate_hz",
        "servo_output_min_interval_ms",
        "system_time_rate_hz",
        "attitude_rate_hz",
        "local_position_rate_hz",
        "heartbeat_rate_hz",
        "loop_rate_hz",
        "lua_script",
        "armed",
    ):
        if key in root:
            kwargs[key] = root.data[key]
    kwargs["params"] = dict(root.table("params").data)
    if "signing_key_file" in root:
        kwargs["signing_key"] = load_key(_resolve(root.string("signing_key_file"), base_dir))
    outputs = root.table("outputs")
    functions = {}
    for key, function in outputs.data.items():
        try:
            output = int(key)
        except ValueError:
            raise outputs.fail(key, f"{key!r} is not an output number (1-{OUTPUT_COUNT})") from None
        functions[output] = function
    kwargs["functions"] = functions
    kwargs["servo"] = ServoConfig(**root.table("servo", allowed=_fields(ServoConfig)).data)
    arm = root.table("arm", allowed=_ARM_KEYS)
    kwargs["arm"] = ArmConfig(
        arm_file=_resolve(arm.string("file"), base_dir) if "file" in arm else None,
        outputs=arm.data.get("outputs", DEFAULT_ARM_OUTPUTS),
        pwm_min_us=arm.data.get("pwm_min_us", DEFAULT_ARM_PWM_MIN_US),
        pwm_max_us=arm.data.get("pwm_max_us", DEFAULT_ARM_PWM_MAX_US),
        reversed_joints=arm.data.get("reversed", ()),
        trims_us=arm.data.get("trims_us", {}),
    )
    fault_table = root.table("faults", allowed=_FAULT_KEYS)
    faults = dict(fault_table.data)
    if "withhold_ack" in faults:
        commands, all_acks = parse_withhold(faults.pop("withhold_ack"), root.source)
        faults["withhold_ack_commands"], faults["withhold_all_acks"] = commands, all_acks
    if "nack_outputs" in faults:
        nack = faults["nack_outputs"]
        if not isinstance(nack, list) or not all(is_int(output) for output in nack):
            raise fault_table.fail(
                "nack_outputs", f"must be a list of output numbers, got {nack!r}"
            )
        faults["nack_outputs"] = frozenset(nack)
    kwargs["faults"] = FaultConfig(**faults)
    vehicle_table = root.table("vehicle", allowed=_fields(VehicleConfig))
    vehicle = dict(vehicle_table.data)
    vehicle["mount"] = MountConfig(
        **vehicle_table.table("mount", allowed=_fields(MountConfig)).data
    )
    kwargs["vehicle"] = VehicleConfig(**vehicle)
    kwargs["link_timing"] = LinkTimingConfig(
        **root.table("link_timing", allowed=_fields(LinkTimingConfig)).data
    )
    kwargs["px4_timing"] = Px4TimingConfig(
        **root.table("px4_timing", allowed=_fields(Px4TimingConfig)).data
    )
    return SimConfig(**kwargs)


def _resolve(path: str, base_dir: Path | None) -> Path:
    candidate = Path(path).expanduser()
    if not candidate.is_absolute() and base_dir is not None:
        candidate = base_dir / candidate
    return candidate


def load_toml(path: str | Path) -> dict[str, Any]:
    """Read a simulator TOML file into a plain dict (validated by :func:`config_from_mapping`);
    an unreadable or invalid file raises :class:`SimFieldError` naming it."""
    return tomlfields.load_toml(path, SimFieldError)
