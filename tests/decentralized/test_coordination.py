"""The local barrier QPs and their price coordination (mpcrl_lite.decentralized.local_qp, .coordination)."""

from __future__ import annotations

import numpy as np
import pytest

from mpcrl_lite.config import CoordinationConfig, MPCConfig, SystemConfig
from mpcrl_lite.decentralized.coordination import CoordinatedMPC, join_theta, split_theta
from mpcrl_lite.decentralized.local_qp import LocalQP, local_system
from mpcrl_lite.mpc.backends.ipopt import IpoptSolver
from mpcrl_lite.mpc.formulation import GRID_INEQUALITIES, INEQUALITIES, MPC
from mpcrl_lite.system.prices import Prices
from mpcrl_lite.theta import Theta

IPOPT = MPCConfig(backend="ipopt")
TIGHT = SystemConfig()  # n = 3, P_bar = 1.5 < n U_bar
FIVE = SystemConfig(n=5, P_bar=2.0)
# the local MPC's own grid row, made inert, moves the local multipliers by ~tau / P_loc; far
# enough away it no longer blurs the comparison with the centralized MPC
FAR = CoordinationConfig(local_grid_factor=1e8)


def random_case(system: SystemConfig, days: int, hour: int, seed: int):
    rng = np.random.default_rng(seed)
    n = system.n
    buy, sell = Prices.month(system, days).window(hour, system.N)
    buy = buy * rng.uniform(0.7, 1.3, buy.shape)
    sell = sell * rng.uniform(0.7, 1.0, sell.shape)
    theta = Theta.nominal(system).replace(
        b=rng.uniform(-3, 3, n), phi1=rng.uniform(5, 40, n), phi2=rng.uniform(-30, 0, n),
        T1=rng.uniform(5, 40, n), T2=rng.uniform(-30, 0, n),
    )
    return rng.uniform(0.0, 1.0, (days, n)), buy, sell, theta


# -- the local problems -----------------------------------------------------------------------
@pytest.fixture(scope="module")
def local() -> tuple[MPC, LocalQP]:
    mpc = MPC(local_system(TIGHT))
    return mpc, LocalQP(mpc)


def test_local_system_and_theta_helpers():
    local = local_system(TIGHT, 50.0)
    assert local.n == 1 and local.P_bar == 50.0 * 1.5 and local.U_bar == TIGHT.U_bar
    theta = random_case(FIVE, 1, 0, 3)[3]
    parts = split_theta(theta)
    assert len(parts) == 5 and join_theta(parts) == theta
    with pytest.raises(ValueError, match="expected a SystemConfig"):
        local_system("paper")
    with pytest.raises(ValueError, match="expected a Theta"):
        split_theta([theta])
    with pytest.raises(ValueError, match="expected a CoordinationConfig"):
        CoordinatedMPC(TIGHT, IPOPT, coordination={"tol": 1e-9})
    with pytest.raises(ValueError, match="the local MPC has n=3"):
        LocalQP(MPC(TIGHT))


def test_local_data_is_the_mpcs_qp(local):
    mpc, qp = local
    rng = np.random.default_rng(0)
    thetas = [split_theta(random_case(TIGHT, 1, 0, k)[3])[k % 3] for k in range(4)]
    P = np.stack([mpc.parameters(rng.uniform(0, 1, 1), rng.uniform(100, 900, mpc.N),
                                 rng.uniform(100, 900, mpc.N), t) for t in thetas])
    Hd, q, A, e = qp.data(P)
    x = rng.normal(size=(4, mpc.nx))
    v = rng.normal(size=(4, mpc.N, qp.nh))
    for k in range(4):
        ref = mpc.qp_data(P[k])
        np.testing.assert_array_equal(np.diag(Hd[k]), ref.H)
        np.testing.assert_allclose(q[k], ref.q, rtol=1e-15)
        np.testing.assert_allclose(A[k], ref.A, rtol=1e-15)
        np.testing.assert_allclose(e[k], ref.e, rtol=1e-15)
        # the stage blocks of C, their transpose, and the grid selection E
        np.testing.assert_allclose(qp.h(x)[k].ravel(), ref.C @ x[k] - ref.d, atol=1e-14)
        np.testing.assert_allclose(qp.Ct(v)[k], ref.C.T @ v[k].ravel(), atol=1e-14)
    Ex = qp.E(x)
    np.testing.assert_array_equal(Ex, np.concatenate([x[:, mpc.index("b")[:, 0]],
                                                      x[:, mpc.index("s")[:, 0]]], axis=1))
    w = rng.normal(size=(4, 2 * mpc.N))
    np.testing.assert_allclose((qp.Et(w) * x).sum(1), (w * Ex).sum(1), rtol=1e-13)


@pytest.mark.parametrize("system", [
    TIGHT, SystemConfig(n=2, gamma=0.9, omega=(3.0, 7.0), omega_f=(20.0, 40.0), N=7),
], ids=["default", "gamma-omega-N"])
def test_written_out_local_data_is_casadis_bit_for_bit(system):
    # LocalQP.data writes the QP data out in numpy; CasADi's map of MPC.qp_function is the
    # reference (the same numbers, not only close ones: the coordination's rounds see them)
    mpc = MPC(local_system(system))
    qp = LocalQP(mpc, system.battery("U_bar"))
    rng = np.random.default_rng(7)
    for scale in (1e-3, 1.0, 1e3):
        P = rng.normal(size=(2 * system.n, mpc.np)) * scale * 10.0 ** rng.integers(
            -2, 3, (2 * system.n, mpc.np))
        for name, new, ref in zip(("Hd", "q", "A", "e"), qp.data(P), qp.data_reference(P)):
            assert new.shape == ref.shape, name
            np.testing.assert_array_equal(new, ref, err_msg=name)
    with pytest.raises(ValueError, match=r"P has shape \(3,\); expected \(B, np="):
        qp.data(np.zeros(3))


def test_local_data_that_leaves_the_formulation_is_refused(monkeypatch):
    written_out = LocalQP.data

    def off(self, P):
        Hd, q, A, e = written_out(self, P)
        return Hd, q, A, e + 1e-9

    monkeypatch.setattr(LocalQP, "data", off)
    with pytest.raises(RuntimeError, match="LocalQP.data's e differs from MPC.qp_function's"):
        LocalQP(MPC(local_system(TIGHT)))


def test_feasible_soc_is_the_dense_solve_of_the_dynamics(local):
    # the running sum of the dynamics gives the numbers of a dense solve with A's soc block
    mpc, qp = local
    rng = np.random.default_rng(5)
    P = rng.normal(size=(50, mpc.np)) * 10.0 ** rng.integers(-2, 3, (50, mpc.np))
    _, _, A, e = qp.data(P)
    x = qp.feasible(A, e, rng.normal(size=(50, mpc.nx)) * 3.0)
    rest = np.ones(mpc.nx, bool)
    rest[qp.isoc] = False
    rhs = e - np.einsum("bri,bi->br", A[:, :, rest], x[:, rest])
    soc = np.linalg.solve(A[:, :, qp.isoc], rhs[..., None])[..., 0]
    np.testing.assert_array_equal(x[:, qp.isoc], soc)


def test_feasible_start_is_strictly_inside(local):
    mpc, qp = local
    rng = np.random.default_rng(1)
    soc0 = np.array([0.0, 1.0, 0.5, 0.05])
    P = np.stack([mpc.parameters(soc0[k : k + 1], np.full(mpc.N, 300.0), np.full(mpc.N, 250.0),
                                 Theta.nominal(local_system(TIGHT))) for k in range(4)])
    _, _, A, e = qp.data(P)
    x = qp.feasible(A, e, rng.uniform(-2, 2, (4, mpc.nx)))
    np.testing.assert_allclose((A @ x[..., None])[..., 0], e, atol=1e-13)
    assert np.all(qp.h(x) < 0)


def test_newton_split_is_the_full_newton_step_with_a_price_change(local):
    # dx0 + X dnu and lam0 + L dnu solve the dense primal-dual system whose linear cost
    # carries the price change E' dnu; M = E X is symmetric negative semidefinite
    mpc, qp = local
    rng = np.random.default_rng(2)
    B, N, nx = 3, mpc.N, mpc.nx
    P = np.stack([mpc.parameters(rng.uniform(0.1, 0.9, 1), rng.uniform(100, 900, N),
                                 rng.uniform(100, 900, N), Theta.nominal(local_system(TIGHT)))
                  for _ in range(B)])
    Hd, q, A, e = qp.data(P)
    x = qp.feasible(A, e, np.tile(IpoptSolver(mpc, IPOPT).default_guess(), (B, 1)))
    x = x + 1e-4 * rng.normal(size=x.shape)  # off the dynamics too: A x != e
    h = qp.h(x)
    assert np.all(h < 0) and np.abs((A @ x[..., None])[..., 0] - e).min() > 1e-7
    mu = rng.uniform(0.5, 2.0, h.shape)
    tau = np.array([0.1, 0.01, 1.0])
    dnu = rng.normal(size=(B, 2 * N))
    dx0, lam0, L, M, Winv = qp.newton(Hd, q, A, e, x, mu, h, tau)
    dx = dx0 + qp.price_step(A, L, Winv, dnu)
    lam = lam0 + (L @ dnu[..., None])[..., 0]
    for k in range(B):
        ref = mpc.qp_data(P[k])
        hk, muk = h[k].ravel(), mu[k].ravel()
        W = ref.H + ref.C.T @ np.diag(muk / -hk) @ ref.C
        K = np.block([[W, ref.A.T], [ref.A, np.zeros((N, N))]])
        grad_phi = ref.H @ x[k] + ref.q + ref.C.T @ (tau[k] / -hk) + qp.Et(dnu[k : k + 1])[0]
        sol = np.linalg.solve(K, np.concatenate([-grad_phi, -(ref.A @ x[k] - ref.e)]))
        np.testing.assert_allclose(dx[k], sol[:nx], rtol=1e-9, atol=1e-11)
        np.testing.assert_allclose(lam[k], sol[nx:], rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(M[k], M[k].T, atol=1e-12)
        assert np.linalg.eigvalsh(0.5 * (M[k] + M[k].T)).max() < 1e-12
    # M is the response of (b, s) to the prices: E X
    X_dnu = qp.price_step(A, L, Winv, dnu)
    np.testing.assert_allclose(qp.E(X_dnu), (M @ dnu[..., None])[..., 0], atol=1e-12)


# -- the coordination -------------------------------------------------------------------------
@pytest.mark.parametrize(("system", "hour", "seed"), [(TIGHT, 17, 1), (FIVE, 7, 2)])
def test_coordination_is_the_centralized_mpc_primal_and_dual(system, hour, seed):
    soc, buy, sell, theta = random_case(system, 3, hour, seed)
    policy = CoordinatedMPC(system, IPOPT, FAR)
    sol = policy.solve(soc, buy, sell, theta)
    assert sol.converged.all() and sol.success.all() and not sol.projected.any()
    mpc, loc, n, N = MPC(system), policy.local_mpc, system.n, system.N
    ref = IpoptSolver(mpc, IPOPT).solve_batch(soc, buy, sell, theta)
    assert ref.success.all()
    for i in range(n):
        for name in ("b", "s", "soc", "sigma_hi", "sigma_lo"):
            np.testing.assert_allclose(sol.x[:, i][:, loc.index(name)[:, 0]],
                                       ref.x[:, mpc.index(name)[:, i]], atol=1e-8)
        np.testing.assert_allclose(sol.lam[:, i], ref.lam[:, np.arange(N) * n + i], atol=1e-7)
        for group in INEQUALITIES:
            if group not in GRID_INEQUALITIES:
                np.testing.assert_allclose(sol.mu[:, i][:, loc.inequality_index(group)[:, 0]],
                                           ref.mu[:, mpc.inequality_index(group)[:, i]],
                                           atol=1e-7)
    np.testing.assert_allclose(sol.price_buy, ref.mu[:, mpc.inequality_index("grid_b")],
                               atol=1e-7)
    np.testing.assert_allclose(sol.price_sell, ref.mu[:, mpc.inequality_index("grid_s")],
                               atol=1e-7)
    np.testing.assert_allclose(sol.action, ref.action, atol=1e-8)


@pytest.mark.parametrize(("system", "tau"), [(TIGHT, 0.1), (TIGHT, 1e-4), (FIVE, 0.01)])
def test_converged_point_meets_the_tolerance_inside_every_limit(system, tau):
    # at the returned point: the grid limit holds strictly at every planned stage, prices and
    # local multipliers are positive, and every KKT residual (local with the grid prices,
    # grid complementarity) is within tol (1 + max |q|)
    days = 4
    soc, buy, sell, theta = random_case(system, days, 18, 4)
    soc[0, 0], soc[-1, -1] = 0.0, 1.0
    mpc_config = MPCConfig(tau=tau, backend="ipopt")
    cfg = CoordinationConfig()
    policy = CoordinatedMPC(system, mpc_config, cfg)
    sol = policy.solve(soc, buy, sell, theta)
    assert sol.converged.all() and not sol.projected.any()
    assert np.all(sol.residual <= cfg.tol) and np.all(sol.iterations >= 1)
    qp, n, N = policy._qp, system.n, system.N
    x = sol.x.reshape(days * n, -1)
    b, s = x[:, qp.ib].reshape(days, n, N).sum(1), x[:, qp.is_].reshape(days, n, N).sum(1)
    assert np.all(b < system.P_bar) and np.all(s < system.P_bar)
    assert np.all(sol.violation < 0) and np.all(sol.planned_power < system.P_bar)
    assert np.all(sol.price_buy > 0) and np.all(sol.price_sell > 0)
    assert np.all(sol.mu > 0)
    nu = np.concatenate([sol.price_buy, sol.price_sell], axis=1)
    Hd, q0, A, e = qp.data(sol.p.reshape(days * n, -1))  # prices already inside p
    rx, rg, rc, h = qp.residual(Hd, q0, A, e, x, sol.lam.reshape(days * n, -1),
                                sol.mu.reshape(days * n, N, -1), np.full(days * n, tau))
    assert np.all(h < 0)
    scale = 1 + np.abs(qp.data(np.stack([
        policy.local_mpc.parameters(soc[:, i : i + 1], buy, sell, t)
        for i, t in enumerate(split_theta(theta))], axis=1).reshape(days * n, -1))[1]
    ).reshape(days, -1).max(1)
    local = np.maximum.reduce([np.abs(rx).max(1), np.abs(rg).max(1), np.abs(rc).max((1, 2))])
    # p carries the prices divided by the discount and multiplied back: a few ulps apart
    assert np.all(local.reshape(days, n).max(1) <= cfg.tol * scale * (1 + 1e-3))
    grid = nu * (np.concatenate([b, s], axis=1) - system.P_bar) + tau
    assert np.all(np.abs(grid).max(1) <= cfg.tol * scale)


def test_a_days_solution_does_not_depend_on_the_other_days():
    # the rounds run per day (a finished day drops out, the others go on); only the start of
    # the barrier path is shared, so a day alone agrees to within the tolerance
    soc, buy, sell, theta = random_case(TIGHT, 4, 19, 6)
    policy = CoordinatedMPC(TIGHT, IPOPT)
    together = policy.solve(soc, buy, sell, theta)
    for d in range(4):
        alone = policy.solve(soc[d : d + 1], buy[d : d + 1], sell[d : d + 1], theta)
        assert alone.converged.all()
        np.testing.assert_allclose(alone.x[0], together.x[d], atol=1e-9)
        np.testing.assert_allclose(alone.price_sell[0], together.price_sell[d],
                                   rtol=1e-8, atol=1e-9)


def test_thetas_as_one_theta_or_per_battery_give_the_same_solution():
    soc, buy, sell, theta = random_case(TIGHT, 2, 5, 8)
    policy = CoordinatedMPC(TIGHT, IPOPT)
    a = policy.solve(soc, buy, sell, theta)
    b = policy.solve(soc, buy, sell, split_theta(theta))
    np.testing.assert_array_equal(a.x, b.x)
    np.testing.assert_array_equal(a.price_buy, b.price_buy)
    with pytest.raises(ValueError, match=r"buy has shape \(2, 5\)"):
        policy.solve(soc, buy[:, :5], sell, theta)
    with pytest.raises(ValueError, match="theta has n=5; expected n=3"):
        policy.solve(soc, buy, sell, random_case(FIVE, 1, 0, 0)[3])
