"""Tests of the compiled back-end (mpcrl_lite.mpc.backends.kernel, mpcrl_lite.mpc.backends.kernel_core).

The kernel runs the batch solver's iteration problem by problem, so it must give the batch
solver's solutions (first action to 1e-9), iteration counts, statuses and sensitivities (1e-8
of each column's largest entry), and the IPOPT reference's solutions and sensitivities, over
states at the soft soc bounds, a binding grid limit, random thetas and several sizes, with
both of its factorisations. A short learning run with it reproduces the batch back-end's.
"""

from __future__ import annotations

import json
import logging
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import convex_theta

from mpcrl_lite._util import jit
from mpcrl_lite.config import LearningConfig, MPCConfig, SystemConfig
from mpcrl_lite.learning.experiment import Experiment
from mpcrl_lite.mpc.backends import kernel_core as _kernel
from mpcrl_lite.mpc.backends.batch import BatchSolver
from mpcrl_lite.mpc.backends.ipopt import IpoptSolver
from mpcrl_lite.mpc.backends.kernel import KernelSolver, cache_dir, warm_up
from mpcrl_lite.mpc.formulation import MPC
from mpcrl_lite.mpc.sensitivity import PolicySensitivity
from mpcrl_lite.mpc.solution import (
    STATUS_BREAKDOWN,
    STATUS_CONVERGED,
    STATUS_MAX_ITER,
    BatchSolution,
)
from mpcrl_lite.theta import CONSTANT_PARTS, Theta

SEED = 20240703
TAUS = sorted({MPCConfig().tau, 1e-4})
METHODS = ("stage", "agent")
REPO = Path(__file__).resolve().parents[2]


# -- helpers ----------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def prices() -> np.ndarray:
    """A month of random buying prices, 30 days x 24 hours, 5..130 NOK/MWh."""
    return np.random.default_rng(2025).uniform(5.0, 130.0, (30, 24))


def windows(prices: np.ndarray, hour: int, N: int, days: int) -> tuple[np.ndarray, np.ndarray]:
    """Buying and selling price windows of the first ``days`` days from ``hour`` on."""
    flat = prices.ravel()
    idx = (np.arange(days)[:, None] * prices.shape[1] + hour + np.arange(N)) % flat.size
    buy = flat[idx]
    return buy, 0.5 * buy


def column_relative(grad: np.ndarray, ref: np.ndarray) -> float:
    """Largest deviation relative to the largest entry of its column (d pi_o / d theta)."""
    scale = np.maximum(np.abs(ref).max(axis=-2, keepdims=True), 1e-300)
    return float(np.max(np.abs(grad - ref) / scale))


def kkt_residual(mpc: MPC, sol: BatchSolution, d: int, tau: float) -> float:
    """max |R| of the barrier problem's KKT conditions (CasADi), relative to 1 + max |p|."""
    y = np.concatenate([sol.x[d], sol.lam[d], sol.mu[d]])
    r = np.array(mpc.kkt.residual(y, sol.p[d], tau)).ravel()
    return float(np.max(np.abs(r)) / (1.0 + np.max(np.abs(sol.p[d]))))


_MPCS: dict = {}


def cached_mpc(**system) -> MPC:
    key = tuple(sorted(system.items()))
    if key not in _MPCS:
        _MPCS[key] = MPC(SystemConfig(**system))
    return _MPCS[key]


# -- agreement with the batch solver and the reference ----------------------------------------
SCENARIOS = {
    # name: (system, theta kind, soc0 range, hour, days)
    "nominal": ({}, "nominal", (0.05, 0.95), 7, 10),
    "grid-binds": ({"P_bar": 0.5}, "mild", (0.05, 0.95), 17, 8),
    "soft-low": ({}, "mild", (0.0, 0.08), 3, 8),
    "soft-high": ({"P_bar": 1.0}, "quadratic", (0.92, 1.0), 19, 8),
    "learned": ({}, "quadratic", (0.05, 0.95), 11, 8),
    "n=1": ({"n": 1, "P_bar": 0.5}, "mild", (0.05, 0.95), 5, 6),
    "n=5": ({"n": 5, "P_bar": 1.0}, "mild", (0.05, 0.95), 9, 6),
    "N=1": ({"N": 1}, "quadratic", (0.0, 1.0), 20, 6),
    "N=2": ({"n": 2, "N": 2, "P_bar": 0.6}, "mild", (0.0, 1.0), 13, 6),
}


@pytest.fixture(scope="module", params=[(name, tau) for tau in TAUS for name in sorted(SCENARIOS)],
                ids=lambda p: f"{p[0]}-tau={p[1]:g}")
def scenario(request, prices):
    """Kernel (both factorisations), batch and IPOPT solutions of one scenario."""
    name, tau = request.param
    config = MPCConfig(tau=tau)
    system_kw, kind, (lo, hi), hour, days = SCENARIOS[name]
    mpc = cached_mpc(**system_kw)
    system = mpc.system
    rng = np.random.default_rng([SEED, sorted(SCENARIOS).index(name)])
    theta = (Theta.nominal(system) if kind == "nominal"
             else convex_theta(rng, system.n, quadratic=kind == "quadratic"))
    soc0 = rng.uniform(lo, hi, (days, system.n))
    buy, sell = windows(prices, hour, system.N, days)
    batch = BatchSolver(mpc, config)
    ref = batch.solve_batch(soc0, buy, sell, theta)
    ipopt = IpoptSolver(mpc, config).solve_batch(soc0, buy, sell, theta)
    kernels = {m: KernelSolver(mpc, config, method=m) for m in METHODS}
    sols = {m: k.solve_batch(soc0, buy, sell, theta) for m, k in kernels.items()}
    return {
        "name": name, "tau": tau, "mpc": mpc, "kernels": kernels, "sols": sols, "batch": ref,
        "ipopt": ipopt,
        "sens": {m: kernels[m].sensitivity(sols[m]) for m in METHODS},
        "sens_on_ipopt": {m: kernels[m].sensitivity(ipopt) for m in METHODS},
        "batch_sens": batch.sensitivity(ref),
        "batch_sens_on_ipopt": batch.sensitivity(ipopt),
        "ref_sens": PolicySensitivity(mpc, config)(ipopt),
    }


@pytest.mark.parametrize("method", METHODS)
def test_same_iteration_as_the_batch_solver(scenario, method):
    sol, ref = scenario["sols"][method], scenario["batch"]
    assert sol.success.all() and ref.success.all()
    assert sol.status == ref.status and set(sol.status) == {STATUS_CONVERGED}
    np.testing.assert_allclose(sol.action, ref.action, rtol=0, atol=1e-9)
    np.testing.assert_allclose(sol.x, ref.x, rtol=0, atol=1e-9)
    for a, b in ((sol.lam, ref.lam), (sol.mu, ref.mu)):
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-9 * (1.0 + np.abs(b).max()))
    np.testing.assert_allclose(sol.cost, ref.cost, rtol=1e-12, atol=1e-9)
    np.testing.assert_array_equal(sol.p, ref.p)
    # the same path: the same Newton steps (one more or less only where the stopping test is
    # decided at the rounding floor)
    assert np.max(np.abs(sol.iterations - ref.iterations)) <= 1
    assert np.mean(sol.iterations == ref.iterations) >= 0.8
    assert sol.backend == "kernel" and sol.solve_time > 0


@pytest.mark.parametrize("method", METHODS)
def test_same_solution_as_ipopt(scenario, method):
    sol, ref, mpc, tau = scenario["sols"][method], scenario["ipopt"], scenario["mpc"], \
        scenario["tau"]
    assert ref.success.all()
    np.testing.assert_allclose(sol.action, ref.action, rtol=0, atol=1e-9)
    np.testing.assert_allclose(sol.action, sol.x @ mpc.policy_selector.T, atol=0)
    for d in range(len(sol)):
        assert kkt_residual(mpc, sol, d, tau) < 1e-12
        f, _, h = mpc.evaluate(sol.x[d], sol.p[d])
        assert np.all(h < 0)
        np.testing.assert_allclose(sol.mu[d] * h, -tau, rtol=1e-8)
        assert sol.cost[d] == pytest.approx(f, rel=1e-12)


@pytest.mark.parametrize("method", METHODS)
def test_same_sensitivities_as_the_batch_solver_and_the_reference(scenario, method):
    mine, batch, ref = scenario["sens"][method], scenario["batch_sens"], scenario["ref_sens"]
    assert mine.ok.all() and batch.ok.all() and ref.ok.all()
    assert mine.reason == ("",) * len(mine.ok)
    assert column_relative(mine.grad, batch.grad) <= 1e-8
    # on IPOPT's solution: the batch solver's to 1e-8, the CasADi QR reference's to 1e-6 (it
    # loses digits at tau = 1e-4: 2e-7 of the column's largest entry for n = 1, where the
    # batch solver and the kernel agree to 1e-15)
    on_ipopt = scenario["sens_on_ipopt"][method]
    assert on_ipopt.ok.all()
    assert column_relative(on_ipopt.grad, scenario["batch_sens_on_ipopt"].grad) <= 1e-8
    assert column_relative(on_ipopt.grad, ref.grad) <= 1e-6
    np.testing.assert_allclose(mine.cond, batch.cond, rtol=1e-6)
    np.testing.assert_allclose(on_ipopt.cond, ref.cond, rtol=1e-6)
    n = scenario["mpc"].n
    for part in CONSTANT_PARTS:
        assert np.all(mine.grad[:, Theta.index(n, part)] == 0.0)


@pytest.mark.parametrize("n, tau", [(1, 1e-5), (2, 1e-5), (3, 1e-4), (3, 1e-5)])
@pytest.mark.parametrize("method", METHODS)
def test_sensitivity_is_exact_where_the_grid_binds(prices, n, tau, method):
    """Against a binding grid limit the adjoint is a small difference of large terms; the
    refined adjoint matches one computed with extended-precision residuals entry by entry
    (entries above 1e-6 of their column's largest, to 1e-8 relative)."""
    mpc = cached_mpc(n=n, P_bar=0.5)
    rng = np.random.default_rng(30 + n)
    theta = convex_theta(rng, n, quadratic=n == 2)
    buy, sell = windows(prices, 2 + 5 * n, mpc.N, 3)
    soc0 = rng.uniform(0.0, 0.5 if n == 2 else 1.0, (3, n))
    solver = KernelSolver(mpc, MPCConfig(tau=tau), method=method)
    sol = solver.solve_batch(soc0, buy, sell, theta)
    sens = solver.sensitivity(sol)
    assert sol.success.all() and sens.ok.all()
    S_y = np.zeros((mpc.n, mpc.kkt.ny))
    S_y[:, : mpc.nx] = mpc.policy_selector
    binding = 0
    for d in range(len(sol)):
        y = np.concatenate([sol.x[d], sol.lam[d], sol.mu[d]])
        _, _, h = mpc.evaluate(sol.x[d], sol.p[d])
        grid = h.reshape(mpc.N, -1)[:, 4 * n : 4 * n + 2]
        binding += int(np.any(grid > -1e-3))
        K, R_theta = mpc.kkt.jacobians(y, sol.p[d], tau)
        Kt, R_theta = np.array(K.full()).T, np.array(R_theta.full())
        Z = np.linalg.solve(Kt, S_y.T)
        for _ in range(3):  # iterative refinement with extended-precision residuals
            r = S_y.T.astype(np.longdouble) - Kt.astype(np.longdouble) @ Z.astype(np.longdouble)
            Z = Z + np.linalg.solve(Kt, np.asarray(r, dtype=float))
        exact = -R_theta.T @ Z
        colmax = np.abs(exact).max(axis=0, keepdims=True)
        big = np.abs(exact) > 1e-6 * colmax
        rel = np.abs(sens.grad[d] - exact) / np.maximum(np.abs(exact), 1e-300)
        assert np.max(np.where(big, rel, 0.0)) <= 1e-8
    assert binding > 0  # the scenario does what it says


@pytest.mark.parametrize("n, N, P_bar", [(12, 12, 6.0), (20, 6, 3.0), (3, 30, 1.5)])
def test_factorisations_and_adjoints_agree(prices, n, N, P_bar):
    """Both factorisations and both adjoints (column by column with refinement, structured)
    give the same solutions and sensitivities, also in sizes the tests above do not cover."""
    mpc = cached_mpc(n=n, N=N, P_bar=P_bar)
    rng = np.random.default_rng(n * 100 + N)
    theta = convex_theta(rng, n)
    buy, sell = windows(prices, 8, N, 3)
    soc0 = rng.uniform(0.05, 0.95, (3, n))
    stage, agent = (KernelSolver(mpc, method=m) for m in METHODS)
    s1, s2 = stage.solve_batch(soc0, buy, sell, theta), agent.solve_batch(soc0, buy, sell, theta)
    assert s1.success.all() and s2.success.all()
    np.testing.assert_allclose(s1.x, s2.x, atol=1e-10)
    grads = [stage.sensitivity(s1)]
    for structured in (False, True):
        agent.structured_adjoint = structured
        grads.append(agent.sensitivity(s2))
    for g in grads:
        assert g.ok.all()
        assert column_relative(g.grad, grads[0].grad) <= 1e-9
        np.testing.assert_allclose(g.cond, grads[0].cond, rtol=1e-8)
    ref = BatchSolver(mpc).sensitivity(s1)
    assert column_relative(grads[0].grad, ref.grad) <= 1e-8


# -- interface, warm starts and failures ------------------------------------------------------
def test_auto_method_and_structured_adjoint_follow_the_size():
    assert KernelSolver(cached_mpc()).method == "stage"
    assert KernelSolver(cached_mpc(N=48)).method == "stage"
    big = KernelSolver(cached_mpc(n=40, P_bar=20.0))
    assert big.method == "agent" and big.structured_adjoint
    with pytest.raises(ValueError, match="method"):
        KernelSolver(cached_mpc(), method="dense")


def test_single_solve_equals_batch_row(prices):
    mpc = cached_mpc()
    solver = KernelSolver(mpc)
    theta = Theta.nominal(mpc.system)
    buy, sell = windows(prices, 4, mpc.N, 3)
    soc0 = np.array([[0.2, 0.5, 0.8], [0.6, 0.6, 0.6], [0.9, 0.1, 0.4]])
    batch = solver.solve_batch(soc0, buy, sell, theta)
    single = solver.solve(soc0[1], buy[1], sell[1], theta)
    np.testing.assert_array_equal(single.x, batch.x[1])
    assert single.success and single.status == STATUS_CONVERGED
    np.testing.assert_array_equal(solver.sensitivity(single).grad[0],
                                  solver.sensitivity(batch).grad[1])


@pytest.mark.parametrize("method", METHODS)
def test_results_do_not_depend_on_the_thread_count(prices, method):
    """Problems spread over threads (any number) give the one-thread call's solutions and
    sensitivities bit for bit, failed rows too; few problems stay on one thread."""
    from mpcrl_lite.mpc.backends import kernel as kernel_module

    mpc = cached_mpc(P_bar=1.0)
    theta = Theta.nominal(mpc.system)
    rng = np.random.default_rng(11)
    days = 4 * kernel_module.THREAD_MIN_PROBLEMS + 3
    soc0 = rng.uniform(0.0, 1.0, (days, mpc.n))
    buy, sell = windows(prices, 9, mpc.N, days)

    def run(threads, max_iter=None):
        config = MPCConfig() if max_iter is None else MPCConfig(max_iter=max_iter)
        solver = KernelSolver(mpc, config, method=method)
        solver.threads = threads
        sol = solver.solve_batch(soc0, buy, sell, theta)
        return solver._threads(days), sol, solver.sensitivity(sol)

    used, ref, ref_sens = run(1)
    assert used == 1
    for threads in (2, 3, 7, None):
        used, sol, sens = run(threads)
        if threads is not None:
            assert used == min(threads, 4)
        for a, b in ((sol.x, ref.x), (sol.lam, ref.lam), (sol.mu, ref.mu), (sol.cost, ref.cost),
                     (sol.iterations, ref.iterations), (sol.action, ref.action),
                     (sens.grad, ref_sens.grad), (sens.cond, ref_sens.cond)):
            np.testing.assert_array_equal(a, b)
        assert sol.status == ref.status and np.array_equal(sens.ok, ref_sens.ok)
    _, short, short_sens = run(1, max_iter=3)
    _, short2, short2_sens = run(3, max_iter=3)
    assert not short.success.all() and short.status == short2.status
    np.testing.assert_array_equal(short.x, short2.x)
    np.testing.assert_array_equal(short_sens.grad, short2_sens.grad)
    assert KernelSolver(mpc)._threads(2 * kernel_module.THREAD_MIN_PROBLEMS - 1) == 1
    two = KernelSolver(mpc)
    two.threads = 2
    assert two._threads(30) == 2  # a learning month's call (30 days) uses both cores
    if method == "stage" and sys.platform.startswith("linux"):
        # a forked child has no helper threads of its parent's: it starts its own
        import multiprocessing

        with multiprocessing.get_context("fork").Pool(1) as pool:
            used, x = pool.apply(_solve_in_child, (soc0, buy, sell))
        assert used == 1
        np.testing.assert_array_equal(x, ref.x)


def _solve_in_child(soc0, buy, sell):
    """A child process: the automatic thread count, and the solutions with 2 threads forced."""
    mpc = cached_mpc(P_bar=1.0)
    solver = KernelSolver(mpc)
    used = solver._threads(len(soc0))
    solver.threads = 2
    return used, solver.solve_batch(soc0, buy, sell, Theta.nominal(mpc.system)).x


def test_shift_and_input_errors():
    mpc = cached_mpc()
    solver = KernelSolver(mpc)
    theta = Theta.nominal(mpc.system)
    buy = np.full((2, mpc.N), 50.0)
    with pytest.raises(ValueError, match="x0"):
        solver.solve_batch(np.full((2, 3), 0.5), buy, buy, theta, x0=np.zeros((2, 5)))
    with pytest.raises(ValueError, match="non-finite"):
        solver.solve_batch(np.full((2, 3), np.nan), buy, buy, theta)
    with pytest.raises(ValueError, match="soc0"):
        solver.solve_batch(np.full((2, 4), 0.5), buy, buy, theta)


def test_warm_start_is_the_batch_solvers(prices):
    """A warm start (shifted plan, garbage, switched off) takes the batch solver's path."""
    mpc = cached_mpc()
    solver, batch = KernelSolver(mpc), BatchSolver(mpc)
    theta = Theta.nominal(mpc.system)
    rng = np.random.default_rng(5)
    soc = rng.uniform(0.2, 0.8, (6, 3))
    buy, sell = windows(prices, 6, mpc.N, 6)
    first = solver.solve_batch(soc, buy, sell, theta)
    soc_next = np.clip(soc + mpc.system.alpha * first.action, 0, 1)
    buy, sell = windows(prices, 7, mpc.N, 6)
    cold = solver.solve_batch(soc_next, buy, sell, theta)
    garbage = np.full_like(first.x, np.nan)
    garbage[:3] = 5.0
    for x0 in (mpc.shift(first.x), garbage):
        warm = solver.solve_batch(soc_next, buy, sell, theta, x0=x0)
        ref = batch.solve_batch(soc_next, buy, sell, theta, x0=x0)
        assert warm.success.all()
        np.testing.assert_array_equal(warm.iterations, ref.iterations)
        np.testing.assert_allclose(warm.x, ref.x, atol=1e-10)
        np.testing.assert_allclose(warm.x, cold.x, atol=1e-8)
    off = KernelSolver(mpc, MPCConfig(warm_start=False))
    ignored = off.solve_batch(soc_next, buy, sell, theta, x0=garbage)
    np.testing.assert_array_equal(ignored.iterations, cold.iterations)


def test_failure_is_reported_per_problem_with_the_fallback(prices):
    mpc = cached_mpc()
    buy, sell = windows(prices, 0, mpc.N, 4)
    theta = Theta.nominal(mpc.system)
    sol = KernelSolver(mpc, MPCConfig(max_iter=1)).solve_batch(np.full((4, 3), 0.5), buy, sell,
                                                               theta)
    ref = BatchSolver(mpc, MPCConfig(max_iter=1)).solve_batch(np.full((4, 3), 0.5), buy, sell,
                                                              theta)
    assert not sol.success.any() and sol.failures == 4
    assert set(sol.status) == {STATUS_MAX_ITER}
    assert np.all(sol.action == 0.0) and np.all(sol.iterations == 1)
    np.testing.assert_allclose(sol.x, ref.x, atol=1e-12)  # the same first step
    for arr in (sol.x, sol.lam, sol.mu, sol.cost):
        assert np.all(np.isfinite(arr))
    sens = KernelSolver(mpc).sensitivity(sol)
    assert not sens.ok.any() and np.all(sens.grad == 0.0)
    assert all(r.startswith("solver failed") for r in sens.reason)


@pytest.mark.parametrize("method", METHODS)
def test_breakdown_is_a_failure_not_an_exception(prices, method):
    """A non-convex theta (phi1 very negative) breaks the factorisation: the problems fail
    like the batch solver's, nothing raises and no NaN leaks into the actions."""
    mpc = cached_mpc()
    theta = Theta.nominal(mpc.system).replace(phi1=np.full(3, -1e6))
    buy, sell = windows(prices, 12, mpc.N, 4)
    solver = KernelSolver(mpc, method=method)
    sol = solver.solve_batch(np.full((4, 3), 0.5), buy, sell, theta)
    ref = BatchSolver(mpc).solve_batch(np.full((4, 3), 0.5), buy, sell, theta)
    assert sol.status == ref.status and STATUS_BREAKDOWN in sol.status
    assert np.all(np.isfinite(sol.action)) and np.all(sol.action[~sol.success] == 0.0)
    sens = solver.sensitivity(sol)
    assert np.all(np.isfinite(sens.grad)) and not sens.ok[~sol.success].any()


def test_sensitivity_reports_unusable_solutions_and_mixed_thetas(prices):
    mpc = cached_mpc()
    solver = KernelSolver(mpc)
    rng = np.random.default_rng(9)
    buy, sell = windows(prices, 14, mpc.N, 2)
    sols = [solver.solve_batch(rng.uniform(0.2, 0.8, (2, 3)), buy, sell, th)
            for th in (Theta.nominal(mpc.system), convex_theta(rng, 3))]
    mixed = BatchSolution.stack([sols[0][0], sols[1][0], sols[0][1]], 0.0, "kernel")
    sens = solver.sensitivity(mixed)
    separate = [solver.sensitivity(s).grad for s in sols]
    np.testing.assert_array_equal(sens.grad, np.stack([separate[0][0], separate[1][0],
                                                       separate[0][1]]))
    mu = sols[0].mu.copy()
    mu[1, 0] = 0.0
    broken = BatchSolution(sols[0].action, sols[0].x, sols[0].lam, mu, sols[0].cost,
                           sols[0].success, sols[0].status, sols[0].iterations, sols[0].p)
    sens = solver.sensitivity(broken)
    assert sens.ok[0] and not sens.ok[1] and "interior" in sens.reason[1]
    assert np.all(sens.grad[1] == 0.0)
    tight = KernelSolver(mpc, MPCConfig(kkt_cond_max=1.0 + 1e-9)).sensitivity(sols[0])
    assert not tight.ok.any() and all("ill-conditioned" in r for r in tight.reason)
    assert np.all(tight.grad == 0.0) and np.all(tight.grad_soc0 == 0.0)
    assert sens.reason[0] == "" and len(tight.reason) == len(sols[0].success)


def test_formulation_mismatch_raises_at_the_first_solve():
    """The kernels' hand-written QP must be the CasADi formulation's: a changed formulation
    (here the prices' discount, seen through qp_function) is caught before the solver gives
    its first solution (the kernels are loaded and checked at the first solve, so that
    building a solver stays cheap), and again at every later attempt."""
    system = SystemConfig()
    mpc = MPC(system)
    original = mpc.qp_function

    def changed(p):
        H, q, c, A, e, C, d = original(p)
        return H, 1.01 * q, c, A, e, C, d

    mpc.qp_function = changed
    solver = KernelSolver(mpc)
    buy = np.linspace(20.0, 80.0, system.N)
    for _ in range(2):
        with pytest.raises(RuntimeError, match="formulation"):
            solver.solve(np.full(system.n, 0.5), buy, 0.9 * buy, Theta.nominal(system))


# -- compilation and cache --------------------------------------------------------------------
def test_warm_up_is_cheap_once_compiled_and_the_cache_is_where_it_says():
    assert warm_up() < 5.0
    assert Path(cache_dir()).is_dir()
    assert any(Path(cache_dir()).glob("kernel_core.solve_rows-*.nbi"))


def test_compile_notice_is_one_line(caplog):
    notice = jit.CompileNotice("the MPC kernels", _kernel.cache_dir())
    with caplog.at_level(logging.WARNING, logger="mpcrl_lite.kernels"):
        notice.on_start(None)
        notice.on_start(None)
    assert len(caplog.records) == 1 and "compiling" in caplog.records[0].getMessage()


def test_cache_falls_back_to_a_temporary_folder():
    """Where numba finds no writable cache folder (here: only the NUMBA_CACHE_DIR locator is
    allowed and it is unset), the kernels are cached in the temporary directory instead of
    failing at import. Nothing is compiled."""
    env = {k: v for k, v in os.environ.items() if k != "NUMBA_CACHE_DIR"}
    env["NUMBA_CACHE_LOCATOR_CLASSES"] = "UserProvidedCacheLocator"
    env["PYTHONPATH"] = os.pathsep.join([str(REPO), env.get("PYTHONPATH", "")])
    code = ("import json, tempfile; from mpcrl_lite.mpc.backends import kernel_core as _kernel; "
            "print(json.dumps([_kernel.cache_dir(), tempfile.gettempdir()]))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env,
                         cwd=str(REPO), check=True)
    where, tmp = json.loads(out.stdout.splitlines()[-1])
    assert where.startswith(os.path.join(tmp, "mpcrl_lite-numba-"))


# -- learning ---------------------------------------------------------------------------------
def test_learning_run_is_the_batch_back_ends():
    """Two learning months (exploration, sensitivities, LSTD, DPG updates, one evaluation)
    with the kernel give the batch back-end's history to 1e-8."""
    learning = LearningConfig(months=2, eval_every=1)
    runs = {}
    for name in ("batch", "kernel"):
        exp = Experiment(mpc_config=MPCConfig(backend="batch"), learning=learning)
        if name == "kernel":
            exp.solver = KernelSolver(exp.mpc, exp.mpc_config)
            exp.history.backend = exp.solver.name
        runs[name] = exp.run(progress=False)
    ref, fast = runs["batch"], runs["kernel"]
    assert fast.backend == "kernel" and ref.backend == "batch"
    np.testing.assert_allclose(fast.J, ref.J, rtol=1e-8)
    np.testing.assert_allclose(fast.J_eval, ref.J_eval, rtol=1e-8)
    np.testing.assert_allclose(fast.theta_final, ref.theta_final, rtol=1e-8, atol=1e-12)
    assert fast.solver_failures == ref.solver_failures == [0, 0]
    assert fast.skipped_steps == ref.skipped_steps


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("P_bar", [1.5, 0.5])
def test_sensitivity_in_the_initial_soc_is_the_central_difference(prices, method, P_bar):
    """``Sensitivity.grad_soc0`` (the adjoint's multiplier of the first dynamics rows) equals
    central differences of the action in the initial soc, states outside [0.1, 0.9] and a
    binding grid limit included; failed rows give zeros; the structured adjoint gives none."""
    mpc = cached_mpc(P_bar=P_bar)
    rng = np.random.default_rng(8)
    days = 24
    soc0 = rng.uniform(-0.05, 1.05, (days, mpc.n))
    buy, sell = windows(prices, 16, mpc.N, days)
    solver = KernelSolver(mpc, method=method)
    theta = convex_theta(rng, mpc.n)
    sol = solver.solve_batch(soc0, buy, sell, theta)
    sens = solver.sensitivity(sol)
    assert sens.ok.all() and sens.grad_soc0.shape == (days, mpc.n, mpc.n)
    h = 1e-5
    fd = np.empty((days, mpc.n, mpc.n))
    for i in range(mpc.n):
        step = np.zeros(mpc.n)
        step[i] = h
        up = solver.solve_batch(soc0 + step, buy, sell, theta, x0=sol.x).action
        down = solver.solve_batch(soc0 - step, buy, sell, theta, x0=sol.x).action
        fd[:, i, :] = (up - down) / (2 * h)
    assert np.abs(fd).max() > 0.1
    np.testing.assert_allclose(sens.grad_soc0, fd, atol=1e-6 * np.abs(fd).max())
    short = KernelSolver(mpc, MPCConfig(max_iter=2), method=method)
    failed = short.solve_batch(soc0, buy, sell, theta)
    bad = short.sensitivity(failed)
    assert not bad.ok.all()
    assert np.all(bad.grad_soc0[~bad.ok] == 0.0)
    many = KernelSolver(mpc, method="agent")
    many.structured_adjoint = True
    assert many.sensitivity(sol).grad_soc0 is None
