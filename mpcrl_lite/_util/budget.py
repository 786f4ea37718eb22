"""The size of a piece of work against the machine: lower estimates of its peak memory and
run time from the problem size, refused beyond what the machine has (:func:`check_budget`).

Every command checks its work with it before allocating anything (``simulate``, ``learn``,
``baselines``, ``evaluate``, ``tune`` through :mod:`mpcrl_lite.cli.inputs`; ``sweep`` and
``study`` for all their runs, :mod:`mpcrl_lite.studies.sweep.api`), and refuses

* memory above what the machine has available (Linux's ``MemAvailable``; elsewhere
  ``psutil.virtual_memory().available`` when psutil is installed, else ``os.sysconf`` of the
  available physical pages), and
* an estimated run time above :data:`TIME_LIMIT_S` seconds (4 hours; the environment
  variable ``MPCRL_LITE_TIME_LIMIT_S`` sets another limit, e.g. for a long cluster run).

The estimates are deliberately low (measured on a laptop core and rounded down for time, up
only where memory grows with the data), so a refusal means the work surely does not fit;
work near the limits is left to run. The learners built from the library
(:func:`mpcrl_lite.learning.learner.resolve_setup`) check the memory of a month alone
(:func:`check_memory`): how long a library user lets a run go is theirs to say.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

__all__ = ["TIME_LIMIT_ENV", "TIME_LIMIT_S", "Budget", "available_memory", "check_budget",
           "check_estimate", "check_memory", "estimate", "learning_estimate"]

#: Default limit of the estimated run time of one command, in seconds.
TIME_LIMIT_S = 4 * 3600.0
TIME_LIMIT_ENV = "MPCRL_LITE_TIME_LIMIT_S"
#: The MPC horizon the constants below were measured with (SystemConfig.N's default).
_HORIZON = 12

# Measured (simulate, N = 12, tau default): about 23 KiB of arrays per battery-day, 125 KiB of
# set-up per battery, 3 ms per battery-day of closed loop, and a set-up that grows with n**2
# (about 2e-5 s * n**2: 170 s at n = 3000). The time constants are rounded down.
_BYTES_PER_AGENT_DAY = 32 * 1024
_BYTES_PER_AGENT = 128 * 1024
_SECONDS_PER_AGENT_DAY = 1e-3
_SETUP_SECONDS_PER_AGENT2 = 1e-5


def _mem_available_linux() -> int | None:
    """``MemAvailable`` of ``/proc/meminfo`` in bytes (Linux's estimate of the memory a new
    allocation can have without swapping, the figure ``psutil`` reports there), or None."""
    try:
        with open("/proc/meminfo", "rb") as f:
            for line in f:
                if line.startswith(b"MemAvailable:"):
                    return int(line.split()[1]) * 1024  # kB
    except (OSError, ValueError, IndexError):
        pass
    return None


def available_memory() -> int | None:
    """Bytes of memory available to a new allocation now, or None where it is not known:
    Linux's ``MemAvailable`` read directly (0.05 ms, where importing psutil takes 7 ms of a
    command's start), else psutil where it is installed, else ``os.sysconf``."""
    found = _mem_available_linux()
    if found is not None:
        return found
    try:
        import psutil
    except ImportError:  # pragma: no cover (psutil is present in the project's environments)
        pass
    else:
        return int(psutil.virtual_memory().available)
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):  # pragma: no cover (not POSIX)
        return None


@dataclass(frozen=True)
class Budget:
    """Estimated peak memory (bytes) and run time (seconds) of a command."""

    memory: float
    seconds: float


def estimate(n: int, days: int, runs: int = 1, sensitivities: bool = False,
             horizon: int = _HORIZON) -> Budget:
    """Lower estimates of the peak memory and run time of ``runs`` closed-loop months of
    ``days`` days with ``n`` batteries (``sensitivities``: a learning month, twice the cost)."""
    scale = max(1.0, (horizon / 12) ** 2)
    factor = 2.0 if sensitivities else 1.0
    memory = factor * scale * float(n) * float(days) * _BYTES_PER_AGENT_DAY \
        + float(n) * _BYTES_PER_AGENT
    seconds = factor * float(runs) * float(n) * float(days) * _SECONDS_PER_AGENT_DAY \
        + _SETUP_SECONDS_PER_AGENT2 * float(n) ** 2
    return Budget(memory, seconds)


def learning_estimate(n: int, days: int, months: int, eval_draws: int = 1, eval_every: int = 0,
                      horizon: int = _HORIZON) -> Budget:
    """:func:`estimate` of a learning run: ``months`` learning months and, every
    ``eval_every`` months (0: never), an evaluation of ``eval_draws`` months simulated as one
    batch."""
    learn = estimate(n, days, months, sensitivities=True, horizon=horizon)
    evaluations = -(-months // eval_every) if eval_every else 0  # ceil: the last month too
    check = estimate(n, days * eval_draws, evaluations, horizon=horizon)
    return Budget(max(learn.memory, check.memory), learn.seconds + check.seconds)


def _time_limit() -> float:
    text = os.environ.get(TIME_LIMIT_ENV)
    if not text:
        return TIME_LIMIT_S
    try:
        value = float(text)
    except ValueError:
        raise ValueError(f"{TIME_LIMIT_ENV}={text!r}: expected a number of seconds") from None
    if not value > 0:
        raise ValueError(f"{TIME_LIMIT_ENV}={text!r}: expected a positive number of seconds")
    return value


def check_budget(what: str, n: int, days: int, runs: int = 1, sensitivities: bool = False,
                 horizon: int = _HORIZON) -> Budget:
    """:func:`estimate`, refused (``ValueError``, one line) above the available memory or the
    time limit. ``what`` names the values in the message, e.g. ``'--days 1000000000 --n 3'``."""
    return check_estimate(what, estimate(n, days, runs, sensitivities, horizon))


def check_memory(what: str, budget: Budget) -> Budget:
    """The memory half of :func:`check_estimate` alone: ``budget`` refused (``ValueError``,
    one line naming ``what``) above the available memory. For the library's entry points
    (:func:`mpcrl_lite.learning.learner.resolve_setup`), whose run time is their caller's
    choice."""
    memory = available_memory()
    if memory is not None and budget.memory > memory:
        raise ValueError(
            f"{what}: needs about {budget.memory / 2**30:.3g} GiB of memory; expected at most "
            f"the {memory / 2**30:.3g} GiB available (use fewer days or batteries)")
    return budget


def check_estimate(what: str, budget: Budget) -> Budget:
    """``budget`` (e.g. a sum of :func:`estimate` over the runs of a sweep), refused
    (``ValueError``, one line naming ``what``) above the available memory or the time limit."""
    check_memory(what, budget)
    limit = _time_limit()
    if budget.seconds > limit:
        raise ValueError(
            f"{what}: would run for about {budget.seconds / 3600:.3g} hours or more; expected "
            f"at most the time limit of {limit / 3600:.3g} hours (set {TIME_LIMIT_ENV} to "
            "raise it)")
    return budget
