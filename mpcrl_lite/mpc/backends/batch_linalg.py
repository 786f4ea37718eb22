"""Batched dense kernels of the batch interior point (:mod:`mpcrl_lite.mpc.backends.batch`).

* :func:`tridiag_inverse` -- inverses of many symmetric positive definite, diagonally
  dominant tridiagonal matrices (the per-agent systems in ``d lambda``), stable for any
  horizon;
* :func:`cholesky`, :func:`cholesky_solve` -- batched Cholesky factorisation and solves of
  the small grid Schur complements, through LAPACK, with per-matrix failure flags instead
  of exceptions.

They know nothing about the MPC: arrays in, arrays out, a leading batch axis.
"""

from __future__ import annotations

import numpy as np


def _dpotrf(*args, **kwargs):
    """LAPACK's dpotrf (``scipy.linalg.lapack``, imported on first use: scipy.linalg takes
    a noticeable part of a second to import)."""
    from scipy.linalg.lapack import dpotrf

    return dpotrf(*args, **kwargs)


def _dpotrs(*args, **kwargs):
    """LAPACK's dpotrs, as :func:`_dpotrf`."""
    from scipy.linalg.lapack import dpotrs

    return dpotrs(*args, **kwargs)

__all__ = ["RHS_BLOCK", "cholesky", "cholesky_solve", "tridiag_inverse"]

RHS_BLOCK = 16  # right-hand sides per LAPACK call (see cholesky_solve)


def tridiag_inverse(a: np.ndarray, V: np.ndarray, upper: np.ndarray) -> np.ndarray:
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


def cholesky(M: np.ndarray, ok: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
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


def cholesky_solve(L: np.ndarray, rhs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Solve ``L[d] L[d]' x[d] = rhs[d]`` for every d (``L`` from :func:`cholesky`); returns
    ``(x, finite per d)``. ``L[d].T`` is the upper factor in Fortran order, passed to LAPACK
    without a copy.

    At most :data:`RHS_BLOCK` right-hand sides go into one LAPACK call: with more, a
    multithreaded BLAS may split the triangular solves over threads, which costs a thousand
    times more than the solve itself on a busy machine.
    """
    x = np.empty(rhs.shape)
    m = rhs.shape[-1]
    if m <= RHS_BLOCK:
        for d in range(L.shape[0]):
            x[d], _ = _dpotrs(L[d].T, rhs[d], lower=0)
    else:
        for d in range(L.shape[0]):
            for j in range(0, m, RHS_BLOCK):
                x[d, :, j : j + RHS_BLOCK], _ = _dpotrs(
                    L[d].T, rhs[d, :, j : j + RHS_BLOCK], lower=0)
    ok = np.all(np.isfinite(x.reshape(x.shape[0], -1)), axis=1)
    return x, ok
