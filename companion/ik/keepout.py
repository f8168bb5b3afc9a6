"""Solutions that keep clear of the vehicle: :func:`solve_clear`, a hard filter around
:func:`~companion.ik.solver.solve`.

The solver knows nothing of keep-out volumes yet (a cost term that steers away from them comes
later); this filter checks each answer with a :class:`~companion.kinematics.collision.KeepOut`
and, while the budget lasts, asks again from elsewhere: first from ``q_start_deg`` (the warm
start, normally the previous command), then alternately a cold start and a warm start from a
random configuration that is itself clear, each with a fresh seed. An answer is taken only if
the configuration, and (with ``q_start_deg``) the straight joint motion from ``q_start_deg`` to
it (the path the daemon's joint-speed limit steps along), keep the margin; otherwise the target
is refused with the reason of the best attempt (which link comes how close to which volume,
and where along the motion). A ``q_start_deg`` that is itself inside a margin refuses every
motion: the arm is not moved from there by this filter.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from enum import Enum
from typing import Any

import numpy as np

from companion.ik import solver as _solver_module
from companion.ik.solver import IKResult, TargetMode, solve, warm_up
from companion.kinematics import Pose, collision_kernels
from companion.kinematics.collision import Collision, KeepOut

Clock = Callable[[], float]
Solver = Callable[..., IKResult]

#: Random configurations drawn to find clear warm starts (one batch check, ~1 ms).
_CLEAR_STARTS = 64


class ClearVerdict(Enum):
    """What :func:`solve_clear` found. Only CLEAR is an answer to command."""

    CLEAR = "clear"
    """A clear answer that meets the tolerances."""
    COLLIDES = "collides"
    """Answers that meet the tolerances were found, but each puts a link inside a volume's
    margin: the target is refused (``collision`` says which link, which volume)."""
    MOTION_COLLIDES = "motion_collides"
    """Answers that meet the tolerances and are clear were found, but the straight motion from
    ``q_start_deg`` to each crosses a volume's margin: refused."""
    NOT_REACHED = "not_reached"
    """No answer met the tolerances (the target is out of reach, or the budget too short)."""
    DEADLINE = "deadline"
    """The budget ended before a single answer."""


@dataclass(frozen=True)
class ClearResult:
    """Outcome of :func:`solve_clear`.

    ``result`` is the best **clear** answer found (clear configuration and, with
    ``q_start_deg``, clear motion), or None: with CLEAR it meets the tolerances; otherwise it is
    the nearest clear configuration found (``converged`` False), what an arm holding "the best
    it can reach" may go to. ``collision`` is why the best colliding answer was refused (None
    if none collided). ``attempts`` solver calls took ``elapsed_ms`` on the clock.
    """

    verdict: ClearVerdict
    result: IKResult | None
    collision: Collision | None
    attempts: int
    elapsed_ms: float

    @property
    def refused(self) -> bool:
        """True unless a clear answer meets the tolerances."""
        return self.verdict is not ClearVerdict.CLEAR


def _rng(seed: int | np.random.Generator | None) -> np.random.Generator:
    if isinstance(seed, np.random.Generator):
        return seed
    if seed is None or (isinstance(seed, int | np.integer) and not isinstance(seed, bool)):
        return np.random.default_rng(None if seed is None else int(seed) & ((1 << 64) - 1))
    raise ValueError(f"seed={seed!r} must be an int, a numpy Generator or None")


def _better(a: IKResult, b: IKResult | None) -> bool:
    """Converged beats not converged; then the lower cost."""
    if b is None:
        return True
    if a.converged != b.converged:
        return a.converged
    return a.cost < b.cost


def solve_clear(
    keepout: KeepOut,
    target: Pose | Sequence[float],
    *,
    budget_ms: float = 20.0,
    seed: int | np.random.Generator | None = None,
    q_start_deg: Sequence[float] | None = None,
    tol_pos_cm: float = 1e-3,
    tol_ori_deg: float = 1e-3,
    mode: TargetMode = TargetMode.POSE,
    max_attempts: int = 16,
    clock: Clock = time.perf_counter,
    solver: Solver = solve,
    **solve_kwargs: Any,
) -> ClearResult:
    """Solve for ``target`` on ``keepout.arm`` and return only an answer clear of
    ``keepout``'s volumes (and, given ``q_start_deg``, reached from it by a clear straight joint
    motion), within ``budget_ms`` in all and at most ``max_attempts`` solver calls.

    The arguments are :func:`~companion.ik.solver.solve`'s (``solve_kwargs`` passes the rest:
    ``settings``, ``tool_axis``, ``direction``, ``cpu_clock``); ``solver`` is injectable for
    tests. A clear answer that meets the tolerances returns at once (CLEAR); otherwise the
    verdict says why not (:class:`ClearVerdict`), with the nearest clear configuration found
    and the reason of the best colliding answer. Same seed, same inputs → same answer, as long
    as the budget does not cut a solve short.
    """
    if solver is solve and not _solver_module._warmed_up:
        warm_up()  # as solve() does: the budget is never for numba's compiler
    collision_kernels.warm_up()  # nor for loading the keep-out kernel (once per process)
    started = clock()
    if not (isinstance(budget_ms, int | float) and math.isfinite(budget_ms) and budget_ms > 0):
        raise ValueError(f"budget_ms={budget_ms!r} must be a finite number > 0")
    if not (isinstance(max_attempts, int) and max_attempts >= 1):
        raise ValueError(f"max_attempts={max_attempts!r} must be an integer >= 1")
    arm = keepout.arm
    rng = _rng(seed)
    q_start_rad = None
    if q_start_deg is not None:
        q_start = np.asarray(q_start_deg, dtype=float)
        if q_start.shape != (arm.dof,) or not np.all(np.isfinite(q_start)):
            raise ValueError(f"q_start_deg={q_start_deg!r} must be {arm.dof} finite values")
        q_start_rad = arm.q_from_user(q_start)
    deadline = started + budget_ms * 1e-3

    best: IKResult | None = None  # the best clear answer
    refusal: tuple[IKResult, Collision, bool] | None = None  # (attempt, why, motion only)
    clear_starts: np.ndarray | None = None
    attempts = 0
    check_s = 0.0  # the longest the checks of one answer took: kept free of solver time
    floor_s = 0.0  # the shortest a solver call took: no use starting one with less left
    while attempts < max_attempts and (best is None or not best.converged):
        if deadline - clock() - check_s <= 0.0:
            break
        start: Sequence[float] | None
        if attempts == 0:
            start = q_start_deg
        elif attempts % 2 == 1:
            start = None
        else:
            if clear_starts is None:
                drawn = arm.random_q_rad(rng, _CLEAR_STARTS)
                clear_starts = drawn[keepout.clear_mask(drawn)]
            start = (
                None
                if len(clear_starts) == 0
                else arm.q_to_user(clear_starts[rng.integers(len(clear_starts))]).tolist()
            )
        left_s = deadline - clock() - check_s
        if left_s <= floor_s:
            break
        # The first try gets half the budget (a warm start normally converges in a fraction
        # of it); later ones share what is left with the next.
        share_s = left_s / 2 if attempts + 1 < max_attempts else left_s
        calling = clock()
        result = solver(
            arm,
            target,
            budget_ms=share_s * 1e3,
            seed=int(rng.integers(0, 1 << 63)),
            q_start_deg=start,
            tol_pos_cm=tol_pos_cm,
            tol_ori_deg=tol_ori_deg,
            mode=mode,
            **solve_kwargs,
        )
        attempts += 1
        checking = clock()
        took_s = checking - calling
        floor_s = took_s if attempts == 1 else min(floor_s, took_s)
        q = result.q_rad
        why = keepout.check(q)
        motion_only = False
        if why is None and q_start_rad is not None:
            why = keepout.check_motion(q_start_rad, q)
            motion_only = True
        check_s = max(check_s, clock() - checking)
        if why is None:
            if _better(result, best):
                best = result
        elif refusal is None or _better(result, refusal[0]):
            refusal = (result, why, motion_only)
    elapsed_ms = (clock() - started) * 1e3
    why = None if refusal is None else refusal[1]
    if best is not None and best.converged:
        return ClearResult(ClearVerdict.CLEAR, best, None, attempts, elapsed_ms)
    if refusal is not None and refusal[0].converged:
        verdict = ClearVerdict.MOTION_COLLIDES if refusal[2] else ClearVerdict.COLLIDES
    elif attempts == 0:
        verdict = ClearVerdict.DEADLINE
    else:
        verdict = ClearVerdict.NOT_REACHED
    return ClearResult(verdict, best, why, attempts, elapsed_ms)
