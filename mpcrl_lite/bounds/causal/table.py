r"""Stored values of the best causal policy's cost J* for the systems the notebooks use.

J* (:mod:`mpcrl_lite.bounds.causal.dp`) depends on the system and on each day's prices only: not on a
learned theta, a seed or a noise draw. Solving the coupled DP of the paper's month costs about
a minute of CPU per system, so the notebooks that measure learned policies against J* would
solve the same DP on every run. ``data/causal_j_star.csv`` holds J* of every day of
:meth:`Prices.default` for the systems ``SystemConfig(P_bar=..., noise_var=...)`` (every other
field at its default) of notebook 07's grid. Its header lines (``# key: JSON value``) record
how, when and from which commit it was computed (``tools/make_causal_table.py``);
``tests/bounds/test_causal_table.py`` solves days again and compares.

:func:`causal_bound` returns the stored values when they cover the system, the prices and the
grid asked for, and solves the DP otherwise, so a caller gets the same :class:`CausalBound`
(without value tables) either way.
"""

from __future__ import annotations

import json
from typing import Any

import pandas as pd

from ...config import SystemConfig
from ...system.prices import DATA_DIR, Prices
from .dp import CausalBound, causal_optimum
from .grid import SocGrid, day_prices, distinct_days

__all__ = ["TABLE_CSV", "causal_bound", "provenance", "stored_bound"]

#: File name in :data:`mpcrl_lite.system.prices.DATA_DIR`: header lines ``# key: JSON value`` (the
#: provenance), then ``P_bar,noise_var,grid,action_step,day,J_star``.
TABLE_CSV = "causal_j_star.csv"


def _table() -> pd.DataFrame | None:
    path = DATA_DIR / TABLE_CSV
    return pd.read_csv(path, comment="#") if path.exists() else None


def provenance() -> dict[str, Any]:
    """How the stored table was computed (its header lines), ``{}`` without a table."""
    path = DATA_DIR / TABLE_CSV
    if not path.exists():
        return {}
    info = {}
    for line in path.read_text().splitlines():
        if not line.startswith("# "):
            break
        key, _, value = line[2:].partition(": ")
        info[key] = json.loads(value)
    return info


def stored_bound(
    system: SystemConfig, prices: Prices | None = None, grid: int = 41, action_step: float = 0.1
) -> CausalBound | None:
    """The stored J* as a :class:`CausalBound` without value tables, or None if not stored.

    Stored means: ``system`` differs from ``SystemConfig()`` in ``P_bar`` and ``noise_var``
    at most (and in the MPC's horizon ``N``, which the true system and J* do not have), the table has that pair for ``grid`` and ``action_step``, and every day of
    ``prices`` (default :meth:`Prices.default`) has the prices of one of the stored days.

    Returns
    -------
    CausalBound or None
        ``J_star_per_day`` of shape ``(30,)`` for the days of :meth:`Prices.default`;
        :meth:`CausalBound.J_star_for` gives the values for the days of ``prices``;
        ``values`` is None (no :meth:`CausalBound.policy`).
    """
    if not isinstance(system, SystemConfig):
        raise ValueError(f"system={system!r}: expected a SystemConfig")  # noqa: TRY004
    table = _table()
    if isinstance(system.noise_var, tuple):  # the table has one noise variance per row
        return None
    # the MPC's horizon N is no part of the true system: J* does not depend on it
    if table is None or system != SystemConfig(P_bar=system.P_bar, noise_var=system.noise_var,
                                               N=system.N):
        return None
    rows = table[(table["P_bar"] == system.P_bar) & (table["noise_var"] == system.noise_var)
                 & (table["grid"] == grid) & (table["action_step"] == action_step)]
    buy, sell = day_prices(system, Prices.default(system))
    if len(rows) != buy.shape[0] or list(rows["day"]) != list(range(buy.shape[0])):
        return None
    _, day_of = distinct_days(buy, sell)
    bound = CausalBound(system, SocGrid(system, grid, action_step), buy, sell,
                        rows["J_star"].to_numpy(dtype=float), None, day_of, 0.0,
                        {"distinct_days": int(day_of.max()) + 1, "source": f"data/{TABLE_CSV}"})
    if prices is not None:
        try:
            bound.rows_for(prices)
        except ValueError:
            return None
    return bound


def causal_bound(
    system: SystemConfig, prices: Prices | None = None, grid: int = 41, action_step: float = 0.1
) -> CausalBound:
    """J* for the days of ``prices``: :func:`stored_bound` if stored, else the DP solved now
    (:func:`mpcrl_lite.bounds.causal.dp.causal_optimum` with ``keep_values=False``).

    Use ``bound.J_star_for(prices)`` for the days of ``prices`` (the stored bound covers the
    30 days of :meth:`Prices.default`); ``bound.info['source']`` says where it came from.
    """
    bound = stored_bound(system, prices, grid, action_step)
    if bound is not None:
        return bound
    bound = causal_optimum(system, prices, grid=grid, action_step=action_step, keep_values=False)
    bound.info["source"] = "solved"
    return bound
