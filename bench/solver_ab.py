"""The IK kernels of another git revision against this checkout's, in one process.

    .venv/bin/python -m bench.solver_ab [--rev HEAD~1] [--arms hyper,coil] [--poses 2000]
                                        [--modes cold,tight] [--seed 2026] [--dispatcher]
                                        [--markdown FILE]

Two processes running the same solves differ by 10-50 % in CPU time on a shared machine (other
programs' load, the host's), more than most changes to the kernels; here both versions of
``kernels.search`` run in one process, taking turns pose by pose in a shuffled order, so the
machine's drift hits both alike. ``--rev``'s ``companion/ik/kernels.py`` is loaded as a module
of its own (its numba cache kept in a directory named after the file's digest, under the system's
temporary directory) and compiled for the signature the solver calls; its ``layout.py`` must be
this checkout's (the calling convention), or the comparison is refused. :func:`solve` itself is
this checkout's for both: only the compiled search differs, both called as ``solve()`` calls it
(the compiled function; ``--dispatcher``: ``--rev``'s through numba's dispatcher, which with
``--rev HEAD`` measures the dispatcher alone).

Modes: ``cold``, every solve right after an rtb ``ik_LM`` call on the same pose and
:func:`bench.solver.judge` of a zero joint vector (what ``bench.solver``'s interleaved tables run
between two solves of ours); ``tight``, each version's solves back to back, in blocks of every
pose, three rounds in a shuffled order. Per arm and mode: median and p99 of thread CPU time per
solve, their ratio (this checkout / ``--rev``), and whether both returned the same joints, bit
for bit, on every pose (they must: a change of the kernels' code that changes results is not
what this compares).
"""

from __future__ import annotations

import argparse
import gc
import hashlib
import importlib.util
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np

from bench.report import md_table, write_markdown
from bench.solver import ARMS, judge, load_arm, prepare_rtb, random_targets, rtb_robot
from companion.ik import aot, solver, warm_up

_ROOT = Path(__file__).resolve().parent.parent


def _git_show(rev: str, path: str) -> bytes:
    return subprocess.run(
        ["git", "show", f"{rev}:{path}"], cwd=_ROOT, check=True, capture_output=True
    ).stdout


def kernels_of(rev: str) -> ModuleType:
    """``rev``'s ``companion/ik/kernels.py`` imported as a module of its own, its ``search``
    compiled for the solver's signature."""
    if _git_show(rev, "companion/ik/layout.py") != (_ROOT / "companion/ik/layout.py").read_bytes():
        raise SystemExit(f"{rev}'s companion/ik/layout.py differs from this checkout's")
    source = _git_show(rev, "companion/ik/kernels.py")
    digest = hashlib.sha256(source).hexdigest()[:16]
    directory = Path(tempfile.gettempdir()) / "armbridge-solver-ab" / digest
    directory.mkdir(parents=True, exist_ok=True)
    name = f"kernels_{digest}"
    path = directory / f"{name}.py"
    if not path.exists() or path.read_bytes() != source:
        path.write_bytes(source)
    spec = importlib.util.spec_from_file_location(name, path)
    if spec is None or spec.loader is None:
        raise SystemExit(f"cannot import {path}")
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    module.search.compile(aot.SEARCH_SIGNATURE)
    return module


def compare(
    name: str, searches: dict[str, Any], poses: int, seed: int, mode: str
) -> dict[str, Any]:
    arm = load_arm(name)
    targets = random_targets(arm, poses, np.random.default_rng([seed, ARMS.index(name)]))
    ets = rtb_robot(name, arm).ets()
    rtb_calls = [prepare_rtb(arm, ets, t, seed + k) for k, t in enumerate(targets)]
    zero = np.zeros(arm.dof)
    labels = list(searches)
    order = np.random.default_rng(seed)
    if mode == "tight":
        turns = [
            (k, i)
            for _ in range(3)
            for i in order.permutation(len(labels))
            for k in range(len(targets))
        ]
    else:
        turns = [(k, i) for k in range(len(targets)) for i in order.permutation(len(labels))]
    cpu: dict[str, list[float]] = {v: [] for v in labels}
    joints: dict[str, dict[int, tuple[float, ...]]] = {v: {} for v in labels}
    same = True
    for label in labels:  # the workspace made before the clock starts
        solver._search = searches[label]
        solver.solve(arm, targets[0], seed=0)
    gc.collect()
    gc.freeze()
    gc.disable()
    try:
        for k, i in turns:
            label = labels[i]
            solver._search = searches[label]
            if mode == "cold":
                rtb_calls[k]()
                judge(arm, targets[k], zero)
            c = time.thread_time()
            res = solver.solve(arm, targets[k], budget_ms=20.0, seed=seed + k)
            cpu[label].append((time.thread_time() - c) * 1e3)
            if joints[label].setdefault(k, res.q) != res.q:
                same = False
    finally:
        gc.enable()
        gc.unfreeze()
        solver._search = searches["this checkout"]
    same = same and joints[labels[0]] == joints[labels[1]]
    a, b = (np.asarray(cpu[v]) for v in labels)
    return {
        "arm": name,
        "mode": mode,
        "solves each": len(a),
        f"{labels[0]} cpu med": float(np.median(a)),
        f"{labels[0]} cpu p99": float(np.percentile(a, 99)),
        f"{labels[1]} cpu med": float(np.median(b)),
        f"{labels[1]} cpu p99": float(np.percentile(b, 99)),
        "med ratio": float(np.median(b) / np.median(a)),
        "p99 ratio": float(np.percentile(b, 99) / np.percentile(a, 99)),
        "same joints": same,
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--rev", default="HEAD~1")
    parser.add_argument("--arms", default="hyper,coil,ball,hyper3d,cobra600,planar3,kr5,al5d")
    parser.add_argument("--poses", type=int, default=2000)
    parser.add_argument("--modes", default="cold,tight")
    parser.add_argument("--seed", type=int, default=2026)
    parser.add_argument(
        "--dispatcher",
        action="store_true",
        help="call --rev's search through numba's dispatcher (which looks up the type of every "
        "argument at every call), not the compiled function solve() calls",
    )
    parser.add_argument("--markdown", type=Path)
    args = parser.parse_args(argv)
    for n in args.arms.split(","):
        if n not in ARMS:
            parser.error(f"--arms: {n!r} is not one of {', '.join(ARMS)}")
    for m in args.modes.split(","):
        if m not in ("cold", "tight"):
            parser.error(f"--modes: {m!r} is not cold or tight")
    warm_up()
    rev = subprocess.run(
        ["git", "rev-parse", "--short", args.rev], cwd=_ROOT, check=True, capture_output=True
    )
    label = f"{args.rev} ({rev.stdout.decode().strip()})"
    other = kernels_of(args.rev).search
    if args.dispatcher:
        label += " via numba's dispatcher"
    else:
        other = other.compile(aot.SEARCH_SIGNATURE)  # the compiled function, as solve() calls
    searches = {label: other, "this checkout": solver._search}
    rows = []
    for mode in args.modes.split(","):
        for n in args.arms.split(","):
            rows.append(compare(n, searches, args.poses, args.seed, mode))
            print(rows[-1], flush=True)
    keys = list(rows[0])
    text = "\n".join(
        [
            f"# IK kernels: this checkout against {label} (bench/solver_ab.py)",
            "",
            f"- kernels of this checkout: {solver.kernels_origin()}",
            "- thread CPU time per solve, ms; ratio = this checkout / the other",
            "",
            *md_table(
                keys,
                [[r[k] for k in keys] for r in rows],
                cell=lambda v: f"{v:.3g}" if isinstance(v, float) else str(v),
            ),
        ]
    )
    print(text)
    if args.markdown:
        write_markdown(args.markdown, text + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
