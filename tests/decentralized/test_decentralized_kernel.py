"""The compiled coordination rounds (mpcrl_lite.decentralized.coordination_kernel) against the reference rounds
of mpcrl_lite.decentralized.coordination: the same iteration, so the same solutions, sensitivities and
learning run."""

from __future__ import annotations

import numpy as np
import pytest

from mpcrl_lite.config import CoordinationConfig, LearningConfig, MPCConfig, SystemConfig
from mpcrl_lite.decentralized import coordination_kernel as _coord_kernel
from mpcrl_lite.decentralized.coordination import CoordinatedMPC
from mpcrl_lite.decentralized.learner import DecentralizedExperiment
from mpcrl_lite.system.prices import Prices
from mpcrl_lite.theta import Theta

FAST = MPCConfig()  # 'auto': compiled for a convex theta
REFERENCE = MPCConfig(backend="batch")
TIGHT = SystemConfig()  # n = 3, P_bar = 1.5 < n U_bar
TWENTY = SystemConfig(n=20)  # P_bar = 1.5: the limit binds for hours on end


def shaped_theta(system: SystemConfig, seed: int) -> Theta:
    rng = np.random.default_rng(seed)
    n = system.n
    return Theta.nominal(system).replace(
        b=rng.uniform(-3, 3, n), phi1=rng.uniform(5, 40, n), phi2=rng.uniform(-30, 0, n),
        T1=rng.uniform(5, 40, n), T2=rng.uniform(-30, 0, n),
    )


def case(system: SystemConfig, days: int, hour: int, seed: int):
    rng = np.random.default_rng(seed)
    buy, sell = Prices.month(system, days).window(hour, system.N)
    return rng.uniform(0.0, 1.0, (days, system.n)), buy, sell


def assert_same_solution(fast, ref) -> None:
    assert fast.compiled and not ref.compiled
    np.testing.assert_array_equal(fast.iterations, ref.iterations)
    np.testing.assert_array_equal(fast.converged, ref.converged)
    np.testing.assert_array_equal(fast.success, ref.success)
    for name in ("x", "lam", "mu", "price_buy", "price_sell", "action", "p"):
        a, b = getattr(fast, name), getattr(ref, name)
        scale = 1.0 + np.abs(b).max()
        assert np.abs(a - b).max() <= 1e-9 * scale, name


@pytest.mark.parametrize(("system", "hour", "seed", "days"),
                         [(TIGHT, 18, 0, 6), (TIGHT, 7, 1, 6), (TWENTY, 18, 2, 4)])
def test_compiled_rounds_give_the_reference_solutions(system, hour, seed, days):
    soc, buy, sell = case(system, days, hour, seed)
    theta = shaped_theta(system, seed) if system.n == 3 else Theta.nominal(system)
    fast = CoordinatedMPC(system, FAST).solve(soc, buy, sell, theta)
    ref = CoordinatedMPC(system, REFERENCE).solve(soc, buy, sell, theta)
    assert ref.converged.all()
    assert_same_solution(fast, ref)
    assert np.all(fast.planned_power < system.P_bar)


def test_compiled_sensitivities_are_the_reference_ones():
    soc, buy, sell = case(TWENTY, 3, 18, 5)
    theta = Theta.nominal(TWENTY)
    fast_mpc, ref_mpc = CoordinatedMPC(TWENTY, FAST), CoordinatedMPC(TWENTY, REFERENCE)
    fast = fast_mpc.solve(soc, buy, sell, theta)
    ref = ref_mpc.solve(soc, buy, sell, theta)
    grad, ok = fast_mpc.sensitivity(fast)
    grad_ref, ok_ref = ref_mpc.sensitivity(ref)
    np.testing.assert_array_equal(ok, ok_ref)
    assert ok.all()
    # per battery and day, relative to that row's largest entry
    scale = np.abs(grad_ref).max(-1, keepdims=True)
    assert np.all(np.abs(grad - grad_ref) <= 1e-8 * scale)


def test_compiled_sensitivity_matches_finite_differences_at_fixed_prices():
    soc, buy, sell = case(TIGHT, 2, 18, 3)
    theta = shaped_theta(TIGHT, 3)
    mpc = CoordinatedMPC(TIGHT, FAST)
    sol = mpc.solve(soc, buy, sell, theta)
    grad, ok = mpc.sensitivity(sol)
    assert ok.all()
    # battery 1's local MPC at the final grid prices, its own theta moved
    local = mpc.local_mpc
    solver = mpc._kernels[id(local)]
    buy_p = buy + sol.price_buy / mpc._discount
    sell_p = sell - sol.price_sell / mpc._discount
    base = theta.to_vector().reshape(-1, TIGHT.n)[:, 1]  # part-major: theta^1's 10 entries
    h = 1e-6
    for k in (0, 3, 7):
        step = np.zeros_like(base)
        step[k] = h
        plus = Theta.from_vector(base + step, 1)
        minus = Theta.from_vector(base - step, 1)
        a_plus = solver.solve_batch(soc[:, 1:2], buy_p, sell_p, plus).action[:, 0]
        a_minus = solver.solve_batch(soc[:, 1:2], buy_p, sell_p, minus).action[:, 0]
        np.testing.assert_allclose(grad[:, 1, k], (a_plus - a_minus) / (2 * h),
                                   rtol=1e-4, atol=1e-6)
    assert local.n == 1


def test_two_learning_months_equal_the_reference_run():
    learning = LearningConfig(days_per_month=3, months=2, seed=2)
    fast = DecentralizedExperiment(TIGHT, FAST, learning).run(progress=False)
    ref = DecentralizedExperiment(TIGHT, REFERENCE, learning).run(progress=False)
    np.testing.assert_allclose(fast.J, ref.J, rtol=1e-8)
    np.testing.assert_allclose(np.asarray(fast.theta), np.asarray(ref.theta), rtol=1e-8,
                               atol=1e-12)
    np.testing.assert_allclose(fast.theta_final, ref.theta_final, rtol=1e-8, atol=1e-12)
    np.testing.assert_allclose(fast.last_month.a, ref.last_month.a, rtol=0, atol=1e-8)
    for mine, theirs in zip(fast.update_info, ref.update_info):
        assert mine["coordination"]["iterations_mean"] == theirs["coordination"][
            "iterations_mean"]


def test_backend_choice():
    theta = Theta.nominal(TIGHT)
    assert CoordinatedMPC(TIGHT, FAST).compiled(theta)
    assert CoordinatedMPC(TIGHT, MPCConfig(backend="kernel")).compiled(theta)
    assert not CoordinatedMPC(TIGHT, REFERENCE).compiled(theta)
    assert not CoordinatedMPC(TIGHT, MPCConfig(backend="ipopt")).compiled(theta)
    concave = theta.replace(phi1=np.array([10.0, -1.0, 10.0]))
    assert not CoordinatedMPC(TIGHT, FAST).compiled(concave)  # 'auto' as for the MPC


def test_unconverged_compiled_rounds_fall_back_like_the_reference():
    soc, buy, sell = case(TIGHT, 3, 18, 5)
    theta = Theta.nominal(TIGHT)
    short = CoordinationConfig(max_iter=2)
    fast = CoordinatedMPC(TIGHT, FAST, short).solve(soc, buy, sell, theta)
    ref = CoordinatedMPC(TIGHT, REFERENCE, short).solve(soc, buy, sell, theta)
    assert not fast.converged.any() and fast.projected.all()
    np.testing.assert_array_equal(fast.iterations, 2)
    assert_same_solution(fast, ref)


def test_a_singular_day_stops_alone_and_takes_the_fallback():
    soc, buy, sell = case(TIGHT, 3, 18, 6)
    theta = Theta.nominal(TIGHT)
    mpc = CoordinatedMPC(TIGHT, FAST)
    reference = mpc.solve(soc, buy, sell, theta)
    hour = mpc._hour

    def broken_day_1(*args):
        h = hour(*args)
        h.Hd[3:6] = np.nan  # day 1's batteries: no finite Newton system
        return h

    mpc._hour = broken_day_1
    sol = mpc.solve(soc, buy, sell, theta)  # no exception mid-run
    np.testing.assert_array_equal(sol.converged, [True, False, True])
    np.testing.assert_array_equal(sol.projected, [False, True, False])
    a = sol.action
    assert np.all(np.maximum(a, 0).sum(1) <= TIGHT.P_bar + 1e-12)
    assert np.all(np.maximum(-a, 0).sum(1) <= TIGHT.P_bar + 1e-12)
    np.testing.assert_allclose(a[[0, 2]], reference.action[[0, 2]], atol=1e-12)


def test_structure_reproduces_the_dense_data():
    mpc = CoordinatedMPC(TWENTY, FAST)
    soc, buy, sell = case(TWENTY, 2, 5, 7)
    hour = mpc._hour(soc, buy, sell, mpc._thetas(Theta.nominal(TWENTY)))
    st = _coord_kernel.structure(*mpc._qp.a_pattern, mpc._qp.Cb)
    aval = st.values(hour.A)
    x = np.random.default_rng(0).normal(size=hour.Hd.shape)
    Ax = np.einsum("brk,brk->br", aval, x[:, st.acol])
    np.testing.assert_allclose(Ax, np.einsum("brc,bc->br", hour.A, x), rtol=1e-14, atol=1e-14)
    nb = mpc._qp.nb
    assert np.all(st.acol // nb >= st.ablo[:, None]) and np.all(st.acol // nb <= st.abhi[:, None])
    # the blocks of W: b and s alone, the soc with its two slacks
    groups = np.split(st.perm, st.cstart[1:-1])
    assert sorted(map(sorted, groups)) == [[0], [1], [2, 3, 4]]


def test_warm_up_compiles_what_the_coordination_uses():
    # the types of the warm-up's call are those of a real hour: no user waits for numba
    # (the coordination kernel's own warm-up, which python -m mpcrl_lite.cli.warm calls)
    _coord_kernel.warm_up()
    assert len(_coord_kernel.coordinate.signatures) == 1
    soc, buy, sell = case(TIGHT, 2, 18, 8)
    assert CoordinatedMPC(TIGHT, FAST).solve(soc, buy, sell, Theta.nominal(TIGHT)).compiled
    assert len(_coord_kernel.coordinate.signatures) == 1


@pytest.mark.parametrize("max_iter", [None, 3])
def test_compiled_rounds_do_not_depend_on_the_thread_count(max_iter):
    """The days go to the compiled rounds in blocks of COORDINATION_BLOCK on any number of
    threads: 1, 2 and 3 threads give the same solutions bit for bit, unconverged days too."""
    from mpcrl_lite.decentralized import coordination as coordination_module

    days = 3 * coordination_module.COORDINATION_BLOCK + 2
    soc, buy, sell = case(TIGHT, days, 18, 7)
    theta = shaped_theta(TIGHT, 7)
    config = CoordinationConfig() if max_iter is None else CoordinationConfig(max_iter=max_iter)

    def run(threads):
        mpc = CoordinatedMPC(TIGHT, FAST, config)
        mpc.threads = threads
        return mpc.solve(soc, buy, sell, theta)

    ref = run(1)
    assert ref.compiled and (ref.converged.all() if max_iter is None else not ref.converged.any())
    for threads in (2, 3):
        sol = run(threads)
        for name in ("x", "lam", "mu", "price_buy", "price_sell", "action", "iterations",
                     "converged"):
            np.testing.assert_array_equal(getattr(sol, name), getattr(ref, name), err_msg=name)
