r"""Checkpoints of a learning run: what is saved after every month, and the verified resume.

After every month the run directory (:mod:`mpcrl_lite.learning.rundir`) gets one commit: the
first and the last month of a run write ``history.json``, ``history.npz`` and
``checkpoint.json``, every month between them appends one line to the journal
``history.jsonl`` (the month's History entries, its arrays and :meth:`Checkpointing.month_state`,
see :meth:`Checkpointing.save_checkpoint`). ``checkpoint.json`` has ``format`` (the
learner's), ``months_done``, ``theta``, the optimizer state (``updater``, or ``updaters``
per battery), the generator state ``rng``, the configurations and ``prices``, a fingerprint of
the month's prices (:func:`prices_fingerprint`); the journal's last line, where there is one,
holds the newer ``months_done``, learner state and ``rng``. :meth:`Learner.load_checkpoint` verifies
everything -- checksums, formats, the learner kind, months_done against the History and the
manifest, every series one entry per month, the configurations, the prices -- before changing
anything: a directory that does not verify is refused with one line, never half-resumed.
Checkpoints written before the price fingerprint existed resume without that check.
"""

from __future__ import annotations

import hashlib
import json
import logging
from collections.abc import Callable
from pathlib import Path
from typing import Any, ClassVar, NamedTuple

import numpy as np

from .._util import jsonio
from ..config import LearningConfig, MPCConfig, SystemConfig
from ..system.prices import Prices
from ..theta import PARTS, Theta
from . import rundir
from .history import History
from .outdir import RunDirError, RunDirMissing
from .rundir import RECOVER

__all__ = ["JOURNAL_LIMIT", "Checkpointing", "open_run", "parse_theta", "prices_fingerprint"]

log = logging.getLogger(__name__)


def prices_fingerprint(prices: Prices) -> dict[str, Any]:
    """What identifies a month of prices in a checkpoint.

    Returns
    -------
    dict
        ``sha256`` (of the shape and the float64 bytes of :attr:`Prices.buy` and
        :attr:`Prices.sell`, what the true system is charged), ``shape`` (``[days, 24]``) and
        ``source`` (informational, not compared).
    """
    buy = np.ascontiguousarray(prices.buy, dtype="<f8")
    sell = np.ascontiguousarray(prices.sell, dtype="<f8")
    digest = hashlib.sha256(json.dumps([list(buy.shape), list(sell.shape)]).encode())
    digest.update(buy.tobytes())
    digest.update(sell.tobytes())
    return {"sha256": digest.hexdigest(), "shape": list(buy.shape), "source": prices.source}


def open_run(learner: Checkpointing, months: int | None, out: str | Path | None, resume: bool,
             force: bool, adopt: bool = False) -> int:
    """Check the arguments of :func:`run_months` and prepare ``out`` (resume, replace or
    refuse); returns the number of months to reach. A run without ``manifest.json`` (written
    before the manifest format: nothing verifies that its files are the ones the run wrote)
    is resumed only with ``adopt``, with a warning; it is then committed in today's format."""
    months = learner.learning.months if months is None else months
    if isinstance(months, bool) or not isinstance(months, int) or months < 1:
        raise ValueError(f"months={months!r}: expected an integer >= 1")
    if resume and force:
        raise ValueError("resume=True and force=True exclude each other")
    out = Path(out) if out is not None else None
    if resume and out is None:
        raise ValueError("resume=True needs out=DIR (where the checkpoint is)")
    if out is not None:
        found = rundir.inspect(out)
        if resume and found.holds_run and not found.manifest and not adopt:
            raise RunDirError(
                f"{out} holds a run without {rundir.MANIFEST} (written before the manifest "
                "format: its files cannot be verified); pass --adopt (adopt=True) to resume "
                "it as it is, or --force (force=True) to start over")
        if resume and found.holds_run:
            if not found.manifest:
                log.warning("adopting %s: a run without %s, resumed unverified (its files "
                            "are only checked against each other)", out, rundir.MANIFEST)
            learner.load_checkpoint(out)
            learner.after_resume()
            if not found.manifest:  # a run of the previous format: committed in this one
                learner.save_checkpoint(out)
        elif resume:
            log.info("no run in %s to resume: starting a new one", out)
        elif found.holds_run and not force:
            raise RunDirError(
                f"{out} already holds a run ({', '.join(found.names)}): resume it "
                "(--resume, resume=True), replace it (--force, force=True) or choose another "
                "directory"
            )
        elif found.holds_run:
            rundir.clear(out)
    return months


class Checkpointing:
    """What a learner needs to checkpoint and resume: its kind and format, its configurations,
    its prices, its generator, its History and its own state (theta and optimizer)."""

    KIND: ClassVar[str] = ""
    FORMAT: ClassVar[str] = ""
    #: What ``checkpoint.json`` of a learner kind is called, to name the right learner.
    FORMATS: ClassVar[dict[str, str]] = {
        "mpcrl_lite.Checkpoint/1": "centralized",
        "mpcrl_lite.DecentralizedCheckpoint/1": "decentralized",
        "mpcrl_lite.QCheckpoint/1": "q-learning",
    }
    #: How each kind is resumed (for the message when the wrong learner is used).
    RESUME_WITH: ClassVar[dict[str, str]] = {
        "centralized": "Experiment, `learn` without --decentralized",
        "decentralized": "DecentralizedExperiment, `learn --decentralized`",
        "q-learning": "QLearningExperiment, `learn --learner q`",
    }

    system: SystemConfig
    mpc_config: MPCConfig
    learning: LearningConfig
    prices: Prices
    rng: np.random.Generator
    history: History

    def learner_state(self) -> dict[str, Any]:
        """The learner's own part of ``checkpoint.json`` (theta and optimizer state)."""
        raise NotImplementedError

    def restore_learner_state(self, state: dict[str, Any], where: str) -> Any:
        """Check the learner's part of a checkpoint (raising :class:`RunDirError` naming
        ``where``) and return a function that applies it; nothing changes before that
        function is called."""
        raise NotImplementedError

    def extra_files(self) -> dict[str, bytes]:
        """Files of the learner's state besides ``checkpoint.json`` (named in
        :data:`~mpcrl_lite.learning.rundir.RUN_FILES`), committed with every checkpoint;
        none here."""
        return {}

    def restore_extra_files(self, files: dict[str, bytes], directory: Path) -> Any:
        """Check the files of :meth:`extra_files` read from a checkpoint (raising
        :class:`RunDirError`) and return a function that applies them; nothing here."""
        return lambda: None

    def configs(self) -> dict[str, Any]:
        """The configuration objects a checkpoint must match, by key."""
        return {"system": self.system, "mpc": self.mpc_config, "learning": self.learning}

    def configs_hash(self) -> str:
        """sha256 of the configurations, ``learning.months`` left out (a resume may extend
        the run); computed once per set of configuration objects (they are frozen)."""
        return self._per_configs(
            "_configs_hash", lambda configs: rundir.config_sha256(_plain_configs(configs)))

    def _config_dicts(self) -> dict[str, Any]:
        """The configurations as ``checkpoint.json`` holds them, made once per set of
        configuration objects (they are frozen; every month's checkpoint repeats them)."""
        return self._per_configs(
            "_config_dicts_of", lambda configs: {k: c.to_dict() for k, c in configs.items()})

    def _per_configs(self, attribute: str, make: Callable[[dict[str, Any]], Any]) -> Any:
        """``make(self.configs())``, kept in ``attribute`` until a configuration object is
        replaced (the objects are kept with it, so that their ids stay theirs)."""
        configs = self.configs()
        key = tuple((name, id(cfg)) for name, cfg in configs.items())
        known = getattr(self, attribute, None)
        if known is None or known[0] != key:
            known = (key, make(configs), tuple(configs.values()))
            setattr(self, attribute, known)
        return known[1]

    def checkpoint_state(self) -> dict[str, Any]:
        """The content of ``checkpoint.json``."""
        return {
            "format": self.FORMAT,
            **self.month_state(),
            **self._config_dicts(),
            "prices": prices_fingerprint(self.prices),
        }

    def month_state(self) -> dict[str, Any]:
        """What changes from month to month in ``checkpoint.json`` (``months_done``, the
        learner's state and ``rng``): the ``checkpoint`` of a journal line."""
        return {"months_done": self.history.months, **self.learner_state(),
                "rng": self.rng.bit_generator.state}

    def save_checkpoint(self, directory: str | Path, last: bool = True,
                        background: bool = False) -> None:
        """Commit the History and the checkpoint to ``directory`` (one atomic commit).

        With ``last=False`` (a month of a run that goes on) and a previous commit of this
        learner in ``directory``, one line is appended to the journal ``history.jsonl``: the
        months since that commit, the last month's arrays and :meth:`month_state`;
        ``history.json``, ``history.npz`` and ``checkpoint.json`` are kept as they are
        (:mod:`mpcrl_lite.learning.rundir`). The cost of a month does not grow with the
        months done. Otherwise (the default), or once the journal holds
        :data:`JOURNAL_LIMIT` bytes, the whole History and checkpoint are written and the
        journal dropped.

        With ``background=True`` the files (or the journal's line) are built here and
        written by the process's writer thread (:func:`~mpcrl_lite.learning.rundir.commit_soon`,
        :func:`~mpcrl_lite.learning.rundir.append_month_soon`) while the caller goes on; a
        journal line is handed to it by :meth:`write_deferred`, which the learners call when
        the next month's update begins. The next checkpoint (or :meth:`wait_for_checkpoint`)
        waits for the write first and raises its error.
        """
        self.wait_for_checkpoint()
        directory = Path(directory)
        previous: _Commit | None = getattr(self, "_last_commit", None)
        self._last_commit = None
        history = self.history
        extra = self.extra_files()
        common: dict[str, Any] = {"kind": self.KIND, "months_done": history.months,
                                  "configs_hash": self.configs_hash()}
        goes_on = not last and previous is not None and previous.directory == directory \
            and previous.history is history
        appended = rundir.appended_size(directory) if goes_on and not extra else None
        if appended is not None and appended < JOURNAL_LIMIT:
            line, payload = history.journal_parts(previous.lengths,
                                                  {"checkpoint": self.month_state()})
            if background:  # kept for write_deferred: beside the next month's update
                self._deferred_append = (directory, line, history.months, payload)
            else:
                rundir.append_month(directory, line, months_done=history.months,
                                    payload=payload)
            self._last_commit = previous._replace(lengths=history.series_lengths())
            return
        files_before = previous.manifest["files"] if goes_on else {}
        if goes_on and extra and set(_KEPT) <= set(files_before) \
                and files_before.get(rundir.JOURNAL, {}).get("size", 0) < JOURNAL_LIMIT \
                and rundir.manifest_of(directory) == previous.manifest:
            # files of the learner's own beside the checkpoint: each month a commit of them
            # and of the journal's line through the manifest
            files = extra
            line = history.journal_record(previous.lengths, {"checkpoint": self.month_state()})
            common.update(previous=previous.manifest, keep=list(_KEPT),
                          append={rundir.JOURNAL: line})
        else:
            # uncompressed: compressing the arrays takes 7 ms and saves a quarter of 330 kB
            files = history.to_files(compress=False)
            files[rundir.CHECKPOINT] = jsonio.dumps(self.checkpoint_state())
            files.update(extra)
            common["journal"] = not last and not extra
        lengths = history.series_lengths()
        if background:
            self._pending_commit = (rundir.commit_soon(directory, files, **common), history,
                                    lengths)
        else:
            manifest = rundir.commit(directory, files, **common)
            self._last_commit = _Commit(directory, history, manifest, lengths)

    def write_deferred(self) -> None:
        """Hand the month's journal line kept by :meth:`save_checkpoint` (``background=True``)
        to the process's writer thread, if there is one: the learner calls it once the next
        month's closed loop has run (its compiled days keep both cores busy) and its update
        begins (one core's work), so that the line's sha256 and write take the idle core.
        :meth:`wait_for_checkpoint` and the next checkpoint call it too."""
        deferred = getattr(self, "_deferred_append", None)
        if deferred is None:
            return
        self._deferred_append = None
        directory, line, months_done, payload = deferred
        self._pending_append = rundir.append_month_soon(directory, line,
                                                        months_done=months_done,
                                                        payload=payload)

    def wait_for_checkpoint(self) -> None:
        """Wait for a checkpoint written in the background (:meth:`save_checkpoint`) and
        raise its error if it failed (the directory then holds the commit before it)."""
        self.write_deferred()
        append = getattr(self, "_pending_append", None)
        if append is not None:
            self._pending_append = None
            append.result()
        pending = getattr(self, "_pending_commit", None)
        if pending is None:
            return
        self._pending_commit = None
        commit, history, lengths = pending
        manifest = commit.result()
        self._last_commit = _Commit(commit.directory, history, manifest, lengths)

    def after_resume(self) -> None:
        """What a resumed run makes before its next month (nothing here; the centralized
        experiment evaluates the months whose evaluations were still out when it stopped)."""

    def load_checkpoint(self, directory: str | Path) -> None:
        """Continue from the run in ``directory``; everything is verified before anything
        changes (see the module docstring). Raises :class:`RunDirError` (a ValueError)."""
        directory = Path(directory)
        found = rundir.inspect(directory)
        if not found.holds_run:
            raise RunDirMissing(f"{directory} holds no run to resume (no {rundir.MANIFEST} "
                                f"or {rundir.CHECKPOINT})")
        if not found.manifest and rundir.HISTORY_JSON not in found.run_files:
            raise RunDirError(
                f"{directory / rundir.HISTORY_JSON} is missing next to {rundir.CHECKPOINT} "
                f"(an incomplete or damaged run); {RECOVER}")
        run = rundir.read(directory, [rundir.HISTORY_JSON, rundir.HISTORY_NPZ, rundir.CHECKPOINT,
                                      rundir.JOURNAL, rundir.CRITIC],
                          optional=[rundir.HISTORY_NPZ, rundir.CHECKPOINT, rundir.JOURNAL,
                                    rundir.CRITIC])
        if run.kind == "history" or rundir.CHECKPOINT not in run.files:
            raise RunDirError(
                f"{directory} holds a History without {rundir.CHECKPOINT}: it cannot be "
                "resumed (the learner's state is missing); start over in it with --force "
                "(force=True) or choose another directory")
        self._check_kind(run.kind, directory, "its manifest")
        where = str(directory / rundir.CHECKPOINT)
        state = _parse_checkpoint(run.files[rundir.CHECKPOINT], where)
        kind = self.FORMATS.get(state.get("format"))
        if kind is None:
            raise RunDirError(f"{where}: format {state.get('format')!r}, expected "
                              f"{self.FORMAT!r}; {RECOVER}")
        self._check_kind(kind, directory, rundir.CHECKPOINT)
        missing = [k for k in self.checkpoint_state() if k not in state and k not in _LATER_KEYS]
        if missing:
            raise RunDirError(f"{where} lacks {', '.join(map(repr, missing))}; {RECOVER}")
        if run.files.get(rundir.JOURNAL):
            state = self._with_journal_state(state, run.files[rundir.JOURNAL], directory)
        saved = self._check_configs(state, directory, where)
        self._check_prices(state.get("prices"), directory, where)
        history = History.from_files(run.files, directory, run.payload)
        months_done = state["months_done"]
        if isinstance(months_done, bool) or not isinstance(months_done, int) or months_done < 0:
            raise RunDirError(f"{where}: months_done={months_done!r}, expected an integer >= 0; "
                              f"{RECOVER}")
        if months_done != history.months or run.months_done not in (None, months_done):
            manifest = "" if run.months_done is None else f", {rundir.MANIFEST} {run.months_done}"
            raise RunDirError(
                f"{where} records months_done={months_done} but history.json {history.months} "
                f"months{manifest}: the files are from different months; {RECOVER}")
        shared = {key: saved[key] for key in history.configs()}
        if _plain_configs(history.configs()) != _plain_configs(shared):
            raise RunDirError(f"{directory}: history.json and {rundir.CHECKPOINT} were written "
                              f"with different configurations; {RECOVER}")
        if run.manifest is not None and run.manifest["config_sha256"] != rundir.config_sha256(
                _plain_configs(saved)):
            raise RunDirError(f"{directory / rundir.MANIFEST}: config_sha256 does not match "
                              f"{rundir.CHECKPOINT}; {RECOVER}")
        rng = np.random.Generator(type(self.rng.bit_generator)())
        try:
            rng.bit_generator.state = state["rng"]
        except (TypeError, ValueError, KeyError, OverflowError) as err:
            raise RunDirError(f"{where}: 'rng' is not a {type(self.rng.bit_generator).__name__} "
                              f"state ({err}); {RECOVER}") from None
        apply = self.restore_learner_state(state, where)
        apply_files = self.restore_extra_files(run.files, directory)
        # everything verified: from here on nothing can fail half-way
        if run.manifest is not None:
            rundir.read(directory, list(run.manifest["files"]), repair=True)
        self.history = history
        self.rng.bit_generator.state = rng.bit_generator.state
        apply()
        apply_files()

    def _with_journal_state(self, state: dict[str, Any], journal: bytes,
                            directory: Path) -> dict[str, Any]:
        """``checkpoint.json``'s ``state`` updated by the journal's last line, whose
        ``checkpoint`` (:meth:`month_state`) is the newer (journals written before it
        existed have none: their ``checkpoint.json`` was written with every month)."""
        where = directory / rundir.JOURNAL
        try:
            line = json.loads(journal.rstrip(b"\n").rsplit(b"\n", 1)[-1])
        except ValueError as err:
            raise RunDirError(f"{where}: the last line is not valid JSON ({err}); {RECOVER}") \
                from None
        newer = line.get("checkpoint") if isinstance(line, dict) else None
        if newer is None:
            return state
        known = set(self.month_state())
        if not isinstance(newer, dict) or set(newer) != known:
            raise RunDirError(f"{where}: the last line's checkpoint is not an object with "
                              f"{', '.join(sorted(known))}; {RECOVER}")
        return {**state, **newer}

    def _check_kind(self, kind: str | None, directory: Path, source: str) -> None:
        if kind is not None and kind != self.KIND:
            raise RunDirError(
                f"{directory} holds a {kind} run ({source}); this is a {self.KIND} learner: "
                f"resume it with {self.RESUME_WITH.get(kind, kind)}")

    def _check_prices(self, saved: Any, directory: Path, where: str) -> None:
        """The run's prices (``checkpoint.json``'s ``prices``) must be the learner's."""
        if saved is None:  # written before the fingerprint existed: nothing to compare
            return
        if not (isinstance(saved, dict) and isinstance(saved.get("sha256"), str)):
            raise RunDirError(f"{where}: bad 'prices' ({saved!r:.80}); {RECOVER}")
        now = prices_fingerprint(self.prices)
        if saved["sha256"] != now["sha256"]:
            def show(p: dict[str, Any]) -> str:
                shape = "x".join(map(str, p.get("shape") or [])) or "?"
                return f"{p.get('source', '?')!r} ({shape}, sha256 {p['sha256'][:12]})"

            raise RunDirError(
                f"checkpoint in {directory} was written with other prices: {show(saved)} in "
                f"the run, {show(now)} now (resume with the run's --prices/--area/--month, or "
                "start over with --force / force=True)")

    def _check_configs(self, state: dict[str, Any], directory: Path, where: str) -> dict[str, Any]:
        """The saved configurations, which must equal the learner's (months aside)."""
        saved: dict[str, Any] = {}
        differ: list[str] = []
        fields: list[str] = []
        for key, cfg in self.configs().items():
            try:
                saved[key] = type(cfg).from_dict(state[key])
            except (TypeError, ValueError, AttributeError) as err:
                raise RunDirError(f"{where}: bad {key} config ({err}); {RECOVER}") from None
            old, new = saved[key].to_dict(), cfg.to_dict()
            if key == "learning":
                old.pop("months"), new.pop("months")
            changed = [f for f in new if old.get(f) != new.get(f)]
            if changed:
                differ.append(key)
                fields += [f"{key}.{f}={old.get(f)!r} in the run, {new.get(f)!r} now"
                           for f in changed]
        if differ:
            raise RunDirError(
                f"checkpoint in {directory} was written with a different {' and '.join(differ)} "
                f"config: {'; '.join(fields)} (resume with the run's settings, or start over "
                "with --force / force=True)")
        return saved


#: The files a month appended to the journal keeps from the commit before it.
_KEPT = (rundir.HISTORY_JSON, rundir.HISTORY_NPZ, rundir.CHECKPOINT)
#: The journal's size (bytes) from which the next month writes the whole History anew
#: (a line is about 170 kB with the month's arrays: about 390 months).
JOURNAL_LIMIT = 64 * 2**20

class _Commit(NamedTuple):
    """A learner's last commit: where, of which History, the manifest written and the
    series' lengths then (what the next journal line continues from)."""

    directory: Path
    history: History
    manifest: dict[str, Any]
    lengths: dict[str, int]


#: Keys of ``checkpoint.json`` added after checkpoints existed (an older one lacks them).
_LATER_KEYS = ("prices",)


def _plain_configs(configs: dict[str, Any]) -> dict[str, Any]:
    plain = {key: cfg if isinstance(cfg, dict) else cfg.to_dict() for key, cfg in configs.items()}
    plain = json.loads(json.dumps(plain))
    plain["learning"].pop("months", None)
    return plain


def _parse_checkpoint(data: bytes, where: str) -> dict[str, Any]:
    try:
        state = json.loads(data)
    except ValueError as err:
        raise RunDirError(f"{where} is not valid JSON ({err}); {RECOVER}") from None
    if not isinstance(state, dict):
        raise RunDirError(f"{where} holds a {type(state).__name__}, expected an object; {RECOVER}")
    return state


def parse_theta(value: Any, n: int, where: str) -> Theta:
    """theta from a checkpoint: ``len(PARTS) * n`` finite numbers, or a RunDirError."""
    size = len(PARTS) * n
    ok = isinstance(value, list) and len(value) == size and all(
        isinstance(v, (int, float)) and not isinstance(v, bool) and np.isfinite(v) for v in value)
    if not ok:
        raise RunDirError(f"{where}: 'theta' is not a list of {size} finite numbers; {RECOVER}")
    return Theta.from_vector(np.asarray(value, dtype=float), n)
