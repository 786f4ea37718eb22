"""One month of an hourly price series as the learning month's day-by-clock-hour matrix.

:func:`daily_matrix` cuts any stretch of local days; :func:`month_matrix` takes one calendar
month (``'YYYY-MM'``) and refuses it when an hour is missing, naming the first one.
:meth:`mpcrl_lite.system.prices.Prices.from_month` makes the :class:`~mpcrl_lite.system.prices.Prices`
of it.
"""

from __future__ import annotations

import calendar
import datetime as _dt
import re

import numpy as np

from ..._util.lazy import lazy_module
from ..._util.validate import InputTypeError, check_instance, check_int
from ...config import HOURS_PER_DAY
from .series import LOCAL_TZ

pd = lazy_module("pandas")  # imported when a file is first read

__all__ = ["daily_matrix", "month_matrix", "parse_month"]

_MONTH = re.compile(r"^(\d{4})-(\d{2})$")


def _as_date(start: _dt.date | str | pd.Timestamp, tz: str) -> _dt.date:
    try:
        stamp = pd.Timestamp(start)
    except (TypeError, ValueError):
        raise ValueError(f"start={start!r}: expected a date or a 'YYYY-MM-DD' string") from None
    if stamp.tzinfo is not None:
        stamp = stamp.tz_convert(tz)
    if stamp != stamp.normalize():
        raise ValueError(f"start={start!r}: expected a date (midnight), not a time of day")
    return stamp.date()


def daily_matrix(
    series: pd.Series,
    start: _dt.date | str | pd.Timestamp,
    days: int,
    tz: str = LOCAL_TZ,
) -> np.ndarray:
    """Hourly prices of ``days`` consecutive local days as a day-by-clock-hour matrix.

    Day ``d`` runs from local midnight of ``start + d`` to the next local midnight, and hour
    ``h`` is the clock hour ``h:00 .. h+1:00`` of that day.

    **Clock-change days** have 23 or 25 real hours and are mapped onto 24 clock hours:

    * 25 hours (autumn): the two hours that both read 02:00 on the clock are averaged into
      hour 2.
    * 23 hours (spring): the skipped clock hour (02:00 in Europe/Oslo) takes the value of the
      hour before it (01:00).

    Every other hour is used as it is.

    Parameters
    ----------
    series : pandas.Series
        Hourly prices on a time-zone-aware ``DatetimeIndex`` (e.g. from
        :func:`load_nordpool_csv`); NaN counts as missing.
    start : datetime.date, str or pandas.Timestamp
        First day, e.g. ``"2020-11-01"``.
    days : int
        Number of days, at least 1.
    tz : str, default ``"Europe/Oslo"``
        Time zone whose midnights delimit the days.

    Returns
    -------
    numpy.ndarray
        Shape ``(days, 24)``, in the series' unit.

    Raises
    ------
    ValueError
        If the index is not time-zone-aware or not on whole hours, ``start`` is not a date, or
        any hour of the requested range is missing (the message names the range and the
        series' coverage, or the first missing hours).
    """
    days = check_int("days", days, 1)
    check_instance("series", series, pd.Series)
    if not isinstance(series.index, pd.DatetimeIndex):
        raise InputTypeError(
            "series: expected a pandas Series with a DatetimeIndex, got an index of type "
            f"{type(series.index).__name__}"
        )
    if series.index.tz is None:
        raise ValueError(
            "series: expected a time-zone-aware DatetimeIndex (naive local times are ambiguous "
            "at the autumn clock change); use load_nordpool_csv or Series.tz_localize"
        )
    first = _as_date(start, tz)
    last = first + _dt.timedelta(days=days)  # exclusive
    t0 = pd.Timestamp(first).tz_localize(tz)
    t1 = pd.Timestamp(last).tz_localize(tz)
    span = f"{first} to {last - _dt.timedelta(days=1)} ({days} day(s), {tz})"

    local = series.dropna().tz_convert(tz)
    local = local[(local.index >= t0) & (local.index < t1)]
    if local.empty:
        have = series.dropna()
        coverage = (
            f"{have.index.min().tz_convert(tz)} .. {have.index.max().tz_convert(tz)}"
            if len(have)
            else "nothing"
        )
        raise ValueError(f"no prices from {span}; the series covers {coverage}")
    idx = local.index
    utc = idx.tz_convert("UTC")
    if (utc != utc.floor("h")).any() or idx.duplicated().any():
        raise ValueError(f"series: expected one value per whole hour in {span}")
    expected = pd.date_range(t0, t1, freq="h", inclusive="left")
    missing = expected.difference(idx)
    if len(missing):
        shown = ", ".join(str(t) for t in missing[:5]) + (" ..." if len(missing) > 5 else "")
        raise ValueError(f"{len(missing)} hour(s) missing from {span}: {shown}")

    day = (idx.tz_localize(None).normalize() - pd.Timestamp(first)).days
    frame = pd.DataFrame({"day": day, "hour": idx.hour, "price": local.to_numpy(dtype=float)})
    table = (
        frame.groupby(["day", "hour"])["price"]
        .mean()  # the repeated autumn hour
        .unstack("hour")
        .reindex(index=range(days), columns=range(HOURS_PER_DAY))
    )
    # A skipped spring hour repeats the hour before it.
    table = table.ffill(axis=1).bfill(axis=1)
    return table.to_numpy(dtype=float)


def parse_month(month: str) -> tuple[_dt.date, int]:
    """``'YYYY-MM'`` as its first day and its number of days."""
    found = _MONTH.match(str(month))
    if not found or not 1 <= int(found.group(2)) <= 12:
        raise ValueError(f"month {month!r}: expected a calendar month as YYYY-MM, e.g. 2025-11")
    year, number = int(found.group(1)), int(found.group(2))
    return _dt.date(year, number, 1), calendar.monthrange(year, number)[1]


def month_matrix(series: pd.Series, month: str, days: int | None = None) -> np.ndarray:
    """The ``(days, 24)`` buying-price matrix of calendar ``month`` of an hourly series.

    Every real hour of the month (its first ``days`` days) must have a price: a month with
    missing hours is refused, naming the first one. Clock-change days are mapped onto 24 clock
    hours as :func:`daily_matrix` describes.
    """
    first, length = parse_month(month)
    if days is not None:
        days = check_int("days", days, 1)
        if days > length:
            raise ValueError(f"days={days}: {month} has {length} days; expected at most {length}")
    count = length if days is None else days
    check_instance("series", series, pd.Series)
    if isinstance(series.index, pd.DatetimeIndex) and series.index.tz is not None:
        t0 = pd.Timestamp(first).tz_localize(LOCAL_TZ)
        t1 = pd.Timestamp(first + _dt.timedelta(days=count)).tz_localize(LOCAL_TZ)
        inside = series[(series.index >= t0) & (series.index < t1)]
        expected = pd.date_range(t0, t1, freq="h", inclusive="left")
        missing = expected.difference(inside.dropna().index)
        if len(missing) and len(inside.dropna()):
            raise ValueError(f"{len(missing)} hour(s) missing from {month}: the first "
                             f"{missing[0]}; expected a price for every hour of the month")
    return daily_matrix(series, first, count)
