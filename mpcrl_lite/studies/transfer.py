r"""A learned theta on prices it never saw: the learned and the nominal MPC on K noise draws.

Draw ``k`` (``k = 0 .. K-1``) is the noise of ``numpy.random.default_rng(seed + k)``; both
policies run on the same draws through the one closed loop
(:func:`mpcrl_lite.sim.closed_loop.evaluate_mpc`), so the differences are paired. For each policy
the month's cost :math:`J = \sum_{d,k} \ell(s_k, a_k)` (paper, eq. 4) is summarised by its
mean over the draws and a 95 % confidence interval of the mean,
:math:`\bar J \pm t_{0.975, K-1}\, s / \sqrt{K}` (Student's t; none for ``K = 1``).
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from .._util.stats import mean_ci
from ..config import MPCConfig, SystemConfig
from ..mpc.backends.registry import make_solver
from ..mpc.formulation import MPC
from ..sim.closed_loop import evaluate_mpc
from ..system.forecast import forecast_prices
from ..system.prices import Prices
from ..theta import Theta

__all__ = ["evaluate_thetas"]


def evaluate_thetas(
    thetas: dict[str, Theta],
    system: SystemConfig,
    mpc_config: MPCConfig,
    prices: Prices,
    draws: int,
    seed: int = 0,
) -> dict[str, Any]:
    """Every theta of ``thetas`` in closed loop on ``draws`` noise draws of ``prices``.

    Parameters
    ----------
    thetas : mapping of name to Theta
        E.g. ``{"learned": history.final_theta(), "nominal": Theta.nominal(system)}``.
    system, mpc_config
        The true system and the MPC back-end.
    prices : Prices
        The month, shape ``(days, 24)``.
    draws : int
        K >= 1.
    seed : int
        Draw ``k`` uses seed ``seed + k``.

    Returns
    -------
    dict
        ``{"draws", "seeds", "policies": {name: {"J": [K values], "J_stats": mean_ci,
        "solver_failures", "hours_soc_below_0_1", "max_P_mpc"}}, "difference": {name:
        mean_ci of J[name] - J[first name]}}``.
    """
    if draws < 1:
        raise ValueError(f"draws={draws!r}: expected an integer >= 1")
    seeds = [int(seed) + k for k in range(draws)]
    mpc = MPC(system)
    seen = forecast_prices(prices, mpc_config)  # what the MPC forecasts (MPCConfig.forecast)
    policies: dict[str, Any] = {}
    for name, theta in thetas.items():
        solver = make_solver(mpc, mpc_config, theta)
        runs = []
        t0 = time.perf_counter()
        for s in seeds:
            runs.append(evaluate_mpc(theta, solver, seen, system, s).summary())
        policies[name] = {
            "J": [r["J"] for r in runs],
            "J_stats": mean_ci([r["J"] for r in runs]).as_dict(),
            "solver_failures": int(sum(r["solver_failures"] for r in runs)),
            "hours_soc_below_0_1": [r["hours_soc_below_0_1"] for r in runs],
            "max_P_mpc": max(r["max_P_mpc"] for r in runs),
            "backend": solver.name,
            "wall_time_s": time.perf_counter() - t0,
        }
    names = list(policies)
    base = np.asarray(policies[names[0]]["J"])
    difference = {f"{name} - {names[0]}": mean_ci(np.asarray(policies[name]["J"]) - base).as_dict()
                  for name in names[1:]}
    return {"draws": draws, "seeds": seeds, "policies": policies, "difference": difference}
