r"""Durable writes: a kill or a full disk at any moment leaves a file's old content or its new.

* :func:`write_atomic` / :func:`write_json` (the one JSON writer of the package) replace a
  file atomically: a temporary file, fsync, rename, fsync of the directory;
  :func:`atomic_output` gives writers that want a path (``savefig``, papermill) the same.
* The low-level steps (:func:`write_file`, :func:`append_file`, :func:`replace`,
  :func:`unlink`, :func:`fsync_dir`) are the only writes of a run directory
  (:mod:`mpcrl_lite.learning.rundir` builds its commits from them); each one is counted.
* :func:`in_background` runs a commit (or a month appended to a journal) on the process's
  writer thread while the next month computes; :func:`settle` waits for the one under way
  in a directory (every reader and writer calls it first, so a commit is never seen
  half-done).

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
from collections.abc import Callable, Iterator, Sequence
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

#: the buffers one ``os.pwritev`` call takes (that call: Linux, the BSDs, macOS 11+)
_IOV_MAX = 1024


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


def append_file(path: Path, offset: int, data: bytes | Sequence[Any], sync: bool = True,
                trim: bool = True) -> None:
    """Write ``data`` to ``path`` at ``offset`` (the file created if needed and cut to
    ``offset`` first, so that a tail left by an interrupted writer goes) and fsync it
    (``sync=False``: left to the operating system's write-back; the bytes survive the
    process being killed, not a power cut before they are written).

    ``data`` is bytes or a sequence of buffers written one after the other (with one
    ``pwritev`` where the system has it, without joining them first). ``trim=False`` skips
    the cut, for a caller that knows the file ends at ``offset`` (its own last write there
    succeeded)."""
    parts = [memoryview(data).cast("B")] if isinstance(data, (bytes, bytearray, memoryview)) \
        else [memoryview(part).cast("B") for part in data]
    mid = _hook(KILL_MID_WRITE_ENV) == _writes + 1
    if mid:
        whole = b"".join(parts)
        parts = [memoryview(whole)[: len(whole) // 2]]
    fd = os.open(path, os.O_WRONLY | os.O_CREAT, 0o666)
    try:
        if trim or mid:
            os.ftruncate(fd, offset)
        parts = [part for part in parts if part.nbytes]
        pwritev = getattr(os, "pwritev", None)
        while parts:
            if pwritev is not None:
                done = pwritev(fd, parts[:_IOV_MAX], offset)
            else:  # pragma: no cover (systems without pwritev)
                done = os.pwrite(fd, parts[0], offset)
            offset += done
            while parts and done >= parts[0].nbytes:  # drop what was written
                done -= parts[0].nbytes
                parts.pop(0)
            if done:
                parts[0] = parts[0][done:]
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
class _Writer:
    """The process's one thread for writes in the background: it runs the work handed to
    it in turn, and ends with the interpreter once it has done what it was given
    (``concurrent.futures``' exit hook). Started at the first such write; a forked child,
    which has none of its parent's threads, starts its own."""

    def __init__(self) -> None:
        from concurrent.futures import ThreadPoolExecutor

        self.pid = os.getpid()
        self.executor = ThreadPoolExecutor(1, thread_name_prefix="mpcrl_lite writer")


_writer: _Writer | None = None
_writer_lock = threading.Lock()
#: set on the writer's thread while it runs a piece of work (:func:`settle` must not wait
#: there for the work it is doing)
_on_writer = threading.local()


def _submit(work: Callable[[], Any]) -> Any:
    """``work`` on the writer's thread, after the work handed to it before; its Future."""
    global _writer
    with _writer_lock:
        if _writer is None or _writer.pid != os.getpid():
            _writer = _Writer()
        executor = _writer.executor

    def run() -> Any:
        _on_writer.active = True
        try:
            return work()
        finally:
            _on_writer.active = False

    return executor.submit(run)


class PendingCommit:
    """A write of a directory under way on the process's writer thread
    (:func:`in_background`; the run directory's
    :func:`~mpcrl_lite.learning.rundir.commit_soon` and
    :func:`~mpcrl_lite.learning.rundir.append_month_soon`)."""

    def __init__(self, directory: Path, run: Callable[[], Any]) -> None:
        self.directory = directory
        self._future = _submit(run)

    def done(self) -> bool:
        """Whether the write has finished (done or failed)."""
        return self._future.done()

    def wait(self) -> None:
        """Wait until the write has finished."""
        from concurrent.futures import wait

        wait([self._future])

    def result(self) -> Any:
        """What the write returned (a commit's manifest, an append's journal size), once
        it has finished; its error if it failed."""
        return self._future.result()


#: The write under way in each directory (a key only while it runs or until waited).
_pending: dict[Path, PendingCommit] = {}
_pending_lock = threading.Lock()


def settle(directory: str | os.PathLike) -> None:
    """Wait for a write under way in ``directory`` (its error stays with its owner)."""
    if not _pending:
        return
    key = Path(os.path.abspath(directory))
    with _pending_lock:
        pending = _pending.get(key)
    if pending is not None and not getattr(_on_writer, "active", False):
        pending.wait()
        with _pending_lock:
            if _pending.get(key) is pending:
                del _pending[key]


def in_background(directory: str | os.PathLike, work: Callable[[], Any]) -> PendingCommit:
    """Run ``work`` (a commit of ``directory``, or a month appended to its journal) on the
    process's writer thread, after any write already under way there: returns at once with
    its :class:`PendingCommit`. Every writer and reader of the directory (:func:`settle`)
    waits for it first."""
    directory = Path(directory)
    settle(directory)
    key = Path(os.path.abspath(directory))
    with _pending_lock:
        pending = _pending[key] = PendingCommit(directory, work)
    return pending
