"""Harmony search (Geem, Kim & Loganathan 2001), as paper 004 uses it, over a box.

One :meth:`HarmonySearch.step` is **one improvisation**: one new harmony, one evaluation.
For each coordinate ``j`` of the new harmony ``x'``:

1. with probability HMCR, memory consideration: ``x'_j`` is coordinate ``j`` of a harmony drawn
   uniformly from the memory (a fresh row for every coordinate); then, with probability
   ``PAR(k)``, pitch adjustment: ``x'_j += bw_j · u``, ``u`` uniform in [−1, 1];
2. otherwise random selection: ``x'_j`` uniform in ``[lower_j, upper_j]``;
3. ``x'`` is clamped into the box.

``x'`` replaces the worst harmony in memory if its cost is lower (paper 004, step 5).
``PAR`` rises linearly, ``PAR(k) = PAR_min + (PAR_max − PAR_min)·k / K`` for improvisation
``k = 0 … K−1`` of a run of ``K`` (paper 004 eq. 6, whose printed form misplaces the brackets;
Mahdavi et al. 2007 give this form). The bandwidth ``bw`` is constant, a fraction of each
coordinate's range (paper 004 gives neither HMCR nor bw; 0.9 and a few % are the usual values).

All random draws of one improvisation are taken in a fixed order and passed to
:meth:`HarmonySearch.improvise`, so one improvisation can be checked exactly by hand.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from companion.kinematics import FloatArray
from companion.papers.base import (
    DEFAULT_CLOCK,
    Clock,
    PopulationSolver,
    Problem,
    SolverResult,
    run,
)

# Paper 004 §4: harmony memory of 50 rows, PAR from 0.3 to 0.95, 10⁴ iterations.
PAPER_MEMORY_SIZE = 50
PAPER_PAR_MIN = 0.3
PAPER_PAR_MAX = 0.95
PAPER_ITERATIONS = 10_000
# Not given by the paper: the customary values.
DEFAULT_HMCR = 0.9
DEFAULT_BANDWIDTH_FRAC = 0.01


def _check_unit(name: str, value: float) -> None:
    if not (np.isfinite(value) and 0.0 <= value <= 1.0):
        raise ValueError(f"{name}={value!r} outside [0, 1]")


class HarmonySearch(PopulationSolver):
    """A harmony memory over ``problem``'s box; ``step()`` is one improvisation.

    ``iterations`` is the run length ``K`` the PAR schedule is spread over; stepping beyond it
    keeps ``PAR = PAR_max``.
    """

    def __init__(
        self,
        problem: Problem,
        *,
        memory_size: int = PAPER_MEMORY_SIZE,
        hmcr: float = DEFAULT_HMCR,
        par_min: float = PAPER_PAR_MIN,
        par_max: float = PAPER_PAR_MAX,
        bandwidth_frac: float = DEFAULT_BANDWIDTH_FRAC,
        iterations: int = PAPER_ITERATIONS,
        rng: np.random.Generator | int | None = None,
        initial: FloatArray | None = None,
    ) -> None:
        if isinstance(memory_size, bool) or not isinstance(memory_size, int | np.integer):
            raise ValueError(f"memory_size={memory_size!r} must be an integer >= 1")
        if memory_size < 1:
            raise ValueError(f"memory_size={memory_size} outside [1, ∞)")
        for name, value in (("hmcr", hmcr), ("par_min", par_min), ("par_max", par_max)):
            _check_unit(name, value)
        if par_min > par_max:
            raise ValueError(f"par_min={par_min!r} must be <= par_max={par_max!r}")
        if not (np.isfinite(bandwidth_frac) and 0.0 < bandwidth_frac <= 1.0):
            raise ValueError(f"bandwidth_frac={bandwidth_frac!r} outside (0, 1]")
        if iterations < 1:
            raise ValueError(f"iterations={iterations} outside [1, ∞)")
        self.hmcr = float(hmcr)
        self.par_min = float(par_min)
        self.par_max = float(par_max)
        self.iterations_planned = int(iterations)
        super().__init__(problem, memory_size, rng, initial)
        self.bandwidth = bandwidth_frac * (self.upper - self.lower)

    @property
    def memory(self) -> FloatArray:
        """The harmony memory: the population, one harmony per row."""
        return self.pop

    @property
    def par(self) -> float:
        """Pitch-adjusting rate of the next improvisation (linear from PAR_min to PAR_max)."""
        frac = min(self.iteration / self.iterations_planned, 1.0)
        return self.par_min + (self.par_max - self.par_min) * frac

    def improvise(
        self,
        consider: FloatArray,
        rows: NDArray[np.intp],
        pitch: FloatArray,
        shift: FloatArray,
        fresh: FloatArray,
    ) -> FloatArray:
        """A new harmony ``(n,)`` from given draws (no evaluation), each of shape ``(n,)``:
        ``consider``, ``pitch``, ``fresh`` uniform in [0, 1), ``rows`` memory rows, ``shift``
        uniform in [−1, 1)."""
        cols = np.arange(self.lower.size)
        from_memory = self.memory[rows, cols]
        adjusted = from_memory + np.where(pitch < self.par, self.bandwidth * shift, 0.0)
        random = self.lower + fresh * (self.upper - self.lower)
        return np.clip(np.where(consider < self.hmcr, adjusted, random), self.lower, self.upper)

    def update(self, harmony: FloatArray) -> bool:
        """Evaluate ``harmony`` and let it replace the worst one if it is better; count one
        iteration. Returns whether it was accepted."""
        new_cost = float(np.asarray(self.problem.cost(harmony[None, :]), float)[0])
        self.evaluations += 1
        self.iteration += 1
        worst = int(np.argmax(self.cost))
        if new_cost < self.cost[worst]:
            self.memory[worst] = harmony
            self.cost[worst] = new_cost
            return True
        return False

    def step(self) -> None:
        n = self.lower.size
        consider = self.rng.random(n)
        rows = self.rng.integers(0, self.memory.shape[0], n)
        pitch = self.rng.random(n)
        shift = 2.0 * self.rng.random(n) - 1.0
        fresh = self.rng.random(n)
        self.update(self.improvise(consider, rows, pitch, shift, fresh))


def harmony_search(
    problem: Problem,
    *,
    memory_size: int = PAPER_MEMORY_SIZE,
    iterations: int = PAPER_ITERATIONS,
    hmcr: float = DEFAULT_HMCR,
    par_min: float = PAPER_PAR_MIN,
    par_max: float = PAPER_PAR_MAX,
    bandwidth_frac: float = DEFAULT_BANDWIDTH_FRAC,
    seed: int | np.random.Generator | None = None,
    tol: float | None = None,
    budget_s: float | None = None,
    clock: Clock = DEFAULT_CLOCK,
    initial: FloatArray | None = None,
) -> SolverResult:
    """Minimise ``problem`` with harmony search. Defaults are paper 004's (memory 50, PAR
    0.3 → 0.95, 10⁴ improvisations) plus HMCR 0.9 and a bandwidth of 1 % of each range.

    ``generations`` in the result counts improvisations; ``cost_history[k]`` is the best cost
    after ``k`` of them. Stops at ``iterations``, when the best cost ≤ ``tol``, or when
    ``budget_s`` seconds on ``clock`` have passed (checked between improvisations).
    """
    started_at = clock()
    solver = HarmonySearch(
        problem,
        memory_size=memory_size,
        hmcr=hmcr,
        par_min=par_min,
        par_max=par_max,
        bandwidth_frac=bandwidth_frac,
        iterations=iterations,
        rng=seed,
        initial=initial,
    )
    return run(
        solver,
        max_iterations=iterations,
        tol=tol,
        budget_s=budget_s,
        clock=clock,
        started_at=started_at,
    )
