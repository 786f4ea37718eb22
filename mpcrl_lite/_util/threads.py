"""Blocks of independent problems spread over threads, for compiled kernels without the GIL.

A compiled kernel that solves independent problems (the MPC back-end's
:func:`~mpcrl_lite.mpc.backends.kernel_core.solve_rows`, the coordination rounds'
:func:`~mpcrl_lite.decentralized.coordination_kernel.coordinate`) can run on several threads
at once when it releases the GIL (``nogil=True``). :func:`run_blocks` hands out blocks of
problems in turn to the calling thread and helpers: a thread on a busy core takes fewer
blocks, and since a problem's result does not depend on the block it is solved in (alone, or
in a group of four with the same operations), which thread solves it does not change it.
"""

from __future__ import annotations

import functools
import multiprocessing
import os
import sys
import threading
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from typing import ParamSpec, TypeVar

_P = ParamSpec("_P")
_R = TypeVar("_R")

__all__ = ["BLAS_THREADS", "auto_threads", "one_blas_thread", "run_blocks"]

#: Threads the BLAS/LAPACK libraries may use while a learning month runs (see
#: :mod:`mpcrl_lite.learning.learner`, "One thread of linear algebra"): one, so that results
#: do not depend on the machine's cores.
BLAS_THREADS = 1


#: how deep the calling thread is in functions wrapped by :func:`one_blas_thread`
_limited = threading.local()


def one_blas_thread(fn: Callable[_P, _R]) -> Callable[_P, _R]:
    """``fn`` run with the BLAS/LAPACK libraries limited to :data:`BLAS_THREADS` threads
    (``threadpoolctl``, its libraries found once: :func:`_blas_controller`; the previous
    limits restored after it).

    A learner's ``run_one_month`` and ``learning_step`` are wrapped in it, so that a month or
    an update called on its own (in a notebook, a benchmark) gives the numbers and the speed
    of one in ``run``: with OpenBLAS's own threads, which wait spinning after each product,
    beside the compiled kernel's threads on two cores, a month of the paper's run took 2.5x
    the wall time (113 ms against 45 ms) and its LSTD products could depend on the core
    count. A wrapped function called inside another (the month's update inside its month)
    runs under the outer limit, which is not set again.
    """

    @functools.wraps(fn)
    def limited(*args: _P.args, **kwargs: _P.kwargs) -> _R:
        if getattr(_limited, "depth", 0):
            return fn(*args, **kwargs)
        _limited.depth = 1
        try:
            with _blas_controller().limit(limits=BLAS_THREADS):
                return fn(*args, **kwargs)
        finally:
            _limited.depth = 0

    return limited


#: the process's ``threadpoolctl.ThreadpoolController`` and how many modules were imported
#: when it was made
_controller: list = [None, -1]
_controller_lock = threading.Lock()


def _blas_controller():
    """The thread-pool libraries loaded in this process (``threadpoolctl``), found once and
    found again only after new modules were imported (a new module is how a new BLAS comes
    in: scipy's with ``scipy.linalg``). Finding them walks every loaded shared library: about
    0.4 ms a call with numba, CasADi and scipy loaded, against 0.014 ms with the libraries kept
    (a study worker's lockstep: 0.97x the time)."""
    loaded = len(sys.modules)
    with _controller_lock:
        if _controller[0] is None or _controller[1] != loaded:
            from threadpoolctl import ThreadpoolController  # loaded with the first month

            _controller[0], _controller[1] = ThreadpoolController(), len(sys.modules)
        return _controller[0]


def auto_threads() -> int:
    """The threads of a call that leaves the choice to the package: the cores this process
    may use (``os.sched_getaffinity``) in the main process, one in a worker process (its
    pool already spreads the work over the cores), and one off the main thread."""
    if multiprocessing.parent_process() is not None:
        return 1
    if threading.current_thread() is not threading.main_thread():
        return 1
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


@functools.cache
def _helpers(count: int, pid: int) -> ThreadPoolExecutor:
    """``count`` helper threads (besides the calling one), created at the first call that
    needs them in process ``pid`` (a forked child gets its own: the parent's threads do not
    exist there)."""
    return ThreadPoolExecutor(count, thread_name_prefix="mpcrl_lite-kernel")


def run_blocks(rows: Callable[..., None], args: tuple, size: int, threads: int, block: int,
               *, whole: bool = True) -> None:
    """``rows(*args, lo, hi)`` over ``0 <= lo < hi <= size`` in blocks of ``block``, taken in
    turn by ``threads`` threads (this one and ``threads - 1`` helpers).

    With one thread and ``whole`` the call is ``rows(*args, 0, size)``; with ``whole=False``
    it goes through the same blocks as on several threads (for a kernel whose problems are
    only independent within the blocks it is given)."""
    if threads <= 1:
        if whole:
            rows(*args, 0, size)
        else:
            for lo in range(0, size, block):
                rows(*args, lo, min(lo + block, size))
        return
    starts = iter(range(0, size, block))
    lock = threading.Lock()

    def work() -> None:
        while True:
            with lock:
                lo = next(starts, None)
            if lo is None:
                return
            rows(*args, lo, min(lo + block, size))

    pool = _helpers(threads - 1, os.getpid())
    futures = [pool.submit(work) for _ in range(threads - 1)]
    try:
        work()
    finally:
        for f in futures:
            f.result()
