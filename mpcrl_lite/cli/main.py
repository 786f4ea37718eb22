"""Command line: ``python -m mpcrl_lite COMMAND ...``.

Each command lives in a module of :mod:`mpcrl_lite.cli.commands` (its options and its work);
the options several commands share and the checks made before any work are in
:mod:`mpcrl_lite.cli.args`. This module builds the parser and dispatches.

Commands
--------
simulate   closed loop of the nominal MPC (theta0) over some days; summary + figure
learn      the learning experiment (months x days, LSTD + DPG); History + summary + figures
report     execute every notebook into a report directory (papermill)
baselines  clairvoyant / nominal / rule-based policies on the same draws as a History
evaluate   a learned theta and the nominal MPC on K noise draws of a (new) month
sweep      a grid of learning runs on Dask
study      one learning run per seed (through sweep); convergence, spread, learning curves

``learn``, ``simulate``, ``baselines`` and ``evaluate`` read another month of prices with
``--prices EXPORT.csv --area AREA --month YYYY-MM`` (a Nord Pool export). ``learn``,
``simulate``, ``baselines``, ``evaluate`` and ``study`` take ``--forecast {paper,
until_midnight}`` (``MPCConfig.forecast``): the paper's MPC by default, or the extension beyond
the paper whose forecast stops at midnight (:mod:`mpcrl_lite.system.forecast`).

Bad arguments end with one line on stderr (``mpcrl_lite <command>: error: ...``) and exit
status 2, never with a traceback; nothing is computed or written before every argument,
the output directory and the size of the work (memory available, time limit: see
:mod:`mpcrl_lite.cli.inputs`) have been checked. Outputs are written atomically and finished
results are never replaced without ``--force``.
"""

from __future__ import annotations

import argparse
import logging
import sys

from .._util.malloc import keep_freed_memory
from .._util.validate import ModelInputError
from .args import Parser, UsageError
from .commands import COMMANDS

# The heavier modules (CasADi, the solvers, matplotlib) are imported inside each command, so
# that --help and argument errors answer at once.

__all__ = ["build_parser", "end_process", "main"]


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of ``python -m mpcrl_lite``."""
    parser = Parser(prog="mpcrl_lite", description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="command", required=True, parser_class=Parser)
    for command in COMMANDS:
        command.add_parser(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point; returns the exit status."""
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    run = {command.NAME: command.run for command in COMMANDS}[args.command]
    keep_freed_memory()  # a command's arrays reuse freed memory (same results, less time)
    try:
        return run(args)
    except (UsageError, ModelInputError) as err:
        print(f"mpcrl_lite {args.command}: error: {' '.join(str(err).split())}",
              file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"mpcrl_lite {args.command}: interrupted (checkpoints, if any, are kept)",
              file=sys.stderr)
        return 130


def end_process(status: int | None) -> int:
    """End the process of ``python -m mpcrl_lite`` with ``status`` once its command has
    returned: wait for the threads that are not daemons (a commit under way), run the exit
    handlers (``atexit``: logging, process pools, temporary folders), flush the output, then
    ``os._exit``. The interpreter's own teardown is skipped: it frees the compiled kernels
    numba loaded object by object, about 0.3 s of a 4-second ``learn`` (``benchmarks/README.md``,
    "A month in one compiled call"); nothing of the command's is left to it (files are
    written and closed, with fsync, before a command returns). Returns ``status`` where
    ``os._exit`` is not reached (never, but a caller may rely on it)."""
    import atexit
    import os
    import threading

    code = 0 if status is None else int(status)
    # what the interpreter does first at its exit: threading's exit callbacks (the thread
    # pools' idle workers, e.g. the kernels' helpers of run_blocks, are told to end), then
    # every thread that is not a daemon joined. Joining without the callbacks waited for ever
    # on an idle pool's worker (learn --decentralized never ended).
    shutdown = getattr(threading, "_shutdown", None)
    if shutdown is not None and threading.current_thread() is threading.main_thread():
        shutdown()
    else:  # pragma: no cover (CPython has it; the command runs on the main thread)
        for thread in threading.enumerate():
            if thread is not threading.current_thread() and not thread.daemon:
                thread.join()
    atexit._run_exitfuncs()
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):  # a closed pipe: nothing more can be said
            pass
    os._exit(code)
    return code  # pragma: no cover (os._exit does not return)
