"""The real stack on loopback for the latency and sustained-load benches.

``Stack`` starts the simulated flight controller (``python -m sim_servo``, UDP on 127.0.0.1,
JSON-lines event log) and the daemon (``python -m companion.daemon.cli run --config F``) as two
subprocesses, and waits until the daemon hears the autopilot. A target goes in through one
small input class (``INPUTS``: a ground station over MAVLink through the simulated autopilot,
the default, or the control socket); everything else in the benches is the same whatever the
input.

Clocks: the client, the daemon's per-target timing (``status()["last_target"]["timing"]``,
``Reply.timing``) and the simulator's event log (``t_s`` + the start event's ``monotonic_s``)
are all CLOCK_MONOTONIC, which is system-wide on Linux, so their stamps can be subtracted.

Used by the benches that run the real stack (``latency``, ``sustained``, ``flood``, ``races``,
``shutdown``); not a module of the package.
"""

from __future__ import annotations

import argparse
import math
import os
import select
import signal
import tempfile
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from bench.report import write_markdown
from devkit.config import write_config
from devkit.control_client import ControlConnection
from devkit.daemon_process import DaemonProcess
from devkit.sim_process import SimProcess
from devkit.timing import wait_until

MAV_CMD_USER_2 = 31011  # the Lua bridge's command
SERVO_COMMANDS = {
    183: "DO_SET_SERVO",
    187: "DO_SET_ACTUATOR",
    MAV_CMD_USER_2: "USER_2 (Lua bridge)",
}
WAIT_S = 30.0

try:  # PNG plots when matplotlib is installed (the `plots` extra); the Markdown never needs it
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
except ImportError:  # pragma: no cover - depends on the environment
    plt = None


class ControlSocketInput:
    """Targets as ``goto`` requests on the control socket; the reply is the client's ACK.

    Requests may be sent without waiting (``send``), answers collected as they come (``poll``).
    A connection answers one request at a time (the daemon reads its next once it answered the
    one before), so a client streaming targets faster than an update's round trip spreads them
    over ``connections`` connections, round robin.
    """

    name = "control socket"

    def __init__(self, stack: Stack, connections: int = 1) -> None:
        self.clients = [ControlConnection(stack.control_path) for _ in range(connections)]
        self.client = self.clients[0]
        self._next = 0

    def send(self, pose: Sequence[float]) -> float:
        """Send one target; the monotonic time it left."""
        client = self.clients[self._next]
        self._next = (self._next + 1) % len(self.clients)
        return client.send({"cmd": "goto", "pose": list(pose)})

    def poll(self, timeout_s: float) -> list[dict[str, Any]]:
        """The answers that arrive within ``timeout_s`` (at least one read): ``answered_s``,
        ``outcome``, and the daemon's ``timing`` and ``solve_ms``."""
        ready, _, _ = select.select(self.clients, [], [], max(timeout_s, 0.0))
        answers = []
        for client in ready:
            client.receive()
            answered_s = time.monotonic()
            while (reply := client.buffered_reply()) is not None:
                answers.append({
                    "answered_s": answered_s,
                    "outcome": reply.get("outcome", "error"),
                    "timing": reply.get("timing"),
                    "solve_ms": (reply.get("solve") or {}).get("elapsed_ms"),
                })  # fmt: skip
        return answers

    def update_ends(
        self, events: list[dict[str, Any]], answers: list[dict[str, Any]], since_s: float
    ) -> list[float]:
        """Per answer: when the autopilot handled the last command of the target's first servo
        update (inf if not accepted): the last servo command it handled between the daemon
        starting that update (``timing.first_out_s``) and having all its ACKs
        (``timing.acked_s``). An update with nothing to send (ardupilot, no PWM changed) ends
        at ``acked_s``; a target already reached (no update at all) at ``solved_s``."""
        sim_s = np.array([t for t, kind in _servo_and_acks(events, since_s) if kind == "servo"])
        ends = []
        for answer in answers:
            timing = answer.get("timing") or {}
            end = math.inf
            if answer["outcome"] == "accepted" and "acked_s" in timing:
                end = timing["acked_s"]
                last = int(np.searchsorted(sim_s, timing["acked_s"])) - 1
                if last >= 0 and sim_s[last] >= timing["first_out_s"]:
                    end = float(sim_s[last])
            elif answer["outcome"] == "accepted" and "solved_s" in timing:
                end = timing["solved_s"]  # nothing to send: the servos were already there
            ends.append(end)
        return ends

    def close(self) -> None:
        for client in self.clients:
            client.close()


class MavlinkInput:
    """Targets as a ground station sends them: COMMAND_LONG ``MAV_CMD_USER_1`` to the
    simulator's ground-station link, routed by the autopilot to the daemon; the COMMAND_ACK
    routed back is the client's ACK. ``status`` (control socket) is asked for the daemon's
    timing and solve time after each ACK, outside the timed path; they are kept when the
    newest target is still the one acknowledged (after every ``status_every``-th ACK)."""

    name = "MAVLink (ground station → autopilot → daemon)"
    #: Ask ``status`` after every n-th ACK only: asked after each one of a 50 Hz stream, the
    #: probe itself cost targets their slot (bench.sustained: 12–16 misses in 5 min with it,
    #: 5 without). The solve times are then a sample of one target in n.
    status_every = 1

    def __init__(self, stack: Stack) -> None:
        from sim_servo.gcs import GroundStation

        self.gcs = GroundStation(stack.gcs_url)
        if not self.gcs.connect(WAIT_S):
            raise TimeoutError("no companion HEARTBEAT through the simulated autopilot")
        self.status = stack.status
        self._poses: list[list[float]] = []  # sent, not yet answered (ACKs come in order)
        self._acks = 0

    def send(self, pose: Sequence[float]) -> float:
        """Send one target; the monotonic time it left."""
        self._poses.append([float(v) for v in pose])
        return self.gcs.send_target(pose)

    def poll(self, timeout_s: float) -> list[dict[str, Any]]:
        """As :meth:`ControlSocketInput.poll`."""
        answers = []
        for msg in self.gcs.receive(timeout_s):
            if msg.get_type() != "COMMAND_ACK" or msg.command != mavlink.MAV_CMD_USER_1:
                continue
            answered_s = time.monotonic()
            pose = self._poses.pop(0) if self._poses else None
            self._acks += 1
            last: dict[str, Any] = {}
            if self._acks % self.status_every == 0:
                last = self.status()["last_target"] or {}
            mine = pose is not None and bool(last) and np.allclose(last.get("pose", ()), pose)
            answers.append({
                "answered_s": answered_s,
                "outcome": _MAV_OUTCOME.get(msg.result, "failed"),
                "timing": last.get("timing") if mine else None,
                "solve_ms": last.get("solve_ms") if mine else None,
            })  # fmt: skip
        return answers

    def update_ends(
        self, events: list[dict[str, Any]], answers: list[dict[str, Any]], since_s: float
    ) -> list[float]:
        """Per answer: when the autopilot handled the last servo command before it routed the
        daemon's COMMAND_ACK for that target (the daemon answers right after the target's first
        update is acknowledged, so in the autopilot's log that update ends just before the
        ACK). An update with nothing to send (ardupilot, no PWM changed) ends at the ACK."""
        ends, last_servo = [], None
        for t_s, kind in _servo_and_acks(events, since_s):
            if kind == "servo":
                last_servo = t_s
            else:
                ends.append(t_s if last_servo is None else last_servo)
                last_servo = None
        ends += [math.inf] * (len(answers) - len(ends))
        return [
            e if a["outcome"] == "accepted" else math.inf
            for e, a in zip(ends, answers, strict=False)
        ]

    def close(self) -> None:
        self.gcs.close()


_MAV_OUTCOME = {
    mavlink.MAV_RESULT_ACCEPTED: "accepted",
    mavlink.MAV_RESULT_DENIED: "denied",
    mavlink.MAV_RESULT_FAILED: "failed",
    mavlink.MAV_RESULT_TEMPORARILY_REJECTED: "temporarily_rejected",
}


def answer_one(source: Any, pose: Sequence[float]) -> dict[str, Any]:
    """Send one target and wait for its answer: ``sent_s`` plus the answer's fields."""
    sent_s = source.send(pose)
    deadline = time.monotonic() + WAIT_S
    while (left := deadline - time.monotonic()) > 0:
        answers = source.poll(left)
        if answers:
            return {"sent_s": sent_s, **answers[0]}
    return {
        "sent_s": sent_s,
        "answered_s": math.inf,
        "outcome": "no answer",
        "timing": None,
        "solve_ms": None,
    }


#: The target inputs by name (``--input``).
INPUTS: dict[str, Callable[[Stack], Any]] = {
    "mavlink": MavlinkInput,
    "control": ControlSocketInput,
}
DEFAULT_INPUT = "mavlink"


def ram_dir() -> str | None:
    """A RAM-backed directory for the stacks' files (``/dev/shm`` where it is writable; None:
    the system's temporary directory). The simulator's JSON event log is written on every pass
    of its loop, the daemon's log on stderr into a file: on a disk file system a write now and
    then waits for the journal's commit (ext4: the file's mtime), and a frame waits behind it,
    a stall no flight controller has (it keeps no such log) and no daemon under systemd has
    (it logs into journald's socket). The bench measures the daemon and the link, not the
    bench's own logging."""
    shm = "/dev/shm"
    return shm if os.path.isdir(shm) and os.access(shm, os.W_OK) else None


class Stack:
    """The simulator and the daemon as subprocesses on UDP loopback (a context manager), by the
    tests' harnesses (:class:`~devkit.sim_process.SimProcess`,
    :class:`~devkit.daemon_process.DaemonProcess`).

    ``daemon`` overrides the daemon config (TOML tables as dicts); ``sim_args`` are extra
    ``sim_servo`` flags; ``daemon_root`` runs the daemon from another checkout (an older
    version of the code, as a peer in the same run). ``transport``: the simulator's link flags
    (default UDP loopback; e.g. ``--pty --pty-baud 115200`` for a modelled serial line). The
    ``ardupilot-lua`` dialect gets an ArduPilot simulator emulating the Lua bridge script.
    """

    def __init__(
        self,
        *,
        dialect: str,
        daemon: dict[str, Any] | None = None,
        sim_args: Sequence[str] = (),
        daemon_root: Path | None = None,
        transport: Sequence[str] = ("--udp", "127.0.0.1:0"),
    ) -> None:
        self.dialect = dialect
        self._tmp = tempfile.TemporaryDirectory(prefix="armbridge-bench-", dir=ram_dir())
        tmp = Path(self._tmp.name)
        self._daemon_root = daemon_root
        #: The logs of the daemons stopped by :meth:`restart_daemon`, in order.
        self.old_daemon_logs: list[Path] = []
        flavour = "px4" if dialect == "px4" else "ardupilot"
        if dialect == "ardupilot-lua":
            sim_args = ("--lua-script", *sim_args)
        self.sim: SimProcess | None = None
        self.daemon: DaemonProcess | None = None
        self._status_client: ControlConnection | None = None
        try:
            self.sim = SimProcess(
                tmp / "sim",
                *transport, "--flavour", flavour, "--gcs", "127.0.0.1:0", *sim_args,
                timeout_s=WAIT_S,
            )  # fmt: skip
            self.event_log = self.sim.log_path
            self.gcs_url = self.sim.gcs_url
            tables: dict[str, Any] = {
                "link": {"url": self.sim.url, "dialect": dialect},
                "control": {"socket": str(tmp / "control.sock")},
            }
            for name, values in (daemon or {}).items():
                if isinstance(values, list):  # an array of tables: [[keepout]], [[joint]]
                    tables[name] = values
                else:
                    tables.setdefault(name, {}).update(values)
            self.daemon = DaemonProcess(
                tmp / "daemon",
                tables,
                ready_timeout_s=WAIT_S,
                **({} if daemon_root is None else {"root": daemon_root}),
            )
            self.control_path = str(self.daemon.control_path)
            self.config_path = self.daemon.config_path
            self.daemon_log = self.daemon.log_path
            self._status_client = ControlConnection(self.control_path)
            if not wait_until(lambda: self.status()["link"] == "up", WAIT_S):
                raise TimeoutError(f"no autopilot link within {WAIT_S} s")
        except BaseException:
            self.close()
            raise

    def __enter__(self) -> Stack:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def status(self) -> dict[str, Any]:
        assert self._status_client is not None
        return self._status_client.request({"cmd": "status"})["status"]

    def stop_daemon(self, how: str) -> None:
        """Stop the daemon as a crash does (``how`` ``kill``: SIGKILL, no clean-up at all) or
        ``systemctl stop`` (``term``: SIGTERM, its exit waited for); its log is kept
        (``old_daemon_logs``). :meth:`start_daemon` starts it again."""
        if how not in ("kill", "term"):
            raise ValueError(f"how={how!r}; valid: kill, term")
        assert self.daemon is not None
        if self._status_client is not None:
            self._status_client.close()
            self._status_client = None
        if how == "kill":
            self.daemon.kill()
        else:
            self.daemon.stop()
        self.old_daemon_logs.append(self.daemon_log)

    def start_daemon(self) -> float:
        """Start the daemon stopped by :meth:`stop_daemon` again, on the config in force (its
        control socket's path too); the monotonic time it answered and heard the autopilot.
        Clients of the control socket must connect again."""
        assert self.daemon is not None
        directory = Path(self._tmp.name) / f"daemon-{len(self.old_daemon_logs)}"
        self.daemon = DaemonProcess(
            directory,
            self.daemon.config,
            ready_timeout_s=WAIT_S,
            **({} if self._daemon_root is None else {"root": self._daemon_root}),
        )
        self.config_path = self.daemon.config_path
        self.daemon_log = self.daemon.log_path
        self._status_client = ControlConnection(self.control_path)
        if not wait_until(lambda: self.status()["link"] == "up", WAIT_S):
            raise TimeoutError(f"no autopilot link within {WAIT_S} s of the restart")
        return time.monotonic()

    def reload_daemon(self, tables: dict[str, dict[str, Any]]) -> None:
        """Rewrite the daemon's config with ``tables`` merged in (e.g. ``{"arm":
        {"joint_speed_deg_s": 30.0}}``) and send it SIGHUP, as ``systemctl reload`` does;
        returns at once (the daemon logs ``reloaded`` once it applied it)."""
        assert self.daemon is not None
        for name, values in tables.items():
            self.daemon.config.setdefault(name, {}).update(values)
        write_config(self.daemon.config_path, self.daemon.config)
        os.kill(self.daemon.pid, signal.SIGHUP)

    @property
    def daemon_pid(self) -> int:
        assert self.daemon is not None
        return self.daemon.pid

    @property
    def sim_pid(self) -> int:
        assert self.sim is not None
        return self.sim.proc.pid

    def stop(self) -> list[dict[str, Any]]:
        """Stop both processes and return the simulator's events (its log is complete then)."""
        if self._status_client is not None:
            self._status_client.close()
            self._status_client = None
        if self.daemon is not None:
            self.daemon.stop()
        if self.sim is None:
            return []
        self.sim.stop()
        return self.sim.events() if self.sim.log_path.exists() else []

    def close(self) -> None:
        try:
            self.stop()
        finally:
            for proc in (self.daemon, self.sim):
                if proc is not None:
                    proc.kill()
            self._tmp.cleanup()


def _servo_and_acks(
    events: list[dict[str, Any]], since_s: float = -math.inf
) -> list[tuple[float, str]]:
    """In the simulator's log order, on CLOCK_MONOTONIC, from ``since_s`` on: ``(t, "servo")``
    for each servo command it handled (DO_SET_SERVO or DO_SET_ACTUATOR: when it read the frame;
    the Lua bridge's USER_2: when the script set the outputs, its ``ack`` event, since the
    script runs several ms after the frame came in) and ``(t, "ack")`` for each COMMAND_ACK to a
    target command (USER_1) that it routed from the daemon."""
    start = next(e for e in events if e["event"] == "start")
    t0 = start["monotonic_s"]
    out = []
    for e in events:
        if t0 + e["t_s"] < since_s:
            continue
        if e["event"] == "ack" and e.get("command") == MAV_CMD_USER_2:
            out.append((t0 + e["t_s"], "servo"))
        if e["event"] != "rx":
            continue
        command = e["fields"].get("command") if e["msg"] == "COMMAND_LONG" else None
        if command in SERVO_COMMANDS and command != MAV_CMD_USER_2:
            out.append((t0 + e["t_s"], "servo"))
        elif e["msg"] == "COMMAND_ACK" and e["fields"]["command"] == mavlink.MAV_CMD_USER_1:
            out.append((t0 + e["t_s"], "ack"))
    return out


def servo_command_times(events: list[dict[str, Any]]) -> np.ndarray:
    """Monotonic times at which the simulator handled each servo command, in order."""
    return np.array([t for t, kind in _servo_and_acks(events) if kind == "servo"])


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


def udp_sockets(pid: int) -> dict[int, int]:
    """The UDP sockets process ``pid`` holds (from ``/proc``): ``{local port: datagrams the
    kernel dropped on it so far}`` (a full receive buffer). The daemon's ``udpout`` link socket
    is bound to an ephemeral port that nothing else tells."""
    inodes = set()
    for fd in os.listdir(f"/proc/{pid}/fd"):
        try:
            target = os.readlink(f"/proc/{pid}/fd/{fd}")
        except OSError:  # closed meanwhile
            continue
        if target.startswith("socket:["):
            inodes.add(target[len("socket:[") : -1])
    sockets = {}
    with open(f"/proc/{pid}/net/udp") as handle:
        next(handle)  # header
        for line in handle:
            fields = line.split()
            if fields[9] in inodes:
                sockets[int(fields[1].rsplit(":", 1)[1], 16)] = int(fields[12])
    return sockets


def udp_ports(pid: int) -> list[int]:
    """The local ports of the UDP sockets process ``pid`` holds."""
    return sorted(udp_sockets(pid))


def load_average() -> str:
    return " ".join(f"{v:.2f}" for v in os.getloadavg())


# -- tables -----------------------------------------------------------------------------------


def percentiles_ms(values_s: Sequence[float]) -> tuple[float, float, float]:
    """(p50, p99, max) in ms of durations in seconds; NaNs if empty."""
    arr = np.asarray([v for v in values_s if v is not None and math.isfinite(v)]) * 1e3
    if arr.size == 0:
        return (math.nan, math.nan, math.nan)
    return (float(np.percentile(arr, 50)), float(np.percentile(arr, 99)), float(arr.max()))


def run_and_report(
    run: Callable[[argparse.Namespace], Any],
    report: Callable[[Any, argparse.Namespace, str], list[str]],
    args: argparse.Namespace,
) -> int:
    """A bench's ``main`` tail: note the load, run, print the report, write its markdown."""
    load_before = load_average()
    out = run(args)
    text = "\n".join(report(out, args, load_before)) + "\n"
    print(text)
    write_markdown(args.markdown, text)
    return 0
