r"""The critic: least-squares temporal-difference (LSTD) fits of value functions.

The policy gradient of the paper (Section III) needs the gradient of the advantage
function at the policy's own action. It is estimated with the *compatible* action-value
function

.. math::

    Q_{w,v}(s, a) = \psi(s, a)^\top w + \Phi(s)^\top v, \qquad
    \psi(s, a) = \nabla_\theta \pi_\theta(s)\,\big(a - \pi_\theta(s)\big),

whose state part :math:`V^v(s) = \Phi(s)^\top v` is a baseline. With
:math:`\nabla_a Q_{w,v}(s, a) = \nabla_\theta\pi_\theta(s)^\top w` the gradient of the
closed-loop cost becomes :math:`\nabla_\theta J = \mathbb E[\nabla_\theta\pi_\theta
\nabla_\theta\pi_\theta^\top]\, w` (see :mod:`mpcrl_lite.learning.dpg`).

The weights are fitted from a batch of transitions :math:`(s, a, \tilde L, s^+)` by
LSTD: with features :math:`z` of the sample and :math:`z^+` of the successor, solve

.. math::

    \Big(\tfrac1S \sum z\,(z - \gamma (1 - d)\, z^+)^\top + \rho\, M\Big)\,x
    = \tfrac1S \sum z\,\tilde L,

where :math:`S` is the number of samples, :math:`d` the per-sample ``done`` flag,
:math:`\rho` the relative ridge and :math:`M = \mathrm{diag}(\tfrac1S \sum z_j^2)` (see
"Ridge" below). This is the fixed point of the projected Bellman equation for the policy
being evaluated: the successor's action is the policy's own, so its :math:`\psi` is zero and
:math:`z^+ = [0;\ \Phi(s^+)]`.

Numerics
--------
* **Scaling.** Each feature is divided by its root-mean-square over the samples before the
  solve, so features of very different magnitudes (policy sensitivities and soc monomials)
  are treated alike; the weights are scaled back afterwards.
* **Ridge.** ``ridge`` is dimensionless: it adds ``ridge`` times the identity to the scaled
  (unit-diagonal) Gram matrix, i.e. :math:`\rho\, M` with :math:`M_{jj}` the mean square of
  feature :math:`j`. The fitted *function* therefore does not depend on the units of any
  feature, and ``ridge`` reads as "relative to the matrix scale".
* **Features that are zero.** A feature whose mean square is at most ``zero_tol`` times the
  largest one of its block (:math:`\psi` or :math:`\Phi`) carries no information -- e.g. the
  columns of ``phi3`` and ``T3``, whose policy sensitivity is identically zero. It is left
  out of the solve and its weight is set to zero (reported in ``dropped_w`` / ``dropped_v``);
  its presence never makes the solve fail.
* **Solve.** :func:`numpy.linalg.lstsq` on the scaled system: a unique solution when the
  system is regular, the minimum-norm least-squares solution (in scaled coordinates) when it
  is singular. ``condition`` and ``rank_deficient`` say which case occurred.

Value features
--------------
The state features :math:`\Phi` of the baseline :math:`V^v(s) = \Phi(s)^\top v` live here,
one set per name of :data:`mpcrl_lite.config.VALUE_FEATURES` (:data:`mpcrl_lite.config.VALUE_FEATURE_SETS`): the
paper's :math:`[soc_i^2, soc_i, 1]` (:func:`value_features`), the same with the constant
replaced by one indicator per hour of the day, the hour indicators alone, and the paper's
features once per hour (``'hour*paper'``, a quadratic in soc for each hour of the day)
(:func:`state_features` for states with given hours, :func:`value_baseline_features` for the
``(H + 1, D, n)`` states of a recorded period).

Why the hour matters for the *gradient*, not only for the baseline's variance: at the LSTD
fixed point the critic's action gradient :math:`\nabla_\theta\pi^\top w` is the least squares
fit of :math:`\nabla_a \tilde L + \gamma\,\alpha\,\partial V^v / \partial\,\mathrm{soc}(s^+)`
(the successor is bootstrapped with the fitted :math:`V^v`). With ``'paper'`` or
``'paper+hour'`` the slope :math:`\partial V^v / \partial\,\mathrm{soc}` is the same at every
hour, while the value of a unit of charge changes through the day (high before the evening
peak, nothing at the end of the day, which restarts at ``soc0``); the policy gradient
inherits that error. ``'hour*paper'`` gives every hour its own slope and curvature.

The same argument holds across the days of a month: the value of a unit of charge at hour
:math:`k` depends on the prices still to come that day, and so does the policy's sensitivity
:math:`\nabla_\theta\pi`. With a slope that is the same on every day, the critic's gradient
is :math:`\mathbb E[\nabla_\theta\pi\,(\nabla_a\tilde L + \gamma\alpha\,\overline{\partial V})]`
instead of :math:`\mathbb E[\nabla_\theta\pi\,(\nabla_a\tilde L + \gamma\alpha\,\partial V_d)]`:
it misses :math:`\gamma\alpha\,\mathrm{Cov}(\nabla_\theta\pi, \partial V_d)` over the days
(an omitted variable; the exploration, independent of the day, does not remove it).
``'hour*paper+price'`` (the default) adds :math:`soc_i \bar p_k` and :math:`soc_i \hat p_k`, the
soc times the highest and the mean buy price of the hours left in the day
(:func:`prices_left`), so that the slope follows the day's prices.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .._util.validate import check_real
from ..config import VALUE_FEATURES

#: The value feature sets that read the day's prices (:func:`prices_left`).
PRICE_FEATURES = ("hour*paper+price",)

__all__ = [
    "LSTDResult",
    "compatible_features",
    "lstd_q",
    "lstd_v",
    "monte_carlo_returns",
    "prices_left",
    "state_features",
    "value_baseline_features",
    "value_features",
]

# -- features ------------------------------------------------------------------------------
def value_features(soc: np.ndarray) -> np.ndarray:
    r"""The paper's state features :math:`\Phi(s) = [soc_1^2, \dots, soc_n^2, soc_1, \dots,
    soc_n, 1]` (paper eq. 22).

    Parameters
    ----------
    soc : array, shape ``(..., n)``
        States of charge; any leading batch dimensions, e.g. ``(hours, days, n)``.

    Returns
    -------
    Phi : array, shape ``(..., 2 n + 1)``
        Squares, then the values, then a constant one (no cross terms, as in the paper).
    """
    soc = np.asarray(soc, dtype=float)
    if soc.ndim < 1 or soc.shape[-1] == 0:
        raise ValueError(f"soc has shape {soc.shape}; expected (..., n) with n >= 1")
    ones = np.ones(soc.shape[:-1] + (1,))
    return np.concatenate([soc**2, soc, ones], axis=-1)


def state_features(
    soc: np.ndarray, hour: np.ndarray, kind: str = "paper", hours_per_day: int = 24,
    prices_left: np.ndarray | None = None,
) -> np.ndarray:
    r"""Features :math:`\Phi(s)` of a set of :data:`mpcrl_lite.config.VALUE_FEATURE_SETS` for states at known hours.

    Parameters
    ----------
    soc : array, shape ``(..., n)``
    hour : int array, broadcastable to ``soc.shape[:-1]``
        Hour of the day of each state; an hour outside ``[0, hours_per_day)`` (e.g. the end
        of the day, which is never bootstrapped from) has no indicator set.
    kind : str
        ``'paper'``: :func:`value_features`; ``'paper+hour'``: :math:`[soc_i^2, soc_i, e_k]`,
        the paper's constant replaced by the indicator :math:`e_k` of the hour;
        ``'hour'``: :math:`e_k` alone (a table over the hours); ``'hour*paper'``:
        :math:`e_k \otimes [soc_i^2, soc_i, 1]`, the paper's features once per hour (all
        zero at an hour outside the range); ``'hour*paper+price'``: those and
        :math:`soc_i \bar p_k, soc_i \hat p_k`, the soc times the highest and the mean buy
        price of the hours left in the state's day (``prices_left``).
    hours_per_day : int, default 24
        Number of hour indicators.
    prices_left : array, shape broadcastable to ``soc.shape[:-1] + (2,)``, optional
        For ``'hour*paper+price'`` (required there): the highest and the mean buy price over
        the hours ``k .. H - 1`` of each state's day (:func:`prices_left`; zero at the end of
        the day).

    Returns
    -------
    array, shape ``(..., 2 n + 1)``, ``(..., 2 n + hours_per_day)``,
    ``(..., hours_per_day)``, ``(..., hours_per_day (2 n + 1))`` (hour-major) or
    ``(..., hours_per_day (2 n + 1) + 2 n)`` (the price terms last: the highest price's
    ``n``, then the mean's)
    """
    if kind not in VALUE_FEATURES:
        raise ValueError(f"kind={kind!r}: expected one of {list(VALUE_FEATURES)}")
    paper = value_features(soc)
    if kind == "paper":
        return paper
    batch = paper.shape[:-1]
    hour = np.asarray(hour)
    try:
        hour = np.broadcast_to(hour, batch)
    except ValueError:
        raise ValueError(
            f"hour has shape {hour.shape}: expected a shape broadcastable to {batch}"
        ) from None
    onehot = (hour[..., None] == np.arange(hours_per_day)).astype(float)
    if kind == "hour":
        return onehot
    if kind in ("hour*paper", "hour*paper+price"):
        product = onehot[..., :, None] * paper[..., None, :]
        per_hour = product.reshape(batch + (hours_per_day * paper.shape[-1],))
        if kind == "hour*paper":
            return per_hour
        if prices_left is None:
            raise ValueError(f"kind={kind!r} needs prices_left (the highest and the mean buy "
                             "price of the hours left in each state's day)")
        left = np.asarray(prices_left, dtype=float)
        try:
            left = np.broadcast_to(left, batch + (2,))
        except ValueError:
            raise ValueError(f"prices_left has shape {left.shape}: expected a shape "
                             f"broadcastable to {batch + (2,)}") from None
        soc = np.asarray(soc, dtype=float)
        return np.concatenate([per_hour, soc * left[..., :1], soc * left[..., 1:]], axis=-1)
    return np.concatenate([paper[..., :-1], onehot], axis=-1)


def prices_left(buy: np.ndarray) -> np.ndarray:
    r"""The highest and the mean buy price over the hours left in the day, at every hour.

    Parameters
    ----------
    buy : array, shape ``(H, D)``
        Buy price of every hour and day of a recorded period.

    Returns
    -------
    array, shape ``(H + 1, D, 2)``
        Row ``k``: :math:`\max_{j \ge k}` and :math:`\frac{1}{H - k}\sum_{j \ge k}` of
        ``buy[j]``; row ``H`` (the end of the day, never bootstrapped from) is zero.
    """
    buy = np.asarray(buy, dtype=float)
    if buy.ndim != 2 or buy.shape[0] == 0:
        raise ValueError(f"buy has shape {buy.shape}; expected (H, D) with H >= 1")
    H, D = buy.shape
    backwards = buy[::-1]
    highest = np.maximum.accumulate(backwards, axis=0)[::-1]
    mean = (np.cumsum(backwards, axis=0) / np.arange(1, H + 1)[:, None])[::-1]
    out = np.zeros((H + 1, D, 2))
    out[:H, :, 0], out[:H, :, 1] = highest, mean
    return out


def value_baseline_features(soc: np.ndarray, kind: str = "paper+hour",
                            buy: np.ndarray | None = None) -> np.ndarray:
    r"""Features :math:`\Phi` of the critic's value baseline :math:`V_v = \Phi^\top v` (paper
    eq. 16) for every state of a period.

    Parameters
    ----------
    soc : array, shape ``(H + 1, D, n)``
        States of charge of a recorded period, row ``k`` at hour ``k`` of the day (row ``H``
        the end of the day, which has no hour indicator: the day is an episode).
    kind : str
        A name of :data:`mpcrl_lite.config.VALUE_FEATURE_SETS` (``LearningConfig.value_features``); see
        :func:`state_features`.
    buy : array, shape ``(H, D)``, optional
        The period's buy prices; needed by ``'hour*paper+price'`` (:func:`prices_left`).

    Returns
    -------
    array, shape ``(H + 1, D, m)``
    """
    soc = np.asarray(soc, dtype=float)
    if soc.ndim != 3:
        raise ValueError(f"soc has shape {soc.shape}; expected (H + 1, D, n)")
    hours = soc.shape[0] - 1
    left = None
    if kind in PRICE_FEATURES:
        if buy is None:
            raise ValueError(f"kind={kind!r} needs buy, the period's buy prices (H, D)")
        if np.shape(buy) != (hours, soc.shape[1]):
            raise ValueError(f"buy has shape {np.shape(buy)}: expected (H, D) = "
                             f"{(hours, soc.shape[1])}")
        left = prices_left(buy)
    return state_features(soc, np.arange(hours + 1)[:, None], kind, hours_per_day=hours,
                          prices_left=left)


def compatible_features(grad_pi: np.ndarray, a: np.ndarray, pi: np.ndarray) -> np.ndarray:
    r"""Compatible features :math:`\psi = \nabla_\theta \pi_\theta(s)\,(a - \pi_\theta(s))`
    of the critic :math:`Q_w = \psi^\top w + V_v` (paper eq. 15).

    Parameters
    ----------
    grad_pi : array, shape ``(..., n_theta, n)``
        Policy sensitivity :math:`\nabla_\theta\pi_\theta(s)` (row ``j`` is the derivative of
        the action with respect to :math:`\theta_j`).
    a : array, shape ``(..., n)``
        Action applied (policy plus exploration, after any projection).
    pi : array, shape ``(..., n)``
        The policy's action :math:`\pi_\theta(s)`.

    Returns
    -------
    psi : array, shape ``(..., n_theta)``
    """
    grad_pi = np.asarray(grad_pi, dtype=float)
    a = np.asarray(a, dtype=float)
    pi = np.asarray(pi, dtype=float)
    if grad_pi.ndim < 2:
        raise ValueError(f"grad_pi has shape {grad_pi.shape}; expected (..., n_theta, n)")
    expected = grad_pi.shape[:-2] + grad_pi.shape[-1:]
    for name, value in (("a", a), ("pi", pi)):
        if value.shape != expected:
            raise ValueError(
                f"{name} has shape {value.shape}; expected {expected} to match grad_pi "
                f"{grad_pi.shape} = (..., n_theta, n)"
            )
    return np.einsum("...ti,...i->...t", grad_pi, a - pi)


# -- result --------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class LSTDResult:
    r"""Weights of an LSTD fit and diagnostics of its linear solve.

    Attributes
    ----------
    w : array, shape ``(n_theta,)``
        Weights of the compatible features :math:`\psi` (shape ``(0,)`` for :func:`lstd_v`).
    v : array, shape ``(m,)``
        Weights of the state features, :math:`V^v(s) = \Phi(s)^\top v`.
    condition : float
        2-norm condition number of the scaled, regularised matrix actually solved
        (``inf`` if it is singular).
    rank_deficient : bool
        True if that matrix is numerically singular; the weights are then the
        minimum-norm least-squares solution (in scaled coordinates).
    n_samples : int
        Number of transitions used (all batch dimensions flattened).
    dropped_w, dropped_v : bool arrays, shapes ``(n_theta,)`` and ``(m,)``
        Features left out because they are (numerically) zero at every sample; their
        weights are exactly zero.
    td_rms : float
        Root-mean-square temporal-difference error
        :math:`\tilde L + \gamma(1-d) Q(s^+, \pi(s^+)) - Q(s, a)` at the fitted weights.
    """

    w: np.ndarray
    v: np.ndarray
    condition: float
    rank_deficient: bool
    n_samples: int
    dropped_w: np.ndarray
    dropped_v: np.ndarray
    td_rms: float

    def value(self, phi: np.ndarray) -> np.ndarray:
        r""":math:`V^v(s) = \Phi(s)^\top v`; ``phi`` shape ``(..., m)`` -> ``(...)``."""
        return np.asarray(phi, dtype=float) @ self.v

    def q_value(self, psi: np.ndarray, phi: np.ndarray) -> np.ndarray:
        r""":math:`Q_{w,v} = \psi^\top w + \Phi^\top v`; shapes ``(..., n_theta)``,
        ``(..., m)`` -> ``(...)``."""
        return np.asarray(psi, dtype=float) @ self.w + self.value(phi)

    def advantage_gradient(self, grad_pi: np.ndarray) -> np.ndarray:
        r""":math:`\nabla_a Q_{w,v}(s, a) = \nabla_\theta\pi_\theta(s)^\top w`; ``grad_pi``
        shape ``(..., n_theta, n)`` -> ``(..., n)``."""
        return np.einsum("...ti,t->...i", np.asarray(grad_pi, dtype=float), self.w)


# -- estimators ----------------------------------------------------------------------------
def lstd_q(
    phi: np.ndarray,
    psi: np.ndarray,
    cost: np.ndarray,
    phi_next: np.ndarray,
    gamma: float,
    done: np.ndarray | None = None,
    ridge: float = 0.0,
    zero_tol: float = 1e-24,
) -> LSTDResult:
    r"""LSTD fit of the compatible action-value function
    :math:`Q_{w,v}(s, a) = \psi^\top w + \Phi(s)^\top v`: the least-squares problem of paper
    eq. 17, solved through the Bellman equations of eqs. 14a-14b (paper eq. 14: ``Q = L~ +
    gamma E[V(s+)]``)

    Features :math:`z = [\psi;\ \Phi(s)]`, successor features
    :math:`z^+ = [0;\ \Phi(s^+)]` (at :math:`s^+` the policy's own action is taken, so its
    :math:`\psi` vanishes); the weights solve

    .. math::

        \Big(\tfrac1S\sum z\,(z - \gamma(1-d) z^+)^\top + \rho M\Big)
        \begin{bmatrix} w \\ v \end{bmatrix} = \tfrac1S \sum z\,\tilde L .

    See the module docstring for the scaling, the relative ridge :math:`\rho M`, zero
    features and the least-squares solve.

    Parameters
    ----------
    phi : array, shape ``(..., m)``
        State features :math:`\Phi(s)` of each sample (see :func:`value_features`).
    psi : array, shape ``(..., n_theta)``
        Compatible features (see :func:`compatible_features`).
    cost : array, shape ``(...)``
        Stage cost :math:`\tilde L(s, a)` of each sample.
    phi_next : array, shape ``(..., m)``
        State features of the successor :math:`\Phi(s^+)`.
    gamma : float
        Discount factor in ``(0, 1]``.
    done : bool array, shape ``(...)``, optional
        True where the successor is terminal (no bootstrap: :math:`V(s^+) = 0`). ``None``
        means a continuing task (never done).
    ridge : float, default 0
        Relative ridge :math:`\rho \ge 0` (dimensionless, see the module docstring).
    zero_tol : float, default 1e-24
        A feature whose mean square is ``<= zero_tol`` times the largest mean square of its
        block is treated as zero and dropped.

    Returns
    -------
    LSTDResult
        ``w`` shape ``(n_theta,)``, ``v`` shape ``(m,)`` and diagnostics.

    Notes
    -----
    The leading dimensions ``(...)`` (e.g. ``(hours, days)``) are flattened; every sample
    has the same weight. Under exploration :math:`a = \pi(s) + e` with :math:`e` zero-mean,
    symmetric and independent of :math:`s`, the fitted :math:`\nabla_\theta\pi^\top w` is the
    least-squares fit of :math:`\nabla_a Q_\pi(s, a)|_{a = \pi(s)}` (exact when the latter
    lies in the span of :math:`\nabla_\theta\pi`).
    """
    phi, phi_next, batch = _check_state_features(phi, phi_next)
    psi = np.asarray(psi, dtype=float)
    if psi.ndim < 1 or psi.shape[:-1] != batch:
        raise ValueError(
            f"psi has shape {psi.shape}; expected {batch + ('n_theta',)} to match phi "
            f"{phi.shape}"
        )
    cost, not_done = _check_cost_done(cost, done, batch)
    gamma = _check_gamma(gamma)
    ridge = _check_ridge(ridge)
    p = psi.shape[-1]
    m = phi.shape[-1]
    z = np.concatenate([psi.reshape(-1, p), phi.reshape(-1, m)], axis=1)
    z_next = np.concatenate([np.zeros((z.shape[0], p)), phi_next.reshape(-1, m)], axis=1)
    x, info = _solve(z, z_next, cost, not_done, gamma, ridge, (p, m), zero_tol)
    return LSTDResult(w=x[:p], v=x[p:], **info)


def lstd_v(
    phi: np.ndarray,
    cost: np.ndarray,
    phi_next: np.ndarray,
    gamma: float,
    done: np.ndarray | None = None,
    ridge: float = 0.0,
    zero_tol: float = 1e-24,
) -> LSTDResult:
    r"""LSTD(0) fit of a state-value function :math:`V^v(s) = \Phi(s)^\top v` from the
    Bellman equation of the policy's value (paper eq. 14b).

    Solves :math:`\big(\tfrac1S\sum \Phi(s)(\Phi(s) - \gamma(1-d)\Phi(s^+))^\top + \rho M\big)
    v = \tfrac1S\sum \Phi(s)\tilde L`: the value of the policy that generated the data
    (exploration included). Arguments, scaling and ridge are as in :func:`lstd_q`.

    Parameters
    ----------
    phi, phi_next : arrays, shape ``(..., m)``
        Features of the states and of their successors.
    cost : array, shape ``(...)``
    gamma : float in ``(0, 1]``
    done : bool array, shape ``(...)``, optional
    ridge : float, default 0
    zero_tol : float, default 1e-24

    Returns
    -------
    LSTDResult
        ``v`` shape ``(m,)``; ``w`` is empty, shape ``(0,)``.
    """
    phi, phi_next, batch = _check_state_features(phi, phi_next)
    cost, not_done = _check_cost_done(cost, done, batch)
    gamma = _check_gamma(gamma)
    ridge = _check_ridge(ridge)
    m = phi.shape[-1]
    x, info = _solve(
        phi.reshape(-1, m), phi_next.reshape(-1, m), cost, not_done, gamma, ridge, (0, m),
        zero_tol,
    )
    return LSTDResult(w=x[:0], v=x, **info)


def monte_carlo_returns(costs: np.ndarray, gamma: float) -> np.ndarray:
    r"""Discounted cost-to-go of each hour: :math:`G_k = \sum_{j \ge k} \gamma^{j-k} c_j`.

    The episode ends after the last row (:math:`G` beyond it is zero), as for one day of the
    experiment.

    Parameters
    ----------
    costs : array, shape ``(hours, ...)``
        Stage costs, time along axis 0, e.g. ``(hours, days)``.
    gamma : float
        Discount factor in ``(0, 1]``.

    Returns
    -------
    returns : array, same shape as ``costs``
    """
    costs = np.asarray(costs, dtype=float)
    if costs.ndim < 1 or costs.shape[0] == 0:
        raise ValueError(f"costs has shape {costs.shape}; expected (hours, ...) with hours >= 1")
    gamma = _check_gamma(gamma)
    returns = np.empty_like(costs)
    running = np.zeros(costs.shape[1:])
    for k in range(costs.shape[0] - 1, -1, -1):
        running = costs[k] + gamma * running
        returns[k] = running
    return returns


# -- internals -----------------------------------------------------------------------------
def _check_state_features(
    phi: np.ndarray, phi_next: np.ndarray
) -> tuple[np.ndarray, np.ndarray, tuple[int, ...]]:
    phi = np.asarray(phi, dtype=float)
    phi_next = np.asarray(phi_next, dtype=float)
    if phi.ndim < 1 or phi.shape[-1] == 0:
        raise ValueError(f"phi has shape {phi.shape}; expected (..., m) with m >= 1")
    if phi_next.shape != phi.shape:
        raise ValueError(f"phi_next has shape {phi_next.shape}; expected {phi.shape} like phi")
    batch = phi.shape[:-1]
    if int(np.prod(batch)) == 0:
        raise ValueError(f"phi has shape {phi.shape}: no samples")
    return phi, phi_next, batch


def _check_cost_done(
    cost: np.ndarray, done: np.ndarray | None, batch: tuple[int, ...]
) -> tuple[np.ndarray, np.ndarray]:
    cost = np.asarray(cost, dtype=float)
    if cost.shape != batch:
        raise ValueError(f"cost has shape {cost.shape}; expected {batch} (one per sample)")
    if done is None:
        not_done = np.ones(cost.size)
    else:
        done = np.asarray(done)
        if done.shape != batch:
            raise ValueError(f"done has shape {done.shape}; expected {batch} (one per sample)")
        if done.dtype != bool:
            raise ValueError(f"done has dtype {done.dtype}; expected bool")
        not_done = (~done).reshape(-1).astype(float)
    return cost.reshape(-1), not_done


def _check_gamma(gamma: float) -> float:
    return check_real("gamma", gamma, 0.0, 1.0, low_open=True)


def _check_ridge(ridge: float) -> float:
    return check_real("ridge", ridge, 0.0)


def _solve(
    z: np.ndarray,
    z_next: np.ndarray,
    cost: np.ndarray,
    not_done: np.ndarray,
    gamma: float,
    ridge: float,
    blocks: tuple[int, ...],
    zero_tol: float,
) -> tuple[np.ndarray, dict]:
    """Scaled, regularised LSTD solve; ``z``, ``z_next`` shape ``(S, k)``, ``cost`` ``(S,)``."""
    for name, value in (("features", z), ("next features", z_next), ("cost", cost)):
        if not np.all(np.isfinite(value)):
            raise ValueError(f"LSTD {name} contain non-finite values (nan or inf)")
    n_samples, k = z.shape
    mean_square = np.mean(z**2, axis=0)
    # Zero features are judged per block: sensitivities and soc monomials have unrelated units.
    keep = np.ones(k, dtype=bool)
    start = 0
    for size in blocks:
        block = mean_square[start : start + size]
        if size:
            keep[start : start + size] = block > zero_tol * block.max()
        start += size
    scale = np.sqrt(mean_square[keep])
    # the same operations in the same order as z[:, keep] / scale and
    # z_next[:, keep] / scale * (gamma * not_done)[:, None], without their temporaries
    zs = z[:, keep]
    zs /= scale
    zs_next = z_next[:, keep]
    zs_next /= scale
    zs_next *= (gamma * not_done)[:, None]
    difference = np.subtract(zs, zs_next, out=zs_next)  # zs - zs_next
    matrix = zs.T @ difference / n_samples + ridge * np.eye(zs.shape[1])
    rhs = zs.T @ cost / n_samples
    if matrix.size:
        solution, _, rank, singular = np.linalg.lstsq(matrix, rhs, rcond=None)
    else:  # every feature is zero: nothing to fit
        solution, rank, singular = np.zeros(0), 0, np.zeros(0)
    x = np.zeros(k)
    x[keep] = solution / scale
    td = cost + (gamma * not_done) * (z_next @ x) - z @ x
    smallest = singular[-1] if singular.size else 0.0
    info = {
        "condition": float(singular[0] / smallest) if smallest > 0 else float("inf"),
        "rank_deficient": bool(rank < zs.shape[1]),
        "n_samples": int(n_samples),
        "dropped_w": ~keep[: blocks[0]],
        "dropped_v": ~keep[blocks[0] :],
        "td_rms": float(np.sqrt(np.mean(td**2))),
    }
    return x, info
