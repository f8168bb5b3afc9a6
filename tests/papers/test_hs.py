"""Harmony search: one improvisation by hand, the PAR schedule, replacement, the loop."""

from __future__ import annotations

import numpy as np
import pytest

from companion.papers.base import StopReason
from companion.papers.hs import HarmonySearch, harmony_search
from devkit.timing import FakeClock


class Sphere:
    def __init__(self, n=2, half_width=1.0):
        self.lower = -half_width * np.ones(n)
        self.upper = half_width * np.ones(n)

    def cost(self, x):
        return (np.asarray(x) ** 2).sum(axis=1)


# A hand-built memory of three 2-D harmonies in the box [−1, 1]²; row 2 is the worst.
MEMORY = np.array([[0.1, -0.2], [0.5, 0.4], [-0.9, 0.8]])


def _hs(**kw):
    kw.setdefault("memory_size", 3)
    kw.setdefault("hmcr", 0.9)
    kw.setdefault("par_min", 0.3)
    kw.setdefault("par_max", 0.9)
    kw.setdefault("bandwidth_frac", 0.05)  # bw = 0.05 · 2 = 0.1
    kw.setdefault("iterations", 10)
    return HarmonySearch(Sphere(), initial=MEMORY, rng=0, **kw)


def test_memory_consideration_with_pitch_adjustment_by_hand():
    h = _hs()
    assert h.par == pytest.approx(0.3)
    x = h.improvise(
        consider=np.array([0.5, 0.5]),  # < HMCR: both from memory
        rows=np.array([1, 2]),  # x0 from row 1, x1 from row 2
        pitch=np.array([0.1, 0.5]),  # only x0 is pitch-adjusted (0.1 < PAR 0.3 ≤ 0.5)
        shift=np.array([-0.5, 1.0]),
        fresh=np.array([0.0, 0.0]),
    )
    np.testing.assert_allclose(x, [0.5 - 0.1 * 0.5, 0.8])


def test_random_selection_by_hand():
    h = _hs()
    x = h.improvise(
        consider=np.array([0.95, 0.2]),  # x0 ≥ HMCR: random; x1 from memory row 0
        rows=np.array([1, 0]),
        pitch=np.array([0.0, 0.9]),  # pitch ignored for the random coordinate
        shift=np.array([1.0, 1.0]),
        fresh=np.array([0.25, 0.99]),
    )
    np.testing.assert_allclose(x, [-1.0 + 0.25 * 2.0, -0.2])


def test_pitch_adjustment_is_clamped_into_the_box():
    h = _hs(bandwidth_frac=0.5)  # bw = 1
    x = h.improvise(
        consider=np.zeros(2),
        rows=np.array([2, 2]),
        pitch=np.zeros(2),
        shift=np.array([-1.0, 1.0]),
        fresh=np.zeros(2),
    )
    np.testing.assert_allclose(x, [-1.0, 1.0])


def test_par_rises_linearly_from_min_to_max_and_stays():
    h = _hs(iterations=10)
    seen = []
    for _ in range(12):
        seen.append(h.par)
        h.step()
    np.testing.assert_allclose(seen[:11], 0.3 + 0.6 * np.arange(11) / 10)
    assert seen[11] == pytest.approx(0.9)


def test_better_harmony_replaces_the_worst_only():
    h = _hs()
    assert h.update(np.array([0.0, 0.3]))  # cost .09 < worst 1.45
    np.testing.assert_allclose(h.memory, [[0.1, -0.2], [0.5, 0.4], [0.0, 0.3]])
    assert h.cost[2] == pytest.approx(0.09)
    assert h.iteration == 1 and h.evaluations == 4


def test_worse_harmony_is_discarded():
    h = _hs()
    assert not h.update(np.array([1.0, 1.0]))  # cost 2 > worst 1.45
    np.testing.assert_allclose(h.memory, MEMORY)
    assert h.iteration == 1 and h.evaluations == 4


def test_step_draws_one_improvisation():
    h = _hs()
    h.step()
    assert h.iteration == 1 and h.evaluations == 4
    assert np.all(h.memory >= -1) and np.all(h.memory <= 1)


@pytest.mark.parametrize(
    ("kw", "names"),
    [
        ({"hmcr": 1.5}, ("hmcr=1.5", "[0, 1]")),
        ({"par_min": -0.1}, ("par_min=-0.1", "[0, 1]")),
        ({"par_min": 0.8, "par_max": 0.5}, ("par_min=0.8", "par_max=0.5")),
        ({"bandwidth_frac": 0.0}, ("bandwidth_frac=0.0", "(0, 1]")),
        ({"memory_size": 0}, ("memory_size=0",)),
        ({"iterations": 0}, ("iterations=0",)),
    ],
)
def test_bad_settings_name_the_value_and_range(kw, names):
    with pytest.raises(ValueError) as info:
        HarmonySearch(Sphere(), rng=0, **kw)
    for name in names:
        assert name in str(info.value)


def test_same_seed_same_result():
    a = harmony_search(Sphere(3), iterations=300, seed=42)
    b = harmony_search(Sphere(3), iterations=300, seed=42)
    np.testing.assert_array_equal(a.x, b.x)
    np.testing.assert_array_equal(a.cost_history, b.cost_history)
    c = harmony_search(Sphere(3), iterations=300, seed=43)
    assert not np.array_equal(a.x, c.x)


def test_minimises_a_sphere_and_counts():
    res = harmony_search(Sphere(3), memory_size=20, iterations=3000, seed=1)
    assert res.stop_reason is StopReason.ITERATION_LIMIT
    assert res.cost < 1e-3
    assert res.generations == 3000 and res.evaluations == 3020
    assert res.cost_history.size == 3001
    assert np.all(np.diff(res.cost_history) <= 0)  # the best never gets worse


def test_tolerance_stops_as_converged():
    res = harmony_search(Sphere(2), iterations=10_000, tol=1e-2, seed=3)
    assert res.stop_reason is StopReason.CONVERGED and res.cost <= 1e-2
    assert res.generations < 10_000


def test_budget_stops_on_a_fake_clock():
    clock = FakeClock(0.0, tick_s=0.5)  # each reading costs 0.5 s
    res = harmony_search(Sphere(2), iterations=10_000, budget_s=2.0, seed=0, clock=clock)
    assert res.stop_reason is StopReason.DEADLINE
    assert res.generations < 10
