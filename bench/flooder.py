"""An unsigned MAVLink target flood aimed straight at the daemon's UDP socket, from a child
process (shared by ``bench/flood.py`` and ``bench/shutdown.py``).

The daemon's ``udpout`` link socket is bound to an ephemeral port and today accepts datagrams
from any address: a sender that learns the port (here from ``/proc``,
:func:`bench.loopback.udp_ports`) can talk to the daemon past the autopilot. The flooder sends
COMMAND_LONG ``MAV_CMD_USER_1`` addressed to the daemon (system = the autopilot's, component
191) from 255/190, unsigned, at a fixed rate, the poses seeded, reachable and unreachable mixed.

The daemon answers every target with a COMMAND_ACK to 255/190, sent (like all its frames) to
the autopilot. So that those ACKs come back, the flooder also sends a HEARTBEAT once a second
from the same socket to the simulator's ground-station link: the autopilot learns the route to
255/190 there and forwards the ACKs, which the flooder counts per MAV_RESULT.

It runs in a child process so that its sending and decoding share no interpreter lock with the
bench's probes (stop latency, RSS), and its collector is off while it floods.
"""

from __future__ import annotations

import collections
import gc
import multiprocessing
import select
import socket
import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from companion.kinematics.arm import Arm, Pose

FLOODER_IDS = (255, mavlink.MAV_COMP_ID_MISSIONPLANNER)  # a ground station's ids
DAEMON_COMPONENT = mavlink.MAV_COMP_ID_ONBOARD_COMPUTER  # 191
#: An unreachable pose: a reachable one moved this far along x (far outside the workspace).
UNREACHABLE_OFFSET_CM = 300.0
DRAIN_S = 2.0  # after the last frame, ACKs are still counted this long
STEP_S = 0.001  # the sender wakes this often and sends the frames that are due


def flood_poses(count: int, unreachable: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """``count`` seeded poses (rows of x, y, z, roll, pitch, yaw) and which are unreachable:
    FK of uniform joints within the limits, a fraction ``unreachable`` moved out of reach."""
    rng = np.random.default_rng(seed)
    arm = Arm.default()
    poses = np.array(
        [Pose.from_matrix(t).as_tuple() for t in arm.fk_batch(arm.random_q_rad(rng, count))]
    )
    far = rng.random(count) < unreachable
    poses[far, 0] += UNREACHABLE_OFFSET_CM
    return poses, far


def encode_targets(poses: np.ndarray, system_id: int) -> list[bytes]:
    """COMMAND_LONG USER_1 frames, one per pose, from 255/190 to ``system_id``/191."""
    mav = mavlink.MAVLink(None, *FLOODER_IDS)
    frames = []
    for pose in poses:
        msg = mav.command_long_encode(
            system_id, DAEMON_COMPONENT, mavlink.MAV_CMD_USER_1, 0, *map(float, pose), 0.0
        )
        frames.append(msg.pack(mav))
        mav.seq = (mav.seq + 1) % 256
    return frames


@dataclass
class FloodResult:
    """What the flooder saw: frames sent and when, the ACKs it got back per MAV_RESULT."""

    sent: int
    send_errors: int
    start_s: float  # CLOCK_MONOTONIC
    end_s: float
    acks: dict[str, int]
    statustexts: int
    other_frames: dict[str, int]

    @property
    def acks_total(self) -> int:
        return sum(self.acks.values())


def _result_name(result: int) -> str:
    if result == 6:  # common.xml's MAV_RESULT_CANCELLED; the pinned pymavlink predates it
        return "CANCELLED"
    entry = mavlink.enums["MAV_RESULT"].get(result)
    return entry.name.removeprefix("MAV_RESULT_") if entry is not None else f"RESULT_{result}"


def _child(
    conn: Any,
    frames: Sequence[bytes],
    daemon_addr: tuple[str, int],
    gcs_addr: tuple[str, int] | None,
    rate_hz: float,
) -> None:
    gc.disable()
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 22)
    sock.bind(("127.0.0.1", 0))
    sock.setblocking(False)
    dec = mavlink.MAVLink(None)
    dec.robust_parsing = True
    beat = mavlink.MAVLink(None, *FLOODER_IDS)
    acks: collections.Counter[str] = collections.Counter()
    other: collections.Counter[str] = collections.Counter()
    statustexts = 0

    def heartbeat() -> None:
        if gcs_addr is None:
            return
        msg = beat.heartbeat_encode(
            mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, mavlink.MAV_STATE_ACTIVE
        )
        sock.sendto(msg.pack(beat), gcs_addr)
        beat.seq = (beat.seq + 1) % 256

    def drain() -> None:
        nonlocal statustexts
        while True:
            try:
                data = sock.recv(65535)
            except (BlockingIOError, ConnectionRefusedError):
                return
            for msg in dec.parse_buffer(data) or ():
                kind = msg.get_type()
                if kind == "COMMAND_ACK" and msg.command == mavlink.MAV_CMD_USER_1:
                    acks[_result_name(msg.result)] += 1
                elif kind == "STATUSTEXT":
                    statustexts += 1
                else:
                    other[kind] += 1

    heartbeat()
    conn.send("ready")
    conn.recv()  # go
    count = len(frames)
    sent = errors = 0
    start_s = time.monotonic()
    next_beat_s = start_s + 1.0
    while sent < count:
        now = time.monotonic()
        due = min(count, int((now - start_s) * rate_hz) + 1)
        while sent < due:
            try:
                sock.sendto(frames[sent], daemon_addr)
            except OSError:  # ENOBUFS / EAGAIN / ECONNREFUSED: counted, not retried
                errors += 1
            sent += 1
        if now >= next_beat_s:
            heartbeat()
            next_beat_s += 1.0
        drain()
        select.select([sock], [], [], STEP_S)
    end_s = time.monotonic()
    conn.send(("done", end_s))
    while time.monotonic() < end_s + DRAIN_S:
        if now >= next_beat_s:
            heartbeat()
            next_beat_s += 1.0
        select.select([sock], [], [], 0.05)
        drain()
        now = time.monotonic()
    conn.send(FloodResult(sent, errors, start_s, end_s, dict(acks), statustexts, dict(other)))
    sock.close()


class Flooder:
    """The flood in a child process: :meth:`start` it, :meth:`wait_done` for the last frame
    sent (its CLOCK_MONOTONIC time), :meth:`result` after the drain."""

    def __init__(
        self,
        frames: Sequence[bytes],
        *,
        daemon_port: int,
        gcs_url: str | None,
        rate_hz: float,
        via_autopilot: bool = False,
    ) -> None:
        gcs_addr = None
        if gcs_url:
            host, _, port = gcs_url.partition(":")[2].rpartition(":")
            gcs_addr = (host, int(port))
        ctx = multiprocessing.get_context("spawn")
        self._conn, child_conn = ctx.Pipe()
        self._proc = ctx.Process(
            target=_child,
            args=(
                child_conn,
                list(frames),
                gcs_addr if via_autopilot and gcs_addr else ("127.0.0.1", daemon_port),
                gcs_addr,
                rate_hz,
            ),
            name="armbridge-flooder",
            daemon=True,
        )
        self._proc.start()
        if not self._conn.poll(30.0) or self._conn.recv() != "ready":
            self.kill()
            raise TimeoutError("the flooder did not start")
        self.end_s: float | None = None

    def start(self) -> float:
        """Start flooding; the monotonic time of the go."""
        start_s = time.monotonic()
        self._conn.send("go")
        return start_s

    def done(self, timeout_s: float = 0.0) -> bool:
        """Whether the last frame has been sent (waits up to ``timeout_s``)."""
        if self.end_s is None and self._conn.poll(timeout_s):
            _, self.end_s = self._conn.recv()
        return self.end_s is not None

    def result(self, timeout_s: float = DRAIN_S + 30.0) -> FloodResult:
        """The counts, once the flooder has drained (about ``DRAIN_S`` after the last frame)."""
        if not self.done(timeout_s):
            raise TimeoutError("the flood did not end")
        if not self._conn.poll(timeout_s):
            raise TimeoutError("the flooder did not report")
        result = self._conn.recv()
        self._proc.join(5.0)
        return result

    def kill(self) -> None:
        if self._proc.is_alive():
            self._proc.kill()
        self._proc.join(5.0)
