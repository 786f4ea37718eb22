"""The MPC solver back-ends by name, and :func:`make_solver`, which builds one from a config.

Back-ends (all solve the barrier problem of :mod:`mpcrl_lite.mpc.formulation` and return the solution
types of :mod:`mpcrl_lite.mpc.solution`):

* ``'ipopt'`` -- :class:`~mpcrl_lite.mpc.backends.ipopt.IpoptSolver`, the reference: IPOPT through
  CasADi's ``nlpsol``, then Newton polishing to machine precision;
* ``'batch'`` -- :class:`~mpcrl_lite.mpc.backends.batch.BatchSolver`, a numpy interior point that
  solves all days of a month at once;
* ``'kernel'`` -- :class:`~mpcrl_lite.mpc.backends.kernel.KernelSolver`, the batch solver's
  iteration compiled with numba, one problem at a time (the same results to rounding);
* ``'auto'`` -- ``'kernel'`` when the MPC is a convex QP for the given theta, else ``'ipopt'``.

:data:`REGISTRY` maps the names of :data:`mpcrl_lite.config.BACKENDS` to the classes; adding a
back-end is one entry there (and its name in the config). This module imports the back-ends;
they never import each other or this module.

Failures never raise mid-run and never leak NaN: a problem that did not converge is marked
``success = False`` with the solver's status, and its ``action`` is the documented fallback
:data:`FALLBACK` (see :mod:`mpcrl_lite.mpc.solution`).
"""

from __future__ import annotations

import logging
from collections.abc import Callable

from ...config import BACKENDS, MPCConfig
from ...theta import Theta
from ..formulation import MPC
from ..solution import SolverBackend
from .batch import BatchSolver
from .ipopt import IpoptSolver
from .kernel import KernelSolver

# MPCSolution, BatchSolution, FALLBACK and IpoptSolver live in their own modules and stay
# importable from here.
__all__ = ["AUTO", "REGISTRY", "make_solver"]

log = logging.getLogger(__name__)

#: The back-end name that chooses one of the others (see :func:`make_solver`).
AUTO = "auto"

#: Back-end constructors ``(mpc, config) -> back-end`` by their name in
#: :data:`mpcrl_lite.config.BACKENDS`.
REGISTRY: dict[str, Callable[[MPC, MPCConfig], SolverBackend]] = {
    "ipopt": IpoptSolver,
    "batch": BatchSolver,
    "kernel": KernelSolver,
}


def _auto_backend(theta: Theta | None, mpc: MPC | None = None) -> str:
    """The compiled interior point for a convex QP (``phi1, T1 >= 0``) whose batteries share
    one input bound ``U_bar`` (the compiled back-ends' formulation), IPOPT otherwise."""
    convex = theta is None or theta.is_convex()
    shared = mpc is None or len(set(mpc.system.battery("U_bar"))) == 1
    return "kernel" if convex and shared else "ipopt"


def make_solver(
    mpc: MPC, config: MPCConfig | None = None, theta: Theta | None = None
) -> SolverBackend:
    """The back-end named by ``config.backend``, built for ``mpc``.

    ``'auto'`` chooses the compiled interior point when the MPC is a convex QP for ``theta``
    (``phi1, T1 >= 0``; always true with ``LearningConfig.keep_well_posed``) and every battery
    has the same ``U_bar``, and IPOPT otherwise; the choice is logged at INFO level and readable from ``solver.name``.

    Raises
    ------
    ValueError
        If ``config.backend`` names no registered back-end.
    """
    config = config or MPCConfig()
    backend = config.backend
    if backend == AUTO:
        backend = _auto_backend(theta, mpc)
        log.info("MPC back-end 'auto' chose %r", backend)
    if backend not in REGISTRY:
        known = tuple(name for name in BACKENDS if name == AUTO or name in REGISTRY)
        raise ValueError(f"MPC back-end {backend!r} is not available; expected one of {known}")
    return REGISTRY[backend](mpc, config)
