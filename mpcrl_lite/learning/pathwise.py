r"""The pathwise policy gradient: the exact derivative of a simulated month's cost in theta.

On a fixed draw of the noise the closed loop is a deterministic function of theta, and so is
its discounted cost. Its derivative is carried forward through the hours of every day
(forward-mode differentiation of the simulation) with the sensitivity
:math:`X_k = \partial soc_k / \partial\theta` of the state:

.. math::

    \frac{d\pi_k}{d\theta} = \nabla_\theta\pi(s_k) + \frac{\partial\pi}{\partial soc}(s_k)\,X_k,
    \qquad X_{k+1} = X_k + \alpha\,\frac{d\pi_k}{d\theta}, \qquad X_0 = 0,

and the hour's cost :math:`\tilde L = \phi_b b - \phi_s s + \mathrm{penalty}(soc_k)` changes
by :math:`\phi\,d\,net + \mathrm{penalty}'(soc_k)\,X_k` (:math:`\phi` the buy price where the
battery buys, the sell price where it sells). Where the low-level controller clips the
action (the soc would leave [0, 1]) the applied power is :math:`(bound - soc_k)/\alpha -
\Delta_k`, so :math:`d\,net = -X_k/\alpha` and :math:`X_{k+1} = 0`.

:math:`\nabla_\theta\pi` is the MPC's KKT sensitivity (the back-end's ``sensitivity``);
:math:`\partial\pi/\partial soc` comes from the same adjoint where the back-end forms it
(the compiled kernel: :attr:`~mpcrl_lite.mpc.solution.Sensitivity.grad_soc0`, the adjoint's
multiplier of the first dynamics row, since the initial soc enters the problem there only),
else it is measured by central differences of the MPC's solution (the barrier problem's
solution is smooth in its initial state; one extra solver call of ``2 n`` rows per hour).
The result is the gradient that
:func:`~mpcrl_lite.learning.rollout_gradient.rollout_policy_gradient` measures by replaying
the days, in the limit of a small nudge, at the cost of a month and its sensitivities
instead of ``n H`` months (``tests/learning/test_pathwise.py`` checks both against finite
differences of J in theta).

Like the rollouts, this needs what a real battery does not have: the model's derivatives and
the month's noise replayed. It is the gradient an MPC-based learner would follow if its
critic were exact, which is why :class:`~mpcrl_lite.learning.experiment.Experiment` offers it
as a labelled extension (``LearningConfig.gradient = 'pathwise'``) beside the paper's LSTD
critic (``'critic'``, the default): the two together split the learner's part of the regret
into what the critic's estimate costs and what the step rule and the distance cost.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from .._util.validate import check_real
from ..config import SystemConfig
from ..sim.closed_loop import HourStep, MPCPolicy, simulate, stacked_draws
from ..system.battery import battery_values
from ..theta import Theta

__all__ = ["DEFAULT_SOC_STEP", "PathwiseGradient", "PathwiseRecorder",
           "pathwise_policy_gradient"]

#: Half-width of the central difference of the MPC's action in its initial soc: small against
#: the soc's range and large against the interior point's tolerance (1e-10).
DEFAULT_SOC_STEP = 1e-4


@dataclass(frozen=True, eq=False)
class PathwiseGradient:
    """The result of :func:`pathwise_policy_gradient` (and of :class:`PathwiseRecorder`).

    Attributes
    ----------
    grad : numpy.ndarray, shape ``(n_theta,)``
        :math:`\\partial J / \\partial\\theta`, the mean over the usable days of the
        derivative of each day's discounted cost.
    per_day : numpy.ndarray, shape ``(D, n_theta)``
        The derivative of each day's discounted cost (zeros on days left out).
    ok : numpy.ndarray of bool, shape ``(D,)``
        Every solve, sensitivity and state difference of the day succeeded; the other days
        are left out of ``grad``.
    """

    grad: np.ndarray
    per_day: np.ndarray
    ok: np.ndarray


class PathwiseRecorder:
    """Hour hook of :func:`~mpcrl_lite.sim.closed_loop.simulate` that carries the derivative of
    the days' discounted cost in theta forward, hour by hour (see the module docstring).

    The policy must be an :class:`~mpcrl_lite.sim.closed_loop.MPCPolicy` with
    ``sensitivities=True`` and the loop must run without exploration (the derivative is the
    deterministic policy's). :meth:`result` gives the :class:`PathwiseGradient` once the day
    is done.

    Parameters
    ----------
    solver
        The policy's back-end (its ``solve_batch`` measures :math:`\\partial\\pi/\\partial soc`).
    system : SystemConfig
        The true system.
    soc_step : float, default :data:`DEFAULT_SOC_STEP`
        Half-width of the central difference in the initial soc, ``> 0``.
    """

    def __init__(self, solver: Any, system: SystemConfig,
                 soc_step: float = DEFAULT_SOC_STEP) -> None:
        if not isinstance(system, SystemConfig):
            raise ValueError(f"system={system!r}: expected a SystemConfig")  # noqa: TRY004
        self.solver, self.system = solver, system
        self.soc_step = check_real("soc_step", soc_step, 0.0, 0.05, low_open=True)
        n = system.n
        self._alpha = np.broadcast_to(np.asarray(battery_values(system, "alpha"), float), (n,))
        self._p = np.broadcast_to(np.asarray(battery_values(system, "p"), float), (n,))
        self._X: np.ndarray | None = None
        self._total: np.ndarray | None = None
        self._ok: np.ndarray | None = None

    def __call__(self, hs: HourStep) -> None:
        d = hs.decision
        if d.grad is None or d.solution is None:
            raise ValueError(f"at hour {hs.hour}: the policy returned no sensitivity (expected "
                             "an MPCPolicy with sensitivities=True)")
        if np.any(hs.a != d.action):
            raise ValueError(f"at hour {hs.hour}: the applied action is not the policy's "
                             "(expected a loop without exploration)")
        D, n = hs.soc.shape
        G = np.swapaxes(d.grad, 1, 2)  # (D, n, T)
        if self._X is None:
            self._X = np.zeros_like(G)
            self._total = np.zeros((D, G.shape[2]))
            self._ok = np.ones(D, bool)
        if d.grad_soc0 is not None:  # from the sensitivity's own adjoint
            dpi_dsoc, ok = np.swapaxes(d.grad_soc0, 1, 2), np.ones(D, bool)
        else:
            dpi_dsoc, ok = self._state_sensitivity(d.solution, n)
        self._ok &= ok & d.solver_ok & d.sens_ok
        X = self._X
        dpi = G + np.einsum("dij,djt->dit", dpi_dsoc, X)
        clipped = (hs.result.correction != 0.0)[..., None]
        dnet = np.where(clipped, -X / self._alpha[:, None], dpi)
        # the price of the side the battery trades on; idle (net = 0) counts as buying
        price = np.where(hs.result.s > 0.0, hs.sell[:, None], hs.buy[:, None])
        low, high = self.system.soc_low, self.system.soc_high
        slope = self._p * ((hs.soc > high).astype(float) - (hs.soc < low).astype(float))
        dL = price[..., None] * dnet + slope[..., None] * X
        self._total += self.system.gamma ** hs.hour * dL.sum(axis=1)
        self._X = np.where(clipped, 0.0, X + self._alpha[:, None] * dpi)

    def _state_sensitivity(self, sol: Any, n: int) -> tuple[np.ndarray, np.ndarray]:
        """:math:`\\partial\\pi/\\partial soc` (D, n, n) at the hour's states by central
        differences (one solver call of ``2 n D`` rows, warm-started at the solution), and
        the rows whose every solve succeeded."""
        P, mpc = np.asarray(sol.p, dtype=float), self.solver.mpc
        D, N = P.shape[0], mpc.N
        soc, buy, sell = P[:, :n], P[:, n:n + N], P[:, n + N:n + 2 * N]
        theta = P[:, mpc.theta_slice]
        h = self.soc_step
        shifts = np.zeros((2 * n, n))
        for i in range(n):
            shifts[2 * i, i], shifts[2 * i + 1, i] = h, -h
        rows = (soc[None] + shifts[:, None, :]).reshape(2 * n * D, n)
        tile = (2 * n, 1)
        res = self.solver.solve_batch(rows, np.tile(buy, tile), np.tile(sell, tile),
                                      np.tile(theta, tile), x0=np.tile(sol.x, tile))
        act = res.action.reshape(2 * n, D, n)
        deriv = (act[0::2] - act[1::2]) / (2.0 * h)  # (n_in, D, n_out)
        ok = res.success.reshape(2 * n, D).all(axis=0)
        return np.transpose(deriv, (1, 2, 0)), ok

    def result(self, rows: slice | None = None) -> PathwiseGradient:
        """The derivative of the days recorded so far, or of the days ``rows`` of them (one
        run's days of a loop of runs in lockstep: the same figures, bit for bit, as that
        run's loop alone)."""
        if self._total is None:
            raise ValueError("no hour recorded yet")
        rows = slice(None) if rows is None else rows
        ok = self._ok[rows].copy()
        per_day = np.where(ok[:, None], self._total[rows], 0.0)
        used = int(ok.sum())
        grad = per_day.sum(axis=0) / used if used else np.zeros(per_day.shape[1])
        return PathwiseGradient(grad=grad, per_day=per_day, ok=ok)


def pathwise_policy_gradient(
    theta: Theta,
    solver: Any,
    prices: Any,
    system: SystemConfig,
    noise: Any,
    soc0: Any = None,
    soc_step: float = DEFAULT_SOC_STEP,
) -> PathwiseGradient:
    """The derivative in theta of the mean discounted daily cost of the MPC at ``theta`` on
    the days of ``prices`` with the noise ``noise`` (see the module docstring).

    Parameters
    ----------
    theta : Theta
    solver
        A back-end from :func:`mpcrl_lite.mpc.backends.registry.make_solver`.
    prices
        Anything with ``buy``, ``sell`` and ``window(hour, N)`` (a
        :class:`~mpcrl_lite.system.prices.Prices`), one row per day.
    system : SystemConfig
        The true system.
    noise : array_like, shape ``(H, K * D, n)``
        The noise of every hour and day: ``K >= 1`` draws of the month stacked draw by draw,
        as :func:`~mpcrl_lite.sim.closed_loop.evaluate_mpc` stacks them (day ``d`` of draw
        ``k`` is column ``k * D + d``).
    soc0 : float or array_like, optional
        State at the start of the days (default ``system.soc0``).
    soc_step : float, default :data:`DEFAULT_SOC_STEP`

    Returns
    -------
    PathwiseGradient
    """
    if not isinstance(theta, Theta) or theta.n != system.n:
        raise ValueError(f"theta={theta!r}: expected a Theta with n={system.n}")
    H = system.hours_per_day
    noise, prices = stacked_draws(prices, system, noise)
    recorder = PathwiseRecorder(solver, system, soc_step)
    simulate(MPCPolicy(solver, theta, prices, sensitivities=True),
             np.asarray(prices.buy)[:, :H], np.asarray(prices.sell)[:, :H], system,
             noise=noise, soc0=soc0, on_hour=[recorder])
    return recorder.result()
