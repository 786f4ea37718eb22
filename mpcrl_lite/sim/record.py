r"""The one record of a simulated period: every array of a closed loop, hour by hour.

Every simulation of a policy on the true system (:func:`mpcrl_lite.sim.closed_loop.simulate`)
returns a :class:`Record`: a learning month, an evaluation month, a baseline on a common
scenario, a day of a widget, a rollout of a rule. The arrays are laid out hour first,
``(H, D, n)`` for ``H`` hours, ``D`` days advancing together and ``n`` batteries
(:data:`RECORD_ARRAYS`).

The closed-loop performance of the period is the paper's

.. math::
   J = \mathbb E\Big[\sum_{k=0}^{H-1} \gamma^k \tilde L(s_k, a_k)\Big],

estimated by the mean over the ``D`` days (:meth:`Record.J`); :math:`J^i` uses the agent's
own :math:`\tilde L_i` (:meth:`Record.J_per_agent`).

:class:`MonthRecord` is a :class:`Record` plus what only learning needs (the policy
sensitivities); it is the type :class:`~mpcrl_lite.learning.history.History` stores.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Any

import numpy as np

from ..config import SystemConfig
from ..system.battery import discounted_return

__all__ = ["MONTH_ARRAYS", "RECORD_ARRAYS", "MonthRecord", "Record", "Trajectory"]

#: The arrays of a :class:`Record`, with their shapes (H hours, D days, n agents); also the
#: names under which :meth:`Record.arrays` saves them.
RECORD_ARRAYS = {
    "soc": "(H+1, D, n) state of charge, soc_0 .. soc_H",
    "policy": "(H, D, n) the policy's action pi(s) before exploration",
    "a": "(H, D, n) commanded action (pi plus projected exploration)",
    "b": "(H, D, n) power bought (after the low-level controller)",
    "s": "(H, D, n) power sold (after the low-level controller)",
    "correction": "(H, D, n) extra net power of the low-level controller",
    "agent_cost": "(H, D, n) per-agent stage cost L~_i",
    "stage_cost": "(H, D) stage cost L~",
    "grid_power": "(H, D) applied grid power P_k",
    "planned_power": "(H, D) largest planned sum b or sum s over the MPC horizon",
    "noise": "(H, D, n) production-demand noise Delta",
    "buy": "(H, D) buying price of the hour",
    "solver_ok": "(H, D) the MPC converged",
    "sens_ok": "(H, D) the sensitivity was usable (False also where none was computed)",
}
#: The name the arrays had when only learning months were recorded.
MONTH_ARRAYS = RECORD_ARRAYS


@dataclass(eq=False)
class Record:
    """``H`` hours of ``D`` days in closed loop, all days advancing together.

    Attributes are the arrays of :data:`RECORD_ARRAYS` and the ``system`` simulated (it
    provides ``gamma`` and the soc band). For a policy that is not an MPC, ``policy`` is its
    output, ``planned_power`` the grid power of that output, ``solver_ok`` all True and
    ``sens_ok`` all False.
    """

    soc: np.ndarray
    policy: np.ndarray
    a: np.ndarray
    b: np.ndarray
    s: np.ndarray
    correction: np.ndarray
    agent_cost: np.ndarray
    stage_cost: np.ndarray
    grid_power: np.ndarray
    planned_power: np.ndarray
    noise: np.ndarray
    buy: np.ndarray
    solver_ok: np.ndarray
    sens_ok: np.ndarray
    system: SystemConfig

    # -- sizes ----------------------------------------------------------------------------
    @property
    def hours(self) -> int:
        """Number of simulated hours ``H``."""
        return self.a.shape[0]

    @property
    def days(self) -> int:
        """Number of days ``D`` in the batch."""
        return self.a.shape[1]

    @property
    def n(self) -> int:
        """Number of agents."""
        return self.a.shape[2]

    @property
    def trajectory(self) -> Record:
        """The record itself (records and trajectories used to be two types)."""
        return self

    # -- figures --------------------------------------------------------------------------
    def J_per_day(self) -> np.ndarray:
        """Discounted cost of each day, ``sum_k gamma^k L~_k``, shape ``(D,)``."""
        return discounted_return(self.stage_cost, self.system.gamma)

    def J(self) -> float:
        """Closed-loop performance estimate: the mean over days of :meth:`J_per_day`."""
        return float(self.J_per_day().mean())

    def J_per_agent(self) -> np.ndarray:
        """Per-agent ``J^i = mean_days sum_k gamma^k L~_i``, shape ``(n,)``."""
        return discounted_return(self.agent_cost, self.system.gamma).mean(axis=0)

    def hours_soc_below(self, level: float | None = None) -> int:
        """Number of (hour, day, agent) triples with ``soc_k < level``, ``k = 0..H-1``.

        ``level`` defaults to ``soc_low``. The final state ``soc_H`` is not counted, as in
        the cost, which charges ``soc_k`` for ``k < H``.
        """
        level = self.system.soc_low if level is None else _level(level)
        return int(np.count_nonzero(self.soc[:-1] < level))

    def hours_soc_above(self, level: float | None = None) -> int:
        """Number of (hour, day, agent) triples with ``soc_k > level``, ``k = 0..H-1``
        (``level`` defaults to ``soc_high``)."""
        level = self.system.soc_high if level is None else _level(level)
        return int(np.count_nonzero(self.soc[:-1] > level))

    def bound_share(self, tol: float = 0.05) -> float:
        """Share of the policy's actions (agent-hours) within ``tol`` of a constraint.

        An action ``pi_i`` counts when ``|pi_i| >= U_bar - tol`` (buying or selling at the
        battery's limit), ``|pi_i| <= tol`` (idle), or it takes part in a grid-limited group
        (``pi_i > 0`` and ``sum_j max(pi_j, 0) >= P_bar - tol``, likewise for selling). A
        bang-bang policy has a share of 1. Hours whose MPC failed are left out.
        """
        if not (np.isfinite(tol) and tol >= 0):
            raise ValueError(f"tol={tol!r}: expected a finite value >= 0")
        sysc = self.system
        a = self.policy
        U = np.array(sysc.battery("U_bar")) if isinstance(sysc.U_bar, tuple) else sysc.U_bar
        at_bound = (np.abs(a) >= U - tol) | (np.abs(a) <= tol)
        buy = np.clip(a, 0.0, None).sum(axis=-1, keepdims=True)
        sell = np.clip(-a, 0.0, None).sum(axis=-1, keepdims=True)
        grid = ((a > 0) & (buy >= sysc.P_bar - tol)) | ((a < 0) & (sell >= sysc.P_bar - tol))
        hit = (at_bound | grid)[self.solver_ok]
        return float(hit.mean()) if hit.size else float("nan")

    def hours_above_P_bar(self, tol: float = 1e-9) -> int:
        """Number of (hour, day) pairs whose applied grid power exceeds ``P_bar + tol``
        (the low-level controller's corrections can push it there; the MPC's planned powers
        respect ``P_bar``)."""
        return int(np.count_nonzero(self.grid_power > self.system.P_bar + tol))

    def summary(self) -> dict[str, Any]:
        """The period's key figures as JSON-friendly values."""
        return {
            "J": self.J(),
            "J_per_agent": self.J_per_agent().tolist(),
            "hours_soc_below_0_1": self.hours_soc_below(),
            "hours_soc_above_0_9": self.hours_soc_above(),
            "max_P_mpc": float(np.max(self.planned_power, initial=0.0, where=self.solver_ok)),
            "max_P_applied": float(np.max(self.grid_power)),
            "hours_above_P_bar": self.hours_above_P_bar(),
            "solver_failures": int(np.count_nonzero(~self.solver_ok)),
            "low_level_interventions": int(np.count_nonzero(np.abs(self.correction) > 1e-12)),
        }

    # -- storage --------------------------------------------------------------------------
    def arrays(self, prefix: str) -> dict[str, np.ndarray]:
        """The saved arrays, keys prefixed (e.g. ``first_soc``)."""
        return {f"{prefix}_{k}": getattr(self, k) for k in RECORD_ARRAYS}

    @classmethod
    def from_arrays(cls, data: Any, prefix: str, system: SystemConfig) -> Any:
        """Inverse of :meth:`arrays` (an instance of the class it is called on)."""
        return cls(**{k: np.asarray(data[f"{prefix}_{k}"]) for k in RECORD_ARRAYS},
                   system=system)

    def fields(self) -> dict[str, Any]:
        """The record's fields by name (the arrays are shared, not copied)."""
        return {f.name: getattr(self, f.name) for f in fields(Record)}


#: Records of single days were once a type of their own; the name stays for old code.
Trajectory = Record


@dataclass(eq=False)
class MonthRecord(Record):
    """A :class:`Record` of a learning month: adds the policy sensitivities.

    ``grad_pi`` (H, D, n_theta, n) holds :math:`\\nabla_\\theta\\pi_\\theta(s_k)` where it
    was computed (kept in memory for the update, never saved; None otherwise).
    """

    grad_pi: np.ndarray | None = None

    @classmethod
    def from_record(cls, record: Record, grad_pi: np.ndarray | None = None) -> MonthRecord:
        """``record`` with the learning extras (its arrays are shared, not copied)."""
        return cls(**record.fields(), grad_pi=grad_pi)


def _level(value: Any) -> float:
    arr = np.asarray(value, dtype=float)
    if arr.ndim != 0 or not np.isfinite(arr):
        raise ValueError(f"level={value!r}: expected a single finite number")
    return float(arr)
