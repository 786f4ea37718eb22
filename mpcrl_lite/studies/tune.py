r"""The best theta of a policy class: a derivative-free search on common random numbers.

How good can the MPC of a class be (the paper's, or one with another forecast) with the best
parameters it holds? :func:`tune` answers it with CMA-ES (the ``cma`` package: N. Hansen's
covariance matrix adaptation evolution strategy) over the parts of theta that change the
policy, and so separates the two halves of a learned policy's regret
``J_learned - J* = (J_learned - J_class) + (J_class - J*)``: what the learner misses and what
the class cannot do.

The search
----------
* **Space.** The parts :data:`SEARCH_PARTS` of theta (``phi3`` and ``T3`` are constants of
  the MPC's cost and do not change its action), tied over the batteries by default (one value
  per part, like ``LearningConfig.tie_agents``: 8 coordinates) or per battery (``tied=False``:
  ``8 n``). A coordinate ``z`` is theta's deviation from the nominal ``theta0`` in units of
  :data:`SCALES` (the size of the changes a learning run makes), so one step of CMA-ES's
  initial ``sigma0 = 1`` is a plausible change of every part. ``phi1`` and ``T1`` stay ``>= 0``
  (CMA-ES's own bound handling, and the map clips them), so every MPC is a convex QP.
* **Selection on train draws.** Each generation's candidates are evaluated in **one**
  batched closed loop (:func:`mpcrl_lite.sim.candidates.evaluate_candidates`: one solver call
  per hour for every candidate, draw and day) on the same ``draws`` noise draws of ``seed``
  (common random numbers: the objective is deterministic, differences between candidates are
  paired). CMA-ES minimises the mean J over those draws. ``theta_best`` is the best candidate
  evaluated, ``J_best`` its train mean (``J_best_search`` the search's own figure of it).
  The search's MPCs stop at the KKT tolerance :attr:`TuneSettings.search_tol` without the
  polishing step (about 1.5x fewer Newton iterations near the class's best; a candidate's J
  moves by about 0.1 NOK/day); ``J_best`` and the held-out judgement are solved
  exactly, as the class's ``mpc_config`` says.
* **Judgement on held-out draws.** ``theta_best`` (and the nominal theta, for reference) are
  evaluated on ``heldout_draws`` draws of ``LearningConfig().eval_seed`` (the draws of a learning
  run's ``J_eval``, so a learned theta and the class's best are compared on the same noise),
  none of which the search saw: the train seed must differ from it. ``J_heldout`` is their
  mean with a 95 % Student-t interval (:func:`mpcrl_lite._util.stats.mean_ci`). Selecting the best
  of many candidates on few draws flatters ``J_best``; the held-out figure does not.
* **Resumable.** After every generation the search's whole state (the CMA-ES object, numpy's
  global generator that CMA-ES draws from, the log) is written atomically to
  ``tune_state.pkl`` (:func:`mpcrl_lite.learning.durable.write_atomic`); ``resume=True`` continues
  from it exactly (the same candidates as an uninterrupted search) and refuses, in one line, a
  state whose settings differ. ``evals`` may grow on a resume. The file is a Python pickle: load
  only states you wrote.
* **Workers.** ``workers > 1`` splits each generation's candidates over that many processes
  (each evaluates its share in one batched loop); the J of a candidate depends only on its own
  rows, so results do not depend on the number of workers.

Outputs in ``out``: ``tune.json`` (:func:`tune`'s result), ``tune.png`` (convergence: best and
median train J per generation against the evaluations, the held-out interval) and
``tune_state.pkl``.
"""

from __future__ import annotations

import hashlib
import math
import os
import pickle
import time
from collections.abc import Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from .._util.stats import mean_ci
from .._util.validate import check_instance, check_int, check_real
from .._util.workers import end_with_parent
from ..config import LearningConfig, MPCConfig, SystemConfig, policy_class_of
from ..learning import durable, outdir
from ..mpc.backends.registry import make_solver
from ..mpc.formulation import MPC
from ..sim.candidates import evaluate_candidates
from ..system.prices import Prices
from ..theta import Theta

__all__ = ["NONNEGATIVE", "OUTPUTS", "SCALES", "SEARCH_PARTS", "SEARCH_TOL", "SEARCH_TOL_MAX",
           "Space", "TuneSettings", "plot_convergence", "tune"]

#: The parts of theta the search moves (``phi3``, ``T3`` are constants of the cost).
SEARCH_PARTS: tuple[str, ...] = ("alpha", "delta", "b", "s", "phi1", "phi2", "T1", "T2")
#: One unit of a search coordinate per part: about the change a learning run makes to it.
SCALES: dict[str, float] = {"alpha": 0.02, "delta": 0.01, "b": 2.0, "s": 2.0,
                            "phi1": 20.0, "phi2": 20.0, "T1": 30.0, "T2": 30.0}
#: Parts kept >= 0 (the MPC stays a convex QP).
NONNEGATIVE: tuple[str, ...] = ("phi1", "T1")
#: The files :func:`tune` writes.
OUTPUTS: tuple[str, ...] = ("tune.json", "tune.png", "tune_state.pkl")
_STATE = "tune_state.pkl"
_FORMAT = 1
#: The default :attr:`TuneSettings.search_tol` (1e-6 until 2026-12-07; see
#: ``benchmarks/README.md``, "The search's tolerance, 1e-4").
SEARCH_TOL = 1e-4
#: The loosest :attr:`TuneSettings.search_tol` accepted.
SEARCH_TOL_MAX = 1e-3


@dataclass(frozen=True)
class TuneSettings:
    """What a search does (every default here, once).

    evals
        Candidate evaluations (each on ``draws`` draws); the search stops after the first
        whole generation that reaches them.
    draws
        Train noise draws (selection), ``0 .. draws - 1`` of ``seed``.
    heldout_draws
        Held-out draws judging the result, ``0 .. heldout_draws - 1`` of
        ``LearningConfig().eval_seed``.
    seed
        The train draws' seed; CMA-ES's generator is seeded with ``seed + 1`` (``cma`` takes 0
        as "seed from the clock").
    tied
        One value per part for all batteries (default), else one per battery.
    sigma0
        CMA-ES's initial step, in units of :data:`SCALES`.
    popsize
        Candidates per generation (None: CMA-ES's default ``4 + floor(3 ln dim)``).
    search_tol
        How exactly the search's candidates are solved. A tolerance (default
        :data:`SEARCH_TOL`): the MPCs of the search stop as soon as their scaled KKT residual
        is at most ``search_tol`` (at most :data:`SEARCH_TOL_MAX`), without the polishing
        step (``MPCConfig.polish``): about 5.4 Newton iterations instead of 7.9 near the
        class's best, with a candidate's J within about 0.1 NOK/day of the exact solves'
        (``benchmarks/README.md``), far inside the train draws' spread (a standard error of
        about 7) and the held-out interval that judges the result.
        ``theta_best``'s ``J_best`` and the held-out judgement are always solved as
        ``mpc_config`` says. None: the search solves as ``mpc_config`` says too.
    """

    evals: int = 2500
    draws: int = 6
    heldout_draws: int = 30
    seed: int = 0
    tied: bool = True
    sigma0: float = 1.0
    popsize: int | None = None
    search_tol: float | None = SEARCH_TOL

    def __post_init__(self) -> None:
        check_int("evals", self.evals, 1)
        check_int("draws", self.draws, 1)
        check_int("heldout_draws", self.heldout_draws, 2)
        check_int("seed", self.seed, 0)
        check_instance("tied", self.tied, bool)
        check_real("sigma0", self.sigma0, 0.0, low_open=True)
        if self.popsize is not None:
            check_int("popsize", self.popsize, 2)
        if self.search_tol is not None:
            check_real("search_tol", self.search_tol, 0.0, SEARCH_TOL_MAX, low_open=True)
        if self.seed == LearningConfig().eval_seed:
            raise ValueError(f"seed={self.seed}: it is the held-out draws' seed "
                             "(LearningConfig().eval_seed); expected another seed for the "
                             "train draws")

    def search_config(self, mpc_config: MPCConfig) -> MPCConfig:
        """The MPC settings of the search's candidates (see :attr:`search_tol`)."""
        if self.search_tol is None:
            return mpc_config
        return mpc_config.replace(polish=False, tol=max(self.search_tol, mpc_config.tol))


class Space:
    """The search coordinates ``z`` and the thetas they stand for.

    ``theta = theta0 + SCALES * z`` part by part (one ``z`` per part when ``tied``, one per
    part and battery otherwise), ``phi1, T1`` clipped at 0; the other parts of theta are
    ``theta0``'s.
    """

    def __init__(self, theta0: Theta, tied: bool = True) -> None:
        check_instance("theta0", theta0, Theta)
        self.theta0, self.tied, self.n = theta0, tied, theta0.n
        width = 1 if tied else self.n
        self.dim = width * len(SEARCH_PARTS)
        self._parts = [(name, slice(i * width, (i + 1) * width))
                       for i, name in enumerate(SEARCH_PARTS)]
        base = {name: getattr(theta0, name) for name in SEARCH_PARTS}
        self.z0 = np.zeros(self.dim)  # theta0
        lower = np.full(self.dim, -np.inf)
        for name, sl in self._parts:
            if name in NONNEGATIVE:
                lower[sl] = -np.min(base[name]) / SCALES[name]
        self.lower = lower

    def theta(self, z: np.ndarray) -> Theta:
        """The theta of the coordinates ``z`` (dim,)."""
        z = np.asarray(z, dtype=float).reshape(self.dim)
        parts = {}
        for name, sl in self._parts:
            value = getattr(self.theta0, name) + SCALES[name] * z[sl]
            parts[name] = np.maximum(value, 0.0) if name in NONNEGATIVE else value
        return self.theta0.replace(**parts)

    def thetas(self, Z: Sequence[np.ndarray]) -> list[Theta]:
        return [self.theta(z) for z in Z]


# -- evaluation in this process or in workers ------------------------------------------------
_WORKER: dict[str, Any] = {}


def _worker_init(system: SystemConfig, mpc_configs: tuple[MPCConfig, ...],
                 prices: Prices) -> None:
    end_with_parent()  # in a pool's worker: a search killed outright leaves none behind
    mpc = MPC(system)
    built: dict[MPCConfig, Any] = {}  # one solver per distinct config (an exact search: one)
    for config in mpc_configs:
        if config not in built:
            built[config] = make_solver(mpc, config)
    _WORKER.update(system=system, mpc_configs=mpc_configs, prices=prices,
                   solvers=[built[c] for c in mpc_configs])


def _worker_eval(vectors: np.ndarray, seed: int, draws: list[int],
                 which: int) -> tuple[np.ndarray, float]:
    t0 = time.process_time()
    w = _WORKER
    J = evaluate_candidates(vectors, w["system"], w["mpc_configs"][which], w["prices"], seed,
                            draws, solver=w["solvers"][which])
    return J, time.process_time() - t0


class _Evaluator:
    """``J (K, M)`` of candidate thetas, in this process or split over ``workers``, solved
    with one of ``mpc_configs`` (``which``: its index)."""

    def __init__(self, system: SystemConfig, mpc_configs: tuple[MPCConfig, ...],
                 prices: Prices, workers: int) -> None:
        self.workers = workers
        self.worker_cpu = 0.0
        _worker_init(system, mpc_configs, prices)
        self.pool = None
        if workers > 1:
            self.pool = ProcessPoolExecutor(workers, initializer=_worker_init,
                                            initargs=(system, mpc_configs, prices))

    def __call__(self, thetas: list[Theta], seed: int, draws: list[int],
                 which: int = 0) -> np.ndarray:
        vectors = np.stack([t.to_vector() for t in thetas])
        if self.pool is None or len(thetas) < 2:
            return _worker_eval(vectors, seed, draws, which)[0]
        chunks = [c for c in np.array_split(vectors, self.workers) if len(c)]
        futures = [self.pool.submit(_worker_eval, c, seed, draws, which) for c in chunks]
        out = [f.result() for f in futures]
        self.worker_cpu += sum(cpu for _, cpu in out)
        return np.concatenate([J for J, _ in out])

    def close(self) -> None:
        if self.pool is not None:
            self.pool.shutdown()


# -- the search -------------------------------------------------------------------------------
def _key(settings: TuneSettings, system: SystemConfig, mpc_config: MPCConfig,
         prices: Prices, theta0: Theta) -> dict[str, Any]:
    """What a resumed search must share with the saved one (``evals`` may grow)."""
    s = asdict(settings)
    s.pop("evals")
    return {
        "format": _FORMAT,
        "settings": s,
        "system": system.to_dict(),
        "mpc": mpc_config.to_dict(),
        "prices": hashlib.sha256(np.ascontiguousarray(prices.buy).tobytes()
                                 + repr(prices.sell_ratio).encode()).hexdigest()[:16],
        "theta0": theta0.to_dict(),
    }


def _mismatch(saved: dict[str, Any], now: dict[str, Any]) -> str | None:
    for group, b in now.items():
        a = saved.get(group)
        if a == b:
            continue
        if isinstance(a, dict) and isinstance(b, dict):
            for name in sorted(set(a) | set(b)):
                if a.get(name) != b.get(name):
                    return f"{group}.{name} is {a.get(name)!r} in the saved search, {b.get(name)!r} now"
        return f"{group} differs from the saved search's"
    return None


def tune(
    out: str | os.PathLike,
    settings: TuneSettings | None = None,
    *,
    system: SystemConfig | None = None,
    mpc_config: MPCConfig | None = None,
    prices: Prices | None = None,
    theta0: Theta | None = None,
    resume: bool = False,
    workers: int = 1,
    progress: bool = True,
    figure: bool = True,
) -> dict[str, Any]:
    """Search the best theta of the policy class of ``mpc_config`` (see the module docstring).

    Parameters
    ----------
    out
        Output directory (created; :data:`OUTPUTS` are written there).
    settings
        The search (:class:`TuneSettings`; default the paper-sized one, 2,500 evaluations on
        6 draws, judged on 30).
    system, mpc_config, prices
        The class: true system and MPC model, the MPC's settings (its ``forecast`` names the
        class), the month (default the shipped month, ``LearningConfig().days_per_month`` days).
    theta0
        Where the search starts (default the nominal theta).
    resume
        Continue the search saved in ``out`` (refused if its settings differ; a new search if
        there is none).
    workers
        Processes evaluating each generation (1: this one).
    progress, figure
        A tqdm progress bar; ``tune.png``.

    Returns
    -------
    dict
        What ``tune.json`` holds: ``J_best`` (train mean of ``theta_best``), ``J_heldout``
        (``{"mean", "ci_low", "ci_high", "draws", "std"}``), ``theta_best`` (parts),
        ``evals``, ``generations``, ``J_nominal_heldout``, the settings, the class and
        timings (``search_wall_time_s``, ``search_cpu_time_s`` with the workers' CPU,
        ``heldout_wall_time_s``, ``heldout_cpu_time_s``).
    """
    import cma  # heavy imports only where used (the CLI builds its parser from
    from tqdm.auto import tqdm  # TuneSettings without them)

    settings = settings or TuneSettings()
    check_instance("settings", settings, TuneSettings)
    system = system or SystemConfig()
    mpc_config = mpc_config or MPCConfig()
    check_instance("system", system, SystemConfig)
    check_instance("mpc_config", mpc_config, MPCConfig)
    prices = prices or Prices.month(system, LearningConfig().days_per_month)
    check_instance("prices", prices, Prices)
    theta0 = theta0 or Theta.nominal(system)
    if theta0.n != system.n:
        raise ValueError(f"theta0 has n={theta0.n}; expected n={system.n}")
    workers = check_int("workers", workers, 1)
    out = outdir.check_output_dir(outdir.refuse_empty(out))
    with outdir.lock_output_dir(out, "tune"):  # one process at a time in out
        space = Space(theta0, settings.tied)
        key = _key(settings, system, mpc_config, prices, theta0)
        state_path = out / _STATE
        train = list(range(settings.draws))
        heldout_seed = LearningConfig().eval_seed
        heldout = list(range(settings.heldout_draws))

        state: dict[str, Any] | None = None
        if resume and state_path.exists():
            try:
                state = pickle.loads(state_path.read_bytes())
            except Exception as err:  # noqa: BLE001 - any unreadable state is one message
                raise ValueError(f"{state_path}: not a readable tune state ({err}); use another "
                                 "--out or start anew without --resume") from None
            why = _mismatch(state.get("key", {}), key)
            if why:
                raise ValueError(f"cannot resume the search in {out}: {why}; use the same settings "
                                 "or another --out")
            np.random.set_state(state["np_random"])
            es = state["es"]
        else:
            opts = {"seed": settings.seed + 1, "verbose": -9,
                    "bounds": [list(space.lower), None], "CMA_diagonal": False}
            if settings.popsize is not None:
                opts["popsize"] = settings.popsize
            es = cma.CMAEvolutionStrategy(space.z0, settings.sigma0, opts)
            state = {"key": key, "log": [], "best_J": math.inf, "best_z": None,
                     "evals": 0, "wall": 0.0, "cpu": 0.0, "worker_cpu": 0.0}

        # the search's solves (index 0) and the judgement's (index 1, as mpc_config says)
        search_config = settings.search_config(mpc_config)
        evaluate = _Evaluator(system, (search_config, mpc_config), prices, workers)
        bar = tqdm(total=settings.evals, initial=min(state["evals"], settings.evals),
                   desc="tune", unit="eval", disable=not progress)
        try:
            while state["evals"] < settings.evals:
                t_wall, t_cpu, w_cpu = time.perf_counter(), time.process_time(), evaluate.worker_cpu
                Z = es.ask()
                J = evaluate(space.thetas(Z), settings.seed, train).mean(axis=1)
                es.tell(Z, J.tolist())
                i = int(np.argmin(J))
                if J[i] < state["best_J"]:
                    state["best_J"], state["best_z"] = float(J[i]), np.asarray(Z[i], float).copy()
                state["evals"] += len(Z)
                state["log"].append({"generation": len(state["log"]) + 1, "evals": state["evals"],
                                     "J_min": float(J.min()), "J_median": float(np.median(J)),
                                     "J_best": state["best_J"], "sigma": float(es.sigma)})
                state["wall"] += time.perf_counter() - t_wall
                state["cpu"] += time.process_time() - t_cpu
                state["worker_cpu"] += evaluate.worker_cpu - w_cpu
                state["es"], state["np_random"] = es, np.random.get_state()
                durable.write_atomic(state_path, pickle.dumps(state))
                bar.set_postfix(J_best=f"{state['best_J']:.1f}", refresh=False)
                bar.update(min(len(Z), settings.evals - bar.n))
            bar.close()
            theta_best = space.theta(state["best_z"])
            t_wall, t_cpu, w_cpu = time.perf_counter(), time.process_time(), evaluate.worker_cpu
            J_held = evaluate([theta_best, theta0], heldout_seed, heldout, which=1)
            # J_best: theta_best's train mean, solved as the judgement is
            J_best = (state["best_J"] if search_config is mpc_config
                      else float(evaluate([theta_best], settings.seed, train, which=1)[0].mean()))
            held_wall = time.perf_counter() - t_wall
            held_cpu = time.process_time() - t_cpu + evaluate.worker_cpu - w_cpu
        finally:
            evaluate.close()

        best_ci, nominal_ci = mean_ci(J_held[0]), mean_ci(J_held[1])
        result = {
            "J_best": J_best,
            "J_best_search": state["best_J"],
            "J_heldout": best_ci.as_dict(),
            "J_nominal_heldout": nominal_ci.as_dict(),
            "theta_best": theta_best.to_dict(),
            "evals": state["evals"],
            "generations": len(state["log"]),
            "popsize": int(es.popsize),
            "dim": space.dim,
            "train": {"seed": settings.seed, "draws": train},
            "heldout": {"seed": heldout_seed, "draws": heldout},
            "settings": asdict(settings),
            "system": system.to_dict(),
            "mpc": mpc_config.to_dict(),
            "search_mpc": search_config.to_dict(),
            "forecast": mpc_config.forecast,
            "policy_class": policy_class_of(system, mpc_config),
            "prices": prices.source,
            "days": prices.days,
            "workers": workers,
            "search_wall_time_s": state["wall"],
            "search_cpu_time_s": state["cpu"] + state["worker_cpu"],
            "heldout_wall_time_s": held_wall,
            "heldout_cpu_time_s": held_cpu,
            "log": state["log"],
        }
        durable.write_json(out / "tune.json", result)
        if figure:
            plot_convergence(result, out / "tune.png")
        return result


def plot_convergence(result: dict[str, Any], path: str | os.PathLike) -> Path:
    """``tune.png``: the best and the median train J of each generation against the
    evaluations, and the held-out mean with its 95 % interval (nominal theta for reference)."""
    import matplotlib.pyplot as plt

    log = result["log"]
    evals = [r["evals"] for r in log]
    fig, ax = plt.subplots(figsize=(7.0, 4.0))
    try:
        ax.plot(evals, [r["J_median"] for r in log], color="0.6", lw=1,
                label="generation median (train)")
        ax.plot(evals, [r["J_best"] for r in log], color="C0", lw=2, label="best so far (train)")
        held, nom = result["J_heldout"], result["J_nominal_heldout"]
        ax.axhline(held["mean"], color="C1", lw=1.5,
                   label=f"best theta, held-out ({held['draws']} draws): {held['mean']:.1f}")
        if held["ci_low"] is not None:
            ax.axhspan(held["ci_low"], held["ci_high"], color="C1", alpha=0.2)
        ax.axhline(nom["mean"], color="C3", ls="--", lw=1,
                   label=f"nominal theta, held-out: {nom['mean']:.1f}")
        top = np.percentile([r["J_median"] for r in log], 90) if log else nom["mean"]
        ax.set_ylim(min(held["mean"], *(r["J_best"] for r in log)) - 20.0,
                    max(top, held["mean"]) + 20.0)
        ax.set_xlabel("candidate evaluations")
        ax.set_ylabel("J (NOK/day)")
        named = result.get("policy_class")
        what = (f"'{named}'" if named else
                f"forecast '{result['forecast']}', N={result['system']['N']}")
        ax.set_title(f"Best theta of the class ({what}, "
                     f"{'tied' if result['settings']['tied'] else 'untied'})")
        ax.legend(loc="upper right", fontsize=8)
        path = Path(path)
        with durable.atomic_output(path) as tmp:
            fig.savefig(tmp, dpi=120, bbox_inches="tight", format="png")
    finally:
        plt.close(fig)
    return path
