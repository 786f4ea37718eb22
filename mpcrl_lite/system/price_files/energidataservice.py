"""Energi Data Service (Energinet, Denmark): the ``Elspotprices`` and ``DayAheadPrices`` data sets.

Format (as the site's CSV download writes them): ``;``-separated, decimal comma, newest row
first. ``Elspotprices`` (hourly, until 30 September 2025): ``HourUTC;HourDK;PriceArea;
SpotPriceDKK;SpotPriceEUR``; ``DayAheadPrices`` (15-minute, from 1 October 2025):
``TimeUTC;TimeDK;PriceArea;DayAheadPriceEUR;DayAheadPriceDKK``. Times are read from the UTC
column, so the clock changes need no rule; the period is the data set's (60 or 15 minutes).
The EUR price is used (the model's currency is NOK, converted from EUR, see
:mod:`~mpcrl_lite.system.price_files.currency`).
"""

from __future__ import annotations

from ..._util.lazy import lazy_module
from .areas import canonical, find_column
from .series import guess_decimal, hourly, parse_numbers, read_table

pd = lazy_module("pandas")  # imported when a file is first read

__all__ = ["NAME", "read"]

NAME = "energidataservice"


def read(text: str, area: str, where: str, offset: int = 0) -> pd.Series:
    """One area's prices in EUR/MWh (see the module docstring)."""
    first = text.split("\n", 1)[0]
    sep = ";" if first.count(";") >= first.count(",") else ","
    frame, labels = read_table(text, sep, where, offset)
    cols = list(frame.columns)
    if "HourUTC" in cols:
        time, price, minutes = "HourUTC", "SpotPriceEUR", 60
    elif "TimeUTC" in cols:
        time, price, minutes = "TimeUTC", "DayAheadPriceEUR", 15
    else:
        raise ValueError(f"{where}: expected an Energi Data Service header starting 'HourUTC;"
                         "HourDK;PriceArea;...' or 'TimeUTC;TimeDK;PriceArea;...'")
    if price not in cols or "PriceArea" not in cols:
        raise ValueError(f"{where}: expected columns PriceArea and {price}; found {cols}")
    column = find_column(area, list(dict.fromkeys(frame["PriceArea"].str.strip())), where)
    keep = (frame["PriceArea"].str.strip() == column).to_numpy().nonzero()[0]
    frame = frame.iloc[keep].reset_index(drop=True)
    labels = [labels[i] for i in keep]
    stamps = frame[time].str.strip()
    utc = pd.to_datetime(stamps, errors="coerce", utc=True, format="mixed")
    if utc.isna().any():
        i = int(utc.isna().to_numpy().nonzero()[0][0])
        raise ValueError(f"{where}: {labels[i]}: cannot read {time} {stamps.iloc[i]!r}; expected "
                         "a time such as '2025-09-30 22:00' or '2025-09-30T22:00:00'")
    labels = [f"{lab} ({s})" for lab, s in zip(labels, stamps)]
    values = parse_numbers(frame[price], labels, where, guess_decimal(frame[price]))
    return hourly(pd.DatetimeIndex(utc), [minutes] * len(values), values, labels, where=where,
                  area=canonical(column), column=column, currency="EUR", fmt=NAME)
