"""A MAVLink target flood at the daemon: does it stay responsive, bounded and quiet?

    python -m bench.flood [--rate-hz 5000] [--duration-s 10] [--unreachable 0.5]
                          [--stop-every-s 0.2] [--baseline-s 3] [--dialect ardupilot]
                          [--via autopilot|direct]
                          [--seed 0] [--markdown bench/results/flood.md]

About 25 s with the defaults (5 000 targets/s for 10 s).

The daemon (``armbridge run``, shipped defaults plus a control socket) and the simulated flight
controller (``python -m sim_servo``, ArduCopter link timing, a ground-station link) run as
subprocesses on UDP loopback (``bench/loopback.py``). A child process (``bench/flooder.py``)
sends ``--rate-hz`` COMMAND_LONG ``MAV_CMD_USER_1`` a second for ``--duration-s``, unsigned,
from 255/190, addressed to the daemon (the autopilot's system id, component 191), with
``--via autopilot`` (the default) to the simulator's ground-station link, which routes them to
the daemon as a ground station's targets are; with ``--via direct`` straight to the daemon's UDP
socket, which reads only its autopilot (the flood is dropped and counted there);
the poses are seeded, a fraction ``--unreachable`` of them out of reach (their solve runs the
whole budget). The
flooder heartbeats to the simulator's ground-station link, so the daemon's ACKs, sent to the
autopilot, are routed back to it and counted per MAV_RESULT.

Measured, with the same probes before the flood (the baseline, ``--baseline-s``) and during it:

* a control-socket ``stop`` every ``--stop-every-s``, each on a new connection as
  ``armbridge stop`` makes, and a ``resume`` after it (a stop holds the arm until one): its
  answer latency (target during the flood: max and p99 ≤ 50 ms);
* the daemon's RSS (VmRSS, every 50 ms): before the flood, peak, at its end, and after the
  drain (target: growth < 5 MB);
* a ``goto`` on the control socket before the flood and at once after its last frame: time to
  ACCEPTED (target after the flood ≤ 1 s);
* the daemon's counters (the difference over the flood), the ACKs the flooder got back, the
  lines the daemon wrote to its log (stdout + stderr, i.e. the journal) during the flood, and
  the daemon's and simulator's CPU time beside the wall time.

The bench process and the flooder run with their garbage collectors off while measuring.
"""

from __future__ import annotations

import argparse
import gc
import math
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from bench.flooder import DRAIN_S, Flooder, encode_targets, flood_poses
from bench.loopback import (
    Stack,
    cpu_s,
    load_average,
    percentiles_ms,
    rss_mb,
    run_and_report,
    udp_sockets,
)
from bench.report import machine, md_table
from companion.daemon.client import request
from companion.kinematics.arm import Arm, Pose
from devkit.timing import wait_until

ROOT = Path(__file__).resolve().parent.parent
RSS_EVERY_S = 0.05
STOP_TARGET_S = 0.050
RSS_GROWTH_TARGET_MB = 5.0
GOTO_TARGET_S = 1.0
GOTO_GIVE_UP_S = 10.0
REPLY_TIMEOUT_S = 10.0


def timed_request(path: str, obj: dict[str, Any]) -> dict[str, Any]:
    """One request on a new connection: ``latency_s`` and the ``reply`` (or ``error``)."""
    start = time.monotonic()
    try:
        reply = request(path, obj, timeout_s=REPLY_TIMEOUT_S)
    except (OSError, ConnectionError, ValueError) as exc:
        return {"t_s": start, "latency_s": math.inf, "reply": None, "error": repr(exc)}
    return {"t_s": start, "latency_s": time.monotonic() - start, "reply": reply, "error": None}


def answered(probe: dict[str, Any]) -> bool:
    reply = probe["reply"]
    return reply is not None and "outcome" in reply


def probe_until(
    stack: Stack, until: Any, every_s: float, rss: list[tuple[float, float]]
) -> list[dict[str, Any]]:
    """``stop`` every ``every_s`` (inf: none) and RSS every :data:`RSS_EVERY_S` until
    ``until()``."""
    stops = []
    next_rss = time.monotonic()
    next_stop = next_rss if math.isfinite(every_s) else math.inf
    while not until():
        now = time.monotonic()
        if now >= next_rss:
            rss.append((now, rss_mb(stack.daemon_pid)))
            next_rss += RSS_EVERY_S
        if now >= next_stop:
            stops.append(timed_request(stack.control_path, {"cmd": "stop"}))
            # A stop holds the arm until a resume: the flood's targets are carried out again
            # (else they would be refused unsolved, a lighter load than the bench means).
            timed_request(stack.control_path, {"cmd": "resume"})
            next_stop += every_s
        time.sleep(max(0.0, min(next_rss, next_stop) - time.monotonic()))
    return stops


def goto_until_accepted(path: str, pose: tuple[float, ...]) -> dict[str, Any]:
    """``goto`` (a new connection each), again at once while it is not ACCEPTED, for at most
    :data:`GOTO_GIVE_UP_S`: ``latency_s`` from the first send to the ACCEPTED answer (inf if
    none), and every attempt."""
    start = time.monotonic()
    attempts = []
    while time.monotonic() - start < GOTO_GIVE_UP_S:
        probe = timed_request(path, {"cmd": "goto", "pose": list(pose)})
        attempts.append(probe)
        if (probe["reply"] or {}).get("outcome") == "accepted":
            return {"latency_s": time.monotonic() - start, "attempts": attempts}
    return {"latency_s": math.inf, "attempts": attempts}


def log_lines(path: Path) -> list[str]:
    return path.read_text(errors="replace").splitlines()


def run(args: argparse.Namespace) -> dict[str, Any]:
    count = int(round(args.rate_hz * args.duration_s))
    poses, far = flood_poses(count, args.unreachable, args.seed)
    arm = Arm.default()
    rng = np.random.default_rng(args.seed + 1)
    goto_before, goto_after = (
        Pose.from_matrix(t).as_tuple() for t in arm.fk_batch(arm.random_q_rad(rng, 2))
    )
    out: dict[str, Any] = {"count": count, "unreachable": int(far.sum())}
    with Stack(dialect=args.dialect) as stack:
        ports = sorted(udp_sockets(stack.daemon_pid))
        if len(ports) != 1:
            raise RuntimeError(f"expected one UDP socket in the daemon, found ports {ports}")
        if not wait_until(lambda: stack.status()["autopilot"] is not None, 10.0):
            raise RuntimeError("the daemon pinned no autopilot")
        system_id = stack.status()["autopilot"][0]
        flooder = Flooder(
            encode_targets(poses, system_id),
            daemon_port=ports[0],
            via_autopilot=args.via == "autopilot",
            gcs_url=stack.gcs_url,
            rate_hz=args.rate_hz,
        )
        try:
            gc.collect()
            gc.freeze()
            gc.disable()
            rss: list[tuple[float, float]] = []
            # Baseline: the same probes with no flood.
            out["goto_before"] = goto_until_accepted(stack.control_path, goto_before)
            base_end = time.monotonic() + args.baseline_s
            out["stops_before"] = probe_until(
                stack, lambda: time.monotonic() >= base_end, args.stop_every_s, rss
            )
            status0 = stack.status()
            lines0 = len(log_lines(stack.daemon_log))
            cpu0 = (cpu_s(stack.daemon_pid), cpu_s(stack.sim_pid))
            drops0 = udp_drops(stack)
            out["rss_before"] = rss_mb(stack.daemon_pid)
            out["load_at_start"] = load_average()
            start_s = flooder.start()
            rss_flood: list[tuple[float, float]] = []
            out["stops_during"] = probe_until(
                stack, lambda: flooder.done(), args.stop_every_s, rss_flood
            )
            out["goto_after"] = goto_until_accepted(stack.control_path, goto_after)
            out["rss_end"] = rss_mb(stack.daemon_pid)
            assert flooder.end_s is not None
            out["flood_wall_s"] = flooder.end_s - start_s
            cpu1 = (cpu_s(stack.daemon_pid), cpu_s(stack.sim_pid))
            lines1 = len(log_lines(stack.daemon_log))
            result = flooder.result()
            drain_end = time.monotonic() + 0.5
            probe_until(stack, lambda: time.monotonic() >= drain_end, math.inf, rss_flood)
            gc.enable()
            out["rss_after"] = rss_mb(stack.daemon_pid)
            out["rss_peak"] = max(r for _, r in rss_flood)
            status1 = stack.status()
            drops1 = udp_drops(stack)
            lines = log_lines(stack.daemon_log)
        finally:
            gc.enable()
            flooder.kill()
        stack.stop()
    out["udp_drops"] = {k: drops1[k] - drops0[k] for k in drops1}
    out["cpu_daemon_s"] = cpu1[0] - cpu0[0]
    out["cpu_sim_s"] = cpu1[1] - cpu0[1]
    out["result"] = result
    out["counters"] = {
        k: status1["counters"][k] - status0["counters"].get(k, 0) for k in status1["counters"]
    }
    out["journal_during"] = lines[lines0:lines1]
    out["journal_after"] = lines[lines1:]
    out["tracebacks"] = sum("Traceback" in line for line in lines)
    out["load_after"] = load_average()
    return out


def udp_drops(stack: Stack) -> dict[str, int]:
    """Datagrams the kernel dropped so far on the daemon's link socket and on the simulator's
    two (companion link, ground-station link)."""
    daemon = udp_sockets(stack.daemon_pid)
    sim = udp_sockets(stack.sim_pid)
    return {"daemon": sum(daemon.values()), "simulator": sum(sim.values())}


def report(out: dict[str, Any], args: argparse.Namespace, load_before: str) -> list[str]:
    r = out["result"]

    def stop_row(name: str, stops: list[dict[str, Any]], target: bool) -> list[Any]:
        ok = [s for s in stops if answered(s)]
        p50, p99, mx = percentiles_ms([s["latency_s"] for s in ok])
        verdict = ""
        if target:
            met = len(ok) == len(stops) and mx <= STOP_TARGET_S * 1e3 and p99 <= STOP_TARGET_S * 1e3
            verdict = "yes" if met else "**no**"
        outcomes = sorted({s["reply"]["outcome"] for s in ok})
        return [name, len(stops), len(stops) - len(ok), p50, p99, mx, ", ".join(outcomes), verdict]

    def goto_cell(goto: dict[str, Any]) -> str:
        tries = [
            f"{(a['reply'] or {}).get('outcome', a['error'])} "
            f"({(a['reply'] or {}).get('message', '')}) in {a['latency_s'] * 1e3:.1f} ms"
            for a in goto["attempts"]
        ]
        shown = "; ".join(tries[:4]) + (f"; ... {len(tries) - 4} more" if len(tries) > 4 else "")
        return f"ACCEPTED after {goto['latency_s'] * 1e3:.1f} ms, {len(tries)} attempt(s): {shown}"

    growth = out["rss_peak"] - out["rss_before"]
    lines = [
        "# MAVLink target flood at the daemon",
        "",
        f"`{' '.join(['python -m bench.flood', *sys.argv[1:]])}` on {machine()}; load average "
        f"(1, 5, 15 min) before: {load_before}, at the flood's start: {out['load_at_start']}, "
        f"after: {out['load_after']}.",
        "",
        f"{out['count']} COMMAND_LONG USER_1 ({out['unreachable']} unreachable, seed "
        f"{args.seed}) at {args.rate_hz:g}/s from 255/190, unsigned, "
        + (
            "to the simulated autopilot's ground-station link, routed to the daemon "
            if args.via == "autopilot"
            else "straight to the daemon's UDP socket (which reads only its autopilot) "
        )
        + f"({args.dialect} dialect, shipped defaults). Sent {r.sent} in "
        f"{out['flood_wall_s']:.2f} s ({r.sent / out['flood_wall_s']:.0f}/s), "
        f"{r.send_errors} send errors.",
        "",
        "Control-socket `stop` (a new connection each), answer latency:",
        "",
    ]
    lines += md_table(
        ["when", "stops", "unanswered", "p50 ms", "p99 ms", "max ms", "outcomes",
         f"max, p99 ≤ {STOP_TARGET_S * 1e3:g} ms"],
        [stop_row(f"before the flood ({args.baseline_s:g} s)", out["stops_before"], False),
         stop_row("during the flood", out["stops_during"], True)],
    )  # fmt: skip
    lines += [
        "",
        "- `goto` on the control socket (sent again at once until ACCEPTED), time from the first "
        f"send to ACCEPTED: before the flood {goto_cell(out['goto_before'])}. At once after the "
        f"flood's last frame: {goto_cell(out['goto_after'])}. Target ≤ {GOTO_TARGET_S:g} s: "
        + ("yes" if out["goto_after"]["latency_s"] <= GOTO_TARGET_S else "**no**")
        + (
            ""
            if len(out["goto_after"]["attempts"]) == 1
            else " (counting from the first goto; the first alone was not ACCEPTED)"
        )
        + ".",
        f"- Daemon RSS: before {out['rss_before']:.1f} MB, peak during the flood "
        f"{out['rss_peak']:.1f} MB, at its end {out['rss_end']:.1f} MB, after the drain "
        f"{out['rss_after']:.1f} MB; growth {growth:+.2f} MB (target < "
        f"{RSS_GROWTH_TARGET_MB:g} MB: {'yes' if growth < RSS_GROWTH_TARGET_MB else '**no**'}).",
        f"- CPU over the flood's {out['flood_wall_s']:.1f} s: daemon {out['cpu_daemon_s']:.2f} s "
        f"({100 * out['cpu_daemon_s'] / out['flood_wall_s']:.0f} % of a core), simulator "
        f"{out['cpu_sim_s']:.2f} s ({100 * out['cpu_sim_s'] / out['flood_wall_s']:.0f} %).",
        "- Daemon counters over the flood (the goto after it included): "
        + ", ".join(f"{k} {v}" for k, v in out["counters"].items() if v),
        f"- ACKs the flooder got back ({DRAIN_S:g} s drain): {r.acks_total} of {r.sent} "
        "targets: "
        + ", ".join(f"{k} {v}" for k, v in sorted(r.acks.items()))
        + f"; STATUSTEXT {r.statustexts}; other frames {r.other_frames}.",
        f"- Datagrams the kernel dropped (receive buffer full) over the flood: on the daemon's "
        f"link socket {out['udp_drops']['daemon']}, on the simulator's sockets "
        f"{out['udp_drops']['simulator']}.",
        f"- Journal lines the daemon wrote during the flood: {len(out['journal_during'])}; "
        f"after it: {len(out['journal_after'])}; tracebacks in the whole log: "
        f"{out['tracebacks']}.",
        f"  During the flood: {sum('autopilot link lost' in x for x in out['journal_during'])} "
        "autopilot link losses (heartbeats lost with the flood), "
        f"{sum('SYSTEM_TIME stopped' in x for x in out['journal_during'])} SYSTEM_TIME "
        f"silences, {sum('motion stopped' in x for x in out['journal_during'])} motions stopped "
        "for unanswered servo updates.",
    ]
    if out["journal_during"]:
        lines += ["", "The journal during the flood:", "", "```"]
        lines += out["journal_during"][:20]
        if len(out["journal_during"]) > 20:
            lines.append(f"... ({len(out['journal_during']) - 20} more)")
        lines.append("```")
    return lines


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--rate-hz", type=float, default=5000.0, help="targets a second")
    parser.add_argument("--duration-s", type=float, default=10.0)
    parser.add_argument("--unreachable", type=float, default=0.5, help="fraction out of reach")
    parser.add_argument("--stop-every-s", type=float, default=0.2)
    parser.add_argument("--baseline-s", type=float, default=3.0)
    parser.add_argument("--dialect", choices=["ardupilot", "px4"], default="ardupilot")
    parser.add_argument(
        "--via",
        choices=["autopilot", "direct"],
        default="autopilot",
        help="autopilot: to the simulator's ground-station link, routed to the daemon (a ground "
        "station's path); direct: to the daemon's UDP socket, which reads only its autopilot "
        "the flood is dropped there",
    )
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--markdown", type=Path, default=ROOT / "bench/results/flood.md")
    return run_and_report(run, report, parser.parse_args())


if __name__ == "__main__":
    raise SystemExit(main())
