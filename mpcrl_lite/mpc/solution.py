"""What every MPC solver back-end returns: solutions, policy sensitivities, the fallback.

This module sits below all back-ends (:mod:`mpcrl_lite.mpc.backends.ipopt`,
:mod:`mpcrl_lite.mpc.backends.batch`) and the sensitivity code, so none of them needs another:

* :class:`MPCSolution` -- one solved MPC (paper eq. 9, as the barrier problem of
  :mod:`mpcrl_lite.mpc.formulation`): the primal-dual point ``y = (x, lam, mu)`` and the policy
  ``pi = b_0 - s_0``;
* :class:`BatchSolution` -- the solutions of a batch of problems (the days of a month at one
  hour), the same arrays with a leading ``days`` axis;
* :class:`Sensitivity` -- ``grad_theta pi`` (paper eq. 20) for a batch, with a per-problem
  flag and reason where it is unusable;
* :class:`SolverBackend` -- the interface a back-end offers to the closed loop;
* :class:`BackendBase` -- that interface's ``solve`` and ``solve_batch`` written once, around
  the one method a back-end implements (its solving of a batch of parameter vectors);
* :class:`StartSettings` -- the starting point and path-following settings of the barrier
  interior point that the batch and compiled back-ends both run, with its status strings
  ``STATUS_*``;
* :func:`check_parameters` -- the parameter vector at which a back-end checks its own QP
  data against the formulation;
* :data:`FALLBACK` -- what the policy does when a solve fails.

Failures never raise mid-run and never leak NaN: a problem that did not converge is marked
``success = False`` with the solver's status, and its ``action`` is the documented fallback
:data:`FALLBACK` -- the battery idles for that hour (``b = s = 0``) and the low-level
controller keeps soc inside [0, 1].
"""

from __future__ import annotations

import logging
import time
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Protocol

import numpy as np

from ..config import MPCConfig
from ..theta import Theta
from .formulation import MPC

__all__ = [
    "FALLBACK",
    "STATUS_BREAKDOWN",
    "STATUS_CONVERGED",
    "STATUS_MAX_ITER",
    "STATUS_NON_FINITE",
    "BackendBase",
    "BatchSolution",
    "MPCSolution",
    "Sensitivity",
    "SolverBackend",
    "StartSettings",
    "check_parameters",
    "failure_summary",
]

#: Description of the action used when a solve fails.
FALLBACK = "idle: b = s = 0 for every battery (the low-level controller still guards soc)"

# Status strings of the interior-point back-ends (batch_solver, kernel_solver).
#: Status of a problem solved to the tolerance.
STATUS_CONVERGED = "converged"
#: Status of a problem that ran out of iterations.
STATUS_MAX_ITER = "max_iter_reached"
#: Status of a problem whose residual became NaN or infinite.
STATUS_NON_FINITE = "non_finite"
#: Status of a problem whose linear algebra broke down (singular or non-finite system).
STATUS_BREAKDOWN = "linear_algebra_breakdown"


def failure_summary(status: Sequence[str], success: Sequence[bool], backend: str = "") -> str:
    """:meth:`BatchSolution.failure_summary` of a call's statuses and successes (the one
    wording of a call with failed problems, also for a compiled closed loop's hours)."""
    failed = [s for s, ok in zip(status, success, strict=True) if not ok]
    if not failed:
        return ""
    statuses = ", ".join(f"{s}: {count}" for s, count in Counter(failed).most_common())
    prefix = f"{backend} back-end: " if backend else ""
    return (f"{prefix}{len(failed)} of {len(status)} MPC problems failed ({statuses}); "
            "their batteries idle (the fallback action)")


@dataclass(frozen=True)
class MPCSolution:
    """Solution of one MPC problem.

    Attributes
    ----------
    action : (n,) the policy pi = b_0 - s_0 (the fallback zeros if ``success`` is False)
    x : (nx,) primal solution; lam : (neq,) equality multipliers; mu : (nin,) inequality
    multipliers (``mu * h = -tau`` at an exact solution)
    cost : MPC cost f at x; success, status, iterations: what the solver reported
    p : (np,) the parameters the problem was solved for
    """

    action: np.ndarray
    x: np.ndarray
    lam: np.ndarray
    mu: np.ndarray
    cost: float
    success: bool
    status: str
    iterations: int
    p: np.ndarray

    @property
    def y(self) -> np.ndarray:
        """Primal-dual vector ``(x, lam, mu)``."""
        return np.concatenate([self.x, self.lam, self.mu])


@dataclass(frozen=True)
class BatchSolution:
    """Solutions of a batch of problems (e.g. the days of a month at one hour).

    Arrays carry a leading axis of length ``days``: action (days, n), x (days, nx),
    lam (days, neq), mu (days, nin), cost, success, iterations (days,), p (days, np);
    ``status`` is a tuple of strings; ``solve_time`` the wall time of the whole call in s.
    """

    action: np.ndarray
    x: np.ndarray
    lam: np.ndarray
    mu: np.ndarray
    cost: np.ndarray
    success: np.ndarray
    status: tuple[str, ...]
    iterations: np.ndarray
    p: np.ndarray
    solve_time: float = 0.0
    backend: str = field(default="")

    def __len__(self) -> int:
        return self.action.shape[0]

    def __getitem__(self, d: int) -> MPCSolution:
        return MPCSolution(
            action=self.action[d],
            x=self.x[d],
            lam=self.lam[d],
            mu=self.mu[d],
            cost=float(self.cost[d]),
            success=bool(self.success[d]),
            status=self.status[d],
            iterations=int(self.iterations[d]),
            p=self.p[d],
        )

    @property
    def failures(self) -> int:
        """Number of problems that did not converge."""
        return int(np.count_nonzero(~self.success))

    def failure_summary(self) -> str:
        """One line for a log: how many problems failed and with which statuses, e.g.
        ``"batch back-end: 3 of 24 MPC problems failed (max_iter_reached: 3); their batteries
        idle (the fallback action)"``; the empty string when none failed."""
        return failure_summary(self.status, self.success, self.backend)

    @staticmethod
    def stack(
        solutions: list[MPCSolution], solve_time: float = 0.0, backend: str = ""
    ) -> BatchSolution:
        """Gather single solutions into a batch."""
        return BatchSolution(
            action=np.stack([s.action for s in solutions]),
            x=np.stack([s.x for s in solutions]),
            lam=np.stack([s.lam for s in solutions]),
            mu=np.stack([s.mu for s in solutions]),
            cost=np.array([s.cost for s in solutions]),
            success=np.array([s.success for s in solutions]),
            status=tuple(s.status for s in solutions),
            iterations=np.array([s.iterations for s in solutions]),
            p=np.stack([s.p for s in solutions]),
            solve_time=solve_time,
            backend=backend,
        )

    @staticmethod
    def of(solution: MPCSolution | BatchSolution) -> BatchSolution:
        """``solution`` as a batch: a single solution becomes a batch of one, a batch is
        returned as it is (what every sensitivity routine takes)."""
        if isinstance(solution, MPCSolution):
            return BatchSolution.stack([solution], 0.0, "")
        return solution


@dataclass(frozen=True)
class Sensitivity:
    """grad_theta pi for a batch of solutions.

    grad : (days, n_theta, n) -- zeros where ``ok`` is False
    ok : (days,) -- False where the problem failed or its KKT system was unusable
    cond : (days,) -- the conditioning proxy ``||K||_max ||Z||_max``
    reason : tuple of str, '' where ok
    grad_soc0 : (days, n, n) or None -- ``d pi_o / d soc0_i`` at ``[d, i, o]``, the policy's
        sensitivity in its initial state, where the back-end forms it from the same adjoint
        (the compiled kernel, column by column); zeros where ``ok`` is False
    """

    grad: np.ndarray
    ok: np.ndarray
    cond: np.ndarray
    reason: tuple[str, ...]
    grad_soc0: np.ndarray | None = None

    @property
    def skipped(self) -> int:
        """How many problems gave no usable sensitivity."""
        return int(np.count_nonzero(~self.ok))


class SolverBackend(Protocol):
    """What the closed loop needs from an MPC back-end (built by
    :func:`mpcrl_lite.mpc.backends.registry.make_solver`).

    ``name`` is the back-end's key in :data:`mpcrl_lite.config.BACKENDS`; ``solve`` takes
    soc0 (n,), buy and sell (N,) and an optional primal guess x0 (nx,); ``solve_batch`` the
    same with a leading ``days`` axis and one shared theta; ``sensitivity`` gives
    ``grad_theta pi`` at any solution of ``mpc``. None of them raises because a problem
    failed: failures are reported in the returned objects.
    """

    name: str
    mpc: MPC
    config: MPCConfig

    def solve(
        self, soc0: np.ndarray, buy: np.ndarray, sell: np.ndarray, theta: Theta,
        x0: np.ndarray | None = None,
    ) -> MPCSolution: ...

    def solve_batch(
        self, soc0: np.ndarray, buy: np.ndarray, sell: np.ndarray, theta: Theta,
        x0: np.ndarray | None = None,
    ) -> BatchSolution: ...

    def sensitivity(self, solution: MPCSolution | BatchSolution) -> Sensitivity: ...


class BackendBase:
    """The public half of a back-end: :meth:`solve` and :meth:`solve_batch` of
    :class:`SolverBackend`, written once around :meth:`_solve_parameters`.

    A back-end sets ``name``, ``mpc`` and ``config`` and implements
    :meth:`_solve_parameters`, the solving of a batch of parameter vectors. This class builds
    those vectors from the states and price windows (checking their shapes before any work),
    applies ``config.warm_start`` to a guess ``x0``, times the call, and logs one warning per
    call with failures (:meth:`BatchSolution.failure_summary`) on the logger of the
    back-end's own module.
    """

    name: str = ""
    mpc: MPC
    config: MPCConfig

    def solve(
        self, soc0: np.ndarray, buy: np.ndarray, sell: np.ndarray, theta: Theta,
        x0: np.ndarray | None = None,
    ) -> MPCSolution:
        """Solve one MPC: soc0 (n,), buy and sell (N,), theta; optional primal guess x0 (nx,).

        The one row of :meth:`solve_batch`: the warm start and a failure are handled as
        there.
        """
        batch = self.solve_batch(
            np.asarray(soc0, float)[None], np.asarray(buy, float)[None],
            np.asarray(sell, float)[None], theta,
            None if x0 is None else np.asarray(x0, float)[None],
        )
        return batch[0]

    def solve_batch(
        self, soc0: np.ndarray, buy: np.ndarray, sell: np.ndarray, theta: Theta,
        x0: np.ndarray | None = None,
    ) -> BatchSolution:
        """Solve one MPC per row, e.g. all days of a month at one hour.

        Parameters
        ----------
        soc0
            States, shape (days, n).
        buy, sell
            Price windows, shape (days, N).
        theta
            MPC parameters, shared by all rows.
        x0
            Optional primal warm start (days, nx), e.g. the previous hour's solutions shifted
            by one stage (:meth:`mpcrl_lite.mpc.formulation.MPC.shift`); used only when
            ``config.warm_start`` is set. What a back-end takes from it is its own affair.

        Returns
        -------
        BatchSolution
            Rows that failed have ``success = False``, the back-end's status string and the
            fallback action zeros (:data:`FALLBACK`); a call with failures logs one warning.

        Raises
        ------
        ValueError
            For inputs of the wrong shape or non-finite parameters (before any work).
        """
        t_start = time.perf_counter()
        P = self.mpc.parameters(soc0, buy, sell, theta)
        if P.ndim != 2:
            raise ValueError(f"solve_batch expects soc0 (days, n); got soc0 {np.shape(soc0)}")
        if x0 is not None:
            days, nx = P.shape[0], self.mpc.nx
            x0 = np.asarray(x0, float)
            if x0.size != days * nx:
                raise ValueError(f"x0 has shape {x0.shape}; expected (days={days}, nx={nx})")
            x0 = x0.reshape(days, nx) if self.config.warm_start else None
        batch = replace(self._solve_parameters(P, x0),
                        solve_time=time.perf_counter() - t_start, backend=self.name)
        if batch.failures:
            logging.getLogger(type(self).__module__).warning("%s", batch.failure_summary())
        return batch

    def _solve_parameters(self, P: np.ndarray, x0: np.ndarray | None) -> BatchSolution:
        """The problems of the parameter vectors ``P`` (days, np), with the warm start ``x0``
        (days, nx) or None; ``solve_time`` and ``backend`` are filled in by the caller."""
        raise NotImplementedError(f"{type(self).__name__} does not implement _solve_parameters")


class StartSettings:
    """Starting point and path-following settings of the barrier interior point, shared by
    :class:`~mpcrl_lite.mpc.backends.batch.BatchSolver` and
    :class:`~mpcrl_lite.mpc.backends.kernel.KernelSolver` (which run the same iteration).

    Tuned on random states, prices and thetas; class attributes so that experiments can
    change them on either solver class or instance.
    """

    #: cold start: ``b^i = s^i = u0_fraction * min(U_bar^i, P_bar / n)`` (each battery's own)
    u0_fraction: float = 0.5
    #: initial barrier value ``mean(mu S)`` relative to the price scale ``1 + max |q|``
    t0_cold: float = 0.1
    t0_warm: float = 0.1
    #: warm start: ``b, s`` of ``x0`` kept this far from their bounds (relative to the
    #: smallest ``min(U_bar^i, P_bar / n)``) and blended with the cold start with this weight. A primal-only
    #: warm start helps an interior point little (about 8 % fewer iterations on the
    #: experiment's hour-to-hour problems); a full weight makes the slowest problems slower.
    warm_margin: float = 1e-2
    warm_weight: float = 0.3
    #: initial distance of sigma_hi, sigma_lo above their kinks
    slack_margin: float = 0.3
    #: switch to pure Newton steps at tau once Mehrotra's target is below this times tau
    switch_factor: float = 1.0


def check_parameters(mpc: MPC, rng: np.random.Generator) -> np.ndarray:
    """A pseudo-random parameter vector (np,) of ``mpc`` -- state, price windows and a
    convex theta away from theta0 -- at which a back-end checks its hand-written QP data
    against :attr:`MPC.qp_function <mpcrl_lite.mpc.formulation.MPC.qp_function>`."""
    n, N = mpc.n, mpc.N
    theta = np.concatenate([
        rng.uniform(0.05, 0.12, n), rng.uniform(-0.01, 0.01, n), rng.uniform(-5, 5, 2 * n),
        rng.uniform(0, 50, n), rng.uniform(-50, 50, 2 * n),
        rng.uniform(0, 50, n), rng.uniform(-50, 50, 2 * n),
    ])
    return mpc.parameters(rng.uniform(0.0, 1.0, n), rng.uniform(5, 130, N),
                          rng.uniform(5, 60, N), theta)
