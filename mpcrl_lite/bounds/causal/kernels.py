r"""Compiled inner loops of the causal dynamic program (:mod:`mpcrl_lite.bounds.causal.dp`).

Notation as in :mod:`mpcrl_lite.bounds.causal.dp`: ``G`` soc nodes per battery, action steps ``m`` in
``[-M, M]`` (index ``t = m + M``), at most ``B`` steps summed over the batteries on each side
of the grid limit, post-decision grid of ``Gy`` nodes on which node ``j`` with step ``m``
lands at ``r j + m + M``. ``cost[j, t]`` is one battery's expected economic stage cost and
``ev`` the post-decision values ``E[V_{k+1}]``.

* :func:`bellman_min3` -- the Bellman minimisation of three batteries at every multiset state
  ``j_1 <= j_2 <= j_3``, in two stages: for every post-decision pair ``(p_1, p_2)`` and last
  node ``j_3``, the running minima over the third battery's steps ``[-k, 0]`` and ``[0, k]``
  (``k = 0..M``), then for each state the minimum over the first two batteries' steps of
  their costs plus the tabulated minimum over the range the grid limit leaves to the third.
  Each ``p_1`` plane is tabulated once, in a ring of ``2M + 1`` planes, and both stages run
  vectorised over ``j_3``. About 7 times fewer operations than enumerating joint actions.
* :func:`bellman_min` -- the same for any ``n`` by plain enumeration (used for ``n != 3``).
* :func:`greedy3`, :func:`greedy_actions` -- the minimisation at arbitrary states of charge
  (the simulated policy), with ``ev`` interpolated multilinearly.
* :func:`expected_cost_rows` -- the closed-form expected economic cost at arbitrary states.
* :func:`bellman_min3_mixed`, :func:`bellman_min_mixed`, :func:`greedy_mixed` -- the same for
  batteries that differ (:mod:`mpcrl_lite.bounds.causal.mixed`): every battery its own
  post-decision grid, the states the full product grid.

All compiled with ``numba.njit(cache=True)`` (the first call on a machine compiles, a few
seconds; later sessions load the cache).
"""

from __future__ import annotations

import math

import numpy as np

from ..._util.jit import njit_cached

__all__ = [
    "bellman_min",
    "bellman_min3",
    "bellman_min3_mixed",
    "bellman_min_mixed",
    "expected_cost_rows",
    "greedy3",
    "greedy_actions",
    "greedy_mixed",
]

_INV_SQRT_2PI = 1.0 / math.sqrt(2.0 * math.pi)
_INV_SQRT_2 = 1.0 / math.sqrt(2.0)


@njit_cached(fastmath=True)
def bellman_min3(
    G: int, r: int, M: int, B: int, cost: np.ndarray, pen: np.ndarray, ev: np.ndarray,
    gamma: float, ring_lo: np.ndarray, ring_hi: np.ndarray,
) -> np.ndarray:
    """``V`` at the multiset states of three batteries (lexicographic order of
    ``itertools.combinations_with_replacement(range(G), 3)``).

    ``V[j] = sum_i pen[j_i] + min_m sum_i cost[j_i, m_i + M] + gamma ev[r j + m + M]`` over
    ``|m_i| <= M``, ``sum m_i^+ <= B``, ``sum m_i^- <= B``; ``ev`` has shape ``(Gy,) * 3``.
    ``ring_lo``, ``ring_hi`` are work arrays of shape ``(2M + 1, Gy, M + 1, G)`` (passed in so
    that their 20 MB are not allocated, and page-faulted, at every hour):
    ``ring[slot, p2, k, j3]`` is the minimum over the third battery's steps in ``[-k, 0]``
    (lo) or ``[0, k]`` (hi) for the first post-decision index held in ``slot``.
    """
    Gy = ev.shape[0]
    K = 2 * M + 1
    out = np.empty(G * (G + 1) * (G + 2) // 6)
    cost_t = np.ascontiguousarray(cost.T)
    plane = np.full(K, -1, dtype=np.int64)
    acc_lo = np.empty(G)
    acc_hi = np.empty(G)
    best = np.empty(G)
    idx = 0
    for j1 in range(G):
        for u in range(K):
            p1 = r * j1 + u
            slot = p1 % K
            if plane[slot] == p1:
                continue  # tabulated for an earlier j1, on a superset of the ranges needed now
            plane[slot] = p1
            for p2 in range(r * j1, Gy):
                row = ev[p1, p2]
                for j3 in range(j1, G):
                    v = cost_t[M, j3] + gamma * row[r * j3 + M]
                    acc_lo[j3] = v
                    acc_hi[j3] = v
                    ring_lo[slot, p2, 0, j3] = v
                    ring_hi[slot, p2, 0, j3] = v
                for k in range(1, M + 1):
                    for j3 in range(j1, G):
                        acc_lo[j3] = min(acc_lo[j3],
                                         cost_t[M - k, j3] + gamma * row[r * j3 + M - k])
                        ring_lo[slot, p2, k, j3] = acc_lo[j3]
                        acc_hi[j3] = min(acc_hi[j3],
                                         cost_t[M + k, j3] + gamma * row[r * j3 + M + k])
                        ring_hi[slot, p2, k, j3] = acc_hi[j3]
        for j2 in range(j1, G):
            for j3 in range(j2, G):
                best[j3] = np.inf
            for m1 in range(-M, M + 1):
                slot = (r * j1 + m1 + M) % K
                c1 = cost[j1, m1 + M]
                up1 = max(m1, 0)
                dn1 = max(-m1, 0)
                for m2 in range(-M, M + 1):
                    up = up1 + max(m2, 0)
                    dn = dn1 + max(-m2, 0)
                    if up > B or dn > B:
                        continue
                    p2 = r * j2 + m2 + M
                    c12 = c1 + cost[j2, m2 + M]
                    lo_row = ring_lo[slot, p2, min(M, B - dn)]
                    hi_row = ring_hi[slot, p2, min(M, B - up)]
                    for j3 in range(j2, G):
                        best[j3] = min(best[j3], c12 + min(lo_row[j3], hi_row[j3]))
            fixed = pen[j1] + pen[j2]
            for j3 in range(j2, G):
                out[idx] = fixed + pen[j3] + best[j3]
                idx += 1
    return out


@njit_cached()
def bellman_min(
    states: np.ndarray, prefixes: np.ndarray, lo: np.ndarray, hi: np.ndarray,
    cost: np.ndarray, pen: np.ndarray, ev: np.ndarray, strides: np.ndarray, r: int, M: int,
    gamma: float,
) -> np.ndarray:
    """As :func:`bellman_min3` for any ``n``, by enumerating the joint actions.

    Parameters
    ----------
    states : int64 array, shape ``(S, n)``
        Node indices of each state.
    prefixes : int64 array, shape ``(P, n - 1)``
        Steps ``m_1 .. m_{n-1}`` of every prefix within the grid limit.
    lo, hi : int64 arrays, shape ``(P,)``
        Range of the last battery's step given the prefix.
    cost : float64 array, shape ``(G, 2M + 1)``
    pen : float64 array, shape ``(G,)``
    ev : float64 array, shape ``(Gy**n,)`` (C order)
    strides : int64 array, shape ``(n,)``
        Element strides of ``ev`` as an ``n``-dimensional array.
    """
    S, n = states.shape
    P = prefixes.shape[0]
    out = np.empty(S)
    last = n - 1
    for s in range(S):
        base = 0
        fixed = 0.0
        for i in range(n):
            j = states[s, i]
            base += (r * j + M) * strides[i]
            fixed += pen[j]
        jl = states[s, last]
        best = np.inf
        for p in range(P):
            partial = 0.0
            off = base
            for i in range(last):
                m = prefixes[p, i]
                partial += cost[states[s, i], m + M]
                off += m * strides[i]
            for m in range(lo[p], hi[p] + 1):
                best = min(best, partial + cost[jl, m + M] + gamma * ev[off + m * strides[last]])
        out[s] = fixed + best
    return out


@njit_cached()
def _base(x: float, inv_hy: float, top: int) -> tuple[int, float]:
    """Post-grid cell of soc ``x`` (clamped so that its upper corner exists) and the fraction."""
    t = x * inv_hy
    b = math.floor(t)
    b = min(max(b, 0), top)
    return b, t - b


@njit_cached(fastmath=True)
def greedy3(
    soc: np.ndarray, cost: np.ndarray, ev: np.ndarray, inv_hy: float, top: int, M: int, B: int,
    gamma: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Best joint step of three batteries at arbitrary states.

    ``argmin_m sum_i cost[row, i, m_i + M] + gamma EV(soc + h_y m)`` with ``EV`` the
    trilinear interpolant of ``ev`` (shape ``(Gy,) * 3``). The post-decision coordinate of
    battery ``i`` is ``soc_i / h_y + m_i + M``: its fraction does not depend on ``m_i``, so
    the ``(2M + 1)^3`` interpolated values of a row are three two-tap filters of one block.

    Returns
    -------
    steps : int64 array, shape ``(R, 3)``
        Minimising steps (ties: the first in lexicographic order).
    value : float64 array, shape ``(R,)``
        The minimum (the penalty of the current state not included).
    """
    R = soc.shape[0]
    K = 2 * M + 1
    steps = np.zeros((R, 3), dtype=np.int64)
    value = np.empty(R)
    t1 = np.empty((K + 1, K + 1, K))
    t2 = np.empty((K + 1, K, K))
    et = np.empty((K, K, K))
    for row in range(R):
        b0, w0 = _base(soc[row, 0], inv_hy, top)
        b1, w1 = _base(soc[row, 1], inv_hy, top)
        b2, w2 = _base(soc[row, 2], inv_hy, top)
        # interpolate along the last axis, then the middle, then the first, on contiguous rows
        for a in range(K + 1):
            for b in range(K + 1):
                src = ev[b0 + a, b1 + b, b2:b2 + K + 1]
                dst = t1[a, b]
                for c in range(K):
                    dst[c] = (1.0 - w2) * src[c] + w2 * src[c + 1]
        for a in range(K + 1):
            for b in range(K):
                lo_row = t1[a, b]
                hi_row = t1[a, b + 1]
                dst = t2[a, b]
                for c in range(K):
                    dst[c] = (1.0 - w1) * lo_row[c] + w1 * hi_row[c]
        c2 = cost[row, 2]
        for a in range(K):
            for b in range(K):
                lo_row = t2[a, b]
                hi_row = t2[a + 1, b]
                dst = et[a, b]
                for c in range(K):
                    dst[c] = c2[c] + gamma * ((1.0 - w0) * lo_row[c] + w0 * hi_row[c])
        best = np.inf
        best1 = 0
        best2 = 0
        best3 = 0
        for u1 in range(K):
            m1 = u1 - M
            c1 = cost[row, 0, u1]
            for u2 in range(K):
                m2 = u2 - M
                up = max(m1, 0) + max(m2, 0)
                dn = max(-m1, 0) + max(-m2, 0)
                if up > B or dn > B:
                    continue
                lo = M - min(M, B - dn)
                hi = M + min(M, B - up)
                # a branch-free minimum first; the argument only when it improves
                local = np.inf
                for u3 in range(lo, hi + 1):
                    local = min(local, et[u1, u2, u3])
                val = c1 + cost[row, 1, u2] + local
                if val < best:
                    best = val
                    best1 = m1
                    best2 = m2
                    for u3 in range(lo, hi + 1):
                        if et[u1, u2, u3] == local:
                            best3 = u3 - M
                            break
        steps[row, 0] = best1
        steps[row, 1] = best2
        steps[row, 2] = best3
        value[row] = best
    return steps, value


@njit_cached()
def greedy_actions(
    soc: np.ndarray, cost: np.ndarray, prefixes: np.ndarray, lo: np.ndarray, hi: np.ndarray,
    ev: np.ndarray, strides: np.ndarray, inv_hy: float, top: int, M: int, gamma: float,
) -> tuple[np.ndarray, np.ndarray]:
    """As :func:`greedy3` for any ``n`` (``2^n`` interpolation corners per joint action).

    ``prefixes``, ``lo``, ``hi`` and ``strides`` as in :func:`bellman_min`; ``ev`` flat.
    """
    R, n = soc.shape
    P = prefixes.shape[0]
    last = n - 1
    ncorner = 1 << n
    steps = np.zeros((R, n), dtype=np.int64)
    value = np.empty(R)
    cw = np.empty(ncorner)
    co = np.empty(ncorner, dtype=np.int64)
    frac = np.empty(n)
    for row in range(R):
        base = 0
        for i in range(n):
            b, frac[i] = _base(soc[row, i], inv_hy, top)
            base += (b + M) * strides[i]
        for c in range(ncorner):
            w = 1.0
            o = 0
            for i in range(n):
                if (c >> i) & 1:
                    w *= frac[i]
                    o += strides[i]
                else:
                    w *= 1.0 - frac[i]
            cw[c] = w
            co[c] = o
        best = np.inf
        best_p = 0
        best_m = 0
        for p in range(P):
            partial = 0.0
            off = base
            for i in range(last):
                m = prefixes[p, i]
                partial += cost[row, i, m + M]
                off += m * strides[i]
            for m in range(lo[p], hi[p] + 1):
                flat = off + m * strides[last]
                e = 0.0
                for c in range(ncorner):
                    e += cw[c] * ev[flat + co[c]]
                val = partial + cost[row, last, m + M] + gamma * e
                if val < best:
                    best = val
                    best_p = p
                    best_m = m
        for i in range(last):
            steps[row, i] = prefixes[best_p, i]
        steps[row, last] = best_m
        value[row] = best
    return steps, value


@njit_cached()
def _hinge(m: float, s: float, c: float) -> tuple[float, float]:
    """``E[(z - c)^+]``, ``E[(c - z)^+]`` for ``z ~ N(m, s^2)``."""
    if s == 0.0:
        return max(m - c, 0.0), max(c - m, 0.0)
    d = (m - c) / s
    tail = s * _INV_SQRT_2PI * math.exp(-0.5 * d * d)
    return (tail + (m - c) * 0.5 * math.erfc(-d * _INV_SQRT_2),
            tail + (c - m) * 0.5 * math.erfc(d * _INV_SQRT_2))


@njit_cached()
def expected_cost_rows(
    soc: np.ndarray, buy: np.ndarray, sell: np.ndarray, actions: np.ndarray, alpha: float,
    mean: float, std: float,
) -> np.ndarray:
    """``phi_s E[net] + (phi_b - phi_s) E[net^+]`` for every row, battery and action.

    The same closed form as :func:`mpcrl_lite.bounds.causal.dp.expected_net_power`.

    Parameters
    ----------
    soc : float64 array, shape ``(R, n)``
    buy, sell : float64 arrays, shape ``(R,)``
    actions : float64 array, shape ``(K,)``

    Returns
    -------
    float64 array, shape ``(R, n, K)``
    """
    R, n = soc.shape
    K = actions.size
    out = np.empty((R, n, K))
    sz = alpha * std
    for row in range(R):
        for i in range(n):
            for t in range(K):
                a = actions[t]
                mz = soc[row, i] + alpha * (a + mean)
                below0 = _hinge(mz, sz, 0.0)[1]
                above1 = _hinge(mz, sz, 1.0)[0]
                e_net = a + (below0 - above1) / alpha
                if a >= 0.0:
                    e_plus = e_net + _hinge(mz, sz, 1.0 + alpha * a)[0] / alpha
                else:
                    e_plus = _hinge(mz, sz, alpha * a)[1] / alpha
                out[row, i, t] = sell[row] * e_net + (buy[row] - sell[row]) * e_plus
    return out


# -- batteries that differ (mpcrl_lite.bounds.causal.mixed) ------------------------------------
# Battery i has its own post-decision grid: node j with step m lands at r[i] j + m + M[i];
# ``cost`` has shape (n, G, 2 Mx + 1) with step m of battery i at column m + Mx
# (Mx = max M[i]); ``pen`` has shape (n, G). The states are the full product grid in C order.


@njit_cached(fastmath=True)
def bellman_min3_mixed(
    G: int, r: np.ndarray, M: np.ndarray, Mx: int, B: int, cost: np.ndarray, pen: np.ndarray,
    ev: np.ndarray, gamma: float, ring_lo: np.ndarray, ring_hi: np.ndarray,
) -> np.ndarray:
    """:func:`bellman_min3` for three batteries that differ, at every state of the product grid.

    ``V[j1, j2, j3] = sum_i pen[i, j_i] + min_m sum_i cost[i, j_i, m_i + Mx]
    + gamma ev[r_1 j_1 + m_1 + M_1, ..]`` over ``|m_i| <= M_i`` and the grid limit ``B``;
    ``ev`` has shape ``(Gy_1, Gy_2, Gy_3)``. The same two stages as :func:`bellman_min3`
    (running minima over the third battery's steps per post-decision pair, a ring of
    ``2 M_1 + 1`` planes of the first battery), over the full ranges of ``j_2`` and ``j_3``.
    ``ring_lo``, ``ring_hi``: work arrays of shape ``(2 M_1 + 1, Gy_2, M_3 + 1, G)``.

    Returns
    -------
    float64 array, shape ``(G ** 3,)``
    """
    Gy2 = ev.shape[1]
    r1, r2, r3 = r[0], r[1], r[2]
    M1, M2, M3 = M[0], M[1], M[2]
    K1 = 2 * M1 + 1
    out = np.empty(G * G * G)
    c3 = np.ascontiguousarray(cost[2].T)  # (2 Mx + 1, G)
    plane = np.full(K1, -1, dtype=np.int64)
    acc_lo = np.empty(G)
    acc_hi = np.empty(G)
    best = np.empty(G)
    idx = 0
    for j1 in range(G):
        for u in range(K1):
            p1 = r1 * j1 + u
            slot = p1 % K1
            if plane[slot] == p1:
                continue  # tabulated for the previous j1 (the ranges are always full)
            plane[slot] = p1
            for p2 in range(Gy2):
                row = ev[p1, p2]
                for j3 in range(G):
                    v = c3[Mx, j3] + gamma * row[r3 * j3 + M3]
                    acc_lo[j3] = v
                    acc_hi[j3] = v
                    ring_lo[slot, p2, 0, j3] = v
                    ring_hi[slot, p2, 0, j3] = v
                for k in range(1, M3 + 1):
                    for j3 in range(G):
                        acc_lo[j3] = min(acc_lo[j3],
                                         c3[Mx - k, j3] + gamma * row[r3 * j3 + M3 - k])
                        ring_lo[slot, p2, k, j3] = acc_lo[j3]
                        acc_hi[j3] = min(acc_hi[j3],
                                         c3[Mx + k, j3] + gamma * row[r3 * j3 + M3 + k])
                        ring_hi[slot, p2, k, j3] = acc_hi[j3]
        for j2 in range(G):
            for j3 in range(G):
                best[j3] = np.inf
            for m1 in range(-M1, M1 + 1):
                slot = (r1 * j1 + m1 + M1) % K1
                c1 = cost[0, j1, m1 + Mx]
                up1 = max(m1, 0)
                dn1 = max(-m1, 0)
                for m2 in range(-M2, M2 + 1):
                    up = up1 + max(m2, 0)
                    dn = dn1 + max(-m2, 0)
                    if up > B or dn > B:
                        continue
                    p2 = r2 * j2 + m2 + M2
                    c12 = c1 + cost[1, j2, m2 + Mx]
                    lo_row = ring_lo[slot, p2, min(M3, B - dn)]
                    hi_row = ring_hi[slot, p2, min(M3, B - up)]
                    for j3 in range(G):
                        best[j3] = min(best[j3], c12 + min(lo_row[j3], hi_row[j3]))
            fixed = pen[0, j1] + pen[1, j2]
            for j3 in range(G):
                out[idx] = fixed + pen[2, j3] + best[j3]
                idx += 1
    return out


@njit_cached()
def bellman_min_mixed(
    states: np.ndarray, prefixes: np.ndarray, lo: np.ndarray, hi: np.ndarray,
    cost: np.ndarray, pen: np.ndarray, ev: np.ndarray, strides: np.ndarray, r: np.ndarray,
    M: np.ndarray, Mx: int, gamma: float,
) -> np.ndarray:
    """:func:`bellman_min` for batteries that differ (any ``n``), by enumeration.

    ``states`` ``(S, n)``, ``prefixes``, ``lo``, ``hi`` and ``strides`` as in
    :func:`bellman_min` (the prefixes keep each battery's own ``|m_i| <= M_i``); ``ev`` flat.
    """
    S, n = states.shape
    P = prefixes.shape[0]
    out = np.empty(S)
    last = n - 1
    for s in range(S):
        base = 0
        fixed = 0.0
        for i in range(n):
            j = states[s, i]
            base += (r[i] * j + M[i]) * strides[i]
            fixed += pen[i, j]
        jl = states[s, last]
        best = np.inf
        for p in range(P):
            partial = 0.0
            off = base
            for i in range(last):
                m = prefixes[p, i]
                partial += cost[i, states[s, i], m + Mx]
                off += m * strides[i]
            for m in range(lo[p], hi[p] + 1):
                best = min(best, partial + cost[last, jl, m + Mx]
                           + gamma * ev[off + m * strides[last]])
        out[s] = fixed + best
    return out


@njit_cached()
def greedy_mixed(
    soc: np.ndarray, cost: np.ndarray, prefixes: np.ndarray, lo: np.ndarray, hi: np.ndarray,
    ev: np.ndarray, strides: np.ndarray, inv_hy: np.ndarray, top: np.ndarray, M: np.ndarray,
    Mx: int, gamma: float,
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`greedy_actions` for batteries that differ: battery ``i``'s post-decision
    coordinate is ``soc_i / h_y,i + m_i + M_i`` (``inv_hy``, ``top``, ``M`` per battery);
    ``cost`` ``(R, n, 2 Mx + 1)``."""
    R, n = soc.shape
    P = prefixes.shape[0]
    last = n - 1
    ncorner = 1 << n
    steps = np.zeros((R, n), dtype=np.int64)
    value = np.empty(R)
    cw = np.empty(ncorner)
    co = np.empty(ncorner, dtype=np.int64)
    frac = np.empty(n)
    for row in range(R):
        base = 0
        for i in range(n):
            b, frac[i] = _base(soc[row, i], inv_hy[i], top[i])
            base += (b + M[i]) * strides[i]
        for c in range(ncorner):
            w = 1.0
            o = 0
            for i in range(n):
                if (c >> i) & 1:
                    w *= frac[i]
                    o += strides[i]
                else:
                    w *= 1.0 - frac[i]
            cw[c] = w
            co[c] = o
        best = np.inf
        best_p = 0
        best_m = 0
        for p in range(P):
            partial = 0.0
            off = base
            for i in range(last):
                m = prefixes[p, i]
                partial += cost[row, i, m + Mx]
                off += m * strides[i]
            for m in range(lo[p], hi[p] + 1):
                flat = off + m * strides[last]
                e = 0.0
                for c in range(ncorner):
                    e += cw[c] * ev[flat + co[c]]
                val = partial + cost[row, last, m + Mx] + gamma * e
                if val < best:
                    best = val
                    best_p = p
                    best_m = m
        for i in range(last):
            steps[row, i] = prefixes[best_p, i]
        steps[row, last] = best_m
        value[row] = best
    return steps, value
