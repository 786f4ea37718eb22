"""Day-ahead prices from the files users download today, as one hourly series type.

- :mod:`~mpcrl_lite.system.price_files.load`: :func:`load_prices`, the one entry point;
- :mod:`~mpcrl_lite.system.price_files.detect`: the format from the file's header;
- one reader per source: :mod:`~mpcrl_lite.system.price_files.nordpool_portal` (Nord Pool's
  data portal), :mod:`~mpcrl_lite.system.price_files.nordpool_elspot` (its old yearly
  export), :mod:`~mpcrl_lite.system.price_files.entsoe` and
  :mod:`~mpcrl_lite.system.price_files.entsoe_legacy` (ENTSO-E's Transparency Platform, 2025
  on and before), :mod:`~mpcrl_lite.system.price_files.energidataservice` (Energinet) and
  :mod:`~mpcrl_lite.system.price_files.pandas_series` (a Series, e.g. from entsoe-py);
- :mod:`~mpcrl_lite.system.price_files.areas`: the names of each bidding zone;
- :mod:`~mpcrl_lite.system.price_files.series`: the returned type (tz-aware, hourly, per
  MWh, currency recorded), quarter-hours to hours, missing and doubled periods;
- :mod:`~mpcrl_lite.system.price_files.currency`: EUR -> NOK;
- :mod:`~mpcrl_lite.system.price_files.month`: one month of a series as the learning month.
"""
