"""Copies of the compiled kernels with the problem's sizes fixed at compile time.

:mod:`~mpcrl_lite.mpc.backends.kernel_core` reads the number of batteries ``n`` and the
horizon ``N`` from its arrays, so one compiled version serves every size. For the sizes in
:data:`SPECIALISED_SIZES` (the paper's, which every learning run, study and search of the
package uses, and the 11-hour tail of the Q-learner's fixed-first-action MPC)
:func:`kernels` imports a copy of that module whose two constants
``FIXED_N`` and ``FIXED_HORIZON`` hold the sizes. The compiler then knows the bounds of the
small loops over batteries and stages, unrolls them and keeps their values in registers:
about 1.5x less CPU per problem at n = 3, N = 12 (``benchmarks/README.md``). The copy does
the same operations in the same order, so its results are those of the generic kernels bit
for bit (``tests/mpc/test_kernel_sizes.py``).

The copy is a file named by its sizes and a hash of its text, in a cache folder outside the
package (``mpcrl_lite-kernels`` in ``NUMBA_CACHE_DIR``, else in ``~/.cache``, else in the
temporary directory; :func:`_folder`). It is written only when missing (with the
modification time of ``kernel_core.py``, so that processes writing it at once leave the same
file and numba's cache of it stays valid), and compiled into numba's cache like the generic
kernels (``python -m mpcrl_lite.cli.warm`` does it ahead; about a minute).
Other sizes use the generic kernels; so does a :class:`~mpcrl_lite.mpc.backends.kernel.
KernelSolver` with ``specialise = False``.

Copies of other versions of ``kernel_core.py`` (an earlier checkout, an upgrade) would stay in
the folder with their compiled code, about 5 MB each; :func:`prune` removes them, and
``python -m mpcrl_lite.cli.warm`` (``make setup``) calls it after compiling the current ones.
"""

from __future__ import annotations

import hashlib
import importlib.util
import os
import py_compile
import sys
import tempfile
import threading
from pathlib import Path
from types import ModuleType

__all__ = ["SPECIALISED_SIZES", "folder", "import_generated", "kernels", "prune", "source",
           "write_once"]

#: the sizes ``(n, N)`` served by a specialised copy: the paper's three batteries and
#: 12-hour horizon (the package's defaults), and the 11-hour tail of their fixed-first-action
#: MPC (:mod:`mpcrl_lite.mpc.q_kernel`, every Q-learning step: about 12 % of a Q-learning
#: month's time; each copy costs ``make setup`` about a minute of compiling)
SPECIALISED_SIZES = frozenset({(3, 12), (3, 11)})

_GENERIC = "mpcrl_lite.mpc.backends.kernel_core"
_MARK = "FIXED_N = 0\nFIXED_HORIZON = 0\n"
_lock = threading.Lock()
_loaded: dict[tuple[int, int], ModuleType] = {}


def _generic() -> ModuleType:
    return importlib.import_module(_GENERIC)


def source(n: int, N: int) -> str:
    """The text of the copy of the kernels for ``n`` batteries and horizon ``N``."""
    if int(n) < 1 or int(N) < 2:
        raise ValueError(f"n={n}, N={N}: expected n >= 1 and N >= 2")
    text = Path(_generic().__file__).read_text(encoding="utf-8")
    if text.count(_MARK) != 1:
        raise RuntimeError(f"{_GENERIC} no longer holds the line pair {_MARK!r} exactly once")
    header = (f"# Generated from kernel_core.py by mpcrl_lite.mpc.backends.kernel_sizes for "
              f"n = {int(n)}, N = {int(N)}; do not edit.\n")
    return header + text.replace(_MARK, f"FIXED_N = {int(n)}\nFIXED_HORIZON = {int(N)}\n")


def _folder() -> Path:
    """Where the copies go: ``mpcrl_lite-kernels`` in ``NUMBA_CACHE_DIR`` if that is set, else
    in the user's cache folder (``XDG_CACHE_HOME`` or ``~/.cache``), else in the system's
    temporary directory; the first that can be written. Never inside the package: its
    folders hold its modules only."""
    bases = [os.environ.get("NUMBA_CACHE_DIR"),
             os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache"),
             tempfile.gettempdir()]
    for base in bases:
        if not base:
            continue
        folder = Path(base) / "mpcrl_lite-kernels"
        try:
            folder.mkdir(parents=True, exist_ok=True)
        except OSError:
            continue
        if os.access(folder, os.W_OK):
            return folder
    raise RuntimeError("no writable folder for the specialised kernels")


def _write(path: Path, text: str, mtime: float) -> None:
    """Write ``text`` to ``path`` unless the file is there (atomically, with ``mtime``): its
    name carries the hash of its text, and a file appears only whole (``os.replace``), so one
    that exists holds ``text``."""
    if path.exists():
        return
    tmp = path.with_name(f".{path.name}.{os.getpid()}.{threading.get_ident()}.tmp")
    tmp.write_text(text, encoding="utf-8")
    os.utime(tmp, (mtime, mtime))
    os.replace(tmp, path)


def folder() -> Path:
    """The cache folder of the generated kernel modules (:func:`_folder`); the compiled closed
    loop (:mod:`mpcrl_lite.sim.compiled_month`) puts its copies there too."""
    return _folder()


def write_once(path: Path, text: str, mtime: float) -> None:
    """Write a generated module's ``text`` to ``path`` unless it is there (:func:`_write`)."""
    _write(path, text, mtime)


def _stem(n: int, N: int, text: str | None = None) -> str:
    """The file name (without ``.py``) of the copy for ``(n, N)`` of this version (``text``:
    its :func:`source`, if at hand): named by its text, copies of other versions of the
    package (another checkout, an upgrade) sit beside it instead of overwriting it, and each
    keeps its numba cache."""
    text = source(n, N) if text is None else text
    digest = hashlib.sha256(text.encode("utf-8")).hexdigest()[:12]
    return f"kernel_core_n{int(n)}_N{int(N)}_{digest}"


def prune() -> list[Path]:
    """Remove the copies of other versions of the kernels from the cache folder, with their
    compiled code in numba's cache (``__pycache__``); returns the files removed.

    The copies of this version (:data:`SPECIALISED_SIZES`) stay. A process of another version
    still running keeps the code it has loaded."""
    folder = _folder()
    keep = {_stem(n, N) for n, N in SPECIALISED_SIZES}
    removed = []
    for path in [*folder.glob("kernel_core_n*_N*_*.py"),
                 *folder.glob("__pycache__/kernel_core_n*_N*_*.*")]:
        if path.name.split(".")[0] not in keep:
            try:
                path.unlink()
            except FileNotFoundError:  # another process pruned it first
                continue
            removed.append(path)
    return removed


def _load(n: int, N: int) -> ModuleType:
    text = source(n, N)
    path = _folder() / f"{_stem(n, N, text)}.py"
    _write(path, text, os.stat(_generic().__file__).st_mtime)
    # its relative imports are the original's
    return import_generated(path, f"{_GENERIC}_n{n}_N{N}", _GENERIC.rpartition(".")[0])


def _write_bytecode(path: Path, cached: str | None) -> None:
    """Write the bytecode of the generated module at ``path`` to ``cached`` (its
    ``__pycache__`` file) unless it is there. Python writes it on import by itself, except
    where the environment says not to (``PYTHONDONTWRITEBYTECODE``, set in many container
    images): then every process would compile the kernels' 2,500 lines again (20-30 ms). The
    module's text never changes under its name, so its bytecode stays valid; the cache folder
    is the package's own, as numba's files beside it."""
    if cached is None or os.path.exists(cached):
        return
    try:
        py_compile.compile(str(path), cfile=cached, doraise=True)
    except (OSError, py_compile.PyCompileError):  # a read-only cache: compiled on import
        pass


def import_generated(path: Path, name: str, package: str) -> ModuleType:
    """Import the generated module at ``path`` as ``name`` (registered in ``sys.modules``,
    where its numba functions' callers find it), its relative imports resolved in
    ``package``; nothing is left registered if it fails."""
    spec = importlib.util.spec_from_file_location(name, path)
    if spec is None or spec.loader is None:
        raise RuntimeError(f"cannot import the generated module {name} from {path}")
    _write_bytecode(path, spec.cached)
    module = importlib.util.module_from_spec(spec)
    module.__package__ = package
    sys.modules[name] = module
    try:
        spec.loader.exec_module(module)
    except BaseException:
        sys.modules.pop(name, None)
        raise
    return module


def kernels(n: int, N: int, specialise: bool = True) -> ModuleType:
    """The kernel module for problems of ``n`` batteries and horizon ``N``: the specialised
    copy if ``(n, N)`` is in :data:`SPECIALISED_SIZES` and ``specialise``, else
    :mod:`~mpcrl_lite.mpc.backends.kernel_core`. Both have the same functions and constants."""
    key = (int(n), int(N))
    if not specialise or key not in SPECIALISED_SIZES:
        return _generic()
    with _lock:
        if key not in _loaded:
            _loaded[key] = _load(*key)
        return _loaded[key]
