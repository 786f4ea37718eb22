r"""The closed loop of :func:`mpcrl_lite.sim.closed_loop.simulate` for an MPC policy, compiled.

A learning month is 24 hours of one solver call, one sensitivity call, the exploration and
the battery step for every day at once. Once the solver was compiled
(:mod:`mpcrl_lite.mpc.backends.kernel_core`), the numpy and Python around those calls were
about a third of a month's time (a month of the paper's run took 30 ms, 20 ms compiled:
``benchmarks/README.md``, "A month in one compiled call"). :func:`month_rows` runs the whole month of a block of days
in one compiled call: for each hour the MPC parameters of each day, the warm start, the
solve, the planned grid power, the sensitivities and their verdict, the exploration
(:func:`mpcrl_lite.sim.exploration_kernel.explore_rows`) and the step of the true system
(:func:`mpcrl_lite.system.battery.step`). The days of a month never meet (each has its own
state; the noise and the exploration are drawn beforehand, in the order the Python loop
draws them), so :func:`month_parallel` gives blocks of days to numba's threads with no
meeting point between the hours.

Every number is computed with the operations of the Python loop in its order: numpy's
``maximum``, ``minimum`` and ``clip`` (:mod:`~mpcrl_lite.sim.exploration_kernel`), its sums
over the few batteries from the first entry on, the kernels' own solves. The record is the
Python loop's to the last bit (``tests/sim/test_compiled_month.py``); the Python loop stays the
reference and the path of everything this one does not cover
(:mod:`mpcrl_lite.sim.compiled_month` says what).

This file is a template: :mod:`mpcrl_lite.sim.compiled_month` writes a copy of it for each
kernel module (the generic kernels, or a copy with fixed sizes from
:mod:`mpcrl_lite.mpc.backends.kernel_sizes`), with the import of the kernels below pointing at
that module, named by a hash of the texts it is made of, so that numba's cache of a copy
never holds code of other kernels.
"""

from __future__ import annotations

from numba import prange

from .._util.jit import njit_cached
from ..mpc.backends.kernel_core import CONVERGED, SENS_OK, sensitivity_rows, solve_rows  # KERNELS
from .exploration_kernel import _np_clip, _np_max, _np_min, explore_rows

_nogil = njit_cached(error_model="numpy", nogil=True)
_parallel = njit_cached(error_model="numpy", nogil=True, parallel=True)

__all__ = ["month_parallel", "month_rows"]


@_nogil
def month_rows(theta, wbuy, wsell, buy, sell, e, noise, opts, ubar, stagew, n, N,
               method, structured, warm_start, sensitivities, explore, symmetric, upper,
               P_bar, cond_max, back_max, alpha, penalty, soc_low, soc_high, ib, is_,
               P, x, lam, mu, xw, cold, cost, iters, status, action, grad, dsoc, cond, back,
               code, solved, socs, policy, a_out, b_out, s_out, corr, agent_cost, stage_cost,
               grid, planned, solver_ok, sens_ok, grad_pi, statuses, keep, xs, lams, mus,
               Ps, costs, iterss, d_lo, d_hi):
    """The month of the days ``d_lo <= d < d_hi`` (see the module docstring).

    Inputs: ``theta`` (D, n_theta) each day's parameters, ``wbuy``,
    ``wsell`` (H, D, N) the MPC's price windows, ``buy``, ``sell`` (D, H) the true prices,
    ``e`` (H, D, n) the exploration drawn (times its std; read when ``explore``), ``noise``
    (H, D, n); the solver's ``opts, ubar, stagew, n, N, method, structured``; the system's
    ``alpha``, ``penalty`` (n,) and the soc band; ``ib``, ``is_`` (N, n) the positions of
    ``b`` and ``s`` in ``x``. Work arrays (D, ...): ``P, x, lam, mu, xw`` (the warm start),
    ``cold`` (1, nx) zeros, ``cost, iters, status, action, grad, dsoc, cond, back, code,
    solved``. Outputs: the record's arrays, hour first (``socs[0]``, the days' start, is an
    input), and ``statuses`` (H, D) the solver's
    status codes; with ``keep``, every hour's solutions too: ``xs, lams, mus, Ps`` (H, D, ...)
    and ``costs, iterss`` (H, D) (else those arrays are not touched)."""
    H = e.shape[0]
    nx = x.shape[1]
    stage = 5 * n
    for k in range(H):
        for d in range(d_lo, d_hi):
            for i in range(n):
                P[d, i] = socs[k, d, i]
            for j in range(N):
                P[d, n + j] = wbuy[k, d, j]
                P[d, n + N + j] = wsell[k, d, j]
            for j in range(theta.shape[1]):
                P[d, n + 2 * N + j] = theta[d, j]
        # the previous hour's solutions shifted by one stage (a failed row keeps the guess
        # it was given), as MPCPolicy.decide with MPC.shift
        warm = warm_start and k > 0
        if k > 0:
            for d in range(d_lo, d_hi):
                # the solution kept from the previous hour: its own, or the guess it was given
                kept = x[d] if status[d] == CONVERGED or k == 1 else xw[d]
                for j in range(nx - stage):
                    xw[d, j] = kept[j + stage]
                for j in range(nx - stage, nx):
                    xw[d, j] = kept[j]
        solve_rows(P, xw if warm else cold, warm, opts, ubar, stagew, n, N, method, x, lam,
                   mu, cost, iters, status, action, d_lo, d_hi)
        for d in range(d_lo, d_hi):
            ok = status[d] == CONVERGED
            solved[d] = ok
            solver_ok[k, d] = ok
            statuses[k, d] = status[d]
            top = 0.0
            for j in range(N):
                bought = x[d, ib[j, 0]]
                sold = x[d, is_[j, 0]]
                for i in range(1, n):
                    bought = bought + x[d, ib[j, i]]
                    sold = sold + x[d, is_[j, i]]
                side = _np_max(bought, sold)
                top = side if j == 0 else _np_max(top, side)
            planned[k, d] = top
            if keep:
                xs[k, d, :] = x[d, :]
                lams[k, d, :] = lam[d, :]
                mus[k, d, :] = mu[d, :]
                Ps[k, d, :] = P[d, :]
                costs[k, d] = cost[d]
                iterss[k, d] = iters[d]
        if sensitivities:
            sensitivity_rows(P, x, lam, mu, solved, opts, ubar, stagew, n, N, method,
                             structured, grad, dsoc, cond, back, code, d_lo, d_hi)
            for d in range(d_lo, d_hi):
                formed = code[d] == SENS_OK
                ill = formed and (back[d] > back_max or cond[d] > cond_max)
                sens_ok[k, d] = formed and not ill
                for t in range(grad.shape[1]):
                    for i in range(n):
                        grad_pi[k, d, t, i] = 0.0 if ill else grad[d, t, i]
        else:
            for d in range(d_lo, d_hi):
                sens_ok[k, d] = False
        if explore:
            commanded = explore_rows(action[d_lo:d_hi], e[k, d_lo:d_hi], upper, P_bar,
                                     symmetric)
        else:
            commanded = action[d_lo:d_hi]
        # the true system's hour (system.battery.step), day by day
        for d in range(d_lo, d_hi):
            total = 0.0
            bought = 0.0
            sold = 0.0
            for i in range(n):
                soc = socs[k, d, i]
                a = commanded[d - d_lo, i]
                delta = noise[k, d, i]
                raw = soc + alpha[i] * (delta + a)
                to_full = (1.0 - soc) / alpha[i] - delta
                to_empty = (0.0 - soc) / alpha[i] - delta
                net = _np_min(a, to_full) if raw > 1.0 else a
                net = _np_max(a, to_empty) if raw < 0.0 else net
                b = _np_max(net, 0.0)
                s = _np_max(-net, 0.0)
                pen = penalty[i] * _np_max(soc - soc_high, 0.0) \
                    + penalty[i] * _np_max(soc_low - soc, 0.0)
                c = buy[d, k] * b - sell[d, k] * s + pen
                policy[k, d, i] = action[d, i]
                a_out[k, d, i] = a
                b_out[k, d, i] = b
                s_out[k, d, i] = s
                corr[k, d, i] = net - a
                agent_cost[k, d, i] = c
                socs[k + 1, d, i] = _np_clip(raw, 0.0, 1.0)
                total = c if i == 0 else total + c
                bought = b if i == 0 else bought + b
                sold = s if i == 0 else sold + s
            stage_cost[k, d] = total
            grid[k, d] = _np_max(bought, sold)


@_parallel
def month_parallel(theta, wbuy, wsell, buy, sell, e, noise, opts, ubar, stagew, n, N,
                   method, structured, warm_start, sensitivities, explore, symmetric, upper,
                   P_bar, cond_max, back_max, alpha, penalty, soc_low, soc_high, ib, is_,
                   P, x, lam, mu, xw, cold, cost, iters, status, action, grad, dsoc, cond,
                   back, code, solved, socs, policy, a_out, b_out, s_out, corr, agent_cost,
                   stage_cost, grid, planned, solver_ok, sens_ok, grad_pi, statuses, keep, xs,
                   lams, mus, Ps, costs, iterss, block):
    """:func:`month_rows` on blocks of ``block`` days spread over numba's threads; each
    day's month is computed alone, so the results do not depend on the blocks."""
    days = socs.shape[1]
    blocks = (days + block - 1) // block
    for b in prange(blocks):
        lo = b * block
        month_rows(theta, wbuy, wsell, buy, sell, e, noise, opts, ubar, stagew, n, N,
                   method, structured, warm_start, sensitivities, explore, symmetric, upper,
                   P_bar, cond_max, back_max, alpha, penalty, soc_low, soc_high, ib, is_,
                   P, x, lam, mu, xw, cold, cost, iters, status, action, grad, dsoc, cond,
                   back, code, solved, socs, policy, a_out, b_out, s_out, corr, agent_cost,
                   stage_cost, grid, planned, solver_ok, sens_ok, grad_pi, statuses, keep, xs,
                   lams, mus, Ps, costs, iterss, lo, min(lo + block, days))
