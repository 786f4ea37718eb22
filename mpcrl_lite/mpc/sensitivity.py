r"""Policy sensitivity d pi / d theta from the KKT conditions of the solved MPC (paper eq. 20).

At a solution ``y* = (x*, lam*, mu*)`` of the barrier problem, ``R(y*, p) = 0`` (see
:class:`mpcrl_lite.mpc.formulation.KKT`). The implicit function theorem gives

.. math:: \frac{\partial y^\star}{\partial\theta} = -\Big(\frac{\partial R}{\partial y}\Big)^{-1}
          \frac{\partial R}{\partial\theta},\qquad
          \nabla_\theta\pi = \Big(S_y\frac{\partial y^\star}{\partial\theta}\Big)^\top ,

where ``S_y`` picks ``b_0 - s_0`` out of ``y``. Because only the ``n`` rows of the policy
are needed, we solve the adjoint system ``(dR/dy)^T Z = S_y^T`` (``n`` right-hand sides
instead of ``n_theta``) and return ``grad_theta pi = -(dR/dtheta)^T Z`` of shape
``(n_theta, n)``.

This is exact for the barrier problem with ``tau`` fixed (relaxed complementarity
``mu * h = -tau``); CasADi's own derivative of an ``nlpsol`` call is *not* used: on this
problem it treats tiny inactive multipliers as active and returns wrong values.

A KKT matrix that is singular or too ill-conditioned to trust is detected (non-finite
solution, a large solve residual, or ``||K||_max ||Z||_max`` above
``MPCConfig.kkt_cond_max``) and reported in :class:`Sensitivity` rather than raised.

This is the reference every back-end is tested against; the IPOPT back-end
(:mod:`mpcrl_lite.mpc.backends.ipopt`) uses it as its own ``sensitivity``. It needs only the
formulation (:mod:`mpcrl_lite.mpc.formulation`) and the solution types (:mod:`mpcrl_lite.mpc.solution`).
"""

from __future__ import annotations

import numpy as np

from .._util.lazy import lazy_module
from ..config import MPCConfig
from .formulation import MPC
from .solution import BatchSolution, MPCSolution, Sensitivity

ca = lazy_module("casadi")  # CasADi (~0.1-0.2 s of import) loads when first used

# Sensitivity is defined in mpcrl_lite.mpc.solution (below every back-end) and kept importable
# from here.
__all__ = ["PolicySensitivity", "policy_sensitivity"]


class PolicySensitivity:
    """KKT sensitivities for one MPC formulation (paper eq. 20); CasADi Functions built once.

    Parameters
    ----------
    mpc
        The formulation.
    config
        Uses ``tau`` and ``kkt_cond_max``.
    """

    def __init__(self, mpc: MPC, config: MPCConfig | None = None) -> None:
        self.mpc = mpc
        self.config = config or MPCConfig()
        kkt = mpc.kkt
        ny = kkt.ny
        S_y = np.zeros((mpc.n, ny))
        S_y[:, : mpc.nx] = mpc.policy_selector
        y = ca.MX.sym("y", ny)
        p = ca.MX.sym("p", mpc.np)
        tau = ca.MX.sym("tau")
        K, R_theta = kkt.jacobians(y, p, tau)
        St = ca.DM(S_y.T)
        Z = ca.solve(K.T, St, "qr")
        grad = -ca.mtimes(R_theta.T, Z)
        residual = ca.mmax(ca.fabs(ca.mtimes(K.T, Z) - St))
        cond = ca.mmax(ca.fabs(K)) * ca.mmax(ca.fabs(Z))
        self._function = ca.Function(
            "policy_sensitivity", [y, p, tau], [grad, residual, cond],
            ["y", "p", "tau"], ["grad", "residual", "cond"],
        )

    def __call__(self, solution: MPCSolution | BatchSolution) -> Sensitivity:
        """Sensitivities of every problem in ``solution`` (a single one gets days = 1)."""
        if isinstance(solution, MPCSolution):
            solution = BatchSolution.stack([solution], 0.0, "")
        days = len(solution)
        n_theta, n = self.mpc.n_theta, self.mpc.n
        grads = np.zeros((days, n_theta, n))
        ok = np.zeros(days, dtype=bool)
        conds = np.full(days, np.inf)
        reasons = []
        y_all = np.concatenate([solution.x, solution.lam, solution.mu], axis=1)
        for d in range(days):
            if not solution.success[d]:
                reasons.append(f"solver failed: {solution.status[d]}")
                continue
            try:
                grad, residual, cond = self._function(y_all[d], solution.p[d], self.config.tau)
            except RuntimeError:  # CasADi's QR refuses an exactly singular matrix
                reasons.append("singular KKT matrix (the linear solve failed)")
                continue
            grad = np.array(grad)
            residual, cond = float(residual), float(cond)
            conds[d] = cond
            if not np.all(np.isfinite(grad)) or not np.isfinite(residual):
                reasons.append("singular KKT matrix")
            elif residual > 1e-6 or cond > self.config.kkt_cond_max:
                reasons.append(f"ill-conditioned KKT matrix (cond ~ {cond:.2e})")
            else:
                grads[d] = grad
                ok[d] = True
                reasons.append("")
        return Sensitivity(grads, ok, conds, tuple(reasons))


def policy_sensitivity(
    mpc: MPC, solution: MPCSolution | BatchSolution, config: MPCConfig | None = None
) -> Sensitivity:
    """One-off convenience wrapper around :class:`PolicySensitivity` (builds it each call;
    keep a :class:`PolicySensitivity` for repeated use)."""
    return PolicySensitivity(mpc, config)(solution)
