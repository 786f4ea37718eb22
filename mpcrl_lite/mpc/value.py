r"""The MPC as a value function: :math:`V_\theta(s)` and :math:`Q_\theta(s, a)` with their
derivatives in theta.

The same barrier MPC (eq. 9 with eqs. 23a-23c, ``tau`` fixed; :mod:`mpcrl_lite.mpc.formulation`)
approximates both value functions, as in the action-value approach the paper's introduction
contrasts with the policy gradient (Gros & Zanon, IEEE TAC 2020):

.. math::
   V_\theta(s) = \min_x F_\theta(x; s), \qquad
   Q_\theta(s, a) = \min_x F_\theta(x; s)\ \text{ s.t. } \hat b_0 - \hat s_0 = a,

with :math:`F = f - \tau\sum_k \log(-h_k)` the barrier objective subject to the model
``g = 0``. So :math:`Q_\theta(s, \pi_\theta(s)) = V_\theta(s)`: the MPC's own first action
is the minimiser of :math:`Q_\theta(s, \cdot)`. The values are those of the *barrier*
problem (not of ``f`` alone), because only for them is the derivative below exact.

Derivatives (exact for the barrier problem at fixed tau). With the Lagrangian
:math:`\mathcal L = f + \lambda^\top g_e + \mu^\top h` (``g_e`` the model, and for Q also the
``n`` rows :math:`\hat b_0 - \hat s_0 - a`) and the KKT residual ``R(y, theta)`` of
:class:`~mpcrl_lite.mpc.formulation.KKT` at the solution ``y*``,

.. math::
   \nabla_\theta Q = \nabla_\theta\mathcal L(y^\star, \theta), \qquad
   \nabla^2_\theta Q = \nabla^2_{\theta\theta}\mathcal L
   - \nabla^2_{\theta y}\mathcal L\,\Big(\frac{\partial R}{\partial y}\Big)^{-1}
     \frac{\partial R}{\partial\theta},

the first by the envelope theorem (the barrier terms do not depend on theta: ``h`` has no
parameters), the second by differentiating the first along the KKT sensitivity
:math:`\partial y^\star / \partial\theta` (the implicit function theorem, as for eq. 20).
:math:`\nabla^2_{\theta\theta}\mathcal L = 0` here (the cost and the model are linear in
theta), so the Hessian is all curvature of the solution.

:class:`MPCValue` gives them for a batch of problems:

* :meth:`MPCValue.state_value` -- V at solutions of the policy problem from *any* back-end
  (the closed loop's own solutions: no extra solve);
* :meth:`MPCValue.action_value` -- Q at the given actions: the fixed-first-action problem,
  solved by IPOPT (the same options as :class:`~mpcrl_lite.mpc.backends.ipopt.IpoptSolver`)
  and polished by Newton steps on its KKT conditions to machine precision.

An action on (or outside) an input bound or a grid limit makes the fixed-first-action
barrier problem infeasible: such a row fails (``ok`` False); pull actions strictly inside
first (e.g. with :func:`mpcrl_lite.sim.exploration.exploration_center`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.sparse import csr_matrix

from .._util.lazy import lazy_module
from ..config import MPCConfig
from .backends.ipopt import IpoptSolver, _ipopt_options, newton_polish
from .formulation import MPC
from .q_kernel import FixedActionKernel
from .solution import BatchSolution, MPCSolution

ca = lazy_module("casadi")  # CasADi (~0.1-0.2 s of import) loads when first used

__all__ = ["MPCValue", "ValueDerivatives"]

#: Largest residual of the linear solve behind a Hessian (relative) that is trusted.
_HESSIAN_RESIDUAL_MAX = 1e-6


@dataclass(frozen=True)
class ValueDerivatives:
    r"""Values of the barrier MPC and their derivatives in theta, for a batch of problems.

    value : (days,) the barrier objective at the solution (NaN where not ``ok``)
    grad : (days, n_theta) :math:`\nabla_\theta` of the value (zeros where not ``ok``)
    hess : (days, n_theta, n_theta) or None -- the Hessian in theta (when asked for)
    ok : (days,) the solve converged and the derivatives are usable
    reason : tuple of str, '' where ``ok``
    solution : the solutions they were computed at (x, lam, mu; for Q ``lam`` has
        ``neq + n`` entries: the model's multipliers, then the first action's)
    """

    value: np.ndarray
    grad: np.ndarray
    hess: np.ndarray | None
    ok: np.ndarray
    reason: tuple[str, ...]
    solution: BatchSolution


class _Closed:
    """The barrier value and the theta gradient of the Lagrangian in closed form, for a batch
    (numpy; the CasADi expressions of :class:`_Problem` are the reference they are tested
    against). Both problems share them: the first action's rows do not depend on theta."""

    def __init__(self, mpc: MPC) -> None:
        self.mpc = mpc
        sysc, N = mpc.system, mpc.N
        gam = sysc.gamma ** np.arange(N + 1, dtype=float)
        stage = np.arange(N) < N - 1
        self.disc = gam[:N]  # price weights of stage j
        self.wsoc = np.where(stage, gam[1:], 0.0)  # phi(soc_{j+1}) weights
        self.whi = np.where(stage, gam[1:] * sysc.omega[0], sysc.omega_f[0])
        self.wlo = np.where(stage, gam[1:] * sysc.omega[1], sysc.omega_f[1])
        qp = mpc.qp_data(mpc.parameters(np.full(mpc.n, 0.5), np.zeros(N), np.zeros(N),
                                        np.ones(mpc.n_theta)))
        self.C, self.d = csr_matrix(qp.C), qp.d  # h = C x - d, independent of the parameters
        self.index = {k: mpc.index(k) for k in ("b", "s", "soc", "sigma_hi", "sigma_lo")}

    def __call__(self, x: np.ndarray, lam: np.ndarray, P: np.ndarray, tau: float
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(value, grad, h)`` for rows of x (days, nx), lam (days, >= neq), P (days, np)."""
        m, sysc = self.mpc, self.mpc.system
        n, N, days = m.n, m.N, x.shape[0]
        th = P[:, m.theta_slice].reshape(days, -1, n)
        tb, ts, p1, p2, p3, t1, t2, t3 = (th[:, k] for k in range(2, 10))
        soc0, buy, sell = P[:, :n], P[:, n:n + N], P[:, n + N:n + 2 * N]
        b, s, soc = x[:, self.index["b"]], x[:, self.index["s"]], x[:, self.index["soc"]]
        shi, slo = x[:, self.index["sigma_hi"]], x[:, self.index["sigma_lo"]]  # (days, N, n)
        lamg = lam[:, :m.neq].reshape(days, N, n)
        d, w = self.disc[None, :, None], self.wsoc[None, :, None]
        socN = soc[:, -1]
        f = (np.sum(d * ((buy[..., None] + tb[:, None]) * b - (sell[..., None] + ts[:, None]) * s),
                    axis=(1, 2))
             + np.sum(w * (p1[:, None] * soc**2 + p2[:, None] * soc + p3[:, None]), axis=(1, 2))
             + np.sum(self.whi[None, :, None] * shi + self.wlo[None, :, None] * slo, axis=(1, 2))
             + np.sum(t1 * socN**2 + t2 * socN + t3, axis=1)
             + np.sum(p1 * soc0**2 + p2 * soc0 + p3, axis=1)
             + np.sum(sysc.omega[0] * np.maximum(soc0 - sysc.soc_high, 0)
                      + sysc.omega[1] * np.maximum(sysc.soc_low - soc0, 0), axis=1))
        h = (self.C @ x.T).T - self.d
        with np.errstate(invalid="ignore", divide="ignore"):
            value = f - tau * np.sum(np.log(-h), axis=1)
        grad = np.concatenate([
            -np.sum(lamg * (b - s), axis=1), -np.sum(lamg, axis=1),
            np.sum(d * b, axis=1), -np.sum(d * s, axis=1),
            soc0**2 + np.sum(w * soc**2, axis=1), soc0 + np.sum(w * soc, axis=1),
            np.broadcast_to(1.0 + self.wsoc.sum(), (days, n)),
            socN**2, socN, np.ones((days, n)),
        ], axis=1)
        return value, grad, h


class _Problem:
    """One barrier problem ``min f - tau sum log(-h) s.t. ge(x, pe) = 0`` as CasADi Functions
    of ``y = (x, lam, mu)`` and its parameters ``pe``: value, the theta gradient and
    Hessian of the Lagrangian's value, the KKT residual and its Newton step."""

    def __init__(self, mpc: MPC, pe: ca.SX, ge: ca.SX, theta: ca.SX) -> None:
        x, _, f, _, h = mpc.symbols
        tau = ca.SX.sym("tau")
        lam = ca.SX.sym("lam", ge.numel())
        mu = ca.SX.sym("mu", mpc.nin)
        y = ca.vertcat(x, lam, mu)
        self.ny = y.numel()
        self.nx, self.nlam = mpc.nx, ge.numel()
        lagrangian = f + ca.dot(lam, ge) + ca.dot(mu, h)
        R = ca.vertcat(ca.gradient(lagrangian, x), ge, mu * h + tau)
        dL = ca.gradient(lagrangian, theta)
        value = f - tau * ca.sum1(ca.log(-h))
        self.value = ca.Function("barrier_value", [y, pe, tau], [value, dL])
        self.residual = ca.Function("value_residual", [y, pe, tau], [R])
        K = ca.jacobian(R, y)
        ym, pm, taum = ca.MX.sym("y", self.ny), ca.MX.sym("p", pe.numel()), ca.MX.sym("tau")
        jac = ca.Function("value_jacobians", [y, pe, tau], [K, ca.jacobian(R, theta), ca.jacobian(dL, y),
                                               ca.jacobian(dL, theta)])
        Km, Rt, Lty, Ltt = jac(ym, pm, taum)
        dy = -ca.solve(Km, Rt, "qr")  # the KKT sensitivity d y* / d theta
        res = ca.mmax(ca.fabs(ca.mtimes(Km, dy) + Rt)) / (1.0 + ca.mmax(ca.fabs(Rt)))
        self.hessian = ca.Function("value_hessian", [ym, pm, taum], [Ltt + ca.mtimes(Lty, dy), res])
        Rm = self.residual(ym, pm, taum)
        self.newton = ca.Function("value_newton", [ym, pm, taum], [-ca.solve(Km, Rm, "qr")])

    def split(self, y: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        return y[: self.nx], y[self.nx : self.nx + self.nlam], y[self.nx + self.nlam :]


class MPCValue:
    r"""The MPC of ``mpc`` as :math:`V_\theta` and :math:`Q_\theta` (see the module docstring).

    Parameters
    ----------
    mpc
        The formulation.
    config
        ``tau`` (the barrier parameter of every value), ``tol``, ``max_iter`` for the
        fixed-first-action solves.
    backend
        Who solves the fixed-first-action problems: ``'ipopt'`` (the reference) or
        ``'kernel'`` (:class:`~mpcrl_lite.mpc.q_kernel.FixedActionKernel`, the compiled
        interior point on the problem's split; ``N >= 2``).
    """

    def __init__(self, mpc: MPC, config: MPCConfig | None = None,
                 backend: str = "ipopt") -> None:
        if backend not in ("ipopt", "kernel"):
            raise ValueError(f"backend={backend!r}: expected 'ipopt' or 'kernel'")
        self.mpc = mpc
        self.config = config or MPCConfig()
        self.backend = backend
        self._kernel = FixedActionKernel(mpc, self.config) if backend == "kernel" else None
        x, p, _, g, h = mpc.symbols
        theta = p[mpc.theta_slice]
        self._closed = _Closed(mpc)
        self._v = _Problem(mpc, p, g, theta)
        a = ca.SX.sym("a", mpc.n)
        S = ca.DM(mpc.policy_selector)
        pq = ca.vertcat(p, a)
        gq = ca.vertcat(g, ca.mtimes(S, x) - a)
        self._q = _Problem(mpc, pq, gq, theta)
        # IPOPT on the fixed-first-action problem, with the reference back-end's options
        # and its split of h into simple bounds and general rows
        ref = IpoptSolver(mpc, self.config)
        self._ref = ref
        rows = ref._general_rows
        self._lbg = np.concatenate([np.zeros(mpc.neq + mpc.n), np.full(len(rows), -np.inf)])
        self._ubg = np.zeros(mpc.neq + mpc.n + len(rows))
        self._nlp = ca.nlpsol("mpc_q_ipopt", "ipopt",
                              {"x": x, "p": pq, "f": mpc.symbols[2],
                               "g": ca.vertcat(gq, h[rows])},
                              _ipopt_options(self.config))

    # -- V ---------------------------------------------------------------------------------
    def state_value(self, solution: BatchSolution, hessian: bool = False) -> ValueDerivatives:
        """:math:`V_\\theta` and its theta derivatives at solutions of the policy problem
        (any back-end's; rows that failed are not ``ok``)."""
        solution = BatchSolution.of(solution)
        ok = np.asarray(solution.success, bool).copy()
        reasons = ["" if s else f"solver failed: {st}" for s, st in zip(ok, solution.status,
                                                                        strict=True)]
        y = np.concatenate([solution.x, solution.lam, solution.mu], axis=1)
        return self._derivatives(self._v, y, solution.p, ok, reasons, hessian, solution)

    # -- Q ---------------------------------------------------------------------------------
    def action_value(
        self, soc0: np.ndarray, buy: np.ndarray, sell: np.ndarray, theta, a: np.ndarray,
        x0: np.ndarray | None = None, hessian: bool = False,
    ) -> ValueDerivatives:
        """:math:`Q_\\theta(s, a)` and its theta derivatives for a batch: soc0 and a (days, n),
        buy and sell (days, N), theta shared (or one vector per row, (days, n_theta)); ``x0``
        (days, nx) an optional primal start (e.g. the policy's solution at the same state)."""
        m = self.mpc
        P = m.parameters(soc0, buy, sell, theta)
        a = np.asarray(a, float)
        if P.ndim != 2 or a.shape != (P.shape[0], m.n):
            raise ValueError(f"a has shape {a.shape}; expected (days, n) = {(P.shape[0], m.n)}")
        if not np.all(np.isfinite(a)):
            raise ValueError("a contains non-finite values")
        if self._kernel is not None:
            batch = self._kernel.solve(P, a, x0)
        else:
            sols = []
            for d in range(P.shape[0]):
                guess = self._ref.default_guess() if x0 is None else np.asarray(x0[d], float)
                sols.append(self._solve_q(np.concatenate([P[d], a[d]]), guess))
            batch = BatchSolution.stack(sols, 0.0, "ipopt")
        ok = batch.success.copy()
        reasons = ["" if s else f"solver failed: {st}" for s, st in zip(ok, batch.status,
                                                                        strict=True)]
        y = np.concatenate([batch.x, batch.lam, batch.mu], axis=1)
        return self._derivatives(self._q, y, batch.p, ok, reasons, hessian, batch)

    def _solve_q(self, pq: np.ndarray, x0: np.ndarray):
        m, cfg = self.mpc, self.config
        nlam = m.neq + m.n
        try:
            out = self._nlp(x0=x0, p=pq, lbx=self._ref._lbx, ubx=self._ref._ubx,
                            lbg=self._lbg, ubg=self._ubg)
            status = str(self._nlp.stats().get("return_status", "unknown"))
            iterations = int(self._nlp.stats().get("iter_count", -1))
            x = np.array(out["x"]).ravel()
            lam = np.array(out["lam_g"]).ravel()[:nlam]
        except RuntimeError as err:
            status, iterations = f"error: {err}", -1
            x, lam = np.asarray(x0, float), np.zeros(nlam)
        converged = status in ("Solve_Succeeded", "Solved_To_Acceptable_Level")
        q = self._q
        x, lam, mu, polished, why = newton_polish(
            q.residual, q.newton, lambda xs: m.evaluate(xs, pq[: m.np])[2], q.split,
            x, lam, pq, cfg.tau, m.nin)
        success = bool(converged and polished and np.all(np.isfinite(x)))
        if converged and not polished:
            status = f"kkt_polish_failed: {why}" if why else "kkt_polish_failed"
        action = m.policy_selector @ x
        f = float(m.fgh(x, pq[: m.np])[0]) if np.all(np.isfinite(x)) else np.nan
        return MPCSolution(action, x, lam, mu, f, success, status, iterations, pq)

    # -- derivatives -----------------------------------------------------------------------
    def _derivatives(self, problem: _Problem, y: np.ndarray, P: np.ndarray, ok: np.ndarray,
                     reasons: list[str], hessian: bool, solution: BatchSolution
                     ) -> ValueDerivatives:
        days, nt, tau, m = y.shape[0], self.mpc.n_theta, self.config.tau, self.mpc
        value = np.full(days, np.nan)
        grad = np.zeros((days, nt))
        hess = np.zeros((days, nt, nt)) if hessian else None
        x, lam = y[:, :m.nx], y[:, m.nx:m.nx + problem.nlam]
        v_all, g_all, _ = self._closed(x, lam, P[:, :m.np], tau)
        # the rows at once (a month of Q-learning asks for 1,440 of them); a row's value and
        # gradient are copied as they are
        finite = np.isfinite(v_all) & np.isfinite(g_all).all(axis=1)
        for d in np.flatnonzero(ok & ~finite).tolist():
            ok[d], reasons[d] = False, "non-finite value (a point outside the barrier's domain)"
        value[ok] = v_all[ok]
        grad[ok] = g_all[ok]
        for d in np.flatnonzero(ok).tolist() if hessian else ():
            try:
                H, res = problem.hessian(y[d], P[d], tau)
            except RuntimeError:
                H, res = np.nan, np.inf
            H, res = np.array(H), float(res)
            if not (np.all(np.isfinite(H)) and res <= _HESSIAN_RESIDUAL_MAX):
                ok[d], reasons[d] = False, "singular or ill-conditioned KKT matrix"
                value[d], grad[d] = np.nan, 0.0
                continue
            hess[d] = 0.5 * (H + H.T)
        return ValueDerivatives(value, grad, hess, ok, tuple(reasons), solution)
