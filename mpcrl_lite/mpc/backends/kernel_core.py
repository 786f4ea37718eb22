r"""Compiled (numba) kernels of :class:`~mpcrl_lite.mpc.backends.kernel.KernelSolver`.

The same barrier interior point as :class:`~mpcrl_lite.mpc.backends.batch.BatchSolver` (same start,
Mehrotra predictor-corrector then pure Newton steps at ``t = tau``, same stopping rule, with
or without its polishing step), run
problem by problem in compiled loops (or four problems side by side, below): nothing here
allocates inside the Newton iteration.

Why one module of ~2,500 lines: it is one algorithm (the start, the Newton iteration and its
factorisations, the stopping rule and the KKT sensitivity of the same barrier problem) whose
parts call each other inside compiled loops, and numba's on-disk cache checks only the source
file of a compiled function, not the files of the functions it calls. Split over several files,
an edit of one part could leave another part's cached machine code stale; in one file, any edit
recompiles everything (``python -m mpcrl_lite.cli.warm``).
The notation follows :mod:`mpcrl_lite.mpc.backends.batch`'s docstring: per problem ``n`` agents,
``N`` stages; ``X`` (5, n, N) holds ``b, s, soc, sigma_hi, sigma_lo``; ``L`` (n, N) the
dynamics multipliers; inequality arrays (``S``, ``mu``, ...) are flat, ``m = 8 n N + 2 N``
entries: the per-agent groups (8, n, N) then the grid rows (2, N) (views :func:`_ag`,
:func:`_gr`).

Reduced Newton system
---------------------
After ``d mu`` is eliminated, a Newton step solves

.. math:: \begin{bmatrix} W & A^\top \\ A & 0\end{bmatrix}
          \begin{bmatrix} dx\\ d\lambda\end{bmatrix} = \begin{bmatrix} r_1 \\ r_2\end{bmatrix},
          \qquad W = H + C^\top D C .

The slack variables ``sigma_hi, sigma_lo`` are eliminated in closed form (``W_soc = 1/V``).
Two factorisations of the rest are implemented; :func:`choose_method` picks the cheaper one.

``STAGE`` (few agents): per stage ``j``, the ``b`` block of ``W`` is
``diag(1/vb) + D_grid,b 1 1'`` (rank one over the agents), inverted exactly by
Sherman-Morrison, ``W_b^{-1} = diag(vb) - kappa_b vb vb'`` with
``kappa_b = D_grid,b / (1 + D_grid,b sum vb)`` (likewise ``s``); ``soc`` has a diagonal block.
Eliminating ``b, s, soc`` leaves the symmetric positive definite block-tridiagonal system
``T d lambda = rho`` with ``n x n`` blocks

.. math:: T_{jj} = \mathrm{diag}(V_j + V_{j-1}) + \mathrm{diag}(\alpha)
          (W_{b,j}^{-1} + W_{s,j}^{-1})\,\mathrm{diag}(\alpha),\qquad
          T_{j,j+1} = -\mathrm{diag}(V_j),

eliminated stage by stage, ``Sigma_j = T_jj - diag(V_{j-1}) Sigma_{j-1}^{-1}
diag(V_{j-1})``, keeping ``Sigma_j^{-1}`` (an ``L D L'`` factorisation of the small block and
its inverse): the solves are then matrix-vector products, ``O(N n^3)`` per step.

``AGENT`` (many agents): as in the batch solver, per-agent tridiagonal systems in
``d lambda_i`` (backward pivots, ``O(N)`` per solve) plus the ``2N x 2N`` Schur complement
``M`` of the grid forces (Jacobi-scaled Cholesky): ``O(n N^2 + N^3)`` per step.

Both restore the exact relation ``sum_i db_i = g_b / D_grid`` where a grid limit is hard
(``D_grid sum vb > 1``; see the batch solver's docstring for why).

Sensitivity
-----------
The adjoint ``(dR/dy)' Z = S_y'`` is the same reduced system with the ``n`` right-hand sides
``(+1 at b_0, -1 at s_0)`` of each agent, solved with a factorisation at the solution; then
``grad = -(dR/dtheta)' Z`` with ``dR/dtheta`` in closed form (the table in
:mod:`mpcrl_lite.mpc.backends.batch`) and the conditioning proxy ``||K||_max ||Z||_max``. Column by
column, every column gets at least one step of iterative refinement (as the batch solver's
full adjoint: where a grid limit binds, an agent's own response and the grid's nearly cancel
and small entries lose digits that the normwise backward error does not show). For many
agents (:func:`_adjoint_structured`, ``AGENT`` only) all columns are formed at once,
``O(n^2 N)``, without refinement, as the batch solver's structured adjoint.

Numerics
--------
IEEE arithmetic (``error_model="numpy"``): a division by zero gives inf or NaN, which the
checks turn into a failure status, never an exception mid-run. Non-finite directions are
detected in :func:`_solve` (``0 * v`` is NaN exactly when ``v`` is not finite), the residual
in :func:`_residual`.

Four problems at once
---------------------
With the ``STAGE`` factorisation (the paper's sizes) :func:`solve_rows` and
:func:`sensitivity_rows` take the problems four at a time (:func:`solve_lanes`,
:func:`sensitivity_lanes`; the rest, and the ``AGENT`` factorisation, one at a time through
:func:`solve_each`, :func:`sensitivity_each`). Every work array gets a last axis of four, one
"lane" per problem, and the numerical parts hold the four entries of a quantity as one LLVM
vector (:mod:`mpcrl_lite._util.vec4`), so that one vector instruction does the work of four
scalar ones. Each lane sees the scalar code's operations in the same order (no fused
multiply-adds, no reordered sums; numba's ``max`` and ``min`` reproduced), so a problem's
results are the same bits whether it was solved alone or beside three others
(``tests/mpc/test_kernel_lanes.py``). The decisions of the iteration (stopping, Mehrotra's
target, a failed step, a refinement step of the sensitivity) are taken lane by lane; a lane
that has finished keeps its values (its updates are masked) while the others go on, so a
group costs as many iterations as its slowest problem (about 8 % more Newton iterations than
one at a time on the learning months' problems). At n = 3, N = 12 the solve takes about half
the CPU and the sensitivity about 0.4 of it (``benchmarks/README.md``).

Threads
-------
Each problem of a batch is solved (and its sensitivity formed) alone or in a group of four
whose lanes do not mix, with work arrays reused from problem to problem but never read before
written: :func:`solve_rows` and
:func:`sensitivity_rows` run a range of the problems without the GIL, so that
:class:`~mpcrl_lite.mpc.backends.kernel.KernelSolver` can spread a large batch over threads,
with the results of the one-thread call bit for bit: :func:`solve_rows_parallel` and
:func:`sensitivity_rows_parallel` hand blocks of problems to numba's threads (``prange``)
within one call; :func:`mpcrl_lite._util.threads.run_blocks` (Python threads, one compiled
call per block) serves where numba's threads may not be used (a forked child process).

Every function is compiled with numba's on-disk cache; see :mod:`mpcrl_lite.mpc.backends.kernel`
for where the cache lives and how to fill it.
"""

from __future__ import annotations

import logging
import math

import numba
import numpy as np
from numba import prange

from ..._util import jit
from ..._util.jit import njit_cached
from ..._util.vec4 import LANES, vabs, vload, vmax, vmin, vsplat, vstore, where_gt, where_lt

log = logging.getLogger("mpcrl_lite.mpc.backends.kernel")


# IEEE arithmetic (x / 0 is inf or NaN, detected by the checks) instead of Python's
# ZeroDivisionError: no exception can escape mid-run, and divisions in loops vectorise
_jit = njit_cached(error_model="numpy")
_inline = njit_cached(error_model="numpy", inline="always")  # helpers of hot loops
# the entries that run blocks of problems, callable from several threads at once
_nogil = njit_cached(error_model="numpy", nogil=True)
# the entries that split a call over numba's own threads (``prange``)
_parallel = njit_cached(error_model="numpy", nogil=True, parallel=True)

# status codes of a solve (strings in kernel_solver)
CONVERGED, MAX_ITER, NON_FINITE, BREAKDOWN = 0, 1, 2, 3
# codes of a sensitivity
SENS_OK, SENS_SKIPPED, SENS_NOT_INTERIOR, SENS_SINGULAR = 0, 1, 2, 3
# factorisations
STAGE, AGENT = 0, 1

# rows of the option vector ``opts`` (the input bounds ``U_bar^i``, one per battery, are the
# separate array ``ubar`` (n,))
(O_TAU, O_TOL, O_MAX_ITER, O_P, O_HI, O_LO, O_OM_HI, O_OM_LO, O_U0, O_T0_COLD,
 O_T0_WARM, O_WARM_MARGIN, O_WARM_WEIGHT, O_SLACK_MARGIN, O_SWITCH, O_POLISH) = range(16)
N_OPTS = 16
# rows of the per-stage weights ``stagew`` (5, N)
W_DISC, W_WSOC, W_TERM, W_QSHI, W_QSLO = range(5)
# rows of the per-agent-stage factor array ``F`` (11, n, N); F_IPIV, F_RAT: agent method
F_VB, F_VS, F_V, F_C4, F_C5, F_ISHI, F_ISLO, F_BB, F_BS, F_IPIV, F_RAT = range(11)
N_F = 11
# rows of the per-stage grid factor array ``FG`` (6, N): kappa, sum of vb or vs, D of the
# grid rows
G_KB, G_KS, G_SVB, G_SVS, G_DB, G_DS = range(6)
N_G = 6

_ETA = 0.995
_TINY = 1e-300
_REFINE_MAX = 4
_BACKWARD_ERROR_GOOD = 1e-14


# ----------------------------------------------------------------------------- helpers ----
#: the problem's sizes ``n, N`` fixed at compile time, or 0 where they are read from the arrays
#: (this module). :func:`mpcrl_lite.mpc.backends.kernel.kernels` imports a copy of this module
#: with both set for the sizes it serves most (the paper's); the compiler then knows every
#: loop bound and unrolls and vectorises the small loops. The copy does the same operations
#: in the same order: its results are those of this module, bit for bit.
FIXED_N = 0
FIXED_HORIZON = 0


@_inline
def _dims(n, N):
    """``n, N`` as given, or the compile-time sizes of a specialised copy."""
    if FIXED_N > 0:
        return FIXED_N, FIXED_HORIZON
    return n, N


def choose_method(n: int, N: int) -> int:
    """``STAGE`` when its block Cholesky (``~2 N n^3`` flops per step) is cheaper than the
    agent method's Schur complement (``~4 n N^2 + 8 N^3 / 3``)."""
    stage = 2.0 * N * n ** 3
    agent = 4.0 * n * N * N + 8.0 * N ** 3 / 3.0
    return STAGE if stage <= agent else AGENT


@_inline
def _ag(a, n, N):
    """The per-agent groups (8, n, N) of a flat inequality array (a view)."""
    return a[: 8 * n * N].reshape((8, n, N))


@_inline
def _gr(a, n, N):
    """The grid rows (2, N) of a flat inequality array (a view)."""
    return a[8 * n * N :].reshape((2, N))


@_inline
def _amax(a, v):
    """``max(a, |v|)`` that keeps a NaN once one was seen."""
    v = abs(v)
    if v > a or math.isnan(v):
        return v
    return a


@_jit
def _problem_data(p, n, N, stagew, opts, soc0, alpha, delta, qb, qs, hsoc, qsoc, e):
    """QP data of one parameter vector ``p`` (``MPC.parameters`` layout) in the internal
    layout; returns ``(scale, c)``: the price scale ``1 + max |q_b, q_s|`` and the cost's
    constant (the batch solver's ``_data``)."""
    th = n + 2 * N
    hi, lo = opts[O_HI], opts[O_LO]
    sum_w = 0.0
    for j in range(N):
        sum_w += stagew[W_WSOC, j]
    c = 0.0
    scale = 0.0
    sum_phi3 = 0.0
    sum_t3 = 0.0
    for i in range(n):
        soc0[i] = p[i]
        alpha[i] = p[th + i]
        delta[i] = p[th + n + i]
        tb, ts = p[th + 2 * n + i], p[th + 3 * n + i]
        phi1, phi2, phi3 = p[th + 4 * n + i], p[th + 5 * n + i], p[th + 6 * n + i]
        t1, t2, t3 = p[th + 7 * n + i], p[th + 8 * n + i], p[th + 9 * n + i]
        sum_phi3 += phi3
        sum_t3 += t3
        s0 = soc0[i]
        c += phi1 * s0 ** 2 + phi2 * s0 + phi3
        c += opts[O_OM_HI] * max(s0 - hi, 0.0) + opts[O_OM_LO] * max(lo - s0, 0.0)
        for j in range(N):
            disc = stagew[W_DISC, j]
            qb[i, j] = disc * (p[n + j] + tb)
            qs[i, j] = -disc * (p[n + N + j] + ts)
            scale = max(scale, abs(qb[i, j]), abs(qs[i, j]))
            wsoc, term = stagew[W_WSOC, j], stagew[W_TERM, j]
            hsoc[i, j] = 2.0 * (phi1 * wsoc + t1 * term)
            qsoc[i, j] = phi2 * wsoc + t2 * term
            e[i, j] = delta[i]
        e[i, 0] += s0
    c += sum_w * sum_phi3 + sum_t3
    return 1.0 + scale, c


@_jit
def _slacks(X, U, P, hi, lo, S):
    """``S = d - C x`` (flat); ``U`` (n,) holds each battery's input bound."""
    n, N = _dims(X.shape[1], X.shape[2])
    SA, SG = _ag(S, n, N), _gr(S, n, N)
    for i in range(n):
        for j in range(N):
            b, s, soc, shi, slo = X[0, i, j], X[1, i, j], X[2, i, j], X[3, i, j], X[4, i, j]
            SA[0, i, j] = b
            SA[1, i, j] = U[i] - b
            SA[2, i, j] = s
            SA[3, i, j] = U[i] - s
            SA[4, i, j] = (shi - soc) + hi
            SA[5, i, j] = (soc + slo) - lo
            SA[6, i, j] = shi
            SA[7, i, j] = slo
    for j in range(N):
        tb = 0.0
        ts = 0.0
        for i in range(n):
            tb += X[0, i, j]
            ts += X[1, i, j]
        SG[0, j] = P - tb
        SG[1, j] = P - ts


@_jit
def _residual(X, L, Mu, S, alpha, qb, qs, hsoc, qsoc, stagew, e, opts, U, scale, base, rp):
    """The slacks ``S = d - C x`` (flat), ``base = H x + q + A' lam`` (5, n, N) and
    ``rp = A x - e`` (n, N) in place; returns the scaled KKT residual
    ``max(max(|r_d|, |mu S - tau|) / scale, |r_p|)`` of the batch solver (inf if anything
    is not finite) and ``sum(mu S)``; ``U`` (n,) the input bounds. (Flat indices: group ``g``, agent ``i``, stage ``j``
    at ``g n N + i N + j``, grid row ``v`` at ``8 n N + v N + j``.)"""
    n, N = _dims(L.shape[0], L.shape[1])
    nN = n * N
    go = 8 * nN
    P, hi, lo, tau = opts[O_P], opts[O_HI], opts[O_LO], opts[O_TAU]
    ed = 0.0
    ep = 0.0
    ec = 0.0
    comp = 0.0
    check = 0.0  # 0 * v is NaN exactly when v is not finite
    for j in range(N):
        tb = 0.0
        ts = 0.0
        for i in range(n):
            tb += X[0, i, j]
            ts += X[1, i, j]
        S[go + j] = P - tb
        S[go + N + j] = P - ts
        for k in (go + j, go + N + j):
            c = Mu[k] * S[k]
            comp += c
            ec = max(ec, abs(c - tau))
    for i in range(n):
        a = alpha[i]
        u = U[i]
        for j in range(N):
            k = i * N + j
            b, sl, soc, shi, slo = X[0, i, j], X[1, i, j], X[2, i, j], X[3, i, j], X[4, i, j]
            S[k] = b
            S[nN + k] = u - b
            S[2 * nN + k] = sl
            S[3 * nN + k] = u - sl
            S[4 * nN + k] = (shi - soc) + hi
            S[5 * nN + k] = (soc + slo) - lo
            S[6 * nN + k] = shi
            S[7 * nN + k] = slo
            for g in range(8):
                c = Mu[g * nN + k] * S[g * nN + k]
                comp += c
                ec = max(ec, abs(c - tau))
            aL = a * L[i, j]
            b0 = qb[i, j] - aL
            b1 = qs[i, j] + aL
            b2 = hsoc[i, j] * soc + qsoc[i, j] + L[i, j]
            if j < N - 1:
                b2 -= L[i, j + 1]
            base[0, i, j] = b0
            base[1, i, j] = b1
            base[2, i, j] = b2
            base[3, i, j] = stagew[W_QSHI, j]
            base[4, i, j] = stagew[W_QSLO, j]
            m4, m5 = Mu[4 * nN + k], Mu[5 * nN + k]
            d0 = b0 + (Mu[go + j] - (Mu[k] - Mu[nN + k]))
            d1 = b1 + (Mu[go + N + j] - (Mu[2 * nN + k] - Mu[3 * nN + k]))
            d2 = b2 + (m4 - m5)
            d3 = stagew[W_QSHI, j] - (m4 + Mu[6 * nN + k])
            d4 = stagew[W_QSLO, j] - (m5 + Mu[7 * nN + k])
            ed = max(ed, abs(d0), abs(d1), abs(d2), abs(d3), abs(d4))
            r = soc - a * (b - sl)
            if j > 0:
                r -= X[2, i, j - 1]
            r -= e[i, j]
            rp[i, j] = r
            ep = max(ep, abs(r))
            check += 0.0 * (d0 + d1 + d2 + d3 + d4 + r)
    err = max(max(ed, ec) / scale, ep)
    if check != 0.0 or not math.isfinite(err) or math.isnan(comp):
        return np.inf, comp
    return err, comp


# ------------------------------------------------------------------------ factorisation ----
@_jit
def _cholesky(A, m):
    """In-place lower Cholesky factor of the leading ``m x m`` block of ``A`` (only the lower
    triangle is read), with the *reciprocals* of the pivots on the diagonal; False if ``A``
    is not positive definite (or not finite)."""
    for k in range(m):
        d = A[k, k]
        for l in range(k):
            d -= A[k, l] * A[k, l]
        if not d > 0.0 or not math.isfinite(d):
            return False
        inv = 1.0 / math.sqrt(d)
        A[k, k] = inv
        for i in range(k + 1, m):
            v = A[i, k]
            for l in range(k):
                v -= A[i, l] * A[k, l]
            A[i, k] = v * inv
    return True


@_inline
def _cholesky_solve(Lc, x, m):
    """``x <- (Lc Lc')^{-1} x`` in place (``Lc`` from :func:`_cholesky`)."""
    for i in range(m):
        v = x[i]
        for l in range(i):
            v -= Lc[i, l] * x[l]
        x[i] = v * Lc[i, i]
    for i in range(m - 1, -1, -1):
        v = x[i]
        for l in range(i + 1, m):
            v -= Lc[l, i] * x[l]
        x[i] = v * Lc[i, i]


@_jit
def _factor(S, Mu, IS, D, alpha, hsoc, method, F, FG, SI, AW, TI, MC, MS, tmp):
    """Factorise the reduced KKT matrix at ``S, mu`` (``IS = 1 / S``, ``D = mu / S`` are
    filled too); False on breakdown."""
    n, N = _dims(alpha.shape[0], FG.shape[1])
    nN = n * N
    go = 8 * nN
    for k in range(S.size):
        inv = 1.0 / S[k]
        IS[k] = inv
        D[k] = Mu[k] * inv
    for i in range(n):
        a = alpha[i]
        for j in range(N):
            k = i * N + j
            d4, d5, d6, d7 = D[4 * nN + k], D[5 * nN + k], D[6 * nN + k], D[7 * nN + k]
            # two reciprocals from one division (products of two D stay far inside the
            # floating-point range)
            whi, wlo = d4 + d6, d5 + d7
            wb, ws = D[k] + D[nN + k], D[2 * nN + k] + D[3 * nN + k]
            inv = 1.0 / (whi * wlo)
            ishi, islo = wlo * inv, whi * inv
            inv = 1.0 / (wb * ws)
            vb, vs = ws * inv, wb * inv
            c4 = d4 * ishi
            c5 = d5 * islo
            F[F_ISHI, i, j] = ishi
            F[F_ISLO, i, j] = islo
            F[F_C4, i, j] = c4
            F[F_C5, i, j] = c5
            F[F_V, i, j] = 1.0 / (hsoc[i, j] + c4 * d6 + c5 * d7)
            F[F_VB, i, j] = vb
            F[F_VS, i, j] = vs
            F[F_BB, i, j] = a * vb
            F[F_BS, i, j] = a * vs
    for j in range(N):
        svb = 0.0
        svs = 0.0
        for i in range(n):
            svb += F[F_VB, i, j]
            svs += F[F_VS, i, j]
        db, ds = D[go + j], D[go + N + j]
        FG[G_SVB, j] = svb
        FG[G_SVS, j] = svs
        FG[G_DB, j] = db
        FG[G_DS, j] = ds
        FG[G_KB, j] = db / (1.0 + db * svb)
        FG[G_KS, j] = ds / (1.0 + ds * svs)
    if method == STAGE:
        return _factor_stage(alpha, F, FG, SI, AW, tmp)
    return _factor_agent(alpha, F, FG, TI, MC, MS)


@_jit
def _factor_stage(alpha, F, FG, SI, A, dv):
    """Block elimination of the block-tridiagonal ``T`` (see the module docstring):
    ``SI[j] = Sigma_j^{-1}`` (symmetric, both triangles) from ``Sigma_j = T_jj - diag(V_{j-1})
    Sigma_{j-1}^{-1} diag(V_{j-1})``, each by an ``L D L'`` factorisation (``A``, ``dv``
    scratch); False if a ``Sigma_j`` is not positive definite."""
    n, N = _dims(alpha.shape[0], F.shape[2])
    for j in range(N):
        kb, ks = FG[G_KB, j], FG[G_KS, j]
        for i in range(n):
            bbi, bsi = F[F_BB, i, j], F[F_BS, i, j]
            for k in range(i + 1):
                A[i, k] = -(kb * bbi * F[F_BB, k, j] + ks * bsi * F[F_BS, k, j])
            A[i, i] += F[F_V, i, j] + alpha[i] * (bbi + bsi)
        if j > 0:
            for i in range(n):
                vi = F[F_V, i, j - 1]
                A[i, i] += vi
                for k in range(i + 1):
                    A[i, k] -= vi * SI[j - 1, i, k] * F[F_V, k, j - 1]
        # L D L': unit lower L below the diagonal of A, D in dv
        for k in range(n):
            dk = A[k, k]
            for l in range(k):
                dk -= A[k, l] * A[k, l] * dv[l]
            if not dk > 0.0 or not math.isfinite(dk):
                return False
            dv[k] = dk
            inv = 1.0 / dk
            for i in range(k + 1, n):
                v = A[i, k]
                for l in range(k):
                    v -= A[i, l] * A[k, l] * dv[l]
                A[i, k] = v * inv
            dv[n + k] = inv
        # L^{-1} (unit lower, its diagonal stored) in place of L, then
        # Sigma^{-1} = L^{-T} D^{-1} L^{-1}
        for c in range(n):
            A[c, c] = 1.0
            for i in range(c + 1, n):
                v = -A[i, c]
                for l in range(c + 1, i):
                    v -= A[i, l] * A[l, c]
                A[i, c] = v
        for i in range(n):
            for k in range(i + 1):
                v = 0.0
                for l in range(i, n):
                    v += A[l, i] * dv[n + l] * A[l, k]
                SI[j, i, k] = v
                SI[j, k, i] = v
    return True


@_jit
def _factor_agent(alpha, F, FG, TI, MC, MS):
    """Per-agent tridiagonal factors (reciprocal backward pivots ``F_IPIV``, ratios
    ``F_RAT``) and the Jacobi-scaled Cholesky factor ``MC`` of the grid Schur complement
    (scaling ``MS``); the scaled ``M`` itself is kept in ``TI`` (lower triangle)."""
    n, N = _dims(alpha.shape[0], F.shape[2])
    m = 2 * N
    for a in range(m):
        for b in range(a + 1):
            MC[a, b] = 0.0
    for i in range(n):
        ai = alpha[i]
        # T_i = tridiag(-V_{j-1}, V_j + V_{j-1} + alpha (beta_b + beta_s), -V_j) = U G U'
        # with the backward pivots g_j = a_j - V_j^2 / g_{j+1}
        F[F_RAT, i, N - 1] = 0.0
        ig_next = 0.0
        for j in range(N - 1, -1, -1):
            Vj = F[F_V, i, j]
            g = Vj + ai * (F[F_BB, i, j] + F[F_BS, i, j])
            if j > 0:
                g += F[F_V, i, j - 1]
            if j < N - 1:
                r = Vj * ig_next
                F[F_RAT, i, j] = r
                g -= Vj * r
            if not g > 0.0 or not math.isfinite(g):
                return False
            ig_next = 1.0 / g
            F[F_IPIV, i, j] = ig_next
        # T_i^{-1} is semiseparable: (T^{-1})_jk = s_j prod_{l=j}^{k-1} r_l for j <= k with
        # s_j = r_{j-1}^2 s_{j-1} + 1 / g_j (positive terms only)
        s = 0.0
        for j in range(N):
            if j > 0:
                r = F[F_RAT, i, j - 1]
                s *= r * r
            s += F[F_IPIV, i, j]
            val = s
            for k in range(j, N):
                TI[j, k] = val
                val *= F[F_RAT, i, k]
                if val < 1e-290:  # the rest underflows: exact zeros, no denormals
                    val = 0.0
        # M -= B_i' T_i^{-1} B_i, B_i = [diag(beta_b), -diag(beta_s)] (lower triangle)
        for j in range(N):
            bbj, bsj = F[F_BB, i, j], F[F_BS, i, j]
            for k in range(j, N):
                t = TI[j, k]
                if t == 0.0:
                    break
                bbk, bsk = F[F_BB, i, k], F[F_BS, i, k]
                MC[k, j] -= bbj * bbk * t
                MC[N + k, N + j] -= bsj * bsk * t
                MC[N + k, j] += bbj * bsk * t
                if k > j:
                    MC[N + j, k] += bbk * bsj * t
    for j in range(N):
        MC[j, j] += 1.0 / FG[G_DB, j] + FG[G_SVB, j]
        MC[N + j, N + j] += 1.0 / FG[G_DS, j] + FG[G_SVS, j]
    for a in range(m):
        d = MC[a, a]
        if not d > 0.0 or not math.isfinite(d):
            return False
        MS[a] = 1.0 / math.sqrt(d)
    for a in range(m):
        for b in range(a + 1):
            MC[a, b] *= MS[a] * MS[b]
            TI[a, b] = MC[a, b]
    return _cholesky(MC, m)


# ------------------------------------------------------------------------------- solves ----
@_inline
def _tri_solve(F, i, x):
    """``x[:N] <- T_i^{-1} x[:N]`` with the backward pivots of agent ``i`` (``T = U G U'``)."""
    N = _dims(1, F.shape[2])[1]
    for j in range(N - 2, -1, -1):
        x[j] += F[F_RAT, i, j] * x[j + 1]
    for j in range(N):
        x[j] *= F[F_IPIV, i, j]
    for j in range(1, N):
        x[j] += F[F_RAT, i, j - 1] * x[j - 1]


@_jit
def _solve(r1, r2, dx, dl, alpha, F, FG, method, SI, AW, MC, MS, rsp, w, wg, only):
    """Solve the reduced system for ``(r1 (5, n, N), r2 (n, N))`` into ``dx, dl``.

    ``only >= 0`` says that ``r1, r2`` vanish outside agent ``only`` (adjoint columns; the
    agent method then skips the other agents' local solves). Returns False when the result
    is not finite.
    """
    n, N = _dims(alpha.shape[0], r2.shape[1])
    for i in range(n):
        for j in range(N):
            rsp[i, j] = r1[2, i, j] + F[F_C4, i, j] * r1[3, i, j] - F[F_C5, i, j] * r1[4, i, j]
    if method == STAGE:
        _solve_stage(r1, r2, dx, dl, alpha, F, FG, SI, rsp, w)
    else:
        _solve_agent(r1, r2, dx, dl, alpha, F, FG, MC, MS, rsp, w, wg, only)
    check = 0.0
    for i in range(n):
        for j in range(N):
            dsoc = rsp[i, j] - dl[i, j]
            if j < N - 1:
                dsoc += dl[i, j + 1]
            dsoc *= F[F_V, i, j]
            dx[2, i, j] = dsoc
            dx[3, i, j] = F[F_ISHI, i, j] * r1[3, i, j] + F[F_C4, i, j] * dsoc
            dx[4, i, j] = F[F_ISLO, i, j] * r1[4, i, j] - F[F_C5, i, j] * dsoc
            # 0 * v is NaN exactly when v is not finite
            check += 0.0 * (dsoc + dx[0, i, j] + dx[1, i, j] + dl[i, j])
    return check == 0.0


@_jit
def _solve_stage(r1, r2, dx, dl, alpha, F, FG, SI, rsp, w):
    """Block-tridiagonal solve (``STAGE``), then ``db, ds``."""
    n, N = _dims(alpha.shape[0], r2.shape[1])
    # forward: w_j = Sigma_j^{-1} (rho_j + V_{j-1} w_{j-1}), kept in dl[:, j]
    for j in range(N):
        kb, ks = FG[G_KB, j], FG[G_KS, j]
        tb = 0.0
        ts = 0.0
        for i in range(n):
            tb += F[F_VB, i, j] * r1[0, i, j]
            ts += F[F_VS, i, j] * r1[1, i, j]
        for i in range(n):
            vb, vs = F[F_VB, i, j], F[F_VS, i, j]
            wb = vb * (r1[0, i, j] - kb * tb)  # W_b^{-1} r_b (Sherman-Morrison)
            ws = vs * (r1[1, i, j] - ks * ts)
            rho = F[F_V, i, j] * rsp[i, j] - r2[i, j] - alpha[i] * (wb - ws)
            if j > 0:
                rho += F[F_V, i, j - 1] * (dl[i, j - 1] - rsp[i, j - 1])
            w[i] = rho
        for i in range(n):
            v = 0.0
            for k in range(n):
                v += SI[j, i, k] * w[k]
            dl[i, j] = v
    # backward: dl_j = w_j + Sigma_j^{-1} V_j dl_{j+1}
    for j in range(N - 2, -1, -1):
        for k in range(n):
            w[k] = F[F_V, k, j] * dl[k, j + 1]
        for i in range(n):
            v = dl[i, j]
            for k in range(n):
                v += SI[j, i, k] * w[k]
            dl[i, j] = v
    # db = W_b^{-1} (r_b + alpha dl), ds = W_s^{-1} (r_s - alpha dl)
    for j in range(N):
        _grid_block(r1, dl, alpha, F, dx, 0, F_VB, 1.0, FG[G_KB, j], FG[G_SVB, j], FG[G_DB, j],
                    j)
        _grid_block(r1, dl, alpha, F, dx, 1, F_VS, -1.0, FG[G_KS, j], FG[G_SVS, j],
                    FG[G_DS, j], j)


@_inline
def _grid_block(r1, dl, alpha, F, dx, v, fv, sgn, kap, sv, dg, j):
    """``d = W^{-1} (r + sgn alpha dl)`` of the ``b`` (``v = 0``) or ``s`` block of stage
    ``j`` by Sherman-Morrison, ``W^{-1} = diag(vb) - kappa vb vb'``."""
    n = _dims(alpha.shape[0], 1)[0]
    t = 0.0
    for i in range(n):
        t += F[fv, i, j] * (r1[v, i, j] + sgn * alpha[i] * dl[i, j])
    tot = 0.0
    for i in range(n):
        d = F[fv, i, j] * (r1[v, i, j] + sgn * alpha[i] * dl[i, j] - kap * t)
        dx[v, i, j] = d
        tot += d
    # the exact flow is sum_i d_i = t / (1 + D_grid sum v): restore it where the limit is
    # hard (its rounding error times D_grid would spoil the step)
    if dg * sv > 1.0:
        delta = (t / (1.0 + dg * sv) - tot) / sv
        for i in range(n):
            dx[v, i, j] += F[fv, i, j] * delta


@_jit
def _solve_agent(r1, r2, dx, dl, alpha, F, FG, MC, MS, rsp, w, wg, only):
    """Per-agent local solves, grid forces from ``M``, every agent's response (``AGENT``)."""
    n, N = _dims(alpha.shape[0], r2.shape[1])
    for a in range(2 * N):
        wg[a] = 0.0
    for i in range(n):
        if only >= 0 and i != only:
            for j in range(N):
                dl[i, j] = 0.0
            continue
        for j in range(N):
            rho = F[F_V, i, j] * rsp[i, j] - r2[i, j] - F[F_BB, i, j] * r1[0, i, j] \
                + F[F_BS, i, j] * r1[1, i, j]
            if j > 0:
                rho -= F[F_V, i, j - 1] * rsp[i, j - 1]
            w[j] = rho
        _tri_solve(F, i, w)
        for j in range(N):
            dl[i, j] = w[j]
            wg[j] += F[F_VB, i, j] * (r1[0, i, j] + alpha[i] * w[j])
            wg[N + j] += F[F_VS, i, j] * (r1[1, i, j] - alpha[i] * w[j])
    m = 2 * N
    for a in range(m):
        wg[a] *= MS[a]
    _cholesky_solve(MC, wg, m)
    for a in range(m):
        wg[a] *= MS[a]
    for i in range(n):
        ai = alpha[i]
        for j in range(N):
            w[j] = F[F_BB, i, j] * wg[j] - F[F_BS, i, j] * wg[N + j]
        _tri_solve(F, i, w)
        for j in range(N):
            d = dl[i, j] + w[j]
            dl[i, j] = d
            dx[0, i, j] = F[F_VB, i, j] * (r1[0, i, j] + ai * d - wg[j])
            dx[1, i, j] = F[F_VS, i, j] * (r1[1, i, j] - ai * d - wg[N + j])
    # the exact flow is sum_i db_i = g_b / D_grid: restore it where the limit is hard
    for v in range(2):
        fv = F_VB if v == 0 else F_VS
        for j in range(N):
            sv = 0.0
            tot = 0.0
            for i in range(n):
                sv += F[fv, i, j]
                tot += dx[v, i, j]
            dg = FG[G_DB + v, j]
            if dg * sv > 1.0:
                delta = wg[v * N + j] / dg - tot
                for i in range(n):
                    dx[v, i, j] += F[fv, i, j] / sv * delta


# ----------------------------------------------------------------------- Newton steps ----
@_inline
def _to_boundary(x, dx, tmp):
    """``min_k x_k / max(-dx_k, tiny)``: the largest step keeping ``x > 0`` (the batch
    solver's formula). Without branches (the signs of real directions would be mispredicted
    half the time): the quotients in one vectorised loop, their minimum in four independent
    chains."""
    m = x.size
    for k in range(m):
        tmp[k] = x[k] / max(-dx[k], _TINY)
    a0 = np.inf
    a1 = np.inf
    a2 = np.inf
    a3 = np.inf
    k = 0
    while k + 4 <= m:
        a0 = min(a0, tmp[k])
        a1 = min(a1, tmp[k + 1])
        a2 = min(a2, tmp[k + 2])
        a3 = min(a3, tmp[k + 3])
        k += 4
    while k < m:
        a0 = min(a0, tmp[k])
        k += 1
    return min(min(a0, a1), min(a2, a3))


@_jit
def _direction(t, has_corr, Cr, S, IS, Mu, D, base, rp, alpha, F, FG, method, SI, AW, MC, MS,
               r1, r2, dX, dL, dS, dMu, rsp, w, wg, tmp):
    """Newton direction for the barrier target ``t`` (with Mehrotra's corrector ``Cr`` when
    ``has_corr``); fills ``dX, dL, dS, dMu`` and returns ``(ok, ap, ad)``: False when not
    finite, and the largest primal and dual steps keeping ``S`` and ``mu`` positive
    (``min S / -dS``, ``min mu / -dmu``; huge if nothing decreases)."""
    n, N = _dims(alpha.shape[0], FG.shape[1])
    nN = n * N
    go = 8 * nN
    # U = (t - corr) / S, kept in dMu until dMu = U - mu - D dS overwrites it
    if has_corr:
        for k in range(IS.size):
            dMu[k] = (t - Cr[k]) * IS[k]
    else:
        for k in range(IS.size):
            dMu[k] = t * IS[k]
    # r1 = -(base + C' U), r2 = -rp
    for i in range(n):
        for j in range(N):
            k = i * N + j
            u4, u5 = dMu[4 * nN + k], dMu[5 * nN + k]
            r1[0, i, j] = -(base[0, i, j] + (dMu[go + j] - (dMu[k] - dMu[nN + k])))
            r1[1, i, j] = -(base[1, i, j] + (dMu[go + N + j] - (dMu[2 * nN + k]
                                                               - dMu[3 * nN + k])))
            r1[2, i, j] = -(base[2, i, j] + (u4 - u5))
            r1[3, i, j] = -(base[3, i, j] - (u4 + dMu[6 * nN + k]))
            r1[4, i, j] = -(base[4, i, j] - (u5 + dMu[7 * nN + k]))
            r2[i, j] = -rp[i, j]
    ok = _solve(r1, r2, dX, dL, alpha, F, FG, method, SI, AW, MC, MS, rsp, w, wg, -1)
    # dS = -C dX, dMu = U - mu - D dS
    for i in range(n):
        for j in range(N):
            k = i * N + j
            db, ds, dsoc, dshi, dslo = dX[0, i, j], dX[1, i, j], dX[2, i, j], dX[3, i, j], \
                dX[4, i, j]
            dS[k] = db
            dS[nN + k] = -db
            dS[2 * nN + k] = ds
            dS[3 * nN + k] = -ds
            dS[4 * nN + k] = dshi - dsoc
            dS[5 * nN + k] = dsoc + dslo
            dS[6 * nN + k] = dshi
            dS[7 * nN + k] = dslo
    for j in range(N):
        tb = 0.0
        ts = 0.0
        for i in range(n):
            tb += dX[0, i, j]
            ts += dX[1, i, j]
        dS[go + j] = -tb
        dS[go + N + j] = -ts
    for k in range(dMu.size):
        dMu[k] = dMu[k] - Mu[k] - D[k] * dS[k]
    return ok, _to_boundary(S, dS, tmp), _to_boundary(Mu, dMu, tmp)


@_jit
def _initial_point(soc0, alpha, delta, hsoc, qsoc, x0, warm, opts, U, scale, X, L, Mu, S):
    """Strictly interior start on the central path of ``t0`` (the batch solver's rule):
    ``b^i = s^i`` a fraction of ``min(U[i], P / n)``, each battery's own; a warm start kept
    one margin (relative to the smallest of these) inside the bounds."""
    n, N = _dims(L.shape[0], L.shape[1])
    P, hi, lo = opts[O_P], opts[O_HI], opts[O_LO]
    cap_min = np.inf
    for i in range(n):
        cap_min = min(cap_min, min(U[i], P / n))
    if not warm:
        for v in range(2):
            for i in range(n):
                u0 = opts[O_U0] * min(U[i], P / n)
                for j in range(N):
                    X[v, i, j] = u0
        t0 = opts[O_T0_COLD] * scale
    else:
        margin = opts[O_WARM_MARGIN] * cap_min
        wgt = opts[O_WARM_WEIGHT]
        for v in range(2):
            for i in range(n):
                u0 = opts[O_U0] * min(U[i], P / n)
                for j in range(N):
                    val = x0[j * 5 * n + v * n + i]
                    if not math.isfinite(val):
                        val = margin
                    val = min(max(val, margin), U[i] - margin)
                    X[v, i, j] = wgt * val + (1.0 - wgt) * u0
        cap = P - n * margin
        for v in range(2):
            for j in range(N):
                tot = 0.0
                for i in range(n):
                    tot += X[v, i, j]
                if tot > cap:
                    f = cap / tot
                    for i in range(n):
                        X[v, i, j] *= f
        t0 = opts[O_T0_WARM] * scale
    sm = opts[O_SLACK_MARGIN]
    for i in range(n):
        soc = soc0[i]
        for j in range(N):
            soc += alpha[i] * (X[0, i, j] - X[1, i, j]) + delta[i]
            X[2, i, j] = soc
            X[3, i, j] = max(soc - hi, 0.0) + sm
            X[4, i, j] = max(lo - soc, 0.0) + sm
    _slacks(X, U, P, hi, lo, S)
    for k in range(S.size):
        Mu[k] = t0 / S[k]
    # lam solves the soc rows of the dual residual exactly (backward from lam_N = 0)
    MuA = _ag(Mu, n, N)
    for i in range(n):
        acc = 0.0
        for j in range(N - 1, -1, -1):
            acc += hsoc[i, j] * X[2, i, j] + qsoc[i, j] + MuA[4, i, j] - MuA[5, i, j]
            L[i, j] = -acc


@_jit
def _work(n, N, method):
    """Work arrays of one problem, reused for every problem of a batch: the primal-dual
    iterate and its direction, the factorisation, right-hand sides and scratch."""
    m = 8 * n * N + 2 * N
    nb = n if method == STAGE else 1
    Nb = N if method == STAGE else 1
    m2 = 2 * N if method == AGENT else 1
    X, dX, base, r1 = (np.empty((5, n, N)), np.empty((5, n, N)), np.empty((5, n, N)),
                       np.empty((5, n, N)))
    L, dL, rp, r2, rsp = (np.empty((n, N)), np.empty((n, N)), np.empty((n, N)),
                          np.empty((n, N)), np.empty((n, N)))
    Mu, S, IS, D, dS, dMu, Cr, R = (np.empty(m), np.empty(m), np.empty(m), np.empty(m),
                                    np.empty(m), np.empty(m), np.empty(m), np.empty(m))
    F, FG = np.empty((N_F, n, N)), np.empty((N_G, N))
    SI, AW = np.empty((Nb, nb, nb)), np.empty((nb, nb))
    TI, MC, MS = np.empty((m2, m2)), np.empty((m2, m2)), np.empty(m2)
    w, wg = np.empty(max(2 * n, N)), np.empty(2 * N)
    return (X, dX, base, r1, L, dL, rp, r2, rsp, Mu, S, IS, D, dS, dMu, Cr, R, F, FG, SI, AW,
            TI, MC, MS, w, wg)


@_jit
def _data_arrays(n, N):
    """Per-problem QP data: soc0, alpha, delta (n,) and qb, qs, hsoc, qsoc, e (n, N)."""
    return (np.empty(n), np.empty(n), np.empty(n), np.empty((n, N)), np.empty((n, N)),
            np.empty((n, N)), np.empty((n, N)), np.empty((n, N)))


@_inline
def _lanes_end(method, d_lo, d_hi):
    """Where the rows ``d_lo <= d < d_hi`` that go four at a time end: whole groups of four
    with the ``STAGE`` factorisation, a last three with them (one group filled up to four is
    cheaper than three alone); ``d_lo`` where none do."""
    if method != STAGE:
        return d_lo
    end = d_lo + (d_hi - d_lo) // LANES * LANES
    return d_hi if d_hi - end == LANES - 1 else end


@_nogil
def solve_rows(P, x0, warm, opts, ubar, stagew, n, N, method, x_out, lam_out, mu_out,
               cost_out, iters_out, status_out, action_out, d_lo, d_hi):
    """Solve the problems ``P[d]``, ``d_lo <= d < d_hi`` (``MPC.parameters`` layout); results
    in the mpc's orderings, written into row ``d`` of the outputs.

    ``ubar`` (n,) holds each battery's input bound ``U_bar^i``. ``x0`` (days, nx) is read only
    when ``warm``. Writes ``x_out``, ``lam_out``, ``mu_out``, ``cost_out``, ``iters_out``,
    ``status_out`` (``CONVERGED``, ``MAX_ITER``, ``NON_FINITE`` or ``BREAKDOWN``) and
    ``action_out`` (``b_0 - s_0`` where converged, else 0). With work arrays of its own and
    without the GIL: blocks of problems may run on several threads at once.

    With the ``STAGE`` factorisation, four problems at a time go through :func:`solve_lanes`
    (a last three too, as a group filled up to four; one or two left over, and every ``AGENT``
    problem, through :func:`solve_each`). Both do the same
    operations on each problem, so a problem's results are the same bits whichever solves it,
    and they do not depend on the blocks or the threads."""
    lo = _lanes_end(method, d_lo, d_hi)
    if lo > d_lo:
        solve_lanes(P, x0, warm, opts, ubar, stagew, n, N, x_out, lam_out, mu_out, cost_out,
                    iters_out, status_out, action_out, d_lo, lo)
    solve_each(P, x0, warm, opts, ubar, stagew, n, N, method, x_out, lam_out, mu_out,
               cost_out, iters_out, status_out, action_out, lo, d_hi)


@_jit
def solve_each(P, x0, warm, opts, ubar, stagew, n, N, method, x_out, lam_out, mu_out,
               cost_out, iters_out, status_out, action_out, d_lo, d_hi):
    """:func:`solve_rows` one problem after the other (either factorisation)."""
    n, N = _dims(n, N)
    (X, dX, base, r1, L, dL, rp, r2, rsp, Mu, S, IS, D, dS, dMu, Cr, R, F, FG, SI, AW, TI, MC,
     MS, w, wg) = _work(n, N, method)
    soc0, alpha, delta, qb, qs, hsoc, qsoc, e = _data_arrays(n, N)
    tau, tol = opts[O_TAU], opts[O_TOL]
    floor = tol * 1e-5
    max_iter = int(opts[O_MAX_ITER])
    switch = opts[O_SWITCH]
    polish = opts[O_POLISH] != 0.0
    m = S.size
    Xf, dXf, Lf, dLf = X.reshape(X.size), dX.reshape(dX.size), L.reshape(L.size), \
        dL.reshape(dL.size)
    for d in range(d_lo, d_hi):
        scale, cconst = _problem_data(P[d], n, N, stagew, opts, soc0, alpha, delta, qb, qs,
                                      hsoc, qsoc, e)
        _initial_point(soc0, alpha, delta, hsoc, qsoc, x0[d] if warm else x0[0], warm, opts,
                       ubar, scale, X, L, Mu, S)
        iters = 0
        status = MAX_ITER
        final = False
        failed = False
        err_prev = np.inf
        while True:
            err, comp = _residual(X, L, Mu, S, alpha, qb, qs, hsoc, qsoc, stagew, e, opts,
                                  ubar, scale, base, rp)
            # at the rounding floor, or one Newton step after reaching tol (quadratic
            # convergence; without ``polish``: at tol), or no more progress
            done = err <= floor or (err <= tol and (not polish or err_prev <= tol
                                                    or err > 0.1 * err_prev))
            bad = not math.isfinite(err)
            if done or bad or failed or iters >= max_iter:
                if done:
                    status = CONVERGED
                elif bad:
                    status = NON_FINITE
                elif failed:
                    status = BREAKDOWN
                break
            err_prev = err
            ok = _factor(S, Mu, IS, D, alpha, hsoc, method, F, FG, SI, AW, TI, MC, MS, w)
            t = tau
            has_corr = False
            if not final:
                # Mehrotra's predictor: the affine direction (target 0) and its step
                mu_avg = comp / m
                ok_a, ap, ad = _direction(0.0, False, Cr, S, IS, Mu, D, base, rp, alpha, F,
                                          FG, method, SI, AW, MC, MS, r1, r2, dX, dL, dS, dMu,
                                          rsp, w, wg, R)
                ok = ok and ok_a
                ap, ad = min(1.0, ap), min(1.0, ad)
                aff = 0.0
                for k in range(m):
                    aff += (Mu[k] + ad * dMu[k]) * (S[k] + ap * dS[k])
                    Cr[k] = dS[k] * dMu[k]
                ratio = (aff / m) / mu_avg
                if not math.isfinite(ratio):  # where the batch solver's NaN breaks down
                    ok = False
                    ratio = 1.0
                target = min(max(ratio, 0.0), 1.0) ** 3 * mu_avg
                t = max(target, tau)
                has_corr = True
                final = target <= switch * tau
            ok_n, ap, ad = _direction(t, has_corr, Cr, S, IS, Mu, D, base, rp, alpha, F, FG,
                                      method, SI, AW, MC, MS, r1, r2, dX, dL, dS, dMu, rsp, w,
                                      wg, R)
            ok = ok and ok_n
            ap, ad = min(1.0, _ETA * ap), min(1.0, _ETA * ad)
            if not (ok and math.isfinite(ap) and math.isfinite(ad)):
                failed = True
                continue
            for k in range(5 * n * N):
                Xf[k] += ap * dXf[k]
            for k in range(n * N):
                Lf[k] += ad * dLf[k]
            for k in range(m):
                Mu[k] += ad * dMu[k]
            iters += 1
        # results in mpc's orderings
        MuA, MuG = _ag(Mu, n, N), _gr(Mu, n, N)
        cost = cconst
        for i in range(n):
            for j in range(N):
                cost += (qb[i, j] * X[0, i, j] + qs[i, j] * X[1, i, j]
                         + (0.5 * hsoc[i, j] * X[2, i, j] + qsoc[i, j]) * X[2, i, j]
                         + stagew[W_QSHI, j] * X[3, i, j] + stagew[W_QSLO, j] * X[4, i, j])
                for k in range(5):
                    x_out[d, j * 5 * n + k * n + i] = X[k, i, j]
                lam_out[d, j * n + i] = L[i, j]
                blk = j * (8 * n + 2)
                for g in range(4):
                    mu_out[d, blk + g * n + i] = MuA[g, i, j]
                    mu_out[d, blk + 4 * n + 2 + g * n + i] = MuA[4 + g, i, j]
        for j in range(N):
            blk = j * (8 * n + 2)
            mu_out[d, blk + 4 * n] = MuG[0, j]
            mu_out[d, blk + 4 * n + 1] = MuG[1, j]
        cost_out[d] = cost
        iters_out[d] = iters
        status_out[d] = status
        for i in range(n):
            action_out[d, i] = X[0, i, 0] - X[1, i, 0] if status == CONVERGED else 0.0


# -------------------------------------------------------------- four problems at once ----
# (the module docstring's "Four problems at once"). The problem data and the start are written
# per lane straight into the lane arrays: routing them through _problem_data and
# _initial_point and copying the results in cost 1.1-1.7 us per problem (benchmarks/README.md).
@_inline
def _x5(g, i, j, n, N):
    """Flat offset of entry ``[g, i, j, 0]`` of a ``(G, n, N, 4)`` lane array."""
    return ((g * n + i) * N + j) * LANES


@_inline
def _ij(i, j, N):
    """Flat offset of ``[i, j, 0]`` of an ``(n, N, 4)`` lane array."""
    return (i * N + j) * LANES


@_inline
def _si(j, i, k, n):
    """Flat offset of ``[j, i, k, 0]`` of the ``(N, n, n, 4)`` lane array ``SI``."""
    return ((j * n + i) * n + k) * LANES


@_jit
def _lanes_data(P, rows, n, N, stagew, opts, soc0, alpha, delta, qb, qs, hsoc, qsoc, e,
                scale_out, c_out):
    """:func:`_problem_data` of the problems ``P[rows[l]]``, lane ``l``, into lane arrays."""
    th = n + 2 * N
    hi, lo = opts[O_HI], opts[O_LO]
    sum_w = 0.0
    for j in range(N):
        sum_w += stagew[W_WSOC, j]
    for l in range(LANES):
        p = P[rows[l]]
        c = 0.0
        scale = 0.0
        sum_phi3 = 0.0
        sum_t3 = 0.0
        for i in range(n):
            soc0[i, l] = p[i]
            alpha[i, l] = p[th + i]
            delta[i, l] = p[th + n + i]
            tb, ts = p[th + 2 * n + i], p[th + 3 * n + i]
            phi1, phi2, phi3 = p[th + 4 * n + i], p[th + 5 * n + i], p[th + 6 * n + i]
            t1, t2, t3 = p[th + 7 * n + i], p[th + 8 * n + i], p[th + 9 * n + i]
            sum_phi3 += phi3
            sum_t3 += t3
            s0 = soc0[i, l]
            c += phi1 * s0 ** 2 + phi2 * s0 + phi3
            c += opts[O_OM_HI] * max(s0 - hi, 0.0) + opts[O_OM_LO] * max(lo - s0, 0.0)
            for j in range(N):
                disc = stagew[W_DISC, j]
                vb = disc * (p[n + j] + tb)
                vs = -disc * (p[n + N + j] + ts)
                qb[i, j, l] = vb
                qs[i, j, l] = vs
                scale = max(scale, abs(vb), abs(vs))
                wsoc, term = stagew[W_WSOC, j], stagew[W_TERM, j]
                hsoc[i, j, l] = 2.0 * (phi1 * wsoc + t1 * term)
                qsoc[i, j, l] = phi2 * wsoc + t2 * term
                e[i, j, l] = delta[i, l]
            e[i, 0, l] += s0
        c += sum_w * sum_phi3 + sum_t3
        scale_out[l] = 1.0 + scale
        c_out[l] = c


@_jit
def _lanes_start(soc0, alpha, delta, hsoc, qsoc, x0, rows, warm, opts, U, scale, X, L, Mu,
                 S):
    """:func:`_initial_point` (with :func:`_slacks`) of each lane, from ``x0[rows[l]]`` when
    ``warm``."""
    n, N = _dims(L.shape[0], L.shape[1])
    nN = n * N
    P, hi, lo = opts[O_P], opts[O_HI], opts[O_LO]
    cap_min = np.inf
    for i in range(n):
        cap_min = min(cap_min, min(U[i], P / n))
    sm = opts[O_SLACK_MARGIN]
    t0_l = np.empty(LANES)
    for l in range(LANES):
        if not warm:
            for v in range(2):
                for i in range(n):
                    u0 = opts[O_U0] * min(U[i], P / n)
                    for j in range(N):
                        X[v, i, j, l] = u0
            t0 = opts[O_T0_COLD] * scale[l]
        else:
            xw = x0[rows[l]]
            margin = opts[O_WARM_MARGIN] * cap_min
            wgt = opts[O_WARM_WEIGHT]
            for v in range(2):
                for i in range(n):
                    u0 = opts[O_U0] * min(U[i], P / n)
                    for j in range(N):
                        val = xw[j * 5 * n + v * n + i]
                        if not math.isfinite(val):
                            val = margin
                        val = min(max(val, margin), U[i] - margin)
                        X[v, i, j, l] = wgt * val + (1.0 - wgt) * u0
            cap = P - n * margin
            for v in range(2):
                for j in range(N):
                    tot = 0.0
                    for i in range(n):
                        tot += X[v, i, j, l]
                    if tot > cap:
                        f = cap / tot
                        for i in range(n):
                            X[v, i, j, l] *= f
            t0 = opts[O_T0_WARM] * scale[l]
        for i in range(n):
            soc = soc0[i, l]
            for j in range(N):
                soc += alpha[i, l] * (X[0, i, j, l] - X[1, i, j, l]) + delta[i, l]
                X[2, i, j, l] = soc
                X[3, i, j, l] = max(soc - hi, 0.0) + sm
                X[4, i, j, l] = max(lo - soc, 0.0) + sm
        t0_l[l] = t0
    _lanes_slacks(X, U, P, hi, lo, S)
    for l in range(LANES):
        t0 = t0_l[l]
        for k in range(S.shape[0]):
            Mu[k, l] = t0 / S[k, l]
        for i in range(n):
            acc = 0.0
            for j in range(N - 1, -1, -1):
                k = i * N + j
                acc += hsoc[i, j, l] * X[2, i, j, l] + qsoc[i, j, l] + Mu[4 * nN + k, l] \
                    - Mu[5 * nN + k, l]
                L[i, j, l] = -acc


@_jit
def _lanes_slacks(X, U, P, hi, lo, S):
    """:func:`_slacks` of the four lanes (``X`` (5, n, N, 4), ``S`` (m, 4))."""
    n, N = _dims(X.shape[1], X.shape[2])
    nN = n * N
    for i in range(n):
        u = U[i]
        for j in range(N):
            k = i * N + j
            b, s, soc = (vload(X, _x5(0, i, j, n, N)), vload(X, _x5(1, i, j, n, N)),
                         vload(X, _x5(2, i, j, n, N)))
            shi, slo = vload(X, _x5(3, i, j, n, N)), vload(X, _x5(4, i, j, n, N))
            vstore(S, k * LANES, b)
            vstore(S, (nN + k) * LANES, u - b)
            vstore(S, (2 * nN + k) * LANES, s)
            vstore(S, (3 * nN + k) * LANES, u - s)
            vstore(S, (4 * nN + k) * LANES, (shi - soc) + hi)
            vstore(S, (5 * nN + k) * LANES, (soc + slo) - lo)
            vstore(S, (6 * nN + k) * LANES, shi)
            vstore(S, (7 * nN + k) * LANES, slo)
    for j in range(N):
        tb = vsplat(0.0)
        ts = vsplat(0.0)
        for i in range(n):
            tb = tb + vload(X, _x5(0, i, j, n, N))
            ts = ts + vload(X, _x5(1, i, j, n, N))
        vstore(S, (8 * nN + j) * LANES, P - tb)
        vstore(S, (8 * nN + N + j) * LANES, P - ts)


@_jit
def _lanes_residual(X, L, Mu, S, alpha, qb, qs, hsoc, qsoc, stagew, e, opts, U, scale, base,
                    rp, out):
    """:func:`_residual` of the four lanes: ``out[:4]`` the residual before its finiteness
    checks, ``out[4:8]`` ``sum(mu S)``, ``out[8:12]`` the non-finite check (0 where
    finite)."""
    n, N = _dims(L.shape[0], L.shape[1])
    nN = n * N
    go = 8 * nN
    P, hi, lo, tau = opts[O_P], opts[O_HI], opts[O_LO], opts[O_TAU]
    zero = vsplat(0.0)
    ed = zero
    ep = zero
    ec = zero
    comp = zero
    check = zero
    for j in range(N):
        tb = zero
        ts = zero
        for i in range(n):
            tb = tb + vload(X, _x5(0, i, j, n, N))
            ts = ts + vload(X, _x5(1, i, j, n, N))
        sb = P - tb
        ss = P - ts
        vstore(S, (go + j) * LANES, sb)
        vstore(S, (go + N + j) * LANES, ss)
        c = vload(Mu, (go + j) * LANES) * sb
        comp = comp + c
        ec = vmax(ec, vabs(c - tau))
        c = vload(Mu, (go + N + j) * LANES) * ss
        comp = comp + c
        ec = vmax(ec, vabs(c - tau))
    for i in range(n):
        a = vload(alpha, i * LANES)
        u = U[i]
        for j in range(N):
            k = i * N + j
            b, sl = vload(X, _x5(0, i, j, n, N)), vload(X, _x5(1, i, j, n, N))
            soc, shi, slo = (vload(X, _x5(2, i, j, n, N)), vload(X, _x5(3, i, j, n, N)),
                             vload(X, _x5(4, i, j, n, N)))
            s_g = (b, u - b, sl, u - sl, (shi - soc) + hi, (soc + slo) - lo, shi, slo)
            mu_g = (vload(Mu, k * LANES), vload(Mu, (nN + k) * LANES),
                    vload(Mu, (2 * nN + k) * LANES), vload(Mu, (3 * nN + k) * LANES),
                    vload(Mu, (4 * nN + k) * LANES), vload(Mu, (5 * nN + k) * LANES),
                    vload(Mu, (6 * nN + k) * LANES), vload(Mu, (7 * nN + k) * LANES))
            for g in range(8):
                vstore(S, (g * nN + k) * LANES, s_g[g])
                c = mu_g[g] * s_g[g]
                comp = comp + c
                ec = vmax(ec, vabs(c - tau))
            Lij = vload(L, _ij(i, j, N))
            aL = a * Lij
            b0 = vload(qb, _ij(i, j, N)) - aL
            b1 = vload(qs, _ij(i, j, N)) + aL
            b2 = vload(hsoc, _ij(i, j, N)) * soc + vload(qsoc, _ij(i, j, N)) + Lij
            if j < N - 1:
                b2 = b2 - vload(L, _ij(i, j + 1, N))
            qshi, qslo = stagew[W_QSHI, j], stagew[W_QSLO, j]
            vstore(base, _x5(0, i, j, n, N), b0)
            vstore(base, _x5(1, i, j, n, N), b1)
            vstore(base, _x5(2, i, j, n, N), b2)
            vstore(base, _x5(3, i, j, n, N), vsplat(qshi))
            vstore(base, _x5(4, i, j, n, N), vsplat(qslo))
            m4, m5 = mu_g[4], mu_g[5]
            d0 = b0 + (vload(Mu, (go + j) * LANES) - (mu_g[0] - mu_g[1]))
            d1 = b1 + (vload(Mu, (go + N + j) * LANES) - (mu_g[2] - mu_g[3]))
            d2 = b2 + (m4 - m5)
            d3 = qshi - (m4 + mu_g[6])
            d4 = qslo - (m5 + mu_g[7])
            ed = vmax(vmax(vmax(vmax(vmax(ed, vabs(d0)), vabs(d1)), vabs(d2)), vabs(d3)),
                      vabs(d4))
            r = soc - a * (b - sl)
            if j > 0:
                r = r - vload(X, _x5(2, i, j - 1, n, N))
            r = r - vload(e, _ij(i, j, N))
            vstore(rp, _ij(i, j, N), r)
            ep = vmax(ep, vabs(r))
            check = check + 0.0 * (d0 + d1 + d2 + d3 + d4 + r)
    vstore(out, 0, vmax(vmax(ed, ec) / vload(scale, 0), ep))
    vstore(out, LANES, comp)
    vstore(out, 2 * LANES, check)


@_jit
def _lanes_factor(S, Mu, IS, D, alpha, hsoc, F, FG, SI, A, dv, out):
    """:func:`_factor` with :func:`_factor_stage` of the four lanes; ``out[:4]`` 1 where
    every ``Sigma_j`` was positive definite, else 0 (``A``, ``dv`` scratch)."""
    n, N = _dims(alpha.shape[0], FG.shape[1])
    nN = n * N
    go = 8 * nN
    one = vsplat(1.0)
    zero = vsplat(0.0)
    inf = vsplat(np.inf)
    for k in range(S.shape[0]):
        inv = 1.0 / vload(S, k * LANES)
        vstore(IS, k * LANES, inv)
        vstore(D, k * LANES, vload(Mu, k * LANES) * inv)
    for i in range(n):
        a = vload(alpha, i * LANES)
        for j in range(N):
            k = i * N + j
            d4, d5 = vload(D, (4 * nN + k) * LANES), vload(D, (5 * nN + k) * LANES)
            d6, d7 = vload(D, (6 * nN + k) * LANES), vload(D, (7 * nN + k) * LANES)
            whi, wlo = d4 + d6, d5 + d7
            wb = vload(D, k * LANES) + vload(D, (nN + k) * LANES)
            ws = vload(D, (2 * nN + k) * LANES) + vload(D, (3 * nN + k) * LANES)
            inv = 1.0 / (whi * wlo)
            ishi, islo = wlo * inv, whi * inv
            inv = 1.0 / (wb * ws)
            vb, vs = ws * inv, wb * inv
            c4 = d4 * ishi
            c5 = d5 * islo
            vstore(F, _x5(F_ISHI, i, j, n, N), ishi)
            vstore(F, _x5(F_ISLO, i, j, n, N), islo)
            vstore(F, _x5(F_C4, i, j, n, N), c4)
            vstore(F, _x5(F_C5, i, j, n, N), c5)
            vstore(F, _x5(F_V, i, j, n, N),
                   1.0 / (vload(hsoc, _ij(i, j, N)) + c4 * d6 + c5 * d7))
            vstore(F, _x5(F_VB, i, j, n, N), vb)
            vstore(F, _x5(F_VS, i, j, n, N), vs)
            vstore(F, _x5(F_BB, i, j, n, N), a * vb)
            vstore(F, _x5(F_BS, i, j, n, N), a * vs)
    for j in range(N):
        svb = zero
        svs = zero
        for i in range(n):
            svb = svb + vload(F, _x5(F_VB, i, j, n, N))
            svs = svs + vload(F, _x5(F_VS, i, j, n, N))
        db, ds = vload(D, (go + j) * LANES), vload(D, (go + N + j) * LANES)
        vstore(FG, _ij(G_SVB, j, N), svb)
        vstore(FG, _ij(G_SVS, j, N), svs)
        vstore(FG, _ij(G_DB, j, N), db)
        vstore(FG, _ij(G_DS, j, N), ds)
        vstore(FG, _ij(G_KB, j, N), db / (1.0 + db * svb))
        vstore(FG, _ij(G_KS, j, N), ds / (1.0 + ds * svs))
    ok = one
    for j in range(N):
        kb, ks = vload(FG, _ij(G_KB, j, N)), vload(FG, _ij(G_KS, j, N))
        for i in range(n):
            bbi, bsi = vload(F, _x5(F_BB, i, j, n, N)), vload(F, _x5(F_BS, i, j, n, N))
            for k in range(i + 1):
                vstore(A, (i * n + k) * LANES,
                       -(kb * bbi * vload(F, _x5(F_BB, k, j, n, N))
                         + ks * bsi * vload(F, _x5(F_BS, k, j, n, N))))
            vstore(A, (i * n + i) * LANES, vload(A, (i * n + i) * LANES) + (
                vload(F, _x5(F_V, i, j, n, N)) + vload(alpha, i * LANES) * (bbi + bsi)))
        if j > 0:
            for i in range(n):
                vi = vload(F, _x5(F_V, i, j - 1, n, N))
                vstore(A, (i * n + i) * LANES, vload(A, (i * n + i) * LANES) + vi)
                for k in range(i + 1):
                    vstore(A, (i * n + k) * LANES, vload(A, (i * n + k) * LANES)
                           - vi * vload(SI, _si(j - 1, i, k, n))
                           * vload(F, _x5(F_V, k, j - 1, n, N)))
        for k in range(n):
            dk = vload(A, (k * n + k) * LANES)
            for q in range(k):
                akq = vload(A, (k * n + q) * LANES)
                dk = dk - akq * akq * vload(dv, q * LANES)
            # :func:`_factor_stage` stops at a pivot that is not > 0 and finite
            ok = where_gt(dk, zero, ok, zero)
            ok = where_lt(vabs(dk), inf, ok, zero)
            vstore(dv, k * LANES, dk)
            inv = 1.0 / dk
            for i in range(k + 1, n):
                v = vload(A, (i * n + k) * LANES)
                for q in range(k):
                    v = v - vload(A, (i * n + q) * LANES) * vload(A, (k * n + q) * LANES) \
                        * vload(dv, q * LANES)
                vstore(A, (i * n + k) * LANES, v * inv)
            vstore(dv, (n + k) * LANES, inv)
        for c in range(n):
            vstore(A, (c * n + c) * LANES, one)
            for i in range(c + 1, n):
                v = -vload(A, (i * n + c) * LANES)
                for q in range(c + 1, i):
                    v = v - vload(A, (i * n + q) * LANES) * vload(A, (q * n + c) * LANES)
                vstore(A, (i * n + c) * LANES, v)
        for i in range(n):
            for k in range(i + 1):
                v = zero
                for q in range(i, n):
                    v = v + vload(A, (q * n + i) * LANES) * vload(dv, (n + q) * LANES) \
                        * vload(A, (q * n + k) * LANES)
                vstore(SI, _si(j, i, k, n), v)
                vstore(SI, _si(j, k, i, n), v)
    vstore(out, 0, ok)


@_jit
def _lanes_solve(r1, r2, dx, dl, alpha, F, FG, SI, rsp, w, out):
    """:func:`_solve` (``STAGE``: :func:`_solve_stage`, :func:`_grid_block`) of the four
    lanes; ``out[:4]`` 0 where the result is finite."""
    n, N = _dims(alpha.shape[0], r2.shape[1])
    zero = vsplat(0.0)
    one = vsplat(1.0)
    for i in range(n):
        for j in range(N):
            vstore(rsp, _ij(i, j, N), vload(r1, _x5(2, i, j, n, N))
                   + vload(F, _x5(F_C4, i, j, n, N)) * vload(r1, _x5(3, i, j, n, N))
                   - vload(F, _x5(F_C5, i, j, n, N)) * vload(r1, _x5(4, i, j, n, N)))
    for j in range(N):
        kb, ks = vload(FG, _ij(G_KB, j, N)), vload(FG, _ij(G_KS, j, N))
        tb = zero
        ts = zero
        for i in range(n):
            tb = tb + vload(F, _x5(F_VB, i, j, n, N)) * vload(r1, _x5(0, i, j, n, N))
            ts = ts + vload(F, _x5(F_VS, i, j, n, N)) * vload(r1, _x5(1, i, j, n, N))
        for i in range(n):
            wb = vload(F, _x5(F_VB, i, j, n, N)) * (vload(r1, _x5(0, i, j, n, N)) - kb * tb)
            ws = vload(F, _x5(F_VS, i, j, n, N)) * (vload(r1, _x5(1, i, j, n, N)) - ks * ts)
            rho = vload(F, _x5(F_V, i, j, n, N)) * vload(rsp, _ij(i, j, N)) \
                - vload(r2, _ij(i, j, N)) - vload(alpha, i * LANES) * (wb - ws)
            if j > 0:
                rho = rho + vload(F, _x5(F_V, i, j - 1, n, N)) * (
                    vload(dl, _ij(i, j - 1, N)) - vload(rsp, _ij(i, j - 1, N)))
            vstore(w, i * LANES, rho)
        for i in range(n):
            v = zero
            for k in range(n):
                v = v + vload(SI, _si(j, i, k, n)) * vload(w, k * LANES)
            vstore(dl, _ij(i, j, N), v)
    for j in range(N - 2, -1, -1):
        for k in range(n):
            vstore(w, k * LANES, vload(F, _x5(F_V, k, j, n, N)) * vload(dl, _ij(k, j + 1, N)))
        for i in range(n):
            v = vload(dl, _ij(i, j, N))
            for k in range(n):
                v = v + vload(SI, _si(j, i, k, n)) * vload(w, k * LANES)
            vstore(dl, _ij(i, j, N), v)
    for j in range(N):
        for v in range(2):
            fv = F_VB if v == 0 else F_VS
            sgn = 1.0 if v == 0 else -1.0
            kap = vload(FG, _ij(G_KB + v, j, N))
            t = zero
            for i in range(n):
                t = t + vload(F, _x5(fv, i, j, n, N)) * (
                    vload(r1, _x5(v, i, j, n, N))
                    + sgn * vload(alpha, i * LANES) * vload(dl, _ij(i, j, N)))
            tot = zero
            for i in range(n):
                d = vload(F, _x5(fv, i, j, n, N)) * (
                    vload(r1, _x5(v, i, j, n, N))
                    + sgn * vload(alpha, i * LANES) * vload(dl, _ij(i, j, N)) - kap * t)
                vstore(dx, _x5(v, i, j, n, N), d)
                tot = tot + d
            # the exact flow where the grid limit is hard (:func:`_grid_block`), per lane
            dgsv = vload(FG, _ij(G_DB + v, j, N)) * vload(FG, _ij(G_SVB + v, j, N))
            delta = (t / (1.0 + dgsv) - tot) / vload(FG, _ij(G_SVB + v, j, N))
            for i in range(n):
                d = vload(dx, _x5(v, i, j, n, N))
                vstore(dx, _x5(v, i, j, n, N),
                       where_gt(dgsv, one, d + vload(F, _x5(fv, i, j, n, N)) * delta, d))
    check = zero
    for i in range(n):
        for j in range(N):
            dsoc = vload(rsp, _ij(i, j, N)) - vload(dl, _ij(i, j, N))
            if j < N - 1:
                dsoc = dsoc + vload(dl, _ij(i, j + 1, N))
            dsoc = dsoc * vload(F, _x5(F_V, i, j, n, N))
            vstore(dx, _x5(2, i, j, n, N), dsoc)
            vstore(dx, _x5(3, i, j, n, N), vload(F, _x5(F_ISHI, i, j, n, N))
                   * vload(r1, _x5(3, i, j, n, N)) + vload(F, _x5(F_C4, i, j, n, N)) * dsoc)
            vstore(dx, _x5(4, i, j, n, N), vload(F, _x5(F_ISLO, i, j, n, N))
                   * vload(r1, _x5(4, i, j, n, N)) - vload(F, _x5(F_C5, i, j, n, N)) * dsoc)
            check = check + 0.0 * (dsoc + vload(dx, _x5(0, i, j, n, N))
                                   + vload(dx, _x5(1, i, j, n, N)) + vload(dl, _ij(i, j, N)))
    vstore(out, 0, check)


@_inline
def _lanes_to_boundary(x, dx):
    """:func:`_to_boundary` of the four lanes (the same four chains of minima)."""
    m = x.shape[0]
    tiny = vsplat(_TINY)
    a0 = vsplat(np.inf)
    a1 = a0
    a2 = a0
    a3 = a0
    k = 0
    while k + 4 <= m:
        a0 = vmin(a0, vload(x, k * LANES) / vmax(-vload(dx, k * LANES), tiny))
        a1 = vmin(a1, vload(x, (k + 1) * LANES) / vmax(-vload(dx, (k + 1) * LANES), tiny))
        a2 = vmin(a2, vload(x, (k + 2) * LANES) / vmax(-vload(dx, (k + 2) * LANES), tiny))
        a3 = vmin(a3, vload(x, (k + 3) * LANES) / vmax(-vload(dx, (k + 3) * LANES), tiny))
        k += 4
    while k < m:
        a0 = vmin(a0, vload(x, k * LANES) / vmax(-vload(dx, k * LANES), tiny))
        k += 1
    return vmin(vmin(a0, a1), vmin(a2, a3))


@_jit
def _lanes_direction(t_l, corr_l, any_corr, Cr, S, IS, Mu, D, base, rp, alpha, F, FG, SI, r1,
                     r2, dX, dL, dS, dMu, rsp, w, ok_out, steps):
    """:func:`_direction` of the four lanes: targets ``t_l`` (4,), Mehrotra's corrector ``Cr``
    in the lanes where ``corr_l`` is 1 (read only if ``any_corr``); ``ok_out[:4]`` 0 where
    finite, ``steps`` the largest primal (``[:4]``) and dual (``[4:8]``) steps."""
    n, N = _dims(alpha.shape[0], FG.shape[1])
    nN = n * N
    go = 8 * nN
    m = S.shape[0]
    t = vload(t_l, 0)
    zero = vsplat(0.0)
    if any_corr:
        corr = vload(corr_l, 0)
        for k in range(m):
            isk = vload(IS, k * LANES)
            vstore(dMu, k * LANES,
                   where_gt(corr, zero, (t - vload(Cr, k * LANES)) * isk, t * isk))
    else:
        for k in range(m):
            vstore(dMu, k * LANES, t * vload(IS, k * LANES))
    for i in range(n):
        for j in range(N):
            k = i * N + j
            u4, u5 = vload(dMu, (4 * nN + k) * LANES), vload(dMu, (5 * nN + k) * LANES)
            vstore(r1, _x5(0, i, j, n, N), -(vload(base, _x5(0, i, j, n, N)) + (
                vload(dMu, (go + j) * LANES)
                - (vload(dMu, k * LANES) - vload(dMu, (nN + k) * LANES)))))
            vstore(r1, _x5(1, i, j, n, N), -(vload(base, _x5(1, i, j, n, N)) + (
                vload(dMu, (go + N + j) * LANES)
                - (vload(dMu, (2 * nN + k) * LANES) - vload(dMu, (3 * nN + k) * LANES)))))
            vstore(r1, _x5(2, i, j, n, N), -(vload(base, _x5(2, i, j, n, N)) + (u4 - u5)))
            vstore(r1, _x5(3, i, j, n, N), -(vload(base, _x5(3, i, j, n, N))
                                             - (u4 + vload(dMu, (6 * nN + k) * LANES))))
            vstore(r1, _x5(4, i, j, n, N), -(vload(base, _x5(4, i, j, n, N))
                                             - (u5 + vload(dMu, (7 * nN + k) * LANES))))
            vstore(r2, _ij(i, j, N), -vload(rp, _ij(i, j, N)))
    _lanes_solve(r1, r2, dX, dL, alpha, F, FG, SI, rsp, w, ok_out)
    for i in range(n):
        for j in range(N):
            k = i * N + j
            db, ds = vload(dX, _x5(0, i, j, n, N)), vload(dX, _x5(1, i, j, n, N))
            dsoc, dshi, dslo = (vload(dX, _x5(2, i, j, n, N)), vload(dX, _x5(3, i, j, n, N)),
                                vload(dX, _x5(4, i, j, n, N)))
            vstore(dS, k * LANES, db)
            vstore(dS, (nN + k) * LANES, -db)
            vstore(dS, (2 * nN + k) * LANES, ds)
            vstore(dS, (3 * nN + k) * LANES, -ds)
            vstore(dS, (4 * nN + k) * LANES, dshi - dsoc)
            vstore(dS, (5 * nN + k) * LANES, dsoc + dslo)
            vstore(dS, (6 * nN + k) * LANES, dshi)
            vstore(dS, (7 * nN + k) * LANES, dslo)
    for j in range(N):
        tb = zero
        ts = zero
        for i in range(n):
            tb = tb + vload(dX, _x5(0, i, j, n, N))
            ts = ts + vload(dX, _x5(1, i, j, n, N))
        vstore(dS, (go + j) * LANES, -tb)
        vstore(dS, (go + N + j) * LANES, -ts)
    for k in range(m):
        vstore(dMu, k * LANES, vload(dMu, k * LANES) - vload(Mu, k * LANES)
               - vload(D, k * LANES) * vload(dS, k * LANES))
    vstore(steps, 0, _lanes_to_boundary(S, dS))
    vstore(steps, LANES, _lanes_to_boundary(Mu, dMu))


@_jit
def solve_lanes(P, x0, warm, opts, ubar, stagew, n, N, x_out, lam_out, mu_out, cost_out,
                iters_out, status_out, action_out, d_lo, d_hi):
    """:func:`solve_each` (``STAGE``) of the problems ``d_lo <= d < d_hi``, four at a time
    (a last block of fewer is filled up with copies of its last problem, whose results are
    not written): the same results bit for bit, in about half the time."""
    n, N = _dims(n, N)
    nN = n * N
    m = 8 * nN + 2 * N
    B = LANES
    X, dX, base, r1 = (np.empty((5, n, N, B)), np.empty((5, n, N, B)), np.empty((5, n, N, B)),
                       np.empty((5, n, N, B)))
    L, dL, rp, r2, rsp = (np.empty((n, N, B)), np.empty((n, N, B)), np.empty((n, N, B)),
                          np.empty((n, N, B)), np.empty((n, N, B)))
    Mu, S, IS, D, dS, dMu, Cr = (np.empty((m, B)), np.empty((m, B)), np.empty((m, B)),
                                 np.empty((m, B)), np.empty((m, B)), np.empty((m, B)),
                                 np.empty((m, B)))
    F, FG = np.empty((N_F, n, N, B)), np.empty((N_G, N, B))
    SI, A, dv, w = (np.empty((N, n, n, B)), np.empty((n, n, B)), np.empty((2 * n, B)),
                    np.empty((n, B)))
    soc0, alpha, delta = np.empty((n, B)), np.empty((n, B)), np.empty((n, B))
    qb, qs, hsoc, qsoc, e = (np.empty((n, N, B)), np.empty((n, N, B)), np.empty((n, N, B)),
                             np.empty((n, N, B)), np.empty((n, N, B)))
    scale, cconst = np.empty(B), np.empty(B)
    res, fact, ok_a, ok_n = np.empty(3 * B), np.empty(B), np.empty(B), np.empty(B)
    steps, t_l, corr_l, aff, mask = (np.empty(2 * B), np.empty(B), np.empty(B), np.empty(B),
                                     np.empty(B))
    err_prev = np.empty(B)
    iters, status, rows = np.empty(B, np.int64), np.empty(B, np.int64), np.empty(B, np.int64)
    active, final, failed, pred = (np.empty(B, np.bool_), np.empty(B, np.bool_),
                                   np.empty(B, np.bool_), np.empty(B, np.bool_))
    tau, tol = opts[O_TAU], opts[O_TOL]
    floor = tol * 1e-5
    max_iter = int(opts[O_MAX_ITER])
    switch = opts[O_SWITCH]
    polish = opts[O_POLISH] != 0.0
    zero = vsplat(0.0)
    for lo in range(d_lo, d_hi, B):
        for l in range(B):
            rows[l] = min(lo + l, d_hi - 1)
            status[l] = MAX_ITER
            err_prev[l] = np.inf
            iters[l] = 0
            active[l] = True
            final[l] = False
            failed[l] = False
        _lanes_data(P, rows, n, N, stagew, opts, soc0, alpha, delta, qb, qs, hsoc, qsoc, e,
                    scale, cconst)
        _lanes_start(soc0, alpha, delta, hsoc, qsoc, x0, rows, warm, opts, ubar, scale, X, L,
                     Mu, S)
        while True:
            _lanes_residual(X, L, Mu, S, alpha, qb, qs, hsoc, qsoc, stagew, e, opts, ubar,
                            scale, base, rp, res)
            # the stopping rule of :func:`solve_each`, lane by lane
            n_active = 0
            n_pred = 0
            for l in range(B):
                pred[l] = False
                if not active[l]:
                    continue
                err = res[l]
                if res[2 * B + l] != 0.0 or not math.isfinite(err) or math.isnan(res[B + l]):
                    err = np.inf
                done = err <= floor or (err <= tol and (not polish or err_prev[l] <= tol
                                                        or err > 0.1 * err_prev[l]))
                bad = not math.isfinite(err)
                if done or bad or failed[l] or iters[l] >= max_iter:
                    if done:
                        status[l] = CONVERGED
                    elif bad:
                        status[l] = NON_FINITE
                    elif failed[l]:
                        status[l] = BREAKDOWN
                    active[l] = False
                    continue
                err_prev[l] = err
                n_active += 1
                pred[l] = not final[l]
                if pred[l]:
                    n_pred += 1
            if n_active == 0:
                break
            _lanes_factor(S, Mu, IS, D, alpha, hsoc, F, FG, SI, A, dv, fact)
            for l in range(B):
                t_l[l] = tau
                corr_l[l] = 0.0
            if n_pred > 0:
                # Mehrotra's predictor (computed in every lane, used where ``pred``)
                for l in range(B):
                    aff[l] = 0.0
                _lanes_direction(aff, corr_l, False, Cr, S, IS, Mu, D, base, rp, alpha, F,
                                 FG, SI, r1, r2, dX, dL, dS, dMu, rsp, w, ok_a, steps)
                ap = vmin(vsplat(1.0), vload(steps, 0))
                ad = vmin(vsplat(1.0), vload(steps, B))
                acc = zero
                for k in range(m):
                    dSk, dMuk = vload(dS, k * B), vload(dMu, k * B)
                    acc = acc + (vload(Mu, k * B) + ad * dMuk) * (vload(S, k * B) + ap * dSk)
                    vstore(Cr, k * B, dSk * dMuk)
                vstore(aff, 0, acc)
                for l in range(B):
                    if not pred[l]:
                        continue
                    if not (fact[l] == 1.0 and ok_a[l] == 0.0):
                        fact[l] = 0.0
                    mu_avg = res[B + l] / m
                    ratio = (aff[l] / m) / mu_avg
                    if not math.isfinite(ratio):
                        fact[l] = 0.0
                        ratio = 1.0
                    target = min(max(ratio, 0.0), 1.0) ** 3 * mu_avg
                    t_l[l] = max(target, tau)
                    corr_l[l] = 1.0
                    final[l] = target <= switch * tau
            _lanes_direction(t_l, corr_l, n_pred > 0, Cr, S, IS, Mu, D, base, rp, alpha, F, FG,
                             SI, r1, r2, dX, dL, dS, dMu, rsp, w, ok_n, steps)
            for l in range(B):
                mask[l] = 0.0
                if not active[l]:
                    continue
                ap_l, ad_l = min(1.0, _ETA * steps[l]), min(1.0, _ETA * steps[B + l])
                steps[l] = ap_l
                steps[B + l] = ad_l
                if not (fact[l] == 1.0 and ok_n[l] == 0.0 and math.isfinite(ap_l)
                        and math.isfinite(ad_l)):
                    failed[l] = True
                    continue
                mask[l] = 1.0
                iters[l] += 1
            # the step, in the lanes that take it
            take = vload(mask, 0)
            ap = vload(steps, 0)
            ad = vload(steps, B)
            for k in range(5 * nN):
                x = vload(X, k * B)
                vstore(X, k * B, where_gt(take, zero, x + ap * vload(dX, k * B), x))
            for k in range(nN):
                x = vload(L, k * B)
                vstore(L, k * B, where_gt(take, zero, x + ad * vload(dL, k * B), x))
            for k in range(m):
                x = vload(Mu, k * B)
                vstore(Mu, k * B, where_gt(take, zero, x + ad * vload(dMu, k * B), x))
        # results in mpc's orderings (as :func:`solve_each`)
        for l in range(min(B, d_hi - lo)):
            d = lo + l
            cost = cconst[l]
            for i in range(n):
                for j in range(N):
                    cost += (qb[i, j, l] * X[0, i, j, l] + qs[i, j, l] * X[1, i, j, l]
                             + (0.5 * hsoc[i, j, l] * X[2, i, j, l] + qsoc[i, j, l])
                             * X[2, i, j, l]
                             + stagew[W_QSHI, j] * X[3, i, j, l]
                             + stagew[W_QSLO, j] * X[4, i, j, l])
                    for k in range(5):
                        x_out[d, j * 5 * n + k * n + i] = X[k, i, j, l]
                    lam_out[d, j * n + i] = L[i, j, l]
                    blk = j * (8 * n + 2)
                    for g in range(4):
                        mu_out[d, blk + g * n + i] = Mu[g * nN + i * N + j, l]
                        mu_out[d, blk + 4 * n + 2 + g * n + i] = Mu[(4 + g) * nN + i * N + j, l]
            for j in range(N):
                blk = j * (8 * n + 2)
                mu_out[d, blk + 4 * n] = Mu[8 * nN + j, l]
                mu_out[d, blk + 4 * n + 1] = Mu[8 * nN + N + j, l]
            cost_out[d] = cost
            iters_out[d] = iters[l]
            status_out[d] = status[l]
            for i in range(n):
                action_out[d, i] = X[0, i, 0, l] - X[1, i, 0, l] if status[l] == CONVERGED \
                    else 0.0


# ------------------------------------------------------------------------- sensitivity ----
@_jit
def _backward_error(zx, zl, r1, D, alpha, hsoc, rx, rl, magnitudes):
    """Residual ``(rx, rl) = K z - (r1, 0)`` of an adjoint column (``K`` the reduced KKT
    matrix) and, with ``magnitudes``, its normwise backward error
    ``max |K z - r| / (max |K| |z| + 1)`` (inf if not finite, or without ``magnitudes``)."""
    n, N = _dims(zl.shape[0], zl.shape[1])
    nN = n * N
    go = 8 * nN
    res = 0.0
    mag = 0.0
    check = 0.0
    for j in range(N):
        tb = 0.0
        ts = 0.0
        ab = 0.0
        at = 0.0
        for i in range(n):
            tb += zx[0, i, j]
            ts += zx[1, i, j]
            ab += abs(zx[0, i, j])
            at += abs(zx[1, i, j])
        dgb, dgs = D[go + j], D[go + N + j]
        for i in range(n):
            k = i * N + j
            a = alpha[i]
            b, s, soc, shi, slo = zx[0, i, j], zx[1, i, j], zx[2, i, j], zx[3, i, j], \
                zx[4, i, j]
            lam = zl[i, j]
            nxt = zl[i, j + 1] if j < N - 1 else 0.0
            prev = zx[2, i, j - 1] if j > 0 else 0.0
            wb, ws = D[k] + D[nN + k], D[2 * nN + k] + D[3 * nN + k]
            d4, d5, d6, d7 = D[4 * nN + k], D[5 * nN + k], D[6 * nN + k], D[7 * nN + k]
            u4 = d4 * (soc - shi)  # D_4 C_4 z
            u5 = d5 * (soc + slo)  # -D_5 C_5 z
            x0 = wb * b + dgb * tb - a * lam - r1[0, i, j]
            x1 = ws * s + dgs * ts + a * lam - r1[1, i, j]
            x2 = hsoc[i, j] * soc + u4 + u5 + lam - nxt - r1[2, i, j]
            x3 = d6 * shi - u4 - r1[3, i, j]
            x4 = d7 * slo + u5 - r1[4, i, j]
            xl = soc - a * b + a * s - prev
            rx[0, i, j] = x0
            rx[1, i, j] = x1
            rx[2, i, j] = x2
            rx[3, i, j] = x3
            rx[4, i, j] = x4
            rl[i, j] = xl
            res = max(res, abs(x0), abs(x1), abs(x2), abs(x3), abs(x4), abs(xl))
            check += 0.0 * (x0 + x1 + x2 + x3 + x4 + xl)
            if magnitudes:
                aa, asoc = abs(a), abs(soc)
                m4 = d4 * (asoc + abs(shi))
                m5 = d5 * (asoc + abs(slo))
                mag = max(mag, wb * abs(b) + dgb * ab + aa * abs(lam),
                          ws * abs(s) + dgs * at + aa * abs(lam),
                          abs(hsoc[i, j]) * asoc + m4 + m5 + abs(lam) + abs(nxt),
                          d6 * abs(shi) + m4, d7 * abs(slo) + m5,
                          asoc + aa * (abs(b) + abs(s)) + abs(prev))
    if not magnitudes or check != 0.0:
        return np.inf
    back = res / (mag + 1.0)
    return np.inf if math.isnan(back) else back


@_jit
def _unpack_solution(x, lam, mu, n, N, X, L, Mu):
    """``x, lam, mu`` in mpc's orderings -> ``X`` (5, n, N), ``L`` (n, N), flat ``Mu``."""
    MuA, MuG = _ag(Mu, n, N), _gr(Mu, n, N)
    for i in range(n):
        for j in range(N):
            for k in range(5):
                X[k, i, j] = x[j * 5 * n + k * n + i]
            L[i, j] = lam[j * n + i]
            blk = j * (8 * n + 2)
            for g in range(4):
                MuA[g, i, j] = mu[blk + g * n + i]
                MuA[4 + g, i, j] = mu[blk + 4 * n + 2 + g * n + i]
    for j in range(N):
        blk = j * (8 * n + 2)
        MuG[0, j] = mu[blk + 4 * n]
        MuG[1, j] = mu[blk + 4 * n + 1]


@_jit
def _grad_column(X, L, zx, zl, stagew, grad, o):
    """``grad[:, o] = -(dR/dtheta)' Z`` for the adjoint column ``Z = (zx, zl)`` of agent
    ``o`` (the batch solver's table; phi3 and T3 rows stay 0)."""
    n, N = _dims(L.shape[0], L.shape[1])
    for i in range(n):
        g0 = 0.0
        g1 = 0.0
        g2 = 0.0
        g3 = 0.0
        g4 = 0.0
        g5 = 0.0
        g7 = 0.0
        g8 = 0.0
        for j in range(N):
            zb, zs, zsoc, zlj = zx[0, i, j], zx[1, i, j], zx[2, i, j], zl[i, j]
            soc = X[2, i, j]
            g0 += L[i, j] * (zb - zs) + (X[0, i, j] - X[1, i, j]) * zlj
            g1 += zlj
            g2 -= stagew[W_DISC, j] * zb
            g3 += stagew[W_DISC, j] * zs
            g4 -= 2.0 * stagew[W_WSOC, j] * soc * zsoc
            g5 -= stagew[W_WSOC, j] * zsoc
            g7 -= 2.0 * stagew[W_TERM, j] * soc * zsoc
            g8 -= stagew[W_TERM, j] * zsoc
        grad[0 * n + i, o] = g0
        grad[1 * n + i, o] = g1
        grad[2 * n + i, o] = g2
        grad[3 * n + i, o] = g3
        grad[4 * n + i, o] = g4
        grad[5 * n + i, o] = g5
        grad[7 * n + i, o] = g7
        grad[8 * n + i, o] = g8


@_jit
def _zmax(zx, zl, IS, zmax):
    """``max(zmax, |Z|)`` over the primal, dual and multiplier rows of an adjoint column,
    with ``Z_mu = C Z_x / S`` (``IS = 1 / S``; the conditioning proxy's ``||Z||_max``; NaN
    if not finite)."""
    n, N = _dims(zl.shape[0], zl.shape[1])
    nN = n * N
    go = 8 * nN
    check = 0.0
    for j in range(N):
        tb = 0.0
        ts = 0.0
        for i in range(n):
            k = i * N + j
            zb, zs, zsoc, zshi, zslo = zx[0, i, j], zx[1, i, j], zx[2, i, j], zx[3, i, j], \
                zx[4, i, j]
            tb += zb
            ts += zs
            zmax = max(zmax, abs(zb) * max(1.0, IS[k], IS[nN + k]),
                       abs(zs) * max(1.0, IS[2 * nN + k], IS[3 * nN + k]), abs(zsoc),
                       abs(zshi) * max(1.0, IS[6 * nN + k]),
                       abs(zslo) * max(1.0, IS[7 * nN + k]), abs(zl[i, j]),
                       abs(zsoc - zshi) * IS[4 * nN + k], abs(zsoc + zslo) * IS[5 * nN + k])
            check += 0.0 * (zb + zs + zsoc + zshi + zslo + zl[i, j])
        zmax = max(zmax, abs(tb) * IS[go + j], abs(ts) * IS[go + N + j])
    return zmax if check == 0.0 else np.nan


@_jit
def _adjoint_structured(X, L, Mu, IS, D, alpha, stagew, F, MC, MS, MM, G, Y, Q, RL, acc, w):
    """All ``n`` adjoint columns at once for many agents (``AGENT`` factorisation, no
    refinement, as the batch solver's structured adjoint).

    Column ``o`` is agent ``o``'s own local solution plus every agent's response to the grid
    forces ``g^(o) = M^{-1} q^(o)``; the responses of agent ``i`` to all columns are one
    tridiagonal solve with ``n`` right-hand sides, and ``grad`` and ``||Z||_max`` are
    accumulated row by row over the columns (contiguous loops). The adjoint right-hand sides
    vanish on ``sigma_hi, sigma_lo``, so ``Z_shi = c4 Z_soc``, ``Z_slo = -c5 Z_soc`` and every
    multiplier row is a multiple of ``Z_b``, ``Z_s`` or ``Z_soc`` (or ``g / mu`` on the grid
    rows). Writes ``grad`` into ``G`` (10 n, n); returns ``(||Z||_max, normwise backward
    error of the 2N solves, finite)``. Scratch: ``Y`` (n, N), ``Q`` (2N, n), ``RL``
    (N + 1, n), ``acc`` (n), ``w`` (2N).
    """
    n, N = _dims(L.shape[0], L.shape[1])
    m2 = 2 * N
    IA, DA = _ag(IS, n, N), _ag(D, n, N)
    off = 8 * n * N
    # own local parts: K_o y = e_o (+1 at b_0, -1 at s_0) without grid forces; their flows
    # q^(o) = (db_o, ds_o)
    for o in range(n):
        for j in range(N):
            Y[o, j] = 0.0
        Y[o, 0] = -(F[F_BB, o, 0] + F[F_BS, o, 0])
        _tri_solve(F, o, Y[o])
        for j in range(N):
            a = alpha[o] * Y[o, j]
            Q[j, o] = F[F_VB, o, j] * a
            Q[N + j, o] = -F[F_VS, o, j] * a
        Q[0, o] += F[F_VB, o, 0]
        Q[N, o] -= F[F_VS, o, 0]
    # grid forces g^(o) = M^{-1} q^(o) (Jacobi-scaled M), with the normwise backward error
    mmax = 0.0
    for a in range(m2):
        for b in range(a + 1):
            mmax = max(mmax, abs(MM[a, b]))
    back = 0.0
    for o in range(n):
        qmax = 0.0
        for a in range(m2):
            w[a] = Q[a, o] * MS[a]
            qmax = max(qmax, abs(w[a]))
        _cholesky_solve(MC, w, m2)
        res = 0.0
        gmax = 0.0
        for a in range(m2):
            v = -Q[a, o] * MS[a]
            for b in range(a + 1):
                v += MM[a, b] * w[b]
            for b in range(a + 1, m2):
                v += MM[b, a] * w[b]
            res = _amax(res, v)
            gmax = max(gmax, abs(w[a]))
        back = max(back, res / max(mmax * gmax + qmax, 1e-300))
        for a in range(m2):
            Q[a, o] = w[a] * MS[a]
    # grid multiplier rows: Z_mu = g / mu
    zmax = 0.0
    for a in range(m2):
        inv = 1.0 / Mu[off + a]
        for o in range(n):
            zmax = _amax(zmax, Q[a, o] * inv)
    for o in range(n):
        acc[o] = 0.0
        RL[N, o] = 0.0
    for k in range(G.size):
        G.flat[k] = 0.0
    for i in range(n):
        ai = alpha[i]
        # responses of agent i to every column's grid forces: RL = T_i^{-1} B_i g
        for j in range(N):
            bb, bs = F[F_BB, i, j], F[F_BS, i, j]
            for o in range(n):
                RL[j, o] = bb * Q[j, o] - bs * Q[N + j, o]
        for j in range(N - 2, -1, -1):
            r = F[F_RAT, i, j]
            for o in range(n):
                RL[j, o] += r * RL[j + 1, o]
        for j in range(N):
            ig = F[F_IPIV, i, j]
            for o in range(n):
                RL[j, o] *= ig
        for j in range(1, N):
            r = F[F_RAT, i, j - 1]
            for o in range(n):
                RL[j, o] += r * RL[j - 1, o]
        # agent i's own part in its own column: lam += y, and the right-hand side e_i on
        # b_0, s_0 folded into the grid forces (Z_b = vb (alpha Z_lam - g_b + [j = 0]))
        for j in range(N):
            RL[j, i] += Y[i, j]
        Q[0, i] -= 1.0
        Q[N, i] += 1.0
        for j in range(N):
            vb, vs, V = F[F_VB, i, j], F[F_VS, i, j], F[F_V, i, j]
            c4, c5 = abs(F[F_C4, i, j]), abs(F[F_C5, i, j])
            fb = max(1.0, IA[0, i, j], IA[1, i, j])
            fs = max(1.0, IA[2, i, j], IA[3, i, j])
            fsoc = max(1.0, c4, c5, DA[6, i, j] * F[F_ISHI, i, j] * IA[4, i, j],
                       DA[7, i, j] * F[F_ISLO, i, j] * IA[5, i, j], c4 * IA[6, i, j],
                       c5 * IA[7, i, j])
            lij, dbs, soc = L[i, j], X[0, i, j] - X[1, i, j], X[2, i, j]
            disc, ws, tm = stagew[W_DISC, j], stagew[W_WSOC, j], stagew[W_TERM, j]
            k4, k7 = -2.0 * ws * soc, -2.0 * tm * soc
            g0, g1, g2, g3 = G[i], G[n + i], G[2 * n + i], G[3 * n + i]
            g4, g5, g7, g8 = G[4 * n + i], G[5 * n + i], G[7 * n + i], G[8 * n + i]
            for o in range(n):
                zl = RL[j, o]
                zb = vb * (ai * zl - Q[j, o])
                zs = vs * (-ai * zl - Q[N + j, o])
                zsoc = V * (RL[j + 1, o] - zl)
                g0[o] += lij * (zb - zs) + dbs * zl
                g1[o] += zl
                g2[o] -= disc * zb
                g3[o] += disc * zs
                g4[o] += k4 * zsoc
                g5[o] -= ws * zsoc
                g7[o] += k7 * zsoc
                g8[o] -= tm * zsoc
                acc[o] = max(acc[o], abs(zb) * fb, abs(zs) * fs, abs(zsoc) * fsoc, abs(zl))
        Q[0, i] += 1.0
        Q[N, i] -= 1.0
    finite = 0.0
    for o in range(n):
        zmax = _amax(zmax, acc[o])
    for k in range(G.size):
        finite += 0.0 * G.flat[k]
    return zmax, back, finite == 0.0


@_nogil
def sensitivity_rows(P, x, lam, mu, solved, opts, ubar, stagew, n, N, method, structured,
                     grad, dsoc, cond, back, code, d_lo, d_hi):
    """``d pi / d theta`` at the solutions ``(x, lam, mu)`` (mpc orderings) of the problems
    ``d_lo <= d < d_hi``.

    Writes ``grad`` (days, 10 n, n), ``dsoc`` (days, n, n): ``d pi_o / d soc0_i`` at
    ``[d, i, o]``, the adjoint's multiplier of the first dynamics row of battery ``i`` (the
    initial soc enters the problem there only; NaN with ``structured``, which forms no
    adjoint per column), ``cond`` (``||K||_max ||Z||_max``), ``back`` (largest
    normwise backward error of the adjoint columns) and ``code`` (``SENS_*``). Rows with
    ``solved[d]`` False are skipped. Where the result is not usable ``grad`` is 0.
    ``structured`` (with the ``AGENT`` factorisation only): all columns at once by
    :func:`_adjoint_structured`; else column by column with iterative refinement. As
    :func:`solve_rows`: own work arrays, no GIL; with the ``STAGE`` factorisation four
    problems at a time (:func:`sensitivity_lanes`, the same bits as
    :func:`sensitivity_each`)."""
    lo = _lanes_end(method, d_lo, d_hi)
    if lo > d_lo:
        sensitivity_lanes(P, x, lam, mu, solved, opts, ubar, stagew, n, N, grad, dsoc, cond,
                          back, code, d_lo, lo)
    sensitivity_each(P, x, lam, mu, solved, opts, ubar, stagew, n, N, method, structured,
                     grad, dsoc, cond, back, code, lo, d_hi)


@_jit
def _lanes_backward_error(zx, zl, r1, D, alpha, hsoc, rx, rl, magnitudes, out):
    """:func:`_backward_error` of the four lanes into ``out[:4]``."""
    n, N = _dims(zl.shape[0], zl.shape[1])
    nN = n * N
    go = 8 * nN
    zero = vsplat(0.0)
    res = zero
    mag = zero
    check = zero
    for j in range(N):
        tb = zero
        ts = zero
        ab = zero
        at = zero
        for i in range(n):
            zb, zs = vload(zx, _x5(0, i, j, n, N)), vload(zx, _x5(1, i, j, n, N))
            tb = tb + zb
            ts = ts + zs
            ab = ab + vabs(zb)
            at = at + vabs(zs)
        dgb, dgs = vload(D, (go + j) * LANES), vload(D, (go + N + j) * LANES)
        for i in range(n):
            k = i * N + j
            a = vload(alpha, i * LANES)
            b, s = vload(zx, _x5(0, i, j, n, N)), vload(zx, _x5(1, i, j, n, N))
            soc, shi, slo = (vload(zx, _x5(2, i, j, n, N)), vload(zx, _x5(3, i, j, n, N)),
                             vload(zx, _x5(4, i, j, n, N)))
            lam = vload(zl, _ij(i, j, N))
            nxt = vload(zl, _ij(i, j + 1, N)) if j < N - 1 else zero
            prev = vload(zx, _x5(2, i, j - 1, n, N)) if j > 0 else zero
            wb = vload(D, k * LANES) + vload(D, (nN + k) * LANES)
            ws = vload(D, (2 * nN + k) * LANES) + vload(D, (3 * nN + k) * LANES)
            d4, d5 = vload(D, (4 * nN + k) * LANES), vload(D, (5 * nN + k) * LANES)
            d6, d7 = vload(D, (6 * nN + k) * LANES), vload(D, (7 * nN + k) * LANES)
            u4 = d4 * (soc - shi)
            u5 = d5 * (soc + slo)
            x0 = wb * b + dgb * tb - a * lam - vload(r1, _x5(0, i, j, n, N))
            x1 = ws * s + dgs * ts + a * lam - vload(r1, _x5(1, i, j, n, N))
            x2 = vload(hsoc, _ij(i, j, N)) * soc + u4 + u5 + lam - nxt \
                - vload(r1, _x5(2, i, j, n, N))
            x3 = d6 * shi - u4 - vload(r1, _x5(3, i, j, n, N))
            x4 = d7 * slo + u5 - vload(r1, _x5(4, i, j, n, N))
            xl = soc - a * b + a * s - prev
            vstore(rx, _x5(0, i, j, n, N), x0)
            vstore(rx, _x5(1, i, j, n, N), x1)
            vstore(rx, _x5(2, i, j, n, N), x2)
            vstore(rx, _x5(3, i, j, n, N), x3)
            vstore(rx, _x5(4, i, j, n, N), x4)
            vstore(rl, _ij(i, j, N), xl)
            res = vmax(vmax(vmax(vmax(vmax(vmax(res, vabs(x0)), vabs(x1)), vabs(x2)),
                                 vabs(x3)), vabs(x4)), vabs(xl))
            check = check + 0.0 * (x0 + x1 + x2 + x3 + x4 + xl)
            if magnitudes:
                aa, asoc = vabs(a), vabs(soc)
                m4 = d4 * (asoc + vabs(shi))
                m5 = d5 * (asoc + vabs(slo))
                mag = vmax(vmax(vmax(vmax(vmax(vmax(
                    mag, wb * vabs(b) + dgb * ab + aa * vabs(lam)),
                    ws * vabs(s) + dgs * at + aa * vabs(lam)),
                    vabs(vload(hsoc, _ij(i, j, N))) * asoc + m4 + m5 + vabs(lam) + vabs(nxt)),
                    d6 * vabs(shi) + m4), d7 * vabs(slo) + m5),
                    asoc + aa * (vabs(b) + vabs(s)) + vabs(prev))
    back = res / (mag + 1.0)
    vstore(out, 0, back)
    vstore(out, LANES, check)


@_jit
def _lanes_grad_column(X, L, zx, zl, stagew, out):
    """:func:`_grad_column` of the four lanes: ``out`` (8, n, 4) holds the rows
    0, 1, 2, 3, 4, 5, 7, 8 of ``grad[:, o]`` (the phi3 and T3 rows stay 0)."""
    n, N = _dims(L.shape[0], L.shape[1])
    zero = vsplat(0.0)
    for i in range(n):
        g0 = zero
        g1 = zero
        g2 = zero
        g3 = zero
        g4 = zero
        g5 = zero
        g7 = zero
        g8 = zero
        for j in range(N):
            zb, zs = vload(zx, _x5(0, i, j, n, N)), vload(zx, _x5(1, i, j, n, N))
            zsoc, zlj = vload(zx, _x5(2, i, j, n, N)), vload(zl, _ij(i, j, N))
            soc = vload(X, _x5(2, i, j, n, N))
            g0 = g0 + (vload(L, _ij(i, j, N)) * (zb - zs)
                       + (vload(X, _x5(0, i, j, n, N)) - vload(X, _x5(1, i, j, n, N))) * zlj)
            g1 = g1 + zlj
            g2 = g2 - stagew[W_DISC, j] * zb
            g3 = g3 + stagew[W_DISC, j] * zs
            g4 = g4 - 2.0 * stagew[W_WSOC, j] * soc * zsoc
            g5 = g5 - stagew[W_WSOC, j] * zsoc
            g7 = g7 - 2.0 * stagew[W_TERM, j] * soc * zsoc
            g8 = g8 - stagew[W_TERM, j] * zsoc
        vstore(out, (0 * n + i) * LANES, g0)
        vstore(out, (1 * n + i) * LANES, g1)
        vstore(out, (2 * n + i) * LANES, g2)
        vstore(out, (3 * n + i) * LANES, g3)
        vstore(out, (4 * n + i) * LANES, g4)
        vstore(out, (5 * n + i) * LANES, g5)
        vstore(out, (6 * n + i) * LANES, g7)
        vstore(out, (7 * n + i) * LANES, g8)


@_jit
def _lanes_zmax(zx, zl, IS, zmax_l):
    """:func:`_zmax` of the four lanes, ``zmax_l[:4]`` updated in place (NaN where the
    column is not finite)."""
    n, N = _dims(zl.shape[0], zl.shape[1])
    nN = n * N
    go = 8 * nN
    zero = vsplat(0.0)
    one = vsplat(1.0)
    zmax = vload(zmax_l, 0)
    check = zero
    for j in range(N):
        tb = zero
        ts = zero
        for i in range(n):
            k = i * N + j
            zb, zs = vload(zx, _x5(0, i, j, n, N)), vload(zx, _x5(1, i, j, n, N))
            zsoc, zshi, zslo = (vload(zx, _x5(2, i, j, n, N)), vload(zx, _x5(3, i, j, n, N)),
                                vload(zx, _x5(4, i, j, n, N)))
            zlij = vload(zl, _ij(i, j, N))
            tb = tb + zb
            ts = ts + zs
            zmax = vmax(vmax(vmax(vmax(vmax(vmax(vmax(vmax(
                zmax,
                vabs(zb) * vmax(vmax(one, vload(IS, k * LANES)),
                                vload(IS, (nN + k) * LANES))),
                vabs(zs) * vmax(vmax(one, vload(IS, (2 * nN + k) * LANES)),
                                vload(IS, (3 * nN + k) * LANES))),
                vabs(zsoc)),
                vabs(zshi) * vmax(one, vload(IS, (6 * nN + k) * LANES))),
                vabs(zslo) * vmax(one, vload(IS, (7 * nN + k) * LANES))),
                vabs(zlij)),
                vabs(zsoc - zshi) * vload(IS, (4 * nN + k) * LANES)),
                vabs(zsoc + zslo) * vload(IS, (5 * nN + k) * LANES))
            check = check + 0.0 * (zb + zs + zsoc + zshi + zslo + zlij)
        zmax = vmax(vmax(zmax, vabs(tb) * vload(IS, (go + j) * LANES)),
                    vabs(ts) * vload(IS, (go + N + j) * LANES))
    # the check is a sum of zeros, or NaN
    vstore(zmax_l, 0, where_lt(vabs(check), one, zmax, vsplat(np.nan)))


@_jit
def sensitivity_lanes(P, x, lam, mu, solved, opts, ubar, stagew, n, N, grad, dsoc, cond,
                      back, code, d_lo, d_hi):
    """:func:`sensitivity_each` (``STAGE``, column by column with refinement) of the problems
    ``d_lo <= d < d_hi``, four at a time (a last group of fewer filled up with copies of its
    last problem, not written): the same results bit for bit. The refinement steps of a
    column are taken lane by lane (a lane whose column is good enough keeps it while the
    others refine theirs)."""
    n, N = _dims(n, N)
    nN = n * N
    m = 8 * nN + 2 * N
    B = LANES
    Pb, hi, lo = opts[O_P], opts[O_HI], opts[O_LO]
    X, zx, rx, r1, cx = (np.empty((5, n, N, B)), np.empty((5, n, N, B)),
                         np.empty((5, n, N, B)), np.empty((5, n, N, B)),
                         np.empty((5, n, N, B)))
    L, zl, rl, r2, rsp, cl = (np.empty((n, N, B)), np.empty((n, N, B)), np.empty((n, N, B)),
                              np.empty((n, N, B)), np.empty((n, N, B)), np.empty((n, N, B)))
    Mu, S, IS, D = np.empty((m, B)), np.empty((m, B)), np.empty((m, B)), np.empty((m, B))
    F, FG = np.empty((N_F, n, N, B)), np.empty((N_G, N, B))
    SI, A, dv, w = (np.empty((N, n, n, B)), np.empty((n, n, B)), np.empty((2 * n, B)),
                    np.empty((n, B)))
    soc0, alpha, delta = np.empty((n, B)), np.empty((n, B)), np.empty((n, B))
    qb, qs, hsoc, qsoc, e = (np.empty((n, N, B)), np.empty((n, N, B)), np.empty((n, N, B)),
                             np.empty((n, N, B)), np.empty((n, N, B)))
    scale, cconst = np.empty(B), np.empty(B)
    fact, okv, be, zmax, bmax, kmax = (np.empty(B), np.empty(B), np.empty(2 * B),
                                       np.empty(B), np.empty(B), np.empty(B))
    bcol, live, refine = np.empty(B), np.empty(B), np.empty(B)
    gcol = np.empty((8, n, B))
    rows = np.empty(B, np.int64)
    usable = np.empty(B, np.bool_)
    zero = vsplat(0.0)
    for lo_d in range(d_lo, d_hi, B):
        n_live = 0
        for l in range(B):
            d = min(lo_d + l, d_hi - 1)
            rows[l] = d
            live[l] = 0.0
            if l < d_hi - lo_d:
                grad[d, :, :] = 0.0
                dsoc[d, :, :] = 0.0
                cond[d] = np.inf
                back[d] = np.inf
            if not solved[d]:
                if l < d_hi - lo_d:
                    code[d] = SENS_SKIPPED
                continue
            xd, ld, md = x[d], lam[d], mu[d]
            for i in range(n):
                for j in range(N):
                    for k in range(5):
                        X[k, i, j, l] = xd[j * 5 * n + k * n + i]
                    L[i, j, l] = ld[j * n + i]
                    blk = j * (8 * n + 2)
                    for g in range(4):
                        Mu[g * nN + i * N + j, l] = md[blk + g * n + i]
                        Mu[(4 + g) * nN + i * N + j, l] = md[blk + 4 * n + 2 + g * n + i]
            for j in range(N):
                blk = j * (8 * n + 2)
                Mu[8 * nN + j, l] = md[blk + 4 * n]
                Mu[8 * nN + N + j, l] = md[blk + 4 * n + 1]
            live[l] = 1.0
            n_live += 1
        if n_live == 0:
            continue
        _lanes_data(P, rows, n, N, stagew, opts, soc0, alpha, delta, qb, qs, hsoc, qsoc, e,
                    scale, cconst)
        _lanes_slacks(X, ubar, Pb, hi, lo, S)
        # ||K||_max (entries 1, alpha, H, mu, h) and whether the point is strictly interior
        for l in range(B):
            km = 1.0
            for i in range(n):
                km = max(km, abs(alpha[i, l]))
                for j in range(N):
                    km = max(km, abs(hsoc[i, j, l]))
            kmax[l] = km
        km = vload(kmax, 0)
        inside = vload(live, 0)
        for k in range(m):
            s_k, mu_k = vload(S, k * B), vload(Mu, k * B)
            inside = where_gt(s_k, zero, inside, zero)
            inside = where_gt(mu_k, zero, inside, zero)
            km = vmax(vmax(km, s_k), mu_k)
        vstore(kmax, 0, km)
        vstore(refine, 0, inside)
        for l in range(B):
            if live[l] == 1.0 and refine[l] == 0.0:
                live[l] = 0.0
                if l < d_hi - lo_d:
                    code[rows[l]] = SENS_NOT_INTERIOR
        _lanes_factor(S, Mu, IS, D, alpha, hsoc, F, FG, SI, A, dv, fact)
        for l in range(B):
            usable[l] = fact[l] == 1.0
            zmax[l] = 0.0
            bmax[l] = 0.0
        for o in range(n):
            r1[:] = 0.0
            r2[:] = 0.0
            r1[0, o, 0, :] = 1.0
            r1[1, o, 0, :] = -1.0
            _lanes_solve(r1, r2, zx, zl, alpha, F, FG, SI, rsp, w, okv)
            for l in range(B):
                usable[l] = usable[l] and okv[l] == 0.0
                bcol[l] = np.inf
                refine[l] = 1.0
            for step in range(_REFINE_MAX + 1):
                _lanes_backward_error(zx, zl, r1, D, alpha, hsoc, rx, rl, step > 0, be)
                n_refine = 0
                for l in range(B):
                    if refine[l] == 0.0:
                        continue
                    b_l = np.inf
                    if step > 0 and be[B + l] == 0.0 and not math.isnan(be[l]):
                        b_l = be[l]
                    bcol[l] = b_l
                    if step == _REFINE_MAX or (step > 0 and b_l <= _BACKWARD_ERROR_GOOD):
                        refine[l] = 0.0
                    else:
                        n_refine += 1
                if n_refine == 0:
                    break
                for k in range(5 * nN):
                    vstore(rx, k * B, -vload(rx, k * B))
                for k in range(nN):
                    vstore(rl, k * B, -vload(rl, k * B))
                _lanes_solve(rx, rl, cx, cl, alpha, F, FG, SI, rsp, w, okv)
                for l in range(B):
                    if refine[l] == 1.0:
                        usable[l] = usable[l] and okv[l] == 0.0
                take = vload(refine, 0)
                for k in range(5 * nN):
                    z = vload(zx, k * B)
                    vstore(zx, k * B, where_gt(take, zero, z + vload(cx, k * B), z))
                for k in range(nN):
                    z = vload(zl, k * B)
                    vstore(zl, k * B, where_gt(take, zero, z + vload(cl, k * B), z))
            for l in range(B):
                bmax[l] = max(bmax[l], bcol[l])
            _lanes_grad_column(X, L, zx, zl, stagew, gcol)
            _lanes_zmax(zx, zl, IS, zmax)
            for l in range(min(B, d_hi - lo_d)):
                if live[l] == 0.0:
                    continue
                d = rows[l]
                for i in range(n):
                    for r, row in enumerate((0, 1, 2, 3, 4, 5, 7, 8)):
                        grad[d, row * n + i, o] = gcol[r, i, l]
                    dsoc[d, i, o] = zl[i, 0, l]
        for l in range(min(B, d_hi - lo_d)):
            if live[l] == 0.0:
                continue
            d = rows[l]
            c = kmax[l] * zmax[l]
            cond[d] = c if math.isfinite(c) else np.inf
            back[d] = bmax[l]
            G = grad[d]
            finite = 0.0
            for k in range(G.size):
                finite += 0.0 * G.flat[k]
            if usable[l] and finite == 0.0 and math.isfinite(c):
                code[d] = SENS_OK
            else:
                code[d] = SENS_SINGULAR
                G[:, :] = 0.0
                dsoc[d, :, :] = 0.0


@_jit
def sensitivity_each(P, x, lam, mu, solved, opts, ubar, stagew, n, N, method, structured,
                     grad, dsoc, cond, back, code, d_lo, d_hi):
    """:func:`sensitivity_rows` one problem after the other (either factorisation)."""
    n, N = _dims(n, N)
    (X, zx, rx, r1, L, zl, rl, r2, rsp, Mu, S, IS, D, _ds, _dmu, _cr, _r, F, FG, SI, AW, TI,
     MC, MS, w, wg) = _work(n, N, method)
    cx, cl = np.empty((5, n, N)), np.empty((n, N))
    structured = structured and method == AGENT
    ns = n if structured else 1
    Y, Q, RL, acc = np.empty((ns, N)), np.empty((2 * N, ns)), np.empty((N + 1, ns)), np.empty(ns)
    soc0, alpha, delta, qb, qs, hsoc, qsoc, e = _data_arrays(n, N)
    Pb, hi, lo = opts[O_P], opts[O_HI], opts[O_LO]
    zxf, zlf, cxf, clf, rxf, rlf = (zx.reshape(zx.size), zl.reshape(zl.size),
                                    cx.reshape(cx.size), cl.reshape(cl.size),
                                    rx.reshape(rx.size), rl.reshape(rl.size))
    for d in range(d_lo, d_hi):
        G = grad[d]
        G[:, :] = 0.0
        dsoc[d, :, :] = np.nan if structured else 0.0
        cond[d] = np.inf
        back[d] = np.inf
        if not solved[d]:
            code[d] = SENS_SKIPPED
            continue
        _problem_data(P[d], n, N, stagew, opts, soc0, alpha, delta, qb, qs, hsoc, qsoc, e)
        _unpack_solution(x[d], lam[d], mu[d], n, N, X, L, Mu)
        _slacks(X, ubar, Pb, hi, lo, S)
        # ||K||_max of the KKT Jacobian (entries 1, alpha, H, mu, h)
        kmax = 1.0
        for i in range(n):
            kmax = max(kmax, abs(alpha[i]))
            for j in range(N):
                kmax = max(kmax, abs(hsoc[i, j]))
        interior = True
        for k in range(S.size):
            if not (S[k] > 0.0 and Mu[k] > 0.0):
                interior = False
            kmax = max(kmax, S[k], Mu[k])
        if not interior:
            code[d] = SENS_NOT_INTERIOR
            continue
        usable = _factor(S, Mu, IS, D, alpha, hsoc, method, F, FG, SI, AW, TI, MC, MS, w)
        zmax = 0.0
        bmax = 0.0
        if structured and usable:
            zmax, bmax, usable = _adjoint_structured(X, L, Mu, IS, D, alpha, stagew, F, MC, MS,
                                                     TI, G, Y, Q, RL, acc, wg)
        for o in range(0 if structured else n):
            # column o of S_y': +1 at b_0, -1 at s_0 of agent o
            r1[:] = 0.0
            r2[:] = 0.0
            r1[0, o, 0] = 1.0
            r1[1, o, 0] = -1.0
            usable &= _solve(r1, r2, zx, zl, alpha, F, FG, method, SI, AW, MC, MS, rsp, w, wg,
                             o)
            # iterative refinement: at least one step (where a grid limit binds, an agent's own
            # response and the grid's nearly cancel and small entries lose digits that the
            # normwise backward error does not see), more while that error is above the
            # rounding level
            bcol = np.inf
            for step in range(_REFINE_MAX + 1):
                bcol = _backward_error(zx, zl, r1, D, alpha, hsoc, rx, rl, step > 0)
                if step == _REFINE_MAX or (step > 0 and bcol <= _BACKWARD_ERROR_GOOD):
                    break
                for k in range(5 * n * N):
                    rxf[k] = -rxf[k]
                for k in range(n * N):
                    rlf[k] = -rlf[k]
                usable &= _solve(rx, rl, cx, cl, alpha, F, FG, method, SI, AW, MC, MS, rsp, w,
                                 wg, -1)
                for k in range(5 * n * N):
                    zxf[k] += cxf[k]
                for k in range(n * N):
                    zlf[k] += clf[k]
            bmax = max(bmax, bcol)
            _grad_column(X, L, zx, zl, stagew, G, o)
            for i in range(n):
                dsoc[d, i, o] = zl[i, 0]
            zmax = _zmax(zx, zl, IS, zmax)
        c = kmax * zmax
        cond[d] = c if math.isfinite(c) else np.inf
        back[d] = bmax
        finite = 0.0
        for k in range(G.size):
            finite += 0.0 * G.flat[k]
        if usable and finite == 0.0 and math.isfinite(c):
            code[d] = SENS_OK
        else:
            code[d] = SENS_SINGULAR
            G[:, :] = 0.0
            dsoc[d, :, :] = 0.0


# ------------------------------------------------------------------ both cores ----
@_parallel
def solve_rows_parallel(P, x0, warm, opts, ubar, stagew, n, N, method, x_out, lam_out, mu_out,
                        cost_out, iters_out, status_out, action_out, d_lo, d_hi, block):
    """:func:`solve_rows` on the blocks of ``block`` problems of ``d_lo <= d < d_hi``, the
    blocks spread over numba's threads (``numba.set_num_threads``). Each problem is solved
    alone, so the results are those of one :func:`solve_rows` call, bit for bit."""
    blocks = (d_hi - d_lo + block - 1) // block
    for b in prange(blocks):
        lo = d_lo + b * block
        solve_rows(P, x0, warm, opts, ubar, stagew, n, N, method, x_out, lam_out, mu_out,
                   cost_out, iters_out, status_out, action_out, lo, min(lo + block, d_hi))


@_parallel
def solve_each_parallel(P, x0, warm, opts, ubar, stagew, n, N, method, x_out, lam_out, mu_out,
                        cost_out, iters_out, status_out, action_out, d_lo, d_hi, block):
    """:func:`solve_each` on blocks spread over numba's threads, as
    :func:`solve_rows_parallel` (the one-at-a-time reference)."""
    blocks = (d_hi - d_lo + block - 1) // block
    for b in prange(blocks):
        lo = d_lo + b * block
        solve_each(P, x0, warm, opts, ubar, stagew, n, N, method, x_out, lam_out, mu_out,
                   cost_out, iters_out, status_out, action_out, lo, min(lo + block, d_hi))


@_parallel
def sensitivity_each_parallel(P, x, lam, mu, solved, opts, ubar, stagew, n, N, method,
                              structured, grad, dsoc, cond, back, code, d_lo, d_hi, block):
    """:func:`sensitivity_each` on blocks spread over numba's threads (the one-at-a-time
    reference)."""
    blocks = (d_hi - d_lo + block - 1) // block
    for b in prange(blocks):
        lo = d_lo + b * block
        sensitivity_each(P, x, lam, mu, solved, opts, ubar, stagew, n, N, method, structured,
                         grad, dsoc, cond, back, code, lo, min(lo + block, d_hi))


@_parallel
def sensitivity_rows_parallel(P, x, lam, mu, solved, opts, ubar, stagew, n, N, method,
                              structured, grad, dsoc, cond, back, code, d_lo, d_hi, block):
    """:func:`sensitivity_rows` on blocks spread over numba's threads, as
    :func:`solve_rows_parallel`."""
    blocks = (d_hi - d_lo + block - 1) // block
    for b in prange(blocks):
        lo = d_lo + b * block
        sensitivity_rows(P, x, lam, mu, solved, opts, ubar, stagew, n, N, method, structured,
                         grad, dsoc, cond, back, code, lo, min(lo + block, d_hi))


def set_threads(threads: int) -> int:
    """Let the ``*_parallel`` entries use ``threads`` threads (at most numba's pool);
    returns the number set."""
    threads = max(1, min(int(threads), numba.config.NUMBA_NUM_THREADS))
    numba.set_num_threads(threads)
    return threads


# ------------------------------------------------------------------ compilation, cache ----
#: The compiled entries of the solver (:func:`warm_up` runs them all by default).
ENTRIES = ("solve_rows", "solve_rows_parallel", "sensitivity_rows", "sensitivity_rows_parallel")


def warm_up(entries: tuple[str, ...] = ENTRIES) -> None:
    """Run the kernels ``entries`` (both factorisations, cold and warm start, both adjoints)
    on a tiny problem (of the fixed sizes in a specialised copy), which compiles them or
    loads them from numba's cache."""
    n, N = (FIXED_N, FIXED_HORIZON) if FIXED_N > 0 else (1, 2)
    opts = np.zeros(N_OPTS)
    opts[[O_TAU, O_TOL, O_MAX_ITER, O_P, O_HI, O_LO]] = (0.1, 1e-10, 50, 1.0, 0.9, 0.1)
    ubar = np.ones(n)
    opts[[O_U0, O_T0_COLD, O_T0_WARM, O_WARM_MARGIN, O_WARM_WEIGHT, O_SLACK_MARGIN,
          O_SWITCH, O_POLISH]] = (0.5, 0.1, 0.1, 1e-2, 0.3, 0.3, 1.0, 1.0)
    stagew = np.ones((5, N))
    theta = np.repeat(np.array([0.1, 0.0, 0.0, 0.0, 1.0, -1.0, 0.0, 1.0, -1.0, 0.0]), n)
    buy = np.linspace(10.0, 20.0, N)
    P = np.concatenate([np.full(n, 0.5), buy, 0.5 * buy, theta])[None, :]
    nx, neq, nin = 5 * n * N, n * N, (8 * n + 2) * N
    for method in (STAGE, AGENT):
        x, lam, mu = np.zeros((1, nx)), np.empty((1, neq)), np.empty((1, nin))
        cost, action = np.empty(1), np.empty((1, n))
        iters, status = np.empty(1, np.int64), np.empty(1, np.int64)
        solved = (P, x.copy(), True, opts, ubar, stagew, n, N, method, x, lam, mu, cost, iters,
                  status, action, 0, 1)
        for warm in (False, True):  # a solution for the sensitivities in any case
            solve_rows(*solved[:2], warm, *solved[3:])
        if "solve_rows_parallel" in entries:
            solve_rows_parallel(*solved, 1)
        grad, cond, back = np.empty((1, 10 * n, n)), np.empty(1), np.empty(1)
        dsoc = np.empty((1, n, n))
        code = np.empty(1, np.int64)
        for structured in (False, True):
            adjoint = (P, x, lam, mu, np.ones(1, np.bool_), opts, ubar, stagew, n, N, method,
                       structured, grad, dsoc, cond, back, code, 0, 1)
            if "sensitivity_rows" in entries:
                sensitivity_rows(*adjoint)
            if "sensitivity_rows_parallel" in entries:
                sensitivity_rows_parallel(*adjoint, 1)


def cache_dir() -> str:
    """The folder numba caches these kernels in."""
    return jit.cache_dir(solve_rows)


def ensure_compiled(entries: tuple[str, ...] = ENTRIES) -> None:
    """Load the kernels ``entries`` (all by default) from the cache or compile them
    (logging one line if it compiles); ``solve_rows`` always, the others find their
    solutions with it. A process loads only the entries it calls (each load takes tens of
    milliseconds)."""
    chosen = tuple(dict.fromkeys(("solve_rows", *entries)))
    jit.ensure_compiled(tuple(globals()[name] for name in chosen),
                        lambda: warm_up(chosen), "the MPC kernels (a minute or two)")
