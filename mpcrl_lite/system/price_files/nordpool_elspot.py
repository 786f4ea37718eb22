"""The old Nord Pool "Elspot Prices" export (``elspot-prices_<year>_hourly_<cur>.csv``).

The reader of the yearly files Nord Pool published before its data portal: a title and a note,
then a header line ``;Hours;SYS;SE1;...;Tr.heim;...``, dates ``DD.MM.YYYY``, hours ``00 - 01``,
decimal comma. :func:`load_nordpool_csv` and :func:`nordpool_areas` are also importable from
:mod:`mpcrl_lite.system.prices`, where they lived first.
"""

from __future__ import annotations

import io
import re
from pathlib import Path

import numpy as np

from ..._util.lazy import lazy_module
from .series import LOCAL_TZ

pd = lazy_module("pandas")  # imported when a file is first read

__all__ = ["load_nordpool_csv", "nordpool_areas"]

# How many lines to search for the header ";Hours;..." before giving up.
_HEADER_SEARCH_LINES = 20
_HOURS_RE = re.compile(r"^\s*(\d{1,2})\s*-\s*(\d{1,2})\s*$")


def _read_export(path: str | Path) -> tuple[Path, list[str], pd.DataFrame, np.ndarray]:
    """Header names, the data rows (all cells as stripped strings) and their line numbers.

    Every data row must have exactly as many cells as the header line (a trailing ``;``
    counts as a cell): the areas are addressed by position, so a missing or extra ``;`` would
    move prices to another area's column, and with a trailing ``;`` a row that lacks one cell
    cannot be told from a row whose last area is empty.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"Nord Pool export {path} not found")
    not_export = (
        f"{path} is not a Nord Pool price export: expected a ';'-separated file whose header "
        "line has an empty first cell, then 'Hours', then area names (e.g. ';Hours;SYS;...;"
        "Tr.heim;...')"
    )
    raw = path.read_bytes()
    try:
        text = raw.decode("utf-8-sig")  # drops the byte-order mark
    except UnicodeDecodeError as err:
        line = raw[: err.start].count(b"\n") + 1
        raise ValueError(
            f"{not_export}; line {line} is not UTF-8 text ({err.reason})"
        ) from None
    # Universal newlines (CRLF, LF, CR) and nothing else: str.splitlines would also split at
    # characters such as U+2028 inside a cell.
    lines = [line.rstrip("\n") for line in io.StringIO(text, newline=None)]
    header_row = None
    for i, line in enumerate(lines[:_HEADER_SEARCH_LINES]):
        cells = [c.strip() for c in line.split(";")]
        if len(cells) >= 3 and cells[0] == "" and cells[1].lower() == "hours":
            header_row = i
            break
    if header_row is None:
        shown = min(len(lines), _HEADER_SEARCH_LINES)
        raise ValueError(f"{not_export}; no such line among the first {shown} lines")
    names = [c.strip() for c in lines[header_row].split(";")]
    width = len(names)
    # Trailing empty header cells (a trailing ';') carry no area.
    while names and names[-1] == "":
        names.pop()
    rows, numbers_ = [], []
    for number, line in enumerate(lines[header_row + 1 :], start=header_row + 2):
        cells = [c.strip() for c in line.split(";")]
        # Lines made only of separators (padding at the end of some exports) are not data.
        if not any(cells):
            continue
        if len(cells) != width:
            raise ValueError(
                f"{path}: line {number} has {len(cells)} ';'-separated cells, the header "
                f"(line {header_row + 1}) has {width}; expected one cell per header column "
                "(a missing or extra ';' would move prices to another area)"
            )
        rows.append(cells[: len(names)])
        numbers_.append(number)
    frame = pd.DataFrame(rows, columns=range(len(names)), dtype=object).astype(str)
    return path, names, frame, np.asarray(numbers_, dtype=int)


def _area_list(names: list[str]) -> list[str]:
    return list(dict.fromkeys(n for n in names[2:] if n))


def nordpool_areas(path: str | Path) -> list[str]:
    """Area names in the header of a Nord Pool export, in file order, each listed once.

    Parameters
    ----------
    path : str or pathlib.Path
        The export (see :func:`load_nordpool_csv` for the format).

    Returns
    -------
    list of str
        E.g. ``['SYS', 'SE1', ..., 'Molde', 'Tr.heim', 'Tromsø', 'EE', ...]``.
    """
    _, names, _, _ = _read_export(path)
    return _area_list(names)


def _parse_prices(cells: pd.Series, path: Path, area: str, where: pd.Series) -> pd.Series:
    """Decimal-comma strings to floats; empty cells become NaN, anything else that is not a
    finite number is an error naming the line."""
    text = cells.str.replace(r"[\s\u00a0]", "", regex=True)
    # A comma is the decimal mark; a '.' next to a comma can only group thousands.
    has_comma = text.str.contains(",", regex=False)
    text = text.where(~has_comma, text.str.replace(".", "", regex=False))
    text = text.str.replace(",", ".", regex=False)
    values = pd.to_numeric(text.where(text != ""), errors="coerce").astype(float)
    bad = values.isna() & (text != "")
    if bad.any():
        i = bad.to_numpy().nonzero()[0][0]
        raise ValueError(
            f"{path}: area {area!r}, {where.iloc[i]}: cannot read price "
            f"{cells.iloc[i]!r}; expected a number with a decimal comma such as '304,19'"
        )
    infinite = np.isinf(values.to_numpy())
    if infinite.any():
        i = infinite.nonzero()[0][0]
        raise ValueError(
            f"{path}: area {area!r}, {where.iloc[i]}: price {cells.iloc[i]!r} is not finite; "
            "expected a finite number with a decimal comma such as '304,19'"
        )
    return values


def load_nordpool_csv(path: str | Path, area: str = "Tr.heim") -> pd.Series:
    """Read one area's hourly prices from a Nord Pool "Elspot Prices" export.

    The format handled (as published by Nord Pool, e.g. ``elspot-prices_2020_hourly_nok.csv``):

    * UTF-8 with or without a byte-order mark, CRLF or LF line ends, ``;`` as separator,
      decimal comma (``304,19``; a ``.`` or space next to a comma is read as a thousands
      separator).
    * Free text lines (a title, a "last updated" note) before the header line, which has an
      empty first cell (the date column), then ``Hours``, then area names. Areas are selected
      by name, never by position, since other exports order their columns differently.
    * Dates ``DD.MM.YYYY``; hours ``00 - 01`` .. ``23 - 00`` in local time (Europe/Oslo).
    * Empty cells mean "no price" and are dropped.
    * Every data line has exactly as many ``;``-separated cells as the header line (lines of
      separators only are padding and skipped): areas are addressed by position, so a line
      with a cell too many or too few would read its prices into the wrong areas.

    **Repeated area names** (``EE;EE``, ``LV;LV``, ...): row by row, the first of the
    same-named columns that holds a value is used (in Nord Pool's exports only one of them is
    filled at a time). Two different values in one row are an error.

    **Daylight saving time.** Each row's timestamp is the local start of its hour. On the
    spring change day the ``02 - 03`` row (a clock hour that does not exist) is empty and
    dropped, so the day has 23 hours; a value there is an error. On the autumn change day
    ``02 - 03`` appears twice: the first row is 02:00 summer time (+02:00), the second 02:00
    winter time (+01:00), so the day has 25 distinct hours. No value is ever moved to another
    hour.

    Parameters
    ----------
    path : str or pathlib.Path
        The export file.
    area : str, default ``"Tr.heim"``
        Column name as written in the header (``"Tr.heim"`` is Trondheim, zone NO3;
        ``"Molde"`` is the same zone; ``"SYS"`` is the system price).

    Returns
    -------
    pandas.Series
        Float prices in the export's unit (NOK/MWh for the NOK exports), one per real hour,
        indexed by the hour's start as a time-zone-aware ``DatetimeIndex`` in Europe/Oslo,
        strictly increasing; ``name`` is ``area``.

    Raises
    ------
    FileNotFoundError
        If ``path`` does not exist.
    ValueError
        If the file is not such an export, ``area`` is not one of its columns (the message
        lists those available), the area has no prices, a line has more or fewer cells than
        the header, or a date, hour or price cannot be read or a price is not finite (``inf``,
        ``1e999``); the message names the file and the line.
    """
    path, names, rows, line = _read_export(path)
    areas = _area_list(names)
    if area not in areas:
        raise ValueError(
            f"{path}: unknown area {area!r}; available areas: {', '.join(areas)}"
        )
    if rows.empty:
        raise ValueError(f"{path}: the export has a header but no data rows")
    where = "line " + pd.Series(line).astype(str) + " (" + rows[0] + " " + rows[1] + ")"

    columns = [i for i, name in enumerate(names) if name == area]
    parsed = [_parse_prices(rows[i], path, area, where) for i in columns]
    values = parsed[0]
    for other in parsed[1:]:
        clash = values.notna() & other.notna() & (values != other)
        if clash.any():
            i = clash.to_numpy().nonzero()[0][0]
            raise ValueError(
                f"{path}: area {area!r} appears in several columns with different prices on "
                f"{where.iloc[i]} ({values.iloc[i]:g} vs {other.iloc[i]:g})"
            )
        values = values.fillna(other)

    dates = pd.to_datetime(rows[0], format="%d.%m.%Y", errors="coerce")
    if dates.isna().any():
        i = dates.isna().to_numpy().nonzero()[0][0]
        raise ValueError(
            f"{path}: line {line[i]}: cannot read date {rows[0].iloc[i]!r}; "
            "expected DD.MM.YYYY"
        )
    hours = rows[1].str.extract(_HOURS_RE)
    start_h = pd.to_numeric(hours[0], errors="coerce")
    end_h = pd.to_numeric(hours[1], errors="coerce")
    bad = start_h.isna() | (start_h > 23) | (end_h != (start_h + 1) % 24)
    if bad.any():
        i = bad.to_numpy().nonzero()[0][0]
        raise ValueError(
            f"{path}: line {line[i]}: cannot read hour {rows[1].iloc[i]!r} on "
            f"{rows[0].iloc[i]}; expected 'HH - HH' such as '00 - 01' or '23 - 00'"
        )

    # The first appearance of a repeated (date, hour) row is summer time, the second winter
    # time; ranks are taken over the file's rows, before empty cells are dropped.
    rank = pd.DataFrame({"d": rows[0], "h": start_h}).groupby(["d", "h"]).cumcount()
    keep = values.notna().to_numpy()
    if not keep.any():
        raise ValueError(f"{path}: area {area!r} has no prices in this file (all cells empty)")
    naive = pd.DatetimeIndex(dates + pd.to_timedelta(start_h, unit="h"))[keep]
    local = naive.tz_localize(
        LOCAL_TZ, ambiguous=(rank.to_numpy() == 0)[keep], nonexistent="NaT"
    )
    if local.isna().any():
        i = np.flatnonzero(local.isna())[0]
        raise ValueError(
            f"{path}: area {area!r} has a price on {where[keep].iloc[i]}, an hour that does "
            f"not exist in {LOCAL_TZ} (spring clock change); expected an empty cell"
        )
    if local.duplicated().any():
        i = np.flatnonzero(local.duplicated())[0]
        raise ValueError(
            f"{path}: {where[keep].iloc[i]} repeats an earlier row; only the autumn "
            "clock-change hour 02 - 03 may appear twice"
        )
    series = pd.Series(values.to_numpy()[keep], index=local, name=area, dtype=float)
    series.index.name = "time"
    return series.sort_index()
