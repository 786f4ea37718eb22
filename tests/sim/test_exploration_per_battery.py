"""The bounded exploration with per-battery input bounds: feasible, zero-mean, and the same
numbers as one bound when the batteries are identical."""

from __future__ import annotations

import numpy as np

from mpcrl_lite.config import SystemConfig
from mpcrl_lite.sim.exploration import bounded_exploration, exploration_center
from mpcrl_lite.system.battery import project_action

MIXED = SystemConfig(U_bar=(2.0, 1.0, 0.5), P_bar=2.5)


def test_explored_actions_respect_each_batterys_bound_and_stay_zero_mean():
    rng = np.random.default_rng(0)
    pi = project_action(rng.uniform(-2.5, 2.5, (4000, 3)), MIXED)
    e = 0.3 * rng.standard_normal(pi.shape)
    for bounds in ("symmetric", "radial"):
        a = bounded_exploration(pi, e, MIXED, bounds)
        assert np.all(np.abs(a) <= np.array(MIXED.U_bar) + 1e-12), bounds
        assert np.all(np.maximum(a, 0).sum(1) <= MIXED.P_bar + 1e-9)
        assert np.all(np.maximum(-a, 0).sum(1) <= MIXED.P_bar + 1e-9)
    # the symmetric exploration is odd in the draw: pi + e and pi - e are both feasible
    plus = bounded_exploration(pi, e, MIXED, "symmetric") - pi
    minus = bounded_exploration(pi, -e, MIXED, "symmetric") - pi
    np.testing.assert_allclose(plus, -minus, atol=1e-12)
    c = exploration_center(pi, MIXED, 0.1)
    assert np.all(np.abs(c) <= np.array(MIXED.U_bar) - 0.1 + 1e-12)


def test_identical_bounds_as_a_tuple_give_the_same_exploration():
    rng = np.random.default_rng(1)
    pi = project_action(rng.uniform(-1.5, 1.5, (500, 3)), SystemConfig())
    e = 0.2 * rng.standard_normal(pi.shape)
    same = SystemConfig(U_bar=(1.0, 1.0, 1.0))
    for bounds in ("symmetric", "radial", "project"):
        np.testing.assert_array_equal(bounded_exploration(pi, e, SystemConfig(), bounds),
                                      bounded_exploration(pi, e, same, bounds))
