r"""The run directory: the files of a learning run, one atomic commit point per month.

A run directory ``D`` holds, once a month has been committed::

    D/manifest.json     the commit point (see below)
    D/history.json      the History's configurations and per-month series (readable JSON)
    D/history.npz       the History's arrays (first and last month), allow_pickle=False
    D/checkpoint.json   what a learner needs to continue (theta, optimizer and RNG state)
    D/history.jsonl     while a run is going on: the months since history.json, one JSON
                        line per commit (the History's journal, see below)
    D/critic.npz        with ``LearningConfig.critic_months > 1`` only: the critic's samples
                        of the earlier months its next fit uses
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
   ``format``         ``"mpcrl_lite.Run/1"``, or ``"mpcrl_lite.Run/2"`` when a file is
                      appended (a journal, below)
   ``kind``           ``"centralized"``, ``"decentralized"`` (a learner's run) or
                      ``"history"`` (a History on its own)
   ``months_done``    months recorded by the committed files
   ``config_sha256``  sha256 of the configurations (:func:`config_sha256`; the
                      learning config without ``months``, which a resume may extend)
   ``files``          per user-visible name (``history.json`` ...): its ``sha256``,
                      ``size`` in bytes and ``staged`` (its name under ``.run/``); for
                      an appended file ``append: true`` instead of ``staged``
   =================  ============================================================

3. the user-visible names are then pointed at the new files (a hard link, or a copy where
   the file system has none, renamed into place) and the staged names removed.

A kill or a full disk before step 2 leaves the previous commit untouched (the staged files
are unreferenced and removed by the next writer); after step 2 the new month is committed,
and a reader finds each file under its visible name or, if step 3 did not finish, under its
staged name: :func:`read` accepts a file only if its sha256 matches the manifest.

Appended files: O(1) per month
------------------------------
Rewriting the whole History every month costs in proportion to the months so far. A commit
may instead **keep** entries of the previous manifest (a file written by an earlier commit,
e.g. ``history.json`` of the run's first month, stays as it is) and **append** to a journal
(:data:`JOURNAL`): the new bytes go after the journal's committed ``size`` (bytes beyond it,
left by an interrupted writer, are cut first) and are fsynced before the manifest is written;
the manifest's ``size`` and ``sha256`` then cover the journal's new length. The committed
prefix is never touched, so step 1's promise holds: a kill before the rename leaves the
previous commit readable, and :func:`read` gives the journal's first ``size`` bytes only if
their sha256 matches. A commit that lists no journal (a whole History again) removes a
journal left from before. The learners append every month but the first and the last of a
call (:meth:`~mpcrl_lite.learning.checkpoint.Checkpointing.save_checkpoint`), so a finished
run holds no journal and reads as format 1.

Commits in the background
-------------------------
The writes of a commit are mostly waits for the disk (fsync, rename): :func:`commit_soon`
runs :func:`commit` in a thread of its own, with contents the caller has built already, so
that the next month computes meanwhile. At most one commit per directory is under way; every
function of this module that reads or writes a directory first waits for it (so a reader in
the process never sees a commit half-done), and its error, if it failed, is raised by the
next :meth:`PendingCommit.result` (the learner's next checkpoint). Nothing changes on the
disk: the same writes in the same order, one commit after the other.

Directories written before the manifest existed (``history.json``, ``history.npz`` and
``checkpoint.json`` only) are read as **legacy** runs: there is no checksum, so the readers
(:class:`~mpcrl_lite.learning.history.History`, :class:`~mpcrl_lite.learning.learner.Learner`) check that the
files agree with each other and refuse them otherwise.

Every problem with a directory is a :class:`RunDirError` (a ``ValueError``) whose message is
one line saying what is wrong and how to recover; a failed write is a :class:`RunWriteError`
(an ``OSError``) after which the last commit is intact.

Where the pieces live
---------------------
The durable low-level writes, the atomic file writer and the background thread are
:mod:`mpcrl_lite.learning.durable` (with the kill hooks that test every interruption); the
check of an output directory and its lock (one process per directory) are
:mod:`mpcrl_lite.learning.outdir`. This module is the run directory's format on top of them.
"""

from __future__ import annotations

import errno
import hashlib
import json
import os
import re
from collections.abc import Collection, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from .._util.jsonio import dumps
from . import durable
from .durable import RunWriteError
from .outdir import RunDirError, RunDirMissing

__all__ = ["APPENDABLE", "CHECKPOINT", "CRITIC", "FORMAT", "FORMATS", "FORMAT_APPEND", "HISTORY_JSON",
           "HISTORY_NPZ", "JOURNAL", "KINDS", "MANIFEST", "RECOVER", "STAGING", "SUMMARY",
           "Contents", "Run", "clear", "commit", "commit_soon", "config_sha256", "inspect",
           "manifest_of", "read"]

FORMAT = "mpcrl_lite.Run/1"
#: The manifest's format when it lists an appended file (readers of format 1 refuse it).
FORMAT_APPEND = "mpcrl_lite.Run/2"
FORMATS = (FORMAT, FORMAT_APPEND)
MANIFEST = "manifest.json"
HISTORY_JSON = "history.json"
HISTORY_NPZ = "history.npz"
CHECKPOINT = "checkpoint.json"
#: The History's journal: the months since ``history.json``, appended (one line a commit).
JOURNAL = "history.jsonl"
#: The critic's samples of the months before the last one, for a critic fitted on several
#: months (``LearningConfig.critic_months > 1``; written anew with every commit).
CRITIC = "critic.npz"
#: The files a commit may append to instead of writing them anew.
APPENDABLE = (JOURNAL,)
SUMMARY = "summary.json"
#: Where a commit's new files are written before the manifest names them.
STAGING = ".run"
#: What a run directory holds: a learner's run or a History on its own.
KINDS = ("history", "centralized", "decentralized", "q-learning")
#: The files a run directory may hold under their visible names.
RUN_FILES = (HISTORY_JSON, HISTORY_NPZ, CHECKPOINT, JOURNAL, CRITIC)
#: How to recover from a directory that does not verify (appended to the error messages).
RECOVER = "restore the directory from a backup, or start over in it with --force (force=True)"

_STAGED = re.compile(r"^\d{6,}-[0-9a-f]{8}-[A-Za-z0-9_.]+$")
_HEX64 = re.compile(r"^[0-9a-f]{64}$")


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


#: The running sha256 of the appended files this process committed, by path: (size, sha256,
#: hash object), so that an append hashes its new bytes only.
_appended: dict[Path, tuple[int, str, Any]] = {}


def _append_hash(path: Path, entry: Mapping[str, Any] | None) -> Any:
    """A sha256 object over the committed prefix ``entry`` describes (a new one for a new
    file), from :data:`_appended` or, if this process did not commit it, from the file."""
    if entry is None:
        return hashlib.sha256()
    known = _appended.get(path)
    if known is not None and known[:2] == (entry["size"], entry["sha256"]):
        return known[2].copy()
    with open(path, "rb") as f:
        prefix = f.read(entry["size"])
    digest = hashlib.sha256(prefix)
    if len(prefix) != entry["size"] or digest.hexdigest() != entry["sha256"]:
        raise OSError(errno.EIO, f"{path.name} changed after its last commit")
    return digest


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
    durable.settle(directory)
    directory = Path(directory)
    found = Contents(directory)
    if not directory.is_dir():
        return found
    found.manifest = (directory / MANIFEST).exists()
    found.run_files = [n for n in RUN_FILES if (directory / n).exists()]
    found.others = [n for n in others if (directory / n).exists()]
    return found


# -- commits in the background -------------------------------------------------------------
def commit_soon(directory: str | os.PathLike, files: Mapping[str, bytes], **options: Any
                ) -> durable.PendingCommit:
    """:func:`commit` (same arguments) in a thread: returns at once with a
    :class:`~mpcrl_lite.learning.durable.PendingCommit` (see "Commits in the background" in the module docstring)."""
    directory = Path(directory)
    files = dict(files)
    return durable.in_background(directory, lambda: commit(directory, files, **options))


# -- commit -------------------------------------------------------------------------------
def commit(
    directory: str | os.PathLike,
    files: Mapping[str, bytes],
    *,
    kind: str,
    months_done: int,
    configs_hash: str,
    previous: Mapping[str, Any] | None = None,
    keep: Sequence[str] = (),
    append: Mapping[str, bytes] | None = None,
) -> dict[str, Any]:
    """Commit ``files`` (visible name -> content) as the directory's new state.

    See the module docstring for the protocol. Returns the manifest written. Raises
    :class:`RunWriteError` if a write before the commit fails (the previous commit is
    intact and the new files are removed); a failure after the commit (pointing the visible
    names at the new files) is retried by the next :func:`commit` or :func:`read` with
    ``repair=True``.

    ``previous`` is the manifest of the directory's last commit (as this function returned
    it); the names in ``keep`` keep their entries from it, unchanged, and ``append`` (name
    among :data:`APPENDABLE` -> bytes) adds bytes after an appended file's committed size
    (or starts the file when ``previous`` does not list it as appended).
    """
    durable.settle(directory)
    if kind not in KINDS:
        raise ValueError(f"kind={kind!r}: expected one of {KINDS}")
    if isinstance(months_done, bool) or not isinstance(months_done, int) or months_done < 0:
        raise ValueError(f"months_done={months_done!r}: expected an integer >= 0")
    append = dict(append or {})
    unknown = set(files) - set(RUN_FILES)
    if unknown:
        raise ValueError(f"files {sorted(unknown)}: expected names among {RUN_FILES}")
    if set(append) - set(APPENDABLE):
        raise ValueError(f"append {sorted(set(append) - set(APPENDABLE))}: expected names "
                         f"among {APPENDABLE}")
    old_files = previous["files"] if previous is not None else {}
    missing = [name for name in keep if name not in old_files]
    if missing or (set(keep) | set(append)) & set(files) or set(keep) & set(append):
        raise ValueError(f"keep={list(keep)}, append={sorted(append)}: expected names of the "
                         "previous commit, each in one of files, keep and append")
    directory = Path(directory)
    staging = directory / STAGING
    token = os.urandom(4).hex()
    entries: dict[str, dict[str, Any]] = {name: dict(old_files[name]) for name in keep}
    written: list[Path] = []
    hashes: dict[Path, tuple[int, str, Any]] = {}
    tmp = directory / (MANIFEST + ".tmp")
    try:
        directory.mkdir(parents=True, exist_ok=True)
        for name, data in append.items():
            path = directory / name
            entry = old_files.get(name)
            entry = entry if entry is not None and entry.get("append") else None
            digest = _append_hash(path, entry)
            size = entry["size"] if entry is not None else 0
            durable.append_file(path, size, data)
            if entry is None:
                durable.fsync_dir(directory)  # the new file's name
            digest.update(data)
            entries[name] = {"sha256": digest.hexdigest(), "size": size + len(data),
                             "append": True}
            hashes[path] = (size + len(data), entries[name]["sha256"], digest)
        if files:
            if not staging.is_dir():
                staging.mkdir()
                durable.wrote()
            for name, data in files.items():
                staged = f"{STAGING}/{months_done:06d}-{token}-{name}"
                written.append(directory / staged)
                durable.write_file(directory / staged, data)
                entries[name] = {"sha256": _sha256(data), "size": len(data), "staged": staged}
            durable.fsync_dir(staging)
        manifest = {
            "format": FORMAT_APPEND if append else FORMAT,
            "kind": kind,
            "months_done": months_done,
            "config_sha256": configs_hash,
            "files": entries,
        }
        durable.write_file(tmp, dumps(manifest))
        durable.replace(tmp, directory / MANIFEST)  # the commit
    except OSError as err:
        for path in [*written, tmp]:
            try:
                path.unlink(missing_ok=True)
            except OSError:
                pass
        raise RunWriteError(
            err.errno,
            f"could not write month {months_done} to {directory}: {durable.reason(err)}; the "
            "previous commit is kept (free the space or fix the permissions, then resume)",
        ) from err
    # committed: from here on a failure only delays pointing the visible names at the files
    for path in list(_appended):
        if path.parent == directory:
            del _appended[path]
    _appended.update(hashes)
    _publish(directory, manifest, dict(files), written=set(files))
    return manifest


def _publish(directory: Path, manifest: Mapping[str, Any], data: Mapping[str, bytes],
             written: Collection[str] = ()) -> None:
    """Make the commit durable (fsync of the directory), point the visible names at the
    committed files, then remove the staged names and any leftovers of interrupted writers.
    A failure here is left for the next writer (the commit is done: readers find the staged
    files). ``written`` names the files the commit has just staged."""
    try:
        durable.fsync_dir(directory)
        for name, entry in manifest["files"].items():
            target = directory / name
            # a file the commit has just staged is pointed at anew (its visible name holds an
            # earlier content, so reading and hashing it first would only cost time); any
            # other only where its visible name does not hold it (an earlier publish failed)
            if entry.get("append") or (name not in written
                                       and _file_sha256(target) == entry["sha256"]):
                continue
            staged = directory / entry["staged"]
            if not staged.exists():
                return  # nothing to publish from; read() reports the file as damaged
            tmp = directory / f".{name}.tmp"
            tmp.unlink(missing_ok=True)
            try:
                os.link(staged, tmp)
                durable.wrote()
            except OSError:  # no hard links on this file system: a copy
                durable.write_file(tmp, data[name] if name in data else staged.read_bytes())
            durable.replace(tmp, target)
        durable.fsync_dir(directory)
        _remove_leftovers(directory, [n for n in APPENDABLE if n not in manifest["files"]])
    except OSError:
        return


def _file_sha256(path: Path) -> str | None:
    try:
        return _sha256(path.read_bytes())
    except OSError:
        return None


def _remove_leftovers(directory: Path, unlisted: Iterable[str] = ()) -> None:
    """Remove the staged files and the temporary files of interrupted writers (called once
    every visible name holds the committed content), and the files ``unlisted`` (appended
    files the manifest no longer lists)."""
    staging = directory / STAGING
    if staging.is_dir():
        for path in sorted(staging.iterdir()):
            if _STAGED.match(path.name):
                durable.unlink(path)
        try:
            staging.rmdir()
            durable.wrote()
        except OSError:
            pass
    for name in (MANIFEST + ".tmp", *(f".{n}.tmp" for n in RUN_FILES), *unlisted):
        durable.unlink(directory / name)


def clear(directory: str | os.PathLike, others: Iterable[str] = ()) -> None:
    """Remove a run from ``directory`` (and the files ``others``): the manifest first, so
    that an interruption never leaves something that reads as a run of mixed origins."""
    durable.settle(directory)
    directory = Path(directory)
    durable.unlink(directory / MANIFEST)
    durable.fsync_dir(directory)
    for name in (*RUN_FILES, *others):
        durable.unlink(directory / name)
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
    if manifest.get("format") not in FORMATS:
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
        )
        if ok and entry.get("append") is True:
            ok = name in APPENDABLE and "staged" not in entry and entry["size"] >= 0 \
                and manifest["format"] == FORMAT_APPEND
        elif ok:
            ok = (isinstance(entry.get("staged"), str)
                  and entry["staged"].startswith(STAGING + "/")
                  and _STAGED.match(entry["staged"][len(STAGING) + 1 :]) is not None)
        if not ok:
            raise RunDirError(f"{where}: the entry of {name!r} is malformed; {RECOVER}")
    return manifest


def manifest_of(directory: str | os.PathLike) -> dict[str, Any] | None:
    """The manifest of ``directory`` as it is on disk, or None if there is none or it does
    not verify (a writer checks with it that the directory still holds its last commit)."""
    durable.settle(directory)
    try:
        return _load_manifest(Path(directory))
    except RunDirError:
        return None


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
    durable.settle(directory)
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
        appended = bool(entry.get("append"))
        candidates = [directory / name] if appended else [directory / name,
                                                          directory / entry["staged"]]
        for candidate in candidates:
            try:
                data = candidate.read_bytes()
            except OSError:
                continue
            if appended:  # bytes after the committed size are an interrupted append's
                data = data[: entry["size"]] if len(data) >= entry["size"] else b""
            if _sha256(data) == entry["sha256"] and len(data) == entry["size"]:
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
            raise RunDirError(f"{path} cannot be read ({durable.reason(err)}); {RECOVER}") from None
    return Run(directory, None, files)
