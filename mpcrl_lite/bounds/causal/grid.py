r"""The discretised battery model of the causal DP: closed-form noise expectations and the grids.

One battery over one hour, with commanded net power ``a`` and post-decision state
``y = soc + alpha a``: the noise moves it to ``z = y + alpha Delta``, normal with mean
``y + alpha mu`` and standard deviation ``alpha sigma``; the low-level controller clips the
next state to ``soc^+ = clip(z, 0, 1)`` and changes the applied net power to

.. math:: \mathrm{net}(z) = a + \frac{(-z)^+}{\alpha} - \frac{(z - 1)^+}{\alpha}

(:func:`mpcrl_lite.system.battery.low_level_control`). Every expectation the DP needs is a sum of
Gaussian hinge expectations ``E[(z - c)^+] = s phi(d) + (m - c) Phi(d)``, ``d = (m - c)/s``
(:func:`hinge_expectations`), so all are taken in closed form with the normal CDF and PDF:

* the expected economic cost ``E[phi_b net^+ - phi_s net^-]`` (:func:`expected_net_power`,
  :func:`expected_agent_cost`);
* the expectation of a piecewise-linear function of ``soc^+`` (the interpolated value
  function), linear in its node values with weights ``E[hat_j(soc^+)]``
  (:func:`interpolation_weights`): per linear piece the mass and first moment of the normal
  law, plus the clip's point masses at 0 and 1.

Quadrature would converge slowly here: the integrands have kinks (the clip, the controller's
switch, the penalty), which the closed forms treat exactly.

:class:`SocGrid` fixes the discretisation: soc nodes ``j / (G - 1)``, actions on multiples of
``action_step``, and the post-decision grid they land on.
"""

from __future__ import annotations

import itertools
import math
from typing import Any

import numpy as np
from scipy.special import ndtr

from ...config import SystemConfig
from ...system.battery import unchecked_penalty
from ...system.prices import Prices
from .kernels import expected_cost_rows

__all__ = [
    "SocGrid",
    "day_prices",
    "distinct_days",
    "expected_agent_cost",
    "expected_net_power",
    "hinge_expectations",
    "interpolation_weights",
]

_INV_SQRT_2PI = 1.0 / math.sqrt(2.0 * math.pi)


def _pdf(d: np.ndarray) -> np.ndarray:
    return _INV_SQRT_2PI * np.exp(-0.5 * d * d)


def hinge_expectations(mean: Any, std: float, c: Any) -> tuple[np.ndarray, np.ndarray]:
    """``E[(z - c)^+]`` and ``E[(c - z)^+]`` for ``z ~ N(mean, std^2)``, elementwise.

    .. math:: \\mathbb E(z - c)^+ = s\\,\\varphi(d) + (m - c)\\,\\Phi(d), \\qquad
              \\mathbb E(c - z)^+ = s\\,\\varphi(d) + (c - m)\\,\\Phi(-d), \\qquad
              d = (m - c)/s

    (``std = 0``: the hinges of the mean).

    Parameters
    ----------
    mean, c : array_like, broadcastable
    std : float, >= 0

    Returns
    -------
    above, below : numpy.ndarray, the broadcast shape
    """
    m = np.asarray(mean, dtype=float)
    c = np.asarray(c, dtype=float)
    if std == 0.0:
        return np.maximum(m - c, 0.0), np.maximum(c - m, 0.0)
    d = (m - c) / std
    tail = std * _pdf(d)
    return tail + (m - c) * ndtr(d), tail + (c - m) * ndtr(-d)


def interpolation_weights(y: Any, nodes: Any, system: SystemConfig) -> np.ndarray:
    """``w_j(y) = E[hat_j(clip(y + alpha Delta, 0, 1))]`` for the hat functions of ``nodes``.

    For node values ``V_j`` with piecewise-linear interpolant ``Vhat``,
    ``E[Vhat(soc^+)] = sum_j w_j(y) V_j`` exactly (``soc^+ = clip(y + alpha Delta)``,
    ``Delta ~ N(noise_mean, noise_var)``). On a piece ``[x_j, x_{j+1}]`` of width ``h`` the
    mass ``P`` and ``T = E[(z - x_j)/h; piece]`` give ``x_j`` the weight ``P - T`` and
    ``x_{j+1}`` the weight ``T``; the clip puts ``P(z < 0)`` on node 0 and ``P(z > 1)`` on the
    last node. The weights are the probabilities of rounding ``soc^+`` at random to a
    neighbouring node with the probabilities of linear interpolation.

    Parameters
    ----------
    y : array_like, shape ``(K,)``
        Post-decision states ``soc + alpha a`` (any real values).
    nodes : array_like, shape ``(G,)``
        Increasing, from 0 to 1.
    system : SystemConfig

    Returns
    -------
    numpy.ndarray, shape ``(K, G)``
        Non-negative rows that sum to one.
    """
    y = np.atleast_1d(np.asarray(y, dtype=float))
    nodes = np.asarray(nodes, dtype=float)
    if (nodes.ndim != 1 or nodes.size < 2 or nodes[0] != 0.0 or nodes[-1] != 1.0
            or np.any(np.diff(nodes) <= 0)):
        raise ValueError("nodes: expected an increasing grid from 0 to 1 with at least 2 points")
    if y.ndim != 1 or not np.all(np.isfinite(y)):
        raise ValueError("y: expected a finite 1-d array of post-decision states")
    m = (y + system.alpha * system.noise_mean)[:, None]
    s = system.alpha * system.noise_std
    if s == 0.0:
        z = np.clip(m[:, 0], 0.0, 1.0)
        return np.stack([np.interp(z, nodes, e) for e in np.eye(nodes.size)], axis=1)
    lo, hi = nodes[None, :-1], nodes[None, 1:]
    a, b = (lo - m) / s, (hi - m) / s
    # mass of a piece, without cancellation in the upper tail
    mass = np.where(a > 0, ndtr(-a) - ndtr(-b), ndtr(b) - ndtr(a))
    moment = (s * (_pdf(a) - _pdf(b)) + (m - lo) * mass) / (hi - lo)
    w = np.zeros((y.size, nodes.size))
    w[:, :-1] += mass - moment
    w[:, 1:] += moment
    w[:, 0] += ndtr(-m[:, 0] / s)
    w[:, -1] += ndtr((m[:, 0] - 1.0) / s)
    return w


def expected_net_power(soc: Any, a: Any, system: SystemConfig) -> tuple[np.ndarray, np.ndarray]:
    """``E[net]`` and ``E[net^+]`` of the net power the low-level controller applies.

    With ``z = soc + alpha (a + Delta)`` (module docstring):

    * ``E[net] = a + (E(0 - z)^+ - E(z - 1)^+) / alpha``;
    * ``a >= 0``: the controller only turns the net power negative above
      ``1 + alpha a``, so ``net^+ = net + (z - 1 - alpha a)^+ / alpha``;
    * ``a < 0``: it only turns it positive below ``alpha a``, so
      ``net^+ = (alpha a - z)^+ / alpha``.

    Parameters
    ----------
    soc, a : array_like, broadcastable
        State of charge in ``[0, 1]`` and commanded net power.
    system : SystemConfig

    Returns
    -------
    E_net, E_net_plus : numpy.ndarray, the broadcast shape
    """
    alpha = system.alpha
    soc = np.asarray(soc, dtype=float)
    a = np.asarray(a, dtype=float)
    mean = soc + alpha * (a + system.noise_mean)
    std = alpha * system.noise_std
    below0 = hinge_expectations(mean, std, 0.0)[1]
    above1 = hinge_expectations(mean, std, 1.0)[0]
    e_net = a + (below0 - above1) / alpha
    above_cut = hinge_expectations(mean, std, 1.0 + alpha * np.maximum(a, 0.0))[0]
    below_cut = hinge_expectations(mean, std, alpha * np.minimum(a, 0.0))[1]
    return e_net, np.where(a >= 0, e_net + above_cut / alpha, below_cut / alpha)


def expected_agent_cost(soc: Any, a: Any, buy: Any, sell: Any, system: SystemConfig) -> np.ndarray:
    """``E[L~_i]`` of one hour for commanded net power ``a`` at ``soc``.

    ``penalty(soc) + phi_s E[net] + (phi_b - phi_s) E[net^+]``: the penalty of the state
    before the step and the prices of the applied power, as :func:`mpcrl_lite.system.battery.step`
    charges them (``phi_b net^+ - phi_s net^- = phi_s net + (phi_b - phi_s) net^+``).

    Parameters
    ----------
    soc, a, buy, sell : array_like, broadcastable
    system : SystemConfig

    Returns
    -------
    numpy.ndarray, the broadcast shape
    """
    e_net, e_plus = expected_net_power(soc, a, system)
    buy, sell = np.asarray(buy, dtype=float), np.asarray(sell, dtype=float)
    return sell * e_net + (buy - sell) * e_plus + unchecked_penalty(np.asarray(soc, dtype=float), system)


# -- the grids --------------------------------------------------------------------------------
def _integer(name: str, value: Any, low: int) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < low:
        raise ValueError(f"{name}={value!r}: expected an integer >= {low}")
    return int(value)


def _grid_inputs(system: Any, points: Any, action_step: Any) -> tuple[int, float]:
    """``(points, action_step)`` checked (a SystemConfig, at least 2 nodes, a positive finite
    step), or a one-line ``ValueError``: the checks of every soc grid, one battery's or a
    site's."""
    if not isinstance(system, SystemConfig):
        raise ValueError(f"system={system!r}: expected a SystemConfig")  # noqa: TRY004
    G = _integer("points", points, 2)
    if (isinstance(action_step, bool) or not isinstance(action_step, (int, float))
            or not (math.isfinite(action_step) and action_step > 0)):
        raise ValueError(f"action_step={action_step!r}: expected a positive number")
    return G, float(action_step)


def _ratio(x: float, step: float) -> int | None:
    """``x / step`` when it is an integer (to rounding), else None."""
    q = x / step
    return round(q) if abs(q - round(q)) <= 1e-9 * max(1.0, abs(q)) else None


class SocGrid:
    """Soc nodes, action steps and the post-decision grid, with the expectation tables.

    Parameters
    ----------
    system : SystemConfig
    points : int, default 41
        Nodes per battery, ``soc = j / (points - 1)``. The defaults put the penalty's kinks
        (0.1, 0.9) and ``soc0`` on nodes.
    action_step : float, default 0.1
        Commanded net powers are ``m * action_step`` with ``|m| <= M = floor(U_bar /
        action_step)``, at most ``B = floor(P_bar / action_step)`` steps summed over the
        batteries on each side (the grid limit). 0.1 MW reaches ``U_bar = 1`` and
        ``P_bar = 1.5`` exactly. The soc spacing must be an integer multiple ``r`` of
        ``h_y = alpha * action_step``.

    Attributes
    ----------
    nodes : numpy.ndarray, shape ``(G,)``
    steps, actions : numpy.ndarray, shape ``(2M + 1,)``
        ``-M..M`` and ``steps * action_step``.
    post_nodes : numpy.ndarray, shape ``(Gy,)``
        ``-M h_y, ..., 1 + M h_y``; node ``j`` with step ``m`` lands on ``r j + m + M``.
    weights : numpy.ndarray, shape ``(Gy, G)``
        :func:`interpolation_weights` of the post-decision nodes.
    penalty : numpy.ndarray, shape ``(G,)``
    e_net, e_net_plus : numpy.ndarray, shape ``(G, 2M + 1)``
        :func:`expected_net_power` at every node and step.
    """

    def __init__(self, system: SystemConfig, points: int = 41, action_step: float = 0.1) -> None:
        G, step = _grid_inputs(system, points, action_step)
        self.system, self.points, self.action_step = system, G, step
        self.h = 1.0 / (G - 1)
        self.h_y = system.alpha * self.action_step
        r = _ratio(self.h, self.h_y)
        if r is None or r < 1:
            raise ValueError(
                f"points={G}, action_step={action_step!r}: the soc spacing 1/(points - 1) = "
                f"{self.h:.6g} must be an integer multiple of alpha * action_step = "
                f"{self.h_y:.6g}, i.e. points - 1 must divide 1 / (alpha * action_step) = "
                f"{1 / self.h_y:.6g}"
            )
        self.r = r
        self.M = math.floor(system.U_bar / self.action_step + 1e-9)
        self.B = math.floor(system.P_bar / self.action_step + 1e-9)
        if self.M < 1:
            raise ValueError(f"action_step={action_step!r}: expected at most U_bar = "
                             f"{system.U_bar:g}")
        self.nodes = np.linspace(0.0, 1.0, G)
        self.steps = np.arange(-self.M, self.M + 1)
        self.actions = self.steps * self.action_step
        self.post_nodes = (np.arange(r * (G - 1) + 1 + 2 * self.M) - self.M) * self.h_y
        self.weights = interpolation_weights(self.post_nodes, self.nodes, system)
        self.penalty = unchecked_penalty(self.nodes, system)
        self.e_net, self.e_net_plus = expected_net_power(self.nodes[:, None],
                                                         self.actions[None, :], system)

    def __repr__(self) -> str:
        return (f"SocGrid(points={self.points}, action_step={self.action_step:g}, r={self.r}, "
                f"M={self.M}, B={self.B}, post_nodes={self.post_nodes.size})")

    @property
    def exact_limits(self) -> bool:
        """Whether ``U_bar`` and ``P_bar`` are multiples of the action step (so reachable)."""
        s = self.system
        return (_ratio(s.U_bar, self.action_step) is not None
                and _ratio(s.P_bar, self.action_step) is not None)

    def describe(self) -> dict[str, Any]:
        """JSON-friendly description."""
        return {"points": self.points, "action_step": self.action_step, "r": self.r,
                "M": self.M, "B": self.B, "post_nodes": int(self.post_nodes.size),
                "exact_limits": self.exact_limits}

    def stage_cost(self, buy: float, sell: float, price_buy: float = 0.0,
                   price_sell: float = 0.0) -> np.ndarray:
        """Expected economic cost of one battery at every node and step, ``(G, 2M + 1)``.

        ``phi_s E[net] + (phi_b - phi_s) E[net^+] + price_buy a^+ + price_sell a^-``; the
        last two terms price the commanded power (the grid limit's multipliers).
        """
        cost = sell * self.e_net + (buy - sell) * self.e_net_plus
        if price_buy or price_sell:
            cost = cost + (price_buy * np.maximum(self.actions, 0.0)
                           + price_sell * np.maximum(-self.actions, 0.0))
        return cost

    def cost_at(self, soc: np.ndarray, buy: float, sell: float) -> np.ndarray:
        """:meth:`stage_cost` (without multipliers) at arbitrary states ``soc`` of shape
        ``(R, n)``; returns ``(R, n, 2M + 1)``."""
        soc = np.ascontiguousarray(soc, dtype=float)
        R = soc.shape[0]
        s = self.system
        return expected_cost_rows(soc, np.full(R, float(buy)), np.full(R, float(sell)),
                                  self.actions, s.alpha, s.noise_mean, s.noise_std)

    def prefixes(self, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Joint steps of ``n`` batteries within the grid limit, enumerated by prefix.

        Returns
        -------
        prefixes : int64 array, shape ``(P, n - 1)``
            Steps of batteries ``1..n-1`` with ``sum m^+ <= B`` and ``sum m^- <= B``.
        lo, hi : int64 arrays, shape ``(P,)``
            The last battery's steps ``lo..hi`` that keep both sums within ``B``.
        """
        n = _integer("n", n, 1)
        M, B = self.M, self.B
        rows, lo, hi = [], [], []
        for pre in itertools.product(range(-M, M + 1), repeat=n - 1):
            up = sum(max(m, 0) for m in pre)
            down = sum(max(-m, 0) for m in pre)
            if up <= B and down <= B:
                rows.append(pre)
                lo.append(-min(M, B - down))
                hi.append(min(M, B - up))
        return (np.array(rows, dtype=np.int64).reshape(len(rows), n - 1),
                np.array(lo, dtype=np.int64), np.array(hi, dtype=np.int64))


def day_prices(system: SystemConfig, prices: Prices | None) -> tuple[np.ndarray, np.ndarray]:
    """Buying and selling prices of every day's ``hours_per_day`` hours, each ``(days, H)``.

    ``prices=None`` is :meth:`Prices.default` (the paper's 30 days).
    """
    if not isinstance(system, SystemConfig):
        raise ValueError(f"system={system!r}: expected a SystemConfig")  # noqa: TRY004
    if prices is None:
        prices = Prices.default(system)
    if not isinstance(prices, Prices):
        raise ValueError(f"prices={prices!r}: expected a mpcrl_lite.system.prices.Prices")  # noqa: TRY004
    H = system.hours_per_day
    if H > prices.buy.shape[1]:
        raise ValueError(f"hours_per_day={H}: expected at most {prices.buy.shape[1]}, the "
                         "hours of a price day")
    return prices.buy[:, :H].copy(), prices.sell[:, :H].copy()


def distinct_days(buy: np.ndarray, sell: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The days with distinct prices and, for every day, which of them it equals.

    Returns
    -------
    first : numpy.ndarray, shape ``(U,)``
        Index of the first day of each distinct price day, in order of appearance.
    day_of : numpy.ndarray, shape ``(days,)``
        For every day, its position in ``first``.
    """
    _, first, inverse = np.unique(np.hstack([buy, sell]), axis=0, return_index=True,
                                  return_inverse=True)
    order = np.argsort(first)
    rank = np.empty_like(order)
    rank[order] = np.arange(order.size)
    return first[order], rank[inverse.reshape(-1)]
