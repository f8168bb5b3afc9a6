"""Serial links: target → last ACK and a 50 Hz stream, per dialect and baud, beside what the
bytes predict.

    python -m bench.serial_links [--bauds 57600 115200 921600]
                                 [--dialects ardupilot ardupilot-lua px4] [--targets 100]
                                 [--duration-s 30] [--seed 0]
                                 [--markdown bench/results/serial_links.md]

The default run (9 stacks, 100 targets and a 30 s stream each) takes about 7 min;
``--duration-s 300`` is the long run. For each baud rate and dialect the daemon (``armbridge
run``) and the simulated flight controller (``python -m sim_servo --pty --pty-baud BAUD``: a
pty with a serial line's bandwidth, 10 bits a byte both ways, ArduPilot's 256-byte transmit
buffer; ``--lua-script`` for ``ardupilot-lua``) run as subprocesses (``bench/loopback.py``). The
daemon runs the shipped defaults but ``control.rate_hz`` = 50 and the joint speed at its
maximum (1000 °/s); targets come over the control socket, so only servo traffic uses the line.

* **Latency**: ``--targets`` reachable targets one at a time (each 0–50 ms after the previous
  answer, seeded), twice: **from rest** (each sent once the arm is still, so its first update
  has the line to itself, as the from-rest figure is one update's) and **mid-motion** (the
  previous target's later steps, speed-limited, may still be on their way: its first update
  then goes out behind one of them and waits for its bytes and its answer). ``update`` = the
  daemon started the target's first servo update → it had every ACK (``timing.first_out_s`` →
  ``acked_s``, from rest), and ``target → last ACK`` = the daemon received the target → that
  last ACK (``received_s`` → ``acked_s``: adds the solve).
* **Predicted** update (``firmware_interface.link_budget``): the commands' bytes + the last
  ACK's bytes at the baud rate + the flight controller's *measured* median answer time
  (ArduCopter 4.7.0-dev SITL over TCP: six pipelined DO_SET_SERVO 3.2 ms, the Lua script
  8.9 ms; PX4 not measured: 2.5 ms assumed). ``sim/pred`` is the simulated median over it.
* **50 Hz stream** (``bench/sustained.py``'s figure-eight, open loop, one target every 20 ms
  for ``--duration-s``, round robin over 4 control-socket connections, as a client streaming
  targets must: a connection answers one request at a time): a miss, as in
  ``bench/sustained.py``, is a target not ACCEPTED (a newer one replaced
  it while it waited: CANCELLED) or whose first update the autopilot had not carried out within
  the target's 20 ms slot (its last servo command handled; for the Lua bridge, the script
  setting the outputs); with the daemon 4 targets behind, a slot is skipped (a miss) rather than
  queued. Beside it, how many updates' last ACK was back at the daemon later than the slot (the
  ACK's bytes on the line come on top).
"""

from __future__ import annotations

import argparse
import gc
import math
import sys
import time
from pathlib import Path

import numpy as np
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from bench.loopback import ControlSocketInput, Stack, answer_one, load_average, percentiles_ms
from bench.report import machine, md_table, write_markdown
from bench.sustained import figure_eight
from companion.daemon.core import stream_intervals_s, stream_requests
from companion.kinematics.arm import Arm, Pose
from devkit.timing import wait_until
from firmware_interface.calibration import ArmCalibration, default_calibration
from firmware_interface.link_budget import update_cost
from firmware_interface.servo import make_servo_dialect
from sim_servo.autopilot import SimAutopilot
from sim_servo.config import LinkTimingConfig, SimConfig
from sim_servo.serial_line import ARDUPILOT_MAVLINK_TX_BUFFER_BYTES, SerialLine

ROOT = Path(__file__).resolve().parent.parent
SLOT_S = 0.02  # 50 Hz
GAP_MS = 50.0
#: The daemon reads a connection's next request once it answered the previous one: with this
#: many unanswered, the stream skips a slot (a miss) instead of filling the socket.
MAX_OUTSTANDING = 4
DIALECTS = ("ardupilot", "ardupilot-lua", "px4")
BAUDS = (57_600, 115_200, 921_600)
HEADERS = (
    "dialect",
    "baud",
    "B to FC",
    "predicted update",
    "sim model p50 / max",
    "model/pred",
    "update p50 / p99 / max",
    "target→last ACK p50 / p99 (from rest)",
    "target→last ACK p50 / p99 (mid-motion)",
    "50 Hz misses",
    "stream slot→servos p50 / p99 / max",
    "ACKs later than the slot",
    "stream slot→ACK p99",
)


def random_targets(arm: Arm, count: int, seed: int) -> list[Pose]:
    q = arm.random_q_rad(np.random.default_rng(seed), count)
    return [Pose.from_matrix(t) for t in arm.fk_batch(q)]


def model_update_s(
    dialect: str, baud: int, calibration: ArmCalibration, samples: int, seed: int
) -> list[float]:
    """The simulator's own figure, free of the OS: its autopilot and serial-line models on a
    simulated clock. Each update's commands are written at once at a random loop phase; the
    time until the last ACK's last byte is out of the line."""
    config = SimConfig(
        flavour="px4" if dialect == "px4" else "ardupilot",
        lua_script=dialect == "ardupilot-lua",
        link_timing=LinkTimingConfig(hold_ms=0.0),  # as --pty-baud sets it
    )
    ap = SimAutopilot(config, now_s=0.0)
    down = SerialLine(baud, split_frames=True)
    up = SerialLine(baud, buffer_bytes=ARDUPILOT_MAVLINK_TX_BUFFER_BYTES)
    planner = make_servo_dialect(dialect, None, calibration)
    pwm = {j.output: (j.pwm_min_us + j.pwm_max_us) // 2 for j in calibration.joints}
    enc = mavlink.MAVLink(None, 1, mavlink.MAV_COMP_ID_ONBOARD_COMPUTER)
    dec = mavlink.MAVLink(None)
    rng = np.random.default_rng(seed)
    # The streams the daemon asks for on such a line (PX4's unasked ATTITUDE and
    # LOCAL_POSITION_NED stopped), asked at 0.5 s: their answers are out before the first update.
    readback_s, sys_status_s = stream_intervals_s(
        ardupilot=dialect != "px4", url=f"/dev/ttyS0,{baud}"
    )
    asks = b"".join(
        enc.command_long_encode(
            1, 1, mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, 0,
            msg_id, -1.0 if interval_s < 0 else interval_s * 1e6, 0, 0, 0, 0, 0,
        ).pack(enc)
        for msg_id, interval_s in stream_requests(
            ardupilot=dialect != "px4",
            readback_interval_s=readback_s,
            sys_status_interval_s=sys_status_s,
            world_telemetry_hz=None,
        )
    )  # fmt: skip
    ap.receive(asks, 0.5)
    out = []
    now = 0.5
    for k in range(samples):
        start = 1.0 + 0.1 * k + rng.uniform(0.0, 0.01)
        commands = planner.plan(pwm)
        frames = b"".join(
            enc.command_long_encode(1, 1, c.command, 0, *c.params).pack(enc) for c in commands
        )
        # Run the models up to the start (heartbeats and all), then send the update.
        while (due := min(ap.next_event_s(now), start)) < start:
            now = max(due, now + 1e-9)
            for _, frame in ap.poll(now):
                up.send(frame, now)
            up.take(now)
        now = start
        down.send(frames, start)
        acks = 0
        while acks < len(commands):
            due_s = [ap.next_event_s(now), down.next_event_s(), up.next_event_s()]
            now = max(min(t for t in due_s if t is not None), now + 1e-9)
            for piece in down.take(now):
                ap.receive(piece, now)
            for _, frame in ap.poll(now):
                up.send(frame, now)
            for frame in up.take(now):
                for msg in dec.parse_buffer(frame) or []:
                    acks += msg.get_type() == "COMMAND_ACK"
        out.append(now - start)
    return out


def latency(stack: Stack, poses: list[Pose], seed: int, *, from_rest: bool) -> dict:
    """Targets one at a time, each 0–``GAP_MS`` after the previous answer. ``from_rest``: each
    only once the arm is still (status ``moving`` false: no update on its way), so its first
    update has the line to itself; otherwise while the previous target's later steps may
    still be on their way (its first update then goes out behind one of them)."""
    source = ControlSocketInput(stack)
    rng = np.random.default_rng(seed + 1)
    update_s, target_s, outcomes = [], [], {}
    try:
        for pose in poses:
            if from_rest:
                wait_until(lambda: not stack.status()["moving"], 5.0)
            time.sleep(rng.uniform(0.0, GAP_MS / 1e3))
            rec = answer_one(source, pose.as_tuple())
            outcomes[rec["outcome"]] = outcomes.get(rec["outcome"], 0) + 1
            timing = rec.get("timing") or {}
            if rec["outcome"] == "accepted" and "acked_s" in timing:
                update_s.append(timing["acked_s"] - timing["first_out_s"])
                target_s.append(timing["acked_s"] - timing["received_s"])
    finally:
        source.close()
    return {"update": update_s, "target": target_s, "outcomes": outcomes}


def stream(stack: Stack, duration_s: float, period_s: float = 4.0) -> dict:
    arm = Arm.default()
    # Round robin over MAX_OUTSTANDING connections: one connection answers one request at a
    # time, so on one a target would wait for the answer to the one before (an update's round
    # trip, 15-20 ms here) before the daemon even read it.
    source = ControlSocketInput(stack, connections=MAX_OUTSTANDING)
    sent: list[float] = []
    answers: list[dict] = []
    skipped = 0
    try:
        answer_one(source, figure_eight(arm, 0.0, period_s).as_tuple())
        time.sleep(2.0)  # onto the path
        slots = int(round(duration_s / SLOT_S))
        gc.collect()
        gc.disable()
        t0 = time.monotonic() + 0.1
        try:
            for k in range(slots):
                slot_s = t0 + k * SLOT_S * (1.0 - 100e-6)  # a sender clock 100 ppm fast
                while (left := slot_s - time.monotonic()) > 0:
                    answers += source.poll(left)
                if len(sent) - len(answers) >= MAX_OUTSTANDING:
                    skipped += 1  # the daemon is this far behind: a miss, not sent
                    continue
                source.send(figure_eight(arm, k * SLOT_S, period_s).as_tuple())
                sent.append(slot_s)
        finally:
            gc.enable()
        deadline = time.monotonic() + 5.0
        while len(answers) < len(sent) and (left := deadline - time.monotonic()) > 0:
            answers += source.poll(left)
    finally:
        source.close()
    return {"sent": sent, "skipped": skipped, "answers": answers, "source": source}


def stream_misses(run: dict, events: list[dict]) -> dict:
    """The stream's figures from its answers and the simulator's log (as
    ``bench/sustained.py``): a miss is a slot skipped, a target not ACCEPTED (a newer one
    replaced it while it waited: CANCELLED), or one whose first update the autopilot had not
    carried out within its 20 ms slot (the last servo command handled; for the Lua bridge the
    script setting the outputs). Separately, ``late_ack``: the update's last ACK back at the
    daemon later than the slot (it adds the ACK's bytes on the line)."""
    sent, answers = run["sent"], run["answers"]
    # Replies come as targets end: a replaced one (CANCELLED) at once, so not in send order.
    # An accepted one is matched to its slot by when the daemon received it.
    slots_s = np.array(sent)
    accepted = [a for a in answers if a.get("outcome") == "accepted"]
    ends = run["source"].update_ends(events, accepted, since_s=sent[0] if sent else 0.0)
    late, late_ack = [], []
    for answer, end_s in zip(accepted, ends, strict=True):
        timing = answer.get("timing") or {}
        received_s = timing.get("received_s", math.inf)
        k = max(0, int(np.searchsorted(slots_s, received_s, side="right")) - 1)
        late.append(end_s - slots_s[k])
        late_ack.append(timing.get("acked_s", timing.get("solved_s", math.inf)) - slots_s[k])
    cancelled = sum(a.get("outcome") == "cancelled" for a in answers)
    misses = run["skipped"] + len(sent) - len(accepted) + sum(x > SLOT_S for x in late)
    return {
        "targets": len(sent) + run["skipped"],
        "misses": misses,
        "cancelled": cancelled,
        "late": late,
        "late_ack": late_ack,
        "acks_late": sum(x > SLOT_S for x in late_ack),
    }


def run(args: argparse.Namespace) -> list[dict]:
    calibration = default_calibration()
    poses = random_targets(Arm.default(), args.targets, args.seed)
    daemon = {"control": {"rate_hz": 50.0}, "arm": {"joint_speed_deg_s": 1000.0}}
    results = []
    for baud in args.bauds:
        for dialect in args.dialects:
            print(f"{dialect} at {baud} baud ...", file=sys.stderr, flush=True)
            transport = ("--pty", "--pty-baud", str(baud))
            with Stack(dialect=dialect, daemon=daemon, transport=transport) as stack:
                lat = latency(stack, poses, args.seed, from_rest=True)
                moving = latency(stack, poses, args.seed + 7, from_rest=False)
                streamed = stream(stack, args.duration_s)
                sus = stream_misses(streamed, stack.stop())
            cost = update_cost(dialect, calibration, baud)
            model = model_update_s(dialect, baud, calibration, 400, args.seed)
            results.append(
                {
                    "baud": baud,
                    "dialect": dialect,
                    "cost": cost,
                    "model": model,
                    **lat,
                    "target_moving": moving["target"],
                    **sus,
                }
            )
    return results


def report(results: list[dict], args: argparse.Namespace, load_before: str) -> list[str]:
    rows = []
    for r in results:
        u50, u99, umax = percentiles_ms(r["update"])
        t50, t99, _ = percentiles_ms(r["target"])
        mt50, mt99, _ = percentiles_ms(r["target_moving"])
        m50, _, mmax = percentiles_ms(r["model"])
        pred = r["cost"].median_ms
        s50, s99, smax = percentiles_ms(r["late"])
        _, ack99, _ = percentiles_ms(r["late_ack"])
        rows.append([
            r["dialect"], r["baud"], r["cost"].to_fc_bytes, f"{pred:.1f}",
            f"{m50:.1f} / {mmax:.1f}", f"{m50 / pred:.2f}",
            f"{u50:.1f} / {u99:.1f} / {umax:.1f}",
            f"{t50:.1f} / {t99:.1f}", f"{mt50:.1f} / {mt99:.1f}",
            f"{r['misses']} / {r['targets']}", f"{s50:.1f} / {s99:.1f} / {smax:.1f}",
            r["acks_late"], f"{ack99:.1f}",
        ])  # fmt: skip
    lines = [
        "# Serial links: target → last ACK and the 50 Hz stream, by dialect and baud",
        "",
        f"`python -m bench.serial_links --targets {args.targets} --duration-s "
        f"{args.duration_s:g}`; {machine()}; load before {load_before}, after "
        f"{load_average()}. Times in ms; simulated serial line (8N1, 10 bits a byte both "
        "ways), the Lua script emulated (median 8.9 / max 11.5 ms).",
        "",
        *md_table(
            HEADERS,
            rows,
        ),  # fmt: skip
        "",
        "predicted: bytes both ways + the FC's measured median answer. sim model: the "
        "simulator's autopilot and serial-line models on a simulated clock (400 updates at "
        "random loop phases): what the simulator itself gives, free of the OS. update / "
        "target→last ACK / stream: the daemon and the simulator as processes on this machine, "
        "so they include both processes' scheduling and the daemon's threads (shared with the "
        "other work on the machine).",
        "",
        "Which to choose: over UDP/TCP or at 921 600 baud, `ardupilot` (pipelined DO_SET_SERVO, "
        "no script, lowest latency); at 57 600–115 200 baud on ArduPilot, `ardupilot-lua` (one "
        "44-byte frame instead of 264 B); PX4 is one frame already (`px4`). `armbridge "
        "check-config` says whether a config's rate fits its baud "
        "(`firmware_interface.link_budget`).",
    ]
    return lines


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--bauds", type=int, nargs="+", default=list(BAUDS))
    parser.add_argument("--dialects", nargs="+", choices=DIALECTS, default=list(DIALECTS))
    parser.add_argument("--targets", type=int, default=100, help="latency targets per stack")
    parser.add_argument("--duration-s", type=float, default=30.0, help="50 Hz stream per stack")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--markdown", type=Path, default=ROOT / "bench/results/serial_links.md")
    args = parser.parse_args()
    load_before = load_average()
    results = run(args)
    text = "\n".join(report(results, args, load_before)) + "\n"
    print(text)
    write_markdown(args.markdown, text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
