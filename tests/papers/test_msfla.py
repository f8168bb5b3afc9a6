"""Modified shuffled frog-leaping: partition, the worst-frog leap and its fall-backs, the loop."""

from __future__ import annotations

import numpy as np
import pytest

from companion.kinematics.arm import Arm, Pose
from companion.papers.base import StopReason
from companion.papers.msfla import ShuffledFrogLeaping, shuffled_frog_leaping
from companion.papers.objective import IKObjective
from devkit.timing import FakeClock


class Sphere:
    def __init__(self, n=2):
        self.lower = -np.ones(n)
        self.upper = np.ones(n)

    def cost(self, x):
        return (np.asarray(x) ** 2).sum(axis=1)


def test_partition_deals_ranked_frogs_round_robin():
    # Frogs 0..5 at distances chosen so the ranking (best first) is 4, 2, 0, 5, 1, 3.
    x = np.array([[0.3, 0], [0.5, 0], [0.2, 0], [0.6, 0], [0.1, 0], [0.4, 0]])
    sfla = ShuffledFrogLeaping(Sphere(), pop_size=6, n_memeplexes=2, initial=x, rng=0)
    # Papers: frog k + m·(i − 1) of the ranking goes to memeplex k.
    np.testing.assert_array_equal(sfla.memeplexes(), [[4, 0, 1], [2, 5, 3]])


def test_local_iteration_moves_only_each_memeplex_worst_frog():
    rng = np.random.default_rng(3)
    sfla = ShuffledFrogLeaping(Sphere(3), pop_size=12, n_memeplexes=3, rng=rng)
    plexes = sfla.memeplexes()
    worst = plexes[np.arange(3), np.argmax(sfla.cost[plexes], axis=1)]
    before = sfla.pop.copy()
    sfla.local_iteration(plexes)
    moved = np.flatnonzero(np.any(sfla.pop != before, axis=1))
    assert set(moved) <= set(worst)
    np.testing.assert_allclose(sfla.cost, Sphere(3).cost(sfla.pop))


def test_no_improving_leap_falls_back_to_a_random_frog():
    # Every frog at the same point: leaps towards the memeplex best and the global best are
    # zero-length, so each memeplex's worst frog is replaced by a random one.
    x = np.full((6, 2), 0.5)
    sfla = ShuffledFrogLeaping(Sphere(), pop_size=6, n_memeplexes=3, initial=x, rng=1)
    sfla.local_iteration(sfla.memeplexes())
    changed = np.any(sfla.pop != 0.5, axis=1)
    assert changed.sum() == 3
    assert sfla.evaluations == 6 + 3 * 3  # initial + leap + global leap + random, per memeplex


def test_leap_is_limited_by_max_leap():
    x = np.array([[-1.0, -1.0], [1.0, 1.0], [-0.9, -0.9], [0.0, 0.0]])
    sfla = ShuffledFrogLeaping(Sphere(), pop_size=4, n_memeplexes=1, max_leap=0.1, initial=x, rng=2)
    moved, _ = sfla._leap(np.array([1]), sfla.pop[[3]])
    assert np.all(np.abs(moved - x[1]) <= 0.1 + 1e-15)


def test_msfla_improves_j_on_the_papers_target():
    obj = IKObjective(Arm.default(), Pose(-20, 3, 40, 0, 10, 15))
    res = shuffled_frog_leaping(obj, pop_size=30, shuffles=10, local_iterations=10, seed=5)
    assert res.stop_reason is StopReason.ITERATION_LIMIT
    assert res.cost < res.cost_history[0]
    assert np.all(np.diff(res.cost_history) <= 0)
    assert res.generations == 10


def test_same_seed_same_result():
    obj = IKObjective(Arm.default(), Pose(-20, 3, 40, 0, 10, 15))
    a = shuffled_frog_leaping(obj, shuffles=3, local_iterations=5, seed=9)
    b = shuffled_frog_leaping(obj, shuffles=3, local_iterations=5, seed=9)
    np.testing.assert_array_equal(a.x, b.x)
    assert a.evaluations == b.evaluations


def test_tolerance_and_budget_stop_the_loop():
    res = shuffled_frog_leaping(Sphere(), pop_size=6, shuffles=500, tol=1e-4, seed=0)
    assert res.stop_reason is StopReason.CONVERGED and res.cost <= 1e-4
    clock = FakeClock(0.0, tick_s=1.0)  # each reading costs 1 s
    res = shuffled_frog_leaping(Sphere(), pop_size=6, shuffles=500, budget_s=3.0, clock=clock)
    assert res.stop_reason is StopReason.DEADLINE and res.generations == 2


@pytest.mark.parametrize(
    ("kwargs", "words"),
    [
        ({"pop_size": 10, "n_memeplexes": 3}, "multiple of n_memeplexes=3"),
        ({"local_iterations": 0}, "local_iterations=0"),
        ({"leap_factor": 0.0}, "leap_factor"),
        ({"max_leap": -1.0}, "max_leap"),
    ],
)
def test_bad_settings(kwargs, words):
    with pytest.raises(ValueError, match=words):
        shuffled_frog_leaping(Sphere(), **kwargs)


def test_the_classic_sfla_is_the_same_loop_with_leap_factor_one():
    from companion.papers.constants import SFLA_CLASSIC_LEAP_FACTOR
    from companion.papers.msfla import classic_shuffled_frog_leaping

    assert SFLA_CLASSIC_LEAP_FACTOR == 1.0
    kw = dict(pop_size=9, shuffles=4, local_iterations=3, seed=5)
    classic = classic_shuffled_frog_leaping(Sphere(3), **kw)
    same = shuffled_frog_leaping(Sphere(3), leap_factor=1.0, **kw)
    modified = shuffled_frog_leaping(Sphere(3), **kw)
    np.testing.assert_array_equal(classic.cost_history, same.cost_history)
    assert not np.array_equal(classic.cost_history, modified.cost_history)


def test_wrapped_msfla_is_repeatable_and_stays_in_the_box():
    from companion.papers.base import Boundary

    kw = dict(pop_size=9, shuffles=3, local_iterations=3, seed=2, boundary=Boundary.WRAP)
    a = shuffled_frog_leaping(Sphere(3), leap_factor=3.0, **kw)
    b = shuffled_frog_leaping(Sphere(3), leap_factor=3.0, **kw)
    np.testing.assert_array_equal(a.x, b.x)
    assert np.all(np.abs(a.x) <= 1.0)
