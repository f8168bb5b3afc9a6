"""``armbridge demo``: the simulated flight controller and the daemon on loopback.

The simulator runs as a separate process (``python -m sim_servo``) and is read over its query
socket (one JSON request per line, see ``docs/simulator.md``); the daemon runs in this process.
The demo sends the arm through a few reachable poses, an unreachable target and a
figure-eight, and prints per target: solve time, errors, PWM sent and the hand pose the
simulator reports. With matplotlib installed it also writes a PNG (``--plot PATH``).
"""

from __future__ import annotations

import math
import os
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from companion import ik
from companion.daemon.client import json_line_request
from companion.daemon.config import parse_config
from companion.daemon.service import ArmDaemon, Outcome
from companion.kinematics import Pose, rotation_angle

# The papers' test target G (§5; cm and deg): out of reach within the Table 2 limits. The same
# value as companion.papers' target G, which the daemon may not import (a test keeps them equal).
PAPER_TARGET_G = Pose(-20.0, 3.0, 40.0, 0.0, 10.0, 15.0)

# Joint configurations (deg) whose hand poses the demo asks for: reachable by construction.
DEMO_JOINTS_DEG = (
    (30.0, 60.0, -20.0, 45.0, 30.0, 10.0),
    (-45.0, 120.0, 30.0, -30.0, -20.0, 60.0),
    (20.0, 70.0, 50.0, 20.0, 30.0, 10.0),
)


def _fmt_pose(p: Pose | Sequence[float]) -> str:
    v = p.as_tuple() if isinstance(p, Pose) else tuple(p)
    return "({:.2f}, {:.2f}, {:.2f}) cm  ({:.2f}, {:.2f}, {:.2f}) deg".format(*v)


def query_sim(path: str, what: str, timeout_s: float = 5.0) -> dict[str, Any]:
    """One request to the simulator's query socket (``{"query": what}``) and its JSON reply."""
    reply = json_line_request(path, {"query": what}, timeout_s=timeout_s)
    if not isinstance(reply, dict) or "error" in reply:
        raise RuntimeError(f"simulator query {what!r} failed: {reply!r}")
    return reply


def _wait(predicate: Callable[[], bool], timeout_s: float) -> bool:
    deadline = time.monotonic() + timeout_s
    while not predicate():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.02)
    return True


def write_demo_plot(
    path: str | Path,
    targets: Sequence[tuple[str, Pose, Pose | None]],
    path_targets: Sequence[Pose],
    path_hand: Sequence[Pose],
) -> str:
    """Draw the demo's targets against the simulator's hand and save a PNG at ``path``.

    ``targets``: ``(name, target, hand pose reached or None if refused)``; ``path_targets``
    and ``path_hand``: the figure-eight's points and the hand sampled while it ran. Returns a
    one-line note for the user: where the plot went, or why it was skipped (no matplotlib)."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return "plot skipped: matplotlib is not installed (pip install 'armbridge[plots]')"
    fig, (side, eight) = plt.subplots(1, 2, figsize=(10, 4.2))
    for k, (name, target, hand) in enumerate(targets):
        colour = f"C{k}"
        side.plot(target.x_cm, target.z_cm, "x", color=colour, markersize=9, label=f"{name}")
        if hand is None:
            side.annotate(
                "refused",
                (target.x_cm, target.z_cm),
                fontsize=7,
                color=colour,
                xytext=(4, 4),
                textcoords="offset points",
            )
        else:
            side.plot(hand.x_cm, hand.z_cm, "o", mfc="none", color=colour, markersize=9)
            error_cm = math.dist(hand.position_cm, target.position_cm)
            side.annotate(
                f"{error_cm:.2f} cm",
                (hand.x_cm, hand.z_cm),
                fontsize=7,
                color=colour,
                xytext=(6, -10),
                textcoords="offset points",
            )
    side.set_title("targets (x) and the simulator's hand (o), side view", fontsize=9)
    side.set_xlabel("x (cm)")
    side.set_ylabel("z (cm)")
    side.legend(fontsize=7)
    side.set_aspect("equal", adjustable="datalim")
    side.grid(True, alpha=0.3)
    if path_targets:
        eight.plot(
            [p.y_cm for p in path_targets],
            [p.z_cm for p in path_targets],
            "-",
            color="C0",
            label="figure-eight targets",
        )
    if path_hand:
        eight.plot(
            [p.y_cm for p in path_hand],
            [p.z_cm for p in path_hand],
            ".",
            color="C1",
            markersize=3,
            label="simulator's hand (sampled)",
        )
    eight.set_title("figure-eight, front view", fontsize=9)
    eight.set_xlabel("y (cm)")
    eight.set_ylabel("z (cm)")
    eight.legend(fontsize=7)
    eight.set_aspect("equal", adjustable="datalim")
    eight.grid(True, alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return f"plot written to {path}"


def demo(seed: int = 0, plot: str = "") -> int:
    """Run the tour; returns the exit code (3 if the simulator did not come up)."""
    # On a first run numba compiles the kernels: say so before the wait, not after it.
    print("loading the IK kernels (the first run compiles them: 10-20 s) ...", flush=True)
    print(f"IK kernels ready in {ik.warm_up():.1f} s")
    with tempfile.TemporaryDirectory(prefix="armbridge-demo-") as tmp:
        sim_sock = str(Path(tmp) / "sim.sock")
        sim = subprocess.Popen(
            [sys.executable, "-m", "sim_servo", "--udp", "127.0.0.1:0", "--query-socket", sim_sock],
            stdout=subprocess.PIPE,
            text=True,
        )
        sim_out = sim.stdout
        assert sim_out is not None  # stdout=PIPE
        daemon = None
        try:
            url = sim_out.readline().strip()
            print(f"simulated flight controller (ArduPilot behaviour) at {url}")
            config = parse_config(
                {
                    "link": {"url": url, "dialect": "ardupilot"},
                    "arm": {"park_deg": [0, 90, 0, 0, 0, 0], "joint_speed_deg_s": 120.0},
                    "solver": {"budget_ms": 20.0, "seed": seed},
                    "control": {"rate_hz": 20.0},
                }
            )
            daemon = ArmDaemon(config)
            daemon.start()
            if not daemon.wait_for_autopilot(10.0) or not _wait(
                lambda: os.path.exists(sim_sock), 10.0
            ):
                print("armbridge: the simulator did not come up", file=sys.stderr)
                return 3
            print(
                f"daemon up: arm {config.arm.name}, outputs {list(config.calibration.outputs)}"
                f", {config.rate_hz:g} Hz, {config.joint_speed_deg_s:g} deg/s\n"
            )

            def settled() -> bool:
                return not daemon.status()["moving"] and query_sim(sim_sock, "state")["settled"]

            plotted: list[tuple[str, Pose, Pose | None]] = []

            def report(name: str, target: Pose) -> None:
                reply = daemon.submit("goto", target).result(10.0)
                print(f"{name}: target {_fmt_pose(target)}")
                if reply.solve is not None:
                    s = reply.solve
                    print(
                        f"  solve {s.elapsed_ms:.3f} ms, pos_err {s.pos_err_cm:.1e} cm, "
                        f"ori_err {s.ori_err_deg:.1e} deg"
                    )
                if reply.outcome is not Outcome.ACCEPTED:
                    print(f"  {reply.outcome.value.upper()}: {reply.message}; nothing sent\n")
                    plotted.append((name.split(" (")[0], target, None))
                    return
                _wait(settled, 15.0)
                status = daemon.status()
                hand = Pose(**query_sim(sim_sock, "state")["hand"]["pose"])
                pos = math.dist(hand.position_cm, target.position_cm)
                ori = math.degrees(rotation_angle(target.rotation, hand.rotation))
                print(
                    f"  ACCEPTED; PWM sent (us) {status['last_pwm_us']}, every DO_SET_SERVO "
                    f"acked ({status['counters']['servo_updates']} updates so far)"
                )
                print(f"  sim hand {_fmt_pose(hand)}: {pos:.3f} cm / {ori:.2f} deg from target\n")
                plotted.append((name, target, hand))

            for i, q in enumerate(DEMO_JOINTS_DEG, start=1):
                report(f"pose {i}", config.arm.fk(q))
            report("papers' target G (unreachable within the Table 2 limits)", PAPER_TARGET_G)

            centre = config.arm.fk(DEMO_JOINTS_DEG[2])
            points = []
            for k in range(41):  # 4 s figure-eight, 10 points per second
                s = 2 * math.pi * k / 40
                points.append(
                    (
                        0.1 * k,
                        (
                            centre.x_cm,
                            centre.y_cm + 5 * math.sin(s),
                            centre.z_cm + 2.5 * math.sin(2 * s),
                            centre.roll_deg,
                            centre.pitch_deg,
                            centre.yaw_deg,
                        ),
                    )
                )
            before = daemon.status()["counters"]["servo_updates"]
            reply = daemon.submit("trajectory", points).result(10.0)
            print(f"figure-eight (10 x 5 cm, 4 s, {len(points)} points): {reply.message}")
            hand_path: list[Pose] = []

            def done_sampling() -> bool:
                hand_path.append(Pose(**query_sim(sim_sock, "state")["hand"]["pose"]))
                return daemon.status()["trajectory_points_left"] == 0 and settled()

            _wait(done_sampling, 20.0)
            status = daemon.status()
            hand = Pose(**query_sim(sim_sock, "state")["hand"]["pose"])
            end = Pose(*points[-1][1])
            print(
                f"  {status['counters']['servo_updates'] - before} servo updates; hand ends "
                f"{math.dist(hand.position_cm, end.position_cm):.3f} cm from the last point"
            )
            print(f"\ncounters: {status['counters']}")
            if plot:
                path_targets = [Pose(*values) for _, values in points]
                print(write_demo_plot(plot, plotted, path_targets, hand_path))
        finally:
            if daemon is not None:
                daemon.close()
            sim.terminate()
            sim.wait(timeout=5)
            sim_out.close()
    return 0
