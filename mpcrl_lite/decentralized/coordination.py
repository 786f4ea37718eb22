r"""The batteries' local MPCs, their shared grid limit coordinated by prices.

Every battery ``i`` has its own MPC -- the paper's MPC (eq. 9) with ``n = 1``
(:func:`~mpcrl_lite.decentralized.local_qp.local_system`) -- and its own parameters :math:`\theta^i`
(:func:`split_theta`). The batteries share the grid: the limits
:math:`\sum_i \hat b^i_j \le \bar P` and :math:`\sum_i \hat s^i_j \le \bar P` (eq. 9f, at every
predicted stage ``j``) couple them. They are coordinated at every hour by **prices**: a
grid-capacity price :math:`\lambda^b_j \ge 0` on buying and :math:`\lambda^s_j \ge 0` on
selling, per stage, is added to every local cost,

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
(:math:`\bar P \ge \sum_i \bar U^i`, each battery's own input bound :math:`\bar U^i`) the
prices settle at :math:`\lambda_j = \tau/(\bar P - \sum_i \hat b^i_j) \le \tau/(\bar P -
\sum_i \bar U^i)`: zero up to the barrier, and the local problems are independent.

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
   response to a price change, :math:`X_i = \partial\Delta x_i/\partial\lambda`
   (:meth:`LocalQP.newton <mpcrl_lite.decentralized.local_qp.LocalQP.newton>`); it sends the coordinator
   :math:`E\Delta x_i^0`, :math:`M_i = E X_i` (``2N x 2N``, negative semidefinite) and its
   current :math:`E x_i = (\hat b^i, \hat s^i)`;
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
``tau`` down to the MPC's ``tau`` (on the paper's system, the 24 hours of 30 days at the states
of a learning month: 11.5 rounds per day and hour on average for ``n = 3``, 8 to 15, and 12.8
for ``n = 20``, 11 to 17; starting from the previous hour's shifted solution saved less than one
round on average and occasionally stalled, so it is not done).

* **Tolerance.** Rounds stop when every KKT residual (local stationarity, dynamics, local and
  grid complementarity) is at most ``tol * (1 + max |q|)``, ``q`` the local linear costs
  (:class:`~mpcrl_lite.config.CoordinationConfig`, default ``tol = 1e-11``, i.e. ~1e-9
  NOK/MWh on the paper's prices). The number of rounds is recorded.
* **The limit.** The iterates stay strictly inside the grid limit (the barrier iteration
  never leaves it), so :math:`\sum_i \hat b^i_j < \bar P` holds at *every* round, converged
  or not, and the recorded ``violation`` is negative; only the fallback's independent local
  solves can exceed the limit, which is why their joint action is projected.
* **Failure.** If a day does not converge within ``max_iter`` rounds, or its Newton system
  is singular or not finite (the day's rounds then stop there), each battery solves its
  own MPC with the reference IPOPT back-end at the last prices, and the joint action is
  projected onto the grid limit with :func:`~mpcrl_lite.system.battery.project_action`; the hour is
  recorded as projected. A battery whose solve fails idles (the fallback of
  :mod:`mpcrl_lite.mpc.backends.registry`).

The sensitivity :math:`\nabla_{\theta^i}\pi^i` of each battery is that of its local MPC at
the final, fixed grid prices (:meth:`CoordinatedMPC.sensitivity`); the learner built on it is
:mod:`mpcrl_lite.decentralized.learner`.

Compiled and reference rounds
-----------------------------
The rounds run either vectorized over the days in numpy (this module's ``_round``: the
reference) or compiled, day by day (:func:`mpcrl_lite.decentralized.coordination_kernel.coordinate`, numba):
the same iteration -- same start, Newton directions, step lengths, line search, ``tau``
path, stopping rule and fallback -- so both give the same rounds and the same local
solutions to rounding (tested to 1e-9). The sensitivities follow: the compiled path
differentiates every local problem in one call of the compiled interior point's adjoint
(:meth:`KernelSolver.sensitivity <mpcrl_lite.mpc.backends.kernel.KernelSolver.sensitivity>`: the
local problem at the final prices *is* an ``n = 1`` MPC), the reference with
:class:`~mpcrl_lite.mpc.sensitivity.PolicySensitivity` (CasADi), problem by problem.
``MPCConfig.backend`` chooses, as it chooses the centralized MPC's back-end:

* ``'auto'`` (default): compiled when every :math:`\theta^i` makes the local MPC a convex QP
  (:meth:`Theta.is_convex <mpcrl_lite.theta.Theta.is_convex>`), else the reference;
* ``'kernel'``: compiled;
* ``'batch'``, ``'ipopt'``: the reference (the fallback's local solves use IPOPT whatever the
  choice).

On the paper's system with ``n = 20`` batteries (30 days, ~12 rounds per hour) a learning
month of the decentralized learner took 2.4 s of CPU with the compiled path (the rounds
1.4 s, the sensitivities 0.05 s, the learners' month-end fits 0.35 s) against 19 s with the
reference, measured in the same run (``benchmarks/bench_decentralized.py``).

Why one module of ~750 lines: about 130 of them are this description; the rest is one
algorithm, the rounds above (residual, decomposed Newton step, coordinator step, line search,
barrier path, stopping rule, fallback), whose parts share the per-hour state
(:class:`_Hour`, :class:`_Point`) and make sense only together. The local problems
(:mod:`~mpcrl_lite.decentralized.local_qp`) and the compiled rounds
(:mod:`~mpcrl_lite.decentralized.coordination_kernel`) are modules of their own.

Example
-------
>>> from mpcrl_lite import SystemConfig, Theta
>>> from mpcrl_lite.decentralized.coordination import CoordinatedMPC
>>> from mpcrl_lite.system.prices import Prices
>>> system = SystemConfig()
>>> buy, sell = Prices.month(system, 2).window(18, system.N)
>>> sol = CoordinatedMPC(system).solve([[0.2, 0.5, 0.8]] * 2, buy, sell, Theta.nominal(system))
>>> bool(sol.converged.all()), bool((sol.planned_power < system.P_bar).all())
(True, True)
"""

from __future__ import annotations

import logging
import time
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import NamedTuple

import numpy as np

from .._util.threads import auto_threads, run_blocks
from ..config import CoordinationConfig, MPCConfig, SystemConfig
from ..mpc.backends.ipopt import IpoptSolver
from ..mpc.backends.kernel import KernelSolver
from ..mpc.backends.registry import AUTO
from ..mpc.formulation import MPC
from ..mpc.sensitivity import PolicySensitivity
from ..mpc.solution import BatchSolution
from ..system.battery import project_action
from ..theta import PARTS, Theta
from . import coordination_kernel as _coord_kernel
from .local_qp import LocalQP, local_system

__all__ = ["CoordinatedMPC", "CoordinatedSolution", "join_theta", "split_theta"]

log = logging.getLogger(__name__)


# -- theta per battery ------------------------------------------------------------------------
def split_theta(theta: Theta) -> list[Theta]:
    """The ``n`` local parameter sets of a centralized ``theta`` (each with ``n = 1``)."""
    if not isinstance(theta, Theta):
        raise ValueError(f"theta={theta!r}: expected a Theta")  # noqa: TRY004
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
    compiled : bool
        The rounds ran compiled (:meth:`CoordinatedMPC.compiled`); the sensitivities then
        do too.
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
    compiled: bool = False

    def local(self, i: int) -> BatchSolution:
        """Battery ``i``'s local solutions (one row per day) as a
        :class:`~mpcrl_lite.mpc.backends.registry.BatchSolution`."""
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


# -- the rounds' data -------------------------------------------------------------------------
# Problems (rows) are ordered (day, battery), battery fastest: ``B = days * n`` rows. A subset
# of ``K`` days owns the ``R = K * n`` rows ``day * n + i``.
@dataclass(frozen=True, eq=False)
class _Hour:
    """One hour's local problems at zero grid prices (data of :meth:`LocalQP.data`)."""

    Hd: np.ndarray  # (B, nx)
    q0: np.ndarray  # (B, nx)
    A: np.ndarray  # (B, N, nx)
    e: np.ndarray  # (B, N)
    scale: np.ndarray  # (D,): 1 + max |q| of the day, the scale of the tolerance


@dataclass(frozen=True, eq=False)
class _Point:
    """A primal-dual point: ``x (R, nx)``, ``lam (R, N)``, ``mu (R, N, 10)`` per problem, the
    grid prices ``nu = (lambda^b, lambda^s) (K, 2N)`` and the barrier parameter ``tau (K,)``
    per day."""

    x: np.ndarray
    lam: np.ndarray
    mu: np.ndarray
    nu: np.ndarray
    tau: np.ndarray

    def take(self, rows: np.ndarray | slice, days: np.ndarray | slice) -> _Point:
        return _Point(self.x[rows], self.lam[rows], self.mu[rows], self.nu[days], self.tau[days])

    def put(self, rows: np.ndarray, days: np.ndarray, point: _Point) -> None:
        self.x[rows], self.lam[rows], self.mu[rows] = point.x, point.lam, point.mu
        self.nu[days], self.tau[days] = point.nu, point.tau


class _Residual(NamedTuple):
    """The barrier KKT residuals of a point (:meth:`CoordinatedMPC._kkt`)."""

    merit: np.ndarray  # (K,): 2-norm of all residuals of the day
    worst: np.ndarray  # (K,): largest absolute residual of the day
    qeff: np.ndarray  # (R, nx): local linear costs with the grid prices
    rc: np.ndarray  # (R, N, 10): local relaxed complementarity mu h + tau
    h: np.ndarray  # (R, N, 10): local inequality rows, < 0
    c: np.ndarray  # (K, 2N): grid rows sum_i E x_i - P_bar, < 0

    def take(self, rows: slice, days: slice) -> _Residual:
        return _Residual(self.merit[days], self.worst[days], self.qeff[rows], self.rc[rows],
                         self.h[rows], self.c[days])


class _Step(NamedTuple):
    """A Newton direction, shaped like :class:`_Point` (``tau`` has none)."""

    dx: np.ndarray
    dlam: np.ndarray
    dmu: np.ndarray
    dnu: np.ndarray


@dataclass(eq=False)
class _Rounds:
    """Every day's point and progress over the rounds of one hour."""

    point: _Point
    days: int
    rounds: np.ndarray = field(init=False)  # (D,) rounds taken
    done: np.ndarray = field(init=False)  # (D,) converged
    stopped: np.ndarray = field(init=False)  # (D,) singular Newton system: fallback
    worst: np.ndarray = field(init=False)  # (D,) last relative residual

    def __post_init__(self) -> None:
        D = self.days
        self.rounds = np.zeros(D, int)
        self.done = np.zeros(D, bool)
        self.stopped = np.zeros(D, bool)
        self.worst = np.full(D, np.inf)


#: days per call of the compiled rounds (:meth:`CoordinatedMPC._compiled_rounds`), taken in
#: turn by the threads. Fixed, so that the thread count cannot change a result: within a call
#: a day that stops early delays the next step of the others by one round (as in the
#: reference's rounds), which matters only to a day that reaches ``max_iter``.
COORDINATION_BLOCK = 4


# -- the coordinated MPC ----------------------------------------------------------------------
class CoordinatedMPC:
    """The ``n`` local MPCs with their grid limit coordinated by prices (module docstring).

    Parameters
    ----------
    system : SystemConfig
        The whole system (``n`` batteries, the grid limit ``P_bar``).
    mpc_config : MPCConfig, optional
        ``tau`` of every barrier problem; ``tol`` of the fallback IPOPT solves; ``backend``
        chooses compiled or reference rounds and sensitivities (:meth:`compiled`, the module
        docstring).
    coordination : CoordinationConfig, optional
    """

    #: threads of the compiled rounds of one hour: ``None`` (default: the cores in the main
    #: process, one in a worker process or off the main thread) or a number. The days go to
    #: the compiled rounds in blocks of :data:`COORDINATION_BLOCK`, whatever the number of
    #: threads, and each block's days are solved alone: the results do not depend on it.
    threads: int | None = None

    def __init__(
        self,
        system: SystemConfig,
        mpc_config: MPCConfig | None = None,
        coordination: CoordinationConfig | None = None,
    ) -> None:
        if not isinstance(system, SystemConfig):
            raise ValueError(f"system={system!r}: expected a SystemConfig")  # noqa: TRY004
        self.system = system
        self.mpc_config = mpc_config or MPCConfig()
        self.coordination = coordination or CoordinationConfig()
        if not isinstance(self.coordination, CoordinationConfig):
            raise ValueError(  # noqa: TRY004
                f"coordination={coordination!r}: expected a CoordinationConfig"
            )
        # one local formulation per distinct input bound U_bar (battery 0's is local_mpc)
        U_all = system.battery("U_bar")
        first = {U: U_all.index(U) for U in dict.fromkeys(U_all)}
        formulations = {U: MPC(local_system(system, self.coordination.local_grid_factor, i))
                        for U, i in first.items()}
        #: the local MPC of every battery (batteries with equal U_bar share one)
        self.local_mpcs = tuple(formulations[U] for U in U_all)
        self.local_mpc = self.local_mpcs[0]
        self._qp = LocalQP(self.local_mpc, U_all)
        self._ipopts: dict[int, IpoptSolver] = {}
        self._sensitivities: dict[int, PolicySensitivity] = {}
        self._kernels: dict[int, KernelSolver] = {}
        self._structure: _coord_kernel.Structure | None = None
        self._discount = system.gamma ** np.arange(system.N)
        # b_j and s_j at positions kb, ks of stage j's block (what the compiled rounds use)
        nb, stages = self._qp.nb, np.arange(system.N)
        self._kb, self._ks = int(self._qp.ib[0]), int(self._qp.is_[0])
        if not (np.array_equal(self._qp.ib, nb * stages + self._kb)
                and np.array_equal(self._qp.is_, nb * stages + self._ks)):
            raise RuntimeError("the local MPC's variables are not ordered by stage")

    @property
    def name(self) -> str:
        """Short description for logs and histories."""
        return f"decentralized(n={self.system.n}, tol={self.coordination.tol:g})"

    @property
    def ipopt(self) -> IpoptSolver:
        """The reference solver of battery 0's local MPC (fallback)."""
        return self.local_ipopt(0)

    def local_ipopt(self, battery: int) -> IpoptSolver:
        """The reference solver of battery ``battery``'s local MPC (fallback)."""
        mpc = self.local_mpcs[battery]
        if id(mpc) not in self._ipopts:
            self._ipopts[id(mpc)] = IpoptSolver(mpc, self.mpc_config.replace(backend="ipopt"))
        return self._ipopts[id(mpc)]

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

    def _windows(
        self, soc: np.ndarray, buy: np.ndarray, sell: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``soc (days, n)``, ``buy, sell (days, N)`` as float arrays, shapes checked."""
        n, N = self.system.n, self.system.N
        soc = np.asarray(soc, float)
        buy = np.asarray(buy, float)
        sell = np.asarray(sell, float)
        if soc.ndim != 2 or soc.shape[1] != n:
            raise ValueError(f"soc has shape {soc.shape}: expected (days, n) = (days, {n})")
        D = soc.shape[0]
        for label, w in (("buy", buy), ("sell", sell)):
            if w.shape != (D, N):
                raise ValueError(f"{label} has shape {w.shape}: expected (days, N) = ({D}, {N})")
        return soc, buy, sell

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
            Price windows (as from :meth:`Prices.window <mpcrl_lite.system.prices.Prices.window>`).
        thetas : Theta with ``n`` agents, or a sequence of ``n`` Theta with ``n = 1``

        Returns
        -------
        CoordinatedSolution
        """
        t0 = time.perf_counter()
        thetas = self._thetas(thetas)
        soc, buy, sell = self._windows(soc, buy, sell)
        hour = self._hour(soc, buy, sell, thetas)
        state = self._start(hour)
        compiled = self.compiled(thetas)
        if compiled:
            self._compiled_rounds(hour, state)
        else:
            for _ in range(self.coordination.max_iter + 1):
                if not self._round(hour, state):
                    break
        return replace(self._finish(soc, buy, sell, thetas, state, t0), compiled=compiled)

    def compiled(self, thetas: Theta | Sequence[Theta]) -> bool:
        """Whether the rounds and sensitivities for ``thetas`` run compiled:
        ``MPCConfig.backend`` ``'kernel'``, or ``'auto'`` and every local MPC a convex QP
        (see the module docstring)."""
        backend = self.mpc_config.backend
        if backend == AUTO:
            return all(t.is_convex() for t in self._thetas(thetas))
        return backend == "kernel"

    def _compiled_rounds(self, hour: _Hour, state: _Rounds) -> None:
        """Every day's rounds by :func:`mpcrl_lite.decentralized.coordination_kernel.coordinate`: the iteration
        of :meth:`_round` to rounding."""
        qp, p, cfg = self._qp, state.point, self.coordination
        _coord_kernel.ensure_compiled()
        c = np.ascontiguousarray
        if self._structure is None:
            self._structure = _coord_kernel.structure(*qp.a_pattern, qp.Cb)
        st = self._structure
        n = self.system.n
        rows = (c(hour.Hd), c(hour.q0), st.values(hour.A), c(hour.e), p.x, p.lam, p.mu)
        days = (c(hour.scale), p.nu, p.tau, state.rounds, state.done, state.stopped,
                state.worst)
        fixed = (*st.kernel_args(), c(qp.db), self._kb, self._ks, n,
                 float(self.system.P_bar), float(self.mpc_config.tau), float(cfg.tol),
                 int(cfg.max_iter))

        def block(lo: int, hi: int) -> None:
            r = [a[lo * n : hi * n] for a in rows]
            d = [a[lo:hi] for a in days]
            _coord_kernel.coordinate(*r[:4], d[0], *fixed, *r[4:], *d[1:])

        D = days[0].shape[0]
        threads = auto_threads() if self.threads is None else int(self.threads)
        run_blocks(block, (), D, max(1, min(threads, D // COORDINATION_BLOCK)),
                   COORDINATION_BLOCK, whole=False)
        for d in np.flatnonzero(state.stopped):
            log.info("coordination stopped (day %d): singular or non-finite Newton system", d)

    def _hour(
        self, soc: np.ndarray, buy: np.ndarray, sell: np.ndarray, thetas: list[Theta]
    ) -> _Hour:
        """The local problems of every day and battery at zero grid prices."""
        n, D = self.system.n, soc.shape[0]
        P0 = self._parameters(soc, buy, sell, thetas).reshape(D * n, -1)
        Hd, q0, A, e = self._qp.data(P0)
        return _Hour(Hd, q0, A, e, scale=1.0 + np.abs(q0).reshape(D, -1).max(1))

    def _parameters(
        self, soc: np.ndarray, buy: np.ndarray, sell: np.ndarray, thetas: list[Theta]
    ) -> np.ndarray:
        """The local MPCs' parameters ``(days, n, np)``: :meth:`MPC.parameters
        <mpcrl_lite.mpc.formulation.MPC.parameters>` of every battery, in one call (its last ``n_theta``
        entries are the battery's theta)."""
        mpc = self.local_mpc
        P = mpc.parameters(soc[:, :, None], buy[:, None], sell[:, None], thetas[0])
        tvec = np.stack([t.to_vector() for t in thetas])
        if not np.all(np.isfinite(tvec)):
            raise ValueError("MPC parameters contain non-finite values (soc0, prices or theta)")
        P[:, :, mpc.np - mpc.n_theta :] = tvec
        return P

    def _start(self, hour: _Hour) -> _Rounds:
        """Every day's start: one interior guess on the barrier path's centre for a large
        ``tau``, from where the rounds follow the path down to the MPC's ``tau`` (every hour
        starts cold, see the module docstring)."""
        sysc, qp = self.system, self._qp
        n, N, P_bar = sysc.n, sysc.N, sysc.P_bar
        D = hour.scale.shape[0]
        x = np.tile(self.ipopt.default_guess(), (D * n, 1))
        start = 0.25 * np.minimum(qp.bound(D * n), P_bar / n)[:, None]  # inside the limits
        x[:, qp.ib] = x[:, qp.is_] = start
        lam = np.zeros((D * n, N))
        tau = np.full(D, max(self.mpc_config.tau, 1e-2 * float(hour.scale.max())))
        x = qp.feasible(hour.A, hour.e, x)
        c = qp.E(x).reshape(D, n, -1).sum(1) - P_bar  # < 0: the guess is inside the limit
        mu = np.repeat(tau, n)[:, None, None] / -qp.h(x)
        nu = tau[:, None] / -c
        c_ = np.ascontiguousarray  # the compiled rounds update the point in place
        return _Rounds(_Point(c_(x), lam, c_(mu), c_(nu), tau), D)

    def _round(self, hour: _Hour, state: _Rounds) -> bool:
        """One round (steps 1.-3. of the module docstring) for the days still running;
        ``False`` when the rounds are over."""
        cfg, n, tau_t = self.coordination, self.system.n, self.mpc_config.tau
        days = np.flatnonzero(~state.done & ~state.stopped)
        if days.size == 0:
            return False
        rows = (days[:, None] * n + np.arange(n)).ravel()
        point = state.point.take(rows, days)
        res = self._kkt(hour, rows, point)
        state.worst[days] = res.worst / hour.scale[days]
        finished = (point.tau <= tau_t) & (state.worst[days] <= cfg.tol)
        state.done[days[finished]] = True
        if finished.all() or state.rounds[days].min() >= cfg.max_iter:
            return False
        if finished.any():
            return True  # step only the days still running
        # move tau down the barrier path once a point is centred for its tau
        lower = (point.tau > tau_t) & (res.worst <= 0.1 * point.tau * hour.scale[days])
        if lower.any():
            point = replace(point, tau=np.where(lower, np.maximum(tau_t, 0.1 * point.tau),
                                                point.tau))
            res = self._kkt(hour, rows, point)
        step, ok = self._direction(hour, rows, point, res)
        if not ok.all():
            # a singular or non-finite Newton system: that day's rounds stop here, and it
            # takes the fallback (local IPOPT solves and projection) in _finish
            for d in days[~ok]:
                log.info("coordination stopped (day %d): singular or non-finite Newton "
                         "system", d)
            state.stopped[days[~ok]] = True
        t = self._step_length(point, step, res, ok)
        state.point.put(rows, days, self._line_search(hour, rows, point, step, res.merit, t))
        state.rounds[days[ok]] += 1
        return True

    def _kkt(self, hour: _Hour, rows: np.ndarray, point: _Point) -> _Residual:
        """Residuals of the days owning ``rows``: per row and the grid coupling per day."""
        qp, n, N = self._qp, self.system.n, self.system.N
        qeff = hour.q0[rows] + qp.Et(np.repeat(point.nu, n, axis=0))
        rx, rg, rc, h = qp.residual(hour.Hd[rows], qeff, hour.A[rows], hour.e[rows], point.x,
                                    point.lam, point.mu, np.repeat(point.tau, n))
        c = qp.E(point.x).reshape(-1, n, 2 * N).sum(1) - self.system.P_bar
        cc = point.nu * c + point.tau[:, None]
        local_sq = ((rx**2).sum(1) + (rg**2).sum(1) + (rc**2).sum((1, 2))).reshape(-1, n).sum(1)
        merit = np.sqrt(local_sq + (cc**2).sum(1))
        local_max = np.maximum.reduce([np.abs(rx).max(1), np.abs(rg).max(1),
                                       np.abs(rc).max((1, 2))]).reshape(-1, n).max(1)
        return _Residual(merit, np.maximum(local_max, np.abs(cc).max(1)), qeff, rc, h, c)

    def _direction_of(
        self, hour: _Hour, rows: np.ndarray, point: _Point, res: _Residual
    ) -> _Step:
        """The Newton direction of the days owning ``rows``."""
        qp, n, N = self._qp, self.system.n, self.system.N
        # 1. local Newton systems, split by their price dependence
        dx0, lam0, L, M, Winv = qp.newton(hour.Hd[rows], res.qeff, hour.A[rows], hour.e[rows],
                                          point.x, point.mu, res.h, np.repeat(point.tau, n))
        # 2. the coordinator's price step, per day
        Mtot = M.reshape(-1, n, 2 * N, 2 * N).sum(1)
        Edx0 = qp.E(dx0).reshape(-1, n, 2 * N).sum(1)
        K = Mtot + np.einsum("dm,mk->dmk", res.c / point.nu, np.eye(2 * N))
        rhs = -(res.c + point.tau[:, None] / point.nu) - Edx0
        dnu = np.linalg.solve(K, rhs[..., None])[..., 0]
        # 3. every battery's step given the price step
        dnu_r = np.repeat(dnu, n, axis=0)
        dx = dx0 + qp.price_step(hour.A[rows], L, Winv, dnu_r)
        dlam = lam0 + (L @ dnu_r[..., None])[..., 0] - point.lam
        dh = qp.h(dx) + qp.d(dx.shape[0])
        dmu = -(res.rc + point.mu * dh) / res.h
        return _Step(dx, dlam, dmu, dnu)

    def _direction(
        self, hour: _Hour, rows: np.ndarray, point: _Point, res: _Residual
    ) -> tuple[_Step, np.ndarray]:
        """:meth:`_direction_of` for every day, and which days ``(K,)`` have a finite
        direction (their Newton systems solved); the others get a zero direction."""
        try:
            with np.errstate(all="ignore"):
                step = self._direction_of(hour, rows, point, res)
        except np.linalg.LinAlgError:
            step = self._direction_by_day(hour, rows, point, res)
        K = point.nu.shape[0]
        ok = np.logical_and.reduce([np.isfinite(d).reshape(K, -1).all(1) for d in step])
        okr = np.repeat(ok, self.system.n)
        return _Step(np.where(okr[:, None], step.dx, 0.0),
                     np.where(okr[:, None], step.dlam, 0.0),
                     np.where(okr[:, None, None], step.dmu, 0.0),
                     np.where(ok[:, None], step.dnu, 0.0)), ok

    def _direction_by_day(
        self, hour: _Hour, rows: np.ndarray, point: _Point, res: _Residual
    ) -> _Step:
        """:meth:`_direction_of` day by day, after one day's Newton system was singular; a
        day whose own system is singular gets a ``nan`` price step (failed)."""
        n = self.system.n
        step = _Step(np.zeros_like(point.x), np.zeros_like(point.lam), np.zeros_like(point.mu),
                     np.zeros_like(point.nu))
        for k in range(point.nu.shape[0]):
            r, d = slice(k * n, (k + 1) * n), slice(k, k + 1)
            try:
                with np.errstate(all="ignore"):
                    part = self._direction_of(hour, rows[r], point.take(r, d), res.take(r, d))
            except np.linalg.LinAlgError:
                step.dnu[k] = np.nan
                continue
            step.dx[r], step.dlam[r], step.dmu[r] = part.dx, part.dlam, part.dmu
            step.dnu[k] = part.dnu[0]
        return step

    def _step_length(
        self, point: _Point, step: _Step, res: _Residual, ok: np.ndarray
    ) -> np.ndarray:
        """Per day, the largest ``t <= 1`` keeping 0.5% of the distance to every bound (local
        rows and multipliers, the grid rows and prices; fraction to the boundary), 0 for a
        day without a direction."""
        qp, n, N = self._qp, self.system.n, self.system.N
        dh = qp.h(step.dx) + qp.d(step.dx.shape[0])
        dc = qp.E(step.dx).reshape(-1, n, 2 * N).sum(1)
        with np.errstate(divide="ignore", invalid="ignore"):
            limits = [
                np.where(dh > 0, -res.h / dh, np.inf).min((1, 2)).reshape(-1, n).min(1),
                np.where(step.dmu < 0, -point.mu / step.dmu, np.inf).min((1, 2))
                .reshape(-1, n).min(1),
                np.where(dc > 0, -res.c / dc, np.inf).min(1),
                np.where(step.dnu < 0, -point.nu / step.dnu, np.inf).min(1),
            ]
        return np.where(ok, np.minimum(1.0, 0.995 * np.minimum.reduce(limits)), 0.0)

    def _line_search(
        self,
        hour: _Hour,
        rows: np.ndarray,
        point: _Point,
        step: _Step,
        merit: np.ndarray,
        t: np.ndarray,
    ) -> _Point:
        """The new point: step lengths ``t (K,)`` halved per day until the total KKT
        residual decreases (at most 40 times)."""
        n = self.system.n
        for _ in range(40):
            tr = np.repeat(t, n)
            new = _Point(point.x + tr[:, None] * step.dx, point.lam + tr[:, None] * step.dlam,
                         point.mu + tr[:, None, None] * step.dmu,
                         point.nu + t[:, None] * step.dnu, point.tau)
            bad = ~(self._kkt(hour, rows, new).merit <= (1.0 - 1e-4 * t) * merit)
            if not bad.any():
                break
            t = np.where(bad, 0.5 * t, t)
        return new

    def _finish(
        self,
        soc: np.ndarray,
        buy: np.ndarray,
        sell: np.ndarray,
        thetas: list[Theta],
        state: _Rounds,
        t0: float,
    ) -> CoordinatedSolution:
        """Outputs, and the fallback for days whose rounds did not converge."""
        sysc, qp = self.system, self._qp
        n, N, D = sysc.n, sysc.N, soc.shape[0]
        nu, done, worst = state.point.nu, state.done, state.worst
        buy_p = buy + nu[:, :N] / self._discount
        sell_p = sell - nu[:, N:] / self._discount
        Pp = self._parameters(soc, buy_p, sell_p, thetas)
        X = state.point.x.reshape(D, n, -1).copy()
        Lm = state.point.lam.reshape(D, n, -1).copy()
        Mu = state.point.mu.reshape(D, n, -1).copy()
        ok = np.ones((D, n), bool)
        for d in np.flatnonzero(~done):
            log.info("coordination did not converge (day %d, residual %.1e): local IPOPT "
                     "solves at the last prices and projection", d, worst[d])
            for i in range(n):
                sol = self.local_ipopt(i).solve(soc[d, i : i + 1], buy_p[d], sell_p[d],
                                                thetas[i])
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
            price_buy=nu[:, :N].copy(), price_sell=nu[:, N:].copy(), iterations=state.rounds,
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
        D, n = solution.action.shape
        if solution.compiled:
            return self._compiled_sensitivity(solution)
        grad = np.zeros((D, n, self.local_mpc.n_theta))
        ok = np.zeros((D, n), bool)
        for i in range(n):
            mpc = self.local_mpcs[i]
            if id(mpc) not in self._sensitivities:
                self._sensitivities[id(mpc)] = PolicySensitivity(mpc, self.mpc_config)
            sens = self._sensitivities[id(mpc)](solution.local(i))
            grad[:, i] = sens.grad[:, :, 0]
            ok[:, i] = sens.ok
        return grad, ok

    def _compiled_sensitivity(
        self, solution: CoordinatedSolution
    ) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`sensitivity` by :meth:`KernelSolver.sensitivity
        <mpcrl_lite.mpc.backends.kernel.KernelSolver.sensitivity>` of the local MPC, every day and
        battery in one call per distinct local MPC (the local problem at the final prices is
        an ``n = 1`` MPC)."""
        D, n = solution.action.shape
        mpcs = list(dict.fromkeys(self.local_mpcs))
        if len(mpcs) > 1:  # batteries of unequal U_bar: each group by its own formulation
            grad = np.zeros((D, n, self.local_mpc.n_theta))
            ok = np.zeros((D, n), bool)
            for mpc in mpcs:
                group = [i for i in range(n) if self.local_mpcs[i] is mpc]
                g, o = self._kernel_sensitivity(mpc, solution, group)
                grad[:, group], ok[:, group] = g, o
            return grad, ok
        return self._kernel_sensitivity(self.local_mpc, solution, list(range(n)))

    def _kernel_sensitivity(
        self, mpc: MPC, solution: CoordinatedSolution, group: list[int]
    ) -> tuple[np.ndarray, np.ndarray]:
        """The compiled sensitivities of the batteries ``group`` (all sharing ``mpc``),
        ``(days, len(group), 10)`` and ``(days, len(group))``."""
        if id(mpc) not in self._kernels:
            self._kernels[id(mpc)] = KernelSolver(mpc, self.mpc_config)
        D = solution.action.shape[0]
        n = len(group)
        solution = replace(solution, action=solution.action[:, group], x=solution.x[:, group],
                           lam=solution.lam[:, group], mu=solution.mu[:, group],
                           p=solution.p[:, group], success=solution.success[:, group])
        ok = solution.success.ravel()
        rows = BatchSolution(
            action=solution.action.reshape(D * n, 1), x=solution.x.reshape(D * n, -1),
            lam=solution.lam.reshape(D * n, -1), mu=solution.mu.reshape(D * n, -1),
            cost=np.full(D * n, np.nan), success=ok,
            status=tuple("coordinated" if s else "local solve failed" for s in ok),
            iterations=np.repeat(solution.iterations, n), p=solution.p.reshape(D * n, -1),
            solve_time=solution.solve_time, backend="decentralized",
        )
        sens = self._kernels[id(mpc)].sensitivity(rows)
        return sens.grad[:, :, 0].reshape(D, n, -1), sens.ok.reshape(D, n)
