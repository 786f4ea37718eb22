"""A :class:`pandas.Series` of prices indexed by time, e.g. what the ``entsoe-py`` client's
``query_day_ahead_prices`` returns (EUR/MWh on a tz-aware index, hourly or quarter-hourly).

The index must be time-zone-aware (naive local times are ambiguous at the autumn change);
each value's period runs to the next index entry, the last one as long as the shortest step
(15 or 60 minutes).
"""

from __future__ import annotations

import numpy as np

from ..._util.lazy import lazy_module
from .areas import canonical
from .series import hourly

pd = lazy_module("pandas")  # imported when a file is first read

__all__ = ["NAME", "read"]

NAME = "pandas"


def read(series: pd.Series, area: str | None, currency: str, where: str = "series") -> pd.Series:
    """The hourly series of ``series`` (prices in ``currency`` per MWh)."""
    if not isinstance(series.index, pd.DatetimeIndex) or series.index.tz is None:
        raise ValueError(f"{where}: expected a Series on a time-zone-aware DatetimeIndex "
                         "(Series.tz_localize gives one)")
    if len(series) == 0:
        raise ValueError(f"{where}: the series is empty")
    index = series.index.tz_convert("UTC")
    order = np.argsort(index.asi8, kind="stable")
    index = index[order]
    values = pd.to_numeric(series.iloc[order], errors="coerce").to_numpy(dtype=float)
    steps = ((index[1:] - index[:-1]) / pd.Timedelta(minutes=1)).to_numpy(dtype=float)
    positive = steps[steps > 0]
    step = int(positive.min()) if len(positive) else 60
    if step not in (15, 60):
        raise ValueError(f"{where}: the shortest step is {step} minutes; expected 15 or 60")
    # a period runs to the next entry (15 or 60 minutes), else (a gap, the last entry) it is
    # as long as the shortest step
    minutes = np.append(steps, step)
    minutes = np.where(np.isin(minutes, (15, 60)), minutes, step).astype(int)
    labels = [f"entry {int(i)} ({t})" for i, t in zip(order, series.index[order])]
    name = area if area is not None else (series.name if series.name is not None else "series")
    return hourly(index, minutes, values, labels, where=where, area=canonical(str(name)),
                  column=str(name), currency=currency, fmt=NAME)
