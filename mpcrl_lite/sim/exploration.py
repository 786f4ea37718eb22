r"""What the learner commands around the policy's action: exploration within the bounds.

The deterministic policy gradient learns from actions explored around the policy,
:math:`a = \pi_\theta(s) + e`. The commanded action must respect the input bounds
:math:`|a_i| \le \bar U` and the grid limit on both total buying and total selling; how the
exploration is kept inside them decides whether it keeps the zero mean the compatible
critic relies on (:mod:`mpcrl_lite.learning.lstd`). This module is the one home of that choice:

* :class:`GaussianExploration`, the closed loop's action hook (:mod:`mpcrl_lite.sim.closed_loop`),
  draws ``e`` and calls :func:`bounded_exploration` (``'symmetric'``, ``'radial'`` or
  ``'project'``) around :func:`exploration_center`;
* :class:`Projection`, the action hook of policies that are not MPCs (a rule's command put
  onto the feasible set).

The arithmetic of :func:`bounded_exploration` runs compiled
(:mod:`mpcrl_lite.sim.exploration_kernel`); ``tests/sim/test_explore_kernel.py`` holds its numpy
statement as the reference.
"""

from __future__ import annotations

import numpy as np

from .._util.lazy import lazy_module
from .._util.validate import check_choice, check_real
from ..config import EXPLORATION_BOUNDS, SystemConfig
from ..system.battery import project_action

#: :mod:`mpcrl_lite.sim.exploration_kernel`, imported at the first compiled exploration (numba
#: comes with it)
kernel = lazy_module("mpcrl_lite.sim.exploration_kernel")

__all__ = [
    "GaussianExploration",
    "Projection",
    "bounded_exploration",
    "check_margin",
    "exploration_center",
]


class GaussianExploration:
    r"""Action hook: the policy's action plus a Gaussian exploration ``std * N(0, I)`` that
    respects the input bounds and the grid limit.

    The exploration ``e`` is drawn from the loop's generator as one ``standard_normal`` of
    shape ``(days, n)`` per hour (times ``std``) and made feasible in one of three ways
    (``bounds``, see :func:`bounded_exploration`):

    * ``'symmetric'`` (default): ``e`` slides along the grid faces it could reach, each
      entry is clipped to the distance of :math:`\pi_i` to its nearer input bound, and the
      vector is shrunk until both :math:`\pi \pm e` are feasible. The map is odd in ``e``,
      so the applied exploration :math:`a - \pi` keeps a zero mean, as the compatible
      critic assumes (:mod:`mpcrl_lite.learning.lstd`);
    * ``'radial'``: the whole vector is shrunk until both :math:`\pi \pm e` are feasible
      (also odd, but little is left where the grid limit is nearly active);
    * ``'project'``: ``project_action(pi + e)``, the closest feasible action. Near a bound
      this shifts the mean of :math:`a - \pi` inwards (about +0.04 MW over a month at
      theta0 with ``std = 0.2``), which biases the critic.

    Parameters
    ----------
    std : float
        Standard deviation in MW, ``>= 0``.
    system : SystemConfig
    bounds : {'symmetric', 'radial', 'project'}, default 'symmetric'
    margin : float, default 0
        With ``margin > 0`` the exploration is centred on :func:`exploration_center` instead
        of :math:`\pi` (:meth:`center`); the critic must then use the same centre.
    """

    def __init__(
        self, std: float, system: SystemConfig, bounds: str = "symmetric", margin: float = 0.0
    ) -> None:
        if isinstance(std, bool) or not (np.isfinite(std) and std >= 0):
            raise ValueError(f"std={std!r}: expected a finite value >= 0")
        self.std, self.system = float(std), system
        self.bounds = check_choice("bounds", bounds, EXPLORATION_BOUNDS)
        self.margin = check_margin(margin, system)
        if self.margin and self.bounds == "project":
            raise ValueError(f"margin={margin!r} with bounds='project': a margin recentres a "
                             "zero-mean exploration; expected margin=0 or another bounds")
        # each battery's input bound, for the hours' compiled calls (bounded_exploration)
        self._upper = np.array(system.battery("U_bar"), dtype=float)

    def center(self, pi: np.ndarray) -> np.ndarray:
        """The centre of the exploration for the policy's actions ``pi`` (days, n):
        :func:`exploration_center` with this hook's margin."""
        return exploration_center(pi, self.system, self.margin)

    def __call__(self, hour: int, pi: np.ndarray, rng: np.random.Generator | None) -> np.ndarray:
        if rng is None:
            raise ValueError("exploration needs rng: expected a numpy.random.Generator")
        e = self.std * rng.standard_normal(np.shape(pi))
        if (self.margin or self.bounds == "project" or not isinstance(pi, np.ndarray)
                or pi.dtype != np.float64 or pi.ndim != 2 or pi.shape[1] != self.system.n
                or not np.isfinite(pi).all()):
            return bounded_exploration(self.center(pi), e, self.system, self.bounds)
        # the common case, an MPC's finite actions explored around themselves: the same
        # compiled call as bounded_exploration's, without its checks and set-up every hour
        return _explore_rows(pi, e, self._upper, self.system.P_bar, self.bounds == "symmetric")


def check_margin(margin: float, system: SystemConfig) -> float:
    """``margin`` as a float in ``[0, min(U_bar, P_bar) / 2]``, else an error naming it."""
    limit = 0.5 * min(min(system.battery("U_bar")), system.P_bar)
    return check_real("margin", margin, 0.0, limit)


def exploration_center(pi: np.ndarray, system: SystemConfig, margin: float) -> np.ndarray:
    r"""The point :math:`c(\pi)` the exploration is centred on: :math:`\pi` pulled inwards
    so that it is at least ``margin`` away from every input bound and from both grid limits.

    Each entry is clipped to :math:`\pm(U - m)`, then, on a side whose grid sum exceeds
    :math:`P - m`, that side's entries are scaled down to the sum :math:`P - m`. A policy at
    (or, with a barrier, very near) a bound still gets an exploration of about ``margin`` in
    both directions around :math:`c`, with zero mean; with ``margin = 0``, :math:`c = \pi`.

    The compatible critic then uses :math:`\psi = \nabla_\theta\pi\,(a - c(s))`, whose
    mean is zero at every state, so the state part of the cost cannot leak into :math:`w`;
    what it measures is :math:`\nabla_a Q_\pi` averaged over the actions explored around
    :math:`c`, which differs from its value at :math:`\pi` by about the curvature of
    :math:`Q_\pi` in :math:`a` times :math:`|c - \pi|` (at most ``margin`` per entry and
    per grid sum).

    Parameters
    ----------
    pi : numpy.ndarray, shape ``(days, n)``
        Feasible actions (an MPC's).
    system : SystemConfig
    margin : float
        In MW, ``0 <= margin <= min(U_bar, P_bar) / 2``.

    Returns
    -------
    numpy.ndarray, shape ``(days, n)``
        ``pi`` itself when ``margin = 0``.
    """
    margin = check_margin(margin, system)
    if margin == 0.0:
        return pi
    inner = (system.U_bar if isinstance(system.U_bar, float)
             else np.array(system.U_bar)) - margin  # each battery's own
    c = np.clip(pi, -inner, inner)
    room = system.P_bar - margin
    for sign in (1.0, -1.0):
        side = np.maximum(sign * c, 0.0)
        total = side.sum(axis=-1, keepdims=True)
        factor = np.where(total > room, room / np.maximum(total, room), 1.0)
        c = np.where(side > 0.0, sign * side * factor, c)
    return c


def bounded_exploration(
    pi: np.ndarray, e: np.ndarray, system: SystemConfig, bounds: str = "symmetric"
) -> np.ndarray:
    r"""The action :math:`a` commanded for the policy's :math:`\pi` and the exploration
    :math:`e`, within the input bounds and the grid limit.

    With ``U = U_bar``, ``P = P_bar`` and the feasible set
    :math:`\mathcal A = \{x: |x_i| \le U,\ \sum_i x_i^+ \le P,\ \sum_i x_i^- \le P\}`:

    * ``'radial'``: :math:`a = \pi + \min(1, t^\star(e))\, e` with
      :math:`t^\star(e) = \max\{t: \pi + t e \in \mathcal A,\ \pi - t e \in \mathcal A\}`;
    * ``'symmetric'``: the same radial step applied to :math:`e'`, where :math:`e'` is
      :math:`e` slid along the grid faces it could reach (on such a face the batteries of the
      face's side lose the mean of their :math:`e_i`, so the grid sum stays put, and idle
      batteries, which could cross zero and join the sum, do not explore) and then clipped
      entrywise to :math:`\pm(U - |\pi_i|)`; of this step and the radial one, the larger
      (in norm) is taken. The grid limit is nearly active in most hours of an economic MPC
      (84 % of the hours at theta0 have a slack below 0.1 MW), where the radial step keeps
      2-12 % of the exploration's energy and this one about half;
    * ``'project'``: :math:`a = \mathrm{proj}_{\mathcal A}(\pi + e)`
      (:func:`mpcrl_lite.system.battery.project_action`).

    For the first two, :math:`a - \pi` is an odd function of :math:`e` (clipping to a
    symmetric interval is odd, :math:`t^\star(-e) = t^\star(e)`, the sliding is linear in
    :math:`e` on sets that depend on :math:`e` only through :math:`\max_i |e_i|`, and the
    choice between two odd steps by their norms is even), so a symmetric
    exploration (a Gaussian) stays symmetric, with zero mean, at every state; and
    :math:`a \in \mathcal A` since :math:`\mathcal A` is convex and both :math:`\pi \pm t e`
    lie in it. An infeasible :math:`\pi` (not an MPC's) is projected onto :math:`\mathcal A`
    first and explored around that point.

    Parameters
    ----------
    pi, e : numpy.ndarray, shape ``(days, n)``
        The policy's action and the drawn exploration (MW).
    system : SystemConfig
        Provides ``U_bar`` and ``P_bar``.
    bounds : {'symmetric', 'radial', 'project'}

    Returns
    -------
    numpy.ndarray, shape ``(days, n)``
    """
    bounds = check_choice("bounds", bounds, EXPLORATION_BOUNDS)
    if bounds == "project":
        return project_action(pi + e, system)
    pi = np.asarray(pi, dtype=float)
    e = np.asarray(e, dtype=float)
    if pi.ndim != 2 or pi.shape[1] != system.n or e.shape != pi.shape:
        raise ValueError(f"pi has shape {pi.shape} and e {e.shape}: expected both (days, "
                         f"{system.n})")
    for name, value in (("pi", pi), ("e", e)):
        if not np.isfinite(value).all():
            raise ValueError(f"{name} has non-finite entries: expected finite values only")
    upper = np.array(system.battery("U_bar"), dtype=float)  # each battery's own bound
    return _explore_rows(pi, e, upper, system.P_bar, bounds == "symmetric")


def _explore_rows(pi: np.ndarray, e: np.ndarray, upper: np.ndarray, P_bar: float,
                  symmetric: bool) -> np.ndarray:
    """The compiled step of :func:`bounded_exploration` for checked ``(days, n)`` arrays."""
    kernel.ensure_compiled()
    # compiled (mpcrl_lite.sim.exploration_kernel): per day, pi projected onto the feasible set,
    # the radial step (and the slide along the grid faces), the result projected once more
    # as a guard against rounding (base + step is feasible up to ~1e-16)
    return kernel.explore_rows(np.ascontiguousarray(pi), np.ascontiguousarray(e), upper,
                               P_bar, symmetric)


class Projection:
    """Action hook: ``a = project_action(pi)``, the command onto the input bounds and the
    grid limit (a no-op for feasible commands such as an MPC's)."""

    def __init__(self, system: SystemConfig) -> None:
        self.system = system

    def __call__(self, hour: int, pi: np.ndarray, rng: np.random.Generator | None) -> np.ndarray:
        return project_action(pi, self.system)
