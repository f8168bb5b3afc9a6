"""Reliability campaign, inputs side: adversarial targets, MAVLink input fuzz, config
fuzz, at full size, written up as a Markdown report.

The machinery is ``devkit/campaign.py`` (tests never import ``bench``); the CI-sized
tests (``tests/integration/test_reliability.py``, ``tests/daemon/test_config_fuzz.py``) run the
same functions smaller. See that module for what each part does and checks.

Usage, from the repository root (it imports ``devkit``)::

    python -m bench.reliability [--targets 300000] [--fuzz-rounds 20] [--seed 8]
                                [--markdown bench/results/reliability.md]
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
from collections import Counter
from collections.abc import Sequence
from pathlib import Path

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from bench.report import write_markdown
from devkit.campaign import (
    TARGET_MIX,
    ConfigReport,
    FuzzReport,
    TargetReport,
    run_config_fuzz,
    run_mavlink_fuzz,
    run_targets,
)


def markdown(
    targets: TargetReport, fuzz: FuzzReport, configs: ConfigReport, args: argparse.Namespace
) -> str:
    lines = [
        "# Reliability campaign (inputs side)",
        "",
        f"`python -m bench.reliability --targets {args.targets} --fuzz-rounds "
        f"{args.fuzz_rounds} --seed {args.seed}` on {os.cpu_count()} cores.",
        "",
        f'## 1. Adversarial targets through `ArmDaemon.submit("goto")` ({targets.elapsed_s:.1f} s)',
        "",
        "| category | inputs | accepted | denied | failed | temporarily rejected |",
        "|---|---:|---:|---:|---:|---:|",
    ]
    for category in TARGET_MIX:
        per = targets.outcomes.get(category, Counter())
        lines.append(
            f"| {category} | {targets.inputs[category]} | {per['accepted']} | {per['denied']} | "
            f"{per['failed']} | {per['temporarily_rejected']} |"
        )
    total = targets.total_outcomes
    lines += [
        f"| **total** | {sum(targets.inputs.values())} | {total['accepted']} | "
        f"{total['denied']} | {total['failed']} | {total['temporarily_rejected']} |",
        "",
        f"- Unresolved futures: {targets.unresolved}; non-Outcome replies: "
        f"{targets.non_outcome}; submit errors: {len(targets.submit_errors)}; control thread "
        f"alive at the end: {targets.control_thread_alive}.",
        f"- Outcomes not allowed for their category: {len(targets.unexpected)}; refusals "
        f"reporting a position error below the geometric floor: {len(targets.dishonest)}.",
        f"- The daemon's counters: {targets.counters}.",
        f"- DO_SET_SERVO frames the simulator received: {targets.sim_servo_commands}; servo "
        f"movements it applied on arm outputs: {targets.sim_servo_events}.",
        f"- **PWM outside calibration: {len(targets.pwm_violations)}** (sim event log, sim "
        "state, daemon status).",
        "",
        f"## 2. MAVLink input fuzz against `armbridge run` ({fuzz.elapsed_s:.1f} s)",
        "",
        "| category | frames |",
        "|---|---:|",
    ]
    lines += [f"| {k} | {v} |" for k, v in fuzz.frames.items()]
    lines += [
        f"| **total** | {sum(fuzz.frames.values())} |",
        "",
        f"- Distinct valid message types sent: {fuzz.message_types_sent} of "
        f"{len(mavlink.mavlink_map)} in ardupilotmega.",
        f"- Daemon alive at the end: {fuzz.daemon_alive}; exit code on SIGTERM: "
        f"{fuzz.exit_code}; markers answered {fuzz.markers_answered}/{fuzz.marker_rounds}; "
        f"status answers {fuzz.status_answers}, link states {dict(fuzz.link_states)}.",
        f"- **Servo commands (any COMMAND_LONG/INT) reaching the autopilot: "
        f"{len(fuzz.servo_commands)}**; what the daemon sent: {dict(fuzz.peer_received)}.",
        f"- VmRSS after the warm-up round {fuzz.rss_kb[0][1]} kB, at the end "
        f"{fuzz.rss_kb[-1][1]} kB: growth {fuzz.rss_growth_kb} kB over "
        f"{fuzz.rss_kb[-1][0] - fuzz.rss_kb[0][0]} frames; by round (frames, kB): "
        f"{fuzz.rss_kb[:: max(1, len(fuzz.rss_kb) // 10)]}.",
        f"- Daemon counters: {fuzz.counters} (USER_1 frames sent to someone else: "
        f"{fuzz.user1_not_for_us_sent}; each must be counted as not_for_us).",
        "",
        f"## 3. Config fuzz via `armbridge check-config` ({configs.elapsed_s:.1f} s)",
        "",
        "| category | cases |",
        "|---|---:|",
    ]
    lines += [f"| {k} | {v} |" for k, v in configs.cases.items()]
    lines += [
        f"| **total** | {sum(configs.cases.values())} |",
        "",
        f"- Fields named: {len(configs.fields_covered)}; **cases without exit 2 naming the "
        f"field: {len(configs.failures)}**.",
    ]
    lines += [f"  - {f}" for f in configs.failures[:20]]
    return "\n".join(lines) + "\n"


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--targets", type=int, default=300_000)
    parser.add_argument("--budget-ms", type=float, default=0.2)
    parser.add_argument("--fuzz-rounds", type=int, default=20)
    parser.add_argument("--seed", type=int, default=8)
    parser.add_argument("--markdown", default="bench/results/reliability.md")
    args = parser.parse_args(argv)

    def progress(text: str) -> None:
        print(f"  {text}", file=sys.stderr, flush=True)

    with tempfile.TemporaryDirectory(prefix="armbridge-reliability-") as tmp:
        root = Path(tmp)
        for sub in ("targets", "fuzz", "config"):
            (root / sub).mkdir()
        targets = run_targets(
            root / "targets",
            args.targets,
            seed=args.seed,
            budget_ms=args.budget_ms,
            progress=progress,
        )
        fuzz = run_mavlink_fuzz(
            root / "fuzz", rounds=args.fuzz_rounds, seed=args.seed, progress=progress
        )
        configs = run_config_fuzz(root / "config", seed=args.seed)
    text = markdown(targets, fuzz, configs, args)
    print(text)
    if args.markdown:
        write_markdown(Path(args.markdown), text)
    failed = (
        targets.pwm_violations
        or targets.unexpected
        or targets.unresolved
        or not targets.control_thread_alive
        or fuzz.servo_commands
        or not fuzz.daemon_alive
        or configs.failures
    )
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
