"""The real stack on loopback for the latency and sustained-load benches.

``Stack`` starts the simulated flight controller (``python -m sim_servo``, UDP on 127.0.0.1,
JSON-lines event log) and the daemon (``python -m companion.cli run --config F``) as two
subprocesses, and waits until the daemon hears the autopilot. A target goes in through one
small input class (``INPUTS``: a ground station over MAVLink through the simulated autopilot,
the default, or the control socket); everything else in the benches is the same whatever the
input.

Clocks: the client, the daemon's per-target timing (``status()["last_target"]["timing"]``,
``Reply.timing``) and the simulator's event log (``t_s`` + the start event's ``monotonic_s``)
are all CLOCK_MONOTONIC, which is system-wide on Linux, so their stamps can be subtracted.

Used by ``bench/latency.py`` and ``bench/sustained.py``; not a module of the package.
"""

from __future__ import annotations

import json
import math
import os
import platform
import signal
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from sim_servo.eventlog import read_events

SERVO_COMMANDS = {183: "DO_SET_SERVO", 187: "DO_SET_ACTUATOR"}
WAIT_S = 30.0

try:  # PNG plots when matplotlib is installed (the `plots` extra); the Markdown never needs it
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
except ImportError:  # pragma: no cover - depends on the environment
    plt = None


def wait_until(predicate: Callable[[], bool], timeout_s: float, what: str) -> None:
    deadline = time.monotonic() + timeout_s
    while not predicate():
        if time.monotonic() > deadline:
            raise TimeoutError(f"no {what} within {timeout_s} s")
        time.sleep(0.02)


class ControlClient:
    """One persistent connection to the daemon's control socket (JSON lines)."""

    def __init__(self, path: str, timeout_s: float = 10.0) -> None:
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        self.sock.settimeout(timeout_s)
        self.sock.connect(path)
        self._buffer = b""

    def request(self, obj: dict[str, Any]) -> dict[str, Any]:
        self.sock.sendall((json.dumps(obj) + "\n").encode())
        while b"\n" not in self._buffer:
            chunk = self.sock.recv(65536)
            if not chunk:
                raise ConnectionError("the daemon closed the control socket")
            self._buffer += chunk
        line, self._buffer = self._buffer.split(b"\n", 1)
        return json.loads(line)

    def close(self) -> None:
        self.sock.close()


class ControlSocketInput:
    """Targets as ``goto`` requests on the control socket; the reply is the client's ACK."""

    name = "control socket"

    def __init__(self, stack: Stack) -> None:
        self.client = ControlClient(stack.control_path)
        self.status = stack.status

    def goto(self, pose: Sequence[float]) -> dict[str, Any]:
        """Send one target and wait for its answer: ``sent_s``, ``answered_s`` (client clock),
        ``outcome``, and the daemon's ``timing`` and ``solve_ms`` when it reported them."""
        sent_s = time.monotonic()
        reply = self.client.request({"cmd": "goto", "pose": list(pose)})
        answered_s = time.monotonic()
        solve = reply.get("solve") or {}
        return {
            "sent_s": sent_s,
            "answered_s": answered_s,
            "outcome": reply.get("outcome", "error"),
            "timing": reply.get("timing"),
            "solve_ms": solve.get("elapsed_ms"),
        }

    def close(self) -> None:
        self.client.close()


class MavlinkInput:
    """Targets as a ground station sends them: COMMAND_LONG ``MAV_CMD_USER_1`` to the
    simulator's ground-station link, routed by the autopilot to the daemon; the COMMAND_ACK
    routed back is the client's ACK. The daemon's timing and solve time are read from its
    status on the control socket once the ACK is in (outside the timed path)."""

    name = "MAVLink (ground station → autopilot → daemon)"

    def __init__(self, stack: Stack) -> None:
        from sim_servo.gcs import GroundStation

        self.gcs = GroundStation(stack.gcs_url)
        if not self.gcs.connect(WAIT_S):
            raise TimeoutError("no companion HEARTBEAT through the simulated autopilot")
        self.status = stack.status

    def goto(self, pose: Sequence[float]) -> dict[str, Any]:
        """As :meth:`ControlSocketInput.goto`."""
        sent_s = self.gcs.send_target(pose)
        ack = self.gcs.wait_ack(WAIT_S, since_s=sent_s)
        answered_s = time.monotonic()
        outcome = "no answer" if ack is None else _MAV_OUTCOME.get(ack.result_name, "failed")
        last = self.status()["last_target"] or {}
        return {
            "sent_s": sent_s,
            "answered_s": answered_s,
            "outcome": outcome,
            "timing": last.get("timing"),
            "solve_ms": last.get("solve_ms"),
        }

    def close(self) -> None:
        self.gcs.close()


_MAV_OUTCOME = {
    "MAV_RESULT_ACCEPTED": "accepted",
    "MAV_RESULT_DENIED": "denied",
    "MAV_RESULT_FAILED": "failed",
    "MAV_RESULT_TEMPORARILY_REJECTED": "temporarily_rejected",
}

#: The target inputs by name (``--input``).
INPUTS: dict[str, Callable[[Stack], Any]] = {
    "mavlink": MavlinkInput,
    "control": ControlSocketInput,
}
DEFAULT_INPUT = "mavlink"


class Stack:
    """The simulator and the daemon as subprocesses on UDP loopback (a context manager).

    ``daemon`` overrides the daemon config (TOML tables as dicts); ``sim_args`` are extra
    ``sim_servo`` flags.
    """

    def __init__(self, *, dialect: str, daemon: dict[str, dict[str, Any]] | None = None,
                 sim_args: Sequence[str] = ()) -> None:
        self.dialect = dialect
        self._tmp = tempfile.TemporaryDirectory(prefix="armbridge-bench-")
        tmp = Path(self._tmp.name)
        self.event_log = tmp / "sim.jsonl"
        self.control_path = str(tmp / "control.sock")
        self.daemon_log = tmp / "daemon.log"
        flavour = "ardupilot" if dialect == "ardupilot" else "px4"
        self.sim = subprocess.Popen(
            [sys.executable, "-m", "sim_servo", "--udp", "127.0.0.1:0", "--flavour", flavour,
             "--gcs", "127.0.0.1:0", "--event-log", str(self.event_log), *sim_args],
            stdout=subprocess.PIPE, text=True,
        )  # fmt: skip
        self.daemon: subprocess.Popen | None = None
        try:
            url = self.sim.stdout.readline().strip()
            kind, _, self.gcs_url = self.sim.stdout.readline().strip().partition(" ")
            if not url.startswith("udpout:") or kind != "gcs":
                raise RuntimeError(f"sim_servo did not start (first lines {url!r}, {kind!r})")
            tables: dict[str, dict[str, Any]] = {
                "link": {"url": url, "dialect": dialect},
                "control": {"socket": self.control_path},
            }
            for name, values in (daemon or {}).items():
                tables.setdefault(name, {}).update(values)
            self.config_path = tmp / "armbridge.toml"
            self.config_path.write_text(_toml(tables))
            self._stderr = open(self.daemon_log, "w")  # noqa: SIM115 - closed in close()
            self.daemon = subprocess.Popen(
                [sys.executable, "-m", "companion.cli", "run", "--config",
                 str(self.config_path)],
                stderr=self._stderr,
            )  # fmt: skip
            wait_until(lambda: os.path.exists(self.control_path), WAIT_S, "control socket")
            self._status_client = ControlClient(self.control_path)
            wait_until(lambda: self.status()["link"] == "up", WAIT_S, "autopilot link")
        except BaseException:
            self.close()
            raise

    def __enter__(self) -> Stack:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def status(self) -> dict[str, Any]:
        return self._status_client.request({"cmd": "status"})["status"]

    @property
    def daemon_pid(self) -> int:
        assert self.daemon is not None
        return self.daemon.pid

    def stop(self) -> list[dict[str, Any]]:
        """Stop both processes and return the simulator's events (its log is complete then)."""
        client = getattr(self, "_status_client", None)
        if client is not None:
            client.close()
            self._status_client = None
        if self.daemon is not None and self.daemon.poll() is None:
            self.daemon.send_signal(signal.SIGTERM)
            self.daemon.wait(timeout=10)
        if self.sim.poll() is None:
            self.sim.send_signal(signal.SIGTERM)
            self.sim.wait(timeout=10)
        return read_events(self.event_log) if self.event_log.exists() else []

    def close(self) -> None:
        try:
            self.stop()
        finally:
            for proc in (self.daemon, self.sim):
                if proc is not None and proc.poll() is None:
                    proc.kill()
                    proc.wait()
            if self.sim.stdout is not None:
                self.sim.stdout.close()
            stderr = getattr(self, "_stderr", None)
            if stderr is not None:
                stderr.close()
            self._tmp.cleanup()


def _toml(tables: dict[str, dict[str, Any]]) -> str:
    lines = []
    for name, values in tables.items():
        lines.append(f"[{name}]")
        for key, value in values.items():
            lines.append(f"{key} = {json.dumps(value)}")
    return "\n".join(lines) + "\n"


def servo_command_times(events: list[dict[str, Any]]) -> np.ndarray:
    """Monotonic times at which the simulator handled each servo command (DO_SET_SERVO or
    DO_SET_ACTUATOR), in order."""
    start = next(e for e in events if e["event"] == "start")
    t0 = start["monotonic_s"]
    return np.array([
        t0 + e["t_s"] for e in events
        if e["event"] == "rx" and e["msg"] == "COMMAND_LONG"
        and e["fields"]["command"] in SERVO_COMMANDS
    ])  # fmt: skip


# -- /proc ----------------------------------------------------------------------------------------


def cpu_s(pid: int) -> float:
    """User + system CPU seconds of process ``pid`` so far (all its threads)."""
    with open(f"/proc/{pid}/stat") as handle:
        fields = handle.read().rsplit(")", 1)[1].split()
    # fields[0] is field 3 (state); utime and stime are fields 14 and 15.
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def rss_mb(pid: int) -> float:
    """Resident set size (VmRSS) of process ``pid`` in MB."""
    with open(f"/proc/{pid}/status") as handle:
        for line in handle:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    raise RuntimeError(f"no VmRSS for pid {pid}")


def load_average() -> str:
    return " ".join(f"{v:.2f}" for v in os.getloadavg())


def machine() -> str:
    return (f"{platform.machine()}, {os.cpu_count()} cores, Python "
            f"{platform.python_version()}, {platform.system()} {platform.release()}")


# -- tables -----------------------------------------------------------------------------------


def percentiles_ms(values_s: Sequence[float]) -> tuple[float, float, float]:
    """(p50, p99, max) in ms of durations in seconds; NaNs if empty."""
    arr = np.asarray([v for v in values_s if v is not None and math.isfinite(v)]) * 1e3
    if arr.size == 0:
        return (math.nan, math.nan, math.nan)
    return (float(np.percentile(arr, 50)), float(np.percentile(arr, 99)), float(arr.max()))


def md_table(headers: Sequence[str], rows: Sequence[Sequence[Any]]) -> list[str]:
    def cell(v: Any) -> str:
        if isinstance(v, float):
            return "–" if math.isnan(v) else f"{v:.2f}"
        return str(v)

    lines = ["| " + " | ".join(headers) + " |", "|" + "---|" * len(headers)]
    lines += ["| " + " | ".join(cell(v) for v in row) + " |" for row in rows]
    return lines
