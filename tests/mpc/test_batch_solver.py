"""Tests of the batch interior point (mpcrl_lite.mpc.backends.batch, with its structured KKT system
mpcrl_lite.mpc.backends.batch_kkt and its sensitivities mpcrl_lite.mpc.backends.batch_adjoint).

The batch back-end must solve the same barrier problem as the IPOPT reference
(:class:`~mpcrl_lite.mpc.backends.registry.IpoptSolver`) and return the same sensitivities as
:class:`~mpcrl_lite.mpc.sensitivity.PolicySensitivity`: its QP data equal the CasADi formulation's,
its closed-form ``dR/dtheta`` equals CasADi's, and its solutions satisfy the KKT conditions to
rounding level, over states near the soft soc bounds, a binding grid limit, random thetas and
several sizes. Failures are reported per problem without exceptions.
"""

from __future__ import annotations

import logging
import time

import numpy as np
import pytest
from conftest import convex_theta

import mpcrl_lite.mpc.backends.batch_adjoint as adjoint
from mpcrl_lite.config import MPCConfig, SystemConfig
from mpcrl_lite.mpc.backends.batch import BatchSolver
from mpcrl_lite.mpc.backends.batch_adjoint import grad_weights
from mpcrl_lite.mpc.backends.registry import make_solver
from mpcrl_lite.mpc.formulation import MPC
from mpcrl_lite.mpc.sensitivity import PolicySensitivity
from mpcrl_lite.mpc.solution import STATUS_CONVERGED, STATUS_MAX_ITER, BatchSolution
from mpcrl_lite.theta import PARTS, Theta

SEED = 20240601  # random states and thetas of the scenarios
#: barrier parameters of the comparisons: the project's default and a small one (the policy is
#: then close to bang-bang and the KKT systems are the hardest)
TAUS = sorted({MPCConfig().tau, 1e-4})


# -- helpers ----------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def prices() -> np.ndarray:
    """A month of random buying prices, 30 days x 24 hours, 5..130 NOK/MWh."""
    return np.random.default_rng(2024).uniform(5.0, 130.0, (30, 24))


def windows(prices: np.ndarray, hour: int, N: int, days: int) -> tuple[np.ndarray, np.ndarray]:
    """Buying and selling price windows of the first ``days`` days from ``hour`` on (past
    midnight into the next day; the month repeats)."""
    flat = prices.ravel()
    idx = (np.arange(days)[:, None] * prices.shape[1] + hour + np.arange(N)) % flat.size
    buy = flat[idx]
    return buy, 0.5 * buy


def assert_sensitivities_match(grad: np.ndarray, ref: np.ndarray, rtol: float = 1e-5) -> None:
    """Entries larger than 1e-6 of their column's largest agree to ``rtol``."""
    colmax = np.abs(ref).max(axis=1, keepdims=True)
    mask = np.abs(ref) > 1e-6 * colmax
    err = np.abs(grad - ref)
    worst = float(np.max(np.where(mask, err / np.maximum(np.abs(ref), 1e-300), 0.0)))
    assert worst <= rtol, f"largest relative deviation {worst:.2e}"


def kkt_residual(mpc: MPC, sol: BatchSolution, d: int, tau: float) -> float:
    """max |R| of the barrier problem's KKT conditions (CasADi), relative to 1 + max |p|."""
    y = np.concatenate([sol.x[d], sol.lam[d], sol.mu[d]])
    r = np.array(mpc.kkt.residual(y, sol.p[d], tau)).ravel()
    return float(np.max(np.abs(r)) / (1.0 + np.max(np.abs(sol.p[d]))))


# -- the formulation --------------------------------------------------------------------------
@pytest.mark.parametrize("n, N", [(1, 3), (2, 4), (3, 12)])
def test_qp_data_match_the_casadi_formulation(n, N, mpc_of):
    """Dense H, q, c, A, e, C, d assembled from the solver's structured operators equal
    MPC.qp_data at random parameters (incl. soc0 outside [0.1, 0.9] and a random theta)."""
    mpc = mpc_of(n=n, N=N, P_bar=0.5 * n)
    kkt = BatchSolver(mpc).kkt
    rng = np.random.default_rng(n * 100 + N)
    for soc0 in (rng.uniform(0, 1, n), np.full(n, 0.03), np.full(n, 0.97)):
        p = mpc.parameters(soc0, rng.uniform(5, 130, N), rng.uniform(5, 60, N),
                           convex_theta(rng, n, quadratic=True))
        ref = mpc.qp_data(p)
        data = kkt.batch_data(p[None])
        eye_x = kkt.to_internal_x(np.eye(mpc.nx))  # unit vectors as a batch
        eye_lam = kkt.to_internal_lam(np.eye(mpc.neq))
        zeros_x = np.zeros_like(eye_x)
        q_int = kkt.grad_lag_part(np.zeros((1,) + eye_x.shape[1:]),
                                      np.zeros((1,) + eye_lam.shape[1:]), data)
        q = kkt.from_internal_x(q_int)[0]
        H = kkt.from_internal_x(
            kkt.grad_lag_part(eye_x, np.zeros((mpc.nx,) + eye_lam.shape[1:]), data)
            - q_int)
        A = kkt.from_internal_lam(kkt.apply_A(eye_x, data))
        At = kkt.from_internal_x(kkt.grad_lag_part(zeros_x[: mpc.neq], eye_lam, data)
                                     - q_int)
        C = -kkt.mu_to_flat(kkt.slacks(eye_x, offset=False))
        Ct = kkt.from_internal_x(kkt.apply_Ct(kkt.mu_from_flat(np.eye(mpc.nin))))
        d = kkt.mu_to_flat(kkt.slacks(np.zeros((1,) + eye_x.shape[1:])))[0]
        np.testing.assert_allclose(H, ref.H, atol=1e-12)
        np.testing.assert_allclose(q, ref.q, rtol=1e-13, atol=1e-12)
        np.testing.assert_allclose(data.c[0], ref.c, rtol=1e-13, atol=1e-12)
        np.testing.assert_array_equal(A.T, ref.A)  # rows of A.T are A applied to unit vectors
        np.testing.assert_allclose(At, ref.A, atol=1e-12)  # rows: A' applied to unit vectors
        np.testing.assert_allclose(kkt.from_internal_lam(data.e)[0], ref.e, atol=1e-15)
        np.testing.assert_array_equal(C.T, ref.C)
        np.testing.assert_array_equal(Ct, ref.C)
        np.testing.assert_array_equal(d, ref.d)


def test_formulation_change_is_detected_at_construction():
    """A QP that differs from the solver's numpy model raises at construction, not mid-run."""
    mpc = MPC(SystemConfig())
    original = mpc.qp_function

    def altered(p):
        H, q, c, A, e, C, d = original(p)
        return H, q + 1.0, c, A, e, C, d

    mpc.qp_function = altered
    with pytest.raises(RuntimeError, match="disagree with MPC.qp_function"):
        BatchSolver(mpc)


def test_dR_dtheta_matches_casadi(mpc_of):
    """The closed-form -dR/dtheta (weights on Zb, Zs, Zsoc, Zlam) equals CasADi's Jacobian
    at a random point; the rows of sigma_hi, sigma_lo and mu do not depend on theta."""
    n, N = 2, 5
    mpc = mpc_of(n=n, N=N)
    kkt = BatchSolver(mpc).kkt
    rng = np.random.default_rng(7)
    p = mpc.parameters(rng.uniform(0, 1, n), rng.uniform(5, 130, N), rng.uniform(5, 60, N),
                       convex_theta(rng, n))
    y = rng.normal(size=mpc.kkt.ny)
    _, R_theta = mpc.kkt.jacobians(y, p, 1e-4)
    ref = -np.array(R_theta.full()).T  # (n_theta, ny)
    x, lam = y[: mpc.nx], y[mpc.nx : mpc.nx + mpc.neq]
    X, L = kkt.to_internal_x(x[None]), kkt.to_internal_lam(lam[None])
    wb, ws, wsoc, wl = grad_weights(kkt, X, L)  # (1, n, parts, N)
    mine = np.zeros((mpc.n_theta, mpc.nx + mpc.neq))
    for i in range(n):
        for k in range(len(PARTS)):
            row = k * n + i
            for j in range(N):
                mine[row, mpc.index("b", j)[i]] = wb[0, i, k, j]
                mine[row, mpc.index("s", j)[i]] = ws[0, i, k, j]
                mine[row, mpc.index("soc", j)[i]] = wsoc[0, i, k, j]
                mine[row, mpc.nx + j * n + i] = wl[0, i, k, j]
    np.testing.assert_allclose(ref[:, : mpc.nx + mpc.neq], mine, atol=1e-12)
    assert np.all(ref[:, mpc.nx + mpc.neq :] == 0.0)


# -- agreement with the reference -------------------------------------------------------------
SCENARIOS = {
    # name: (system, theta kind, soc0 range, hour, days)
    "nominal": ({}, "nominal", (0.05, 0.95), 7, 10),
    "grid-binds": ({"P_bar": 0.5}, "mild", (0.05, 0.95), 17, 8),
    "soft-low": ({}, "mild", (0.0, 0.08), 3, 8),
    "soft-high": ({"P_bar": 1.0}, "quadratic", (0.92, 1.0), 19, 8),
    "learned": ({}, "quadratic", (0.05, 0.95), 11, 8),
    "n=1": ({"n": 1, "P_bar": 0.5}, "mild", (0.05, 0.95), 5, 6),
    "n=5": ({"n": 5, "P_bar": 1.0}, "mild", (0.05, 0.95), 9, 6),
    "N=3": ({"N": 3}, "quadratic", (0.0, 1.0), 20, 6),
}


@pytest.fixture(scope="module", params=[(name, tau) for tau in TAUS for name in sorted(SCENARIOS)],
                ids=lambda p: f"{p[0]}-tau={p[1]:g}")
def scenario(request, prices, mpc_of, ipopt_at):
    """Both back-ends' solutions and sensitivities of one scenario."""
    name, tau = request.param
    config = MPCConfig(tau=tau)
    system_kw, kind, (lo, hi), hour, days = SCENARIOS[name]
    mpc = mpc_of(**system_kw)
    system = mpc.system
    rng = np.random.default_rng([SEED, sorted(SCENARIOS).index(name)])
    theta = (Theta.nominal(system) if kind == "nominal"
             else convex_theta(rng, system.n, quadratic=kind == "quadratic"))
    soc0 = rng.uniform(lo, hi, (days, system.n))
    buy, sell = windows(prices, hour, system.N, days)
    batch = BatchSolver(mpc, config)
    ours = batch.solve_batch(soc0, buy, sell, theta)
    ref = ipopt_at(tau, on=mpc).solve_batch(soc0, buy, sell, theta)
    return {
        "name": name, "tau": tau, "mpc": mpc, "batch": batch, "ours": ours, "ref": ref,
        "grad": batch.sensitivity(ours), "grad_on_ref": batch.sensitivity(ref),
        "grad_ref": PolicySensitivity(mpc, config)(ref),
    }


def test_same_solution_as_ipopt(scenario):
    ours, ref = scenario["ours"], scenario["ref"]
    assert ours.success.all() and ref.success.all()
    assert set(ours.status) == {STATUS_CONVERGED}
    np.testing.assert_allclose(ours.action, ref.action, rtol=0, atol=1e-6)
    np.testing.assert_allclose(ours.x, ref.x, rtol=0, atol=1e-7)
    for a, b in ((ours.lam, ref.lam), (ours.mu, ref.mu)):
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-7 * (1.0 + np.abs(b).max()))
    np.testing.assert_allclose(ours.cost, ref.cost, rtol=1e-10, atol=1e-8)
    np.testing.assert_array_equal(ours.p, ref.p)
    assert ours.backend == "batch" and ours.solve_time > 0


def test_solution_satisfies_the_barrier_kkt_conditions(scenario):
    mpc, ours, tau = scenario["mpc"], scenario["ours"], scenario["tau"]
    for d in range(len(ours)):
        assert kkt_residual(mpc, ours, d, tau) < 1e-12
        _, g, h = mpc.evaluate(ours.x[d], ours.p[d])
        assert np.all(h < 0)
        np.testing.assert_allclose(ours.mu[d] * h, -tau, rtol=1e-8)
        np.testing.assert_allclose(g, 0.0, atol=1e-13)
        assert ours.cost[d] == pytest.approx(mpc.evaluate(ours.x[d], ours.p[d])[0], rel=1e-12)
    np.testing.assert_allclose(ours.action, ours.x @ mpc.policy_selector.T, atol=0)
    assert np.all(scenario["batch"].residual(ours) < MPCConfig().tol)


def test_sensitivities_match_the_reference(scenario):
    """Ours on our solution and ours on IPOPT's solution both match PolicySensitivity on
    IPOPT's solution; the conditioning proxy is the same quantity."""
    ref = scenario["grad_ref"]
    assert ref.ok.all()
    for mine in (scenario["grad"], scenario["grad_on_ref"]):
        assert mine.ok.all(), mine.reason
        assert mine.grad.shape == ref.grad.shape
        assert_sensitivities_match(mine.grad, ref.grad)
    np.testing.assert_allclose(scenario["grad_on_ref"].cond, ref.cond, rtol=1e-6)
    # phi3 and T3 are constants of the cost
    n = scenario["mpc"].n
    for part in ("phi3", "T3"):
        assert np.all(scenario["grad"].grad[:, Theta.index(n, part)] == 0.0)


@pytest.mark.parametrize("n, tau", [(1, 1e-5), (2, 1e-5), (3, 1e-4)])
def test_sensitivity_is_exact_where_the_grid_binds(prices, n, tau, mpc_of):
    """Against a binding grid limit a battery's policy is nearly pinned and its adjoint is a
    small difference of large terms (the CasADi QR reference can lose several digits in
    small entries there); the refined adjoint matches one computed with extended-precision
    residuals to 1e-8 relative (entries above 1e-6 of their column's largest)."""
    mpc = mpc_of(n=n, P_bar=0.5)
    rng = np.random.default_rng(30 + n)
    theta = convex_theta(rng, n, quadratic=n == 2)
    buy, sell = windows(prices, 2 + 5 * n, mpc.N, 3)
    soc0 = rng.uniform(0.0, 0.5 if n == 2 else 1.0, (3, n))
    solver = BatchSolver(mpc, MPCConfig(tau=tau))
    sol = solver.solve_batch(soc0, buy, sell, theta)
    sens = solver.sensitivity(sol)
    assert sol.success.all() and sens.ok.all()
    S_y = np.zeros((mpc.n, mpc.kkt.ny))
    S_y[:, : mpc.nx] = mpc.policy_selector
    for d in range(len(sol)):
        y = np.concatenate([sol.x[d], sol.lam[d], sol.mu[d]])
        K, R_theta = mpc.kkt.jacobians(y, sol.p[d], tau)
        Kt, R_theta = np.array(K.full()).T, np.array(R_theta.full())
        Z = np.linalg.solve(Kt, S_y.T)
        for _ in range(3):  # iterative refinement with extended-precision residuals
            r = S_y.T.astype(np.longdouble) - Kt.astype(np.longdouble) @ Z.astype(np.longdouble)
            Z = Z + np.linalg.solve(Kt, np.asarray(r, dtype=float))
        exact = -R_theta.T @ Z
        assert_sensitivities_match(sens.grad[d : d + 1], exact[None], rtol=1e-8)


def test_structured_adjoint_for_many_agents(prices, monkeypatch, mpc_of):
    """The column-structured adjoint (used for many agents) agrees with the full one and,
    for n = 12, with the reference."""
    mpc = mpc_of(n=12, P_bar=6.0)
    theta = convex_theta(np.random.default_rng(12), 12)
    rng = np.random.default_rng(13)
    soc0 = rng.uniform(0.05, 0.95, (2, 12))
    buy, sell = windows(prices, 8, mpc.N, 2)
    solver = BatchSolver(mpc, MPCConfig(tau=1e-4))
    sol = solver.solve_batch(soc0, buy, sell, theta)
    assert sol.success.all()
    monkeypatch.setattr(adjoint, "_FULL_ADJOINT_MAX", 1 << 40)
    full = solver.sensitivity(sol)
    monkeypatch.setattr(adjoint, "_FULL_ADJOINT_MAX", 0)
    structured = solver.sensitivity(sol)
    assert full.ok.all() and structured.ok.all()
    np.testing.assert_allclose(structured.cond, full.cond, rtol=1e-6)
    scale = np.abs(full.grad).max(axis=1, keepdims=True)
    assert np.max(np.abs(structured.grad - full.grad) / scale) < 1e-8
    ref = PolicySensitivity(mpc, MPCConfig(tau=1e-4))(sol)
    assert_sensitivities_match(structured.grad, ref.grad, rtol=1e-4)


# -- interface, warm starts and failures ------------------------------------------------------
def test_single_solve_equals_batch_row(prices, mpc_of):
    mpc = mpc_of()
    solver = BatchSolver(mpc)
    theta = Theta.nominal(mpc.system)
    buy, sell = windows(prices, 4, mpc.N, 3)
    soc0 = np.array([[0.2, 0.5, 0.8], [0.6, 0.6, 0.6], [0.9, 0.1, 0.4]])
    batch = solver.solve_batch(soc0, buy, sell, theta)
    single = solver.solve(soc0[1], buy[1], sell[1], theta)
    np.testing.assert_allclose(single.x, batch.x[1], atol=1e-12)
    np.testing.assert_allclose(single.action, batch[1].action, atol=1e-12)
    assert single.success and single.status == STATUS_CONVERGED
    sens = solver.sensitivity(single)
    np.testing.assert_allclose(sens.grad[0], solver.sensitivity(batch).grad[1], atol=1e-12)


def test_warm_start_gives_the_cold_start_solution(prices, mpc_of):
    mpc = mpc_of()
    solver = BatchSolver(mpc)
    theta = Theta.nominal(mpc.system)
    rng = np.random.default_rng(5)
    soc = rng.uniform(0.2, 0.8, (6, 3))
    buy, sell = windows(prices, 6, mpc.N, 6)
    first = solver.solve_batch(soc, buy, sell, theta)
    soc_next = np.clip(soc + mpc.system.alpha * first.action, 0, 1)
    buy, sell = windows(prices, 7, mpc.N, 6)
    cold = solver.solve_batch(soc_next, buy, sell, theta)
    garbage = np.full_like(first.x, np.nan)
    garbage[:3] = 5.0  # far outside the bounds
    for x0 in (mpc.shift(first.x), garbage):
        warm = solver.solve_batch(soc_next, buy, sell, theta, x0=x0)
        assert warm.success.all()
        np.testing.assert_allclose(warm.x, cold.x, atol=1e-8)
    off = BatchSolver(mpc, MPCConfig(warm_start=False))
    ignored = off.solve_batch(soc_next, buy, sell, theta, x0=garbage)
    np.testing.assert_array_equal(ignored.iterations, cold.iterations)


def test_failure_is_reported_per_problem_with_the_fallback(prices, mpc_of):
    mpc = mpc_of()
    solver = BatchSolver(mpc, MPCConfig(max_iter=1))
    theta = Theta.nominal(mpc.system)
    buy, sell = windows(prices, 0, mpc.N, 4)
    sol = solver.solve_batch(np.full((4, 3), 0.5), buy, sell, theta)
    assert not sol.success.any() and sol.failures == 4
    assert set(sol.status) == {STATUS_MAX_ITER}
    assert np.all(sol.action == 0.0)
    assert np.all(sol.iterations == 1)
    for arr in (sol.x, sol.lam, sol.mu, sol.cost):
        assert np.all(np.isfinite(arr))
    sens = solver.sensitivity(sol)
    assert not sens.ok.any() and np.all(sens.grad == 0.0)
    assert all(r.startswith("solver failed") for r in sens.reason)


def test_failures_are_logged_once_per_call(prices, mpc_of, caplog):
    """At tau = 1e-11 the scaled residual cannot reach the tolerance: every problem runs out
    of iterations. The call says so in one warning instead of failing silently."""
    mpc = mpc_of()
    theta = Theta.nominal(mpc.system)
    buy, sell = windows(prices, 0, mpc.N, 24)
    soc0 = np.full((24, 3), 0.5)
    with caplog.at_level(logging.WARNING, logger="mpcrl_lite"):
        fine = BatchSolver(mpc).solve_batch(soc0, buy, sell, theta)
        assert fine.failures == 0 and not caplog.records
        sol = BatchSolver(mpc, MPCConfig(tau=1e-11)).solve_batch(soc0, buy, sell, theta)
    assert sol.failures == 24 and set(sol.status) == {STATUS_MAX_ITER}
    (record,) = caplog.records
    assert record.levelno == logging.WARNING and record.name == "mpcrl_lite.mpc.backends.batch"
    assert "batch back-end: 24 of 24 MPC problems failed (max_iter_reached: 24)" in (
        record.getMessage())


def test_breakdown_is_a_failure_not_an_exception(prices, mpc_of):
    """A non-convex theta (phi1 very negative) can break the factorisation; only the
    affected problems fail, nothing raises and no NaN leaks into the actions."""
    mpc = mpc_of()
    theta = Theta.nominal(mpc.system).replace(phi1=np.full(3, -1e6))
    buy, sell = windows(prices, 12, mpc.N, 4)
    solver = BatchSolver(mpc)
    sol = solver.solve_batch(np.full((4, 3), 0.5), buy, sell, theta)
    assert np.all(np.isfinite(sol.action))
    assert np.all(sol.action[~sol.success] == 0.0)
    assert len(sol.status) == 4
    sens = solver.sensitivity(sol)
    assert np.all(np.isfinite(sens.grad))


def test_sensitivity_reports_unusable_solutions(prices, mpc_of):
    """Failed problems and points that are not strictly interior are flagged, not raised."""
    mpc = mpc_of()
    solver = BatchSolver(mpc)
    theta = Theta.nominal(mpc.system)
    buy, sell = windows(prices, 1, mpc.N, 2)
    sol = solver.solve_batch(np.full((2, 3), 0.5), buy, sell, theta)
    mu = sol.mu.copy()
    mu[1, 0] = 0.0
    broken = BatchSolution(sol.action, sol.x, sol.lam, mu, sol.cost, sol.success, sol.status,
                           sol.iterations, sol.p)
    sens = solver.sensitivity(broken)
    assert sens.ok[0] and not sens.ok[1]
    assert "interior" in sens.reason[1]


def test_sensitivity_of_mixed_thetas(prices, mpc_of):
    """Solutions for different thetas in one batch are handled group by group."""
    mpc = mpc_of()
    solver = BatchSolver(mpc)
    rng = np.random.default_rng(9)
    buy, sell = windows(prices, 14, mpc.N, 2)
    sols = [solver.solve_batch(rng.uniform(0.2, 0.8, (2, 3)), buy, sell, th)
            for th in (Theta.nominal(mpc.system), convex_theta(rng, 3))]
    mixed = BatchSolution.stack([sols[0][0], sols[1][0], sols[0][1]], 0.0, "batch")
    sens = solver.sensitivity(mixed)
    separate = [solver.sensitivity(s).grad for s in sols]
    np.testing.assert_allclose(sens.grad, np.stack([separate[0][0], separate[1][0],
                                                    separate[0][1]]), atol=1e-12)
    np.testing.assert_allclose(solver.residual(mixed), 0.0, atol=1e-13)


def test_make_solver_batch_builds_without_compilation(prices, mpc_of):
    """The 'batch' back-end builds in milliseconds (nothing is compiled) and solves at once."""
    mpc = mpc_of()
    t0 = time.perf_counter()
    solver = make_solver(mpc, MPCConfig(backend="batch"))
    buy, sell = windows(prices, 0, mpc.N, 2)
    sol = solver.solve_batch(np.full((2, 3), 0.6), buy, sell, Theta.nominal(mpc.system))
    assert time.perf_counter() - t0 < 1.0
    assert isinstance(solver, BatchSolver) and solver.name == "batch"
    assert sol.success.all()
