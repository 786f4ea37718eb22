r"""The policy gradient with the exact slope of the cost-to-go: what the critic should estimate.

The deterministic policy gradient theorem for a day of ``H`` hours that starts at a given
state reads

.. math::

    \nabla_\theta J = \sum_{k=0}^{H-1} \gamma^k\,
    \mathbb E\big[\nabla_\theta\pi_\theta(s_k)\,\nabla_a Q_\pi(s_k, a)|_{a = \pi_\theta(s_k)}\big],
    \qquad Q_\pi(s_k, a) = \tilde L(s_k, a) + \sum_{j > k} \gamma^{j - k}\,\tilde L(s_j, \pi(s_j)),

the expectation over the noise and the days. The learner of :mod:`mpcrl_lite.learning.step`
replaces :math:`\nabla_a Q_\pi` by the action gradient of its compatible critic, a least-squares
fit from explored actions (and averages the hours alike). In a simulation the slope itself
can be measured: from every state of a recorded closed loop the day is played on twice per
battery, with that battery's action at hour ``k`` moved by :math:`\pm\varepsilon` and the
policy acting from hour ``k + 1`` on, on the **same** noise (common random numbers), and

.. math::

    \widehat{\partial_{a_i} Q}(s_k) = \frac{Q(s_k, \pi + \varepsilon e_i) - Q(s_k, \pi -
    \varepsilon e_i)}{2\varepsilon}.

With a small :math:`\varepsilon` (:data:`DEFAULT_EPS`) this is the local slope, and the sum
above is the gradient of :math:`J` on those noise draws (``tests/learning/test_rollout_gradient.py``
checks it against finite differences of :math:`J` in theta). With :math:`\varepsilon` as wide as
the learner's exploration it is the *secant* over the explored actions, which is what a
compatible critic fitted from that exploration measures at best; where :math:`Q_\pi` is far
from linear over a few tenths of a MW (the soc penalty's kinks, the buy/sell price step, the
low-level controller's clipping, the MPC's own change of plan) the two differ, and so do the
gradients they imply (``benchmarks/README.md``, notebook 09).

This is a tool for analysis, not a learner: a real battery lives each day once, and the
rollouts replay a day from a state with the same noise. Cost: for every hour ``k`` one closed
loop of ``2 n D`` rows over the remaining ``H - k`` hours, about ``n H`` times the solves of
the month itself.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from .._util.validate import check_real
from ..config import SystemConfig
from ..sim.closed_loop import (
    MPCPolicy,
    SensitivityRecorder,
    _TiledPrices,
    simulate,
    stacked_draws,
)
from ..system.battery import step
from ..theta import Theta

__all__ = ["DEFAULT_EPS", "RolloutGradient", "rollout_policy_gradient"]

#: Half-width (MW) of the central difference of the local slope: small against the
#: exploration (0.2 MW) and large against the interior point's tolerance.
DEFAULT_EPS = 1e-3


@dataclass(frozen=True, eq=False)
class RolloutGradient:
    """The result of :func:`rollout_policy_gradient`.

    Attributes
    ----------
    grad : numpy.ndarray, shape ``(n_theta,)``
        :math:`\\sum_k \\gamma^k\\,\\mathrm{mean}_d\\,\\nabla_\\theta\\pi\\,\\widehat{\\nabla_a Q}`
        over the usable samples: the gradient of the mean discounted daily cost ``J``.
    action_gradient : numpy.ndarray, shape ``(H, D, n)``
        :math:`\\widehat{\\partial_{a_i} Q}` at every hour, day and battery (NOK/MW).
    grad_pi : numpy.ndarray, shape ``(H, D, n_theta, n)``
        The policy's sensitivity at the recorded states.
    ok : numpy.ndarray of bool, shape ``(H, D)``
        The sample's MPC, its sensitivity and every solve of its rollouts succeeded; the
        others are left out of ``grad`` (their ``action_gradient`` is NaN).
    J : float
        The mean discounted daily cost of the recorded (unperturbed) days.
    eps : float
        The half-width of the difference, MW.
    """

    grad: np.ndarray
    action_gradient: np.ndarray
    grad_pi: np.ndarray
    ok: np.ndarray
    J: float
    eps: float


def rollout_policy_gradient(
    theta: Theta,
    solver: Any,
    prices: Any,
    system: SystemConfig,
    noise: Any,
    eps: float = DEFAULT_EPS,
    soc0: Any = None,
) -> RolloutGradient:
    """The policy gradient of the MPC at ``theta`` on the days of ``prices`` with ``noise``,
    from measured slopes of the cost-to-go (see the module docstring).

    Parameters
    ----------
    theta : Theta
    solver
        A back-end from :func:`mpcrl_lite.mpc.backends.registry.make_solver` (its
        ``sensitivity`` is used once per hour of the recorded days).
    prices
        Anything with ``days``, ``buy``, ``sell`` and ``window(hour, N)`` (a
        :class:`~mpcrl_lite.system.prices.Prices`), one row per day.
    system : SystemConfig
        The true system.
    noise : array_like, shape ``(H, K * days, n)``
        The noise of every hour and day: ``K >= 1`` draws of the month stacked draw by draw,
        as :func:`~mpcrl_lite.sim.closed_loop.evaluate_mpc` stacks them (day ``d`` of draw
        ``k`` is column ``k * days + d``); e.g. ``sample_noise(evaluation_rng(seed, k), (H,
        days, n), system)`` for ``k < K``, concatenated along axis 1.
    eps : float, default :data:`DEFAULT_EPS`
        Half-width of the central difference in MW, ``> 0``.
    soc0 : float or array_like, optional
        State at the start of the days (default ``system.soc0``).

    Returns
    -------
    RolloutGradient
    """
    if not isinstance(theta, Theta) or theta.n != system.n:
        raise ValueError(f"theta={theta!r}: expected a Theta with n={system.n}")
    eps = check_real("eps", eps, 0.0, low_open=True)
    H, n, gamma = system.hours_per_day, system.n, system.gamma
    noise, prices = stacked_draws(prices, system, noise)
    D = noise.shape[1]
    sens = SensitivityRecorder()
    record = simulate(MPCPolicy(solver, theta, prices, sensitivities=True),
                      np.asarray(prices.buy)[:, :H], np.asarray(prices.sell)[:, :H], system,
                      noise=noise, soc0=soc0, on_hour=[sens])
    grad_pi = sens.grad_pi
    ok = record.solver_ok & record.sens_ok
    rows = 2 * n  # +eps and -eps for each battery, battery-major: block 2i is +, 2i+1 is -
    signs = np.tile([eps, -eps], n)
    tiled = _TiledPrices(prices, rows)
    slope = np.full((H, D, n), np.nan)
    for k in range(H):
        soc = np.tile(record.soc[k], (rows, 1))
        a = np.tile(record.policy[k], (rows, 1))
        for j in range(rows):
            a[j * D:(j + 1) * D, j // 2] += signs[j]
        policy = MPCPolicy(solver, theta, tiled)
        cost = np.zeros(rows * D)
        solved = np.ones(rows * D, bool)
        for hour in range(k, H):
            if hour > k:
                decision = policy.decide(hour, soc)
                a, solved = decision.action, solved & decision.solver_ok
            res = step(soc, a, np.tile(noise[hour], (rows, 1)), tiled.buy[:, hour],
                       tiled.sell[:, hour], system)
            cost += gamma ** (hour - k) * res.stage_cost
            soc = res.soc_next
        cost, solved = cost.reshape(rows, D), solved.reshape(rows, D)
        slope[k] = ((cost[0::2] - cost[1::2]) / (2.0 * eps)).T
        ok[k] &= solved.all(axis=0)
    slope[~ok] = np.nan
    weights = gamma ** np.arange(H)
    per_sample = np.einsum("kdti,kdi->kdt", grad_pi, np.where(ok[..., None], slope, 0.0))
    grad = np.einsum("k,kdt->t", weights, per_sample) / D
    return RolloutGradient(grad=grad, action_gradient=slope, grad_pi=grad_pi, ok=ok,
                           J=float(record.J()), eps=eps)

