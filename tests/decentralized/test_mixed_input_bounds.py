"""The decentralized learner on a site whose batteries have their own input bounds U_bar:
each local MPC keeps its own bound, the coordination keeps the grid limit, and the result is
the centralized MPC's."""

from __future__ import annotations

import json

import numpy as np
import pytest

from mpcrl_lite.cli.main import main
from mpcrl_lite.config import CoordinationConfig, MPCConfig, SystemConfig
from mpcrl_lite.decentralized.coordination import CoordinatedMPC
from mpcrl_lite.decentralized.local_qp import LocalQP, local_system
from mpcrl_lite.mpc.backends.ipopt import IpoptSolver
from mpcrl_lite.mpc.formulation import GRID_INEQUALITIES, INEQUALITIES, MPC
from mpcrl_lite.system.prices import Prices
from mpcrl_lite.theta import Theta

U = (1.0, 0.6, 0.3)
MIXED = SystemConfig(U_bar=U, P_bar=1.2)  # sum U_bar = 1.9 > P_bar: the limit binds
IPOPT = MPCConfig(backend="ipopt")
FAR = CoordinationConfig(local_grid_factor=1e8)


def mixed_case(days: int, hour: int, seed: int):
    rng = np.random.default_rng(seed)
    n = MIXED.n
    buy, sell = Prices.month(MIXED, days).window(hour, MIXED.N)
    buy = buy * rng.uniform(0.7, 1.3, buy.shape)
    sell = sell * rng.uniform(0.7, 1.0, sell.shape)
    theta = Theta.nominal(MIXED).replace(
        b=rng.uniform(-3, 3, n), phi1=rng.uniform(5, 40, n), phi2=rng.uniform(-30, 0, n),
        T1=rng.uniform(5, 40, n), T2=rng.uniform(-30, 0, n),
    )
    return rng.uniform(0.0, 1.0, (days, n)), buy, sell, theta


def test_each_local_system_and_qp_has_its_batterys_bound():
    for i, u in enumerate(U):
        local = local_system(MIXED, 50.0, i)
        assert local.n == 1 and local.U_bar == u and local.P_bar == 50.0 * 1.2
    assert local_system(SystemConfig(U_bar=(2.0, 1.0, 0.5), P_bar=1.2), 10.0, 2).P_bar == 20.0
    with pytest.raises(ValueError, match="battery=3"):
        local_system(MIXED, 50.0, 3)
    mpc = MPC(local_system(MIXED))
    qp = LocalQP(mpc, U)
    rows = [int(mpc.inequality_index(g, 0)[0]) for g in ("b_max", "s_max")]
    for i, u in enumerate(U):
        # battery i's own rows b <= U_bar_i, s <= U_bar_i; its other rows are battery 0's
        assert np.all(qp.db[i][:, rows] == u)
        other = np.delete(qp.db[i], rows, axis=1)
        np.testing.assert_array_equal(other, np.delete(qp.db[0], rows, axis=1))
        ref = MPC(local_system(MIXED, battery=i)).qp_data(np.full(mpc.np, 0.5)).d
        np.testing.assert_array_equal(qp.db[i].ravel(), ref)
    with pytest.raises(ValueError, match=r"U_bar=\(1.0, -0.5\)"):
        LocalQP(mpc, (1.0, -0.5))


def test_the_start_is_inside_each_batterys_bound():
    soc, buy, sell, theta = mixed_case(2, 18, 3)
    policy = CoordinatedMPC(MIXED, IPOPT)
    qp = policy._qp
    hour = policy._hour(soc, buy, sell, list(policy._thetas(theta)))
    x = policy._start(hour).point.x.reshape(2, MIXED.n, -1)
    for i, u in enumerate(U):
        for idx in (qp.ib, qp.is_):
            assert np.all(x[:, i][:, idx] > 0) and np.all(x[:, i][:, idx] < u)
            np.testing.assert_array_equal(x[:, i][:, idx], 0.25 * min(u, 1.2 / 3))


@pytest.mark.parametrize(("hour", "seed"), [(17, 1), (7, 2)])
def test_mixed_bounds_coordination_is_the_centralized_mpc(hour, seed):
    soc, buy, sell, theta = mixed_case(3, hour, seed)
    policy = CoordinatedMPC(MIXED, IPOPT, FAR)
    sol = policy.solve(soc, buy, sell, theta)
    assert sol.converged.all() and sol.success.all() and not sol.projected.any()
    mpc, loc, n, N = MPC(MIXED), policy.local_mpc, MIXED.n, MIXED.N
    ref = IpoptSolver(mpc, IPOPT).solve_batch(soc, buy, sell, theta)
    assert ref.success.all()
    # every battery's plan within its own bound, the site within the grid limit
    b = sol.x[:, :, loc.index("b")[:, 0]]
    s = sol.x[:, :, loc.index("s")[:, 0]]
    for i, u in enumerate(U):
        assert np.all(b[:, i] < u) and np.all(s[:, i] < u)
        assert np.all(b[:, i] > 0) and np.all(s[:, i] > 0)
    assert np.all(b.sum(1) < MIXED.P_bar) and np.all(s.sum(1) < MIXED.P_bar)
    # the limit binds somewhere and a small battery's bound too (a real test of both)
    assert max(b.sum(1).max(), s.sum(1).max()) > 0.9 * MIXED.P_bar
    assert max(b[:, 2].max(), s[:, 2].max()) > 0.9 * U[2]
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


def test_compiled_rounds_and_sensitivities_are_the_reference_ones():
    soc, buy, sell, theta = mixed_case(4, 18, 5)
    fast_mpc = CoordinatedMPC(MIXED, MPCConfig())
    ref_mpc = CoordinatedMPC(MIXED, MPCConfig(backend="batch"))
    fast = fast_mpc.solve(soc, buy, sell, theta)
    ref = ref_mpc.solve(soc, buy, sell, theta)
    assert fast.compiled and not ref.compiled and ref.converged.all()
    np.testing.assert_array_equal(fast.iterations, ref.iterations)
    for name in ("x", "lam", "mu", "price_buy", "price_sell", "action"):
        a, b = getattr(fast, name), getattr(ref, name)
        assert np.abs(a - b).max() <= 1e-9 * (1.0 + np.abs(b).max()), name
    grad, ok = fast_mpc.sensitivity(fast)
    grad_ref, ok_ref = ref_mpc.sensitivity(ref)
    assert ok.all() and ok_ref.all()
    scale = np.abs(grad_ref).max(-1, keepdims=True)
    assert np.all(np.abs(grad - grad_ref) <= 1e-8 * scale)
    # the sensitivities of batteries of different bounds come from their own formulations
    assert len({id(m) for m in fast_mpc.local_mpcs}) == 3


def test_two_decentralized_learning_months_on_a_mixed_site(tmp_path):
    path = tmp_path / "site.yaml"
    path.write_text("U_bar: [1.0, 0.6, 0.3]\nP_bar: 1.2\n")
    out = tmp_path / "out"
    assert main(["learn", "--decentralized", "--months", "2", "--days", "3", "--no-figures",
                 "--out", str(out), "--system", str(path), "--quiet"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["months"] == 2 and len(summary["J"]) == 2
    assert np.all(np.isfinite(summary["J"]))
    assert np.array(summary["J_per_agent"]).shape == (2, 3)
    assert max(summary["max_P_mpc"]) < 1.2  # every planned hour within the grid limit
    history = np.load(out / "history.npz")
    for month in ("first", "last"):  # each battery's action within its own bound
        policy = history[f"{month}_policy"]
        assert policy.shape[-1] == 3
        assert np.all(np.abs(policy).reshape(-1, 3).max(0) < np.array(U))
