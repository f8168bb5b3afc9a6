"""What every solver shares: the problem interface, the result type and the stop loop.

A solver is an object with ``step()`` (one generation / one shuffle / one improvisation batch)
and the current best; :func:`run` is the thin loop around it that checks the stop conditions —
tolerance, iteration limit, time budget — in one place, so one step can be tested exactly on a
hand-built population and the deadline logic is written once.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from enum import Enum
from typing import Protocol

import numpy as np

from companion.kinematics import FloatArray

Clock = Callable[[], float]
"""A monotonic clock in seconds; ``time.perf_counter`` by default, a fake one in tests."""


class Problem(Protocol):
    """A box-bounded minimisation problem evaluated on a whole population at once."""

    @property
    def lower(self) -> FloatArray: ...

    @property
    def upper(self) -> FloatArray: ...

    def cost(self, x: FloatArray) -> FloatArray:
        """Cost of each row of ``x`` ``(S, n)``; returns ``(S,)``."""
        ...


class Steppable(Protocol):
    iteration: int
    evaluations: int

    @property
    def best_x(self) -> FloatArray: ...

    @property
    def best_cost(self) -> float: ...

    def step(self) -> None: ...


class Boundary(Enum):
    """What happens to a coordinate that an update puts outside the box ``[lower, upper]``."""

    CLAMP = "clamp"
    """Set it to the nearest edge: the papers' rule (§4: "clamping each dimension within these
    bounds at each iteration immediately after it is updated")."""
    WRAP = "wrap"
    """Periodic coordinates: ``lower + (x − lower) mod (upper − lower)``. For a joint without
    limits and a box of one turn (±π) this is the angle modulo 2π, which is what a free
    revolute joint does."""
    REDRAW = "redraw"
    """Draw it again uniformly in ``[lower, upper]`` (from the solver's generator)."""


def apply_boundary(
    x: FloatArray,
    lower: FloatArray,
    upper: FloatArray,
    boundary: Boundary,
    rng: np.random.Generator,
) -> FloatArray:
    """``x`` (any shape ending in ``n``) brought into the box by ``boundary``. Coordinates
    already inside are returned unchanged, bit for bit, under every rule; ``rng`` is drawn from
    only by ``REDRAW`` and only when some coordinate is outside."""
    x = np.asarray(x, float)
    if boundary is Boundary.CLAMP:
        return np.clip(x, lower, upper)
    outside = (x < lower) | (x > upper)
    if not outside.any():
        return x
    if boundary is Boundary.WRAP:
        wrapped = lower + np.mod(x - lower, upper - lower)
        return np.where(outside, wrapped, x)
    if boundary is Boundary.REDRAW:
        fresh = lower + rng.random(x.shape) * (upper - lower)
        return np.where(outside, fresh, x)
    raise ValueError(f"boundary={boundary!r} is not one of {[b.value for b in Boundary]}")


def check_boundary(boundary: Boundary) -> Boundary:
    if not isinstance(boundary, Boundary):
        raise ValueError(f"boundary={boundary!r} is not one of {[b.value for b in Boundary]}")
    return boundary


class StopReason(Enum):
    """Why a solver stopped. Not converging is a result, not an exception."""

    CONVERGED = "converged"
    """The best cost reached the tolerance."""
    ITERATION_LIMIT = "iteration_limit"
    """The generation (or shuffle, or iteration) limit was used up."""
    DEADLINE = "deadline"
    """The time budget ran out."""


@dataclass(frozen=True, eq=False)
class SolverResult:
    """Outcome of one solver run.

    ``x`` is the best vector found (radians for IK problems), ``cost`` its objective value,
    ``cost_history[k]`` the best cost after ``k`` iterations (``[0]`` is the initial
    population), ``generations`` the iterations run, ``evaluations`` the objective evaluations
    (one per candidate), ``elapsed_s`` the wall time measured on the solver's clock.
    """

    x: FloatArray
    cost: float
    cost_history: FloatArray
    generations: int
    evaluations: int
    elapsed_s: float
    stop_reason: StopReason

    @property
    def converged(self) -> bool:
        return self.stop_reason is StopReason.CONVERGED


def make_rng(seed: int | np.random.Generator | None) -> np.random.Generator:
    """A ``Generator`` from a seed, or the generator itself (never the global ``np.random``)."""
    return np.random.default_rng(seed)


def check_bounds(problem: Problem) -> tuple[FloatArray, FloatArray]:
    lower = np.asarray(problem.lower, float)
    upper = np.asarray(problem.upper, float)
    if lower.shape != upper.shape or lower.ndim != 1 or not np.all(lower < upper):
        raise ValueError(f"problem bounds must satisfy lower < upper, got {lower} and {upper}")
    return lower, upper


def initial_population(
    lower: FloatArray,
    upper: FloatArray,
    pop_size: int,
    rng: np.random.Generator,
    given: FloatArray | None,
) -> FloatArray:
    """Uniform population within the bounds (papers: θ = θ_min + rand·(θ_max − θ_min)),
    or ``given`` checked for shape and clamped into the bounds."""
    if given is None:
        return lower + rng.random((pop_size, lower.size)) * (upper - lower)
    pop = np.array(given, dtype=float)
    if pop.shape != (pop_size, lower.size) or not np.all(np.isfinite(pop)):
        raise ValueError(
            f"initial population must be {pop_size}x{lower.size} finite values, "
            f"got shape {pop.shape}"
        )
    return np.clip(pop, lower, upper)


class PopulationSolver:
    """What DE, MSFLA and HS share: the problem's box, the boundary rule, the RNG, a population
    (one candidate per row, uniform in the box or ``initial`` clamped into it) with its costs,
    and the counters. Subclasses add ``step()`` and bring each update into the box with
    :meth:`bound`."""

    def __init__(
        self,
        problem: Problem,
        pop_size: int,
        rng: np.random.Generator | int | None,
        initial: FloatArray | None,
        boundary: Boundary = Boundary.CLAMP,
    ) -> None:
        self.problem = problem
        self.boundary = check_boundary(boundary)
        self.rng = make_rng(rng)
        self.lower, self.upper = check_bounds(problem)
        self.pop = initial_population(self.lower, self.upper, pop_size, self.rng, initial)
        self.cost = np.asarray(problem.cost(self.pop), float)
        self.evaluations = pop_size
        self.iteration = 0

    def bound(self, x: FloatArray) -> FloatArray:
        """``x`` brought into the box by this solver's boundary rule."""
        return apply_boundary(x, self.lower, self.upper, self.boundary, self.rng)

    @property
    def best_index(self) -> int:
        return int(np.argmin(self.cost))

    @property
    def best_x(self) -> FloatArray:
        return self.pop[self.best_index]

    @property
    def best_cost(self) -> float:
        return float(self.cost[self.best_index])


def run(
    solver: Steppable,
    *,
    max_iterations: int,
    tol: float | None,
    budget_s: float | None,
    clock: Clock,
    started_at: float,
) -> SolverResult:
    """Step ``solver`` until the best cost ≤ ``tol``, ``max_iterations`` steps, or the budget
    (seconds since ``started_at`` on ``clock``) is used up, whichever comes first."""
    if max_iterations < 0:
        raise ValueError(f"max_iterations={max_iterations} must be >= 0")
    if budget_s is not None and not budget_s > 0:
        raise ValueError(f"budget_s={budget_s!r} must be > 0")
    history = [solver.best_cost]
    while True:
        if tol is not None and solver.best_cost <= tol:
            reason = StopReason.CONVERGED
            break
        if solver.iteration >= max_iterations:
            reason = StopReason.ITERATION_LIMIT
            break
        if budget_s is not None and clock() - started_at >= budget_s:
            reason = StopReason.DEADLINE
            break
        solver.step()
        history.append(solver.best_cost)
    return SolverResult(
        x=solver.best_x.copy(),
        cost=float(solver.best_cost),
        cost_history=np.asarray(history),
        generations=solver.iteration,
        evaluations=solver.evaluations,
        elapsed_s=clock() - started_at,
        stop_reason=reason,
    )


DEFAULT_CLOCK: Clock = time.perf_counter
