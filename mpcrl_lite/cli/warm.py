"""``python -m mpcrl_lite.cli.warm``: compile every kernel of the package into numba's cache.

The Makefile's ``setup`` runs it once, so that no notebook, test or command waits for the
compiler: the MPC back-end (:mod:`mpcrl_lite.mpc.backends.kernel_core`), the exploration
(:mod:`mpcrl_lite.sim.exploration_kernel`), the month of the closed loop
(:mod:`mpcrl_lite.sim.compiled_month`, for the generic kernels and the paper's sizes) and the
coordination rounds of the decentralized learner
(:mod:`mpcrl_lite.decentralized.coordination_kernel`) and the first stage of the Q-learner's MPC
(:mod:`mpcrl_lite.mpc.q_stage_kernel`). Each loads its kernels on
first use anyway; this only moves the wait ahead: from an empty cache about five minutes of
CPU, three on two cores (176 s on 2026-12-07; the generic kernels with the exploration, the
coordination rounds and their compiled month in one process, each size's copy of the MPC
kernels, with the paper's size's compiled month, in the other). (The causal dynamic
program's kernels compile on their first solve, a few seconds.)
"""

from __future__ import annotations

import argparse
import logging
import multiprocessing
import os
import time
from concurrent.futures import ProcessPoolExecutor

from .._util.workers import end_with_parent
from ..decentralized import coordination_kernel
from ..mpc import q_stage_kernel
from ..mpc.backends import kernel, kernel_sizes
from ..sim import compiled_month, exploration_kernel

__all__ = ["main", "warm_up"]


def _groups() -> list[str]:
    """The kernels in groups that compile independently (numba caches each module's
    functions in files of their own): the generic MPC kernels with the exploration and the
    coordination rounds, and each size's copy of the MPC kernels (``"3x12"``)."""
    return ["generic", *(f"{n}x{N}" for n, N in sorted(kernel_sizes.SPECIALISED_SIZES))]


#: the sizes whose compiled month (:mod:`mpcrl_lite.sim.compiled_month`) is compiled here with
#: their kernels: the paper's (the 11-hour tail of the Q-learner's MPC never runs a month)
MONTH_SIZES = frozenset({(3, 12)})


def _compile(group: str) -> float:
    """Compile (or load) one group of :func:`_groups`; the seconds it took."""
    t0 = time.perf_counter()
    if group == "generic":
        kernel.K.ensure_compiled()
        exploration_kernel.ensure_compiled()
        coordination_kernel.ensure_compiled()
        q_stage_kernel.ensure_compiled()
        _warm_month(2, 4)
    else:
        n, N = (int(v) for v in group.split("x"))
        kernel_sizes.kernels(n, N).ensure_compiled()
        if (n, N) in MONTH_SIZES:
            _warm_month(n, N)
    return time.perf_counter() - t0


class _Threads:
    """``solver`` whose compiled months take ``threads`` threads, also in a worker process
    (where a run takes one): both entries of the compiled month get compiled."""

    def __init__(self, solver, threads: int) -> None:
        self.solver, self.threads = solver, threads
        self.mpc, self.name = solver.mpc, solver.name

    def loop_parts(self, rows: int):
        parts = self.solver.loop_parts(rows)
        return None if parts is None else {**parts, "threads": self.threads}

    def report_failures(self, status) -> None:
        self.solver.report_failures(status)


def _warm_month(n: int, N: int) -> None:
    """Compile (or load) the compiled month of the kernels of ``n`` batteries and horizon
    ``N`` (:mod:`mpcrl_lite.sim.compiled_month`): a short month with exploration and
    sensitivities, in one block of days and in two, with the argument types of a run."""
    import numpy as np

    from ..config import LearningConfig, MPCConfig, SystemConfig
    from ..mpc.backends.registry import make_solver
    from ..mpc.formulation import MPC
    from ..sim.closed_loop import run_month
    from ..system.prices import Prices
    from ..theta import Theta

    system = SystemConfig(n=n, N=N)
    solver = make_solver(MPC(system), MPCConfig(backend="kernel"))
    prices = Prices.month(system, 16)
    for threads in (1, 2):
        run_month(Theta.nominal(system), _Threads(solver, threads), prices, system,
                  np.random.default_rng(0), exploration_std=LearningConfig().exploration_std,
                  sensitivities=True)


def warm_up(verbose: bool = False, workers: int | None = None) -> float:
    """Compile (or load from the cache) every kernel; returns the seconds it took.

    The groups of :func:`_groups` compile side by side in ``workers`` processes (default: one
    per core, at most one per group), each filling numba's cache; this process then loads them
    all from there (a second or two). ``workers=1`` compiles them here one after the other."""
    t0 = time.perf_counter()
    groups = _groups()
    workers = min(len(groups), os.cpu_count() or 1) if workers is None else int(workers)
    if workers > 1:
        # spawned, not forked: the workers start without this process's numba state
        with ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn"),
                                 initializer=end_with_parent) as pool:
            list(pool.map(_compile, groups))
    for group in groups:
        _compile(group)
    # the copies of other versions, now that these are ready
    removed = kernel_sizes.prune() + compiled_month.prune()
    took = time.perf_counter() - t0
    if verbose:
        print(f"mpcrl_lite kernels ready in {took:.1f} s (cache: {kernel.cache_dir()})")
        if removed:
            print(f"removed {len(removed)} files of other versions' kernels")
    return took


def main(argv: list[str] | None = None) -> int:
    """Fill numba's cache with every kernel of the package."""
    parser = argparse.ArgumentParser(prog="python -m mpcrl_lite.cli.warm",
                                     description="Compile every kernel into numba's cache.")
    parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    warm_up(verbose=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
