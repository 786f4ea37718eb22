"""The true system and what it is given: prices, the batteries, the MPC's price forecast.

- :mod:`~mpcrl_lite.system.prices`: the default month, price files, forecast windows;
- :mod:`~mpcrl_lite.system.battery`: the batteries' noisy dynamics (paper eq. 1), the
  low-level controller, the stage costs (eqs. 2-3) and the grid power;
- :mod:`~mpcrl_lite.system.forecast`: the forecast that stops at midnight, an option beside
  the paper's.

May import: :mod:`mpcrl_lite.config`, :mod:`mpcrl_lite.theta`, :mod:`mpcrl_lite._util`.
"""
