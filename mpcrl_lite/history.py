"""Results of a learning run as data: per-month figures and two months of trajectories.

A :class:`History` is saved as two plain files, never as pickle:

* ``history.json`` -- the configurations, theta's entry names, and every per-month scalar
  series (human-readable), including the evaluation series (``J_eval`` and friends: the
  parameters of a month evaluated on one fixed noise draw without exploration, see
  :meth:`mpcrl_lite.experiment.Experiment.evaluate`);
* ``history.npz`` -- the arrays (theta per month, J per agent, and the full trajectories of
  the first and last month), loaded with ``allow_pickle=False``.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .config import LearningConfig, MPCConfig, SystemConfig
from .record import MONTH_ARRAYS, MonthRecord, Record
from .theta import Theta

# MonthRecord and MONTH_ARRAYS live in mpcrl_lite.record; they stay importable from here.
__all__ = ["MONTH_ARRAYS", "History", "MonthRecord"]


@dataclass(eq=False)
class History:
    """Per-month results of a learning run.

    Lists grow by one entry per month; ``theta`` holds the parameters *used* in each month
    and ``theta_final`` those after the last update.

    The evaluation series (:data:`EVAL_SERIES`) grow by one entry per evaluated month:
    ``eval_month[j]`` is the month whose parameters were evaluated, ``J_eval[j]`` their J on
    the fixed evaluation draw (no exploration), ``J_eval_per_agent[j]`` the per-agent J^i,
    ``eval_hours_soc_below_0_1[j]`` the agent-hours with soc < 0.1, ``eval_max_P_mpc[j]`` the
    largest planned grid power and ``eval_bound_share[j]`` the share of actions within 0.05 of
    a constraint (:meth:`MonthRecord.bound_share`). Unlike ``J``, these are not disturbed by
    the month's own noise and exploration, so they show the learning trend.
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
    first_month: Record | None = None
    last_month: Record | None = None
    backend: str = ""

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

    @property
    def months(self) -> int:
        """Number of months recorded."""
        return len(self.J)

    def append(
        self, record: Record, theta: Theta, grad: np.ndarray, skipped: int,
        wall_time: float, info: dict[str, Any],
    ) -> None:
        """Record one month (``theta`` is the parameter vector used during the month)."""
        s = record.summary()
        self.J.append(s["J"])
        self.J_per_agent.append(s["J_per_agent"])
        self.grad_norm.append(float(np.linalg.norm(grad)))
        self.theta.append(theta.to_vector().tolist())
        self.hours_soc_below_0_1.append(s["hours_soc_below_0_1"])
        self.hours_soc_above_0_9.append(s["hours_soc_above_0_9"])
        self.max_P_mpc.append(s["max_P_mpc"])
        self.max_P_applied.append(s["max_P_applied"])
        self.solver_failures.append(s["solver_failures"])
        self.skipped_steps.append(int(skipped))
        self.low_level_interventions.append(s["low_level_interventions"])
        self.wall_time_s.append(float(wall_time))
        self.update_info.append(info)
        if self.first_month is None:
            self.first_month = record
        self.last_month = record

    def append_evaluation(self, month: int, record: Record) -> None:
        """Record the evaluation of month ``month``'s parameters (a month on the fixed
        evaluation draw, without exploration)."""
        if isinstance(month, bool) or not isinstance(month, (int, np.integer)) or month < 0:
            raise ValueError(f"month={month!r}: expected an integer >= 0")
        s = record.summary()
        self.eval_month.append(int(month))
        self.J_eval.append(s["J"])
        self.J_eval_per_agent.append(s["J_per_agent"])
        self.eval_hours_soc_below_0_1.append(s["hours_soc_below_0_1"])
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

    def summary(self) -> dict[str, Any]:
        """The JSON summary written next to a run (see the ``learn`` command)."""
        n = self.system.n
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
            "solver_failures": self.solver_failures,
            "skipped_steps": self.skipped_steps,
            "wall_time_s": self.wall_time_s,
            "backend": self.backend,
            **{k: getattr(self, k) for k in self.EVAL_SERIES},
        }

    # -- storage --------------------------------------------------------------------------
    def save(self, directory: str | Path) -> Path:
        """Write ``history.json`` and ``history.npz`` into ``directory`` (atomically)."""
        directory = Path(directory)
        directory.mkdir(parents=True, exist_ok=True)
        meta = {
            "format": "mpcrl_lite.History/1",
            "system": self.system.to_dict(),
            "mpc": self.mpc.to_dict(),
            "learning": self.learning.to_dict(),
            "theta_final": self.theta_final,
            "backend": self.backend,
            **{k: getattr(self, k) for k in self.SERIES + self.EVAL_SERIES},
        }
        arrays: dict[str, np.ndarray] = {}
        if self.first_month is not None:
            arrays.update(self.first_month.arrays("first"))
        if self.last_month is not None:
            arrays.update(self.last_month.arrays("last"))
        tmp_json = directory / "history.json.tmp"
        tmp_npz = directory / "history.tmp.npz"
        tmp_json.write_text(json.dumps(meta, indent=1))
        np.savez_compressed(tmp_npz, **arrays)
        tmp_npz.replace(directory / "history.npz")
        tmp_json.replace(directory / "history.json")
        return directory

    @classmethod
    def load(cls, directory: str | Path) -> History:
        """Read a History written by :meth:`save`."""
        directory = Path(directory)
        path = directory / "history.json"
        if not path.exists():
            raise FileNotFoundError(f"{path} not found: expected a directory written by History.save")
        meta = json.loads(path.read_text())
        if meta.get("format") != "mpcrl_lite.History/1":
            raise ValueError(f"{path}: format {meta.get('format')!r}, expected 'mpcrl_lite.History/1'")
        system = SystemConfig.from_dict(meta["system"])
        hist = cls(
            system=system,
            mpc=MPCConfig.from_dict(meta["mpc"]),
            learning=LearningConfig.from_dict(meta["learning"]),
            theta_final=meta["theta_final"],
            backend=meta.get("backend", ""),
            **{k: meta[k] for k in cls.SERIES},
            **{k: meta.get(k, []) for k in cls.EVAL_SERIES},
        )
        npz = directory / "history.npz"
        if npz.exists():
            with np.load(npz, allow_pickle=False) as data:
                if "first_soc" in data:
                    hist.first_month = MonthRecord.from_arrays(data, "first", system)
                if "last_soc" in data:
                    hist.last_month = MonthRecord.from_arrays(data, "last", system)
        return hist
