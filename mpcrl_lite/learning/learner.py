r"""What every learner shares: the learning step, the month loop, checkpoints and resume.

Both learners -- :class:`~mpcrl_lite.learning.experiment.Experiment` (one centralized MPC) and
:class:`~mpcrl_lite.decentralized.learner.DecentralizedExperiment` (one MPC and one learner per
battery) -- are a :class:`Learner`. A subclass simulates and updates one month
(:meth:`Learner.run_one_month`) and says what its state is (:meth:`Learner.learner_state`,
:meth:`Learner.restore_learner_state`); the base runs the months, writes a checkpoint after
each and resumes from one.

The learning step
-----------------
From a month of transitions (:class:`~mpcrl_lite.sim.record.MonthRecord`) the critic is the
compatible action-value function (paper, eqs. 12-13)

.. math::
   Q_w(s, a) = (a - \pi_\theta(s))^\top \nabla_\theta\pi_\theta(s)^\top w + V_v(s),

fitted by LSTD on the samples whose MPC and sensitivity were usable
(:func:`mpcrl_lite.learning.lstd.lstd_q`; every day is an episode, its last hour does not bootstrap),
and the policy gradient is :math:`\widehat{\nabla_\theta J} = \frac1M\sum
\nabla_\theta\pi_\theta(s)\nabla_\theta\pi_\theta(s)^\top w` (eq. 11,
:func:`mpcrl_lite.learning.dpg.policy_gradient`): :func:`lstd_policy_gradient`. The centralized learner
applies it to all batteries with the stage cost :math:`\tilde L`, the decentralized one to
each battery with its own cost :math:`\tilde L_i` and its own soc.

Checkpoints
-----------
After every month the run directory (:mod:`mpcrl_lite.learning.rundir`) gets one commit holding
``history.json``, ``history.npz`` and ``checkpoint.json``; the latter has ``format`` (the
learner's), ``months_done``, ``theta``, the optimizer state (``updater``, or ``updaters``
per battery), the generator state ``rng``, the configurations and ``prices``, a fingerprint of
the month's prices (:func:`prices_fingerprint`). :meth:`Learner.load_checkpoint` verifies
everything -- checksums, formats, the learner kind, months_done against the History and the
manifest, every series one entry per month, the configurations, the prices -- before changing
anything: a directory that does not verify is refused with one line, never half-resumed.
Checkpoints written before the price fingerprint existed resume without that check.

One thread of linear algebra
----------------------------
The month loop runs with the BLAS/LAPACK libraries limited to one thread
(``threadpoolctl``). The matrices of a month are small (tens to hundreds of rows), where
threads cost more than they bring, and a multi-threaded BLAS may sum in another order on a
machine with another number of cores or in a worker process that limits its threads (Dask
does): with one thread, a run gives the same numbers to the last bit in a notebook, under
``learn``, in a sweep's worker and on any machine with the same libraries.

Failed solves
-------------
Hours whose MPC failed act with the fallback (idle) and are left out of the learning step.
When more than :data:`MAX_FAILED_SOLVE_SHARE` of a month's solves fail, a warning is logged;
the ``learn`` command exits with status 2 when the whole run exceeds it.
"""

from __future__ import annotations

import hashlib
import json
import logging
from collections.abc import Callable
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
from threadpoolctl import threadpool_limits
from tqdm.auto import tqdm

from .._util import jsonio
from ..config import LearningConfig, MPCConfig, SystemConfig
from ..sim.record import MonthRecord
from ..system.forecast import forecast_of, forecast_prices
from ..system.prices import Prices
from ..theta import PARTS, Theta
from . import rundir
from .dpg import policy_gradient
from .history import History
from .lstd import compatible_features, lstd_q, value_baseline_features
from .rundir import RECOVER, RunDirError, RunDirMissing

__all__ = [
    "BLAS_THREADS",
    "MAX_FAILED_SOLVE_SHARE",
    "Learner",
    "close_month",
    "lstd_policy_gradient",
    "open_run",
    "parse_theta",
    "prices_fingerprint",
    "resolve_setup",
    "run_months",
]

log = logging.getLogger(__name__)

#: A month (and, for the ``learn`` command, a run) with a larger share of failed MPC solves
#: is reported: its learning signal comes from too few hours to be trusted.
MAX_FAILED_SOLVE_SHARE = 0.5

#: Threads the BLAS/LAPACK libraries may use inside the month loop (see the module
#: docstring): one, so that results do not depend on the machine's cores.
BLAS_THREADS = 1


def resolve_setup(
    system: SystemConfig | None,
    mpc_config: MPCConfig | None,
    learning: LearningConfig | None,
    prices: Prices | None,
    theta0: Theta | None,
) -> tuple[SystemConfig, MPCConfig, LearningConfig, Prices, Theta]:
    """Defaults and consistency checks shared by every learner: the paper's configs, the
    shipped month cut to ``days_per_month`` days, theta0 = the nominal model; prices with
    another number of days or a theta0 for another ``n`` are errors.

    The prices returned are those the MPC sees (:func:`mpcrl_lite.system.forecast.forecast_prices`
    of ``MPCConfig.forecast``); prices given already as
    :func:`~mpcrl_lite.system.forecast.until_midnight` set ``forecast='until_midnight'`` in the
    returned config, so that the run records what its MPC saw."""
    system = system or SystemConfig()
    mpc_config = mpc_config or MPCConfig()
    learning = learning or LearningConfig()
    if prices is None:
        prices = Prices.month(system, learning.days_per_month)
    if prices.days != learning.days_per_month:
        raise ValueError(
            f"prices have {prices.days} days; expected days_per_month={learning.days_per_month}"
        )
    if forecast_of(prices) != mpc_config.forecast and mpc_config.forecast == "paper":
        mpc_config = mpc_config.replace(forecast=forecast_of(prices))
    prices = forecast_prices(prices, mpc_config)
    theta0 = theta0 or Theta.nominal(system)
    if theta0.n != system.n:
        raise ValueError(f"theta0 has n={theta0.n}; expected n={system.n}")
    return system, mpc_config, learning, prices, theta0


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


def lstd_policy_gradient(
    soc: np.ndarray,
    a: np.ndarray,
    policy: np.ndarray,
    grad_pi: np.ndarray,
    cost: np.ndarray,
    use: np.ndarray,
    learning: LearningConfig,
    gamma: float,
) -> tuple[np.ndarray, dict[str, Any]]:
    """LSTD critic and policy gradient of one month (see the module docstring).

    Parameters
    ----------
    soc : (H+1, D, m)
        State of charge of the ``m`` batteries the policy acts for.
    a, policy : (H, D, m)
        Commanded action and the policy's action.
    grad_pi : (H, D, n_theta, m)
        :math:`\\nabla_\\theta\\pi_\\theta(s_k)`.
    cost : (H, D)
        Stage cost of the learner (all batteries', or one battery's own).
    use : (H, D) bool
        Samples whose MPC and sensitivity were usable.
    learning : LearningConfig
        ``value_features`` and ``ridge``.
    gamma : float

    Returns
    -------
    grad : (n_theta,)
        Zero when no sample is usable.
    info : dict
        ``lstd_condition``, ``lstd_rank_deficient``, ``td_rms``, ``samples`` (or
        ``{"lstd": "no usable samples"}``).
    """
    if not use.any():
        return np.zeros(grad_pi.shape[2]), {"lstd": "no usable samples"}
    H = cost.shape[0]
    features = value_baseline_features(soc, learning.value_features)
    phi, phi_next = features[:-1], features[1:]
    psi = compatible_features(grad_pi, a, policy)
    done = np.broadcast_to((np.arange(H) == H - 1)[:, None], use.shape)
    fit = lstd_q(
        phi[use], psi[use], cost[use], phi_next[use], gamma,
        done=done[use], ridge=learning.ridge,
    )
    grad = policy_gradient(grad_pi[use], fit.w)
    info = {
        "lstd_condition": float(fit.condition),
        "lstd_rank_deficient": bool(fit.rank_deficient),
        "td_rms": float(fit.td_rms),
        "samples": int(fit.n_samples),
    }
    return grad, info


def run_months(
    learner: Learner,
    months: int | None,
    out: str | Path | None,
    resume: bool,
    progress: bool,
    desc: str = "learning",
    force: bool = False,
) -> History:
    """The month loop of every learner.

    Runs until ``months`` months are recorded (default ``learning.months``). With ``out``
    every month is committed to that run directory; a directory that already holds a run
    is continued with ``resume`` (verified first, see :meth:`Learner.load_checkpoint`),
    replaced with ``force``, and refused otherwise. ``resume`` in a directory without a run
    starts one.
    """
    months = open_run(learner, months, out, resume, force)
    out = Path(out) if out is not None else None
    history = learner.history
    bar = tqdm(total=months, initial=min(history.months, months), desc=desc, unit="month",
               disable=not progress)
    with bar, threadpool_limits(limits=BLAS_THREADS):
        while learner.history.months < months:
            learner.run_one_month()
            history = learner.history
            postfix = {"J": f"{history.J[-1]:.1f}"}
            if history.J_eval:
                postfix["J_eval"] = f"{history.J_eval[-1]:.1f}"
            bar.set_postfix(postfix, refresh=False)
            bar.update(1)
            close_month(learner, out)
    return learner.history


def open_run(learner: Learner, months: int | None, out: str | Path | None, resume: bool,
             force: bool) -> int:
    """Check the arguments of :func:`run_months` and prepare ``out`` (resume, replace or
    refuse); returns the number of months to reach."""
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
        if resume and found.holds_run:
            learner.load_checkpoint(out)
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


def close_month(learner: Learner, out: Path | None) -> None:
    """What follows every month of :func:`run_months`: the warning on failed solves, the
    checkpoint in ``out`` and the learner's callbacks."""
    history = learner.history
    _warn_failed_solves(history)
    if out is not None:
        learner.save_checkpoint(out)
    for callback in learner.callbacks:
        callback(history.months - 1, history, learner)


def _warn_failed_solves(history: History) -> None:
    solves = history.system.hours_per_day * history.learning.days_per_month
    failed = history.solver_failures[-1]
    if failed > MAX_FAILED_SOLVE_SHARE * solves:
        log.warning(
            "month %d: %d of %d MPC solves failed (more than MAX_FAILED_SOLVE_SHARE=%g); "
            "those hours idle and are left out of the update",
            history.months - 1, failed, solves, MAX_FAILED_SOLVE_SHARE,
        )


class Learner:
    """Base of the learners: the month loop, checkpoints and resume.

    A subclass sets :attr:`KIND` (the manifest's learner kind), :attr:`FORMAT` (its
    ``checkpoint.json`` format), the attributes ``system``, ``mpc_config``, ``learning``,
    ``prices``, ``rng``, ``history`` and ``callbacks``, and implements
    :meth:`run_one_month`, :meth:`learner_state` and :meth:`restore_learner_state`.
    """

    KIND: ClassVar[str] = ""
    FORMAT: ClassVar[str] = ""
    DESC: ClassVar[str] = "learning"
    #: What ``checkpoint.json`` of a learner kind is called, to name the right learner.
    FORMATS: ClassVar[dict[str, str]] = {
        "mpcrl_lite.Checkpoint/1": "centralized",
        "mpcrl_lite.DecentralizedCheckpoint/1": "decentralized",
    }
    #: How each kind is resumed (for the message when the wrong learner is used).
    RESUME_WITH: ClassVar[dict[str, str]] = {
        "centralized": "Experiment, `learn` without --decentralized",
        "decentralized": "DecentralizedExperiment, `learn --decentralized`",
    }

    system: SystemConfig
    mpc_config: MPCConfig
    learning: LearningConfig
    prices: Prices
    rng: np.random.Generator
    history: History
    callbacks: list[Callable[..., None]]

    # -- what a subclass provides ---------------------------------------------------------
    def run_one_month(self) -> MonthRecord:
        """Simulate one month with the current parameters, update them, record the month."""
        raise NotImplementedError

    def learner_state(self) -> dict[str, Any]:
        """The learner's own part of ``checkpoint.json`` (theta and optimizer state)."""
        raise NotImplementedError

    def restore_learner_state(self, state: dict[str, Any], where: str) -> Callable[[], None]:
        """Check the learner's part of a checkpoint (raising :class:`RunDirError` naming
        ``where``) and return a function that applies it; nothing changes before that
        function is called."""
        raise NotImplementedError

    def configs(self) -> dict[str, Any]:
        """The configuration objects a checkpoint must match, by key."""
        return {"system": self.system, "mpc": self.mpc_config, "learning": self.learning}

    # -- the run --------------------------------------------------------------------------
    def run(
        self,
        months: int | None = None,
        out: str | Path | None = None,
        resume: bool = False,
        progress: bool = True,
        force: bool = False,
    ) -> History:
        """Run until ``months`` months are recorded (default ``learning.months``).

        With ``out`` each month is committed to that run directory; ``resume`` continues the
        run found there (same results as an uninterrupted run) and ``force`` replaces it;
        without either, a directory that holds a run is refused.
        """
        return run_months(self, months, out, resume, progress, desc=self.DESC, force=force)

    # -- checkpoints ----------------------------------------------------------------------
    def configs_hash(self) -> str:
        """sha256 of the configurations, ``learning.months`` left out (a resume may extend
        the run)."""
        return rundir.config_sha256(_plain_configs(self.configs()))

    def checkpoint_state(self) -> dict[str, Any]:
        """The content of ``checkpoint.json``."""
        return {
            "format": self.FORMAT,
            "months_done": self.history.months,
            **self.learner_state(),
            "rng": self.rng.bit_generator.state,
            **{key: cfg.to_dict() for key, cfg in self.configs().items()},
            "prices": prices_fingerprint(self.prices),
        }

    def save_checkpoint(self, directory: str | Path) -> None:
        """Commit the History and the checkpoint to ``directory`` (one atomic commit)."""
        files = self.history.to_files()
        files[rundir.CHECKPOINT] = jsonio.dumps(self.checkpoint_state())
        rundir.commit(directory, files, kind=self.KIND, months_done=self.history.months,
                      configs_hash=self.configs_hash())

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
        run = rundir.read(directory, [rundir.HISTORY_JSON, rundir.HISTORY_NPZ, rundir.CHECKPOINT],
                          optional=[rundir.HISTORY_NPZ, rundir.CHECKPOINT])
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
        saved = self._check_configs(state, directory, where)
        self._check_prices(state.get("prices"), directory, where)
        history = History.from_files(run.files, directory)
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
        # everything verified: from here on nothing can fail half-way
        if run.manifest is not None:
            rundir.read(directory, list(run.manifest["files"]), repair=True)
        self.history = history
        self.rng.bit_generator.state = rng.bit_generator.state
        apply()

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
