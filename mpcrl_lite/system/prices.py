"""Electricity prices: the default month, a Nord Pool reader, and MPC forecast windows.

The paper drives its batteries with the hourly day-ahead buying price ``phi_b`` of Trondheim
(Nord Pool zone NO3) in November 2020, and sells at ``phi_s = 0.5 phi_b``. Prices are in
:data:`~mpcrl_lite.config.PRICE_UNIT` (NOK/MWh).

Three layers, each usable alone:

* :func:`load_default_profile` -- the month shipped in ``data/`` as a ``(30, 24)`` array,
  rebuilt from daily aggregates as ``price[d, h] = daily_mean[d] + daily_std[d] * shape[h]``
  (see ``data/README.md`` for the provenance).
* :func:`load_nordpool_csv` and :func:`daily_matrix` -- read a Nord Pool "Elspot Prices" export
  into an hourly, time-zone-aware :class:`pandas.Series`, and cut it into local-time days.
* :class:`Prices` -- a ``(days, 24)`` buying price matrix with the selling ratio, and the MPC's
  forecast window: at hour ``k`` the MPC sees the prices of hours ``k .. k+N-1``, reading on
  into the next day's prices after midnight; the month repeats, so its last day is followed by
  its first.
"""

from __future__ import annotations

import datetime as _dt
import io
import re
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np

from .._util.lazy import lazy_module
from .._util.resources import candidate_folders, package_folder
from .._util.validate import InputTypeError, check_instance, check_int, check_real
from ..config import HOURS_PER_DAY, PRICE_LIMIT, PRICE_UNIT, SystemConfig

#: pandas, imported when a CSV file is first read (it reads and parses every price file)
pd = lazy_module("pandas")

__all__ = ["DATA_DIR", "LOCAL_TZ", "Prices", "daily_matrix", "load_default_profile", "load_nordpool_csv", "nordpool_areas"]

#: Folder of the shipped data, found through the package (never through the working directory):
#: ``mpcrl_lite/data`` in an installed wheel, the repository's ``data/`` in a checkout.
DATA_DIR: Path = package_folder("data")

#: Local time zone of Nord Pool's Nordic exports (CET/CEST).
LOCAL_TZ = "Europe/Oslo"

_SHAPE_FILE = "no3_nov2020_intraday_shape.csv"
_DAILY_FILE = "no3_nov2020_daily.csv"
_DEFAULT_SOURCE = (
    "Nord Pool day-ahead, Trondheim (NO3), November 2020, rebuilt from daily aggregates "
    "(data/README.md)"
)

# How many lines to search for the header ";Hours;..." before giving up.
_HEADER_SEARCH_LINES = 20
_HOURS_RE = re.compile(r"^\s*(\d{1,2})\s*-\s*(\d{1,2})\s*$")


# ----------------------------------------------------------------------------------------------
# The shipped default month
# ----------------------------------------------------------------------------------------------


@lru_cache(maxsize=1)
def _default_profile_cached() -> np.ndarray:
    shape_path = DATA_DIR / _SHAPE_FILE
    daily_path = DATA_DIR / _DAILY_FILE
    for path in (shape_path, daily_path):
        if not path.is_file():
            raise FileNotFoundError(
                f"default price data {path.name} not found; expected it in the package's data "
                f"folder, one of {[str(p) for p in candidate_folders('data')]}"
            )
    shape = pd.read_csv(shape_path)
    daily = pd.read_csv(daily_path, parse_dates=["date"])
    if list(shape.columns) != ["hour", "shape"] or shape["hour"].tolist() != list(
        range(HOURS_PER_DAY)
    ):
        raise ValueError(f"{shape_path}: expected columns hour,shape with hours 0..23 in order")
    if list(daily.columns) != ["date", "daily_mean", "daily_std"]:
        raise ValueError(f"{daily_path}: expected columns date,daily_mean,daily_std")
    steps = daily["date"].diff().dropna()
    if len(daily) == 0 or not (steps == pd.Timedelta(days=1)).all():
        raise ValueError(f"{daily_path}: expected consecutive dates, one row per day")
    mean = daily["daily_mean"].to_numpy(dtype=float)
    std = daily["daily_std"].to_numpy(dtype=float)
    profile = mean[:, None] + std[:, None] * shape["shape"].to_numpy(dtype=float)[None, :]
    profile.setflags(write=False)
    return profile


def load_default_profile() -> np.ndarray:
    """Buying prices of the shipped month (Trondheim/NO3, November 2020).

    Rebuilt from the aggregates in ``data/`` as

    .. math:: \\phi_b[d, h] = \\mathrm{daily\\_mean}[d] + \\mathrm{daily\\_std}[d]\\,\\mathrm{shape}[h]

    which has correlation 0.977 with the real hourly series (RMSE 6.6 NOK/MWh).

    Returns
    -------
    numpy.ndarray
        Shape ``(30, 24)``: day ``d`` (2020-11-01 is day 0) by clock hour ``h``, in NOK/MWh.
        A fresh, writable copy.
    """
    return _default_profile_cached().copy()


# ----------------------------------------------------------------------------------------------
# Nord Pool exports
# ----------------------------------------------------------------------------------------------


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


# ----------------------------------------------------------------------------------------------
# Cutting a series into days
# ----------------------------------------------------------------------------------------------


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


# ----------------------------------------------------------------------------------------------
# The price matrix used by the experiment
# ----------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False, repr=False)
class Prices:
    """Hourly buying and selling prices of a month of ``days`` days.

    Parameters
    ----------
    buy : array_like
        Buying prices ``phi_b``, shape ``(days, 24)``: day by clock hour. Stored as a
        read-only float copy.
    sell_ratio : float, default 0.5
        Selling price = ``sell_ratio * buy`` (the paper uses ``phi_s = 0.5 phi_b``).
    unit : str, default :data:`~mpcrl_lite.config.PRICE_UNIT`
        Unit of ``buy`` (and ``sell``).
    source : str
        Where the prices come from (shown in reports and plots).

    Notes
    -----
    The month is cyclic: the forecast window of the last day's late hours continues with the
    first day's prices (the paper repeats the same 30 days every month).

    Examples
    --------
    >>> prices = Prices.default()
    >>> prices.days
    30
    >>> buy, sell = prices.window(hour=20, N=12)   # 20:00 .. 07:00 the next day
    >>> buy.shape
    (30, 12)
    """

    buy: np.ndarray
    sell_ratio: float = 0.5
    unit: str = PRICE_UNIT
    source: str = "user-supplied array"

    def __post_init__(self) -> None:
        try:
            buy = np.array(self.buy, dtype=float)
        except (TypeError, ValueError):
            raise ValueError("buy: expected an array of real numbers of shape (days, 24)") from None
        if buy.ndim != 2 or buy.shape[1] != HOURS_PER_DAY:
            raise ValueError(f"buy: expected shape (days, 24), got {buy.shape}")
        if buy.shape[0] < 1:
            raise ValueError("buy: expected at least 1 day, got 0 rows")
        if not np.isfinite(buy).all():
            d, h = np.argwhere(~np.isfinite(buy))[0]
            raise ValueError(f"buy: expected finite prices, got {buy[d, h]} at day {d}, hour {h}")
        outside = np.abs(buy) > PRICE_LIMIT
        if outside.any():
            d, h = np.argwhere(outside)[0]
            raise ValueError(f"buy: price {buy[d, h]:g} at day {d}, hour {h}: expected prices "
                             f"within +-{PRICE_LIMIT:g} per MWh (config.PRICE_LIMIT)")
        buy.setflags(write=False)
        object.__setattr__(self, "buy", buy)
        object.__setattr__(self, "sell_ratio", check_real("sell_ratio", self.sell_ratio, 0.0))
        for name in ("unit", "source"):
            check_instance(name, getattr(self, name), str)

    def __repr__(self) -> str:
        return (
            f"Prices(days={self.days}, buy mean={self.buy.mean():.2f} {self.unit}, "
            f"range [{self.buy.min():.2f}, {self.buy.max():.2f}], sell_ratio={self.sell_ratio:g}, "
            f"source={self.source!r})"
        )

    # -- views -----------------------------------------------------------------------------

    @property
    def days(self) -> int:
        """Number of days (rows of :attr:`buy`)."""
        return self.buy.shape[0]

    @property
    def sell(self) -> np.ndarray:
        """Selling prices ``phi_s = sell_ratio * phi_b``, shape ``(days, 24)``."""
        return self.sell_ratio * self.buy

    def window(self, hour: int, N: int) -> tuple[np.ndarray, np.ndarray]:
        """Buying and selling prices the MPC sees at ``hour`` over a horizon of ``N`` hours.

        Row ``d`` holds the prices of hours ``hour, hour+1, ..., hour+N-1`` counted from day
        ``d``'s midnight: hour ``24 + j`` is hour ``j`` of day ``d+1``, and so on. Days are
        taken cyclically, so after the last day comes day 0 again (also for ``N > 24``, which
        wraps over several days).

        Parameters
        ----------
        hour : int
            Current clock hour ``k``, in ``[0, 24)``.
        N : int
            Horizon length, at least 1.

        Returns
        -------
        buy, sell : numpy.ndarray
            Each of shape ``(days, N)``; ``sell = sell_ratio * buy``.
        """
        hour = check_int("hour", hour, 0, HOURS_PER_DAY - 1)
        N = check_int("N", N, 1)
        ahead = int(hour) + np.arange(N)  # hours counted from today's midnight, (N,)
        day = (np.arange(self.days)[:, None] + ahead[None, :] // HOURS_PER_DAY) % self.days
        buy = self.buy[day, ahead[None, :] % HOURS_PER_DAY]  # (days, N)
        return buy, self.sell_ratio * buy

    def to_frame(self) -> pd.DataFrame:
        """The prices as a tidy table for plotting: one row per (day, hour).

        Returns
        -------
        pandas.DataFrame
            Columns ``day`` (0-based), ``hour`` (0..23), ``buy`` and ``sell`` (in
            :attr:`unit`), ``days * 24`` rows, day-major. ``attrs`` holds ``unit`` and
            ``source``.
        """
        frame = pd.DataFrame(
            {
                "day": np.repeat(np.arange(self.days), HOURS_PER_DAY),
                "hour": np.tile(np.arange(HOURS_PER_DAY), self.days),
                "buy": self.buy.reshape(-1),
                "sell": self.sell.reshape(-1),
            }
        )
        frame.attrs.update(unit=self.unit, source=self.source)
        return frame

    # -- derived price sets ----------------------------------------------------------------

    def take(self, days: int) -> Prices:
        """The first ``days`` days, as a smaller month (for quick runs).

        The result is cyclic on its own: its last day is followed by its day 0, not by the
        day that followed it in the original month.
        """
        days = check_int("days", days, 1)
        if days > self.days:
            raise ValueError(f"days={days}: expected at most {self.days} (the days available)")
        if days == self.days:
            return self
        return Prices(
            self.buy[:days],
            sell_ratio=self.sell_ratio,
            unit=self.unit,
            source=f"{self.source}; first {days} day(s)",
        )

    def scaled(self, factor: float) -> Prices:
        """All prices multiplied by ``factor`` (finite, >= 0); unit and ratio unchanged."""
        factor = check_real("factor", factor, 0.0)
        if factor == 1.0:
            return self
        return Prices(
            self.buy * factor,
            sell_ratio=self.sell_ratio,
            unit=self.unit,
            source=f"{self.source}; scaled x{factor:g}",
        )

    # -- constructors ----------------------------------------------------------------------

    @classmethod
    def default(cls, system: SystemConfig | None = None) -> Prices:
        """The shipped month (Trondheim/NO3, November 2020, 30 days) for ``system``.

        Buying prices are :func:`load_default_profile` times ``system.price_scale``; the
        selling ratio is ``system.sell_ratio``. ``system=None`` uses ``SystemConfig()``.
        """
        system = SystemConfig() if system is None else system
        prices = cls(load_default_profile(), sell_ratio=system.sell_ratio, source=_DEFAULT_SOURCE)
        return prices.scaled(system.price_scale)

    @classmethod
    def month(cls, system: SystemConfig | None, days: int) -> Prices:
        """``days`` days of the shipped month for ``system``: the first ``days`` days, or
        the 30-day month repeated (day 31 is day 1 again) when ``days > 30``."""
        days = check_int("days", days, 1)
        prices = cls.default(system)
        if days <= prices.days:
            return prices.take(days)
        reps = np.resize(prices.buy, (days, prices.buy.shape[1]))
        return cls(reps, sell_ratio=prices.sell_ratio, unit=prices.unit,
                   source=f"{prices.source}; repeated to {days} days")

    @classmethod
    def from_series(
        cls,
        series: pd.Series,
        start: _dt.date | str | pd.Timestamp,
        days: int,
        sell_ratio: float = 0.5,
    ) -> Prices:
        """Prices from an hourly series (e.g. :func:`load_nordpool_csv`), via :func:`daily_matrix`.

        Clock-change days are mapped onto 24 hours as :func:`daily_matrix` describes.
        """
        buy = daily_matrix(series, start, days)
        name = series.name if series.name is not None else "series"
        first = _as_date(start, LOCAL_TZ)
        return cls(buy, sell_ratio=sell_ratio, source=f"{name}, {days} day(s) from {first}")
