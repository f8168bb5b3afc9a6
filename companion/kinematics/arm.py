"""Arm description (a serial chain of revolute and prismatic joints, limits, base and tool) and
hand poses.

An arm is read from a TOML file of Denavit–Hartenberg rows (schema in ``docs/arm.md``) or
from a URDF (:mod:`companion.kinematics.urdf`)::

    from companion.kinematics.arm import Arm, Pose
    arm = Arm.default()                    # the papers' 6-DOF arm, standard DH + Table 2 limits
    arm = Arm.from_toml("my_arm.toml")
    arm = Arm.from_urdf("my_arm.urdf")
    pose = arm.fk([q1, ..., q6])           # degrees (cm for prismatic joints) -> Pose
    arm.link_shapes                        # per joint: its link's collision capsules (cm)

Centimetres and degrees live at this boundary (the papers' units); inside, angles are radians
and lengths centimetres.

The model every arm compiles to (and the compiled solver uses), whatever it was written in: a
chain of ``n + 1`` fixed transforms ``F_0 … F_n`` (cm) and ``n`` joint motions ``M_i``::

    T(q) = F_0 · M_1(q_1) · F_1 · M_2(q_2) · … · M_n(q_n) · F_n

where ``M_i`` is ``Rz(s_i·q_i + offset_i)`` for a revolute joint and ``Tz(s_i·q_i + offset_i)``
for a prismatic one (``s_i`` = ``direction``, ±1): every joint moves about or along the z axis of
the frame it acts in. The base transform is folded into ``F_0`` and the tool into ``F_n``; a DH
row splits into the fixed part before and after its variable (:func:`dh.split_dh_row`); a URDF
joint's origin and axis become ``F`` with a rotation taking z onto the axis.

Joint coordinates ``q``: radians for a revolute joint, centimetres for a prismatic joint
(degrees and cm at :meth:`Arm.fk` and in arm files; prismatic limits are in the file's
``length_unit``).
"""

from __future__ import annotations

import math
import numbers
import tomllib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from enum import Enum
from functools import cached_property
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from companion.errors import ArmConfigError, JointLimitError, KinematicsError
from companion.kinematics.dh import DHConvention, split_dh_row
from companion.kinematics.rotations import FloatArray, matrix_to_rpy, rpy_to_matrix
from tomlfields import Table, load_toml

LENGTH_UNITS_TO_CM = {"mm": 0.1, "cm": 1.0, "m": 100.0}
"""Units accepted for ``length_unit`` and their size in centimetres."""

DEFAULT_ARM_FILE = "paper_arm.toml"

Matrix = tuple[tuple[float, ...], ...]
"""A 4×4 homogeneous transform, row by row (hashable, so an :class:`Arm` compares by value)."""


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


class JointKind(Enum):
    """How a joint moves: about (REVOLUTE) or along (PRISMATIC) its axis."""

    REVOLUTE = "revolute"
    PRISMATIC = "prismatic"


@dataclass(frozen=True)
class DHRow:
    """The DH parameters a joint came from (None for URDF joints). Radians and cm.

    ``d_cm`` is the fixed offset of a revolute joint, ``theta_rad`` the fixed angle of a
    prismatic one (the other is the joint variable, plus the joint's ``offset``).
    """

    alpha_rad: float
    a_cm: float
    d_cm: float = 0.0
    theta_rad: float = 0.0


@dataclass(frozen=True)
class Joint:
    """One joint: kind, limits, direction and offset, in joint units (rad, or cm if prismatic).

    The joint variable is ``s·q + offset`` (``s`` = ``direction``); limits apply to ``q``.
    """

    name: str
    lower: float
    upper: float
    kind: JointKind = JointKind.REVOLUTE
    direction: int = 1
    offset: float = 0.0
    dh: DHRow | None = None

    @property
    def revolute(self) -> bool:
        return self.kind is JointKind.REVOLUTE

    def _need_revolute(self, what: str) -> None:
        if not self.revolute:
            raise KinematicsError(f"joint {self.name} is prismatic: {what} is for revolute joints")

    def _need_dh(self, what: str) -> DHRow:
        if self.dh is None:
            raise KinematicsError(f"joint {self.name} has no DH row (a URDF joint): no {what}")
        return self.dh

    @property
    def min_rad(self) -> float:
        """Lower limit in radians (revolute joints only)."""
        self._need_revolute("min_rad")
        return self.lower

    @property
    def max_rad(self) -> float:
        """Upper limit in radians (revolute joints only)."""
        self._need_revolute("max_rad")
        return self.upper

    @property
    def offset_rad(self) -> float:
        self._need_revolute("offset_rad")
        return self.offset

    @property
    def alpha_rad(self) -> float:
        return self._need_dh("alpha_rad").alpha_rad

    @property
    def a_cm(self) -> float:
        return self._need_dh("a_cm").a_cm

    @property
    def d_cm(self) -> float:
        return self._need_dh("d_cm").d_cm

    def to_user(self, q: float) -> float:
        """Joint coordinate → degrees (revolute) or cm (prismatic)."""
        return math.degrees(q) if self.revolute else q

    def from_user(self, value: float) -> float:
        """Degrees (revolute) or cm (prismatic) → joint coordinate."""
        return math.radians(value) if self.revolute else value


def transform(
    xyz: Sequence[float] | FloatArray, rpy_rad: Sequence[float] | FloatArray
) -> FloatArray:
    """4×4 transform: translation ``xyz`` after the rotation ``Rz(yaw)·Ry(pitch)·Rx(roll)``."""
    out = np.eye(4)
    out[:3, :3] = rpy_to_matrix(*rpy_rad)
    out[:3, 3] = xyz
    return out


def as_matrix_tuple(matrix: FloatArray) -> Matrix:
    return tuple(tuple(float(v) for v in row) for row in np.asarray(matrix, float))


@dataclass(frozen=True)
class LinkCapsule:
    """A collision capsule of one link: the points within ``radius_cm`` of the segment
    ``from_cm`` → ``to_cm``, in the link's frame (cm).

    Link ``i``'s frame is the frame joint ``i`` moves in, turned (or slid) by the joint:
    ``F_0 · M_1 · … · F_{i−1} · M_i`` in the module docstring's chain. Its origin is on joint
    ``i``'s axis and its z axis is that axis; joint ``i + 1``'s origin (the hand's, for the
    last joint) is at the translation of ``F_i``. A zero-length segment is a sphere.
    """

    from_cm: tuple[float, float, float]
    to_cm: tuple[float, float, float]
    radius_cm: float

    def __post_init__(self) -> None:
        for name in ("from_cm", "to_cm"):
            value = tuple(float(v) for v in getattr(self, name))
            if len(value) != 3 or not all(math.isfinite(v) for v in value):
                raise ValueError(f"LinkCapsule.{name}={value!r} must be 3 finite numbers")
            object.__setattr__(self, name, value)
        radius = float(self.radius_cm)
        if not (math.isfinite(radius) and radius > 0.0):
            raise ValueError(f"LinkCapsule.radius_cm={self.radius_cm!r} must be finite and > 0")
        object.__setattr__(self, "radius_cm", radius)


@dataclass(frozen=True)
class Arm:
    """A serial arm: joints, the fixed transforms between them (cm), base and tool.

    ``frames`` holds ``F_0 … F_n`` of the module docstring, base and tool folded in. ``base``
    and ``tool`` are kept for reference (None = identity); ``convention`` is the DH convention
    of an arm built from DH rows, None for one built from a URDF.

    ``link_shapes`` holds, per joint, the collision capsules of the link that joint moves
    (:class:`LinkCapsule`, in that link's frame); empty (the default) for an arm without
    shapes. The keep-out checks (:mod:`companion.kinematics.collision`) need them.
    """

    name: str
    joints: tuple[Joint, ...]
    frames: tuple[Matrix, ...]
    convention: DHConvention | None = None
    base: Matrix | None = None
    tool: Matrix | None = None
    link_shapes: tuple[tuple[LinkCapsule, ...], ...] = ()

    def __post_init__(self) -> None:
        if not self.joints:
            raise ValueError("an arm needs at least one joint")
        if len(self.frames) != len(self.joints) + 1:
            raise ValueError(
                f"an arm of {len(self.joints)} joints needs {len(self.joints) + 1} frames, "
                f"got {len(self.frames)}"
            )
        if self.link_shapes and len(self.link_shapes) != len(self.joints):
            raise ValueError(
                f"link_shapes must have one entry per joint ({len(self.joints)}), "
                f"got {len(self.link_shapes)}"
            )

    @property
    def has_shapes(self) -> bool:
        """True if at least one link has a collision capsule."""
        return any(self.link_shapes)

    # -- construction -------------------------------------------------------------------------

    @classmethod
    def default(cls) -> Arm:
        """The papers' 6-DOF arm: standard DH table and the Table 2 joint ranges."""
        return cls.from_package_file(DEFAULT_ARM_FILE)

    @classmethod
    def from_package_file(cls, name: str) -> Arm:
        """Load one of the arm files shipped in ``companion/kinematics/arms/`` (TOML or URDF)."""
        ref = resources.files("companion.kinematics") / "arms" / name
        text = ref.read_text(encoding="utf-8")
        if name.endswith(".urdf"):
            from companion.kinematics.urdf import parse_urdf

            return parse_urdf(text, source=name)
        return cls.from_dict(tomllib.loads(text), source=name)

    @classmethod
    def from_toml(cls, path: str | Path, *, dof: int | None = None) -> Arm:
        """Load an arm file; ``dof`` (if given) is the joint count the caller requires."""
        data = load_toml(path, ArmConfigError)
        return cls.from_dict(data, source=str(path), dof=dof)

    @classmethod
    def from_urdf(cls, path: str | Path, *, tip_link: str | None = None) -> Arm:
        """Load the serial chain of a URDF file (see :mod:`companion.kinematics.urdf`)."""
        from companion.kinematics.urdf import load_urdf

        return load_urdf(path, tip_link=tip_link)

    @classmethod
    def from_dict(
        cls, data: Mapping[str, Any], *, source: str = "<dict>", dof: int | None = None
    ) -> Arm:
        """Build an arm from the parsed TOML structure; every problem names source and field."""
        return _parse_arm(data, source, dof)

    @classmethod
    def from_dh(
        cls,
        name: str,
        convention: DHConvention,
        joints: Sequence[Joint],
        *,
        base: FloatArray | None = None,
        tool: FloatArray | None = None,
    ) -> Arm:
        """An arm from joints that each carry a :class:`DHRow` (the frames are computed)."""
        pre, post = [], []
        for joint in joints:
            if joint.dh is None:
                raise ValueError(f"joint {joint.name}: a DH arm needs a DH row for every joint")
            before, after = split_dh_row(
                convention,
                joint.revolute,
                joint.dh.alpha_rad,
                joint.dh.a_cm,
                joint.dh.d_cm,
                joint.dh.theta_rad,
            )
            pre.append(before)
            post.append(after)
        return cls.from_parts(name, joints, pre, post, base=base, tool=tool, convention=convention)

    @classmethod
    def from_parts(
        cls,
        name: str,
        joints: Sequence[Joint],
        before: Sequence[FloatArray],
        after: Sequence[FloatArray],
        *,
        base: FloatArray | None = None,
        tool: FloatArray | None = None,
        convention: DHConvention | None = None,
    ) -> Arm:
        """An arm whose joint ``i`` is ``before[i] · M_i(q_i) · after[i]`` (cm)."""
        n = len(joints)
        frames = []
        left = np.eye(4) if base is None else np.asarray(base, float)
        for i in range(n):
            frames.append(left @ before[i])
            left = np.asarray(after[i], float)
        frames.append(left if tool is None else left @ tool)
        return cls(
            name=name,
            joints=tuple(joints),
            frames=tuple(as_matrix_tuple(f) for f in frames),
            convention=convention,
            base=None if base is None else as_matrix_tuple(base),
            tool=None if tool is None else as_matrix_tuple(tool),
        )

    # -- derived arrays (radians / cm), computed once ----------------------------------------

    @property
    def dof(self) -> int:
        return len(self.joints)

    @cached_property
    def revolute(self) -> NDArray[np.bool_]:
        """Per joint: True for revolute, False for prismatic."""
        return np.array([j.revolute for j in self.joints])

    @cached_property
    def all_revolute(self) -> bool:
        return bool(self.revolute.all())

    @cached_property
    def lower_q(self) -> FloatArray:
        """Lower limits in joint units (rad, cm for prismatic joints)."""
        return np.array([j.lower for j in self.joints])

    @cached_property
    def upper_q(self) -> FloatArray:
        """Upper limits in joint units (rad, cm for prismatic joints)."""
        return np.array([j.upper for j in self.joints])

    @property
    def lower_rad(self) -> FloatArray:
        """Lower limits in radians; an arm with a prismatic joint raises (use ``lower_q``)."""
        self._need_all_revolute("lower_rad")
        return self.lower_q

    @property
    def upper_rad(self) -> FloatArray:
        """Upper limits in radians; an arm with a prismatic joint raises (use ``upper_q``)."""
        self._need_all_revolute("upper_rad")
        return self.upper_q

    def _need_all_revolute(self, what: str) -> None:
        if not self.all_revolute:
            joint = next(j for j in self.joints if not j.revolute)
            raise KinematicsError(
                f"arm {self.name}: joint {joint.name} is prismatic; {what} is for all-revolute arms"
            )

    @cached_property
    def frames_array(self) -> FloatArray:
        """``F_0 … F_n`` as a read-only ``(n + 1, 4, 4)`` array (cm)."""
        out = np.array(self.frames, dtype=float)
        out.setflags(write=False)
        return out

    @cached_property
    def directions(self) -> FloatArray:
        return np.array([float(j.direction) for j in self.joints])

    @cached_property
    def offsets(self) -> FloatArray:
        return np.array([j.offset for j in self.joints])

    @cached_property
    def tool_matrix(self) -> FloatArray | None:
        """The tool transform as a read-only 4×4 array, or None."""
        if self.tool is None:
            return None
        matrix = np.array(self.tool, dtype=float)
        matrix.setflags(write=False)
        return matrix

    @cached_property
    def base_matrix(self) -> FloatArray | None:
        """The base transform as a read-only 4×4 array, or None."""
        if self.base is None:
            return None
        matrix = np.array(self.base, dtype=float)
        matrix.setflags(write=False)
        return matrix

    # -- kinematics ---------------------------------------------------------------------------

    def joint_frames(self, q: FloatArray) -> tuple[FloatArray, FloatArray]:
        """For joint vectors ``q`` ``(S, n)``: the frame each joint moves in, ``(S, n, 4, 4)``
        (its z axis is the joint axis), and the hand transform ``(S, 4, 4)``; base frame, cm."""
        q = np.asarray(q, float)
        if q.ndim != 2 or q.shape[1] != self.dof:
            raise ValueError(f"q must have shape (S, {self.dof}), got {q.shape}")
        f = self.frames_array
        value = q * self.directions + self.offsets
        s, n = q.shape
        axes_frames = np.empty((s, n, 4, 4))
        t = np.broadcast_to(f[0], (s, 4, 4)).copy()
        c, sn = np.cos(value), np.sin(value)
        for i in range(n):
            axes_frames[:, i] = t
            if self.joints[i].revolute:
                r0 = t[:, :, 0].copy()
                t[:, :, 0] = r0 * c[:, i, None] + t[:, :, 1] * sn[:, i, None]
                t[:, :, 1] = t[:, :, 1] * c[:, i, None] - r0 * sn[:, i, None]
            else:
                t[:, :, 3] += t[:, :, 2] * value[:, i, None]
            t = t @ f[i + 1]
        return axes_frames, t

    def fk_batch(self, q_rad: FloatArray) -> FloatArray:
        """Hand transforms ``(S, 4, 4)`` (translation in cm) for joint vectors ``(S, dof)``
        (radians; cm for prismatic joints)."""
        return self.joint_frames(q_rad)[1]

    def fk_matrix(self, q_rad: Sequence[float] | FloatArray) -> FloatArray:
        """Hand transform 4×4 for one joint vector (radians; cm for prismatic joints)."""
        return self.fk_batch(np.asarray(q_rad, float).reshape(1, -1))[0]

    def q_from_user(self, values: Sequence[float] | FloatArray) -> FloatArray:
        """Degrees (cm for prismatic joints) → joint units (rad, cm)."""
        v = np.asarray(values, float)
        return np.where(self.revolute, np.radians(v), v)

    def q_to_user(self, q: FloatArray) -> FloatArray:
        """Joint units (rad, cm) → degrees (cm for prismatic joints)."""
        q = np.asarray(q, float)
        return np.where(self.revolute, np.degrees(q), q)

    def fk(self, q_deg: Sequence[float]) -> Pose:
        """Hand pose for one joint vector in degrees (cm for prismatic joints); limits are not
        checked (see check_limits)."""
        q = np.asarray(q_deg, float)
        if q.shape != (self.dof,):
            raise ValueError(f"q_deg must have {self.dof} values, got shape {q.shape}")
        return Pose.from_matrix(self.fk_matrix(self.q_from_user(q)))

    def within_limits(
        self, q_rad: FloatArray, tol_rad: float = 1e-9
    ) -> NDArray[np.bool_] | np.bool_:
        """Per row of ``q_rad`` ``(S, dof)`` (a scalar for ``(dof,)``) with every joint in range
        (joint units; ``tol_rad`` is in cm for prismatic joints)."""
        q = np.asarray(q_rad, float)
        ok = (q >= self.lower_q - tol_rad) & (q <= self.upper_q + tol_rad)
        return ok.all(axis=-1)

    def check_limits(self, q_deg: Sequence[float]) -> None:
        """Raise :class:`JointLimitError` naming the first joint outside its range (or NaN);
        degrees, cm for prismatic joints."""
        for joint, value in zip(self.joints, q_deg, strict=True):
            lo, hi = joint.to_user(joint.lower), joint.to_user(joint.upper)
            field = "angle_deg" if joint.revolute else "position_cm"
            if not (lo - 1e-9 <= value <= hi + 1e-9):
                raise JointLimitError(
                    f"joint {joint.name}: {field}={value!r} outside [{lo:g}, {hi:g}]"
                )

    def random_q_rad(self, rng: np.random.Generator, count: int) -> FloatArray:
        """``count`` joint vectors drawn uniformly within the limits, shape ``(count, dof)``."""
        return self.lower_q + rng.random((count, self.dof)) * (self.upper_q - self.lower_q)


# -- TOML parsing ---------------------------------------------------------------------------------

_TOP_FIELDS = (
    "name",
    "convention",
    "length_unit",
    "dof",
    "joint",
    "base",
    "tool",
    "link_radius",
)
_SHAPE_FIELDS = ("link_radius", "capsules")
_CAPSULE_FIELDS = ("from", "to", "radius")
_REVOLUTE_FIELDS = (
    "name",
    "type",
    "direction",
    "alpha_deg",
    "a",
    "d",
    "offset_deg",
    "min_deg",
    "max_deg",
    *_SHAPE_FIELDS,
)
_PRISMATIC_FIELDS = (
    "name",
    "type",
    "direction",
    "alpha_deg",
    "a",
    "theta_deg",
    "offset",
    "min",
    "max",
    *_SHAPE_FIELDS,
)
_FRAME_FIELDS = ("xyz", "rpy_deg")

#: Every length in an arm file (DH ``a`` and ``d``, prismatic limits and offsets, base and
#: tool, shapes) lies within 100 m of its frame (10 000 cm; the file's unit scales it): the
#: longest industrial arms reach about 4 m, so more is a unit slip. It also keeps the maths
#: finite: 1e308 m would be inf in cm, and squared errors of lengths past 1e154 overflow.
LENGTH_LIMIT_CM = 10_000.0
#: Every fixed angle in an arm file (DH ``alpha_deg``, ``offset_deg``, ``theta_deg``,
#: ``rpy_deg``) lies within one turn either way: a larger one is the same angle written with a
#: slip (a radian value multiplied out, a digit too many).
ANGLE_LIMIT_DEG = 360.0
#: A revolute joint's limits may span more than a turn (a multi-turn joint), but not past ten
#: turns either way: no servo or geared joint travels that far, and the solver draws its start
#: points across the whole range, so a huge range would leave it searching mostly nowhere.
JOINT_LIMIT_DEG = 3600.0


def _length(t: Table, key: str, to_cm: float, default: float | None = None) -> float:
    """A length in the file's unit, within :data:`LENGTH_LIMIT_CM`, returned in cm."""
    limit = LENGTH_LIMIT_CM / to_cm
    args = () if default is None else (default,)
    return t.number(key, *args, min_value=-limit, max_value=limit) * to_cm


def _angle(t: Table, key: str, default: float | None = None) -> float:
    """An angle in degrees within :data:`ANGLE_LIMIT_DEG`."""
    args = () if default is None else (default,)
    return t.number(key, *args, min_value=-ANGLE_LIMIT_DEG, max_value=ANGLE_LIMIT_DEG)


def _point_cm(t: Table, key: str, to_cm: float, default: list[float] | None = None) -> list[float]:
    """3 lengths in the file's unit, each within :data:`LENGTH_LIMIT_CM`, returned in cm."""
    limit = LENGTH_LIMIT_CM / to_cm
    args = () if default is None else (default,)
    return [v * to_cm for v in t.numbers(key, *args, length=3, min_value=-limit, max_value=limit)]


def _radius_cm(t: Table, key: str, to_cm: float) -> float:
    """A positive length in the file's unit, within :data:`LENGTH_LIMIT_CM`, returned in cm."""
    return t.number(key, max_value=LENGTH_LIMIT_CM / to_cm, positive=True) * to_cm


def _parse_frame(root: Table, key: str, to_cm: float) -> FloatArray | None:
    if key not in root:
        return None
    table = root.table(key, allowed=_FRAME_FIELDS)
    xyz = _point_cm(table, "xyz", to_cm, [0.0, 0.0, 0.0])
    rpy = table.numbers(
        "rpy_deg", [0.0, 0.0, 0.0], length=3, min_value=-ANGLE_LIMIT_DEG, max_value=ANGLE_LIMIT_DEG
    )
    return transform(np.asarray(xyz), np.radians(rpy))


def _parse_joint(row: Table, index: int, to_cm: float) -> Joint:
    kind_text = row.string("type", "revolute", choices=tuple(k.value for k in JointKind))
    kind = JointKind(kind_text)
    name = row.string("name", f"q{index}")
    if kind is JointKind.REVOLUTE:
        row.allow(_REVOLUTE_FIELDS)
        lo_key, hi_key = "min_deg", "max_deg"
        lo = row.number(lo_key, min_value=-JOINT_LIMIT_DEG, max_value=JOINT_LIMIT_DEG)
        hi = row.number(hi_key, min_value=-JOINT_LIMIT_DEG, max_value=JOINT_LIMIT_DEG)
        scale = math.pi / 180.0
        dh = DHRow(
            alpha_rad=math.radians(_angle(row, "alpha_deg")),
            a_cm=_length(row, "a", to_cm),
            d_cm=_length(row, "d", to_cm),
        )
        offset = math.radians(_angle(row, "offset_deg", 0.0))
    else:
        row.allow(_PRISMATIC_FIELDS)
        lo_key, hi_key = "min", "max"
        limit = LENGTH_LIMIT_CM / to_cm  # the limits stay in the file's unit until scaled
        lo = row.number(lo_key, min_value=-limit, max_value=limit)
        hi = row.number(hi_key, min_value=-limit, max_value=limit)
        scale = to_cm
        dh = DHRow(
            alpha_rad=math.radians(_angle(row, "alpha_deg")),
            a_cm=_length(row, "a", to_cm),
            theta_rad=math.radians(_angle(row, "theta_deg", 0.0)),
        )
        offset = _length(row, "offset", to_cm, 0.0)
    if not lo < hi:
        raise row.fail(lo_key, f"{lo_key}={lo:g} must be less than {hi_key}={hi:g}")
    direction = row.integer("direction", 1)
    if direction not in (1, -1):
        raise row.fail("direction", f"{direction!r} is not one of 1, -1")
    return Joint(
        name=name,
        lower=lo * scale,
        upper=hi * scale,
        kind=kind,
        direction=direction,
        offset=offset,
        dh=dh,
    )


def _parse_arm(data: Mapping[str, Any], source: str, dof: int | None) -> Arm:
    root = Table(data, source, allowed=_TOP_FIELDS, error=ArmConfigError)
    convention = DHConvention(
        root.string("convention", choices=tuple(c.value for c in DHConvention))
    )
    to_cm = LENGTH_UNITS_TO_CM[root.string("length_unit", "cm", choices=tuple(LENGTH_UNITS_TO_CM))]
    name = root.string("name", Path(source).stem or "arm")

    rows = root.tables("joint")
    if "dof" in root:
        declared = root.integer("dof", min_value=1)
        if declared != len(rows):
            raise root.fail("joint", f"{len(rows)} [[joint]] tables but dof = {declared}")
    if dof is not None and len(rows) != dof:
        raise root.fail("joint", f"{len(rows)} joints given, this use needs {dof}")

    joints = [_parse_joint(row, i, to_cm) for i, row in enumerate(rows, start=1)]
    base = _parse_frame(root, "base", to_cm)
    tool = _parse_frame(root, "tool", to_cm)
    arm = Arm.from_dh(name, convention, joints, base=base, tool=tool)
    default_radius = _radius_cm(root, "link_radius", to_cm) if "link_radius" in root else None
    shapes = tuple(_parse_shapes(row, arm, i, default_radius, to_cm) for i, row in enumerate(rows))
    return replace(arm, link_shapes=shapes) if any(shapes) else arm


def _parse_shapes(
    row: Table, arm: Arm, index: int, default_radius_cm: float | None, to_cm: float
) -> tuple[LinkCapsule, ...]:
    """A joint's link shapes: ``capsules = [{from, to, radius}, …]`` (link frame, the file's
    length unit; ``[]`` for none), else one capsule from the link's origin to the next joint's
    (the hand's, for the last joint) of radius ``link_radius`` (the joint's, else the arm's)."""
    if "capsules" in row:
        if "link_radius" in row:
            raise row.fail("link_radius", "give either link_radius or capsules, not both")
        items = row.data["capsules"]
        if not isinstance(items, list):
            raise row.fail(
                "capsules", f"must be a list of {{from, to, radius}} tables, got {items!r}"
            )
        out = []
        for k, item in enumerate(items):
            t = Table(
                item,
                row.source,
                row.name(f"capsules[{k}]"),
                allowed=_CAPSULE_FIELDS,
                error=row.error,
            )
            start = _point_cm(t, "from", to_cm)
            end = _point_cm(t, "to", to_cm)
            out.append(
                LinkCapsule(
                    from_cm=(start[0], start[1], start[2]),
                    to_cm=(end[0], end[1], end[2]),
                    radius_cm=_radius_cm(t, "radius", to_cm),
                )
            )
        return tuple(out)
    radius = _radius_cm(row, "link_radius", to_cm) if "link_radius" in row else default_radius_cm
    if radius is None:
        return ()
    end = arm.frames_array[index + 1][:3, 3]
    return (LinkCapsule((0.0, 0.0, 0.0), (float(end[0]), float(end[1]), float(end[2])), radius),)
