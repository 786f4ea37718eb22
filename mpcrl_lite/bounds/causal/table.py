r"""Stored values of the best causal policy's cost J* for the systems the notebooks use.

J* (:mod:`mpcrl_lite.bounds.causal.dp`) depends on the system and on each day's prices only: not on a
learned theta, a seed or a noise draw. Solving the coupled DP of the paper's month costs about
a minute of CPU per system, so the notebooks that measure learned policies against J* would
solve the same DP on every run. ``data/causal_j_star.csv`` holds J* of every day of
:meth:`Prices.default` for the systems ``SystemConfig(P_bar=..., noise_var=...)`` (every other
field at its default) of notebook 07's grid. Its header lines (``# key: JSON value``) record
how, when and from which commit it was computed (``tools/make_causal_table.py``);
``tests/bounds/test_causal_table.py`` solves days again and compares.

``data/causal_j_star_sites.csv`` does the same for other sites the notebooks use, whole
systems with batteries of their own (notebook 06's mixed site: its coupled DP on a grid with
fewer symmetries costs about 200 s of CPU), each row keyed by :func:`site_key`.

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
from .dp import CausalBound, causal_optimum, dp_grid
from .grid import day_prices, distinct_days

__all__ = ["SITES_CSV", "TABLE_CSV", "causal_bound", "provenance", "site_key", "stored_bound"]

#: File name in :data:`mpcrl_lite.system.prices.DATA_DIR`: header lines ``# key: JSON value`` (the
#: provenance), then ``P_bar,noise_var,grid,action_step,day,J_star``.
TABLE_CSV = "causal_j_star.csv"
#: File name in :data:`~mpcrl_lite.system.prices.DATA_DIR` of the sites' table: header lines as
#: above, then ``site,grid,action_step,day,J_star`` (``site`` from :func:`site_key`).
SITES_CSV = "causal_j_star_sites.csv"


def _table(name: str = TABLE_CSV) -> pd.DataFrame | None:
    path = DATA_DIR / name
    return pd.read_csv(path, comment="#") if path.exists() else None


def site_key(system: SystemConfig) -> str:
    """The key of ``system`` in the sites' table: the fields in which it differs from
    ``SystemConfig()``, as sorted JSON (the MPC's horizon ``N`` left out: J* does not depend
    on it)."""
    default = SystemConfig().to_dict()
    return json.dumps({k: v for k, v in system.to_dict().items()
                       if k != "N" and v != default[k]}, sort_keys=True)


def provenance(name: str = TABLE_CSV) -> dict[str, Any]:
    """How a stored table (``name``: :data:`TABLE_CSV` or :data:`SITES_CSV`) was computed (its
    header lines), ``{}`` without a table."""
    path = DATA_DIR / name
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
    at most (and in the MPC's horizon ``N``, which the true system and J* do not have) and
    the table has that pair, or the sites' table has the system (:func:`site_key`), for
    ``grid`` and ``action_step``; and every day of ``prices`` (default
    :meth:`Prices.default`) has the prices of one of the stored days.

    Returns
    -------
    CausalBound or None
        ``J_star_per_day`` of shape ``(30,)`` for the days of :meth:`Prices.default`;
        :meth:`CausalBound.J_star_for` gives the values for the days of ``prices``;
        ``values`` is None (no :meth:`CausalBound.policy`).
    """
    if not isinstance(system, SystemConfig):
        raise ValueError(f"system={system!r}: expected a SystemConfig")  # noqa: TRY004
    rows, source = _stored_rows(system, grid, action_step)
    if rows is None:
        return None
    buy, sell = day_prices(system, Prices.default(system))
    if len(rows) != buy.shape[0] or list(rows["day"]) != list(range(buy.shape[0])):
        return None
    _, day_of = distinct_days(buy, sell)
    system, soc_grid = dp_grid(system, grid, action_step)
    bound = CausalBound(system, soc_grid, buy, sell,
                        rows["J_star"].to_numpy(dtype=float), None, day_of, 0.0,
                        {"distinct_days": int(day_of.max()) + 1, "source": f"data/{source}"})
    if prices is not None:
        try:
            bound.rows_for(prices)
        except ValueError:
            return None
    return bound


def _stored_rows(system: SystemConfig, grid: int,
                 action_step: float) -> tuple[pd.DataFrame | None, str]:
    """The stored rows of ``system`` (either table) and the table's name."""
    # the MPC's horizon N is no part of the true system: J* does not depend on it
    table = _table()
    if table is not None and not isinstance(system.noise_var, tuple) \
            and system == SystemConfig(P_bar=system.P_bar, noise_var=system.noise_var,
                                       N=system.N):
        rows = table[(table["P_bar"] == system.P_bar) & (table["noise_var"] == system.noise_var)
                     & (table["grid"] == grid) & (table["action_step"] == action_step)]
        if len(rows):
            return rows, TABLE_CSV
    sites = _table(SITES_CSV)
    if sites is not None:
        rows = sites[(sites["site"] == site_key(system)) & (sites["grid"] == grid)
                     & (sites["action_step"] == action_step)]
        if len(rows):
            return rows, SITES_CSV
    return None, ""


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
