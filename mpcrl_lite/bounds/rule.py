r"""A price rule: charge below the day's median price, discharge above it, at full power
within the bounds and the grid limit (the baseline a learned MPC should clearly beat).
"""

from __future__ import annotations

import numpy as np

from ..config import SystemConfig
from ..system.battery import battery_values, project_action
from ..system.prices import Prices

__all__ = ['RuleBasedPolicy']


class RuleBasedPolicy:
    """Charge below the day's median price, discharge above it, at full power.

    At hour ``k`` of day ``d`` with buying price :math:`\\phi_{b,d,k}` and the day's median
    :math:`\\tilde\\phi_d`, every battery commands ``+U_bar`` if
    :math:`\\phi_{b,d,k} < \\tilde\\phi_d`, ``-U_bar`` if above, 0 on a tie (the day-ahead
    market publishes the whole day's prices, so the rule is causal in practice). With
    ``soc_guard`` the command is limited so that the *expected* next soc (noise at its mean)
    stays in ``[soc_low, soc_high]``: charging at most :math:`(soc_{high} - soc)/\\alpha -
    \\bar\\delta`, discharging at most :math:`(soc - soc_{low})/\\alpha + \\bar\\delta`, never
    below 0. The command is then projected onto the input bounds and the grid limit
    (:func:`~mpcrl_lite.system.battery.project_action`: batteries asking for the same direction share
    :math:`\\bar P` by an equal cut).

    Parameters
    ----------
    prices : Prices
    system : SystemConfig
    soc_guard : bool, default True
    """

    def __init__(self, prices: Prices, system: SystemConfig, soc_guard: bool = True) -> None:
        if not isinstance(soc_guard, bool):
            raise ValueError(f"soc_guard={soc_guard!r}: expected True or False")  # noqa: TRY004
        self.prices, self.system, self.soc_guard = prices, system, soc_guard
        self.median = np.median(prices.buy, axis=1)

    def __call__(self, hour: int, soc: np.ndarray) -> np.ndarray:
        sysc = self.system
        price = self.prices.buy[:, hour]
        direction = np.sign(self.median - price)[:, None]  # +1 buy (cheap), -1 sell
        U, alpha = battery_values(sysc, "U_bar"), battery_values(sysc, "alpha")
        mean = battery_values(sysc, "noise_mean")  # each battery's own
        a = np.broadcast_to(direction * U, soc.shape).copy()
        if self.soc_guard:
            room_up = np.maximum((sysc.soc_high - soc) / alpha - mean, 0.0)
            room_down = np.maximum((soc - sysc.soc_low) / alpha + mean, 0.0)
            a = np.clip(a, -room_down, room_up)
        return project_action(a, sysc)
