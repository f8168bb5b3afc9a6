"""Keep-out checks: the arm's link capsules against keep-out volumes on the vehicle.

numpy, its hot loop compiled (:mod:`~companion.kinematics.collision_kernels`, with this
module's numpy version as the reference); no I/O, no clocks. Lengths in cm, joints in joint
units (rad; cm for a prismatic joint). The arm's links carry capsules
(:class:`~companion.kinematics.arm.LinkCapsule`, from the arm file); the volumes are written in
the vehicle's body frame FRD, and the arm's base sits in it at a
:class:`~companion.kinematics.vehicle.Mount`.

Volumes: :class:`Sphere`, :class:`Capsule` (legs), :class:`Box` (the body; oriented by
``rpy_deg``, axis-aligned at 0) and :class:`Cylinder` (propeller discs: a thin cylinder about its
local z axis). A link is **clear** of a volume when the distance between the link's capsule and
the volume is at least ``margin_cm``. Every distance here is exact or a lower bound, never more,
so an error only ever refuses a clear configuration, never accepts a colliding one:

* capsule–sphere and capsule–capsule: exact (closest points of two segments, Ericson,
  *Real-Time Collision Detection* §5.1.9), less 1e-7 cm for rounding;
* capsule–box: exact. The squared distance from the segment's point ``p(t)`` to the box is a
  convex piecewise quadratic in ``t``, whose pieces end where ``p(t)`` crosses a face's plane;
  each piece is minimised in closed form;
* capsule–cylinder: conservative. The distance to a set is at most the distance to any subset,
  so the distance to the cylinder is at least the largest of the distances to three sets that
  contain it: its bounding capsule (axis segment, same radius), its bounding square prism, and
  that prism turned 45° about the axis (an octagonal prism together). Beside the rim (within
  the disc's thickness) and over the disc this is exact; above or below the rim's edge it can
  be short by up to about 11 % of the radius (1.4 cm for a 13 cm disc, sampled), where the
  octagon's corners stick out of the circle.

:meth:`KeepOut.check_motion` checks the whole straight-line joint motion between two
configurations, not samples of it. Every point of a link moves, per unit of the motion's
parameter ``s`` ∈ [0, 1], at most ``V = Σ_j |Δq_j| · ρ_j`` (revolute joints ``j`` up to the
link: ``ρ_j`` bounds the distance from joint ``j``'s axis to any point of the link over all
configurations, by the triangle inequality along the chain) plus ``Σ |Δq_j|`` (prismatic ones).
Each lower bound above is a distance from the moving capsule to a fixed set (or the largest of
three), so it changes by at most ``V·|Δs|``: between two samples ``a < b`` with clearances
``c_a, c_b`` it stays above ``(c_a + c_b − V·(b − a)) / 2``. The motion is accepted only when,
for every link and every interval, that is at least ``margin_cm``; intervals that fail are
halved (up to ``max_depth`` times and ``max_samples`` configurations; past that, refused). So
no volume, however thin, can hide between samples: a link crossing it would have clearance 0
somewhere inside an interval the bound proved clear.

Self-collision between the arm's own links is not checked (the arm's joint limits are trusted
for that); the base (the part before joint 1) is fixed to the vehicle and not checked either.
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from companion.kinematics.arm import Arm
from companion.kinematics.rotations import FloatArray, rpy_to_matrix
from companion.kinematics.vehicle import Mount, finite_triple, invert, transform

#: Subtracted from every computed distance (cm): float64 rounding on arms of metres is ~1e-13.
ROUNDING_CM = 1e-7


def _positive(owner: str, name: str, value: object) -> float:
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise ValueError(f"{owner}.{name}={value!r} must be a number")
    number = float(value)
    if not (math.isfinite(number) and number > 0.0):
        raise ValueError(f"{owner}.{name}={value!r} must be finite and > 0")
    return number


def _name(owner: str, value: object) -> str:
    if not isinstance(value, str) or not value:
        raise ValueError(f"{owner}.name={value!r} must be a non-empty string")
    return value


@dataclass(frozen=True)
class Sphere:
    """A ball of ``radius_cm`` about ``center_cm`` (body FRD)."""

    name: str
    center_cm: tuple[float, float, float]
    radius_cm: float

    def __post_init__(self) -> None:
        _name("Sphere", self.name)
        object.__setattr__(self, "center_cm", finite_triple("Sphere", "center_cm", self.center_cm))
        object.__setattr__(self, "radius_cm", _positive("Sphere", "radius_cm", self.radius_cm))


@dataclass(frozen=True)
class Capsule:
    """The points within ``radius_cm`` of the segment ``from_cm`` → ``to_cm`` (body FRD)."""

    name: str
    from_cm: tuple[float, float, float]
    to_cm: tuple[float, float, float]
    radius_cm: float

    def __post_init__(self) -> None:
        _name("Capsule", self.name)
        object.__setattr__(self, "from_cm", finite_triple("Capsule", "from_cm", self.from_cm))
        object.__setattr__(self, "to_cm", finite_triple("Capsule", "to_cm", self.to_cm))
        object.__setattr__(self, "radius_cm", _positive("Capsule", "radius_cm", self.radius_cm))


@dataclass(frozen=True)
class Box:
    """A box of edge lengths ``size_cm`` (its own x, y, z), centred on ``center_cm`` and turned
    by ``rpy_deg`` (ZYX yaw-pitch-roll; 0: axis-aligned with the body)."""

    name: str
    center_cm: tuple[float, float, float]
    size_cm: tuple[float, float, float]
    rpy_deg: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def __post_init__(self) -> None:
        _name("Box", self.name)
        object.__setattr__(self, "center_cm", finite_triple("Box", "center_cm", self.center_cm))
        size = finite_triple("Box", "size_cm", self.size_cm)
        for i, v in enumerate(size):
            _positive("Box", f"size_cm[{i}]", v)
        object.__setattr__(self, "size_cm", size)
        object.__setattr__(self, "rpy_deg", finite_triple("Box", "rpy_deg", self.rpy_deg))


@dataclass(frozen=True)
class Cylinder:
    """A solid cylinder of ``radius_cm`` and ``length_cm`` along its own z axis, centred on
    ``center_cm`` and turned by ``rpy_deg`` (0: axis along the body's z, a disc in the body's
    x–y plane, as a propeller's)."""

    name: str
    center_cm: tuple[float, float, float]
    radius_cm: float
    length_cm: float
    rpy_deg: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def __post_init__(self) -> None:
        _name("Cylinder", self.name)
        object.__setattr__(
            self, "center_cm", finite_triple("Cylinder", "center_cm", self.center_cm)
        )
        object.__setattr__(self, "radius_cm", _positive("Cylinder", "radius_cm", self.radius_cm))
        object.__setattr__(self, "length_cm", _positive("Cylinder", "length_cm", self.length_cm))
        object.__setattr__(self, "rpy_deg", finite_triple("Cylinder", "rpy_deg", self.rpy_deg))


Volume = Sphere | Capsule | Box | Cylinder


@dataclass(frozen=True)
class Collision:
    """A refusal: the link moved by joint ``link`` comes within ``clearance_cm`` (a lower bound
    of the distance between its capsule and the volume; negative: they overlap by at least
    that much) of keep-out volume ``volume``, less than ``margin_cm``.

    ``fraction`` is where along a motion (0 for a single configuration). ``proven`` is False
    when a motion was refused because the bound could not show it clear after ``max_depth``
    halvings (a link grazing the margin), not because a sample was inside it.
    """

    link: str
    volume: str
    clearance_cm: float
    margin_cm: float
    fraction: float = 0.0
    proven: bool = True

    @property
    def reason(self) -> str:
        where = "" if self.fraction == 0.0 else f" at {self.fraction:.3f} of the motion"
        if self.proven:
            what = (
                f"overlaps keep-out volume {self.volume!r} by at least {-self.clearance_cm:.2f} cm"
                if self.clearance_cm < 0
                else f"is {self.clearance_cm:.2f} cm from keep-out volume {self.volume!r}"
            )
            return f"the link of joint {self.link} {what}{where} (margin {self.margin_cm:g} cm)"
        return (
            f"the motion could not be shown clear of keep-out volume {self.volume!r} for the link "
            f"of joint {self.link}: it comes within about {self.clearance_cm:.2f} cm{where} "
            f"(margin {self.margin_cm:g} cm)"
        )


# -- distances (vectorised over leading axes) ----------------------------------------------------


def segment_segment_distance(
    p1: FloatArray, q1: FloatArray, p2: FloatArray, q2: FloatArray
) -> FloatArray:
    """Exact distance between segments ``p1q1`` and ``p2q2`` (``(..., 3)`` each, broadcast).
    A zero-length segment is a point. (Ericson, *Real-Time Collision Detection*, §5.1.9.)"""
    d1 = q1 - p1
    d2 = q2 - p2
    r = p1 - p2
    a = (d1 * d1).sum(axis=-1)
    e = (d2 * d2).sum(axis=-1)
    f = (d2 * r).sum(axis=-1)
    c = (d1 * r).sum(axis=-1)
    b = (d1 * d2).sum(axis=-1)
    tiny = 1e-18
    a_ok = a > tiny
    e_ok = e > tiny
    a_safe = np.where(a_ok, a, 1.0)
    e_safe = np.where(e_ok, e, 1.0)
    denom = a * e - b * b
    denom_ok = denom > tiny * np.maximum(a * e, 1.0)
    s = np.where(denom_ok, np.clip((b * f - c * e) / np.where(denom_ok, denom, 1.0), 0.0, 1.0), 0.0)
    t = (b * s + f) / e_safe
    s = np.where(
        t < 0.0,
        np.clip(-c / a_safe, 0.0, 1.0),
        np.where(t > 1.0, np.clip((b - c) / a_safe, 0.0, 1.0), s),
    )
    t = np.clip(t, 0.0, 1.0)
    # Degenerate segments: a point against a segment, or two points.
    s = np.where(a_ok, np.where(e_ok, s, np.clip(-c / a_safe, 0.0, 1.0)), 0.0)
    t = np.where(e_ok, np.where(a_ok, t, np.clip(f / e_safe, 0.0, 1.0)), 0.0)
    gap = (p1 + s[..., None] * d1) - (p2 + t[..., None] * d2)
    return np.sqrt((gap * gap).sum(axis=-1))


def segment_box_distance(p0: FloatArray, p1: FloatArray, half_cm: FloatArray) -> FloatArray:
    """Exact distance from segment ``p0p1`` to the box ``|x_k| ≤ half_cm[k]`` (box frame;
    ``(..., 3)`` each, broadcast); 0 if they meet.

    ``|p(t) − box|²`` is convex and quadratic between the ``t`` where ``p(t)`` crosses one of the
    six face planes; on each piece the axes outside the slab are fixed, so its minimum is in
    closed form. The smallest piece minimum is the distance.
    """
    p0, p1, half = np.broadcast_arrays(p0, p1, half_cm)
    d = p1 - p0
    moving = np.abs(d) > 1e-15
    d_safe = np.where(moving, d, 1.0)
    cross_hi = np.where(moving, (half - p0) / d_safe, 0.0)
    cross_lo = np.where(moving, (-half - p0) / d_safe, 0.0)
    shape = p0.shape[:-1]
    ts = np.concatenate(
        [np.zeros(shape + (1,)), np.ones(shape + (1,)), cross_hi, cross_lo], axis=-1
    )
    ts = np.sort(np.clip(ts, 0.0, 1.0), axis=-1)  # (..., 8)
    lo, hi = ts[..., :-1], ts[..., 1:]  # (..., 7) pieces
    mid = 0.5 * (lo + hi)
    p0e, de, he = p0[..., None, :], d[..., None, :], half[..., None, :]
    at_mid = p0e + mid[..., None] * de  # (..., 7, 3)
    above = at_mid > he
    below = at_mid < -he
    out = above | below
    bound = np.where(above, he, -he)
    a = np.where(out, p0e - bound, 0.0)
    b = np.where(out, de, 0.0)
    ab = (a * b).sum(axis=-1)
    bb = (b * b).sum(axis=-1)
    t = np.where(bb > 0.0, -ab / np.where(bb > 0.0, bb, 1.0), lo)
    t = np.clip(t, lo, hi)
    gap = a + t[..., None] * b
    sq = (gap * gap).sum(axis=-1)
    return np.sqrt(sq.min(axis=-1))


# -- the prepared check ---------------------------------------------------------------------------


def _pose(center_cm: Sequence[float], rpy_deg: Sequence[float]) -> FloatArray:
    """A volume's pose in body FRD (4×4, cm) from its centre and roll/pitch/yaw (deg)."""
    roll, pitch, yaw = np.radians(rpy_deg)
    return transform(rpy_to_matrix(roll, pitch, yaw), center_cm)


_TURN_45 = _pose((0.0, 0.0, 0.0), (0.0, 0.0, 45.0))


class KeepOut:
    """An arm, its mount and keep-out volumes, prepared once for repeated checks.

    ``margin_cm`` (≥ 0) is the clearance every link capsule must keep from every volume;
    :meth:`check_motion` first samples a motion every ``step_cm`` of bounded link travel, then
    halves the intervals it cannot prove clear, at most ``max_depth`` times and ``max_samples``
    configurations in all; a motion not proven clear by then is refused (``proven`` False).
    None of these can let a colliding motion through; they bound the work. Raises
    ``ValueError`` for an arm without link shapes when volumes are given (nothing to check).
    """

    def __init__(
        self,
        arm: Arm,
        volumes: Sequence[Volume],
        mount: Mount | None = None,
        margin_cm: float = 1.0,
        *,
        max_depth: int = 12,
        step_cm: float = 4.0,
        max_samples: int = 1024,
    ) -> None:
        self.arm = arm
        self.volumes = tuple(volumes)
        self.mount = Mount() if mount is None else mount
        margin: object = margin_cm
        if isinstance(margin, bool) or not isinstance(margin, numbers.Real):
            raise ValueError(f"margin_cm={margin_cm!r} must be a number")
        if not (math.isfinite(float(margin)) and float(margin) >= 0.0):
            raise ValueError(f"margin_cm={margin_cm!r} must be finite and >= 0")
        self.margin_cm: float = float(margin)
        if max_depth < 0:
            raise ValueError(f"max_depth={max_depth!r} must be >= 0")
        self.max_depth: int = int(max_depth)
        if not step_cm > 0:
            raise ValueError(f"step_cm={step_cm!r} must be > 0")
        self.step_cm = float(step_cm)
        if max_samples < 2:
            raise ValueError(f"max_samples={max_samples!r} must be >= 2")
        self.max_samples = int(max_samples)
        names = [v.name for v in self.volumes]
        for v in self.volumes:
            if not isinstance(v, Sphere | Capsule | Box | Cylinder):
                raise ValueError(f"volume {v!r} is not a Sphere, Capsule, Box or Cylinder")
        duplicate = next((n for n in names if names.count(n) > 1), None)
        if duplicate is not None:
            raise ValueError(f"two keep-out volumes are named {duplicate!r}")
        if self.volumes and not arm.has_shapes:
            raise ValueError(
                f"arm {arm.name} has no link shapes (link_radius or capsules in the arm file): "
                "keep-out volumes cannot be checked"
            )
        self._prepare_links()
        self._prepare_volumes()
        self._ceiling: FloatArray | None = None

    # -- preparation ------------------------------------------------------------------------

    def _prepare_links(self) -> None:
        arm = self.arm
        link_idx, ends, radii = [], [], []
        for i, shapes in enumerate(arm.link_shapes):
            for cap in shapes:
                link_idx.append(i)
                ends.append([cap.from_cm, cap.to_cm])
                radii.append(cap.radius_cm)
        self._link_idx = np.array(link_idx, dtype=np.intp)
        self._ends = np.array(ends, dtype=float).reshape(-1, 2, 3)
        self._radii = np.array(radii, dtype=float)
        f = arm.frames_array
        self._inv_frames = np.array([invert(f[i + 1]) for i in range(arm.dof)])
        self._mount = self.mount.matrix
        self._reach = self._lever_arms()
        self._frames = np.array(f)  # writable: numba types a read-only array apart
        self._directions = np.array(arm.directions)
        self._offsets = np.array(arm.offsets)
        self._revolute = np.array(arm.revolute, dtype=np.bool_)

    def _lever_arms(self) -> FloatArray:
        """``(C, n)``: per capsule and joint, the speed bound per unit of joint motion (cm/rad
        for a revolute joint: a bound on the distance from its axis to any point of the
        capsule over all configurations; 1 for a prismatic joint; 0 for later joints)."""
        arm = self.arm
        f = arm.frames_array
        n = arm.dof
        # How far each joint's own motion can carry its link's origin from the joint's origin.
        slide = np.zeros(n)
        for j, joint in enumerate(arm.joints):
            if not joint.revolute:
                lo = joint.direction * joint.lower + joint.offset
                hi = joint.direction * joint.upper + joint.offset
                slide[j] = max(abs(lo), abs(hi))
        step = np.linalg.norm(f[1:n, :3, 3], axis=1) if n > 1 else np.zeros(0)
        out = np.zeros((len(self._radii), n))
        for c, (link, ends) in enumerate(zip(self._link_idx, self._ends, strict=True)):
            far_end = float(np.linalg.norm(ends, axis=1).max())
            for j in range(link + 1):
                if not arm.joints[j].revolute:
                    out[c, j] = 1.0
                    continue
                # joint j's origin → link j origin (0: it turns) → … → link `link` origin
                chain = float(step[j:link].sum() + slide[j + 1 : link + 1].sum())
                out[c, j] = chain + far_end
        return out

    def _prepare_volumes(self) -> None:
        caps_a: list[ArrayLike] = []
        caps_b: list[ArrayLike] = []
        caps_r: list[float] = []
        boxes_inv: list[FloatArray] = []
        boxes_half: list[FloatArray] = []
        cap_of = np.full(len(self.volumes), -1, dtype=np.intp)
        box_of = np.full((len(self.volumes), 2), -1, dtype=np.intp)
        for v_index, v in enumerate(self.volumes):
            if isinstance(v, Sphere):
                cap_of[v_index] = len(caps_r)
                caps_a.append(v.center_cm)
                caps_b.append(v.center_cm)
                caps_r.append(v.radius_cm)
            elif isinstance(v, Capsule):
                cap_of[v_index] = len(caps_r)
                caps_a.append(v.from_cm)
                caps_b.append(v.to_cm)
                caps_r.append(v.radius_cm)
            elif isinstance(v, Box):
                box_of[v_index, 0] = len(boxes_half)
                boxes_inv.append(invert(_pose(v.center_cm, v.rpy_deg)))
                boxes_half.append(np.asarray(v.size_cm) / 2)
            else:  # Cylinder: its bounding capsule and two bounding square prisms
                pose = _pose(v.center_cm, v.rpy_deg)
                axis = pose[:3, 2] * (v.length_cm / 2)
                cap_of[v_index] = len(caps_r)
                caps_a.append(pose[:3, 3] - axis)
                caps_b.append(pose[:3, 3] + axis)
                caps_r.append(v.radius_cm)
                half = np.array([v.radius_cm, v.radius_cm, v.length_cm / 2])
                for k, turned in enumerate((pose, pose @ _TURN_45)):
                    box_of[v_index, k] = len(boxes_half)
                    boxes_inv.append(invert(turned))
                    boxes_half.append(half)
        self._caps_a = np.array(caps_a, dtype=float).reshape(-1, 3)
        self._caps_b = np.array(caps_b, dtype=float).reshape(-1, 3)
        self._caps_r = np.array(caps_r, dtype=float)
        self._boxes_inv = np.array(boxes_inv, dtype=float).reshape(-1, 4, 4)
        self._boxes_half = np.array(boxes_half, dtype=float).reshape(-1, 3)
        # -1 indexes the padding column of -inf appended to each distance array.
        self._cap_of = cap_of
        self._box_of = box_of

    # -- geometry -----------------------------------------------------------------------------

    def segments(self, q: FloatArray) -> FloatArray:
        """The link capsules' segments in body FRD for joint vectors ``q`` ``(S, n)``:
        ``(S, C, 2, 3)`` (cm); their radii are :attr:`radii_cm`, their joints
        :attr:`capsule_links`."""
        axes, hand = self.arm.joint_frames(q)
        after = np.concatenate([axes[:, 1:], hand[:, None]], axis=1)  # frame of joint i + 1
        links = self._mount @ after @ self._inv_frames  # (S, n, 4, 4) link frames in body
        g = links[:, self._link_idx]  # (S, C, 4, 4)
        return np.einsum("scij,ckj->scki", g[:, :, :3, :3], self._ends) + g[:, :, None, :3, 3]

    @property
    def radii_cm(self) -> FloatArray:
        return self._radii

    @property
    def capsule_links(self) -> tuple[str, ...]:
        """The joint name of each capsule's link."""
        return tuple(self.arm.joints[i].name for i in self._link_idx)

    def clearances(self, q: FloatArray) -> FloatArray:
        """Lower bounds of the clearance (cm) between each link capsule and each volume,
        ``(S, C, V)`` for joint vectors ``(S, n)``: distance less the capsule's radius and
        :data:`ROUNDING_CM` (negative: they overlap). Compiled
        (:mod:`~companion.kinematics.collision_kernels`); :meth:`clearances_reference` is the
        same in numpy, and the tests hold the two equal."""
        # Imported here: numba costs a start-up that config checks (check-config) must not pay.
        from companion.kinematics import collision_kernels

        q = np.ascontiguousarray(q, dtype=float)
        if q.ndim != 2 or q.shape[1] != self.arm.dof:
            raise ValueError(f"q must have shape (S, {self.arm.dof}), got {q.shape}")
        out = np.empty((q.shape[0], len(self._radii), len(self.volumes)))
        return collision_kernels.clearances(
            q,
            self._frames,
            self._directions,
            self._offsets,
            self._revolute,
            self._mount,
            self._link_idx,
            self._ends,
            self._radii,
            self._caps_a,
            self._caps_b,
            self._caps_r,
            self._boxes_inv,
            self._boxes_half,
            self._cap_of,
            self._box_of,
            ROUNDING_CM,
            out,
        )

    def clearances_reference(self, q: FloatArray) -> FloatArray:
        """:meth:`clearances` in numpy (vectorised over samples, capsules and volumes)."""
        q = np.asarray(q, float)
        seg = self.segments(q)
        s, c = seg.shape[:2]
        p, e = seg[:, :, 0], seg[:, :, 1]
        pad = np.full((s, c, 1), -np.inf)
        if self._caps_r.size:
            dc = (
                segment_segment_distance(p[:, :, None], e[:, :, None], self._caps_a, self._caps_b)
                - self._caps_r
            )
            dc = np.concatenate([dc, pad], axis=2)
        else:
            dc = pad
        if self._boxes_half.size:
            rot = self._boxes_inv[:, :3, :3]
            off = self._boxes_inv[:, :3, 3]
            rot_t = rot.transpose(0, 2, 1)
            pl = (p[:, :, None, None, :] @ rot_t)[..., 0, :] + off
            el = (e[:, :, None, None, :] @ rot_t)[..., 0, :] + off
            db = segment_box_distance(pl, el, self._boxes_half)
            db = np.concatenate([db, pad], axis=2)
        else:
            db = pad
        dist = np.maximum(
            dc[:, :, self._cap_of],
            np.maximum(db[:, :, self._box_of[:, 0]], db[:, :, self._box_of[:, 1]]),
        )
        return dist - self._radii[None, :, None] - ROUNDING_CM

    def clearance_ceiling_cm(self) -> FloatArray:
        """``(C, V)``: per (link capsule, volume) pair, the largest clearance seen over 256
        configurations drawn with a fixed seed (computed once; cm). Some pairs can never get
        far from a volume (a link starting on joint 1's axis under the body keeps that end where
        it is): a cost term asking them for more could not be steered."""
        if self._ceiling is None:
            q = self.arm.random_q_rad(np.random.default_rng(0), 256)
            if self.volumes and len(self._radii):
                self._ceiling = np.asarray(self.clearances(q).max(axis=0))
            else:
                self._ceiling = np.zeros((len(self._radii), len(self.volumes)))
        return self._ceiling

    def _as_batch(self, q: FloatArray | Sequence[float], name: str) -> FloatArray:
        arr = np.asarray(q, float)
        if arr.shape != (self.arm.dof,) or not math.isfinite(float(arr.sum())):
            raise ValueError(f"{name}={q!r} must be {self.arm.dof} finite joint values (rad, cm)")
        return arr.reshape(1, -1)

    def _collision(
        self, clear: FloatArray, fraction: float = 0.0, proven: bool = True
    ) -> Collision:
        """The worst (capsule, volume) pair of one sample's clearances ``(C, V)``."""
        c, v = np.unravel_index(int(np.argmin(clear)), clear.shape)
        return Collision(
            link=self.arm.joints[int(self._link_idx[c])].name,
            volume=self.volumes[int(v)].name,
            clearance_cm=float(clear[c, v]),
            margin_cm=self.margin_cm,
            fraction=fraction,
            proven=proven,
        )

    # -- checks -------------------------------------------------------------------------------

    def clear_mask(self, q: FloatArray) -> FloatArray:
        """Per joint vector of ``q`` ``(S, n)``: True if every capsule keeps the margin."""
        q = np.asarray(q, float)
        if not self.volumes or not len(self._radii):
            return np.ones(q.shape[0], dtype=bool)
        return self.clearances(q).min(axis=(1, 2)) >= self.margin_cm

    def check(
        self, q_rad: FloatArray | Sequence[float], *, reference: bool = False
    ) -> Collision | None:
        """None if the configuration ``q_rad`` (joint units) keeps every link ``margin_cm`` from
        every volume, else the worst link and volume. ``reference``: computed by
        :meth:`clearances_reference` (numpy only, no numba to load: for one-off checks such as
        the config's)."""
        q = self._as_batch(q_rad, "q_rad")
        if not self.volumes or not len(self._radii):
            return None
        clear = (self.clearances_reference if reference else self.clearances)(q)[0]
        if clear.min() >= self.margin_cm:
            return None
        return self._collision(clear)

    def speeds(self, q_from: FloatArray, q_to: FloatArray) -> FloatArray:
        """Per capsule: the bound (cm per unit of the motion parameter) on how fast any of its
        points moves along the straight joint motion ``q_from → q_to``."""
        dq = np.abs(np.asarray(q_to, float) - np.asarray(q_from, float)).reshape(-1)
        return self._reach @ dq

    def check_motion(
        self, q_from_rad: FloatArray | Sequence[float], q_to_rad: FloatArray | Sequence[float]
    ) -> Collision | None:
        """None if every configuration on the straight joint motion ``q_from_rad → q_to_rad``
        keeps every link ``margin_cm`` from every volume (proven by the speed bound of the
        module docstring), else a :class:`Collision` (``fraction``: where along the motion)."""
        q0 = self._as_batch(q_from_rad, "q_from_rad")[0]
        q1 = self._as_batch(q_to_rad, "q_to_rad")[0]
        if not self.volumes or not len(self._radii):
            return None
        speed = self.speeds(q0, q1)  # (C,)
        dq = q1 - q0
        top = float(speed.max())
        # Start with samples step_cm of link travel apart: one interval for a control tick.
        count = int(min(max(math.ceil(top / self.step_cm), 1), self.max_samples // 4))
        s = np.arange(count + 1) / count
        clear = self.clearances(q0 + s[:, None] * dq).min(axis=2)  # (S, C)
        lo_s, hi_s = s[:-1], s[1:]
        lo_c, hi_c = clear[:-1], clear[1:]
        margin = self.margin_cm
        samples = count + 1
        for depth in range(self.max_depth + 1):
            bound = 0.5 * (lo_c + hi_c - speed * (hi_s - lo_s)[:, None])  # (I, C)
            if bound.min() >= margin and clear.min() >= margin:
                return None  # every interval proven (the common case: one check per tick)
            lo_bad = lo_c.min(axis=1) < margin
            hi_bad = hi_c.min(axis=1) < margin
            if lo_bad.any() or hi_bad.any():
                # The earliest sample found inside the margin.
                where = float(min(lo_s[lo_bad].min(initial=2.0), hi_s[hi_bad].min(initial=2.0)))
                q = (q0 + where * dq).reshape(1, -1)
                return self._collision(self.clearances(q)[0], where)
            open_ = np.flatnonzero(bound.min(axis=1) < margin)
            if depth == self.max_depth or samples + open_.size > self.max_samples:
                k = open_[np.argmin(bound[open_].min(axis=1))]
                where = float(0.5 * (lo_s[k] + hi_s[k]))
                q = (q0 + where * dq).reshape(1, -1)
                clear_mid = self.clearances(q)[0]
                worst = int(np.argmin(bound[k]))
                c = int(np.argmin(clear_mid[worst]))
                return Collision(
                    link=self.arm.joints[int(self._link_idx[worst])].name,
                    volume=self.volumes[c].name,
                    clearance_cm=float(bound[k, worst]),
                    margin_cm=margin,
                    fraction=where,
                    proven=False,
                )
            mid_s = 0.5 * (lo_s[open_] + hi_s[open_])
            mid_c = self.clearances(q0 + mid_s[:, None] * dq).min(axis=2)
            samples += mid_s.size
            clear = mid_c
            lo_s = np.concatenate([lo_s[open_], mid_s])
            hi_s = np.concatenate([mid_s, hi_s[open_]])
            lo_c = np.concatenate([lo_c[open_], mid_c])
            hi_c = np.concatenate([mid_c, hi_c[open_]])
        raise AssertionError("unreachable")  # pragma: no cover

    def check_path(self, path_rad: FloatArray | Sequence[Sequence[float]]) -> Collision | None:
        """:meth:`check_motion` over each leg of the polyline ``path_rad`` ``(K, n)`` (joint
        units), in one batch when every leg is proven by its two ends (the common case: a
        control step's outputs changing one after another); else leg by leg. None if every
        configuration on it keeps the margin, else the first :class:`Collision` (``fraction``
        along its leg)."""
        qs = np.asarray(path_rad, float)
        if qs.ndim != 2 or qs.shape[1] != self.arm.dof or not np.all(np.isfinite(qs)):
            raise ValueError(f"path_rad must be (K, {self.arm.dof}) finite joint values")
        if not self.volumes or not len(self._radii) or len(qs) == 0:
            return None
        if len(qs) == 1:
            return self.check(qs[0])
        clear = self.clearances(qs).min(axis=2)  # (K, C)
        if clear.min() >= self.margin_cm:
            speed = np.abs(np.diff(qs, axis=0)) @ self._reach.T  # (K - 1, C)
            bound = 0.5 * (clear[:-1] + clear[1:] - speed)
            if bound.min() >= self.margin_cm:
                return None
        for q_from, q_to in zip(qs[:-1], qs[1:], strict=True):
            hit = self.check_motion(q_from, q_to)
            if hit is not None:
                return hit
        return None


def check_configuration(
    arm: Arm,
    q_rad: FloatArray | Sequence[float],
    volumes: Sequence[Volume],
    mount: Mount | None = None,
    margin_cm: float = 1.0,
) -> Collision | None:
    """One-off :meth:`KeepOut.check` (build a :class:`KeepOut` once for repeated checks)."""
    return KeepOut(arm, volumes, mount, margin_cm).check(q_rad)


def check_motion(
    arm: Arm,
    q_from_rad: FloatArray | Sequence[float],
    q_to_rad: FloatArray | Sequence[float],
    volumes: Sequence[Volume],
    mount: Mount | None = None,
    margin_cm: float = 1.0,
) -> Collision | None:
    """One-off :meth:`KeepOut.check_motion` (build a :class:`KeepOut` once for repeated use)."""
    return KeepOut(arm, volumes, mount, margin_cm).check_motion(q_from_rad, q_to_rad)
