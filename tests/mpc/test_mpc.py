"""Tests of the MPC formulation (mpcrl_lite.mpc.formulation), the reference IPOPT back-end
(mpcrl_lite.mpc.backends.ipopt): layout, QP data, the barrier solution's optimality conditions,
economic behaviour, warm starts, failures (never raised, logged once per batch) and batches."""

from __future__ import annotations

import dataclasses
import itertools
import logging

import numpy as np
import pytest
from conftest import random_theta, window
from scipy.optimize import linprog

from mpcrl_lite.config import MPCConfig, SystemConfig
from mpcrl_lite.mpc.backends.ipopt import IpoptSolver
from mpcrl_lite.mpc.formulation import GRID_INEQUALITIES, INEQUALITIES, MPC, Plan, QPData
from mpcrl_lite.mpc.solution import BatchSolution, MPCSolution
from mpcrl_lite.theta import PARTS, Theta

SUCCESS = ("Solve_Succeeded", "Solved_To_Acceptable_Level")
VARIABLES = ("b", "s", "soc", "sigma_hi", "sigma_lo")


# -- helpers ----------------------------------------------------------------------------------
def reference_fgh(
    system: SystemConfig, x: np.ndarray, soc0: np.ndarray, buy: np.ndarray, sell: np.ndarray,
    th: Theta,
) -> tuple[float, np.ndarray, np.ndarray]:
    """Cost, equalities and inequalities of the paper's eq. 9, written out independently in
    numpy. ``x`` is stage-major: stage j holds (b_j, s_j, soc_{j+1}, sigma_hi_{j+1},
    sigma_lo_{j+1}), n entries each."""
    n, N, gamma = system.n, system.N, system.gamma
    z = x.reshape(N, 5, n)
    b, s, soc, shi, slo = (z[:, k, :] for k in range(5))
    socs = np.vstack([soc0, soc])  # soc_0 .. soc_N

    def phi(v):
        return th.phi1 * v**2 + th.phi2 * v + th.phi3

    w_hi, w_lo = system.omega
    wf_hi, wf_lo = system.omega_f
    disc = gamma ** np.arange(N)
    f = np.sum(disc[:, None] * ((buy[:, None] + th.b) * b - (sell[:, None] + th.s) * s))
    # j = 0: phi(soc_0) and the slack soc_0 forces (constants of the problem)
    f += np.sum(phi(soc0) + w_hi * np.maximum(soc0 - system.soc_high, 0.0)
                + w_lo * np.maximum(system.soc_low - soc0, 0.0))
    # j = 1 .. N-1
    f += np.sum(disc[1:, None] * (phi(socs[1:N]) + w_hi * shi[: N - 1] + w_lo * slo[: N - 1]))
    # terminal
    f += np.sum(th.T1 * socs[N] ** 2 + th.T2 * socs[N] + th.T3 + wf_hi * shi[N - 1]
                + wf_lo * slo[N - 1])
    g = (socs[1:] - socs[:-1] - th.alpha * (b - s) - th.delta).ravel()
    U, P = system.U_bar, system.P_bar
    h = np.concatenate([
        np.concatenate([
            -b[j], b[j] - U, -s[j], s[j] - U, [b[j].sum() - P], [s[j].sum() - P],
            soc[j] - system.soc_high - shi[j], system.soc_low - soc[j] - slo[j], -shi[j], -slo[j],
        ])
        for j in range(N)
    ])
    return float(f), g, h


def random_point(mpc: MPC, rng: np.random.Generator) -> np.ndarray:
    """Any x: the formulation and its QP data must agree everywhere, feasible or not."""
    return rng.uniform(-0.5, 1.5, mpc.nx)


# -- layout -----------------------------------------------------------------------------------
def test_index_covers_every_variable_once(mpc):
    n, N = mpc.n, mpc.N
    assert mpc.nx == 5 * n * N and mpc.neq == n * N and mpc.nin == (8 * n + 2) * N
    assert mpc.np == n + 2 * N + len(PARTS) * n
    everything = np.concatenate([mpc.index(name).ravel() for name in VARIABLES])
    np.testing.assert_array_equal(np.sort(everything), np.arange(mpc.nx))
    # stage-major: stage j occupies [5 n j, 5 n (j+1)) in the order b, s, soc, sigma_hi, sigma_lo
    blocks = np.arange(mpc.nx).reshape(N, 5, n)
    for k, name in enumerate(VARIABLES):
        assert mpc.index(name).shape == (N, n)
        np.testing.assert_array_equal(mpc.index(name), blocks[:, k, :])
        for j in (0, N - 1):
            np.testing.assert_array_equal(mpc.index(name, j), blocks[j, k, :])
    with pytest.raises(ValueError, match="unknown variable 'u'"):
        mpc.index("u")


def test_policy_selector_picks_b0_minus_s0(mpc):
    S = mpc.policy_selector
    assert S.shape == (mpc.n, mpc.nx)
    x = np.random.default_rng(0).normal(size=mpc.nx)
    np.testing.assert_array_equal(S @ x, x[mpc.index("b", 0)] - x[mpc.index("s", 0)])
    assert np.count_nonzero(S) == 2 * mpc.n
    assert set(np.unique(S)) == {-1.0, 0.0, 1.0}


def test_parameters_layout_and_broadcasting(mpc, system, month_prices):
    n, N = mpc.n, mpc.N
    rng = np.random.default_rng(1)
    theta = random_theta(rng, system.n)
    soc0 = np.array([0.2, 0.5, 0.8])
    buy = window(month_prices, 3, 20, N)
    sell = 0.5 * buy
    p = mpc.parameters(soc0, buy, sell, theta)
    assert p.shape == (mpc.np,)
    np.testing.assert_array_equal(p[:n], soc0)
    np.testing.assert_array_equal(p[n : n + N], buy)
    np.testing.assert_array_equal(p[n + N : n + 2 * N], sell)
    np.testing.assert_array_equal(p[mpc.theta_slice], theta.to_vector())
    np.testing.assert_array_equal(mpc.parameters(soc0, buy, sell, theta.to_vector()), p)
    # leading batch axes: days of soc0 and prices, one theta
    socs = np.array([[0.2, 0.5, 0.8], [0.1, 0.1, 0.1]])
    P = mpc.parameters(socs, np.stack([buy, buy + 1]), sell, theta)
    assert P.shape == (2, mpc.np)
    np.testing.assert_array_equal(P[0], p)
    np.testing.assert_array_equal(P[1, :n], socs[1])
    np.testing.assert_array_equal(P[1, n : n + N], buy + 1)
    np.testing.assert_array_equal(P[1, n + N : n + 2 * N], sell)


@pytest.mark.parametrize(
    "change, message",
    [
        ({"soc0": np.full(4, 0.5)}, r"soc0 has shape \(4,\)"),
        ({"soc0": 0.5}, r"soc0 has shape \(\)"),
        ({"buy": np.full(11, 50.0)}, "price windows have shapes"),
        ({"sell": np.full((2, 13), 50.0)}, "price windows have shapes"),
        ({"theta": np.zeros(29)}, r"theta has shape \(29,\)"),
        ({"theta": np.zeros((2, 30))}, r"theta has shape \(2, 30\)"),
        ({"soc0": np.array([0.5, np.nan, 0.5])}, "non-finite"),
        ({"buy": np.r_[np.full(11, 50.0), np.inf]}, "non-finite"),
        ({"sell": np.r_[np.nan, np.full(11, 25.0)]}, "non-finite"),
        ({"theta": np.r_[np.full(29, 0.1), np.nan]}, "non-finite"),
    ],
)
def test_parameters_reject_bad_input(mpc, system, change, message):
    args = {"soc0": np.full(3, 0.5), "buy": np.full(12, 50.0), "sell": np.full(12, 25.0),
            "theta": Theta.nominal(system)}
    args.update(change)
    with pytest.raises(ValueError, match=message):
        mpc.parameters(**args)


def test_plan_shapes_and_content(mpc):
    n, N = mpc.n, mpc.N
    x = np.random.default_rng(2).normal(size=mpc.nx)
    soc0 = np.array([0.3, 0.4, 0.5])
    plan = mpc.plan(x, soc0)
    assert isinstance(plan, Plan)
    for name in ("b", "s", "sigma_hi", "sigma_lo"):
        assert getattr(plan, name).shape == (N, n)
        np.testing.assert_array_equal(getattr(plan, name), x[mpc.index(name)])
    assert plan.soc.shape == (N + 1, n)
    np.testing.assert_array_equal(plan.soc[0], soc0)
    np.testing.assert_array_equal(plan.soc[1:], x[mpc.index("soc")])
    np.testing.assert_array_equal(plan.action, plan.b - plan.s)
    np.testing.assert_array_equal(plan.action[0], mpc.policy_selector @ x)


def test_inequality_index_names_the_rows_of_h(mpc, system):
    n, N = mpc.n, mpc.N
    rng = np.random.default_rng(11)
    x = rng.uniform(-0.5, 1.5, mpc.nx)
    p = mpc.parameters(np.full(n, 0.5), np.full(N, 50.0), np.full(N, 25.0),
                       Theta.nominal(system))
    h = mpc.evaluate(x, p)[2]
    b, s, soc = (x[mpc.index(v)] for v in ("b", "s", "soc"))
    shi, slo = x[mpc.index("sigma_hi")], x[mpc.index("sigma_lo")]
    U, P = system.U_bar, system.P_bar
    expected = {
        "b_min": -b, "b_max": b - U, "s_min": -s, "s_max": s - U,
        "grid_b": b.sum(axis=1) - P, "grid_s": s.sum(axis=1) - P,
        "soc_max": soc - system.soc_high - shi, "soc_min": system.soc_low - soc - slo,
        "sigma_hi_min": -shi, "sigma_lo_min": -slo,
    }
    assert tuple(expected) == tuple(INEQUALITIES)
    rows = []
    for name, value in expected.items():
        idx = mpc.inequality_index(name)
        assert idx.shape == ((N,) if name in GRID_INEQUALITIES else (N, n))
        np.testing.assert_allclose(h[idx], value, rtol=0, atol=1e-14)
        np.testing.assert_array_equal(mpc.inequality_index(name, 3), idx[3])
        rows.append(idx.ravel())
    # every row of h belongs to exactly one group
    np.testing.assert_array_equal(np.sort(np.concatenate(rows)), np.arange(mpc.nin))
    with pytest.raises(ValueError, match="unknown inequality group 'grid'"):
        mpc.inequality_index("grid")


def test_shift_drops_stage_zero_and_repeats_the_last(mpc):
    x = np.arange(3 * mpc.nx, dtype=float).reshape(3, mpc.nx)
    out = mpc.shift(x)
    block = 5 * mpc.n
    assert out.shape == x.shape
    np.testing.assert_array_equal(out[:, :-block], x[:, block:])
    np.testing.assert_array_equal(out[:, -block:], x[:, -block:])
    np.testing.assert_array_equal(mpc.shift(x[0]), out[0])
    with pytest.raises(ValueError, match=r"expected \(\.\.\., nx=180\)"):
        mpc.shift(x[:, :-1])


# -- formulation and QP data ------------------------------------------------------------------
def _random_problems(system, month_prices, count, seed):
    rng = np.random.default_rng(seed)
    for k in range(count):
        theta = Theta.nominal(system) if k == 0 else random_theta(rng, system.n)
        if k == count - 1:  # a non-convex theta: the QP data must still be exact
            theta = theta.replace(phi1=-theta.phi1, T1=-np.abs(theta.T1) - 1.0)
        soc0 = rng.uniform(-0.1, 1.1, system.n)  # also outside [0.1, 0.9]: constant slacks
        buy = window(month_prices, rng.integers(30), rng.integers(24), system.N)
        yield rng, soc0, buy, system.sell_ratio * buy, theta


def test_formulation_matches_the_paper(mpc, system, month_prices):
    for rng, soc0, buy, sell, theta in _random_problems(system, month_prices, 4, 3):
        p = mpc.parameters(soc0, buy, sell, theta)
        for _ in range(3):
            x = random_point(mpc, rng)
            f, g, h = mpc.evaluate(x, p)
            f_ref, g_ref, h_ref = reference_fgh(system, x, soc0, buy, sell, theta)
            assert f == pytest.approx(f_ref, rel=1e-12, abs=1e-9)
            np.testing.assert_allclose(g, g_ref, rtol=0, atol=1e-14)
            np.testing.assert_allclose(h, h_ref, rtol=0, atol=1e-14)


def test_qp_data_is_consistent_with_f_g_h(mpc, system, month_prices):
    data = []
    for rng, soc0, buy, sell, theta in _random_problems(system, month_prices, 4, 4):
        p = mpc.parameters(soc0, buy, sell, theta)
        qp = mpc.qp_data(p)
        assert isinstance(qp, QPData)
        assert qp.H.shape == (mpc.nx, mpc.nx) and qp.q.shape == (mpc.nx,)
        assert qp.A.shape == (mpc.neq, mpc.nx) and qp.e.shape == (mpc.neq,)
        assert qp.C.shape == (mpc.nin, mpc.nx) and qp.d.shape == (mpc.nin,)
        for _ in range(3):
            x = random_point(mpc, rng)
            f, g, h = mpc.evaluate(x, p)
            assert f == pytest.approx(0.5 * x @ qp.H @ x + qp.q @ x + qp.c, rel=1e-12, abs=1e-9)
            np.testing.assert_allclose(g, qp.A @ x - qp.e, rtol=0, atol=1e-13)
            np.testing.assert_allclose(h, qp.C @ x - qp.d, rtol=0, atol=1e-13)
        # H is diagonal, with the soc curvature: 2 gamma^(j+1) phi1 for j < N-1, 2 T1 at the end
        np.testing.assert_array_equal(qp.H, np.diag(np.diag(qp.H)))
        expected = np.zeros(mpc.nx)
        soc = mpc.index("soc")
        for j in range(mpc.N - 1):
            expected[soc[j]] = 2 * system.gamma ** (j + 1) * theta.phi1
        expected[soc[-1]] = 2 * theta.T1
        np.testing.assert_allclose(np.diag(qp.H), expected, rtol=1e-14, atol=0)
        data.append((p, qp))
    # C and d never depend on p; A depends on theta only
    for p, qp in data[1:]:
        np.testing.assert_array_equal(qp.C, data[0][1].C)
        np.testing.assert_array_equal(qp.d, data[0][1].d)
    p0, qp0 = data[0]
    p_other = p0.copy()
    p_other[: mpc.n + 2 * mpc.N] += 0.37  # other soc0 and prices, same theta
    np.testing.assert_array_equal(mpc.qp_data(p_other).A, qp0.A)
    assert not np.array_equal(data[1][1].A, qp0.A)  # another theta_alpha


# -- the barrier solution ---------------------------------------------------------------------
def _solution_cases(system, month_prices):
    rng = np.random.default_rng(5)
    cases = [
        ("theta0, mid soc, evening", Theta.nominal(system), np.array([0.6, 0.6, 0.6]), (0, 14)),
        ("theta0, mixed soc, night", Theta.nominal(system), np.array([0.05, 0.5, 0.95]), (7, 22)),
    ]
    for k in range(3):
        soc0 = rng.uniform(0.05, 0.95, system.n)
        cases.append((f"random convex theta {k}", random_theta(rng, system.n), soc0,
                      (int(rng.integers(30)), int(rng.integers(24)))))
    out = []
    for name, theta, soc0, (day, hour) in cases:
        buy = window(month_prices, day, hour, system.N)
        out.append((name, theta, soc0, buy, system.sell_ratio * buy))
    return out


def check_barrier_solution(mpc: MPC, sol: MPCSolution, soc0, buy, sell, theta, tau):
    """Every optimality condition of the barrier problem, checked on the raw arrays."""
    system = mpc.system
    assert sol.success and sol.status in SUCCESS
    assert all(np.all(np.isfinite(v)) for v in (sol.x, sol.lam, sol.mu))
    plan = mpc.plan(sol.x, soc0)
    U, P = system.U_bar, system.P_bar
    # inputs strictly inside their bounds, grid limit at every stage (barrier: never on them)
    assert np.all(plan.b > 0) and np.all(plan.b < U)
    assert np.all(plan.s > 0) and np.all(plan.s < U)
    assert np.all(plan.b.sum(axis=1) < P) and np.all(plan.s.sum(axis=1) < P)
    # dynamics (eq. 9b) with the MPC's model theta_alpha, theta_delta
    residual = plan.soc[1:] - plan.soc[:-1] - theta.alpha * (plan.b - plan.s) - theta.delta
    assert np.max(np.abs(residual)) <= 1e-12
    # relaxed soft bounds (eqs. 9c-9d)
    assert np.all(plan.sigma_hi > 0) and np.all(plan.sigma_lo > 0)
    assert np.all(plan.sigma_hi > plan.soc[1:] - system.soc_high)
    assert np.all(plan.sigma_lo > system.soc_low - plan.soc[1:])
    # relaxed complementarity and dual feasibility
    qp = mpc.qp_data(sol.p)
    h = qp.C @ sol.x - qp.d
    assert np.all(h < 0) and np.all(sol.mu > 0)
    np.testing.assert_allclose(sol.mu * h, -tau, rtol=1e-8, atol=0)
    # stationarity of the Lagrangian, from the QP data
    grad = qp.H @ sol.x + qp.q + qp.A.T @ sol.lam + qp.C.T @ sol.mu
    assert np.max(np.abs(grad)) <= 1e-10 * (1 + np.max(np.abs(qp.q)))
    np.testing.assert_allclose(qp.A @ sol.x, qp.e, rtol=0, atol=1e-12)
    # the reported numbers
    np.testing.assert_array_equal(sol.action, plan.action[0])
    f_ref = reference_fgh(system, sol.x, soc0, buy, sell, theta)[0]
    assert sol.cost == pytest.approx(f_ref, rel=1e-12, abs=1e-9)
    np.testing.assert_array_equal(sol.p, mpc.parameters(soc0, buy, sell, theta))
    return plan


def test_ipopt_solution_satisfies_the_barrier_kkt_conditions(mpc, ipopt, system, month_prices):
    for name, theta, soc0, buy, sell in _solution_cases(system, month_prices):
        sol = ipopt.solve(soc0, buy, sell, theta)
        try:
            check_barrier_solution(mpc, sol, soc0, buy, sell, theta, ipopt.config.tau)
        except AssertionError as err:
            raise AssertionError(f"case {name!r}: {err}") from err
        # the package's own KKT residual agrees
        r = np.array(mpc.kkt.residual(sol.y, sol.p, ipopt.config.tau)).ravel()
        assert np.max(np.abs(r)) <= 1e-10


def test_ipopt_solution_at_tau_1e_3(mpc, ipopt_at, system, month_prices):
    solver = ipopt_at(1e-3)
    for name, theta, soc0, buy, sell in _solution_cases(system, month_prices)[::2]:
        sol = solver.solve(soc0, buy, sell, theta)
        check_barrier_solution(mpc, sol, soc0, buy, sell, theta, 1e-3)


@pytest.fixture(scope="module")
def tight_grid(mpc_of, ipopt_at):
    """A grid that takes at most 0.6 of the three batteries' 3.0, solved nearly exactly
    (tau = 1e-4), so that the barrier keeps the grid power within 1e-3 of its limit."""
    mpc = mpc_of(P_bar=0.6)
    return mpc.system, mpc, ipopt_at(1e-4, on=mpc)


@pytest.mark.parametrize(
    "soc0, buy, direction",
    [
        (0.6, np.linspace(40.0, 110.0, 12), "s"),  # full battery, rising prices: sell
        (0.1, np.r_[np.full(4, 5.0), np.full(8, 110.0)], "b"),  # empty, cheap first: buy
    ],
)
def test_grid_limit_binds_but_holds(tight_grid, soc0, buy, direction):
    system, mpc, solver = tight_grid
    soc0 = np.full(system.n, soc0)
    sol = solver.solve(soc0, buy, 0.5 * buy, Theta.nominal(system))
    plan = check_barrier_solution(mpc, sol, soc0, buy, 0.5 * buy, Theta.nominal(system),
                                  solver.config.tau)
    total = getattr(plan, direction).sum(axis=1)
    assert np.all(total < system.P_bar)
    assert np.max(total) > system.P_bar - 1e-3
    assert total[0] > system.P_bar - 1e-3  # the policy itself runs at the limit


# -- economic behaviour at theta0 -------------------------------------------------------------
def test_buys_cheap_first_then_sells_expensive(mpc, ipopt, system):
    # theta0 has no terminal value for charge, so a battery with charge to spare just sells.
    # From an empty battery (soc 0.1) selling at the later high price drives soc below the
    # soft bound, and every hour spent below 0.1 costs omega = 20 per unit of soc: charge
    # bought now for 5 saves more than that, so the MPC buys in the cheap hours.
    buy = np.r_[np.full(4, 5.0), np.full(8, 110.0)]
    soc0 = np.full(system.n, 0.1)
    sol = ipopt.solve(soc0, buy, 0.5 * buy, Theta.nominal(system))
    assert sol.success
    plan = mpc.plan(sol.x, soc0)
    assert np.all(sol.action > 0.1)
    assert np.all(plan.action[:4] > 0.1)  # buys through the cheap hours
    assert np.all(plan.action[4:] < -0.1)  # sells through the expensive ones


def test_sells_expensive_first(mpc, ipopt, system):
    buy = np.r_[np.full(4, 110.0), np.full(8, 5.0)]
    soc0 = np.full(system.n, 0.2)
    sol = ipopt.solve(soc0, buy, 0.5 * buy, Theta.nominal(system))
    assert sol.success
    plan = mpc.plan(sol.x, soc0)
    assert np.all(sol.action < -0.1)
    assert np.all(plan.action[:4] < -0.1)


def test_barrier_solution_tends_to_the_exact_lp_solution(mpc, ipopt_at, system):
    # Asymmetric agents, so that the LP (phi1 = T1 = 0) has a unique solution.
    theta = Theta.nominal(system).replace(
        alpha=np.array([0.08, 0.09, 0.075]), b=np.array([0.0, 3.0, -2.0]),
        s=np.array([1.0, -4.0, 2.5]),
    )
    soc0 = np.array([0.3, 0.5, 0.7])
    buy = np.array([37.0, 33, 31, 30, 31, 35, 42, 52, 61, 65, 66, 69])
    sell = 0.5 * buy
    p = mpc.parameters(soc0, buy, sell, theta)
    qp = mpc.qp_data(p)
    assert not np.any(qp.H)
    lp = linprog(qp.q, A_ub=qp.C, b_ub=qp.d, A_eq=qp.A, b_eq=qp.e, bounds=(None, None),
                 method="highs")
    assert lp.status == 0
    f_star = lp.fun + qp.c
    distances, policy_gaps = [], []
    for tau in (1e-2, 1e-3, 1e-4, 1e-5):
        sol = ipopt_at(tau).solve(soc0, buy, sell, theta)
        assert sol.success
        # on the central path of an LP the duality gap is exactly nin * tau
        assert -1e-9 <= sol.cost - f_star <= mpc.nin * tau + 1e-9
        distances.append(np.linalg.norm(sol.x - lp.x))
        policy_gaps.append(np.max(np.abs(sol.action - mpc.policy_selector @ lp.x)))
    assert all(a > 3 * b for a, b in itertools.pairwise(distances)), distances
    assert all(a > 3 * b for a, b in itertools.pairwise(policy_gaps)), policy_gaps
    assert distances[-1] < 1e-2 and policy_gaps[-1] < 1e-3


# -- warm start, failures, batches ------------------------------------------------------------
def test_warm_start_gives_the_cold_start_solution(mpc, ipopt, system, month_prices):
    theta = random_theta(np.random.default_rng(6), system.n)
    soc0 = np.array([0.25, 0.5, 0.75])
    buy = window(month_prices, 10, 6, system.N)
    cold = ipopt.solve(soc0, buy, 0.5 * buy, theta)
    previous_hour = ipopt.solve(soc0 + 0.02, window(month_prices, 10, 5, system.N),
                                0.5 * window(month_prices, 10, 5, system.N), theta)
    shifted = mpc.shift(previous_hour.x)
    for guess in (cold.x, shifted, 0.7 * ipopt.default_guess()):
        warm = ipopt.solve(soc0, buy, 0.5 * buy, theta, x0=guess)
        assert warm.success
        np.testing.assert_allclose(warm.x, cold.x, rtol=0, atol=1e-9)
        np.testing.assert_allclose(warm.action, cold.action, rtol=0, atol=1e-10)
        np.testing.assert_allclose(warm.mu, cold.mu, rtol=1e-7, atol=0)


def test_warm_started_solutions_are_polished_to_rounding_level(mpc, ipopt, system, month_prices):
    # Warm starts land IPOPT close to the solution; the Newton polish must still finish the
    # job (the sensitivities and their finite-difference checks rely on exact solutions).
    rng = np.random.default_rng(1)
    worst = 0.0
    for _ in range(30):
        theta = random_theta(rng, system.n)
        soc0 = rng.uniform(0.05, 0.95, system.n)
        buy = window(month_prices, rng.integers(30), rng.integers(24), system.N)
        first = ipopt.solve(soc0, buy, 0.5 * buy, theta)
        warm = ipopt.solve(soc0 + 1e-6, buy, 0.5 * buy, theta, x0=first.x)
        assert warm.success
        r = np.array(mpc.kkt.residual(warm.y, warm.p, ipopt.config.tau)).ravel()
        worst = max(worst, np.max(np.abs(r)))
    assert worst <= 2e-12


def test_failure_is_reported_with_the_fallback_action(mpc, system, month_prices):
    solver = IpoptSolver(mpc, MPCConfig(max_iter=1, backend="ipopt"))
    buy = window(month_prices, 2, 12, system.N)
    sol = solver.solve(np.full(system.n, 0.5), buy, 0.5 * buy, Theta.nominal(system))
    assert sol.success is False
    assert isinstance(sol.status, str) and sol.status and sol.status not in SUCCESS
    np.testing.assert_array_equal(sol.action, np.zeros(system.n))
    assert np.all(np.isfinite(sol.action))
    # a whole batch of failures
    batch = solver.solve_batch(np.full((3, system.n), 0.5), np.stack([buy] * 3),
                               np.stack([0.5 * buy] * 3), Theta.nominal(system))
    assert batch.failures == 3 and not np.any(batch.success)
    np.testing.assert_array_equal(batch.action, np.zeros((3, system.n)))


def test_ipopt_gets_every_inequality_once(mpc, ipopt, system):
    """The rows IPOPT takes as general constraints plus its simple bounds on x are exactly
    the inequalities of the formulation, each once."""
    x = np.random.default_rng(12).uniform(-0.5, 1.5, mpc.nx)
    p = mpc.parameters(np.full(system.n, 0.5), np.full(system.N, 50.0),
                       np.full(system.N, 25.0), Theta.nominal(system))
    h = mpc.evaluate(x, p)[2]
    general = ipopt._general_rows
    assert np.all(np.diff(general) > 0)
    bounds = np.concatenate([(ipopt._lbx - x)[np.isfinite(ipopt._lbx)],
                             (x - ipopt._ubx)[np.isfinite(ipopt._ubx)]])
    rest = np.delete(h, general)
    assert rest.size == bounds.size == mpc.nin - general.size
    np.testing.assert_allclose(np.sort(rest), np.sort(bounds), rtol=0, atol=1e-15)


def test_invalid_guess_is_a_failure_not_an_exception(mpc, ipopt, system):
    guess = ipopt.default_guess()
    guess[7] = np.nan
    buy = np.full(system.N, 50.0)
    sol = ipopt.solve(np.full(system.n, 0.5), buy, 0.5 * buy, Theta.nominal(system), x0=guess)
    assert sol.success is False and sol.status
    np.testing.assert_array_equal(sol.action, np.zeros(system.n))


def test_guess_is_ignored_without_warm_start(mpc, system):
    """With ``warm_start=False`` a single solve starts cold whatever ``x0`` is, as a batch
    does: the invalid guess that fails the solve above is not used."""
    solver = IpoptSolver(mpc, MPCConfig(backend="ipopt", warm_start=False))
    guess = solver.default_guess()
    guess[7] = np.nan
    buy = np.full(system.N, 50.0)
    args = (np.full(system.n, 0.5), buy, 0.5 * buy, Theta.nominal(system))
    sol = solver.solve(*args, x0=guess)
    assert sol.success
    np.testing.assert_array_equal(sol.x, solver.solve(*args).x)


def test_solve_batch_equals_single_solves(mpc, ipopt, system, month_prices):
    rng = np.random.default_rng(7)
    theta = random_theta(rng, system.n)
    days = [0, 9, 17, 29]
    socs = rng.uniform(0.1, 0.9, (len(days), system.n))
    buys = np.stack([window(month_prices, d, 21, system.N) for d in days])
    batch = ipopt.solve_batch(socs, buys, 0.5 * buys, theta)
    assert isinstance(batch, BatchSolution) and len(batch) == len(days)
    assert batch.backend == "ipopt" and batch.solve_time > 0
    assert batch.action.shape == (len(days), system.n)
    assert batch.x.shape == (len(days), mpc.nx) and batch.mu.shape == (len(days), mpc.nin)
    assert batch.failures == 0
    for d in range(len(days)):
        single = ipopt.solve(socs[d], buys[d], 0.5 * buys[d], theta)
        one = batch[d]
        assert isinstance(one, MPCSolution) and one.success
        np.testing.assert_allclose(one.x, single.x, rtol=0, atol=1e-12)
        np.testing.assert_allclose(one.action, single.action, rtol=0, atol=1e-12)
        assert one.cost == pytest.approx(single.cost, rel=1e-12)
        np.testing.assert_array_equal(one.p, single.p)
    # warm-started batch from the solutions themselves: same answers
    warm = ipopt.solve_batch(socs, buys, 0.5 * buys, theta, x0=batch.x)
    np.testing.assert_allclose(warm.x, batch.x, rtol=0, atol=1e-9)
    with pytest.raises(ValueError, match="solve_batch expects soc0"):
        ipopt.solve_batch(socs[0], buys[0], 0.5 * buys[0], theta)




def test_solution_is_a_frozen_record(ipopt, system):
    buy = np.full(system.N, 50.0)
    sol = ipopt.solve(np.full(system.n, 0.5), buy, 0.5 * buy, Theta.nominal(system))
    with pytest.raises(dataclasses.FrozenInstanceError):
        sol.success = False  # type: ignore[misc]
    np.testing.assert_array_equal(sol.y, np.concatenate([sol.x, sol.lam, sol.mu]))


# -- robustness: failures are reported, never raised ------------------------------------------
#: Buying prices of the first 12 hours of the default price month. With soc0 = 0.6, theta0 and
#: tau = 1e-11 IPOPT converges, but the barrier KKT matrix at its point is numerically singular
#: and CasADi's QR cannot evaluate the Newton step of the polish.
POLISH_FAILS_BUY = np.array([47.870433399999996, 41.523979, 37.1952832, 36.45563, 39.3950808,
                             47.128864, 52.9330338, 64.4359824, 70.8169284, 74.0533902,
                             77.3262598, 77.93369519999999])


def test_tiny_tau_never_raises_from_the_polish(mpc, system):
    solver = IpoptSolver(mpc, MPCConfig(tau=1e-11, backend="ipopt"))
    soc0 = np.full(system.n, 0.6)
    sol = solver.solve(soc0, POLISH_FAILS_BUY, 0.5 * POLISH_FAILS_BUY, Theta.nominal(system))
    assert np.all(np.isfinite(sol.action))
    if sol.success:  # a platform whose QR copes must have polished to the rounding level
        r = np.array(mpc.kkt.residual(sol.y, sol.p, 1e-11)).ravel()
        assert np.max(np.abs(r)) <= 1e-6 * (1 + np.max(np.abs(sol.p)))
    else:
        assert sol.status and sol.status not in SUCCESS
        np.testing.assert_array_equal(sol.action, np.zeros(system.n))


def test_polish_error_marks_the_solve_failed(mpc, system, monkeypatch, caplog):
    solver = IpoptSolver(mpc, MPCConfig(backend="ipopt"))

    def newton_fails(*args):
        raise RuntimeError("Error in Function::call for 'kkt_newton' [MXFunction] at .../"
                           "function.cpp:514:\n.../function_internal.hpp:1766: Evaluation failed")

    monkeypatch.setattr(mpc.kkt, "newton", newton_fails)
    buy = np.full(system.N, 50.0)
    sol = solver.solve(np.full(system.n, 0.5), buy, 0.5 * buy, Theta.nominal(system))
    assert sol.success is False
    assert sol.status == "kkt_polish_failed: Newton step failed (Evaluation failed)"
    np.testing.assert_array_equal(sol.action, np.zeros(system.n))
    assert np.all(np.isfinite(sol.x)) and np.isfinite(sol.cost)
    # one warning per call, for a single solve as for a batch
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 1 and "1 of 1 MPC problems failed" in warnings[0]
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="mpcrl_lite"):
        batch = solver.solve_batch(np.full((2, system.n), 0.5), np.stack([buy] * 2),
                                   np.stack([0.5 * buy] * 2), Theta.nominal(system))
    assert batch.failures == 2
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 1 and "2 of 2 MPC problems failed" in warnings[0]


def test_a_batch_with_failures_logs_one_warning(mpc, system, month_prices, caplog):
    buy = np.stack([window(month_prices, d, 12, system.N) for d in range(3)])
    socs = np.full((3, system.n), 0.5)
    with caplog.at_level(logging.WARNING, logger="mpcrl_lite"):
        IpoptSolver(mpc, MPCConfig(backend="ipopt")).solve_batch(socs, buy, 0.5 * buy,
                                                                 Theta.nominal(system))
        assert not caplog.records  # all solved: nothing to say
        failed = IpoptSolver(mpc, MPCConfig(max_iter=1, backend="ipopt")).solve_batch(
            socs, buy, 0.5 * buy, Theta.nominal(system))
    assert failed.failures == 3
    (record,) = caplog.records
    assert record.levelno == logging.WARNING and record.name == "mpcrl_lite.mpc.backends.ipopt"
    message = record.getMessage()
    assert "ipopt back-end: 3 of 3 MPC problems failed" in message
    assert f"{failed.status[0]}: 3" in message and "idle" in message
