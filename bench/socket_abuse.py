"""Control-socket abuse: do 500 connections, 200 slowloris clients and 1 MiB partial lines
cost the daemon memory, lock out its other clients or disturb its MAVLink path?

    python -m bench.socket_abuse [--connections 500] [--slowloris 200] [--big-lines 20]
                                 [--attack-s 15] [--baseline-s 5] [--dialect ardupilot]
                                 [--markdown bench/results/socket_abuse.md]

About 35 s with the defaults. The daemon (``armbridge run``, shipped defaults: 32 connections,
30 s idle timeout) and the simulated flight controller run as subprocesses on UDP loopback
(``bench/loopback.py``). The attacker is a third process (this module with ``attack``), one
non-blocking loop that for ``--attack-s`` seconds keeps open, reopening each one the daemon
closes at once:

* ``--connections`` idle connections (connect, send nothing);
* ``--slowloris`` connections that send one byte of a request line a second, never its end;
* ``--big-lines`` connections that each send 1 MiB without a newline.

Meanwhile, and for ``--baseline-s`` before (the reference), the bench asks as a normal client
would, each on a new connection: ``status`` every 0.2 s, a control-socket ``goto`` every second,
and a MAVLink ``goto`` (COMMAND_LONG USER_1 from a ground station through the simulated
autopilot) every second, alternating between two reachable poses so that each one moves the
arm; it samples the daemon's RSS at each probe.

Targets: RSS growth (peak during the attack − before) < 10 MB; every probe answered,
every goto accepted, latencies as before within reason; the socket alive afterwards; the link
up throughout.
"""

from __future__ import annotations

import argparse
import errno
import json
import resource
import selectors
import socket
import subprocess
import sys
import time
from collections import Counter
from pathlib import Path
from typing import Any

from bench.loopback import (
    MavlinkInput,
    Stack,
    answer_one,
    cpu_s,
    load_average,
    percentiles_ms,
    rss_mb,
    run_and_report,
)
from bench.report import machine, md_table
from companion.daemon.client import request
from companion.kinematics.arm import Arm

ROOT = Path(__file__).resolve().parents[1]
RSS_GROWTH_TARGET_MB = 10.0
STATUS_EVERY_S = 0.2
GOTO_EVERY_S = 1.0
BIG_LINE_BYTES = 1 << 20
PROBE_TIMEOUT_S = 10.0


# -- the attacker (its own process) ------------------------------------------------------------


class _Attacker:
    """One non-blocking loop holding the three kinds of abusive connections."""

    def __init__(self, path: str, counts: dict[str, int]) -> None:
        self.path = path
        self.want = counts
        self.open: dict[str, set[socket.socket]] = {kind: set() for kind in counts}
        self.kind: dict[socket.socket, str] = {}
        self.sent: dict[socket.socket, int] = {}
        self.next_byte_s: dict[socket.socket, float] = {}
        self.selector = selectors.DefaultSelector()
        self.stats: Counter[str] = Counter()
        self.max_open = 0

    def run(self, duration_s: float) -> dict[str, Any]:
        end = time.monotonic() + duration_s
        while (now := time.monotonic()) < end:
            self._top_up(now)
            for key, mask in self.selector.select(0.02):
                sock = key.fileobj
                assert isinstance(sock, socket.socket)
                if mask & selectors.EVENT_READ:
                    self._readable(sock)
                if mask & selectors.EVENT_WRITE and sock in self.kind:
                    self._writable(sock)
            self._dribble(time.monotonic())
            self.max_open = max(self.max_open, len(self.kind))
        for sock in list(self.kind):
            self._drop(sock)
        return {"stats": dict(self.stats), "max_open": self.max_open}

    def _top_up(self, now: float) -> None:
        for kind, want in self.want.items():
            for _ in range(min(64, want - len(self.open[kind]))):
                sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
                sock.setblocking(False)
                try:
                    sock.connect(self.path)
                except BlockingIOError:  # the backlog is full: try again next round
                    sock.close()
                    self.stats["connect would block"] += 1
                    break
                except OSError as exc:
                    sock.close()
                    self.stats[f"connect {errno.errorcode.get(exc.errno or 0, exc)}"] += 1
                    break
                self.stats[f"{kind} opened"] += 1
                self.open[kind].add(sock)
                self.kind[sock] = kind
                events = selectors.EVENT_READ
                if kind == "big":
                    self.sent[sock] = 0
                    events |= selectors.EVENT_WRITE
                elif kind == "slowloris":
                    self.sent[sock] = 0
                    self.next_byte_s[sock] = now
                self.selector.register(sock, events)

    def _readable(self, sock: socket.socket) -> None:
        try:
            data = sock.recv(65536)
        except BlockingIOError:
            return
        except OSError:
            data = b""
        for line in data.splitlines():
            try:
                error = json.loads(line).get("error", "?")
            except ValueError:
                error = "?"
            self.stats[f"told: {_reason(error)}"] += 1
        if not data:
            self.stats[f"{self.kind[sock]} closed by the daemon"] += 1
            self._drop(sock)

    def _writable(self, sock: socket.socket) -> None:
        left = BIG_LINE_BYTES - self.sent[sock]
        if left <= 0:
            self.selector.modify(sock, selectors.EVENT_READ)
            return
        try:
            sent = sock.send(b"x" * min(left, 65536))
        except BlockingIOError:
            return
        except OSError:
            self.stats["big closed by the daemon"] += 1
            self._drop(sock)
            return
        self.sent[sock] += sent
        self.stats["big bytes sent"] += sent

    def _dribble(self, now: float) -> None:
        for sock in list(self.open["slowloris"]):
            if self.next_byte_s[sock] > now:
                continue
            line = b'{"cmd": "status", "padding": "' + b"x" * 10_000
            try:
                sock.send(line[self.sent[sock] % len(line) :][:1])
            except BlockingIOError:
                pass
            except OSError:
                self.stats["slowloris closed by the daemon"] += 1
                self._drop(sock)
                continue
            self.sent[sock] += 1
            self.next_byte_s[sock] = now + 1.0

    def _drop(self, sock: socket.socket) -> None:
        kind = self.kind.pop(sock)
        self.open[kind].discard(sock)
        self.sent.pop(sock, None)
        self.next_byte_s.pop(sock, None)
        self.selector.unregister(sock)
        sock.close()


def _reason(error: str) -> str:
    """An error line's gist, without its numbers."""
    for words in (
        "closed to make room",
        "too many connections",
        "idle for",
        "longer than",
        "permission denied",
    ):
        if words in error:
            return words
    return error[:40]


def attack(path: str, duration_s: float, counts: dict[str, int]) -> dict[str, Any]:
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    need = sum(counts.values()) + 64
    if soft < need:
        resource.setrlimit(resource.RLIMIT_NOFILE, (min(hard, need), hard))
    return _Attacker(path, counts).run(duration_s)


# -- the probes (the bench's own process) ----------------------------------------------------


def _timed(call: Any) -> dict[str, Any]:
    started = time.monotonic()
    try:
        reply = call()
    except (OSError, ConnectionError, ValueError) as exc:
        return {"ok": False, "latency_s": time.monotonic() - started, "error": repr(exc)}
    return {"latency_s": time.monotonic() - started, **reply}


def probe(stack: Stack, mav: MavlinkInput, poses: list[list[float]], until_s: float) -> dict:
    """Status, socket goto and MAVLink goto probes until ``until_s``; RSS and link samples."""
    out: dict[str, list[Any]] = {"status": [], "goto": [], "mavlink": [], "rss": [], "link": []}
    next_goto_s = next_mav_s = time.monotonic()
    next_mav_s += GOTO_EVERY_S / 2
    while (now := time.monotonic()) < until_s:
        s = _timed(
            lambda: request(stack.control_path, {"cmd": "status"}, timeout_s=PROBE_TIMEOUT_S)
        )
        out["status"].append(s)
        if s.get("ok"):
            out["link"].append(s["status"]["link"])
        out["rss"].append(rss_mb(stack.daemon_pid))
        if now >= next_goto_s:
            goto = {"cmd": "goto", "pose": poses[len(out["goto"]) % 2]}
            out["goto"].append(
                _timed(lambda: request(stack.control_path, goto, timeout_s=PROBE_TIMEOUT_S))  # noqa: B023
            )
            next_goto_s += GOTO_EVERY_S
        if now >= next_mav_s:
            answer = answer_one(mav, poses[(len(out["mavlink"]) + 1) % 2])
            out["mavlink"].append(
                {"latency_s": answer["answered_s"] - answer["sent_s"], "outcome": answer["outcome"]}
            )
            next_mav_s += GOTO_EVERY_S
        time.sleep(max(0.0, STATUS_EVERY_S - (time.monotonic() - now)))  # the probes' pace
    for s in out["status"]:
        s.pop("status", None)  # keep the report's data small
    return out


def run(args: argparse.Namespace) -> dict[str, Any]:
    arm = Arm.default()
    poses = [
        list(arm.fk(q).as_tuple()) for q in ([20, 70, 50, 20, 30, 10], [25, 75, 45, 20, 30, 10])
    ]
    out: dict[str, Any] = {}
    with Stack(dialect=args.dialect) as stack:
        mav = MavlinkInput(stack)
        try:
            out["rss_start"] = rss_mb(stack.daemon_pid)
            t0 = time.monotonic()
            cpu0 = cpu_s(stack.daemon_pid)
            out["baseline"] = probe(stack, mav, poses, t0 + args.baseline_s)
            out["daemon_cpu_baseline"] = (cpu_s(stack.daemon_pid) - cpu0) / (time.monotonic() - t0)
            out["load_at_attack"] = load_average()
            counts = {"idle": args.connections, "slowloris": args.slowloris, "big": args.big_lines}
            attacker = subprocess.Popen(
                [sys.executable, "-m", "bench.socket_abuse", "attack", stack.control_path,
                 str(args.attack_s), json.dumps(counts)],
                cwd=ROOT, stdout=subprocess.PIPE, text=True,
            )  # fmt: skip
            t1 = time.monotonic()
            cpu1 = cpu_s(stack.daemon_pid)
            out["attack"] = probe(stack, mav, poses, t1 + args.attack_s)
            stdout, _ = attacker.communicate(timeout=args.attack_s + 30)
            t2 = time.monotonic()
            out["daemon_cpu_attack"] = (cpu_s(stack.daemon_pid) - cpu1) / (t2 - t1)
            out["attacker"] = json.loads(stdout)
            out["after"] = probe(stack, mav, poses, t2 + 2.0)
            out["rss_end"] = rss_mb(stack.daemon_pid)
            out["load_after"] = load_average()
            out["persistent_status_ok"] = stack.status()["link"] == "up"
        finally:
            mav.close()
        stack.stop()
        log = stack.daemon_log.read_text(errors="replace")
    out["tracebacks"] = log.count("Traceback")
    out["log_tail"] = [x for x in log.splitlines() if "control" in x][-10:]
    return out


def report(out: dict[str, Any], args: argparse.Namespace, load_before: str) -> list[str]:
    def row(name: str, phase: dict[str, Any]) -> list[list[Any]]:
        rows = []
        for kind, good in (("status", "ok"), ("goto", "accepted"), ("mavlink", "accepted")):
            probes = phase[kind]
            answered = [p for p in probes if "error" not in p or p.get("outcome")]
            if kind == "status":
                fine = [p for p in probes if p.get("ok")]
            else:
                fine = [p for p in probes if p.get("outcome") == "accepted"]
            p50, p99, mx = percentiles_ms([p["latency_s"] for p in answered])
            other = Counter(
                p.get("outcome") or p.get("error", "?")[:40] for p in probes if p not in fine
            )
            others = ", ".join(f"{k} {v}" for k, v in other.items()) or "–"
            rows.append([name, kind, len(probes), f"{len(fine)} {good}", others, p50, p99, mx])
        return rows

    phases = [("before", out["baseline"]), ("attack", out["attack"]), ("after", out["after"])]
    rss_before = max(out["baseline"]["rss"])
    rss_peak = max(out["attack"]["rss"] + out["after"]["rss"])
    growth = rss_peak - rss_before
    probes_ok = all(p.get("ok") for _, ph in phases[1:] for p in ph["status"]) and all(
        p.get("outcome") == "accepted"
        for _, ph in phases[1:]
        for k in ("goto", "mavlink")
        for p in ph[k]
    )
    links = {x for _, ph in phases for x in ph["link"]}
    attacker = out["attacker"]
    lines = [
        "# Control-socket abuse",
        "",
        f"`{' '.join(['python -m bench.socket_abuse', *sys.argv[1:]])}` on {machine()}; load "
        f"average (1, 5, 15 min) before: {load_before}, at the attack's start: "
        f"{out['load_at_attack']}, after: {out['load_after']}.",
        "",
        f"Attack for {args.attack_s:g} s from one process: {args.connections} idle connections, "
        f"{args.slowloris} slowloris (a byte a second), {args.big_lines} sending 1 MiB lines, "
        f"each reopened as soon as the daemon closes it (at most {attacker['max_open']} open at "
        "once on the attacker's side). Probes, each on a new connection: status every "
        f"{STATUS_EVERY_S:g} s, control-socket goto and MAVLink goto every {GOTO_EVERY_S:g} s.",
        "",
    ]
    lines += md_table(
        ["phase", "probe", "sent", "answered well", "other", "p50 ms", "p99 ms", "max ms"],
        [r for name, ph in phases for r in row(name, ph)],
    )
    lines += [
        "",
        f"- Daemon RSS: at start {out['rss_start']:.1f} MB, highest before the attack "
        f"{rss_before:.1f} MB, peak during and after it {rss_peak:.1f} MB, at the end "
        f"{out['rss_end']:.1f} MB; growth {growth:+.2f} MB (target < {RSS_GROWTH_TARGET_MB:g} MB: "
        f"{'yes' if growth < RSS_GROWTH_TARGET_MB else '**no**'}).",
        f"- Every probe during and after the attack answered well: "
        f"{'yes' if probes_ok else '**no**'}. Link states seen: {', '.join(sorted(links))}. "
        f"The bench's persistent connection (opened before the attack) still served at the end: "
        f"{'yes' if out['persistent_status_ok'] else '**no**'}.",
        f"- Daemon CPU: {100 * out['daemon_cpu_baseline']:.0f} % of a core before the attack, "
        f"{100 * out['daemon_cpu_attack']:.0f} % during it (accepting and closing the "
        "attacker's connections).",
        "- What the attacker saw: "
        + ", ".join(f"{k} {v}" for k, v in sorted(attacker["stats"].items())),
        f"- Tracebacks in the daemon's log: {out['tracebacks']}.",
    ]
    if out["log_tail"]:
        lines += ["", "The daemon's last log lines about the control socket:", "", "```"]
        lines += out["log_tail"]
        lines.append("```")
    return lines


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["attack"]:  # the attacker process
        path, duration_s, counts = argv[1], float(argv[2]), json.loads(argv[3])
        print(json.dumps(attack(path, duration_s, counts)))
        return 0
    parser = argparse.ArgumentParser(description=(__doc__ or "").split("\n")[0])
    parser.add_argument("--connections", type=int, default=500)
    parser.add_argument("--slowloris", type=int, default=200)
    parser.add_argument("--big-lines", type=int, default=20)
    parser.add_argument("--attack-s", type=float, default=15.0)
    parser.add_argument("--baseline-s", type=float, default=5.0)
    parser.add_argument("--dialect", choices=["ardupilot", "px4"], default="ardupilot")
    parser.add_argument("--markdown", type=Path, default=ROOT / "bench/results/socket_abuse.md")
    return run_and_report(run, report, parser.parse_args(argv))


if __name__ == "__main__":
    raise SystemExit(main())
