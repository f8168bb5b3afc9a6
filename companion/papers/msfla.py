"""Modified shuffled frog-leaping (MSFLA), papers §4.2 and Table 6.

One :meth:`ShuffledFrogLeaping.step` is one shuffle (the papers' outer loop, ``iN`` of them):

1. rank all frogs, best first;
2. deal them into ``m`` memeplexes: frog ``k + m·(i−1)`` of the ranking goes to memeplex ``k``;
3. ``iM`` times, in every memeplex move only the worst frog ``Θ_w``:
   ``D = C_L · rand · (Θ_b − Θ_w)`` with ``Θ_b`` the memeplex best, each coordinate clipped to
   ``±D_max``, ``Θ_w ← clamp(Θ_w + D)`` if that improves it; otherwise the same leap towards the
   global best ``Θ_g``; otherwise the frog is replaced by a random one (the classic fall-backs of
   Eusuff & Lansey, which the papers leave implicit);
4. the memeplexes are merged back (the next step re-ranks them).

``rand`` is one uniform number per leap, as the papers write it. The papers give no ``D_max``;
ours defaults to half of each coordinate's range. All memeplexes leap together, so each local
iteration costs one batched evaluation of ``m`` frogs plus the fall-backs.
"""

from __future__ import annotations

import numpy as np

from companion.kinematics import FloatArray
from companion.papers.base import (
    DEFAULT_CLOCK,
    Clock,
    PopulationSolver,
    Problem,
    SolverResult,
    check_bounds,
    run,
)
from companion.papers.constants import MSFLA_LEAP_FACTOR, MSFLA_MEMEPLEXES


class ShuffledFrogLeaping(PopulationSolver):
    """A population of ``n_memeplexes · frogs_per_memeplex`` frogs; ``step()`` is one shuffle."""

    def __init__(
        self,
        problem: Problem,
        *,
        pop_size: int = 30,
        n_memeplexes: int = MSFLA_MEMEPLEXES,
        local_iterations: int = 40,
        leap_factor: float = MSFLA_LEAP_FACTOR,
        max_leap: FloatArray | float | None = None,
        rng: np.random.Generator | int | None = None,
        initial: FloatArray | None = None,
    ) -> None:
        if n_memeplexes < 1 or pop_size < 2 * n_memeplexes or pop_size % n_memeplexes:
            raise ValueError(
                f"pop_size={pop_size} must be a multiple of n_memeplexes={n_memeplexes} "
                f"with at least 2 frogs per memeplex"
            )
        if local_iterations < 1:
            raise ValueError(f"local_iterations={local_iterations} must be >= 1")
        if not (np.isfinite(leap_factor) and leap_factor > 0):
            raise ValueError(f"leap_factor={leap_factor!r} must be > 0")
        lower, upper = check_bounds(problem)
        span = upper - lower
        self.max_leap = 0.5 * span if max_leap is None else np.broadcast_to(max_leap, span.shape)
        if not np.all(self.max_leap > 0):
            raise ValueError(f"max_leap={max_leap!r} must be > 0")
        self.n_memeplexes = n_memeplexes
        self.local_iterations = local_iterations
        self.leap_factor = leap_factor
        super().__init__(problem, pop_size, rng, initial)

    def memeplexes(self) -> np.ndarray:
        """Frog indices per memeplex, shape ``(m, n)``: ranked frog ``k + m·i`` → memeplex ``k``."""
        order = np.argsort(self.cost, kind="stable")
        return order.reshape(-1, self.n_memeplexes).T

    def _leap(self, frogs: np.ndarray, towards: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Leap ``frogs`` (indices) towards ``towards`` rows; returns new positions and costs."""
        draw = self.rng.random(frogs.size)[:, None]
        jump = np.clip(
            self.leap_factor * draw * (towards - self.pop[frogs]), -self.max_leap, self.max_leap
        )
        moved = np.clip(self.pop[frogs] + jump, self.lower, self.upper)
        self.evaluations += frogs.size
        return moved, np.asarray(self.problem.cost(moved), float)

    def local_iteration(self, plexes: np.ndarray) -> None:
        """Improve the worst frog of every memeplex once (with the fall-backs)."""
        rows = np.arange(plexes.shape[0])
        plex_cost = self.cost[plexes]
        best = plexes[rows, np.argmin(plex_cost, axis=1)]
        worst = plexes[rows, np.argmax(plex_cost, axis=1)]
        pending = np.arange(worst.size)
        for towards_global in (False, True):
            if pending.size == 0:
                return
            frogs = worst[pending]
            towards = self.best_x if towards_global else self.pop[best[pending]]
            moved, moved_cost = self._leap(frogs, towards)
            better = moved_cost < self.cost[frogs]
            self.pop[frogs[better]] = moved[better]
            self.cost[frogs[better]] = moved_cost[better]
            pending = pending[~better]
        frogs = worst[pending]
        if frogs.size:  # no leap improved these: replace them by random frogs
            fresh = self.lower + self.rng.random((frogs.size, self.lower.size)) * (
                self.upper - self.lower
            )
            self.pop[frogs] = fresh
            self.cost[frogs] = np.asarray(self.problem.cost(fresh), float)
            self.evaluations += frogs.size

    def step(self) -> None:
        plexes = self.memeplexes()
        for _ in range(self.local_iterations):
            self.local_iteration(plexes)
        self.iteration += 1


def shuffled_frog_leaping(
    problem: Problem,
    *,
    pop_size: int = 30,
    n_memeplexes: int = MSFLA_MEMEPLEXES,
    shuffles: int = 90,
    local_iterations: int = 40,
    leap_factor: float = MSFLA_LEAP_FACTOR,
    max_leap: FloatArray | float | None = None,
    seed: int | np.random.Generator | None = None,
    tol: float | None = None,
    budget_s: float | None = None,
    clock: Clock = DEFAULT_CLOCK,
    initial: FloatArray | None = None,
) -> SolverResult:
    """Minimise ``problem`` with MSFLA: ``shuffles`` = the papers' iN, ``local_iterations`` = iM,
    ``leap_factor`` = C_L (Table 6: 1.3), ``n_memeplexes`` = m (Table 6: 3), ``pop_size`` = NP.

    ``generations`` in the result counts shuffles.
    """
    started_at = clock()
    solver = ShuffledFrogLeaping(
        problem,
        pop_size=pop_size,
        n_memeplexes=n_memeplexes,
        local_iterations=local_iterations,
        leap_factor=leap_factor,
        max_leap=max_leap,
        rng=seed,
        initial=initial,
    )
    return run(
        solver,
        max_iterations=shuffles,
        tol=tol,
        budget_s=budget_s,
        clock=clock,
        started_at=started_at,
    )
