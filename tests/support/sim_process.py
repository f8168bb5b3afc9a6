"""The simulator as a subprocess, and the hand's distance from a target: shared by the tests that
run ``python -m sim_servo`` for real."""

from __future__ import annotations

import math
import os
import select
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np

from companion.kinematics import rotation_angle
from companion.kinematics.arm import Pose
from sim_servo.eventlog import read_events
from sim_servo.query import query
from tests.support.mavlink_peer import wait_until

ROOT = Path(__file__).resolve().parents[2]
WAIT_S = 10.0


class SimProcess:
    """A ``python -m sim_servo *args`` subprocess with a query socket and an event log in
    ``directory``; ``url`` is the first line it printed."""

    def __init__(self, directory: Path, *args: str) -> None:
        self.query_path = str(directory / "sim.sock")
        self.log_path = directory / "events.jsonl"
        command = [
            sys.executable,
            "-m",
            "sim_servo",
            *args,
            "--query-socket",
            self.query_path,
            "--event-log",
            str(self.log_path),
        ]
        self.proc = subprocess.Popen(
            command, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
        )
        ready, _, _ = select.select([self.proc.stdout], [], [], WAIT_S)
        self.url = self.proc.stdout.readline().strip() if ready else ""
        if not self.url:
            self.kill()
            raise AssertionError(f"simulator did not start: {self.proc.stderr.read()}")
        assert wait_until(lambda: os.path.exists(self.query_path), WAIT_S)

    def state(self) -> dict:
        return query(self.query_path, "state")

    def events(self, event: str | None = None, **fields) -> list[dict]:
        """The event log so far, optionally only ``event`` entries with these field values."""
        return [
            e
            for e in read_events(self.log_path)
            if (event is None or e["event"] == event)
            and all(e.get(k) == v for k, v in fields.items())
        ]

    def stop(self) -> int:
        self.proc.send_signal(signal.SIGTERM)
        try:
            return self.proc.wait(WAIT_S)
        finally:
            self.kill()

    def kill(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(WAIT_S)
        for pipe in (self.proc.stdout, self.proc.stderr):
            pipe.close()


def hand_errors(target, hand: dict) -> tuple[float, float]:
    """Position (cm) and orientation (deg, rotation angle) of the sim's reported ``hand`` from a
    target pose (6 numbers)."""
    goal = Pose(*target)
    reached = Pose(**hand["pose"])
    pos_cm = float(np.linalg.norm(reached.position_cm - goal.position_cm))
    ori_deg = math.degrees(float(rotation_angle(goal.rotation, reached.rotation)))
    return pos_cm, ori_deg
