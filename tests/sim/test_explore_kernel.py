"""The compiled exploration (mpcrl_lite.sim.exploration_kernel) against a plain numpy statement of the
same arithmetic: equal to the last bit for a few batteries, feasible and odd for many.

The numpy functions below are the reference: vectorised over days, written as the
mathematics of :func:`mpcrl_lite.sim.exploration.bounded_exploration` reads (the radial step,
the slide along the grid faces, both around the projection of pi).
"""

from __future__ import annotations

import numpy as np
import pytest

from mpcrl_lite import SystemConfig
from mpcrl_lite.sim.exploration import bounded_exploration
from mpcrl_lite.sim.exploration_kernel import project_rows
from mpcrl_lite.system.battery import project_action


def reference(pi: np.ndarray, e: np.ndarray, system: SystemConfig, bounds: str) -> np.ndarray:
    base = project_action(pi, system)
    if bounds == "symmetric":
        room = np.maximum(system.U_bar - np.abs(base), 0.0)
        along = np.clip(_along_grid_faces(base, e, system.P_bar), -room, room)
        both = _radial(np.concatenate([base, base]), np.concatenate([e, along]), system)
        step, along = both[: len(base)], both[len(base):]
        larger = (along**2).sum(axis=-1) > (step**2).sum(axis=-1)
        step = np.where(larger[:, None], along, step)
    else:
        step = _radial(base, e, system)
    return project_action(base + step, system)


def _radial(base: np.ndarray, e: np.ndarray, system: SystemConfig) -> np.ndarray:
    """``min(1, t*) e`` with ``t*`` the largest ``t`` for which both ``base + t e`` and
    ``base - t e`` respect the input bounds and the grid limit (``base`` feasible)."""
    room = np.maximum(system.U_bar - np.abs(base), 0.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.min(np.where(e != 0.0, room / np.abs(e), np.inf), axis=-1)
    # both grid sums at base + t e and base - t e, as four stacked problems of one call
    grid = _largest_step(np.concatenate([base, base, -base, -base]),
                         np.concatenate([e, -e, e, -e]), system.P_bar)
    t = np.minimum(t, grid.reshape(4, -1).min(axis=0))
    return np.minimum(t, 1.0)[:, None] * e


def _along_grid_faces(base: np.ndarray, e: np.ndarray, total: float) -> np.ndarray:
    """The exploration ``e`` (days, n) moved into the directions along which both
    ``base + e`` and ``base - e`` keep the grid sums where they are, on the faces it could
    reach.

    With ``r = max_i |e_i|`` (per day), the buying face ``sum_i max(x_i, 0) <= total`` counts
    as reachable when its slack at ``base`` is below ``r`` (likewise the selling face). On a
    reachable face, the batteries at ``|base_i| <= r`` (they could cross zero and join the
    sum) do not explore, and among those on the face's side (``base_i > r`` buying,
    ``< -r`` selling) the mean of ``e`` is removed: ``e`` then slides along the face. The
    sets depend on ``e`` only through ``r``, which is even in ``e``, and the map is linear
    in ``e`` given them, so it is odd in ``e``.
    """
    r = np.abs(e).max(axis=-1, keepdims=True)
    out = e.copy()
    idle = np.abs(base) <= r
    pinned = np.zeros(base.shape[0], dtype=bool)
    for sign in (1.0, -1.0):
        side = sign * base
        reach = total - np.maximum(side, 0.0).sum(axis=-1) < r[:, 0]
        pinned |= reach
        members = reach[:, None] & (side > r)
        count = members.sum(axis=-1, keepdims=True)
        mean = np.where(members, out, 0.0).sum(axis=-1, keepdims=True) / np.maximum(count, 1)
        out = np.where(members, out - mean, out)
    return np.where(pinned[:, None] & idle, 0.0, out)


def _largest_step(c: np.ndarray, d: np.ndarray, total: float) -> np.ndarray:
    """Row-wise ``max{t in [0, 1]: sum_i max(c_i + t d_i, 0) <= total}`` for rows with
    ``sum_i max(c_i, 0) <= total``.

    ``f(t) = sum_i max(c_i + t d_i, 0)`` is convex and piecewise linear with kinks at
    ``-c_i / d_i``; it is evaluated at 0, at the kinks inside ``(0, 1)`` and at 1, and the
    crossing of ``total`` is found exactly by linear interpolation on the segment where it
    happens. Shapes ``(days, n)`` -> ``(days,)``.
    """
    with np.errstate(divide="ignore", invalid="ignore"):
        kinks = np.where(d != 0.0, -c / d, 1.0)
    kinks = np.clip(np.where(np.isfinite(kinks), kinks, 1.0), 0.0, 1.0)
    ts = np.sort(np.concatenate([np.zeros_like(kinks[:, :1]), kinks,
                                 np.ones_like(kinks[:, :1])], axis=1), axis=1)  # (days, n+2)
    f = np.maximum(c[:, None, :] + ts[:, :, None] * d[:, None, :], 0.0).sum(-1)
    over = f > total
    t = np.ones(c.shape[0])
    rows = over.any(axis=1)
    if rows.any():
        j = np.argmax(over[rows], axis=1)  # first point above total; >= 1 as f(0) <= total
        j = np.maximum(j, 1)
        r = np.flatnonzero(rows)
        t0, t1, f0, f1 = ts[r, j - 1], ts[r, j], f[r, j - 1], f[r, j]
        slope = np.where(f1 > f0, f1 - f0, 1.0)
        t[r] = np.clip(t0 + (total - f0) * (t1 - t0) / slope, 0.0, 1.0)
        t[r] = np.where(f0 > total, t0, t[r])  # f(0) > total (rounding): no exploration
    return t


def _cases(n: int, rng: np.random.Generator, days: int = 400):
    """Actions inside, on the bounds, on the grid faces and beyond; explorations of several
    sizes, some with zero entries."""
    U = 1.0
    yield rng.uniform(-1.2 * U, 1.2 * U, (days, n)), rng.normal(0.0, 0.3, (days, n))
    on_bounds = rng.choice([-U, 0.0, U, 1.5 / n, -1.5 / n, 0.5 * U], (days, n))
    yield on_bounds, rng.normal(0.0, 0.1, (days, n)) * rng.integers(0, 2, (days, n))
    faces = project_action(rng.uniform(-1.3, 1.3, (days, n)), SystemConfig(n=n, P_bar=min(1.5, n - 0.5)))
    yield faces, rng.normal(0.0, 0.2, (days, n))


@pytest.mark.parametrize("n", [1, 2, 3, 4, 5])
def test_equal_to_the_numpy_statement_to_the_last_bit(n):
    system = SystemConfig(n=n, P_bar=1.5) if n > 1 else SystemConfig(n=1, P_bar=0.6)
    rng = np.random.default_rng(n)
    for pi, e in _cases(n, rng):
        np.testing.assert_array_equal(project_rows(pi, np.full(system.n, system.U_bar), system.P_bar),
                                      project_action(pi, system))
        for bounds in ("symmetric", "radial"):
            np.testing.assert_array_equal(bounded_exploration(pi, e, system, bounds),
                                          reference(pi, e, system, bounds))


@pytest.mark.parametrize("n", [8, 20])
def test_many_batteries_feasible_odd_and_near_the_numpy_statement(n):
    """With 8 or more entries numpy sums in pairs, the kernel in order: the projections agree
    to rounding; the explorations are both valid (odd in e, feasible) and agree except where
    rounding decides whether a grid face is reached."""
    system = SystemConfig(n=n, P_bar=0.4 * n)
    rng = np.random.default_rng(n)
    for pi, e in _cases(n, rng, days=1000):
        pi = pi * 0.4 * n / 1.5
        np.testing.assert_allclose(project_rows(pi, np.full(system.n, system.U_bar), system.P_bar),
                                   project_action(pi, system), rtol=0, atol=1e-14)
        for bounds in ("symmetric", "radial"):
            plus = bounded_exploration(pi, e, system, bounds)
            minus = bounded_exploration(pi, -e, system, bounds)
            base = project_action(pi, system)
            np.testing.assert_allclose(plus - base, -(minus - base), atol=1e-12)
            np.testing.assert_allclose(project_action(plus, system), plus, atol=1e-12)
            same = np.abs(plus - reference(pi, e, system, bounds)).max(axis=1) <= 1e-12
            assert same.mean() > 0.95, same.mean()


def test_bad_input_is_named():
    system = SystemConfig()
    pi = np.zeros((2, 3))
    with pytest.raises(ValueError, match=r"pi has shape \(2, 2\) and e \(2, 3\)"):
        bounded_exploration(pi[:, :2], pi, system)
    e = pi.copy()
    e[1, 2] = np.nan
    with pytest.raises(ValueError, match="e has non-finite entries"):
        bounded_exploration(pi, e, system)


def test_the_rows_sort_orders_as_numpy_does():
    """The kernels' insertion sort of a row's kinks gives numpy's sorted values, with ties,
    zeros of both signs and the lengths the kernels sort (n + 2 and 2 n, up to n = 20)."""
    from mpcrl_lite.sim.exploration_kernel import _sort_small

    rng = np.random.default_rng(7)
    for size in [1, 2, 3, 5, 7, 10, 22, 40]:
        for _ in range(200):
            row = rng.choice([-1.0, -0.0, 0.0, 0.25, 1.0], size) if rng.random() < 0.5 \
                else rng.uniform(-2.0, 2.0, size)
            got = row.copy()
            _sort_small(got)
            np.testing.assert_array_equal(got, np.sort(row))
            assert np.all(np.diff(got) >= 0.0)
