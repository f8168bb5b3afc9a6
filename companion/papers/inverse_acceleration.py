"""Inverse acceleration (paper 004): constant joint accelerations from a hand-acceleration record.

**Units: SI throughout this module** — metres, seconds, radians; accelerations in m/s² and
rad/s². A DH :class:`~companion.kinematics.Arm` keeps lengths in cm inside, so :class:`DHChainModel`
converts its output to m/s² at this boundary.

Forward model (paper 004 eqs. 10–16): with constant joint accelerations ``q̈`` and the initial
state ``q(0) = q0``, ``q̇(0) = q̇0`` (zero by default)::

    q̇(t) = q̇0 + q̈·t,    q(t) = q0 + q̇0·t + q̈·t²/2,    ẍ(t) = J(q)·q̈ + J̇(q, q̇)·q̇

Two ready models implement :class:`AccelerationModel`:

* :class:`PlanarChain` — a planar chain of revolute joints about parallel z axes (all α = 0,
  d = 0), written in closed form as in paper 004 eqs. 8–30; :func:`planar_3r` is the paper's
  arm (links 1, 1, 1 m). Output: ``(ẍ, ÿ)``.
* :class:`DHChainModel` — any :class:`~companion.kinematics.Arm`, through the geometric Jacobian of
  :mod:`companion.kinematics.jacobian`. Output: the hand point's ``(ẍ, ÿ, z̈)``.

**Uniqueness.** The full-vector fit is unique only up to the symmetries of the arm: a planar
chain with links of equal length (paper 004's 1, 1, 1 m) cannot tell apart joint accelerations
whose absolute-angle accelerations ``φ̈_j = q̈_1 + … + q̈_j`` are permutations of each other
(:func:`equivalent_accelerations`) — paper 004's answers for cases 2 and 3 are such
permutations. The magnitude fit adds at least the mirror image ``−q̈``.

Fitting (:func:`fit_joint_accelerations`) minimises one of two fitness measures
(:class:`AccelerationFit`) over ``q̈`` in a box with harmony search, then (by default) polishes
the best harmony with a few Levenberg–Marquardt steps on the residual vector.
"""

from __future__ import annotations

import itertools
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from enum import Enum
from typing import Protocol

import numpy as np

from companion.kinematics import FloatArray
from companion.kinematics.arm import Arm
from companion.kinematics.jacobian import hand_acceleration
from companion.papers import hs
from companion.papers.base import Clock, SolverResult, run

CM_PER_M = 100.0

# Paper 004 §7: records run "from 0 to 5 seconds separated to 103 points". The transcription
# drops superscripts (its MaxItr "104" is 10⁴), so this is read as 10³: 0 … 5 s in 10³ steps of
# 5 ms, 1 001 samples (MATLAB's 0:0.005:5), which hold every instant of Tables 2–3 exactly
# (i/200 is the double nearest to each printed instant). Read literally, 103 samples 5/102 s
# apart hold none of them (TEXT_T_S_103).
PAPER_T_S = np.arange(1001) / 200.0
TEXT_T_S_103 = np.linspace(0.0, 5.0, 103)
# Paper 004, Tables 2–3: the instants listed.
PAPER_TABLE_T_S = np.array([0.12, 0.37, 0.87, 1.37, 1.87, 2.37, 2.87, 3.37, 3.87, 4.37, 4.87])
# Paper 004 §7: the four cases' joint accelerations (rad/s²). Case 4's text claims links
# (0.9, 0.7, 0.3) m, but its table column matches unit links (shared spec §5).
PAPER_CASES_QDD = (
    (0.1, -0.15, -0.12),
    (0.2, 0.6, -0.3),
    (0.4, -0.7, -0.5),
    (-0.8, 0.1, -0.9),
)
PAPER_CASE4_CLAIMED_LINKS_M = (0.9, 0.7, 0.3)
# Paper 004 §4: each q̈_i searched in [−1, 1].
PAPER_BOUND_RAD_S2 = 1.0


class AccelerationModel(Protocol):
    """Hand acceleration of a chain driven by constant joint accelerations."""

    @property
    def dof(self) -> int: ...

    def acc_m_s2(self, qdd_rad_s2: FloatArray, t_s: FloatArray) -> FloatArray:
        """Hand acceleration ``(S, T, k)`` in m/s² for ``qdd_rad_s2`` ``(S, dof)`` at ``t_s``
        ``(T,)``."""
        ...


def joint_state(
    qdd_rad_s2: FloatArray,
    t_s: FloatArray,
    q0_rad: Sequence[float] | FloatArray | None = None,
    qd0_rad_s: Sequence[float] | FloatArray | None = None,
) -> tuple[FloatArray, FloatArray]:
    """Joint angles and rates ``(S, T, n)`` under constant accelerations (eqs. 11–16)."""
    qdd = np.asarray(qdd_rad_s2, float)
    if qdd.ndim != 2:
        raise ValueError(f"qdd_rad_s2 must have shape (S, n), got {qdd.shape}")
    t = np.asarray(t_s, float)[None, :, None]
    q0 = 0.0 if q0_rad is None else np.asarray(q0_rad, float)
    qd0 = 0.0 if qd0_rad_s is None else np.asarray(qd0_rad_s, float)
    qd = qd0 + qdd[:, None, :] * t
    q = q0 + qd0 * t + 0.5 * qdd[:, None, :] * t * t
    return q, qd


@dataclass(frozen=True)
class PlanarChain:
    """Planar chain of revolute joints (standard DH, all α = 0, d = 0), links in metres.

    With ``φ_j = q_1 + … + q_j``: ``x = Σ a_j cos φ_j``, ``y = Σ a_j sin φ_j``, hence
    ``ẍ = Σ a_j (−sin φ_j·φ̈_j − cos φ_j·φ̇_j²)``, ``ÿ = Σ a_j (cos φ_j·φ̈_j − sin φ_j·φ̇_j²)`` —
    the same numbers as ``J q̈ + J̇ q̇`` with paper 004 eqs. 17–30.
    """

    link_lengths_m: tuple[float, ...]
    q0_rad: tuple[float, ...] | None = None
    qd0_rad_s: tuple[float, ...] | None = None

    def __post_init__(self) -> None:
        links = tuple(float(v) for v in self.link_lengths_m)
        if not links or not all(np.isfinite(v) and v > 0 for v in links):
            raise ValueError(f"link_lengths_m={self.link_lengths_m!r} must be lengths > 0")
        object.__setattr__(self, "link_lengths_m", links)
        _check_state(self.q0_rad, self.qd0_rad_s, len(links))

    @property
    def dof(self) -> int:
        return len(self.link_lengths_m)

    def acc_m_s2(self, qdd_rad_s2: FloatArray, t_s: FloatArray) -> FloatArray:
        """``(ẍ, ÿ)`` in m/s², shape ``(S, T, 2)``."""
        q, qd = joint_state(_rows(qdd_rad_s2, self.dof), t_s, self.q0_rad, self.qd0_rad_s)
        qdd = np.asarray(qdd_rad_s2, float)[:, None, :]
        phi = np.cumsum(q, axis=2)
        phi_d = np.cumsum(qd, axis=2)
        phi_dd = np.broadcast_to(np.cumsum(qdd, axis=2), phi.shape)
        a = np.asarray(self.link_lengths_m)
        c, s = np.cos(phi), np.sin(phi)
        w2 = phi_d * phi_d
        xdd = (a * (-s * phi_dd - c * w2)).sum(axis=2)
        ydd = (a * (c * phi_dd - s * w2)).sum(axis=2)
        return np.stack([xdd, ydd], axis=2)


def planar_3r(link_lengths_m: Sequence[float] = (1.0, 1.0, 1.0)) -> PlanarChain:
    """Paper 004's planar 3R arm (Table 1; links 1, 1, 1 m), starting at rest at q = 0."""
    if len(link_lengths_m) != 3:
        raise ValueError(f"planar 3R needs 3 link lengths, got {len(link_lengths_m)}")
    return PlanarChain(tuple(link_lengths_m))


def planar_3r_arm(link_lengths_m: Sequence[float] = (1.0, 1.0, 1.0)) -> Arm:
    """The same arm as a DH :class:`~companion.kinematics.Arm` (``length_unit = "m"``, ±180° limits,
    which inverse acceleration does not use)."""
    return Arm.from_dict(
        {
            "name": "planar-3r",
            "convention": "standard",
            "length_unit": "m",
            "joint": [
                {"alpha_deg": 0, "a": float(a), "d": 0, "min_deg": -180, "max_deg": 180}
                for a in link_lengths_m
            ],
        },
        source="planar_3r_arm()",
    )


@dataclass(frozen=True)
class DHChainModel:
    """Any :class:`~companion.kinematics.Arm` through its geometric Jacobian; output
    ``(ẍ, ÿ, z̈)`` of the hand point in m/s² (the arm's cm are converted here)."""

    arm: Arm
    q0_rad: tuple[float, ...] | None = None
    qd0_rad_s: tuple[float, ...] | None = None

    def __post_init__(self) -> None:
        _check_state(self.q0_rad, self.qd0_rad_s, self.arm.dof)

    @property
    def dof(self) -> int:
        return self.arm.dof

    def acc_m_s2(self, qdd_rad_s2: FloatArray, t_s: FloatArray) -> FloatArray:
        qdd = _rows(qdd_rad_s2, self.dof)
        q, qd = joint_state(qdd, t_s, self.q0_rad, self.qd0_rad_s)
        s, t, n = q.shape
        qdd_rep = np.broadcast_to(qdd[:, None, :], q.shape).reshape(-1, n)
        acc = hand_acceleration(self.arm, q.reshape(-1, n), qd.reshape(-1, n), qdd_rep)
        return acc[:, :3].reshape(s, t, 3) / CM_PER_M


class AccelerationFit(Enum):
    """What the fitness compares, in m/s²."""

    VECTOR = "vector"
    """Default. RMS over the samples of ``‖ẍ_model − ẍ_given‖``: unique answer."""
    MAGNITUDE = "magnitude"
    """Paper 004 §6: mean over the samples of ``| |ẍ_model| − |ẍ_given| |``. The paper's
    pseudo-code is garbled; this is our reading. Many ``q̈`` fit equally (non-unique)."""


@dataclass(frozen=True)
class InverseAccelerationProblem:
    """Box-bounded problem over ``q̈`` (rad/s²) for the solvers: ``lower``, ``upper``, ``cost``."""

    model: AccelerationModel
    t_s: FloatArray
    acc_m_s2: FloatArray
    fit: AccelerationFit = AccelerationFit.VECTOR
    bound_rad_s2: float = PAPER_BOUND_RAD_S2
    _target_norm: FloatArray = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        t = np.asarray(self.t_s, float)
        acc = np.asarray(self.acc_m_s2, float)
        if t.ndim != 1 or t.size == 0 or not np.all(np.isfinite(t)):
            raise ValueError(f"t_s must be a non-empty 1-D array of finite times, got {t.shape}")
        if acc.ndim != 2 or acc.shape[0] != t.size or not np.all(np.isfinite(acc)):
            raise ValueError(f"acc_m_s2 must be finite with shape ({t.size}, k), got {acc.shape}")
        if not isinstance(self.fit, AccelerationFit):
            raise ValueError(f"fit={self.fit!r} is not one of {[f.value for f in AccelerationFit]}")
        if not (np.isfinite(self.bound_rad_s2) and self.bound_rad_s2 > 0):
            raise ValueError(f"bound_rad_s2={self.bound_rad_s2!r} outside (0, ∞)")
        object.__setattr__(self, "t_s", t)
        object.__setattr__(self, "acc_m_s2", acc)
        object.__setattr__(self, "_target_norm", np.linalg.norm(acc, axis=1))

    @property
    def lower(self) -> FloatArray:
        return np.full(self.model.dof, -self.bound_rad_s2)

    @property
    def upper(self) -> FloatArray:
        return np.full(self.model.dof, self.bound_rad_s2)

    def residuals(self, qdd_rad_s2: FloatArray) -> FloatArray:
        """Residuals ``(S, m)`` in m/s²: all components (VECTOR) or magnitude differences."""
        model = self.model.acc_m_s2(qdd_rad_s2, self.t_s)
        if self.fit is AccelerationFit.VECTOR:
            return (model - self.acc_m_s2).reshape(model.shape[0], -1)
        return np.linalg.norm(model, axis=2) - self._target_norm

    def cost(self, qdd_rad_s2: FloatArray) -> FloatArray:
        """Fitness ``(S,)`` in m/s² (see :class:`AccelerationFit`)."""
        r = self.residuals(qdd_rad_s2)
        if self.fit is AccelerationFit.VECTOR:
            return np.sqrt((r * r).sum(axis=1) / self.t_s.size)
        return np.abs(r).mean(axis=1)


def levenberg_marquardt(
    problem: InverseAccelerationProblem,
    x0: FloatArray,
    *,
    max_steps: int = 20,
    xtol: float = 1e-12,
    fd_step: float = 1e-7,
) -> tuple[FloatArray, int]:
    """Polish ``x0`` by Levenberg–Marquardt on ``problem.residuals`` (least squares), with a
    central finite-difference Jacobian (one batched model call of ``2n + 1`` rows per step).
    Steps are clamped into the box and accepted only if the sum of squares drops.
    Returns the point and the number of steps taken."""
    x = np.clip(np.asarray(x0, float), problem.lower, problem.upper)
    n = x.size
    eye = np.eye(n) * fd_step
    damping = 1e-6
    steps = 0
    while steps < max_steps:
        steps += 1
        probes = np.concatenate([x[None, :], x + eye, x - eye])
        res = problem.residuals(probes)
        r = res[0]
        jac = ((res[1 : n + 1] - res[n + 1 :]) / (2 * fd_step)).T  # (m, n)
        jtj = jac.T @ jac
        g = jac.T @ r
        sse = r @ r
        improved = False
        for _ in range(8):
            dx = np.linalg.solve(jtj + damping * np.diag(np.diag(jtj) + 1e-12), -g)
            x_new = np.clip(x + dx, problem.lower, problem.upper)
            r_new = problem.residuals(x_new[None, :])[0]
            if r_new @ r_new < sse:
                x, r = x_new, r_new
                damping = max(damping / 10, 1e-12)
                improved = True
                break
            damping *= 10
        if not improved or np.max(np.abs(dx)) < xtol:
            break
    return x, steps


@dataclass(frozen=True)
class AccelerationFitResult:
    """``qdd_rad_s2`` is the answer; ``cost`` its fitness over the whole record in m/s²
    (:class:`AccelerationFit`).

    ``search`` is the harmony-search run of the attempt kept (with the polish on, that HS saw
    only the record up to ``search_horizon_s``), ``polish_steps`` the Levenberg–Marquardt steps
    of that attempt, ``attempts`` the HS runs made, ``elapsed_s`` the total time.
    """

    qdd_rad_s2: FloatArray
    cost: float
    search: SolverResult
    polish_steps: int
    attempts: int
    elapsed_s: float


# Defaults of the HS + LM fit (see fit_joint_accelerations), chosen on paper 004's 5-second
# records sampled at 103 points (TEXT_T_S_103) with links (1, 1, 1), (0.9, 0.7, 0.3),
# (1, 0.8, 0.5) and (0.5, 1, 0.8) m, 4 cases × 15 seeds each: 0 wrong answers in 240, median
# 0.1 s. Measured on the same records: polishing only
# HS's best (wrong basin in ~15 % of fits), or running HS longer (2000 improvisations: 25–50 %
# wrong with unequal links, the memory collapses into one basin), is worse.
DEFAULT_FIT_ITERATIONS = 200
DEFAULT_SEARCH_HORIZON_S = 1.5
DEFAULT_POLISH_HORIZONS_S = (2.5, 3.5, 4.5)
DEFAULT_BEAM = 5
DEFAULT_MAX_ATTEMPTS = 5


def fit_joint_accelerations(
    model: AccelerationModel,
    t_s: FloatArray,
    acc_m_s2: FloatArray,
    *,
    fit: AccelerationFit = AccelerationFit.VECTOR,
    bound_rad_s2: float = PAPER_BOUND_RAD_S2,
    iterations: int = DEFAULT_FIT_ITERATIONS,
    memory_size: int = hs.PAPER_MEMORY_SIZE,
    hmcr: float = hs.DEFAULT_HMCR,
    par_min: float = hs.PAPER_PAR_MIN,
    par_max: float = hs.PAPER_PAR_MAX,
    bandwidth_frac: float = hs.DEFAULT_BANDWIDTH_FRAC,
    polish: bool = True,
    polish_starts: int = hs.PAPER_MEMORY_SIZE,
    beam: int = DEFAULT_BEAM,
    search_horizon_s: float | None = DEFAULT_SEARCH_HORIZON_S,
    polish_horizons_s: Sequence[float] = DEFAULT_POLISH_HORIZONS_S,
    tol_m_s2: float = 1e-9,
    max_attempts: int = DEFAULT_MAX_ATTEMPTS,
    seed: int | np.random.Generator | None = None,
    clock: Clock = time.perf_counter,
) -> AccelerationFitResult:
    """Recover constant joint accelerations (rad/s²) from a hand-acceleration record.

    ``polish=False`` is paper 004's method: harmony search alone over the whole record,
    ``iterations`` improvisations (the paper: 10⁴), one attempt.

    ``polish=True`` (default) is HS for the global search and Levenberg–Marquardt to converge:

    1. HS over ``[−bound, bound]ⁿ`` fits the record up to ``search_horizon_s`` (``None``: all
       of it), ``iterations`` improvisations (default 200: a short, still diverse search) —
       over a short horizon the joints turn little and the fitness has few basins;
    2. the ``polish_starts`` best harmonies (default: the whole memory) are polished by LM on
       that horizon, and the ``beam`` best of them are carried on through growing horizons
       (``polish_horizons_s``, then the whole record), polished again at each — a continuation
       that follows each basin as the record lengthens;
    3. the best point on the whole record is kept; if its cost is above ``tol_m_s2`` all of
       this is repeated with fresh draws from the same generator, up to ``max_attempts``
       times, and the best attempt is returned.

    Same seed, same answer.
    """
    if polish_starts < 1 or polish_starts > memory_size:
        raise ValueError(f"polish_starts={polish_starts} outside [1, memory_size={memory_size}]")
    if beam < 1:
        raise ValueError(f"beam={beam} outside [1, ∞)")
    if max_attempts < 1:
        raise ValueError(f"max_attempts={max_attempts} outside [1, ∞)")
    started = clock()
    rng = np.random.default_rng(seed)
    full = InverseAccelerationProblem(model, t_s, acc_m_s2, fit, bound_rad_s2)
    horizons: list[float] = []
    if polish:
        horizons = sorted(
            h
            for h in ([search_horizon_s] if search_horizon_s is not None else [])
            + list(polish_horizons_s)
            if h < full.t_s.max()
        )
    search_problem = _window(full, horizons[0]) if horizons else full
    best: tuple[FloatArray, float, SolverResult, int] | None = None
    attempts = 0
    while attempts < (max_attempts if polish else 1):
        attempts += 1
        solver = hs.HarmonySearch(
            search_problem,
            memory_size=memory_size,
            hmcr=hmcr,
            par_min=par_min,
            par_max=par_max,
            bandwidth_frac=bandwidth_frac,
            iterations=iterations,
            rng=rng,
        )
        search = run(
            solver,
            max_iterations=iterations,
            tol=None,
            budget_s=None,
            clock=clock,
            started_at=clock(),
        )
        x, steps = search.x, 0
        cost = float(full.cost(x[None, :])[0])
        if polish:
            order = np.argsort(solver.cost, kind="stable")[:polish_starts]
            points = list(solver.memory[order])
            for horizon in [*horizons, None]:
                problem = full if horizon is None else _window(full, horizon)
                polished = [levenberg_marquardt(problem, p) for p in points]
                steps += sum(k for _, k in polished)
                points = [p for p, _ in polished]
                # Beam: only the best few follow the continuation to the next horizon.
                stage_cost = problem.cost(np.array(points))
                points = [points[i] for i in np.argsort(stage_cost, kind="stable")[:beam]]
            x_k = points[0]
            cost_k = float(full.cost(x_k[None, :])[0])
            if cost_k < cost:
                x, cost = x_k, cost_k
        if best is None or cost < best[1]:
            best = (x, cost, search, steps)
        if best[1] <= tol_m_s2:
            break
    assert best is not None
    return AccelerationFitResult(
        qdd_rad_s2=best[0],
        cost=best[1],
        search=best[2],
        polish_steps=best[3],
        attempts=attempts,
        elapsed_s=clock() - started,
    )


def _window(problem: InverseAccelerationProblem, horizon_s: float) -> InverseAccelerationProblem:
    """The same problem restricted to the samples at ``t ≤ horizon_s``."""
    keep = problem.t_s <= horizon_s
    return InverseAccelerationProblem(
        problem.model, problem.t_s[keep], problem.acc_m_s2[keep], problem.fit, problem.bound_rad_s2
    )


def equivalent_accelerations(
    chain: PlanarChain,
    qdd_rad_s2: Sequence[float] | FloatArray,
    t_s: FloatArray = PAPER_T_S,
    atol_m_s2: float = 1e-9,
) -> FloatArray:
    """Every ``q̈`` ``(K, n)`` whose record ``ẍ(t)`` equals that of ``qdd_rad_s2`` (first row).

    The hand point of a planar chain, ``Σ a_j (cos φ_j, sin φ_j)``, is symmetric in the
    absolute angles ``φ_j = q_1 + … + q_j`` of links of equal length. Permuting ``φ̈`` among
    such links therefore gives another ``q̈`` with the same acceleration record, whenever the
    initial state allows (at rest at q = 0 it always does). With paper 004's unit links this
    makes up to 3! = 6 answers that even the full-vector fit cannot tell apart. Candidates are
    kept only if their records agree within ``atol_m_s2`` at ``t_s``.
    """
    qdd = np.asarray(qdd_rad_s2, float).reshape(-1)
    links = np.asarray(chain.link_lengths_m)
    phi_dd = np.cumsum(qdd)
    reference = chain.acc_m_s2(qdd[None, :], t_s)[0]
    found = [qdd]
    for order in itertools.permutations(range(qdd.size)):
        perm = list(order)
        if perm == sorted(perm) or not np.array_equal(links[perm], links):
            continue
        candidate = np.diff(phi_dd[perm], prepend=0.0)
        if any(np.array_equal(candidate, f) for f in found):
            continue
        if np.max(np.abs(chain.acc_m_s2(candidate[None, :], t_s)[0] - reference)) <= atol_m_s2:
            found.append(candidate)
    return np.array(found)


def recovery_error(
    chain: PlanarChain, qdd_found: FloatArray, qdd_true: Sequence[float] | FloatArray
) -> tuple[float, int]:
    """Largest joint error (rad/s²) of ``qdd_found`` to the nearest answer equivalent to
    ``qdd_true`` (:func:`equivalent_accelerations`), and that answer's index (0 = ``qdd_true``
    itself)."""
    options = equivalent_accelerations(chain, qdd_true)
    errors = np.max(np.abs(options - np.asarray(qdd_found, float)), axis=1)
    k = int(np.argmin(errors))
    return float(errors[k]), k


def _rows(qdd_rad_s2: FloatArray, dof: int) -> FloatArray:
    qdd = np.asarray(qdd_rad_s2, float)
    if qdd.ndim != 2 or qdd.shape[1] != dof:
        raise ValueError(f"qdd_rad_s2 must have shape (S, {dof}), got {qdd.shape}")
    return qdd


def _check_state(q0: Sequence[float] | None, qd0: Sequence[float] | None, dof: int) -> None:
    for name, value in (("q0_rad", q0), ("qd0_rad_s", qd0)):
        if value is not None and (len(value) != dof or not all(np.isfinite(v) for v in value)):
            raise ValueError(f"{name}={value!r} must be {dof} finite values or None")
