"""ENTSO-E Transparency Platform day-ahead prices, the CSV of 2025 on (``GUI_ENERGY_PRICES_<start>-<end>.csv``).

Format (as the platform's "Energy Prices" export writes it): quoted, ``,``-separated, header
``"MTU (CET/CEST)","Area","Sequence","Day-ahead Price (EUR/MWh)","Intraday Period (CET/CEST)",
"Intraday Price (EUR/MWh)"`` (or ``"MTU (UTC)"``), rows
``"01/01/2025 00:00:00 - 01/01/2025 00:15:00","BZN|NO1","Without Sequence","22.14","",""``.
Local times carry ``(CET)``/``(CEST)`` on the rows around a clock change. One file may hold
several areas (``Area``) and, for a few areas, several auctions (``Sequence``): the rows
``Without Sequence`` are used, or the only sequence there is. A year of 15-minute rows repeats
the hourly price four times before 1 October 2025.
"""

from __future__ import annotations

import re

from ..._util.lazy import lazy_module
from .areas import canonical, find_column
from .series import hourly, localize, parse_numbers, period_minutes, read_table, separator

pd = lazy_module("pandas")  # imported when a file is first read

__all__ = ["NAME", "read"]

NAME = "entsoe"
_MTU = re.compile(
    r"^\s*(?P<s>\d\d/\d\d/\d{4} \d\d:\d\d(?::\d\d)?)\s*(?:\((?P<sm>CEST|CET)\))?\s*-\s*"
    r"(?P<e>\d\d/\d\d/\d{4} \d\d:\d\d(?::\d\d)?)\s*(?:\((?P<em>CEST|CET)\))?\s*$")
_CURRENCY = re.compile(r"\((?P<cur>[A-Za-z]{3})/MWh\)")


def _times(text: pd.Series) -> pd.Series:
    text = text.where(text.str.count(":") > 1, text + ":00")
    return pd.to_datetime(text, format="%d/%m/%Y %H:%M:%S", errors="coerce")


def read(text: str, area: str, where: str, offset: int = 0) -> pd.Series:
    """One area's day-ahead prices (see the module docstring)."""
    frame, labels = read_table(text, separator(text), where, offset)
    cols = list(frame.columns)
    mtu = next((c for c in cols if c.startswith("MTU")), None)
    price = next((c for c in cols if c.startswith("Day-ahead Price")), None)
    if mtu is None or price is None or "Area" not in cols:
        raise ValueError(f"{where}: expected an ENTSO-E header with 'MTU (CET/CEST)', 'Area' and "
                         "'Day-ahead Price (EUR/MWh)' columns")
    found = _CURRENCY.search(price)
    currency = found["cur"].upper() if found else "EUR"
    column = find_column(area, list(dict.fromkeys(frame["Area"].str.strip())), where)
    rows = frame["Area"].str.strip() == column
    if "Sequence" in cols:
        seqs = list(dict.fromkeys(frame.loc[rows, "Sequence"].str.strip()))
        if len(seqs) > 1:
            if "Without Sequence" not in seqs:
                raise ValueError(f"{where}: area {column!r} has several auctions {seqs}; expected "
                                 "rows 'Without Sequence' or a single sequence")
            rows &= frame["Sequence"].str.strip() == "Without Sequence"
    keep = rows.to_numpy().nonzero()[0]
    frame = frame.iloc[keep].reset_index(drop=True)
    labels = [labels[i] for i in keep]
    parts = frame[mtu].str.extract(_MTU)
    bad = parts["s"].isna()
    if bad.any():
        i = int(bad.to_numpy().nonzero()[0][0])
        raise ValueError(f"{where}: {labels[i]}: cannot read the period {frame[mtu].iloc[i]!r}; "
                         "expected 'DD/MM/YYYY HH:MM:SS - DD/MM/YYYY HH:MM:SS'")
    labels = [f"{lab} ({s})" for lab, s in zip(labels, parts["s"])]
    start, end = _times(parts["s"]), _times(parts["e"])
    values = parse_numbers(frame[price], labels, where)
    if "UTC" in mtu:
        utc = pd.DatetimeIndex(start).tz_localize("UTC")
        minutes = ((end - start) / pd.Timedelta(minutes=1)).to_numpy().astype(int)
    else:
        minutes = period_minutes(start, end, labels, where)
        utc = localize(start, labels, where, marker=parts["sm"])
    return hourly(utc, minutes, values, labels, where=where, area=canonical(column),
                  column=column, currency=currency, fmt=NAME)
