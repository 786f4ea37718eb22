"""ENTSO-E Transparency Platform day-ahead prices, the CSV before 2025.

Format (as the platform's "Day-ahead Prices" export wrote it): quoted, ``,``-separated, header
``"MTU (CET/CEST)","Day-ahead Price [EUR/MWh]","Currency","BZN|FI"`` -- the area is the last
header cell, the rows have three fields:
``"28.03.2021 01:00 - 28.03.2021 02:00","18.68","EUR"``. The spring change hour
(``02:00 - 03:00``, a wall time that does not exist) is present but empty and dropped; the
autumn ``02:00 - 03:00`` hour is there twice (summer time first); hours not yet published are
``"-"``. ``(CET)``/``(CEST)`` markers are read when present; a ``MTU (UTC)`` header gives UTC
times.
"""

from __future__ import annotations

import re

import numpy as np

from ..._util.lazy import lazy_module
from .areas import canonical, find_column
from .series import hourly, localize, parse_numbers, period_minutes, read_table, separator

pd = lazy_module("pandas")  # imported when a file is first read

__all__ = ["NAME", "read"]

NAME = "entsoe_legacy"
_MTU = re.compile(
    r"^\s*(?P<s>\d\d\.\d\d\.\d{4} \d\d:\d\d)\s*(?:\((?P<sm>CEST|CET)\))?\s*-\s*"
    r"(?P<e>\d\d\.\d\d\.\d{4} \d\d:\d\d)\s*(?:\((?P<em>CEST|CET)\))?\s*$")
_CURRENCY = re.compile(r"\[(?P<cur>[A-Za-z]{3})/MWh\]")


def read(text: str, area: str, where: str, offset: int = 0) -> pd.Series:
    """The prices of the file's one area (see the module docstring); ``area`` must name it
    (any alias) or be None."""
    frame, labels = read_table(text, separator(text), where, offset)
    cols = list(frame.columns)
    if len(cols) < 2 or not cols[0].startswith("MTU") or not cols[1].startswith("Day-ahead"):
        raise ValueError(f"{where}: expected an ENTSO-E header '\"MTU (CET/CEST)\",\"Day-ahead "
                         "Price [EUR/MWh]\",\"Currency\",\"BZN|..\"'")
    named = [c for c in cols[2:] if c.upper().startswith("BZN") or c not in ("Currency",)]
    named = [c for c in named if c != "Currency" and not c.startswith("Unnamed")]
    column = named[-1] if named else "?"
    if area is not None:
        column = find_column(area, [column], where)
    found = _CURRENCY.search(cols[1])
    currency = found["cur"].upper() if found else "EUR"
    if "Currency" in cols:
        given = set(frame["Currency"].str.strip()) - {""}
        if len(given) == 1:
            currency = given.pop().upper()
    parts = frame[cols[0]].str.extract(_MTU)
    bad = parts["s"].isna()
    if bad.any():
        i = int(bad.to_numpy().nonzero()[0][0])
        raise ValueError(f"{where}: {labels[i]}: cannot read the period {frame[cols[0]].iloc[i]!r};"
                         " expected 'DD.MM.YYYY HH:MM - DD.MM.YYYY HH:MM'")
    labels = [f"{lab} ({s})" for lab, s in zip(labels, parts["s"])]
    start = pd.to_datetime(parts["s"], format="%d.%m.%Y %H:%M")
    end = pd.to_datetime(parts["e"], format="%d.%m.%Y %H:%M")
    values = parse_numbers(frame[cols[1]], labels, where)
    if "UTC" in cols[0]:
        utc = pd.DatetimeIndex(start).tz_localize("UTC")
        minutes = ((end - start) / pd.Timedelta(minutes=1)).to_numpy().astype(int)
    else:
        # the spring hour that does not exist on the clock: empty and dropped, a price an error
        gap = pd.DatetimeIndex(start).tz_localize("Europe/Oslo", ambiguous="NaT",
                                                  nonexistent="NaT").isna()
        ambiguous = pd.DatetimeIndex(start).tz_localize(
            "Europe/Oslo", ambiguous="NaT", nonexistent="shift_forward").isna()
        drop = gap & ~ambiguous & np.isnan(values)
        keep = ~drop
        start, end, values = start[keep].reset_index(drop=True), end[keep].reset_index(
            drop=True), values[keep]
        labels = [lab for lab, k in zip(labels, keep) if k]
        marker = parts["sm"][keep].reset_index(drop=True)
        minutes = period_minutes(start, end, labels, where)
        utc = localize(start, labels, where, marker=marker)
    return hourly(utc, minutes, values, labels, where=where, area=canonical(column),
                  column=column, currency=currency, fmt=NAME)
