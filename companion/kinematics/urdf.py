"""Serial chains from URDF: :func:`load_urdf` / :func:`parse_urdf` → :class:`~.arm.Arm`.

Parsed with the standard library's ``xml.etree.ElementTree``. A URDF parser package
(urdf_parser_py, yourdfpy) was not worth a runtime dependency: what we read is five elements
(``robot``, ``link``, ``joint`` with ``origin``, ``axis``, ``limit``, ``mimic``), the tree walk is a
dozen lines, and those packages pull in lxml, trimesh or ROS-era code for meshes and
transmissions we never use. The XML comes from the operator's own arm file, not from the network,
but it is still read as untrusted text: ElementTree expands no external entities.

What is taken (and ``<collision>`` shapes, below):

* the chain from the root link (the one link that is no joint's child) to ``tip_link``; without
  it, the tip is chosen as below (ROS-Industrial and full-robot URDFs hang fixed frames, sensors
  and fingers beside the arm, so the tree seldom has one path);
* ``revolute`` (``<limit lower upper>`` required, radians), ``continuous`` (limits [−π, π]: every
  orientation once) and ``prismatic`` (``<limit>`` required, metres) joints; ``fixed`` joints are
  folded into the transforms around them (or the base and tool at either end);
* ``floating`` and ``planar`` joints, ``<mimic>``, a zero axis and unknown types are refused with
  an :class:`~companion.errors.ArmConfigError` naming the joint.

The tip without ``tip_link``, in three rules:

* the arm is the chain from the root with the most moving joints (every joint but ``fixed``
  counts: a ``floating`` or mistyped joint is then on the chain and refused by name, not cut off
  silently; a ``<mimic>`` finger counts like its leader). Branches of fixed joints only (a
  ``base_link``→``base`` frame, sensor frames) and shorter moving branches (a camera's pan
  joint) are left off; a tree without a moving joint is refused;
* its tip is the link its last moving joint moves, followed on through fixed joints while the
  link has exactly one child joint and that one is fixed: ``wrist_3_link``→``flange``→``tool0``
  ends at ``tool0``, but a ``tool0`` beside a ``flange`` (or a sensor frame) stops at
  ``wrist_3_link``;
* chains tied for the most moving joints, each ending in a moving joint of its own, part at a
  link (the deepest they all pass). When each has fewer moving joints after that link than
  before it (a gripper's fingers, one or two joints each, after a 6- or 7-joint arm), the arm
  ends at that link (the hand; its fixed tool frames are not followed: give ``tip_link`` for a
  TCP frame). Otherwise (two arms from a torso) the URDF is refused, naming the candidate tip
  links, each found by these rules within its branch (``left_tool0, right_tool0``).

A gripper with a single moving joint (one finger moves, or a turning jaw) makes the longest chain
on its own and is taken as the arm's last joint: give ``tip_link`` for the hand.

Collision shapes (for the keep-out checks, :mod:`~companion.kinematics.collision`): the
``<collision>`` elements of each link the chain moves (a moving joint's child and the links fixed
to it) become that joint's :class:`~companion.kinematics.arm.LinkCapsule` list, each the
smallest capsule of its kind that contains the shape (so a check errs on the safe side):

* ``<sphere radius>``: the sphere itself (a zero-length capsule);
* ``<capsule radius length>``: itself (``length``: the cylindrical part, between the cap centres);
* ``<cylinder radius length>``: the capsule of the same radius along its axis, ``length`` long;
* ``<box size>``: a capsule along its longest edge, as long as that edge, of radius the half
  diagonal of the other two;
* ``<mesh>``: not read (it would need the mesh file): give such a link a primitive as well.

The root link's (and any link before the first moving joint's) collisions are fixed to the
vehicle and not taken.

Each moving joint ``origin · Rot(axis, q)`` becomes ``(origin · R_a) · Rz(q) · R_aᵀ`` with
``R_a`` taking z onto the axis, so the arm has the one form the solver uses (module docstring of
:mod:`~.arm`). Lengths go from metres to centimetres.
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from dataclasses import replace
from pathlib import Path

import numpy as np

from companion.errors import ArmConfigError
from companion.kinematics.arm import Arm, Joint, JointKind, LinkCapsule, transform
from companion.kinematics.rotations import FloatArray

M_TO_CM = 100.0
_MOVING = {"revolute": JointKind.REVOLUTE, "continuous": JointKind.REVOLUTE}
_MOVING["prismatic"] = JointKind.PRISMATIC
_REFUSED = ("floating", "planar")


def load_urdf(path: str | Path, *, tip_link: str | None = None) -> Arm:
    """Read a URDF file; problems raise :class:`ArmConfigError` naming the file and joint."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise ArmConfigError(str(path), "<file>", f"cannot read: {exc}") from exc
    return parse_urdf(text, source=str(path), tip_link=tip_link)


def _floats(source: str, field: str, text: str | None, default: str) -> list[float]:
    parts = (text if text is not None else default).split()
    try:
        values = [float(p) for p in parts]
    except ValueError as exc:
        raise ArmConfigError(source, field, f"must be 3 numbers, got {text!r}") from exc
    if len(values) != 3 or not all(math.isfinite(v) for v in values):
        raise ArmConfigError(source, field, f"must be 3 finite numbers, got {text!r}")
    return values


def _limit(source: str, field: str, element: ET.Element | None, key: str) -> float:
    text = None if element is None else element.get(key)
    if text is None:
        raise ArmConfigError(source, field, f"<limit {key}=...> is required for this joint type")
    try:
        value = float(text)
    except ValueError as exc:
        raise ArmConfigError(source, field, f"{key}={text!r} is not a number") from exc
    if not math.isfinite(value):
        raise ArmConfigError(source, field, f"{key}={text!r} must be finite")
    return value


def _z_onto(axis: FloatArray) -> FloatArray:
    """A rotation (4×4) taking the z axis onto the unit vector ``axis``."""
    out = np.eye(4)
    z = np.array([0.0, 0.0, 1.0])
    c = float(axis @ z)
    if c > 1.0 - 1e-15:
        return out
    if c < -1.0 + 1e-15:
        out[:3, :3] = np.diag([1.0, -1.0, -1.0])  # half a turn about x
        return out
    v = np.cross(z, axis)
    vx = np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])
    out[:3, :3] = np.eye(3) + vx + vx @ vx / (1.0 + c)
    return out


def _positive_attr(source: str, field: str, element: ET.Element, key: str) -> float:
    text = element.get(key)
    try:
        value = float(text) if text is not None else math.nan
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and value > 0):
        raise ArmConfigError(source, field, f"{key}={text!r} must be a finite number > 0")
    return value


def _link_capsules(source: str, link: ET.Element, attach: FloatArray) -> list[LinkCapsule]:
    """The bounding capsules of ``link``'s ``<collision>`` primitives (module docstring), in
    the arm's link frame: ``attach`` takes the URDF link's coordinates (m → cm done) there."""
    out = []
    lname = link.get("name") or "?"
    for k, collision in enumerate(link.findall("collision")):
        field = f"link {lname}.collision[{k}]"
        geometry = collision.find("geometry")
        shape = None if geometry is None else next(iter(geometry), None)
        if shape is None:
            raise ArmConfigError(source, field, "needs a <geometry> with one shape")
        origin = collision.find("origin")
        xyz = _floats(
            source, f"{field}.origin.xyz", None if origin is None else origin.get("xyz"), "0 0 0"
        )
        rpy = _floats(
            source, f"{field}.origin.rpy", None if origin is None else origin.get("rpy"), "0 0 0"
        )
        place = attach @ transform(np.asarray(xyz) * M_TO_CM, rpy)
        half = np.zeros(3)
        if shape.tag == "sphere":
            radius = _positive_attr(source, f"{field}.sphere", shape, "radius")
        elif shape.tag in ("cylinder", "capsule"):
            radius = _positive_attr(source, f"{field}.{shape.tag}", shape, "radius")
            half[2] = _positive_attr(source, f"{field}.{shape.tag}", shape, "length") / 2
        elif shape.tag == "box":
            size = np.asarray(_floats(source, f"{field}.box.size", shape.get("size"), ""))
            if not np.all(size > 0):
                raise ArmConfigError(source, f"{field}.box.size", f"must be > 0, got {size}")
            axis = int(np.argmax(size))
            others = np.delete(size, axis)
            half[axis] = size[axis] / 2
            radius = float(np.hypot(others[0], others[1])) / 2
        elif shape.tag == "mesh":
            continue
        else:
            raise ArmConfigError(
                source, field, f"<{shape.tag}> is not one of sphere, capsule, cylinder, box, mesh"
            )
        ends = [place[:3, :3] @ (sign * half * M_TO_CM) + place[:3, 3] for sign in (-1, 1)]
        out.append(
            LinkCapsule(
                (float(ends[0][0]), float(ends[0][1]), float(ends[0][2])),
                (float(ends[1][0]), float(ends[1][1]), float(ends[1][2])),
                radius * M_TO_CM,
            )
        )
    return out


def _default_tip(
    source: str,
    root: str,
    joints: list[ET.Element],
    by_parent: dict[str, list[ET.Element]],
    parent_of: dict[str, str],
    child_of: dict[int, str],
) -> str:
    """The tip link when none is given: the rules in the module docstring."""
    moving = {root: 0}  # link -> moving joints from the root to it, for links the root reaches
    todo = [root]
    while todo:
        link = todo.pop()
        for j in by_parent.get(link, []):
            child = child_of[id(j)]
            moving[child] = moving[link] + (j.get("type") != "fixed")
            todo.append(child)
    most = max(moving.values())
    if most == 0:
        raise ArmConfigError(
            source, "<robot>", f"no moving joint: every joint from the root link {root!r} is fixed"
        )
    ends = [  # the links the last moving joint of each longest chain moves, in file order
        child_of[id(j)]
        for j in joints
        if j.get("type") != "fixed" and moving.get(child_of[id(j)]) == most
    ]

    def from_root(link: str) -> list[str]:
        out = [link]
        while out[-1] != root:
            out.append(parent_of[out[-1]])
        return out[::-1]

    def shared(paths: list[list[str]]) -> int:  # how many links the paths share from the root
        n = 0
        while all(len(p) > n and p[n] == paths[0][n] for p in paths):
            n += 1
        return n

    def tips(ends: list[str]) -> list[str]:
        if len(ends) == 1:
            link = ends[0]
            while len(by_parent.get(link, [])) == 1 and by_parent[link][0].get("type") == "fixed":
                link = child_of[id(by_parent[link][0])]
            return [link]
        paths = [from_root(end) for end in ends]  # none holds another: each ends moving
        n = shared(paths)
        branch = paths[0][n - 1]
        if most - moving[branch] < moving[branch]:
            return [branch]  # fingers after a hand: the arm ends at the hand
        groups: dict[str, list[str]] = {}
        for end, p in zip(ends, paths, strict=True):
            groups.setdefault(p[n], []).append(end)
        return [tip for group in groups.values() for tip in tips(group)]

    found = tips(ends)
    if len(found) > 1:
        paths = [from_root(end) for end in ends]
        word = "joint" if most == 1 else "joints"
        raise ArmConfigError(
            source,
            "tip_link",
            f"the tree branches at link {paths[0][shared(paths) - 1]!r} into {len(found)} "
            f"chains of {most} moving {word}: set tip_link to one of: {', '.join(found)}",
        )
    return found[0]


def parse_urdf(text: str, *, source: str = "<urdf>", tip_link: str | None = None) -> Arm:
    """Build an :class:`Arm` from URDF text (see the module docstring for what is accepted)."""
    try:
        root = ET.fromstring(text)
    except ET.ParseError as exc:
        raise ArmConfigError(source, "<file>", f"not valid XML: {exc}") from exc
    if root.tag != "robot":
        raise ArmConfigError(source, "<file>", f"the root element is <{root.tag}>, not <robot>")
    name = root.get("name") or Path(source).stem or "arm"
    link_elements = {link.get("name") or "": link for link in root.findall("link")}
    links = set(link_elements)
    joints = root.findall("joint")
    by_child: dict[str, ET.Element] = {}
    by_parent: dict[str, list[ET.Element]] = {}
    parent_of: dict[str, str] = {}  # child link -> parent link
    child_of: dict[int, str] = {}  # id(joint element) -> child link
    for j in joints:
        jname = j.get("name") or "?"
        parent, child = j.find("parent"), j.find("child")
        if parent is None or child is None:
            raise ArmConfigError(source, f"joint {jname}", "needs <parent link=...> and <child>")
        p, c = parent.get("link") or "", child.get("link") or ""
        for link in (p, c):
            if link not in links:
                raise ArmConfigError(source, f"joint {jname}", f"link {link!r} is not defined")
        if c in by_child:
            raise ArmConfigError(
                source, f"joint {jname}", f"link {c!r} is already the child of another joint"
            )
        by_child[c] = j
        by_parent.setdefault(p, []).append(j)
        parent_of[c] = p
        child_of[id(j)] = c
    roots = sorted(link for link in links if link not in by_child)
    if len(roots) != 1:
        raise ArmConfigError(source, "<robot>", f"needs exactly one root link, found {roots}")

    if tip_link is None:
        tip_link = _default_tip(source, roots[0], joints, by_parent, parent_of, child_of)
    elif tip_link not in links:
        raise ArmConfigError(source, "tip_link", f"link {tip_link!r} is not defined")
    path: list[ET.Element] = []
    link = tip_link
    seen = {link}
    while link in by_child:
        path.append(by_child[link])
        link = parent_of[link]
        if link in seen:  # every link has one parent: a loop never reaches the root
            raise ArmConfigError(
                source,
                "tip_link",
                f"link {tip_link!r} hangs from a loop of joints through link {link!r}, "
                f"not from the root link {roots[0]!r}",
            )
        seen.add(link)
    path.reverse()

    arm_joints: list[Joint] = []
    before: list[FloatArray] = []
    after: list[FloatArray] = []
    pending = np.eye(4)
    shapes: list[list[LinkCapsule]] = []
    attach = np.eye(4)  # the current URDF link's frame in the last moving joint's link frame
    for j in path:
        jname = j.get("name") or "?"
        field = f"joint {jname}"
        kind_text = j.get("type") or ""
        if j.find("mimic") is not None:
            raise ArmConfigError(source, field, "mimic joints are not supported")
        if kind_text in _REFUSED:
            raise ArmConfigError(source, field, f"{kind_text} joints are not supported")
        origin = j.find("origin")
        xyz = _floats(
            source, f"{field}.origin.xyz", None if origin is None else origin.get("xyz"), "0 0 0"
        )
        rpy = _floats(
            source, f"{field}.origin.rpy", None if origin is None else origin.get("rpy"), "0 0 0"
        )
        placed = pending @ transform(np.asarray(xyz) * M_TO_CM, rpy)
        if kind_text == "fixed":
            pending = placed
            if shapes:
                attach = attach @ transform(np.asarray(xyz) * M_TO_CM, rpy)
                shapes[-1] += _link_capsules(source, link_elements[child_of[id(j)]], attach)
            continue
        if kind_text not in _MOVING:
            allowed = "revolute, continuous, prismatic, fixed"
            raise ArmConfigError(source, f"{field}.type", f"{kind_text!r} is not one of {allowed}")
        axis_el = j.find("axis")
        axis = np.asarray(
            _floats(
                source, f"{field}.axis", None if axis_el is None else axis_el.get("xyz"), "1 0 0"
            )
        )
        norm = float(np.linalg.norm(axis))
        if norm < 1e-9:
            raise ArmConfigError(source, f"{field}.axis", "the axis is zero")
        rot = _z_onto(axis / norm)
        kind = _MOVING[kind_text]
        limit = j.find("limit")
        if kind_text == "continuous":
            lower, upper = -math.pi, math.pi
        else:
            lower = _limit(source, f"{field}.limit", limit, "lower")
            upper = _limit(source, f"{field}.limit", limit, "upper")
            if not lower < upper:
                raise ArmConfigError(
                    source, f"{field}.limit", f"lower={lower:g} must be less than upper={upper:g}"
                )
            if kind is JointKind.PRISMATIC:
                lower, upper = lower * M_TO_CM, upper * M_TO_CM
        arm_joints.append(Joint(name=jname, lower=lower, upper=upper, kind=kind))
        before.append(placed @ rot)
        after.append(rot.T.copy())
        pending = np.eye(4)
        # The URDF child link's frame is origin · Rot(axis, q) = (our link frame) · R_aᵀ.
        attach = rot.T.copy()
        shapes.append(_link_capsules(source, link_elements[child_of[id(j)]], attach))
    if not arm_joints:
        raise ArmConfigError(source, "<robot>", "no moving joint on the chain")
    if len(after) > 0:
        after[-1] = after[-1] @ pending
    arm = Arm.from_parts(name, arm_joints, before, after)
    if any(shapes):
        arm = replace(arm, link_shapes=tuple(tuple(s) for s in shapes))
    return arm
