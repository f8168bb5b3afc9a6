"""World-frame hold: the hand's error in the world while the simulated vehicle hovers, with and
without the daemon's compensation.

    python -m bench.world_hold [--duration-s 30] [--start-s 10] [--seed 0]
                               [--dialect ardupilot|px4] [--rate-hz 50] [--telemetry-hz 50]
                               [--markdown bench/results/world_hold.md]
                               [--plot bench/results/world_hold.png]

Two runs on the same seeded hover disturbance (``sim_servo.hover``: drift up to 10 cm, tilt up
to 5°, periods 1–5 s), each a fresh daemon and simulator on UDP loopback (``bench/loopback.py``)
with ``control.rate_hz`` = 50 and ``[world] enabled``:

* **held in the arm's frame**: ``goto`` the base-frame pose ``H`` of a comfortable
  configuration; the arm holds it relative to the vehicle, so the hand moves with it;
* **held in the world**: ``goto`` with ``"frame": "local_ned"`` the world pose ``W`` that ``H``
  is with the vehicle at its home (the centre of the disturbance, level, yaw 0).

The simulator logs the vehicle and the hand in LOCAL_NED (``vehicle`` events, 50 Hz); the error
is the hand's distance from ``W`` (position, cm) and the angle between their orientations (°),
over the same window of simulator time ``[start_s, start_s + duration_s]`` in both runs.
Also: the daemon's CPU over the window (utime + stime, % of one core), and the floor that the
servos' 1 µs PWM resolution leaves (the ideal joints for each logged vehicle pose, solved and
rounded to whole µs through the calibration: the error no controller can go under).
``--plot`` (with matplotlib, the ``plots`` extra) draws the hand's world error over time in both
runs; ``docs/world_hold.png`` is one such plot.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import numpy as np

from bench.loopback import Stack, cpu_s, load_average, plt
from bench.report import machine, md_table, write_markdown
from companion import ik
from companion.kinematics.arm import Arm, Pose
from companion.kinematics.rotations import rotation_angle, rpy_to_matrix
from companion.kinematics.vehicle import Mount, base_to_world, transform, world_to_base
from devkit.control_client import ControlConnection
from firmware_interface.calibration import default_calibration
from sim_servo.eventlog import world_timeline
from sim_servo.world import WorldPose, pose_error

ROOT = Path(__file__).resolve().parent.parent
#: The arm's configuration held (the demo's comfortable pose).
HOLD_DEG = (0.0, 70.0, -70.0, 0.0, 0.0, 0.0)
#: The simulator's default home: 2 m up over the origin, level, yaw 0.
HOME_NED_CM = (0.0, 0.0, -200.0)


def world_target(arm: Arm, mount: Mount) -> tuple[Pose, Pose]:
    hand = arm.fk(HOLD_DEG)
    home = transform(np.eye(3), HOME_NED_CM)
    return hand, base_to_world(hand, home, mount.matrix)


def run(compensate: bool, args: argparse.Namespace) -> dict:
    arm, mount = Arm.default(), Mount()
    hand, world = world_target(arm, mount)
    started = time.monotonic()
    with Stack(
        dialect=args.dialect,
        daemon={
            "control": {"rate_hz": args.rate_hz},
            "arm": {"joint_speed_deg_s": args.joint_speed_deg_s},
            "world": {
                "enabled": True,
                "lead_ms": args.lead_ms,
                "telemetry_hz": args.telemetry_hz,
            },
        },
        sim_args=("--hover-seed", str(args.seed), "--vehicle-log-hz", "50"),
    ) as stack:
        client = ControlConnection(stack.control_path)
        try:
            # The streams are asked for on link-up; the first frames follow.
            deadline = time.monotonic() + 10.0
            while (
                client.request({"cmd": "status"})["status"]["world"].get("telemetry_age_ms") is None
            ):
                if time.monotonic() > deadline:
                    raise RuntimeError("no ATTITUDE / LOCAL_POSITION_NED within 10 s")
                time.sleep(0.05)
            request: dict = (
                {
                    "cmd": "goto",
                    "pose": list(world.as_tuple()),
                    "frame": "local_ned",
                    "mode": args.mode,
                }
                if compensate
                else {"cmd": "goto", "pose": list(hand.as_tuple())}
            )
            reply = client.request(request)
            if reply.get("outcome") != "accepted":
                raise RuntimeError(f"goto not accepted: {reply}")
            # The simulator started a little after `started`: wait past the window's end.
            while time.monotonic() - started < args.start_s:
                time.sleep(0.05)
            cpu0, wall0 = cpu_s(stack.daemon_pid), time.monotonic()
            while time.monotonic() - started < args.start_s + args.duration_s + 1.0:
                time.sleep(0.05)
            cpu_pct = 100.0 * (cpu_s(stack.daemon_pid) - cpu0) / (time.monotonic() - wall0)
            client.close()  # idle past control.idle_timeout_s: the daemon closed it
            client = ControlConnection(stack.control_path)
            status = client.request({"cmd": "status"})["status"]
        finally:
            client.close()
        events = stack.stop()
    samples = [
        s
        for s in world_timeline(events)
        if args.start_s <= s.t_s <= args.start_s + args.duration_s and s.hand is not None
    ]
    pos_cm, ori_deg = errors(samples, world)
    return {
        "compensate": compensate,
        "samples": samples,
        "pos_cm": pos_cm,
        "ori_deg": ori_deg,
        "cpu_pct": cpu_pct,
        "world_status": status.get("world", {}),
    }


def errors(samples: list, world: Pose) -> tuple[np.ndarray, np.ndarray]:
    """Per sample: the hand's distance from ``world`` (cm) and its rotation from it (°), by the
    simulator's own :func:`sim_servo.world.pose_error`."""
    target = WorldPose(
        world.x_cm / 100.0, world.y_cm / 100.0, world.z_cm / 100.0, *map(math.radians, (
            world.roll_deg, world.pitch_deg, world.yaw_deg))
    )  # fmt: skip
    pairs = [pose_error(s.hand, target) for s in samples]
    return (
        np.array([100.0 * d for d, _ in pairs]),
        np.array([math.degrees(a) for _, a in pairs]),
    )


def quantisation_floor(samples: list, world: Pose, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """For each sample's vehicle pose: the ideal joints for ``world``, rounded to whole µs."""
    arm, mount, calibration = Arm.default(), Mount(), default_calibration()
    target = world.as_matrix()
    pos, ori = [], []
    q_prev: tuple[float, ...] = HOLD_DEG
    for s in samples[:: max(1, len(samples) // 300)]:
        v = s.vehicle
        vehicle = transform(
            rpy_to_matrix(v.roll_rad, v.pitch_rad, v.yaw_rad),
            (100.0 * v.north_m, 100.0 * v.east_m, 100.0 * v.down_m),
        )
        in_base = world_to_base(world, vehicle, mount.matrix)
        res = ik.solve(arm, in_base, budget_ms=50.0, seed=seed, q_start_deg=q_prev)
        if not res.converged:
            continue
        q_prev = tuple(res.q_deg)
        pwm = calibration.angles_to_pwm_us(res.q_deg)
        q_rounded = [
            calibration.for_output(o).pwm_us_to_angle_deg(pwm[o]) for o in calibration.outputs
        ]
        hand = base_to_world(arm.fk(q_rounded), vehicle, mount.matrix)
        m = hand.as_matrix()
        pos.append(float(np.linalg.norm(m[:3, 3] - target[:3, 3])))
        ori.append(math.degrees(float(rotation_angle(m[:3, :3], target[:3, :3]))))
    return np.asarray(pos), np.asarray(ori)


def plot(held: dict, followed: dict, floor_pos: np.ndarray, path: Path) -> None:
    """The hand's position error in the world over simulator time, both runs, and the floor."""
    fig, ax = plt.subplots(figsize=(9, 4))
    for r, label in ((held, "held in the arm's frame"), (followed, "held in LOCAL_NED")):
        t = np.array([s.t_s for s in r["samples"]])
        ax.plot(t, r["pos_cm"], linewidth=0.9, label=label)
    ax.axhline(float(np.percentile(floor_pos, 99)), color="grey", linewidth=0.8,
               linestyle="--", label="1 µs PWM floor (p99)")  # fmt: skip
    ax.set_xlabel("simulator time (s)")
    ax.set_ylabel("hand position error in the world (cm)")
    ax.set_yscale("log")
    ax.legend(fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def stats(values: np.ndarray) -> tuple[float, float, float]:
    return (
        float(np.sqrt(np.mean(values**2))),
        float(np.percentile(values, 99)),
        float(values.max()),
    )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--duration-s", type=float, default=30.0)
    parser.add_argument("--start-s", type=float, default=10.0)
    parser.add_argument("--seed", type=int, default=0, help="the hover disturbance's seed")
    parser.add_argument("--dialect", default="ardupilot", choices=("ardupilot", "px4"))
    parser.add_argument("--rate-hz", type=float, default=50.0)
    parser.add_argument("--joint-speed-deg-s", type=float, default=60.0, help="the default 60")
    parser.add_argument("--lead-ms", type=float, default=20.0, help="world.lead_ms (default 20)")
    parser.add_argument(
        "--telemetry-hz", type=float, default=50.0, help="world.telemetry_hz (default 50)"
    )
    parser.add_argument(
        "--mode",
        default="position",
        choices=("pose", "position", "position_axis"),
        help="what of the world target is held (default: the position; the paper arm's "
        "whole pose is out of reach for some of a 10 cm / 5 deg hover)",
    )
    parser.add_argument("--markdown", type=Path)
    parser.add_argument("--plot", type=Path, help="a PNG of the error over time (matplotlib)")
    args = parser.parse_args(argv)
    load_before = load_average()
    held, followed = run(False, args), run(True, args)
    _, world = world_target(Arm.default(), Mount())
    floor_pos, floor_ori = quantisation_floor(followed["samples"], world, args.seed)
    rows = []
    for name, r in (("held in the arm's frame", held), ("held in the world", followed)):
        p, o = stats(r["pos_cm"]), stats(r["ori_deg"])
        rows.append([name, len(r["pos_cm"]), *(f"{x:.2f}" for x in p), *(f"{x:.2f}" for x in o),
                     f"{r['cpu_pct']:.1f}"])  # fmt: skip
    p, o = stats(floor_pos), stats(floor_ori)
    rows.append(["floor: ideal joints, 1 µs PWM", len(floor_pos), *(f"{x:.2f}" for x in p),
                 *(f"{x:.2f}" for x in o), "–"])  # fmt: skip
    ratio_rms = stats(held["pos_cm"])[0] / stats(followed["pos_cm"])[0]
    ratio_p99 = stats(held["pos_cm"])[1] / stats(followed["pos_cm"])[1]
    ratio_ori = stats(held["ori_deg"])[0] / max(stats(followed["ori_deg"])[0], 1e-9)
    lines = [
        "# World-frame hold on a hovering vehicle",
        "",
        f"`{' '.join(['python -m bench.world_hold', *sys.argv[1:]])}` on {machine()}; load "
        f"before {load_before}, after {load_average()}. Dialect {args.dialect}, control "
        f"{args.rate_hz:g} Hz, joint speed {args.joint_speed_deg_s:g} °/s, world.lead_ms "
        f"{args.lead_ms:g}, world.telemetry_hz {args.telemetry_hz:g}, mode {args.mode}, hover "
        f"seed {args.seed}, simulator time "
        f"[{args.start_s:g}, {args.start_s + args.duration_s:g}] s.",
        "",
        *md_table(
            [
                "run",
                "samples",
                "pos RMS cm",
                "pos p99 cm",
                "pos max cm",
                "ori RMS °",
                "ori p99 °",
                "ori max °",
                "daemon CPU %",
            ],
            rows,
        ),  # fmt: skip
        "",
        f"Compensation cuts the position error {ratio_rms:.1f}× (RMS) and {ratio_p99:.1f}× "
        f"(p99), the orientation error {ratio_ori:.1f}× (RMS). Daemon status at the end: "
        f"{followed['world_status']}.",
    ]
    if args.plot is not None:
        if plt is None:
            print("(no PNG: matplotlib is not installed; it is the optional `plots` extra)")
        else:
            plot(held, followed, floor_pos, args.plot)
            lines += ["", f"![the hand's world error over time]({args.plot.name})"]
    print("\n".join(lines))
    if args.markdown:
        write_markdown(args.markdown, "\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
