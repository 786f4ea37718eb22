"""Electricity prices: the default month, a Nord Pool reader, and MPC forecast windows.

The paper drives its batteries with the hourly day-ahead buying price ``phi_b`` of Trondheim
(Nord Pool zone NO3) in November 2020, and sells at ``phi_s = 0.5 phi_b``. Prices are in
:data:`~mpcrl_lite.config.PRICE_UNIT` (NOK/MWh).

Three layers, each usable alone:

* :func:`load_default_profile` -- the month shipped in ``data/`` as a ``(30, 24)`` array,
  rebuilt from daily aggregates as ``price[d, h] = daily_mean[d] + daily_std[d] * shape[h]``
  (see ``data/README.md`` for the provenance).
* the price files (:mod:`mpcrl_lite.system.price_files`): :func:`~mpcrl_lite.system.price_files.load.load_prices`
  reads the day-ahead prices of today's sources into an hourly, time-zone-aware
  :class:`pandas.Series`; :func:`load_nordpool_csv` (the old Nord Pool export) and
  :func:`daily_matrix` (a series cut into local-time days) are importable here too.
* :class:`Prices` -- a ``(days, 24)`` buying price matrix with the selling ratio, and the MPC's
  forecast window: at hour ``k`` the MPC sees the prices of hours ``k .. k+N-1``, reading on
  into the next day's prices after midnight; the month repeats, so its last day is followed by
  its first.
"""

from __future__ import annotations

import datetime as _dt
import itertools
import warnings
from collections.abc import Mapping
from dataclasses import dataclass, field, fields
from functools import lru_cache
from pathlib import Path
from types import MappingProxyType
from typing import Any

import numpy as np

from .._util.lazy import lazy_module, lazy_names
from .._util.resources import candidate_folders, package_folder
from .._util.validate import check_instance, check_int, check_real
from ..config import HOURS_PER_DAY, PRICE_LIMIT, PRICE_UNIT, PriceFileConfig, SystemConfig

#: pandas, imported when a CSV file is first read (it reads and parses every price file)
pd = lazy_module("pandas")

# The old Nord Pool reader and the day matrix moved to price_files; their names stay importable
# here (``from mpcrl_lite.system.prices import load_nordpool_csv``), loaded on first use: the
# readers (a dozen modules) are not needed to learn on the shipped month.
_MOVED = {"LOCAL_TZ": "series", "PriceFileWarning": "series", "daily_matrix": "month",
          "month_matrix": "month", "load_nordpool_csv": "nordpool_elspot",
          "nordpool_areas": "nordpool_elspot", "load_prices": "load"}
__getattr__ = lazy_names(__name__, {name: f"{__package__}.price_files.{home}"
                                    for name, home in _MOVED.items()})

__all__ = ["DATA_DIR", "Prices", "load_default_profile", "sell_prices"]

#: Folder of the shipped data, found through the package (never through the working directory):
#: ``mpcrl_lite/data`` in an installed wheel, the repository's ``data/`` in a checkout.
DATA_DIR: Path = package_folder("data")


_SHAPE_FILE = "no3_nov2020_intraday_shape.csv"
_DAILY_FILE = "no3_nov2020_daily.csv"
_DEFAULT_SOURCE = (
    "Nord Pool day-ahead, Trondheim (NO3), November 2020, rebuilt from daily aggregates "
    "(data/README.md)"
)



def sell_prices(buy: np.ndarray, sell_ratio: float) -> np.ndarray:
    """Selling prices of buying prices ``buy``: the paper's ``phi_s = r phi_b`` (``r`` =
    ``sell_ratio``) where ``phi_b >= 0``, and ``phi_s = (2 - r) phi_b`` where ``phi_b < 0``.

    Both are ``phi_s = phi_b - (1 - r) |phi_b|``: selling is never worth more than buying
    (the spread ``(1 - r) |phi_b|`` is never negative). With ``r phi_b`` also for negative
    prices (common in 2025) selling would be worth more than buying -- ``phi_b = -10`` would
    sell at ``-5`` -- and a battery could earn money by buying and selling the same energy in
    the same hour. For ``phi_b >= 0`` the value is ``sell_ratio * buy``, bit for bit.
    """
    buy = np.asarray(buy, dtype=float)
    spread = sell_ratio * buy
    if (buy < 0).any():
        return np.where(buy < 0, (2.0 - sell_ratio) * buy, spread)
    return spread


# ----------------------------------------------------------------------------------------------
# The shipped default month
# ----------------------------------------------------------------------------------------------


def _read_small_csv(path: Path) -> tuple[list[str], list[list[str]]]:
    """Header and rows (as strings, surrounding blanks removed) of a small comma-separated file."""
    import csv

    with open(path, newline="", encoding="utf-8") as fh:
        rows = [[cell.strip() for cell in row] for row in csv.reader(fh) if row]
    return (rows[0], rows[1:]) if rows else ([], [])


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
    # two small files of our own: the standard library reads them (pandas, ~0.7 s to import,
    # is loaded only for users' price files)
    shape_cols, shape_rows = _read_small_csv(shape_path)
    daily_cols, daily_rows = _read_small_csv(daily_path)
    if shape_cols != ["hour", "shape"] or [r[0] for r in shape_rows] != [
        str(h) for h in range(HOURS_PER_DAY)
    ]:
        raise ValueError(f"{shape_path}: expected columns hour,shape with hours 0..23 in order")
    if daily_cols != ["date", "daily_mean", "daily_std"]:
        raise ValueError(f"{daily_path}: expected columns date,daily_mean,daily_std")
    try:
        dates = [_dt.date.fromisoformat(r[0]) for r in daily_rows]
        mean = np.array([float(r[1]) for r in daily_rows])
        std = np.array([float(r[2]) for r in daily_rows])
        shape = np.array([float(r[1]) for r in shape_rows])
    except (ValueError, IndexError) as exc:
        raise ValueError(f"default price data: unreadable value ({exc})") from None
    steps = {(b - a).days for a, b in itertools.pairwise(dates)}
    if not dates or not steps <= {1}:
        raise ValueError(f"{daily_path}: expected consecutive dates, one row per day")
    profile = mean[:, None] + std[:, None] * shape[None, :]
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
    origin : mapping, optional
        For prices read from a file: ``file``, ``format``, ``area``, ``column``, ``month``,
        ``currency`` (of the file), ``unit`` and ``eur_rate`` (NOK per EUR, None if not
        converted); empty for the shipped month. Recorded in the run's History and
        ``summary.json``.

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
    origin: Mapping[str, Any] = field(default_factory=dict)

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
        object.__setattr__(self, "origin", MappingProxyType(dict(self.origin)))

    def __reduce__(self) -> tuple[Any, tuple[Any, ...]]:
        """Pickled through the constructor (``origin`` as a plain dict: a read-only mapping
        does not pickle), so prices reach a worker process started with ``spawn`` too."""
        values = tuple(dict(self.origin) if f.name == "origin" else getattr(self, f.name)
                       for f in fields(self))
        return (type(self), values)

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
        """Selling prices, shape ``(days, 24)``: ``phi_s = sell_ratio * phi_b`` where
        ``phi_b >= 0`` (:func:`sell_prices` for negative prices)."""
        return sell_prices(self.buy, self.sell_ratio)

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
            Each of shape ``(days, N)``; ``sell = sell_ratio * buy``. Read-only (the same
            arrays for every call with the same ``hour`` and ``N``).
        """
        hour = check_int("hour", hour, 0, HOURS_PER_DAY - 1)
        N = check_int("N", N, 1)
        # the prices are read-only, so each window is made once (a learning run asks for the
        # same 24 every month) and handed out read-only
        windows = self.__dict__.get("_windows")
        if windows is None:
            windows = {}
            object.__setattr__(self, "_windows", windows)
        found = windows.get((int(hour), int(N)))
        if found is None:
            ahead = int(hour) + np.arange(N)  # hours counted from today's midnight, (N,)
            day = (np.arange(self.days)[:, None] + ahead[None, :] // HOURS_PER_DAY) % self.days
            buy = self.buy[day, ahead[None, :] % HOURS_PER_DAY]  # (days, N)
            sell = sell_prices(buy, self.sell_ratio)
            buy.setflags(write=False)
            sell.setflags(write=False)
            found = windows[int(hour), int(N)] = (buy, sell)
        return found

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
            origin={**self.origin, "days": days} if self.origin else {},
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
            origin={**self.origin, "scale": factor} if self.origin else {},
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
        from .price_files.month import _as_date, daily_matrix
        from .price_files.series import LOCAL_TZ

        buy = daily_matrix(series, start, days)
        name = series.name if series.name is not None else "series"
        first = _as_date(start, LOCAL_TZ)
        return cls(buy, sell_ratio=sell_ratio, source=f"{name}, {days} day(s) from {first}")

    @classmethod
    def from_month(
        cls,
        series: pd.Series,
        month: str,
        system: SystemConfig | None = None,
        days: int | None = None,
    ) -> Prices:
        """Calendar ``month`` (``'YYYY-MM'``) of an hourly series (e.g. from
        :func:`~mpcrl_lite.system.price_files.load.load_prices`) as the learning month.

        Every hour of the month (its first ``days`` days) must have a price (the first
        missing hour is named otherwise); the series must be in :data:`PRICE_UNIT`
        (``attrs['unit']``, when present). The selling ratio and the price scale are
        ``system``'s, as for :meth:`default`; ``origin`` records the file, format, area,
        currency and conversion rate from the series' ``attrs``.
        """
        from .price_files.month import month_matrix

        system = SystemConfig() if system is None else system
        unit = series.attrs.get("unit", PRICE_UNIT)
        if unit != PRICE_UNIT:
            raise ValueError(f"prices in {unit}; expected {PRICE_UNIT} (load_prices(..., "
                             "currency='NOK') converts EUR at a stated rate)")
        buy = month_matrix(series, month, days)
        keys = ("source", "format", "area", "column", "currency", "eur_rate",
                "resolution_min")
        origin = {k: series.attrs.get(k) for k in keys}
        origin["file_currency"] = series.attrs.get("file_currency", origin["currency"])
        origin["file"] = origin.pop("source")
        origin.update(month=str(month), unit=unit, days=int(buy.shape[0]))
        name = series.name if series.name is not None else "series"
        if origin.get("column") and origin["column"] != name:
            name = f"{origin['column']} ({name})"
        where = origin["file"] or "series"
        rate = (f", EUR x {origin['eur_rate']:g} NOK/EUR" if origin.get("eur_rate") else "")
        prices = cls(buy, sell_ratio=system.sell_ratio, unit=unit, origin=origin,
                     source=f"{name}, {buy.shape[0]} day(s) from {month}-01 ({where}{rate})")
        return prices.scaled(system.price_scale)

    @classmethod
    def from_file(
        cls,
        config: PriceFileConfig,
        system: SystemConfig | None = None,
        days: int | None = None,
    ) -> Prices:
        """The month of a :class:`~mpcrl_lite.config.PriceFileConfig` (file, area, month,
        currency, rate, format) through :func:`~mpcrl_lite.system.price_files.load.load_prices`
        and :meth:`from_month`; its first ``days`` days when given (the whole month must have
        a price every hour). Hours without a price outside the month are not reported."""
        from .price_files.load import load_prices
        from .price_files.series import PriceFileWarning

        check_instance("config", config, PriceFileConfig)
        if not config.file:
            raise ValueError("config.file is empty; expected a price file (Prices.month gives "
                             "the shipped month)")
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", PriceFileWarning)
            series = load_prices(config.file, config.area or None, currency=config.currency,
                                 format=config.format or None, eur_rate=config.eur_rate)
        prices = cls.from_month(series, config.month, system)
        return prices.take(days) if days is not None and days < prices.days else prices
