r"""A structure-exploiting interior point that solves all days of a month at once.

:class:`BatchSolver` is a drop-in replacement for :class:`~mpcrl_lite.solvers.IpoptSolver`.
It solves *the same barrier problem* (``tau`` fixed, see :mod:`mpcrl_lite.mpc`)

.. math:: \min_x\; \tfrac12 x^\top H x + q^\top x + c - \tau\sum_k \log(d - Cx)_k
          \quad\text{s.t.}\quad Ax = e

for a batch of problems (the ``days`` of a month at one hour: they share theta and differ in
``soc0`` and prices) in plain numpy, and computes the policy sensitivities
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
rounding level), or the residual is at the floor ``tol * 1e-5``, or it stopped improving. The
returned points satisfy the KKT conditions to about machine precision; the sensitivities are
exact only there. Steps keep ``S, mu > 0`` (fraction 0.995 to the boundary, separate primal
and dual step lengths). Finished problems leave the working set, so stragglers run alone.
The starting point is central for a barrier value proportional to the price scale (class
attributes of :class:`BatchSolver`). A warm start ``x0`` (e.g. the previous hour's solution
shifted by one stage, :meth:`BatchSolver.shift`) only moves the starting ``b, s``: a
primal-only warm start saves an interior point little (about 8 % of the iterations here).

**Linear algebra**, per Newton step and day (``n`` agents, ``N`` stages). ``H`` is diagonal
and every inequality except the two grid rows per stage involves one agent at one stage.

1. The slack variables ``sigma_hi, sigma_lo`` couple only with their own ``soc`` and are
   eliminated in closed form: ``W_soc = H_soc + D_4 D_6/(D_4 + D_6) + D_5 D_7/(D_5 + D_7)``
   (the per-agent inequality groups are numbered below).
2. With the grid "forces" ``g_b,j = D_grid,b,j sum_i db_ij`` (and ``g_s``) held fixed,
   ``b, s, soc`` have diagonal Hessians; eliminating them from the dynamics rows leaves per
   agent a symmetric positive definite, diagonally dominant **tridiagonal** system in
   ``d lambda``:

   .. math:: T_i\, d\lambda_i = \rho_i + \beta_{b,i}\circ g_b - \beta_{s,i}\circ g_s,\quad
             T = \mathrm{tridiag}(-V_{j-1},\ V_j + V_{j-1} + \alpha^2(1/W_b + 1/W_s),\ -V_j),

   ``V = 1/W_soc``, ``beta = alpha / W``. With the backward pivots ``g_j`` of
   ``T = U G U'``, ``T^{-1}`` is semiseparable: ``(T^{-1})_{jk} = (T^{-1})_{jj}
   prod_{l=j}^{k-1} V_l/g_{l+1}`` for ``j <= k`` and the diagonal is a sum of positive terms;
   all products are formed as exponentials of differences of cumulative log sums (no
   overflow, no cancellation). This costs ``O(N^2)`` per agent and ``O(N)`` Python-level
   operations, batched over ``days x agents``.
3. The grid rows give a Schur complement of size ``2N`` per day,
   ``M = diag(1/D_grid + sum_i 1/W) - sum_i B_i' T_i^{-1} B_i`` (symmetric positive definite;
   Jacobi-scaled, batched Cholesky). Back substitution recovers ``d lambda`` and then
   ``db, ds, d soc, d sigma``. Where a grid limit is hard (``D_grid sum_i 1/W >> 1``, e.g.
   ``tau = 1e-5`` with a free battery against a binding limit) the flow ``sum_i db_i`` is a
   tiny difference of order-one terms whose rounding error, multiplied by ``D_grid``, would
   spoil the step (Newton stalls near 1e-9); the back substitution therefore restores the
   exact relation ``sum_i db_i = g_b / D_grid`` by spreading the rounding-level difference
   over the agents like a change of ``g_b``.

One Newton step costs ``O(days n N^2 + days N^3)``; this is what makes ``n = 100`` batteries
cheap.

**Sensitivity.** By the implicit function theorem ``d pi/d theta = -(dR/dtheta)' Z`` with the
adjoint ``(dR/dy)' Z = S_y'`` (``S`` the policy selector, see
:mod:`mpcrl_lite.sensitivity`). ``h`` does not depend on theta, so the complementarity rows of
``dR/dtheta`` vanish and ``Z_mu = C Z_x / S`` drops out: ``(Z_x, Z_lambda)`` solve the *same*
reduced system as a Newton step, with the ``n`` right-hand sides ``(S', 0)``, and the
factorisation of the solution point is reused for all of them. Two ways to use it:

* few agents (``days n^2 N`` small): all ``n`` columns at once plus iterative refinement on
  the reduced system (at least one step). Refinement matters where the grid limit binds:
  there an agent's own response and the grid's response nearly cancel and small entries of
  the adjoint lose digits. After it the sensitivities agree with an extended-precision
  reference to about 1e-10 relative or better, also where the CasADi QR reference is off by
  up to 5e-4 (entries 1e-6 of their column's largest, ``tau = 1e-5``).
* many agents: column ``o`` is nonzero only at agent ``o``, so its solution is agent ``o``'s
  local solution plus every agent's response to the grid forces ``g^(o)`` (one ``2N`` solve
  per column); the responses of each agent to the ``2N`` unit grid forces are contracted
  with ``dR/dtheta`` once, so the cost is ``O(days n N^2 + days n^2 N)`` instead of
  ``O(days n^2 N^2)``. Without refinement, entries of columns pinned by a binding grid limit
  carry absolute errors of about 1e-11 of the column's scale.

``dR/dtheta`` in closed form (tested against CasADi's :attr:`~mpcrl_lite.mpc.KKT.jacobians`):

=========== ==========================================================================
theta part  ``grad[theta_i, o]`` (sums over the stages ``j``; ``Z = Z^(o)``)
=========== ==========================================================================
alpha       ``sum_j lam_ij (Zb - Zs)_ij + (b - s)_ij Zlam_ij``
delta       ``sum_j Zlam_ij``
b, s        ``-sum_j gamma^j Zb_ij``,  ``sum_j gamma^j Zs_ij``
phi1, phi2  ``-sum_{j<N-1} gamma^{j+1} (2 soc_ij, 1) Zsoc_ij``
T1, T2      ``-(2 soc_{i,N-1}, 1) Zsoc_{i,N-1}``
phi3, T3    0 (constants of the cost)
=========== ==========================================================================

``cond`` is the conditioning proxy ``||K||_max ||Z||_max`` of
:class:`~mpcrl_lite.sensitivity.PolicySensitivity`, computed from the same ``Z`` (for many
agents by forming ``Z`` a chunk of columns at a time).

Performance notes: everything is vectorised over ``days x agents``; only the tridiagonal
recursions (``N`` steps) and the ``2N`` Cholesky solves (one LAPACK call per day) loop in
Python. Products with many columns avoid BLAS calls large enough to be multithreaded, which
can stall badly on a busy machine.

Data and layout
---------------
The QP data are built in numpy from the system and theta (``H``, ``q``, ``c`` affine in the
prices, ``A`` from theta, ``C``, ``d`` constant). The constructor checks them against
:attr:`MPC.qp_function <mpcrl_lite.mpc.MPC.qp_function>` at a test point, so the CasADi
formulation stays the single source of truth (a mismatch raises at construction, never
mid-run). Internally arrays are agent-major, ``(days, ..., n, N)``; the results use
:mod:`mpcrl_lite.mpc`'s orderings exactly. Per-agent inequality groups (internal index ->
row of :mod:`mpcrl_lite.mpc`'s per-stage block of ``h``): 0 ``-b``, 1 ``b - U``, 2 ``-s``,
3 ``s - U``, 4 ``soc - hi - sigma_hi``, 5 ``lo - soc - sigma_lo``, 6 ``-sigma_hi``,
7 ``-sigma_lo``; the grid rows ``sum b - P``, ``sum s - P`` are stored after them.

Failures (no convergence within ``max_iter``, non-finite numbers, breakdown of the linear
algebra) are reported per problem (``success = False``, a status string, the fallback action
zeros, see :data:`~mpcrl_lite.solvers.FALLBACK`); a batch call never raises because of one
bad problem and never returns NaN in ``action``.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import casadi as ca
import numpy as np
from scipy.linalg.lapack import dpotrf as _dpotrf
from scipy.linalg.lapack import dpotrs as _dpotrs

from .config import MPCConfig
from .mpc import MPC
from .sensitivity import Sensitivity
from .solvers import BatchSolution, MPCSolution
from .theta import PARTS, Theta

__all__ = [
    "BatchSolver",
    "shift",
    "STATUS_CONVERGED",
    "STATUS_MAX_ITER",
    "STATUS_NON_FINITE",
    "STATUS_BREAKDOWN",
]

#: Status of a problem solved to the tolerance.
STATUS_CONVERGED = "converged"
#: Status of a problem that ran out of iterations.
STATUS_MAX_ITER = "max_iter_reached"
#: Status of a problem whose residual became NaN or infinite.
STATUS_NON_FINITE = "non_finite"
#: Status of a problem whose linear algebra broke down (singular or non-finite system).
STATUS_BREAKDOWN = "linear_algebra_breakdown"

_ETA = 0.995  # fraction to the boundary
_TINY = 1e-300
_BACKWARD_ERROR_MAX = 1e-6  # of the adjoint solve; above it a sensitivity is flagged
_N_PARTS = len(PARTS)
_FULL_ADJOINT_MAX = 1 << 17  # days n^2 N up to which the adjoint is formed in full (refined)
_RHS_BLOCK = 16  # right-hand sides per LAPACK call (see _cholesky_solve)
_REFINE_MAX = 4  # iterative refinement steps of the adjoint at most
_BACKWARD_ERROR_GOOD = 1e-14  # backward error at which refinement stops

# Per-agent slacks S_agent = _SLACK_OFFSET + _SLACK_MAP @ (b, s, soc, sigma_hi, sigma_lo)
_SLACK_MAP = np.array(
    [
        [1.0, 0.0, 0.0, 0.0, 0.0],  # 0: b                    (-b <= 0)
        [-1.0, 0.0, 0.0, 0.0, 0.0],  # 1: U - b               (b - U <= 0)
        [0.0, 1.0, 0.0, 0.0, 0.0],  # 2: s
        [0.0, -1.0, 0.0, 0.0, 0.0],  # 3: U - s
        [0.0, 0.0, -1.0, 1.0, 0.0],  # 4: hi - soc + sigma_hi
        [0.0, 0.0, 1.0, 0.0, 1.0],  # 5: soc - lo + sigma_lo
        [0.0, 0.0, 0.0, 1.0, 0.0],  # 6: sigma_hi
        [0.0, 0.0, 0.0, 0.0, 1.0],  # 7: sigma_lo
    ]
)
_SLACK_MAP_T = np.ascontiguousarray(_SLACK_MAP.T)
_ABS_SLACK_MAP = np.abs(_SLACK_MAP)
_ABS_SLACK_MAP_T = np.ascontiguousarray(_ABS_SLACK_MAP.T)


def shift(x: np.ndarray, n: int) -> np.ndarray:
    """Shift MPC solutions one stage forward, for warm starting the next hour.

    Stage ``j`` of the result is stage ``j + 1`` of ``x``; the last stage is repeated.

    Parameters
    ----------
    x
        Primal solutions in :mod:`mpcrl_lite.mpc`'s layout, shape ``(..., 5 n N)``.
    n
        Number of agents.

    Returns
    -------
    numpy.ndarray
        Array of the same shape as ``x``.
    """
    x = np.asarray(x, dtype=float)
    stage = 5 * n
    if x.shape[-1] % stage:
        raise ValueError(
            f"x has {x.shape[-1]} entries per problem; expected a multiple of 5 n = {stage}"
        )
    out = np.empty_like(x)
    out[..., :-stage] = x[..., stage:]
    out[..., -stage:] = x[..., -stage:]
    return out


@dataclass
class _Data:
    """QP data of a batch (one theta, per-day prices and soc0) in the internal layout.

    Per-agent arrays are ``(n, N)`` (theta only) or ``(days, n, N)``; ``alpha`` and ``delta``
    are ``(n, 1)`` for broadcasting along the stages.
    """

    alpha: np.ndarray
    delta: np.ndarray
    hsoc: np.ndarray  # diagonal of H on soc, (n, N)
    qsoc: np.ndarray  # (n, N)
    qshi: np.ndarray  # (N,)
    qslo: np.ndarray  # (N,)
    qb: np.ndarray  # (days, n, N)
    qs: np.ndarray  # (days, n, N)
    soc0: np.ndarray  # (days, n)
    c: np.ndarray  # constant of the cost, (days,)
    e: np.ndarray  # right-hand side of A x = e, (days, n, N)
    scale: np.ndarray  # 1 + largest price term of q, (days,)

    def take(self, idx: np.ndarray) -> "_Data":
        """The data of the problems ``idx`` only."""
        return _Data(
            self.alpha, self.delta, self.hsoc, self.qsoc, self.qshi, self.qslo,
            self.qb[idx], self.qs[idx], self.soc0[idx], self.c[idx], self.e[idx],
            self.scale[idx],
        )


@dataclass
class _Factor:
    """Factorisation of the reduced KKT matrix at one iterate (see the module docstring).

    Per-agent arrays are ``(days, n, N)``.
    """

    S: np.ndarray  # all slacks, (days, m)
    D: np.ndarray  # mu / S, (days, m)
    vb: np.ndarray  # 1 / W_b
    vs: np.ndarray  # 1 / W_s
    V: np.ndarray  # 1 / W_soc (slack variables eliminated)
    c4: np.ndarray  # D_4 / W_shi
    c5: np.ndarray  # D_5 / W_slo
    ishi: np.ndarray  # 1 / W_shi
    islo: np.ndarray  # 1 / W_slo
    beta_b: np.ndarray  # alpha / W_b
    beta_s: np.ndarray  # alpha / W_s
    Tinv: np.ndarray  # inverses of the tridiagonal T, (days, n, N, N)
    M: np.ndarray  # Jacobi-scaled grid Schur complement, (days, 2N, 2N)
    Mchol: np.ndarray  # its lower Cholesky factors
    Mscale: np.ndarray  # its scaling, (days, 2N)


class BatchSolver:
    r"""Vectorised primal-dual interior point for the MPC's barrier problem.

    See the module docstring for the method.

    Parameters
    ----------
    mpc
        The formulation. Its QP data are re-derived in numpy and checked against
        ``mpc.qp_function`` here (a mismatch raises :class:`RuntimeError`).
    config
        ``tau`` (fixed barrier parameter), ``tol`` (scaled KKT residual, see
        :meth:`residual`), ``max_iter`` (Newton steps per problem), ``warm_start`` (use
        ``x0`` when given), ``kkt_cond_max`` (sensitivity conditioning limit).

    Notes
    -----
    The interface is that of :class:`~mpcrl_lite.solvers.IpoptSolver` (:meth:`solve`,
    :meth:`solve_batch`) plus :meth:`sensitivity`, which returns what
    :class:`~mpcrl_lite.sensitivity.PolicySensitivity` returns, and :meth:`shift` for warm
    starts.
    """

    name = "batch"

    # Starting point and path-following settings (tuned on random states, prices and thetas;
    # class attributes so that experiments can change them).
    #: cold start: ``b = s = u0_fraction * min(U, P / n)``
    u0_fraction: float = 0.5
    #: initial barrier value ``mean(mu S)`` relative to the price scale ``1 + max |q|``
    t0_cold: float = 0.1
    t0_warm: float = 0.1
    #: warm start: ``b, s`` of ``x0`` kept this far from their bounds (relative to
    #: ``min(U, P / n)``) and blended with the cold start with this weight. A primal-only
    #: warm start helps an interior point little (about 8 % fewer iterations on the
    #: experiment's hour-to-hour problems); a full weight makes the slowest problems slower.
    warm_margin: float = 1e-2
    warm_weight: float = 0.3
    #: initial distance of sigma_hi, sigma_lo above their kinks
    slack_margin: float = 0.3
    #: switch to pure Newton steps at tau once Mehrotra's target is below this times tau
    switch_factor: float = 1.0

    def __init__(self, mpc: MPC, config: MPCConfig | None = None) -> None:
        self.mpc = mpc
        self.config = config or MPCConfig()
        sysc = mpc.system
        n, N = mpc.n, mpc.N
        self.n, self.N = n, N
        self.U, self.P = float(sysc.U_bar), float(sysc.P_bar)
        self.hi, self.lo = float(sysc.soc_high), float(sysc.soc_low)
        self._m_agent = 8 * n * N
        self._m = self._m_agent + 2 * N
        offset = np.array([0.0, self.U, 0.0, self.U, self.hi, -self.lo, 0.0, 0.0])
        self._offset = np.repeat(offset, n * N).reshape(8, n * N)
        gam = sysc.gamma ** np.arange(N + 1, dtype=float)
        self._disc = gam[:N]  # gamma^j, weights of the stage-j prices
        stage = np.arange(N) < N - 1
        # weights of the stage costs of soc_{j+1}: gamma^{j+1}; the terminal cost is undiscounted
        self._wsoc = np.where(stage, gam[1:], 0.0)
        self._term = (~stage).astype(float)
        self._qshi = np.where(stage, gam[1:] * sysc.omega[0], sysc.omega_f[0])
        self._qslo = np.where(stage, gam[1:] * sysc.omega[1], sysc.omega_f[1])
        self._upper = np.triu(np.ones((N, N), dtype=bool))
        self._theta_cache: tuple[np.ndarray, tuple] | None = None
        self._check_formulation()

    # ------------------------------------------------------------------ QP data ------------
    def _theta_parts(self, tvec: np.ndarray) -> tuple:
        """theta-only data, cached for the last theta (it changes once a month)."""
        if self._theta_cache is not None and np.array_equal(self._theta_cache[0], tvec):
            return self._theta_cache[1]
        n = self.n
        th = {name: tvec[i * n : (i + 1) * n] for i, name in enumerate(PARTS)}
        alpha = th["alpha"][:, None].copy()
        delta = th["delta"][:, None].copy()
        # H_soc = 2 gamma^{j+1} phi1 on the stages, 2 T1 at the end; q_soc likewise (phi2, T2)
        hsoc = 2.0 * (th["phi1"][:, None] * self._wsoc + th["T1"][:, None] * self._term)
        qsoc = th["phi2"][:, None] * self._wsoc + th["T2"][:, None] * self._term
        const = float(np.sum(self._wsoc) * th["phi3"].sum() + th["T3"].sum())
        parts = (alpha, delta, hsoc, qsoc, th, const)
        self._theta_cache = (tvec.copy(), parts)
        return parts

    def _data(self, P: np.ndarray) -> _Data:
        """Internal QP data of parameter vectors ``P`` (days, np) that share theta."""
        n, N = self.n, self.N
        sysc = self.mpc.system
        days = P.shape[0]
        soc0 = P[:, :n].copy()
        buy = P[:, n : n + N]
        sell = P[:, n + N : n + 2 * N]
        alpha, delta, hsoc, qsoc, th, const = self._theta_parts(P[0, self.mpc.theta_slice])
        qb = self._disc * (buy[:, None, :] + th["b"][None, :, None])
        qs = -self._disc * (sell[:, None, :] + th["s"][None, :, None])
        c = (
            (th["phi1"] * soc0**2 + th["phi2"] * soc0 + th["phi3"]).sum(axis=1)
            + (sysc.omega[0] * np.maximum(soc0 - self.hi, 0.0)
               + sysc.omega[1] * np.maximum(self.lo - soc0, 0.0)).sum(axis=1)
            + const
        )
        e = np.repeat(np.repeat(delta[None], days, axis=0), N, axis=2)
        e[:, :, 0] += soc0
        scale = 1.0 + np.maximum(np.abs(qb).reshape(days, -1).max(axis=1),
                                 np.abs(qs).reshape(days, -1).max(axis=1))
        return _Data(alpha, delta, hsoc, qsoc, self._qshi, self._qslo, qb, qs, soc0, c, e, scale)

    def _check_formulation(self) -> None:
        """Compare the numpy QP data with ``mpc.qp_function`` at a pseudo-random point
        (products with random vectors, so no dense matrices are formed)."""
        m = self.mpc
        rng = np.random.default_rng(12345)
        n, N = self.n, self.N
        theta = np.concatenate([
            rng.uniform(0.05, 0.12, n), rng.uniform(-0.01, 0.01, n), rng.uniform(-5, 5, 2 * n),
            rng.uniform(0, 50, n), rng.uniform(-50, 50, 2 * n),
            rng.uniform(0, 50, n), rng.uniform(-50, 50, 2 * n),
        ])
        p = m.parameters(rng.uniform(0.0, 1.0, n), rng.uniform(5, 130, N),
                         rng.uniform(5, 60, N), theta)
        H, q, c, A, e, C, d = m.qp_function(p)
        data = self._data(p[None, :])
        x = rng.standard_normal(m.nx)
        w = rng.standard_normal(m.nin)
        v = rng.standard_normal(m.neq)
        X = self._to_internal_x(x[None])
        HX = np.zeros_like(X)
        HX[:, 2] = data.hsoc * X[:, 2]
        Q = np.stack([data.qb, data.qs] + [np.broadcast_to(a, data.qb.shape)
                                           for a in (data.qsoc, data.qshi, data.qslo)], axis=1)
        mine = {
            "H x": self._from_internal_x(HX)[0],
            "q": self._from_internal_x(Q)[0],
            "c": data.c,
            "A x": self._from_internal_lam(self._apply_A(X, data))[0],
            "A' v": self._from_internal_x(
                self._grad_lag_part(np.zeros_like(X), self._to_internal_lam(v[None]), data)
                - Q)[0],
            "e": self._from_internal_lam(data.e)[0],
            "d - C x": self._mu_to_flat(self._slacks(X))[0],
            "C' w": self._from_internal_x(self._apply_Ct(self._mu_from_flat(w[None])))[0],
        }
        ref = {
            "H x": np.array(ca.mtimes(H, ca.DM(x))).ravel(),
            "q": np.array(q).ravel(),
            "c": np.array([float(c)]),
            "A x": np.array(ca.mtimes(A, ca.DM(x))).ravel(),
            "A' v": np.array(ca.mtimes(A.T, ca.DM(v))).ravel(),
            "e": np.array(e).ravel(),
            "d - C x": np.array(d).ravel() - np.array(ca.mtimes(C, ca.DM(x))).ravel(),
            "C' w": np.array(ca.mtimes(C.T, ca.DM(w))).ravel(),
        }
        for key, val in ref.items():
            err = float(np.max(np.abs(mine[key] - val)))
            if not err <= 1e-9 * (1.0 + float(np.max(np.abs(val)))):
                raise RuntimeError(
                    f"BatchSolver's QP data disagree with MPC.qp_function ({key}: max error "
                    f"{err:.3e}); the formulation in mpcrl_lite.mpc changed and "
                    "mpcrl_lite.batch_solver must be updated to match it"
                )

    # ---------------------------------------------------------------- layout --------------
    def _to_internal_x(self, x: np.ndarray) -> np.ndarray:
        """(days, nx) in mpc order -> (days, 5, n, N)."""
        days = x.shape[0]
        return np.ascontiguousarray(x.reshape(days, self.N, 5, self.n).transpose(0, 2, 3, 1))

    def _from_internal_x(self, X: np.ndarray) -> np.ndarray:
        """(days, 5, n, N) -> (days, nx) in mpc order."""
        return np.ascontiguousarray(X.transpose(0, 3, 1, 2)).reshape(X.shape[0], -1)

    def _to_internal_lam(self, lam: np.ndarray) -> np.ndarray:
        """(days, neq) in mpc order -> (days, n, N)."""
        return np.ascontiguousarray(lam.reshape(lam.shape[0], self.N, self.n).transpose(0, 2, 1))

    def _from_internal_lam(self, L: np.ndarray) -> np.ndarray:
        """(days, n, N) -> (days, neq) in mpc order."""
        return np.ascontiguousarray(L.transpose(0, 2, 1)).reshape(L.shape[0], -1)

    def _agent(self, A: np.ndarray) -> np.ndarray:
        """View of the per-agent groups of a flat inequality array (days, m): (days, 8, n, N)."""
        return A[:, : self._m_agent].reshape(A.shape[0], 8, self.n, self.N)

    def _grid(self, A: np.ndarray) -> np.ndarray:
        """View of the grid rows of a flat inequality array (days, m): (days, 2, N)."""
        return A[:, self._m_agent :].reshape(A.shape[0], 2, self.N)

    def _mu_to_flat(self, A: np.ndarray) -> np.ndarray:
        """Internal inequality array (days, m) -> (days, nin) in mpc order."""
        days, n, N = A.shape[0], self.n, self.N
        AL, AG = self._agent(A), self._grid(A)
        out = np.empty((days, N, 8 * n + 2))
        out[:, :, : 4 * n] = AL[:, :4].transpose(0, 3, 1, 2).reshape(days, N, 4 * n)
        out[:, :, 4 * n : 4 * n + 2] = AG.transpose(0, 2, 1)
        out[:, :, 4 * n + 2 :] = AL[:, 4:].transpose(0, 3, 1, 2).reshape(days, N, 4 * n)
        return out.reshape(days, -1)

    def _mu_from_flat(self, mu: np.ndarray) -> np.ndarray:
        """(days, nin) in mpc order -> internal inequality array (days, m)."""
        days, n, N = mu.shape[0], self.n, self.N
        blk = mu.reshape(days, N, 8 * n + 2)
        out = np.empty((days, self._m))
        AL, AG = self._agent(out), self._grid(out)
        AL[:, :4] = blk[:, :, : 4 * n].reshape(days, N, 4, n).transpose(0, 2, 3, 1)
        AL[:, 4:] = blk[:, :, 4 * n + 2 :].reshape(days, N, 4, n).transpose(0, 2, 3, 1)
        AG[:] = blk[:, :, 4 * n : 4 * n + 2].transpose(0, 2, 1)
        return out

    # ----------------------------------------------------------- structured products ------
    def _apply_A(self, X: np.ndarray, data: _Data) -> np.ndarray:
        """``A x`` (days, n, N): ``soc_j - soc_{j-1} - alpha (b_j - s_j)``."""
        soc = X[:, 2]
        out = soc - data.alpha * (X[:, 0] - X[:, 1])
        out[..., 1:] -= soc[..., :-1]
        return out

    def _slacks(self, X: np.ndarray, offset: bool = True) -> np.ndarray:
        """``S = d - C x`` (or ``-C x`` without ``offset``) as a flat array (days, m)."""
        days = X.shape[0]
        S = np.empty((days, self._m))
        SL = S[:, : self._m_agent].reshape(days, 8, -1)
        np.matmul(_SLACK_MAP, X.reshape(days, 5, -1), out=SL)
        SG = self._grid(S)
        np.sum(X[:, :2], axis=2, out=SG)
        if offset:
            SL += self._offset
            np.subtract(self.P, SG, out=SG)
        else:
            np.negative(SG, out=SG)
        return S

    def _apply_Ct(self, u: np.ndarray) -> np.ndarray:
        """``C' u`` in the internal x layout for a flat inequality array ``u`` (days, m)."""
        days = u.shape[0]
        out = (_SLACK_MAP_T @ u[:, : self._m_agent].reshape(days, 8, -1)).reshape(
            days, 5, self.n, self.N)
        np.negative(out, out=out)
        out[:, :2] += self._grid(u)[:, :, None, :]
        return out

    def _grad_lag_part(self, X: np.ndarray, L: np.ndarray, data: _Data) -> np.ndarray:
        """``H x + q + A' lam`` (days, 5, n, N)."""
        out = np.empty((L.shape[0], 5) + L.shape[1:])
        aL = data.alpha * L
        np.subtract(data.qb, aL, out=out[:, 0])
        np.add(data.qs, aL, out=out[:, 1])
        np.add(data.hsoc * X[:, 2] + data.qsoc, L, out=out[:, 2])
        out[:, 2, :, :-1] -= L[..., 1:]
        out[:, 3] = data.qshi
        out[:, 4] = data.qslo
        return out

    # ------------------------------------------------------------------ residual ----------
    @staticmethod
    def _errors(rd, rp, Mu, S, data: _Data, tau: float) -> np.ndarray:
        """Scaled KKT residual per problem from the dual and primal residuals."""
        days = rd.shape[0]
        ed = np.abs(rd).reshape(days, -1).max(axis=1)
        ec = np.abs(Mu * S - tau).max(axis=1)
        ep = np.abs(rp).reshape(days, -1).max(axis=1)
        err = np.maximum(np.maximum(ed, ec) / data.scale, ep)
        return np.where(np.isfinite(err), err, np.inf)

    def residual(self, solution: BatchSolution | MPCSolution) -> np.ndarray:
        r"""Scaled KKT residual of each problem of ``solution``, shape (days,).

        .. math:: \max\Big(\frac{\|r_d\|_\infty}{s},\ \|r_p\|_\infty,\
                  \frac{\|\mu\circ S - \tau\|_\infty}{s}\Big),\qquad
                  s = 1 + \max |\text{price terms of } q| :

        the dual, primal and complementarity residuals of the barrier problem, with the dual
        quantities measured relative to the prices (soc is of order one). The solver stops one
        Newton step after this is below ``config.tol`` (it ends near 1e-15).
        """
        if isinstance(solution, MPCSolution):
            solution = BatchSolution.stack([solution], 0.0, "")
        P = np.atleast_2d(solution.p)
        out = np.empty(P.shape[0])
        for idx in self._theta_groups(P, np.arange(P.shape[0])):
            data = self._data(P[idx])
            X = self._to_internal_x(np.asarray(solution.x)[idx])
            L = self._to_internal_lam(np.asarray(solution.lam)[idx])
            Mu = self._mu_from_flat(np.asarray(solution.mu)[idx])
            rd = self._grad_lag_part(X, L, data) + self._apply_Ct(Mu)
            rp = self._apply_A(X, data) - data.e
            out[idx] = self._errors(rd, rp, Mu, self._slacks(X), data, self.config.tau)
        return out

    def _theta_groups(self, P: np.ndarray, rows: np.ndarray) -> list[np.ndarray]:
        """Split ``rows`` of ``P`` into groups with equal theta."""
        thetas = P[rows][:, self.mpc.theta_slice]
        if np.all(thetas == thetas[:1]):
            return [rows]
        _, inverse = np.unique(thetas, axis=0, return_inverse=True)
        inverse = inverse.ravel()
        return [rows[inverse == g] for g in range(inverse.max() + 1)]

    # ------------------------------------------------------------ factorisation -----------
    def _factor(self, S: np.ndarray, Mu: np.ndarray, data: _Data) -> tuple[_Factor, np.ndarray]:
        """Factorise the reduced KKT matrix at slacks ``S`` and multipliers ``Mu`` (flat);
        also returns a per-problem flag, False where the factorisation broke down."""
        days, N = S.shape[0], self.N
        D = Mu / S
        DL = self._agent(D)
        ishi = 1.0 / (DL[:, 4] + DL[:, 6])
        islo = 1.0 / (DL[:, 5] + DL[:, 7])
        c4 = DL[:, 4] * ishi
        c5 = DL[:, 5] * islo
        V = 1.0 / (data.hsoc + c4 * DL[:, 6] + c5 * DL[:, 7])
        vb = 1.0 / (DL[:, 0] + DL[:, 1])
        vs = 1.0 / (DL[:, 2] + DL[:, 3])
        beta_b = data.alpha * vb
        beta_s = data.alpha * vs
        # tridiagonal T per (day, agent): diagonal a, off-diagonals -V[:-1]
        a = V + data.alpha * (beta_b + beta_s)
        a[..., 1:] += V[..., :-1]
        Tinv = _tridiag_inverse(a, V, self._upper)
        # grid Schur complement M = diag(1/D_grid + sum 1/W) - sum_i B_i' T_i^{-1} B_i
        M = np.empty((days, 2 * N, 2 * N))
        tb = Tinv * beta_b[:, :, None, :]
        ts = Tinv * beta_s[:, :, None, :]
        np.einsum("dnj,dnjk->djk", -beta_b, tb, out=M[:, :N, :N])
        np.einsum("dnj,dnjk->djk", beta_b, ts, out=M[:, :N, N:])
        np.einsum("dnj,dnjk->djk", -beta_s, ts, out=M[:, N:, N:])
        M[:, N:, :N] = M[:, :N, N:].transpose(0, 2, 1)
        mdiag = M.reshape(days, -1)[:, :: 2 * N + 1]  # a view of the diagonal
        mdiag += 1.0 / self._grid(D).reshape(days, 2 * N)
        mdiag[:, :N] += vb.sum(axis=1)
        mdiag[:, N:] += vs.sum(axis=1)
        ok = np.all(mdiag > 0, axis=1) & np.all(np.isfinite(mdiag), axis=1)
        scale = 1.0 / np.sqrt(np.where(ok[:, None], mdiag, 1.0))
        M *= scale[:, :, None]
        M *= scale[:, None, :]
        Mchol, ok_chol = _cholesky(M, ok)
        ok &= ok_chol
        f = _Factor(S, D, vb, vs, V, c4, c5, ishi, islo, beta_b, beta_s, Tinv, M, Mchol, scale)
        return f, ok

    def _solve_local(self, f: _Factor, data: _Data, r1: np.ndarray, r2: np.ndarray):
        """Solve every agent's own block ``K_i z_i = r_i`` (no grid forces).

        r1 (days, 5, n, N, k), r2 (days, n, N, k) for k right-hand sides; returns
        dx (days, 5, n, N, k) and dlam (days, n, N, k).
        """
        ex = (..., None)
        rb, rs, rshi, rslo = r1[:, 0], r1[:, 1], r1[:, 3], r1[:, 4]
        c4, c5, V = f.c4[ex], f.c5[ex], f.V[ex]
        rsoc = r1[:, 2] + c4 * rshi - c5 * rslo  # slack variables eliminated
        Vr = V * rsoc
        rho = Vr - r2 - f.beta_b[ex] * rb + f.beta_s[ex] * rs
        rho[:, :, 1:] -= Vr[:, :, :-1]
        dlam = f.Tinv @ rho
        adl = data.alpha[ex] * dlam
        dx = np.empty(r1.shape)
        np.multiply(f.vb[ex], rb + adl, out=dx[:, 0])
        np.multiply(f.vs[ex], rs - adl, out=dx[:, 1])
        dsoc = dx[:, 2]
        np.subtract(rsoc, dlam, out=dsoc)
        dsoc[:, :, :-1] += dlam[:, :, 1:]
        dsoc *= V
        np.multiply(f.ishi[ex], rshi, out=dx[:, 3])
        dx[:, 3] += c4 * dsoc
        np.multiply(f.islo[ex], rslo, out=dx[:, 4])
        dx[:, 4] -= c5 * dsoc
        return dx, dlam

    def _grid_response(self, f: _Factor, data: _Data, gb: np.ndarray, gs: np.ndarray):
        """Every agent's response ``z_i = R_i g`` to the grid forces ``g = (gb, gs)``.

        ``K_i z_i + E_i g = 0`` (``E_i`` adds ``gb`` to the b rows and ``gs`` to the s rows).
        gb, gs broadcast to (days, n, N, k); returns dx (days, 5, n, N, k), dlam (days, n, N, k).
        """
        ex = (..., None)
        dlam = f.Tinv @ (f.beta_b[ex] * gb - f.beta_s[ex] * gs)
        adl = data.alpha[ex] * dlam
        dx = np.empty((dlam.shape[0], 5) + dlam.shape[1:])
        np.multiply(f.vb[ex], adl - gb, out=dx[:, 0])
        np.multiply(f.vs[ex], -adl - gs, out=dx[:, 1])
        dsoc = dx[:, 2]
        np.negative(dlam, out=dsoc)
        dsoc[:, :, :-1] += dlam[:, :, 1:]
        dsoc *= f.V[ex]
        np.multiply(f.c4[ex], dsoc, out=dx[:, 3])
        np.multiply(-f.c5[ex], dsoc, out=dx[:, 4])
        return dx, dlam

    def _solve_reduced(self, f: _Factor, data: _Data, r1: np.ndarray, r2: np.ndarray):
        """Solve ``[[W, A'], [A, 0]] [dx; dlam] = [r1; r2]`` with the factorisation ``f``.

        Local solves of every agent, the grid forces ``g`` from ``M g = sum_i E_i' z_i``,
        then every agent's response to ``g``. r1 (days, 5, n, N, k), r2 (days, n, N, k) for
        k right-hand sides; returns dx (days, 5, n, N, k), dlam (days, n, N, k) and a
        per-problem success flag.
        """
        ex = (..., None)
        days, N = r1.shape[0], self.N
        dx, dlam = self._solve_local(f, data, r1, r2)
        q = dx[:, :2].sum(axis=2).reshape(days, 2 * N, -1)
        g, ok = _cholesky_solve(f.Mchol, q * f.Mscale[ex])
        g *= f.Mscale[ex]
        gx, glam = self._grid_response(f, data, g[:, None, :N], g[:, None, N:])
        dx += gx
        dlam += glam
        # Where a grid limit is hard (D_grid sum_i 1/W >> 1) the flow sum_i db_i is a tiny
        # difference of O(1) terms and its rounding error, times D_grid, would dominate the
        # b rows' residual. The exact solution has sum_i db_i = g_b / D_grid: restore that,
        # spreading the (rounding-level) difference over the agents like a change of g_b.
        g = g.reshape(days, 2, N, -1)
        for v, w in ((0, f.vb), (1, f.vs)):
            wsum = w.sum(axis=1)  # (days, N)
            DG = self._grid(f.D)[:, v]
            stiff = (DG * wsum)[..., None] > 1.0
            if np.any(stiff):
                delta = g[:, v] / DG[..., None] - dx[:, v].sum(axis=1)
                dx[:, v] += (w / wsum[:, None])[..., None] * np.where(stiff, delta, 0.0)[:, None]
        return dx, dlam, ok

    def _local_apply(self, f: _Factor, data: _Data, Zx: np.ndarray, Zl: np.ndarray,
                     absolute: bool = False):
        """Every agent's own block applied to ``(Zx, Zl)``, without the grid rows:
        ``([W_i, A_i'] z, A_i z)`` for k right-hand sides on a trailing axis. With
        ``absolute`` every coefficient is replaced by its absolute value (pass ``|Z|`` to get
        the magnitudes of a backward error)."""
        k = Zx.shape[0]
        ex = (..., None)
        smap, smap_t = (_ABS_SLACK_MAP, _ABS_SLACK_MAP_T) if absolute else (_SLACK_MAP,
                                                                             _SLACK_MAP_T)
        sgn = 1.0 if absolute else -1.0
        alpha = np.abs(data.alpha[ex]) if absolute else data.alpha[ex]
        hsoc = np.abs(data.hsoc[ex]) if absolute else data.hsoc[ex]
        # W_i z = H z + C_i' D C_i z with C_i z = -(slack map) z
        UL = self._agent(f.D)[..., None] * (smap @ Zx.reshape(k, 5, -1)).reshape(
            (k, 8) + Zx.shape[2:])
        W = (smap_t @ UL.reshape(k, 8, -1)).reshape(Zx.shape)
        W[:, 2] += hsoc * Zx[:, 2]
        aZ = alpha * Zl
        W[:, 0] += sgn * aZ
        W[:, 1] += aZ
        W[:, 2] += Zl
        W[:, 2, :, :-1] += sgn * Zl[:, :, 1:]
        Az = Zx[:, 2] + sgn * alpha * Zx[:, 0] + alpha * Zx[:, 1]
        Az[:, :, 1:] += sgn * Zx[:, 2, :, :-1]
        return W, Az

    def _reduced_apply(self, f: _Factor, data: _Data, Zx: np.ndarray, Zl: np.ndarray,
                       absolute: bool = False):
        """The reduced KKT matrix applied to ``(Zx, Zl)``: the agents' own blocks plus the
        grid terms ``E D_grid E' Zx`` (see :meth:`_local_apply`)."""
        W, Az = self._local_apply(f, data, Zx, Zl, absolute=absolute)
        force = self._grid(f.D)[..., None] * Zx[:, :2].sum(axis=2)  # (k, 2, N, m)
        W[:, :2] += force[:, :, None]
        return W, Az

    # ------------------------------------------------------------------ Newton ------------
    def _direction(self, f: _Factor, data: _Data, base, rp, Mu, t, corr=None):
        """Newton direction for the barrier targets ``t`` (days,), optionally with Mehrotra's
        corrector term ``corr`` (days, m).

        Returns dX, dL, dMu, dS (flat inequality arrays) and a per-problem success flag.
        """
        U = t[:, None] / f.S if corr is None else (t[:, None] - corr) / f.S
        r1 = self._apply_Ct(U)
        r1 += base
        np.negative(r1, out=r1)
        dX, dL, ok = self._solve_reduced(f, data, r1[..., None], -rp[..., None])
        dX, dL = dX[..., 0], dL[..., 0]
        dS = self._slacks(dX, offset=False)
        dMu = U - Mu - f.D * dS
        return dX, dL, dMu, dS, ok

    @staticmethod
    def _step_lengths(S, Mu, dS, dMu, eta: float):
        """Largest primal and dual steps in (0, 1] keeping S and mu positive (fraction
        ``eta`` of the way to the boundary)."""
        ap = (S / np.maximum(-dS, _TINY)).min(axis=1)
        ad = (Mu / np.maximum(-dMu, _TINY)).min(axis=1)
        return np.minimum(1.0, eta * ap), np.minimum(1.0, eta * ad)

    # ------------------------------------------------------------ starting points ---------
    def _initial_point(self, data: _Data, x0: np.ndarray | None):
        """Strictly interior primal point and multipliers on the central path of ``t0``.

        Cold start: ``b = s = u0``; warm start: ``x0``'s ``b, s`` pushed into the interior
        and blended with ``u0`` (see the class attributes). soc then follows the dynamics (so
        ``A x = e`` holds), the slack variables sit :attr:`slack_margin` above their kinks,
        ``mu = t0 / S`` and ``lam`` solves the soc rows of the dual residual exactly (a
        backward recursion from ``lam_N = 0``).
        """
        days, n, N = data.qb.shape[0], self.n, self.N
        X = np.empty((days, 5, n, N))
        if x0 is None:
            u0 = self.u0_fraction * min(self.U, self.P / n)
            X[:, :2] = u0
            t0 = self.t0_cold * data.scale
        else:
            X0 = self._to_internal_x(np.asarray(x0, dtype=float))
            margin = self.warm_margin * min(self.U, self.P / n)
            bs = np.where(np.isfinite(X0[:, :2]), X0[:, :2], margin)
            u0 = self.u0_fraction * min(self.U, self.P / n)
            w = self.warm_weight
            X[:, :2] = w * np.clip(bs, margin, self.U - margin) + (1.0 - w) * u0
            tot = X[:, :2].sum(axis=2, keepdims=True)
            cap = self.P - n * margin
            X[:, :2] *= np.where(tot > cap, cap / np.maximum(tot, _TINY), 1.0)
            t0 = self.t0_warm * data.scale
        inc = data.alpha * (X[:, 0] - X[:, 1]) + data.delta
        X[:, 2] = data.soc0[:, :, None] + np.cumsum(inc, axis=2)
        X[:, 3] = np.maximum(X[:, 2] - self.hi, 0.0) + self.slack_margin
        X[:, 4] = np.maximum(self.lo - X[:, 2], 0.0) + self.slack_margin
        Mu = t0[:, None] / self._slacks(X)
        ML = self._agent(Mu)
        rsoc = data.hsoc * X[:, 2] + data.qsoc + ML[:, 4] - ML[:, 5]
        L = -np.cumsum(rsoc[..., ::-1], axis=2)[..., ::-1]
        return X, np.ascontiguousarray(L), Mu

    # ------------------------------------------------------------------- solving ----------
    def solve(
        self,
        soc0: np.ndarray,
        buy: np.ndarray,
        sell: np.ndarray,
        theta: Theta,
        x0: np.ndarray | None = None,
    ) -> MPCSolution:
        """Solve one MPC: soc0 (n,), buy and sell (N,), theta; optional primal guess x0 (nx,)."""
        sol = self.solve_batch(
            np.asarray(soc0, float)[None], np.asarray(buy, float)[None],
            np.asarray(sell, float)[None], theta,
            None if x0 is None else np.asarray(x0, float)[None],
        )
        return sol[0]

    def solve_batch(
        self,
        soc0: np.ndarray,
        buy: np.ndarray,
        sell: np.ndarray,
        theta: Theta,
        x0: np.ndarray | None = None,
    ) -> BatchSolution:
        """Solve one MPC per row, all rows at once.

        Parameters
        ----------
        soc0
            States, shape (days, n).
        buy, sell
            Price windows, shape (days, N).
        theta
            MPC parameters, shared by all rows.
        x0
            Optional primal warm start (days, nx), e.g. ``self.shift(previous.x)``; used when
            ``config.warm_start`` is set. Only its ``b, s`` are used (pushed into the
            interior and blended with the cold start, see the class attributes); soc follows
            from the dynamics. Non-finite entries are ignored.

        Returns
        -------
        BatchSolution
            Exact barrier solutions in :mod:`mpcrl_lite.mpc`'s orderings; rows that failed
            have ``success = False``, a status string (:data:`STATUS_MAX_ITER`,
            :data:`STATUS_NON_FINITE`, :data:`STATUS_BREAKDOWN`) and action zeros; their
            ``x, lam, mu`` are the last iterate.

        Raises
        ------
        ValueError
            For inputs of the wrong shape or non-finite parameters (before any work).
        """
        t_start = time.perf_counter()
        P = self.mpc.parameters(soc0, buy, sell, theta)
        if P.ndim != 2:
            raise ValueError(f"solve_batch expects soc0 (days, n); got soc0 {np.shape(soc0)}")
        days = P.shape[0]
        if x0 is not None:
            x0 = np.asarray(x0, float).reshape(days, self.mpc.nx)
            if not self.config.warm_start:
                x0 = None
        data = self._data(P)
        with np.errstate(all="ignore"):  # non-finite numbers are detected per problem
            X, L, Mu, iters, status = self._run(data, x0)
        success = status == STATUS_CONVERGED
        action = np.where(success[:, None], X[:, 0, :, 0] - X[:, 1, :, 0], 0.0)
        return BatchSolution(
            action=action,
            x=self._from_internal_x(X),
            lam=self._from_internal_lam(L),
            mu=self._mu_to_flat(Mu),
            cost=self._cost(X, data),
            success=success,
            status=tuple(str(s) for s in status),
            iterations=iters,
            p=P,
            solve_time=time.perf_counter() - t_start,
            backend=self.name,
        )

    @staticmethod
    def _cost(X: np.ndarray, data: _Data) -> np.ndarray:
        """``f(x) = 0.5 x'Hx + q'x + c`` per problem."""
        days = X.shape[0]
        f = (data.qb * X[:, 0] + data.qs * X[:, 1]
             + (0.5 * data.hsoc * X[:, 2] + data.qsoc) * X[:, 2]
             + data.qshi * X[:, 3] + data.qslo * X[:, 4])
        return f.reshape(days, -1).sum(axis=1) + data.c

    def _run(self, data: _Data, x0: np.ndarray | None):
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
            S = self._slacks(Xa)
            base = self._grad_lag_part(Xa, La, d)
            rd = self._apply_Ct(Mua)
            rd += base
            rp = self._apply_A(Xa, d)
            rp -= d.e
            err = self._errors(rd, rp, Mua, S, d, tau)
            # at the rounding floor, or one Newton step after reaching tol (quadratic
            # convergence), or no more progress
            done = (err <= floor) | ((err <= tol) & ((err_prev <= tol) | (err > 0.1 * err_prev)))
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
            f, ok = self._factor(S, Mua, d)
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

        Works on any solution of this MPC (e.g. from :class:`~mpcrl_lite.solvers.IpoptSolver`
        too); problems with different theta are handled group by group.

        Returns
        -------
        Sensitivity
            ``grad`` (days, n_theta, n), ``ok``, ``cond`` (the proxy ``||K||_max ||Z||_max``)
            and ``reason``, as :class:`~mpcrl_lite.sensitivity.PolicySensitivity`.
        """
        if isinstance(solution, MPCSolution):
            solution = BatchSolution.stack([solution], 0.0, "")
        m = self.mpc
        days, n = len(solution), self.n
        grads = np.zeros((days, m.n_theta, n))
        ok = np.zeros(days, dtype=bool)
        conds = np.full(days, np.inf)
        reasons = [""] * days
        P = np.atleast_2d(solution.p)
        good = np.asarray(solution.success, dtype=bool)
        for d in np.flatnonzero(~good):
            reasons[d] = f"solver failed: {solution.status[d]}"
        rows = np.flatnonzero(good)
        with np.errstate(all="ignore"):  # non-finite numbers are detected per problem
            for idx in self._theta_groups(P, rows) if rows.size else []:
                self._sensitivity_group(solution, P, idx, grads, ok, conds, reasons)
        return Sensitivity(grads, ok, conds, tuple(reasons))

    def _sensitivity_group(self, solution, P, idx, grads, ok, conds, reasons) -> None:
        """Sensitivities of the problems ``idx`` (which share theta), written in place."""
        n, N = self.n, self.N
        X = self._to_internal_x(np.asarray(solution.x)[idx])
        Mu = self._mu_from_flat(np.asarray(solution.mu)[idx])
        S = self._slacks(X)
        interior = np.all(S > 0, axis=1) & np.all(Mu > 0, axis=1)
        for d in idx[~interior]:
            reasons[d] = "solution not strictly interior (S > 0 and mu > 0 violated)"
        if not np.all(interior):
            idx, X, Mu, S = idx[interior], X[interior], Mu[interior], S[interior]
            if idx.size == 0:
                return
        k = idx.size
        data = self._data(P[idx])
        L = self._to_internal_lam(np.asarray(solution.lam)[idx])
        f, fok = self._factor(S, Mu, data)
        if k * n * n * N <= _FULL_ADJOINT_MAX:
            grad, cond, back, sok = self._adjoint_full(f, data, X, L, Mu, S)
        else:
            grad, cond, back, sok = self._adjoint_structured(f, data, X, L, Mu, S)
        usable = fok & sok & np.all(np.isfinite(grad), axis=(1, 2)) & np.isfinite(cond)
        for pos, d in enumerate(idx):
            conds[d] = cond[pos] if np.isfinite(cond[pos]) else np.inf
            if not usable[pos]:
                reasons[d] = "singular KKT matrix"
            elif back[pos] > _BACKWARD_ERROR_MAX or cond[pos] > self.config.kkt_cond_max:
                reasons[d] = f"ill-conditioned KKT matrix (cond ~ {cond[pos]:.2e})"
            else:
                grads[d] = grad[pos]
                ok[d] = True

    def _adjoint_structured(self, f: _Factor, data: _Data, X, L, Mu, S):
        """Sensitivities from the column structure of the adjoint (for many agents).

        Column ``o`` of Z is agent ``o``'s own local solution plus every agent's response to
        the grid forces ``g^(o)``; the responses are contracted with ``dR/dtheta`` once per
        agent, so nothing of size ``n^2 N^2`` is formed. Without refinement: where the grid
        limit binds, the own part and the grid's response nearly cancel and entries lose
        digits in absolute terms (about 1e-11 of the column's scale). Returns grad
        (k, n_theta, n), the conditioning proxy, the backward error of the ``2N`` solve and
        a success flag.
        """
        k, n, N = X.shape[0], self.n, self.N
        alpha = data.alpha
        vb, vs, V = f.vb, f.vs, f.V
        # Column o of Z (the adjoint for the policy of agent o) = agent o's own local
        # solution for the right-hand side e_o (+1 at b_0, -1 at s_0) + every agent's
        # response R_i g^(o) to the grid forces g^(o), with M g^(o) = (b_0.., s_0..) of the
        # own local solution (see _solve_reduced).
        e1 = np.zeros((k, 5, n, N, 1))
        e1[:, 0, :, 0] = 1.0
        e1[:, 1, :, 0] = -1.0
        e2 = np.zeros((k, n, N, 1))
        yx, yl = self._solve_local(f, data, e1, e2)  # own local parts

        def own_columns(zx):  # (b, s) of agent o's own part as column o, (k, 2N, n)
            return zx[:, :2, :, :, 0].transpose(0, 1, 3, 2).reshape(k, 2 * N, n)

        scale = f.Mscale[..., None]
        q = own_columns(yx) * scale
        g, sok = _cholesky_solve(f.Mchol, q)
        # normwise backward error of the 2N solve (the local solves cannot break down: their
        # tridiagonal matrices are diagonally dominant with positive pivots)
        back = np.abs(np.einsum("kab,kbo->kao", f.M, g) - q).reshape(k, -1).max(axis=1)
        back /= np.maximum(
            np.abs(f.M).reshape(k, -1).max(axis=1) * np.abs(g).reshape(k, -1).max(axis=1)
            + np.abs(q).reshape(k, -1).max(axis=1), _TINY)
        g *= scale
        cond = self._adjoint_sweep(f, data, Mu, S, yx, yl, g)

        # -dR/dtheta as weights on (Zb, Zs, Zsoc, Zlam); for the responses R_i they are folded
        # into weights on lam alone: R_i's lam part is [T^{-1} diag(beta_b), -T^{-1} diag(beta_s)],
        # b = vb (alpha lam - I_b), s = vs (-alpha lam - I_s), soc_j = V_j (lam_{j+1} - lam_j)
        wb, ws, wsoc, wl = self._grad_weights(X, L)  # (k, n, parts, N) each
        vb4, vs4, V4 = vb[:, :, None, :], vs[:, :, None, :], V[:, :, None, :]
        a4 = alpha[None, :, :, None]
        wbv, wsv, wsocv = wb * vb4, ws * vs4, wsoc * V4
        Wc = a4 * (wbv - wsv) - wsocv + wl
        Wc[..., 1:] += wsocv[..., :-1]
        WT = Wc @ f.Tinv
        Gamma = np.empty((k, _N_PARTS, n, 2 * N))  # contracted responses, parts first
        Gamma[..., :N] = (WT * f.beta_b[:, :, None, :] - wbv).transpose(0, 2, 1, 3)
        Gamma[..., N:] = (-WT * f.beta_s[:, :, None, :] - wsv).transpose(0, 2, 1, 3)
        Gloc = (np.einsum("knpj,knj->knp", wb, yx[:, 0, ..., 0])
                + np.einsum("knpj,knj->knp", ws, yx[:, 1, ..., 0])
                + np.einsum("knpj,knj->knp", wsoc, yx[:, 2, ..., 0])
                + np.einsum("knpj,knj->knp", wl, yl[..., 0]))  # (k, n, parts)
        # grad[p, i, o] = Gamma_i[p] . g^(o) + [i == o] Gloc_i[p]
        grad4 = Gamma @ g[:, None]  # (k, parts, n, n); each product small enough for BLAS
        ar = np.arange(n)
        grad4[:, :, ar, ar] += Gloc.transpose(0, 2, 1)
        grad = grad4.reshape(k, _N_PARTS * n, n)

        return grad, cond, back, sok

    def _adjoint_full(self, f: _Factor, data: _Data, X, L, Mu, S):
        """Sensitivities from the full adjoint Z, all ``n`` columns at once, with iterative
        refinement on the reduced system (for few agents: ``Z`` has ``O(n^2 N)`` entries).
        Returns grad (k, n_theta, n), the conditioning proxy, the normwise backward error of
        the refined solve and a success flag."""
        k, n, N = X.shape[0], self.n, self.N
        ar = np.arange(n)
        r1 = np.zeros((k, 5, n, N, n))
        r1[:, 0, ar, 0, ar] = 1.0
        r1[:, 1, ar, 0, ar] = -1.0
        r2 = np.zeros((k, n, N, n))
        Zx, Zl, sok = self._solve_reduced(f, data, r1, r2)
        # iterative refinement: at least one step (it restores the small entries, which the
        # normwise backward error does not see), more until that error max |r| / max(|K||Z| + 1)
        # is at the rounding level
        for step in range(_REFINE_MAX + 1):
            W, Az = self._reduced_apply(f, data, Zx, Zl)
            W -= r1
            Wm, Azm = self._reduced_apply(f, data, np.abs(Zx), np.abs(Zl), absolute=True)
            back = np.maximum(np.abs(W).reshape(k, -1).max(axis=1),
                              np.abs(Az).reshape(k, -1).max(axis=1)) / np.maximum(
                np.maximum(Wm.reshape(k, -1).max(axis=1), Azm.reshape(k, -1).max(axis=1))
                + 1.0, _TINY)
            if step == _REFINE_MAX or (step and np.all(back <= _BACKWARD_ERROR_GOOD)):
                break
            cx, cl, sok2 = self._solve_reduced(f, data, -W, -Az)
            Zx += cx
            Zl += cl
            sok &= sok2
        # grad[p, i, o] = sum over the stages of the weights times Z
        wb, ws, wsoc, wl = self._grad_weights(X, L)
        grad = wb @ Zx[:, 0] + ws @ Zx[:, 1] + wsoc @ Zx[:, 2] + wl @ Zl  # (k, n, parts, n)
        grad = grad.transpose(0, 2, 1, 3).reshape(k, _N_PARTS * n, n)
        # conditioning proxy ||K||_max ||Z||_max, with Z_mu = C Z_x / S
        ZS = self._slacks(Zx.transpose(0, 4, 1, 2, 3).reshape(k * n, 5, n, N), offset=False)
        Zmu = ZS.reshape(k, n, -1) / S[:, None, :]
        zmax = np.max(np.stack([np.abs(Zx).reshape(k, -1).max(axis=1),
                                np.abs(Zl).reshape(k, -1).max(axis=1),
                                np.abs(Zmu).reshape(k, -1).max(axis=1)]), axis=0)
        cond = self._kmax(data, Mu, S) * zmax
        return grad, cond, back, sok

    def _kmax(self, data: _Data, Mu, S) -> np.ndarray:
        """``||K||_max`` of the KKT Jacobian ``dR/dy`` (entries 1, alpha, H, mu, h)."""
        k = Mu.shape[0]
        return np.max(np.stack([
            np.ones(k), np.full(k, np.abs(data.alpha).max()),
            np.full(k, np.abs(data.hsoc).max()), Mu.max(axis=1), S.max(axis=1),
        ]), axis=0)

    def _grad_weights(self, X: np.ndarray, L: np.ndarray) -> tuple[np.ndarray, ...]:
        """``-dR/dtheta`` as weights on (Zb, Zs, Zsoc, Zlam) per theta part, each of shape
        (k, n, parts, N) (see the table in the module docstring)."""
        k, n, N = L.shape[0], self.n, self.N
        wb = np.zeros((k, n, _N_PARTS, N))
        ws = np.zeros_like(wb)
        wsoc = np.zeros_like(wb)
        wl = np.zeros_like(wb)
        soc = X[:, 2]
        wb[:, :, 0] = L
        ws[:, :, 0] = -L
        wl[:, :, 0] = X[:, 0] - X[:, 1]
        wl[:, :, 1] = 1.0
        wb[:, :, 2] = -self._disc
        ws[:, :, 3] = self._disc
        wsoc[:, :, 4] = -2.0 * self._wsoc * soc
        wsoc[:, :, 5] = -self._wsoc
        wsoc[:, :, 7] = -2.0 * self._term * soc
        wsoc[:, :, 8] = -self._term
        return wb, ws, wsoc, wl

    def _adjoint_sweep(self, f: _Factor, data: _Data, Mu, S, yx, yl, g) -> np.ndarray:
        """``||K||_max ||Z||_max``, the conditioning proxy of
        :class:`~mpcrl_lite.sensitivity.PolicySensitivity`, forming all columns of the
        adjoint Z a chunk at a time (bounded memory).

        Column ``o`` is agent ``o``'s own part ``(yx, yl)`` plus every agent's response
        ``R_i g^(o)`` to the grid forces; the multiplier rows are ``Z_mu = -dS / S`` group by
        group and ``g / mu`` on the grid rows.
        """
        k, n, N = Mu.shape[0], self.n, self.N
        alpha = data.alpha[..., None]
        SL, DL = self._agent(S), self._agent(f.D)
        iS = 1.0 / SL
        one = np.ones_like(f.V)
        # |Z_mu| of the groups of b, s, soc relative to |Zb|, |Zs|, |Zsoc| (with 1 for Z_x)
        fb = np.maximum(one, np.maximum(iS[:, 0], iS[:, 1]))[..., None]
        fs = np.maximum(one, np.maximum(iS[:, 2], iS[:, 3]))[..., None]
        fsoc = np.max(np.stack([one, DL[:, 6] * f.ishi * iS[:, 4], DL[:, 7] * f.islo * iS[:, 5],
                                f.c4 * iS[:, 6], f.c5 * iS[:, 7], f.c4, f.c5]), axis=0)[..., None]
        vb, vs, V = f.vb[..., None], f.vs[..., None], f.V[..., None]
        own = [yx[:, v, :, :, 0] for v in range(3)] + [yl[..., 0]]  # (k, n, N) each
        # responses of lam to unit grid forces, (k, n, N, 2N)
        Rl = np.concatenate([f.Tinv * f.beta_b[:, :, None, :],
                             -f.Tinv * f.beta_s[:, :, None, :]], axis=-1)
        zmax = np.zeros(k)
        chunk = max(1, (1 << 18) // max(1, k * n * N))
        for o0 in range(0, n, chunk):
            cols = np.arange(o0, min(n, o0 + chunk))
            c, cc = cols.size, np.arange(cols.size)
            gc = g[:, None, :, o0 : o0 + c]
            gb, gs = gc[:, :, :N], gc[:, :, N:]
            Zl = Rl @ gc  # (k, n, N, c)
            aZ = alpha * Zl
            Z = aZ - gb  # b
            Z *= vb
            Z[:, cols, :, cc] += own[0][:, cols].transpose(1, 0, 2)
            zmax = np.maximum(zmax, _absmax(Z, fb))
            np.negative(aZ, out=Z)  # s
            Z -= gs
            Z *= vs
            Z[:, cols, :, cc] += own[1][:, cols].transpose(1, 0, 2)
            zmax = np.maximum(zmax, _absmax(Z, fs))
            np.negative(Zl, out=Z)  # soc
            Z[:, :, :-1] += Zl[:, :, 1:]
            Z *= V
            Z[:, cols, :, cc] += own[2][:, cols].transpose(1, 0, 2)
            zmax = np.maximum(zmax, _absmax(Z, fsoc))
            Zl[:, cols, :, cc] += own[3][:, cols].transpose(1, 0, 2)
            zmax = np.maximum(zmax, _absmax(Zl, None))
        zgrid = (np.abs(g) / self._grid(Mu).reshape(k, -1, 1)).reshape(k, -1).max(axis=1)
        zmax = np.maximum(zmax, zgrid)
        return self._kmax(data, Mu, S) * zmax

    # -------------------------------------------------------------------- misc ------------
    def shift(self, x: np.ndarray) -> np.ndarray:
        """Shift solutions ``x`` (..., nx) one stage forward for warm starting (see
        :func:`shift`)."""
        return shift(x, self.n)


def _tridiag_inverse(a: np.ndarray, V: np.ndarray, upper: np.ndarray) -> np.ndarray:
    r"""Inverses of symmetric positive definite tridiagonal matrices, batched.

    ``T = tridiag(-V_{j-1}, a_j, -V_j)`` of size ``N`` for every leading index; ``a`` and
    ``V`` have shape ``(..., N)`` (``V[..., N-1]`` is unused), ``V > 0`` and ``T`` is
    diagonally dominant; ``upper`` is the boolean mask of the upper triangle (with the
    diagonal) of an ``N x N`` matrix.

    With the backward pivots ``g_{N-1} = a_{N-1}``, ``g_j = a_j - V_j^2 / g_{j+1}``,
    ``T = U G U'`` with ``U`` unit upper bidiagonal (superdiagonal ``-V_j / g_{j+1}``), so
    ``U^{-1}`` has the entries ``E_{jk} = prod_{l=j}^{k-1} r_l`` for ``j <= k`` with
    ``r_l = V_l / g_{l+1}`` in (0, 1) (diagonal dominance). Then
    ``s_j = (T^{-1})_{jj} = sum_{m <= j} E_{mj}^2 / g_m`` follows the recursion
    ``s_j = r_{j-1}^2 s_{j-1} + 1 / g_j`` (positive terms only), and
    ``(T^{-1})_{jk} = s_j E_{jk}`` for ``j <= k`` (the column recursion of a tridiagonal
    inverse). With ``c_k = sum_{l<k} log r_l`` this is
    ``exp(log s_j - c_j + c_k)``, evaluated for both triangles at once: no over- or
    underflow, no cancellation, ``O(N^2)`` work and ``O(N)`` Python-level operations.
    """
    N = a.shape[-1]
    g = np.empty_like(a)
    g[..., N - 1] = a[..., N - 1]
    V2 = V * V
    for j in range(N - 2, -1, -1):
        g[..., j] = a[..., j] - V2[..., j] / g[..., j + 1]
    r = V[..., :-1] / g[..., 1:]
    ig = 1.0 / g
    diag = np.empty_like(a)
    diag[..., 0] = ig[..., 0]
    r2 = r * r
    for j in range(1, N):
        diag[..., j] = r2[..., j - 1] * diag[..., j - 1] + ig[..., j]
    cs = np.zeros_like(a)
    np.cumsum(np.log(r), axis=-1, out=cs[..., 1:])
    u = np.log(diag) - cs
    L = u[..., :, None] + cs[..., None, :]  # log T_jk for j <= k
    return np.exp(np.where(upper, L, np.swapaxes(L, -1, -2)))


def _absmax(Z: np.ndarray, w: np.ndarray | None) -> np.ndarray:
    """``max |Z * w|`` per leading index (in place on ``Z``)."""
    np.abs(Z, out=Z)
    if w is not None:
        Z *= w
    return Z.reshape(Z.shape[0], -1).max(axis=1)


def _cholesky(M: np.ndarray, ok: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Lower Cholesky factors ``L[d]`` of the SPD matrices ``M[d]`` (batched). Matrices with
    ``ok[d]`` False or that are not positive definite get the identity and ``ok[d] = False``."""
    ok = ok.copy()
    if np.all(ok):
        try:
            return np.linalg.cholesky(M), ok
        except np.linalg.LinAlgError:
            pass
    out = np.empty_like(M)
    eye = np.eye(M.shape[-1])
    for d in range(M.shape[0]):
        if ok[d]:
            c, info = _dpotrf(M[d], lower=1, clean=1)
            if info == 0:
                out[d] = c
                continue
            ok[d] = False
        out[d] = eye
    return out, ok


def _cholesky_solve(L: np.ndarray, rhs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Solve ``L[d] L[d]' x[d] = rhs[d]`` for every d (``L`` from :func:`_cholesky`); returns
    ``(x, finite per d)``. ``L[d].T`` is the upper factor in Fortran order, passed to LAPACK
    without a copy.

    At most :data:`_RHS_BLOCK` right-hand sides go into one LAPACK call: with more, a
    multithreaded BLAS may split the triangular solves over threads, which costs a thousand
    times more than the solve itself on a busy machine.
    """
    x = np.empty(rhs.shape)
    m = rhs.shape[-1]
    if m <= _RHS_BLOCK:
        for d in range(L.shape[0]):
            x[d], _ = _dpotrs(L[d].T, rhs[d], lower=0)
    else:
        for d in range(L.shape[0]):
            for j in range(0, m, _RHS_BLOCK):
                x[d, :, j : j + _RHS_BLOCK], _ = _dpotrs(
                    L[d].T, rhs[d, :, j : j + _RHS_BLOCK], lower=0)
    ok = np.all(np.isfinite(x.reshape(x.shape[0], -1)), axis=1)
    return x, ok
