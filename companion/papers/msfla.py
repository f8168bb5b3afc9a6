"""Modified shuffled frog-leaping (MSFLA), papers §4.2 and Table 6, and the classic SFLA.

Two papers describe it: the DE/MSFLA comparison (§4.2, Tables 6–7) and paper 001, "Obtaining
the kinematics solution of an aerial manipulator using the shuffled frog-leaping algorithm"
(Ibrahim 2018, Vestnik IzhGTU 21(4), DOI 10.22213/2413-1172-2018-4-28-34). Despite its title,
paper 001's body says its algorithm is the MSFLA, with the same settings (its Table 2) and the
same results (its Table 3 is the comparison's Table 7, rounded).

The "modification" is the leap factor ``C_L`` (Table 6: 1.3). The classic SFLA of Eusuff &
Lansey (2003, 2006) is the same loop with ``C_L = 1``; :func:`classic_shuffled_frog_leaping`
offers it by name. (Eusuff & Lansey also evolve a random sub-memeplex of ``q`` frogs; neither
paper mentions one, and here the whole memeplex is used, ``q = n``, for both variants.)

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
iteration costs one batched evaluation of ``m`` frogs plus the fall-backs. A leap that leaves
the box is clamped into it (papers §4), or wrapped or re-drawn (``boundary``, see
:class:`~companion.papers.base.Boundary`).
"""

from __future__ import annotations

import numpy as np

from companion.kinematics import FloatArray
from companion.papers.base import (
    DEFAULT_CLOCK,
    Boundary,
    Clock,
    PopulationSolver,
    Problem,
    SolverResult,
    check_bounds,
    run,
)
from companion.papers.constants import (
    MSFLA_LEAP_FACTOR,
    MSFLA_MEMEPLEXES,
    SFLA_CLASSIC_LEAP_FACTOR,
)


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
        boundary: Boundary = Boundary.CLAMP,
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
        super().__init__(problem, pop_size, rng, initial, boundary)

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
        moved = self.bound(self.pop[frogs] + jump)
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
    boundary: Boundary = Boundary.CLAMP,
) -> SolverResult:
    """Minimise ``problem`` with MSFLA: ``shuffles`` = the papers' iN, ``local_iterations`` = iM,
    ``leap_factor`` = C_L (Table 6: 1.3; 1 is the classic SFLA), ``n_memeplexes`` = m
    (Table 6: 3), ``pop_size`` = NP.

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
        boundary=boundary,
    )
    return run(
        solver,
        max_iterations=shuffles,
        tol=tol,
        budget_s=budget_s,
        clock=clock,
        started_at=started_at,
    )


def classic_shuffled_frog_leaping(
    problem: Problem,
    *,
    pop_size: int = 30,
    n_memeplexes: int = MSFLA_MEMEPLEXES,
    shuffles: int = 90,
    local_iterations: int = 40,
    max_leap: FloatArray | float | None = None,
    seed: int | np.random.Generator | None = None,
    tol: float | None = None,
    budget_s: float | None = None,
    clock: Clock = DEFAULT_CLOCK,
    initial: FloatArray | None = None,
    boundary: Boundary = Boundary.CLAMP,
) -> SolverResult:
    """The classic SFLA (Eusuff & Lansey): :func:`shuffled_frog_leaping` with the leap factor
    ``C_L = 1`` (``D = rand·(Θ_b − Θ_w)``), every other setting and the random draws the same,
    so the same seed gives the same run as ``shuffled_frog_leaping(..., leap_factor=1)``."""
    return shuffled_frog_leaping(
        problem,
        pop_size=pop_size,
        n_memeplexes=n_memeplexes,
        shuffles=shuffles,
        local_iterations=local_iterations,
        leap_factor=SFLA_CLASSIC_LEAP_FACTOR,
        max_leap=max_leap,
        seed=seed,
        tol=tol,
        budget_s=budget_s,
        clock=clock,
        initial=initial,
        boundary=boundary,
    )
