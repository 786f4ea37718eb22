"""Nord Pool's data portal CSV (``AuctionPrice_<year>_DayAhead_<areas>_<currency>_None.csv``).

Format (as the portal's day-ahead export writes it): ``;``-separated, header
``Delivery Start (CET);Delivery End (CET);NO3 Price (NOK);NO4 Price (NOK);...`` (or
``... Price (EUR)``), rows ``30.09.2025 00:00:00;30.09.2025 01:00:00;140.02;19.34``, decimal
point (a decimal comma is read too). The times are local wall time (CET/CEST, whatever the
label says): on the spring change day one period runs ``01:00 -> 03:00`` (hourly) or
``01:45 -> 03:00``; on the autumn day the ``02:00`` hour or its quarters appear twice without a
marker, the first time in summer time. Quarter-hour rows from 1 October 2025.
"""

from __future__ import annotations

import re

from ..._util.lazy import lazy_module
from .areas import canonical, find_column
from .series import (
    guess_decimal,
    hourly,
    local_times,
    localize,
    parse_numbers,
    period_minutes,
    read_table,
    separator,
)

pd = lazy_module("pandas")  # imported when a file is first read

__all__ = ["NAME", "read"]

NAME = "nordpool_portal"
_PRICE = re.compile(r"^(?P<area>.+?)\s+Price\s*\((?P<cur>[A-Za-z]{3})\)\s*$")


def read(text: str, area: str, where: str, offset: int = 0) -> pd.Series:
    """One area's prices (see the module docstring); ``area`` is any name of
    :mod:`~mpcrl_lite.system.price_files.areas`."""
    frame, labels = read_table(text, separator(text), where, offset)
    cols = list(frame.columns)
    if len(cols) < 3 or not cols[0].startswith("Delivery Start") \
            or not cols[1].startswith("Delivery End"):
        raise ValueError(f"{where}: expected a Nord Pool portal header 'Delivery Start (CET);"
                         "Delivery End (CET);NO3 Price (NOK);...'")
    areas = {}
    for c in cols[2:]:
        found = _PRICE.match(c)
        if found:
            areas[found["area"].strip()] = (c, found["cur"].upper())
    column = find_column(area, list(areas), where)
    name, currency = areas[column]
    formats = ("%d.%m.%Y %H:%M:%S", "%d.%m.%Y %H:%M")
    start, end = local_times(frame[cols[0]], formats), local_times(frame[cols[1]], formats)
    for times, col in ((start, cols[0]), (end, cols[1])):
        if times.isna().any():
            i = int(times.isna().to_numpy().nonzero()[0][0])
            raise ValueError(f"{where}: {labels[i]}: cannot read {col} {frame[col].iloc[i]!r}; "
                             "expected DD.MM.YYYY HH:MM:SS")
    labels = [f"{lab} ({s})" for lab, s in zip(labels, frame[cols[0]].str.strip())]
    minutes = period_minutes(start, end, labels, where)
    values = parse_numbers(frame[name], labels, where, guess_decimal(frame[name]))
    utc = localize(start, labels, where)
    return hourly(utc, minutes, values, labels, where=where, area=canonical(column), column=column,
                  currency=currency, fmt=NAME)

