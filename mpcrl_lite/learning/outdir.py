r"""Output directories: the check every command makes before any work, and one process
per directory.

:func:`check_output_dir` judges a ``--out`` before anything runs (an empty path, a file, a
directory that cannot be written are refused in one line); :func:`lock_output_dir` holds an
OS file lock on ``D/.mpcrl_lite.lock`` (``fcntl.flock``) while a command (``learn``,
``study``, ``sweep``, ``report``, ``tune``) works in ``D``. The file names the holder's PID and
command; a second process on the same directory is refused in one line
(:class:`RunDirLocked`) naming that PID. The lock dies with its process, so the lock file of a
killed process is simply taken over, and the file is removed when the holder ends.

Every problem is a :class:`RunDirError` (a ``ValueError``) whose message is one line saying
what is wrong and how to recover.
"""

from __future__ import annotations

import os
import tempfile
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from .durable import reason

try:  # POSIX file locks; elsewhere a directory is not locked
    import fcntl
except ImportError:  # pragma: no cover (Windows)
    fcntl = None  # type: ignore[assignment]

__all__ = ["LOCK", "RunDirError", "RunDirLocked", "RunDirMissing", "check_output_dir",
           "lock_output_dir", "refuse_empty"]

#: The lock file of a directory in use (:func:`lock_output_dir`).
LOCK = ".mpcrl_lite.lock"


class RunDirError(ValueError):
    """A directory that cannot be used as asked (one-line message with the remedy)."""


class RunDirMissing(RunDirError, FileNotFoundError):
    """No run (or no History) where one was expected."""


class RunDirLocked(RunDirError):
    """The directory is in use by another process (:func:`lock_output_dir`)."""


def _existing_ancestor(path: Path) -> Path:
    while not path.exists() and path != path.parent:
        path = path.parent
    return path


def refuse_empty(path: str | os.PathLike, flag: str = "--out") -> str:
    """``path`` as a string, or a :class:`RunDirError` if it is empty (``Path('')`` is the
    current directory: an empty ``--out`` must not quietly write there)."""
    text = os.fspath(path)
    if text == "":
        raise RunDirError(f"{flag} '': expected a directory path (an empty path would "
                          "write into the current directory; pass '.' to mean it)")
    return text


def check_output_dir(path: str | os.PathLike, flag: str = "--out", create: bool = True) -> Path:
    """An output directory that exists (created if needed) and can be written, or a
    :class:`RunDirError` naming the problem; called before any work starts.

    With ``create=False`` nothing is created: a directory that does not exist yet is judged by
    its nearest existing parent (it must be a directory this process can write to). The one
    check of every command's output directory (runs, sweeps, studies, reports).
    """
    text = refuse_empty(path, flag)
    directory = Path(text)
    if not create:
        try:
            if directory.exists() and not directory.is_dir():
                raise RunDirError(f"{flag} {text}: is an existing file; expected a directory")
            parent = _existing_ancestor(directory)
            if not parent.is_dir():
                raise RunDirError(f"{flag} {text}: {parent} is an existing file, so it cannot be "
                                  "created; expected a directory")
            if not os.access(parent, os.W_OK | os.X_OK):
                raise RunDirError(f"{flag} {text}: cannot write there ({parent} is not "
                                  "writable); expected a writable directory")
        except OSError as err:
            raise RunDirError(f"{flag} {text}: cannot be checked ({reason(err)})") from None
        return directory
    created = False
    try:
        if directory.exists() and not directory.is_dir():
            raise RunDirError(f"{flag} {text}: is an existing file; expected a directory")
        created = not directory.exists()
        directory.mkdir(parents=True, exist_ok=True)
        fd, probe = tempfile.mkstemp(prefix=".probe-", dir=directory)
        os.close(fd)
        os.unlink(probe)
    except OSError as err:
        if created:
            try:
                directory.rmdir()
            except OSError:
                pass
        raise RunDirError(
            f"{flag} {text}: cannot write there ({reason(err)}); expected a writable directory"
        ) from None
    return directory


# -- one process per directory ----------------------------------------------------------------
#: Locks this process holds: real path -> [file descriptor, depth] (a lock is re-entrant in
#: its process: a command and the library function it calls may both take it).
_held: dict[str, list[int]] = {}


def _holder(path: Path) -> str:
    """'PID 1234, learn' as the lock file says (read a few times: the holder writes it just
    after taking the lock)."""
    for _ in range(20):
        try:
            text = path.read_text().split()
        except OSError:
            text = []
        if text:
            return f"PID {text[0]}" + (f", {' '.join(text[1:])}" if len(text) > 1 else "")
        time.sleep(0.01)
    return "PID unknown"


@contextmanager
def lock_output_dir(path: str | os.PathLike, command: str, flag: str = "--out") -> Iterator[Path]:
    """Hold the lock of the directory ``path`` (which must exist) for the block: one process
    at a time writes a directory.

    The lock is ``fcntl.flock`` on ``path/.mpcrl_lite.lock`` (:data:`LOCK`), which holds the
    PID and ``command``; the OS releases it when the process ends, however it ends, so the
    file of a killed process is taken over. It is re-entrant within a process (a command and
    the library function it calls may both take it) and released, its file removed, when the
    outermost block ends. Where ``fcntl`` does not exist (Windows) nothing is locked.

    Raises
    ------
    RunDirLocked
        (a :class:`RunDirError`) at once, one line naming the holder's PID, if another
        process holds the lock.
    """
    directory = Path(path)
    key = os.path.realpath(directory)
    if fcntl is None or key in _held:
        if key in _held:
            _held[key][1] += 1
        try:
            yield directory
        finally:
            if key in _held:
                _held[key][1] -= 1
        return
    lock = directory / LOCK
    while True:
        try:
            fd = os.open(lock, os.O_RDWR | os.O_CREAT, 0o644)
        except OSError as err:
            raise RunDirError(f"{flag} {os.fspath(path)}: cannot create its lock file "
                              f"({reason(err)}); expected a writable directory") from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            os.close(fd)
            raise RunDirLocked(
                f"{flag} {os.fspath(path)} is in use by another process ({_holder(lock)}); "
                f"wait for it to end or choose another {flag}") from None
        try:  # the file may have been removed by a holder that ended meanwhile: lock anew
            same = os.fstat(fd).st_ino == os.stat(lock).st_ino
        except OSError:
            same = False
        if same:
            break
        os.close(fd)
    try:
        os.ftruncate(fd, 0)
        os.write(fd, f"{os.getpid()} {command}\n".encode())
    except OSError:  # a full disk: the lock holds without its note
        pass
    _held[key] = [fd, 1]
    try:
        yield directory
    finally:
        _held[key][1] -= 1
        if _held[key][1] == 0:
            del _held[key]
            try:
                lock.unlink()  # while locked: a waiting process then locks a new file
            except OSError:
                pass
            os.close(fd)
