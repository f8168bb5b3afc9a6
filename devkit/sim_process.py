"""The simulator as a subprocess, and the hand's distance from a target: shared by the tests
(and the benches) that run ``python -m sim_servo`` for real."""

from __future__ import annotations

import json
import math
import select
import subprocess
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from companion.kinematics import rotation_angle
from companion.kinematics.arm import Arm, Pose
from companion.kinematics.jacobian import geometric_jacobian
from devkit.process import kill, terminate
from devkit.provenance import ROOT  # the checkout
from devkit.timing import WAIT_S, wait_until
from firmware_interface.calibration import ArmCalibration, default_calibration
from sim_servo.errors import SimIOError
from sim_servo.eventlog import read_events
from sim_servo.query import query


class SimProcess:
    """A ``python -m sim_servo *args`` subprocess with a query socket and an event log in
    ``directory``; stderr goes to a file there.

    ``url`` is the first line it printed (its link), ``gcs_url`` the second one's URL when
    ``--gcs`` is among ``args``. Returns once the query socket answers. A context manager:
    leaving it stops (and reaps) the process.

    ``ready`` (default) starts a vehicle set up for the arm (``--ready``): on PX4 the arm's
    outputs on functions 301–306, ``COM_PREARM_MODE`` 2, forwarding on, armed at start, so its
    outputs are live as most tests assume; ArduPilot's safety switch is off
    anyway. ``ready=False`` gives the firmware's defaults (PX4: outputs dead until armed).
    """

    def __init__(
        self, directory: Path, *args: str, timeout_s: float = WAIT_S, ready: bool = True
    ) -> None:
        directory.mkdir(parents=True, exist_ok=True)
        self.query_path = str(directory / "sim.sock")
        self.log_path = directory / "events.jsonl"
        self.stderr_path = directory / "sim.stderr"
        command = [
            sys.executable,
            "-m",
            "sim_servo",
            *args,
            *(["--ready"] if ready and "--ready" not in args else []),
            "--query-socket",
            self.query_path,
            "--event-log",
            str(self.log_path),
        ]
        with open(self.stderr_path, "wb") as stderr:
            self.proc = subprocess.Popen(
                command,
                cwd=ROOT,
                stdin=subprocess.DEVNULL,
                stdout=subprocess.PIPE,
                stderr=stderr,
                bufsize=0,  # unbuffered: select() then sees every line still unread
            )
        try:
            self.url = self._line(timeout_s)
            self.gcs_url = ""
            if "--gcs" in args:
                kind, _, self.gcs_url = self._line(timeout_s).partition(" ")
                assert kind == "gcs", f"second line {kind!r}, expected 'gcs URL'"
            # Ready means answering, not merely a socket file existing.
            answered = wait_until(
                lambda: self.proc.poll() is not None or self.ping(),
                timeout_s,
                ignore=(OSError, ValueError, SimIOError),
            )
            if not answered or self.proc.poll() is not None:
                raise AssertionError("query socket does not answer")
        except BaseException as exc:
            self.kill()
            raise AssertionError(f"simulator did not start ({exc}): {self.stderr()}") from exc

    def _line(self, timeout_s: float) -> str:
        stdout = self.proc.stdout
        assert stdout is not None
        ready, _, _ = select.select([stdout], [], [], timeout_s)
        line = stdout.readline().decode().strip() if ready else ""
        if not line:
            raise AssertionError(f"no line on stdout within {timeout_s} s")
        return line

    def ping(self) -> bool:
        return bool(query(self.query_path, "ping", timeout_s=2.0).get("ok"))

    def state(self) -> dict:
        return query(self.query_path, "state")

    def pause_heartbeat(self, paused: bool = True) -> None:
        """Stop (or with ``paused=False`` restart) the autopilot's HEARTBEAT now."""
        query(self.query_path, "pause_heartbeat" if paused else "resume_heartbeat")

    def reboot(self) -> bool:
        """Reboot the autopilot now: silent for its reboot gap (``--reboot-gap``, 0.36 s by
        default), then back with time_boot from 0, default streams, an empty routing table;
        False if it was already rebooting. Wait for the ``fault`` event ``booted`` (or a
        HEARTBEAT) to know it is back."""
        return bool(query(self.query_path, "reboot").get("ok"))

    def arm(self, armed: bool = True) -> bool:
        """PX4: arm (or with ``armed=False`` disarm) now; False on ArduPilot."""
        return bool(query(self.query_path, "arm" if armed else "disarm").get("ok"))

    def kill_switch(self) -> bool:
        """PX4: kill now (a forced disarm: outputs to the disarmed PWM); False on ArduPilot."""
        return bool(query(self.query_path, "kill").get("ok"))

    def safety(self, on: bool) -> bool:
        """ArduPilot: engage (``on``) or disengage the safety switch now; False on PX4."""
        return bool(query(self.query_path, "safety_on" if on else "safety_off").get("ok"))

    def forge(self, msg: str, **fields: Any) -> None:
        """A test fault: ``msg`` (SERVO_OUTPUT_RAW, SYS_STATUS, SYSTEM_TIME) forged as if from
        the autopilot on the companion's link, once or every ``interval_s`` for ``for_s``
        (see :mod:`sim_servo.autopilot.forge` for the fields); ``SimIOError`` if refused."""
        reply = query(self.query_path, json.dumps({"query": "forge", "msg": msg, **fields}))
        if not reply.get("ok"):
            raise SimIOError(str(reply.get("error", reply)))

    def hangup(self) -> bool:
        """Close the port now (with ``--hangup-for``, a new pty comes back that much later);
        False while it is away. Wait for the ``fault`` events ``hangup``/``reopen``."""
        return bool(query(self.query_path, "hangup").get("ok"))

    def events(self, event: str | None = None, **fields: Any) -> list[dict]:
        """The event log so far, optionally only ``event`` entries with these field values."""
        return [
            e
            for e in read_events(self.log_path)
            if (event is None or e["event"] == event)
            and all(e.get(k) == v for k, v in fields.items())
        ]

    def stderr(self) -> str:
        return self.stderr_path.read_text(errors="replace") if self.stderr_path.exists() else ""

    def stop(self, timeout_s: float = WAIT_S) -> int:
        """SIGTERM, wait (bounded) and reap; the exit code (a later call returns it again)."""
        try:
            return terminate(self.proc, timeout_s)
        finally:
            self.kill()

    def kill(self) -> None:
        """SIGKILL if still running, reap, close the pipe (idempotent)."""
        kill(self.proc)
        if self.proc.stdout is not None:
            self.proc.stdout.close()

    def __enter__(self) -> SimProcess:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()


def hand_errors(target: Sequence[float], hand: dict) -> tuple[float, float]:
    """Position (cm) and orientation (deg, rotation angle) of the sim's reported ``hand`` from a
    target pose (6 numbers)."""
    goal = Pose(*target)
    reached = Pose(**hand["pose"])
    pos_cm = float(np.linalg.norm(reached.position_cm - goal.position_cm))
    ori_deg = math.degrees(float(rotation_angle(goal.rotation, reached.rotation)))
    return pos_cm, ori_deg


def quantisation_bound(
    q_deg: Sequence[float],
    slack_us: float,
    arm: Arm | None = None,
    calibration: ArmCalibration | None = None,
) -> tuple[float, float]:
    """The largest hand error (cm, deg) that each joint's PWM being off by ``slack_us`` can
    cause at ``q_deg``: first order, summed over joints (a bound), plus 10 %. Defaults: the
    default arm and the calibration the daemon uses without ``[[joint]]`` tables."""
    arm = arm or Arm.default()
    calibration = calibration or default_calibration()
    deg_per_us = np.array(
        [
            (j.angle_max_deg - j.angle_min_deg) / (j.pwm_max_us - j.pwm_min_us)
            for j in calibration.joints
        ]
    )
    dq_rad = np.radians(slack_us * deg_per_us)
    jac = geometric_jacobian(arm, np.radians([q_deg]))[0]
    pos_cm = float(np.sum(np.linalg.norm(jac[:3], axis=0) * dq_rad))
    ori_deg = math.degrees(float(np.sum(np.linalg.norm(jac[3:], axis=0) * dq_rad)))
    return 1.1 * pos_cm, 1.1 * ori_deg


# PWM is rounded to whole µs (±0.5) and the simulated servos stop within their dead band (1 µs).
SERVO_SLACK_US = 1.5


def assert_within_quantisation(
    target: Sequence[float], hand: dict, q_deg: Sequence[float], slack_us: float = SERVO_SLACK_US
) -> tuple[float, float]:
    """The sim's ``hand`` is at ``target`` as nearly as PWM off by ``slack_us`` at the commanded
    joints ``q_deg`` allows; returns the errors (cm, deg)."""
    pos, ori = hand_errors(target, hand)
    bound_pos, bound_ori = quantisation_bound(q_deg, slack_us)
    assert pos <= bound_pos and ori <= bound_ori, (pos, bound_pos, ori, bound_ori)
    return pos, ori
