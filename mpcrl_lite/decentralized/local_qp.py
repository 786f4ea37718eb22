r"""The local MPCs' barrier problems, vectorized over a batch of days and batteries.

Battery ``i``'s local MPC is the paper's MPC (eq. 9) with ``n = 1``
(:func:`local_system`), whose grid row is made inert because the real, shared grid limit is
priced by the coordination (:mod:`mpcrl_lite.decentralized.coordination`). For fixed :math:`\theta^i` and
grid prices it is a QP with the barrier of its inequality rows,

.. math::
   \min_x\; \tfrac12 x^\top H x + q^\top x - \tau\sum_k\log(d_k - C_k x)
   \quad\text{s.t.}\quad A x = e,

with KKT conditions ``Hx + q + A' lam + C' mu = 0``, ``Ax = e``, ``mu_k (C_k x - d_k) = -tau``.
A grid price enters only the linear cost: the prices ``nu = (lambda^b, lambda^s)`` (``2N``)
add ``E' nu`` to ``q``, where ``E x = (b_0..b_{N-1}, s_0..s_{N-1})`` picks the grid-relevant
part of ``x``.

:class:`LocalQP` evaluates the data of many such problems at once (one per day and battery)
and takes their primal-dual Newton systems apart into a step at fixed prices and the response
to a price step -- the pieces the coordinator assembles into the centralized Newton step.
"""

from __future__ import annotations

import warnings

import numpy as np

from .._util.lazy import lazy_module
from ..config import PER_BATTERY, ConfigWarning, SystemConfig
from ..mpc.formulation import MPC
from ..theta import PARTS

ca = lazy_module("casadi")  # CasADi (~0.1-0.2 s of import) loads when first used

__all__ = ["LocalQP", "local_system"]


def local_system(system: SystemConfig, local_grid_factor: float = 1e4,
                 battery: int = 0) -> SystemConfig:
    """The local MPC's system: ``system`` with ``n = 1``, the per-battery fields of battery
    ``battery`` (its own input bound ``U_bar`` among them) and an inert grid row
    (``P_bar = local_grid_factor * max(U_bar..., P_bar)`` with the largest ``U_bar`` of all
    batteries, the same row for every battery; the true limit is priced)."""
    if not isinstance(system, SystemConfig):
        raise ValueError(f"system={system!r}: expected a SystemConfig")  # noqa: TRY004
    U_all = system.battery("U_bar")
    if not 0 <= battery < system.n:
        raise ValueError(f"battery={battery!r}: expected an index 0..{system.n - 1}")
    own = {name: system.battery(name)[battery] for name in PER_BATTERY if name != "U_bar"}
    own = {name: value for name, value in own.items() if isinstance(getattr(system, name), tuple)}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ConfigWarning)
        return system.replace(n=1, P_bar=local_grid_factor * max(*U_all, system.P_bar),
                              U_bar=U_all[battery], **own)


def _scatter(out: ca.DM, shape: tuple[int, int], flat: np.ndarray) -> np.ndarray:
    """The dense array of a CasADi output with the structural nonzeros at the flat
    (row-major) positions ``flat``."""
    dense = np.zeros(shape)
    dense.ravel()[flat] = np.fromiter(out.nonzeros(), float, len(flat))
    return dense


class LocalQP:
    """The local MPC's barrier problems, many at once (one per day and battery).

    Data ``f = 0.5 x'Hx + q'x``, ``Ax = e``, ``Cx <= d`` of the MPC's own
    :meth:`~mpcrl_lite.mpc.formulation.MPC.qp_function`. ``H`` is diagonal and ``C`` block diagonal by
    stage (5 variables and 10 rows per stage for ``n = 1``), so a Newton system is solved with
    5x5 block inverses and an ``N x N`` Schur complement on the dynamics multipliers.

    Arrays have a leading batch axis ``B`` (problems); ``nx = 5N`` variables, ``N`` dynamics
    rows, ``10`` inequality rows per stage.

    Parameters
    ----------
    mpc : MPC
        The local MPC (``n = 1``), e.g. ``MPC(local_system(system))``.
    U_bar : sequence of float, optional
        Every battery's input bound, ``n`` values (default: the one of ``mpc``). The batch
        axis is then ordered (day, battery), battery fastest, and battery ``i``'s rows
        ``b <= U_bar``, ``s <= U_bar`` use ``U_bar[i]``: ``db`` has shape ``(n, N, 10)``.
    """

    nb, nh = 5, 10

    def __init__(self, mpc: MPC, U_bar: tuple[float, ...] | None = None) -> None:
        if mpc.n != 1:
            raise ValueError(f"the local MPC has n={mpc.n}; expected n=1")
        self.mpc = mpc
        N = mpc.N
        p = ca.MX.sym("p", mpc.np)
        rows, cols = mpc.qp_function.sparsity_out("H").get_triplet()
        if list(rows) != list(cols):  # the structure the Newton systems rely on
            raise RuntimeError("the MPC's Hessian is not diagonal")
        H, q, _, A, e, _, _ = mpc.qp_function(p)
        self._data = ca.Function("local_qp", [p], [ca.diag(H), q, A, e])
        #: rows and columns of the dynamics matrix's structural nonzeros
        self.a_pattern = tuple(np.array(v, dtype=np.int64)
                               for v in self._data.sparsity_out(2).get_triplet())
        ref = mpc.qp_data(np.full(mpc.np, 0.5))  # C and d do not depend on p
        self.Cb = np.stack([ref.C[j * self.nh : (j + 1) * self.nh, j * self.nb : (j + 1) * self.nb]
                            for j in range(N)])
        rebuilt = np.zeros_like(ref.C)
        for j in range(N):
            rebuilt[j * self.nh : (j + 1) * self.nh, j * self.nb : (j + 1) * self.nb] = self.Cb[j]
        if not np.array_equal(rebuilt, ref.C):
            raise RuntimeError("the MPC's inequality rows are not block diagonal by stage")
        self._CbT = np.ascontiguousarray(np.swapaxes(self.Cb, 1, 2))
        sysc = mpc.system
        U = np.array([sysc.U_bar] if U_bar is None else U_bar, dtype=float)
        if U.ndim != 1 or U.size == 0 or not np.all(np.isfinite(U) & (U > 0)):
            raise ValueError(f"U_bar={U_bar!r}: expected one positive bound per battery")
        #: every battery's input bound, ``(n,)``
        self.U = U
        #: right-hand sides of the inequality rows by battery and stage, ``(n, N, 10)``
        self.db = np.tile(ref.d.reshape(N, self.nh), (U.size, 1, 1))
        for name in ("b_max", "s_max"):
            row = int(mpc.inequality_index(name, 0)[0])
            self.db[:, :, row] = U[:, None]
        self._maps: dict[int, tuple[ca.Function, list]] = {}
        self.soc_low, self.soc_high = sysc.soc_low, sysc.soc_high
        self.ib, self.is_ = mpc.index("b")[:, 0], mpc.index("s")[:, 0]
        self.isoc = mpc.index("soc")[:, 0]
        self.ihi, self.ilo = mpc.index("sigma_hi")[:, 0], mpc.index("sigma_lo")[:, 0]
        # gamma**j as the formulation computes it (Python's power, not numpy's: the same bits)
        self._gamma = np.array([sysc.gamma**j for j in range(N + 1)])
        self._check_data()

    def data(self, P: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """``Hd (B, nx), q (B, nx), A (B, N, nx), e (B, N)`` for parameters ``P (B, np)``.

        Written out from the formulation's cost and dynamics (paper eq. 9 with ``n = 1``):
        with ``gamma_j = gamma**j``,

        * ``q[b_j] = gamma_j (buy_j + theta_b)``, ``q[s_j] = -gamma_j (sell_j + theta_s)``;
        * ``Hd[soc_j] = 2 gamma_{j+1} phi1``, ``q[soc_j] = gamma_{j+1} phi2`` before the last
          stage, ``2 T1`` and ``T2`` at it; ``q[sigma_j] = gamma_{j+1} omega`` (``omega_f`` at
          the last stage);
        * row ``j`` of ``A``: ``+1`` at ``soc_j``, ``-1`` at ``soc_{j-1}``, ``-alpha`` at
          ``b_j``, ``+alpha`` at ``s_j``; ``e_j = delta`` (``soc0 + delta`` at ``j = 0``).

        The same operations as CasADi's evaluation of :attr:`MPC.qp_function
        <mpcrl_lite.mpc.formulation.MPC.qp_function>`, so the same numbers bit for bit
        (:meth:`data_reference`, checked at construction and in the tests), ~8x faster for a
        month's batch (the CasADi map and its sparse outputs cost ~9 ms an hour at
        ``n = 20``).
        """
        P = np.asarray(P, dtype=float)
        m = self.mpc
        if P.ndim != 2 or P.shape[1] != m.np:
            raise ValueError(f"P has shape {P.shape}; expected (B, np={m.np})")
        B, N = P.shape[0], m.N
        part = {name: P[:, 1 + 2 * N + k] for k, name in enumerate(PARTS)}
        gam, omega, omega_f = self._gamma, self.mpc.system.omega, self.mpc.system.omega_f
        w = gam[1:N]  # the weights of soc_j and sigma_j before the last stage
        Hd = np.zeros((B, m.nx))
        q = np.zeros((B, m.nx))
        q[:, self.ib] = gam[:N] * (P[:, 1 : 1 + N] + part["b"][:, None])
        q[:, self.is_] = -(gam[:N] * (P[:, 1 + N : 1 + 2 * N] + part["s"][:, None]))
        Hd[:, self.isoc[:-1]] = 2.0 * (part["phi1"][:, None] * w)
        Hd[:, self.isoc[-1]] = 2.0 * part["T1"]
        q[:, self.isoc[:-1]] = part["phi2"][:, None] * w
        q[:, self.isoc[-1]] = part["T2"]
        for idx, om, om_f in ((self.ihi, omega[0], omega_f[0]), (self.ilo, omega[1], omega_f[1])):
            q[:, idx[:-1]] = w * om
            q[:, idx[-1]] = om_f
        A = np.zeros((B, N, m.nx))
        j = np.arange(N)
        A[:, j, self.isoc] = 1.0
        A[:, j[1:], self.isoc[:-1]] = -1.0
        A[:, j, self.ib] = -part["alpha"][:, None]
        A[:, j, self.is_] = part["alpha"][:, None]
        e = np.repeat(part["delta"][:, None], N, axis=1)
        e[:, 0] = P[:, 0] + part["delta"]
        return Hd, q, A, e

    def data_reference(
        self, P: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`data` evaluated by CasADi from :attr:`MPC.qp_function
        <mpcrl_lite.mpc.formulation.MPC.qp_function>` (the reference of the written-out data)."""
        B = P.shape[0]
        if B not in self._maps:
            fn = self._data.map(B)
            patterns = []
            for k in range(fn.n_out()):
                rows, cols = fn.sparsity_out(k).get_triplet()
                shape = fn.size_out(k)
                patterns.append((shape, np.ravel_multi_index((rows, cols), shape)))
            self._maps[B] = (fn, patterns)
        fn, patterns = self._maps[B]
        # the structural nonzeros scattered into dense arrays: ~10x faster than converting
        # the dense matrices (A alone has N x B nx entries), the same numbers
        Hd, q, A, e = (_scatter(out, *pattern) for out, pattern in zip(fn(P.T), patterns))
        m = self.mpc
        return (np.array(Hd).T, np.array(q).T,
                np.array(A).reshape(m.neq, B, m.nx).transpose(1, 0, 2), np.array(e).T)

    def _check_data(self) -> None:
        """:meth:`data` against :meth:`data_reference` at pseudo-random parameters of several
        magnitudes: a change of the formulation must not go unnoticed."""
        rng = np.random.default_rng(20201)
        P = rng.normal(size=(4, self.mpc.np)) * 10.0 ** rng.integers(-3, 3, (4, self.mpc.np))
        for name, new, ref in zip(("Hd", "q", "A", "e"), self.data(P), self.data_reference(P)):
            if not np.allclose(new, ref, rtol=1e-14, atol=0.0):
                raise RuntimeError(
                    f"LocalQP.data's {name} differs from MPC.qp_function's; the formulation "
                    "in mpcrl_lite.mpc.formulation changed and LocalQP.data must be updated "
                    "to match it")

    def h(self, x: np.ndarray) -> np.ndarray:
        """``h = Cx - d`` by stage, shape ``(B, N, 10)`` (``B`` a multiple of ``n``, ordered
        (day, battery))."""
        Cx = (self.Cb @ x.reshape(x.shape[0], -1, self.nb, 1))[..., 0]
        return (Cx.reshape(-1, *self.db.shape) - self.db).reshape(Cx.shape)

    def d(self, B: int) -> np.ndarray:
        """``d`` by stage for a batch of ``B`` problems ordered (day, battery), ``(B, N, 10)``."""
        return np.tile(self.db, (B // self.db.shape[0], 1, 1))

    def bound(self, B: int) -> np.ndarray:
        """Every problem's input bound for a batch of ``B`` ordered (day, battery), ``(B,)``."""
        return np.tile(self.U, B // self.U.size)

    def Ct(self, v: np.ndarray) -> np.ndarray:
        """``C' v`` for ``v (B, N, 10)``, shape ``(B, nx)``."""
        return (self._CbT @ v[..., None]).reshape(v.shape[0], -1)

    def E(self, x: np.ndarray) -> np.ndarray:
        """The grid-relevant part ``(b_0..b_{N-1}, s_0..s_{N-1})`` of ``x (..., nx)``."""
        return np.concatenate([x[..., self.ib], x[..., self.is_]], axis=-1)

    def Et(self, v: np.ndarray) -> np.ndarray:
        """``E' v`` for ``v (B, 2N)``, shape ``(B, nx)``."""
        N = self.mpc.N
        out = np.zeros((v.shape[0], self.mpc.nx))
        out[:, self.ib], out[:, self.is_] = v[:, :N], v[:, N:]
        return out

    def feasible(self, A: np.ndarray, e: np.ndarray, x: np.ndarray) -> np.ndarray:
        """A point near ``x`` satisfying the dynamics and strictly inside every local bound:
        inputs kept where strictly inside their bounds, soc recomputed from the model, slacks
        raised only where needed (to at least 1e-3 above the soc band's bound, so that no
        barrier term starts at a vanishing distance from its bound)."""
        x = x.copy()
        U = self.bound(x.shape[0])[:, None]
        margin = 1e-3 * U
        for i in (self.ib, self.is_):
            v = x[:, i]
            x[:, i] = np.where((v > 0) & (v < U), v, np.clip(v, margin, U - margin))
        # the dynamics (rows of A as in :meth:`data`): soc_j = soc_{j-1} + e_j - (A_b b_j +
        # A_s s_j), a running sum (the numbers of a dense solve with A's soc block, bit for
        # bit: that block is unit lower bidiagonal)
        j = np.arange(A.shape[1])
        flow = A[:, j, self.ib] * x[:, self.ib] + A[:, j, self.is_] * x[:, self.is_]
        soc = np.cumsum(e - flow, axis=1)
        x[:, self.isoc] = soc
        for i, need in ((self.ihi, np.maximum(soc - self.soc_high, 0.0)),
                        (self.ilo, np.maximum(self.soc_low - soc, 0.0))):
            x[:, i] = np.where(x[:, i] >= need + 1e-3, x[:, i], need + 1e-3)
        return x

    def residual(
        self,
        Hd: np.ndarray,
        q: np.ndarray,
        A: np.ndarray,
        e: np.ndarray,
        x: np.ndarray,
        lam: np.ndarray,
        mu: np.ndarray,
        tau: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Barrier KKT residual ``r_x (B, nx), r_g (B, N), r_c (B, N, 10)`` and ``h``
        (``(B, N, 10)``) at ``x (B, nx)``, ``lam (B, N)``, ``mu (B, N, 10)`` of the problems
        with data ``Hd, q (B, nx)``, ``A (B, N, nx)``, ``e (B, N)`` and ``tau (B,)``."""
        h = self.h(x)
        rx = Hd * x + q + (np.swapaxes(A, 1, 2) @ lam[..., None])[..., 0] + self.Ct(mu)
        rg = (A @ x[..., None])[..., 0] - e
        rc = mu * h + tau[:, None, None]
        return rx, rg, rc, h

    def newton(
        self,
        Hd: np.ndarray,
        q: np.ndarray,
        A: np.ndarray,
        e: np.ndarray,
        x: np.ndarray,
        mu: np.ndarray,
        h: np.ndarray,
        tau: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The local Newton system, split by its dependence on a price step ``dlambda``.

        The primal-dual step with ``mu`` eliminated solves ``W dx + A' lam_new = -grad_phi
        - E' dlambda``, ``A dx = -r_g`` with ``W = H + C' diag(mu/-h) C`` and
        ``grad_phi = Hx + q + C' (tau/-h)``; its solution is ``dx = dx0 + X dlambda``,
        ``lam_new = lam0 + L dlambda``.

        Returns
        -------
        dx0 (B, nx), lam0 (B, N)
            The step at fixed prices.
        L (B, N, 2N), M (B, 2N, 2N)
            ``L`` as above and ``M = E X``, the response of ``(b, s)`` to the prices
            (symmetric negative semidefinite).
        Winv (B, N, 5, 5)
            The block inverses of ``W``, for :meth:`price_step`.
        """
        B, N, nb = x.shape[0], self.mpc.N, self.nb
        W = self._CbT @ ((mu / -h)[..., None] * self.Cb)  # (B, N, nb, nb)
        W[:, :, np.arange(nb), np.arange(nb)] += Hd.reshape(B, N, nb)
        Winv = np.linalg.inv(W)
        At = np.swapaxes(A, 1, 2)
        Ab = A.reshape(B, N, N, nb).transpose(0, 2, 1, 3)  # (B, block j, row r, k)
        AW = (Ab @ Winv).transpose(0, 2, 1, 3).reshape(B, N, -1)  # A W^{-1}, (B, N, nx)
        S = AW @ At
        rg = (A @ x[..., None])[..., 0] - e
        r1 = -(Hd * x + q + self.Ct(tau[:, None, None] / -h))
        lam0 = np.linalg.solve(S, ((AW @ r1[..., None])[..., 0] + rg)[..., None])[..., 0]
        dx0 = self._winv(Winv, r1 - (At @ lam0[..., None])[..., 0])
        # A W^{-1} E: the b_j and s_j columns of A W^{-1}; E W^{-1} E: 2x2 blocks of W^{-1}
        AWE = np.concatenate([AW[:, :, self.ib], AW[:, :, self.is_]], axis=2)  # (B, N, 2N)
        L = -np.linalg.solve(S, AWE)
        EWE = np.zeros((B, 2, N, 2, N))
        j = np.arange(N)
        for a in (0, 1):
            for b in (0, 1):
                EWE[:, a, j, b, j] = Winv[:, :, a, b]
        M = -(EWE.reshape(B, 2 * N, 2 * N) + np.swapaxes(AWE, 1, 2) @ L)
        return dx0, lam0, L, M, Winv

    def _winv(self, Winv: np.ndarray, v: np.ndarray) -> np.ndarray:
        """``W^{-1} v`` for ``v (B, nx)``."""
        B, N, nb = v.shape[0], self.mpc.N, self.nb
        return (Winv @ v.reshape(B, N, nb, 1)).reshape(B, -1)

    def price_step(
        self, A: np.ndarray, L: np.ndarray, Winv: np.ndarray, dnu: np.ndarray
    ) -> np.ndarray:
        """``X dlambda = -W^{-1} (E' dlambda + A' L dlambda)`` for ``dnu (B, 2N)``."""
        rhs = self.Et(dnu) + (np.swapaxes(A, 1, 2) @ (L @ dnu[..., None]))[..., 0]
        return -self._winv(Winv, rhs)
