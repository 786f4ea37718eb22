r"""Durable writes: a kill or a full disk at any moment leaves a file's old content or its new.

* :func:`write_atomic` / :func:`write_json` (the one JSON writer of the package) replace a
  file atomically: a temporary file, fsync, rename, fsync of the directory;
  :func:`atomic_output` gives writers that want a path (``savefig``, papermill) the same.
* The low-level steps (:func:`write_file`, :func:`append_file`, :func:`replace`,
  :func:`unlink`, :func:`fsync_dir`) are the only writes of a run directory
  (:mod:`mpcrl_lite.learning.rundir` builds its commits from them); each one is counted.
* :func:`in_background` runs a commit in a thread while the next month computes;
  :func:`settle` waits for the one under way in a directory (every reader and writer calls
  it first, so a commit is never seen half-done).

Test hooks
----------
``MPCRL_LITE_KILL_AFTER_WRITE=i`` makes the process kill itself (SIGKILL) right after its
``i``-th write (a file written, renamed, linked or removed, counted from 1 over the whole
process); ``MPCRL_LITE_KILL_MID_WRITE=i`` kills it half-way through the ``i``-th write if that
write is a file's content. They exist to test that every interruption leaves a directory
that resumes or is refused (``tests/learning/test_durability.py``).
"""

from __future__ import annotations

import os
import signal
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from .._util.jsonio import dumps

__all__ = ["KILL_AFTER_WRITE_ENV", "KILL_MID_WRITE_ENV", "PendingCommit", "RunWriteError",
           "append_file", "atomic_output", "fsync_dir", "in_background", "reason", "replace",
           "settle", "unlink", "write_atomic", "write_file", "write_json", "wrote"]

KILL_AFTER_WRITE_ENV = "MPCRL_LITE_KILL_AFTER_WRITE"
KILL_MID_WRITE_ENV = "MPCRL_LITE_KILL_MID_WRITE"


class RunWriteError(OSError):
    """Writing failed; what the write would have replaced is intact."""


# -- low-level writes (every one counted for the test hooks) ----------------------------------
_writes = 0


def _kill_self() -> None:
    os.kill(os.getpid(), getattr(signal, "SIGKILL", signal.SIGTERM))
    os._exit(137)  # pragma: no cover (where SIGKILL is not delivered at once)


def _hook(variable: str) -> int | None:
    text = os.environ.get(variable)
    return int(text) if text else None


def wrote() -> None:
    global _writes
    _writes += 1
    if _hook(KILL_AFTER_WRITE_ENV) == _writes:
        _kill_self()


def write_file(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path`` (created or truncated) and fsync it."""
    mid = _hook(KILL_MID_WRITE_ENV) == _writes + 1
    with open(path, "wb") as f:
        if mid:
            f.write(data[: len(data) // 2])
            f.flush()
            os.fsync(f.fileno())
            _kill_self()
        f.write(data)
        f.flush()
        os.fsync(f.fileno())
    wrote()


def append_file(path: Path, offset: int, data: bytes, sync: bool = True) -> None:
    """Write ``data`` to ``path`` at ``offset`` (the file created if needed and cut to
    ``offset`` first, so that a tail left by an interrupted writer goes) and fsync it
    (``sync=False``: left to the operating system's write-back; the bytes survive the
    process being killed, not a power cut before they are written)."""
    mid = _hook(KILL_MID_WRITE_ENV) == _writes + 1
    fd = os.open(path, os.O_WRONLY | os.O_CREAT, 0o666)
    try:
        os.ftruncate(fd, offset)
        view = memoryview(data)
        if mid:
            view = view[: len(data) // 2]
        while view:
            done = os.pwrite(fd, view, offset)
            offset += done
            view = view[done:]
        if sync or mid:
            os.fsync(fd)
        if mid:
            _kill_self()
    finally:
        os.close(fd)
    wrote()


def replace(src: Path, dst: Path) -> None:
    os.replace(src, dst)
    wrote()


def unlink(path: Path) -> None:
    try:
        path.unlink()
    except FileNotFoundError:
        return
    wrote()


def fsync_dir(directory: Path) -> None:
    if os.name == "nt":  # directories cannot be opened there; renames are durable anyway
        return
    fd = os.open(directory, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def write_atomic(path: str | os.PathLike, data: bytes) -> None:
    """Replace ``path`` by ``data`` atomically (temporary file, fsync, rename, fsync of the
    directory): a reader sees the old or the new file, never a part of one."""
    path = Path(path)
    settle(path.parent)
    tmp = path.with_name(f".{path.name}.tmp")
    try:
        write_file(tmp, data)
        replace(tmp, path)
        fsync_dir(path.parent)
    except OSError as err:
        tmp.unlink(missing_ok=True)
        raise RunWriteError(err.errno, f"could not write {path}: {reason(err)}") from err


def write_json(path: str | os.PathLike, data: Any) -> None:
    """Write ``data`` as strict JSON (:func:`mpcrl_lite._util.jsonio.dumps`: NaN as ``null``)
    to ``path`` atomically (:func:`write_atomic`): the one JSON writer of the package."""
    write_atomic(path, dumps(data))


@contextmanager
def atomic_output(path: str | os.PathLike,
                  failed: str | os.PathLike | None = None) -> Iterator[Path]:
    """A temporary path to write ``path``'s new content to, for writers that want a path
    (``savefig``, papermill): on leaving the block it is fsynced and renamed onto ``path``
    (then the directory is fsynced), so ``path`` is the old file or the whole new one, never a
    part of one.

    The temporary file, ``.<stem>.partial<suffix>`` in the same directory, keeps the suffix
    (writers choose the format by it). If the block raises, it is removed (or, with
    ``failed``, renamed to that path, e.g. a notebook executed up to its failing cell, kept
    for inspection), ``path`` is left as it was and the error goes on.

    Examples
    --------
    >>> with atomic_output(directory / "fig2_performance.png") as tmp:  # doctest: +SKIP
    ...     fig.savefig(tmp)

    Raises
    ------
    RunWriteError
        (an ``OSError``) if the new file cannot be fsynced or renamed into place.
    """
    path = Path(path)
    tmp = path.with_name(f".{path.stem}.partial{path.suffix}")
    try:
        yield tmp
    except BaseException:
        if failed is not None and tmp.exists():
            os.replace(tmp, failed)
        tmp.unlink(missing_ok=True)
        raise
    try:
        with open(tmp, "rb") as f:
            os.fsync(f.fileno())
        replace(tmp, path)
        fsync_dir(path.parent)
    except OSError as err:
        tmp.unlink(missing_ok=True)
        raise RunWriteError(err.errno, f"could not write {path}: {reason(err)}") from err


def reason(err: OSError) -> str:
    return err.strerror or str(err)


# -- work in the background ----------------------------------------------------------------
class PendingCommit:
    """A commit of a directory under way in a thread (:func:`in_background`; the run
    directory's :func:`~mpcrl_lite.learning.rundir.commit_soon`)."""

    def __init__(self, directory: Path, run: Any) -> None:
        self.directory = directory
        self._manifest: dict[str, Any] | None = None
        self._error: BaseException | None = None

        def work() -> None:
            try:
                self._manifest = run()
            except BaseException as err:  # noqa: BLE001 (raised by result())
                self._error = err

        self._thread = threading.Thread(target=work, name=f"mpcrl_lite commit {directory.name}")
        self._thread.start()

    def done(self) -> bool:
        """Whether the commit has finished (committed or failed)."""
        return not self._thread.is_alive()

    def wait(self) -> None:
        """Wait until the commit has finished."""
        self._thread.join()

    def result(self) -> dict[str, Any]:
        """The manifest written, once the commit has finished; its error if it failed."""
        self.wait()
        if self._error is not None:
            raise self._error
        assert self._manifest is not None
        return self._manifest


#: The commit under way in each directory (a key only while its thread runs or until waited).
_pending: dict[Path, PendingCommit] = {}
_pending_lock = threading.Lock()


def settle(directory: str | os.PathLike) -> None:
    """Wait for a commit under way in ``directory`` (its error stays with its owner)."""
    key = Path(os.path.abspath(directory))
    with _pending_lock:
        pending = _pending.get(key)
    if pending is not None and pending._thread is not threading.current_thread():
        pending.wait()
        with _pending_lock:
            if _pending.get(key) is pending:
                del _pending[key]


def in_background(directory: str | os.PathLike, work: Callable[[], dict[str, Any]]
                  ) -> PendingCommit:
    """Run ``work`` (a commit of ``directory``) in a thread of its own, after any commit
    already under way there: returns at once with its :class:`PendingCommit`. Every writer
    and reader of the directory (:func:`settle`) waits for it first."""
    directory = Path(directory)
    settle(directory)
    key = Path(os.path.abspath(directory))
    with _pending_lock:
        pending = _pending[key] = PendingCommit(directory, work)
    return pending
