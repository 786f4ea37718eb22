r"""Compiled (numba) coordination rounds of the local MPCs (:mod:`mpcrl_lite.decentralized.coordination`).

:func:`coordinate` runs *the same rounds* as the vectorized
:class:`~mpcrl_lite.decentralized.coordination.CoordinatedMPC` (the decomposed interior point of the
centralized barrier problem, see that module's docstring), day by day in compiled loops, on
the local problems' data of :class:`~mpcrl_lite.decentralized.local_qp.LocalQP`: per battery ``i`` and day

.. math::
   \min_{x_i}\; \tfrac12 x_i^\top H_i x_i + (q_i + E^\top\nu)^\top x_i
   - \tau\sum_k\log(d_k - C_k x_i)\quad\text{s.t.}\quad A_i x_i = e_i ,

``nu = (lambda^b, lambda^s)`` the day's grid prices, coupled by
:math:`\nu_m (\sum_i E x_i - \bar P)_m + \tau = 0`. The vectorized code is the reference;
both give the same iterates to rounding (same starting point, Newton directions, step
lengths, line search, ``tau`` path and stopping rule, and the same lockstep of the days: a
round in which some day finishes steps no day, as there).

One round of one day
--------------------
1. Every battery forms its barrier KKT residual ``r_x = Hx + q + E'nu + A'lam + C'mu``,
   ``r_g = Ax - e``, ``r_c = mu h + tau`` (``h = Cx - d < 0``) and its Newton system with
   ``mu`` eliminated, ``W = H + C' diag(mu/-h) C`` (5x5 blocks per stage, inverted),
   ``S = A W^{-1} A'`` (``N x N``), and splits the step by its dependence on a price step:
   ``dx = dx0 + X dnu``, ``lam_new = lam0 + L dnu`` with ``L = -S^{-1} A W^{-1} E'`` and
   ``M = E X = -(E W^{-1} E' + E W^{-1} A' L)`` (``2N x 2N``).
2. The coordinator solves :math:`(\sum_i M_i + \mathrm{diag}(c/\nu))\,d\nu = -(c + \tau/\nu)
   - \sum_i E\,dx^0_i` with ``c = sum_i E x_i - P_bar`` (LU with partial pivoting).
3. Fraction to the boundary (0.995) over the local rows and multipliers, the grid rows and
   prices; backtracking (halving, at most 40 times) until the 2-norm of all residuals
   decreases by the factor ``1 - 1e-4 t``.

Linear systems are solved by Gaussian elimination with partial pivoting (``W`` blocks,
``S``, the coordinator's system); a zero pivot or a non-finite direction stops that day's
rounds (the caller's fallback), as a singular system does in the reference. The fixed
sparsity is used (:class:`Structure`): ``A`` and ``C`` by their nonzero entries, ``W_j``
by its diagonal blocks (on the paper's MPC ``b`` and ``s`` alone, ``soc`` with its two
slacks), ``S`` and ``A W^{-1}`` by the stages a dynamics row touches. Cost: about 5 us per
battery and round (``n = 20``, ``N = 12``: ~0.15 ms per day and round), against ~2.5 ms per
day and round for the vectorized reference.

The kernels are compiled into numba's on-disk cache with those of :mod:`mpcrl_lite.mpc.backends.kernel_core`
(:func:`warm_up`, called by ``python -m mpcrl_lite.cli.warm``).

Why one module of ~630 lines: the compiled rounds call each other inside numba's loops, and
numba's on-disk cache checks only the source file of a compiled function, not the files of
the functions it calls; kept in one file, an edit recompiles all of them together.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from .._util import jit

# IEEE semantics kept (NaN and inf are detected), reassociation and fused multiply-adds allowed
_FAST = {"reassoc", "contract", "nsz", "arcp"}
_jit = jit.njit_cached(error_model="numpy", fastmath=_FAST)
_inline = jit.njit_cached(error_model="numpy", fastmath=_FAST, inline="always")
# the rounds of blocks of days, callable from several threads at once
_nogil = jit.njit_cached(error_model="numpy", fastmath=_FAST, nogil=True)

_ETA = 0.995  # fraction to the boundary
_ARMIJO = 1e-4
_BACKTRACKS = 40


# ----------------------------------------------------------------------- linear algebra ----
@_inline
def _lu(a, piv):
    """In-place LU factorisation with partial pivoting of the square ``a``; False if a
    pivot is zero or not finite."""
    m = a.shape[0]
    for k in range(m):
        p = k
        big = abs(a[k, k])
        for r in range(k + 1, m):
            v = abs(a[r, k])
            if v > big:
                big, p = v, r
        piv[k] = p
        if not (big > 0.0) or not math.isfinite(big):
            return False
        if p != k:
            for col in range(m):
                a[k, col], a[p, col] = a[p, col], a[k, col]
        inv = 1.0 / a[k, k]
        for r in range(k + 1, m):
            f = a[r, k] * inv
            a[r, k] = f
            if f != 0.0:
                for col in range(k + 1, m):
                    a[r, col] -= f * a[k, col]
    return True


@_inline
def _lu_solve(a, piv, b):
    """Solve ``a_orig z = b`` in place for ``b`` of shape ``(m,)`` or ``(m, k)`` given
    :func:`_lu`'s factors (``b`` 2-d: every column)."""
    m = a.shape[0]
    k = b.shape[1]
    for i in range(m):
        p = piv[i]
        if p != i:
            for col in range(k):
                b[i, col], b[p, col] = b[p, col], b[i, col]
    for i in range(m):
        for r in range(i + 1, m):
            f = a[r, i]
            if f != 0.0:
                for col in range(k):
                    b[r, col] -= f * b[i, col]
    for i in range(m - 1, -1, -1):
        inv = 1.0 / a[i, i]
        for col in range(k):
            b[i, col] *= inv
        for r in range(i):
            f = a[r, i]
            if f != 0.0:
                for col in range(k):
                    b[r, col] -= f * b[i, col]


# ------------------------------------------------------------------------- residuals ----
# Sparse data of the local problems (built by :func:`structure`): the dynamics rows
# ``A[r] = sum_k aval[r, k] e_{acol[r, k]}'`` (padded with zero values), their blocks
# ``ablo[r]..abhi[r]``, and per stage the inequality entries ``Cb[j, cr, cc] = cv`` and the
# products ``C' D C`` needs, ``W[wa, wb] += D[wr] wv``.
@_inline
def _kkt_day(Hd, q0, aval, e, acol, cr, cc, cv, db, kb, ks, P_bar, x, lam, mu, nu, tau,
             qeff, h, rc, c, rx):
    """Barrier KKT residuals of one day (``n`` batteries): fills ``qeff (n, nx)``,
    ``h, rc (n, N, 10)``, ``c (2N,)``; returns the 2-norm of every residual and the
    largest absolute one."""
    n, nx = x.shape
    N, nh = db.shape[1], db.shape[2]
    nb = nx // N
    ka, kc = acol.shape[1], cr.shape[1]
    sq = 0.0
    big = 0.0
    for m in range(2 * N):
        c[m] = -P_bar
    for i in range(n):
        for k in range(nx):
            qeff[i, k] = q0[i, k]
        for j in range(N):
            qeff[i, j * nb + kb] += nu[j]
            qeff[i, j * nb + ks] += nu[N + j]
            c[j] += x[i, j * nb + kb]
            c[N + j] += x[i, j * nb + ks]
        # r_x = H x + q + A' lam + C' mu
        for k in range(nx):
            rx[k] = Hd[i, k] * x[i, k] + qeff[i, k]
        for r in range(N):
            v = -e[i, r]
            for k in range(ka):
                col = acol[r, k]
                a = aval[i, r, k]
                rx[col] += a * lam[i, r]
                v += a * x[i, col]
            sq += v * v
            big = max(big, abs(v))
        for j in range(N):
            for row in range(nh):
                h[i, j, row] = -db[i, j, row]
            for k in range(kc):
                h[i, j, cr[j, k]] += cv[j, k] * x[i, j * nb + cc[j, k]]
                rx[j * nb + cc[j, k]] += cv[j, k] * mu[i, j, cr[j, k]]
            for row in range(nh):
                r = mu[i, j, row] * h[i, j, row] + tau
                rc[i, j, row] = r
                sq += r * r
                big = max(big, abs(r))
        for k in range(nx):
            sq += rx[k] * rx[k]
            big = max(big, abs(rx[k]))
    for m in range(2 * N):
        r = nu[m] * c[m] + tau
        sq += r * r
        big = max(big, abs(r))
    if not math.isfinite(sq):
        big = np.inf
    return math.sqrt(sq), big


# --------------------------------------------------------------------- Newton pieces ----
@_jit
def _newton_battery(Hd, q, aval, e, acol, ablo, abhi, cr, cc, cv, wr, wa, wb, wv, perm, cstart,
                    kb, ks, x, mu, h, tau, dx0, lam0, L, Winv, Mtot, Edx0, W, W5, I5, piv5, AW, S,
                    pivN, rhs, tmp, AWE):
    """One battery's Newton system split by the price step (step 1 of the module
    docstring): fills ``dx0 (nx,)``, ``lam0 (N,)``, ``L (N, 2N)``, ``Winv (N, 5, 5)`` and
    adds ``M`` to ``Mtot`` and ``E dx0`` to ``Edx0``; False if a system is singular."""
    nx = x.shape[0]
    N = h.shape[0]
    nb = nx // N
    ka, kc, kw = acol.shape[1], cr.shape[1], wr.shape[1]
    # W_j = H_j + C_j' diag(mu / -h) C_j and its inverse, per stage
    for j in range(N):
        for a in range(nb):
            for b in range(nb):
                W[a, b] = 0.0
            W[a, a] = Hd[j * nb + a]
        for k in range(kw):
            W[wa[j, k], wb[j, k]] += wv[j, k] * (mu[j, wr[j, k]] / -h[j, wr[j, k]])
        # W_j is block diagonal (groups of variables coupled by a row, cstart/perm)
        for a in range(nb):
            for b in range(nb):
                Winv[j, a, b] = 0.0
        for g in range(cstart.shape[0] - 1):
            g0, m = cstart[g], cstart[g + 1] - cstart[g]
            if m == 1:
                v = perm[g0]
                Winv[j, v, v] = 1.0 / W[v, v]
                continue
            Wg, Ig = W5[:m, :m], I5[:m, :m]
            for a in range(m):
                for b in range(m):
                    Wg[a, b] = W[perm[g0 + a], perm[g0 + b]]
                    Ig[a, b] = 1.0 if a == b else 0.0
            if not _lu(Wg, piv5):
                return False
            _lu_solve(Wg, piv5, Ig)
            for a in range(m):
                for b in range(m):
                    Winv[j, perm[g0 + a], perm[g0 + b]] = Ig[a, b]
    # A W^{-1} (N, nx): row r lives in blocks ablo[r]..abhi[r]
    for r in range(N):
        for col in range(ablo[r] * nb, (abhi[r] + 1) * nb):
            AW[r, col] = 0.0
        for k in range(ka):
            col = acol[r, k]
            a = aval[r, k]
            j, p = col // nb, col % nb
            for b in range(nb):
                AW[r, j * nb + b] += a * Winv[j, p, b]
    for r in range(N):
        for s in range(N):
            v = 0.0
            if ablo[s] <= abhi[r] and ablo[r] <= abhi[s]:
                for k in range(ka):
                    col = acol[s, k]
                    if ablo[r] * nb <= col < (abhi[r] + 1) * nb:
                        v += AW[r, col] * aval[s, k]
            S[r, s] = v
    if not _lu(S, pivN):
        return False
    # r1 = -(H x + q + C' (tau / -h)), kept in dx0; rhs of lam0 is A W^{-1} r1 + r_g
    r1 = dx0
    for k in range(nx):
        r1[k] = -(Hd[k] * x[k] + q[k])
    for j in range(N):
        for k in range(kc):
            r1[j * nb + cc[j, k]] -= cv[j, k] * (tau / -h[j, cr[j, k]])
    for r in range(N):
        v = -e[r]
        for k in range(ka):
            v += aval[r, k] * x[acol[r, k]]
        for col in range(ablo[r] * nb, (abhi[r] + 1) * nb):
            v += AW[r, col] * r1[col]
        rhs[r, 0] = v
    _lu_solve(S, pivN, rhs)
    for r in range(N):
        lam0[r] = rhs[r, 0]
    # dx0 = W^{-1} (r1 - A' lam0)
    for k in range(nx):
        tmp[k] = r1[k]
    for r in range(N):
        for k in range(ka):
            tmp[acol[r, k]] -= aval[r, k] * lam0[r]
    for j in range(N):
        for a in range(nb):
            v = 0.0
            for b in range(nb):
                v += Winv[j, a, b] * tmp[j * nb + b]
            dx0[j * nb + a] = v
    for j in range(N):
        Edx0[j] += dx0[j * nb + kb]
        Edx0[N + j] += dx0[j * nb + ks]
    # L = -S^{-1} A W^{-1} E'
    for r in range(N):
        for j in range(N):
            if ablo[r] <= j <= abhi[r]:
                AWE[r, j] = AW[r, j * nb + kb]
                AWE[r, N + j] = AW[r, j * nb + ks]
            else:
                AWE[r, j] = 0.0
                AWE[r, N + j] = 0.0
            L[r, j] = -AWE[r, j]
            L[r, N + j] = -AWE[r, N + j]
    _lu_solve(S, pivN, L)
    # M = -(E W^{-1} E' + (A W^{-1} E')' L)
    for j in range(N):
        Mtot[j, j] -= Winv[j, kb, kb]
        Mtot[j, N + j] -= Winv[j, kb, ks]
        Mtot[N + j, j] -= Winv[j, ks, kb]
        Mtot[N + j, N + j] -= Winv[j, ks, ks]
    for r in range(N):
        for jj in range(ablo[r], abhi[r] + 1):
            for m in (jj, N + jj):
                w = AWE[r, m]
                if w != 0.0:
                    for m2 in range(2 * N):
                        Mtot[m, m2] -= w * L[r, m2]
    return True


@_jit
def _direction_day(Hd, aval, e, acol, ablo, abhi, cr, cc, cv, wr, wa, wb, wv, perm, cstart, kb,
                   ks, x, lam,
                   mu, nu, tau, qeff, h, rc, c, dx, dlam, dmu, dnu, lam0, L, Winv, Mtot, Edx0,
                   W, W5, I5, piv5, AW, S, pivN, rhs, tmp, AWE, K, pivK, rhsK):
    """The Newton direction of one day (steps 1-2 and every battery's step); False if a
    system is singular or the direction not finite."""
    n, nx = x.shape
    N, nh = h.shape[1], h.shape[2]
    nb = nx // N
    ka, kc = acol.shape[1], cr.shape[1]
    for a in range(2 * N):
        Edx0[a] = 0.0
        for b in range(2 * N):
            Mtot[a, b] = 0.0
    for i in range(n):
        if not _newton_battery(Hd[i], qeff[i], aval[i], e[i], acol, ablo, abhi, cr, cc, cv, wr,
                               wa, wb, wv, perm, cstart, kb, ks, x[i], mu[i], h[i], tau, dx[i],
                               lam0[i], L[i], Winv[i], Mtot, Edx0, W, W5, I5, piv5, AW, S, pivN,
                               rhs, tmp, AWE):
            return False
    for a in range(2 * N):
        for b in range(2 * N):
            K[a, b] = Mtot[a, b]
        K[a, a] += c[a] / nu[a]
        rhsK[a, 0] = -(c[a] + tau / nu[a]) - Edx0[a]
    if not _lu(K, pivK):
        return False
    _lu_solve(K, pivK, rhsK)
    for a in range(2 * N):
        dnu[a] = rhsK[a, 0]
    finite = 0.0
    for i in range(n):
        # dx = dx0 - W^{-1} (E' dnu + A' L dnu)
        for k in range(nx):
            tmp[k] = 0.0
        for r in range(N):
            v = 0.0
            for m in range(2 * N):
                v += L[i, r, m] * dnu[m]
            dlam[i, r] = lam0[i, r] + v - lam[i, r]
            for k in range(ka):
                tmp[acol[r, k]] += aval[i, r, k] * v
        for j in range(N):
            tmp[j * nb + kb] += dnu[j]
            tmp[j * nb + ks] += dnu[N + j]
        for j in range(N):
            for a in range(nb):
                v = 0.0
                for b in range(nb):
                    v += Winv[i, j, a, b] * tmp[j * nb + b]
                dx[i, j * nb + a] -= v
        # dmu = -(r_c + mu C dx) / h
        for j in range(N):
            for row in range(nh):
                dmu[i, j, row] = 0.0
            for k in range(kc):
                dmu[i, j, cr[j, k]] += cv[j, k] * dx[i, j * nb + cc[j, k]]
            for row in range(nh):
                dmu[i, j, row] = -(rc[i, j, row] + mu[i, j, row] * dmu[i, j, row]) / h[i, j, row]
                finite += 0.0 * dmu[i, j, row]
        for k in range(nx):
            finite += 0.0 * dx[i, k]
        for r in range(N):
            finite += 0.0 * dlam[i, r]
    for a in range(2 * N):
        finite += 0.0 * dnu[a]
    return finite == 0.0


@_inline
def _step_length(cr, cc, cv, mu, nu, h, c, dx, dmu, dnu, dc, dh, kb, ks):
    """The largest ``t <= 1`` keeping the fraction 0.995 of the distance to every bound."""
    n, N, nh = h.shape
    nb = dx.shape[1] // N
    kc = cr.shape[1]
    lim = np.inf
    for m in range(2 * N):
        dc[m] = 0.0
    for i in range(n):
        for j in range(N):
            dc[j] += dx[i, j * nb + kb]
            dc[N + j] += dx[i, j * nb + ks]
            for row in range(nh):
                dh[row] = 0.0
            for k in range(kc):
                dh[cr[j, k]] += cv[j, k] * dx[i, j * nb + cc[j, k]]
            for row in range(nh):
                if dh[row] > 0.0:
                    lim = min(lim, -h[i, j, row] / dh[row])
                if dmu[i, j, row] < 0.0:
                    lim = min(lim, -mu[i, j, row] / dmu[i, j, row])
    for m in range(2 * N):
        if dc[m] > 0.0:
            lim = min(lim, -c[m] / dc[m])
        if dnu[m] < 0.0:
            lim = min(lim, -nu[m] / dnu[m])
    return min(1.0, _ETA * lim)


# --------------------------------------------------------------------------- rounds ----
class Structure(NamedTuple):
    """The fixed sparsity of the local problems, for :func:`coordinate` (see the comment
    above :func:`_kkt_day`): dynamics entries ``acol (N, ka)`` with blocks ``ablo, abhi
    (N,)``; inequality entries ``cr, cc, cv (N, kc)``; the products of ``C' D C``,
    ``wr, wa, wb, wv (N, kw)``; the diagonal blocks of ``W``, variables
    ``perm[cstart[g]:cstart[g + 1]]``; and where the dynamics values come from,
    ``A[:, rows, cols]`` into ``aval[:, rows, slots]``."""

    acol: np.ndarray
    ablo: np.ndarray
    abhi: np.ndarray
    cr: np.ndarray
    cc: np.ndarray
    cv: np.ndarray
    wr: np.ndarray
    wa: np.ndarray
    wb: np.ndarray
    wv: np.ndarray
    perm: np.ndarray
    cstart: np.ndarray
    rows: np.ndarray
    cols: np.ndarray
    slots: np.ndarray

    def values(self, A: np.ndarray) -> np.ndarray:
        """``aval (B, N, ka)``: the dynamics entries of ``A (B, N, nx)``."""
        aval = np.zeros((A.shape[0], *self.acol.shape))
        aval[:, self.rows, self.slots] = A[:, self.rows, self.cols]
        return aval

    def kernel_args(self) -> tuple[np.ndarray, ...]:
        """The arrays :func:`coordinate` takes after ``scale``."""
        return self[:12]


def structure(a_rows: np.ndarray, a_cols: np.ndarray, Cb: np.ndarray) -> Structure:
    """:class:`Structure` of local problems whose dynamics matrix ``A (N, nx)`` has its
    (structural) nonzeros at ``a_rows, a_cols`` and whose inequality rows are ``Cb (N, 10,
    5)``."""
    N, _, nb = Cb.shape
    a_rows, a_cols = np.asarray(a_rows, np.int64), np.asarray(a_cols, np.int64)
    order = np.lexsort((a_cols, a_rows))
    rows, cols = a_rows[order], a_cols[order]
    counts = np.bincount(rows, minlength=N)
    ka = max(1, int(counts.max()))
    slots = np.arange(rows.size) - np.concatenate([[0], np.cumsum(counts)[:-1]])[rows]
    acol = np.zeros((N, ka), np.int64)
    ablo, abhi = np.zeros(N, np.int64), np.zeros(N, np.int64)
    for r in range(N):
        mine = cols[rows == r]
        acol[r, :] = mine[0] if mine.size else 0  # padding: zero values
        acol[r, : mine.size] = mine
        if mine.size:
            ablo[r], abhi[r] = mine.min() // nb, mine.max() // nb
    entries = [np.argwhere(Cb[j] != 0.0) for j in range(N)]
    kc = max(1, max(len(ent) for ent in entries))
    cr, cc, cv = np.zeros((N, kc), np.int64), np.zeros((N, kc), np.int64), np.zeros((N, kc))
    pairs = [[(row, a, b, Cb[j, row, a] * Cb[j, row, b]) for row, a in ent for r2, b in ent
              if r2 == row] for j, ent in enumerate(entries)]
    kw = max(1, max(len(pr) for pr in pairs))
    wr, wa, wb = (np.zeros((N, kw), np.int64) for _ in range(3))
    wv = np.zeros((N, kw))
    for j in range(N):
        for k, (row, col) in enumerate(entries[j]):
            cr[j, k], cc[j, k], cv[j, k] = row, col, Cb[j, row, col]
        for k, (row, a, b, v) in enumerate(pairs[j]):
            wr[j, k], wa[j, k], wb[j, k], wv[j, k] = row, a, b, v
    # groups of variables coupled in W (the same at every stage): its diagonal blocks
    group = np.arange(nb)
    for j in range(N):
        for k in range(len(pairs[j])):
            ga, gb = group[wa[j, k]], group[wb[j, k]]
            group[group == max(ga, gb)] = min(ga, gb)
    perm = np.argsort(group, kind="stable").astype(np.int64)
    _, sizes = np.unique(group[perm], return_counts=True)
    cstart = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
    return Structure(acol, ablo, abhi, cr, cc, cv, wr, wa, wb, wv, perm, cstart, rows, cols,
                     slots.astype(np.int64))


@_nogil
def coordinate(Hd, q0, aval, e, scale, acol, ablo, abhi, cr, cc, cv, wr, wa, wb, wv, perm, cstart,
               db, kb, ks,
               n, P_bar, tau_t, tol, max_iter, x, lam, mu, nu, tau, rounds, done, stopped,
               worst):
    """Every day's rounds of one hour, in place (the reference: ``CoordinatedMPC._round``).

    Runs without the GIL, so blocks of days (slices of the day-indexed arguments) may run on
    several threads at once; each call allocates its own work arrays.

    Parameters
    ----------
    Hd, q0 : (B, nx)
        Local Hessian diagonals and linear costs at zero grid prices, ``B = days * n`` rows
        ordered (day, battery), battery fastest.
    aval (B, N, ka), e (B, N), acol, ablo, abhi, cr, cc, cv, wr, wa, wb, wv
        Local dynamics ``A x = e`` and inequality rows in the sparse form of
        :func:`structure`; ``db (n, N, 10)`` the right-hand sides of the inequality rows by
        battery (each battery's own input bound).
    scale : (D,)
        ``1 + max |q|`` per day, the scale of the tolerance.
    kb, ks : int
        Positions of ``b`` and ``s`` in a stage's block of 5 variables.
    n : int
    P_bar, tau_t, tol : float
        The grid limit, the MPC's ``tau``, the tolerance.
    max_iter : int
    x (B, nx), lam (B, N), mu (B, N, 10), nu (D, 2N), tau (D,)
        The start; overwritten by the last point.
    rounds (D,) int, done (D,) bool, stopped (D,) bool, worst (D,)
        Rounds taken, converged, stopped by a singular or non-finite system, last relative
        residual (updated in place).
    """
    B, nx = x.shape
    N, nh = db.shape[1], db.shape[2]
    nb = nx // N
    D = nu.shape[0]
    qeff, h, rc = np.empty((B, nx)), np.empty((B, N, nh)), np.empty((B, N, nh))
    c, dc, dh, rx = np.empty((D, 2 * N)), np.empty(2 * N), np.empty(nh), np.empty(nx)
    dx, dlam, dmu, dnu = np.empty((n, nx)), np.empty((n, N)), np.empty((n, N, nh)), np.empty(2 * N)
    lam0, L, Winv = np.empty((n, N)), np.empty((n, N, 2 * N)), np.empty((n, N, nb, nb))
    Mtot, Edx0 = np.empty((2 * N, 2 * N)), np.empty(2 * N)
    W, piv5 = np.empty((nb, nb)), np.empty(nb, np.int64)
    W5, I5 = np.empty((nb, nb)), np.empty((nb, nb))
    AW, S, pivN = np.zeros((N, nx)), np.empty((N, N)), np.empty(N, np.int64)
    rhs, tmp, AWE = np.empty((N, 1)), np.empty(nx), np.empty((N, 2 * N))
    K, pivK, rhsK = np.empty((2 * N, 2 * N)), np.empty(2 * N, np.int64), np.empty((2 * N, 1))
    xn, lamn, mun, nun = np.empty((n, nx)), np.empty((n, N)), np.empty((n, N, nh)), np.empty(2 * N)
    wabs, merit = np.empty(D), np.empty(D)
    fin = np.zeros(D, np.bool_)
    known = np.zeros(D, np.bool_)  # merit, wabs and the buffers are those of the day's point
    for _call in range(max_iter + 1):
        nrun, nfin, rmin = 0, 0, 1 << 62
        for d in range(D):
            fin[d] = False
            if done[d] or stopped[d]:
                continue
            nrun += 1
            rmin = min(rmin, rounds[d])
            s = slice(d * n, (d + 1) * n)
            if not known[d]:  # else the line search left them at this point
                merit[d], wabs[d] = _kkt_day(Hd[s], q0[s], aval[s], e[s], acol, cr, cc, cv, db,
                                             kb, ks, P_bar, x[s], lam[s], mu[s], nu[d], tau[d],
                                             qeff[s], h[s], rc[s], c[d], rx)
                known[d] = True
            worst[d] = wabs[d] / scale[d]
            if tau[d] <= tau_t and worst[d] <= tol:
                fin[d] = True
                nfin += 1
        if nrun == 0:
            break
        for d in range(D):
            if fin[d]:
                done[d] = True
        if nfin == nrun or rmin >= max_iter:
            break
        if nfin > 0:
            continue  # step only the days still running, in the next round
        for d in range(D):
            if done[d] or stopped[d]:
                continue
            s = slice(d * n, (d + 1) * n)
            if tau[d] > tau_t and wabs[d] <= 0.1 * tau[d] * scale[d]:
                tau[d] = max(tau_t, 0.1 * tau[d])  # centred: down the barrier path
                merit[d], _ = _kkt_day(Hd[s], q0[s], aval[s], e[s], acol, cr, cc, cv, db, kb,
                                       ks, P_bar, x[s], lam[s], mu[s], nu[d], tau[d], qeff[s],
                                       h[s], rc[s], c[d], rx)
            if not _direction_day(Hd[s], aval[s], e[s], acol, ablo, abhi, cr, cc, cv, wr, wa,
                                  wb, wv, perm, cstart, kb, ks, x[s], lam[s], mu[s], nu[d], tau[d], qeff[s],
                                  h[s], rc[s], c[d], dx, dlam, dmu, dnu, lam0, L, Winv, Mtot,
                                  Edx0, W, W5, I5, piv5, AW, S, pivN, rhs, tmp, AWE, K, pivK,
                                  rhsK):
                stopped[d] = True
                continue
            t = _step_length(cr, cc, cv, mu[s], nu[d], h[s], c[d], dx, dmu, dnu, dc, dh, kb, ks)
            xs, ls, ms, nus = x[s], lam[s], mu[s], nu[d]
            merit0 = merit[d]
            # the residuals of the last trial point (the new point) go to the day's buffers
            for _ in range(_BACKTRACKS):
                for i in range(n):
                    for k in range(nx):
                        xn[i, k] = xs[i, k] + t * dx[i, k]
                    for r in range(N):
                        lamn[i, r] = ls[i, r] + t * dlam[i, r]
                    for j in range(N):
                        for row in range(nh):
                            mun[i, j, row] = ms[i, j, row] + t * dmu[i, j, row]
                for m in range(2 * N):
                    nun[m] = nus[m] + t * dnu[m]
                merit[d], wabs[d] = _kkt_day(Hd[s], q0[s], aval[s], e[s], acol, cr, cc, cv, db,
                                             kb, ks, P_bar, xn, lamn, mun, nun, tau[d], qeff[s],
                                             h[s], rc[s], c[d], rx)
                if merit[d] <= (1.0 - _ARMIJO * t) * merit0:
                    break
                t *= 0.5
            xs[:] = xn
            ls[:] = lamn
            ms[:] = mun
            nus[:] = nun
            rounds[d] += 1


# ------------------------------------------------------------------ compilation, cache ----
def warm_up() -> None:
    """Run :func:`coordinate` on a tiny problem (two batteries, two stages), which compiles
    it or loads it from numba's cache."""
    n, N, nb, nh = 2, 2, 5, 10
    nx = nb * N
    Cb = np.zeros((N, nh, nb))
    for j in range(N):
        for k in range(nb):
            Cb[j, 2 * k, k], Cb[j, 2 * k + 1, k] = -1.0, 1.0
    db = np.tile(np.array([0.0, 1.0] * nb), (n, N, 1))
    A = np.zeros((n, N, nx))
    for r in range(N):
        A[:, r, r * nb + 2], A[:, r, r * nb], A[:, r, r * nb + 1] = 1.0, -0.1, 0.1
        if r:
            A[:, r, (r - 1) * nb + 2] = -1.0
    e = np.zeros((n, N))
    e[:, 0] = 0.5
    x = np.full((n, nx), 0.25)
    x[:, 2::nb] = 0.5
    rows, cols = np.nonzero(A[0])
    st = structure(rows, cols, Cb)
    coordinate(np.zeros((n, nx)), np.ones((n, nx)), st.values(A), e, np.ones(1),
               *st.kernel_args(), db, 0, 1, n, 1.5, 0.1, 1e-9, 5, x, np.zeros((n, N)),
               np.full((n, N, nh), 0.1), np.full((1, 2 * N), 0.1), np.full(1, 0.1),
               np.zeros(1, np.int64), np.zeros(1, np.bool_), np.zeros(1, np.bool_),
               np.full(1, np.inf))


def ensure_compiled() -> None:
    """Load :func:`coordinate` from the cache or compile it (logging one line if it compiles)."""
    jit.ensure_compiled((coordinate,), warm_up, "the coordination kernel")
