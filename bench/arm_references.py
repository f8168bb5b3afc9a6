"""Arm files and FK references from roboticstoolbox-python's DH models (needs the bench extra).

    .venv/bin/python -m bench.arm_references [--write-arms] [--check]

``--write-urdf`` writes ``ur5.urdf``: ur5.toml as a URDF, the joint axes turned to other
directions and fixed joints at either end, to test the URDF import against the DH arm.

``--write-arms`` (re)writes ``companion/kinematics/arms/<name>.toml`` from
``roboticstoolbox.models.DH.<Model>()``: lengths in metres as rtb has them, angles in degrees.
Models without joint limits (UR5, UR10, Baxter) get rtb's own default for them, ±180°, the
limits its ``ets().ik_LM`` then applies. Puma560 keeps its full ranges (joint 6: ±266°).

Without options it writes ``tests/kinematics/data/rtb_fk.json``: for every model, 8 joint vectors
drawn within the limits (seed 16) and rtb's ``fkine`` of each (4×4, metres), which the tests
compare the arm files against to 1e-9 m without needing roboticstoolbox. ``--check`` compares
live instead, and prints the largest difference per arm.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import numpy as np

from companion.kinematics.arm import Arm

ROOT = Path(__file__).resolve().parent.parent
ARMS = ROOT / "companion" / "kinematics" / "arms"
REFERENCE = ROOT / "tests" / "kinematics" / "data" / "rtb_fk.json"
MODELS = {
    "puma560": "Puma560",
    "ur5": "UR5",
    "ur10": "UR10",
    "panda": "Panda",
    "stanford": "Stanford",
    "baxter": "Baxter",
}


def _model(name: str):  # noqa: ANN202 - roboticstoolbox is untyped
    import roboticstoolbox as rtb

    return getattr(rtb.models.DH, MODELS[name])()


def _frame_toml(key: str, matrix: np.ndarray) -> str:
    from companion.kinematics import matrix_to_rpy

    rpy = np.degrees(matrix_to_rpy(matrix[:3, :3]))
    xyz = ", ".join(repr(float(v)) for v in matrix[:3, 3])
    return f"\n[{key}]\nxyz = [{xyz}]\nrpy_deg = [{', '.join(repr(float(v)) for v in rpy)}]\n"


def arm_toml(name: str) -> str:
    return model_toml(MODELS[name], name)


def model_toml(model: str, name: str) -> str:
    """The arm file of ``roboticstoolbox.models.DH.<model>()`` (any of rtb's DH zoo)."""
    import roboticstoolbox as rtb

    robot = getattr(rtb.models.DH, model)()
    qlim = robot.ets().qlim  # rtb's limits, ±π where the model has none
    lines = [
        f"# {robot.name} from roboticstoolbox-python {_rtb_version()} (models.DH.{model}),",
        "# written by bench/arm_references.py --write-arms. Lengths in metres as rtb has them.",
        f'name = "{name}"',
        f'convention = "{"modified" if robot.mdh else "standard"}"',
        'length_unit = "m"',
        f"dof = {robot.n}",
    ]
    for i, link in enumerate(robot.links):
        lines += ["", "[[joint]]", f'name = "q{i + 1}"']
        if link.isprismatic:
            lines += [
                'type = "prismatic"',
                f"alpha_deg = {math.degrees(link.alpha)!r}",
                f"a = {float(link.a)!r}",
                f"theta_deg = {math.degrees(link.theta)!r}",
                f"offset = {float(link.offset)!r}",
                f"min = {float(qlim[0, i])!r}",
                f"max = {float(qlim[1, i])!r}",
            ]
        else:
            lines += [
                f"alpha_deg = {math.degrees(link.alpha)!r}",
                f"a = {float(link.a)!r}",
                f"d = {float(link.d)!r}",
                f"offset_deg = {math.degrees(link.offset)!r}",
                f"min_deg = {math.degrees(qlim[0, i])!r}",
                f"max_deg = {math.degrees(qlim[1, i])!r}",
            ]
        if link.isflip:
            lines.append("direction = -1")
    text = "\n".join(lines) + "\n"
    if not np.allclose(robot.base.A, np.eye(4)):
        text += _frame_toml("base", robot.base.A)
    if not np.allclose(robot.tool.A, np.eye(4)):
        text += _frame_toml("tool", robot.tool.A)
    return text


# Axes the URDF's joints are written about (the frames are rotated to match), so that the import's
# general axes are exercised, not only z.
_URDF_AXES = ([0, 0, 1], [0, 1, 0], [1, 0, 0], [0, 0, -1], [0, -0.6, 0.8], [-1, 0, 0], [0, 0, 1])


def _origin(matrix: np.ndarray) -> str:
    from companion.kinematics import matrix_to_rpy

    xyz = " ".join(repr(float(v) / 100.0) for v in matrix[:3, 3])  # cm -> m
    rpy = " ".join(repr(float(v)) for v in matrix_to_rpy(matrix[:3, :3]))
    return f'<origin xyz="{xyz}" rpy="{rpy}"/>'


def arm_urdf(arm: Arm) -> str:
    """A URDF of a (revolute, DH) arm with the same FK: a fixed base joint, the moving joints
    about the axes of ``_URDF_AXES``, a fixed flange joint at the end."""
    from companion.kinematics.urdf import _z_onto

    f = arm.frames_array
    n = arm.dof
    rots = [_z_onto(np.asarray(_URDF_AXES[i], float)) for i in range(n)]
    lines = [
        '<?xml version="1.0"?>',
        f"<!-- {arm.name} written as URDF by bench/arm_references.py (option write-urdf);",
        f"     the same FK as {arm.name}.toml (tests/kinematics/test_urdf.py). -->",
        f'<robot name="{arm.name}-urdf">',
        '  <link name="world"/>',
        '  <link name="base_link"/>',
    ]
    lines += [f'  <link name="link{i + 1}"/>' for i in range(n)]
    lines += [
        '  <link name="flange"/>',
        '  <joint name="world_to_base" type="fixed">',
        '    <parent link="world"/><child link="base_link"/>',
        "    " + _origin(np.eye(4)),
        "  </joint>",
    ]
    parent = "base_link"
    prev_rot = np.eye(4)
    for i, joint in enumerate(arm.joints):
        origin = prev_rot @ f[i] @ rots[i].T
        axis = " ".join(repr(float(v)) for v in rots[i][:3, 2])
        lo, hi = joint.lower, joint.upper
        lines += [
            f'  <joint name="{joint.name}" type="revolute">',
            f'    <parent link="{parent}"/><child link="link{i + 1}"/>',
            "    " + _origin(origin),
            f'    <axis xyz="{axis}"/>',
            f'    <limit lower="{lo!r}" upper="{hi!r}" effort="1" velocity="1"/>',
            "  </joint>",
        ]
        parent = f"link{i + 1}"
        prev_rot = rots[i]
    lines += [
        '  <joint name="flange" type="fixed">',
        f'    <parent link="{parent}"/><child link="flange"/>',
        "    " + _origin(prev_rot @ f[n]),
        "  </joint>",
        "</robot>",
    ]
    return "\n".join(lines) + "\n"


def _rtb_version() -> str:
    import roboticstoolbox as rtb

    return str(rtb.__version__)


def reference() -> dict:
    out: dict = {"rtb_version": _rtb_version(), "unit": "m", "arms": {}}
    for name in MODELS:
        robot = _model(name)
        arm = Arm.from_package_file(f"{name}.toml")
        q = arm.random_q_rad(np.random.default_rng(16), 8)
        q[0] = np.clip(0.0, arm.lower_q, arm.upper_q)
        out["arms"][name] = [
            {"q": row.tolist(), "T": robot.fkine(_rtb_q(arm, row)).A.tolist()} for row in q
        ]
    return out


def _rtb_q(arm: Arm, q: np.ndarray) -> np.ndarray:
    """Our joint units (rad, cm) → rtb's (rad, m)."""
    return np.where(arm.revolute, q, q / 100.0)


def check() -> None:
    for name in MODELS:
        robot = _model(name)
        arm = Arm.from_package_file(f"{name}.toml")
        q = arm.random_q_rad(np.random.default_rng(99), 200)
        scale = np.array([[1.0, 1.0, 1.0, 100.0]])  # translation cm -> m
        worst = max(
            float(
                np.abs(arm.fk_matrix(row)[:3] / scale - robot.fkine(_rtb_q(arm, row)).A[:3]).max()
            )
            for row in q
        )
        print(f"{name:10s} max |T_ours - T_rtb| = {worst:.2e} (m and rotation entries)")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--write-arms", action="store_true")
    parser.add_argument("--check", action="store_true")
    parser.add_argument("--write-urdf", action="store_true")
    args = parser.parse_args()
    if args.write_arms:
        for name in MODELS:
            (ARMS / f"{name}.toml").write_text(arm_toml(name))
            print("wrote", name)
    elif args.write_urdf:
        (ARMS / "ur5.urdf").write_text(arm_urdf(Arm.from_package_file("ur5.toml")))
        print("wrote ur5.urdf")
    elif args.check:
        check()
    else:
        REFERENCE.write_text(json.dumps(reference(), indent=1) + "\n")
        print("wrote", REFERENCE.relative_to(ROOT))


if __name__ == "__main__":
    main()
