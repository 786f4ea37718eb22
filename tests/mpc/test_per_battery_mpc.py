"""The MPC of a mixed site: every back-end agrees with unequal batteries and the grid limit
binding; a per-battery U_bar is each battery's bound (IPOPT) or refused in one line."""

from __future__ import annotations

import numpy as np
import pytest

from mpcrl_lite.config import MPCConfig, SystemConfig
from mpcrl_lite.mpc.backends.batch import BatchSolver
from mpcrl_lite.mpc.backends.ipopt import IpoptSolver
from mpcrl_lite.mpc.backends.kernel import KernelSolver
from mpcrl_lite.mpc.formulation import MPC
from mpcrl_lite.mpc.sensitivity import PolicySensitivity
from mpcrl_lite.theta import Theta

MIXED = SystemConfig(alpha=(1 / 24, 1 / 12, 1 / 12), noise_mean=(0.1, 0.0, -0.05),
                     noise_var=(1.0, 0.5, 0.5), P_bar=1.2)


def _problem(system, days=6, seed=0):
    rng = np.random.default_rng(seed)
    soc = rng.uniform(0.1, 0.4, (days, system.n))
    buy = rng.uniform(100.0, 300.0, (days, system.N))
    buy[:, :3] = 1.0  # cheap first hours: every battery wants to buy, the grid limit binds
    return soc, buy, 0.5 * buy


def test_nominal_theta_is_each_batterys_own_model():
    theta = Theta.nominal(MIXED)
    np.testing.assert_array_equal(theta.alpha, MIXED.alpha)
    np.testing.assert_array_equal(theta.delta, np.array(MIXED.alpha) * np.array(MIXED.noise_mean))
    np.testing.assert_array_equal(Theta.nominal(SystemConfig()).to_vector(),
                                  Theta.nominal(SystemConfig(alpha=(1 / 12,) * 3)).to_vector())


def test_every_backend_agrees_on_a_mixed_site_with_the_grid_binding():
    mpc, config = MPC(MIXED), MPCConfig()
    theta = Theta.nominal(MIXED)
    soc, buy, sell = _problem(MIXED)
    ref = IpoptSolver(mpc, config).solve_batch(soc, buy, sell, theta)
    assert ref.success.all()
    planned = ref.x[:, mpc.index("b", 0)].sum(axis=1)
    assert np.any(planned > MIXED.P_bar - 0.1)  # the limit binds (up to the barrier)
    ref_sens = PolicySensitivity(mpc, config)(ref)
    for solver in (BatchSolver(mpc, config), KernelSolver(mpc, config)):
        sol = solver.solve_batch(soc, buy, sell, theta)
        assert sol.success.all()
        np.testing.assert_allclose(sol.action, ref.action, rtol=0, atol=1e-8)
        sens = solver.sensitivity(sol)
        assert sens.ok.all()
        scale = np.abs(ref_sens.grad).max(axis=1, keepdims=True) + 1.0
        np.testing.assert_allclose(sens.grad / scale, ref_sens.grad / scale, atol=1e-6)


def test_per_battery_input_bounds_in_ipopt_and_refused_by_the_compiled_backends():
    system = SystemConfig(U_bar=(2.0, 1.0, 0.5), P_bar=2.5)
    mpc, config = MPC(system), MPCConfig()
    theta = Theta.nominal(system)
    soc, buy, sell = _problem(system)
    sol = IpoptSolver(mpc, config).solve_batch(soc, buy, sell, theta)
    assert sol.success.all()
    b = sol.x[:, mpc.index("b")]  # (days, N, n)
    assert np.all(b <= np.array(system.U_bar) + 1e-9)
    assert b[..., 0].max() > 1.5  # the large battery uses its larger bound
    for backend in (BatchSolver, KernelSolver):
        with pytest.raises(ValueError, match=r"U_bar=\[2.0, 1.0, 0.5\]: .* expects one value"):
            backend(mpc, config)
