r"""The coupled DP's grids and Bellman step for batteries that differ (up to three).

:mod:`mpcrl_lite.bounds.causal.dp` solves the same recursion for every system; this module
holds what changes when the per-battery fields (:data:`~mpcrl_lite.config.PER_BATTERY`:
``alpha``, the noise, ``U_bar``, ``p``, ``soc0``) differ from battery to battery:

* every battery has its own :class:`~mpcrl_lite.bounds.causal.grid.SocGrid` on the common soc
  nodes ``j / (G - 1)``: its own post-decision spacing ``h_{y,i} = alpha_i action_step``
  (``1 / (G - 1)`` must be a multiple of it), its own step bound ``M_i = U_bar_i /
  action_step``, its own expectation weights ``W_i`` and expected stage costs; the grid limit
  ``B = P_bar / action_step`` is the site's;
* the expectation of the interpolated ``V_{k+1}`` is still exact: the noise is independent
  across batteries, so ``E V_{k+1}`` on the post-decision grid is ``V_{k+1}`` contracted with
  ``W_i`` along axis ``i`` (:class:`MixedContraction`);
* ``V_k`` is no longer symmetric, so it is kept and minimised at every state of the product
  grid (``G^n``: 68 921 for three batteries at 41 nodes, against 12 341 multiset states), by
  the compiled loops :func:`~mpcrl_lite.bounds.causal.kernels.bellman_min3_mixed` (three
  batteries, the two-stage minimisation of the identical case) and
  :func:`~mpcrl_lite.bounds.causal.kernels.bellman_min_mixed` (one or two, by enumeration).

For identical batteries the result is the symmetric DP's to rounding (the tests check it);
:func:`~mpcrl_lite.bounds.causal.dp.causal_optimum` keeps the symmetric path for them.
"""

from __future__ import annotations

import itertools
import warnings
from typing import Any

import numpy as np

from ...config import PER_BATTERY, ConfigWarning, SystemConfig
from ...system.battery import unchecked_penalty
from .grid import SocGrid, _grid_inputs
from .kernels import bellman_min3_mixed, bellman_min_mixed, expected_cost_rows, greedy_mixed

__all__ = ["MAX_MIXED_BATTERIES", "BatteryGrids", "MixedContraction", "MixedStage",
           "battery_system"]

#: Most batteries that differ the coupled DP takes (its states are the full product grid).
MAX_MIXED_BATTERIES = 3


def battery_system(system: SystemConfig, i: int) -> SystemConfig:
    """Battery ``i`` of ``system`` alone: ``n = 1``, its own per-battery fields as scalars,
    the site's other fields (the grid limit ``P_bar`` among them)."""
    own = {name: system.battery(name)[i] for name in PER_BATTERY}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ConfigWarning)
        return system.replace(n=1, **own)


class BatteryGrids:
    """One :class:`~mpcrl_lite.bounds.causal.grid.SocGrid` per battery on common soc nodes.

    Parameters
    ----------
    system : SystemConfig
    points : int, default 41
        Soc nodes per battery.
    action_step : float, default 0.1
        MW; ``1 / (points - 1)`` must be a multiple of ``alpha_i * action_step`` for every
        battery (else a one-line error naming the battery).

    Attributes
    ----------
    grids : list of SocGrid
        Battery ``i``'s grid (built on :func:`battery_system`).
    points, action_step, B : the common nodes, step and grid limit (steps per side)
    M : numpy.ndarray, int64, shape ``(n,)``
        Each battery's step bound; ``Mx = M.max()`` fixes the width ``2 Mx + 1`` of the cost
        tables (battery ``i``'s step ``m`` in column ``m + Mx``).
    r, Gy : numpy.ndarray, int64, shape ``(n,)``
        Post-decision nodes per soc spacing and post-decision nodes of each battery.
    penalty : numpy.ndarray, shape ``(n, G)``
    """

    def __init__(self, system: SystemConfig, points: int = 41, action_step: float = 0.1) -> None:
        G, step = _grid_inputs(system, points, action_step)
        self.system, self.points, self.action_step = system, G, step
        self.grids = []
        for i in range(system.n):
            own = battery_system(system, i)
            try:
                self.grids.append(SocGrid(own, G, action_step))
            except ValueError as err:
                raise ValueError(f"battery {i} (alpha={own.alpha:.6g}, U_bar={own.U_bar:g}): "
                                 f"{err}") from None
        self.B = self.grids[0].B
        self.M = np.array([g.M for g in self.grids], dtype=np.int64)
        self.Mx = int(self.M.max())
        self.r = np.array([g.r for g in self.grids], dtype=np.int64)
        self.Gy = np.array([g.post_nodes.size for g in self.grids], dtype=np.int64)
        self.nodes = self.grids[0].nodes
        self.actions = np.arange(-self.Mx, self.Mx + 1) * self.action_step
        self.penalty = np.stack([g.penalty for g in self.grids])

    def __repr__(self) -> str:
        return f"BatteryGrids({', '.join(map(repr, self.grids))})"

    @property
    def exact_limits(self) -> bool:
        """Whether every battery's ``U_bar`` and the site's ``P_bar`` are reachable steps."""
        return all(g.exact_limits for g in self.grids)

    def describe(self) -> dict[str, Any]:
        """JSON-friendly description: the common fields and every battery's grid."""
        return {"points": self.points, "action_step": self.action_step, "B": self.B,
                "exact_limits": self.exact_limits,
                "batteries": [g.describe() for g in self.grids]}

    def _padded(self, tables: list[np.ndarray]) -> np.ndarray:
        """Per-battery ``(..., 2 M_i + 1)`` tables in one ``(n, ..., 2 Mx + 1)`` array, the
        steps a battery cannot take at ``+inf``."""
        out = np.full((len(tables), *tables[0].shape[:-1], 2 * self.Mx + 1), np.inf)
        for i, t in enumerate(tables):
            M = int(self.M[i])
            out[i, ..., self.Mx - M:self.Mx + M + 1] = t
        return out

    def stage_cost(self, buy: float, sell: float) -> np.ndarray:
        """Expected economic cost of every battery at every node and step, ``(n, G, 2Mx + 1)``
        (:meth:`SocGrid.stage_cost` of each)."""
        return self._padded([g.stage_cost(buy, sell) for g in self.grids])

    def cost_at(self, soc: np.ndarray, buy: float, sell: float) -> np.ndarray:
        """The expected economic cost at states ``soc`` ``(R, n)``: ``(R, n, 2 Mx + 1)``."""
        soc = np.ascontiguousarray(soc, dtype=float)
        R = soc.shape[0]
        out = np.full((R, soc.shape[1], 2 * self.Mx + 1), np.inf)
        for i, g in enumerate(self.grids):
            s, M = g.system, int(self.M[i])
            out[:, i, self.Mx - M:self.Mx + M + 1] = expected_cost_rows(
                np.ascontiguousarray(soc[:, i:i + 1]), np.full(R, float(buy)),
                np.full(R, float(sell)), g.actions, s.alpha, s.noise_mean, s.noise_std)[:, 0]
        return out

    def prefixes(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Joint steps within each battery's bound and the grid limit, by prefix: as
        :meth:`SocGrid.prefixes`, with battery ``i``'s steps in ``[-M_i, M_i]``."""
        M, B, n = self.M, self.B, len(self.grids)
        rows, lo, hi = [], [], []
        for pre in itertools.product(*(range(-int(m), int(m) + 1) for m in M[:-1])):
            up = sum(max(m, 0) for m in pre)
            down = sum(max(-m, 0) for m in pre)
            if up <= B and down <= B:
                rows.append(pre)
                lo.append(-min(int(M[-1]), B - down))
                hi.append(min(int(M[-1]), B - up))
        return (np.array(rows, dtype=np.int64).reshape(len(rows), n - 1),
                np.array(lo, dtype=np.int64), np.array(hi, dtype=np.int64))


class MixedContraction:
    """``EV[p_1..p_n] = sum_j prod_i W_i[p_i, j_i] V[j_1..j_n]``, one product per axis."""

    def __init__(self, weights: list[np.ndarray]) -> None:
        self.weights = weights
        self.shape = tuple(w.shape[0] for w in weights)

    def __call__(self, values: np.ndarray) -> np.ndarray:
        ev = values
        for w in self.weights:
            ev = np.tensordot(ev, w, axes=([0], [1]))  # the contracted axis moves last
        return np.ascontiguousarray(ev)

    def zeros(self) -> np.ndarray:
        """Post-decision values after the last hour."""
        return np.zeros(self.shape)


class MixedStage:
    """The Bellman minimisation of batteries that differ, at the nodes and at any state
    (the interface of the symmetric stage in :mod:`mpcrl_lite.bounds.causal.dp`)."""

    def __init__(self, system: SystemConfig, grid: BatteryGrids, max_post_values: int) -> None:
        n = system.n
        if n > MAX_MIXED_BATTERIES:
            raise ValueError(f"n={n}: the causal DP takes at most {MAX_MIXED_BATTERIES} "
                             "batteries that differ (use causal_dual.lagrangian_bound)")
        self.system, self.grid, self.n = system, grid, n
        post = int(np.prod(grid.Gy))
        if post > max_post_values:
            raise ValueError(
                f"n={n} with {list(grid.Gy)} post-decision nodes per battery needs {post:.3g}"
                f" values per hour (limit {max_post_values:.0e}): use fewer points, a larger "
                "action_step, or causal_dual.lagrangian_bound (any n)")
        G = grid.points
        self.shape = (G,) * n
        self.states = np.indices(self.shape).reshape(n, -1).T.copy()
        self.prefixes = grid.prefixes()
        self.contract = MixedContraction([g.weights for g in grid.grids])
        self.strides = np.array([int(np.prod(grid.Gy[i + 1:])) for i in range(n)],
                                dtype=np.int64)
        self.inv_hy = np.array([1.0 / g.h_y for g in grid.grids])
        # largest post-grid cell of each battery with an upper corner
        self.top = np.array([g.r * (G - 1) - 1 for g in grid.grids], dtype=np.int64)
        self._rings: tuple[np.ndarray, np.ndarray] | None = None

    @property
    def joint_actions(self) -> int:
        """Joint steps within the bounds and the grid limit."""
        return int((self.prefixes[2] - self.prefixes[1] + 1).sum())

    def full(self, values: np.ndarray) -> np.ndarray:
        """The value tensor, shape ``(G,) * n``, of values at the states (C order)."""
        return values.reshape(self.shape)

    def at_nodes(self, cost: np.ndarray, ev: np.ndarray) -> np.ndarray:
        """``V`` at every state of the product grid, shape ``(G ** n,)``."""
        g, gamma = self.grid, self.system.gamma
        if self.n == 3:
            if self._rings is None:
                shape = (2 * int(g.M[0]) + 1, int(g.Gy[1]), int(g.M[2]) + 1, g.points)
                self._rings = (np.empty(shape), np.empty(shape))
            return bellman_min3_mixed(g.points, g.r, g.M, g.Mx, g.B, cost, g.penalty, ev,
                                      gamma, *self._rings)
        return bellman_min_mixed(self.states, *self.prefixes, cost, g.penalty, ev.reshape(-1),
                                 self.strides, g.r, g.M, g.Mx, gamma)

    def at_states(self, soc: np.ndarray, buy: float, sell: float,
                  ev: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Best steps ``(R, n)`` and ``V`` ``(R,)`` at states ``soc`` of shape ``(R, n)``."""
        g = self.grid
        soc = np.ascontiguousarray(np.clip(soc, 0.0, 1.0))
        steps, value = greedy_mixed(soc, g.cost_at(soc, buy, sell), *self.prefixes,
                                    ev.reshape(-1), self.strides, self.inv_hy, self.top, g.M,
                                    g.Mx, self.system.gamma)
        return steps, value + unchecked_penalty(soc, self.system).sum(axis=1)
