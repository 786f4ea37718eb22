"""Solver back-ends for the MPC, all returning the same solution objects.

* :class:`IpoptSolver` -- the reference: IPOPT through CasADi's ``nlpsol`` with the barrier
  parameter held at ``tau`` (``mu_target = tau``, no scaling, no bound relaxation, no
  damping), followed by at most a few Newton steps on the barrier problem's KKT conditions so
  the solution is exact to machine precision (the sensitivities need that).
* :class:`~mpcrl_lite.batch_solver.BatchSolver` -- a numpy interior point that solves all
  days of a month at once (see that module).

:func:`make_solver` picks one from :class:`~mpcrl_lite.config.MPCConfig`.

Failures never raise mid-run and never leak NaN: a problem that did not converge is marked
``success = False`` with the solver's status, and its ``action`` is the documented fallback
:data:`FALLBACK` -- the battery idles for that hour (``b = s = 0``) and the low-level
controller keeps soc inside [0, 1].
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field

import casadi as ca
import numpy as np

from .config import MPCConfig
from .mpc import MPC
from .theta import Theta

__all__ = ["MPCSolution", "BatchSolution", "IpoptSolver", "make_solver", "FALLBACK"]

log = logging.getLogger(__name__)

#: Description of the action used when a solve fails.
FALLBACK = "idle: b = s = 0 for every battery (the low-level controller still guards soc)"


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

    @staticmethod
    def stack(solutions: list[MPCSolution], solve_time: float, backend: str) -> "BatchSolution":
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


def _ipopt_options(config: MPCConfig) -> dict:
    return {
        "print_time": False,
        "ipopt": {
            "mu_target": config.tau,
            "nlp_scaling_method": "none",
            "bound_relax_factor": 0.0,
            "kappa_d": 0.0,
            "hessian_constant": "yes",
            "jac_c_constant": "yes",
            "jac_d_constant": "yes",
            "tol": max(config.tol, 1e-12),
            "acceptable_tol": 1e-7,
            "max_iter": config.max_iter,
            "print_level": 0,
            "sb": "yes",
        },
    }


class IpoptSolver:
    """Reference back-end: IPOPT on the barrier problem, then Newton polishing.

    Parameters
    ----------
    mpc
        The formulation (built once).
    config
        Barrier parameter ``tau``, tolerance, iteration limit, warm start flag.
    """

    name = "ipopt"

    def __init__(self, mpc: MPC, config: MPCConfig | None = None) -> None:
        self.mpc = mpc
        self.config = config or MPCConfig()
        x, p, f, g, h = mpc.symbols
        sysc = mpc.system
        # simple bounds go to lbx/ubx (same barrier problem, cheaper for IPOPT); the grid
        # and slack constraints stay general constraints
        m = mpc
        lbx = np.full(m.nx, -np.inf)
        ubx = np.full(m.nx, np.inf)
        for name in ("b", "s"):
            lbx[m.index(name)] = 0.0
            ubx[m.index(name)] = sysc.U_bar
        for name in ("sigma_hi", "sigma_lo"):
            lbx[m.index(name)] = 0.0
        self._lbx, self._ubx = lbx, ubx
        # rows of h that are not simple bounds
        per_stage = 8 * m.n + 2
        rows = []
        for j in range(m.N):
            base = j * per_stage + 4 * m.n
            rows += list(range(base, base + 2)) + list(range(base + 2, base + 2 + 2 * m.n))
        self._general_rows = np.array(rows)
        g_all = ca.vertcat(g, h[self._general_rows])
        self._lbg = np.concatenate([np.zeros(m.neq), np.full(len(rows), -np.inf)])
        self._ubg = np.zeros(m.neq + len(rows))
        self._nlp = ca.nlpsol("mpc_ipopt", "ipopt", {"x": x, "p": p, "f": f, "g": g_all},
                              _ipopt_options(self.config))
        self._kkt = mpc.kkt
        self._sensitivity = None

    # -- single problem -------------------------------------------------------------------
    def solve(
        self,
        soc0: np.ndarray,
        buy: np.ndarray,
        sell: np.ndarray,
        theta: Theta,
        x0: np.ndarray | None = None,
    ) -> MPCSolution:
        """Solve one MPC. soc0 (n,), buy and sell (N,), theta; optional primal guess x0."""
        p = self.mpc.parameters(soc0, buy, sell, theta)
        return self._solve_p(p, x0)

    def _solve_p(self, p: np.ndarray, x0: np.ndarray | None) -> MPCSolution:
        m = self.mpc
        if x0 is None:
            x0 = self.default_guess()
        try:
            out = self._nlp(x0=x0, p=p, lbx=self._lbx, ubx=self._ubx, lbg=self._lbg, ubg=self._ubg)
            stats = self._nlp.stats()
            status = str(stats.get("return_status", "unknown"))
            iterations = int(stats.get("iter_count", -1))
            x = np.array(out["x"]).ravel()
            lam = np.array(out["lam_g"]).ravel()[: m.neq]
        except RuntimeError as err:  # IPOPT raised (e.g. invalid number in evaluation)
            status, iterations = f"error: {err}", -1
            x, lam = np.asarray(x0, float), np.zeros(m.neq)
        converged = status in ("Solve_Succeeded", "Solved_To_Acceptable_Level")
        x, lam, mu, polished = self._polish(x, lam, p)
        success = converged and polished
        if converged and not polished:
            status = "kkt_polish_failed"
        if not np.all(np.isfinite(x)):
            success = False
        action = m.policy_selector @ x if success else np.zeros(m.n)
        f = float(self.mpc.fgh(x, p)[0]) if np.all(np.isfinite(x)) else np.nan
        return MPCSolution(action, x, lam, mu, f, bool(success), status, iterations, p)

    def _polish(
        self, x: np.ndarray, lam: np.ndarray, p: np.ndarray, steps: int = 8
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, bool]:
        """Newton steps on the barrier KKT system from IPOPT's point, keeping h < 0 and
        mu > 0; returns ``(x, lam, mu, ok)`` with ``ok`` when the residual is tiny."""
        kkt, tau = self._kkt, self.config.tau
        _, _, h = self.mpc.evaluate(x, p)
        if not np.all(h < 0):
            return x, lam, np.zeros(self.mpc.nin), False
        mu = tau / -h
        y = np.concatenate([x, lam, mu])
        scale = 1.0 + np.abs(p).max()
        r = np.array(kkt.residual(y, p, tau)).ravel()
        for _ in range(steps):
            if np.max(np.abs(r)) == 0.0:
                break
            dy = np.array(kkt.newton(y, p, tau)).ravel()
            if not np.all(np.isfinite(dy)):
                break
            xs, _, mus = kkt.split(y)
            dx, _, dmu = kkt.split(dy)
            _, _, h = self.mpc.evaluate(xs, p)
            dh = self.mpc.evaluate(xs + dx, p)[2] - h
            step = 1.0
            neg = dh > 0
            if np.any(neg):
                step = min(step, 0.99 * np.min(-h[neg] / dh[neg]))
            neg = dmu < 0
            if np.any(neg):
                step = min(step, 0.99 * np.min(-mus[neg] / dmu[neg]))
            y_new = y + step * dy
            r_new = np.array(kkt.residual(y_new, p, tau)).ravel()
            if not np.max(np.abs(r_new)) < np.max(np.abs(r)):
                break  # no more progress: at machine precision
            # a full Newton step that gains less than two digits is at the rounding level
            at_floor = step == 1.0 and np.max(np.abs(r_new)) > 1e-2 * np.max(np.abs(r))
            y, r = y_new, r_new
            if at_floor:
                break
        x, lam, mu = kkt.split(y)
        ok = bool(np.all(np.isfinite(r)) and np.max(np.abs(r)) <= 1e-6 * scale)
        return x, lam, mu, ok

    def default_guess(self) -> np.ndarray:
        """A strictly feasible interior starting point (mid-range inputs, soc at 0.5)."""
        m, sysc = self.mpc, self.mpc.system
        x0 = np.zeros(m.nx)
        u0 = min(0.25 * sysc.U_bar, 0.25 * sysc.P_bar / m.n)
        x0[m.index("b")] = u0
        x0[m.index("s")] = u0
        x0[m.index("soc")] = 0.5
        x0[m.index("sigma_hi")] = 0.1
        x0[m.index("sigma_lo")] = 0.1
        return x0

    def sensitivity(self, solution: "MPCSolution | BatchSolution"):
        """grad_theta pi at ``solution`` (see :class:`mpcrl_lite.sensitivity.PolicySensitivity`)."""
        if self._sensitivity is None:
            from .sensitivity import PolicySensitivity

            self._sensitivity = PolicySensitivity(self.mpc, self.config)
        return self._sensitivity(solution)

    # -- batches --------------------------------------------------------------------------
    def solve_batch(
        self,
        soc0: np.ndarray,
        buy: np.ndarray,
        sell: np.ndarray,
        theta: Theta,
        x0: np.ndarray | None = None,
    ) -> BatchSolution:
        """Solve one MPC per row: soc0 (days, n), buy and sell (days, N); optional x0
        (days, nx) warm start. One call for all days of a month at one hour."""
        t0 = time.perf_counter()
        P = self.mpc.parameters(soc0, buy, sell, theta)
        if P.ndim != 2:
            raise ValueError(f"solve_batch expects soc0 (days, n); got soc0 {np.shape(soc0)}")
        sols = []
        for d in range(P.shape[0]):
            guess = None if x0 is None or not self.config.warm_start else x0[d]
            sols.append(self._solve_p(P[d], guess))
        return BatchSolution.stack(sols, time.perf_counter() - t0, self.name)


def make_solver(mpc: MPC, config: MPCConfig | None = None, theta: Theta | None = None):
    """The back-end named by ``config.backend``.

    ``'auto'`` chooses the batch interior point when the MPC is a convex QP for ``theta``
    (``phi1, T1 >= 0``; always true with ``LearningConfig.keep_well_posed``) and IPOPT
    otherwise; the choice is logged at INFO level and readable from ``solver.name``.
    """
    config = config or MPCConfig()
    backend = config.backend
    if backend == "auto":
        convex = theta is None or theta.is_convex()
        backend = "batch" if convex and _batch_available() else "ipopt"
        log.info("MPC back-end 'auto' chose %r", backend)
    if backend == "batch":
        from .batch_solver import BatchSolver

        return BatchSolver(mpc, config)
    return IpoptSolver(mpc, config)


def _batch_available() -> bool:
    try:
        from . import batch_solver  # noqa: F401
    except ImportError:
        return False
    return True
