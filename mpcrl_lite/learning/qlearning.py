r"""LSTD Q-learning with the MPC as the action-value function (beside the policy gradient).

The paper's introduction contrasts learning the policy (the deterministic policy gradient it
uses, :mod:`mpcrl_lite.learning.dpg`) with learning the action-value function (Q-learning,
LSTD). Here the same barrier MPC is the approximator of both value functions
(:class:`mpcrl_lite.mpc.value.MPCValue`): :math:`Q_\theta(s, a)` with its first action fixed
to ``a``, :math:`V_\theta(s)` the MPC itself, and :math:`\pi_\theta = \arg\min_a Q_\theta`.

From a month of transitions :math:`(s_k, a_k, L_k, s_{k+1})` -- ``a_k`` the applied,
explored action -- the TD errors are

.. math:: \delta_k = \tilde L(s_k, a_k) + \gamma V_\theta(s_{k+1}) - Q_\theta(s_k, a_k),

with no bootstrap at the last hour of a day (every day is an episode, as for the DPG critic:
the next day restarts at ``soc0``). Q-learning fits :math:`Q_\theta` to its TD targets, the
least-squares TD loss :math:`\frac12\,\mathrm{mean}\,\delta^2` with the target held fixed
(semi-gradient), whose gradient and Hessian in theta are

.. math::
   g = -\mathrm{mean}(\delta\,\nabla_\theta Q), \qquad
   H_\text{approx} = \mathrm{mean}(\nabla_\theta Q\,\nabla_\theta Q^\top), \qquad
   H_\text{full} = \mathrm{mean}(\nabla_\theta Q\,\nabla_\theta Q^\top
                   - \delta\,\nabla^2_\theta Q)

(:func:`td_gradient`; the Gauss-Newton ``'approx'`` drops the curvature of Q, the ``'full'``
one keeps it). :class:`QLearningUpdater` takes a first-order step with the configured
optimizer (``hessian='none'``) or a Newton step :math:`\theta - \alpha H^{-1} g`
(``alpha = newton_step``) with ``H``
made positive definite by adding a multiple of the identity (:func:`regularised_solve`,
Nocedal & Wright, *Numerical Optimization*, 2nd ed., Algorithm 3.3), in the coordinates of
the learnable parameters (tied over the agents with ``tie_agents``), then the DPG's
safeguards (clipping, the projection that keeps the MPC a convex QP).

Samples whose Q solve failed, whose next state's MPC failed (where it bootstraps) or whose
hour's MPC failed are left out and counted.

The applied action is the MPC's plus the same bounded zero-mean Gaussian exploration as for
DPG (:mod:`mpcrl_lite.sim.exploration`); Q is evaluated at it pulled :data:`Q_ACTION_MARGIN`
inside the input bounds and grid limits (an action on a bound is outside the barrier's
domain).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from .._util.validate import check_choice, check_instance
from ..config import HESSIANS, LearningConfig, SystemConfig
from ..mpc.value import MPCValue
from ..sim.closed_loop import HourStep
from ..sim.exploration import exploration_center
from ..theta import CONSTANT_PARTS, PARTS
from .dpg import DPGUpdater, learnable_mask

__all__ = ["Q_ACTION_MARGIN", "QLearningUpdater", "ValueRecorder", "regularised_solve",
           "td_errors", "td_gradient"]

#: In MW: how far inside the input bounds and grid limits the applied action is pulled before
#: Q is evaluated at it (the barrier is infinite on the bounds).
Q_ACTION_MARGIN = 1e-3

#: Initial shift of :func:`regularised_solve` (Nocedal & Wright's beta).
REGULARISATION_BETA = 1e-3


def q_action(a: np.ndarray, system: SystemConfig) -> np.ndarray:
    """The action at which Q is evaluated: ``a`` pulled :data:`Q_ACTION_MARGIN` inside."""
    return exploration_center(a, system, Q_ACTION_MARGIN)


class ValueRecorder:
    """Hour hook of the closed loop: :math:`V_\\theta` at each hour's MPC solutions (no extra
    solve) and those solutions' primal points (the warm start of the Q solves).

    After the month, :attr:`value` and :attr:`ok` are ``(H, D)`` and :attr:`x` ``(H, D, nx)``.
    """

    #: it only reads the steps: a compiled month calls it after the month with the same steps
    #: (:func:`mpcrl_lite.sim.closed_loop.run_month`)
    replayable = True

    def __init__(self, value: MPCValue) -> None:
        self.mpc_value = value
        self._v: list[np.ndarray] = []
        self._ok: list[np.ndarray] = []
        self._x: list[np.ndarray] = []

    def __call__(self, hour_step: HourStep) -> None:
        solution = hour_step.decision.solution
        if solution is None:
            raise ValueError(f"at hour {hour_step.hour}: the policy returned no solution "
                             "(expected an MPC policy)")
        v = self.mpc_value.state_value(solution)
        self._v.append(v.value)
        self._ok.append(v.ok)
        self._x.append(np.asarray(solution.x))

    @property
    def value(self) -> np.ndarray:
        return np.stack(self._v)

    @property
    def ok(self) -> np.ndarray:
        return np.stack(self._ok)

    @property
    def x(self) -> np.ndarray:
        return np.stack(self._x)


def td_errors(cost: np.ndarray, q: np.ndarray, v: np.ndarray, gamma: float,
              bootstrap_last: bool = False) -> np.ndarray:
    r"""The TD errors :math:`\delta_k = L_k + \gamma V(s_{k+1}) - Q(s_k, a_k)` of ``H`` hours.

    cost, q : (H, D); v : (H, D) the values at the hours' own states (``v[k + 1]`` is the
    bootstrap of hour ``k``), or (H + 1, D) with the state after the last hour. The last hour
    bootstraps only with ``bootstrap_last`` (then ``v`` must have ``H + 1`` rows).
    """
    cost, q, v = (np.asarray(x, dtype=float) for x in (cost, q, v))
    H = cost.shape[0]
    nxt = np.zeros_like(cost)
    nxt[: H - 1] = v[1:H]
    if bootstrap_last:
        if v.shape[0] != H + 1:
            raise ValueError(f"v has {v.shape[0]} rows; expected H + 1 = {H + 1} to bootstrap "
                             "the last hour")
        nxt[H - 1] = v[H]
    return cost + gamma * nxt - q


def td_gradient(delta: np.ndarray, dq: np.ndarray, d2q: np.ndarray | None,
                hessian: str) -> tuple[np.ndarray, np.ndarray | None]:
    r"""Gradient and Hessian of the TD loss over the samples (see the module docstring).

    delta (S,), dq (S, n_theta), d2q (S, n_theta, n_theta) (needed for ``'full'``). Returns
    ``(g, H)``, ``H`` None for ``hessian='none'``.
    """
    hessian = check_choice("hessian", hessian, HESSIANS)
    delta, dq = np.asarray(delta, float), np.asarray(dq, float)
    if delta.ndim != 1 or dq.shape[:1] != delta.shape or not delta.size:
        raise ValueError(f"delta {delta.shape} and dq {dq.shape}: expected (S,) and "
                         "(S, n_theta) with S >= 1")
    g = -(delta[:, None] * dq).mean(axis=0)
    if hessian == "none":
        return g, None
    H = np.einsum("si,sj->ij", dq, dq) / delta.size
    if hessian == "full":
        if d2q is None:
            raise ValueError("hessian='full' needs d2q, the Hessians of Q")
        H = H - np.einsum("s,sij->ij", delta, np.asarray(d2q, float)) / delta.size
    return g, 0.5 * (H + H.T)


def regularised_solve(H: np.ndarray, g: np.ndarray, beta: float = REGULARISATION_BETA,
                      max_tries: int = 200, growth: float = 2.0) -> tuple[np.ndarray, float]:
    r"""``(H + t I)^{-1} g`` with the smallest ``t`` of the sequence ``0`` (if ``H``'s
    diagonal is positive, else ``beta - min diag``), then growing by ``growth`` (doubling)
    from ``beta``, for which the Cholesky factorisation succeeds (Nocedal & Wright, Algorithm
    3.3); returns the solution and ``t``. An indefinite ``H`` (the full TD Hessian far from a
    fit) is shifted: the step then depends on the schedule, which is why ``growth`` can be set
    (``benchmarks/bench_mpcrl_q.py`` uses mpcrl's 1.05 to compare with it)."""
    if not growth > 1.0:
        raise ValueError(f"growth={growth!r}: expected a factor > 1")
    H = np.asarray(H, float)
    t = 0.0 if np.diag(H).min() > 0 else beta - np.diag(H).min()
    eye = np.eye(H.shape[0])
    for _ in range(max_tries):
        try:
            L = np.linalg.cholesky(H + t * eye)
        except np.linalg.LinAlgError:
            t = max(growth * t, beta)
            continue
        return np.linalg.solve(L.T, np.linalg.solve(L, g)), t
    raise ValueError(f"no positive definite H + t I found after {max_tries} tries (t = {t:g})")


class QLearningUpdater:
    """The Q-learning step on theta: first order through :class:`DPGUpdater` with the
    configured optimizer, or a regularised Newton step (see the module docstring).

    The learned parameters are those of :func:`~mpcrl_lite.learning.dpg.learnable_mask`
    (with ``tie_agents`` one value per part for all batteries) and the level of Q, which the
    TD fit needs: ``T3`` shared by all batteries (``phi3`` stays; see :meth:`_make_basis`). State, checkpoints and
    :attr:`last_info` are the inner :class:`DPGUpdater`'s (with, for a Newton step,
    ``newton_shift`` the ``t`` of :func:`regularised_solve`).
    """

    def __init__(self, config: LearningConfig, system: SystemConfig, prices: Any = None) -> None:
        self.config = check_instance("config", config, LearningConfig)
        self.n = system.n
        self.second_order = config.hessian != "none"
        inner = config.replace(learn_constants=True)
        if self.second_order:  # the direction is the Newton step itself
            inner = inner.replace(optimizer="sgd", step_size=config.newton_step)
        self.inner = DPGUpdater.from_configs(inner, system, prices)
        self._basis = self._make_basis()
        self._hessian: np.ndarray | None = None

    def observe(self, hessian: np.ndarray | None) -> None:
        """Give the next :meth:`step` the month's TD Hessian (used by one step)."""
        self._hessian = None if hessian is None else np.asarray(hessian, float)

    @classmethod
    def from_configs(cls, learning: LearningConfig, system: SystemConfig,
                     prices: Any = None) -> QLearningUpdater:
        return cls(learning, system, prices)

    def _make_basis(self) -> np.ndarray:
        """Columns spanning what is learned: one per learnable entry of the non-constant
        parts (with ``tie_agents`` one per part, ones on its agents), and one column for the
        level of Q, ``T3`` shared by all batteries (``phi3`` and ``T3`` only add constants to
        every value: their entries are collinear in the TD fit, so one level is learned)."""
        n, size = self.n, len(PARTS) * self.n
        mask = learnable_mask(n, learn_constants=False)
        cols = []
        for k, part in enumerate(PARTS):
            entries = np.arange(k * n, (k + 1) * n)
            if part in CONSTANT_PARTS:
                if part == "T3":
                    col = np.zeros(size)
                    col[entries] = 1.0
                    cols.append(col)
                continue
            if self.config.tie_agents:
                col = np.zeros(size)
                col[entries] = mask[entries]
                cols.append(col)
            else:
                cols += [np.eye(size)[i] for i in entries if mask[i]]
        return np.stack(cols, axis=1)

    def direction(self, g: np.ndarray, H: np.ndarray | None) -> tuple[np.ndarray, float]:
        """What the inner updater is given: ``g`` projected onto the learned parameters
        (first order) or the regularised Newton direction in their coordinates, mapped back
        to theta's, and the shift of :func:`regularised_solve`."""
        B = self._basis
        if H is None:
            return B @ np.linalg.solve(B.T @ B, B.T @ g), 0.0
        d, shift = regularised_solve(B.T @ H @ B, B.T @ g)
        return B @ d, shift

    def step(self, theta, g: np.ndarray, H: np.ndarray | None = None):
        """One update of theta from the TD gradient ``g`` and Hessian ``H`` (default: the
        one given with :meth:`observe`)."""
        g = np.asarray(g, dtype=float)
        if H is None:
            H, self._hessian = self._hessian, None
        if self.second_order and H is None and g.any():
            raise ValueError(f"hessian={self.config.hessian!r}: the step needs the TD Hessian")
        if self.second_order and H is not None and not np.all(np.isfinite(H)):
            raise ValueError("the TD Hessian contains non-finite values (nan or inf)")
        d, shift = self.direction(g, H if self.second_order else None)
        new = self.inner.step(theta, d)
        if self.second_order:
            self.inner.last_info["newton_shift"] = float(shift)
        return new

    @property
    def last_info(self) -> dict[str, Any]:
        return self.inner.last_info

    @property
    def step_count(self) -> int:
        return self.inner.step_count

    def state_dict(self) -> dict[str, Any]:
        return self.inner.state_dict()

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.inner.load_state_dict(state)
