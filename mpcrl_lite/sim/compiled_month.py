"""A month of the MPC in closed loop in one compiled call (:mod:`mpcrl_lite.sim.month_kernel`).

:func:`mpcrl_lite.sim.closed_loop.run_month` and :func:`~mpcrl_lite.sim.closed_loop.evaluate_mpc`
hand a month to :func:`run` when everything in it is covered here:

* the compiled back-end (:class:`~mpcrl_lite.mpc.backends.kernel.KernelSolver`, four problems at
  once: :meth:`~mpcrl_lite.mpc.backends.kernel.KernelSolver.loop_parts` says so);
* no exploration, or the package's Gaussian one with the ``'symmetric'`` or ``'radial'``
  bounds around the policy itself (no margin);
* hour hooks only where they just read their steps (``replayable``, as the sensitivity and
  the Q-learner's value recorders): they get the month's steps after it;
* fewer than eight batteries (numpy sums eight or more numbers in another order).

Everything else runs the Python loop (:func:`~mpcrl_lite.sim.closed_loop.simulate`), which is
the reference: the compiled month gives its record to the last bit, and so the same learning
run (``tests/sim/test_compiled_month.py``). ``MPCRL_LITE_COMPILED_LOOP=0`` (or
:data:`ENABLED` set to False) sends every month through the Python loop.

The draws come first, which is possible because neither depends on the state: the caller
draws the month's exploration and noise in one call of the generator, the numbers the Python
loop draws hour by hour (the exploration, then the noise, every hour) to the last bit
(:func:`~mpcrl_lite.sim.closed_loop._month_draws`; runs in lockstep each from its own
generator).

Each kernel module gets its own copy of the template :mod:`mpcrl_lite.sim.month_kernel`
(:func:`module`), written to the cache folder of the generated kernels
(:func:`mpcrl_lite.mpc.backends.kernel_sizes.folder`) under a name that carries a hash of the
template, the kernels and the exploration kernel: numba's cache of a copy never holds code of
other versions. ``python -m mpcrl_lite.cli.warm`` compiles them (``make setup``).
"""

from __future__ import annotations

import hashlib
import logging
import os
import threading
from contextlib import nullcontext
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np
from numba.core import event

from .._util import jit

__all__ = ["ENABLED", "ENV", "eligible", "module", "prune", "run", "source"]

log = logging.getLogger(__name__)

#: Set to ``0`` to run every month through the Python loop.
ENV = "MPCRL_LITE_COMPILED_LOOP"
#: Whether eligible months run compiled (read at each month; tests switch it).
ENABLED = os.environ.get(ENV, "").strip() != "0"
#: Fewer batteries than this: numpy's sums over them go from the first entry on.
MAX_BATTERIES = 7

_TEMPLATE = Path(__file__).with_name("month_kernel.py")
_KERNELS_LINE = ("from ..mpc.backends.kernel_core import CONVERGED, SENS_OK, sensitivity_rows, "
                 "solve_rows  # KERNELS")
_lock = threading.Lock()
_loaded: dict[str, ModuleType] = {}


def _suffix(kernels: ModuleType) -> str:
    name = kernels.__name__.rpartition(".")[2]
    return "generic" if name == "kernel_core" else name.replace("kernel_core_", "")


def source(kernels: ModuleType) -> str:
    """The text of the copy of the template for the kernel module ``kernels``."""
    text = _TEMPLATE.read_text(encoding="utf-8")
    if text.count(_KERNELS_LINE) != 1:
        raise RuntimeError(f"{_TEMPLATE} no longer holds the line {_KERNELS_LINE!r} exactly once")
    header = (f"# Generated from month_kernel.py by mpcrl_lite.sim.compiled_month for "
              f"{kernels.__name__}; do not edit.\n")
    names = _KERNELS_LINE.split(" import ")[1].split("  #")[0]
    return header + text.replace(_KERNELS_LINE, f"from {kernels.__name__} import {names}")


def _stem(kernels: ModuleType, text: str) -> str:
    from . import exploration_kernel

    digest = hashlib.sha256(text.encode("utf-8"))
    for path in (kernels.__file__, exploration_kernel.__file__, jit.__file__):
        digest.update(Path(path).read_bytes())
    return f"month_kernel_{_suffix(kernels)}_{digest.hexdigest()[:12]}"


def module(kernels: ModuleType) -> ModuleType:
    """The compiled month for the kernel module ``kernels`` (written and imported once per
    process; numba loads or compiles its functions at their first call)."""
    from ..mpc.backends import kernel_sizes

    with _lock:
        key = kernels.__name__
        if key not in _loaded:
            text = source(kernels)
            path = kernel_sizes.folder() / f"{_stem(kernels, text)}.py"
            kernel_sizes.write_once(path, text, os.stat(_TEMPLATE).st_mtime)
            # its relative imports are the template's
            _loaded[key] = kernel_sizes.import_generated(
                path, f"mpcrl_lite.sim.month_kernel_{_suffix(kernels)}", "mpcrl_lite.sim")
        return _loaded[key]


def prune() -> list[Path]:
    """Remove copies made for other versions of the template or the kernels (and their
    compiled code) from the cache folder; the copies of this version stay. Returns the files
    removed."""
    from ..mpc.backends import kernel_core, kernel_sizes

    folder = kernel_sizes.folder()
    keep = {_stem(kernel_core, source(kernel_core))}
    for n, N in kernel_sizes.SPECIALISED_SIZES:
        copy = kernel_sizes.kernels(n, N)
        keep.add(_stem(copy, source(copy)))
    removed = []
    for path in [*folder.glob("month_kernel_*.py"), *folder.glob("__pycache__/month_kernel_*.*")]:
        if path.name.split(".")[0] not in keep:
            try:
                path.unlink()
            except FileNotFoundError:
                continue
            removed.append(path)
    return removed


def eligible(parts: dict[str, Any] | None, n: int, bounds: str | None, margin: float) -> bool:
    """Whether a month with these solver parts (``loop_parts``), ``n`` batteries and this
    exploration (``bounds`` None for none) runs compiled."""
    return (ENABLED and parts is not None and n <= MAX_BATTERIES
            and (bounds is None or (bounds in ("symmetric", "radial") and margin == 0.0)))


def run(parts: dict[str, Any], system: Any, mpc: Any, soc0: np.ndarray, theta: np.ndarray,
        wbuy: np.ndarray, wsell: np.ndarray, buy: np.ndarray, sell: np.ndarray,
        e: np.ndarray | None, noise: np.ndarray, sensitivities: bool,
        symmetric: bool, keep: bool = False,
        ) -> tuple[dict[str, np.ndarray], np.ndarray | None, np.ndarray, dict | None]:
    """The month's arrays: ``soc0`` (D, n) checked, ``theta`` (D, n_theta), the windows
    ``wbuy``, ``wsell`` (H, D, N), the true prices ``buy``, ``sell`` (D, H), the exploration
    ``e`` (H, D, n) already times its std (None: none) and the ``noise`` (H, D, n).

    Returns the record's arrays by name (as :class:`~mpcrl_lite.sim.record.Record` takes
    them, ``soc`` included), ``grad_pi`` (H, D, n_theta, n) or None, the solver's status
    codes (H, D) and, with ``keep``, every hour's solutions (``x``, ``lam``, ``mu``, ``p``
    (H, D, ...), ``cost``, ``iterations`` (H, D); else None)."""
    from ..system.battery import battery_values

    H, D, n = noise.shape
    N, nx, nt = mpc.N, mpc.nx, theta.shape[1]
    kernels = parts["kernels"]
    month = module(kernels)
    def c(a: Any, dtype: Any = np.float64) -> np.ndarray:
        # C order and writable: numba compiles a read-only or strided array as another type
        return np.require(a, dtype, ["C", "W"])

    explore = e is not None
    arrays = {k: np.empty((H, D, n)) for k in ("policy", "a", "b", "s", "correction",
                                               "agent_cost")}
    per_day = {k: np.empty((H, D)) for k in ("stage_cost", "grid_power", "planned_power")}
    socs = np.empty((H + 1, D, n))
    socs[0] = soc0
    solver_ok, sens_ok = np.empty((H, D), bool), np.empty((H, D), bool)
    grad_pi = np.empty((H, D, nt, n)) if sensitivities else np.empty((1, 1, nt, n))
    statuses = np.empty((H, D), np.int64)
    rows = (H, D) if keep else (1, 1)
    kept = {"x": np.empty((*rows, nx)), "lam": np.empty((*rows, mpc.neq)),
            "mu": np.empty((*rows, mpc.nin)), "p": np.empty((*rows, mpc.np)),
            "cost": np.empty(rows), "iterations": np.empty(rows, np.int64)}
    args = (
        c(theta), c(wbuy), c(wsell), c(buy), c(sell),
        c(e if explore else np.zeros((H, D, n))), c(noise),
        c(parts["opts"]), c(parts["ubar"]), c(parts["stagew"]), int(n), int(N),
        int(parts["method"]), bool(parts["structured"]), bool(parts["warm_start"]),
        bool(sensitivities), bool(explore), bool(symmetric),
        c(system.battery("U_bar")), float(system.P_bar),
        float(parts["cond_max"]), float(parts["back_max"]),
        c(np.broadcast_to(battery_values(system, "alpha"), (n,))),
        c(np.broadcast_to(battery_values(system, "p"), (n,))),
        float(system.soc_low), float(system.soc_high),
        c(mpc.index("b"), np.int64), c(mpc.index("s"), np.int64),
        # work arrays of the solver calls
        np.empty((D, mpc.np)), np.zeros((D, nx)), np.empty((D, mpc.neq)),
        np.empty((D, mpc.nin)), np.zeros((D, nx)), np.zeros((1, nx)), np.empty(D),
        np.empty(D, np.int64), np.empty(D, np.int64), np.empty((D, n)),
        np.empty((D, nt, n)), np.empty((D, n, n)), np.empty(D), np.empty(D),
        np.empty(D, np.int64), np.empty(D, np.bool_),
        # the record
        socs, arrays["policy"], arrays["a"], arrays["b"], arrays["s"], arrays["correction"],
        arrays["agent_cost"], per_day["stage_cost"], per_day["grid_power"],
        per_day["planned_power"], solver_ok, sens_ok, grad_pi, statuses, bool(keep),
        kept["x"], kept["lam"], kept["mu"], kept["p"], kept["cost"], kept["iterations"],
    )
    threads = int(parts["threads"])
    entry = month.month_parallel if threads > 1 else month.month_rows
    # a month that has to compile says so once (numba's cache is filled by make setup);
    # ``overloads`` is numba's dict of what is loaded (its ``signatures``, a list made at
    # every read, took 20 us a month)
    with (nullcontext() if entry.overloads else event.install_listener(
            "numba:compile", jit.CompileNotice("the compiled closed loop (a minute or two)",
                                               jit.cache_dir(entry)))):
        if threads > 1:
            threads = kernels.set_threads(threads)
            lanes = int(parts["lanes"])
            block = -(-D // threads)
            block = -(-block // lanes) * lanes  # whole groups of four, as the solver's calls
            entry(*args, block)
        else:
            entry(*args, 0, D)
    out = {"soc": socs, **arrays, "noise": noise, **per_day, "buy": np.ascontiguousarray(buy.T),
           "solver_ok": solver_ok, "sens_ok": sens_ok}
    return out, (grad_pi if sensitivities else None), statuses, (kept if keep else None)
