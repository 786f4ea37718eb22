"""Prices in the model's currency: EUR/MWh series converted to NOK/MWh at a stated rate.

The model's costs and penalties are in NOK (:data:`~mpcrl_lite.config.PRICE_UNIT`), so a
price series in EUR is converted at ``eur_rate`` NOK per EUR, by default
:data:`~mpcrl_lite.config.EUR_NOK_RATE` (its source and date are stated there). The rate used
is recorded in the series' ``attrs['eur_rate']`` (and from there in the run's files).
"""

from __future__ import annotations

import math

from ..._util.lazy import lazy_module
from ...config import EUR_NOK_RATE

pd = lazy_module("pandas")  # imported when a file is first read

__all__ = ["CURRENCIES", "convert"]

#: Currencies a series may be converted to.
CURRENCIES = ("NOK", "EUR")


def convert(series: pd.Series, currency: str | None, eur_rate: float | None = None) -> pd.Series:
    """``series`` in ``currency`` (``None``: unchanged), EUR <-> NOK at ``eur_rate``."""
    have = series.attrs.get("currency")
    if eur_rate is not None and (isinstance(eur_rate, bool)
                                 or not isinstance(eur_rate, int | float)
                                 or not math.isfinite(eur_rate) or eur_rate <= 0):
        raise ValueError(f"eur_rate={eur_rate!r}: expected a positive number of NOK per EUR")
    if currency is None or currency == have:
        return series
    currency = str(currency).upper()
    if currency not in CURRENCIES:
        raise ValueError(f"currency={currency!r}: expected one of {', '.join(CURRENCIES)}")
    if (have, currency) not in (("EUR", "NOK"), ("NOK", "EUR")):
        raise ValueError(f"{series.attrs.get('source', 'series')}: prices in {have}; expected "
                         "EUR or NOK to convert to " + currency)
    rate = float(EUR_NOK_RATE if eur_rate is None else eur_rate)
    out = series * rate if currency == "NOK" else series / rate
    out.attrs = {**series.attrs, "currency": currency, "unit": f"{currency}/MWh",
                 "eur_rate": rate, "file_currency": have}
    return out
