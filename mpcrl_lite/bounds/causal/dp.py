r"""The best causal policy: a stochastic dynamic program over the day, for all batteries at once.

Every policy the project learns is causal: at hour ``k`` it knows the states of charge and the
prices, not the noise to come. The clairvoyant LP of :mod:`mpcrl_lite.bounds.baselines` knows the noise
and bounds every policy from far below; the figure a causal learner can really reach is

.. math:: J^\star = \min_{\pi\ \text{causal}} \frac1D \sum_{d=1}^{D}
          \mathbb E\Big[\sum_{k=0}^{H-1} \gamma^k \tilde L(s_k, a_k)\Big],

with ``J`` exactly as the closed loop (:func:`mpcrl_lite.bounds.scenario.evaluate_policy`) measures
it: each day is an episode of ``H = hours_per_day`` hours that starts at ``soc0`` with its own
prices; hour ``k`` is charged ``gamma^k`` times the penalty of the state *before* the step plus
the prices of the powers the low-level controller really exchanged; the state after the last
hour is not charged (the next day restarts at ``soc0``), so the value after hour ``H - 1`` is
zero. The MPC's forecast reaches past midnight, but nothing of the next day enters ``J``.

The dynamic program
-------------------
Per day, backwards from ``V_H = 0``:

.. math:: V_k(s) = \sum_i p(s_i) + \min_{a \in A}\Big[\sum_i \mathbb E\,\ell_k(s_i, a_i)
          + \gamma\, \mathbb E\, V_{k+1}\big(\mathrm{clip}(s + \alpha a + \alpha\Delta, 0, 1)\big)
          \Big],

``A`` the input bounds and the grid limit on the *commanded* powers (``|a_i| <= U_bar``,
``sum_i a_i^+ <= P_bar``, ``sum_i a_i^- <= P_bar``; the controller's extra power is not
limited), ``p`` the soc penalty and ``E l_k`` the expected price of the applied power, in
closed form (:mod:`mpcrl_lite.bounds.causal.grid`). ``J^star`` (of the day) is ``V_0(soc0)``.

``V_k`` is kept on ``G`` nodes per battery and interpolated multilinearly; actions are the
multiples of ``action_step`` (0.1 MW: ``U_bar`` and ``P_bar`` are reached exactly), so from a
node every post-decision state ``s + alpha a`` lies on a regular post-decision grid
(:class:`~mpcrl_lite.bounds.causal.grid.SocGrid`). The expectation of the interpolant over the
clipped Gaussian is exact: one weight matrix ``W`` (post-decision nodes x soc nodes) per
battery, and, the noise being independent across batteries, the ``n``-dimensional expectation
is ``V_{k+1}`` contracted with ``W`` along every axis. For identical batteries ``V_k`` is
symmetric and is minimised only at the multiset states ``j_1 <= .. <= j_n`` (``G^3/6`` for
three batteries), in compiled loops (:mod:`mpcrl_lite.bounds.causal.kernels`).

Batteries that differ (per-battery ``alpha``, noise, ``U_bar``, ``p`` or ``soc0``; at most
three) are solved on the same soc nodes with one grid per battery
(:mod:`mpcrl_lite.bounds.causal.mixed`): battery ``i`` has its own post-decision spacing
``alpha_i action_step``, step bound and weights ``W_i``, the contraction uses ``W_i`` along
axis ``i``, and ``V_k``, no longer symmetric, is minimised at every state of the product grid
(``G^3``). Identical batteries written as per-battery lists take the symmetric path.

What is exact, what is estimated, what is bounded
--------------------------------------------------
The recursion is the *exact* optimum of a slightly different system, the **grid model**: the
same prices, costs, noise and controller, but after every hour each battery's soc is rounded at
random to a neighbouring node with the probabilities of linear interpolation (the rounding
keeps the mean). The approximations are that rounding (the soc grid) and the action grid; both
vanish under refinement, and the refinement is measured (``benchmarks/bench_causal.py``, the
tests). Hence three figures:

* :attr:`CausalBound.J_star` -- the grid model's optimum: an **estimate** of ``J^star``;
* the DP policy (:meth:`CausalBound.policy`: the same minimisation at the true states, with
  the expected costs in closed form there and ``E[V_{k+1}]`` interpolated) simulated in the
  closed loop on the true system: an **achievable** cost, so ``J^star`` is at most its
  expectation;
* :func:`mpcrl_lite.bounds.causal.dual.lagrangian_bound`: a **lower bound** by weak duality, for any
  ``n``.

Cost and memory
---------------
Per day and hour: one contraction (``G^n`` values into ``Gy^n`` post-decision values, three
matrix products) and the minimisation. With ``n = 3`` and the defaults (``G = 41``,
``Gy = 141``, 12 341 multiset states, 7 121 joint actions within the grid limit) a day takes
about 2 s of CPU on one core and the paper's month about a minute (60 s CPU measured; 61 nodes
take about 5 times longer); the kept value tables take ``days x (H - 1) x S x 8`` bytes
(68 MB for 30 days). The DP policy costs about 20 s of CPU for the contractions of the
post-decision values (one per price day and hour) plus about 1 ms per simulated day (30 000
days in 45 s). ``n = 1`` and ``2`` run in milliseconds; ``n >= 4`` is refused at the
defaults (``Gy^4`` values per hour) -- use the Lagrangian bound there.

Three batteries that differ cost more: ``G^3 = 68 921`` states, and the large battery of
``examples/mixed_site.yaml`` (``alpha = 1/24``) has 261 post-decision nodes against 141, so
5.2 million post-decision values per hour. The site's month takes about 3.5 minutes of CPU
(220 s measured on one core, about 8 s per price day) and its value tables 380 MB.

Figures for the paper's system
------------------------------
``n = 3``, the shipped month, NOK/day (``benchmarks/bench_causal.py``):

=====================================================  ==========================
coupled DP, 41 / 61 nodes (``J_star``, grid model)     -399.3 / -400.5
the same, extrapolated in ``h^2`` (Richardson)         -401.5
DP policy (41 nodes) in closed loop, 30 000 days       -401.4 +- 1.6 (std. error)
Lagrangian bound, 41 nodes / 241 nodes at 0.05 MW      -416.6 / -418.5
grid limit dropped (``lambda = 0``), 41 / 241 nodes    -438.2 / -440.2
=====================================================  ==========================

The grid model is pessimistic (its random rounding adds noise): on one battery its error falls
as ``h^2``, 2.1 NOK/day at 41 nodes for three batteries, which is what separates -399.3 from the
achievable -401.4.

The mixed site ``examples/mixed_site.yaml`` (one battery with ``alpha = 1/24``, noise variance
1, two with the paper's values), the shipped month, NOK/day:

=====================================================  ==========================
coupled DP on the product grid, 41 nodes (``J_star``)  -537.0 (220 s CPU)
DP policy in closed loop, 3 000 days                   -540.6 +- 6.1 (std. error)
the same, minus ``J_star`` of its days (paired)        -3.6 +- 3.6
Lagrangian bound, 41 nodes                             -568.3
=====================================================  ==========================
"""

from __future__ import annotations

import itertools
import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ...config import PER_BATTERY, SystemConfig
from ...system.battery import unchecked_penalty
from ...system.prices import Prices
from .grid import SocGrid, day_prices, distinct_days
from .kernels import bellman_min, bellman_min3, greedy3, greedy_actions
from .mixed import MAX_MIXED_BATTERIES, BatteryGrids, MixedStage

__all__ = [
    "MAX_POST_VALUES",
    "CausalBound",
    "CausalPolicy",
    "causal_optimum",
    "compare_with_optimum",
    "dp_grid",
]

#: Largest post-decision tensor the coupled DP builds (entries of 8 bytes).
MAX_POST_VALUES = 30_000_000


class _Symmetric:
    """Multiset states ``j_1 <= .. <= j_n`` (lexicographic) and the map to full tensors."""

    def __init__(self, G: int, n: int) -> None:
        self.shape = (G,) * n
        self.states = np.array(list(itertools.combinations_with_replacement(range(G), n)),
                               dtype=np.int64).reshape(-1, n)
        full = np.indices(self.shape).reshape(n, -1)
        key = np.ravel_multi_index(np.sort(full, axis=0), self.shape)
        where = np.empty(G ** n, dtype=np.int64)
        where[np.ravel_multi_index(self.states.T, self.shape)] = np.arange(len(self.states))
        self.to_full = where[key]

    def full(self, values: np.ndarray) -> np.ndarray:
        """The symmetric tensor, shape ``(G,) * n``, of values at the multiset states."""
        return values[self.to_full].reshape(self.shape)


class _Contraction:
    """``EV[p_1..p_n] = sum_j prod_i W[p_i, j_i] V[j_1..j_n]``, one product per axis.

    The buffers are kept between calls: fresh 20 MB arrays every hour cost more in page
    faults than the products themselves.
    """

    def __init__(self, weights: np.ndarray, n: int) -> None:
        self.weights, self.n = weights, n
        self.Gy, self.G = weights.shape
        G, Gy = self.G, self.Gy
        if n == 3:
            self._t1 = np.empty((G * G, Gy))
            self._t2 = np.empty((G, Gy, Gy))
        self._out = np.empty((Gy,) * n)

    def __call__(self, values: np.ndarray) -> np.ndarray:
        W, G, Gy = self.weights, self.G, self.Gy
        if self.n == 3:
            # last axis, then the middle one per first index, then the first in one product
            np.dot(values.reshape(G * G, G), W.T, out=self._t1)
            np.matmul(W, self._t1.reshape(G, G, Gy), out=self._t2)
            np.dot(W, self._t2.reshape(G, Gy * Gy), out=self._out.reshape(Gy, Gy * Gy))
            return self._out
        ev = values
        for _ in range(self.n):
            ev = np.tensordot(ev, W, axes=([0], [1]))  # the contracted axis moves last
        self._out[...] = ev
        return self._out

    def zeros(self) -> np.ndarray:
        """Post-decision values after the last hour."""
        self._out[...] = 0.0
        return self._out


def _morton(soc: np.ndarray, bits: int = 7) -> np.ndarray:
    """Z-order key of states in ``[0, 1]^n``: sorting by it keeps neighbours together."""
    cells = np.minimum((soc * (1 << bits)).astype(np.int64), (1 << bits) - 1)
    key = np.zeros(soc.shape[0], dtype=np.int64)
    for bit in range(bits - 1, -1, -1):
        for i in range(soc.shape[1]):
            key = (key << 1) | ((cells[:, i] >> bit) & 1)
    return key


class _Stage:
    """The Bellman minimisation of one system on one grid, at nodes and at any state."""

    def __init__(self, system: SystemConfig, grid: SocGrid) -> None:
        self.system, self.grid, self.n = system, grid, system.n
        Gy = grid.post_nodes.size
        if Gy ** self.n > MAX_POST_VALUES:
            raise ValueError(
                f"n={self.n} with {Gy} post-decision nodes per battery needs {Gy ** self.n:.3g}"
                f" values per hour (limit {MAX_POST_VALUES:.0e}): use fewer points, a larger "
                "action_step, or causal_dual.lagrangian_bound (any n)")
        self.sym = _Symmetric(grid.points, self.n)
        self.prefixes = grid.prefixes(self.n)
        self.contract = _Contraction(grid.weights, self.n)
        self.strides = np.array([Gy ** (self.n - 1 - i) for i in range(self.n)], dtype=np.int64)
        self.top = grid.r * (grid.points - 1) - 1  # largest post-grid cell with an upper corner
        self._rings: tuple[np.ndarray, np.ndarray] | None = None  # bellman_min3's work arrays

    @property
    def states(self) -> np.ndarray:
        """The multiset states ``(S, n)``."""
        return self.sym.states

    @property
    def joint_actions(self) -> int:
        """Joint steps within the bounds and the grid limit."""
        return int((self.prefixes[2] - self.prefixes[1] + 1).sum())

    def full(self, values: np.ndarray) -> np.ndarray:
        """The symmetric tensor, shape ``(G,) * n``, of values at the multiset states."""
        return self.sym.full(values)

    def at_nodes(self, cost: np.ndarray, ev: np.ndarray) -> np.ndarray:
        """``V`` at the multiset states, shape ``(S,)``."""
        g, gamma = self.grid, self.system.gamma
        if self.n == 3:
            if self._rings is None:
                shape = (2 * g.M + 1, g.post_nodes.size, g.M + 1, g.points)
                self._rings = (np.empty(shape), np.empty(shape))
            return bellman_min3(g.points, g.r, g.M, g.B, cost, g.penalty, ev, gamma,
                                *self._rings)
        return bellman_min(self.sym.states, *self.prefixes, cost, g.penalty, ev.reshape(-1),
                           self.strides, g.r, g.M, gamma)

    def at_states(self, soc: np.ndarray, buy: float, sell: float,
                  ev: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Best steps ``(R, n)`` and ``V`` ``(R,)`` at states ``soc`` of shape ``(R, n)``."""
        g, gamma = self.grid, self.system.gamma
        soc = np.clip(soc, 0.0, 1.0)
        # The problem is symmetric in the batteries: solve it with each row's states sorted
        # and the rows in Z order, so that consecutive rows read neighbouring blocks of ev
        # (rows in random order make the kernel wait on memory for every block).
        perm = np.argsort(soc, axis=1, kind="stable")
        ordered = np.take_along_axis(soc, perm, axis=1)
        rows = np.argsort(_morton(ordered), kind="stable")
        ordered = np.ascontiguousarray(ordered[rows])
        cost = g.cost_at(ordered, buy, sell)
        if self.n == 3:
            found, best = greedy3(ordered, cost, ev, 1.0 / g.h_y, self.top, g.M, g.B, gamma)
        else:
            found, best = greedy_actions(ordered, cost, *self.prefixes, ev.reshape(-1),
                                         self.strides, 1.0 / g.h_y, self.top, g.M, gamma)
        steps = np.empty_like(found)
        np.put_along_axis(steps, perm[rows], found, axis=1)
        unsorted = np.empty_like(steps)
        unsorted[rows] = steps
        value = np.empty_like(best)
        value[rows] = best
        return unsorted, value + unchecked_penalty(soc, self.system).sum(axis=1)


@dataclass(frozen=True, eq=False)
class CausalBound:
    """The coupled DP of every day (:func:`causal_optimum`).

    Attributes
    ----------
    system : SystemConfig
    grid : SocGrid or BatteryGrids
        The soc grid; for batteries that differ one per battery
        (:class:`~mpcrl_lite.bounds.causal.mixed.BatteryGrids`).
    buy, sell : numpy.ndarray, shape ``(days, H)``
    J_star_per_day : numpy.ndarray, shape ``(days,)``
        ``V_0(soc0)`` of each day: the grid model's optimum (an estimate of the causal optimum).
    values : numpy.ndarray or None, shape ``(distinct days, H - 1, S)``
        ``V_1 .. V_{H-1}`` at the multiset states (``V_H = 0``), at every state of the product
        grid (``S = G^n``, C order) for batteries that differ; None with
        ``keep_values=False``.
    day_of : numpy.ndarray, shape ``(days,)``
        Row of ``values`` of each day (days with equal prices share one).
    wall_time_s : float
    info : dict
        Sizes: states, joint actions, distinct price days; ``method``: ``"symmetric"``
        (identical batteries, multiset states) or ``"product"`` (batteries that differ).
    """

    system: SystemConfig
    grid: SocGrid | BatteryGrids
    buy: np.ndarray
    sell: np.ndarray
    J_star_per_day: np.ndarray
    values: np.ndarray | None
    day_of: np.ndarray
    wall_time_s: float
    info: dict[str, Any] = field(default_factory=dict)

    @property
    def J_star(self) -> float:
        """Mean of :attr:`J_star_per_day`, NOK/day."""
        return float(self.J_star_per_day.mean())

    @property
    def days(self) -> int:
        """Number of days."""
        return self.buy.shape[0]

    def value_table(self, day: int, hour: int) -> np.ndarray:
        """``V_hour`` of ``day`` on the node grid, shape ``(G,) * n`` (``1 <= hour <= H``)."""
        H, grid = self.system.hours_per_day, self.grid
        if self.values is None:
            raise ValueError("the value tables were not kept: rerun with keep_values=True")
        if not 0 <= day < self.days:
            raise ValueError(f"day={day!r}: expected an integer in [0, {self.days})")
        if not 1 <= hour <= H:
            raise ValueError(f"hour={hour!r}: expected an integer in [1, {H}]")
        if hour == H:
            return np.zeros((grid.points,) * self.system.n)
        if isinstance(grid, BatteryGrids):
            return self.values[self.day_of[day], hour - 1].reshape((grid.points,) * self.system.n)
        return _symmetric(grid.points, self.system.n).full(self.values[self.day_of[day],
                                                                       hour - 1])

    def rows_for(self, prices: Prices) -> np.ndarray:
        """Row of :attr:`values` for every day of ``prices``, shape ``(days,)``.

        Each day of ``prices`` must have the prices of one of the bound's days (e.g.
        :meth:`Prices.month` with more than 30 days repeats the month).
        """
        buy, sell = day_prices(self.system, prices)
        table = {row.tobytes(): int(self.day_of[d])
                 for d, row in enumerate(np.hstack([self.buy, self.sell]))}
        keys = [row.tobytes() for row in np.hstack([buy, sell])]
        missing = [d for d, key in enumerate(keys) if key not in table]
        if missing:
            raise ValueError(f"prices: day {missing[0]} ({len(missing)} day(s) in all) has "
                             "prices the bound was not solved for; run causal_optimum on them")
        return np.array([table[key] for key in keys], dtype=np.int64)

    def J_star_for(self, prices: Prices) -> np.ndarray:
        """``J_star`` of every day of ``prices`` (see :meth:`rows_for`), shape ``(days,)``."""
        per_row = np.empty(int(self.day_of.max()) + 1)
        per_row[self.day_of] = self.J_star_per_day
        return per_row[self.rows_for(prices)]

    def policy(self, prices: Prices | None = None) -> CausalPolicy:
        """The DP policy for the days of ``prices`` (default: the bound's own days; see
        :meth:`rows_for`)."""
        if self.values is None:
            raise ValueError("the value tables were not kept: rerun with keep_values=True")
        return CausalPolicy(self, self.day_of.copy() if prices is None else self.rows_for(prices))

    def summary(self) -> dict[str, Any]:
        """JSON-friendly figures."""
        return {"J_star": self.J_star, "J_star_per_day": self.J_star_per_day.tolist(),
                "grid": self.grid.describe(), "wall_time_s": self.wall_time_s, **self.info}


_SYMMETRIC: dict[tuple[int, int], _Symmetric] = {}


def _symmetric(G: int, n: int) -> _Symmetric:
    if (G, n) not in _SYMMETRIC:
        _SYMMETRIC.clear()  # keep one map: they are large
        _SYMMETRIC[(G, n)] = _Symmetric(G, n)
    return _SYMMETRIC[(G, n)]


class CausalPolicy:
    """The DP policy ``(hour, soc (days, n)) -> a (days, n)`` (:meth:`CausalBound.policy`).

    At any state it takes the joint action of the action grid that minimises
    ``sum_i E[l(soc_i, a_i)] + gamma E[V_{hour+1}](soc + alpha a)``: the expected stage
    costs in closed form at ``soc`` itself, the post-decision values interpolated
    multilinearly. On the nodes this is the DP's own minimisation. Its actions keep the input
    bounds and the grid limit, so :func:`~mpcrl_lite.system.battery.project_action` leaves them alone.

    Attributes
    ----------
    bound : CausalBound
    day_of : numpy.ndarray, shape ``(days,)``
        Row of ``bound.values`` of each day (row of ``soc``).
    failures : int
        Always 0 (read by the closed loop like an MPC's failed solves).
    """

    def __init__(self, bound: CausalBound, day_of: np.ndarray) -> None:
        self.bound, self.day_of = bound, np.asarray(day_of, dtype=np.int64)
        self.failures = 0
        self._stage = _stage(bound.system, bound.grid)
        self._rows = {int(u): np.flatnonzero(self.day_of == u) for u in np.unique(self.day_of)}
        self._price_day: dict[int, int] = {}
        for d in range(bound.days):
            self._price_day.setdefault(int(bound.day_of[d]), d)

    def __call__(self, hour: int, soc: np.ndarray) -> np.ndarray:
        sysc = self.bound.system
        H = sysc.hours_per_day
        if isinstance(hour, bool) or not isinstance(hour, (int, np.integer)) or not 0 <= hour < H:
            raise ValueError(f"hour={hour!r}: expected an integer in [0, {H})")
        soc = np.asarray(soc, dtype=float)
        if soc.shape != (self.day_of.size, sysc.n):
            raise ValueError(f"soc has shape {soc.shape}: expected (days, n) = "
                             f"{(self.day_of.size, sysc.n)}")
        steps = np.empty(soc.shape, dtype=np.int64)
        for u, rows in self._rows.items():
            steps[rows] = self.steps(self._price_day[u], hour, soc[rows])
        return steps * self.bound.grid.action_step

    def steps(self, day: int, hour: int, soc: np.ndarray) -> np.ndarray:
        """Action steps ``(R, n)`` at states ``soc`` ``(R, n)`` of one day of the bound."""
        b, st = self.bound, self._stage
        ev = st.contract.zeros() if hour == b.system.hours_per_day - 1 else st.contract(
            b.value_table(day, hour + 1))
        return st.at_states(soc, b.buy[day, hour], b.sell[day, hour], ev)[0]


def _stage(system: SystemConfig, grid: SocGrid | BatteryGrids) -> _Stage | MixedStage:
    """The Bellman step of ``system`` on ``grid``: symmetric for one :class:`SocGrid`, on the
    product grid for one grid per battery."""
    if isinstance(grid, BatteryGrids):
        return MixedStage(system, grid, MAX_POST_VALUES)
    return _Stage(system, grid)


def _identical(system: SystemConfig) -> SystemConfig | None:
    """``system`` with its per-battery fields as scalars (the symmetric DP), None when they
    differ (the DP on the product grid, for at most three batteries; more are refused in one
    line)."""
    values = {name: system.battery(name) for name in PER_BATTERY}
    differ = [name for name, v in values.items() if len(set(v)) > 1]
    if differ:
        if system.n > MAX_MIXED_BATTERIES:
            raise ValueError(
                f"n={system.n} with {', '.join(f'{name}={list(values[name])}' for name in differ)}"
                f": the causal DP takes at most {MAX_MIXED_BATTERIES} batteries that differ "
                "(lagrangian_bound handles any n)")
        return None
    scalars = {name: v[0] for name, v in values.items()
               if isinstance(getattr(system, name), tuple)}
    return system.replace(**scalars) if scalars else system


def causal_optimum(
    system: SystemConfig,
    prices: Prices | None = None,
    grid: int = 41,
    action_step: float = 0.1,
    keep_values: bool = True,
) -> CausalBound:
    """Solve the coupled DP of every day (module docstring).

    Parameters
    ----------
    system : SystemConfig
    prices : Prices, optional
        Default :meth:`Prices.default`, the paper's 30 days. Days with equal prices are solved
        once.
    grid : int, default 41
        Soc nodes per battery (:class:`~mpcrl_lite.bounds.causal.grid.SocGrid`).
    action_step : float, default 0.1
        MW; ``1 / (grid - 1)`` must be a multiple of ``alpha * action_step`` (of every
        battery's ``alpha``).
    keep_values : bool, default True
        Keep ``V_1 .. V_{H-1}`` for :meth:`CausalBound.policy` (68 MB for the default month
        with ``n = 3``; 380 MB for three batteries that differ).

    Identical batteries (also when written as per-battery lists of one value) are solved on
    the multiset states; batteries that differ (at most three) on the full product grid, each
    battery on its own grid (:mod:`mpcrl_lite.bounds.causal.mixed`).

    Returns
    -------
    CausalBound
    """
    buy, sell = day_prices(system, prices)
    if not isinstance(keep_values, bool):
        raise ValueError(f"keep_values={keep_values!r}: expected True or False")  # noqa: TRY004
    system, soc_grid = dp_grid(system, grid, action_step)
    return _solve(system, soc_grid, buy, sell, keep_values)


def dp_grid(system: SystemConfig, grid: int = 41,
            action_step: float = 0.1) -> tuple[SystemConfig, SocGrid | BatteryGrids]:
    """The system the DP solves and its soc grid: identical batteries on the symmetric grid
    (``system`` with scalar fields), batteries that differ one grid each."""
    same = _identical(system)
    if same is None:
        return system, BatteryGrids(system, grid, action_step)
    return same, SocGrid(same, grid, action_step)


def _solve(system: SystemConfig, soc_grid: SocGrid | BatteryGrids, buy: np.ndarray,
           sell: np.ndarray, keep_values: bool) -> CausalBound:
    """The backward recursion of every distinct day on ``soc_grid`` (either stage)."""
    stage = _stage(system, soc_grid)
    t0 = time.perf_counter()
    first, day_of = distinct_days(buy, sell)
    H = system.hours_per_day
    S = len(stage.states)
    values = np.empty((first.size, H - 1, S)) if keep_values else None
    j_day = np.empty(first.size)
    soc0 = np.full((1, system.n), system.soc0)
    for u, d in enumerate(first):
        ev = stage.contract.zeros()
        for k in range(H - 1, 0, -1):
            v = stage.at_nodes(soc_grid.stage_cost(buy[d, k], sell[d, k]), ev)
            if values is not None:
                values[u, k - 1] = v
            ev = stage.contract(stage.full(v))
        j_day[u] = stage.at_states(soc0, buy[d, 0], sell[d, 0], ev)[1][0]
    info = {"states": S, "joint_actions": stage.joint_actions, "distinct_days": int(first.size),
            "method": "product" if isinstance(soc_grid, BatteryGrids) else "symmetric"}
    return CausalBound(system, soc_grid, buy, sell, j_day[day_of], values, day_of,
                       time.perf_counter() - t0, info)


def compare_with_optimum(
    J: Mapping[str, float], J_star: float, nominal: str = "nominal"
) -> dict[str, dict[str, float | None]]:
    """Regret and gap closed of every policy against the causal optimum.

    * regret ``J - J_star`` (NOK/day): what a causal policy could still gain;
    * gap closed ``(J_nominal - J) / (J_nominal - J_star)``: 0 for the nominal MPC, 1 at the
      causal optimum (None without a nominal entry or when ``J_nominal <= J_star``).

    Parameters
    ----------
    J : mapping of policy name to its closed-loop cost (NOK/day)
    J_star : float
        E.g. :attr:`CausalBound.J_star` on the same prices.
    nominal : str, default "nominal"
        Name of the reference policy of the gap.

    Returns
    -------
    dict
        ``{name: {"J": .., "regret": .., "gap_closed": ..}}``.
    """
    j_nom = J.get(nominal)
    gap = None if j_nom is None else float(j_nom) - float(J_star)
    return {name: {"J": float(j), "regret": float(j) - float(J_star),
                   "gap_closed": ((float(j_nom) - float(j)) / gap
                                  if gap is not None and gap > 0 else None)}
            for name, j in J.items()}
