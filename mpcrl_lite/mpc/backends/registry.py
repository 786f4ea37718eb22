"""The MPC solver back-ends by name, and :func:`make_solver`, which builds one from a config.

Back-ends (all solve the barrier problem of :mod:`mpcrl_lite.mpc.formulation` and return the solution
types of :mod:`mpcrl_lite.mpc.solution`):

* ``'ipopt'`` -- :class:`~mpcrl_lite.mpc.backends.ipopt.IpoptSolver`, the reference: IPOPT through
  CasADi's ``nlpsol``, then Newton polishing to machine precision;
* ``'batch'`` -- :class:`~mpcrl_lite.mpc.backends.batch.BatchSolver`, a numpy interior point that
  solves all days of a month at once;
* ``'kernel'`` -- :class:`~mpcrl_lite.mpc.backends.kernel.KernelSolver`, the batch solver's
  iteration compiled with numba, four problems at a time in vector registers (the same
  results to rounding);
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
import sys
from collections.abc import Callable, Iterator, MutableMapping

from ..._util.lazy import lazy_names
from ...config import BACKENDS, MPCConfig
from ...theta import Theta
from ..formulation import MPC
from ..solution import SolverBackend
from .kernel import KernelSolver

# MPCSolution, BatchSolution, FALLBACK, BatchSolver and IpoptSolver live in their own modules
# and stay importable from here (the two last loaded on first use, :func:`__getattr__`).
__all__ = ["AUTO", "CONVEX_ONLY", "REGISTRY", "make_solver"]

log = logging.getLogger(__name__)

#: The back-end name that chooses one of the others (see :func:`make_solver`).
AUTO = "auto"

#: The back-ends that solve a convex MPC only (``phi1, T1 >= 0``); given a theta that is not
#: convex, :func:`make_solver` uses IPOPT instead, with a warning.
CONVEX_ONLY = ("batch", "kernel")

class _Registry(MutableMapping):
    """Back-end classes by name, each imported at its first lookup: a learner on the default
    compiled back-end never loads the numpy interior point or the IPOPT wrapper (about 30 ms
    of start-up). An entry is a class or the name of one in this module (loaded there on
    first read, :func:`__getattr__`); setting and deleting entries work as on a dict."""

    def __init__(self, entries: dict[str, object]) -> None:
        self._entries = dict(entries)

    def __getitem__(self, name: str) -> Callable[[MPC, MPCConfig], SolverBackend]:
        entry = self._entries[name]
        if isinstance(entry, str):
            entry = self._entries[name] = getattr(sys.modules[__name__], entry)
        return entry

    def __setitem__(self, name: str, value) -> None:
        self._entries[name] = value

    def __delitem__(self, name: str) -> None:
        del self._entries[name]

    def __iter__(self) -> Iterator[str]:
        return iter(self._entries)

    def __len__(self) -> int:
        return len(self._entries)


#: Back-end constructors ``(mpc, config) -> back-end`` by their name in
#: :data:`mpcrl_lite.config.BACKENDS` (a mapping that imports a back-end at its first lookup).
REGISTRY: MutableMapping[str, Callable[[MPC, MPCConfig], SolverBackend]] = _Registry({
    "ipopt": "IpoptSolver",
    "batch": "BatchSolver",
    "kernel": KernelSolver,
})


__getattr__ = lazy_names(__name__, {"BatchSolver": f"{__package__}.batch",
                                    "IpoptSolver": f"{__package__}.ipopt"})


def _auto_backend(theta: Theta | None, mpc: MPC | None = None) -> str:
    """The compiled interior point for a convex QP (``phi1, T1 >= 0``; each battery with its
    own input bound ``U_bar^i``), IPOPT otherwise. ``mpc`` is not needed for the choice and
    kept for the callers that pass it."""
    convex = theta is None or theta.is_convex()
    return "kernel" if convex else "ipopt"


def make_solver(
    mpc: MPC, config: MPCConfig | None = None, theta: Theta | None = None
) -> SolverBackend:
    """The back-end named by ``config.backend``, built for ``mpc``.

    ``'auto'`` chooses the compiled interior point when the MPC is a convex QP for ``theta``
    (``phi1, T1 >= 0``; always true with ``LearningConfig.keep_well_posed``; one ``U_bar``
    per battery or one for all), and IPOPT otherwise; the choice is logged at INFO level and
    readable from ``solver.name``. An explicit ``'kernel'`` or ``'batch'``
    (:data:`CONVEX_ONLY`) given a theta that is not convex is replaced by IPOPT too, with a
    warning.

    A kernel that cannot solve the MPC of this system and config says so at its first solve
    (:class:`~mpcrl_lite.mpc.backends.kernel.KernelInputError`, naming the input), never
    blaming the formulation.

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
    elif backend in CONVEX_ONLY and theta is not None and not theta.is_convex():
        log.warning("theta is not convex (phi1 or T1 < 0): the %r back-end solves convex MPCs "
                    "only (it breaks down on a share of the solves); using 'ipopt' instead, "
                    "as 'auto' does", backend)
        backend = "ipopt"
    if backend not in REGISTRY:
        known = tuple(name for name in BACKENDS if name == AUTO or name in REGISTRY)
        raise ValueError(f"MPC back-end {backend!r} is not available; expected one of {known}")
    return REGISTRY[backend](mpc, config)
