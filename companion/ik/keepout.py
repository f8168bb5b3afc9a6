"""Solutions that keep clear of the vehicle: :func:`solve_clear`, a hard check and a cost term
around :func:`~companion.ik.solver.solve`.

**The cost term** (:func:`clearance_penalty`): ``Σ max(0, margin_cm + soft_margin_cm − c)²`` (cm²)
over every (link capsule, volume) pair whose clearance ``c`` is below the hard margin plus a soft
one (:data:`SOFT_MARGIN_CM`, 3 cm), or below the most that pair is ever seen to get if that is
less: it grows with the penetration depth inside a volume and with the shortfall of clearance
outside one. The answer to be returned (clear, meeting the tolerances) is **steered** while it has
a penalty and the budget lasts (:func:`_steer`): a step down the penalty's gradient (central
differences, one batch of ``2n + 1`` configurations), projected onto the null space of the
target's Jacobian rows (position rows for a position target, all six otherwise), so that to first
order the hand stays on the target; then a warm solve from there puts it back on the target
exactly (within the tolerances). A step is kept only if that answer still meets the tolerances and
has a lower penalty; otherwise the step is halved. So an answer moves away from the volumes along
the target's own solution set, as far as the pose allows: a whole-pose target on a 6-joint arm has
no null space (its answers are isolated) and is left as it is; a position target has three joints
of freedom to use. The steered answer is then judged by the hard checks below like any other (the
cost term never lets anything through); if it fails them, the plain answer is returned. Colliding
answers are not steered: pushing one out of a volume took the budget that other solutions use
better (``bench/keepout.py``, ~20 % fewer targets reached clear when they were).

**The hard check**: each answer is checked with a :class:`~companion.kinematics.collision.KeepOut`
and, while the budget lasts, the target is solved again from elsewhere: first from ``q_start_deg``
(the warm start, normally the previous command), then alternately a cold start and a warm start
from a random configuration that is itself clear, each with a fresh seed. An answer is taken only
if the configuration, and (with ``q_start_deg``) the straight joint motion from ``q_start_deg`` to
it (the path the daemon's joint-speed limit steps along), keep the margin; otherwise the target is
refused with the reason of the best attempt (which link comes how close to which volume, and where
along the motion). A ``q_start_deg`` that is itself inside a margin refuses every motion: the arm
is not moved from there by this filter.
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
from companion.kinematics import Pose
from companion.kinematics.collision import Collision, KeepOut
from companion.kinematics.jacobian import geometric_jacobian
from companion.kinematics.rotations import FloatArray

Clock = Callable[[], float]
Solver = Callable[..., IKResult]

#: Random configurations drawn to find clear warm starts (one batch check, ~1 ms).
_CLEAR_STARTS = 64
#: The cost term's soft margin (cm beyond the hard ``KeepOut.margin_cm``): answers whose links
#: come closer than that to a volume are steered away where the target leaves them freedom.
SOFT_MARGIN_CM = 3.0
#: Solver calls (warm, ~0.1 ms each) the steering of one answer may take; the first step moves
#: the joints by up to STEER_STEP_DEG along the projected gradient, 1.5 times more after a kept
#: step (at most STEER_MAX_STEP_DEG), half as much after a refused one.
STEER_CALLS = 12
STEER_STEP_DEG = 10.0
STEER_MAX_STEP_DEG = 30.0
#: Central-difference step of the penalty's gradient (rad; cm for a prismatic joint).
_FD_STEP = 1e-4


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
    refused_answer: IKResult | None = None
    """The best answer refused for a collision (its configuration or its motion), or None."""
    steered: int = 0
    """Steering steps (the cost term) kept over all attempts."""
    steer_calls: int = 0
    """Solver calls the steering made (on top of ``attempts``; at most :data:`STEER_CALLS`
    per answer)."""

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


def clearance_penalty(
    keepout: KeepOut, q: FloatArray, soft_margin_cm: float = SOFT_MARGIN_CM
) -> FloatArray:
    """The cost term for joint vectors ``q`` ``(S, n)`` (joint units): per configuration,
    ``Σ max(0, min(margin_cm + soft_margin_cm, ceiling) − clearance)²`` over every (link
    capsule, volume) pair, in cm² (0: every link keeps the soft margin too); ``ceiling`` is the
    most that pair is ever seen to get (:meth:`KeepOut.clearance_ceiling_cm`): no pair is asked
    for more than it can have."""
    q = np.asarray(q, float)
    if not keepout.volumes or not len(keepout.radii_cm):
        return np.zeros(q.shape[0])
    wanted = np.minimum(keepout.margin_cm + soft_margin_cm, keepout.clearance_ceiling_cm())
    short = np.maximum(wanted - keepout.clearances(q), 0.0)
    return np.asarray((short * short).sum(axis=(1, 2)))


def _task_rows(mode: TargetMode) -> slice:
    """The Jacobian rows a target of ``mode`` holds: position only, or all six (a held axis
    leaves one rotation free, which is left unused: the projection stays conservative)."""
    if mode is TargetMode.POSITION:
        return slice(0, 3)
    if mode in (TargetMode.POSE, TargetMode.POSITION_AXIS):
        return slice(0, 6)
    raise ValueError(f"mode={mode!r} must be a TargetMode")


def _steer_direction(
    keepout: KeepOut, q: FloatArray, rows: slice, soft_margin_cm: float
) -> tuple[float, FloatArray]:
    """The penalty at ``q`` and its descent direction projected onto the null space of the
    task's Jacobian rows (zero where the target leaves no freedom)."""
    n = q.size
    probe = np.repeat(q[None], 2 * n + 1, axis=0)
    eye = np.eye(n) * _FD_STEP
    probe[1 : n + 1] += eye
    probe[n + 1 :] -= eye
    values = clearance_penalty(keepout, probe, soft_margin_cm)
    gradient = (values[1 : n + 1] - values[n + 1 :]) / (2 * _FD_STEP)
    jac = geometric_jacobian(keepout.arm, q[None])[0][rows]
    null = np.eye(n) - np.linalg.pinv(jac, rcond=1e-6) @ jac
    return float(values[0]), -(null @ gradient)


def _steer(
    keepout: KeepOut,
    result: IKResult,
    call: Callable[[Sequence[float], float], IKResult],
    *,
    mode: TargetMode,
    soft_margin_cm: float,
    deadline: float,
    clock: Clock,
    calls_left: int,
) -> tuple[IKResult, int, int]:
    """Move a converged ``result`` down the cost term along the target's solution set (see the
    module docstring). ``call(q_start_deg, budget_ms)`` solves the target warm. Returns the
    steered answer (``result`` itself if no step was kept), the solver calls made and the steps
    kept; stops at ``deadline``, after ``calls_left`` calls or when the penalty is 0."""
    arm = keepout.arm
    rows = _task_rows(mode)
    q = result.q_rad
    if clearance_penalty(keepout, q[None], soft_margin_cm)[0] == 0.0:
        return result, 0, 0  # the common case, one configuration's clearances
    computing = clock()
    penalty, direction = _steer_direction(keepout, q, rows, soft_margin_cm)
    direction_s = clock() - computing  # each kept step computes the next direction
    step_rad = math.radians(STEER_STEP_DEG)
    calls = kept = 0
    while penalty > 0.0 and calls < calls_left and step_rad > 1e-4:
        size = float(np.abs(direction).max())
        if not size > 1e-12:
            break  # no freedom left, or a flat penalty
        left_s = deadline - clock() - 2 * direction_s
        if left_s <= 0.0:
            break
        moved = np.clip(q + direction * (step_rad / size), arm.lower_q, arm.upper_q)
        answer = call(arm.q_to_user(moved).tolist(), left_s * 1e3 / 2)
        calls += 1
        if answer.converged:
            new_q = answer.q_rad
            new_penalty, new_direction = _steer_direction(keepout, new_q, rows, soft_margin_cm)
            if new_penalty < penalty:
                result, q, penalty, direction = answer, new_q, new_penalty, new_direction
                kept += 1
                step_rad = min(step_rad * 1.5, math.radians(STEER_MAX_STEP_DEG))
                continue
        step_rad /= 2
    return result, calls, kept


def _judge(
    keepout: KeepOut, result: IKResult, q_start_rad: FloatArray | None
) -> tuple[Collision | None, bool]:
    """Why ``result`` is refused (None: clear), and whether only its motion is."""
    why = keepout.check(result.q_rad)
    if why is None and q_start_rad is not None:
        return keepout.check_motion(q_start_rad, result.q_rad), True
    return why, False


def _warm_call(
    solver: Solver,
    arm: Any,
    target: Pose | Sequence[float],
    rng: np.random.Generator,
    tol_pos_cm: float,
    tol_ori_deg: float,
    mode: TargetMode,
    solve_kwargs: dict[str, Any],
) -> Callable[[Sequence[float], float], IKResult]:
    """``(q_start_deg, budget_ms) → IKResult``: the target solved warm, a fresh seed each."""

    def call(start_deg: Sequence[float], budget_ms: float) -> IKResult:
        return solver(
            arm,
            target,
            budget_ms=budget_ms,
            seed=int(rng.integers(0, 1 << 63)),
            q_start_deg=start_deg,
            tol_pos_cm=tol_pos_cm,
            tol_ori_deg=tol_ori_deg,
            mode=mode,
            **solve_kwargs,
        )

    return call


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
    soft_margin_cm: float = SOFT_MARGIN_CM,
    clock: Clock = time.perf_counter,
    solver: Solver = solve,
    **solve_kwargs: Any,
) -> ClearResult:
    """Solve for ``target`` on ``keepout.arm`` and return only an answer clear of
    ``keepout``'s volumes (and, given ``q_start_deg``, reached from it by a clear straight joint
    motion), within ``budget_ms`` in all and at most ``max_attempts`` solver calls.

    The arguments are :func:`~companion.ik.solver.solve`'s (``solve_kwargs`` passes the rest:
    ``settings``, ``tool_axis``, ``direction``, ``cpu_clock``); ``solver`` is injectable for
    tests. The clear answer found is steered away from the volumes (the cost term,
    ``soft_margin_cm`` beyond the margin; 0: off) with what is left of the budget. A clear
    answer that meets the tolerances returns at once (CLEAR); otherwise the
    verdict says why not (:class:`ClearVerdict`), with the nearest clear configuration found
    and the reason of the best colliding answer. Same seed, same inputs → same answer, as long
    as the budget does not cut a solve short.
    """
    if solver is solve and not _solver_module._warmed_up:
        warm_up()  # as solve() does: the budget is never for numba's compiler
    # Nor for loading the keep-out kernel (once per process). Imported here: it imports numba,
    # which a process that never checks keep-out (or whose IK kernels were compiled ahead of
    # time) does not need.
    from companion.kinematics import collision_kernels

    collision_kernels.warm_up()
    started = clock()
    if not (isinstance(budget_ms, int | float) and math.isfinite(budget_ms) and budget_ms > 0):
        raise ValueError(f"budget_ms={budget_ms!r} must be a finite number > 0")
    if not (isinstance(max_attempts, int) and max_attempts >= 1):
        raise ValueError(f"max_attempts={max_attempts!r} must be an integer >= 1")
    if not (
        isinstance(soft_margin_cm, int | float)
        and math.isfinite(soft_margin_cm)
        and soft_margin_cm >= 0
    ):
        raise ValueError(f"soft_margin_cm={soft_margin_cm!r} must be a finite number >= 0")
    _task_rows(mode)
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
    steered = steer_calls = 0
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
        took_s = clock() - calling
        floor_s = took_s if attempts == 1 else min(floor_s, took_s)
        checking = clock()
        why, motion_only = _judge(keepout, result, q_start_rad)
        check_s = max(check_s, clock() - checking)
        if why is None and result.converged and soft_margin_cm > 0:
            # The answer to return: steered away from the volumes with what is left (colliding
            # answers are not steered: the budget goes to other solutions, which measured
            # better than pushing one out of a volume).
            moved, steer_calls, steered = _steer(
                keepout,
                result,
                _warm_call(solver, arm, target, rng, tol_pos_cm, tol_ori_deg, mode, solve_kwargs),
                mode=mode,
                soft_margin_cm=soft_margin_cm,
                deadline=deadline - 2 * check_s,  # its answer is checked again
                clock=clock,
                calls_left=STEER_CALLS,
            )
            if moved is not result and _judge(keepout, moved, q_start_rad)[0] is None:
                result = moved  # else the plain answer, which is clear
        if why is None:
            if _better(result, best):
                best = result
        elif refusal is None or _better(result, refusal[0]):
            refusal = (result, why, motion_only)
    elapsed_ms = (clock() - started) * 1e3
    why = None if refusal is None else refusal[1]
    refused = None if refusal is None else refusal[0]
    if best is not None and best.converged:
        return ClearResult(
            ClearVerdict.CLEAR, best, None, attempts, elapsed_ms, None, steered, steer_calls
        )
    if refusal is not None and refusal[0].converged:
        verdict = ClearVerdict.MOTION_COLLIDES if refusal[2] else ClearVerdict.COLLIDES
    elif attempts == 0:
        verdict = ClearVerdict.DEADLINE
    else:
        verdict = ClearVerdict.NOT_REACHED
    return ClearResult(verdict, best, why, attempts, elapsed_ms, refused, steered, steer_calls)
