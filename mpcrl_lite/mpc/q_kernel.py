r"""The fixed-first-action MPC (the MPC as Q) on the compiled interior point.

With the first action fixed, :math:`\hat b_0 - \hat s_0 = a`, the model gives the first
predicted state outright, :math:`\widehat{soc}_1 = soc_0 + \theta_\alpha a + \theta_\delta`,
and the barrier problem of :mod:`mpcrl_lite.mpc.value` splits into independent parts:

* the **tail**: stages ``1 .. N-1`` from :math:`\widehat{soc}_1`, the MPC with horizon
  ``N - 1`` and the stage weights of stages ``1 .. N-1`` (price weights :math:`\gamma^j`,
  soc costs :math:`\gamma^{j+1}`, the terminal cost undiscounted) -- solved by
  :class:`~mpcrl_lite.mpc.backends.kernel.KernelSolver` built for horizon ``N - 1`` with
  those weights;
* the **first stage**: the slacks of :math:`\widehat{soc}_1` (each a scalar barrier
  problem with a closed-form solution) and :math:`\hat s_0` (``\hat b_0 = \hat s_0 + a``):
  ``n`` variables with the box barriers and the two grid rows, solved by damped Newton steps
  (its Hessian is diagonal plus a rank one term), all rows of a batch at once.

The multipliers of the full problem follow from its stationarity conditions: the model's
first row from the derivative in :math:`\widehat{soc}_1`, the first action's rows from the
derivative in :math:`\hat b_0`; the inequality multipliers are ``tau / (-h)``. The assembled
point satisfies the full problem's KKT conditions to the kernel's tolerance, so values and
derivatives computed from it (:class:`~mpcrl_lite.mpc.value.MPCValue`) are those of the
reference (IPOPT with Newton polish) to that tolerance (``tests/mpc/test_value.py``).
"""

from __future__ import annotations

import numpy as np
from scipy.sparse import csr_matrix

from ..config import MPCConfig
from . import q_stage_kernel
from .backends.kernel import KernelSolver
from .formulation import MPC
from .solution import BatchSolution

__all__ = ["FixedActionKernel"]

#: Newton steps of the first-stage problem (it converges in about 10-20).
_STAGE0_MAX_ITER = 100
#: Stop when the Newton decrement of the first-stage problem is below this (relative).
_STAGE0_TOL = 1e-15
#: The first stage's Newton iteration compiled (:mod:`mpcrl_lite.mpc.q_stage_kernel`, the same
#: bits); False runs its numpy form, the reference.
COMPILED = True


class FixedActionKernel:
    """Solves the fixed-first-action barrier MPC of ``mpc`` for a batch (see the module
    docstring); ``N >= 2``."""

    def __init__(self, mpc: MPC, config: MPCConfig | None = None) -> None:
        if mpc.N < 2:
            raise ValueError(f"N={mpc.N}: the compiled fixed-action MPC needs N >= 2")
        self.mpc = mpc
        self.config = config or MPCConfig()
        self.tail_mpc = MPC(mpc.system.replace(N=mpc.N - 1))
        self.tail = KernelSolver(self.tail_mpc, self.config.replace(warm_start=True))
        gam = mpc.system.gamma ** np.arange(mpc.N + 1, dtype=float)
        stage = np.arange(mpc.N) < mpc.N - 1
        sysc = mpc.system
        weights = np.stack([
            gam[: mpc.N], np.where(stage, gam[1:], 0.0), (~stage).astype(float),
            np.where(stage, gam[1:] * sysc.omega[0], sysc.omega_f[0]),
            np.where(stage, gam[1:] * sysc.omega[1], sysc.omega_f[1]),
        ])
        self.weights = weights
        # the kernels' check against the formulation runs with the tail MPC's own weights,
        # before they are replaced by those of stages 1 .. N-1
        self.tail._ready()
        self.tail._stagew = np.ascontiguousarray(weights[:, 1:])
        # h = C x - d: C and d do not depend on the parameters
        qp = mpc.qp_data(mpc.parameters(np.full(mpc.n, 0.5), np.zeros(mpc.N),
                                        np.zeros(mpc.N), np.ones(mpc.n_theta)))
        self._C, self._d = csr_matrix(qp.C), qp.d

    def solve(self, P: np.ndarray, a: np.ndarray, x0: np.ndarray | None = None) -> BatchSolution:
        """The problems of parameter vectors ``P`` (days, np) and actions ``a`` (days, n)
        (strictly inside the bounds), from the policy's solutions ``x0`` (days, nx) if given.

        Returns the solutions in the full problem's layout: ``x`` (days, nx), ``lam``
        (days, neq + n), ``mu`` (days, nin); ``p`` holds ``(P, a)``; ``cost`` is NaN (:class:`~mpcrl_lite.mpc.value.MPCValue`
        evaluates the values)."""
        m, sysc, tau = self.mpc, self.mpc.system, self.config.tau
        n, N = m.n, m.N
        P, a = np.asarray(P, float), np.asarray(a, float)
        days = P.shape[0]
        th = P[:, m.theta_slice].reshape(days, -1, n)  # (days, parts, n)
        alpha, delta, tb, ts, phi1, phi2 = (th[:, k] for k in range(6))
        t1, t2 = th[:, 7], th[:, 8]
        soc0 = P[:, :n]
        buy, sell = P[:, n:n + N], P[:, n + N:n + 2 * N]
        soc1 = soc0 + alpha * a + delta
        U, Pb = np.array(sysc.battery("U_bar")), sysc.P_bar  # each battery's own bound
        feasible = np.all((np.abs(a) < U), axis=1) & (np.maximum(a, 0).sum(1) < Pb) \
            & (np.maximum(-a, 0).sum(1) < Pb)
        # the tail: stages 1 .. N-1 from soc1
        Pt = self.tail_mpc.parameters(np.clip(soc1, -1e3, 1e3), buy[:, 1:], sell[:, 1:],
                                      P[:, m.theta_slice])
        warm = None if x0 is None else np.asarray(x0, float)[:, 5 * n:]
        tail = self.tail.solve_batch(Pt[:, :n], Pt[:, n:n + N - 1], Pt[:, n + N - 1:n + 2 * N - 2],
                                     P[:, m.theta_slice], x0=warm)
        # the first stage: slacks of soc1 in closed form, s0 by Newton steps
        w = self.weights
        shi = _slack(w[3, 0], soc1 - sysc.soc_high, tau)
        slo = _slack(w[4, 0], sysc.soc_low - soc1, tau)
        c = (buy[:, :1] + tb) - (sell[:, :1] + ts)  # cost of s0 (b0 = s0 + a)
        s0, ok0 = _first_stage(c, a, U, Pb, tau, feasible)
        b0 = s0 + a
        # the full primal point
        x = np.empty((days, m.nx))
        x[:, 5 * n:] = tail.x
        x[:, m.index("b", 0)], x[:, m.index("s", 0)] = b0, s0
        x[:, m.index("soc", 0)] = soc1
        x[:, m.index("sigma_hi", 0)], x[:, m.index("sigma_lo", 0)] = shi, slo
        h = (self._C @ x.T).T - self._d
        with np.errstate(divide="ignore", invalid="ignore"):
            mu = tau / -h
        # multipliers of the model's first row (d/d soc1) and of the first action (d/d b0)
        lam = np.zeros((days, m.neq + n))
        lam[:, n:m.neq] = tail.lam
        row = {name: m.inequality_index(name, 0) for name in
               ("b_min", "b_max", "soc_max", "soc_min")}
        grid_b = m.inequality_index("grid_b", 0)
        dsoc = w[1, 0] * (2 * phi1 * soc1 + phi2) + w[2, 0] * (2 * t1 * soc1 + t2)
        lam0 = tail.lam[:, :n] - dsoc - mu[:, row["soc_max"]] + mu[:, row["soc_min"]]
        lam[:, :n] = lam0
        db0 = w[0, 0] * (buy[:, :1] + tb)
        lam[:, m.neq:] = -(db0 - alpha * lam0 - mu[:, row["b_min"]] + mu[:, row["b_max"]]
                           + mu[:, [int(grid_b)]])
        success = feasible & ok0 & tail.success & np.all(h < 0, axis=1) \
            & np.all(np.isfinite(x), axis=1)
        status = tuple("converged" if s else
                       ("infeasible action" if not f else f"tail: {st}" if not ts_ok
                        else "first stage did not converge")
                       for s, f, ts_ok, st in zip(success, feasible, tail.success, tail.status,
                                                  strict=True))
        cost = np.full(days, np.nan)  # f is not needed: MPCValue evaluates the barrier value
        return BatchSolution(
            action=np.where(success[:, None], a, 0.0), x=x, lam=lam, mu=np.where(np.isfinite(mu), mu, 0.0),
            cost=cost, success=success, status=status,
            iterations=tail.iterations, p=np.concatenate([P, a], axis=1), backend="kernel",
        )


def _slack(c: float, e: np.ndarray, tau: float) -> np.ndarray:
    """``argmin_s c s - tau log s - tau log(s - e)`` (``s > max(0, e)``), in closed form: the
    larger root of ``c s^2 - (c e + 2 tau) s + tau e = 0``, written without cancellation."""
    bq = c * e + 2 * tau
    disc = np.sqrt(bq * bq - 4 * c * tau * e)
    big = np.where(bq >= 0, (bq + disc) / (2 * c), 2 * tau * e / (bq - disc))
    return big


def _first_stage(c: np.ndarray, a: np.ndarray, U: np.ndarray, P: float, tau: float,
                 feasible: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``argmin_s sum c s - tau sum [log s + log(U - s) + log(s + a) + log(U - s - a)]
    - tau log(P - sum(s + a)) - tau log(P - sum s)`` for every row, by damped Newton steps
    (``U`` (n,) each battery's input bound)."""
    lo, hi = np.maximum(0.0, -a), np.minimum(U, U - a)
    width = hi - lo
    room = np.minimum(P - np.maximum(a, 0).sum(1), P - np.maximum(-a, 0).sum(1))
    t = np.minimum(0.5, 0.5 * np.maximum(room, 0) / np.maximum(width.sum(1), 1e-300))
    s = np.where(feasible[:, None], lo + t[:, None] * width, 0.5 * U)
    A = a.sum(1)
    done = ~feasible
    if not COMPILED or a.shape[1] >= 8:  # numpy sums eight or more in another order
        with np.errstate(divide="ignore", invalid="ignore"):  # rows already done may be nan
            return _newton_numpy(s, c, a, A, U, P, tau, done, feasible)
    q_stage_kernel.ensure_compiled()
    s = np.array(s, dtype=float, order="C")
    q_stage_kernel.newton_rows(s, np.ascontiguousarray(c, dtype=float),
                               np.ascontiguousarray(a, dtype=float),
                               np.ascontiguousarray(A, dtype=float),
                               np.ascontiguousarray(U, dtype=float), float(P), float(tau), done,
                               _STAGE0_MAX_ITER, _STAGE0_TOL)
    return s, done & feasible


def _newton_numpy(s, c, a, A, U, P, tau, done, feasible):
    """The damped Newton iteration of :func:`_first_stage` from ``s``, in numpy: the
    reference of the compiled :func:`~mpcrl_lite.mpc.q_stage_kernel.newton_rows`."""
    for _ in range(_STAGE0_MAX_ITER):
        gb, gs = P - (s.sum(1) + A), P - s.sum(1)
        grad = (c - tau * (1 / s - 1 / (U - s) + 1 / (s + a) - 1 / (U - s - a))
                + (tau / gb + tau / gs)[:, None])
        diag = tau * (1 / s**2 + 1 / (U - s) ** 2 + 1 / (s + a) ** 2 + 1 / (U - s - a) ** 2)
        rank = tau / gb**2 + tau / gs**2  # H = diag + rank * 1 1'
        Dg, D1 = grad / diag, 1 / diag
        ds = -(Dg - D1 * (rank * Dg.sum(1) / (1 + rank * D1.sum(1)))[:, None])
        decrement = -(grad * ds).sum(1)
        done = done | (decrement <= _STAGE0_TOL * (1 + np.abs(c).max(1)))
        if done.all():
            break
        # the longest step keeping every log argument positive, then 0.99 of it (at most 1)
        step = np.ones(len(s))
        for num, den in ((s, -ds), (U - s, ds), (s + a, -ds), (U - s - a, ds)):
            r = np.where(den > 0, num / den, np.inf)
            step = np.minimum(step, 0.99 * r.min(1))
        for num, den in ((gb, ds.sum(1)), (gs, ds.sum(1))):
            step = np.minimum(step, np.where(den > 0, 0.99 * num / den, np.inf))
        step = np.where(done, 0.0, step)
        s = s + step[:, None] * ds
    return s, done & feasible
