"""The ``armbridge`` command line.

Subcommands:

* ``demo``: solve the inverse kinematics of a few poses of the default arm (reachable ones and
  the papers' unreachable target G) with :func:`companion.ik.solve` and print the joints,
  errors and times.
* ``solve X Y Z ROLL PITCH YAW``: one-off IK for a target in cm and degrees.

Exit codes: 0 success, 1 target not reached within tolerance, 2 bad input or configuration.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

from companion import ik
from companion.arm import Arm, Pose
from companion.errors import ArmConfigError

PAPER_TARGET_G = Pose(-20.0, 3.0, 40.0, 0.0, 10.0, 15.0)  # papers' test target (cm, deg)

# Joint configurations (deg) whose hand poses the demo asks for: reachable by construction.
DEMO_JOINTS_DEG = (
    (0.0, 90.0, 0.0, 0.0, 0.0, 0.0),
    (30.0, 60.0, -20.0, 45.0, 30.0, 10.0),
    (-45.0, 120.0, 30.0, -30.0, -20.0, 60.0),
)


def _print_solution(arm: Arm, target: Pose, args: argparse.Namespace) -> bool:
    res = ik.solve(
        arm,
        target,
        budget_ms=args.budget_ms,
        seed=args.seed,
        tol_pos_cm=args.tol_pos_cm,
        tol_ori_deg=args.tol_ori_deg,
    )
    q = ", ".join(f"{v:7.2f}" for v in res.q_deg)
    print(
        f"target  x,y,z = {target.x_cm:7.2f} {target.y_cm:7.2f} {target.z_cm:7.2f} cm   "
        f"r,p,y = {target.roll_deg:7.2f} {target.pitch_deg:7.2f} {target.yaw_deg:7.2f} deg"
    )
    print(f"  joints_deg = [{q}]")
    print(
        f"  pos_err = {res.pos_err_cm:.1e} cm   ori_err = {res.ori_err_deg:.1e} deg   "
        f"{res.elapsed_ms:.3f} ms   {res.generations} generations   "
        f"{'REACHED' if res.converged else 'NOT REACHED (best compromise shown)'}"
    )
    return res.converged


def _cmd_demo(args: argparse.Namespace) -> int:
    arm = Arm.default()
    print(f"arm: {arm.name} ({arm.convention.value} DH, {arm.dof} joints)\n")
    for q in DEMO_JOINTS_DEG:
        _print_solution(arm, arm.fk(q), args)
    print("\nthe papers' target G (unreachable within the Table 2 limits):")
    _print_solution(arm, PAPER_TARGET_G, args)
    return 0


def _cmd_solve(args: argparse.Namespace) -> int:
    arm = Arm.from_toml(args.arm, dof=None) if args.arm else Arm.default()
    target = Pose.from_sequence(args.pose)
    ok = _print_solution(arm, target, args)
    return 0 if ok else 1


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="armbridge", description=__doc__.split("\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)

    def tolerances(p: argparse.ArgumentParser) -> None:
        p.add_argument("--tol-pos-cm", type=float, default=1e-3, help="position tolerance (cm)")
        p.add_argument(
            "--tol-ori-deg", type=float, default=1e-3, help="orientation tolerance (deg)"
        )
        p.add_argument("--seed", type=int, default=0, help="random seed")
        p.add_argument("--budget-ms", type=float, default=20.0, help="solver time budget (ms)")

    demo = sub.add_parser("demo", help="solve IK for a few poses of the default arm and print them")
    tolerances(demo)
    demo.set_defaults(func=_cmd_demo)

    solve = sub.add_parser("solve", help="one-off IK for a target pose")
    solve.add_argument(
        "pose",
        nargs=6,
        type=float,
        metavar=("X_CM", "Y_CM", "Z_CM", "ROLL_DEG", "PITCH_DEG", "YAW_DEG"),
    )
    solve.add_argument("--arm", help="arm TOML file (default: the papers' arm)")
    tolerances(solve)
    solve.set_defaults(func=_cmd_solve)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args))
    except (ArmConfigError, ValueError) as exc:
        print(f"armbridge: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
