"""The one entry point for price files: :func:`load_prices`."""

from __future__ import annotations

import os
from pathlib import Path

from ..._util.lazy import lazy_module
from . import energidataservice, entsoe, entsoe_legacy, nordpool_portal, pandas_series
from .areas import canonical, find_column
from .currency import convert
from .detect import FORMATS, detect_format
from .nordpool_elspot import load_nordpool_csv, nordpool_areas
from .series import hourly, read_text

pd = lazy_module("pandas")  # imported when a file is first read

__all__ = ["load_prices"]

_READERS = {m.NAME: m.read for m in (nordpool_portal, entsoe, entsoe_legacy, energidataservice)}


def _elspot(path: Path, area: str | None) -> pd.Series:
    column = find_column("Tr.heim" if area is None else area, nordpool_areas(path), str(path))
    old = load_nordpool_csv(path, column)
    title = read_text(path).split("\n", 1)[0]
    currency = "EUR" if "EUR" in title.upper() else "NOK"
    labels = [str(t) for t in old.index]
    return hourly(old.index, [60] * len(old), old.to_numpy(), labels, where=str(path),
                  area=canonical(column), column=column, currency=currency,
                  fmt="nordpool_elspot")


def load_prices(source: str | os.PathLike | pd.Series, area: str | None = None,
                currency: str | None = None, format: str | None = None, *,
                eur_rate: float | None = None, series_currency: str = "EUR") -> pd.Series:
    """Day-ahead prices from a file of any source this package reads, as an hourly series.

    The format is recognised from the file's header
    (:func:`~mpcrl_lite.system.price_files.detect.detect_format`): Nord Pool's data portal
    CSV, its old yearly "Elspot Prices" export, ENTSO-E's Transparency Platform CSV (2025 on,
    and before), Energi Data Service (``Elspotprices``, ``DayAheadPrices``); a
    :class:`pandas.Series` on a tz-aware index (what ``entsoe-py`` returns) is read too.

    Parameters
    ----------
    source : path or pandas.Series
        The file, or a series of prices.
    area : str, optional
        The bidding zone by any of its names (``'NO3'``, ``'Tr.heim'``, ``'Molde'``,
        ``'BZN|NO3'``, ``'DK2'``; the table in
        :mod:`~mpcrl_lite.system.price_files.areas`). Default: Tr.heim (NO3) for the old Nord
        Pool export, the file's only area for the ENTSO-E file before 2025; required
        otherwise.
    currency : {'NOK', 'EUR'}, optional
        Convert to this currency (EUR <-> NOK at ``eur_rate``); default: the file's.
    format : str, optional
        Force a format (one of :data:`~mpcrl_lite.system.price_files.detect.FORMATS`) instead
        of reading it from the header.
    eur_rate : float, optional
        NOK per EUR for a conversion (default :data:`~mpcrl_lite.config.EUR_NOK_RATE`).
    series_currency : str, default ``'EUR'``
        The currency of a :class:`pandas.Series` ``source`` (entsoe-py gives EUR/MWh).

    Returns
    -------
    pandas.Series
        Hourly prices per MWh on a tz-aware Europe/Oslo index: DST days have 23 and 25
        hours; quarter-hours are averaged to hours; hours without a price are NaN and
        reported (``attrs['missing']``). ``attrs`` records the unit, currency, area, file,
        format and conversion rate (:mod:`~mpcrl_lite.system.price_files.series`).

    Raises
    ------
    FileNotFoundError
        If the file does not exist.
    ValueError
        A one-line message naming the file and the row, area or value that is wrong.
    """
    if format is not None and format not in FORMATS:
        raise ValueError(f"format={format!r}: expected one of {', '.join(FORMATS)}")
    if isinstance(source, pd.Series):
        if format not in (None, "pandas"):
            raise ValueError(f"format={format!r} given with a pandas Series; expected 'pandas'")
        series = pandas_series.read(source, area, series_currency)
        return convert(series, currency, eur_rate)
    if format == "pandas":
        raise ValueError(f"format='pandas' given with {source!r}; expected a pandas Series")
    path = Path(source)
    where = str(path)
    text = read_text(path)
    found, header = detect_format(text, where) if format is None else (format, None)
    if found == "nordpool_elspot":
        series = _elspot(path, area)
    else:
        if header is None:
            header = next(i for i, line in enumerate(text.split("\n")) if line.strip())
        body = "\n".join(text.split("\n")[header:])
        if area is None and found != "entsoe_legacy":
            raise ValueError(f"{where}: a {found} file; expected area= (e.g. 'NO3')")
        series = _READERS[found](body, area, where, offset=header)
    return convert(series, currency, eur_rate)
