"""One numba set-up for every compiled kernel of the package.

Every kernel (the MPC back-end :mod:`mpcrl_lite.mpc.backends.kernel_core`, the exploration
:mod:`mpcrl_lite.sim.exploration_kernel`, the coordination rounds
:mod:`mpcrl_lite.decentralized.coordination_kernel`, the causal dynamic program
:mod:`mpcrl_lite.bounds.causal.kernels`) is compiled through :func:`njit_cached`, so all of
them share one on-disk cache and one fallback when that cache cannot be written, and each
says so in one log line (:func:`ensure_compiled`) when it has to compile.

Where the cache goes: ``NUMBA_CACHE_DIR`` if set; else the ``__pycache__`` folder next to the
kernel's module if it is writable; else numba's per-user cache directory; if none of these is
writable (a read-only installation and home), a folder in the system's temporary directory.
"""

from __future__ import annotations

import logging
import os
import tempfile
from collections.abc import Callable, Iterable
from typing import Any

import numba
from numba import njit
from numba.core import event

__all__ = ["CACHED", "CompileNotice", "cache_dir", "ensure_compiled", "njit_cached"]

log = logging.getLogger("mpcrl_lite.kernels")


def _probe() -> int:
    return 0


def _cache_location() -> bool:
    """Numba looks for a writable cache folder (``NUMBA_CACHE_DIR``, the package's
    ``__pycache__``, the per-user cache) when a ``cache=True`` function is defined and raises
    if there is none; then point it at a folder in the temporary directory instead. False
    if even that fails (the kernels are then compiled in every process)."""
    try:
        njit(cache=True)(_probe)
        return True
    except RuntimeError:
        uid = os.getuid() if hasattr(os, "getuid") else "user"
        numba.config.CACHE_DIR = os.path.join(tempfile.gettempdir(), f"mpcrl_lite-numba-{uid}")
    try:
        njit(cache=True)(_probe)
        return True
    except RuntimeError:
        return False


#: whether the compiled kernels are cached on disk
CACHED = _cache_location()


def njit_cached(**options: Any) -> Callable:
    """``numba.njit`` with the package's cache setting (:data:`CACHED`) and ``options``."""
    return njit(cache=CACHED, **options)


def cache_dir(dispatcher: Any) -> str:
    """The folder numba caches ``dispatcher`` (a compiled function) in."""
    cache = getattr(dispatcher, "_cache", None)
    return str(getattr(cache, "_cache_path", "(unknown)"))


class CompileNotice(event.Listener):
    """Logs one line (WARNING) when numba starts compiling, i.e. when it found no cache."""

    def __init__(self, what: str, where: str) -> None:
        self.what, self.where, self.said = what, where, False

    def on_start(self, ev) -> None:
        if not self.said:
            self.said = True
            log.warning("mpcrl_lite: compiling %s (once; cached in %s; 'python -m "
                        "mpcrl_lite.cli.warm' does it ahead)", self.what, self.where)

    def on_end(self, ev) -> None:
        pass


#: the sets of dispatchers :func:`ensure_compiled` found loaded (by identity): a set is not
#: looked at again (numba's ``signatures`` is a list made at every read, and a kernel called
#: every hour asks at every call)
_loaded: set[tuple[int, ...]] = set()


def ensure_compiled(dispatchers: Iterable[Any], warm_up: Callable[[], None], what: str) -> None:
    """Load ``dispatchers`` from the cache or compile them by calling ``warm_up`` (logging
    one line, naming ``what``, if anything compiles). Nothing happens once they are loaded."""
    dispatchers = tuple(dispatchers)
    key = tuple(map(id, dispatchers))
    if key in _loaded:
        return
    if not all(d.signatures for d in dispatchers):
        with event.install_listener("numba:compile",
                                    CompileNotice(what, cache_dir(dispatchers[0]))):
            warm_up()
    if all(d.signatures for d in dispatchers):
        _loaded.add(key)
