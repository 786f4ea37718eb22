"""``python -m mpcrl_lite.cli.warm``: compile every kernel of the package into numba's cache.

The Makefile's ``setup`` runs it once, so that no notebook, test or command waits for the
compiler: the MPC back-end (:mod:`mpcrl_lite.mpc.backends.kernel_core`), the exploration
(:mod:`mpcrl_lite.sim.exploration_kernel`) and the coordination rounds of the decentralized
learner (:mod:`mpcrl_lite.decentralized.coordination_kernel`). Each loads its kernels on
first use anyway; this only moves the wait ahead: about four minutes of CPU, two on two cores
(the generic kernels with the exploration and the coordination rounds about 1.9 minutes, each
size's copy of the MPC kernels about one). (The causal dynamic program's kernels
compile on their first solve, a few seconds.)
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
from ..mpc.backends import kernel, kernel_sizes
from ..sim import exploration_kernel

__all__ = ["main", "warm_up"]


def _groups() -> list[str]:
    """The kernels in groups that compile independently (numba caches each module's
    functions in files of their own): the generic MPC kernels with the exploration and the
    coordination rounds, and each size's copy of the MPC kernels (``"3x12"``)."""
    return ["generic", *(f"{n}x{N}" for n, N in sorted(kernel_sizes.SPECIALISED_SIZES))]


def _compile(group: str) -> float:
    """Compile (or load) one group of :func:`_groups`; the seconds it took."""
    t0 = time.perf_counter()
    if group == "generic":
        kernel.K.ensure_compiled()
        exploration_kernel.ensure_compiled()
        coordination_kernel.ensure_compiled()
    else:
        n, N = (int(v) for v in group.split("x"))
        kernel_sizes.kernels(n, N).ensure_compiled()
    return time.perf_counter() - t0


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
    removed = kernel_sizes.prune()  # the copies of other versions, now that these are ready
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
