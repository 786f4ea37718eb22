r"""A structure-exploiting interior point that solves all days of a month at once.

:class:`BatchSolver` is a drop-in replacement for :class:`~mpcrl_lite.mpc.backends.ipopt.IpoptSolver`.
It solves *the same barrier problem* (``tau`` fixed, see :mod:`mpcrl_lite.mpc.formulation`)

.. math:: \min_x\; \tfrac12 x^\top H x + q^\top x + c - \tau\sum_k \log(d - Cx)_k
          \quad\text{s.t.}\quad Ax = e

for a batch of problems (the ``days`` of a month at one hour: they differ in ``soc0`` and
prices and share theta, or come in groups of equal theta, solved group by group) in plain numpy, and computes the policy sensitivities
``d pi / d theta`` of all of them with the same linear algebra. Nothing is compiled:
constructing the solver takes milliseconds.

Method
------
**Primal-dual Newton on the barrier KKT conditions.** With slacks ``S = d - Cx > 0`` and
multipliers ``mu > 0`` the conditions are

.. math:: r_d = Hx + q + A^\top\lambda + C^\top\mu = 0,\qquad r_p = Ax - e = 0,\qquad
          \mu\circ S = \tau .

A Newton step for the target ``mu o S = t`` eliminates
``d mu = (t - corr)/S - mu - D dS`` (``D = diag(mu/S)``, ``dS = -C dx``) and leaves the
symmetric reduced system

.. math:: \begin{bmatrix} W & A^\top \\ A & 0\end{bmatrix}
          \begin{bmatrix} dx\\ d\lambda\end{bmatrix} =
          \begin{bmatrix} -(Hx + q + A^\top\lambda) - C^\top u \\ e - Ax\end{bmatrix},
          \qquad W = H + C^\top D C,\quad u = (t - corr)/S .

The target follows Mehrotra's predictor-corrector rule, ``t = max(tau, sigma mean(mu o S))``
with ``sigma = (mu_aff / mean(mu o S))^3``, but never goes below ``tau``. Once the rule asks
for ``t <= tau`` the problem switches for good to pure Newton steps at ``t = tau`` (no
corrector); they converge quadratically to the exact barrier solution. A problem is finished
when its scaled residual (:meth:`BatchSolver.residual`) is at most ``config.tol`` and either
one more Newton step has been taken since (which, by quadratic convergence, reaches the
rounding level), or the residual is at the floor ``tol * 1e-5``, or it stopped improving
(without ``config.polish``: as soon as the residual is at most ``tol``, for evaluations that
need the action only). The
returned points satisfy the KKT conditions to about machine precision; the sensitivities are
exact only there. Steps keep ``S, mu > 0`` (fraction 0.995 to the boundary, separate primal
and dual step lengths). Finished problems leave the working set, so stragglers run alone.
The starting point is central for a barrier value proportional to the price scale (class
attributes of :class:`BatchSolver`). A warm start ``x0`` (e.g. the previous hour's solution
shifted by one stage, :meth:`BatchSolver.shift`) only moves the starting ``b, s``: a
primal-only warm start saves an interior point little (about 8 % of the iterations here).

The linear algebra of a Newton step (eliminations, tridiagonal inverses, the grid Schur
complement) and the data layout are described in :mod:`mpcrl_lite.mpc.backends.batch_kkt`, the policy
sensitivities in :mod:`mpcrl_lite.mpc.backends.batch_adjoint`; the dense kernels are in
:mod:`mpcrl_lite.mpc.backends.batch_linalg`.

Failures (no convergence within ``max_iter``, non-finite numbers, breakdown of the linear
algebra) are reported per problem (``success = False``, a status string, the fallback action
zeros, see :data:`~mpcrl_lite.mpc.solution.FALLBACK`); a batch call never raises because of one
bad problem and never returns NaN in ``action``. A call with failures logs one warning that
counts them by status.
"""

from __future__ import annotations

import numpy as np

from ...config import MPCConfig
from ..formulation import MPC
from ..solution import (
    STATUS_BREAKDOWN,
    STATUS_CONVERGED,
    STATUS_MAX_ITER,
    STATUS_NON_FINITE,
    BackendBase,
    BatchSolution,
    MPCSolution,
    Sensitivity,
    StartSettings,
)
from .batch_adjoint import batch_sensitivity
from .batch_kkt import TINY, BatchData, BatchKKT, KKTFactor

__all__ = ["BatchSolver"]

_ETA = 0.995  # fraction to the boundary


class BatchSolver(StartSettings, BackendBase):
    r"""Vectorised primal-dual interior point for the MPC's barrier problem.

    See the module docstring for the method.

    Parameters
    ----------
    mpc
        The formulation; :class:`~mpcrl_lite.mpc.backends.batch_kkt.BatchKKT` re-derives its QP data in
        numpy and checks them.
    config
        ``tau`` (fixed barrier parameter), ``tol`` (scaled KKT residual, see
        :meth:`residual`), ``max_iter`` (Newton steps per problem), ``warm_start`` (use
        ``x0`` when given), ``kkt_cond_max`` (sensitivity conditioning limit).

    Notes
    -----
    The interface is :class:`~mpcrl_lite.mpc.solution.SolverBackend` (:meth:`solve` and
    :meth:`solve_batch` from :class:`~mpcrl_lite.mpc.solution.BackendBase`, around
    :meth:`_solve_parameters`; :meth:`sensitivity`, which returns what
    :class:`~mpcrl_lite.mpc.sensitivity.PolicySensitivity` returns) plus :meth:`residual` and
    :meth:`shift` for warm starts. The QP data, layout and factorisation are in
    :attr:`kkt` (:class:`~mpcrl_lite.mpc.backends.batch_kkt.BatchKKT`).
    """

    name = "batch"

    # The starting point and path-following settings (u0_fraction, t0_cold, t0_warm,
    # warm_margin, warm_weight, slack_margin, switch_factor) are StartSettings' class
    # attributes.

    def __init__(self, mpc: MPC, config: MPCConfig | None = None) -> None:
        self.mpc = mpc
        self.config = config or MPCConfig()
        #: the structured KKT system (QP data, layout, factorisation), checked against ``mpc``
        self.kkt = BatchKKT(mpc)
        kkt = self.kkt
        self.n, self.N = kkt.n, kkt.N
        self.U, self.P, self.hi, self.lo = kkt.U, kkt.P, kkt.hi, kkt.lo

    # ------------------------------------------------------------------ Newton ------------
    def _direction(self, f: KKTFactor, data: BatchData, base, rp, Mu, t, corr=None):
        """Newton direction for the barrier targets ``t`` (days,), optionally with Mehrotra's
        corrector term ``corr`` (days, m).

        Returns dX, dL, dMu, dS (flat inequality arrays) and a per-problem success flag.
        """
        U = t[:, None] / f.S if corr is None else (t[:, None] - corr) / f.S
        r1 = self.kkt.apply_Ct(U)
        r1 += base
        np.negative(r1, out=r1)
        dX, dL, ok = self.kkt.solve_reduced(f, data, r1[..., None], -rp[..., None])
        dX, dL = dX[..., 0], dL[..., 0]
        dS = self.kkt.slacks(dX, offset=False)
        dMu = U - Mu - f.D * dS
        return dX, dL, dMu, dS, ok

    @staticmethod
    def _step_lengths(S, Mu, dS, dMu, eta: float):
        """Largest primal and dual steps in (0, 1] keeping S and mu positive (fraction
        ``eta`` of the way to the boundary)."""
        ap = (S / np.maximum(-dS, TINY)).min(axis=1)
        ad = (Mu / np.maximum(-dMu, TINY)).min(axis=1)
        return np.minimum(1.0, eta * ap), np.minimum(1.0, eta * ad)

    # ------------------------------------------------------------ starting points ---------
    def _initial_point(self, data: BatchData, x0: np.ndarray | None):
        """Strictly interior primal point and multipliers on the central path of ``t0``.

        Cold start: ``b^i = s^i = u0^i`` (a fraction of ``min(U_bar^i, P_bar / n)``, each
        battery's own); warm start: ``x0``'s ``b, s`` pushed into the interior (one margin,
        relative to the smallest ``min(U_bar^i, P_bar / n)``) and blended with ``u0`` (see the
        class attributes). soc then follows the dynamics (so
        ``A x = e`` holds), the slack variables sit :attr:`slack_margin` above their kinks,
        ``mu = t0 / S`` and ``lam`` solves the soc rows of the dual residual exactly (a
        backward recursion from ``lam_N = 0``).
        """
        days, n, N = data.qb.shape[0], self.n, self.N
        X = np.empty((days, 5, n, N))
        cap_u = np.minimum(self.U, self.P / n)  # (n, 1): each battery's share of the bounds
        u0 = self.u0_fraction * cap_u
        if x0 is None:
            X[:, :2] = u0
            t0 = self.t0_cold * data.scale
        else:
            X0 = self.kkt.to_internal_x(np.asarray(x0, dtype=float))
            margin = self.warm_margin * float(cap_u.min())  # one margin for every bound
            bs = np.where(np.isfinite(X0[:, :2]), X0[:, :2], margin)
            w = self.warm_weight
            X[:, :2] = w * np.clip(bs, margin, self.U - margin) + (1.0 - w) * u0
            tot = X[:, :2].sum(axis=2, keepdims=True)
            cap = self.P - n * margin
            X[:, :2] *= np.where(tot > cap, cap / np.maximum(tot, TINY), 1.0)
            t0 = self.t0_warm * data.scale
        inc = data.alpha * (X[:, 0] - X[:, 1]) + data.delta
        X[:, 2] = data.soc0[:, :, None] + np.cumsum(inc, axis=2)
        X[:, 3] = np.maximum(X[:, 2] - self.hi, 0.0) + self.slack_margin
        X[:, 4] = np.maximum(self.lo - X[:, 2], 0.0) + self.slack_margin
        Mu = t0[:, None] / self.kkt.slacks(X)
        ML = self.kkt.agent(Mu)
        rsoc = data.hsoc * X[:, 2] + data.qsoc + ML[:, 4] - ML[:, 5]
        L = -np.cumsum(rsoc[..., ::-1], axis=2)[..., ::-1]
        return X, np.ascontiguousarray(L), Mu

    # ------------------------------------------------------------------- solving ----------
    def _solve_parameters(self, P: np.ndarray, x0: np.ndarray | None) -> BatchSolution:
        """All problems of the parameter vectors ``P`` (days, np) at once (the hook of
        :meth:`~mpcrl_lite.mpc.solution.BackendBase.solve_batch`).

        Only the ``b, s`` of a warm start ``x0`` (days, nx) are used (pushed into the interior
        and blended with the cold start, see the class attributes; non-finite entries are
        ignored); soc follows from the dynamics. The solutions are exact barrier solutions in
        :mod:`mpcrl_lite.mpc.formulation`'s orderings; rows that failed have the status
        :data:`STATUS_MAX_ITER`, :data:`STATUS_NON_FINITE` or :data:`STATUS_BREAKDOWN`, and
        their ``x, lam, mu`` are the last iterate. Rows with different theta (runs or
        candidates stacked in one call) are solved group by group, each group as its own
        batch, so every row gets its own theta's solution.
        """
        groups = self.kkt.theta_groups(P, np.arange(P.shape[0]))
        if len(groups) == 1:  # one theta for all rows: the common path
            return self._solve_group(P, x0)
        # one interior point per theta (the QP data share theta within a run of _run)
        parts = [(idx, self._solve_group(P[idx], None if x0 is None else x0[idx]))
                 for idx in groups]
        days = P.shape[0]
        out = {}
        for key in ("action", "x", "lam", "mu", "cost", "success", "iterations"):
            first = getattr(parts[0][1], key)
            arr = np.empty((days, *first.shape[1:]), dtype=first.dtype)
            for idx, sol in parts:
                arr[idx] = getattr(sol, key)
            out[key] = arr
        status = np.empty(days, dtype=object)
        for idx, sol in parts:
            status[idx] = sol.status
        return BatchSolution(**out, status=tuple(str(s) for s in status), p=P)

    def _solve_group(self, P: np.ndarray, x0: np.ndarray | None) -> BatchSolution:
        """The problems of ``P`` (days, np) that share one theta."""
        data = self.kkt.batch_data(P)
        with np.errstate(all="ignore"):  # non-finite numbers are detected per problem
            X, L, Mu, iters, status = self._run(data, x0)
        success = status == STATUS_CONVERGED
        return BatchSolution(
            action=np.where(success[:, None], X[:, 0, :, 0] - X[:, 1, :, 0], 0.0),
            x=self.kkt.from_internal_x(X),
            lam=self.kkt.from_internal_lam(L),
            mu=self.kkt.mu_to_flat(Mu),
            cost=self.kkt.cost(X, data),
            success=success,
            status=tuple(str(s) for s in status),
            iterations=iters,
            p=P,
        )

    def _run(self, data: BatchData, x0: np.ndarray | None):
        """The interior-point iteration for all problems of ``data`` at once.

        Returns the final iterates (X, L, Mu), iteration counts and status strings.
        """
        cfg = self.config
        tau, tol, floor = cfg.tau, cfg.tol, cfg.tol * 1e-5
        days = data.qb.shape[0]
        X, L, Mu = self._initial_point(data, x0)
        iters = np.zeros(days, dtype=int)
        status = np.full(days, STATUS_MAX_ITER, dtype=object)
        # working set: compacted copies of the problems still running
        idx = np.arange(days)
        d, Xa, La, Mua = data, X.copy(), L.copy(), Mu.copy()
        final = np.zeros(days, dtype=bool)  # pure Newton steps at t = tau from now on
        failed = np.zeros(days, dtype=bool)
        err_prev = np.full(days, np.inf)
        while True:
            S = self.kkt.slacks(Xa)
            base = self.kkt.grad_lag_part(Xa, La, d)
            rd = self.kkt.apply_Ct(Mua)
            rd += base
            rp = self.kkt.apply_A(Xa, d)
            rp -= d.e
            err = self.kkt.errors(rd, rp, Mua, S, d, tau)
            # at the rounding floor, or one Newton step after reaching tol (quadratic
            # convergence; without ``polish``: at tol), or no more progress
            done = (err <= floor) | ((err <= tol) & ((not cfg.polish) | (err_prev <= tol)
                                                     | (err > 0.1 * err_prev)))
            bad = ~np.isfinite(err)
            stop = done | bad | failed | (iters[idx] >= cfg.max_iter)
            if np.any(stop):
                out = idx[stop]
                X[out], L[out], Mu[out] = Xa[stop], La[stop], Mua[stop]
                status[out[done[stop]]] = STATUS_CONVERGED
                status[out[bad[stop]]] = STATUS_NON_FINITE
                status[out[(failed & ~done & ~bad)[stop]]] = STATUS_BREAKDOWN
                keep = ~stop
                if not np.any(keep):
                    break
                idx = idx[keep]
                d = d.take(keep)
                Xa, La, Mua = Xa[keep], La[keep], Mua[keep]
                S, base, rp = S[keep], base[keep], rp[keep]
                err, final, failed = err[keep], final[keep], failed[keep]
            err_prev = err
            k = idx.size
            f, ok = self.kkt.factor(S, Mua, d)
            t = np.full(k, tau)
            corr = None
            if not np.all(final):
                # Mehrotra's predictor: the affine direction (target 0) and its step
                comp = Mua * S
                mu_avg = comp.mean(axis=1)
                _, _, dMu, dS, ok_a = self._direction(f, d, base, rp, Mua, np.zeros(k))
                ok &= ok_a
                ap, ad = self._step_lengths(S, Mua, dS, dMu, 1.0)
                mu_aff = ((Mua + ad[:, None] * dMu) * (S + ap[:, None] * dS)).mean(axis=1)
                sigma = np.clip(mu_aff / mu_avg, 0.0, 1.0) ** 3
                target = sigma * mu_avg
                t = np.where(final, tau, np.maximum(target, tau))
                corr = dS * dMu
                corr *= np.where(final, 0.0, 1.0)[:, None]
                final |= target <= self.switch_factor * tau
            dX, dL, dMu, dS, ok_n = self._direction(f, d, base, rp, Mua, t, corr)
            ok &= ok_n
            ap, ad = self._step_lengths(S, Mua, dS, dMu, _ETA)
            ok &= np.isfinite(ap) & np.isfinite(ad)
            if not np.all(ok):
                failed |= ~ok
                ap = np.where(ok, ap, 0.0)
                ad = np.where(ok, ad, 0.0)
                dX = np.where(ok[:, None, None, None], dX, 0.0)
                dL = np.where(ok[:, None, None], dL, 0.0)
                dMu = np.where(ok[:, None], dMu, 0.0)
            Xa += ap[:, None, None, None] * dX
            La += ad[:, None, None] * dL
            Mua += ad[:, None] * dMu
            iters[idx] += ok
        return X, L, Mu, iters, status

    # -------------------------------------------------------------- sensitivity ----------
    def sensitivity(self, solution: BatchSolution | MPCSolution) -> Sensitivity:
        r"""Policy sensitivities ``d pi / d theta`` of every problem in ``solution``.

        Works on any solution of this MPC (e.g. from :class:`~mpcrl_lite.mpc.backends.ipopt.IpoptSolver`
        too); problems with different theta are handled group by group.

        Returns
        -------
        Sensitivity
            ``grad`` (days, n_theta, n), ``ok``, ``cond`` (the proxy ``||K||_max ||Z||_max``)
            and ``reason``, as :class:`~mpcrl_lite.mpc.sensitivity.PolicySensitivity`.
        """
        return batch_sensitivity(self.kkt, solution, self.config.kkt_cond_max)

    def residual(self, solution: BatchSolution | MPCSolution) -> np.ndarray:
        """Scaled KKT residual of each problem of ``solution``, shape (days,), at
        ``config.tau`` (see :meth:`~mpcrl_lite.mpc.backends.batch_kkt.BatchKKT.residual`)."""
        return self.kkt.residual(solution, self.config.tau)
