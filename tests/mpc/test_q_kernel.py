"""The fixed-first-action MPC's first stage: its compiled Newton iteration gives the numpy
form's results to the last bit, on rows of every kind (done at once, infeasible, at the
grid bound, several steps) for fewer than eight batteries (numpy sums eight or more in
another order: those batches run the numpy form)."""

from __future__ import annotations

import numpy as np
import pytest

from mpcrl_lite.mpc import q_kernel


def rows(rng: np.random.Generator, days: int, n: int):
    """A batch as the Q-learner's months give it: actions inside and outside the bounds,
    some at the grid bound, prices of a few tens."""
    U = rng.uniform(0.5, 1.5, n)
    P = float(rng.uniform(0.6, 1.2) * U.sum())
    a = rng.uniform(-1.1, 1.1, (days, n)) * U
    a[::7] *= 0.999  # near the boxes
    a[1::11] = 0.0
    c = rng.normal(0.0, 30.0, (days, n))
    feasible = np.all(np.abs(a) < U, axis=1) & (np.maximum(a, 0).sum(1) < P) \
        & (np.maximum(-a, 0).sum(1) < P)
    return c, a, U, P, feasible


@pytest.mark.parametrize(("n", "seed"), [(3, 0), (3, 1), (1, 2), (7, 3), (10, 4)])
@pytest.mark.parametrize("tau", [0.1, 1e-3])
def test_the_compiled_first_stage_is_the_numpy_one(monkeypatch, n, seed, tau):
    c, a, U, P, feasible = rows(np.random.default_rng(seed), 300, n)
    assert 0 < feasible.sum() < len(feasible)
    monkeypatch.setattr(q_kernel, "COMPILED", False)
    s_ref, ok_ref = q_kernel._first_stage(c, a, U, P, tau, feasible)
    monkeypatch.setattr(q_kernel, "COMPILED", True)
    s, ok = q_kernel._first_stage(c, a, U, P, tau, feasible)
    np.testing.assert_array_equal(ok, ok_ref)
    np.testing.assert_array_equal(s, s_ref)  # NaN where the numpy form has NaN
    assert ok.sum() > 0.9 * feasible.sum()
    # a solution: the gradient of the barrier problem vanishes on the rows solved
    A = a.sum(1)
    gb, gs = P - (s.sum(1) + A), P - s.sum(1)
    grad = (c - tau * (1 / s - 1 / (U - s) + 1 / (s + a) - 1 / (U - s - a))
            + (tau / gb + tau / gs)[:, None])
    # against the size of its terms (a barrier term tau / distance is large near a bound)
    terms = (np.abs(c) + tau * (1 / s + 1 / (U - s) + 1 / np.abs(s + a) + 1 / np.abs(U - s - a))
             + (tau / gb + tau / gs)[:, None])
    assert np.all(np.abs(grad[ok]) <= 1e-4 * terms[ok])  # the Newton decrement stops it


def test_a_batch_done_at_once_is_left_as_it_is():
    c, a, U, P, _ = rows(np.random.default_rng(5), 20, 3)
    none = np.zeros(len(c), dtype=bool)
    s, ok = q_kernel._first_stage(c, a, U, P, 0.1, none)
    assert not ok.any()
    np.testing.assert_array_equal(s, np.broadcast_to(0.5 * U, s.shape))
