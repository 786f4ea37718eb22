r"""The clairvoyant bound: knows each day's noise and prices and optimizes the true cost.

The clairvoyant lower bound
---------------------------
For one day with known noise :math:`\Delta_{k,i}` and prices (hours :math:`k = 0..23`,
batteries :math:`i`, :math:`soc_{0,i}` given), the clairvoyant splits the applied powers
into a *commanded* part, bound by the input bounds and the grid limit, and the low-level
controller's *extra* power, which is not:

.. math::
   \min \sum_k \gamma^k \sum_i \Big[\phi_{b,k}(u^b_{k,i} + e^b_{k,i})
        - \phi_{s,k}(u^s_{k,i} + e^s_{k,i}) + p\,(\epsilon^{hi}_{k,i} + \epsilon^{lo}_{k,i})\Big]

subject to

.. math::
   soc_{k+1,i} &= soc_{k,i} + \alpha\big(\Delta_{k,i} + u^b_{k,i} + e^b_{k,i}
                 - u^s_{k,i} - e^s_{k,i}\big), \qquad 0 \le soc_{k,i} \le 1, \\
   0 \le u^b_{k,i}, u^s_{k,i} &\le \bar U, \qquad
   \textstyle\sum_i u^b_{k,i} \le \bar P,\quad \sum_i u^s_{k,i} \le \bar P, \\
   \epsilon^{hi}_{k,i} &\ge soc_{k,i} - 0.9,\quad \epsilon^{lo}_{k,i} \ge 0.1 - soc_{k,i},
   \quad \epsilon \ge 0 \quad (k \ge 1;\ \text{the penalty at } soc_0 \text{ is a constant}),

and the controller's reach, with :math:`m^b = \max(-\Delta, 0)`, :math:`m^s = \max(\Delta, 0)`:

.. math::
   0 \le e^b_{k,i} \le m^b_{k,i}\,\min\big(1 - soc_{k+1,i},\
       \epsilon^{lo}_{k+1,i}/0.1,\ \ell^b(soc_{k,i})\big), \qquad
   0 \le e^s_{k,i} \le m^s_{k,i}\,\min\big(soc_{k+1,i},\
       \epsilon^{hi}_{k+1,i}/0.1,\ \ell^s(soc_{k,i})\big),

where :math:`\ell` is the chord of the reach over :math:`soc_k \in [0, 1]` (the penalty
link is left out in the last hour, whose end state is not charged). It is a linear program,
solved per day with HiGHS.

**Why it is a lower bound.** Take any policy -- causal or not -- whose commanded action
:math:`a` obeys the input bounds and the grid limit (the evaluation projects every command,
see :func:`evaluate_policy`; for the MPCs and the rule this changes nothing). The low-level
controller leaves :math:`a` alone unless soc would leave :math:`[0, 1]`. If soc would fall
below 0, it raises the net power to :math:`-soc_k/\alpha - \Delta` and the battery ends the
hour *empty*; if soc would exceed 1, it lowers it to :math:`(1 - soc_k)/\alpha - \Delta` and
the battery ends *full*. So with :math:`u^b = \min(b, a^+)`, :math:`e^b = b - u^b` (and the
same for selling) for the applied powers :math:`b, s`: the commanded parts obey the bounds
and the grid limit; :math:`e^b > 0` only when :math:`soc_{k+1} = 0`, and then
:math:`e^b \le b \le \max(-soc_k/\alpha - \Delta, 0) \le m^b`, :math:`1 - soc_{k+1} = 1`
and :math:`\epsilon^{lo}_{k+1} = 0.1`; :math:`e^s > 0` only when :math:`soc_{k+1} = 1`,
symmetrically. Every reach constraint therefore holds, the soc trajectory (in
:math:`[0, 1]`) follows the dynamics with the applied powers, and with the exact penalties as
:math:`\epsilon` the LP objective equals the closed loop's discounted cost: the closed loop
of any such policy is a feasible point, and the LP optimum is at most its cost on *every*
day of the scenario.

Giving the clairvoyant the controller's extra power is necessary (a closed loop's applied
grid power exceeds :math:`\bar P` when the noise is large, so without it the closed loops
would not be feasible points and the "bound" could fail), but it is the extra power the
controller can really give -- tied to an empty or full battery and to the penalty that comes
with it -- not an unbounded corrective power, so the bound stays tight:
:attr:`ClairvoyantResult.J_replayed`, the cost of replaying the plan in closed loop, is an
achievable cost, and on the paper's system it lies within ~0.5 % of the bound.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import scipy.sparse as sp
from scipy.optimize import linprog

from ..sim.record import Record
from ..system.battery import battery_values, penalty
from .scenario import PolicyResult, Scenario, evaluate_policy

__all__ = ['ClairvoyantResult', 'clairvoyant', 'clairvoyant_lp']


# -- the clairvoyant LP -----------------------------------------------------------------------
@dataclass(frozen=True)
class _LPLayout:
    """Variable blocks of one day's LP, flat offsets; each block is ``(rows, n)``."""

    H: int
    n: int

    def sizes(self) -> dict[str, int]:
        H = self.H
        return {"ub": H, "us": H, "eb": H, "es": H, "soc": H, "ehi": H - 1, "elo": H - 1}

    def block(self, name: str) -> np.ndarray:
        start = 0
        for key, rows in self.sizes().items():
            if key == name:
                return start + np.arange(rows * self.n).reshape(rows, self.n)
            start += rows * self.n
        raise KeyError(name)

    @property
    def size(self) -> int:
        return sum(self.sizes().values()) * self.n


def clairvoyant_lp(
    scenario: Scenario, day: int
) -> tuple[np.ndarray, sp.csr_matrix, np.ndarray, sp.csr_matrix, np.ndarray, list, _LPLayout]:
    """The clairvoyant LP of one day as :func:`scipy.optimize.linprog` data.

    Variables (module docstring), each laid out hour-major ``(hours, n)``: commanded parts
    ``ub``, ``us``; the low-level controller's extra powers ``eb``, ``es``; ``soc_1 ..
    soc_H``; penalty epigraphs ``ehi``, ``elo`` of ``soc_1 .. soc_{H-1}`` (``soc_0`` is fixed
    and its penalty a constant; ``soc_H`` is not charged, as in the closed-loop cost).

    Returns
    -------
    c, A_ub, b_ub, A_eq, b_eq, bounds, layout
        ``min c'z`` s.t. ``A_ub z <= b_ub``, ``A_eq z = b_eq`` and ``bounds``; ``layout``
        locates the blocks in ``z``.
    """
    sysc = scenario.system
    valid_day = isinstance(day, (int, np.integer)) and not isinstance(day, bool)
    if not valid_day or not 0 <= day < scenario.days:
        raise ValueError(f"day={day!r}: expected an integer in [0, {scenario.days})")
    H, n = sysc.hours_per_day, sysc.n
    # each battery's own (floats when one value serves all: the same numbers as a scalar)
    alpha, U, p = (battery_values(sysc, name) for name in ("alpha", "U_bar", "p"))
    lay = _LPLayout(H, n)
    iub, ius, ieb, ies = (lay.block(k) for k in ("ub", "us", "eb", "es"))
    isoc, ihi, ilo = lay.block("soc"), lay.block("ehi"), lay.block("elo")
    noise = scenario.noise[:, day, :]  # (H, n)
    disc = sysc.gamma ** np.arange(H)
    c = np.zeros(lay.size)
    for var, price in ((iub, scenario.buy[day]), (ieb, scenario.buy[day])):
        c[var] = (disc * price)[:, None]
    for var, price in ((ius, scenario.sell[day]), (ies, scenario.sell[day])):
        c[var] = -(disc * price)[:, None]
    c[ihi] = c[ilo] = p * disc[1:, None]

    def sparse(terms: list[tuple[np.ndarray, np.ndarray, Any]], rows: int) -> sp.csr_matrix:
        r = np.concatenate([t[0].ravel() for t in terms])
        col = np.concatenate([t[1].ravel() for t in terms])
        v = np.concatenate([np.broadcast_to(t[2], t[0].shape).ravel() for t in terms])
        return sp.csr_matrix((v, (r, col)), shape=(rows, lay.size))

    # dynamics: soc_{k+1} - soc_k - alpha (ub + eb - us - es)_k = alpha Delta_k
    r = np.arange(H * n).reshape(H, n)
    A_eq = sparse([(r, isoc, 1.0), (r, iub, -alpha), (r, ieb, -alpha), (r, ius, alpha),
                   (r, ies, alpha), (r[1:], isoc[:-1], -1.0)], H * n)
    b_eq = (alpha * noise).ravel()
    b_eq[:n] += scenario.soc0[day]

    terms: list[tuple[np.ndarray, np.ndarray, Any]] = []
    rhs: list[np.ndarray] = []
    count = 0

    def row(shape: tuple[int, ...]) -> np.ndarray:
        nonlocal count
        index = count + np.arange(int(np.prod(shape))).reshape(shape)
        count += index.size
        return index

    # grid limit on the commanded parts
    for var in (iub, ius):
        g = row((H,))
        terms.append((np.repeat(g, n).reshape(H, n), var, 1.0))
        rhs.append(np.full(H, sysc.P_bar))
    # the controller's reach: extra buying only down at soc_{k+1} = 0, extra selling only up
    # at soc_{k+1} = 1, at most the noise it compensates
    m_buy, m_sell = np.maximum(-noise, 0.0), np.maximum(noise, 0.0)
    soc_prev = (isoc[:-1], scenario.soc0[day])  # soc_k for k >= 1 (variables), soc_0 fixed
    for extra, m, sign in ((ieb, m_buy, 1.0), (ies, m_sell, -1.0)):
        # eb <= m (1 - soc_{k+1});  es <= m soc_{k+1}
        q = row((H, n))
        terms += [(q, extra, 1.0), (q, isoc, sign * m)]
        rhs.append((m if sign > 0 else np.zeros_like(m)).ravel())
        # at soc_k: eb <= max(m - soc_k/alpha, 0) <= chord over soc_k in [0, 1], same for es
        far = np.maximum(m - 1.0 / alpha, 0.0)  # reach from the other end of the range
        near_coef = (far - m) if sign > 0 else (m - far)  # slope of the chord in soc_k
        base = m if sign > 0 else far
        q0 = row((1, n))
        terms.append((q0, extra[:1], 1.0))
        rhs.append((base[:1] + near_coef[:1] * soc_prev[1]).ravel())
        q1 = row((H - 1, n))
        terms += [(q1, extra[1:], 1.0), (q1, soc_prev[0], -near_coef[1:])]
        rhs.append(base[1:].ravel())
    # ... and they put the next soc on the penalty's edge: elo_{k+1} = soc_low, ehi = 1 - soc_high
    if sysc.soc_low > 0:
        q = row((H - 1, n))
        terms += [(q, ieb[:-1], 1.0), (q, ilo, -m_buy[:-1] / sysc.soc_low)]
        rhs.append(np.zeros((H - 1) * n))
    if sysc.soc_high < 1:
        q = row((H - 1, n))
        terms += [(q, ies[:-1], 1.0), (q, ihi, -m_sell[:-1] / (1.0 - sysc.soc_high))]
        rhs.append(np.zeros((H - 1) * n))
    # penalty epigraphs
    q = row((H - 1, n))
    terms += [(q, isoc[:-1], 1.0), (q, ihi, -1.0)]
    rhs.append(np.full((H - 1) * n, sysc.soc_high))
    q = row((H - 1, n))
    terms += [(q, isoc[:-1], -1.0), (q, ilo, -1.0)]
    rhs.append(np.full((H - 1) * n, -sysc.soc_low))
    A_ub = sparse(terms, count)
    b_ub = np.concatenate(rhs)

    upper = np.full(lay.size, np.inf)
    upper[iub] = upper[ius] = U
    upper[ieb], upper[ies] = m_buy, m_sell
    upper[isoc] = 1.0
    bounds = list(zip(np.zeros(lay.size), upper))
    return c, A_ub, b_ub, A_eq, b_eq, bounds, lay


@dataclass(frozen=True, eq=False)
class ClairvoyantResult(PolicyResult):
    """The clairvoyant's plans as a :class:`PolicyResult`: ``trajectory.a`` (and
    ``trajectory.policy``) holds the commanded part ``ub - us``, ``trajectory.b``/``s`` the applied powers and
    ``trajectory.correction`` the controller's extra ``eb - es``.

    Attributes
    ----------
    J_replayed : float
        ``J`` of replaying the plan's applied net powers ``b - s`` as commands in closed loop
        (projected onto the input bounds and the grid limit): an achievable cost of a
        non-causal policy, so the best cost on these draws lies in ``[J, J_replayed]``.
    parts : dict of numpy.ndarray, each ``(hours, days, n)``
        The LP's ``ub``, ``us`` (commanded) and ``eb``, ``es`` (controller's extra).
    """

    J_replayed: float = float("nan")
    parts: dict[str, np.ndarray] = field(default_factory=dict)


def clairvoyant(scenario: Scenario) -> ClairvoyantResult:
    """Solve the clairvoyant LP of every day (HiGHS through :func:`scipy.optimize.linprog`).

    Returns
    -------
    ClairvoyantResult
        ``J`` is the lower bound of the module docstring; per-agent costs are evaluated at
        the LP's applied powers and soc, penalties with :func:`mpcrl_lite.system.battery.penalty`.
    """
    t0 = time.perf_counter()
    sysc = scenario.system
    H, D, n = sysc.hours_per_day, scenario.days, sysc.n
    soc = np.empty((H + 1, D, n))
    soc[0] = scenario.soc0
    parts = {key: np.empty((H, D, n)) for key in ("ub", "us", "eb", "es")}
    statuses = set()
    for d in range(D):
        c, A_ub, b_ub, A_eq, b_eq, bounds, lay = clairvoyant_lp(scenario, d)
        res = linprog(c, A_ub=A_ub, b_ub=b_ub, A_eq=A_eq, b_eq=b_eq, bounds=bounds,
                      method="highs")
        if res.status != 0:
            raise RuntimeError(f"clairvoyant LP of day {d} failed: {res.message}")
        z = np.maximum(res.x, 0.0)  # remove -1e-12 rounding on non-negative variables
        for key, part in parts.items():
            part[:, d] = z[lay.block(key)]
        soc[1:, d] = np.clip(z[lay.block("soc")], 0.0, 1.0)
        statuses.add(res.message)
    b, s = parts["ub"] + parts["eb"], parts["us"] + parts["es"]
    buy, sell = scenario.buy.T[:, :, None], scenario.sell.T[:, :, None]  # (H, D, 1)
    agent_cost = buy * b - sell * s + penalty(soc[:-1], sysc)
    commanded = parts["ub"] - parts["us"]
    power = np.maximum(parts["ub"].sum(-1), parts["us"].sum(-1))
    # the plan is the policy: its commands are the actions, its grid power the planned one
    trajectory = Record(
        soc=soc, policy=commanded, a=commanded, b=b, s=s, correction=parts["eb"] - parts["es"],
        agent_cost=agent_cost, stage_cost=agent_cost.sum(-1),
        grid_power=np.maximum(b.sum(-1), s.sum(-1)), planned_power=power,
        noise=np.array(scenario.noise), buy=np.array(scenario.buy.T),
        solver_ok=np.ones((H, D), bool), sens_ok=np.zeros((H, D), bool), system=sysc,
    )
    plan = b - s
    replayed = evaluate_policy(lambda hour, _soc: plan[hour], scenario, "clairvoyant replay").J
    info = {"lp_status": sorted(statuses), "J_replayed": replayed,
            "controller_extra_hours": int(np.count_nonzero(parts["eb"] + parts["es"] > 1e-9))}
    return ClairvoyantResult("clairvoyant", trajectory, power, 0, time.perf_counter() - t0, info,
                             replayed, parts)
