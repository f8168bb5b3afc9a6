"""companion.ik.aot, built (seconds of numba and the C compiler): the module solves bit for
bit like the JIT, and a process loads it without numba."""

from __future__ import annotations

import importlib.util
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from companion.ik import aot, kernels, solve, solver, warm_up
from companion.kinematics.arm import Arm, Pose

pytestmark = pytest.mark.slow

#: Both searches bounded by generations alone: a solve preempted past a wall-clock budget would
#: stop at another generation than its twin, and the two would differ for that alone.
UNTIMED = solver.SolverSettings(max_generations=10_000)


@pytest.fixture(scope="module")
def built(tmp_path_factory) -> Path:
    """The module built into a directory of its own (a few seconds: numba compiles, the C
    compiler links; the JIT kernels it calls come from numba's cache when it is warm)."""
    if shutil.which(os.environ.get("CC", "cc")) is None:
        pytest.skip("no C compiler: the ahead-of-time module cannot be built here")
    try:
        return aot.build(tmp_path_factory.mktemp("aot"))
    except aot.AotUnavailable as exc:
        pytest.skip(str(exc))


def test_the_ahead_of_time_module_solves_bit_for_bit_like_the_jit(built, monkeypatch):
    spec = importlib.util.spec_from_file_location(built.name.split(".", 1)[0], built)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    warm_up()
    rng = np.random.default_rng(11)
    for arm in (Arm.default(), Arm.from_package_file("stanford.toml")):  # a prismatic joint
        targets = [Pose.from_matrix(t) for t in arm.fk_batch(arm.random_q_rad(rng, 25))]
        runs = []
        for search, goal_matrix in (
            (kernels.search, kernels.goal_matrix),
            (module.search, module.goal_matrix),
        ):
            monkeypatch.setattr(solver, "_search", search)
            monkeypatch.setattr(solver, "_goal_matrix", goal_matrix)
            runs.append(
                [
                    solve(arm, t, seed=i, budget_ms=None, settings=UNTIMED, **kw)
                    for i, t in enumerate(targets)
                    for kw in ({}, {"mode": solver.TargetMode.POSITION_AXIS})
                ]
            )
        jit, ahead = runs
        assert all(r.converged for r in jit)
        for a, b in zip(jit, ahead, strict=True):
            assert (a.q, a.pos_err_cm, a.ori_err_deg, a.generations, a.lm_iterations) == (
                b.q,
                b.pos_err_cm,
                b.ori_err_deg,
                b.generations,
                b.lm_iterations,
            )


def test_with_the_module_built_the_solver_does_not_import_numba(built):
    code = (
        "import sys\n"
        "from companion import ik\n"
        "ik.warm_up()\n"
        "arm = ik.solver.Arm.default()\n"
        "r = ik.solve(arm, arm.fk([10, 80, 20, 10, 20, 30]), seed=0)\n"
        "print('numba' in sys.modules, ik.kernels_origin(), r.converged)\n"
    )
    env = dict(os.environ, NUMBA_CACHE_DIR=str(built.parent))
    env.pop("ARMBRIDGE_IK_JIT", None)
    out = subprocess.run(
        [sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120
    )
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == ["False", str(built), "True"]
