"""The daemon's configuration file (TOML): schema, defaults, validation.

Everything is checked at load time, before anything is opened or sent. An error is a
:class:`~companion.errors.ConfigError` that names the file, the field (``link.url``,
``joint[3].pwm_max_us``) and the allowed values; ``armbridge run`` and ``check-config`` turn it
into exit code 2. The schema is documented in the README ("Daemon configuration") and in the
example ``companion/daemon/examples/armbridge.toml``.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path

from companion.errors import ArmConfigError, ConfigError, JointLimitError
from companion.kinematics.arm import Arm
from companion.tomltable import Table, load_toml
from firmware_interface import (
    SERVO_DIALECTS,
    ArmCalibration,
    FirmwareInterfaceError,
    InvalidUrl,
    JointCalibration,
    SigningConfig,
    parse_url,
)

DEFAULT_OUTPUTS = (9, 10, 11, 12, 13, 14)  # outputs 1–4 drive a quad's motors


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
    rate_hz: float = 20.0
    joint_speed_deg_s: float = 60.0
    park_deg: tuple[float, ...] | None = None
    park_on_stop: bool = False
    control_socket: str | None = None


_SECTIONS = ("link", "arm", "solver", "control", "joint")
_LINK_KEYS = (
    "url",
    "dialect",
    "system_id",
    "component_id",
    "target_system",
    "loss_timeout_s",
    "command_timeout_s",
    "command_retries",
    "signing_key",
    "signing_link_id",
    "signing_state",
)
_ARM_KEYS = ("file", "park_deg", "park_on_stop", "joint_speed_deg_s")
_SOLVER_KEYS = ("budget_ms", "tol_pos_cm", "tol_ori_deg", "seed")
_CONTROL_KEYS = ("rate_hz", "socket")
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
    return parse_config(load_toml(path), source=str(path))


def parse_config(data: dict, *, source: str = "<dict>") -> DaemonConfig:
    root = Table(data, source, allowed=_SECTIONS)
    base = Path(source).parent if source != "<dict>" else Path.cwd()
    link = _parse_link(root.table("link", allowed=_LINK_KEYS), base)

    arm_table = root.table("arm", allowed=_ARM_KEYS)
    if "file" in arm_table:
        arm_path = base / arm_table.string("file")
        try:
            arm = Arm.from_toml(arm_path, dof=None)
        except ArmConfigError as exc:
            raise arm_table.fail("file", f"arm file {exc}") from exc
    else:
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
    return DaemonConfig(
        source=source,
        link=link,
        arm=arm,
        calibration=_parse_calibration(root, arm),
        budget_ms=solver.number("budget_ms", 20.0, positive=True, max_value=10_000),
        tol_pos_cm=solver.number("tol_pos_cm", 0.01, positive=True),
        tol_ori_deg=solver.number("tol_ori_deg", 0.1, positive=True),
        seed=solver.integer("seed", min_value=0) if "seed" in solver else None,
        rate_hz=control.number("rate_hz", 20.0, positive=True, max_value=500),
        joint_speed_deg_s=arm_table.number("joint_speed_deg_s", 60.0, positive=True),
        park_deg=park,
        park_on_stop=arm_table.boolean("park_on_stop", False),
        control_socket=_socket_path(control) if "socket" in control else None,
    )


# A Unix socket's path must fit sockaddr_un.sun_path (108 bytes on Linux, with its NUL).
SOCKET_PATH_MAX_BYTES = 107


def _socket_path(t: Table) -> str:
    path = t.string("socket")
    size = len(os.fsencode(path))
    if size > SOCKET_PATH_MAX_BYTES:
        raise t.fail(
            "socket",
            f"path is {size} bytes, a Unix socket path takes at most {SOCKET_PATH_MAX_BYTES}",
        )
    return path


def _parse_link(t: Table, base: Path) -> LinkSettings:
    url = t.string("url")
    try:
        parse_url(url)
    except InvalidUrl as exc:
        raise t.fail("url", str(exc)) from exc
    signing = None
    if "signing_key" in t:
        key_path = base / t.string("signing_key")
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
    return LinkSettings(
        url=url,
        dialect=t.string("dialect", "ardupilot", choices=tuple(SERVO_DIALECTS)),
        system_id=t.integer("system_id", min_value=1, max_value=255) if "system_id" in t else None,
        component_id=t.integer("component_id", 191, min_value=1, max_value=255),
        target_system=(
            t.integer("target_system", min_value=1, max_value=255) if "target_system" in t else None
        ),
        loss_timeout_s=t.number("loss_timeout_s", 3.0, positive=True),
        command_timeout_s=t.number("command_timeout_s", 0.5, positive=True),
        command_retries=t.integer("command_retries", 2, min_value=0, max_value=10),
        signing=signing,
    )


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
            Table({"output": o}, root.source, f"joint[{i}]")
            for i, o in enumerate(DEFAULT_OUTPUTS, start=1)
        ]
    joints = []
    for row, arm_joint in zip(rows, arm.joints, strict=True):
        lo = math.degrees(arm_joint.min_rad)
        hi = math.degrees(arm_joint.max_rad)
        try:
            joints.append(
                JointCalibration(
                    name=row.string("name", arm_joint.name),
                    output=row.integer("output", min_value=1, max_value=16),
                    angle_min_deg=row.number("angle_min_deg", lo),
                    angle_max_deg=row.number("angle_max_deg", hi),
                    pwm_min_us=row.integer("pwm_min_us", 1000),
                    pwm_max_us=row.integer("pwm_max_us", 2000),
                    reversed=row.boolean("reversed", False),
                    trim_us=row.integer("trim_us", 0),
                )
            )
        except FirmwareInterfaceError as exc:
            raise ConfigError(root.source, row.prefix, str(exc)) from exc
        cal = joints[-1]
        # The calibrated range must cover the arm's limits: the solver may return any angle in
        # them, and an angle the calibration refuses would stop the arm mid-motion.
        if cal.angle_min_deg > lo + 1e-9 or cal.angle_max_deg < hi - 1e-9:
            raise row.fail(
                "angle_min_deg" if cal.angle_min_deg > lo + 1e-9 else "angle_max_deg",
                f"calibrated [{cal.angle_min_deg:g}, {cal.angle_max_deg:g}] deg must cover the "
                f"arm's joint limits [{lo:g}, {hi:g}] for {arm_joint.name}",
            )
    try:
        return ArmCalibration(tuple(joints))
    except FirmwareInterfaceError as exc:
        raise root.fail("joint", str(exc)) from exc
