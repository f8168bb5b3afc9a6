"""Differential evolution as the papers describe it (Storn & Price; papers §4.1, Table 4).

Mutations and crossovers are registries of plain functions with one signature each, and take
their random draws as arguments, so one generation can be checked exactly on a hand-built
population:

* mutation ``(pop (NP, n), i_best, r (NP, k), a (NP,), params) -> donors (NP, n)``, where ``r``
  holds ``k`` distinct random indices per row, none equal to the row's own index, and ``a`` one
  uniform draw per row (used by ``either-or``);
* crossover ``(target (NP, n), donor (NP, n), u (NP, n), h (NP,), Cr) -> trial (NP, n)``, where
  ``u`` are uniform draws and ``h`` a random coordinate per row.

Trials are clamped into the bounds right after they are made (papers §4) — or, with
``boundary=Boundary.WRAP``, wrapped (joints without limits: angles modulo one turn), or re-drawn
(``Boundary.REDRAW``, which draws from the solver's generator) — and selection is greedy
one-to-one: a trial replaces its target when its cost is not worse.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TypeVar

import numpy as np
from numpy.typing import NDArray

from companion.kinematics import FloatArray
from companion.papers.base import (
    DEFAULT_CLOCK,
    Boundary,
    Clock,
    PopulationSolver,
    Problem,
    SolverResult,
    run,
)
from companion.papers.constants import DE_CR, DE_F, DE_GENERATIONS, DE_POP_SIZE

IntArray = NDArray[np.intp]
_T = TypeVar("_T")


@dataclass(frozen=True)
class DEParams:
    """Scalar settings. Defaults are the papers' Table 4 (F = 0.9, Cr = 0.95).

    ``p_f`` and ``K`` belong to ``either-or`` (rand/1 with probability ``p_f``, else the
    rand/2-like recombination with factor ``K``); the papers give no values, so we use Price's
    usual ``p_f = 0.5`` and ``K = 0.5·(F + 1)``.
    """

    F: float = DE_F
    Cr: float = DE_CR
    p_f: float = 0.5
    K: float | None = None

    def __post_init__(self) -> None:
        if self.K is None:
            object.__setattr__(self, "K", 0.5 * (self.F + 1.0))
        for name, lo, hi in (("F", 0.0, 2.0), ("Cr", 0.0, 1.0), ("p_f", 0.0, 1.0), ("K", 0.0, 2.0)):
            value = getattr(self, name)
            if not (np.isfinite(value) and lo <= value <= hi):
                raise ValueError(f"{name}={value!r} outside [{lo:g}, {hi:g}]")


MutationFn = Callable[[FloatArray, int, IntArray, FloatArray, DEParams], FloatArray]
CrossoverFn = Callable[[FloatArray, FloatArray, FloatArray, IntArray, float], FloatArray]


@dataclass(frozen=True)
class Mutation:
    """A mutation strategy: how many distinct random indices it needs, and the donor formula."""

    n_random: int
    donor: MutationFn


def _rand_1(pop: FloatArray, i_best: int, r: IntArray, a: FloatArray, p: DEParams) -> FloatArray:
    # DE/rand/1: v = Θ_r1 + F·(Θ_r2 − Θ_r3)
    return pop[r[:, 0]] + p.F * (pop[r[:, 1]] - pop[r[:, 2]])


def _best_2(pop: FloatArray, i_best: int, r: IntArray, a: FloatArray, p: DEParams) -> FloatArray:
    # DE/best/2: v = Θ_best + F·(Θ_r1 − Θ_r2) + F·(Θ_r3 − Θ_r4)
    return pop[i_best] + p.F * (pop[r[:, 0]] - pop[r[:, 1]]) + p.F * (pop[r[:, 2]] - pop[r[:, 3]])


def _current_to_best_1(
    pop: FloatArray, i_best: int, r: IntArray, a: FloatArray, p: DEParams
) -> FloatArray:
    # DE/current-to-best/1: v = Θ_i + F·(Θ_best − Θ_i) + F·(Θ_r1 − Θ_r2)
    return pop + p.F * (pop[i_best] - pop) + p.F * (pop[r[:, 0]] - pop[r[:, 1]])


def _either_or(pop: FloatArray, i_best: int, r: IntArray, a: FloatArray, p: DEParams) -> FloatArray:
    # if a < p_f: DE/rand/1; else v = Θ_r1 + K·(Θ_r2 − Θ_r1 + Θ_r3 − Θ_r1)
    x1, x2, x3 = pop[r[:, 0]], pop[r[:, 1]], pop[r[:, 2]]
    rand_1 = x1 + p.F * (x2 - x3)
    assert p.K is not None  # DEParams.__post_init__ sets it
    recombined = x1 + p.K * (x2 - x1 + x3 - x1)
    return np.where((a < p.p_f)[:, None], rand_1, recombined)


MUTATIONS: dict[str, Mutation] = {
    "rand/1": Mutation(3, _rand_1),
    "best/2": Mutation(4, _best_2),
    "current-to-best/1": Mutation(2, _current_to_best_1),
    "either-or": Mutation(3, _either_or),
}


def _binomial(
    target: FloatArray, donor: FloatArray, u: FloatArray, h: IntArray, cr: float
) -> FloatArray:
    # μ_ij = v_ij if j = h_i or u_ij ≤ Cr, else Θ_ij
    take = u <= cr
    take[np.arange(target.shape[0]), h] = True
    return np.where(take, donor, target)


def _exponential(
    target: FloatArray, donor: FloatArray, u: FloatArray, h: IntArray, cr: float
) -> FloatArray:
    # Copy L consecutive coordinates from h on, circularly: L = 1, then L += 1 while
    # u_i,L ≤ Cr and L < n (u[:, 0] is unused so that both crossovers take the same draws).
    n = target.shape[1]
    run_length = 1 + np.cumprod(u[:, 1:] <= cr, axis=1).sum(axis=1)
    position = (np.arange(n)[None, :] - h[:, None]) % n
    return np.where(position < run_length[:, None], donor, target)


CROSSOVERS: dict[str, CrossoverFn] = {
    "binomial": _binomial,
    "exponential": _exponential,
}


def distinct_indices(rng: np.random.Generator, pop_size: int, k: int) -> IntArray:
    """For each row i, ``k`` distinct indices from ``range(pop_size)``, none equal to ``i``."""
    picks = np.argsort(rng.random((pop_size, pop_size - 1)), axis=1)[:, :k]
    return picks + (picks >= np.arange(pop_size)[:, None])


def _lookup(registry: dict[str, _T], kind: str, name: str) -> _T:
    try:
        return registry[name]
    except KeyError:
        raise ValueError(f"unknown {kind} {name!r}; valid: {', '.join(registry)}") from None


class DifferentialEvolution(PopulationSolver):
    """A DE population over ``problem``'s box; ``step()`` runs one generation."""

    def __init__(
        self,
        problem: Problem,
        *,
        pop_size: int = 12,
        mutation: str = "rand/1",
        crossover: str = "binomial",
        params: DEParams | None = None,
        rng: np.random.Generator | int | None = None,
        initial: FloatArray | None = None,
        boundary: Boundary = Boundary.CLAMP,
    ) -> None:
        self.mutation = _lookup(MUTATIONS, "mutation", mutation)
        self.crossover = _lookup(CROSSOVERS, "crossover", crossover)
        if pop_size < self.mutation.n_random + 1:
            raise ValueError(
                f"pop_size={pop_size} too small for mutation {mutation!r}: "
                f"needs at least {self.mutation.n_random + 1}"
            )
        self.params = params or DEParams()
        super().__init__(problem, pop_size, rng, initial, boundary)

    def trials(self, r: IntArray, a: FloatArray, u: FloatArray, h: IntArray) -> FloatArray:
        """Mutation, crossover and the boundary rule for given random draws (no evaluation;
        with ``Boundary.REDRAW`` the re-drawn coordinates come from the solver's generator)."""
        donors = self.mutation.donor(self.pop, self.best_index, r, a, self.params)
        trial = self.crossover(self.pop, donors, u, h, self.params.Cr)
        return self.bound(trial)

    def select(self, trials: FloatArray) -> None:
        """Evaluate ``trials`` and keep each one that is not worse than its target."""
        trial_cost = np.asarray(self.problem.cost(trials), float)
        keep = trial_cost <= self.cost
        self.pop[keep] = trials[keep]
        self.cost[keep] = trial_cost[keep]
        self.evaluations += trials.shape[0]
        self.iteration += 1

    def step(self) -> None:
        pop_size, n = map(int, self.pop.shape)
        r = distinct_indices(self.rng, pop_size, self.mutation.n_random)
        a = self.rng.random(pop_size)
        u = self.rng.random((pop_size, n))
        h = self.rng.integers(0, n, pop_size)
        self.select(self.trials(r, a, u, h))


def differential_evolution(
    problem: Problem,
    *,
    pop_size: int = DE_POP_SIZE,
    generations: int = DE_GENERATIONS,
    F: float = DE_F,
    Cr: float = DE_CR,
    mutation: str = "rand/1",
    crossover: str = "binomial",
    p_f: float = 0.5,
    K: float | None = None,
    seed: int | np.random.Generator | None = None,
    tol: float | None = None,
    budget_s: float | None = None,
    clock: Clock = DEFAULT_CLOCK,
    initial: FloatArray | None = None,
    boundary: Boundary = Boundary.CLAMP,
) -> SolverResult:
    """Minimise ``problem`` with DE. Defaults are the papers' choice (Table 4/5 test 9:
    rand/1/bin, F 0.9, Cr 0.95, NP 12, 400 generations, trials clamped into the box).

    Stops at ``generations``, when the best cost ≤ ``tol``, or when ``budget_s`` seconds on
    ``clock`` have passed since the call began — checked between generations.
    """
    started_at = clock()
    solver = DifferentialEvolution(
        problem,
        pop_size=pop_size,
        mutation=mutation,
        crossover=crossover,
        params=DEParams(F=F, Cr=Cr, p_f=p_f, K=K),
        rng=seed,
        initial=initial,
        boundary=boundary,
    )
    return run(
        solver,
        max_iterations=generations,
        tol=tol,
        budget_s=budget_s,
        clock=clock,
        started_at=started_at,
    )
