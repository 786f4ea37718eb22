r"""The MPC's barrier KKT system in the structured layout of the batch interior point.

:class:`BatchKKT` holds what :class:`~mpcrl_lite.mpc.backends.batch.BatchSolver` (the Newton
iteration) and :mod:`mpcrl_lite.mpc.backends.batch_adjoint` (the policy sensitivities) share: the QP data
of a batch of problems, the conversions between :mod:`mpcrl_lite.mpc.formulation`'s orderings and the
internal one, the structured products with ``H``, ``A``, ``C`` and the factorisation of the
reduced KKT matrix with its solves. The barrier problem and its reduced system are derived in
:mod:`mpcrl_lite.mpc.backends.batch`; the dense kernels are in :mod:`mpcrl_lite.mpc.backends.batch_linalg`.

Linear algebra
--------------
Per Newton step and day (``n`` agents, ``N`` stages). ``H`` is diagonal and every inequality
except the two grid rows per stage involves one agent at one stage.

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

Performance notes: everything is vectorised over ``days x agents``; only the tridiagonal
recursions (``N`` steps) and the ``2N`` Cholesky solves (one LAPACK call per day) loop in
Python. Products with many columns avoid BLAS calls large enough to be multithreaded, which
can stall badly on a busy machine.

Data and layout
---------------
The QP data are built in numpy from the system and theta (``H``, ``q``, ``c`` affine in the
prices, ``A`` from theta, ``C``, ``d`` constant). The constructor checks them against
:attr:`MPC.qp_function <mpcrl_lite.mpc.formulation.MPC.qp_function>` at a test point, so the CasADi
formulation stays the single source of truth (a mismatch raises at construction, never
mid-run). Internally arrays are agent-major, ``(days, ..., n, N)``; the results use
:mod:`mpcrl_lite.mpc.formulation`'s orderings exactly. Per-agent inequality groups (internal index ->
row of :mod:`mpcrl_lite.mpc.formulation`'s per-stage block of ``h``): 0 ``-b``, 1 ``b - U``, 2 ``-s``,
3 ``s - U``, 4 ``soc - hi - sigma_hi``, 5 ``lo - soc - sigma_lo``, 6 ``-sigma_hi``,
7 ``-sigma_lo``; the grid rows ``sum b - P``, ``sum s - P`` are stored after them. ``U`` is
each battery's own input bound ``U_bar^i``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..._util.lazy import lazy_module
from ...theta import PARTS
from ..formulation import MPC
from ..solution import BatchSolution, MPCSolution, check_parameters
from .batch_linalg import cholesky, cholesky_solve, tridiag_inverse

ca = lazy_module("casadi")  # CasADi (~0.1-0.2 s of import) loads when first used

__all__ = ["TINY", "BatchData", "BatchKKT", "KKTFactor"]

TINY = 1e-300  # guards divisions by quantities that may underflow to zero


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


@dataclass
class BatchData:
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

    def take(self, idx: np.ndarray) -> BatchData:
        """The data of the problems ``idx`` only."""
        return BatchData(
            self.alpha, self.delta, self.hsoc, self.qsoc, self.qshi, self.qslo,
            self.qb[idx], self.qs[idx], self.soc0[idx], self.c[idx], self.e[idx],
            self.scale[idx],
        )


@dataclass
class KKTFactor:
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


class BatchKKT:
    r"""The barrier KKT system of a batch of MPC problems in the internal layout.

    Built once per formulation; every method works on a batch (leading axis ``days``) of
    problems that share theta (see :meth:`theta_groups`).

    Parameters
    ----------
    mpc
        The formulation. Its QP data are re-derived in numpy and checked against
        ``mpc.qp_function`` here (a mismatch raises :class:`RuntimeError`).

    Attributes
    ----------
    n, N : numbers of agents and stages
    U : (n, 1) each battery's input bound ``U_bar^i`` (a column, to broadcast along stages)
    P, hi, lo : the bounds ``P_bar``, ``soc_high``, ``soc_low``
    disc : (N,) ``gamma^j``, the weights of the stage-``j`` prices
    wsoc : (N,) weights ``gamma^{j+1}`` of the stage costs of ``soc_{j+1}`` (0 at the end)
    term : (N,) 1 at the last stage (the undiscounted terminal cost), else 0
    """

    def __init__(self, mpc: MPC) -> None:
        self.mpc = mpc
        sysc = mpc.system
        n, N = mpc.n, mpc.N
        self.n, self.N = n, N
        self.U = np.array(sysc.battery("U_bar"), dtype=float)[:, None]  # each battery's own
        self.P = float(sysc.P_bar)
        self.hi, self.lo = float(sysc.soc_high), float(sysc.soc_low)
        self._m_agent = 8 * n * N
        self._m = self._m_agent + 2 * N
        offset = np.zeros((8, n, N))
        offset[1] = offset[3] = self.U
        offset[4], offset[5] = self.hi, -self.lo
        self._offset = offset.reshape(8, n * N)
        gam = sysc.gamma ** np.arange(N + 1, dtype=float)
        self.disc = gam[:N]  # gamma^j, weights of the stage-j prices
        stage = np.arange(N) < N - 1
        # weights of the stage costs of soc_{j+1}: gamma^{j+1}; the terminal cost is undiscounted
        self.wsoc = np.where(stage, gam[1:], 0.0)
        self.term = (~stage).astype(float)
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
        hsoc = 2.0 * (th["phi1"][:, None] * self.wsoc + th["T1"][:, None] * self.term)
        qsoc = th["phi2"][:, None] * self.wsoc + th["T2"][:, None] * self.term
        const = float(np.sum(self.wsoc) * th["phi3"].sum() + th["T3"].sum())
        parts = (alpha, delta, hsoc, qsoc, th, const)
        self._theta_cache = (tvec.copy(), parts)
        return parts

    def batch_data(self, P: np.ndarray) -> BatchData:
        """Internal QP data of parameter vectors ``P`` (days, np) that share theta.

        Raises
        ------
        ValueError
            If the rows of ``P`` do not share one theta (split them with
            :meth:`theta_groups` first).
        """
        n, N = self.n, self.N
        tslice = self.mpc.theta_slice
        if P.shape[0] > 1 and not np.array_equal(P[:, tslice], np.broadcast_to(
                P[:1, tslice], P[:, tslice].shape)):
            raise ValueError("batch_data: the rows of P have different theta; expected one "
                             "theta (split them with BatchKKT.theta_groups)")
        sysc = self.mpc.system
        days = P.shape[0]
        soc0 = P[:, :n].copy()
        buy = P[:, n : n + N]
        sell = P[:, n + N : n + 2 * N]
        alpha, delta, hsoc, qsoc, th, const = self._theta_parts(P[0, self.mpc.theta_slice])
        qb = self.disc * (buy[:, None, :] + th["b"][None, :, None])
        qs = -self.disc * (sell[:, None, :] + th["s"][None, :, None])
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
        return BatchData(alpha, delta, hsoc, qsoc, self._qshi, self._qslo, qb, qs, soc0, c, e,
                         scale)

    def _check_formulation(self) -> None:
        """Compare the numpy QP data with ``mpc.qp_function`` at a pseudo-random point
        (products with random vectors, so no dense matrices are formed)."""
        m = self.mpc
        rng = np.random.default_rng(12345)
        p = check_parameters(m, rng)
        H, q, c, A, e, C, d = m.qp_function(p)
        data = self.batch_data(p[None, :])
        x = rng.standard_normal(m.nx)
        w = rng.standard_normal(m.nin)
        v = rng.standard_normal(m.neq)
        X = self.to_internal_x(x[None])
        HX = np.zeros_like(X)
        HX[:, 2] = data.hsoc * X[:, 2]
        Q = np.stack([data.qb, data.qs] + [np.broadcast_to(a, data.qb.shape)
                                           for a in (data.qsoc, data.qshi, data.qslo)], axis=1)
        mine = {
            "H x": self.from_internal_x(HX)[0],
            "q": self.from_internal_x(Q)[0],
            "c": data.c,
            "A x": self.from_internal_lam(self.apply_A(X, data))[0],
            "A' v": self.from_internal_x(
                self.grad_lag_part(np.zeros_like(X), self.to_internal_lam(v[None]), data)
                - Q)[0],
            "e": self.from_internal_lam(data.e)[0],
            "d - C x": self.mu_to_flat(self.slacks(X))[0],
            "C' w": self.from_internal_x(self.apply_Ct(self.mu_from_flat(w[None])))[0],
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
                    f"{err:.3e}); the formulation in mpcrl_lite.mpc.formulation changed and "
                    "mpcrl_lite.mpc.backends.batch_kkt must be updated to match it"
                )

    # ---------------------------------------------------------------- layout --------------
    def to_internal_x(self, x: np.ndarray) -> np.ndarray:
        """(days, nx) in mpc order -> (days, 5, n, N)."""
        days = x.shape[0]
        return np.ascontiguousarray(x.reshape(days, self.N, 5, self.n).transpose(0, 2, 3, 1))

    def from_internal_x(self, X: np.ndarray) -> np.ndarray:
        """(days, 5, n, N) -> (days, nx) in mpc order."""
        return np.ascontiguousarray(X.transpose(0, 3, 1, 2)).reshape(X.shape[0], -1)

    def to_internal_lam(self, lam: np.ndarray) -> np.ndarray:
        """(days, neq) in mpc order -> (days, n, N)."""
        return np.ascontiguousarray(lam.reshape(lam.shape[0], self.N, self.n).transpose(0, 2, 1))

    def from_internal_lam(self, L: np.ndarray) -> np.ndarray:
        """(days, n, N) -> (days, neq) in mpc order."""
        return np.ascontiguousarray(L.transpose(0, 2, 1)).reshape(L.shape[0], -1)

    def agent(self, A: np.ndarray) -> np.ndarray:
        """View of the per-agent groups of a flat inequality array (days, m): (days, 8, n, N)."""
        return A[:, : self._m_agent].reshape(A.shape[0], 8, self.n, self.N)

    def grid(self, A: np.ndarray) -> np.ndarray:
        """View of the grid rows of a flat inequality array (days, m): (days, 2, N)."""
        return A[:, self._m_agent :].reshape(A.shape[0], 2, self.N)

    def mu_to_flat(self, A: np.ndarray) -> np.ndarray:
        """Internal inequality array (days, m) -> (days, nin) in mpc order."""
        days, n, N = A.shape[0], self.n, self.N
        AL, AG = self.agent(A), self.grid(A)
        out = np.empty((days, N, 8 * n + 2))
        out[:, :, : 4 * n] = AL[:, :4].transpose(0, 3, 1, 2).reshape(days, N, 4 * n)
        out[:, :, 4 * n : 4 * n + 2] = AG.transpose(0, 2, 1)
        out[:, :, 4 * n + 2 :] = AL[:, 4:].transpose(0, 3, 1, 2).reshape(days, N, 4 * n)
        return out.reshape(days, -1)

    def mu_from_flat(self, mu: np.ndarray) -> np.ndarray:
        """(days, nin) in mpc order -> internal inequality array (days, m)."""
        days, n, N = mu.shape[0], self.n, self.N
        blk = mu.reshape(days, N, 8 * n + 2)
        out = np.empty((days, self._m))
        AL, AG = self.agent(out), self.grid(out)
        AL[:, :4] = blk[:, :, : 4 * n].reshape(days, N, 4, n).transpose(0, 2, 3, 1)
        AL[:, 4:] = blk[:, :, 4 * n + 2 :].reshape(days, N, 4, n).transpose(0, 2, 3, 1)
        AG[:] = blk[:, :, 4 * n : 4 * n + 2].transpose(0, 2, 1)
        return out

    # ----------------------------------------------------------- structured products ------
    def apply_A(self, X: np.ndarray, data: BatchData) -> np.ndarray:
        """``A x`` (days, n, N): ``soc_j - soc_{j-1} - alpha (b_j - s_j)``."""
        soc = X[:, 2]
        out = soc - data.alpha * (X[:, 0] - X[:, 1])
        out[..., 1:] -= soc[..., :-1]
        return out

    def slacks(self, X: np.ndarray, offset: bool = True) -> np.ndarray:
        """``S = d - C x`` (or ``-C x`` without ``offset``) as a flat array (days, m)."""
        days = X.shape[0]
        S = np.empty((days, self._m))
        SL = S[:, : self._m_agent].reshape(days, 8, -1)
        np.matmul(_SLACK_MAP, X.reshape(days, 5, -1), out=SL)
        SG = self.grid(S)
        np.sum(X[:, :2], axis=2, out=SG)
        if offset:
            SL += self._offset
            np.subtract(self.P, SG, out=SG)
        else:
            np.negative(SG, out=SG)
        return S

    def apply_Ct(self, u: np.ndarray) -> np.ndarray:
        """``C' u`` in the internal x layout for a flat inequality array ``u`` (days, m)."""
        days = u.shape[0]
        out = (_SLACK_MAP_T @ u[:, : self._m_agent].reshape(days, 8, -1)).reshape(
            days, 5, self.n, self.N)
        np.negative(out, out=out)
        out[:, :2] += self.grid(u)[:, :, None, :]
        return out

    def grad_lag_part(self, X: np.ndarray, L: np.ndarray, data: BatchData) -> np.ndarray:
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
    def errors(rd, rp, Mu, S, data: BatchData, tau: float) -> np.ndarray:
        """Scaled KKT residual per problem from the dual and primal residuals."""
        days = rd.shape[0]
        ed = np.abs(rd).reshape(days, -1).max(axis=1)
        ec = np.abs(Mu * S - tau).max(axis=1)
        ep = np.abs(rp).reshape(days, -1).max(axis=1)
        err = np.maximum(np.maximum(ed, ec) / data.scale, ep)
        return np.where(np.isfinite(err), err, np.inf)

    def residual(self, solution: BatchSolution | MPCSolution, tau: float) -> np.ndarray:
        r"""Scaled KKT residual of each problem of ``solution``, shape (days,).

        .. math:: \max\Big(\frac{\|r_d\|_\infty}{s},\ \|r_p\|_\infty,\
                  \frac{\|\mu\circ S - \tau\|_\infty}{s}\Big),\qquad
                  s = 1 + \max |\text{price terms of } q| :

        the dual, primal and complementarity residuals of the barrier problem, with the dual
        quantities measured relative to the prices (soc is of order one). The solver stops one
        Newton step after this is below ``config.tol`` (it ends near 1e-15). ``tau`` is the
        barrier parameter the problems were solved for.
        """
        solution = BatchSolution.of(solution)
        P = np.atleast_2d(solution.p)
        out = np.empty(P.shape[0])
        for idx in self.theta_groups(P, np.arange(P.shape[0])):
            data = self.batch_data(P[idx])
            X = self.to_internal_x(np.asarray(solution.x)[idx])
            L = self.to_internal_lam(np.asarray(solution.lam)[idx])
            Mu = self.mu_from_flat(np.asarray(solution.mu)[idx])
            rd = self.grad_lag_part(X, L, data) + self.apply_Ct(Mu)
            rp = self.apply_A(X, data) - data.e
            out[idx] = self.errors(rd, rp, Mu, self.slacks(X), data, tau)
        return out

    def theta_groups(self, P: np.ndarray, rows: np.ndarray) -> list[np.ndarray]:
        """Split ``rows`` of ``P`` into groups with equal theta."""
        thetas = P[rows][:, self.mpc.theta_slice]
        if np.all(thetas == thetas[:1]):
            return [rows]
        _, inverse = np.unique(thetas, axis=0, return_inverse=True)
        inverse = inverse.ravel()
        return [rows[inverse == g] for g in range(inverse.max() + 1)]

    # ------------------------------------------------------------ factorisation -----------
    def factor(
        self, S: np.ndarray, Mu: np.ndarray, data: BatchData
    ) -> tuple[KKTFactor, np.ndarray]:
        """Factorise the reduced KKT matrix at slacks ``S`` and multipliers ``Mu`` (flat);
        also returns a per-problem flag, False where the factorisation broke down."""
        days, N = S.shape[0], self.N
        D = Mu / S
        DL = self.agent(D)
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
        Tinv = tridiag_inverse(a, V, self._upper)
        # grid Schur complement M = diag(1/D_grid + sum 1/W) - sum_i B_i' T_i^{-1} B_i
        M = np.empty((days, 2 * N, 2 * N))
        tb = Tinv * beta_b[:, :, None, :]
        ts = Tinv * beta_s[:, :, None, :]
        np.einsum("dnj,dnjk->djk", -beta_b, tb, out=M[:, :N, :N])
        np.einsum("dnj,dnjk->djk", beta_b, ts, out=M[:, :N, N:])
        np.einsum("dnj,dnjk->djk", -beta_s, ts, out=M[:, N:, N:])
        M[:, N:, :N] = M[:, :N, N:].transpose(0, 2, 1)
        mdiag = M.reshape(days, -1)[:, :: 2 * N + 1]  # a view of the diagonal
        mdiag += 1.0 / self.grid(D).reshape(days, 2 * N)
        mdiag[:, :N] += vb.sum(axis=1)
        mdiag[:, N:] += vs.sum(axis=1)
        ok = np.all(mdiag > 0, axis=1) & np.all(np.isfinite(mdiag), axis=1)
        scale = 1.0 / np.sqrt(np.where(ok[:, None], mdiag, 1.0))
        M *= scale[:, :, None]
        M *= scale[:, None, :]
        Mchol, ok_chol = cholesky(M, ok)
        ok &= ok_chol
        f = KKTFactor(S, D, vb, vs, V, c4, c5, ishi, islo, beta_b, beta_s, Tinv, M, Mchol, scale)
        return f, ok

    def solve_local(self, f: KKTFactor, data: BatchData, r1: np.ndarray, r2: np.ndarray):
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

    def grid_response(self, f: KKTFactor, data: BatchData, gb: np.ndarray, gs: np.ndarray):
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

    def solve_reduced(self, f: KKTFactor, data: BatchData, r1: np.ndarray, r2: np.ndarray):
        """Solve ``[[W, A'], [A, 0]] [dx; dlam] = [r1; r2]`` with the factorisation ``f``.

        Local solves of every agent, the grid forces ``g`` from ``M g = sum_i E_i' z_i``,
        then every agent's response to ``g``. r1 (days, 5, n, N, k), r2 (days, n, N, k) for
        k right-hand sides; returns dx (days, 5, n, N, k), dlam (days, n, N, k) and a
        per-problem success flag.
        """
        ex = (..., None)
        days, N = r1.shape[0], self.N
        dx, dlam = self.solve_local(f, data, r1, r2)
        q = dx[:, :2].sum(axis=2).reshape(days, 2 * N, -1)
        g, ok = cholesky_solve(f.Mchol, q * f.Mscale[ex])
        g *= f.Mscale[ex]
        gx, glam = self.grid_response(f, data, g[:, None, :N], g[:, None, N:])
        dx += gx
        dlam += glam
        # Where a grid limit is hard (D_grid sum_i 1/W >> 1) the flow sum_i db_i is a tiny
        # difference of O(1) terms and its rounding error, times D_grid, would dominate the
        # b rows' residual. The exact solution has sum_i db_i = g_b / D_grid: restore that,
        # spreading the (rounding-level) difference over the agents like a change of g_b.
        g = g.reshape(days, 2, N, -1)
        for v, w in ((0, f.vb), (1, f.vs)):
            wsum = w.sum(axis=1)  # (days, N)
            DG = self.grid(f.D)[:, v]
            stiff = (DG * wsum)[..., None] > 1.0
            if np.any(stiff):
                delta = g[:, v] / DG[..., None] - dx[:, v].sum(axis=1)
                dx[:, v] += (w / wsum[:, None])[..., None] * np.where(stiff, delta, 0.0)[:, None]
        return dx, dlam, ok

    def local_apply(self, f: KKTFactor, data: BatchData, Zx: np.ndarray, Zl: np.ndarray,
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
        UL = self.agent(f.D)[..., None] * (smap @ Zx.reshape(k, 5, -1)).reshape(
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

    def reduced_apply(self, f: KKTFactor, data: BatchData, Zx: np.ndarray, Zl: np.ndarray,
                       absolute: bool = False):
        """The reduced KKT matrix applied to ``(Zx, Zl)``: the agents' own blocks plus the
        grid terms ``E D_grid E' Zx`` (see :meth:`local_apply`)."""
        W, Az = self.local_apply(f, data, Zx, Zl, absolute=absolute)
        force = self.grid(f.D)[..., None] * Zx[:, :2].sum(axis=2)  # (k, 2, N, m)
        W[:, :2] += force[:, :, None]
        return W, Az

    # -------------------------------------------------------------------- cost ------------
    @staticmethod
    def cost(X: np.ndarray, data: BatchData) -> np.ndarray:
        """``f(x) = 0.5 x'Hx + q'x + c`` per problem."""
        days = X.shape[0]
        f = (data.qb * X[:, 0] + data.qs * X[:, 1]
             + (0.5 * data.hsoc * X[:, 2] + data.qsoc) * X[:, 2]
             + data.qshi * X[:, 3] + data.qslo * X[:, 4])
        return f.reshape(days, -1).sum(axis=1) + data.c
