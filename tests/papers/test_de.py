"""Differential evolution: each strategy exactly, one generation, the stop loop, round trips."""

from __future__ import annotations

import numpy as np
import pytest

from companion.kinematics.arm import Arm, Pose
from companion.papers.base import StopReason
from companion.papers.de import (
    CROSSOVERS,
    MUTATIONS,
    DEParams,
    DifferentialEvolution,
    differential_evolution,
    distinct_indices,
)
from companion.papers.objective import IKObjective, OrientationMetric
from devkit.timing import FakeClock

# A hand-built population of five 2-D points; costs make row 3 the best.
POP = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0], [2.0, 2.0], [3.0, 1.0]])
BEST = 3
PARAMS = DEParams(F=0.5, Cr=0.95, p_f=0.5)  # K = 0.5·(F + 1) = 0.75
R = np.array([[1, 2, 3, 4], [4, 0, 2, 3], [0, 1, 3, 4], [4, 1, 0, 2], [0, 2, 1, 3]])
A = np.array([0.2, 0.9, 0.2, 0.2, 0.2])


def _mutate(name):
    m = MUTATIONS[name]
    return m.donor(POP, BEST, R[:, : m.n_random], A, PARAMS)


def test_rand_1_by_hand():
    v = _mutate("rand/1")
    np.testing.assert_allclose(v[0], [0.0, -0.5])  # (1,0) + .5·((0,1) − (2,2))
    np.testing.assert_allclose(v[1], [3.0, 0.5])  # (3,1) + .5·((0,0) − (0,1))


def test_best_2_by_hand():
    v = _mutate("best/2")
    np.testing.assert_allclose(v[0], [2.0, 2.0])  # (2,2) + .5·((1,0)−(0,1)) + .5·((2,2)−(3,1))
    np.testing.assert_allclose(v[2], [1.0, 2.5])  # (2,2) + .5·((0,0)−(1,0)) + .5·((2,2)−(3,1))


def test_current_to_best_1_by_hand():
    v = _mutate("current-to-best/1")
    np.testing.assert_allclose(v[0], [1.5, 0.5])  # (0,0) + .5·((2,2)−(0,0)) + .5·((1,0)−(0,1))
    np.testing.assert_allclose(v[4], [2.5, 1.0])  # (3,1) + .5·((2,2)−(3,1)) + .5·((0,0)−(0,1))


def test_either_or_by_hand():
    v = _mutate("either-or")
    np.testing.assert_allclose(v[0], [0.0, -0.5])  # a = .2 < p_f: rand/1
    # a = .9 ≥ p_f: (3,1) + .75·((0,0)−(3,1) + (0,1)−(3,1)) = (3,1) + .75·(−6,−1)
    np.testing.assert_allclose(v[1], [-1.5, 0.25])


def test_either_or_default_k_is_prices():
    assert DEParams(F=0.5).K == 0.75


TARGET = np.zeros((3, 4))
DONOR = np.ones((3, 4))


def test_binomial_crossover_by_hand():
    u = np.array([[0.96, 0.5, 0.99, 0.95], [0.97, 0.98, 0.99, 0.96], [0.1, 0.1, 0.1, 0.1]])
    h = np.array([2, 0, 1])
    trial = CROSSOVERS["binomial"](TARGET, DONOR, u, h, 0.95)
    # u ≤ Cr takes the donor (0.95 ≤ 0.95 included); coordinate h always does.
    np.testing.assert_array_equal(trial, [[0, 1, 1, 1], [1, 0, 0, 0], [1, 1, 1, 1]])


def test_exponential_crossover_by_hand():
    u = np.array([[0.0, 0.1, 0.2, 0.99], [0.0, 0.99, 0.1, 0.1], [0.0, 0.1, 0.1, 0.1]])
    h = np.array([3, 1, 2])
    trial = CROSSOVERS["exponential"](TARGET, DONOR, u, h, 0.95)
    # Row 0: L = 3 from coordinate 3, circular: 3, 0, 1.  Row 1: L = 1.  Row 2: L = n = 4.
    np.testing.assert_array_equal(trial, [[1, 1, 0, 1], [0, 1, 0, 0], [1, 1, 1, 1]])


def test_distinct_indices_never_repeat_or_hit_the_target():
    rng = np.random.default_rng(0)
    for pop_size, k in ((5, 4), (12, 3), (30, 4)):
        for _ in range(50):
            r = distinct_indices(rng, pop_size, k)
            assert r.shape == (pop_size, k)
            assert r.min() >= 0 and r.max() < pop_size
            for i, row in enumerate(r):
                assert len(set(row)) == k and i not in row


class Sphere:
    """Σx² over [−1, 1]ⁿ, counting its calls."""

    def __init__(self, n=2):
        self.lower = -np.ones(n)
        self.upper = np.ones(n)
        self.calls = 0

    def cost(self, x):
        self.calls += 1
        return (np.asarray(x) ** 2).sum(axis=1)


def test_one_generation_exactly():
    problem = Sphere()
    start = POP / 3.0  # inside the box [-1, 1]²
    de = DifferentialEvolution(problem, pop_size=5, params=DEParams(F=2.0), initial=start)
    r = np.array([[3, 2, 1], [4, 0, 2], [0, 1, 3], [4, 0, 1], [0, 2, 1]])
    u = np.zeros((5, 2))  # take every donor coordinate
    h = np.zeros(5, dtype=int)
    trials = de.trials(r, np.zeros(5), u, h)
    # Row 0: (2/3, 2/3) + 2·((0, 1/3) − (1/3, 0)) = (0, 4/3), clamped to (0, 1).
    np.testing.assert_allclose(trials[0], [0.0, 1.0])
    # Row 2: (0, 0) + 2·((1/3, 0) − (2/3, 2/3)) = (−2/3, −4/3), clamped to (−2/3, −1).
    np.testing.assert_allclose(trials[2], [-2 / 3, -1.0])
    np.testing.assert_allclose(trials[1], [1.0, -1 / 3])
    before = de.cost.copy()
    de.select(trials)
    kept = (trials**2).sum(axis=1) <= before
    assert kept.tolist() == [False, False, False, True, True]  # 2/9 < 8/9, 8/9 < 10/9
    np.testing.assert_allclose(de.pop[kept], trials[kept])
    np.testing.assert_allclose(de.pop[~kept], start[~kept])
    assert (de.iteration, de.evaluations) == (1, 10)


def test_clamping_keeps_every_candidate_inside_the_box():
    problem = Sphere(3)
    de = DifferentialEvolution(problem, pop_size=8, params=DEParams(F=2.0, Cr=1.0), rng=1)
    for _ in range(30):
        de.step()
        assert np.all(de.pop >= -1) and np.all(de.pop <= 1)


@pytest.mark.parametrize(
    ("kwargs", "words"),
    [
        ({"mutation": "rand/9"}, "valid: rand/1, best/2, current-to-best/1, either-or"),
        ({"crossover": "uniform"}, "valid: binomial, exponential"),
        ({"mutation": "best/2", "pop_size": 4}, "needs at least 5"),
        ({"F": -0.1}, r"F=-0.1 outside \[0, 2\]"),
        ({"Cr": 1.5}, r"Cr=1.5 outside \[0, 1\]"),
    ],
)
def test_bad_settings_fail_at_construction(kwargs, words):
    with pytest.raises(ValueError, match=words):
        differential_evolution(Sphere(), **kwargs)


ARM = Arm.default()
TARGET_POSE = Pose(-20, 3, 40, 0, 10, 15)  # the papers' G


def test_same_seed_gives_identical_result():
    obj = IKObjective(ARM, TARGET_POSE)
    a = differential_evolution(obj, seed=42, generations=50)
    b = differential_evolution(obj, seed=42, generations=50)
    c = differential_evolution(obj, seed=43, generations=50)
    np.testing.assert_array_equal(a.x, b.x)
    np.testing.assert_array_equal(a.cost_history, b.cost_history)
    assert not np.array_equal(a.x, c.x)


def test_history_is_monotone_and_counts_add_up():
    obj = IKObjective(ARM, TARGET_POSE)
    res = differential_evolution(obj, seed=1, pop_size=12, generations=40)
    assert res.stop_reason is StopReason.ITERATION_LIMIT and not res.converged
    assert res.generations == 40 and res.evaluations == 12 * 41
    assert len(res.cost_history) == 41
    assert np.all(np.diff(res.cost_history) <= 0)
    assert res.cost == res.cost_history[-1] == pytest.approx(obj.cost(res.x[None, :])[0])


def test_tolerance_stops_early_as_converged():
    res = differential_evolution(Sphere(), seed=0, pop_size=10, generations=10_000, tol=1e-6)
    assert res.stop_reason is StopReason.CONVERGED
    assert res.cost <= 1e-6 and res.generations < 10_000


def test_budget_on_an_injected_clock():
    # Time advances 1 ms per objective call (one per generation): a 5.5 ms budget allows the
    # initial evaluation plus exactly five generations.
    clock = FakeClock(0.0)

    class SlowSphere(Sphere):
        def cost(self, x):
            clock.advance(1e-3)
            return super().cost(x)

    res = differential_evolution(
        SlowSphere(), seed=0, generations=1000, budget_s=5.5e-3, clock=clock
    )
    assert res.stop_reason is StopReason.DEADLINE
    assert res.generations == 5
    assert res.elapsed_s == pytest.approx(6e-3)


@pytest.mark.parametrize("seed", [11, 12, 13, 14])
def test_round_trip_fk_de_fk_on_reachable_poses(seed):
    # A reachable target (FK of joints within the limits) is found again; plain DE can stall in
    # a local minimum, so up to three restarts, as a caller would do.
    rng = np.random.default_rng(seed)
    q_true = ARM.random_q_rad(rng, 1)[0]
    target = Pose.from_matrix(ARM.fk_matrix(q_true))
    obj = IKObjective(ARM, target, metric=OrientationMetric.ROTATION)
    for restart in range(3):
        res = differential_evolution(obj, seed=restart, pop_size=30, generations=1000, tol=1e-7)
        errors = obj.errors(res.x)
        if errors.pos_err_cm[0] < 1e-2 and errors.ori_err_deg[0] < 1e-1:
            break
    assert errors.pos_err_cm[0] < 1e-2 and errors.ori_err_deg[0] < 1e-1
    assert ARM.within_limits(res.x)
    again = ARM.fk(np.degrees(res.x))
    assert again.as_tuple()[:3] == pytest.approx(target.as_tuple()[:3], abs=1e-2)
