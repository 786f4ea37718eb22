"""The MPC of a mixed site: every back-end agrees with unequal batteries and the grid limit
binding, also with one input bound U_bar per battery (solutions, warm starts, sensitivities
and a short learning run)."""

from __future__ import annotations

import numpy as np
import pytest

from mpcrl_lite.config import LearningConfig, MPCConfig, SystemConfig
from mpcrl_lite.learning.experiment import Experiment
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


# one input bound per battery: the large battery may use more than the small ones may
UNEQUAL = SystemConfig(U_bar=(1.0, 0.6, 0.3), P_bar=1.2)


def _unequal_problem(days=6, seed=1):
    """States and prices with cheap first hours (every battery buys: the grid limit and the
    small batteries' own bounds bind) and an expensive evening (they sell)."""
    soc, buy, _ = _problem(UNEQUAL, days, seed)
    buy[:, 6:] = 400.0
    return soc, buy, 0.9 * buy


def _scaled(grad, ref):
    scale = np.abs(ref).max(axis=1, keepdims=True) + 1.0
    return grad / scale, ref / scale


@pytest.fixture(scope="module")
def unequal_reference():
    mpc, config = MPC(UNEQUAL), MPCConfig()
    soc, buy, sell = _unequal_problem()
    theta = Theta.nominal(UNEQUAL)
    ref = IpoptSolver(mpc, config).solve_batch(soc, buy, sell, theta)
    assert ref.success.all()
    return mpc, config, (soc, buy, sell, theta), ref, PolicySensitivity(mpc, config)(ref)


def test_ipopt_keeps_each_battery_inside_its_own_input_bound(unequal_reference):
    mpc, _, _, ref, _ = unequal_reference
    U = np.array(UNEQUAL.U_bar)
    b, s = ref.x[:, mpc.index("b")], ref.x[:, mpc.index("s")]  # (days, N, n)
    assert np.all((b > 0) & (b < U)) and np.all((s > 0) & (s < U))
    assert b[..., 0].max() > U[1] + 0.1  # the large battery uses its larger bound
    # the small battery's bound binds: it would buy more than 0.3 with the large one's bound
    assert b[..., 2].max() > 0.7 * U[2] and s[..., 2].max() > 0.8 * U[2]
    wide = UNEQUAL.replace(U_bar=1.0)
    soc, buy, sell = _unequal_problem()
    free = IpoptSolver(MPC(wide), MPCConfig()).solve_batch(soc, buy, sell, Theta.nominal(wide))
    assert free.x[:, mpc.index("b")][..., 2].max() > U[2] + 0.1
    assert np.any(b.sum(axis=2) > UNEQUAL.P_bar - 0.1)  # the grid limit binds too
    assert np.all(b.sum(axis=2) < UNEQUAL.P_bar)


@pytest.mark.parametrize("make", [
    lambda mpc, config: BatchSolver(mpc, config),
    lambda mpc, config: KernelSolver(mpc, config, method="stage"),
    lambda mpc, config: KernelSolver(mpc, config, method="agent"),
], ids=["batch", "kernel-stage", "kernel-agent"])
def test_compiled_backends_solve_unequal_input_bounds_as_ipopt(unequal_reference, make):
    mpc, config, (soc, buy, sell, theta), ref, ref_sens = unequal_reference
    solver = make(mpc, config)
    U = np.array(UNEQUAL.U_bar)
    for x0 in (None, ref.x, np.roll(ref.x, 1, axis=0)):  # cold, exact and other warm starts
        sol = solver.solve_batch(soc, buy, sell, theta, x0=x0)
        assert sol.success.all()
        np.testing.assert_allclose(sol.x, ref.x, rtol=0, atol=1e-6)
        np.testing.assert_allclose(sol.action, ref.action, rtol=0, atol=1e-8)
        b, s = sol.x[:, mpc.index("b")], sol.x[:, mpc.index("s")]
        assert np.all((b > 0) & (b < U)) and np.all((s > 0) & (s < U))
    sens = solver.sensitivity(sol)
    assert sens.ok.all()
    np.testing.assert_allclose(*_scaled(sens.grad, ref_sens.grad), atol=1e-6)
    # the compiled sensitivity of IPOPT's own solutions is IPOPT's
    np.testing.assert_allclose(*_scaled(solver.sensitivity(ref).grad, ref_sens.grad), atol=1e-6)


def test_kernel_structured_adjoint_with_unequal_input_bounds(unequal_reference):
    mpc, config, problem, _, ref_sens = unequal_reference
    solver = KernelSolver(mpc, config, method="agent")
    solver.structured_adjoint = True  # all columns at once, as for many agents
    sens = solver.sensitivity(solver.solve_batch(*problem))
    assert sens.ok.all()
    np.testing.assert_allclose(*_scaled(sens.grad, ref_sens.grad), atol=1e-6)


def test_sensitivity_with_unequal_input_bounds_matches_finite_differences(unequal_reference):
    """d pi / d theta of the kernel against central differences of its own policy."""
    mpc, config, (soc, buy, sell, theta), _, _ = unequal_reference
    solver = KernelSolver(mpc, config)
    sens = solver.sensitivity(solver.solve_batch(soc[:2], buy[:2], sell[:2], theta))
    vec, h = theta.to_vector(), 1e-6
    for k in range(0, len(vec), 7):  # a spread of theta's entries
        step = np.zeros_like(vec)
        step[k] = h
        up, down = (solver.solve_batch(soc[:2], buy[:2], sell[:2], Theta.from_vector(
            vec + sign * step, UNEQUAL.n)).action for sign in (1.0, -1.0))
        np.testing.assert_allclose(sens.grad[:, k], (up - down) / (2 * h), rtol=1e-4,
                                   atol=1e-6, err_msg=f"theta entry {k}")


def test_auto_chooses_the_kernel_for_unequal_input_bounds():
    from mpcrl_lite.mpc.backends.registry import make_solver

    assert make_solver(MPC(UNEQUAL)).name == "kernel"
    assert make_solver(MPC(UNEQUAL), MPCConfig(backend="batch")).name == "batch"


def test_learning_a_site_with_unequal_input_bounds_on_the_kernel_follows_ipopt():
    system = UNEQUAL.replace(N=6)
    learning = LearningConfig(days_per_month=2, months=2, seed=3, eval_every=1)
    runs = {backend: Experiment(system=system, mpc_config=MPCConfig(backend=backend),
                                learning=learning).run(progress=False)
            for backend in ("ipopt", "kernel")}
    ref, fast = runs["ipopt"], runs["kernel"]
    assert ref.backend == "ipopt" and fast.backend == "kernel"
    np.testing.assert_allclose(fast.J, ref.J, rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(fast.J_eval, ref.J_eval, rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(fast.theta_final, ref.theta_final, rtol=1e-5, atol=1e-8)
    assert fast.solver_failures == ref.solver_failures == [0, 0]
    assert not np.allclose(ref.theta_final, Theta.nominal(system).to_vector())  # it learned
