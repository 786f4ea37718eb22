"""Results of a learning run as data: per-month figures and two months of trajectories.

A :class:`History` is saved as two plain files, never as pickle:

* ``history.json`` -- the configurations, theta's entry names, and every per-month scalar
  series (human-readable), including the evaluation series (``J_eval`` and friends: the
  parameters of a month evaluated on ``LearningConfig.eval_draws`` fixed noise draws without
  exploration, see :meth:`mpcrl_lite.learning.experiment.Experiment.evaluate`);
* ``history.npz`` -- the arrays (theta per month, J per agent, and the full trajectories of
  the first and last month), loaded with ``allow_pickle=False``;
* while a run is going on, ``history.jsonl`` -- the months since ``history.json`` was
  written, one JSON line per monthly commit (:meth:`History.journal_record`; see
  :mod:`mpcrl_lite.learning.rundir`); :meth:`History.load` adds them to ``history.json``'s.

A number that is not finite (e.g. ``eval_bound_share`` of a month whose every MPC solve
failed) is written as ``null`` -- JSON has no NaN -- and read back as NaN. Series added
later (:data:`History.LATER_SERIES`, e.g. the confidence interval of ``J_eval`` and
``hours_above_P_bar``) are optional: files without them read back with NaN entries.
:meth:`History.load` checks that the files agree with each other (every series one entry per
month, the arrays of the first and last month present) and refuses them otherwise.
"""

from __future__ import annotations

import base64
import io
import json
import math
import zipfile
from collections import Counter
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .._util import jsonio
from .._util.stats import mean_ci
from ..config import LearningConfig, MPCConfig, SystemConfig, policy_class_of
from ..sim.record import RECORD_ARRAYS, MonthRecord, Record
from ..theta import PARTS, Theta
from . import rundir
from .outdir import RunDirError
from .rundir import RECOVER

__all__ = ["History"]


@dataclass(eq=False)
class History:
    """Per-month results of a learning run.

    Lists grow by one entry per month; ``theta`` holds the parameters *used* in each month
    and ``theta_final`` those after the last update.

    The evaluation series (:data:`EVAL_SERIES` and :data:`EVAL_CI_SERIES`) grow by one entry
    per evaluated month: ``eval_month[j]`` is the month whose parameters were evaluated on
    the ``K = LearningConfig.eval_draws`` fixed noise draws (no exploration; each draw a month
    of ``days_per_month`` days), ``J_eval[j]`` the mean over the draws of each draw's J,
    ``J_eval_ci_low[j]``, ``J_eval_ci_high[j]`` its 95 % Student-t confidence interval over
    the K draws (:func:`~mpcrl_lite._util.stats.mean_ci`; NaN for K = 1 and in files written before it existed),
    ``J_eval_per_agent[j]`` the per-agent J^i, ``eval_hours_soc_below_0_1[j]`` the
    agent-hours with soc < 0.1 per draw (mean over the draws), ``eval_max_P_mpc[j]`` the
    largest planned grid power and ``eval_bound_share[j]`` the share of actions within 0.05 of
    a constraint (:meth:`MonthRecord.bound_share`). Unlike ``J``, these are not disturbed by
    the month's own noise and exploration, so they show the learning trend.

    The grid limit: ``max_P_mpc[m]`` is the largest grid power the MPC *planned* in month
    ``m`` -- the paper's claim ``P <= P_bar`` is about these planned powers, which respect it
    by construction. The low-level controller may push the *applied* power above ``P_bar``
    (its corrections follow the noise, not the MPC): ``max_P_applied[m]`` is the largest
    applied grid power and ``hours_above_P_bar[m]`` the number of (hour, day) pairs whose
    applied power exceeds ``P_bar`` (:meth:`Record.hours_above_P_bar`).
    """

    system: SystemConfig
    mpc: MPCConfig
    learning: LearningConfig
    J: list[float] = field(default_factory=list)
    J_per_agent: list[list[float]] = field(default_factory=list)
    grad_norm: list[float] = field(default_factory=list)
    theta: list[list[float]] = field(default_factory=list)
    theta_final: list[float] = field(default_factory=list)
    hours_soc_below_0_1: list[int] = field(default_factory=list)
    hours_soc_above_0_9: list[int] = field(default_factory=list)
    max_P_mpc: list[float] = field(default_factory=list)
    max_P_applied: list[float] = field(default_factory=list)
    solver_failures: list[int] = field(default_factory=list)
    skipped_steps: list[int] = field(default_factory=list)
    low_level_interventions: list[int] = field(default_factory=list)
    wall_time_s: list[float] = field(default_factory=list)
    update_info: list[dict[str, Any]] = field(default_factory=list)
    eval_month: list[int] = field(default_factory=list)
    J_eval: list[float] = field(default_factory=list)
    J_eval_per_agent: list[list[float]] = field(default_factory=list)
    eval_hours_soc_below_0_1: list[int] = field(default_factory=list)
    eval_max_P_mpc: list[float] = field(default_factory=list)
    eval_bound_share: list[float] = field(default_factory=list)
    J_eval_ci_low: list[float] = field(default_factory=list)
    J_eval_ci_high: list[float] = field(default_factory=list)
    hours_above_P_bar: list[float] = field(default_factory=list)
    first_month: Record | None = None
    last_month: Record | None = None
    backend: str = ""
    prices_origin: dict[str, Any] = field(default_factory=dict)
    """Where the month's prices come from when read from a file (``Prices.origin``: file,
    format, area, month, currency, conversion rate); empty for the shipped month, and then
    not written, so such runs' files are as before (and files without it read back empty)."""

    SERIES = (
        "J", "J_per_agent", "grad_norm", "theta", "hours_soc_below_0_1",
        "hours_soc_above_0_9", "max_P_mpc", "max_P_applied", "solver_failures",
        "skipped_steps", "low_level_interventions", "wall_time_s", "update_info",
    )
    #: Series of the evaluation on fixed noise (absent from files of older versions).
    EVAL_SERIES = (
        "eval_month", "J_eval", "J_eval_per_agent", "eval_hours_soc_below_0_1",
        "eval_max_P_mpc", "eval_bound_share",
    )

    #: The confidence interval of ``J_eval`` over the evaluation draws (one per evaluation).
    EVAL_CI_SERIES = ("J_eval_ci_low", "J_eval_ci_high")
    #: Per-month series added after files existed (optional when reading).
    MONTH_LATER_SERIES = ("hours_above_P_bar",)
    #: Series a file may lack (older versions): read back as NaN entries.
    LATER_SERIES = EVAL_CI_SERIES + MONTH_LATER_SERIES

    #: Series holding numbers (possibly nested in lists): ``null`` in the file is NaN here.
    NUMBER_SERIES = (
        "J", "J_per_agent", "grad_norm", "theta", "max_P_mpc", "max_P_applied", "wall_time_s",
        "J_eval", "J_eval_per_agent", "eval_max_P_mpc", "eval_bound_share",
        "J_eval_ci_low", "J_eval_ci_high", "hours_above_P_bar",
    )
    #: Every series a file holds, in the order written.
    STORED_SERIES = SERIES + EVAL_SERIES + LATER_SERIES
    FORMAT = "mpcrl_lite.History/1"

    @property
    def months(self) -> int:
        """Number of months recorded."""
        return len(self.J)

    @property
    def policy_class(self) -> str | None:
        """The named policy class of the run's MPC (its horizon ``system.N`` and
        ``mpc.forecast``, :data:`mpcrl_lite.config.POLICY_CLASSES`), None if no class has them."""
        return policy_class_of(self.system, self.mpc)

    def failed_solve_share(self) -> float:
        """Share of the learning months' MPC solves (hours x days) that failed (0 without
        months)."""
        solves = self.months * self.system.hours_per_day * self.learning.days_per_month
        return float(sum(self.solver_failures)) / solves if solves else 0.0

    def append(
        self, record: Record, theta: Theta, grad: np.ndarray, skipped: int,
        wall_time: float, info: dict[str, Any],
    ) -> None:
        """Record one month (``theta`` is the parameter vector used during the month)."""
        s = record.summary()
        self.J.append(s["J"])
        self.J_per_agent.append(s["J_per_agent"])
        self.grad_norm.append(_norm(grad))
        self.theta.append(theta.to_vector().tolist())
        self.hours_soc_below_0_1.append(s["hours_soc_below_0_1"])
        self.hours_soc_above_0_9.append(s["hours_soc_above_0_9"])
        self.max_P_mpc.append(s["max_P_mpc"])
        self.max_P_applied.append(s["max_P_applied"])
        self.hours_above_P_bar.append(s["hours_above_P_bar"])
        self.solver_failures.append(s["solver_failures"])
        self.skipped_steps.append(int(skipped))
        self.low_level_interventions.append(s["low_level_interventions"])
        self.wall_time_s.append(float(wall_time))
        self.update_info.append(info)
        if self.first_month is None:
            self.first_month = record
        self.last_month = record

    def append_evaluation(self, month: int, record: Record, draws: int = 1) -> None:
        """Record the evaluation of month ``month``'s parameters: ``record`` holds ``draws``
        months on the fixed evaluation draws, stacked as ``draws * days`` days
        (:func:`mpcrl_lite.sim.closed_loop.evaluate_mpc`), without exploration."""
        if isinstance(month, bool) or not isinstance(month, (int, np.integer)) or month < 0:
            raise ValueError(f"month={month!r}: expected an integer >= 0")
        if isinstance(draws, bool) or not isinstance(draws, (int, np.integer)) or draws < 1 \
                or record.days % draws:
            raise ValueError(f"draws={draws!r}: expected an integer >= 1 dividing the "
                             f"record's {record.days} days")
        s = record.summary()
        per_draw = record.J_per_day().reshape(draws, -1).mean(axis=1)
        ci = mean_ci(per_draw)
        mean, low, high = ci.mean, ci.ci_low, ci.ci_high
        self.eval_month.append(int(month))
        self.J_eval.append(mean)
        self.J_eval_ci_low.append(low)
        self.J_eval_ci_high.append(high)
        self.J_eval_per_agent.append(s["J_per_agent"])
        below = s["hours_soc_below_0_1"]
        self.eval_hours_soc_below_0_1.append(below if draws == 1 else below / draws)
        self.eval_max_P_mpc.append(s["max_P_mpc"])
        self.eval_bound_share.append(record.bound_share())

    # -- views ----------------------------------------------------------------------------
    def theta_array(self) -> np.ndarray:
        """theta per month, shape (months, n_theta)."""
        return np.asarray(self.theta, dtype=float).reshape(len(self.theta), -1)

    def theta_part(self, part: str) -> np.ndarray:
        """One part of theta per month, shape (months + 1, n), the final value last."""
        n = self.system.n
        values = np.vstack([self.theta_array(), np.asarray(self.theta_final)[None, :]])
        return values[:, Theta.index(n, part)]

    def final_theta(self) -> Theta:
        """theta after the last update."""
        return Theta.from_vector(np.asarray(self.theta_final), self.system.n)

    def improvement(self) -> dict[str, Any] | None:
        """How the last evaluation compares with the first, on the same evaluation draws.

        ``J_eval[0]`` is the starting theta's (the run's first month; the nominal theta
        unless the run was given another); every evaluation uses the same noise draws
        (``LearningConfig.eval_seed``), so the difference is paired. Returns None without
        two evaluations, else ``{"J_eval_start", "J_eval_last", "change",
        "improved_on_start"}``: ``change`` is last minus start (negative: a lower cost) and
        ``improved_on_start`` says whether it is negative. A run that did not improve has
        learned nothing usable: with the paper's critic this happens on some seeds of some
        months (``benchmarks/README.md``, "Runs that never leave the start")."""
        if len(self.J_eval) < 2:
            return None
        start, last = float(self.J_eval[0]), float(self.J_eval[-1])
        return {"J_eval_start": start, "J_eval_last": last, "change": last - start,
                "improved_on_start": bool(last < start)}

    def summary(self) -> dict[str, Any]:
        """The JSON summary written next to a run (see the ``learn`` command)."""
        n = self.system.n
        improvement = self.improvement()
        return {
            "months": self.months,
            "J": self.J,
            "J_per_agent": self.J_per_agent,
            "grad_norm": self.grad_norm,
            "theta_final": self.final_theta().to_dict() if self.theta_final else {},
            "theta_names": Theta.names(n),
            "hours_soc_below_0_1": self.hours_soc_below_0_1,
            "hours_soc_above_0_9": self.hours_soc_above_0_9,
            "max_P_mpc": self.max_P_mpc,
            "max_P_applied": self.max_P_applied,
            "P_bar": self.system.P_bar,
            "hours_above_P_bar": self.hours_above_P_bar,
            "solver_failures": self.solver_failures,
            "skipped_steps": self.skipped_steps,
            "wall_time_s": self.wall_time_s,
            "backend": self.backend,
            **{k: getattr(self, k) for k in self.EVAL_SERIES + self.EVAL_CI_SERIES},
            **({"prices_origin": dict(self.prices_origin)} if self.prices_origin else {}),
            **({"improvement": improvement} if improvement is not None else {}),
        }

    # -- storage --------------------------------------------------------------------------
    def configs(self) -> dict[str, dict[str, Any]]:
        """The configurations as plain dicts (``system``, ``mpc``, ``learning``)."""
        return {"system": self.system.to_dict(), "mpc": self.mpc.to_dict(),
                "learning": self.learning.to_dict()}

    def series_lengths(self) -> dict[str, int]:
        """The length of every stored series (what :meth:`journal_record` continues from)."""
        return {k: len(getattr(self, k)) for k in self.STORED_SERIES}

    def journal_record(self, since: Mapping[str, int],
                       extra: Mapping[str, Any] | None = None) -> bytes:
        """One line of ``history.jsonl``: the entries of every series after ``since`` (as
        :meth:`series_lengths` gave it), ``theta_final``, ``backend``, the entries of
        ``extra`` (a learner's state, see :mod:`mpcrl_lite.learning.checkpoint`) and the
        last month's arrays (``last_month``: per array of
        :data:`~mpcrl_lite.sim.record.RECORD_ARRAYS` its ``dtype``, ``shape`` and the base64
        of its C-ordered bytes), as strict JSON.

        Read back by :meth:`from_files`, ``history.json`` and its journal give the same
        History as ``history.json`` and ``history.npz`` written whole (:meth:`to_files`):
        the journal's last line holds the last month, ``history.npz`` the first."""
        line, _ = self._journal_line(since, extra, inline=True)
        return line + b"\n"

    def journal_parts(self, since: Mapping[str, int], extra: Mapping[str, Any] | None = None
                      ) -> tuple[bytes, list[memoryview]]:
        """:meth:`journal_record` as a line and a payload (the run directory's appended
        months, :func:`~mpcrl_lite.learning.rundir.append_month`): the JSON record without its
        newline, whose ``last_month`` gives each array's ``dtype``, ``shape`` and ``offset``
        in the payload, and the payload, the arrays' bytes one after the other (not copied).
        :meth:`from_files` reads them back with the payload given."""
        return self._journal_line(since, extra, inline=False)

    def _journal_line(self, since: Mapping[str, int], extra: Mapping[str, Any] | None,
                      inline: bool) -> tuple[bytes, list[memoryview]]:
        """A journal line without its newline, the last month's arrays in it (``inline``)
        or in the payload returned."""
        record = {
            "months": self.months,
            "theta_final": self.theta_final,
            "backend": self.backend,
            "series": {k: getattr(self, k)[since[k]:] for k in self.STORED_SERIES},
            **(extra or {}),
        }
        line = jsonio.dumps(record, indent=None)
        if self.last_month is None:
            return line, []
        # spliced in: the arrays need no escaping, and json.dumps would scan them for it
        arrays, payload = _month_arrays(self.last_month, inline)
        return line[:-1] + b',"last_month":' + arrays + b"}", payload

    def npz_bytes(self, compress: bool = True) -> bytes:
        """The content of ``history.npz`` (the first and last month's arrays); ``compress=False``
        stores them as they are (a run's monthly commits: several times faster to write)."""
        arrays: dict[str, np.ndarray] = {}
        if self.first_month is not None:
            arrays.update(self.first_month.arrays("first"))
        if self.last_month is not None:
            arrays.update(self.last_month.arrays("last"))
        buffer = io.BytesIO()
        (np.savez_compressed if compress else np.savez)(buffer, **arrays)
        return buffer.getvalue()

    def to_files(self, compress: bool = True) -> dict[str, bytes]:
        """The contents of ``history.json`` and ``history.npz`` (see :meth:`npz_bytes` for
        ``compress``)."""
        meta = {
            "format": self.FORMAT,
            **self.configs(),
            "theta_final": self.theta_final,
            "backend": self.backend,
            **{k: getattr(self, k) for k in self.STORED_SERIES},
            **({"prices_origin": dict(self.prices_origin)} if self.prices_origin else {}),
        }
        return {rundir.HISTORY_JSON: jsonio.dumps_by_key(meta),
                rundir.HISTORY_NPZ: self.npz_bytes(compress)}

    def save(self, directory: str | Path) -> Path:
        """Write ``history.json`` and ``history.npz`` into ``directory`` as one commit
        (:func:`mpcrl_lite.learning.rundir.commit`, kind ``"history"``); returns the directory.

        A directory holding a learner's run is refused: the History would replace the one
        its checkpoint belongs to.
        """
        directory = Path(directory)
        found = rundir.inspect(directory)
        if rundir.CHECKPOINT in found.run_files:
            raise RunDirError(
                f"{directory} holds a learning run (checkpoint.json); saving a History there "
                "would detach the checkpoint: choose another directory"
            )
        learning = {k: v for k, v in self.learning.to_dict().items() if k != "months"}
        rundir.commit(
            directory, self.to_files(), kind="history", months_done=self.months,
            configs_hash=rundir.config_sha256({**self.configs(), "learning": learning}),
        )
        return directory

    @classmethod
    def load(cls, directory: str | Path) -> History:
        """Read a History written by :meth:`save` or by a learning run, verified.

        Raises
        ------
        FileNotFoundError
            No ``history.json`` (and no manifest) in ``directory``.
        ValueError
            (:class:`~mpcrl_lite.learning.outdir.RunDirError`) a file that does not verify, or files
            that disagree; the message names the file and the problem.
        """
        run = rundir.read(directory, [rundir.HISTORY_JSON, rundir.HISTORY_NPZ, rundir.JOURNAL],
                          optional=[rundir.HISTORY_NPZ, rundir.JOURNAL])
        history = cls.from_files(run.files, Path(directory), run.payload)
        if run.months_done is not None and run.months_done != history.months:
            raise RunDirError(
                f"{Path(directory) / rundir.MANIFEST} records {run.months_done} months but "
                f"history.json {history.months}; {RECOVER}"
            )
        return history

    @classmethod
    def from_files(cls, files: Mapping[str, bytes], directory: Path | str = ".",
                   payload: bytes = b"") -> History:
        """Inverse of :meth:`to_files` (with the journal ``history.jsonl`` of a run in
        progress, if ``files`` hold it, and the ``payload`` of its last line,
        :meth:`journal_parts`), checked: a :class:`~mpcrl_lite.learning.outdir.RunDirError`
        names the first problem found (``directory`` only names the files in messages)."""
        path = Path(directory) / rundir.HISTORY_JSON
        try:
            meta = json.loads(files[rundir.HISTORY_JSON])
        except ValueError as err:
            raise RunDirError(f"{path} is not valid JSON ({err}); {RECOVER}") from None
        if not isinstance(meta, dict):
            raise RunDirError(
                f"{path} holds a {type(meta).__name__}, expected an object; {RECOVER}")
        if meta.get("format") != cls.FORMAT:
            raise RunDirError(f"{path}: format {meta.get('format')!r}, expected {cls.FORMAT!r}")
        last_line: dict[str, Any] | None = None
        if files.get(rundir.JOURNAL):
            last_line = _merge_journal(meta, files[rundir.JOURNAL],
                                       Path(directory) / rundir.JOURNAL)
        missing = [k for k in ("system", "mpc", "learning", "theta_final", *cls.SERIES)
                   if k not in meta]
        if missing:
            raise RunDirError(f"{path} lacks {', '.join(map(repr, missing))}; {RECOVER}")
        try:
            system = SystemConfig.from_dict(meta["system"])
            mpc = MPCConfig.from_dict(meta["mpc"])
            learning = LearningConfig.from_dict(meta["learning"])
        except (TypeError, ValueError, AttributeError) as err:
            raise RunDirError(f"{path}: bad configuration ({err}); {RECOVER}") from None
        series = {k: meta[k] for k in cls.SERIES}
        series.update({k: meta.get(k, []) for k in cls.EVAL_SERIES})
        for key in cls.LATER_SERIES:
            like = "J" if key in cls.MONTH_LATER_SERIES else "J_eval"
            default = [None] * len(series[like]) if isinstance(series[like], list) else []
            series[key] = meta.get(key, default)
        _check_series(path, series, system.n)
        theta_final = meta["theta_final"]
        n_theta = len(PARTS) * system.n
        if not _numbers(theta_final, (n_theta,) if series["J"] else None):
            raise RunDirError(
                f"{path}: theta_final has {_length(theta_final)} entries, expected {n_theta}; "
                f"{RECOVER}")
        for key in cls.NUMBER_SERIES:
            series[key] = _nan_for_null(series[key])
        hist = cls(system=system, mpc=mpc, learning=learning,
                   theta_final=_nan_for_null(theta_final), backend=str(meta.get("backend", "")),
                   prices_origin=dict(meta.get("prices_origin") or {}), **series)
        hist._load_months(files.get(rundir.HISTORY_NPZ), Path(directory) / rundir.HISTORY_NPZ)
        if last_line is not None and "last_month" in last_line:
            where = Path(directory) / rundir.JOURNAL
            hist.last_month = hist._month_from_arrays(
                _arrays_from_json(last_line["last_month"], where, payload), "last", where)
        return hist

    def _load_months(self, data: bytes | None, path: Path) -> None:
        if data is None:
            if self.months:
                raise RunDirError(
                    f"{path} is missing but history.json records {self.months} months (the "
                    f"first and last month's trajectories are lost); {RECOVER}")
            return
        try:
            with np.load(io.BytesIO(data), allow_pickle=False) as npz:
                arrays = {k: npz[k] for k in npz.files}
        except (OSError, ValueError, zipfile.BadZipFile, EOFError) as err:
            raise RunDirError(f"{path} cannot be read ({err}); {RECOVER}") from None
        for prefix in ("first", "last"):
            if not any(f"{prefix}_{k}" in arrays for k in RECORD_ARRAYS):
                if self.months:
                    raise RunDirError(
                        f"{path} lacks the {prefix} month's arrays but history.json records "
                        f"{self.months} months; {RECOVER}")
                continue
            setattr(self, f"{prefix}_month", self._month_from_arrays(arrays, prefix, path))

    def _month_from_arrays(self, arrays: Mapping[str, np.ndarray], prefix: str,
                           path: Path) -> MonthRecord:
        """The month of ``arrays`` (keys ``{prefix}_soc`` ...), all of them there and of
        this History's shape, else a :class:`RunDirError` naming ``path``."""
        H, D, n = self.system.hours_per_day, self.learning.days_per_month, self.system.n
        names = [f"{prefix}_{k}" for k in RECORD_ARRAYS]
        if any(k not in arrays for k in names) or arrays[f"{prefix}_soc"].shape != (H + 1, D, n):
            raise RunDirError(
                f"{path}: the {prefix} month's arrays are incomplete or not of shape "
                f"({H + 1}, {D}, {n}); {RECOVER}")
        return MonthRecord.from_arrays(arrays, prefix, self.system)


def _norm(grad: np.ndarray) -> float:
    """Euclidean norm that does not overflow for entries beyond ~1e154 (the plain one
    squares them); equal to :func:`numpy.linalg.norm` wherever that one is finite."""
    grad = np.asarray(grad, dtype=float)
    with np.errstate(over="ignore"):
        value = float(np.linalg.norm(grad))
    if math.isinf(value) and np.all(np.isfinite(grad)):
        top = float(np.max(np.abs(grad)))
        value = top * float(np.linalg.norm(grad / top))
    return value


def _length(value: Any) -> Any:
    return len(value) if isinstance(value, list) else type(value).__name__


def _numbers(value: Any, shape: tuple[int, ...] | None) -> bool:
    """``value`` is a (nested) list of numbers or nulls of ``shape`` (any length if None)."""
    if shape is None:
        return isinstance(value, list)
    if not isinstance(value, list) or len(value) != shape[0]:
        return False
    if len(shape) == 1:
        return all(v is None or (isinstance(v, (int, float)) and not isinstance(v, bool))
                   for v in value)
    return all(_numbers(v, shape[1:]) for v in value)


def _check_series(path: Path, series: dict[str, Any], n: int) -> None:
    """Every series one entry per month (and per evaluation), entries of the right size."""
    def usual_length(keys: tuple[str, ...]) -> int:
        """The length most series share (a damaged one stands out against it)."""
        lengths = Counter(len(series[k]) for k in keys if isinstance(series[k], list))
        return lengths.most_common(1)[0][0] if lengths else -1

    months = usual_length(History.SERIES)
    evals = usual_length(History.EVAL_SERIES)
    eval_keys = History.EVAL_SERIES + History.EVAL_CI_SERIES
    n_theta = len(PARTS) * n
    shapes = {"J_per_agent": (n,), "theta": (n_theta,), "J_eval_per_agent": (n,)}
    for key, value in series.items():
        count = evals if key in eval_keys else months
        if not isinstance(value, list) or count < 0 or len(value) != count:
            raise RunDirError(
                f"{path}: series {key!r} has {_length(value)} entries, expected {count} "
                f"like the other series; {RECOVER}")
        if key in shapes:
            good = all(_numbers(v, shapes[key]) for v in value)
        elif key == "update_info":
            good = all(isinstance(v, dict) for v in value)
        else:
            good = _numbers(value, (count,))
        if not good:
            shape = f"lists of {shapes[key][0]} numbers" if key in shapes else (
                "objects" if key == "update_info" else "numbers")
            raise RunDirError(
                f"{path}: series {key!r} has entries that are not {shape}; {RECOVER}")
    eval_month = series["eval_month"]
    if any(isinstance(m, bool) or not isinstance(m, int) or not 0 <= m < months
           for m in eval_month):
        raise RunDirError(f"{path}: eval_month holds months outside 0..{months - 1}; {RECOVER}")


def _month_arrays(month: Record, inline: bool) -> tuple[bytes, list[memoryview]]:
    """A month's arrays as a journal line's ``last_month`` object: per array of
    :data:`~mpcrl_lite.sim.record.RECORD_ARRAYS` its ``dtype``, ``shape`` and either the base64
    of its C-ordered bytes (``data``, ``inline``) or their ``offset`` in the payload returned
    (the arrays' bytes one after the other, not copied)."""
    parts, payload, offset = [], [], 0
    for name in RECORD_ARRAYS:
        value = np.ascontiguousarray(getattr(month, name))
        if inline:
            where = b'"data":"%s"' % base64.b64encode(value.tobytes())
        else:
            where = b'"offset":%d' % offset
            payload.append(memoryview(value).cast("B"))
            offset += value.nbytes
        # the shape as json.dumps writes a list of ints ("[720, 3]"), without its call
        shape = ", ".join(map(str, value.shape))
        parts.append(b'"%s":{"dtype":"%s","shape":[%s],%s}' % (
            name.encode(), value.dtype.str.encode(), shape.encode(), where))
    return b"{" + b",".join(parts) + b"}", payload


#: The element types a journal's arrays may have (what :class:`Record` holds).
_JOURNAL_DTYPES = ("<f8", "|b1")


def _arrays_from_json(data: Any, path: Path, payload: bytes = b"") -> dict[str, np.ndarray]:
    """Inverse of :func:`_month_arrays` (each entry's ``data`` inline, or its ``offset`` in
    ``payload``; keys prefixed ``last_``), checked: a :class:`RunDirError` naming ``path`` for
    anything that is not such an object."""
    arrays: dict[str, np.ndarray] = {}
    for name in RECORD_ARRAYS:
        entry = data.get(name) if isinstance(data, dict) else None
        shape = entry.get("shape") if isinstance(entry, dict) else None
        offset = entry.get("offset") if isinstance(entry, dict) else None
        ok = (isinstance(entry, dict) and entry.get("dtype") in _JOURNAL_DTYPES
              and (isinstance(entry.get("data"), str) or _natural(offset))
              and isinstance(shape, list) and all(_natural(k) for k in shape))
        if ok:
            dtype = np.dtype(entry["dtype"])
            size = dtype.itemsize * math.prod(shape)
            if "data" in entry:
                try:
                    raw = base64.b64decode(entry["data"], validate=True)
                except ValueError:
                    ok = False
            else:
                raw = payload[offset:offset + size]
        if ok:
            ok = len(raw) == size
        if not ok:
            raise RunDirError(f"{path}: the last line's array {name!r} is malformed; {RECOVER}")
        arrays[f"last_{name}"] = np.frombuffer(raw, dtype=dtype).reshape(shape).copy()
    return arrays


def _natural(value: Any) -> bool:
    """An integer >= 0 (not a bool)."""
    return isinstance(value, int) and not isinstance(value, bool) and value >= 0


def _merge_journal(meta: dict[str, Any], data: bytes, path: Path) -> dict[str, Any] | None:
    """Add the journal's lines (:meth:`History.journal_record`) to ``history.json``'s
    ``meta``; the merged series are checked as a whole file's afterwards. Returns the last
    line (None if there is none)."""
    record: Any = None
    for number, line in enumerate(data.splitlines(), start=1):
        try:
            record = json.loads(line)
        except ValueError as err:
            raise RunDirError(f"{path}: line {number} is not valid JSON ({err}); {RECOVER}") \
                from None
        series = record.get("series") if isinstance(record, dict) else None
        if not isinstance(series, dict) or set(series) - set(History.STORED_SERIES) or any(
                not isinstance(v, list) or not isinstance(meta.get(k, []), list)
                for k, v in series.items()):
            raise RunDirError(f"{path}: line {number} is not a month record; {RECOVER}")
        for key, values in series.items():
            meta.setdefault(key, []).extend(values)
        meta["theta_final"] = record.get("theta_final")
        meta["backend"] = record.get("backend", meta.get("backend", ""))
        if record.get("months") != len(meta.get("J", [])):
            raise RunDirError(f"{path}: line {number} records {record.get('months')!r} months, "
                              f"the series before it {len(meta.get('J', []))}; {RECOVER}")
    return record


def _nan_for_null(value: Any) -> Any:
    if value is None:
        return math.nan
    if isinstance(value, list):
        return [_nan_for_null(v) for v in value]
    return value
