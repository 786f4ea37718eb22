"""LSTD must recover value functions known in closed form.

The test system is scalar and linear, ``x+ = a x + c u + eps`` with ``eps ~ N(0, s2)``, the
policy is affine, ``u = k x + m`` (``theta = (k, m)``, so ``grad_theta pi = [x, 1]``), and the
stage cost is ``q x^2 + r u^2``. Then

* ``V(x) = P x^2 + p x + C`` with (matching powers of x in the Bellman equation)
  ``P = (q + r k^2) / (1 - gamma A^2)``, ``p = (2 r k m + 2 gamma P A B) / (1 - gamma A)``,
  ``C = (r m^2 + gamma (P (B^2 + s2) + p B)) / (1 - gamma)``, where ``A = a + c k`` and
  ``B = c m`` (closed loop ``x+ = A x + B + eps``);
* ``Q(x, u) = q x^2 + r u^2 + gamma E[V(x+)]`` is quadratic in u, and at ``u = pi(x)``
  ``dQ/du = 2 r pi + gamma (2 P c (a x + c pi) + p c) = g1 x + g0``;
* with exploration ``e`` (zero mean, symmetric, independent of x) the compatible critic's
  ``grad_theta pi^T w = w1 x + w2`` reproduces ``dQ/du`` exactly, so ``w = (g1, g0)``; the
  curvature ``h e^2`` of Q in u (``h = r + gamma P c^2``) only moves the constant of the
  baseline by ``h E[e^2] / (1 - gamma)``.
"""

from __future__ import annotations

import numpy as np
import pytest

from mpcrl_lite.config import VALUE_FEATURE_SETS, VALUE_FEATURES
from mpcrl_lite.learning.lstd import (
    LSTDResult,
    compatible_features,
    lstd_q,
    lstd_v,
    monte_carlo_returns,
    prices_left,
    state_features,
    value_baseline_features,
    value_features,
)

SYS = {"a": 0.9, "c": 0.5, "q": 1.0, "r": 0.5, "s2": 0.04, "gamma": 0.9}
K, M = -0.6, 0.3  # policy u = K x + M


def closed_form(a, c, q, r, s2, gamma, k=K, m=M):
    """(P, p, C) of V, (g1, g0) of dQ/du at u = pi, and the curvature h of Q in u."""
    A, B = a + c * k, c * m
    P = (q + r * k**2) / (1 - gamma * A**2)
    p = (2 * r * k * m + 2 * gamma * P * A * B) / (1 - gamma * A)
    C = (r * m**2 + gamma * (P * (B**2 + s2) + p * B)) / (1 - gamma)
    # dQ/du = 2 r u + gamma (2 P c (a x + c u) + p c), with u = k x + m
    g1 = 2 * r * k + 2 * gamma * P * c * (a + c * k)
    g0 = 2 * r * m + gamma * (2 * P * c * c * m + p * c)
    h = r + gamma * P * c**2
    return {"P": P, "p": p, "C": C, "g1": g1, "g0": g0, "h": h}


def scalar_features(x):
    """Phi = [x^2, x, 1] for scalar states of any shape."""
    return value_features(np.asarray(x)[..., None])


def expected_next_features(x, u, a, c, s2):
    """E[Phi(x+) | x, u]: the exact successor features in expectation."""
    mean = a * x + c * u
    return np.stack([mean**2 + s2, mean, np.ones_like(mean)], axis=-1)


# -- features ------------------------------------------------------------------------------
def test_value_features_shape_and_order():
    soc = np.array([[[0.2, 0.5, 0.9]]] * 4)  # (4, 1, 3)
    phi = value_features(soc)
    assert phi.shape == (4, 1, 7)
    np.testing.assert_allclose(phi[0, 0], [0.04, 0.25, 0.81, 0.2, 0.5, 0.9, 1.0])
    with pytest.raises(ValueError, match="soc has shape"):
        value_features(np.float64(0.5))


def test_feature_sets_are_the_configs_and_agree_with_each_other():
    assert tuple(VALUE_FEATURE_SETS) == VALUE_FEATURES
    soc = np.random.default_rng(1).uniform(size=(6, 2, 3))  # a 5-hour day, 2 days
    hour = np.array([0, 1, 2, 3, 4, 5])[:, None]           # 5 is the end of the day
    buy = np.random.default_rng(2).uniform(10.0, 90.0, size=(5, 2))
    for kind in VALUE_FEATURE_SETS:
        # states at given hours and the states of a recorded period give the same features
        np.testing.assert_array_equal(
            state_features(soc, hour, kind, hours_per_day=5, prices_left=prices_left(buy)),
            value_baseline_features(soc, kind, buy),
        )
    both = state_features(soc, hour, "paper+hour", hours_per_day=5)
    np.testing.assert_array_equal(both[..., :6], value_features(soc)[..., :6])
    np.testing.assert_array_equal(both[..., 6:], state_features(soc, hour, "hour", 5))
    np.testing.assert_array_equal(both[:5, 1, 6:], np.eye(5))
    assert np.all(both[5, :, 6:] == 0)  # no indicator at the end of the day
    assert state_features(soc, hour, "hour").shape == (6, 2, 24)  # 24 hours by default
    # the paper's features once per hour, hour-major; nothing at the end of the day
    per_hour = state_features(soc, hour, "hour*paper", hours_per_day=5)
    assert per_hour.shape == (6, 2, 5 * 7)
    blocks = per_hour.reshape(6, 2, 5, 7)
    for k in range(5):
        np.testing.assert_array_equal(blocks[k, :, k], value_features(soc[k]))
        assert np.all(np.delete(blocks[k], k, axis=1) == 0)
    assert np.all(per_hour[5] == 0)
    with pytest.raises(ValueError, match="kind='cubic'"):
        state_features(soc, hour, "cubic")
    with pytest.raises(ValueError, match="needs prices_left"):
        state_features(soc, hour, "hour*paper+price", hours_per_day=5)
    with pytest.raises(ValueError, match="needs buy"):
        value_baseline_features(soc, "hour*paper+price")
    with pytest.raises(ValueError, match=r"buy has shape \(4, 2\)"):
        value_baseline_features(soc, "hour*paper+price", buy[:4])
    with pytest.raises(ValueError, match=r"hour has shape \(3,\)"):
        state_features(soc, np.arange(3), "hour")


def test_compatible_features_matches_definition():
    rng = np.random.default_rng(0)
    grad_pi = rng.normal(size=(5, 2, 30, 3))
    a, pi = rng.normal(size=(2, 5, 2, 3))
    psi = compatible_features(grad_pi, a, pi)
    assert psi.shape == (5, 2, 30)
    np.testing.assert_allclose(psi[3, 1], grad_pi[3, 1] @ (a[3, 1] - pi[3, 1]))
    with pytest.raises(ValueError, match=r"a has shape \(5, 3\)"):
        compatible_features(grad_pi, a[:, 0], pi)


# -- lstd_v ----------------------------------------------------------------------------------
def test_lstd_v_exact_with_expected_successor():
    """With E[Phi(x+)|x] in place of a sampled successor, LSTD(0) is exact."""
    cf = closed_form(**SYS)
    x = np.linspace(-2, 2, 41)
    u = K * x + M
    cost = SYS["q"] * x**2 + SYS["r"] * u**2
    res = lstd_v(
        scalar_features(x), cost, expected_next_features(x, u, SYS["a"], SYS["c"], SYS["s2"]),
        SYS["gamma"],
    )
    np.testing.assert_allclose(res.v, [cf["P"], cf["p"], cf["C"]], rtol=1e-10)
    assert res.w.shape == (0,) and res.n_samples == 41
    assert not res.rank_deficient and np.isfinite(res.condition)
    assert res.td_rms < 1e-9


def test_lstd_v_exact_on_noise_free_samples():
    """Deterministic dynamics: real sampled transitions, exact answer."""
    system = dict(SYS, s2=0.0)
    cf = closed_form(**system)
    x = np.random.default_rng(1).uniform(-2, 2, size=(24, 30))  # (hours, days)
    u = K * x + M
    x_next = system["a"] * x + system["c"] * u
    cost = system["q"] * x**2 + system["r"] * u**2
    res = lstd_v(scalar_features(x), cost, scalar_features(x_next), system["gamma"])
    np.testing.assert_allclose(res.v, [cf["P"], cf["p"], cf["C"]], rtol=1e-9)
    assert res.n_samples == 24 * 30


def test_lstd_v_statistical_recovery_on_trajectories():
    """Many 24-hour on-policy trajectories with process noise, laid out (hours, days) like
    the experiment: P, p and C within a tight statistical tolerance. Over 20 seeds at this
    size the estimates spread by 0.25 % (P), 0.0045 (p, absolute) and 0.3 % (C); the
    tolerances are about six of those spreads."""
    cf = closed_form(**SYS)
    rng = np.random.default_rng(2)
    hours, days = 24, 10_000
    A, B = SYS["a"] + SYS["c"] * K, SYS["c"] * M
    x = np.empty((hours + 1, days))
    x[0] = rng.uniform(-2, 2, days)  # a broad start excites the quadratic feature
    for t in range(hours):
        x[t + 1] = A * x[t] + B + rng.normal(0.0, np.sqrt(SYS["s2"]), days)
    u = K * x[:-1] + M
    cost = SYS["q"] * x[:-1] ** 2 + SYS["r"] * u**2
    res = lstd_v(scalar_features(x[:-1]), cost, scalar_features(x[1:]), SYS["gamma"])
    assert res.n_samples == hours * days
    np.testing.assert_allclose(res.v[0], cf["P"], rtol=0.015)
    np.testing.assert_allclose(res.v[1], cf["p"], rtol=0, atol=0.03)
    np.testing.assert_allclose(res.v[2], cf["C"], rtol=0.02)


def test_lstd_v_batch_dims_are_flattened():
    rng = np.random.default_rng(3)
    phi, phi_next = rng.normal(size=(2, 6, 5, 3))
    cost = rng.normal(size=(6, 5))
    done = rng.random((6, 5)) < 0.2
    a = lstd_v(phi, cost, phi_next, 0.95, done=done)
    b = lstd_v(phi.reshape(30, 3), cost.reshape(30), phi_next.reshape(30, 3), 0.95, done.ravel())
    np.testing.assert_allclose(a.v, b.v, rtol=1e-12)


# -- done handling ---------------------------------------------------------------------------
def test_all_done_is_plain_regression_of_the_cost():
    rng = np.random.default_rng(4)
    x = rng.uniform(-1, 1, 50)
    phi = scalar_features(x)
    cost = 3 * x**2 - x + 0.5 + 0.1 * rng.normal(size=50)
    res = lstd_v(phi, cost, scalar_features(rng.normal(size=50)), 0.9, done=np.ones(50, bool))
    np.testing.assert_allclose(res.v, np.linalg.lstsq(phi, cost, rcond=None)[0], rtol=1e-10)


def test_done_equals_zeroed_successor_and_none_equals_never_done():
    rng = np.random.default_rng(5)
    phi, phi_next = rng.normal(size=(2, 40, 3))
    cost = rng.normal(size=40)
    done = rng.random(40) < 0.3
    with_done = lstd_v(phi, cost, phi_next, 0.8, done=done)
    zeroed = lstd_v(phi, cost, np.where(done[:, None], 0.0, phi_next), 0.8)
    np.testing.assert_allclose(with_done.v, zeroed.v, rtol=1e-12)
    never = lstd_v(phi, cost, phi_next, 0.8, done=np.zeros(40, bool))
    np.testing.assert_allclose(lstd_v(phi, cost, phi_next, 0.8).v, never.v, rtol=1e-12)


def test_episodic_termination_acts_as_extra_discount():
    """Each state sampled twice, once ending the episode and once continuing: the LSTD
    fixed point is exactly the value with discount gamma / 2 (continuation probability 1/2)."""
    system = dict(SYS, s2=0.0)
    gamma = 0.9
    x = np.linspace(-2, 2, 21)
    u = K * x + M
    cost = system["q"] * x**2 + system["r"] * u**2
    x_next = system["a"] * x + system["c"] * u
    twice = lambda v: np.concatenate([v, v])
    done = np.concatenate([np.ones(21, bool), np.zeros(21, bool)])
    episodic = lstd_v(
        scalar_features(twice(x)), twice(cost), scalar_features(twice(x_next)), gamma, done=done
    )
    cf = closed_form(**dict(system, gamma=gamma / 2))
    np.testing.assert_allclose(episodic.v, [cf["P"], cf["p"], cf["C"]], rtol=1e-9)
    continuing = lstd_v(
        scalar_features(twice(x)), twice(cost), scalar_features(twice(x_next)), gamma
    )
    cf = closed_form(**dict(system, gamma=gamma))
    np.testing.assert_allclose(continuing.v, [cf["P"], cf["p"], cf["C"]], rtol=1e-9)


# -- lstd_q and the advantage gradient -------------------------------------------------------
def _q_samples(rng, size, sigma, exact):
    """Transitions of the scalar system under u = K x + M + e.

    ``exact``: e = +-sigma paired at each x and E[Phi(x+)] as successor (no sampling
    noise left); otherwise e ~ N(0, sigma^2) and x+ sampled."""
    if exact:
        x = np.repeat(np.linspace(-2, 2, size // 2), 2)
        e = np.tile([sigma, -sigma], size // 2)
    else:
        x = rng.uniform(-2, 2, size)
        e = rng.normal(0.0, sigma, size)
    pi = K * x + M
    u = pi + e
    grad_pi = np.stack([x, np.ones_like(x), np.zeros_like(x)], axis=-1)[..., None]  # (S, 3, 1)
    psi = compatible_features(grad_pi, u[:, None], pi[:, None])
    cost = SYS["q"] * x**2 + SYS["r"] * u**2
    if exact:
        phi_next = expected_next_features(x, u, SYS["a"], SYS["c"], SYS["s2"])
    else:
        x_next = SYS["a"] * x + SYS["c"] * u + rng.normal(0.0, np.sqrt(SYS["s2"]), size)
        phi_next = scalar_features(x_next)
    return scalar_features(x), psi, cost, phi_next, grad_pi, x


def test_lstd_q_exact_advantage_gradient():
    """w equals (g1, g0), the exact dQ/du at u = pi; the psi column of a parameter with zero
    sensitivity gets weight 0 and does not break the solve; v is V plus h sigma^2/(1-gamma)."""
    cf = closed_form(**SYS)
    sigma = 0.1
    phi, psi, cost, phi_next, grad_pi, x = _q_samples(None, 400, sigma, exact=True)
    for ridge in (0.0, 1e-12):
        res = lstd_q(phi, psi, cost, phi_next, SYS["gamma"], ridge=ridge)
        np.testing.assert_allclose(res.w[:2], [cf["g1"], cf["g0"]], rtol=1e-8)
        assert res.w[2] == 0.0
        assert res.dropped_w.tolist() == [False, False, True]
        shift = cf["h"] * sigma**2 / (1 - SYS["gamma"])
        np.testing.assert_allclose(res.v, [cf["P"], cf["p"], cf["C"] + shift], rtol=1e-8)
        assert not res.rank_deficient
    # the critic's action gradient at pi is the true dQ/du(x, pi(x)) = g1 x + g0
    np.testing.assert_allclose(
        res.advantage_gradient(grad_pi)[:, 0], cf["g1"] * x + cf["g0"], rtol=1e-7, atol=1e-9
    )


def _hourly_q_samples(size: int, sigma: float, q=(1.0, 3.0, 0.5)):
    """A 3-hour episode of the scalar system with the state cost ``q_k x^2`` changing by the
    hour and one affine policy per hour (theta = (k_0, m_0, k_1, m_1, k_2, m_2)). Returns the
    samples with the exact expected successor features for ``kind`` features and the true
    dQ/du = g1_k x + g0_k at u = pi."""
    a, c, r, s2, gamma = SYS["a"], SYS["c"], SYS["r"], SYS["s2"], SYS["gamma"]
    H = len(q)
    gains = [(-0.6, 0.3), (-0.2, -0.1), (-0.9, 0.5)]
    P, p = np.zeros(H + 1), np.zeros(H + 1)  # V_k(x) = P_k x^2 + p_k x + C_k, V_H = 0
    g1, g0 = np.zeros(H), np.zeros(H)
    for k in range(H - 1, -1, -1):
        kk, mm = gains[k]
        A, B = a + c * kk, c * mm
        P[k] = q[k] + r * kk**2 + gamma * P[k + 1] * A**2
        p[k] = 2 * r * kk * mm + gamma * (2 * P[k + 1] * A * B + p[k + 1] * A)
        g1[k] = 2 * r * kk + 2 * gamma * P[k + 1] * c * (a + c * kk)
        g0[k] = 2 * r * mm + gamma * (2 * P[k + 1] * c * c * mm + p[k + 1] * c)
    rng = np.random.default_rng(11)
    x = rng.uniform(-1.0, 1.0, size)
    hour = np.arange(size) % H
    e = sigma * np.where(np.arange(size) // H % 2 == 0, 1.0, -1.0)  # exactly symmetric
    kk, mm = np.array(gains)[hour].T
    u = kk * x + mm + e
    grad_pi = np.zeros((size, 2 * H, 1))
    grad_pi[np.arange(size), 2 * hour, 0] = x
    grad_pi[np.arange(size), 2 * hour + 1, 0] = 1.0
    psi = compatible_features(grad_pi, u[:, None], (kk * x + mm)[:, None])
    mean = a * x + c * u
    second = mean**2 + s2  # E[x+^2]
    done = hour == H - 1
    cost = np.asarray(q)[hour] * x**2 + r * u**2

    def features(kind):
        """Phi(x) and the exact E[Phi(x+)] (zero where the episode ends). Every feature is
        f2 x^2 + f1 x + f0 at a given hour, read off its values at x = -1, 0, 1."""
        phi = state_features(x[:, None], hour, kind, hours_per_day=H)
        nxt = np.minimum(hour + 1, H - 1)
        at = {v: state_features(np.full((size, 1), v), nxt, kind, H) for v in (-1.0, 0.0, 1.0)}
        f0 = at[0.0]
        f1 = (at[1.0] - at[-1.0]) / 2
        f2 = (at[1.0] + at[-1.0]) / 2 - f0
        phi_next = f2 * second[:, None] + f1 * mean[:, None] + f0
        return phi, np.where(done[:, None], 0.0, phi_next)

    truth = np.stack([g1, g0], axis=1).reshape(-1)
    return psi, cost, done, features, truth


def test_hourly_value_slopes_are_needed_for_the_exact_action_gradient():
    """When the value of the state changes with the hour, the compatible critic recovers
    the exact dQ/du only if its baseline can have a different soc slope at every hour
    ('hour*paper'); with one slope for the day ('paper+hour') the action gradient, and so
    the policy gradient, is biased."""
    psi, cost, done, features, truth = _hourly_q_samples(3000, 0.1)
    gamma = SYS["gamma"]
    phi, phi_next = features("hour*paper")
    exact = lstd_q(phi, psi, cost, phi_next, gamma, done=done)
    np.testing.assert_allclose(exact.w, truth, rtol=1e-7, atol=1e-9)
    phi, phi_next = features("paper+hour")
    shared = lstd_q(phi, psi, cost, phi_next, gamma, done=done)
    assert np.abs(shared.w - truth).max() > 0.05 * np.abs(truth).max()


def test_lstd_q_statistical_advantage_gradient():
    """Sampled exploration and process noise. Over 20 seeds at this size w spreads by about
    0.8 % (g1), 0.5 % (g0) and 0.06 % (P); the tolerances are five to eight of those
    spreads."""
    cf = closed_form(**SYS)
    phi, psi, cost, phi_next, _, _ = _q_samples(np.random.default_rng(6), 400_000, 0.3, False)
    res = lstd_q(phi, psi, cost, phi_next, SYS["gamma"], ridge=1e-9)
    np.testing.assert_allclose(res.w[0], cf["g1"], rtol=0.05)
    np.testing.assert_allclose(res.w[1], cf["g0"], rtol=0.025)
    np.testing.assert_allclose(res.v[0], cf["P"], rtol=0.005)
    assert res.n_samples == 400_000 and res.w.shape == (3,) and res.v.shape == (3,)


def test_lstd_q_shapes_and_batch_dims():
    rng = np.random.default_rng(7)
    hours, days, n_theta, m = 24, 30, 30, 7
    phi, phi_next = rng.normal(size=(2, hours, days, m))
    psi = rng.normal(size=(hours, days, n_theta))
    cost = rng.normal(size=(hours, days))
    res = lstd_q(phi, psi, cost, phi_next, 0.99, ridge=1e-6)
    assert isinstance(res, LSTDResult)
    assert res.w.shape == (n_theta,) and res.v.shape == (m,) and res.n_samples == hours * days
    flat = lstd_q(phi.reshape(-1, m), psi.reshape(-1, n_theta), cost.ravel(),
                  phi_next.reshape(-1, m), 0.99, ridge=1e-6)
    np.testing.assert_allclose(res.w, flat.w, rtol=1e-12)
    q = res.q_value(psi, phi)
    assert q.shape == (hours, days)


def test_zero_psi_columns_do_not_fail():
    """phi3/T3-like parameters: all-zero psi columns, with and without ridge."""
    rng = np.random.default_rng(8)
    phi, phi_next = rng.normal(size=(2, 100, 4))
    psi = rng.normal(size=(100, 5))
    psi[:, [1, 3]] = 0.0
    cost = rng.normal(size=100)
    reduced = lstd_q(phi, psi[:, [0, 2, 4]], cost, phi_next, 0.9)
    for ridge in (0.0, 1e-6):
        res = lstd_q(phi, psi, cost, phi_next, 0.9, ridge=ridge)
        assert np.all(np.isfinite(res.w)) and res.w[1] == 0.0 and res.w[3] == 0.0
        assert res.dropped_w.tolist() == [False, True, False, True, False]
        assert not res.rank_deficient and np.isfinite(res.condition)
    np.testing.assert_allclose(res.w[[0, 2, 4]], reduced.w, rtol=1e-4)
    # every psi column zero (e.g. a policy saturated at every sample): w = 0, v still fitted
    res = lstd_q(phi, np.zeros((100, 5)), cost, phi_next, 0.9)
    np.testing.assert_array_equal(res.w, 0.0)
    np.testing.assert_allclose(res.v, lstd_v(phi, cost, phi_next, 0.9).v, rtol=1e-12)


def test_rank_deficient_system_gives_min_norm_solution():
    rng = np.random.default_rng(9)
    phi, phi_next = rng.normal(size=(2, 60, 3))
    psi = rng.normal(size=(60, 1))
    psi = np.concatenate([psi, 2 * psi], axis=1)  # duplicated direction
    cost = rng.normal(size=60)
    res = lstd_q(phi, psi, cost, phi_next, 0.9)
    assert res.rank_deficient and np.all(np.isfinite(res.w))
    single = lstd_q(phi, psi[:, :1], cost, phi_next, 0.9)
    # the same Q-function, split between the two copies
    np.testing.assert_allclose(res.w[0] + 2 * res.w[1], single.w[0], rtol=1e-6)


def test_ridge_effect_and_scale_invariance():
    phi, psi, cost, phi_next, _, _ = _q_samples(np.random.default_rng(10), 2000, 0.1, False)
    plain = lstd_q(phi, psi, cost, phi_next, 0.9)
    tiny = lstd_q(phi, psi, cost, phi_next, 0.9, ridge=1e-12)
    np.testing.assert_allclose(tiny.w, plain.w, rtol=1e-6)
    some = lstd_q(phi, psi, cost, phi_next, 0.9, ridge=1e-2)
    huge = lstd_q(phi, psi, cost, phi_next, 0.9, ridge=1e6)
    assert np.max(np.abs(some.w - plain.w)) > 1e-6
    assert np.linalg.norm(huge.w) < 1e-4 * np.linalg.norm(plain.w)
    assert np.linalg.norm(huge.v) < 1e-4 * np.linalg.norm(plain.v)
    # the ridge is relative: changing a feature's unit rescales its weight, not the fit
    units = np.array([1e6, 1e-3, 1.0])
    rescaled = lstd_q(phi, psi * units, cost, phi_next, 0.9, ridge=1e-2)
    np.testing.assert_allclose(rescaled.w * units, some.w, rtol=1e-8)
    np.testing.assert_allclose(rescaled.v, some.v, rtol=1e-8)


# -- errors ----------------------------------------------------------------------------------
def test_errors_name_the_bad_input():
    phi = np.ones((10, 3))
    psi = np.ones((10, 2))
    cost = np.ones(10)
    with pytest.raises(ValueError, match=r"phi_next has shape \(10, 2\)"):
        lstd_q(phi, psi, cost, np.ones((10, 2)), 0.9)
    with pytest.raises(ValueError, match=r"psi has shape \(9, 2\)"):
        lstd_q(phi, psi[:9], cost, phi, 0.9)
    with pytest.raises(ValueError, match=r"cost has shape \(10, 1\)"):
        lstd_v(phi, cost[:, None], phi, 0.9)
    with pytest.raises(ValueError, match="done has dtype"):
        lstd_v(phi, cost, phi, 0.9, done=np.zeros(10))
    with pytest.raises(ValueError, match=r"done has shape \(3,\)"):
        lstd_v(phi, cost, phi, 0.9, done=np.zeros(3, bool))
    with pytest.raises(ValueError, match="gamma=1.5"):
        lstd_v(phi, cost, phi, 1.5)
    with pytest.raises(ValueError, match="ridge=-1"):
        lstd_v(phi, cost, phi, 0.9, ridge=-1)
    with pytest.raises(ValueError, match="non-finite"):
        lstd_v(phi, np.full(10, np.nan), phi, 0.9)


# -- Monte Carlo returns ---------------------------------------------------------------------
def test_monte_carlo_returns():
    rng = np.random.default_rng(11)
    costs = rng.normal(size=(24, 5))
    gamma = 0.9
    returns = monte_carlo_returns(costs, gamma)
    assert returns.shape == (24, 5)
    for k in (0, 7, 23):
        expected = sum(gamma ** (j - k) * costs[j] for j in range(k, 24))
        np.testing.assert_allclose(returns[k], expected, rtol=1e-12)
    # constant cost: geometric sum
    const = monte_carlo_returns(np.ones((10, 1)), 0.5)
    np.testing.assert_allclose(const[:, 0], [(1 - 0.5 ** (10 - k)) / 0.5 for k in range(10)])
    with pytest.raises(ValueError, match="gamma=0"):
        monte_carlo_returns(costs, 0.0)


def test_prices_left_and_the_price_features():
    """The highest and the mean buy price of the hours left, by hand; the price features are
    the per-hour quadratics followed by soc times each of them, zero at the end of the day."""
    buy = np.array([[30.0, 10.0], [50.0, 40.0], [20.0, 70.0]])  # 3 hours, 2 days
    left = prices_left(buy)
    assert left.shape == (4, 2, 2)
    np.testing.assert_array_equal(left[:3, 0, 0], [50.0, 50.0, 20.0])
    np.testing.assert_array_equal(left[:3, 1, 0], [70.0, 70.0, 70.0])
    np.testing.assert_allclose(left[:3, 0, 1], [100.0 / 3, 35.0, 20.0])
    np.testing.assert_allclose(left[:3, 1, 1], [40.0, 55.0, 70.0])
    assert np.all(left[3] == 0)
    soc = np.random.default_rng(3).uniform(size=(4, 2, 3))
    features = value_baseline_features(soc, "hour*paper+price", buy)
    per_hour = value_baseline_features(soc, "hour*paper")
    assert features.shape == (4, 2, per_hour.shape[-1] + 6)
    np.testing.assert_array_equal(features[..., : per_hour.shape[-1]], per_hour)
    np.testing.assert_allclose(features[..., -6:-3], soc * left[..., :1])
    np.testing.assert_allclose(features[..., -3:], soc * left[..., 1:])
    assert np.all(features[3] == 0)
    with pytest.raises(ValueError, match=r"buy has shape \(3,\)"):
        prices_left(buy[:, 0])
