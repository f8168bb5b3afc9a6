"""A machine stall probe: an idle process that wakes every ``period_ms`` and records every wake
that came ``threshold_ms`` or more late, beside the machine's steal time (``/proc/stat``: CPU
time a virtual machine's host gave to someone else).

    python -m bench.stall_probe --out FILE [--period-ms 2] [--threshold-ms 5]

A bench runs it beside what it measures (:class:`StallProbe`, a context manager) and attributes
a late target to the machine when a probe wake was late around the same moment: a process that
does nothing but sleep cannot be late by its own fault, so such a stall is the scheduler's or
the hypervisor's, and it hits the daemon and the simulator the same way. Costs about 0.5 % of
a core (500 wakes a second).
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any


def steal_s() -> float:
    """The machine's total steal time so far (all CPUs), in seconds; 0 where not reported."""
    try:
        with open("/proc/stat") as handle:
            fields = handle.readline().split()
    except OSError:
        return 0.0
    steal_ticks = int(fields[8]) if len(fields) > 8 else 0
    return steal_ticks / os.sysconf("SC_CLK_TCK")


def probe(out: Path, period_s: float, threshold_s: float) -> None:
    """Sleep ``period_s`` at a time until SIGTERM; then write the late wakes to ``out``."""
    stop = False

    def on_term(*_: Any) -> None:
        nonlocal stop
        stop = True

    signal.signal(signal.SIGTERM, on_term)
    stalls: list[tuple[float, float]] = []
    steal0, t0 = steal_s(), time.monotonic()
    last = t0
    while not stop:
        time.sleep(period_s)
        now = time.monotonic()
        if now - last - period_s >= threshold_s:
            stalls.append((last, now - last - period_s))  # (when it should have woken, late)
        last = now
    result = {
        "start_s": t0,
        "end_s": time.monotonic(),
        "steal_s": steal_s() - steal0,
        "period_s": period_s,
        "threshold_s": threshold_s,
        "stalls": stalls,
    }
    out.write_text(json.dumps(result))


@dataclass
class ProbeResult:
    start_s: float
    end_s: float
    steal_s: float
    threshold_s: float
    stalls: list[tuple[float, float]]  # (monotonic s, how late s)

    def near(self, t0_s: float, t1_s: float) -> list[tuple[float, float]]:
        """The stalls that overlap [t0_s, t1_s]."""
        return [(t, late) for t, late in self.stalls if t <= t1_s and t + late >= t0_s]

    def summary(self) -> str:
        wall_s = self.end_s - self.start_s
        worst = max((late for _, late in self.stalls), default=0.0)
        return (
            f"an idle probe process woke {self.threshold_s * 1e3:g} ms or more late "
            f"{len(self.stalls)} times in {wall_s:.0f} s (worst {worst * 1e3:.1f} ms); "
            f"steal time {self.steal_s:.2f} s"
        )


class StallProbe:
    """Runs :func:`probe` in its own process for the ``with`` block; ``result`` after it."""

    def __init__(self, period_ms: float = 2.0, threshold_ms: float = 5.0) -> None:
        self._tmp = tempfile.TemporaryDirectory(prefix="armbridge-stall-")
        self._out = Path(self._tmp.name) / "stalls.json"
        self._args = ["--period-ms", str(period_ms), "--threshold-ms", str(threshold_ms)]
        self.result: ProbeResult | None = None

    def __enter__(self) -> StallProbe:
        root = Path(__file__).resolve().parent.parent
        self._proc = subprocess.Popen(
            [sys.executable, "-m", "bench.stall_probe", "--out", str(self._out), *self._args],
            cwd=root,
        )
        return self

    def __exit__(self, *exc: object) -> None:
        try:
            self._proc.send_signal(signal.SIGTERM)
            self._proc.wait(timeout=10)
            data = json.loads(self._out.read_text())
            self.result = ProbeResult(
                data["start_s"],
                data["end_s"],
                data["steal_s"],
                data["threshold_s"],
                [(t, late) for t, late in data["stalls"]],
            )
        except (OSError, ValueError, subprocess.TimeoutExpired):
            self._proc.kill()
            self.result = None
        finally:
            self._tmp.cleanup()


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--period-ms", type=float, default=2.0)
    parser.add_argument("--threshold-ms", type=float, default=5.0)
    args = parser.parse_args()
    probe(args.out, args.period_ms / 1e3, args.threshold_ms / 1e3)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
