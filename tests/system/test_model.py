"""Tests of the true battery system (mpcrl_lite.system.battery)."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp
from scipy.optimize import minimize

from mpcrl_lite.config import ConfigWarning, SystemConfig
from mpcrl_lite.system.battery import (
    StepResult,
    agent_costs,
    discounted_return,
    grid_power,
    low_level_control,
    penalty,
    project_action,
    sample_noise,
    split_action,
    step,
)

SYSTEM = SystemConfig()  # n = 3, Table I
SMALL = SystemConfig(n=2, alpha=0.1, U_bar=1.0, P_bar=1.5, p=1000.0)

finite = st.floats(allow_nan=False, allow_infinity=False)


DAYS = st.integers(1, 4)


def batch(elements, days=DAYS, n=3):
    return days.flatmap(lambda d: hnp.arrays(float, (d, n), elements=elements))


# -- low-level controller: invariants ------------------------------------------------------
@pytest.mark.filterwarnings("ignore::RuntimeWarning")  # costs of huge powers overflow
@settings(max_examples=300, deadline=None)
@given(
    data=st.data(),
    alpha=st.floats(1e-3, 10.0),
    days=st.integers(1, 4),
)
def test_soc_stays_in_unit_interval_for_any_finite_input(data, alpha, days):
    system = SystemConfig(alpha=alpha)
    shape = (days, system.n)
    soc = data.draw(hnp.arrays(float, shape, elements=st.floats(0.0, 1.0)))
    a = data.draw(hnp.arrays(float, shape, elements=finite))
    noise = data.draw(hnp.arrays(float, shape, elements=finite))

    result = step(soc, a, noise, 100.0, 50.0, system)

    assert result.soc_next.shape == shape
    assert np.all(result.soc_next >= -1e-12) and np.all(result.soc_next <= 1 + 1e-12)
    assert np.all(result.b >= 0) and np.all(result.s >= 0)
    assert np.all((result.b == 0) | (result.s == 0))
    with np.errstate(over="ignore"):
        raw = soc + alpha * (noise + a)
    inside = (raw >= 0) & (raw <= 1)
    assert np.all(result.correction[inside] == 0)
    np.testing.assert_array_equal(result.soc_next[inside], raw[inside])
    # above 1 the controller only ever lowers the net power, below 0 only raises it
    assert np.all(result.correction[raw > 1] <= 0)
    assert np.all(result.correction[raw < 0] >= 0)
    assert np.all(result.soc_next[raw > 1] == 1.0)
    assert np.all(result.soc_next[raw < 0] == 0.0)


@settings(max_examples=200, deadline=None)
@given(
    data=st.data(),
    alpha=st.floats(1e-2, 1.0),
    days=st.integers(1, 4),
)
def test_applied_powers_reproduce_next_soc(data, alpha, days):
    """For moderate values, soc + alpha (Delta + b - s) with the applied powers is soc_next."""
    system = SystemConfig(alpha=alpha)
    shape = (days, system.n)
    soc = data.draw(hnp.arrays(float, shape, elements=st.floats(0.0, 1.0)))
    a = data.draw(hnp.arrays(float, shape, elements=st.floats(-1e3, 1e3)))
    noise = data.draw(hnp.arrays(float, shape, elements=st.floats(-1e3, 1e3)))

    b, s, correction = low_level_control(soc, a, noise, system)
    result = step(soc, a, noise, 1.0, 0.5, system)

    np.testing.assert_array_equal(b, result.b)
    np.testing.assert_array_equal(s, result.s)
    np.testing.assert_allclose(b - s, a + correction, atol=1e-9)
    np.testing.assert_allclose(soc + alpha * (noise + b - s), result.soc_next, atol=1e-9)


# -- low-level controller: hand-computed cases ---------------------------------------------
def _llc(soc, a, noise, system=SMALL):
    return low_level_control(np.array([soc]), np.array([a]), np.array([noise]), system)


def test_llc_upper_edge_buys_less():
    # raw = 0.95 + 0.1 (0.3 + 1.0) = 1.08 > 1; allowed net = (1 - 0.95)/0.1 - 0.3 = 0.2
    b, s, corr = _llc([0.95, 0.5], [1.0, 1.0], [0.3, 0.3])
    np.testing.assert_allclose(b, [[0.2, 1.0]])
    np.testing.assert_allclose(s, [[0.0, 0.0]])
    np.testing.assert_allclose(corr, [[-0.8, 0.0]])
    assert corr[0, 1] == 0.0


def test_llc_upper_edge_buys_less_first_then_sells_extra():
    # raw = 0.95 + 0.1 (0.8 + 0.2) = 1.05; allowed net = 0.5 - 0.8 = -0.3:
    # the planned purchase 0.2 is dropped and 0.3 is sold on top
    b, s, corr = _llc([0.95, 0.95], [0.2, -0.5], [0.8, 0.8])
    np.testing.assert_allclose(b, [[0.0, 0.0]])
    np.testing.assert_allclose(s, [[0.3, 0.5]])
    np.testing.assert_allclose(corr, [[-0.5, 0.0]], atol=1e-15)
    res = step([[0.95, 0.95]], [[0.2, -0.5]], [[0.8, 0.8]], 1.0, 0.5, SMALL)
    np.testing.assert_allclose(res.soc_next, [[1.0, 0.98]])


def test_llc_lower_edge_sells_less():
    # raw = 0.05 + 0.1 (-0.2 - 0.5) = -0.02; allowed net = -0.05/0.1 + 0.2 = -0.3
    b, s, corr = _llc([0.05, 0.5], [-0.5, -0.5], [-0.2, -0.2])
    np.testing.assert_allclose(b, [[0.0, 0.0]])
    np.testing.assert_allclose(s, [[0.3, 0.5]])
    np.testing.assert_allclose(corr, [[0.2, 0.0]])


def test_llc_lower_edge_sells_less_first_then_buys_extra():
    # raw = 0.05 + 0.1 (-0.6 - 0.5) = -0.06; allowed net = -0.5 + 0.6 = 0.1:
    # the planned sale 0.5 is dropped and 0.1 is bought on top
    b, s, corr = _llc([0.05, 0.05], [-0.5, 0.0], [-0.6, -0.6])
    np.testing.assert_allclose(b, [[0.1, 0.1]])
    np.testing.assert_allclose(s, [[0.0, 0.0]])
    np.testing.assert_allclose(corr, [[0.6, 0.1]])
    res = step([[0.05, 0.05]], [[-0.5, 0.0]], [[-0.6, -0.6]], 1.0, 0.5, SMALL)
    np.testing.assert_array_equal(res.soc_next, [[0.0, 0.0]])


def test_llc_extra_power_is_not_bounded_by_U_bar_or_P_bar():
    # a surplus of 30 (per hour) at a full battery must all be sold: 30 > U_bar, P_bar
    b, s, _ = _llc([1.0, 1.0], [0.0, 0.0], [30.0, 30.0])
    np.testing.assert_allclose(s, [[30.0, 30.0]])
    assert grid_power(b, s)[0] == pytest.approx(60.0)


def test_llc_keeps_soc_exactly_at_edges_when_resting_there():
    res = step([[1.0, 0.0]], [[0.0, 0.0]], [[0.0, 0.0]], 1.0, 0.5, SMALL)
    np.testing.assert_array_equal(res.soc_next, [[1.0, 0.0]])
    np.testing.assert_array_equal(res.correction, [[0.0, 0.0]])


# -- costs ---------------------------------------------------------------------------------
def test_penalty_hand_values():
    soc = np.array([0.05, 0.1, 0.5, 0.9, 0.95, 0.0, 1.0])
    np.testing.assert_allclose(penalty(soc, SYSTEM), [50, 0, 0, 0, 50, 100, 100], atol=1e-9)
    assert penalty(0.05, SYSTEM) == pytest.approx(50.0)
    assert penalty(0.05, SYSTEM.replace(p=10.0)) == pytest.approx(0.5)


def test_agent_costs_broadcast_day_prices_over_agents():
    soc = np.array([[0.5, 0.05, 0.95], [0.5, 0.5, 0.5]])
    b = np.array([[1.0, 0.0, 0.5], [0.0, 0.2, 0.0]])
    s = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0]])
    buy = np.array([100.0, 300.0])
    sell = np.array([50.0, 150.0])
    costs = agent_costs(soc, b, s, buy, sell, SYSTEM)
    expected = np.array([[100.0, -50.0 + 50.0, 50.0 + 50.0], [-150.0, 60.0, 0.0]])
    np.testing.assert_allclose(costs, expected, atol=1e-9)


def test_step_costs_use_state_before_step_and_applied_powers():
    # soc 0.05 is penalised (50) even though the step moves it back inside the band;
    # the controller's extra purchase is charged at the buying price
    res = step([[0.05, 0.5]], [[-0.5, 0.0]], [[-0.6, 0.0]], [200.0], [100.0], SMALL)
    assert isinstance(res, StepResult)
    np.testing.assert_allclose(res.agent_cost, [[200.0 * 0.1 + 50.0, 0.0]])
    np.testing.assert_allclose(res.stage_cost, [70.0])
    np.testing.assert_allclose(res.grid_power, [0.1])


def test_grid_power_hand_values():
    b = np.array([[0.5, 0.7, 0.0], [0.0, 0.0, 0.0]])
    s = np.array([[0.0, 0.0, 1.0], [0.4, 0.4, 0.0]])
    np.testing.assert_allclose(grid_power(b, s), [1.2, 0.8])


def test_split_action():
    b, s = split_action([[1.5, -0.25, 0.0]])
    np.testing.assert_array_equal(b, [[1.5, 0.0, 0.0]])
    np.testing.assert_array_equal(s, [[0.0, 0.25, 0.0]])


# -- project_action ------------------------------------------------------------------------
def _feasible(x, system, tol=1e-12):
    return (
        np.all(np.abs(x) <= system.U_bar + tol)
        and np.all(np.maximum(x, 0).sum(-1) <= system.P_bar + tol)
        and np.all(np.maximum(-x, 0).sum(-1) <= system.P_bar + tol)
    )


def _qp_projection(y, system):
    """Brute-force projection with SLSQP on the split variables (b, s), a = b - s."""
    n = y.size
    buy_row, sell_row = np.r_[np.ones(n), np.zeros(n)], np.r_[np.zeros(n), np.ones(n)]
    cons = [
        {"type": "ineq", "fun": lambda z: system.P_bar - buy_row @ z, "jac": lambda z: -buy_row},
        {"type": "ineq", "fun": lambda z: system.P_bar - sell_row @ z, "jac": lambda z: -sell_row},
    ]

    def fun(z):
        r = z[:n] - z[n:] - y
        return r @ r, np.r_[2 * r, -2 * r]

    z0 = np.r_[np.clip(y, 0, system.U_bar), np.clip(-y, 0, system.U_bar)] * 0.5
    sol = minimize(
        fun, z0, jac=True, method="SLSQP", bounds=[(0, system.U_bar)] * (2 * n),
        constraints=cons, options={"ftol": 1e-13, "maxiter": 1000},
    )
    assert sol.success, sol.message
    return sol.x[:n] - sol.x[n:]


@pytest.mark.parametrize("n", [1, 2, 3, 5, 8])
def test_project_action_matches_brute_force_qp(n):
    rng = np.random.default_rng(n)
    system = SystemConfig(n=n, U_bar=1.0, P_bar=0.4 * n + 0.1)
    a = rng.normal(0.0, 1.5, size=(40, n))
    a[::5] *= 0.1  # some already feasible rows
    x = project_action(a, system)
    for row, got in zip(a, x):
        np.testing.assert_allclose(got, _qp_projection(row, system), atol=1e-6)


@pytest.mark.parametrize("n", [2, 3, 6])
def test_project_action_satisfies_optimality_condition(n):
    """x is the projection iff <a - x, z - x> <= 0 for every feasible z."""
    rng = np.random.default_rng(10 + n)
    system = SystemConfig(n=n, U_bar=1.0, P_bar=0.5 * n)
    a = rng.normal(0.0, 2.0, size=(20, n))
    x = project_action(a, system)
    z = project_action(rng.normal(0.0, 2.0, size=(500, n)), system)  # feasible points
    assert _feasible(z, system)
    inner = np.einsum("ik,ijk->ij", a - x, z[None, :, :] - x[:, None, :])
    assert inner.max() <= 1e-9


@settings(max_examples=300, deadline=None)
@given(
    data=st.data(),
    n=st.integers(1, 6),
    U_bar=st.floats(0.1, 5.0),
    frac=st.floats(0.05, 1.2),
)
def test_project_action_feasible_idempotent_and_exact_when_feasible(data, n, U_bar, frac):
    with warnings.catch_warnings():  # P_bar >= n U_bar (never binding) is part of the test
        warnings.simplefilter("ignore", ConfigWarning)
        system = SystemConfig(n=n, U_bar=U_bar, P_bar=max(frac * n * U_bar, 1e-3))
    a = data.draw(batch(st.floats(-1e4, 1e4), n=n))
    x = project_action(a, system)
    assert x.shape == a.shape
    assert _feasible(x, system, tol=1e-9)
    np.testing.assert_allclose(project_action(x, system), x, atol=1e-9)
    # signs never flip, and feasible inputs come back unchanged
    assert np.all(x * a >= 0)
    feasible_rows = [
        i for i in range(a.shape[0]) if _feasible(a[i : i + 1], system, tol=0.0)
    ]
    np.testing.assert_array_equal(x[feasible_rows], a[feasible_rows])


def test_project_action_hand_case():
    # U_bar = 1, P_bar = 1.5: buying parts (2, 1, 0) -> clip at 1 gives (1, 1, 0), sum 2 > 1.5,
    # threshold tau = 0.25 gives (0.75, 0.75, 0); the selling part (0, 0, 3) becomes (0, 0, 1)
    system = SystemConfig(n=3)
    x = project_action([[2.0, 1.0, -3.0]], system)
    np.testing.assert_allclose(x, [[1.0, 0.5, -1.0]])
    x = project_action([[2.0, 1.25, 0.0]], system)
    np.testing.assert_allclose(x, [[1.0, 0.5, 0.0]])
    x = project_action([[1.0, 1.0, 1.0]], system)
    np.testing.assert_allclose(x, [[0.5, 0.5, 0.5]])


# -- noise ---------------------------------------------------------------------------------
def test_sample_noise_moments_and_shape():
    system = SystemConfig(noise_mean=0.3, noise_var=0.5)
    delta = sample_noise(np.random.default_rng(0), (200_000, 3), system)
    assert delta.shape == (200_000, 3)
    assert delta.mean() == pytest.approx(0.3, abs=5e-3)
    assert delta.var() == pytest.approx(0.5, rel=1e-2)  # a variance, not a std
    corr = np.corrcoef(delta.T)
    assert np.abs(corr - np.eye(3)).max() < 1e-2


# -- whole days ----------------------------------------------------------------------------
def test_discounted_return_constant_costs_geometric_series():
    hours, gamma, c = 24, 0.9, 3.5
    costs = np.full((hours, 4), c)
    np.testing.assert_allclose(
        discounted_return(costs, gamma), c * (1 - gamma**hours) / (1 - gamma)
    )
    costs3 = np.full((hours, 2, 3), c)
    out = discounted_return(costs3, gamma)
    assert out.shape == (2, 3)
    np.testing.assert_allclose(out, c * (1 - gamma**hours) / (1 - gamma))
    np.testing.assert_allclose(discounted_return(costs, 1.0), c * hours)


# -- bad inputs ----------------------------------------------------------------------------
def _zeros(days=1, n=3):
    return np.zeros((days, n))


def _half(days=1, n=3):
    return np.full((days, n), 0.5)


@pytest.mark.parametrize(
    "call, match",
    [
        (
            lambda: step([[0.5, 0.5, np.nan]], _zeros(), _zeros(), 1.0, 1.0, SYSTEM),
            r"soc\[0, 2\]=.*nan",
        ),
        (
            lambda: step(_half(), [[0.0, np.inf, 0.0]], _zeros(), 1.0, 1.0, SYSTEM),
            r"a\[0, 1\]=.*inf",
        ),
        (
            lambda: step(_half(), _zeros(), _zeros(2), 1.0, 1.0, SYSTEM),
            r"noise has shape \(2, 3\).*\(1, 3\)",
        ),
        (
            lambda: step(_half(1, 2), _zeros(1, 2), _zeros(1, 2), 1.0, 1.0, SYSTEM),
            r"soc has shape \(1, 2\).*\(days, 3\)",
        ),
        (
            lambda: step(np.full(3, 0.5), np.zeros(3), np.zeros(3), 1.0, 1.0, SYSTEM),
            r"soc has shape \(3,\)",
        ),
        (
            lambda: step([[0.5, 1.5, 0.5]], _zeros(), _zeros(), 1.0, 1.0, SYSTEM),
            r"soc\[0, 1\]=.*1\.5.*\[0, 1\]",
        ),
        (
            lambda: step(_half(2), _zeros(2), _zeros(2), [1.0, 2.0, 3.0], 1.0, SYSTEM),
            r"buy_price has shape \(3,\).*\(2,\)",
        ),
        (
            lambda: step(_half(), _zeros(), _zeros(), 1.0, [np.nan], SYSTEM),
            r"sell_price\[0\]=.*nan",
        ),
        (
            lambda: low_level_control([[0.5, -0.1, 0.5]], _zeros(), _zeros(), SYSTEM),
            r"soc\[0, 1\]=.*-0\.1",
        ),
        (lambda: project_action([[np.nan, 0.0, 0.0]], SYSTEM), r"a\[0, 0\]=.*nan"),
        (lambda: project_action(_zeros(2, 4), SYSTEM), r"a has shape \(2, 4\)"),
        (lambda: project_action(_zeros(), "system"), r"system='system'"),
        (lambda: penalty([0.5, np.inf], SYSTEM), r"soc\[1\]=.*inf"),
        (
            lambda: agent_costs(_half(), [[-1.0, 0.0, 0.0]], _zeros(), 1.0, 1.0, SYSTEM),
            r"b\[0, 0\]=.*-1\.0.*>= 0",
        ),
        (lambda: grid_power(_zeros(2), _zeros(2, 2)), r"s has shape \(2, 2\).*\(2, 3\)"),
        (lambda: grid_power(_zeros(), [[0.0, -2.0, 0.0]]), r"s\[0, 1\]=.*-2\.0"),
        (lambda: split_action("abc"), r"a='abc'"),
        (lambda: discounted_return(np.ones((3, 2)), 1.5), r"gamma=1\.5"),
        (lambda: discounted_return(np.ones((3, 2)), 0.0), r"gamma=0\.0"),
        (lambda: discounted_return(5.0, 0.9), r"stage_costs has shape \(\)"),
        (lambda: discounted_return([1.0, np.nan], 0.9), r"stage_costs\[1\]=.*nan"),
        (
            lambda: sample_noise(np.random.RandomState(0), (1, 3), SYSTEM),
            r"rng=.*Generator",
        ),
        (
            lambda: sample_noise(np.random.default_rng(0), (1, -3), SYSTEM),
            r"shape=\(1, -3\)",
        ),
    ],
)
def test_bad_inputs_raise_value_error_naming_the_value(call, match):
    with pytest.raises(ValueError, match=match):
        call()
