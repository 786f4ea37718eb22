"""The MPC as V and Q (:mod:`mpcrl_lite.mpc.value`): Q at the policy's own action is V, and the
theta gradient and Hessian of both are those of central finite differences of the solved values."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import window

from mpcrl_lite.config import MPCConfig
from mpcrl_lite.mpc.backends.kernel import KernelSolver
from mpcrl_lite.mpc.value import MPCValue
from mpcrl_lite.theta import Theta


@pytest.fixture(scope="module")
def value(mpc):
    return MPCValue(mpc, MPCConfig())


@pytest.fixture(scope="module")
def case(mpc, ipopt, system, month_prices):
    """Three states over two hours of the month, solved by the reference back-end."""
    rng = np.random.default_rng(7)
    theta = Theta.from_vector(Theta.nominal(system).to_vector()
                              + np.concatenate([np.zeros(6), rng.uniform(-3, 3, 6),
                                                rng.uniform(0, 20, 3), rng.uniform(-20, 20, 6),
                                                rng.uniform(0, 20, 3), rng.uniform(-20, 20, 6)]),
                              system.n)
    soc = rng.uniform(0.15, 0.85, (3, system.n))
    buy = np.stack([window(month_prices, day, hour, mpc.N) for day, hour in ((0, 3), (4, 17),
                                                                            (9, 20))])
    sell = 0.6 * buy
    return soc, buy, sell, theta, ipopt.solve_batch(soc, buy, sell, theta)


def test_q_at_the_policy_action_is_v(value, case):
    soc, buy, sell, theta, sol = case
    V = value.state_value(sol)
    Q = value.action_value(soc, buy, sell, theta, sol.action, x0=sol.x)
    assert V.ok.all() and Q.ok.all()
    np.testing.assert_allclose(Q.value, V.value, rtol=1e-10)
    np.testing.assert_allclose(Q.grad, V.grad, rtol=1e-8, atol=1e-8 * np.abs(V.grad).max())
    np.testing.assert_allclose(Q.solution.action, sol.action, atol=1e-9)


def test_q_is_minimal_at_the_policy_action(value, case):
    soc, buy, sell, theta, sol = case
    V = value.state_value(sol)
    for factor in (0.8, 0.95):  # shrunk towards idle: strictly inside every bound
        Q = value.action_value(soc, buy, sell, theta, factor * sol.action, x0=sol.x)
        assert Q.ok.all()
        assert np.all(Q.value > V.value)


def _fd(fun, tvec, h=1e-5):
    """Central differences of ``fun(theta_vector)`` entry by entry (relative steps)."""
    cols = []
    for i in range(tvec.size):
        e = np.zeros_like(tvec)
        e[i] = h * max(1.0, abs(tvec[i]))
        cols.append((fun(tvec + e) - fun(tvec - e)) / (2 * e[i]))
    return np.stack(cols, axis=-1)


@pytest.mark.parametrize("kind", ["V", "Q"])
def test_gradient_and_hessian_match_finite_differences(value, case, ipopt, system, kind):
    soc, buy, sell, theta, sol = case
    soc, buy, sell = soc[:1], buy[:1], sell[:1]
    a = 0.7 * sol.action[:1] + np.array([0.1, -0.1, 0.05])

    def values(tvec):
        t = Theta.from_vector(tvec, system.n)
        if kind == "V":
            return value.state_value(ipopt.solve_batch(soc, buy, sell, t), hessian=True)
        return value.action_value(soc, buy, sell, t, a, x0=sol.x[:1], hessian=True)

    tvec = theta.to_vector()
    at = values(tvec)
    assert at.ok.all()
    grad_fd = _fd(lambda t: values(t).value[0], tvec)
    hess_fd = _fd(lambda t: values(t).grad[0], tvec)
    assert np.abs(grad_fd - at.grad[0]).max() <= 1e-6 * np.abs(at.grad[0]).max()
    assert np.abs(hess_fd - at.hess[0]).max() <= 1e-6 * np.abs(at.hess[0]).max()
    np.testing.assert_allclose(at.hess[0], at.hess[0].T)


def test_v_from_the_kernel_back_end_equals_the_reference(value, case, mpc):
    soc, buy, sell, theta, sol = case
    kernel = KernelSolver(mpc, MPCConfig()).solve_batch(soc, buy, sell, theta)
    ref, fast = value.state_value(sol, hessian=True), value.state_value(kernel, hessian=True)
    np.testing.assert_allclose(fast.value, ref.value, rtol=1e-9)
    np.testing.assert_allclose(fast.grad, ref.grad, rtol=1e-7, atol=1e-7 * np.abs(ref.grad).max())
    np.testing.assert_allclose(fast.hess, ref.hess, atol=1e-6 * np.abs(ref.hess).max())


def test_an_action_on_a_bound_fails_without_raising(value, case, system):
    soc, buy, sell, theta, sol = case
    a = sol.action.copy()
    a[0, 0] = system.U_bar  # b_0 = U_bar: outside the barrier's domain
    Q = value.action_value(soc, buy, sell, theta, a, x0=sol.x)
    assert not Q.ok[0] and Q.ok[1:].all()
    assert Q.reason[0] and np.isnan(Q.value[0]) and not Q.grad[0].any()


def test_bad_action_shape_is_refused(value, case):
    soc, buy, sell, theta, _ = case
    with pytest.raises(ValueError, match="a has shape"):
        value.action_value(soc, buy, sell, theta, np.zeros((2, 3)))


@pytest.fixture(scope="module")
def kernel_value(mpc):
    return MPCValue(mpc, MPCConfig(), backend="kernel")


def test_q_on_the_kernel_equals_the_reference(value, kernel_value, case, system):
    soc, buy, sell, theta, sol = case
    rng = np.random.default_rng(3)
    a = 0.8 * sol.action + rng.uniform(-0.1, 0.1, sol.action.shape)
    ref = value.action_value(soc, buy, sell, theta, a, x0=sol.x, hessian=True)
    fast = kernel_value.action_value(soc, buy, sell, theta, a, x0=sol.x, hessian=True)
    assert ref.ok.all() and fast.ok.all()
    np.testing.assert_allclose(fast.value, ref.value, rtol=1e-9)
    np.testing.assert_allclose(fast.grad, ref.grad, atol=1e-7 * np.abs(ref.grad).max())
    np.testing.assert_allclose(fast.hess, ref.hess, atol=1e-6 * np.abs(ref.hess).max())
    np.testing.assert_allclose(fast.solution.x, ref.solution.x, atol=1e-7)
    # without a warm start, and at the policy's own action: V
    cold = kernel_value.action_value(soc, buy, sell, theta, sol.action)
    np.testing.assert_allclose(cold.value, value.state_value(sol).value, rtol=1e-9)


def test_kernel_refuses_an_action_on_a_bound(kernel_value, case, system):
    soc, buy, sell, theta, sol = case
    a = 0.5 * sol.action
    a[1] = [system.U_bar, 0.0, 0.0]
    a[2] = [0.6 * system.P_bar, 0.6 * system.P_bar, 0.0]  # beyond the grid limit
    Q = kernel_value.action_value(soc, buy, sell, theta, a, x0=sol.x)
    assert Q.ok.tolist() == [True, False, False]
    assert Q.reason[1] and np.isnan(Q.value[1:]).all()


def test_closed_form_value_and_gradient_equal_casadi(value, case):
    """The numpy value and theta gradient used for every row against the CasADi
    expressions of the formulation (V problem)."""
    sol = case[-1]
    V = value.state_value(sol)
    for d in range(len(sol)):
        y = np.concatenate([sol.x[d], sol.lam[d], sol.mu[d]])
        v, dL = value._v.value(y, sol.p[d], MPCConfig().tau)
        np.testing.assert_allclose(V.value[d], float(v), rtol=1e-12)
        np.testing.assert_allclose(V.grad[d], np.array(dL).ravel(), rtol=1e-10, atol=1e-9)
