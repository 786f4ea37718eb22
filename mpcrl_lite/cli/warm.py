"""``python -m mpcrl_lite.cli.warm``: compile every kernel of the package into numba's cache.

The Makefile's ``setup`` runs it once, so that no notebook, test or command waits for the
compiler: the MPC back-end (:mod:`mpcrl_lite.mpc.backends.kernel_core`), the exploration
(:mod:`mpcrl_lite.sim.exploration_kernel`) and the coordination rounds of the decentralized
learner (:mod:`mpcrl_lite.decentralized.coordination_kernel`). Each loads its kernels on
first use anyway; this only moves the wait ahead. (The causal dynamic program's kernels
compile on their first solve, a few seconds.)
"""

from __future__ import annotations

import argparse
import logging
import time

from ..decentralized import coordination_kernel
from ..mpc.backends import kernel, kernel_sizes
from ..sim import exploration_kernel

__all__ = ["main", "warm_up"]


def warm_up(verbose: bool = False) -> float:
    """Compile (or load from the cache) every kernel; returns the seconds it took."""
    t0 = time.perf_counter()
    kernel.warm_up()
    exploration_kernel.ensure_compiled()
    coordination_kernel.ensure_compiled()
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
