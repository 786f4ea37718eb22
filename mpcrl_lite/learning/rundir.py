r"""The run directory: the files of a learning run, one commit point per month.

A run directory ``D`` holds, once a month has been committed::

    D/manifest.json     the commit point of the whole files (see below)
    D/history.json      the History's configurations and per-month series (readable JSON)
    D/history.npz       the History's arrays (first and last month), allow_pickle=False
    D/checkpoint.json   what a learner needs to continue (theta, optimizer and RNG state)
    D/history.jsonl     while a run is going on: the months since the whole files, one line
                        each (the journal, see below)
    D/critic.npz        with ``LearningConfig.critic_months > 1`` only: the critic's samples
                        of the earlier months its next fit uses
    D/summary.json      written by the ``learn`` command at the end (derived, not committed)

:meth:`History.save <mpcrl_lite.learning.history.History.save>` writes the same format without
``checkpoint.json`` (kind ``"history"``).

How whole files are committed (:func:`commit`)
----------------------------------------------
1. every file of the commit is written under a **new** name in ``D/.run/`` and fsynced;
   nothing the last commit refers to is touched;
2. ``D/manifest.json`` is replaced atomically (written as ``manifest.json.tmp``, fsynced,
   renamed, directory fsynced). **This rename is the commit.** The manifest carries

   =================  ============================================================
   ``format``         ``"mpcrl_lite.Run/1"``, or ``"mpcrl_lite.Run/3"`` when it lists a
                      journal (``"mpcrl_lite.Run/2"``, the previous version's journal
                      without the months' states, is still read)
   ``kind``           ``"centralized"``, ``"decentralized"`` (a learner's run) or
                      ``"history"`` (a History on its own)
   ``months_done``    months recorded by the committed files
   ``config_sha256``  sha256 of the configurations (:func:`config_sha256`; the
                      learning config without ``months``, which a resume may extend)
   ``files``          per user-visible name (``history.json`` ...): its ``sha256``,
                      ``size`` in bytes and ``staged`` (its name under ``.run/``); for
                      an appended file ``append: true`` instead of ``staged``, and for
                      a journal that months are appended to a ``token``
   =================  ============================================================

3. the user-visible names are then pointed at the new files (a hard link, or a copy where
   the file system has none, renamed into place) and the staged names removed.

A kill or a full disk before step 2 leaves the previous commit untouched (the staged files
are unreferenced and removed by the next writer); after step 2 the new month is committed,
and a reader finds each file under its visible name or, if step 3 did not finish, under its
staged name: :func:`read` accepts a file only if its sha256 matches the manifest.

Months appended without a manifest: O(1) per month
--------------------------------------------------
Rewriting the whole History every month costs in proportion to the months so far, and even
a commit of a few files costs milliseconds of writes and fsyncs against a month that takes
about 20. The learners' commit of a run's first month (and of the first after a resume)
therefore lists an empty journal (:data:`JOURNAL`) with a random ``token``
(``journal=True``), and every later month but the last is **one line appended** to it
(:func:`append_month`), leaving the manifest and the other files as they are::

    {"sha256":"<64 hex>","previous":"<64 hex>","token":"<16 hex>","months_done":M,"payload":P,"record":{...}}
    <P bytes>

``sha256`` is that of the line after its ``",`` (so of everything else in it) and of the
``P`` bytes of payload that follow its newline, ``previous`` the ``sha256`` of the line
before (of the empty journal for the first), ``token`` the manifest's and ``M`` the month
the line commits; ``record`` (JSON) and the payload are what the learner appends (the month's
History entries and state, and the month's arrays as raw bytes, see
:meth:`~mpcrl_lite.learning.checkpoint.Checkpointing.save_checkpoint`). **Writing the
payload's last byte is the month's commit.** :func:`read` takes the lines in order while each one
verifies and follows the one before; the first that does not is a write the process did not
finish (it can only be the last: the next append cuts it off), and a whole line of the same
token after it is a changed journal, refused. Lines of another token are those of an earlier
commit's journal, ignored and cut by the next append. :attr:`Run.months_done` is the last
month the lines commit.

A line survives the process being killed as soon as it is written; it is fsynced with the
first line appended :data:`SYNC_EVERY_S` seconds or more after the journal's last fsync, so a
power cut can take the months of the last few seconds (and of the month then running), never
the directory's consistency (a line only
counts if it verifies). The last month of a run (and of each call) writes the whole files
again, fsynced, and drops the journal, so a finished run holds none and reads as format 1.

A commit may also **keep** entries of the previous manifest and **append** to the journal
through the manifest (:func:`commit` with ``previous``, ``keep`` and ``append``; a learner
with files of its own, :data:`CRITIC`, commits its months so): the new bytes go after the
journal's committed ``size`` (bytes beyond it, left by an interrupted writer, are cut first)
and are fsynced before the manifest is written; the manifest's ``size`` and ``sha256`` then
cover the journal's new length.

Commits in the background
-------------------------
The writes of a commit are mostly waits for the disk (fsync, rename): :func:`commit_soon`
runs :func:`commit` on the process's writer thread, with contents the caller has built
already, so that the next month computes meanwhile; :func:`append_month_soon` does the same
for a month's line (its sha256 and its write, about 0.3 ms of a month's 20; the learners hand
it over when the next month's update begins, on the core the compiled days leave idle:
:meth:`~mpcrl_lite.learning.checkpoint.Checkpointing.write_deferred`). At most one
commit per directory is under way; every
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
import time
from collections.abc import Collection, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from .._util.jsonio import dumps
from . import durable
from .durable import RunWriteError
from .outdir import RunDirError, RunDirMissing

__all__ = ["APPENDABLE", "CHECKPOINT", "CRITIC", "FORMAT", "FORMATS", "FORMAT_APPEND",
           "FORMAT_APPEND_2", "HISTORY_JSON", "HISTORY_NPZ", "JOURNAL", "KINDS", "MANIFEST", "RECOVER", "STAGING", "SUMMARY",
           "SYNC_EVERY_S", "Contents", "Run", "append_month", "appended_size", "clear", "commit", "commit_soon",
           "config_sha256", "inspect", "manifest_of", "read"]

FORMAT = "mpcrl_lite.Run/1"
#: The manifest's format when it lists an appended file (readers of formats 1 and 2 refuse
#: it): the journal's last line may hold a state newer than ``history.npz`` and
#: ``checkpoint.json`` (:mod:`mpcrl_lite.learning.checkpoint`).
FORMAT_APPEND = "mpcrl_lite.Run/3"
#: The appending format of the previous version (its journal lines hold the History's
#: series only; ``history.npz`` and ``checkpoint.json`` were written with every month).
FORMAT_APPEND_2 = "mpcrl_lite.Run/2"
FORMATS = (FORMAT, FORMAT_APPEND_2, FORMAT_APPEND)
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

#: At most how many seconds the months appended by :func:`append_month` wait for their
#: fsync (see "Months appended without a manifest" in the module docstring).
SYNC_EVERY_S = 5.0

_STAGED = re.compile(r"^\d{6,}-[0-9a-f]{8}-[A-Za-z0-9_.]+$")
_HEX64 = re.compile(r"^[0-9a-f]{64}$")
_TOKEN = re.compile(r"^[0-9a-f]{16}$")
#: How a line appended by :func:`append_month` starts: its sha256 follows, then ``",`` and
#: the body the sha256 is of.
_LINE_HEAD = b'{"sha256":"'
_LINE_BODY = len(_LINE_HEAD) + 64 + 2
_LINE_RECORD = b',"record":'
_EMPTY_SHA256 = hashlib.sha256(b"").hexdigest()


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
    journal: bool = False,
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

    ``journal=True`` lists an empty journal (:data:`JOURNAL`) with a new ``token``, which
    :func:`append_month` then appends months to without a manifest.
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
    if missing or (set(keep) | set(append)) & set(files) or set(keep) & set(append) or (
            journal and JOURNAL in {*files, *keep, *append}):
        raise ValueError(f"keep={list(keep)}, append={sorted(append)}, journal={journal}: "
                         "expected names of the previous commit, each in one of files, keep "
                         "and append (and the journal in none of them with journal=True)")
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
        if journal:
            entries[JOURNAL] = {"sha256": _EMPTY_SHA256, "size": 0, "append": True,
                                "token": os.urandom(8).hex()}
        manifest = {
            "format": FORMAT_APPEND if append or journal else FORMAT,
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
    _tails.pop(directory, None)
    if journal:
        _tails[directory] = _Tail(entries[JOURNAL]["token"], 0, _EMPTY_SHA256, months_done)
    _publish(directory, manifest, dict(files), written=set(files))
    return manifest


# -- months appended without a manifest ----------------------------------------------------
@dataclass
class _Tail:
    """Where :func:`append_month` continues a directory's journal: the manifest's
    ``token``, the end of the journal's committed bytes, the sha256 of its last line (the
    empty file's at first), the months committed, and when the journal was last fsynced."""

    token: str
    offset: int
    last: str
    months_done: int
    synced: float = field(default_factory=time.monotonic)
    #: whether the journal ends at ``offset`` (this process's last append there succeeded):
    #: the next append need not cut it first
    clean: bool = False


#: The journals this process's commits listed with a token, by directory.
_tails: dict[Path, _Tail] = {}


def _month_line(record: bytes, payload: Sequence[Any], token: str, previous: str,
                months_done: int) -> tuple[list[Any], str]:
    """A month's line followed by its payload (see the module docstring), as the buffers to
    write one after the other (the payload's not copied), and its sha256."""
    size = sum(memoryview(part).nbytes for part in payload)
    body = b'"previous":"%s","token":"%s","months_done":%d,"payload":%d%s%s}\n' % (
        previous.encode(), token.encode(), months_done, size, _LINE_RECORD, record)
    digest = hashlib.sha256(body)
    for part in payload:
        digest.update(part)
    hexdigest = digest.hexdigest()
    return [_LINE_HEAD + hexdigest.encode() + b'",' + body, *payload], hexdigest


def _read_line(whole: bytes, start: int) -> tuple[dict[str, Any], bytes, bytes, str, int] | None:
    """The line of :func:`append_month` at ``start`` of ``whole``, if it is one whose
    sha256 matches: its head (``previous``, ``token``, ``months_done``, ``payload``), its
    record, its payload, its sha256 and where the next line starts; else None."""
    end = whole.find(b"\n", start)
    if end < 0 or not whole.startswith(_LINE_HEAD, start) \
            or whole[start + _LINE_BODY - 2:start + _LINE_BODY] != b'",' \
            or whole[end - 1:end] != b"}":
        return None
    body = whole[start + _LINE_BODY:end + 1]
    split = body.find(_LINE_RECORD)
    try:
        head = json.loads(b"{" + body[:split] + b"}") if split > 0 else None
    except ValueError:
        return None
    size = head.get("payload") if isinstance(head, dict) else None
    if isinstance(size, bool) or not isinstance(size, int) or size < 0 \
            or end + 1 + size > len(whole):
        return None
    payload = whole[end + 1:end + 1 + size]
    digest = hashlib.sha256(body)
    digest.update(payload)
    if digest.hexdigest().encode() != whole[start + len(_LINE_HEAD):start + _LINE_BODY - 2]:
        return None
    return head, body[split + len(_LINE_RECORD):-2], payload, digest.hexdigest(), end + 1 + size


def _tail_for(directory: Path, record: bytes, months_done: Any) -> _Tail:
    """The journal :func:`append_month` continues in ``directory`` for a line ``record`` of
    month ``months_done``; ValueError without one, for a month that does not follow its last,
    or for a record of more than one line."""
    tail = _tails.get(directory)
    if tail is None:
        raise ValueError(f"{directory}: no commit of this process lists a journal to append "
                         "to (commit with journal=True first)")
    if isinstance(months_done, bool) or not isinstance(months_done, int) \
            or months_done != tail.months_done + 1:
        raise ValueError(f"months_done={months_done!r}: expected {tail.months_done + 1}, the "
                         "month after the last one committed")
    if b"\n" in record:
        raise ValueError("record: expected one line of JSON (it holds a newline)")
    return tail


def append_month(directory: str | os.PathLike, record: bytes, *, months_done: int,
                 payload: Sequence[Any] = ()) -> int:
    """Commit month ``months_done`` by appending one line (``record``, one line of JSON, and
    the bytes of ``payload``, buffers written one after the other) to the journal the
    directory's last commit by this process listed (``journal=True`` of :func:`commit`);
    returns the journal's size in bytes.

    The line is fsynced if :data:`SYNC_EVERY_S` seconds have passed since the journal's last
    fsync (see the module docstring). Raises :class:`RunWriteError` if the write fails (the
    months before stay committed) and ValueError without such a journal or when
    ``months_done`` does not follow the last month committed.
    """
    durable.settle(directory)
    directory = Path(directory)
    tail = _tail_for(directory, record, months_done)
    line, digest = _month_line(record, payload, tail.token, tail.last, months_done)
    sync = time.monotonic() - tail.synced >= SYNC_EVERY_S
    try:
        # cut first unless this process's last append there ended the file
        clean, tail.clean = tail.clean, False
        durable.append_file(directory / JOURNAL, tail.offset, line, sync=sync, trim=not clean)
        if sync:
            durable.fsync_dir(directory)  # the journal's name, if this append made it
    except OSError as err:
        raise RunWriteError(
            err.errno,
            f"could not write month {months_done} to {directory}: {durable.reason(err)}; the "
            "months before it are kept (free the space or fix the permissions, then resume)",
        ) from err
    tail.offset += sum(memoryview(part).nbytes for part in line)
    tail.last, tail.months_done, tail.clean = digest, months_done, True
    if sync:
        tail.synced = time.monotonic()
    return tail.offset


def append_month_soon(directory: str | os.PathLike, record: bytes, *, months_done: int,
                      payload: Sequence[Any] = ()) -> durable.PendingCommit:
    """:func:`append_month` (same arguments; checked here, before it returns) on the
    process's writer thread: returns at once with a
    :class:`~mpcrl_lite.learning.durable.PendingCommit` whose result is the journal's size
    (see "Commits in the background" in the module docstring). ``record`` and the buffers
    of ``payload`` must not change until it has finished."""
    durable.settle(directory)
    _tail_for(Path(directory), record, months_done)
    payload = list(payload)
    return durable.in_background(directory, lambda: append_month(
        directory, record, months_done=months_done, payload=payload))


def appended_size(directory: str | os.PathLike) -> int | None:
    """The size in bytes of the journal :func:`append_month` continues in ``directory``
    (None where the last commit of this process there listed none)."""
    durable.settle(directory)
    tail = _tails.get(Path(directory))
    return None if tail is None else tail.offset


#: The visible names this process pointed at committed files and the sha256 they then
#: held, so that a commit keeping a file does not read and hash it again (the directory's
#: lock keeps other writers out; :func:`clear` forgets a directory's names).
_published: dict[Path, str] = {}


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
            if entry.get("append"):
                continue
            if name not in written and (_published.get(target) == entry["sha256"]
                                        or _file_sha256(target) == entry["sha256"]):
                _published[target] = entry["sha256"]
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
            _published[target] = entry["sha256"]
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
    for name in RUN_FILES:
        _published.pop(directory / name, None)
    _tails.pop(directory, None)
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
    #: The months the journal's appended lines commit (:func:`append_month`), if any.
    appended_months: int | None = None
    #: The payload of the journal's last appended line (empty if there is none).
    payload: bytes = b""

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
        """The months committed: the manifest's months_done, or the last month its journal's
        appended lines commit (None for a legacy directory)."""
        if self.appended_months is not None:
            return self.appended_months
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
                and manifest["format"] in (FORMAT_APPEND, FORMAT_APPEND_2)
            if ok and "token" in entry:
                ok = manifest["format"] == FORMAT_APPEND and isinstance(entry["token"], str) \
                    and _TOKEN.match(entry["token"]) is not None
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
    appended_months, payload = None, b""
    journal = manifest["files"].get(JOURNAL)
    if journal is not None and "token" in journal and JOURNAL not in names:
        names = [*names, JOURNAL]  # its lines may commit months: months_done needs them
        optional = [*optional, JOURNAL]
        unasked = True
    else:
        unasked = False
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
            except FileNotFoundError:
                if appended and entry["size"] == 0:  # nothing appended yet
                    files[name] = b""
                    break
                continue
            except OSError:
                continue
            whole = data
            if appended:  # bytes after the committed size are an interrupted append's
                data = data[: entry["size"]] if len(data) >= entry["size"] else b""
            if _sha256(data) == entry["sha256"] and len(data) == entry["size"]:
                if "token" in entry:
                    data, appended_months, payload = _with_appended_months(
                        data, whole, entry, manifest["months_done"], directory / name)
                files[name] = data
                break
        else:
            state = "is missing" if not (directory / name).exists() else "does not match its sha256"
            raise RunDirError(
                f"{directory / name} {state} in {MANIFEST} (damaged or changed after the run "
                f"wrote it); {RECOVER}"
            )
    if unasked:
        files.pop(JOURNAL, None)
    if repair:
        _publish(directory, manifest, {**files})
    return Run(directory, manifest, files, appended_months, payload)


def _with_appended_months(prefix: bytes, whole: bytes, entry: Mapping[str, Any],
                          months_done: int, path: Path) -> tuple[bytes, int | None, bytes]:
    """The committed ``prefix`` of a journal followed by the records of the lines
    :func:`append_month` committed after it (read from ``whole``, the file), the last month
    they commit (None if there is none) and the last line's payload.

    The lines are taken in order while each one verifies; the first that does not ends them
    (a write the process did not finish: it can only be the last). A line after it that
    verifies on its own means that a committed line was changed: a :class:`RunDirError`."""
    token = entry["token"]
    records, payload = [], b""
    previous, month, start = entry["sha256"], months_done, len(prefix)
    while (found := _read_line(whole, start)) is not None and found[0] == {
            "previous": previous, "token": token, "months_done": month + 1,
            "payload": len(found[2])}:
        records.append(found[1] + b"\n")
        payload, previous, month, start = found[2], found[3], month + 1, found[4]
    # what follows is a write the process did not finish, or lines of an earlier commit
    # (another token); a whole line of this commit's that did not fit is a changed one
    later = whole.find(_LINE_HEAD, start)
    while later >= 0:
        found = _read_line(whole, later)
        if found is not None and found[0].get("token") == token:
            raise RunDirError(
                f"{path} does not match its sha256 after line {len(records)} (damaged or "
                f"changed after the run wrote it); {RECOVER}")
        later = whole.find(_LINE_HEAD, later + 1)
    return prefix + b"".join(records), (month if records else None), payload


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
