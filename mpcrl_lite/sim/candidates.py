r"""Many thetas at once: K candidates x D days x M noise draws in one closed loop.

A derivative-free search over theta (:mod:`mpcrl_lite.studies.tune`) compares many candidate
parameter vectors on the same noise. :func:`evaluate_candidates` stacks them as the runs of the
lockstep are stacked (:mod:`mpcrl_lite.sim.closed_loop`, "Runs in lockstep"): rows
``(k * M + j) * D + d`` are day ``d`` of draw ``j`` of candidate ``k``, :class:`MPCPolicy` gives
each candidate's block its own theta, and every hour is **one** solver call for all
``K * M * D`` problems. The noise of draw ``j`` is that of
:func:`~mpcrl_lite.sim.closed_loop.evaluate_mpc`'s draw ``j`` (``sample_noise(evaluation_rng(seed,
j), (H, D, n))``) and is the same for every candidate (common random numbers), so differences
between candidates are paired. Every computation of the loop is row by row, so each
candidate's J equals an :func:`~mpcrl_lite.sim.closed_loop.evaluate_mpc` of that candidate alone
(to the rounding of the sums over hours and days), and it does not depend on which other
candidates share the call (the sums are taken row by row), bit for bit.

Draws are named by their index, so a search can select on draws ``0 .. M - 1`` and judge its
result on draws it never saw (e.g. ``M .. M + M' - 1``).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from ..config import MPCConfig, SystemConfig
from ..mpc.backends.registry import make_solver
from ..mpc.formulation import MPC
from ..system.battery import sample_noise
from ..system.forecast import forecast_prices
from ..system.prices import Prices
from ..theta import Theta
from .closed_loop import MPCPolicy, _TiledPrices, evaluation_rng, simulate

__all__ = ["candidate_noise", "check_draws", "evaluate_candidates"]


def check_draws(draws: int | Sequence[int]) -> list[int]:
    """``draws`` as a list of draw indices: an integer ``M >= 1`` is ``0 .. M - 1``; a sequence
    must hold distinct integers >= 0."""
    if isinstance(draws, (int, np.integer)) and not isinstance(draws, bool):
        if draws < 1:
            raise ValueError(f"draws={draws!r}: expected an integer >= 1 or a sequence of draw "
                             "indices")
        return list(range(int(draws)))
    try:
        out = [int(k) for k in draws]
    except (TypeError, ValueError):
        raise ValueError(f"draws={draws!r}: expected an integer >= 1 or a sequence of draw "
                         "indices") from None
    if not out or any(isinstance(k, bool) or k < 0 for k in draws) or len(set(out)) != len(out) \
            or any(int(k) != k for k in draws):
        raise ValueError(f"draws={draws!r}: expected distinct integers >= 0 (at least one)")
    return out


def candidate_noise(system: SystemConfig, days: int, seed: int,
                    draws: int | Sequence[int]) -> np.ndarray:
    """The noise of the draws ``draws`` of ``seed``, stacked draw by draw: ``(H, M * D, n)``,
    draw ``j`` being :func:`~mpcrl_lite.sim.closed_loop.evaluate_mpc`'s draw ``j``."""
    H, n = system.hours_per_day, system.n
    return np.concatenate([sample_noise(evaluation_rng(seed, k), (H, days, n), system)
                           for k in check_draws(draws)], axis=1)


def evaluate_candidates(
    thetas: Sequence[Theta] | np.ndarray,
    system: SystemConfig,
    mpc_config: MPCConfig | None,
    prices: Prices,
    seed: int,
    draws: int | Sequence[int] = 1,
    *,
    solver: Any = None,
    soc0: float | np.ndarray | None = None,
) -> np.ndarray:
    """J of every candidate on every draw, all in one batched closed loop.

    Parameters
    ----------
    thetas
        ``K`` candidates: :class:`~mpcrl_lite.theta.Theta` objects or an array ``(K, n_theta)``
        of theta vectors.
    system
        The true system (and the MPC's model).
    mpc_config
        The MPC's settings (back-end, tau, forecast); default :class:`MPCConfig`. The prices
        the MPC sees follow ``mpc_config.forecast``
        (:func:`~mpcrl_lite.system.forecast.forecast_prices`); the true cost uses the real ones.
    prices
        The month (``D`` days).
    seed, draws
        The noise: draws ``0 .. draws - 1`` of ``seed`` (an integer) or the listed draw indices,
        each a month of noise as in :func:`~mpcrl_lite.sim.closed_loop.evaluate_mpc`, common to all
        candidates.
    solver
        A back-end for this system's MPC (built from ``system`` and ``mpc_config`` when None;
        pass one to evaluate many times without rebuilding it).
    soc0
        Start of day soc (default ``system.soc0``), scalar or (n,).

    Returns
    -------
    numpy.ndarray
        ``J[k, j]``, shape ``(K, M)``: the mean over the days of draw ``j`` of
        :meth:`~mpcrl_lite.sim.record.Record.J_per_day` under candidate ``k``.
    """
    if not isinstance(system, SystemConfig):
        raise ValueError(f"system={system!r}: expected a SystemConfig")  # noqa: TRY004
    mpc_config = mpc_config or MPCConfig()
    if not isinstance(mpc_config, MPCConfig):
        raise ValueError(f"mpc_config={mpc_config!r}: expected an MPCConfig")  # noqa: TRY004
    if not isinstance(prices, Prices):
        raise ValueError(f"prices={prices!r}: expected a Prices")  # noqa: TRY004
    if soc0 is not None and np.ndim(soc0) > 1:
        raise ValueError(f"soc0 has shape {np.shape(soc0)}: expected a scalar or (n,) = "
                         f"({system.n},)")
    thetas = _candidates(thetas, system.n)
    index = check_draws(draws)
    if solver is None:
        solver = make_solver(MPC(system), mpc_config, thetas[0])
    elif solver.mpc.system != system:
        raise ValueError("solver: built for another system; expected one for `system`")
    seen = forecast_prices(prices, mpc_config)
    H, D, K, M = system.hours_per_day, prices.days, len(thetas), len(index)
    noise = np.tile(candidate_noise(system, D, seed, index), (1, K, 1))
    tiled = _TiledPrices(seen, K * M)
    record = simulate(MPCPolicy(solver, thetas, tiled), tiled.buy[:, :H], tiled.sell[:, :H],
                      system, noise=noise, soc0=soc0)
    # J_per_day's discounted sum, hour by hour: every day's J is then the same whatever the
    # number of rows of the call (a matrix-vector product may round differently per width),
    # so a search gives the same candidates however its generations are split
    per_day = np.zeros(K * M * D)
    for k, cost in enumerate(record.stage_cost):
        per_day += system.gamma**k * cost
    return per_day.reshape(K, M, D).mean(axis=2)


def _candidates(thetas: Sequence[Theta] | np.ndarray, n: int) -> list[Theta]:
    if isinstance(thetas, Theta):
        raise ValueError("thetas: expected a sequence of Theta (or an array (K, n_theta)), "  # noqa: TRY004
                         "got one Theta; pass [theta]")
    if isinstance(thetas, np.ndarray):
        arr = np.asarray(thetas, dtype=float)
        if arr.ndim != 2 or arr.shape[0] < 1:
            raise ValueError(f"thetas has shape {arr.shape}: expected (K, n_theta) with K >= 1")
        return [Theta.from_vector(row, n) for row in arr]
    out = list(thetas)
    if not out or any(not isinstance(t, Theta) or t.n != n for t in out):
        raise ValueError(f"thetas: expected a non-empty sequence of Theta with n={n}")
    return out
