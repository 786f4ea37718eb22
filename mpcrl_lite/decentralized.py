r"""Decentralized learning: one local MPC and one learner per battery, grid limit by prices.

The paper learns one centralized MPC for all batteries and names decentralized learning as
future work. Here every battery ``i`` has

* its own MPC -- the paper's MPC (eq. 9) with ``n = 1`` -- and its own parameters
  :math:`\theta^i` (10 entries, see :mod:`mpcrl_lite.theta`);
* its own critic and actor: LSTD on its *own* cost :math:`\tilde L_i` with value features of
  its *own* soc, :math:`\Phi_i = [soc_i^2, soc_i, 1]`, and compatible features from its own
  policy sensitivity :math:`\nabla_{\theta^i}\pi^i`; the DPG step updates :math:`\theta^i`
  only.

The batteries share the grid: the limits :math:`\sum_i \hat b^i_j \le \bar P` and
:math:`\sum_i \hat s^i_j \le \bar P` (eq. 9f, at every predicted stage ``j``) couple them.
They are coordinated at every hour by **prices**: a grid-capacity price
:math:`\lambda^b_j \ge 0` on buying and :math:`\lambda^s_j \ge 0` on selling, per stage, is
added to every local cost,

.. math::
   \min_{x_i}\; f_i(x_i;\theta^i) + \sum_{j}\big(\lambda^b_j \hat b^i_j
   + \lambda^s_j \hat s^i_j\big) - \tau\sum_k\log(-h_{ik}(x_i))
   \quad\text{s.t. local dynamics,}

i.e. battery ``i`` sees the buying price :math:`\phi_{b,j} + \lambda^b_j/\gamma^j` and the
selling price :math:`\phi_{s,j} - \lambda^s_j/\gamma^j` and nothing else of the others.

Which prices
------------
Every MPC here is solved as its barrier problem with ``tau`` fixed
(:class:`~mpcrl_lite.config.MPCConfig`), the centralized one too, whose grid rows carry the
barrier :math:`-\tau\log(\bar P - \sum_i \hat b^i_j)`. Its KKT conditions are those of the
local problems above together with the relaxed complementarity of the grid rows,

.. math::
   \lambda^b_j\big(\textstyle\sum_i \hat b^i_j - \bar P\big) + \tau = 0,\qquad
   \lambda^s_j\big(\textstyle\sum_i \hat s^i_j - \bar P\big) + \tau = 0 .

The coordination finds the prices satisfying these ``2N`` equations per day; the local
solutions then **are** the centralized MPC's solution for the stacked
:math:`\theta = (\theta^1, \dots, \theta^n)` (:func:`join_theta`): decentralizing changes
who computes the policy and how it learns, not the policy. With a loose limit
(:math:`\bar P \ge n\bar U`) the prices settle at
:math:`\lambda_j = \tau/(\bar P - \sum_i \hat b^i_j) \le \tau/(\bar P - n\bar U)`: zero up to
the barrier, and the local problems are independent.

How the prices are found
------------------------
*Plain dual decomposition* -- every battery solves its problem exactly at the current prices,
the coordinator moves the prices along the limit violation -- does not work well here: the
local MPC is a linear program up to the barrier, so a battery's response to a price is a step
of width ~``tau`` (buy all or nothing). A dual gradient step must then be ~``tau`` small, and
a dual Newton step built from the batteries' price sensitivities is only valid within ~``tau``
of a step (in trials on the paper's system it sent the selling prices to 1e5).

The coordination therefore runs the interior-point iteration of the centralized barrier
problem in decomposed form (a Schur-complement, message-passing primal-dual method). One
**round**:

1. every battery evaluates its local barrier KKT residual at the current prices and takes
   its local Newton system apart into a step at fixed prices :math:`\Delta x_i^0` and the
   response to a price change, :math:`X_i = \partial\Delta x_i/\partial\lambda`; it sends
   the coordinator :math:`E\Delta x_i^0`, :math:`M_i = E X_i` (``2N x 2N``, negative
   semidefinite) and its current :math:`E x_i = (\hat b^i, \hat s^i)`;
2. the coordinator linearizes the grid complementarity and solves, per day,

   .. math:: \Big(\sum_i M_i + \mathrm{diag}(c/\lambda)\Big)\Delta\lambda
             = -\big(c + \tau/\lambda\big) - \sum_i E\Delta x_i^0,
             \qquad c = \textstyle\sum_i E x_i - \bar P < 0,

   picks a step length that keeps everything strictly inside (fraction to the boundary,
   local bounds reported by each battery) and backtracks on the total KKT residual;
3. every battery updates :math:`x_i \leftarrow x_i + t(\Delta x_i^0 + X_i\Delta\lambda)` and
   its multipliers; the coordinator updates :math:`\lambda \leftarrow \lambda + t\Delta\lambda`.

This is exactly the centralized Newton step, so it converges like an interior-point method.
Every hour starts from the same interior guess and follows the barrier path from a larger
``tau`` down to the MPC's ``tau`` (on the paper's system about 14 rounds per hour for
``n = 3`` and 20-26 for ``n = 20``; starting from the previous hour's shifted solution saved
less than one round on average and occasionally stalled, so it is not done).

* **Tolerance.** Rounds stop when every KKT residual (local stationarity, dynamics, local and
  grid complementarity) is at most ``tol * (1 + max |q|)``, ``q`` the local linear costs
  (:class:`CoordinationConfig`, default ``tol = 1e-11``, i.e. ~1e-9 NOK/MWh on the paper's
  prices). The number of rounds is recorded.
* **The limit.** The iterates stay strictly inside the grid limit (the barrier iteration
  never leaves it), so :math:`\sum_i \hat b^i_j < \bar P` holds at *every* round, converged
  or not, and the recorded ``violation`` is negative; only the fallback's independent local
  solves can exceed the limit, which is why their joint action is projected.
* **Failure.** If a day does not converge within ``max_iter`` rounds, or its Newton system
  is singular or not finite (the day's rounds then stop there), each battery solves its
  own MPC with the reference IPOPT back-end at the last prices, and the joint action is
  projected onto the grid limit with :func:`~mpcrl_lite.model.project_action`; the hour is
  recorded as projected. A battery whose solve fails idles (the fallback of
  :mod:`mpcrl_lite.solvers`).

Learning and its approximation
------------------------------
Battery ``i`` uses :math:`\nabla_{\theta^i}\pi^i` computed from its own KKT system at the
final prices (:class:`~mpcrl_lite.sensitivity.PolicySensitivity` of the local MPC), i.e.
**at fixed grid prices**: the response of the prices to :math:`\theta^i` (and through them
of the other batteries) is ignored. That is exact when the grid limit is slack (the prices
are then ~0 and insensitive) and an approximation when it binds. Exploration is drawn per
battery and the explored actions are projected jointly onto the grid limit, as in the
centralized experiment; random draws follow the same order (per hour: exploration, then
noise), so with the same seed both experiments see the same noise.

Example
-------
>>> from mpcrl_lite import LearningConfig, MPCConfig, SystemConfig
>>> from mpcrl_lite.decentralized import DecentralizedExperiment
>>> exp = DecentralizedExperiment(SystemConfig(), MPCConfig(), LearningConfig(months=2))
>>> history = exp.run(progress=False)                             # doctest: +SKIP
>>> history.update_info[-1]["coordination"]["iterations_mean"]    # doctest: +SKIP
"""

from __future__ import annotations

import json
import logging
import time
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import casadi as ca
import numpy as np

from .closed_loop import Decision, GaussianExploration, simulate
from .config import (
    ConfigWarning,
    CoordinationConfig,
    LearningConfig,
    MPCConfig,
    SystemConfig,
    check_int,
)
from .dpg import DPGUpdater, policy_gradient
from .experiment import (
    Experiment,
    resolve_setup,
    run_months,
    value_baseline_features,
    write_checkpoint,
)
from .history import History, MonthRecord
from .lstd import compatible_features, lstd_q
from .model import project_action
from .mpc import MPC
from .prices import Prices
from .sensitivity import PolicySensitivity
from .solvers import BatchSolution, IpoptSolver
from .theta import PARTS, Theta

__all__ = [
    "CoordinationConfig",
    "CoordinatedSolution",
    "CoordinatedMPC",
    "DecentralizedMonth",
    "DecentralizedExperiment",
    "compare_learners",
    "join_theta",
    "local_system",
    "run_month_decentralized",
    "split_theta",
]

log = logging.getLogger(__name__)

CHECKPOINT = "checkpoint.json"
_FORMAT = "mpcrl_lite.DecentralizedCheckpoint/1"


# -- theta per battery ------------------------------------------------------------------------
def split_theta(theta: Theta) -> list[Theta]:
    """The ``n`` local parameter sets of a centralized ``theta`` (each with ``n = 1``)."""
    if not isinstance(theta, Theta):
        raise ValueError(f"theta={theta!r}: expected a Theta")
    return [Theta(**{name: getattr(theta, name)[i : i + 1] for name in PARTS})
            for i in range(theta.n)]


def join_theta(thetas: Sequence[Theta]) -> Theta:
    """Inverse of :func:`split_theta`: stack local ``theta^i`` (``n = 1`` each) into one
    :class:`Theta` with ``n = len(thetas)``; the centralized MPC with it has the policy of the
    coordinated local MPCs."""
    thetas = list(thetas)
    if not thetas or any(not isinstance(t, Theta) or t.n != 1 for t in thetas):
        raise ValueError(f"thetas={thetas!r}: expected a non-empty list of Theta with n=1 each")
    return Theta(**{name: np.concatenate([getattr(t, name) for t in thetas]) for name in PARTS})


def local_system(system: SystemConfig, local_grid_factor: float = 1e4) -> SystemConfig:
    """The local MPC's system: ``system`` with ``n = 1`` and an inert grid row
    (``P_bar = local_grid_factor * max(U_bar, P_bar)``; the true limit is priced)."""
    if not isinstance(system, SystemConfig):
        raise ValueError(f"system={system!r}: expected a SystemConfig")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ConfigWarning)
        return system.replace(n=1, P_bar=local_grid_factor * max(system.U_bar, system.P_bar))


# -- the local problems, vectorized -----------------------------------------------------------
class _LocalQP:
    """The local MPC's barrier problems, many at once (one per day and battery).

    Data ``f = 0.5 x'Hx + q'x``, ``Ax = e``, ``Cx <= d`` from the MPC's own
    :meth:`~mpcrl_lite.mpc.MPC.qp_function`. ``H`` is diagonal and ``C`` block diagonal by
    stage (5 variables and 10 rows per stage for ``n = 1``), so a Newton system is solved with
    5x5 block inverses and an ``N x N`` Schur complement on the dynamics multipliers.
    """

    nb, nh = 5, 10

    def __init__(self, mpc: MPC) -> None:
        if mpc.n != 1:
            raise ValueError(f"the local MPC has n={mpc.n}; expected n=1")
        self.mpc = mpc
        N = mpc.N
        p = ca.MX.sym("p", mpc.np)
        rows, cols = mpc.qp_function.sparsity_out("H").get_triplet()
        if list(rows) != list(cols):  # the structure the Newton systems rely on
            raise RuntimeError("the MPC's Hessian is not diagonal")
        H, q, _, A, e, _, _ = mpc.qp_function(p)
        self._data = ca.Function("local_qp", [p], [ca.diag(H), q, A, e])
        ref = mpc.qp_data(np.full(mpc.np, 0.5))  # C and d do not depend on p
        self.Cb = np.stack([ref.C[j * self.nh : (j + 1) * self.nh, j * self.nb : (j + 1) * self.nb]
                            for j in range(N)])
        rebuilt = np.zeros_like(ref.C)
        for j in range(N):
            rebuilt[j * self.nh : (j + 1) * self.nh, j * self.nb : (j + 1) * self.nb] = self.Cb[j]
        if not np.array_equal(rebuilt, ref.C):
            raise RuntimeError("the MPC's inequality rows are not block diagonal by stage")
        self._CbT = np.ascontiguousarray(np.swapaxes(self.Cb, 1, 2))
        self.db = ref.d.reshape(N, self.nh)
        self._maps: dict[int, ca.Function] = {}
        sysc = mpc.system
        self.U, self.soc_low, self.soc_high = sysc.U_bar, sysc.soc_low, sysc.soc_high
        self.ib, self.is_ = mpc.index("b")[:, 0], mpc.index("s")[:, 0]
        self.isoc = mpc.index("soc")[:, 0]
        self.ihi, self.ilo = mpc.index("sigma_hi")[:, 0], mpc.index("sigma_lo")[:, 0]

    def data(self, P: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """``Hd (B, nx), q (B, nx), A (B, N, nx), e (B, N)`` for parameters ``P (B, np)``."""
        B = P.shape[0]
        if B not in self._maps:
            self._maps[B] = self._data.map(B)
        Hd, q, A, e = self._maps[B](P.T)
        m = self.mpc
        return (np.array(Hd).T, np.array(q).T,
                np.array(A).reshape(m.neq, B, m.nx).transpose(1, 0, 2), np.array(e).T)

    def h(self, x: np.ndarray) -> np.ndarray:
        """``h = Cx - d`` by stage, shape ``(B, N, 10)``."""
        return (self.Cb @ x.reshape(x.shape[0], -1, self.nb, 1))[..., 0] - self.db

    def Ct(self, v: np.ndarray) -> np.ndarray:
        """``C' v`` for ``v (B, N, 10)``, shape ``(B, nx)``."""
        return (self._CbT @ v[..., None]).reshape(v.shape[0], -1)

    def E(self, x: np.ndarray) -> np.ndarray:
        """The grid-relevant part ``(b_0..b_{N-1}, s_0..s_{N-1})`` of ``x (..., nx)``."""
        return np.concatenate([x[..., self.ib], x[..., self.is_]], axis=-1)

    def Et(self, v: np.ndarray) -> np.ndarray:
        """``E' v`` for ``v (B, 2N)``, shape ``(B, nx)``."""
        N = self.mpc.N
        out = np.zeros((v.shape[0], self.mpc.nx))
        out[:, self.ib], out[:, self.is_] = v[:, :N], v[:, N:]
        return out

    def feasible(self, A: np.ndarray, e: np.ndarray, x: np.ndarray) -> np.ndarray:
        """A point near ``x`` satisfying the dynamics and strictly inside every local bound:
        inputs kept where strictly inside their bounds, soc recomputed from the model, slacks
        raised only where needed (to at least 1e-3 above the soc band's bound, so that no
        barrier term starts at a vanishing distance from its bound)."""
        x = x.copy()
        margin = 1e-3 * self.U
        for i in (self.ib, self.is_):
            v = x[:, i]
            x[:, i] = np.where((v > 0) & (v < self.U), v, np.clip(v, margin, self.U - margin))
        rest = np.ones(x.shape[1], bool)
        rest[self.isoc] = False
        rhs = e - np.einsum("bri,bi->br", A[:, :, rest], x[:, rest])
        soc = np.linalg.solve(A[:, :, self.isoc], rhs[..., None])[..., 0]
        x[:, self.isoc] = soc
        for i, need in ((self.ihi, np.maximum(soc - self.soc_high, 0.0)),
                        (self.ilo, np.maximum(self.soc_low - soc, 0.0))):
            x[:, i] = np.where(x[:, i] >= need + 1e-3, x[:, i], need + 1e-3)
        return x

    def residual(self, Hd, q, A, e, x, lam, mu, tau):
        """Barrier KKT residual ``r_x (B, nx), r_g (B, N), r_c (B, N, 10)`` and ``h``;
        ``tau`` has shape ``(B,)``."""
        h = self.h(x)
        rx = Hd * x + q + (np.swapaxes(A, 1, 2) @ lam[..., None])[..., 0] + self.Ct(mu)
        rg = (A @ x[..., None])[..., 0] - e
        rc = mu * h + tau[:, None, None]
        return rx, rg, rc, h

    def newton(self, Hd, q, A, e, x, mu, h, tau):
        """The local Newton system, split by its dependence on a price step ``dlambda``.

        The primal-dual step with ``mu`` eliminated solves ``W dx + A' lam_new = -grad_phi
        - E' dlambda``, ``A dx = -r_g`` with ``W = H + C' diag(mu/-h) C`` and
        ``grad_phi = Hx + q + C' (tau/-h)``; its solution is ``dx = dx0 + X dlambda``,
        ``lam_new = lam0 + L dlambda``.

        Returns
        -------
        dx0 (B, nx), lam0 (B, N)
            The step at fixed prices.
        L (B, N, 2N), M (B, 2N, 2N)
            ``L`` as above and ``M = E X``, the response of ``(b, s)`` to the prices
            (symmetric negative semidefinite).
        Winv (B, N, 5, 5)
            The block inverses of ``W``, for :meth:`price_step`.
        """
        B, N, nb = x.shape[0], self.mpc.N, self.nb
        W = self._CbT @ ((mu / -h)[..., None] * self.Cb)  # (B, N, nb, nb)
        W[:, :, np.arange(nb), np.arange(nb)] += Hd.reshape(B, N, nb)
        Winv = np.linalg.inv(W)
        At = np.swapaxes(A, 1, 2)
        Ab = A.reshape(B, N, N, nb).transpose(0, 2, 1, 3)  # (B, block j, row r, k)
        AW = (Ab @ Winv).transpose(0, 2, 1, 3).reshape(B, N, -1)  # A W^{-1}, (B, N, nx)
        S = AW @ At
        rg = (A @ x[..., None])[..., 0] - e
        r1 = -(Hd * x + q + self.Ct(tau[:, None, None] / -h))
        lam0 = np.linalg.solve(S, ((AW @ r1[..., None])[..., 0] + rg)[..., None])[..., 0]
        dx0 = self._winv(Winv, r1 - (At @ lam0[..., None])[..., 0])
        # A W^{-1} E: the b_j and s_j columns of A W^{-1}; E W^{-1} E: 2x2 blocks of W^{-1}
        AWE = np.concatenate([AW[:, :, self.ib], AW[:, :, self.is_]], axis=2)  # (B, N, 2N)
        L = -np.linalg.solve(S, AWE)
        EWE = np.zeros((B, 2, N, 2, N))
        j = np.arange(N)
        for a in (0, 1):
            for b in (0, 1):
                EWE[:, a, j, b, j] = Winv[:, :, a, b]
        M = -(EWE.reshape(B, 2 * N, 2 * N) + np.swapaxes(AWE, 1, 2) @ L)
        return dx0, lam0, L, M, Winv

    def _winv(self, Winv: np.ndarray, v: np.ndarray) -> np.ndarray:
        """``W^{-1} v`` for ``v (B, nx)``."""
        B, N, nb = v.shape[0], self.mpc.N, self.nb
        return (Winv @ v.reshape(B, N, nb, 1)).reshape(B, -1)

    def price_step(self, A, L, Winv, dnu):
        """``X dlambda = -W^{-1} (E' dlambda + A' L dlambda)`` for ``dnu (B, 2N)``."""
        rhs = self.Et(dnu) + (np.swapaxes(A, 1, 2) @ (L @ dnu[..., None]))[..., 0]
        return -self._winv(Winv, rhs)


# -- coordinated solution ---------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class CoordinatedSolution:
    """The coordinated local MPCs of one hour, for a batch of days.

    Attributes
    ----------
    action : numpy.ndarray, shape ``(days, n)``
        The coordinated policy :math:`\\pi = (\\hat b^i_0 - \\hat s^i_0)_i` (after the fallback
        projection where coordination failed; 0 for a battery whose local solve failed).
    x, lam, mu, p : numpy.ndarray, shapes ``(days, n, nx)``, ``(days, n, N)``,
        ``(days, n, nin)``, ``(days, n, np)``
        Local primal-dual solutions and the local MPC parameters, whose price windows include
        the grid-capacity prices (each row is an exact solution of the local MPC at ``p``).
    success : numpy.ndarray of bool, shape ``(days, n)``
        The local problem was solved.
    price_buy, price_sell : numpy.ndarray, shape ``(days, N)``
        Grid-capacity prices :math:`\\lambda^b_j`, :math:`\\lambda^s_j` (cost per unit of
        power at stage ``j``, undiscounted; the centralized MPC's grid multipliers).
    iterations : numpy.ndarray of int, shape ``(days,)``
        Coordination rounds used.
    converged, projected : numpy.ndarray of bool, shape ``(days,)``
        The rounds met the tolerance; the fallback (local IPOPT + projection) was used.
    residual : numpy.ndarray, shape ``(days,)``
        Largest KKT residual at the end, relative to ``1 + max|q|``.
    violation : numpy.ndarray, shape ``(days,)``
        :math:`\\max(\\sum_i a_i^+, \\sum_i a_i^-)/\\bar P - 1` of the coordinated action before
        any projection (negative: the limit holds).
    planned_power : numpy.ndarray, shape ``(days,)``
        Largest planned :math:`\\max(\\sum_i \\hat b^i_j, \\sum_i \\hat s^i_j)` over the horizon.
    solve_time : float
        Wall time of the whole coordination in seconds.
    """

    action: np.ndarray
    x: np.ndarray
    lam: np.ndarray
    mu: np.ndarray
    p: np.ndarray
    success: np.ndarray
    price_buy: np.ndarray
    price_sell: np.ndarray
    iterations: np.ndarray
    converged: np.ndarray
    projected: np.ndarray
    residual: np.ndarray
    violation: np.ndarray
    planned_power: np.ndarray
    solve_time: float

    def local(self, i: int) -> BatchSolution:
        """Battery ``i``'s local solutions (one row per day) as a
        :class:`~mpcrl_lite.solvers.BatchSolution`."""
        days = self.x.shape[0]
        ok = self.success[:, i]
        return BatchSolution(
            action=np.where(ok, self.x[:, i, 0] - self.x[:, i, 1], 0.0)[:, None],
            x=self.x[:, i], lam=self.lam[:, i], mu=self.mu[:, i],
            cost=np.full(days, np.nan), success=ok.copy(),
            status=tuple("coordinated" if s else "local solve failed" for s in ok),
            iterations=self.iterations.copy(), p=self.p[:, i], solve_time=self.solve_time,
            backend="decentralized",
        )


class CoordinatedMPC:
    """The ``n`` local MPCs with their grid limit coordinated by prices (module docstring).

    Parameters
    ----------
    system : SystemConfig
        The whole system (``n`` batteries, the grid limit ``P_bar``).
    mpc_config : MPCConfig, optional
        ``tau`` of every barrier problem; ``tol`` of the fallback IPOPT solves (the back-end
        field is not used: the rounds are the decomposed interior-point iteration).
    coordination : CoordinationConfig, optional
    """

    def __init__(
        self,
        system: SystemConfig,
        mpc_config: MPCConfig | None = None,
        coordination: CoordinationConfig | None = None,
    ) -> None:
        if not isinstance(system, SystemConfig):
            raise ValueError(f"system={system!r}: expected a SystemConfig")
        self.system = system
        self.mpc_config = mpc_config or MPCConfig()
        self.coordination = coordination or CoordinationConfig()
        if not isinstance(self.coordination, CoordinationConfig):
            raise ValueError(f"coordination={coordination!r}: expected a CoordinationConfig")
        self.local_mpc = MPC(local_system(system, self.coordination.local_grid_factor))
        self._qp = _LocalQP(self.local_mpc)
        self._ipopt: IpoptSolver | None = None
        self._sensitivity: PolicySensitivity | None = None
        self._discount = system.gamma ** np.arange(system.N)

    @property
    def name(self) -> str:
        """Short description for logs and histories."""
        return f"decentralized(n={self.system.n}, tol={self.coordination.tol:g})"

    @property
    def ipopt(self) -> IpoptSolver:
        """The reference solver of the local MPC (fallback)."""
        if self._ipopt is None:
            self._ipopt = IpoptSolver(self.local_mpc, self.mpc_config.replace(backend="ipopt"))
        return self._ipopt

    def _thetas(self, thetas: Theta | Sequence[Theta]) -> list[Theta]:
        n = self.system.n
        if isinstance(thetas, Theta):
            if thetas.n != n:
                raise ValueError(f"theta has n={thetas.n}; expected n={n}")
            return split_theta(thetas)
        thetas = list(thetas)
        if len(thetas) != n or any(not isinstance(t, Theta) or t.n != 1 for t in thetas):
            raise ValueError(f"thetas: expected {n} Theta objects with n=1 (one per battery)")
        return thetas

    # -- one hour ---------------------------------------------------------------------------
    def solve(
        self,
        soc: np.ndarray,
        buy: np.ndarray,
        sell: np.ndarray,
        thetas: Theta | Sequence[Theta],
    ) -> CoordinatedSolution:
        """Coordinate the local MPCs of every day of the batch.

        Parameters
        ----------
        soc : array, shape ``(days, n)``
            Measured states of charge.
        buy, sell : array, shape ``(days, N)``
            Price windows (as from :meth:`Prices.window <mpcrl_lite.prices.Prices.window>`).
        thetas : Theta with ``n`` agents, or a sequence of ``n`` Theta with ``n = 1``

        Returns
        -------
        CoordinatedSolution
        """
        t0 = time.perf_counter()
        sysc, cfg, qp, mpc = self.system, self.coordination, self._qp, self.local_mpc
        n, N, P_bar, tau_t = sysc.n, sysc.N, sysc.P_bar, self.mpc_config.tau
        thetas = self._thetas(thetas)
        soc = np.asarray(soc, float)
        buy = np.asarray(buy, float)
        sell = np.asarray(sell, float)
        if soc.ndim != 2 or soc.shape[1] != n:
            raise ValueError(f"soc has shape {soc.shape}: expected (days, n) = (days, {n})")
        D = soc.shape[0]
        for label, w in (("buy", buy), ("sell", sell)):
            if w.shape != (D, N):
                raise ValueError(f"{label} has shape {w.shape}: expected (days, N) = ({D}, {N})")
        B = D * n  # problems ordered (day, battery), battery fastest
        P0 = np.stack([mpc.parameters(soc[:, i : i + 1], buy, sell, thetas[i])
                       for i in range(n)], axis=1).reshape(B, -1)
        Hd, q0, A, e = qp.data(P0)  # at zero grid prices
        scale = 1.0 + np.abs(q0).reshape(D, -1).max(1)

        # every hour starts cold and follows the barrier path from a large tau down to tau
        x = np.tile(self.ipopt.default_guess(), (B, 1))
        x[:, qp.ib] = x[:, qp.is_] = 0.25 * min(sysc.U_bar, P_bar / n)  # inside the limit
        lam = np.zeros((B, N))
        tau = np.full(D, max(tau_t, 1e-2 * float(scale.max())))
        x = qp.feasible(A, e, x)
        c = qp.E(x).reshape(D, n, -1).sum(1) - P_bar  # < 0: the guess is inside the limit
        h = qp.h(x)
        mu = np.repeat(tau, n)[:, None, None] / -h  # on the barrier path's centre
        nu = tau[:, None] / -c

        rounds = np.zeros(D, int)
        done = np.zeros(D, bool)
        worst = np.full(D, np.inf)

        def kkt(rows, x, lam, mu, nu, tau):
            """Residuals of the days owning ``rows``: per row and the coupling per day."""
            taur = np.repeat(tau, n)
            qeff = q0[rows] + qp.Et(np.repeat(nu, n, axis=0))
            rx, rg, rc, h = qp.residual(Hd[rows], qeff, A[rows], e[rows], x, lam, mu, taur)
            c = qp.E(x).reshape(-1, n, 2 * N).sum(1) - P_bar
            cc = nu * c + tau[:, None]
            local_sq = ((rx**2).sum(1) + (rg**2).sum(1) + (rc**2).sum((1, 2))).reshape(-1, n).sum(1)
            merit = np.sqrt(local_sq + (cc**2).sum(1))
            local_max = np.maximum.reduce([np.abs(rx).max(1), np.abs(rg).max(1),
                                           np.abs(rc).max((1, 2))]).reshape(-1, n).max(1)
            return merit, np.maximum(local_max, np.abs(cc).max(1)), qeff, rc, h, c, cc

        def direction_of(rows, xa, la, ma, na, ta, qeff, rc, h, c):
            """The Newton direction ``(dx, dlam, dmu, dnu)`` of the days owning ``rows``."""
            # 1. local Newton systems, split by their price dependence
            dx0, lam0, L, M, Winv = qp.newton(Hd[rows], qeff, A[rows], e[rows], xa, ma, h,
                                              np.repeat(ta, n))
            # 2. the coordinator's price step, per day
            Mtot = M.reshape(-1, n, 2 * N, 2 * N).sum(1)
            Edx0 = qp.E(dx0).reshape(-1, n, 2 * N).sum(1)
            K = Mtot + np.einsum("dm,mk->dmk", c / na, np.eye(2 * N))
            dnu = np.linalg.solve(K, (-(c + ta[:, None] / na) - Edx0)[..., None])[..., 0]
            # 3. every battery's step given the price step
            dnu_r = np.repeat(dnu, n, axis=0)
            dx = dx0 + qp.price_step(A[rows], L, Winv, dnu_r)
            dlam = lam0 + (L @ dnu_r[..., None])[..., 0] - la
            dh = qp.h(dx) + qp.db
            dmu = -(rc + ma * dh) / h
            return dx, dlam, dmu, dnu

        def direction(rows, xa, la, ma, na, ta, qeff, rc, h, c):
            """:func:`direction_of` for every day, and which days have a finite direction
            (their Newton systems solved); the others get a zero direction."""
            D_a = na.shape[0]
            try:
                with np.errstate(all="ignore"):
                    out = direction_of(rows, xa, la, ma, na, ta, qeff, rc, h, c)
            except np.linalg.LinAlgError:
                out = None  # one day's system is singular: solve them day by day
            if out is None:
                out = (np.zeros_like(xa), np.zeros((xa.shape[0], N)), np.zeros_like(ma),
                       np.zeros_like(na))
                for k in range(D_a):
                    r = slice(k * n, (k + 1) * n)
                    try:
                        with np.errstate(all="ignore"):
                            part = direction_of(rows[r], xa[r], la[r], ma[r], na[k : k + 1],
                                                ta[k : k + 1], qeff[r], rc[r], h[r], c[k : k + 1])
                    except np.linalg.LinAlgError:
                        part = None
                    if part is not None:
                        for full, piece in zip(out[:3], part[:3]):
                            full[r] = piece
                        out[3][k] = part[3][0]
                    else:
                        out[3][k] = np.nan  # marks the day as failed below
            dx, dlam, dmu, dnu = out
            ok = (np.isfinite(dnu).all(1)
                  & np.isfinite(dx).reshape(D_a, -1).all(1)
                  & np.isfinite(dlam).reshape(D_a, -1).all(1)
                  & np.isfinite(dmu).reshape(D_a, -1).all(1))
            okr = np.repeat(ok, n)
            dx = np.where(okr[:, None], dx, 0.0)
            dlam = np.where(okr[:, None], dlam, 0.0)
            dmu = np.where(okr[:, None, None], dmu, 0.0)
            dnu = np.where(ok[:, None], dnu, 0.0)
            return (dx, dlam, dmu, dnu), ok

        stopped = np.zeros(D, bool)  # singular Newton system: no more rounds, fallback
        for _ in range(cfg.max_iter + 1):
            days = np.flatnonzero(~done & ~stopped)
            if days.size == 0:
                break
            rows = (days[:, None] * n + np.arange(n)).ravel()
            xa, la, ma, na, ta = x[rows], lam[rows], mu[rows], nu[days], tau[days]
            merit, wmax, qeff, rc, h, c, cc = kkt(rows, xa, la, ma, na, ta)
            worst[days] = wmax / scale[days]
            finished = (ta <= tau_t) & (worst[days] <= cfg.tol)
            done[days[finished]] = True
            if finished.all() or rounds[days].min() >= cfg.max_iter:
                break
            if finished.any():
                continue  # step only the days still running
            # move tau down the barrier path once a point is centred for its tau
            lower = (ta > tau_t) & (wmax <= 0.1 * ta * scale[days])
            if lower.any():
                ta = np.where(lower, np.maximum(tau_t, 0.1 * ta), ta)
                merit, wmax, qeff, rc, h, c, cc = kkt(rows, xa, la, ma, na, ta)
            # 1.-3. the Newton direction: local systems, price step, every battery's step
            step, ok = direction(rows, xa, la, ma, na, ta, qeff, rc, h, c)
            if not ok.all():
                # a singular or non-finite Newton system: that day's rounds stop here, and
                # it takes the fallback (local IPOPT solves and projection) in _finish
                for d in days[~ok]:
                    log.info("coordination stopped (day %d): singular or non-finite Newton "
                             "system", d)
                stopped[days[~ok]] = True
            dx, dlam, dmu, dnu = step
            dh = qp.h(dx) + qp.db
            dc = qp.E(dx).reshape(-1, n, 2 * N).sum(1)
            with np.errstate(divide="ignore", invalid="ignore"):
                limits = [
                    np.where(dh > 0, -h / dh, np.inf).min((1, 2)).reshape(-1, n).min(1),
                    np.where(dmu < 0, -ma / dmu, np.inf).min((1, 2)).reshape(-1, n).min(1),
                    np.where(dc > 0, -c / dc, np.inf).min(1),
                    np.where(dnu < 0, -na / dnu, np.inf).min(1),
                ]
            t = np.where(ok, np.minimum(1.0, 0.995 * np.minimum.reduce(limits)), 0.0)
            for _ in range(40):  # backtracking on the total KKT residual
                tr = np.repeat(t, n)
                xn, ln = xa + tr[:, None] * dx, la + tr[:, None] * dlam
                mn, nn = ma + tr[:, None, None] * dmu, na + t[:, None] * dnu
                merit_new = kkt(rows, xn, ln, mn, nn, ta)[0]
                bad = ~(merit_new <= (1.0 - 1e-4 * t) * merit)
                if not bad.any():
                    break
                t = np.where(bad, 0.5 * t, t)
            x[rows], lam[rows], mu[rows], nu[days], tau[days] = xn, ln, mn, nn, ta
            rounds[days[ok]] += 1

        return self._finish(soc, buy, sell, thetas, x, lam, mu.reshape(B, -1), nu, rounds,
                            done, worst, t0)

    def _finish(self, soc, buy, sell, thetas, x, lam, mu, nu, rounds, done, worst, t0):
        """Outputs, and the fallback for days whose rounds did not converge."""
        sysc, mpc, qp = self.system, self.local_mpc, self._qp
        n, N, D = sysc.n, sysc.N, soc.shape[0]
        buy_p = buy + nu[:, :N] / self._discount
        sell_p = sell - nu[:, N:] / self._discount
        Pp = np.stack([mpc.parameters(soc[:, i : i + 1], buy_p, sell_p, thetas[i])
                       for i in range(n)], axis=1)
        X = x.reshape(D, n, -1).copy()
        Lm = lam.reshape(D, n, -1).copy()
        Mu = mu.reshape(D, n, -1).copy()
        ok = np.ones((D, n), bool)
        for d in np.flatnonzero(~done):
            log.info("coordination did not converge (day %d, residual %.1e): local IPOPT "
                     "solves at the last prices and projection", d, worst[d])
            for i in range(n):
                sol = self.ipopt.solve(soc[d, i : i + 1], buy_p[d], sell_p[d], thetas[i])
                ok[d, i] = sol.success
                if sol.success:
                    X[d, i], Lm[d, i], Mu[d, i] = sol.x, sol.lam, sol.mu
        action = np.where(ok, X[:, :, 0] - X[:, :, 1], 0.0)
        pos, neg = np.maximum(action, 0).sum(1), np.maximum(-action, 0).sum(1)
        violation = np.maximum(pos, neg) / sysc.P_bar - 1.0
        projected = ~done
        if projected.any():
            action[projected] = project_action(action[projected], sysc)
        planned = np.maximum(X[:, :, qp.ib].sum(1), X[:, :, qp.is_].sum(1)).max(1)
        return CoordinatedSolution(
            action=action, x=X, lam=Lm, mu=Mu, p=Pp, success=ok,
            price_buy=nu[:, :N].copy(), price_sell=nu[:, N:].copy(), iterations=rounds,
            converged=done.copy(), projected=projected, residual=worst.copy(),
            violation=violation, planned_power=planned, solve_time=time.perf_counter() - t0,
        )

    # -- sensitivities ----------------------------------------------------------------------
    def sensitivity(self, solution: CoordinatedSolution) -> tuple[np.ndarray, np.ndarray]:
        """:math:`\\nabla_{\\theta^i}\\pi^i` of every battery, at fixed grid prices.

        Returns
        -------
        grad : numpy.ndarray, shape ``(days, n, 10)``
            Row ``[d, i]`` is the derivative of battery ``i``'s action with respect to its own
            ``theta^i`` (flat order of :meth:`Theta.to_vector`); zeros where ``ok`` is False.
        ok : numpy.ndarray of bool, shape ``(days, n)``
        """
        if self._sensitivity is None:
            self._sensitivity = PolicySensitivity(self.local_mpc, self.mpc_config)
        D, n = solution.action.shape
        grad = np.zeros((D, n, self.local_mpc.n_theta))
        ok = np.zeros((D, n), bool)
        for i in range(n):
            sens = self._sensitivity(solution.local(i))
            grad[:, i] = sens.grad[:, :, 0]
            ok[:, i] = sens.ok
        return grad, ok


# -- a month in closed loop -------------------------------------------------------------------
@dataclass(eq=False)
class DecentralizedMonth:
    """What a decentralized month adds to its :class:`~mpcrl_lite.history.MonthRecord`.

    Arrays have a leading ``(H, D)`` (hours, days); ``n`` batteries.

    Attributes
    ----------
    grad_pi : numpy.ndarray, shape ``(H, D, n, 10)`` or None
        :math:`\\nabla_{\\theta^i}\\pi^i` at fixed grid prices.
    sens_ok, solver_ok : numpy.ndarray of bool, shape ``(H, D, n)``
    iterations : numpy.ndarray of int, shape ``(H, D)``
        Coordination rounds.
    converged, projected : numpy.ndarray of bool, shape ``(H, D)``
    violation : numpy.ndarray, shape ``(H, D)``
        Relative excess of the coordinated action over the grid limit before projection.
    price_max : numpy.ndarray, shape ``(H, D)``
        Largest grid-capacity price of the hour (over stages, buy and sell).
    solve_time : numpy.ndarray, shape ``(H,)``
        Wall time of each hour's coordination (all days).
    """

    grad_pi: np.ndarray | None
    sens_ok: np.ndarray
    solver_ok: np.ndarray
    iterations: np.ndarray
    converged: np.ndarray
    projected: np.ndarray
    violation: np.ndarray
    price_max: np.ndarray
    solve_time: np.ndarray

    def summary(self, tol: float) -> dict[str, Any]:
        """Per-month coordination figures (JSON-friendly)."""
        return {
            "iterations_mean": float(self.iterations.mean()),
            "iterations_max": int(self.iterations.max()),
            "not_converged": int(np.count_nonzero(~self.converged)),
            "projected": int(np.count_nonzero(self.projected)),
            "limit_violations": int(np.count_nonzero(self.violation > tol)),
            "max_violation": float(self.violation.max()),
            "price_max": float(self.price_max.max()),
            "solve_time_s": float(self.solve_time.sum()),
            "tol": float(tol),
        }


def run_month_decentralized(
    thetas: Theta | Sequence[Theta],
    policy: CoordinatedMPC,
    prices: Prices,
    system: SystemConfig,
    rng: np.random.Generator,
    exploration_std: float = 0.0,
    sensitivities: bool = True,
    soc0: float | np.ndarray | None = None,
) -> tuple[MonthRecord, DecentralizedMonth]:
    """One month in closed loop with the coordinated local MPCs.

    The counterpart of :func:`mpcrl_lite.closed_loop.run_month` (the same loop,
    :func:`~mpcrl_lite.closed_loop.simulate`), with the same draws in the same order (per
    hour: exploration ``(days, n)`` if ``exploration_std > 0``, then noise ``(days, n)``).

    Parameters
    ----------
    thetas : Theta with ``n`` agents, or ``n`` Theta with ``n = 1``
    policy : CoordinatedMPC
    prices : Prices
        ``prices.days`` days advancing together.
    system : SystemConfig
    rng : numpy.random.Generator
    exploration_std : float
        Std of the Gaussian exploration added to each battery's action (then projected
        jointly onto the input bounds and the grid limit).
    sensitivities : bool
        Compute :math:`\\nabla_{\\theta^i}\\pi^i` (needed for learning).
    soc0 : float or array, optional
        Start-of-day soc (default ``system.soc0``), scalar, ``(n,)`` or ``(days, n)``.

    Returns
    -------
    record : MonthRecord
        As in the centralized experiment (``solver_ok``/``sens_ok`` are True where every
        battery's local problem / sensitivity was fine; ``grad_pi`` is None).
    extra : DecentralizedMonth
    """
    D, H, n, N = prices.days, system.hours_per_day, system.n, system.N
    solver_ok = np.zeros((H, D, n), bool)
    sens_ok = np.zeros((H, D, n), bool)
    grad_pi = np.zeros((H, D, n, 10)) if sensitivities else None
    iters = np.zeros((H, D), int)
    conv, proj = np.zeros((H, D), bool), np.zeros((H, D), bool)
    viol, pmax = np.zeros((H, D)), np.zeros((H, D))
    times = np.zeros(H)

    def decide(k: int, soc: np.ndarray) -> Decision:
        buy_w, sell_w = prices.window(k, N)
        sol = policy.solve(soc, buy_w, sell_w, thetas)
        solver_ok[k] = sol.success
        iters[k], conv[k], proj[k] = sol.iterations, sol.converged, sol.projected
        viol[k] = sol.violation
        pmax[k] = np.maximum(sol.price_buy.max(1), sol.price_sell.max(1))
        times[k] = sol.solve_time
        if sensitivities:
            grad_pi[k], sens_ok[k] = policy.sensitivity(sol)
        return Decision(sol.action, solver_ok[k].all(-1), sol.planned_power, sens_ok[k].all(-1))

    explore = GaussianExploration(exploration_std, system) if exploration_std > 0 else None
    record = MonthRecord.from_record(simulate(
        decide, prices.buy[:, :H], prices.sell[:, :H], system, rng=rng, soc0=soc0, explore=explore
    ))
    extra = DecentralizedMonth(grad_pi, sens_ok, solver_ok, iters, conv, proj, viol, pmax, times)
    return record, extra


# -- the learning experiment ------------------------------------------------------------------
class DecentralizedExperiment:
    """Decentralized learning run with the interface of :class:`~mpcrl_lite.experiment.Experiment`.

    Every month all batteries act with their coordinated local MPCs; at the month's end each
    battery fits its own compatible critic (LSTD on :math:`\\tilde L_i`, value features of
    :math:`soc_i`) and takes its own DPG step on :math:`\\theta^i`. The results go into a
    :class:`~mpcrl_lite.history.History` (theta per month is the stacked
    :func:`join_theta`, so every plot works); ``History.update_info`` holds per month the
    coordination figures (``"coordination"``: mean/max rounds, projections, limit
    violations, largest price) and each battery's critic/actor diagnostics (``"agents"``).

    Parameters
    ----------
    system, mpc_config, learning
        As for :class:`~mpcrl_lite.experiment.Experiment` (defaults: the paper's).
    prices : Prices, optional
        Default: the embedded month, ``learning.days_per_month`` days.
    theta0 : Theta, optional
        Initial parameters with ``n`` agents (default :meth:`Theta.nominal`), split into the
        batteries' ``theta^i``.
    coordination : CoordinationConfig, optional
    callbacks : sequence of callables ``callback(month, history, experiment)``
    """

    def __init__(
        self,
        system: SystemConfig | None = None,
        mpc_config: MPCConfig | None = None,
        learning: LearningConfig | None = None,
        prices: Prices | None = None,
        theta0: Theta | None = None,
        coordination: CoordinationConfig | None = None,
        callbacks: Sequence[Callable[[int, History, "DecentralizedExperiment"], None]] = (),
    ) -> None:
        self.system, self.mpc_config, self.learning, self.prices, theta0 = resolve_setup(
            system, mpc_config, learning, prices, theta0
        )
        self.coordination = coordination or CoordinationConfig()
        self.thetas = split_theta(theta0)
        self.callbacks = list(callbacks)
        self.policy = CoordinatedMPC(self.system, self.mpc_config, self.coordination)
        local = self.policy.local_mpc.system
        self.updaters = [DPGUpdater.from_configs(self.learning, local)
                         for _ in range(self.system.n)]
        self.rng = np.random.default_rng(self.learning.seed)
        self.history = History(self.system, self.mpc_config, self.learning, backend=self.backend)

    @property
    def backend(self) -> str:
        """Name recorded in the History."""
        return f"decentralized(n={self.system.n}, tol={self.coordination.tol:g})"

    @property
    def theta(self) -> Theta:
        """The batteries' current parameters stacked into one :class:`Theta`."""
        return join_theta(self.thetas)

    # -- one learning step ----------------------------------------------------------------
    def learning_step(
        self, record: MonthRecord, extra: DecentralizedMonth
    ) -> tuple[list[np.ndarray], int, list[dict[str, Any]]]:
        """Each battery's LSTD fit and policy gradient; returns ``(grads, skipped, infos)``
        with ``grads[i]`` of shape ``(10,)``."""
        sysc = self.system
        H = sysc.hours_per_day
        done = np.broadcast_to((np.arange(H) == H - 1)[:, None], record.stage_cost.shape)
        grads, infos = [], []
        any_skipped = np.zeros(record.stage_cost.shape, bool)
        for i in range(sysc.n):
            use = extra.sens_ok[..., i] & extra.solver_ok[..., i]
            any_skipped |= ~use
            if not use.any():
                grads.append(np.zeros(10))
                infos.append({"lstd": "no usable samples"})
                continue
            features = value_baseline_features(record.soc[..., i : i + 1], self.learning.value_features)
            phi, phi_next = features[:-1], features[1:]
            g_pi = extra.grad_pi[:, :, i, :, None]  # (H, D, 10, 1)
            psi = compatible_features(g_pi, record.a[..., i : i + 1], record.policy[..., i : i + 1])
            fit = lstd_q(
                phi[use], psi[use], record.agent_cost[..., i][use], phi_next[use], sysc.gamma,
                done=done[use], ridge=self.learning.ridge,
            )
            grads.append(policy_gradient(g_pi[use], fit.w))
            infos.append({
                "lstd_condition": float(fit.condition),
                "lstd_rank_deficient": bool(fit.rank_deficient),
                "td_rms": float(fit.td_rms),
                "samples": int(fit.n_samples),
            })
        return grads, int(np.count_nonzero(any_skipped)), infos

    def run_one_month(self) -> MonthRecord:
        """Simulate one month with the current parameters and update every battery."""
        t0 = time.perf_counter()
        used = list(self.thetas)
        record, extra = run_month_decentralized(
            used, self.policy, self.prices, self.system, self.rng,
            exploration_std=self.learning.exploration_std, sensitivities=True,
        )
        grads, skipped, infos = self.learning_step(record, extra)
        n = self.system.n
        full_grad = np.zeros(10 * n)
        for i in range(n):
            self.thetas[i] = self.updaters[i].step(used[i], grads[i])
            infos[i].update(self.updaters[i].last_info)
            full_grad[i::n] = grads[i]  # part-major order of Theta.to_vector
        info = {"coordination": extra.summary(self.coordination.tol), "agents": infos}
        info = json.loads(json.dumps(info, default=_jsonable))
        self.history.append(record, join_theta(used), full_grad, skipped,
                            time.perf_counter() - t0, info)
        self.history.theta_final = self.theta.to_vector().tolist()
        return record

    def run(
        self,
        months: int | None = None,
        out: str | Path | None = None,
        resume: bool = False,
        progress: bool = True,
    ) -> History:
        """Run until ``months`` months are recorded (default ``learning.months``); with
        ``out`` a checkpoint is written after every month, with ``resume`` a run found in
        ``out`` continues where it stopped (same results as an uninterrupted run)."""
        return run_months(self, months, out, resume, progress, desc="learning (decentralized)")

    # -- checkpoints ----------------------------------------------------------------------
    def save_checkpoint(self, directory: str | Path) -> None:
        """History plus everything needed to continue (thetas, optimizers, RNG state)."""
        directory = Path(directory)
        self.history.save(directory)
        state = {
            "format": _FORMAT,
            "months_done": self.history.months,
            "theta": self.theta.to_vector().tolist(),
            "updaters": [u.state_dict() for u in self.updaters],
            "rng": self.rng.bit_generator.state,
            "system": self.system.to_dict(),
            "mpc": self.mpc_config.to_dict(),
            "learning": self.learning.to_dict(),
            "coordination": self.coordination.to_dict(),
        }
        write_checkpoint(directory, state)

    def load_checkpoint(self, directory: str | Path) -> None:
        """Continue from :meth:`save_checkpoint`'s files; the configs must match."""
        directory = Path(directory)
        state = json.loads((directory / CHECKPOINT).read_text())
        if state.get("format") != _FORMAT:
            raise ValueError(
                f"{directory / CHECKPOINT}: format {state.get('format')!r}, expected {_FORMAT!r} "
                "(a centralized run? use Experiment to resume it)"
            )
        pairs = (("system", self.system), ("mpc", self.mpc_config), ("learning", self.learning),
                 ("coordination", self.coordination))
        for key, cfg in pairs:
            saved = type(cfg).from_dict(state[key])
            mine = cfg if key != "learning" else cfg.replace(months=saved.months)
            if saved != mine:
                raise ValueError(
                    f"checkpoint in {directory} was written with a different {key} config: "
                    f"{saved} vs {cfg}"
                )
        self.history = History.load(directory)
        self.thetas = split_theta(Theta.from_vector(np.asarray(state["theta"]), self.system.n))
        for updater, s in zip(self.updaters, state["updaters"]):
            updater.load_state_dict(s)
        self.rng.bit_generator.state = state["rng"]
        self.history.backend = self.backend


def _jsonable(value: Any) -> Any:
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    raise TypeError(f"cannot store {type(value).__name__} in JSON")


# -- centralized vs decentralized ----------------------------------------------------------
def compare_learners(
    system: SystemConfig | None = None,
    mpc_config: MPCConfig | None = None,
    learning: LearningConfig | None = None,
    months: int = 2,
    coordination: CoordinationConfig | None = None,
    progress: bool = False,
) -> dict[str, Any]:
    """Run the centralized and the decentralized learner on the same configuration.

    Both start from :meth:`Theta.nominal`, use the same prices and seed (hence the same
    noise) and run ``months`` months of ``learning.days_per_month`` days.

    Returns
    -------
    dict
        ``{"centralized": {...}, "decentralized": {...}, "settings": {...}}``; each learner
        has ``J`` and ``J_per_agent`` per month, ``hours_soc_below_0_1``, the largest
        commanded and applied grid power, ``limit_violations`` (hours x days whose
        commanded action exceeds ``P_bar (1 + tol)``), ``wall_time_s`` per month and
        ``ms_per_step`` (one control step: all days of one hour, sensitivities and the
        month-end update included, i.e. month wall time / hours) and ``theta_final`` (as
        :meth:`Theta.to_dict`; the decentralized one is the stacked :func:`join_theta`, whose
        centralized MPC has the same policy). The decentralized entry also holds the
        coordination figures per month.
    """
    system = system or SystemConfig()
    mpc_config = mpc_config or MPCConfig()
    learning = learning or LearningConfig()
    coordination = coordination or CoordinationConfig()
    check_int("months", months, 1)
    learning = learning.replace(months=months)
    runs = {
        "centralized": Experiment(system, mpc_config, learning),
        "decentralized": DecentralizedExperiment(system, mpc_config, learning,
                                                 coordination=coordination),
    }
    result: dict[str, Any] = {
        "settings": {
            "system": system.to_dict(), "mpc": mpc_config.to_dict(),
            "learning": learning.to_dict(), "coordination": coordination.to_dict(),
        }
    }
    tol = coordination.tol
    for name, exp in runs.items():
        commanded: list[float] = []
        violations: list[int] = []

        def watch(month: int, history: History, _exp: Any) -> None:
            a = history.last_month.a
            power = np.maximum(np.maximum(a, 0).sum(-1), np.maximum(-a, 0).sum(-1))
            commanded.append(float(power.max()))
            violations.append(int(np.count_nonzero(power > system.P_bar * (1 + tol))))

        exp.callbacks.append(watch)
        history = exp.run(months=months, progress=progress)
        H = system.hours_per_day
        entry = {
            "backend": history.backend,
            "J": list(history.J),
            "J_per_agent": list(history.J_per_agent),
            "hours_soc_below_0_1": list(history.hours_soc_below_0_1),
            "max_P_commanded": commanded,
            "max_P_applied": list(history.max_P_applied),
            "limit_violations": violations,
            "wall_time_s": list(history.wall_time_s),
            "ms_per_step": [1000 * t / H for t in history.wall_time_s],
            "skipped_steps": list(history.skipped_steps),
            "theta_final": history.final_theta().to_dict(),
        }
        if name == "decentralized":
            entry["coordination"] = [info["coordination"] for info in history.update_info]
        result[name] = entry
    return result
