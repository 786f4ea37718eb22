"""The compiled kernels' formulation check, remembered per machine once it has passed.

Before its first solve a :class:`~mpcrl_lite.mpc.backends.kernel.KernelSolver` solves one
problem at a pseudo-random parameter and checks the KKT conditions of the CasADi formulation
there (``KernelSolver._check_formulation``): the kernels' hand-written QP data must be the
formulation's. That check loads the kernels' ``solve_rows`` and evaluates the formulation in
CasADi, about 0.1 s of a command's start, although nothing it depends on changes between
runs of the same installation.

So a check that passed is remembered: a small file in the kernels' cache folder
(:func:`mpcrl_lite.mpc.backends.kernel_sizes.folder`, ``checked/``) named by the hash of
everything the check's outcome depends on (:func:`key`):

* the text of the kernel module the solver runs (the generic kernels or a sized copy), of
  the formulation (``mpcrl_lite/mpc/formulation.py``), of the parameter layout and solutions
  (``mpcrl_lite/mpc/solution.py``) and of the solver with its check (``kernel.py``);
* the versions of Python, numpy, numba and llvmlite, CasADi's installed file (without importing
  it) and the machine's architecture;
* the system's configuration, the solver's class, factorisation and problem layout
  (``lanes``), its bounds and stage weights, the check's parameter and its option vector
  (which holds every value of the MPC's configuration the check reads: ``tau``, the
  tolerance and the solver's start settings).

A later solver with the same key skips the check; any change to one of these runs it again.
Only the package's own solver class and formulation as written are remembered
(:func:`applies`): a subclass, or a formulation whose functions were replaced on the instance,
is code the key cannot see, and is checked every time.
``KernelSolver.remember_check = False`` (or ``MPCRL_LITE_RECHECK=1`` in the environment)
checks every solver, as before. ``python -m mpcrl_lite.cli.warm`` (``make setup``) runs a
month of the paper's system, which checks its solver, so that the first run finds the check
remembered. A folder that cannot be written only means the check runs every time.
"""

from __future__ import annotations

import hashlib
import importlib.util
import json
import logging
import os
import platform
import sys
import threading
from pathlib import Path
from typing import Any

import numpy as np

from ..formulation import MPC
from .kernel_sizes import folder

__all__ = ["ENV", "applies", "key", "passed", "record"]

log = logging.getLogger(__name__)

#: Set to ``1`` to check every solver (nothing is read from or written to ``checked/``).
ENV = "MPCRL_LITE_RECHECK"

_HERE = Path(__file__).resolve().parent
#: the package's sources the check's outcome depends on, besides the kernel module
_SOURCES = (_HERE / "kernel.py", _HERE.parent / "formulation.py", _HERE.parent / "solution.py")
_source_digest: dict[str, str] = {}


def enabled() -> bool:
    """Whether checks are remembered (:data:`ENV` unset or ``0``)."""
    return os.environ.get(ENV, "").strip() in ("", "0")


def _digest_of(path: Path) -> str:
    name = str(path)
    if name not in _source_digest:
        _source_digest[name] = hashlib.sha256(path.read_bytes()).hexdigest()
    return _source_digest[name]


def _installed(module: str) -> str:
    """Where ``module`` is installed and when that file was written, without importing it
    (CasADi's import is what a remembered check saves): another version is another file."""
    spec = importlib.util.find_spec(module)
    if spec is None or spec.origin is None:
        return "absent"
    stat = os.stat(spec.origin)
    return f"{spec.origin}:{stat.st_size}:{stat.st_mtime_ns}"


def _versions() -> dict[str, str]:
    import llvmlite
    import numba  # imported with the kernels already

    return {"python": sys.version, "machine": platform.machine(),
            "numpy": np.__version__, "numba": numba.__version__,
            "llvmlite": llvmlite.__version__, "casadi": _installed("casadi")}


def applies(mpc: MPC) -> bool:
    """Whether a check of a solver of ``mpc`` may be remembered: the package's formulation as
    written (the class ``MPC`` itself, no function of it replaced on the instance; its own
    CasADi Functions, built on first use, are its own). A formulation changed in the process
    or by a subclass is checked every time: :func:`key` hashes the package's files, not code
    defined elsewhere. (The solver's class is the caller's to judge the same way.)"""
    if type(mpc) is not MPC:
        return False
    casadi = sys.modules.get("casadi")  # imported if the instance built its functions
    for value in vars(mpc).values():
        if callable(value) and not (casadi is not None and isinstance(value, casadi.Function)):
            return False
    return True


def key(solver: Any, kernels: Any, opts: np.ndarray, parameter: np.ndarray) -> str:
    """The hash of everything the check of ``solver`` (running the kernel module
    ``kernels`` with the option vector ``opts`` at the parameter ``parameter``) depends on;
    see the module docstring."""
    what = {
        "kernels": _digest_of(Path(kernels.__file__)),
        "sources": [_digest_of(path) for path in _SOURCES],
        "versions": _versions(),
        "solver": f"{type(solver).__module__}.{type(solver).__qualname__}",
        "system": solver.mpc.system.to_dict(),
        "method": int(solver._method),
        "lanes": bool(solver.lanes),
    }
    digest = hashlib.sha256(json.dumps(what, sort_keys=True, default=repr).encode("utf-8"))
    for array in (opts, parameter, solver._ubar, solver._stagew):
        digest.update(np.ascontiguousarray(array, dtype=np.float64).tobytes())
    return digest.hexdigest()[:32]


def _path(name: str) -> Path:
    return folder() / "checked" / f"{name}.json"


def passed(name: str) -> bool:
    """Whether a check with the key ``name`` passed on this machine before."""
    if not enabled():
        return False
    try:
        return _path(name).is_file()
    except (OSError, RuntimeError):  # no cache folder at all
        return False


def record(name: str, errors: dict[str, float]) -> None:
    """Remember that the check with the key ``name`` passed (its residuals ``errors`` kept
    for whoever looks); a folder that cannot be written is left alone."""
    if not enabled():
        return
    try:
        path = _path(name)
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f".{path.name}.{os.getpid()}.{threading.get_ident()}.tmp")
        tmp.write_text(json.dumps({k: float(v) for k, v in errors.items()}), encoding="utf-8")
        os.replace(tmp, path)  # appears whole
    except (OSError, RuntimeError) as err:
        log.debug("the formulation check is not remembered: %s", err)
