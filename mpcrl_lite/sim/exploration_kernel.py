r"""The bounded exploration of :func:`mpcrl_lite.sim.exploration.bounded_exploration`, compiled.

Exploring is done every hour of every learning month for every day at once, on arrays of
a few numbers per day; written with numpy the work is a few dozen array calls per hour, and
their call overhead was a fifth of a learning month's CPU time once the MPC itself had been
compiled (:mod:`mpcrl_lite.mpc.backends.kernel_core`). These functions do the same arithmetic row by row in
compiled loops. The mathematics -- the radial step, the slide along the grid faces, the
projection onto the feasible set -- is documented where it is used
(:func:`~mpcrl_lite.sim.exploration.bounded_exploration`) and, for the projection, in
:func:`mpcrl_lite.system.battery.project_action`, whose numpy form is the reference: every operation
here is taken in the order numpy takes it (sums from the first entry on, ``maximum``,
``minimum`` and ``clip`` with numpy's rules), so for a few batteries the results are those of
the numpy form to the last bit (``tests/sim/test_closed_loop.py`` checks it).

Compiled with numba's on-disk cache in the folder of the MPC kernels
(:mod:`mpcrl_lite.mpc.backends.kernel`; ``python -m mpcrl_lite.cli.warm`` fills it).
"""

from __future__ import annotations

import numpy as np

from .._util import jit

_jit = jit.njit_cached(error_model="numpy")

__all__ = ["ensure_compiled", "explore_rows", "project_rows", "warm_up"]


@_jit
def _np_max(x, y):
    """``numpy.maximum(x, y)``."""
    return x if (x >= y or np.isnan(x)) else y


@_jit
def _np_min(x, y):
    """``numpy.minimum(x, y)``."""
    return x if (x <= y or np.isnan(x)) else y


@_jit
def _np_clip(x, lo, hi):
    """``numpy.clip(x, lo, hi)``."""
    m = x if (x > lo or np.isnan(x)) else lo
    return m if (m < hi or np.isnan(m)) else hi


@_jit
def _sort_small(a):
    """``a.sort()`` for the few finite entries of one row, in place (insertion sort: numba's
    ``sort`` took about 0.27 us on 5 entries, this about 3 ns, and a row sorted 8 to 12
    times). Equal values may only differ in the order of a ``-0.0`` and a ``+0.0``, which
    changes no result: :func:`_largest_step` clips its entries to ``[0, 1]`` before the sort
    (so it has no ``-0.0``), and every use of a sorted entry in :func:`_capped_simplex` ends
    in a clip to ``[0, upper]``, which maps both zeros to ``+0.0``."""
    for i in range(1, a.shape[0]):
        v = a[i]
        j = i - 1
        while j >= 0 and a[j] > v:
            a[j + 1] = a[j]
            j -= 1
        a[j + 1] = v


@_jit
def _capped_simplex(y, upper, total, out, kinks):
    """Projection of ``y >= 0`` (n,) onto ``{0 <= x_i <= upper_i, sum x_i <= total}`` into
    ``out``: ``model._project_capped_simplex`` for one row (``upper`` (n,): each battery's
    bound; ``kinks``: a work array of ``2 n`` entries)."""
    n = y.shape[0]
    s = 0.0
    for i in range(n):
        out[i] = _np_min(y[i], upper[i])
        s = out[i] if i == 0 else s + out[i]
    if not s > total:
        return
    for i in range(n):
        kinks[i] = y[i] - upper[i]
        kinks[n + i] = y[i]
    _sort_small(kinks)
    j = 0
    g_prev, g_here = 0.0, 0.0
    for k in range(2 * n):
        g = 0.0
        for i in range(n):
            v = _np_clip(y[i] - kinks[k], 0.0, upper[i])
            g = v if i == 0 else g + v
        if g <= total:
            j = k
            g_here = g
            break
        g_prev = g
    if j == 0:  # numpy's argmax of an all-False row is 0; then index 1 is used
        j = 1
        g_prev = 0.0
        for i in range(n):
            v = _np_clip(y[i] - kinks[0], 0.0, upper[i])
            g_prev = v if i == 0 else g_prev + v
        g_here = 0.0
        for i in range(n):
            v = _np_clip(y[i] - kinks[1], 0.0, upper[i])
            g_here = v if i == 0 else g_here + v
    t0, t1 = kinks[j - 1], kinks[j]
    tau = t0 + (g_prev - total) * (t1 - t0) / (g_prev - g_here)
    for i in range(n):
        out[i] = _np_clip(y[i] - tau, 0.0, upper[i])


@_jit
def _project(a, upper, total, out, buy, sell, pb, ps, kinks):
    """``model.project_action`` of one row ``a`` into ``out`` (work arrays buy .. ps, and
    ``kinks`` of ``2 n`` entries)."""
    n = a.shape[0]
    for i in range(n):
        buy[i] = _np_max(a[i], 0.0)
        sell[i] = _np_max(-a[i], 0.0)
    _capped_simplex(buy, upper, total, pb, kinks)
    _capped_simplex(sell, upper, total, ps, kinks)
    for i in range(n):
        out[i] = pb[i] - ps[i]


@_jit
def _largest_step(c, d, total, kinks, ts):
    """``closed_loop._largest_step`` of one row: the largest ``t`` in [0, 1] with
    ``sum_i max(c_i + t d_i, 0) <= total`` (``c`` within the limit)."""
    n = c.shape[0]
    for i in range(n):
        k = -c[i] / d[i] if d[i] != 0.0 else 1.0
        if not np.isfinite(k):
            k = 1.0
        kinks[i] = _np_clip(k, 0.0, 1.0)
    ts[0] = 0.0
    for i in range(n):
        ts[1 + i] = kinks[i]
    ts[n + 1] = 1.0
    _sort_small(ts)
    f_prev = 0.0
    for j in range(n + 2):
        f = 0.0
        for i in range(n):
            v = _np_max(c[i] + ts[j] * d[i], 0.0)
            f = v if i == 0 else f + v
        if f > total:
            if j == 0:  # f(0) > total (rounding): numpy's index 1, then t = t0
                return ts[0]
            t0, t1, f0, f1 = ts[j - 1], ts[j], f_prev, f
            if f0 > total:
                return t0
            slope = f1 - f0 if f1 > f0 else 1.0
            return _np_clip(t0 + (total - f0) * (t1 - t0) / slope, 0.0, 1.0)
        f_prev = f
    return 1.0


@_jit
def _radial(base, e, upper, total, out, neg_base, neg_e, kinks, ts):
    """``closed_loop._radial`` of one row: ``min(1, t*) e`` into ``out``."""
    n = base.shape[0]
    t = np.inf
    for i in range(n):
        room = _np_max(upper[i] - abs(base[i]), 0.0)
        q = room / abs(e[i]) if e[i] != 0.0 else np.inf
        t = q if i == 0 else _np_min(t, q)
        neg_base[i] = -base[i]
        neg_e[i] = -e[i]
    g = _largest_step(base, e, total, kinks, ts)
    g = _np_min(g, _largest_step(base, neg_e, total, kinks, ts))
    g = _np_min(g, _largest_step(neg_base, e, total, kinks, ts))
    g = _np_min(g, _largest_step(neg_base, neg_e, total, kinks, ts))
    t = _np_min(_np_min(t, g), 1.0)
    for i in range(n):
        out[i] = t * e[i]


@_jit
def _along_grid_faces(base, e, total, out):
    """``closed_loop._along_grid_faces`` of one row into ``out``."""
    n = base.shape[0]
    r = 0.0
    for i in range(n):
        r = abs(e[i]) if i == 0 else _np_max(r, abs(e[i]))
        out[i] = e[i]
    pinned = False
    for sign in (1.0, -1.0):
        s = 0.0
        for i in range(n):
            v = _np_max(sign * base[i], 0.0)
            s = v if i == 0 else s + v
        reach = total - s < r
        pinned = pinned or reach
        count = 0
        total_e = 0.0
        for i in range(n):
            member = reach and sign * base[i] > r
            v = out[i] if member else 0.0
            total_e = v if i == 0 else total_e + v
            if member:
                count += 1
        mean = total_e / max(count, 1)
        for i in range(n):
            if reach and sign * base[i] > r:
                out[i] = out[i] - mean
    for i in range(n):
        if pinned and abs(base[i]) <= r:
            out[i] = 0.0


@_jit
def project_rows(a, upper, total):
    """:func:`mpcrl_lite.system.battery.project_action` of every row of ``a`` (days, n);
    ``upper`` (n,) holds each battery's input bound."""
    days, n = a.shape
    out = np.empty((days, n))
    buy, sell, pb, ps = np.empty(n), np.empty(n), np.empty(n), np.empty(n)
    simplex = np.empty(2 * n)
    for d in range(days):
        _project(a[d], upper, total, out[d], buy, sell, pb, ps, simplex)
    return out


@_jit
def explore_rows(pi, e, upper, total, symmetric):
    """The commanded action for the policy's ``pi`` and the exploration ``e`` (days, n):
    :func:`mpcrl_lite.sim.exploration.bounded_exploration` with ``bounds='symmetric'`` (when
    ``symmetric``) or ``'radial'``; ``upper`` (n,) holds each battery's input bound."""
    days, n = pi.shape
    out = np.empty((days, n))
    base, step, along, clipped = np.empty(n), np.empty(n), np.empty(n), np.empty(n)
    other, work, neg_base, neg_e = np.empty(n), np.empty(n), np.empty(n), np.empty(n)
    buy, sell, pb, ps = np.empty(n), np.empty(n), np.empty(n), np.empty(n)
    kinks, ts, simplex = np.empty(n), np.empty(n + 2), np.empty(2 * n)
    for d in range(days):
        _project(pi[d], upper, total, base, buy, sell, pb, ps, simplex)
        _radial(base, e[d], upper, total, step, neg_base, neg_e, kinks, ts)
        if symmetric:
            _along_grid_faces(base, e[d], total, along)
            for i in range(n):
                room = _np_max(upper[i] - abs(base[i]), 0.0)
                clipped[i] = _np_clip(along[i], -room, room)
            _radial(base, clipped, upper, total, other, neg_base, neg_e, kinks, ts)
            s_step, s_other = 0.0, 0.0
            for i in range(n):
                v, w = step[i] * step[i], other[i] * other[i]
                s_step = v if i == 0 else s_step + v
                s_other = w if i == 0 else s_other + w
            if s_other > s_step:
                for i in range(n):
                    step[i] = other[i]
        for i in range(n):
            work[i] = base[i] + step[i]  # a guard against rounding only, as in numpy
        _project(work, upper, total, out[d], buy, sell, pb, ps, simplex)
    return out


def warm_up() -> None:
    """Run both functions on a tiny input: compiles them or loads them from the cache."""
    a = np.array([[0.4, -0.2, 0.9]])
    upper = np.ones(3)
    project_rows(a, upper, 1.0)
    for symmetric in (False, True):
        explore_rows(a, 0.1 * a, upper, 1.0, symmetric)


def ensure_compiled() -> None:
    """Load both functions from the cache or compile them (logging one line if it compiles)."""
    jit.ensure_compiled((explore_rows, project_rows), warm_up, "the exploration kernel")
