r"""The first stage of the fixed-first-action MPC (:mod:`mpcrl_lite.mpc.q_kernel`), compiled.

Its damped Newton iteration works on arrays of a few numbers per row, all rows of a batch
together (720 in a month of Q-learning): written with numpy it is about thirty array calls
per step and twenty steps, 5 ms of a 37 ms Q-learning month. :func:`newton_rows` does the
same arithmetic row by row in a compiled loop. The numpy form (``q_kernel._newton_numpy``) is
the reference, and every operation is taken in the order numpy takes it -- the sums over the
batteries from the first entry on, ``minimum`` and ``maximum`` with numpy's rules, the same
steps for every row until all of them are done, a done row moved by ``0 * ds`` -- so the
results are those of the numpy form to the last bit for fewer than eight batteries
(``tests/mpc/test_q_kernel.py``; numpy sums eight or more pairwise, and ``q_kernel`` runs
those batches in numpy).

Compiled with numba's on-disk cache in the folder of the MPC kernels
(``python -m mpcrl_lite.cli.warm`` fills it).
"""

from __future__ import annotations

import numpy as np

from .._util import jit

_jit = jit.njit_cached(error_model="numpy")

__all__ = ["ensure_compiled", "newton_rows", "warm_up"]


@_jit
def _np_min(x, y):
    """``numpy.minimum(x, y)``."""
    return x if (x <= y or np.isnan(x)) else y


@_jit
def _np_max(x, y):
    """``numpy.maximum(x, y)``."""
    return x if (x >= y or np.isnan(x)) else y


@_jit
def newton_rows(s, c, a, A, U, P, tau, done, max_iter, tol):
    """The damped Newton iteration of ``q_kernel._first_stage`` from ``s`` (rows, n), in
    place: ``c``, ``a`` (rows, n) the costs and actions, ``A`` (rows,) the actions' sums,
    ``U`` (n,) the input bounds, ``P`` the grid bound, ``done`` (rows,) the rows already
    done (updated in place)."""
    rows, n = s.shape
    grad = np.empty((rows, n))
    ds = np.empty((rows, n))
    gbs = np.empty(rows)
    gss = np.empty(rows)
    dg = np.empty(n)
    d1 = np.empty(n)
    for _ in range(max_iter):
        every = True
        for d in range(rows):
            total = s[d, 0]
            for i in range(1, n):
                total = total + s[d, i]
            gb = P - (total + A[d])
            gs = P - total
            gbs[d], gss[d] = gb, gs
            edge = tau / gb + tau / gs
            rank = tau / (gb * gb) + tau / (gs * gs)
            for i in range(n):
                si, ai, ui = s[d, i], a[d, i], U[i]
                up = ui - si
                inner = 1.0 / si - 1.0 / up + 1.0 / (si + ai) - 1.0 / (up - ai)
                g = (c[d, i] - tau * inner) + edge
                diag = tau * (1.0 / (si * si) + 1.0 / (up * up) + 1.0 / ((si + ai) * (si + ai))
                              + 1.0 / ((up - ai) * (up - ai)))
                grad[d, i] = g
                dg[i] = g / diag
                d1[i] = 1.0 / diag
            sum_dg, sum_d1 = dg[0], d1[0]
            for i in range(1, n):
                sum_dg = sum_dg + dg[i]
                sum_d1 = sum_d1 + d1[i]
            coef = rank * sum_dg / (1.0 + rank * sum_d1)
            for i in range(n):
                ds[d, i] = -(dg[i] - d1[i] * coef)
            decrement = grad[d, 0] * ds[d, 0]
            top = abs(c[d, 0])
            for i in range(1, n):
                decrement = decrement + grad[d, i] * ds[d, i]
                top = _np_max(top, abs(c[d, i]))
            done[d] = done[d] or (-decrement <= tol * (1.0 + top))
            every = every and done[d]
        if every:
            break
        # the longest step keeping every log argument positive, then 0.99 of it (at most 1)
        for d in range(rows):
            step = 1.0
            for k in range(4):
                least = np.inf
                for i in range(n):
                    si, ai, ui, di = s[d, i], a[d, i], U[i], ds[d, i]
                    if k == 0:
                        num, den = si, -di
                    elif k == 1:
                        num, den = ui - si, di
                    elif k == 2:
                        num, den = si + ai, -di
                    else:
                        num, den = ui - si - ai, di
                    r = num / den if den > 0 else np.inf
                    least = r if i == 0 else _np_min(least, r)
                step = _np_min(step, 0.99 * least)
            total = ds[d, 0]
            for i in range(1, n):
                total = total + ds[d, i]
            for num in (gbs[d], gss[d]):
                step = _np_min(step, 0.99 * num / total if total > 0 else np.inf)
            if done[d]:
                step = 0.0
            for i in range(n):
                s[d, i] = s[d, i] + step * ds[d, i]


def warm_up() -> None:
    """Run :func:`newton_rows` on a tiny input: compiles it or loads it from the cache."""
    s = np.full((1, 3), 0.25)
    newton_rows(s, np.ones((1, 3)), np.zeros((1, 3)), np.zeros(1), np.ones(3), 1.5, 0.1,
                np.zeros(1, np.bool_), 5, 1e-15)


def ensure_compiled() -> None:
    """Load :func:`newton_rows` from the cache or compile it (one log line if it compiles)."""
    jit.ensure_compiled((newton_rows,), warm_up, "the first stage of the Q-learner's MPC")
