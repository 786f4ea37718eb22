r"""An extension beside the paper's policy class: an MPC that knows the day ends at midnight.

In the experiment every day is an episode: the true cost (:mod:`mpcrl_lite.system.battery`) counts
the 24 hours of the day and nothing after them, since the next day restarts at ``soc0``.
The paper's MPC does not know this. Its 12-hour forecast (:meth:`Prices.window`) reads on
into the next day's prices, so at 20:00 it keeps charge to sell tomorrow morning, charge
that is worth nothing to the true cost. None of the paper's parameters can undo this: the
terminal cost :math:`T_\theta` is the same at every hour, while the value of the charge at
the end of the horizon is large in the afternoon and nil after midnight.

:class:`DayEndPrices` changes only the forecast: the prices of the hours after the day's
midnight are zero, so the MPC sees that energy bought or sold after midnight costs and earns
nothing. Everything else -- the MPC, its parameters theta, the learning -- is unchanged;
the true cost still uses the real prices (:attr:`Prices.buy`, :attr:`Prices.sell`).

Measured (``benchmarks/bench_learner_robustness.py``, the default learner, 20 learning seeds
never tuned on, 10 evaluation draws of the month each; ``benchmarks/README.md``): with this
forecast the final J has a median of -314 NOK/day (worst -281; the best causal policy earns
-401.5), against -217 (worst -167) for the paper's MPC. This is *not* the paper's policy class
and is never a default. It is chosen in one place, ``MPCConfig(forecast='until_midnight')``
(:data:`mpcrl_lite.config.FORECASTS`; ``--forecast until_midnight`` on the command line):
every learner, evaluation and baseline that builds the MPC from that config passes its prices
through :func:`forecast_prices`, and the run's History records the choice. Passing
``prices=until_midnight(prices)`` to :class:`~mpcrl_lite.learning.experiment.Experiment` does the same
(the learner then records ``forecast='until_midnight'``).
"""

from __future__ import annotations

import numpy as np

from .._util.validate import check_choice, check_instance
from ..config import FORECASTS, HOURS_PER_DAY, MPCConfig
from .prices import Prices

__all__ = ["DayEndPrices", "forecast_of", "forecast_prices", "until_midnight"]


class DayEndPrices(Prices):
    """:class:`~mpcrl_lite.system.prices.Prices` whose forecast stops at the end of the day.

    :meth:`window` is :meth:`Prices.window` with the prices of the hours after the day's
    midnight set to zero; :attr:`buy` and :attr:`sell` (what the true system is charged) are
    the real ones.

    Examples
    --------
    >>> prices = until_midnight(Prices.default())
    >>> buy, sell = prices.window(hour=20, N=12)   # 20:00 .. 23:00 priced, then zeros
    >>> bool((buy[:, 4:] == 0).all()), bool((buy[:, :4] > 0).all())
    (True, True)
    """

    def window(self, hour: int, N: int) -> tuple[np.ndarray, np.ndarray]:
        """Buying and selling prices over ``N`` hours from ``hour``, zero after midnight.

        Returns
        -------
        buy, sell : numpy.ndarray
            Each of shape ``(days, N)``.
        """
        buy, sell = super().window(hour, N)
        after = hour + np.arange(N) >= HOURS_PER_DAY  # (N,), hours of the next day(s)
        return np.where(after, 0.0, buy), np.where(after, 0.0, sell)

    def __repr__(self) -> str:
        return "DayEndPrices" + super().__repr__()[len("Prices"):]


def until_midnight(prices: Prices) -> DayEndPrices:
    """The same prices with a forecast that stops at midnight (:class:`DayEndPrices`)."""
    check_instance("prices", prices, Prices)
    return DayEndPrices(prices.buy, sell_ratio=prices.sell_ratio, unit=prices.unit,
                        source=f"{prices.source}; forecast until midnight",
                        origin=prices.origin)


def forecast_prices(prices: Prices, forecast: str | MPCConfig) -> Prices:
    """``prices`` as the MPC of ``forecast`` sees them.

    Parameters
    ----------
    prices : Prices
        The month; its :attr:`~Prices.buy` and :attr:`~Prices.sell` are what the true system
        is charged, whatever the forecast.
    forecast : str or MPCConfig
        One of :data:`~mpcrl_lite.config.FORECASTS`, or an MPC config (its ``forecast``).

    Returns
    -------
    Prices
        ``prices`` itself for ``'paper'``; :func:`until_midnight` of them for
        ``'until_midnight'`` (``prices`` itself if they already stop at midnight).
    """
    check_instance("prices", prices, Prices)
    if isinstance(forecast, MPCConfig):
        forecast = forecast.forecast
    forecast = check_choice("forecast", forecast, FORECASTS)
    if forecast == "paper" or isinstance(prices, DayEndPrices):
        return prices
    return until_midnight(prices)


def forecast_of(prices: Prices) -> str:
    """The forecast ``prices`` give the MPC: ``'until_midnight'`` for :class:`DayEndPrices`,
    else ``'paper'``."""
    return "until_midnight" if isinstance(prices, DayEndPrices) else "paper"
