"""The one type every price file becomes: a time-zone-aware hourly :class:`pandas.Series`.

What :func:`hourly` returns (and so :func:`~mpcrl_lite.system.price_files.load.load_prices`):

* float prices per MWh, one per real hour, indexed by the hour's start as a strictly
  increasing ``DatetimeIndex`` in Europe/Oslo (CET/CEST): clock-change days have 23 and 25
  hours, never a shifted series;
* ``attrs``: ``unit`` (e.g. ``'EUR/MWh'``), ``currency``, ``area`` (the canonical code, e.g.
  ``'NO3'``), ``column`` (the file's name of it), ``format``, ``source`` (the file),
  ``resolution_min`` (60 or 15 as in the file), ``eur_rate`` (NOK per EUR if converted, else
  None) and ``missing`` (the hours without a price, see below);
* ``name``: the area code.

**Quarter-hours** (the Nordic day-ahead market since 1 October 2025) become hourly means of
their four quarters. Before October 2025 the hourly price equals the mean of four equal
quarters, so the choice is exact there (an hour whose quarters are equal keeps that value
exactly, with no rounding of the sum).

**Empty, missing and doubled periods.** A period given twice (other than the autumn
clock-change hour, which is two real hours) is an error naming both rows. An empty or ``-``
cell (a price not, or not yet, published) and a period with no row at all leave the hour as
NaN inside the series' span -- never filled -- and are reported in ``attrs['missing']`` and
by a :class:`PriceFileWarning` naming the first; an hour of which only some quarters have a
price is missing too. Empty periods before the first and after the last price (future hours
of a yearly file) are trimmed and reported the same way.
"""

from __future__ import annotations

import io
import warnings
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from ..._util.lazy import lazy_module

pd = lazy_module("pandas")  # imported when a file is first read

__all__ = ["LOCAL_TZ", "PriceFileWarning", "guess_decimal", "hourly", "local_times", "localize",
           "parse_numbers", "period_minutes", "read_table", "read_text", "separator"]

#: Local time zone of the Nordic exports (CET/CEST), and of the series returned.
LOCAL_TZ = "Europe/Oslo"

#: Lengths of a market period the files hold, in minutes.
RESOLUTIONS = (15, 60)


class PriceFileWarning(UserWarning):
    """A price file read with hours left without a price (reported, never filled)."""


def read_text(path: str | Path) -> str:
    """A price file's text: UTF-8 with or without a byte-order mark, any line ends."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"price file {path} not found")
    raw = path.read_bytes()
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError as err:
        line = raw[: err.start].count(b"\n") + 1
        raise ValueError(f"{path}: line {line} is not UTF-8 text ({err.reason}); expected a "
                         "CSV price file") from None
    return "\n".join(line.rstrip("\r\n") for line in io.StringIO(text, newline=None))


def read_table(text: str, sep: str, where: str, offset: int = 0) -> tuple[pd.DataFrame, list[str]]:
    """A separated table of strings (header on the first line, quotes removed) and a label
    ``'line L'`` per row (``offset`` lines before the header in the file); lines that are
    empty or only separators are skipped."""
    try:
        frame = pd.read_csv(io.StringIO(text), sep=sep, dtype=str, keep_default_na=False,
                            skip_blank_lines=False, skipinitialspace=True)
    except (pd.errors.ParserError, ValueError) as err:
        raise ValueError(f"{where}: cannot read the table ({' '.join(str(err).split())})") \
            from None
    frame.columns = [str(c).strip() for c in frame.columns]
    keep = (frame.apply(lambda col: col.astype(str).str.strip()) != "").any(axis=1).to_numpy()
    labels = [f"line {i + 2 + offset}" for i in np.flatnonzero(keep)]
    return frame[keep].reset_index(drop=True), labels


def separator(text: str) -> str:
    """``';'`` or ``','``: the one the header line uses more."""
    first = text.split("\n", 1)[0]
    return ";" if first.count(";") >= first.count(",") else ","


def local_times(cells: pd.Series, formats: tuple[str, ...]) -> pd.Series:
    """Wall-clock times read with the first of ``formats`` that reads them all, else as ISO
    8601; NaT where none does."""
    text = cells.astype(str).str.strip()
    for fmt in formats:
        times = pd.to_datetime(text, format=fmt, errors="coerce")
        if not times.isna().any():
            return times
    iso = pd.to_datetime(text, format="ISO8601", errors="coerce")
    return iso if iso.notna().sum() >= times.notna().sum() else times


def guess_decimal(cells: pd.Series) -> str:
    """``','`` if the cells are written with a decimal comma (``'140,02'``), else ``'.'``."""
    text = cells.astype(str).str.strip()
    comma = text.str.fullmatch(r"-?[\d.\s]*\d,\d+").sum()
    point = text.str.fullmatch(r"-?\d+\.\d+").sum()
    return "," if comma > point else "."


def localize(naive: pd.Series, labels: Sequence[str], where: str,
             marker: pd.Series | None = None) -> pd.DatetimeIndex:
    """Local wall-clock times (naive) to UTC instants.

    A wall time that occurs twice (the autumn change) is the summer-time one (+02:00) at its
    first occurrence in file order and the winter-time one (+01:00) at its second, unless
    ``marker`` says ``'CEST'``/``'CET'``; a wall time that does not exist (spring) is an
    error naming the row.
    """
    naive = pd.Series(pd.DatetimeIndex(naive))
    rank = naive.groupby(naive).cumcount().to_numpy()
    first = rank == 0
    if marker is not None:
        mark = marker.fillna("").to_numpy()
        first = np.where(mark == "CEST", True, np.where(mark == "CET", False, first))
    local = pd.DatetimeIndex(naive).tz_localize(LOCAL_TZ, ambiguous=first, nonexistent="NaT")
    if local.isna().any():
        i = int(np.flatnonzero(local.isna())[0])
        raise ValueError(f"{where}: {labels[i]}: {naive.iloc[i]} does not exist in {LOCAL_TZ} "
                         "(spring clock change); expected no price for it")
    return local.tz_convert("UTC")


def period_minutes(start_naive: pd.Series, end_naive: pd.Series, labels: Sequence[str],
                   where: str) -> np.ndarray:
    """Each row's period length (15 or 60 minutes) from its local start and end wall times.

    Across a clock change the wall times differ by an hour more (spring: ``01:00 -> 03:00``)
    or less (autumn: ``02:45 -> 02:00``) than the period; the two cases cannot be confused,
    since 15 +- 60 and 60 +- 60 are four different values.
    """
    diff = ((pd.DatetimeIndex(end_naive) - pd.DatetimeIndex(start_naive))
            / pd.Timedelta(minutes=1)).to_numpy()
    out = np.full(diff.shape, -1.0)
    for shift in (0, -60, 60):  # ordinary, spring, autumn
        for length in RESOLUTIONS:
            out = np.where((out < 0) & (diff + shift == length), length, out)
    if (out < 0).any():
        i = int(np.flatnonzero(out < 0)[0])
        raise ValueError(f"{where}: {labels[i]}: a period of {diff[i]:g} minutes; expected "
                         "15 or 60 minutes (or one hour more or less across a clock change)")
    return out.astype(int)


def parse_numbers(cells: pd.Series, labels: Sequence[str], where: str,
                  decimal: str = ".") -> np.ndarray:
    """Price cells as floats; empty cells and ``-`` are NaN (no price), anything else that is
    not a finite number is an error naming the row."""
    text = cells.fillna("").astype(str).str.strip().str.replace(r"[\s\u00a0]", "", regex=True)
    text = text.str.strip('"')
    empty = text.isin(["", "-", "n/e", "N/A"])
    if decimal == ",":
        text = text.str.replace(".", "", regex=False).str.replace(",", ".", regex=False)
    values = pd.to_numeric(text.where(~empty), errors="coerce").to_numpy(dtype=float)
    bad = (np.isnan(values) & ~empty.to_numpy()) | np.isinf(values)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        example = "140,02" if decimal == "," else "140.02"
        raise ValueError(f"{where}: {labels[i]}: cannot read price {cells.iloc[i]!r}; expected "
                         f"a finite number such as {example!r}, an empty cell or '-'")
    return values


def hourly(starts_utc: pd.DatetimeIndex, minutes: np.ndarray, values: np.ndarray,
           labels: Sequence[str], *, where: str, area: str, column: str, currency: str,
           fmt: str) -> pd.Series:
    """The hourly series of periods given by their UTC start, length and price.

    Parameters
    ----------
    starts_utc : pandas.DatetimeIndex
        Period starts, tz-aware, in file order.
    minutes : numpy.ndarray
        Period lengths, 15 or 60 each.
    values : numpy.ndarray
        Prices, NaN for an empty cell.
    labels : sequence of str
        How to name each row in a message (``'line 12 (30.09.2025 01:00:00)'``).
    where, area, column, currency, fmt
        The file, the area's code and column, the file's currency and format name.

    Raises
    ------
    ValueError
        A period given twice, periods overlapping, an hour mixing 15- and 60-minute rows, or
        no price at all.
    """
    n = len(values)
    if n == 0:
        raise ValueError(f"{where}: area {column!r} has no rows")
    starts = pd.DatetimeIndex(starts_utc).tz_convert("UTC")
    order = np.argsort(starts.asi8, kind="stable")
    starts, minutes, values = starts[order], np.asarray(minutes)[order], np.asarray(values)[order]
    labels = [labels[i] for i in order]
    dup = starts.duplicated()
    if dup.any():
        i = int(np.flatnonzero(dup)[0])
        j = int(np.flatnonzero(starts == starts[i])[0])
        raise ValueError(f"{where}: area {column!r}: {labels[i]} repeats the period of "
                         f"{labels[j]} ({starts[i].tz_convert(LOCAL_TZ)}); expected each "
                         "period once")
    ends = starts + pd.to_timedelta(minutes, unit="min")
    overlap = ends[:-1] > starts[1:]
    if overlap.any():
        i = int(np.flatnonzero(overlap)[0])
        raise ValueError(f"{where}: area {column!r}: {labels[i]} overlaps {labels[i + 1]}; "
                         "expected consecutive periods")
    priced = ~np.isnan(values)
    if not priced.any():
        raise ValueError(f"{where}: area {column!r} has no prices (every cell empty or '-')")
    hour = starts.floor("h")
    frame = pd.DataFrame({"hour": hour, "min": minutes, "v": values, "ok": priced})
    groups = frame.groupby("hour", sort=True)
    if (groups["min"].nunique() > 1).any():
        h = groups["min"].nunique().pipe(lambda s: s[s > 1]).index[0]
        i = int(np.flatnonzero(hour == h)[0])
        raise ValueError(f"{where}: area {column!r}: {labels[i]}: the hour mixes 15- and "
                         "60-minute periods; expected one resolution per hour")
    covered = groups["min"].sum()
    complete = (covered == 60) & groups["ok"].all()
    mean = groups["v"].mean()
    low, high = groups["v"].min(), groups["v"].max()
    exact = groups["v"].first()
    price = mean.where(low != high, exact).where(complete)
    first_row = frame.reset_index().groupby("hour")["index"].first()
    # the span from the first to the last priced hour, every hour in it
    have = price.dropna()
    span = pd.date_range(have.index[0], have.index[-1], freq="h")
    full = price.reindex(span)
    trimmed = int((price.index < span[0]).sum() + (price.index > span[-1]).sum())
    missing = full.index[full.isna()]
    series = pd.Series(full.to_numpy(dtype=float), index=span.tz_convert(LOCAL_TZ),
                       name=area, dtype=float)
    series.index.name = "time"
    resolution = int(np.min(minutes))
    series.attrs.update(unit=f"{currency}/MWh", currency=currency, area=area, column=column,
                        format=fmt, source=where, resolution_min=resolution, eur_rate=None,
                        missing=[str(t.tz_convert(LOCAL_TZ)) for t in missing[:20]],
                        missing_count=len(missing), trimmed=trimmed)
    if len(missing):
        t = missing[0]
        near = (f"row {labels[int(first_row[t])]}" if t in first_row.index
                else "no row for it")
        warnings.warn(f"{where}: area {column!r}: {len(missing)} hour(s) without a price, the "
                      f"first {t.tz_convert(LOCAL_TZ)} ({near}); they are NaN, not filled",
                      PriceFileWarning, stacklevel=3)
    return series
