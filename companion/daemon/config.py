"""The daemon's configuration file (TOML): schema, defaults, validation.

Everything is checked at load time, before anything is opened or sent. An error is a
:class:`~companion.errors.ConfigError` that names the file, the field (``link.url``,
``joint[3].pwm_max_us``) and the allowed values; ``armbridge run`` and ``check-config`` turn it
into exit code 2. The schema is documented in ``docs/configuration.md`` and in the
example ``companion/daemon/examples/armbridge.toml``.
"""

from __future__ import annotations

import functools
import grp
import math
import os
import stat
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from companion.errors import ArmConfigError, ConfigError, JointLimitError
from companion.kinematics.arm import Arm
from companion.kinematics.collision import Box, Capsule, Cylinder, KeepOut, Sphere, Volume
from companion.kinematics.vehicle import Mount
from firmware_interface import (
    SERVO_DIALECTS,
    ArmCalibration,
    FirmwareInterfaceError,
    InvalidUrl,
    JointCalibration,
    LinkConfig,
    SigningConfig,
    parse_url,
)
from firmware_interface.calibration import (
    ANGLE_LIMIT_DEG,
    OUTPUT_MAX,
    OUTPUT_MIN,
    PWM_LIMIT_MAX_US,
    PWM_LIMIT_MIN_US,
)
from firmware_interface.errors import CalibrationError, PwmOutOfRange, SettingError
from firmware_interface.link_budget import LinkBudget, link_budget
from tomlfields import Table, load_toml

if TYPE_CHECKING:
    from companion.ik import SolverSettings

DEFAULT_OUTPUTS = (9, 10, 11, 12, 13, 14)  # outputs 1–4 drive a quad's motors

# -- Bounds of the numbers, each with its physical reason (also in the example config and the
# docs/configuration.md). A bound is (min, max); None for min means "> 0".

#: The control loop's rate. 1 Hz: the service counts itself healthy while it ticked within
#: 2 / rate_hz + 1 s, which must stay inside the shipped unit's WatchdogSec=5: 3 s at 1 Hz,
#: 5 s at 0.5 Hz.
#: 400 Hz: ArduPilot's copter main loop (SCHED_LOOP_RATE) and a digital servo's frame rate;
#: updates faster than that are never executed (and a serial link tops out near it:
#: docs/ardupilot.md).
RATE_HZ = (1.0, 400.0)
#: The autopilot's HEARTBEAT comes at 1 Hz: below 2 s one lost or late heartbeat would be
#: taken for a lost link (and stop the arm). Above 60 s the arm keeps commanding a dead link.
LOSS_TIMEOUT_S = (2.0, 60.0)
#: No ACK comes back in under a millisecond, even on loopback; 60 s is past any radio's delay.
COMMAND_TIMEOUT_S = (0.001, 60.0)
#: Resends after the first attempt of one servo command.
COMMAND_RETRIES = (0, 10)
#: One servo command is given up after (retries + 1) × command_timeout_s, and a target waiting on
#: it is answered no later: over a minute, its sender (and the watchdog of whoever waits) has
#: long given up, whatever each number says.
COMMAND_WAIT_MAX_S = 60.0
#: The solve runs on the control thread (no tick meanwhile), and a target on a flying drone
#: that takes over a second to solve is stale.
BUDGET_MS = (None, 1000.0)
#: 1e-6 cm and 1e-6 deg sit far above float64 FK noise (~1e-12) and far below what a 1 µs PWM
#: step moves the hand (~0.1 cm, 0.18 deg). 10 cm is the size of a hand: farther off, the arm
#: is not at the target; 180 deg is the largest orientation error there is (position only).
TOL_POS_CM = (1e-6, 10.0)
TOL_ORI_DEG = (1e-6, 180.0)
#: The solver's search methods: the names of companion.ik.METHODS (a test keeps the two equal;
#: named here so that check-config starts without the solver).
SOLVER_METHODS = ("restarts", "memetic", "de")
#: The default method (companion.ik.DEFAULT_METHOD; the same test keeps the two equal).
SOLVER_METHOD = "restarts"
#: The search's settings (``solver.method`` and the rest; the defaults are the method's own,
#: companion.ik.METHODS). NP: the individuals drawn at each restart, and DE's population;
#: DE rand/1 draws three others besides each individual: 4 at least. The papers' populations
#: went to 30; at 100 one generation is ~30 µs of evaluations.
POP_SIZE = (4, 100)
#: DE's scale factor F: 0 would not move; past 2 a difference vector overshoots the joint box.
MUTATION_F = (None, 2.0)
#: DE's crossover probability Cr (binomial; one coordinate always comes from the donor).
CROSSOVER_CR = (0.0, 1.0)
#: Least-squares steps per refinement ("restarts" and "memetic"; 0: none). LM hands over to
#: the next restart or DE generation when a few steps did not cut the cost; 100 steps from
#: one start is past converging.
LM_ITERATIONS = (0, 100)
#: Generations in a row without progress before the population is drawn anew (a restart;
#: "memetic" and "de": "restarts" draws it anew at every generation); 10 000 generations are
#: past any budget (~1 µs each at the least).
STALL_GENERATIONS = (1, 10_000)
#: A generation makes progress when it brings the best cost below this times what it was:
#: 0 counts none (restart after every ``stall_generations``), 1 counts any improvement.
STALL_GAIN = (0.0, 1.0)
#: Fast hobby servos turn 60 deg in 0.06 s (1000 deg/s); a higher limit limits nothing. Below
#: 1 deg/s a joint takes three minutes to cross a 180 deg range: the arm would hang mid-motion
#: long after its target went stale (and 1e-300 is a typo, not a speed).
JOINT_SPEED_DEG_S = (1.0, 1000.0)
#: The control socket's connections: each holds at most a ~370 KiB request line (a 2 000-point
#: trajectory) and 64 KiB of queued replies (control_socket.MAX_LINE_BYTES,
#: MAX_QUEUED_REPLY_BYTES), so 256 bound the socket's buffers to ~110 MiB; onboard software
#: needs a handful.
MAX_CONNECTIONS = (1, 256)
#: A connection that completes no request for this long is closed. 0.1 s is already shorter
#: than a loaded board may take between connecting and sending; past an hour a dead client
#: holds its slot all day.
IDLE_TIMEOUT_S = (0.1, 3600.0)
#: A trim corrects a horn's mounting (one spline tooth is 80-130 us); past 500 us, half a
#: standard 1000-2000 us servo's travel, it is a different calibration: set pwm_min/max_us.
TRIM_US_MAX = 500
#: Keep-out volumes and the mount sit on the vehicle: a coordinate beyond 10 m of its body
#: origin, or a volume larger than that, is a typo (a unit slip), not a drone.
VEHICLE_EXTENT_CM = 1000.0
#: The clearance kept between the arm's link capsules and every keep-out volume. 0 trusts the
#: shapes exactly; past 50 cm, a small arm under a quad could not move at all.
KEEPOUT_MARGIN_CM = (0.0, 50.0)


@dataclass(frozen=True)
class LinkSettings:
    """How to reach the flight controller (see firmware_interface.LinkConfig)."""

    url: str
    dialect: str = "ardupilot"
    system_id: int | None = None
    component_id: int = 191
    target_system: int | None = None
    target_component: int | None = None
    loss_timeout_s: float = 3.0
    command_timeout_s: float = 0.5
    command_retries: int = 2
    signing: SigningConfig | None = None
    #: Who may send MAVLink targets: (system id, component id) pairs; None: anyone routed to us.
    allowed_senders: frozenset[tuple[int, int]] | None = None


def link_config(settings: LinkSettings) -> LinkConfig:
    """The link's own settings from the daemon's (``run`` and ``doctor`` open the same link)."""
    return LinkConfig(
        system_id=settings.system_id,
        component_id=settings.component_id,
        target_system=settings.target_system,
        target_component=settings.target_component,
        loss_timeout_s=settings.loss_timeout_s,
        signing=settings.signing,
    )


@dataclass(frozen=True)
class WorldSettings:
    """``[world]``: world-frame targets.

    ``enabled``: the daemon asks the autopilot for ATTITUDE and LOCAL_POSITION_NED at
    ``telemetry_hz`` and takes targets in LOCAL_NED (off by default: on a serial link the two
    streams cost 80 bytes each a frame). ``lead_ms``: how far ahead of the link's own latency
    (half an update's measured round trip) the vehicle's motion is predicted: the servo's
    response. ``max_age_ms``: telemetry older than this is not followed (the arm holds and
    status says why).
    """

    enabled: bool = False
    telemetry_hz: float = 50.0
    lead_ms: float = 20.0
    max_age_ms: float = 200.0


@dataclass(frozen=True)
class DaemonConfig:
    """A validated daemon configuration."""

    source: str
    link: LinkSettings
    arm: Arm
    calibration: ArmCalibration
    budget_ms: float = 20.0
    tol_pos_cm: float = 0.01
    tol_ori_deg: float = 0.1
    seed: int | None = None
    #: ``solver.method``, and the search settings the file sets over the method's own, as
    #: sorted (SolverSettings field, value) pairs (see :attr:`search_settings`).
    solver_method: str = SOLVER_METHOD
    solver_settings: tuple[tuple[str, float], ...] = ()
    rate_hz: float = 20.0
    joint_speed_deg_s: float = 60.0
    park_deg: tuple[float, ...] | None = None
    park_on_stop: bool = False
    #: Where the daemon keeps the PWMs the outputs were left at, for its next start
    #: (:mod:`companion.daemon.pose_file`); None: not kept.
    pose_file: str | None = None
    #: The control socket's absolute path (a relative one in the file counts from the file's
    #: directory); None: no socket.
    control_socket: str | None = None
    #: The group the socket belongs to (mode 0660): its members may use it, and so may root
    #: and the daemon's own user. None: the daemon's primary group.
    control_socket_group: str | None = None
    control_max_connections: int = 32
    control_idle_timeout_s: float = 30.0
    #: After an autopilot reboot, go on towards the goal accepted before it (default: the
    #: goal is dropped; the operator sends it again).
    resume_after_reboot: bool = False
    #: Where the arm's base sits in the vehicle's body frame FRD (``[mount]``).
    mount: Mount = Mount()
    #: Keep-out volumes in the body frame FRD (``[[keepout]]``); none by default.
    keepout: tuple[Volume, ...] = ()
    #: Clearance kept from every keep-out volume (``safety.keepout_margin_cm``).
    keepout_margin_cm: float = 1.0

    #: World-frame targets (``[world]``): the hand held in LOCAL_NED while the vehicle moves.
    world: WorldSettings = WorldSettings()

    @functools.cached_property
    def search_settings(self) -> SolverSettings:
        """The solver's settings: one object per config, built at first use (the solver keeps
        its arrays and estimates from call to call for one object; check-config never loads
        the solver)."""
        from companion.ik import method_settings

        return method_settings(self.solver_method, **dict(self.solver_settings))

    def keepout_check(self) -> KeepOut:
        """The arm, mount, volumes and margin, prepared for the keep-out checks."""
        return KeepOut(self.arm, self.keepout, self.mount, self.keepout_margin_cm)


_SECTIONS = ("link", "arm", "solver", "control", "joint", "mount", "safety", "keepout", "world")
_WORLD_KEYS = ("enabled", "telemetry_hz", "lead_ms", "max_age_ms")
_MOUNT_KEYS = ("xyz_cm", "rpy_deg")
_SAFETY_KEYS = ("keepout_margin_cm",)
#: Per keep-out volume type, its fields besides ``name`` and ``type``.
_KEEPOUT_KEYS = {
    "sphere": ("center_cm", "radius_cm"),
    "capsule": ("from_cm", "to_cm", "radius_cm"),
    "box": ("center_cm", "size_cm", "rpy_deg"),
    "cylinder": ("center_cm", "radius_cm", "length_cm", "rpy_deg"),
}
_LINK_KEYS = (
    "url",
    "dialect",
    "system_id",
    "component_id",
    "target_system",
    "target_component",
    "loss_timeout_s",
    "command_timeout_s",
    "command_retries",
    "signing_key",
    "signing_link_id",
    "signing_state",
    "allowed_senders",
)
_ARM_KEYS = ("file", "tip_link", "park_deg", "park_on_stop", "joint_speed_deg_s", "pose_file")
#: ``[solver]``'s search settings: key → the SolverSettings field it sets.
_SEARCH_FIELDS = {
    "pop_size": "pop_size",
    "mutation_f": "F",
    "crossover_cr": "Cr",
    "lm_iterations": "lm_iterations",
    "stall_generations": "stall_generations",
    "stall_gain": "stall_gain",
}
_SOLVER_KEYS = ("budget_ms", "tol_pos_cm", "tol_ori_deg", "seed", "method", *_SEARCH_FIELDS)
_CONTROL_KEYS = (
    "rate_hz",
    "socket",
    "socket_group",
    "max_connections",
    "idle_timeout_s",
    "resume_after_reboot",
)
_JOINT_KEYS = (
    "name",
    "output",
    "pwm_min_us",
    "pwm_max_us",
    "angle_min_deg",
    "angle_max_deg",
    "reversed",
    "trim_us",
)


def load_config(path: str | Path) -> DaemonConfig:
    """Read and validate the daemon config at ``path``."""
    return parse_config(load_toml(path, ConfigError), source=str(path))


def parse_config(data: dict, *, source: str = "<dict>") -> DaemonConfig:
    root = Table(data, source, allowed=_SECTIONS, error=ConfigError)
    base = Path(source).parent if source != "<dict>" else Path.cwd()
    link = _parse_link(root.table("link", allowed=_LINK_KEYS), base)

    arm_table = root.table("arm", allowed=_ARM_KEYS)
    tip_link = arm_table.string("tip_link") if "tip_link" in arm_table else None
    if "file" in arm_table:
        arm_path = base / arm_table.string("file")
        if tip_link is not None and arm_path.suffix.lower() != ".urdf":
            raise arm_table.fail("tip_link", 'set only with a URDF arm file (file = "*.urdf")')
        try:
            if arm_path.suffix.lower() == ".urdf":
                arm = Arm.from_urdf(arm_path, tip_link=tip_link)
            else:
                arm = Arm.from_toml(arm_path, dof=None)
        except ArmConfigError as exc:
            raise arm_table.fail("file", f"arm file {exc}") from exc
        prismatic = [j.name for j in arm.joints if not j.revolute]
        if prismatic:
            # A servo output maps an angle range to PWM; a slider's calibration (cm ↔ PWM)
            # is not written yet. The solver API takes such arms (companion.ik.solve).
            raise arm_table.fail(
                "file",
                f"joint {prismatic[0]} is prismatic: the daemon drives revolute joints only "
                "(companion.ik.solve takes prismatic arms)",
            )
    else:
        if tip_link is not None:
            raise arm_table.fail("tip_link", 'set only with a URDF arm file (file = "*.urdf")')
        arm = Arm.default()
    park = None
    if "park_deg" in arm_table:
        park = tuple(arm_table.numbers("park_deg", length=arm.dof))
        try:
            arm.check_limits(park)
        except JointLimitError as exc:
            raise arm_table.fail("park_deg", str(exc)) from exc

    solver = root.table("solver", allowed=_SOLVER_KEYS)
    control = root.table("control", allowed=_CONTROL_KEYS)
    socket_path = _socket_path(control, base)
    if socket_path is None:
        for key in ("socket_group", "max_connections", "idle_timeout_s"):
            if key in control:
                raise control.fail(key, 'set with control.socket = "" (there is no socket)')
    calibration = _parse_calibration(root, arm)
    _check_pwm_covers_arm(source, arm, calibration, park)
    mount = _parse_mount(root.table("mount", allowed=_MOUNT_KEYS))
    volumes = _parse_keepout(root, arm)
    margin = root.table("safety", allowed=_SAFETY_KEYS).number(
        "keepout_margin_cm", 1.0, min_value=KEEPOUT_MARGIN_CM[0], max_value=KEEPOUT_MARGIN_CM[1]
    )
    _check_rest_pose_clear(root, arm, park, KeepOut(arm, volumes, mount, margin))
    return DaemonConfig(
        source=source,
        link=link,
        arm=arm,
        calibration=calibration,
        budget_ms=_bounded(solver, "budget_ms", 20.0, BUDGET_MS),
        tol_pos_cm=_bounded(solver, "tol_pos_cm", 0.01, TOL_POS_CM),
        tol_ori_deg=_bounded(solver, "tol_ori_deg", 0.1, TOL_ORI_DEG),
        seed=solver.integer("seed", min_value=0) if "seed" in solver else None,
        solver_method=solver.string("method", SOLVER_METHOD, choices=SOLVER_METHODS),
        solver_settings=search_changes(solver),
        rate_hz=_bounded(control, "rate_hz", 20.0, RATE_HZ),
        joint_speed_deg_s=_bounded(arm_table, "joint_speed_deg_s", 60.0, JOINT_SPEED_DEG_S),
        park_deg=park,
        park_on_stop=arm_table.boolean("park_on_stop", False),
        pose_file=_pose_file(arm_table, base),
        control_socket=socket_path,
        control_socket_group=_group(control, "socket_group") if "socket_group" in control else None,
        control_max_connections=control.integer(
            "max_connections", 32, min_value=MAX_CONNECTIONS[0], max_value=MAX_CONNECTIONS[1]
        ),
        control_idle_timeout_s=_bounded(control, "idle_timeout_s", 30.0, IDLE_TIMEOUT_S),
        resume_after_reboot=control.boolean("resume_after_reboot", False),
        mount=mount,
        keepout=volumes,
        keepout_margin_cm=margin,
        world=_parse_world(root.table("world", allowed=_WORLD_KEYS)),
    )


#: ArduPilot streams a message at most at its main loop's rate; 50 Hz is what SERVO_OUTPUT_RAW
#: reached when 400 Hz was asked, so more is not asked for.
TELEMETRY_HZ = (1.0, 50.0)
LEAD_MS = (0.0, 500.0)
MAX_AGE_MS = (10.0, 2000.0)


def _parse_world(t: Table) -> WorldSettings:
    return WorldSettings(
        enabled=t.boolean("enabled", False),
        telemetry_hz=t.number(
            "telemetry_hz", 50.0, min_value=TELEMETRY_HZ[0], max_value=TELEMETRY_HZ[1]
        ),
        lead_ms=t.number("lead_ms", 20.0, min_value=LEAD_MS[0], max_value=LEAD_MS[1]),
        max_age_ms=t.number("max_age_ms", 200.0, min_value=MAX_AGE_MS[0], max_value=MAX_AGE_MS[1]),
    )


def _vehicle_point(
    t: Table, key: str, default: list[float] | None = None
) -> tuple[float, float, float]:
    """3 numbers (cm) within :data:`VEHICLE_EXTENT_CM` of the body origin."""
    x, y, z = t.numbers(
        key,
        *(() if default is None else (default,)),
        length=3,
        min_value=-VEHICLE_EXTENT_CM,
        max_value=VEHICLE_EXTENT_CM,
        unit="cm (body frame)",
    )
    return (x, y, z)


def _angles(t: Table, key: str) -> tuple[float, float, float]:
    roll, pitch, yaw = t.numbers(
        key, [0.0, 0.0, 0.0], length=3, min_value=-360.0, max_value=360.0, unit="deg"
    )
    return (roll, pitch, yaw)


def _size(t: Table, key: str) -> float:
    return t.number(key, max_value=VEHICLE_EXTENT_CM, positive=True, unit="cm")


def _parse_mount(t: Table) -> Mount:
    """``[mount]``: the arm base in body FRD (default: 10 cm under the body origin, base axes
    along the body's)."""
    xyz = _vehicle_point(t, "xyz_cm", [0.0, 0.0, 10.0])
    return Mount(xyz, _angles(t, "rpy_deg"))


def _parse_keepout(root: Table, arm: Arm) -> tuple[Volume, ...]:
    """``[[keepout]]``: named volumes in body FRD (cm, degrees); none if absent."""
    if "keepout" not in root or root.data["keepout"] == []:
        return ()
    rows = root.tables("keepout")
    volumes: list[Volume] = []
    seen: dict[str, int] = {}
    for index, row in enumerate(rows, start=1):
        kind = row.string("type", choices=tuple(_KEEPOUT_KEYS))
        row.allow(("name", "type", *_KEEPOUT_KEYS[kind]))
        name = row.string("name")
        if name in seen:
            raise row.fail("name", f"{name!r} is already the name of keepout[{seen[name]}]")
        seen[name] = index
        volume: Volume
        if kind == "sphere":
            volume = Sphere(name, _vehicle_point(row, "center_cm"), _size(row, "radius_cm"))
        elif kind == "capsule":
            volume = Capsule(
                name,
                _vehicle_point(row, "from_cm"),
                _vehicle_point(row, "to_cm"),
                _size(row, "radius_cm"),
            )
        elif kind == "box":
            size = _vehicle_point(row, "size_cm")
            for i, v in enumerate(size):
                if not v > 0:
                    raise row.fail(f"size_cm[{i}]", f"{v:g} must be > 0")
            volume = Box(name, _vehicle_point(row, "center_cm"), size, _angles(row, "rpy_deg"))
        elif kind == "cylinder":
            volume = Cylinder(
                name,
                _vehicle_point(row, "center_cm"),
                _size(row, "radius_cm"),
                _size(row, "length_cm"),
                _angles(row, "rpy_deg"),
            )
        else:  # pragma: no cover - string(choices=) refused it
            raise row.fail("type", f"{kind!r}")
        volumes.append(volume)
    if not arm.has_shapes:
        raise root.fail(
            "keepout",
            f"arm {arm.name} has no link shapes: keep-out volumes need them (link_radius or "
            "capsules in the arm file, <collision> in a URDF)",
        )
    return tuple(volumes)


def start_pose_deg(arm: Arm, park_deg: tuple[float, ...] | None) -> tuple[float, ...]:
    """Where the daemon assumes the arm is before any acknowledgement: the park pose, else
    the middle of every joint's range (as the control core does)."""
    if park_deg is not None:
        return park_deg
    return tuple(math.degrees((j.min_rad + j.max_rad) / 2) for j in arm.joints)


def _check_rest_pose_clear(
    root: Table, arm: Arm, park_deg: tuple[float, ...] | None, keepout: KeepOut
) -> None:
    """The park pose (or, without one, the assumed start pose) keeps the margin from every
    keep-out volume: the arm starts there, and goes there on ``park``."""
    pose = start_pose_deg(arm, park_deg)
    hit = keepout.check(arm.q_from_user(pose), reference=True)  # no numba in check-config
    if hit is None:
        return
    index = next(i for i, v in enumerate(keepout.volumes, start=1) if v.name == hit.volume)
    what = (
        f"arm.park_deg {list(pose)}"
        if park_deg is not None
        else f"the start pose {[round(a, 3) for a in pose]} (the middle of each joint's range; "
        "set arm.park_deg)"
    )
    raise root.fail(
        f"keepout[{index}]",
        f"{what} is not clear: {hit.reason}",
    )


#: ``[solver]`` keys only some methods use: key → (those methods, why not the others). The
#: same rules as ``companion.ik.method_settings``, named here for check-config.
_SEARCH_KEY_METHODS = {
    "mutation_f": (("memetic", "de"), '"restarts" runs no DE generation'),
    "crossover_cr": (("memetic", "de"), '"restarts" runs no DE generation'),
    "stall_generations": (
        ("memetic", "de"),
        '"restarts" draws the population anew at every generation',
    ),
    "stall_gain": (("memetic", "de"), '"restarts" draws the population anew at every generation'),
    "lm_iterations": (("restarts", "memetic"), '"de" runs no least-squares steps'),
}


def search_changes(t: Table) -> tuple[tuple[str, float], ...]:
    """``[solver]``'s search settings, each checked against its bounds, as sorted
    (SolverSettings field, value) pairs over the method's own (``companion.ik.method_settings``
    takes them). ``armbridge solve`` checks its flags with this too (a table of them, its
    errors naming the flag)."""
    method = t.string("method", SOLVER_METHOD, choices=SOLVER_METHODS)
    for key, (users, why) in _SEARCH_KEY_METHODS.items():
        if key in t and method not in users:
            named = " or ".join(f'"{m}"' for m in users)
            raise t.fail(key, f"goes with method = {named} ({why})")
    changes: dict[str, float] = {}
    for key, (low, high) in (
        ("pop_size", POP_SIZE),
        ("lm_iterations", LM_ITERATIONS),
        ("stall_generations", STALL_GENERATIONS),
    ):
        if key in t:
            changes[_SEARCH_FIELDS[key]] = t.integer(key, min_value=low, max_value=high)
    for key, bounds in (
        ("mutation_f", MUTATION_F),
        ("crossover_cr", CROSSOVER_CR),
        ("stall_gain", STALL_GAIN),
    ):
        if key in t:
            changes[_SEARCH_FIELDS[key]] = _bounded(t, key, 0.0, bounds)
    return tuple(sorted(changes.items()))


def _bounded(t: Table, key: str, default: float, bounds: tuple[float | None, float]) -> float:
    low, high = bounds
    return t.number(key, default, min_value=low, max_value=high, positive=low is None)


# A Unix socket's path must fit sockaddr_un.sun_path (108 bytes on Linux, with its NUL).
SOCKET_PATH_MAX_BYTES = 107


#: Where the control socket is when the config does not say: the directory the shipped unit's
#: ``RuntimeDirectory=armbridge`` makes, and the CLI's default (``ARMBRIDGE_SOCKET`` overrides
#: the CLI's side only).
DEFAULT_CONTROL_SOCKET = "/run/armbridge/control.sock"


def _pose_file(t: Table, base: Path) -> str | None:
    """``arm.pose_file``, absolute (relative: from the config file's directory); its directory
    must exist (systemd's ``StateDirectory=`` makes /var/lib/armbridge)."""
    if "pose_file" not in t:
        return None
    path = os.path.abspath(base / t.string("pose_file"))
    if not os.path.isdir(os.path.dirname(path)):
        raise t.fail("pose_file", f"directory {os.path.dirname(path)} does not exist")
    return path


def _socket_path(t: Table, base: Path) -> str | None:
    """``control.socket``, absolute (a relative path counts from the config file's directory,
    like every other path in it); :data:`DEFAULT_CONTROL_SOCKET` when absent; None for ``""``
    (no socket: MAVLink targets only). Checked as ``run`` would use it: it fits ``sun_path``,
    its directory exists or this user can create it (``run`` makes a missing last directory,
    mode 0750, as systemd's ``RuntimeDirectory=`` would), and whatever is at the path already
    is a socket (``run`` replaces only a stale socket of its own; it also refuses one that a
    live daemon listens on, which a static check cannot tell from a stale one)."""
    if t.data.get("socket") == "":
        return None
    path = os.path.abspath(base / t.string("socket", DEFAULT_CONTROL_SOCKET))
    size = len(os.fsencode(path))
    if size > SOCKET_PATH_MAX_BYTES:
        raise t.fail(
            "socket",
            f"path {path} is {size} bytes, a Unix socket path takes at most "
            f"{SOCKET_PATH_MAX_BYTES}",
        )
    directory = os.path.dirname(path)
    if not os.path.isdir(directory):
        parent = os.path.dirname(directory)
        if not os.path.isdir(parent):
            raise t.fail("socket", f"directory {directory} does not exist (for {path})")
        if not os.access(parent, os.W_OK | os.X_OK):
            # systemd's RuntimeDirectory= makes /run/armbridge when the service starts (and
            # removes it when it stops); a foreground run must be able to make it itself.
            raise t.fail(
                "socket",
                f"directory {directory} does not exist and this user cannot create it in "
                f"{parent} (the service's RuntimeDirectory= makes it; check as root, or set "
                'control.socket to a path of yours, or "" for no socket)',
            )
    try:
        mode = os.lstat(path).st_mode
    except FileNotFoundError:
        return path
    except OSError as exc:
        raise t.fail("socket", f"cannot check {path}: {exc.strerror or exc}") from exc
    if not stat.S_ISSOCK(mode):
        raise t.fail(
            "socket",
            f"{path} exists and is not a socket ({file_kind(mode)}): the daemon replaces only a "
            "stale socket of its own; move it away or choose another path",
        )
    return path


def file_kind(mode: int) -> str:
    """What a file of ``st_mode`` ``mode`` is, in words (for messages)."""
    for test, kind in (
        (stat.S_ISREG, "a regular file"),
        (stat.S_ISDIR, "a directory"),
        (stat.S_ISLNK, "a symbolic link"),
        (stat.S_ISFIFO, "a FIFO"),
        (stat.S_ISCHR, "a character device"),
        (stat.S_ISBLK, "a block device"),
        (stat.S_ISSOCK, "a socket"),
    ):
        if test(mode):
            return kind
    return f"mode {mode:o}"


def _group(t: Table, key: str) -> str:
    """A group name that exists on this system (the daemon gives its socket to it)."""
    name = t.string(key)
    try:
        grp.getgrnam(name)
    except KeyError:
        raise t.fail(
            key, f"no group {name!r} on this system (create it: groupadd {name})"
        ) from None
    return name


def _parse_link(t: Table, base: Path) -> LinkSettings:
    url = t.string("url")
    try:
        parse_url(url)
    except InvalidUrl as exc:
        raise t.fail("url", str(exc)) from exc
    signing = None
    if "signing_key" in t:
        key_path = _signing_key_path(t, base)
        state = base / t.string("signing_state") if "signing_state" in t else None
        try:
            signing = SigningConfig.from_key_file(
                key_path,
                link_id=t.integer("signing_link_id", 0, min_value=0, max_value=255),
                state_path=state,
            )
        except FirmwareInterfaceError as exc:
            raise t.fail("signing_key", str(exc)) from exc
    elif "signing_state" in t or "signing_link_id" in t:
        raise t.fail("signing_key", "missing: signing_state / signing_link_id need a key")
    command_timeout_s = _bounded(t, "command_timeout_s", 0.5, COMMAND_TIMEOUT_S)
    command_retries = t.integer(
        "command_retries", 2, min_value=COMMAND_RETRIES[0], max_value=COMMAND_RETRIES[1]
    )
    wait_s = (command_retries + 1) * command_timeout_s
    if wait_s > COMMAND_WAIT_MAX_S:
        raise t.fail(
            "command_timeout_s",
            f"(command_retries + 1) x command_timeout_s = {command_retries + 1} x "
            f"{command_timeout_s:g} s = {wait_s:g} s outside (0, {COMMAND_WAIT_MAX_S:g}] s: "
            "a target waiting on an unanswered servo command is answered only after that",
        )
    allowed = _allowed_senders(t) if "allowed_senders" in t else None
    return LinkSettings(
        url=url,
        dialect=t.string("dialect", "ardupilot", choices=tuple(SERVO_DIALECTS)),
        system_id=_mavlink_id(t, "system_id"),
        component_id=t.integer("component_id", 191, min_value=1, max_value=255),
        target_system=_mavlink_id(t, "target_system"),
        target_component=_mavlink_id(t, "target_component"),
        loss_timeout_s=_bounded(t, "loss_timeout_s", 3.0, LOSS_TIMEOUT_S),
        command_timeout_s=command_timeout_s,
        command_retries=command_retries,
        signing=signing,
        allowed_senders=allowed,
    )


#: ``link.signing_key = "credential:NAME"``: the key systemd passed with
#: ``LoadCredential=NAME:PATH`` (the shipped unit: ``signing.key``), read from
#: ``$CREDENTIALS_DIRECTORY/NAME``. The key file itself stays root-only; the service's dynamic
#: user reads systemd's copy.
CREDENTIAL_PREFIX = "credential:"


def _signing_key_path(t: Table, base: Path) -> Path:
    """``link.signing_key``: a path (relative to the config's directory), or
    ``credential:NAME`` for ``$CREDENTIALS_DIRECTORY/NAME``."""
    value = t.string("signing_key")
    if not value.startswith(CREDENTIAL_PREFIX):
        return base / value
    name = value.removeprefix(CREDENTIAL_PREFIX)
    if not name or "/" in name or name in (".", ".."):
        raise t.fail(
            "signing_key",
            f"credential name {name!r} must be a file name, as in LoadCredential=NAME:PATH",
        )
    directory = os.environ.get("CREDENTIALS_DIRECTORY")
    if not directory:
        raise t.fail(
            "signing_key",
            f"{value!r} is read from $CREDENTIALS_DIRECTORY, which is not set: systemd sets it "
            f"for a unit with LoadCredential={name}:PATH; outside the service set it to the "
            f"directory that holds {name} (e.g. CREDENTIALS_DIRECTORY=/etc/armbridge)",
        )
    return Path(directory) / name


def _allowed_senders(t: Table) -> frozenset[tuple[int, int]]:
    """``link.allowed_senders``: a list of ``[system_id, component_id]`` pairs, each 1-255
    (an empty list: no MAVLink sender may move the arm, only the control socket)."""
    value = t.data["allowed_senders"]
    if not isinstance(value, list):
        raise t.fail(
            "allowed_senders",
            f"must be a list of [system_id, component_id] pairs, got {value!r}",
        )
    pairs = []
    for index, entry in enumerate(value):
        key = f"allowed_senders[{index}]"
        if not isinstance(entry, list) or len(entry) != 2:
            raise t.fail(key, f"must be a [system_id, component_id] pair, got {entry!r}")
        for part, label in zip(entry, ("system_id", "component_id"), strict=True):
            if isinstance(part, bool) or not isinstance(part, int) or not 1 <= part <= 255:
                raise t.fail(key, f"{label}={part!r} must be an integer in [1, 255]")
        pairs.append((entry[0], entry[1]))
    return frozenset(pairs)


def _mavlink_id(t: Table, key: str) -> int | None:
    """An optional MAVLink system or component id, 1-255 (absent: learned from the link)."""
    return t.integer(key, min_value=1, max_value=255) if key in t else None


def _parse_calibration(root: Table, arm: Arm) -> ArmCalibration:
    """One ``[[joint]]`` per arm joint, in order; absent: outputs 9–14 over the arm's limits."""
    if "joint" in root:
        rows = root.tables("joint", allowed=_JOINT_KEYS)
        if len(rows) != arm.dof:
            raise root.fail("joint", f"{len(rows)} [[joint]] tables, the arm has {arm.dof} joints")
    else:
        if arm.dof != len(DEFAULT_OUTPUTS):
            raise root.fail("joint", f"missing: a {arm.dof}-joint arm needs [[joint]] tables")
        rows = [
            Table({"output": o}, root.source, f"joint[{i}]", error=ConfigError)
            for i, o in enumerate(DEFAULT_OUTPUTS, start=1)
        ]
    joints = []
    for index, (row, arm_joint) in enumerate(zip(rows, arm.joints, strict=True)):
        lo, hi = _limits_deg(arm, index)
        angle_min_deg = _arm_limit_if_equal(
            row.number("angle_min_deg", lo, min_value=-ANGLE_LIMIT_DEG, max_value=ANGLE_LIMIT_DEG),
            lo,
        )
        angle_max_deg = _arm_limit_if_equal(
            row.number("angle_max_deg", hi, min_value=-ANGLE_LIMIT_DEG, max_value=ANGLE_LIMIT_DEG),
            hi,
        )
        try:
            joints.append(
                JointCalibration(
                    name=row.string("name", arm_joint.name),
                    output=row.integer("output", min_value=OUTPUT_MIN, max_value=OUTPUT_MAX),
                    angle_min_deg=angle_min_deg,
                    angle_max_deg=angle_max_deg,
                    pwm_min_us=row.integer(
                        "pwm_min_us", 1000, min_value=PWM_LIMIT_MIN_US, max_value=PWM_LIMIT_MAX_US
                    ),
                    pwm_max_us=row.integer(
                        "pwm_max_us", 2000, min_value=PWM_LIMIT_MIN_US, max_value=PWM_LIMIT_MAX_US
                    ),
                    reversed=row.boolean("reversed", False),
                    trim_us=row.integer(
                        "trim_us", 0, min_value=-TRIM_US_MAX, max_value=TRIM_US_MAX
                    ),
                )
            )
        except SettingError as exc:
            # A rule between fields of the row (the field checks above came first): named by
            # the row, exc.field one of the fields, the problem the other.
            raise ConfigError(root.source, row.prefix, f"{exc.field}: {exc.problem}") from exc
        except FirmwareInterfaceError as exc:
            raise ConfigError(root.source, row.prefix, str(exc)) from exc
        cal = joints[-1]
        # The calibrated range must cover the arm's limits: the solver may return any angle in
        # them, and an angle the calibration refuses would stop the arm mid-motion.
        if cal.angle_min_deg > lo or cal.angle_max_deg < hi:
            raise row.fail(
                "angle_min_deg" if cal.angle_min_deg > lo else "angle_max_deg",
                f"calibrated [{cal.angle_min_deg:g}, {cal.angle_max_deg:g}] deg must cover the "
                f"arm's joint limits [{lo:g}, {hi:g}] for {arm_joint.name}",
            )
    try:
        return ArmCalibration(tuple(joints))
    except FirmwareInterfaceError as exc:
        raise root.fail("joint", str(exc)) from exc


def _limits_deg(arm: Arm, index: int) -> tuple[float, float]:
    """Joint ``index``'s limits in degrees, exactly as the solver's answers reach them."""
    joint = arm.joints[index]
    return math.degrees(joint.min_rad), math.degrees(joint.max_rad)


def _arm_limit_if_equal(angle_deg: float, limit_deg: float) -> float:
    """The arm's limit for a calibrated angle equal to it but for the degrees → radians →
    degrees round trip (-127 comes back as -127.00000000000001): otherwise the solver's answer
    at that limit would fall an ulp outside the calibration and be refused mid-motion."""
    return limit_deg if abs(angle_deg - limit_deg) <= 1e-9 else angle_deg


def _check_pwm_covers_arm(
    source: str, arm: Arm, calibration: ArmCalibration, park_deg: tuple[float, ...] | None
) -> None:
    """Every joint's limits (both ends) and park angle must map, through that joint's own
    :meth:`~firmware_interface.JointCalibration.angle_to_pwm_us` (reversal and trim included),
    into its [pwm_min_us, pwm_max_us]: the function that gates every PWM the daemon sends, so
    this check and the running daemon cannot disagree. The mapping is monotonic: the two ends
    prove every angle between them. A calibration that covers the arm maps inside untrimmed;
    a trim is what pushes an end out, so ``joint[N].trim_us`` is the field named."""
    for index, cal in enumerate(calibration.joints):
        lo, hi = _limits_deg(arm, index)
        angles = [
            (f"the arm's lower limit {lo:g} deg", lo),
            (f"the arm's upper limit {hi:g} deg", hi),
        ]
        if park_deg is not None:
            angles.append((f"arm.park_deg[{index}]={park_deg[index]:g} deg", park_deg[index]))
        for what, angle in angles:
            try:
                cal.angle_to_pwm_us(angle)
            except PwmOutOfRange:
                raise ConfigError(
                    source,
                    f"joint[{index + 1}].trim_us" if cal.trim_us else f"joint[{index + 1}]",
                    f"trim_us={cal.trim_us} maps {what} (joint {cal.name!r}, "
                    f"{'reversed, ' if cal.reversed else ''}output {cal.output}) to "
                    f"{cal.mapped_pwm_us(angle)} µs, outside [{cal.pwm_min_us}, "
                    f"{cal.pwm_max_us}] µs; a trim needs a calibrated angle range wider than "
                    "the arm's limits",
                ) from None
            except CalibrationError as exc:  # only a park angle within 1e-9 deg past a limit
                raise ConfigError(source, "arm.park_deg", f"[{index}]: {exc}") from exc


def link_budget_of(config: DaemonConfig) -> LinkBudget:
    """Whether the config's updates fit its link (a serial link's bytes per second), for
    ``check-config`` and ``doctor``."""
    return link_budget(
        config.link.url,
        config.link.dialect,
        config.calibration,
        config.rate_hz,
        signed=config.link.signing is not None,
    )
