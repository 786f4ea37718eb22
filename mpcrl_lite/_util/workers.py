"""Worker processes of the package's process pools: they end with the process that made them.

A process pool's worker waits for work on a pipe from its parent. If the parent ends
normally it tells the workers to stop; if it is killed outright (``SIGKILL``, an
out-of-memory kill) a worker started with ``fork`` still holds copies of the pipe's ends,
sees no end of it, and would wait for ever, with its memory. :func:`end_with_parent`, called
in a pool's initializer (the evaluation worker of :mod:`mpcrl_lite.learning.eval_worker`,
``tune``'s workers), watches the parent and ends the worker once it is gone.
"""

from __future__ import annotations

import multiprocessing
import os
import threading
import time

__all__ = ["end_with_parent"]


def end_with_parent(poll_s: float = 0.5) -> None:
    """In a worker process: end it (``os._exit``) once its parent process has ended, checked
    every ``poll_s`` seconds by a daemon thread (the parent is gone when this process has been
    handed to another one: its parent id changes). The parent is the one multiprocessing
    started the worker from, so a parent that died while the worker was still starting counts
    too. Outside a worker process (an initializer also run in the main process) nothing."""
    started_by = multiprocessing.parent_process()
    if started_by is None:
        return
    parent = started_by.pid

    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(poll_s)
        os._exit(0)

    threading.Thread(target=watch, name="mpcrl_lite-parent-watch", daemon=True).start()
