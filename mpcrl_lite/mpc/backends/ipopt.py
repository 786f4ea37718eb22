"""The reference MPC back-end: IPOPT through CasADi's ``nlpsol``, then Newton polishing.

IPOPT solves the barrier problem of :mod:`mpcrl_lite.mpc.formulation` with the barrier parameter held at
``tau`` (``mu_target = tau``, no scaling, no bound relaxation, no damping). At most a few
Newton steps on the barrier problem's KKT conditions (:class:`mpcrl_lite.mpc.formulation.KKT`) then make
the solution exact to machine precision, which the sensitivities (paper eq. 20, computed by
:class:`~mpcrl_lite.mpc.sensitivity.PolicySensitivity`) need.

Failures never raise mid-run: IPOPT errors, non-convergence and a polish that cannot proceed
(e.g. a Newton step that CasADi cannot evaluate at a tiny ``tau``) are reported as
``success = False`` with a status saying why, and the action is the fallback
(:data:`~mpcrl_lite.mpc.solution.FALLBACK`).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from ..._util.lazy import lazy_module
from ...config import MPCConfig
from ..formulation import MPC
from ..sensitivity import PolicySensitivity
from ..solution import BackendBase, BatchSolution, MPCSolution, Sensitivity

ca = lazy_module("casadi")  # CasADi (~0.1-0.2 s of import) loads when first used

__all__ = ["STATUS_POLISH_FAILED", "IpoptSolver", "newton_polish"]

#: Status (prefix) of a problem IPOPT solved but whose Newton polish failed.
STATUS_POLISH_FAILED = "kkt_polish_failed"
#: IPOPT's return statuses that count as converged.
_IPOPT_CONVERGED = ("Solve_Succeeded", "Solved_To_Acceptable_Level")
#: Inequality groups IPOPT gets as general constraints; the others are simple bounds on x
#: (lbx/ubx: the same barrier problem, cheaper for IPOPT).
_GENERAL_INEQUALITIES = ("grid_b", "grid_s", "soc_max", "soc_min")


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


def _casadi_reason(err: RuntimeError) -> str:
    """The last clause of a CasADi error (its first lines are source locations)."""
    lines = [line for line in str(err).splitlines() if line.strip()]
    return lines[-1].rsplit(": ", 1)[-1].strip() if lines else type(err).__name__


def newton_polish(
    residual: ca.Function, newton: ca.Function, h_of: Callable[[np.ndarray], np.ndarray],
    split: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray, np.ndarray]],
    x: np.ndarray, lam: np.ndarray, p: np.ndarray, tau: float, nin: int, steps: int = 8,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, bool, str]:
    """Newton steps on a barrier problem's KKT conditions (``residual(y, p, tau)`` and its
    step ``newton(y, p, tau)``, ``y = (x, lam, mu)`` cut by ``split``, ``h_of(x)`` the
    inequalities) from a solver's point, keeping h < 0 and mu > 0; returns
    ``(x, lam, mu, ok, why)`` with ``ok`` when the residual is tiny and ``why`` naming an
    evaluation failure ('' otherwise). A Newton step that CasADi cannot evaluate (its sparse
    QR fails on a numerically singular KKT matrix, e.g. at ``tau = 1e-11``) ends the polish
    with ``ok`` False instead of raising."""
    h = h_of(x)
    if not np.all(h < 0):
        return x, lam, np.zeros(nin), False, ""
    mu = tau / -h
    y = np.concatenate([x, lam, mu])
    scale = 1.0 + np.abs(p).max()
    r = np.array(residual(y, p, tau)).ravel()
    try:
        for _ in range(steps):
            if np.max(np.abs(r)) == 0.0:
                break
            dy = np.array(newton(y, p, tau)).ravel()
            if not np.all(np.isfinite(dy)):
                break
            xs, _, mus = split(y)
            dx, _, dmu = split(dy)
            h = h_of(xs)
            dh = h_of(xs + dx) - h
            step = 1.0
            neg = dh > 0
            if np.any(neg):
                step = min(step, 0.99 * np.min(-h[neg] / dh[neg]))
            neg = dmu < 0
            if np.any(neg):
                step = min(step, 0.99 * np.min(-mus[neg] / dmu[neg]))
            y_new = y + step * dy
            r_new = np.array(residual(y_new, p, tau)).ravel()
            if not np.max(np.abs(r_new)) < np.max(np.abs(r)):
                break  # no more progress: at machine precision
            # a full Newton step that gains less than two digits is at the rounding level
            at_floor = step == 1.0 and np.max(np.abs(r_new)) > 1e-2 * np.max(np.abs(r))
            y, r = y_new, r_new
            if at_floor:
                break
    except RuntimeError as err:
        x, lam, mu = split(y)
        return x, lam, mu, False, f"Newton step failed ({_casadi_reason(err)})"
    x, lam, mu = split(y)
    ok = bool(np.all(np.isfinite(r)) and np.max(np.abs(r)) <= 1e-6 * scale)
    return x, lam, mu, ok, ""


class IpoptSolver(BackendBase):
    """Reference back-end: IPOPT on the barrier problem, then Newton polishing.

    :meth:`solve` and :meth:`solve_batch` come from
    :class:`~mpcrl_lite.mpc.solution.BackendBase`; the problems of a batch are solved one by one.

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
        # the interior points' stop without polishing: refused where IPOPT was asked for by
        # name, ignored where 'auto' fell back to it (a non-convex theta)
        if not self.config.polish and self.config.backend == "ipopt":
            raise ValueError("MPCConfig.polish=False: the IPOPT back-end has its own stopping "
                             "rule; expected polish=True, or backend 'kernel' or 'batch'")
        x, p, f, g, h = mpc.symbols
        sysc = mpc.system
        m = mpc
        lbx = np.full(m.nx, -np.inf)
        ubx = np.full(m.nx, np.inf)
        for name in ("b", "s"):
            lbx[m.index(name)] = 0.0
            ubx[m.index(name)] = np.array(sysc.battery("U_bar"))  # (N, n), each battery's
        for name in ("sigma_hi", "sigma_lo"):
            lbx[m.index(name)] = 0.0
        self._lbx, self._ubx = lbx, ubx
        # rows of h that are not simple bounds, in the order of h
        self._general_rows = np.sort(
            np.concatenate([m.inequality_index(k).ravel() for k in _GENERAL_INEQUALITIES])
        )
        rows = self._general_rows
        g_all = ca.vertcat(g, h[rows])
        self._lbg = np.concatenate([np.zeros(m.neq), np.full(len(rows), -np.inf)])
        self._ubg = np.zeros(m.neq + len(rows))
        self._nlp = ca.nlpsol("mpc_ipopt", "ipopt", {"x": x, "p": p, "f": f, "g": g_all},
                              _ipopt_options(self.config))
        self._kkt = mpc.kkt
        self._sensitivity: PolicySensitivity | None = None

    # -- one problem ---------------------------------------------------------------------
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
        converged = status in _IPOPT_CONVERGED
        x, lam, mu, polished, why = self._polish(x, lam, p)
        success = converged and polished
        if converged and not polished:
            status = f"{STATUS_POLISH_FAILED}: {why}" if why else STATUS_POLISH_FAILED
        if not np.all(np.isfinite(x)):
            success = False
        action = m.policy_selector @ x if success else np.zeros(m.n)
        f = float(self.mpc.fgh(x, p)[0]) if np.all(np.isfinite(x)) else np.nan
        return MPCSolution(action, x, lam, mu, f, bool(success), status, iterations, p)

    def _polish(
        self, x: np.ndarray, lam: np.ndarray, p: np.ndarray, steps: int = 8
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, bool, str]:
        """Newton steps on the barrier KKT system from IPOPT's point (:func:`newton_polish`
        with the policy problem's KKT conditions)."""
        kkt = self._kkt
        return newton_polish(kkt.residual, kkt.newton, lambda xs: self.mpc.evaluate(xs, p)[2],
                             kkt.split, x, lam, p, self.config.tau, self.mpc.nin, steps)

    def default_guess(self) -> np.ndarray:
        """A strictly feasible interior starting point (mid-range inputs, soc at 0.5)."""
        m, sysc = self.mpc, self.mpc.system
        x0 = np.zeros(m.nx)
        u0 = min(0.25 * min(sysc.battery("U_bar")), 0.25 * sysc.P_bar / m.n)
        x0[m.index("b")] = u0
        x0[m.index("s")] = u0
        x0[m.index("soc")] = 0.5
        x0[m.index("sigma_hi")] = 0.1
        x0[m.index("sigma_lo")] = 0.1
        return x0

    def sensitivity(self, solution: MPCSolution | BatchSolution) -> Sensitivity:
        """grad_theta pi at ``solution`` (see :class:`mpcrl_lite.mpc.sensitivity.PolicySensitivity`,
        built on first use)."""
        if self._sensitivity is None:
            self._sensitivity = PolicySensitivity(self.mpc, self.config)
        return self._sensitivity(solution)

    # -- batches --------------------------------------------------------------------------
    def _solve_parameters(self, P: np.ndarray, x0: np.ndarray | None) -> BatchSolution:
        """IPOPT and the polish on each row of ``P`` (days, np) in turn, from the row of
        ``x0`` (days, nx) or :meth:`default_guess` (the hook of
        :meth:`~mpcrl_lite.mpc.solution.BackendBase.solve_batch`)."""
        return BatchSolution.stack(
            [self._solve_p(P[d], None if x0 is None else x0[d]) for d in range(P.shape[0])]
        )
