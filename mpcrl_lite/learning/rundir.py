r"""The run directory: the files of a learning run, one atomic commit point per month.

A run directory ``D`` holds, once a month has been committed::

    D/manifest.json     the commit point (see below)
    D/history.json      the History's configurations and per-month series (readable JSON)
    D/history.npz       the History's arrays (first and last month), allow_pickle=False
    D/checkpoint.json   what a learner needs to continue (theta, optimizer and RNG state)
    D/summary.json      written by the ``learn`` command at the end (derived, not committed)

:meth:`History.save <mpcrl_lite.learning.history.History.save>` writes the same format without
``checkpoint.json`` (kind ``"history"``).

How a month is committed (:func:`commit`)
-----------------------------------------
1. every file of the month is written under a **new** name in ``D/.run/`` and fsynced;
   nothing the last commit refers to is touched;
2. ``D/manifest.json`` is replaced atomically (written as ``manifest.json.tmp``, fsynced,
   renamed, directory fsynced). **This rename is the commit.** The manifest carries

   =================  ============================================================
   ``format``         ``"mpcrl_lite.Run/1"``
   ``kind``           ``"centralized"``, ``"decentralized"`` (a learner's run) or
                      ``"history"`` (a History on its own)
   ``months_done``    months recorded by the committed files
   ``config_sha256``  sha256 of the configurations (:func:`config_sha256`; the
                      learning config without ``months``, which a resume may extend)
   ``files``          per user-visible name (``history.json`` ...): its ``sha256``,
                      ``size`` in bytes and ``staged`` (its name under ``.run/``)
   =================  ============================================================

3. the user-visible names are then pointed at the new files (a hard link, or a copy where
   the file system has none, renamed into place) and the staged names removed.

A kill or a full disk before step 2 leaves the previous commit untouched (the staged files
are unreferenced and removed by the next writer); after step 2 the new month is committed,
and a reader finds each file under its visible name or, if step 3 did not finish, under its
staged name: :func:`read` accepts a file only if its sha256 matches the manifest.

Directories written before the manifest existed (``history.json``, ``history.npz`` and
``checkpoint.json`` only) are read as **legacy** runs: there is no checksum, so the readers
(:class:`~mpcrl_lite.learning.history.History`, :class:`~mpcrl_lite.learning.learner.Learner`) check that the
files agree with each other and refuse them otherwise.

Every problem with a directory is a :class:`RunDirError` (a ``ValueError``) whose message is
one line saying what is wrong and how to recover; a failed write is a :class:`RunWriteError`
(an ``OSError``) after which the last commit is intact.

Test hooks
----------
``MPCRL_LITE_KILL_AFTER_WRITE=i`` makes the process kill itself (SIGKILL) right after its
``i``-th write to a run directory (a file written, renamed, linked or removed, counted from
1 over the whole process); ``MPCRL_LITE_KILL_MID_WRITE=i`` kills it half-way through the
``i``-th write if that write is a file's content. They exist to test that every interruption
leaves a directory that resumes or is refused (``tests/learning/test_durability.py``).
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import signal
import tempfile
from collections.abc import Iterable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from .._util.jsonio import dumps

__all__ = ["CHECKPOINT", "FORMAT", "HISTORY_JSON", "HISTORY_NPZ", "KINDS", "MANIFEST", "RECOVER", "STAGING", "SUMMARY", "Contents", "Run", "RunDirError", "RunDirMissing", "RunWriteError", "atomic_output", "check_output_dir", "clear", "commit", "config_sha256", "inspect", "read", "write_atomic", "write_json"]

FORMAT = "mpcrl_lite.Run/1"
MANIFEST = "manifest.json"
HISTORY_JSON = "history.json"
HISTORY_NPZ = "history.npz"
CHECKPOINT = "checkpoint.json"
SUMMARY = "summary.json"
#: Where a commit's new files are written before the manifest names them.
STAGING = ".run"
#: What a run directory holds: a learner's run or a History on its own.
KINDS = ("history", "centralized", "decentralized", "q-learning")
#: The files a run directory may hold under their visible names.
RUN_FILES = (HISTORY_JSON, HISTORY_NPZ, CHECKPOINT)
#: How to recover from a directory that does not verify (appended to the error messages).
RECOVER = "restore the directory from a backup, or start over in it with --force (force=True)"

KILL_AFTER_WRITE_ENV = "MPCRL_LITE_KILL_AFTER_WRITE"
KILL_MID_WRITE_ENV = "MPCRL_LITE_KILL_MID_WRITE"

_STAGED = re.compile(r"^\d{6,}-[0-9a-f]{8}-[A-Za-z0-9_.]+$")
_HEX64 = re.compile(r"^[0-9a-f]{64}$")


class RunDirError(ValueError):
    """A run directory that cannot be used as asked (one-line message with the remedy)."""


class RunDirMissing(RunDirError, FileNotFoundError):
    """No run (or no History) where one was expected."""


class RunWriteError(OSError):
    """Writing a commit failed; the directory still holds the previous commit."""


#: Configuration fields added after run directories existed, with the value the older runs
#: had: left out of :func:`config_sha256` at that value, so older manifests still match.
LEGACY_VALUES: dict[str, dict[str, Any]] = {"learning": {"eval_draws": 1},
                                          "mpc": {"forecast": "paper"}}
_NO = object()


def config_sha256(configs: Mapping[str, Mapping[str, Any]]) -> str:
    """sha256 of configurations given as plain dicts (``{"system": {...}, ...}``), over
    their canonical JSON (sorted keys, no spaces); a field at its :data:`LEGACY_VALUES`
    value is left out."""
    configs = {key: {k: v for k, v in cfg.items() if LEGACY_VALUES.get(key, {}).get(k, _NO) != v}
               if isinstance(cfg, Mapping) else cfg for key, cfg in configs.items()}
    text = dumps(configs, indent=None, sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text).hexdigest()


def _sha256(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


# -- low-level writes (every one counted for the test hooks) ----------------------------------
_writes = 0


def _kill_self() -> None:
    os.kill(os.getpid(), getattr(signal, "SIGKILL", signal.SIGTERM))
    os._exit(137)  # pragma: no cover (where SIGKILL is not delivered at once)


def _hook(variable: str) -> int | None:
    text = os.environ.get(variable)
    return int(text) if text else None


def _wrote() -> None:
    global _writes
    _writes += 1
    if _hook(KILL_AFTER_WRITE_ENV) == _writes:
        _kill_self()


def _write_file(path: Path, data: bytes) -> None:
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
    _wrote()


def _replace(src: Path, dst: Path) -> None:
    os.replace(src, dst)
    _wrote()


def _unlink(path: Path) -> None:
    try:
        path.unlink()
    except FileNotFoundError:
        return
    _wrote()


def _fsync_dir(directory: Path) -> None:
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
    tmp = path.with_name(f".{path.name}.tmp")
    try:
        _write_file(tmp, data)
        _replace(tmp, path)
        _fsync_dir(path.parent)
    except OSError as err:
        tmp.unlink(missing_ok=True)
        raise RunWriteError(err.errno, f"could not write {path}: {_reason(err)}") from err


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
        _replace(tmp, path)
        _fsync_dir(path.parent)
    except OSError as err:
        tmp.unlink(missing_ok=True)
        raise RunWriteError(err.errno, f"could not write {path}: {_reason(err)}") from err


def _reason(err: OSError) -> str:
    return err.strerror or str(err)


# -- what a directory holds ---------------------------------------------------------------
@dataclass
class Contents:
    """What :func:`inspect` found in a directory."""

    directory: Path
    manifest: bool = False
    run_files: list[str] = field(default_factory=list)
    others: list[str] = field(default_factory=list)

    @property
    def holds_run(self) -> bool:
        """A manifest or any of history.json, history.npz, checkpoint.json."""
        return self.manifest or bool(self.run_files)

    @property
    def names(self) -> list[str]:
        """Every file of a run found (manifest first)."""
        return ([MANIFEST] if self.manifest else []) + self.run_files + self.others


def inspect(directory: str | os.PathLike, others: Iterable[str] = ()) -> Contents:
    """Which run files (and which of ``others``, e.g. ``summary.json``) ``directory`` holds."""
    directory = Path(directory)
    found = Contents(directory)
    if not directory.is_dir():
        return found
    found.manifest = (directory / MANIFEST).exists()
    found.run_files = [n for n in RUN_FILES if (directory / n).exists()]
    found.others = [n for n in others if (directory / n).exists()]
    return found


def _existing_ancestor(path: Path) -> Path:
    while not path.exists() and path != path.parent:
        path = path.parent
    return path


def check_output_dir(path: str | os.PathLike, flag: str = "--out", create: bool = True) -> Path:
    """An output directory that exists (created if needed) and can be written, or a
    :class:`RunDirError` naming the problem; called before any work starts.

    With ``create=False`` nothing is created: a directory that does not exist yet is judged by
    its nearest existing parent (it must be a directory this process can write to). The one
    check of every command's output directory (runs, sweeps, studies, reports).
    """
    text = os.fspath(path)
    if text == "":
        raise RunDirError(f"{flag} '': expected a directory path (an empty path would "
                          "write into the current directory; pass '.' to mean it)")
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
            raise RunDirError(f"{flag} {text}: cannot be checked ({_reason(err)})") from None
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
            f"{flag} {text}: cannot write there ({_reason(err)}); expected a writable directory"
        ) from None
    return directory


# -- commit -------------------------------------------------------------------------------
def commit(
    directory: str | os.PathLike,
    files: Mapping[str, bytes],
    *,
    kind: str,
    months_done: int,
    configs_hash: str,
) -> dict[str, Any]:
    """Commit ``files`` (visible name -> content) as the directory's new state.

    See the module docstring for the protocol. Returns the manifest written. Raises
    :class:`RunWriteError` if a write before the commit fails (the previous commit is
    intact and the new files are removed); a failure after the commit (pointing the visible
    names at the new files) is retried by the next :func:`commit` or :func:`read` with
    ``repair=True``.
    """
    if kind not in KINDS:
        raise ValueError(f"kind={kind!r}: expected one of {KINDS}")
    if isinstance(months_done, bool) or not isinstance(months_done, int) or months_done < 0:
        raise ValueError(f"months_done={months_done!r}: expected an integer >= 0")
    unknown = set(files) - set(RUN_FILES)
    if unknown:
        raise ValueError(f"files {sorted(unknown)}: expected names among {RUN_FILES}")
    directory = Path(directory)
    staging = directory / STAGING
    token = os.urandom(4).hex()
    entries: dict[str, dict[str, Any]] = {}
    written: list[Path] = []
    tmp = directory / (MANIFEST + ".tmp")
    try:
        directory.mkdir(parents=True, exist_ok=True)
        if not staging.is_dir():
            staging.mkdir()
            _wrote()
        for name, data in files.items():
            staged = f"{STAGING}/{months_done:06d}-{token}-{name}"
            written.append(directory / staged)
            _write_file(directory / staged, data)
            entries[name] = {"sha256": _sha256(data), "size": len(data), "staged": staged}
        _fsync_dir(staging)
        manifest = {
            "format": FORMAT,
            "kind": kind,
            "months_done": months_done,
            "config_sha256": configs_hash,
            "files": entries,
        }
        _write_file(tmp, dumps(manifest))
        _replace(tmp, directory / MANIFEST)  # the commit
    except OSError as err:
        for path in [*written, tmp]:
            try:
                path.unlink(missing_ok=True)
            except OSError:
                pass
        raise RunWriteError(
            err.errno,
            f"could not write month {months_done} to {directory}: {_reason(err)}; the "
            "previous commit is kept (free the space or fix the permissions, then resume)",
        ) from err
    # committed: from here on a failure only delays pointing the visible names at the files
    _publish(directory, manifest, dict(files))
    return manifest


def _publish(directory: Path, manifest: Mapping[str, Any], data: Mapping[str, bytes]) -> None:
    """Make the commit durable (fsync of the directory), point the visible names at the
    committed files, then remove the staged names and any leftovers of interrupted writers.
    A failure here is left for the next writer (the commit is done: readers find the staged
    files)."""
    try:
        _fsync_dir(directory)
        for name, entry in manifest["files"].items():
            target = directory / name
            if _file_sha256(target) == entry["sha256"]:
                continue
            staged = directory / entry["staged"]
            if not staged.exists():
                return  # nothing to publish from; read() reports the file as damaged
            tmp = directory / f".{name}.tmp"
            tmp.unlink(missing_ok=True)
            try:
                os.link(staged, tmp)
                _wrote()
            except OSError:  # no hard links on this file system: a copy
                _write_file(tmp, data[name] if name in data else staged.read_bytes())
            _replace(tmp, target)
        _fsync_dir(directory)
        _remove_leftovers(directory)
    except OSError:
        return


def _file_sha256(path: Path) -> str | None:
    try:
        return _sha256(path.read_bytes())
    except OSError:
        return None


def _remove_leftovers(directory: Path) -> None:
    """Remove the staged files and the temporary files of interrupted writers (called once
    every visible name holds the committed content)."""
    staging = directory / STAGING
    if staging.is_dir():
        for path in sorted(staging.iterdir()):
            if _STAGED.match(path.name):
                _unlink(path)
        try:
            staging.rmdir()
            _wrote()
        except OSError:
            pass
    for name in (MANIFEST + ".tmp", *(f".{n}.tmp" for n in RUN_FILES)):
        _unlink(directory / name)


def clear(directory: str | os.PathLike, others: Iterable[str] = ()) -> None:
    """Remove a run from ``directory`` (and the files ``others``): the manifest first, so
    that an interruption never leaves something that reads as a run of mixed origins."""
    directory = Path(directory)
    _unlink(directory / MANIFEST)
    _fsync_dir(directory)
    for name in (*RUN_FILES, *others):
        _unlink(directory / name)
    _remove_leftovers(directory)


# -- read ---------------------------------------------------------------------------------
@dataclass
class Run:
    """The verified files of a run directory (as read by :func:`read`).

    ``manifest`` is None for a legacy directory (written before the manifest existed); its
    files are then unverified and their readers check them against each other.
    """

    directory: Path
    manifest: dict[str, Any] | None
    files: dict[str, bytes]

    @property
    def legacy(self) -> bool:
        """True for a directory without a manifest."""
        return self.manifest is None

    @property
    def kind(self) -> str | None:
        """The manifest's kind (None for a legacy directory)."""
        return None if self.manifest is None else self.manifest["kind"]

    @property
    def months_done(self) -> int | None:
        """The manifest's months_done (None for a legacy directory)."""
        return None if self.manifest is None else self.manifest["months_done"]


def _load_manifest(directory: Path) -> dict[str, Any]:
    path = directory / MANIFEST
    where = f"{path}"
    try:
        manifest = json.loads(path.read_bytes())
    except (OSError, ValueError) as err:
        raise RunDirError(f"{where} cannot be read ({err}); {RECOVER}") from None
    if not isinstance(manifest, dict):
        raise RunDirError(f"{where} holds a {type(manifest).__name__}, expected an object; {RECOVER}")
    if manifest.get("format") != FORMAT:
        raise RunDirError(
            f"{where}: format {manifest.get('format')!r}, expected {FORMAT!r} (written by "
            f"another program or version); {RECOVER}"
        )
    kind, months, files = manifest.get("kind"), manifest.get("months_done"), manifest.get("files")
    if kind not in KINDS:
        raise RunDirError(f"{where}: kind {kind!r}, expected one of {KINDS}; {RECOVER}")
    if isinstance(months, bool) or not isinstance(months, int) or months < 0:
        raise RunDirError(f"{where}: months_done {months!r}, expected an integer >= 0; {RECOVER}")
    if not isinstance(manifest.get("config_sha256"), str):
        raise RunDirError(f"{where}: config_sha256 missing; {RECOVER}")
    if not isinstance(files, dict) or not files:
        raise RunDirError(f"{where}: 'files' missing or empty; {RECOVER}")
    for name, entry in files.items():
        ok = (
            name in RUN_FILES and isinstance(entry, dict)
            and isinstance(entry.get("sha256"), str) and _HEX64.match(entry["sha256"])
            and isinstance(entry.get("size"), int)
            and isinstance(entry.get("staged"), str)
            and entry["staged"].startswith(STAGING + "/")
            and _STAGED.match(entry["staged"][len(STAGING) + 1 :])
        )
        if not ok:
            raise RunDirError(f"{where}: the entry of {name!r} is malformed; {RECOVER}")
    return manifest


def read(
    directory: str | os.PathLike,
    names: Sequence[str],
    *,
    optional: Sequence[str] = (),
    repair: bool = False,
) -> Run:
    """Read and verify the files ``names`` of a run directory.

    With a manifest, every file named must be listed and match its sha256 (under its
    visible or its staged name). Without one (a legacy directory) the files are read as
    they are; ``optional`` ones may be absent. ``repair=True`` (for a writer about to
    continue the run) also finishes an interrupted commit: visible names pointed at the
    committed files, leftovers removed.

    Raises
    ------
    RunDirMissing
        No manifest and no ``names[0]`` (nothing of a run).
    RunDirError
        Anything that does not verify; the message says which file and what to do.
    """
    directory = Path(directory)
    if not directory.is_dir():
        raise RunDirMissing(f"{directory / names[0]} not found: {directory} is not a directory")
    if not (directory / MANIFEST).exists():
        return _read_legacy(directory, names, optional)
    manifest = _load_manifest(directory)
    files: dict[str, bytes] = {}
    for name in names:
        entry = manifest["files"].get(name)
        if entry is None:
            if name in optional:
                continue
            raise RunDirError(
                f"{directory / MANIFEST} lists no {name} (a {manifest['kind']} directory); {RECOVER}"
            )
        for candidate in (directory / name, directory / entry["staged"]):
            try:
                data = candidate.read_bytes()
            except OSError:
                continue
            if _sha256(data) == entry["sha256"]:
                files[name] = data
                break
        else:
            state = "is missing" if not (directory / name).exists() else "does not match its sha256"
            raise RunDirError(
                f"{directory / name} {state} in {MANIFEST} (damaged or changed after the run "
                f"wrote it); {RECOVER}"
            )
    if repair:
        _publish(directory, manifest, {**files})
    return Run(directory, manifest, files)


def _read_legacy(directory: Path, names: Sequence[str], optional: Sequence[str]) -> Run:
    files: dict[str, bytes] = {}
    for name in names:
        path = directory / name
        try:
            files[name] = path.read_bytes()
        except FileNotFoundError:
            if name in optional:
                continue
            if name == names[0]:
                raise RunDirMissing(
                    f"{path} not found: expected a directory written by a learning run or "
                    "History.save"
                ) from None
            raise RunDirError(
                f"{path} is missing next to {directory / names[0]} (an incomplete or damaged "
                f"run); {RECOVER}"
            ) from None
        except OSError as err:
            raise RunDirError(f"{path} cannot be read ({_reason(err)}); {RECOVER}") from None
    return Run(directory, None, files)
