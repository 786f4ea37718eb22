"""Where the runs of a sweep execute: serially in this process, or on Dask.

:func:`run_serial` and :func:`run_dask` hand the runs still to do to
:func:`~mpcrl_lite.studies.sweep.run.run_chunk` in chunks of ``lockstep`` runs, whose learning runs
advance month by month in lockstep in one process (:mod:`mpcrl_lite.studies.lockstep`; the results
are those of the runs one by one), and call ``finished(run, row)`` as each chunk completes,
in completion order. By default (:func:`chunks` with ``lockstep=None``) each worker gets one
chunk, its share of the runs, and the serial scheduler one chunk of all runs;
``lockstep=1`` runs one run per task. A run's own errors are recorded by the task; a task
that could not run at all (its worker died) is recorded here for each of its runs, so the
table always gets a row.

:func:`check_scheduler` asks the scheduler at an address who it is, with a short timeout, so a
wrong address is reported in one line before the sweep writes anything (Dask's own client
waits 30 s and then raises a traceback).
"""

from __future__ import annotations

import asyncio
import logging
import math
import os
import re
import time
import traceback
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from contextlib import ExitStack, contextmanager
from pathlib import Path
from typing import Any

from ..._util.progress import progress_bar
from .grid import GridError, SweepRun, one_line
from .run import run_chunk
from .store import run_dir, write_json
from .table import run_row

__all__ = [
    "CONNECT_TIMEOUT",
    "NO_WORKER_TIMEOUT",
    "NO_WORKER_TIMEOUT_ENV",
    "DaskMissingError",
    "SchedulerError",
    "check_address",
    "check_scheduler",
    "chunks",
    "require_dask",
    "run_dask",
    "run_serial",
]

#: Seconds :func:`check_scheduler` waits for a scheduler's answer by default.
CONNECT_TIMEOUT = 5.0

#: Seconds a sweep on Dask waits while no worker is alive before it stops (one line; the
#: finished runs are kept). The environment variable :data:`NO_WORKER_TIMEOUT_ENV` sets
#: another value.
NO_WORKER_TIMEOUT = 120.0
NO_WORKER_TIMEOUT_ENV = "MPCRL_LITE_NO_WORKER_TIMEOUT_S"
#: What a scheduler address looks like: ``PROTOCOL://HOST[:PORT]`` or ``HOST:PORT``.
_ADDRESS = re.compile(r"^(?:[a-z][a-z0-9+.-]*://[^\s/]+|[^\s/:]+:\d{1,5})$")

Finished = Callable[[SweepRun, dict[str, Any]], None]


class SchedulerError(GridError):
    """The Dask scheduler named cannot be used: no answer, not a scheduler, a bad address."""


class DaskMissingError(GridError, ImportError):
    """A parallel sweep was asked for, but Dask's ``distributed`` is not installed."""


def require_dask() -> None:
    """Fail in one line if ``distributed`` cannot be imported."""
    try:
        import distributed  # noqa: F401  (optional dependency, only needed here)
    except ImportError:
        raise DaskMissingError(
            "Dask is needed for parallel sweeps: pip install 'mpcrl_lite[sweep]' "
            "(or pass scheduler='serial')"
        ) from None


async def _identity(address: str, timeout: float) -> Any:
    from distributed.comm import connect

    comm = await connect(address, timeout=timeout)
    try:
        await comm.write({"op": "identity", "reply": True})
        return await comm.read()
    finally:
        await comm.close()


async def _identity_within(address: str, timeout: float) -> Any:
    # connect()'s timeout does not cover a peer that accepts and then stays silent
    return await asyncio.wait_for(_identity(address, timeout), timeout)


def check_address(address: Any) -> str:
    """``address`` if it reads as a Dask scheduler address (``tcp://HOST:PORT``,
    ``tls://...``, ``HOST:PORT``), else a :class:`SchedulerError` in one line; nothing is
    contacted (:func:`check_scheduler` does that)."""
    if not isinstance(address, str) or not _ADDRESS.match(address.strip()):
        raise SchedulerError(
            f"scheduler address {address!r} is not an address; expected the address of a "
            "running Dask scheduler, e.g. tcp://HOST:8786 (or 'serial', or none for a local "
            "cluster)")
    return address


def check_scheduler(address: str, timeout: float = CONNECT_TIMEOUT) -> None:
    """Check that a Dask scheduler answers at ``address`` within ``timeout`` seconds.

    The question runs on a thread of its own, so this also works where an event loop is
    already running (a Jupyter kernel).

    Raises
    ------
    SchedulerError
        In one line naming the address and what was expected: a malformed address, no
        answer in time, or an answer from something that is not a scheduler (a worker).
    DaskMissingError
        ``distributed`` is not installed.
    """
    if isinstance(timeout, bool) or not isinstance(timeout, (int, float)) or not (
        math.isfinite(timeout) and timeout > 0
    ):
        raise GridError(f"connect_timeout={timeout!r}: expected a number of seconds > 0")
    require_dask()
    expected = "expected the address of a running Dask scheduler, e.g. tcp://HOST:8786"
    if not isinstance(address, str) or not address.strip():
        raise SchedulerError(f"scheduler address {address!r} is not an address; {expected}")
    with ThreadPoolExecutor(1, thread_name_prefix="check-scheduler") as pool:
        try:
            answer = pool.submit(asyncio.run, _identity_within(address, timeout)).result()
        except (ValueError, TypeError) as err:  # distributed's parsing of the address
            raise SchedulerError(
                f"scheduler address {address!r} is malformed ({one_line(err)}); {expected}"
            ) from None
        except Exception as err:  # noqa: BLE001 (refused, unknown host, timed out, closed)
            # distributed retries a refused connection until the timeout, so most failures
            # read 'Timed out trying to connect'; other reasons are worth showing
            text = one_line(err)
            timed_out = isinstance(err, TimeoutError) or "timed out" in text.lower()
            reason = "" if timed_out else f" ({text or type(err).__name__})"
            raise SchedulerError(
                f"no Dask scheduler answered at {address} within {timeout:g} s{reason}; "
                f"{expected}"
            ) from None
    kind = answer.get("type") if isinstance(answer, dict) else None
    if kind != "Scheduler":
        raise SchedulerError(
            f"{address} is not a Dask scheduler (it answered as {kind!r}); {expected}"
        )


def chunks(todo: Sequence[SweepRun], lockstep: int | None, workers: int) -> list[list[SweepRun]]:
    """``todo`` in grid order, cut into chunks of ``lockstep`` runs (default: as equal as
    possible, one per worker)."""
    if lockstep is not None and (isinstance(lockstep, bool) or not isinstance(lockstep, int)
                                 or lockstep < 1):
        raise GridError(f"lockstep={lockstep!r}: expected an integer >= 1 (runs per chunk)")
    todo = list(todo)
    if not todo:
        return []
    size = lockstep or math.ceil(len(todo) / max(workers, 1))
    return [todo[i:i + size] for i in range(0, len(todo), size)]


def run_serial(
    todo: Sequence[SweepRun], args: tuple, finished: Finished, progress: bool,
    lockstep: int | None = None,
) -> None:
    """Run the tasks in this process, ``lockstep`` runs at a time (default all)."""
    with progress_bar(total=len(todo), desc="sweep (serial)", unit="run", disable=not progress) as bar:
        for chunk in chunks(todo, lockstep, 1):
            for run, row in zip(chunk, run_chunk(chunk, *args), strict=True):
                finished(run, row)
                bar.update(1)


def run_dask(
    todo: Sequence[SweepRun], args: tuple, finished: Finished, progress: bool,
    scheduler: str | None, workers: int | None, out: Path, lockstep: int | None = None,
) -> None:
    """Run the tasks on Dask: a local cluster of ``workers`` processes, or ``scheduler``;
    each task is a chunk of ``lockstep`` runs (default: one chunk per worker).

    ``args`` are the task's arguments after the runs (``out``, notebook, mapping).
    """
    require_dask()
    from distributed import Client, LocalCluster

    with ExitStack() as stack:
        # Dask's own INFO lines (cluster start, connections, shutdown) are not the sweep's
        # news: WARNING and above only, ERROR and above without a progress bar (--quiet)
        stack.enter_context(_log_level("distributed", logging.WARNING if progress
                                       else logging.ERROR))
        if scheduler is None:
            cluster = stack.enter_context(LocalCluster(
                n_workers=workers or 2, threads_per_worker=1, processes=True,
                host="127.0.0.1", dashboard_address="127.0.0.1:0",
                # shutdown races (a worker's last heartbeat) log tracebacks at ERROR level;
                # a run's own errors are in its error.json, a lost worker raises here
                silence_logs=logging.CRITICAL,
            ))
            client = stack.enter_context(Client(cluster))
            slots = workers or 2
        else:
            client = stack.enter_context(Client(scheduler))
            slots = sum(w.get("nthreads", 1) for w in client.scheduler_info()["workers"].values())
        token = os.urandom(4).hex()
        futures = {
            client.submit(run_chunk, chunk, *args, pure=False,
                          key=f"sweep-{token}-{chunk[0].run_id}-{len(chunk)}"): chunk
            for chunk in chunks(todo, lockstep, slots)
        }
        failed = 0
        with progress_bar(total=len(todo), desc="sweep", unit="run", disable=not progress) as bar:
            for future in _completed(client, futures, scheduler):
                chunk = futures[future]
                try:
                    rows = future.result()
                except Exception as err:  # noqa: BLE001 (the worker died, the task could not run)
                    rows = []
                    for run in chunk:
                        directory = run_dir(out, run)
                        directory.mkdir(parents=True, exist_ok=True)
                        write_json(directory / "error.json", {
                            "type": type(err).__name__, "message": str(err),
                            "traceback": "".join(traceback.format_exception(err)),
                        })
                        rows.append(run_row(run, out, args[1] is not None))
                for run, row in zip(chunk, rows, strict=True):
                    if row["status"] == "failed":
                        failed += 1
                        bar.set_postfix(failed=failed, refresh=False)
                    finished(run, row)
                    bar.update(1)


def _no_worker_timeout() -> float:
    text = os.environ.get(NO_WORKER_TIMEOUT_ENV)
    if not text:
        return NO_WORKER_TIMEOUT
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and value > 0):
        raise GridError(f"{NO_WORKER_TIMEOUT_ENV}={text!r}: expected a number of seconds > 0")
    return value


def _completed(client: Any, futures: Any, scheduler: str | None, poll: float = 1.0):
    """The futures as they complete, like ``distributed.as_completed``; a
    :class:`SchedulerError` (one line) once no worker has been alive for
    :data:`NO_WORKER_TIMEOUT` seconds (the tasks would wait forever)."""
    from distributed import wait

    limit = _no_worker_timeout()
    pending = set(futures)
    alone_since: float | None = None
    while pending:
        try:
            done, pending = wait(pending, timeout=poll, return_when="FIRST_COMPLETED")
        except TimeoutError:
            done = set()
        yield from done
        if not pending or done:
            alone_since = None
            continue
        try:
            alive = len(client.scheduler_info()["workers"])
        except Exception:  # noqa: BLE001 (the scheduler itself is gone)
            alive = 0
        now = time.monotonic()
        if alive:
            alone_since = None
        elif alone_since is None:
            alone_since = now
        elif now - alone_since > limit:
            raise SchedulerError(
                f"no Dask worker alive at {scheduler or 'the local cluster'} for {limit:g} s "
                f"with {len(pending)} task(s) left; the finished runs are kept: start workers "
                f"(or set {NO_WORKER_TIMEOUT_ENV}) and run the same sweep again")


@contextmanager
def _log_level(name: str, level: int):
    """The logger ``name`` at ``level`` for the block (at least that severe), then as it was."""
    logger = logging.getLogger(name)
    before = logger.level
    logger.setLevel(max(level, before))
    try:
        yield
    finally:
        logger.setLevel(before)
