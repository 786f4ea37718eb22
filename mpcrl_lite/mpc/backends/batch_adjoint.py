r"""Policy sensitivities of the batch interior point (:mod:`mpcrl_lite.mpc.backends.batch`).

By the implicit function theorem ``d pi/d theta = -(dR/dtheta)' Z`` with the
adjoint ``(dR/dy)' Z = S_y'`` (``S`` the policy selector, see
:mod:`mpcrl_lite.mpc.sensitivity`). ``h`` does not depend on theta, so the complementarity rows of
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

``dR/dtheta`` in closed form (tested against CasADi's :attr:`~mpcrl_lite.mpc.formulation.KKT.jacobians`):

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
:class:`~mpcrl_lite.mpc.sensitivity.PolicySensitivity`, computed from the same ``Z`` (for many
agents by forming ``Z`` a chunk of columns at a time).

The functions here work on the structured KKT system of :mod:`mpcrl_lite.mpc.backends.batch_kkt` at a
solution point and know nothing of the Newton iteration; any solution of the MPC will do
(e.g. one from the IPOPT back-end).
"""

from __future__ import annotations

import numpy as np

from ...theta import PARTS
from ..solution import BatchSolution, MPCSolution, Sensitivity
from .batch_kkt import TINY, BatchData, BatchKKT, KKTFactor
from .batch_linalg import cholesky_solve

__all__ = ["batch_sensitivity", "grad_weights"]

_BACKWARD_ERROR_MAX = 1e-6  # of the adjoint solve; above it a sensitivity is flagged
_N_PARTS = len(PARTS)
_FULL_ADJOINT_MAX = 1 << 17  # days n^2 N up to which the adjoint is formed in full (refined)
_REFINE_MAX = 4  # iterative refinement steps of the adjoint at most
_BACKWARD_ERROR_GOOD = 1e-14  # backward error at which refinement stops


def batch_sensitivity(
    kkt: BatchKKT, solution: BatchSolution | MPCSolution, cond_max: float
) -> Sensitivity:
    r"""Policy sensitivities ``d pi / d theta`` of every problem in ``solution``.

    Works on any solution of ``kkt.mpc`` (e.g. from :class:`~mpcrl_lite.mpc.backends.ipopt.IpoptSolver`
    too); problems with different theta are handled group by group.

    Parameters
    ----------
    kkt
        The structured KKT system of the MPC.
    solution
        One solution or a batch (days problems).
    cond_max
        Conditioning proxy above which a sensitivity is reported as ill-conditioned
        (``MPCConfig.kkt_cond_max``).

    Returns
    -------
    Sensitivity
        ``grad`` (days, n_theta, n), ``ok``, ``cond`` (the proxy ``||K||_max ||Z||_max``)
        and ``reason``, as :class:`~mpcrl_lite.mpc.sensitivity.PolicySensitivity`.
    """
    solution = BatchSolution.of(solution)
    m = kkt.mpc
    days, n = len(solution), kkt.n
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
        for idx in kkt.theta_groups(P, rows) if rows.size else []:
            _sensitivity_group(kkt, solution, P, idx, cond_max, grads, ok, conds, reasons)
    return Sensitivity(grads, ok, conds, tuple(reasons))


def _sensitivity_group(
    kkt: BatchKKT, solution, P, idx, cond_max: float, grads, ok, conds, reasons
) -> None:
    """Sensitivities of the problems ``idx`` (which share theta), written in place."""
    n, N = kkt.n, kkt.N
    X = kkt.to_internal_x(np.asarray(solution.x)[idx])
    Mu = kkt.mu_from_flat(np.asarray(solution.mu)[idx])
    S = kkt.slacks(X)
    interior = np.all(S > 0, axis=1) & np.all(Mu > 0, axis=1)
    for d in idx[~interior]:
        reasons[d] = "solution not strictly interior (S > 0 and mu > 0 violated)"
    if not np.all(interior):
        idx, X, Mu, S = idx[interior], X[interior], Mu[interior], S[interior]
        if idx.size == 0:
            return
    k = idx.size
    data = kkt.batch_data(P[idx])
    L = kkt.to_internal_lam(np.asarray(solution.lam)[idx])
    f, fok = kkt.factor(S, Mu, data)
    if k * n * n * N <= _FULL_ADJOINT_MAX:
        grad, cond, back, sok = _adjoint_full(kkt, f, data, X, L, Mu, S)
    else:
        grad, cond, back, sok = _adjoint_structured(kkt, f, data, X, L, Mu, S)
    usable = fok & sok & np.all(np.isfinite(grad), axis=(1, 2)) & np.isfinite(cond)
    for pos, d in enumerate(idx):
        conds[d] = cond[pos] if np.isfinite(cond[pos]) else np.inf
        if not usable[pos]:
            reasons[d] = "singular KKT matrix"
        elif back[pos] > _BACKWARD_ERROR_MAX or cond[pos] > cond_max:
            reasons[d] = f"ill-conditioned KKT matrix (cond ~ {cond[pos]:.2e})"
        else:
            grads[d] = grad[pos]
            ok[d] = True


def _adjoint_structured(kkt: BatchKKT, f: KKTFactor, data: BatchData, X, L, Mu, S):
    """Sensitivities from the column structure of the adjoint (for many agents).

    Column ``o`` of Z is agent ``o``'s own local solution plus every agent's response to
    the grid forces ``g^(o)``; the responses are contracted with ``dR/dtheta`` once per
    agent, so nothing of size ``n^2 N^2`` is formed. Without refinement: where the grid
    limit binds, the own part and the grid's response nearly cancel and entries lose
    digits in absolute terms (about 1e-11 of the column's scale). Returns grad
    (k, n_theta, n), the conditioning proxy, the backward error of the ``2N`` solve and
    a success flag.
    """
    k, n, N = X.shape[0], kkt.n, kkt.N
    alpha = data.alpha
    vb, vs, V = f.vb, f.vs, f.V
    # Column o of Z (the adjoint for the policy of agent o) = agent o's own local
    # solution for the right-hand side e_o (+1 at b_0, -1 at s_0) + every agent's
    # response R_i g^(o) to the grid forces g^(o), with M g^(o) = (b_0.., s_0..) of the
    # own local solution (see BatchKKT.solve_reduced).
    e1 = np.zeros((k, 5, n, N, 1))
    e1[:, 0, :, 0] = 1.0
    e1[:, 1, :, 0] = -1.0
    e2 = np.zeros((k, n, N, 1))
    yx, yl = kkt.solve_local(f, data, e1, e2)  # own local parts

    def own_columns(zx):  # (b, s) of agent o's own part as column o, (k, 2N, n)
        return zx[:, :2, :, :, 0].transpose(0, 1, 3, 2).reshape(k, 2 * N, n)

    scale = f.Mscale[..., None]
    q = own_columns(yx) * scale
    g, sok = cholesky_solve(f.Mchol, q)
    # normwise backward error of the 2N solve (the local solves cannot break down: their
    # tridiagonal matrices are diagonally dominant with positive pivots)
    back = np.abs(np.einsum("kab,kbo->kao", f.M, g) - q).reshape(k, -1).max(axis=1)
    back /= np.maximum(
        np.abs(f.M).reshape(k, -1).max(axis=1) * np.abs(g).reshape(k, -1).max(axis=1)
        + np.abs(q).reshape(k, -1).max(axis=1), TINY)
    g *= scale
    cond = _adjoint_sweep(kkt, f, data, Mu, S, yx, yl, g)

    # -dR/dtheta as weights on (Zb, Zs, Zsoc, Zlam); for the responses R_i they are folded
    # into weights on lam alone: R_i's lam part is [T^{-1} diag(beta_b), -T^{-1} diag(beta_s)],
    # b = vb (alpha lam - I_b), s = vs (-alpha lam - I_s), soc_j = V_j (lam_{j+1} - lam_j)
    wb, ws, wsoc, wl = grad_weights(kkt, X, L)  # (k, n, parts, N) each
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


def _adjoint_full(kkt: BatchKKT, f: KKTFactor, data: BatchData, X, L, Mu, S):
    """Sensitivities from the full adjoint Z, all ``n`` columns at once, with iterative
    refinement on the reduced system (for few agents: ``Z`` has ``O(n^2 N)`` entries).
    Returns grad (k, n_theta, n), the conditioning proxy, the normwise backward error of
    the refined solve and a success flag."""
    k, n, N = X.shape[0], kkt.n, kkt.N
    ar = np.arange(n)
    r1 = np.zeros((k, 5, n, N, n))
    r1[:, 0, ar, 0, ar] = 1.0
    r1[:, 1, ar, 0, ar] = -1.0
    r2 = np.zeros((k, n, N, n))
    Zx, Zl, sok = kkt.solve_reduced(f, data, r1, r2)
    # iterative refinement: at least one step (it restores the small entries, which the
    # normwise backward error does not see), more until that error max |r| / max(|K||Z| + 1)
    # is at the rounding level
    for step in range(_REFINE_MAX + 1):
        W, Az = kkt.reduced_apply(f, data, Zx, Zl)
        W -= r1
        Wm, Azm = kkt.reduced_apply(f, data, np.abs(Zx), np.abs(Zl), absolute=True)
        back = np.maximum(np.abs(W).reshape(k, -1).max(axis=1),
                          np.abs(Az).reshape(k, -1).max(axis=1)) / np.maximum(
            np.maximum(Wm.reshape(k, -1).max(axis=1), Azm.reshape(k, -1).max(axis=1))
            + 1.0, TINY)
        if step == _REFINE_MAX or (step and np.all(back <= _BACKWARD_ERROR_GOOD)):
            break
        cx, cl, sok2 = kkt.solve_reduced(f, data, -W, -Az)
        Zx += cx
        Zl += cl
        sok &= sok2
    # grad[p, i, o] = sum over the stages of the weights times Z
    wb, ws, wsoc, wl = grad_weights(kkt, X, L)
    grad = wb @ Zx[:, 0] + ws @ Zx[:, 1] + wsoc @ Zx[:, 2] + wl @ Zl  # (k, n, parts, n)
    grad = grad.transpose(0, 2, 1, 3).reshape(k, _N_PARTS * n, n)
    # conditioning proxy ||K||_max ||Z||_max, with Z_mu = C Z_x / S
    ZS = kkt.slacks(Zx.transpose(0, 4, 1, 2, 3).reshape(k * n, 5, n, N), offset=False)
    Zmu = ZS.reshape(k, n, -1) / S[:, None, :]
    zmax = np.max(np.stack([np.abs(Zx).reshape(k, -1).max(axis=1),
                            np.abs(Zl).reshape(k, -1).max(axis=1),
                            np.abs(Zmu).reshape(k, -1).max(axis=1)]), axis=0)
    cond = _kmax(data, Mu, S) * zmax
    return grad, cond, back, sok


def _kmax(data: BatchData, Mu, S) -> np.ndarray:
    """``||K||_max`` of the KKT Jacobian ``dR/dy`` (entries 1, alpha, H, mu, h)."""
    k = Mu.shape[0]
    return np.max(np.stack([
        np.ones(k), np.full(k, np.abs(data.alpha).max()),
        np.full(k, np.abs(data.hsoc).max()), Mu.max(axis=1), S.max(axis=1),
    ]), axis=0)


def grad_weights(kkt: BatchKKT, X: np.ndarray, L: np.ndarray) -> tuple[np.ndarray, ...]:
    """``-dR/dtheta`` as weights on (Zb, Zs, Zsoc, Zlam) per theta part, each of shape
    (k, n, parts, N) (see the table in the module docstring), at primal points ``X``
    (k, 5, n, N) and multipliers ``L`` (k, n, N) in the internal layout."""
    k, n, N = L.shape[0], kkt.n, kkt.N
    wb = np.zeros((k, n, _N_PARTS, N))
    ws = np.zeros_like(wb)
    wsoc = np.zeros_like(wb)
    wl = np.zeros_like(wb)
    soc = X[:, 2]
    wb[:, :, 0] = L
    ws[:, :, 0] = -L
    wl[:, :, 0] = X[:, 0] - X[:, 1]
    wl[:, :, 1] = 1.0
    wb[:, :, 2] = -kkt.disc
    ws[:, :, 3] = kkt.disc
    wsoc[:, :, 4] = -2.0 * kkt.wsoc * soc
    wsoc[:, :, 5] = -kkt.wsoc
    wsoc[:, :, 7] = -2.0 * kkt.term * soc
    wsoc[:, :, 8] = -kkt.term
    return wb, ws, wsoc, wl


def _adjoint_sweep(
    kkt: BatchKKT, f: KKTFactor, data: BatchData, Mu, S, yx, yl, g
) -> np.ndarray:
    """``||K||_max ||Z||_max``, the conditioning proxy of
    :class:`~mpcrl_lite.mpc.sensitivity.PolicySensitivity`, forming all columns of the
    adjoint Z a chunk at a time (bounded memory).

    Column ``o`` is agent ``o``'s own part ``(yx, yl)`` plus every agent's response
    ``R_i g^(o)`` to the grid forces; the multiplier rows are ``Z_mu = -dS / S`` group by
    group and ``g / mu`` on the grid rows.
    """
    k, n, N = Mu.shape[0], kkt.n, kkt.N
    alpha = data.alpha[..., None]
    SL, DL = kkt.agent(S), kkt.agent(f.D)
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
    zgrid = (np.abs(g) / kkt.grid(Mu).reshape(k, -1, 1)).reshape(k, -1).max(axis=1)
    zmax = np.maximum(zmax, zgrid)
    return _kmax(data, Mu, S) * zmax


def _absmax(Z: np.ndarray, w: np.ndarray | None) -> np.ndarray:
    """``max |Z * w|`` per leading index (in place on ``Z``)."""
    np.abs(Z, out=Z)
    if w is not None:
        Z *= w
    return Z.reshape(Z.shape[0], -1).max(axis=1)

