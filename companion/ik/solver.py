"""Deadline-bounded, warm-startable inverse kinematics: :func:`solve`.

This is where the time budget is enforced. The search itself is compiled
(:mod:`companion.ik.kernels`); three methods share it (:data:`METHODS`, the daemon's
``[solver] method``, ``armbridge solve --method``):

* ``"restarts"``, the default: multi-start damped least squares. Draw NP = 4 joint vectors
  uniformly within the limits (at every restart after the first, one of them a corner of the
  joint box: targets reached with joints at their limits converge from there), run
  Levenberg–Marquardt (LM, analytic geometric Jacobian, clamped to the limits) from the best of
  them; if it does not reach the tolerances, draw 4 anew and run LM again, until it does or the
  budget is spent. The best configuration seen is kept throughout. No DE generation runs
  (``stall_generations`` 0: every generation is a restart). LM runs at most 30 steps from a
  start, and abandons it early for a fresh draw when it stops making progress: its cost
  (cm² + deg²) not below 0.3 × what it was 4 steps before while above ``lm_near_cost`` (400),
  or not below 0.9 × once within it (near the target slow progress is more often a solution
  near a singularity, approached linearly, than a local minimum).
* ``"memetic"``: memetic DE, DE rand/1/bin generations (NP 6, F 0.5, Cr 0.3) each followed by
  LM on the best individual not yet refined to a standstill, written back into the population;
  the population is drawn anew after 2 generations in a row that did not improve its best.
* ``"de"``: the papers' DE with no least squares (rand/1/bin, Table 4's F 0.9 and Cr 0.95, NP
  12), with a restart after 50 generations without improvement.

Why the default is "restarts" and not DE: measured on the tuning arms and seeds (``bench/
solver.py``: seeds 0–99; paper arm, Puma560, UR5, Panda, Stanford, Orion5), every setting that
lets DE generations run between restarts did more work than restarting. Over NP 6–12, 1–4
generations between restarts, F 0.5–0.9 and Cr 0.3–0.95, the median CPU time per solve was
−8 % to +26 % of restarts' and p99 −26 % to +200 %, the mean always higher; their DE
generations lowered the population's best cost in 1–4 % of solves
(``IKResult.de_improvements``). "memetic" is the least bad of them: median +0–21 %, p99
−4 % to +39 %. One DE generation after a failed first LM (NP 4), then restarts,
spends that generation for little as well: restarting right away is 1–8 % faster at the
median and up to 42 % at p99. On random reachable poses 3 in 4 solves or more end in the
first LM run. On the bench (``docs/measurements/solver.md``: rtb's whole DH zoo, seed 2026,
the three methods and roboticstoolbox's ``ik_LM`` taking turns pose by pose; two runs)
memetic's median was −2 % to +15 % of restarts' (above it on 23 and 24 of the 25 arms)
and its DE generations lowered the best cost in 0–8 % of solves (3 % or less on every arm of 3
joints or more); the papers' DE took 5–45× rtb's time and missed the 20 ms budget on up to
17 % of poses.

This module runs the search in chunks of generations (one compiled call each,
:func:`kernels.search`), reading the clocks between chunks; the first call also initialises
the population (for "restarts": the first draw and its LM run). Two limits bound it: the budget
(``budget_ms``) counts this thread's CPU time, so time other processes hold the CPU is not
taken from the search; the ceiling (``ceiling_ms``, by default :data:`CEILING_PER_BUDGET` × the
budget) bounds the call in wall time however little CPU it got. It stops:

* as soon as the hand is within ``tol_pos_cm`` and ``tol_ori_deg`` of the target (CONVERGED);
* before a chunk that is predicted not to finish inside the budget (DEADLINE), or before the
  ceiling (CEILING: the budget was not spent, the machine was busy). Each prediction is a
  moving average of a generation's CPU time (for the budget; each sample capped at 4× the
  average, as a restart or a full LM run costs more than most) or wall time (for the ceiling).
  The averages carry over from call to call (same arm, settings, thread and clocks); the first
  call with a pair of clocks calibrates them on the initialisation, counted in CPU time if that
  is less. A chunk is never predicted to take more than half of the budget, or of the time to
  the ceiling, left; so the ceiling holds unless one generation takes twice the average and
  more, or the machine does not let this thread run at all. (A call whose first compiled call
  does not converge counts that call's CPU time as its wall time, an upper bound: the CPU
  clock is not read before it, to keep a system call off every solve.)
* at ``settings.max_generations`` (ITERATION_LIMIT).

With ``budget_ms=None`` there is no deadline (and no ceiling unless one is given): the search is
bounded by ``settings.max_generations`` alone, so what it returns depends on the inputs and the
seed, never on how busy the machine is.

Any serial arm :class:`~companion.kinematics.arm.Arm` describes works (2–7 joints or more,
revolute and prismatic, base and tool transforms, reversed joints, DH or URDF). At this API a
prismatic joint is in cm wherever a revolute one is in degrees (``q_start_deg``, ``q_deg``).
What must be met is chosen per call (:class:`TargetMode`): the whole pose, the position, or the
position and a pointing direction.

It always returns the best configuration found, within the joint limits, with both errors.
A target it cannot reach (the papers' G is one) comes back with ``converged=False``; that is
never an exception.

Warm start: ``q_start_deg`` (normally the previous command) is in the first population (with
the default NP 4 the only individual around it; a larger one adds a third within
``settings.warm_spread_deg``), so the first LM run starts from it whenever it is the best of
the draws (a small move of the target), and a minimal-movement term
(``settings.movement_weight``) keeps consecutive solutions on the same elbow/wrist branch.

Importing this module does no work and does not import numba. :func:`warm_up` loads the
kernels: the ahead-of-time module (:mod:`companion.ik.aot`: a plain extension module, no numba
at run time) where ``python -m companion.ik`` has built an up-to-date one (the board
install in ``docs/board.md`` does, with a C compiler); otherwise numba's JIT, which compiles
them for the same signatures (about 20 s of CPU on the 2-core development machine) and caches
them on disk, so later processes load them (numba's import and first call, 0.5–0.8 s). Either
way a solve calls the compiled functions directly, not through numba's dispatcher. The daemon
calls :func:`warm_up` before it reports READY; a first :func:`solve` without it calls it before
its clock starts. So no budget ever pays for loading or compiling.
"""

from __future__ import annotations

import logging
import math
import os
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from enum import Enum
from typing import Any

import numpy as np

from companion.ik import aot, layout
from companion.ik.layout import (
    F_TOL_ORI,
    F_TOL_POS,
    MODE_AXIS,
    MODE_POSE,
    MODE_POSITION,
    O_COST,
    O_ORI_DEG,
    O_POS_CM,
    O_Q,
    S_DE_GAINS,
    S_EVALUATIONS,
    S_GENERATIONS,
    S_LM_ITERATIONS,
    S_RESTARTS,
    START_GOAL_SET,
    START_HAS_PREV,
    START_NEW,
)
from companion.kinematics import Arm, FloatArray, Pose

log = logging.getLogger(__name__)

Clock = Callable[[], float]
"""A monotonic clock in seconds (``time.perf_counter`` by default; tests pass a fake one)."""

_MASK64 = (1 << 64) - 1


class StopReason(Enum):
    """Why :func:`solve` stopped. Not converging is a result, not an exception."""

    CONVERGED = "converged"
    """The hand is within both tolerances of the target."""
    ITERATION_LIMIT = "iteration_limit"
    """``settings.max_generations`` were run."""
    DEADLINE = "deadline"
    """Another generation would not have finished inside the budget (``budget_ms`` of this
    thread's CPU time)."""
    CEILING = "ceiling"
    """Another generation would not have finished before the wall-clock ceiling
    (``ceiling_ms``): the budget was not spent, other processes held the CPU."""


@dataclass(frozen=True)
class SolverSettings:
    """Settings of the search. The defaults are :data:`METHODS` ``"restarts"``: no DE
    generation at all (``stall_generations`` 0), so ``F``, ``Cr`` and ``stall_gain`` do not
    apply; ``"memetic"`` and ``"de"`` are the DE searches (see ``bench/solver.py`` and
    ``docs/measurements/solver.md`` for how each was chosen)."""

    pop_size: int = 4
    """Population NP: the individuals drawn at each restart (LM starts from their best) and
    DE's population between restarts."""
    F: float = 0.7
    """DE scale factor."""
    Cr: float = 0.7
    """DE crossover probability (binomial)."""
    lm_iterations: int = 30
    """Damped-least-squares steps per refinement of the population's best (at most)."""
    lm_lambda0: float = 0.1
    """Initial Levenberg–Marquardt damping (relative to diag(JᵀJ))."""
    lm_window: int = 4
    """LM gives up when the cost has not dropped below ``lm_progress`` × its value
    ``lm_window`` steps ago (0: never): a start that is not converging hands over to the next
    restart or DE generation."""
    lm_progress: float = 0.3
    """See ``lm_window``."""
    lm_near_cost: float = 400.0
    """Within this cost (cm² + deg²: about 20 cm or 20°) of the target, the window test gives
    up only on a start that stalls (its cost not below 0.9 × what it was): there slow but
    steady progress is more often a solution near a singularity, approached linearly, than a
    local minimum. Targets whose every solution has a wrist near its singularity (UR10, seed
    2026, pose 986: q5 179.3°) otherwise restarted thousands of times (from 40 seeds, 17 ran
    out of a 20 ms budget); with it all 40 converge in the first LM run. Tuning arms and
    seeds: the worst UR5 solve 1.2 ms instead of 6.5 ms, p99 0.9–1.1× elsewhere (a window of
    3 steps and 0.5 was also tried: 0.9–1.0× at p99, but the UR5 tail stayed)."""
    stall_generations: int = 0
    """Generations without progress (see ``stall_gain``) before the population is drawn anew
    (the restart takes the next generation's DE step's place, and LM starts from its best).
    0: every generation is a restart, no DE step ever runs (method ``"restarts"``)."""
    stall_gain: float = 0.0
    """A generation makes progress when it brings the best cost below ``stall_gain`` times
    what it was (0.5: at least halves it; 1: any improvement; 0: none counts)."""
    movement_weight: float = 1.0
    """Warm start: cost per rad² of joint motion from ``q_start`` (pose cost is cm² + deg²)."""
    warm_spread_deg: float = 5.0
    """Warm start: half-width of the uniform noise around ``q_start`` for a third of the pop
    after ``q_start`` itself (with NP 4: none, only ``q_start``)."""
    max_generations: int = 1_000_000
    """Generation limit (the budget normally ends the search first)."""

    def __post_init__(self) -> None:
        checks = (
            ("pop_size", self.pop_size >= 4, ">= 4"),
            ("F", 0.0 < self.F <= 2.0, "in (0, 2]"),
            ("Cr", 0.0 <= self.Cr <= 1.0, "in [0, 1]"),
            ("lm_iterations", self.lm_iterations >= 0, ">= 0"),
            ("lm_lambda0", self.lm_lambda0 > 0.0, "> 0"),
            ("lm_window", self.lm_window >= 0, ">= 0"),
            ("lm_progress", 0.0 < self.lm_progress <= 1.0, "in (0, 1]"),
            ("lm_near_cost", self.lm_near_cost >= 0.0, ">= 0"),
            ("stall_generations", self.stall_generations >= 0, ">= 0"),
            ("stall_gain", 0.0 <= self.stall_gain <= 1.0, "in [0, 1]"),
            ("movement_weight", self.movement_weight >= 0.0, ">= 0"),
            ("warm_spread_deg", self.warm_spread_deg >= 0.0, ">= 0"),
            ("max_generations", self.max_generations >= 0, ">= 0"),
        )
        for name, ok, allowed in checks:
            if not ok:
                raise ValueError(f"SolverSettings.{name}={getattr(self, name)!r} must be {allowed}")


DEFAULT_SETTINGS = SolverSettings()

#: Search methods by name, each the settings it starts from (the daemon's ``solver.method``,
#: ``armbridge solve --method``):
#:
#: * ``"restarts"`` (the default, :data:`DEFAULT_SETTINGS`): multi-start LM. Draw NP = 4
#:   joint vectors uniformly within the limits (one of them, at each restart, a corner of the
#:   joint box), run LM from the best; if it does not converge, draw 4 anew, and again. No DE
#:   generation runs.
#: * ``"memetic"``: memetic DE. DE rand/1/bin generations (NP 6, F 0.5, Cr 0.3) each followed
#:   by LM on the best individual not yet refined to a standstill, the result written back
#:   into the population; the population is drawn anew after 2 generations in a row that did
#:   not improve its best. Tuned on seeds 0–99 of six arms (F, Cr, NP, generations between
#:   restarts; bench/solver.py): the least bad of the DE variants, and still 0–20 % more work
#:   at the median and up to 40 % at p99 than "restarts" (its DE generations lower the best
#:   cost in 1–3 % of solves).
#: * ``"de"``: the papers' DE, no least squares: rand/1/bin with Table 4's F = 0.9 and
#:   Cr = 0.95 and the authors' pick of NP (Table 5, test 9: 12), plus a restart (the
#:   population drawn anew, the best kept aside) after 50 generations in a row that did not
#:   improve the best. Without the restarts 40 % of random reachable poses of the default arm
#:   stall short of the daemon's tolerances (0.01 cm, 0.1°) within 20 ms; with them none (200
#:   poses: median 1.7 ms of CPU, p90 6.5 ms).
METHODS: dict[str, SolverSettings] = {
    "restarts": DEFAULT_SETTINGS,
    "memetic": SolverSettings(pop_size=6, F=0.5, Cr=0.3, stall_generations=2, stall_gain=1.0),
    "de": SolverSettings(
        pop_size=12, F=0.9, Cr=0.95, lm_iterations=0, stall_generations=50, stall_gain=1.0
    ),
}

DEFAULT_METHOD = "restarts"
"""The method :data:`DEFAULT_SETTINGS` are (the daemon's default ``solver.method``)."""

#: Settings a method does not use, refused by :func:`method_settings` with the reason.
_NOT_FOR = {
    "restarts": {
        "F": "restarts runs no DE generation",
        "Cr": "restarts runs no DE generation",
        "stall_generations": "restarts draws the population anew at every generation",
        "stall_gain": "restarts draws the population anew at every generation",
    },
    "memetic": {},
    "de": {"lm_iterations": "de runs no least-squares steps"},
}


def method_settings(method: str = DEFAULT_METHOD, **changes: Any) -> SolverSettings:
    """The settings of search ``method`` (a name in :data:`METHODS`) with ``changes``
    (:class:`SolverSettings` fields) over its own. With no changes, the method's own object:
    :func:`solve` keeps its arrays and estimates from call to call for one settings object.
    A setting the method does not use is refused (``ValueError`` naming it and the method):
    ``F``, ``Cr``, ``stall_generations`` and ``stall_gain`` with ``"restarts"``,
    ``lm_iterations`` above 0 with ``"de"``; ``"memetic"`` and ``"de"`` need
    ``stall_generations`` ≥ 1 (0 is ``"restarts"``)."""
    if method not in METHODS:
        raise ValueError(f"method={method!r} must be one of {', '.join(METHODS)}")
    for name, why in _NOT_FOR[method].items():
        if name in changes and not (name == "lm_iterations" and changes[name] == 0):
            users = [m for m in METHODS if name not in _NOT_FOR[m]]
            raise ValueError(
                f"{name}={changes[name]!r} goes with method {' or '.join(map(repr, users))}: {why}"
            )
    if method != "restarts" and changes.get("stall_generations", 1) < 1:
        raise ValueError(
            f"stall_generations={changes['stall_generations']!r} must be >= 1 with method "
            f"{method!r} (0, a restart at every generation, is method 'restarts')"
        )
    return replace(METHODS[method], **changes) if changes else METHODS[method]


@dataclass(frozen=True)
class IKResult:
    """Outcome of :func:`solve`.

    ``q_deg`` is the best joint vector found, always within the limits, in degrees (cm for a
    prismatic joint); ``q`` the same in joint units (rad, cm). ``pos_err_cm`` and
    ``ori_err_deg`` are its errors; the latter is the angle the target mode checks
    (:class:`TargetMode`: the rotation angle of ``R_goalᵀ·R`` for a whole pose). ``cost`` is
    what the solver minimised: ``pos_err_cm² + ori_err_deg²``. ``elapsed_ms`` is measured on
    the solver's wall clock, from the call to the return: the budget is CPU time, so on a busy
    machine it may exceed ``budget_ms`` (up to the ceiling).
    """

    q_deg: tuple[float, ...]
    pos_err_cm: float
    ori_err_deg: float
    cost: float
    converged: bool
    elapsed_ms: float
    generations: int
    evaluations: int
    lm_iterations: int
    restarts: int
    stop_reason: StopReason
    q: tuple[float, ...] = ()
    de_improvements: int = 0
    """DE generations (not restarts) whose selection lowered the population's best cost: the
    search's DE did measurable work in this solve when it is above 0."""

    @property
    def q_rad(self) -> FloatArray:
        """The joints in joint units: radians (cm for a prismatic joint)."""
        return np.array(self.q) if self.q else np.radians(self.q_deg)


class TargetMode(Enum):
    """What of the target :func:`solve` must meet (per call).

    The result's ``ori_err_deg`` is the angle the mode checks.
    """

    POSE = "pose"
    """Position and orientation; the angle is that of ``R_goalᵀ·R``."""
    POSITION = "position"
    """Position only; the angle is 0 (orientation free)."""
    POSITION_AXIS = "position_axis"
    """Position, and the hand's ``tool_axis`` (hand frame) pointing along a direction (base
    frame); roll about it is free. The angle is that between the axis and the direction."""


@dataclass(frozen=True)
class _ArmArrays:
    frames: FloatArray
    joint_params: FloatArray
    lower: FloatArray
    upper: FloatArray
    to_joint: FloatArray
    """Per joint, degrees → rad (or 1 for a prismatic joint's cm)."""
    to_user: FloatArray


# The daemon solves for one arm over and over: remember the last one. A tuple swapped whole, so
# a reader in another thread never sees one arm paired with another's arrays.
_last_arm: tuple[Arm, _ArmArrays] | None = None

# Set once warm_up() has started (its own solves must not recurse into it).
_warmed_up = False


def kernel_arrays(arm: Arm) -> _ArmArrays:
    """The arm's fixed frames, joint parameters and limits as the compiled kernels take them."""
    global _last_arm
    last = _last_arm
    if last is not None and last[0] is arm:
        return last[1]
    arrays = _build_kernel_arrays(arm)
    _last_arm = (arm, arrays)
    return arrays


def _build_kernel_arrays(arm: Arm) -> _ArmArrays:
    joint_params = np.array(
        [
            [float(j.direction) for j in arm.joints],
            [j.offset for j in arm.joints],
            [1.0 if j.revolute else 0.0 for j in arm.joints],
            # A whole turn within the limits: the kernels wrap such a joint instead of clamping.
            [1.0 if j.revolute and j.upper - j.lower >= 2 * math.pi else 0.0 for j in arm.joints],
            arm.lower_q,
            arm.upper_q,
        ]
    )
    return _ArmArrays(
        frames=np.array(arm.frames_array),
        joint_params=joint_params,
        lower=arm.lower_q.copy(),
        upper=arm.upper_q.copy(),
        to_joint=np.where(arm.revolute, math.pi / 180.0, 1.0),
        to_user=np.where(arm.revolute, 180.0 / math.pi, 1.0),
    )


def _seed_value(seed: int | np.random.Generator | None) -> int:
    """splitmix64 state from a seed (any int), a Generator (advanced by one draw) or entropy."""
    if type(seed) is int:
        return seed & _MASK64
    if seed is None:
        return int.from_bytes(os.urandom(8), "little")
    if isinstance(seed, np.random.Generator):
        return int(seed.integers(0, 1 << 63)) * 2 + int(seed.integers(0, 2))
    if isinstance(seed, int | np.integer) and not isinstance(seed, bool):
        return int(seed) & _MASK64
    raise ValueError(f"seed={seed!r} must be an int, a numpy Generator or None")


def _positive(name: str, value: float) -> float:
    if type(value) is float and 0.0 < value < math.inf:
        return value
    try:
        number = float(value)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name}={value!r} is not a number") from exc
    if not (math.isfinite(number) and number > 0.0):
        raise ValueError(f"{name}={value!r} must be a finite number > 0")
    return number


def _unit(name: str, values: Sequence[float]) -> FloatArray:
    v = np.asarray(values, dtype=float)
    norm = float(np.linalg.norm(v)) if v.shape == (3,) else 0.0
    if not (math.isfinite(norm) and norm > 1e-9):
        raise ValueError(f"{name}={values!r} must be 3 finite numbers, not all zero")
    return v / norm


def _as_pose(target: Pose | Sequence[float]) -> Pose:
    if isinstance(target, Pose):
        return target
    try:
        return Pose.from_sequence(target)
    except TypeError as exc:
        raise ValueError(f"target={target!r} must be a Pose or 6 numbers") from exc


def solve(
    arm: Arm,
    target: Pose | Sequence[float],
    *,
    budget_ms: float | None = 20.0,
    ceiling_ms: float | None = None,
    seed: int | np.random.Generator | None = None,
    q_start_deg: Sequence[float] | None = None,
    tol_pos_cm: float = 1e-3,
    tol_ori_deg: float = 1e-3,
    settings: SolverSettings = DEFAULT_SETTINGS,
    clock: Clock = time.perf_counter,
    cpu_clock: Clock = time.thread_time,
    mode: TargetMode = TargetMode.POSE,
    tool_axis: Sequence[float] = (0.0, 0.0, 1.0),
    direction: Sequence[float] | None = None,
) -> IKResult:
    """Joint angles that put ``arm``'s hand at ``target``, within ``budget_ms`` of CPU time.

    ``target`` is a :class:`Pose` (or 6 numbers: x, y, z in cm; roll, pitch, yaw in degrees).
    ``q_start_deg`` is the joint vector to start from and stay close to (the previous
    command), or None for a cold start; degrees, cm for a prismatic joint. ``seed`` makes the
    search repeatable (same seed, same inputs → same result, as long as the budget doesn't cut
    it short). ``budget_ms=None``: no deadline; the search ends when it converges or after
    ``settings.max_generations`` (pass a small enough one), with the result a budget that did
    not cut it short would give. Bad input raises ``ValueError`` naming the argument.

    ``mode`` (:class:`TargetMode`) says what must be met: the whole pose (default), the
    position only (the target's orientation is ignored), or the position and a pointing
    direction: the hand's ``tool_axis`` (hand frame, default its z axis) must point along
    ``direction`` (base frame; default: the target orientation's ``tool_axis``, i.e.
    ``R_target · tool_axis``), roll about it free. Neither vector needs to be unit length.

    ``budget_ms`` is counted in this thread's CPU time (``cpu_clock``), so time that other
    processes hold the CPU is not taken from the search; ``ceiling_ms`` bounds the call in
    wall time (``clock``) however little CPU it got: the control period of a caller that must
    answer within one. Default: :data:`CEILING_PER_BUDGET` × ``budget_ms`` (none without a
    budget). A ceiling below the budget ends the search first (a thread's CPU time never
    runs ahead of the wall clock). Which of the two ended the search is the stop reason
    (:class:`StopReason` DEADLINE or CEILING). Tests pass fake clocks.

    The first call in a process that has not run :func:`warm_up` runs it first, before the
    clock starts: the budget is for the search, never for numba's compiler.
    """
    if not _warmed_up:
        warm_up()
    started = clock()
    pose = target if type(target) is Pose else _as_pose(target)
    # The common case inline (a Python call costs ~0.06 µs; a fast solve is ~15 µs).
    if type(budget_ms) is float and 0.0 < budget_ms < _INF:
        budget_s = budget_ms * 1e-3
    elif budget_ms is None:
        budget_s = _INF  # never "predicted not to finish": only convergence or the limit
    else:
        budget_s = _positive("budget_ms", budget_ms) * 1e-3
    if ceiling_ms is None:
        ceiling_s = CEILING_PER_BUDGET * budget_s  # inf without a budget
    else:
        ceiling_s = _positive("ceiling_ms", ceiling_ms) * 1e-3
    ws = getattr(_local, "ws", None)
    if ws is None or ws.arm is not arm or ws.settings is not settings:
        ws = _workspace(arm, settings)
    # Tolerances are written only when they change: each numpy item set costs ~0.1 µs.
    if tol_pos_cm is not ws.tol_pos_cm or tol_ori_deg is not ws.tol_ori_deg:
        ws.fparams[F_TOL_POS] = _positive("tol_pos_cm", tol_pos_cm)
        ws.fparams[F_TOL_ORI] = _positive("tol_ori_deg", tol_ori_deg)
        ws.tol_pos_cm, ws.tol_ori_deg = tol_pos_cm, tol_ori_deg
    # Identity tests, not a dict: hashing an Enum member runs Python code (~0.3 µs).
    if mode is _POSE:
        start = _START_POSE
    elif mode is TargetMode.POSITION:
        start = START_NEW | MODE_POSITION
    elif mode is TargetMode.POSITION_AXIS:
        start = START_NEW | MODE_AXIS | START_GOAL_SET
        _axis_goal(pose, tool_axis, direction, ws.goal)
    else:
        raise ValueError(f"mode={mode!r} must be one of {', '.join(m.name for m in TargetMode)}")
    if q_start_deg is not None:
        q_start = np.asarray(q_start_deg, dtype=float)
        n = ws.n
        if q_start.shape != (n,) or not np.all(np.isfinite(q_start)):
            raise ValueError(f"q_start_deg={q_start_deg!r} must be {n} finite angles in degrees")
        np.clip(q_start * ws.to_joint, ws.lower, ws.upper, out=ws.q_start)
        start |= START_HAS_PREV
    ws.rng_items[0] = seed & _MASK64 if type(seed) is int else _seed_value(seed)
    args = ws.args
    search = _search

    # Two limits, each with its own estimate of a generation: the budget counts this thread's
    # CPU time (``cpu_clock``), the ceiling wall time (``clock``). Another process that holds
    # the CPU stretches the wall time of a generation, not its CPU time: on a busy machine the
    # search then goes on until it has had its budget of CPU, or until the ceiling.
    #
    # Each estimate is a moving average of the past generations (per generation of a chunk).
    # A CPU sample is capped at 4× the estimate (a restart or a full LM run costs more than
    # the average, and wears off); a wall sample is not: a preempted chunk is what the wall
    # estimate is there to see, and it only guards the ceiling. Chunks double up to 64
    # generations, never predicted past half of what is left of the budget, nor of the
    # ceiling: one generation can cost several times the average (a restart, a full LM run),
    # so the last one gets that margin; at most two average generations go unused.
    #
    # The estimates carry over from one call to the next (same arm, settings, thread and
    # clocks), so a call starts with the initialisation and a first chunk in one compiled
    # call. The first call with a pair of clocks calibrates them: the initialisation alone
    # (about one generation's work), counted in CPU time if that is less, so an
    # initialisation preempted for 11 ms does not make every generation look 11 ms long.
    # Carried over, the estimates stay within 4× of that calibration either way. The CPU
    # clock is a system call (~0.7 µs, and a lock in the kernel: 5 % of a fast solve), so a
    # calibrated call reads it only after a chunk that did not converge, never at the start
    # nor at the end: the first chunk's CPU time is then counted as its wall time (an upper
    # bound; a first chunk preempted for a while leaves the search that much less budget).
    if ws.clock is clock and ws.cpu_clock is cpu_clock:
        cpu_estimate_s = ws.cpu_estimate_s
        wall_estimate_s = ws.wall_estimate_s
        # The first chunk is sized on the whole budget and ceiling: the microseconds of
        # Python since ``started`` are left out of the sizing (not out of the search's time).
        limit = ws.first_limit
        if limit * cpu_estimate_s > 0.5 * budget_s:
            limit = int(0.5 * budget_s / cpu_estimate_s)
        if limit * wall_estimate_s > 0.5 * ceiling_s:
            limit = int(0.5 * ceiling_s / wall_estimate_s)
        gens = limit - 1 if limit > 1 else 0
        done = search(
            *args,
            start,
            pose.x_cm,
            pose.y_cm,
            pose.z_cm,
            pose.roll_deg,
            pose.pitch_deg,
            pose.yaw_deg,
            gens,
        )
        if not done:
            now = clock()
            cpu_now = cpu_clock()
            cpu_started = cpu_now - (now - started)  # see above: wall time so far
            sample_s = (now - started) / (gens + 1)
            if sample_s > 4.0 * cpu_estimate_s:
                sample_s = 4.0 * cpu_estimate_s
            cpu_estimate_s += 0.25 * (sample_s - cpu_estimate_s)
            wall_estimate_s += 0.25 * ((now - started) / (gens + 1) - wall_estimate_s)
            chunk = 2 * gens if gens > 0 else 2
            if chunk > 64:
                chunk = 64
    else:
        cpu_started = cpu_clock()
        done = search(
            *args,
            start,
            pose.x_cm,
            pose.y_cm,
            pose.z_cm,
            pose.roll_deg,
            pose.pitch_deg,
            pose.yaw_deg,
            0,
        )
        now = clock()
        cpu_now = cpu_clock()
        cpu_estimate_s = wall_estimate_s = min(now - started, cpu_now - cpu_started)
        ws.calibration_s = cpu_estimate_s
        ws.cpu_estimate_s = ws.wall_estimate_s = cpu_estimate_s
        ws.clock = clock
        ws.cpu_clock = cpu_clock
        chunk = 1
    # A call that converged in its first compiled call (most do) changed no estimate.
    at_once = done
    while True:
        if done:
            reason = _CONVERGED
            break
        left = settings.max_generations - int(ws.counts[S_GENERATIONS])
        if left <= 0:
            reason = StopReason.ITERATION_LIMIT
            break
        gens = min(chunk, left)
        # An estimate is > 0 wherever a division by it happens, unless that limit is spent.
        left_s = budget_s - (cpu_now - cpu_started)
        if gens * cpu_estimate_s > 0.5 * left_s:
            gens = int(0.5 * left_s / cpu_estimate_s) if left_s > 0.0 else 0
            if gens < 1:
                reason = StopReason.DEADLINE
                break
        left_s = ceiling_s - (now - started)
        if gens * wall_estimate_s > 0.5 * left_s:
            gens = int(0.5 * left_s / wall_estimate_s) if left_s > 0.0 else 0
            if gens < 1:
                reason = StopReason.CEILING
                break
        # The pose arguments are read only when a search starts (start 0 goes on).
        done = search(*args, 0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, gens)
        after = clock()
        if not done:
            cpu_after = cpu_clock()
            sample_s = (cpu_after - cpu_now) / gens
            cpu_estimate_s += 0.25 * (min(sample_s, 4.0 * cpu_estimate_s) - cpu_estimate_s)
            wall_estimate_s += 0.25 * ((after - now) / gens - wall_estimate_s)
            cpu_now = cpu_after
        now = after
        chunk = min(2 * chunk, 64)
    if not at_once:
        calibration_s = ws.calibration_s
        ws.cpu_estimate_s = min(max(cpu_estimate_s, 0.25 * calibration_s), 4.0 * calibration_s)
        ws.wall_estimate_s = min(max(wall_estimate_s, 0.25 * calibration_s), 4.0 * calibration_s)

    out = ws.out_items.tolist()
    n = ws.n
    # The frozen dataclass's own __init__ sets its 12 fields one object.__setattr__ at a time
    # (~2 µs); filling the instance's dict is the same object for a third of that.
    result = _new_result(IKResult)
    fields = result.__dict__
    fields["q_deg"] = tuple(out[O_Q + n :])
    fields["pos_err_cm"] = out[O_POS_CM]
    fields["ori_err_deg"] = out[O_ORI_DEG]
    fields["cost"] = out[O_COST]
    fields["converged"] = reason is _CONVERGED
    fields["elapsed_ms"] = (clock() - started) * 1e3
    counts = ws.counts_items.tolist()  # ints already: no int() of each float in ``out``
    fields["generations"] = counts[S_GENERATIONS]
    fields["evaluations"] = counts[S_EVALUATIONS]
    fields["lm_iterations"] = counts[S_LM_ITERATIONS]
    fields["restarts"] = counts[S_RESTARTS]
    fields["stop_reason"] = reason
    fields["q"] = tuple(out[O_Q : O_Q + n])
    fields["de_improvements"] = counts[S_DE_GAINS]
    return result


_new_result = object.__new__
_INF = math.inf
# Enum members as module globals: reading one off its class costs ~0.09 µs (~0.01 µs here).
_POSE = TargetMode.POSE
_CONVERGED = StopReason.CONVERGED
_START_POSE = START_NEW | MODE_POSE


def _axis_goal(
    pose: Pose, tool_axis: Sequence[float], direction: Sequence[float] | None, goal: FloatArray
) -> None:
    """POSITION_AXIS's goal: the target position, the hand axis (hand frame) as column 0 and
    the direction it must point along (base frame) as column 2 (see ``kernels.residual``)."""
    _goal_matrix(
        pose.x_cm,
        pose.y_cm,
        pose.z_cm,
        math.radians(pose.roll_deg),
        math.radians(pose.pitch_deg),
        math.radians(pose.yaw_deg),
        goal,
    )
    hand_axis = _unit("tool_axis", tool_axis)
    goal[:3, 2] = goal[:3, :3] @ hand_axis if direction is None else _unit("direction", direction)
    goal[:3, 0] = hand_axis


_FIRST_CHUNK = 4
"""Generations the first compiled call runs after the initialisation, once calibrated."""

CEILING_PER_BUDGET = 4.0
"""The wall-clock ceiling of a call that names none, per unit of budget: a thread that gets a
quarter of a core (four busy threads per core) still has its whole budget of CPU."""


class _Workspace:
    """The arrays of one (arm, settings) pair, reused call after call by one thread: allocating
    them took a quarter of a fast solve. :func:`solve` copies its result out."""

    def __init__(self, arm: Arm, settings: SolverSettings) -> None:
        k = kernel_arrays(arm)
        n, size = arm.dof, settings.pop_size
        self.arm = arm
        self.settings = settings
        self.lower, self.upper = k.lower, k.upper
        self.to_joint, self.to_user = k.to_joint, k.to_user
        self.n = n
        # The kernels' arrays are views of two buffers (see layout.SEARCH_ARRAYS).
        o = layout.float_layout(n, size)
        self.fbuf = np.zeros(o[-1])
        views = [self.fbuf[o[m] : o[m + 1]] for m in range(len(o) - 1)]
        (
            _pop,
            _cost,
            frames,
            joint_params,
            goal,
            self.q_start,
            self.fparams,
            record,
            self.record_q,
            self.out,
            _lm,
        ) = views
        i = layout.int_layout(size)
        self.ibuf = np.zeros(i[-1], dtype=np.int64)
        self.iparams, self.counts, _stuck = (self.ibuf[i[m] : i[m + 1]] for m in range(len(i) - 1))
        frames.reshape(k.frames.shape)[...] = k.frames
        joint_params.reshape(k.joint_params.shape)[...] = k.joint_params
        self.goal = goal.reshape(4, 4)
        self.goal[...] = np.eye(4)
        record[...] = np.inf
        self.out_items = self.out.data
        self.counts_items = self.counts.data
        self.fparams[layout.F_SPREAD] = math.radians(settings.warm_spread_deg)
        self.fparams[layout.F_SCALE] = settings.F
        self.fparams[layout.F_CR] = settings.Cr
        self.fparams[layout.F_MOVE_W] = settings.movement_weight
        self.fparams[layout.F_LM_LAMBDA0] = settings.lm_lambda0
        self.fparams[layout.F_LM_WINDOW] = settings.lm_window
        self.fparams[layout.F_LM_PROGRESS] = settings.lm_progress
        self.fparams[layout.F_LM_NEAR] = settings.lm_near_cost
        self.fparams[layout.F_STALL_GAIN] = settings.stall_gain
        self.iparams[layout.I_LM_ITERS] = settings.lm_iterations
        self.iparams[layout.I_STALL_GENS] = settings.stall_generations
        self.iparams[layout.I_DOF] = n
        self.iparams[layout.I_POP] = size
        self.rng = np.zeros(1, dtype=np.uint64)
        # The generator's state and the results through memoryviews: setting and reading
        # them so runs CPython's own code, not numpy's item machinery (solve() does both at
        # every call; from cold caches it is the lighter path).
        self.rng_items = self.rng.data
        # The first compiled call: the initialisation and up to _FIRST_CHUNK generations.
        self.first_limit = min(_FIRST_CHUNK, settings.max_generations) + 1
        # The estimates of a generation's CPU and wall time, carried from call to call, and
        # the clocks they were measured on (see solve()).
        self.clock: Clock | None = None
        self.cpu_clock: Clock | None = None
        self.tol_pos_cm: object = None
        self.tol_ori_deg: object = None
        self.cpu_estimate_s = 0.0
        self.wall_estimate_s = 0.0
        self.calibration_s = 0.0
        self.args = (self.fbuf, self.ibuf, self.rng)
        _check_search_arrays(self.args)


def _check_search_arrays(args: tuple[np.ndarray, ...]) -> None:
    """The arrays as ``layout.SEARCH_ARRAYS`` says (dtype, dimensions, C order, writable): the
    ahead-of-time module's wrapper does not check them, and would read the wrong memory."""
    for array, (name, dtype, ndim) in zip(args, layout.SEARCH_ARRAYS, strict=True):
        if not (
            array.dtype == np.dtype(dtype)
            and array.ndim == ndim
            and array.flags.c_contiguous
            and array.flags.writeable
        ):
            raise TypeError(f"kernels.search's {name} must be C-contiguous {dtype}, {ndim}-d")


_local = threading.local()


_WORKSPACES = 8
"""Workspaces a thread keeps (the last used is also ``_local.ws``, the fast path): a caller
that alternates settings or arms (a bench comparing methods pose by pose) keeps each one's
arrays and estimates instead of rebuilding them at every switch."""


def _workspace(arm: Arm, settings: SolverSettings) -> _Workspace:
    ws: _Workspace | None = getattr(_local, "ws", None)
    if ws is None or ws.arm is not arm or ws.settings is not settings:
        kept: dict[tuple[int, int], _Workspace] | None = getattr(_local, "kept", None)
        if kept is None:
            kept = _local.kept = {}
        key = (id(arm), id(settings))
        ws = kept.pop(key, None)
        if ws is None or ws.arm is not arm or ws.settings is not settings:
            ws = _Workspace(arm, settings)
        if len(kept) >= _WORKSPACES:
            del kept[next(iter(kept))]  # the least recently used
        kept[key] = ws
        _local.ws = ws
    return ws


def warm_up() -> float:
    """Load the kernels :func:`solve` uses and run each path once; returns seconds.

    The kernels are the ahead-of-time module (:mod:`companion.ik.aot`, built by ``python -m
    companion.ik``) where an up-to-date one exists, otherwise numba's JIT compiles them (or
    loads them from its cache): then the compiled entry points (``kernels.search``, which holds
    every other kernel, and ``kernels.goal_matrix``) are compiled here, not in a solve. Setting
    ``ARMBRIDGE_IK_JIT=1`` in the environment skips the ahead-of-time module. Call it once
    before the first time-critical solve (the daemon does, before READY). The target is the
    papers' G, which cannot converge, so the search runs cold and warm, and so does the
    pointing-direction mode's path.
    """
    global _warmed_up
    t = time.perf_counter()
    _load_kernels()
    _warmed_up = True
    arm = Arm.default()
    unreachable = Pose(-20.0, 3.0, 40.0, 0.0, 10.0, 15.0)
    few = SolverSettings(max_generations=2)
    solve(arm, unreachable, budget_ms=1e4, seed=0, settings=few)
    solve(arm, unreachable, budget_ms=1e4, seed=0, q_start_deg=[0, 90, 0, 0, 0, 0], settings=few)
    solve(arm, unreachable, budget_ms=1e4, seed=0, settings=few, mode=TargetMode.POSITION_AXIS)
    return time.perf_counter() - t


def kernels_origin() -> str:
    """Where the kernels :func:`solve` runs come from: the ahead-of-time module's path, or
    ``"numba JIT"`` (empty before :func:`warm_up`)."""
    return _origin


def jit_cache_ready() -> bool:
    """Whether numba's cache holds the JIT kernels for the current sources (False: the first
    solve or :func:`warm_up` compiles them, ~20 s of CPU). Imports numba."""
    from companion.ik import kernels

    if not kernels.CACHE:
        return False
    try:
        # numba's index of the cached versions, {} when missing or stale (source stamp or
        # numba version): not a public API, so anything unexpected reads as "not cached".
        cache: Any = getattr(kernels.search, "_cache", None)
        return bool(cache._cache_file._load_index())
    except Exception:
        return False


# The compiled entry points solve() calls, set by _load_kernels() (warm_up() calls it first).
_search: Callable[..., bool] = None  # type: ignore[assignment]
_goal_matrix: Callable[..., None] = None  # type: ignore[assignment]
_origin = ""
_load_lock = threading.Lock()


def _load_kernels() -> None:
    global _search, _goal_matrix, _origin
    with _load_lock:
        if _origin:
            return
        module = None if os.environ.get("ARMBRIDGE_IK_JIT") == "1" else aot.load()
        if module is not None:
            _search, _goal_matrix = module.search, module.goal_matrix
            _origin = str(module.__file__)
            return
        from companion.ik import kernels  # imports numba (~0.5 s)

        if os.environ.get("ARMBRIDGE_IK_JIT") != "1":
            log.info(
                "no ahead-of-time IK module %s (python -m companion.ik builds it): the "
                "kernels run on numba's JIT",
                aot.file_name(),
            )
        if not jit_cache_ready():
            log.warning(
                "compiling the IK kernels (once, ~20 s of CPU; `python -P -m companion.ik` "
                "does it at install)"
            )
        # The compiled functions themselves (what ``compile`` returns), not numba's
        # dispatchers: a dispatcher looks up the type of every argument at every call to
        # choose a compiled version, and there is one, for the types of the solver's arrays
        # (the ahead-of-time module's signatures; _check_search_arrays holds the arrays to
        # them). Loaded from numba's cache, or compiled here, before any solve. Median CPU time
        # per solve 0.94-0.97x after an rtb ik_LM call and bench.solver's judge, 0.94-1.05x in
        # a tight loop, 8 arms (docs/measurements/solver_ab_dispatcher.md: python -m
        # bench.solver_ab --rev HEAD --dispatcher --poses 2000).
        _search = kernels.search.compile(aot.SEARCH_SIGNATURE)
        _goal_matrix = kernels.goal_matrix.compile(aot.GOAL_MATRIX_SIGNATURE)
        _origin = "numba JIT"
