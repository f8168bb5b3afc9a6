"""The boundary rules shared by the solvers: clamp (the papers'), wrap (free joints), redraw."""

from __future__ import annotations

import numpy as np
import pytest

from companion.papers.base import Boundary, apply_boundary
from companion.papers.de import DifferentialEvolution

LOWER = np.array([-np.pi, 0.0])
UPPER = np.array([np.pi, 1.0])


def test_inside_values_are_untouched_by_every_rule():
    x = np.array([[0.5, 0.25], [-np.pi, 1.0]])
    for rule in Boundary:
        rng = np.random.default_rng(0)
        np.testing.assert_array_equal(apply_boundary(x, LOWER, UPPER, rule, rng), x)
        # No draw is spent when nothing is outside.
        assert rng.random() == np.random.default_rng(0).random()


def test_clamp_sets_the_edge_and_wrap_takes_the_angle_modulo_one_turn():
    x = np.array([[np.radians(190.0), 1.25], [np.radians(-200.0), -0.5]])
    rng = np.random.default_rng(0)
    np.testing.assert_allclose(
        apply_boundary(x, LOWER, UPPER, Boundary.CLAMP, rng), [[np.pi, 1.0], [-np.pi, 0.0]]
    )
    wrapped = apply_boundary(x, LOWER, UPPER, Boundary.WRAP, rng)
    # 190° is −170°, −200° is 160°: the same joint position, so the same hand.
    np.testing.assert_allclose(wrapped, [[np.radians(-170.0), 0.25], [np.radians(160.0), 0.5]])


def test_redraw_replaces_only_the_outside_coordinates_within_the_box():
    x = np.array([[4.0, 0.5], [0.0, 7.0]])
    out = apply_boundary(x, LOWER, UPPER, Boundary.REDRAW, np.random.default_rng(1))
    assert out[0, 1] == 0.5 and out[1, 0] == 0.0
    assert np.all((out >= LOWER) & (out <= UPPER))
    assert out[0, 0] != 4.0 and out[1, 1] != 7.0


class Box:
    lower = LOWER
    upper = UPPER

    def cost(self, x):
        return (np.asarray(x) ** 2).sum(axis=1)


def test_a_solver_rejects_an_unknown_boundary_naming_the_valid_ones():
    with pytest.raises(ValueError, match="clamp"):
        DifferentialEvolution(Box(), pop_size=6, boundary="wrap")  # type: ignore[arg-type]


def test_de_trials_follow_the_boundary_rule():
    pop = np.array([[3.0, 0.9]] * 6)
    de = DifferentialEvolution(Box(), pop_size=6, initial=pop, rng=0, boundary=Boundary.WRAP)
    de.pop[1] = [-3.0, 0.1]  # r1 = 0, r2 = 0, r3 = 1 below: donor 3 + 0.9·6 = 8.4 rad
    r = np.array([[0, 0, 1]] * 6)
    trial = de.trials(r, np.zeros(6), np.zeros((6, 2)), np.zeros(6, dtype=np.intp))
    np.testing.assert_allclose(trial[0, 0], 8.4 - 2 * np.pi)
