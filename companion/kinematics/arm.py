"""Arm description (DH table, joint limits, tool) and hand poses.

An arm is read from a TOML file (schema in the README, "Arm files")::

    from companion.kinematics.arm import Arm, Pose
    arm = Arm.default()                    # the papers' 6-DOF arm, standard DH + Table 2 limits
    arm = Arm.from_toml("my_arm.toml")
    pose = arm.fk([q1, ..., q6])           # joint angles in degrees -> Pose

Centimetres and degrees live at this boundary (the papers' units); inside, angles are radians
and lengths centimetres.
"""

from __future__ import annotations

import math
import numbers
import tomllib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from functools import cached_property
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from companion.errors import ArmConfigError, JointLimitError
from companion.kinematics.dh import DHConvention, chain, link_transforms
from companion.kinematics.rotations import FloatArray, matrix_to_rpy, rpy_to_matrix
from companion.tomltable import Table, load_toml

LENGTH_UNITS_TO_CM = {"mm": 0.1, "cm": 1.0, "m": 100.0}
"""Units accepted for ``length_unit`` and their size in centimetres."""

DEFAULT_ARM_FILE = "paper_arm.toml"


@dataclass(frozen=True)
class Pose:
    """A hand pose: position in cm, orientation as roll/pitch/yaw in degrees.

    Orientation convention: ``R = Rz(yaw) · Ry(pitch) · Rx(roll)`` (fixed-axis X–Y–Z).
    Every field must be a finite number; anything else raises ``ValueError`` naming it.
    """

    x_cm: float
    y_cm: float
    z_cm: float
    roll_deg: float
    pitch_deg: float
    yaw_deg: float

    def __post_init__(self) -> None:
        for name in ("x_cm", "y_cm", "z_cm", "roll_deg", "pitch_deg", "yaw_deg"):
            value = getattr(self, name)
            # Text, bytes and bools are not numbers here, even where float() would take them.
            if isinstance(value, bool) or not isinstance(value, numbers.Real):
                raise ValueError(f"Pose.{name}={value!r} is not a number")
            try:
                number = float(value)
            except OverflowError as exc:  # an int beyond the float range, e.g. 10**400
                raise ValueError(f"Pose.{name}={value!r} must be finite") from exc
            if not math.isfinite(number):
                raise ValueError(f"Pose.{name}={value!r} must be finite")
            object.__setattr__(self, name, number)

    @classmethod
    def from_sequence(cls, values: Sequence[float]) -> Pose:
        """``(x_cm, y_cm, z_cm, roll_deg, pitch_deg, yaw_deg)`` → Pose; wrong length raises."""
        values = list(values)
        if len(values) != 6:
            raise ValueError(
                f"pose needs 6 values (x_cm, y_cm, z_cm, roll_deg, pitch_deg, yaw_deg), "
                f"got {len(values)}"
            )
        return cls(*values)

    @classmethod
    def from_matrix(cls, transform: FloatArray) -> Pose:
        """Pose of a 4×4 homogeneous transform whose translation is in cm."""
        t = np.asarray(transform, float)
        roll, pitch, yaw = np.degrees(matrix_to_rpy(t[:3, :3]))
        return cls(t[0, 3], t[1, 3], t[2, 3], roll, pitch, yaw)

    @property
    def position_cm(self) -> FloatArray:
        return np.array([self.x_cm, self.y_cm, self.z_cm])

    @property
    def rpy_rad(self) -> FloatArray:
        return np.radians([self.roll_deg, self.pitch_deg, self.yaw_deg])

    @property
    def rotation(self) -> FloatArray:
        """3×3 rotation matrix of the orientation."""
        return rpy_to_matrix(*self.rpy_rad)

    def as_matrix(self) -> FloatArray:
        """4×4 homogeneous transform (translation in cm)."""
        out = np.eye(4)
        out[:3, :3] = self.rotation
        out[:3, 3] = self.position_cm
        return out

    def as_tuple(self) -> tuple[float, float, float, float, float, float]:
        return (self.x_cm, self.y_cm, self.z_cm, self.roll_deg, self.pitch_deg, self.yaw_deg)


@dataclass(frozen=True)
class Joint:
    """One DH row. Angles in radians, lengths in cm; limits apply to ``q`` (before the offset)."""

    name: str
    alpha_rad: float
    a_cm: float
    d_cm: float
    offset_rad: float
    min_rad: float
    max_rad: float


@dataclass(frozen=True)
class Arm:
    """A serial arm: DH table, joint limits and an optional fixed tool transform (cm)."""

    name: str
    convention: DHConvention
    joints: tuple[Joint, ...]
    tool: tuple[tuple[float, ...], ...] | None = None
    """Fixed 4×4 transform from the last DH frame to the hand (cm), row by row; None = identity."""

    # -- construction -------------------------------------------------------------------------

    @classmethod
    def default(cls) -> Arm:
        """The papers' 6-DOF arm: standard DH table and the Table 2 joint ranges."""
        return cls.from_package_file(DEFAULT_ARM_FILE)

    @classmethod
    def from_package_file(cls, name: str) -> Arm:
        """Load one of the arm files shipped in ``companion/kinematics/arms/``."""
        ref = resources.files("companion.kinematics") / "arms" / name
        return cls.from_dict(tomllib.loads(ref.read_text(encoding="utf-8")), source=name)

    @classmethod
    def from_toml(cls, path: str | Path, *, dof: int | None = None) -> Arm:
        """Load an arm file; ``dof`` (if given) is the joint count the caller requires."""
        data = load_toml(path, ArmConfigError)
        return cls.from_dict(data, source=str(path), dof=dof)

    @classmethod
    def from_dict(
        cls, data: Mapping[str, Any], *, source: str = "<dict>", dof: int | None = None
    ) -> Arm:
        """Build an arm from the parsed TOML structure; every problem names source and field."""
        return _parse_arm(data, source, dof)

    # -- derived arrays (radians / cm), computed once ----------------------------------------

    @property
    def dof(self) -> int:
        return len(self.joints)

    @cached_property
    def lower_rad(self) -> FloatArray:
        return np.array([j.min_rad for j in self.joints])

    @cached_property
    def upper_rad(self) -> FloatArray:
        return np.array([j.max_rad for j in self.joints])

    @cached_property
    def tool_matrix(self) -> FloatArray | None:
        """The tool transform as a read-only 4×4 array, or None."""
        if self.tool is None:
            return None
        matrix = np.array(self.tool, dtype=float)
        matrix.setflags(write=False)
        return matrix

    @cached_property
    def _dh(self) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
        return (
            np.array([j.alpha_rad for j in self.joints]),
            np.array([j.a_cm for j in self.joints]),
            np.array([j.d_cm for j in self.joints]),
            np.array([j.offset_rad for j in self.joints]),
        )

    # -- kinematics ---------------------------------------------------------------------------

    def fk_batch(self, q_rad: FloatArray) -> FloatArray:
        """Hand transforms ``(S, 4, 4)`` (translation in cm) for joint vectors ``(S, dof)`` rad."""
        q = np.asarray(q_rad, float)
        if q.ndim != 2 or q.shape[1] != self.dof:
            raise ValueError(f"q_rad must have shape (S, {self.dof}), got {q.shape}")
        alpha, a, d, offset = self._dh
        return chain(link_transforms(q, alpha, a, d, offset, self.convention), self.tool_matrix)

    def fk_matrix(self, q_rad: Sequence[float] | FloatArray) -> FloatArray:
        """Hand transform 4×4 for one joint vector in radians."""
        return self.fk_batch(np.asarray(q_rad, float).reshape(1, -1))[0]

    def fk(self, q_deg: Sequence[float]) -> Pose:
        """Hand pose for one joint vector in degrees (limits are not checked; see check_limits)."""
        q = np.asarray(q_deg, float)
        if q.shape != (self.dof,):
            raise ValueError(f"q_deg must have {self.dof} values, got shape {q.shape}")
        return Pose.from_matrix(self.fk_matrix(np.radians(q)))

    def within_limits(
        self, q_rad: FloatArray, tol_rad: float = 1e-9
    ) -> NDArray[np.bool_] | np.bool_:
        """Per row of ``q_rad`` ``(S, dof)`` (a scalar for ``(dof,)``) with every joint in range."""
        q = np.asarray(q_rad, float)
        ok = (q >= self.lower_rad - tol_rad) & (q <= self.upper_rad + tol_rad)
        return ok.all(axis=-1)

    def check_limits(self, q_deg: Sequence[float]) -> None:
        """Raise :class:`JointLimitError` naming the first joint outside its range (or NaN)."""
        for joint, value in zip(self.joints, q_deg, strict=True):
            lo, hi = math.degrees(joint.min_rad), math.degrees(joint.max_rad)
            if not (lo - 1e-9 <= value <= hi + 1e-9):
                raise JointLimitError(
                    f"joint {joint.name}: angle_deg={value!r} outside [{lo:g}, {hi:g}]"
                )

    def random_q_rad(self, rng: np.random.Generator, count: int) -> FloatArray:
        """``count`` joint vectors drawn uniformly within the limits, shape ``(count, dof)``."""
        return self.lower_rad + rng.random((count, self.dof)) * (self.upper_rad - self.lower_rad)


# -- TOML parsing ---------------------------------------------------------------------------------

_TOP_FIELDS = ("name", "convention", "length_unit", "dof", "joint", "tool")
_JOINT_FIELDS = ("name", "alpha_deg", "a", "d", "offset_deg", "min_deg", "max_deg")
_TOOL_FIELDS = ("xyz", "rpy_deg")


def _parse_arm(data: Mapping[str, Any], source: str, dof: int | None) -> Arm:
    root = Table(data, source, allowed=_TOP_FIELDS, error=ArmConfigError)
    convention = DHConvention(
        root.string("convention", choices=tuple(c.value for c in DHConvention))
    )
    to_cm = LENGTH_UNITS_TO_CM[root.string("length_unit", "cm", choices=tuple(LENGTH_UNITS_TO_CM))]
    name = root.string("name", Path(source).stem or "arm")

    rows = root.tables("joint", allowed=_JOINT_FIELDS)
    if "dof" in root:
        declared = root.integer("dof", min_value=1)
        if declared != len(rows):
            raise root.fail("joint", f"{len(rows)} [[joint]] tables but dof = {declared}")
    if dof is not None and len(rows) != dof:
        raise root.fail("joint", f"{len(rows)} joints given, this use needs {dof}")

    joints = []
    for i, row in enumerate(rows, start=1):
        lo, hi = row.number("min_deg"), row.number("max_deg")
        if not lo < hi:
            raise row.fail("min_deg", f"min_deg={lo:g} must be less than max_deg={hi:g}")
        if hi - lo > 360.0:
            raise row.fail("max_deg", f"range [{lo:g}, {hi:g}] spans more than 360 degrees")
        joints.append(
            Joint(
                name=row.string("name", f"q{i}"),
                alpha_rad=math.radians(row.number("alpha_deg")),
                a_cm=row.number("a") * to_cm,
                d_cm=row.number("d") * to_cm,
                offset_rad=math.radians(row.number("offset_deg", 0.0)),
                min_rad=math.radians(lo),
                max_rad=math.radians(hi),
            )
        )

    tool = None
    if "tool" in root:
        tool_table = root.table("tool", allowed=_TOOL_FIELDS)
        xyz = tool_table.numbers("xyz", [0.0, 0.0, 0.0], length=3)
        rpy = tool_table.numbers("rpy_deg", [0.0, 0.0, 0.0], length=3)
        matrix = np.eye(4)
        matrix[:3, :3] = rpy_to_matrix(*np.radians(rpy))
        matrix[:3, 3] = np.asarray(xyz) * to_cm
        tool = tuple(tuple(float(v) for v in row) for row in matrix)

    return Arm(name=name, convention=convention, joints=tuple(joints), tool=tool)
