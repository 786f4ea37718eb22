r"""The barrier interior point compiled with numba; problems of few agents four at a time.

:class:`KernelSolver` is a drop-in replacement for
:class:`~mpcrl_lite.mpc.backends.batch.BatchSolver`: it runs *the same iteration* on the same
barrier problem (:mod:`mpcrl_lite.mpc.formulation`, ``tau`` fixed) -- same starting point, Mehrotra's
predictor-corrector until the target reaches ``tau``, then Newton steps at ``tau``, the same
stopping rule and failure semantics -- so its solutions, iteration counts and sensitivities
are those of the batch solver to rounding. Where the batch solver pays numpy's call overhead
about 20 times per Newton step, the kernels (:mod:`mpcrl_lite.mpc.backends.kernel_core`) solve each problem
in compiled loops with the structure of the KKT system spelled out (slack variables,
``soc``, ``b`` and ``s`` eliminated in closed form, the per-stage grid coupling inverted
exactly, a block-tridiagonal factorisation in the multipliers for few agents and the batch
solver's grid Schur complement for many; see :mod:`mpcrl_lite.mpc.backends.kernel_core`).
With the block-tridiagonal factorisation (few agents, the paper's sizes) the kernels take four
problems side by side, each quantity of the four held in one vector register, with each
problem's operations those it would have alone: the results are the same bits as one at a time
(:attr:`KernelSolver.lanes`).

Compilation and its cache
-------------------------
The kernels are compiled once per machine (about four minutes of CPU for the generic kernels
and the copies for the paper's sizes; ``python -m mpcrl_lite.cli.warm`` compiles them on two
cores in about two) and cached on disk by
numba (``@njit(cache=True)``); later processes load them in about a second. Fill the cache
ahead of time with ``python -m mpcrl_lite.cli.warm`` (the Makefile's ``setup``
does) or :func:`warm_up`. A process that finds no cache logs one line (WARNING) before it
compiles. Where the cache goes: ``NUMBA_CACHE_DIR`` if set; else the package's
``__pycache__`` if it is writable; else numba's per-user cache directory
(``~/.cache/numba``); if none of these is writable (a read-only installation and home), a
folder in the system's temporary directory (:func:`cache_dir` tells which).

Shapes and layouts are those of every back-end (:class:`~mpcrl_lite.mpc.backends.registry.BatchSolution`,
:class:`~mpcrl_lite.mpc.sensitivity.Sensitivity`); any ``n`` and ``N`` work with the same
compiled code.

Threads
-------
A call on many problems is spread over threads (:attr:`KernelSolver.threads`; by default the
cores in the main process and one thread in a worker process, whose pool already uses the
cores; at most one thread per :data:`THREAD_MIN_PROBLEMS` problems, so small calls stay on the
calling thread, and the learning months' 30 problems go to two). In the process that was
started, one compiled call hands a block of problems to each of numba's threads
(``kernel_core.solve_rows_parallel``); in a forked child, where numba's OpenMP threads cannot
be used, Python threads take blocks of :data:`THREAD_BLOCK` problems in turn. Either way the
blocks are whole groups of four where they can be (the kernels solve four problems side by
side, each with the operations it would have alone: ``kernel_core``'s "Four problems at
once"), without the GIL: the results do not depend on the thread count, bit for bit.

Sizes fixed at compile time
---------------------------
For the paper's sizes (n = 3, N = 12) the solver runs a copy of the kernels compiled with
``n`` and ``N`` as constants (:mod:`~mpcrl_lite.mpc.backends.kernel_sizes`,
:attr:`KernelSolver.specialise`): the same operations in the same order, so the same results
bit for bit, at about 1.3-1.6x less CPU.

Cost (``benchmarks/bench_kernel.py``, closed-loop hours of a 30-day month, solve plus
sensitivity per problem, measured beside the batch solver in the same run; benchmarks/README.md
keeps the history): for the paper's size (n = 3, N = 12) about 24 us of CPU per problem on one
thread, four at a time (about 14 us for the solve, 5 for the sensitivity; 41-46 us one at a
time), a 30-problem call on two threads in about two thirds of the wall time of one; about
3 ms for n = 100 and 0.11 ms for N = 48. Loading numba and the kernels adds about a second
to the first use in a process and about 100 MB of resident memory: importing this module
and building a :class:`KernelSolver` load neither (numba comes with the first solver built,
the kernels with its first solve or sensitivity).
"""

from __future__ import annotations

import functools
import logging
import multiprocessing
import threading
import time
from typing import Any

import numpy as np

from ..._util.lazy import lazy_module
from ..._util.threads import auto_threads, run_blocks
from ..._util.validate import ModelInputError
from ...config import MPCConfig, SystemConfig
from ..formulation import MPC
from ..solution import (
    STATUS_BREAKDOWN,
    STATUS_CONVERGED,
    STATUS_MAX_ITER,
    STATUS_NON_FINITE,
    BackendBase,
    BatchSolution,
    MPCSolution,
    Sensitivity,
    StartSettings,
    check_parameters,
    failure_summary,
)
from . import check_memo

ca = lazy_module("casadi")  # CasADi (~0.1-0.2 s of import) loads when first used

__all__ = ["KernelInputError", "KernelSolver", "cache_dir", "warm_up"]


class KernelInputError(ModelInputError):
    """The compiled kernel cannot solve the MPC of the system and config it was given (its
    check problem fails there, and passes with the default system and config): the input, not
    the formulation, is what it cannot handle (raised at the first solve, where the kernel is
    checked; the message names the input and the reference back-end)."""

log = logging.getLogger(__name__)



#: :mod:`~mpcrl_lite.mpc.backends.kernel_core`, imported when a solver first needs it (numba
#: comes with it): importing this module and building a :class:`KernelSolver` stay cheap.
K = lazy_module("mpcrl_lite.mpc.backends.kernel_core")
#: :mod:`~mpcrl_lite.mpc.backends.kernel_sizes`: the copies of the kernels for fixed sizes
KS = lazy_module("mpcrl_lite.mpc.backends.kernel_sizes")


@functools.cache
def _status_names() -> np.ndarray:
    """The status strings by the kernels' codes (STATUS_*, those of every interior-point
    back-end, :mod:`mpcrl_lite.mpc.solution`, stay importable from here)."""
    names = np.empty(4, dtype=object)
    names[[K.CONVERGED, K.MAX_ITER, K.NON_FINITE, K.BREAKDOWN]] = (
        STATUS_CONVERGED, STATUS_MAX_ITER, STATUS_NON_FINITE, STATUS_BREAKDOWN)
    return names

_BACKWARD_ERROR_MAX = 1e-6  # of the adjoint solve; above it a sensitivity is flagged
_KKT_CHECK_TOL = 1e-9  # relative KKT residual of the formulation check at construction
# agents from which the 'agent' factorisation forms the adjoint structured (all columns at
# once, no refinement; ~10x faster at n = 100) instead of column by column with refinement
_STRUCTURED_MIN_N = 16
#: problems per thread below which a call stays on one thread. A problem of the paper's size
#: costs about 14 us to solve and 5 us for its sensitivity (four at a time; 27 and 11 one at
#: a time), starting numba's second thread some ten: with 8 the learning months' calls (30
#: problems) use two threads (a call alone: about two thirds of the wall time of one; the
#: 100-month `learn` command: 9 % less wall time at 1.3x the CPU, as the second thread idles
#: or spins between calls; benchmarks/README.md), while single problems and small calls stay
#: on one
THREAD_MIN_PROBLEMS = 8
#: problems per block that a Python thread takes at a time in a forked child
#: (:func:`mpcrl_lite._util.threads.run_blocks`)
THREAD_BLOCK = 4


def cache_dir() -> str:
    """The folder numba caches the kernels in (see the module docstring)."""
    return K.cache_dir()


def warm_up(verbose: bool = False) -> float:
    """Compile the MPC kernels, or load them from numba's cache; returns the seconds it took.

    :class:`KernelSolver` loads them on first use; ``python -m mpcrl_lite.cli.warm`` (the
    Makefile's setup) warms every kernel of the package ahead, so that no notebook waits for
    the compiler.
    """
    t0 = time.perf_counter()
    K.ensure_compiled()
    for n, N in sorted(KS.SPECIALISED_SIZES):
        KS.kernels(n, N).ensure_compiled()
    took = time.perf_counter() - t0
    if verbose:
        print(f"mpcrl_lite MPC kernels ready in {took:.1f} s (cache: {cache_dir()})")
    return took


class KernelSolver(StartSettings, BackendBase):
    r"""Compiled primal-dual interior point for the MPC's barrier problem.

    Parameters
    ----------
    mpc
        The formulation. Before the first solve one problem at a pseudo-random parameter is
        solved and its KKT residual evaluated with :attr:`MPC.qp_function
        <mpcrl_lite.mpc.formulation.MPC.qp_function>`, so a formulation that no longer matches
        the kernels raises :class:`RuntimeError` there, never mid-run (a check that passed is
        remembered on this machine while nothing it depends on changes:
        :mod:`~mpcrl_lite.mpc.backends.check_memo`).
    config
        ``tau``, ``tol``, ``max_iter``, ``warm_start``, ``kkt_cond_max`` as for
        :class:`~mpcrl_lite.mpc.backends.batch.BatchSolver`.
    method
        ``'auto'`` (default), ``'stage'`` (block-tridiagonal in the stage multipliers,
        ``O(N n^3)`` per Newton step: few agents) or ``'agent'`` (per-agent tridiagonal plus
        the ``2N x 2N`` grid Schur complement, ``O(n N^2 + N^3)``: many agents). Both give
        the same results to rounding.

    Notes
    -----
    The interface is the batch solver's: :meth:`solve` and :meth:`solve_batch` (from
    :class:`~mpcrl_lite.mpc.solution.BackendBase`, around :meth:`_solve_parameters`; a warm
    start ``x0`` is used exactly as by the batch solver: only ``b, s``, pushed into the
    interior and blended with the cold start, non-finite entries ignored; failed rows have
    the status :data:`STATUS_MAX_ITER`, :data:`STATUS_NON_FINITE` or
    :data:`STATUS_BREAKDOWN` and keep their last iterate in ``x, lam, mu``),
    :meth:`sensitivity`, :meth:`shift`, :attr:`name`, :attr:`mpc`. The starting-point and
    path-following settings are the batch solver's
    (:class:`~mpcrl_lite.mpc.solution.StartSettings`).
    """

    name = "kernel"
    #: threads of one :meth:`solve_batch` or :meth:`sensitivity` call: ``None`` (default,
    #: :func:`~mpcrl_lite._util.threads.auto_threads`: the cores, one in a worker process)
    #: or a number; at most one per :data:`THREAD_MIN_PROBLEMS` problems, so that calls on
    #: fewer than twice as many stay on the calling thread. A block of problems per numba
    #: thread in one compiled call (in a forked child: Python threads taking blocks of
    #: :data:`THREAD_BLOCK` in turn). A problem's results are the same bits in any block:
    #: they do not depend on the thread count. Only calls from the main
    #: thread split.
    threads: int | None = None
    #: use the copy of the kernels compiled for this solver's sizes where there is one
    #: (:data:`~mpcrl_lite.mpc.backends.kernel_sizes.SPECIALISED_SIZES`, the paper's n = 3,
    #: N = 12): about 1.5x less CPU per problem, the same results bit for bit. Read at the
    #: first solve.
    specialise: bool = True
    #: solve four problems at once, and form their sensitivities, where the factorisation is
    #: ``'stage'`` (the paper's sizes: about half the CPU, the same results bit for bit;
    #: ``kernel_core.solve_lanes``, ``kernel_core.sensitivity_lanes``); False takes one
    #: problem after the other, as a reference for benchmarks and tests.
    lanes: bool = True
    #: skip the formulation check (:meth:`_check_formulation`) where the same check passed
    #: on this machine before, with the same kernels, formulation, versions, configs and
    #: options (:mod:`~mpcrl_lite.mpc.backends.check_memo`); False checks every solver.
    remember_check: bool = True

    def __init__(self, mpc: MPC, config: MPCConfig | None = None, method: str = "auto") -> None:
        if method not in ("auto", "stage", "agent"):
            raise ValueError(f"method={method!r}: expected 'auto', 'stage' or 'agent'")
        self.mpc = mpc
        self.config = config or MPCConfig()
        sysc = mpc.system
        self.n, self.N = mpc.n, mpc.N
        #: each battery's input bound ``U_bar^i`` (n,), the kernels' bounds of ``b^i, s^i``
        self._ubar = np.ascontiguousarray(sysc.battery("U_bar"), dtype=float)
        N = self.N
        self._method_asked = method
        gam = sysc.gamma ** np.arange(N + 1, dtype=float)
        stage = np.arange(N) < N - 1
        self._stagew = np.ascontiguousarray(np.stack([
            gam[:N],  # gamma^j, weights of the stage-j prices
            np.where(stage, gam[1:], 0.0),  # stage costs of soc_{j+1}
            (~stage).astype(float),  # the terminal cost (undiscounted)
            np.where(stage, gam[1:] * sysc.omega[0], sysc.omega_f[0]),
            np.where(stage, gam[1:] * sysc.omega[1], sysc.omega_f[1]),
        ]))
        # the kernels are loaded (or compiled) and checked against the formulation at the
        # first solve (:meth:`_ready`); the coordination kernel by its own first use; each
        # other entry of the kernels where first called (:meth:`_run`)
        self._checked = False
        self._entries: set[str] = set()

    @property
    def _method(self) -> int:
        """The kernels' code of the factorisation (numba is imported on first use)."""
        asked = self._method_asked
        if asked == "auto":
            return K.choose_method(self.n, self.N)
        return K.STAGE if asked == "stage" else K.AGENT

    @property
    def method(self) -> str:
        """The factorisation in use, 'stage' or 'agent'."""
        return "stage" if self._method == K.STAGE else "agent"

    @property
    def structured_adjoint(self) -> bool:
        """Sensitivities of all columns at once without refinement (many agents, 'agent'
        factorisation), else column by column with iterative refinement; may be set."""
        chosen = self.__dict__.get("_structured")
        if chosen is None:
            return self._method == K.AGENT and self.n >= _STRUCTURED_MIN_N
        return chosen

    @structured_adjoint.setter
    def structured_adjoint(self, value: bool) -> None:
        self._structured = bool(value)

    def _ready(self) -> None:
        """Load the kernels (from numba's cache, or compile them) and check them against the
        CasADi formulation (:meth:`_check_formulation`), once per solver; a check that passed
        on this machine with everything it depends on the same is remembered
        (:mod:`~mpcrl_lite.mpc.backends.check_memo`, :attr:`remember_check`)."""
        if not self._checked:
            self._kernels = KS.kernels(self.n, self.N, self.specialise)
            self._checked = True
            try:
                parameter, opts = self._check_inputs()
                # remembered for the package's own solver and formulation only
                remember = self.remember_check and type(self) is KernelSolver \
                    and check_memo.applies(self.mpc)
                memo = check_memo.key(self, self._kernels, opts, parameter) if remember \
                    else None
                if memo is None or not check_memo.passed(memo):
                    # the other entries are loaded where first called
                    self._kernels.ensure_compiled(("solve_rows",))
                    errors = self._check_formulation(parameter, opts)
                    if memo is not None:
                        check_memo.record(memo, errors)
            except BaseException:
                self._checked = False
                raise

    # ------------------------------------------------------------------ options ----------
    def _opts(self, max_iter: int | None = None) -> np.ndarray:
        """The option vector of the kernels (built at every call, so changed class or
        instance attributes take effect)."""
        sysc, cfg = self.mpc.system, self.config
        opts = np.empty(K.N_OPTS)
        opts[K.O_TAU], opts[K.O_TOL] = cfg.tau, cfg.tol
        opts[K.O_MAX_ITER] = cfg.max_iter if max_iter is None else max_iter
        opts[K.O_P] = sysc.P_bar
        opts[K.O_HI], opts[K.O_LO] = sysc.soc_high, sysc.soc_low
        opts[K.O_OM_HI], opts[K.O_OM_LO] = sysc.omega
        opts[K.O_U0], opts[K.O_T0_COLD], opts[K.O_T0_WARM] = (
            self.u0_fraction, self.t0_cold, self.t0_warm)
        opts[K.O_WARM_MARGIN], opts[K.O_WARM_WEIGHT] = self.warm_margin, self.warm_weight
        opts[K.O_SLACK_MARGIN], opts[K.O_SWITCH] = self.slack_margin, self.switch_factor
        opts[K.O_POLISH] = 1.0 if cfg.polish else 0.0
        return opts

    def _check_inputs(self) -> tuple[np.ndarray, np.ndarray]:
        """The parameter (np,) and the option vector of :meth:`_check_formulation`."""
        p = check_parameters(self.mpc, np.random.default_rng(12345))
        # with its own iteration limit and stopping rule: the check must not depend on
        # config.max_iter, config.tol or config.polish
        opts = self._opts(max_iter=500)
        opts[K.O_TOL], opts[K.O_POLISH] = min(opts[K.O_TOL], 1e-10), 1.0
        return p, opts

    def _check_formulation(self, p: np.ndarray, opts: np.ndarray) -> dict[str, float]:
        """Solve one problem at the pseudo-random parameter ``p`` with the options ``opts``
        (:meth:`_check_inputs`) and check the barrier KKT conditions of
        :attr:`MPC.qp_function <mpcrl_lite.mpc.formulation.MPC.qp_function>` there (sparse
        products, no dense matrices): the kernels' hand-written QP data and orderings must be
        the CasADi formulation's. Returns the residuals found (each within the tolerance)."""
        m = self.mpc
        sol = self._solve_parameters(p[None], None, opts)[0]
        H, q, c, A, e, C, d = m.qp_function(sol.p)
        x, lam, mu = ca.DM(sol.x), ca.DM(sol.lam), ca.DM(sol.mu)
        tau = self.config.tau
        rd = np.array(ca.mtimes(H, x) + q + ca.mtimes(A.T, lam) + ca.mtimes(C.T, mu)).ravel()
        rp = np.array(ca.mtimes(A, x) - e).ravel()
        rc = np.array(mu * (d - ca.mtimes(C, x))).ravel() - tau
        f = float(0.5 * ca.mtimes(x.T, ca.mtimes(H, x)) + ca.dot(q, x) + c)
        scale = 1.0 + float(np.abs(np.array(q)).max())
        errors = {
            "dual residual": np.abs(rd).max() / scale,
            "primal residual": np.abs(rp).max(),
            "complementarity": np.abs(rc).max() / scale,
            "cost": abs(f - sol.cost) / (1.0 + abs(f)),
        }
        bad = {k: v for k, v in errors.items() if not v <= _KKT_CHECK_TOL}
        if (not sol.success or bad) and self._defaults_pass():
            sysc, cfg = self.mpc.system, self.config
            raise KernelInputError(
                f"the compiled MPC kernel cannot solve the MPC of this system and config "
                f"({sol.status}; tau={cfg.tau:g}, tol={cfg.tol:g}, P_bar={sysc.P_bar!r}, "
                f"U_bar={sysc.U_bar!r}, alpha={sysc.alpha!r}, N={sysc.N}); expected inputs "
                "nearer the defaults (config.RANGES), or backend 'ipopt' (the reference)")
        if not sol.success or bad:
            raise RuntimeError(
                "KernelSolver's solution violates the KKT conditions of MPC.qp_function "
                f"({sol.status}; {bad}); the formulation in mpcrl_lite.mpc.formulation changed and "
                "mpcrl_lite.mpc.backends.kernel_core must be updated to match it"
            )
        return errors

    def _defaults_pass(self) -> bool:
        """Whether the check passes for the default system (same n and N) and config, i.e.
        the formulation agrees with the kernel and only the input is out of its reach."""
        system = self.mpc.system
        reference = SystemConfig(n=system.n, N=system.N)
        if system == reference and self.config == MPCConfig():
            return False
        try:
            KernelSolver(MPC(reference), MPCConfig(), method=self.method)
        except (RuntimeError, ValueError):
            return False
        return True

    def _threads(self, days: int) -> int:
        """Threads of a call on ``days`` problems (see :attr:`threads`)."""
        if days < 2 * THREAD_MIN_PROBLEMS or threading.current_thread() is not \
                threading.main_thread():
            return 1
        threads = auto_threads() if self.threads is None else int(self.threads)
        return max(1, min(threads, days // THREAD_MIN_PROBLEMS))

    def _run(self, rows: str, args: tuple, days: int) -> None:
        """The kernel ``rows`` (``'solve_rows'`` or ``'sensitivity_rows'``) on the ``days``
        problems of ``args``: on the calling thread; or, with several threads (:meth:`_threads`),
        in one call of its ``*_parallel`` entry, a block of problems per numba thread (in the
        process that was started, not forked: numba's OpenMP threads do not survive a fork), in
        a forked child on Python threads, blocks of :data:`THREAD_BLOCK` in turn."""
        kernels = self._kernels
        threads = self._threads(days)
        parallel = threads > 1 and multiprocessing.parent_process() is None
        entry = rows + "_parallel" if parallel else rows
        if entry not in self._entries and entry in kernels.ENTRIES:
            kernels.ensure_compiled((entry,))  # loaded where first called
            self._entries.add(entry)
        if threads <= 1:
            getattr(kernels, rows)(*args, 0, days)
        elif parallel:
            threads = kernels.set_threads(threads)
            # blocks of whole groups of four, which the kernels solve at once
            block = -(-days // threads)
            block = -(-block // kernels.LANES) * kernels.LANES
            getattr(kernels, rows + "_parallel")(*args, 0, days, block)
        else:
            run_blocks(getattr(kernels, rows), args, days, threads, THREAD_BLOCK)

    # ------------------------------------------------------- inside a compiled loop ------
    def loop_parts(self, rows: int) -> dict[str, Any] | None:
        """What a compiled closed loop needs to call this solver's kernels itself
        (:mod:`mpcrl_lite.sim.compiled_month`) for calls of ``rows`` problems: the kernel
        module, the arguments of its ``solve_rows`` and ``sensitivity_rows`` that stay the
        same all month, the sensitivity's verdict thresholds, whether to warm start, and the
        threads a call of this size gets (one in a forked child, whose numba threads are
        gone: :meth:`_run`). None where the loop must call :meth:`solve_batch` instead (the
        one-problem-at-a-time reference, ``lanes=False``). Loads and checks the kernels
        (:meth:`_ready`)."""
        if not self.lanes:
            return None
        self._ready()
        threads = self._threads(rows) if multiprocessing.parent_process() is None else 1
        return {
            "kernels": self._kernels, "opts": self._opts(), "ubar": self._ubar,
            "stagew": self._stagew, "n": self.n, "N": self.N, "method": self._method,
            "structured": bool(self.structured_adjoint),
            "cond_max": float(self.config.kkt_cond_max),
            "back_max": _BACKWARD_ERROR_MAX, "warm_start": bool(self.config.warm_start),
            "threads": threads, "lanes": int(self._kernels.LANES),
        }

    def status_strings(self, status: np.ndarray) -> tuple[str, ...]:
        """The status strings (``BatchSolution.status``) of the kernels' status codes."""
        return tuple(_status_names()[np.asarray(status, np.int64)].tolist())

    def report_failures(self, status: np.ndarray) -> None:
        """Log the failed problems of one call, given the kernels' status codes of its rows,
        as :meth:`solve_batch` does (for a compiled loop's hours)."""
        success = status == K.CONVERGED
        if not success.all():
            log.warning("%s", failure_summary(self.status_strings(status), success, self.name))

    # ------------------------------------------------------------------ solving ----------
    def _solve_parameters(self, P: np.ndarray, x0: np.ndarray | None,
                          opts: np.ndarray | None = None) -> BatchSolution:
        """Run the kernel on parameter vectors ``P`` (days, np) from ``x0`` (days, nx) or
        the cold start, with the option vector ``opts`` (default :meth:`_opts`)."""
        self._ready()
        t_start = time.perf_counter()
        opts = self._opts() if opts is None else opts
        m, days = self.mpc, P.shape[0]
        warm = x0 is not None
        x0 = np.ascontiguousarray(x0) if warm else np.zeros((1, m.nx))
        x, lam, mu = np.empty((days, m.nx)), np.empty((days, m.neq)), np.empty((days, m.nin))
        cost, action = np.empty(days), np.empty((days, self.n))
        iters, status = np.empty(days, np.int64), np.empty(days, np.int64)
        args = (np.ascontiguousarray(P), x0, warm, opts, self._ubar, self._stagew, self.n,
                self.N, self._method, x, lam, mu, cost, iters, status, action)
        self._run("solve_rows" if self.lanes else "solve_each", args, days)
        return BatchSolution(
            action=action, x=x, lam=lam, mu=mu, cost=cost,
            success=status == K.CONVERGED,
            status=self.status_strings(status),
            iterations=iters, p=P,
            solve_time=time.perf_counter() - t_start, backend=self.name,
        )

    # -------------------------------------------------------------- sensitivity ----------
    def sensitivity(self, solution: BatchSolution | MPCSolution) -> Sensitivity:
        r"""Policy sensitivities ``d pi / d theta`` of every problem in ``solution``.

        Works on any solution of this MPC (e.g. from
        :class:`~mpcrl_lite.mpc.backends.registry.IpoptSolver`), also with a different theta per row.

        Returns
        -------
        Sensitivity
            As :class:`~mpcrl_lite.mpc.solution.Sensitivity` documents; a row is not ``ok``
            (zero ``grad``, a ``reason``) where the solver failed, the point is not strictly
            interior, or the KKT matrix is singular or ill-conditioned (``cond`` above
            ``config.kkt_cond_max`` or an adjoint backward error above 1e-6). ``grad_soc0``
            holds ``d pi / d soc0`` from the same adjoint columns (None with the structured
            adjoint, which forms no column alone).
        """
        self._ready()
        solution = BatchSolution.of(solution)
        m = self.mpc
        days = len(solution)
        P = np.ascontiguousarray(np.atleast_2d(solution.p), dtype=float)
        success = np.ascontiguousarray(solution.success, dtype=np.bool_)
        grad = np.empty((days, m.n_theta, self.n))
        dsoc = np.empty((days, self.n, self.n))
        cond, back = np.empty(days), np.empty(days)
        code = np.empty(days, np.int64)
        structured = self.structured_adjoint

        def rows(a: np.ndarray, width: int) -> np.ndarray:
            return np.ascontiguousarray(np.asarray(a, dtype=float).reshape(days, width))

        args = (P, rows(solution.x, m.nx), rows(solution.lam, m.neq), rows(solution.mu, m.nin),
                success, self._opts(), self._ubar, self._stagew, self.n, self.N, self._method,
                structured, grad, dsoc, cond, back, code)
        self._run("sensitivity_rows" if self.lanes else "sensitivity_each", args, days)
        # the rows' verdicts at once (a decentralized hour has days x batteries of them);
        # only the rows that are not ok get a reason
        cond_max = self.config.kkt_cond_max
        if days and (code == K.SENS_OK).all() and back.max() <= _BACKWARD_ERROR_MAX \
                and cond.max() <= cond_max:
            # every row formed and well conditioned (the usual call; NaN goes the long way)
            return Sensitivity(grad, np.ones(days, np.bool_), cond, ("",) * days,
                               None if structured else dsoc)
        formed = code == K.SENS_OK
        ill = formed & ((back > _BACKWARD_ERROR_MAX) | (cond > cond_max))
        grad[ill] = 0.0
        dsoc[ill] = 0.0
        ok = formed & ~ill
        reasons = [""] * days
        for d in np.flatnonzero(~ok).tolist():
            c = int(code[d])
            if c == K.SENS_SKIPPED:
                reasons[d] = f"solver failed: {solution.status[d]}"
            elif c == K.SENS_NOT_INTERIOR:
                reasons[d] = "solution not strictly interior (S > 0 and mu > 0 violated)"
            elif c == K.SENS_SINGULAR:
                reasons[d] = "singular KKT matrix"
            else:
                reasons[d] = f"ill-conditioned KKT matrix (cond ~ {cond[d]:.2e})"
        return Sensitivity(grad, ok, cond, tuple(reasons), None if structured else dsoc)
