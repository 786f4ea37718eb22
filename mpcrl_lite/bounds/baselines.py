r"""Baselines: what the learned MPC is measured against, on exactly the same draws.

Every policy is evaluated on one common :class:`Scenario` -- the same days, prices and noise
draws -- with the true dynamics, the low-level controller and the true cost :math:`\tilde L`
(penalties included) of :mod:`mpcrl_lite.system.battery`:

* **clairvoyant** (:func:`clairvoyant`) -- knows each day's noise and prices in advance and
  optimizes the true cost over the day: a linear program per day, a *lower bound* on the cost
  of every policy on these draws (see below);
* **nominal** -- the MPC at :math:`\theta_0` (:meth:`Theta.nominal`), never learning;
* **rule_based** (:class:`RuleBasedPolicy`) -- charge below the day's median price,
  discharge above it, at full power within the bounds and the grid limit;
* **learned** -- the MPC at any given theta, e.g. :meth:`History.final_theta
  <mpcrl_lite.learning.history.History.final_theta>`.
* **causal_dp** (``causal=True``) -- the best causal policy of :mod:`mpcrl_lite.bounds.causal.dp`, a
  dynamic program over the day; every policy is then also reported against its optimum
  :math:`J^\star`: the regret :math:`J - J^\star` and the share of the nominal-to-:math:`J^\star`
  gap closed.

Reported per policy: :math:`J` and :math:`J^i` (discounted daily cost, mean over days), the
hours with soc below 0.1, grid powers, low-level interventions; and, for every learned theta,
the share of the nominal-to-clairvoyant gap closed by learning,
:math:`(J_{nominal} - J_{learned}) / (J_{nominal} - J_{clairvoyant})`.

The policies' homes: :mod:`~mpcrl_lite.bounds.scenario` (the common draws and the
evaluation), :mod:`~mpcrl_lite.bounds.rule` (the price rule),
:mod:`~mpcrl_lite.bounds.clairvoyant` (the clairvoyant bound and why it is one).
"""

from __future__ import annotations

import json
import warnings
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from .._util.stats import mean_ci
from ..config import LearningConfig, MPCConfig, SystemConfig, policy_class_of
from ..learning import durable, outdir, rundir
from ..learning.history import History
from ..mpc.backends.registry import make_solver
from ..mpc.formulation import MPC
from ..sim.closed_loop import MPCPolicy
from ..system.forecast import forecast_prices
from ..system.prices import Prices
from ..theta import Theta
from .causal.dp import CausalBound, causal_optimum, compare_with_optimum
from .causal.dual import lagrangian_bound
from .causal.table import causal_bound
from .clairvoyant import clairvoyant
from .rule import RuleBasedPolicy
from .scenario import PolicyResult, evaluate_policy, make_scenario

__all__ = ['BASELINES_JSON', 'causal_reference', 'evaluate_baselines', 'load_class_best',
           'regret_split', 'run_baselines_cli']


# -- all baselines ----------------------------------------------------------------------------
def evaluate_baselines(
    system: SystemConfig,
    mpc_config: MPCConfig | None = None,
    days: int = 30,
    seed: int = 0,
    thetas: Mapping[str, Theta] | None = None,
    prices: Prices | None = None,
    rule_soc_guard: bool = True,
    causal: bool | CausalBound | float = False,
) -> dict[str, Any]:
    """Evaluate the clairvoyant, nominal, rule-based and given-theta policies on one scenario.

    Parameters
    ----------
    system : SystemConfig
    mpc_config : MPCConfig, optional
        Back-end and barrier parameter of the MPC policies (:func:`make_solver`).
    days : int
        Days of the scenario (the first ``days`` of :meth:`Prices.month` unless ``prices``).
    seed : int
        Seed of the noise (:func:`make_scenario`).
    thetas : mapping of name to Theta, optional
        MPCs to evaluate besides the nominal one, e.g. ``{"learned": history.final_theta()}``;
        the names ``clairvoyant``, ``nominal``, ``rule_based`` and ``causal_dp`` are reserved.
    prices : Prices, optional
    rule_soc_guard : bool, default True
        Passed to :class:`RuleBasedPolicy`.
    causal : bool or CausalBound, default False
        Also measure against the best causal policy (:mod:`mpcrl_lite.bounds.causal.dp`): True solves
        the coupled DP of the scenario's days (about 2 s of CPU per distinct day for three
        batteries), or pass a :class:`~mpcrl_lite.bounds.causal.dp.CausalBound` solved on these prices.
        The DP policy's closed loop is added as ``"causal_dp"`` (not for a bound without value
        tables, e.g. :func:`mpcrl_lite.bounds.causal.table.causal_bound`), and ``"causal"`` holds
        ``J_star`` (mean over the scenario's days), ``grid``, and for every policy the regret
        ``J - J_star`` (NOK/day) and the gap closed ``(J_nominal - J)/(J_nominal - J_star)``.
        A number is taken as J* of the scenario's days (e.g. a Lagrangian bound where the DP
        does not run: :func:`causal_reference`); ``"causal"`` then has no ``grid``. With a
        bound, ``"causal"`` also holds ``J_star_per_day``.

    Returns
    -------
    dict
        ``{"scenario": {...}, "policies": {name: summary}, "gap_closed": {name: share},
        "system": {...}, "mpc": {...}}`` (and ``"causal"``); each summary holds ``J``,
        ``J_per_agent``, ``J_per_day``, ``hours_soc_below_0_1``, ``hours_soc_above_0_9``, grid
        powers, interventions, solver failures and wall time. ``gap_closed[name]`` is
        :math:`(J_{nominal} - J_{name})/(J_{nominal} - J_{clairvoyant})` (None when the
        nominal MPC is already at the bound).
    """
    mpc_config = mpc_config or MPCConfig()
    thetas = dict(thetas or {})
    reserved = {"clairvoyant", "nominal", "rule_based", "causal_dp"} & set(thetas)
    if reserved:
        raise ValueError(f"thetas uses reserved name(s) {sorted(reserved)}; choose others")
    for name, theta in thetas.items():
        if not isinstance(theta, Theta) or theta.n != system.n:
            raise ValueError(f"thetas[{name!r}]: expected a Theta with n={system.n}")
    given = isinstance(causal, (float, np.floating)) and np.isfinite(causal)
    if causal is not True and causal is not False and not given and (
            not isinstance(causal, CausalBound) or causal.system != system):
        raise ValueError(f"causal={causal!r}: expected True, False, a CausalBound of this system "
                         "or a finite J* (float)")
    scenario = make_scenario(system, days, seed, prices)
    if isinstance(causal, CausalBound):
        causal.rows_for(scenario.prices)  # the bound must cover the scenario's days
    results: dict[str, PolicyResult] = {"clairvoyant": clairvoyant(scenario)}
    mpc = MPC(system)
    for name, theta in {"nominal": Theta.nominal(system), **thetas}.items():
        solver = make_solver(mpc, mpc_config, theta)
        seen = forecast_prices(scenario.prices, mpc_config)  # MPCConfig.forecast
        results[name] = evaluate_policy(MPCPolicy(solver, theta, seen), scenario, name)
        results[name].info["backend"] = solver.name
    results["rule_based"] = evaluate_policy(
        RuleBasedPolicy(scenario.prices, system, rule_soc_guard), scenario, "rule_based"
    )
    order = ["clairvoyant", "nominal", "rule_based", *thetas]
    extra: dict[str, Any] = {}
    if given:
        table = compare_with_optimum({name: results[name].J for name in order}, float(causal))
        extra["causal"] = {"J_star": float(causal), "J_star_per_day": None, "grid": None,
                           "regret": {k: v["regret"] for k, v in table.items()},
                           "gap_closed": {k: v["gap_closed"] for k, v in table.items()}}
    elif causal is not False:
        if causal is True:
            causal = causal_optimum(system, scenario.prices)
        per_day = causal.J_star_for(scenario.prices)
        j_star = float(per_day.mean())
        if causal.values is not None:  # a bound without value tables gives J*, no policy
            results["causal_dp"] = evaluate_policy(causal.policy(scenario.prices), scenario,
                                                   "causal_dp")
            order.insert(1, "causal_dp")
        table = compare_with_optimum({name: results[name].J for name in order}, j_star)
        extra["causal"] = {"J_star": j_star, "J_star_per_day": per_day.tolist(),
                           "grid": causal.grid.describe(),
                           "regret": {k: v["regret"] for k, v in table.items()},
                           "gap_closed": {k: v["gap_closed"] for k, v in table.items()}}
    policies = {name: results[name].summary() for name in order}
    j_nom, j_clair = results["nominal"].J, results["clairvoyant"].J
    gap = j_nom - j_clair
    gap_closed = {name: ((j_nom - results[name].J) / gap if gap > 0 else None)
                  for name in order if name not in ("clairvoyant", "nominal")}
    return {
        "scenario": scenario.describe(),
        "policies": policies,
        "gap_closed": gap_closed,
        "system": system.to_dict(),
        "mpc": mpc_config.to_dict(),
        **extra,
    }


#: The file written by :func:`run_baselines_cli`.
BASELINES_JSON = "baselines.json"


def causal_reference(system: SystemConfig, prices: Prices) -> tuple[CausalBound | float, str]:
    """J* of the best causal policy for ``evaluate_baselines(causal=...)`` and where it comes
    from: the stored table ``data/causal_j_star.csv`` where it covers the system and the days
    (:func:`mpcrl_lite.bounds.causal.table.causal_bound`), else the coupled DP solved now (up to
    three batteries, identical or not: the source then says ``"coupled DP (solved)"``, with
    ``", one grid per battery"`` for batteries that differ), else the Lagrangian lower bound
    (:mod:`mpcrl_lite.bounds.causal.dual`: below the true J*, so the regret is overstated)."""
    if system.n <= 3:
        try:
            bound = causal_bound(system, prices)
        except ValueError:
            pass
        else:
            if bound.info.get("source") != "solved":
                return bound, "stored table data/causal_j_star.csv"
            return bound, ("coupled DP (solved, one grid per battery)"
                           if bound.info.get("method") == "product" else "coupled DP (solved)")
    return float(lagrangian_bound(system, prices).J_bound), "Lagrangian lower bound"


def load_class_best(directory: str | Path) -> dict[str, Any]:
    """The result of a ``tune`` run in ``directory`` (its ``tune.json``), with
    ``theta_best`` as a :class:`Theta`."""
    path = Path(directory) / "tune.json"
    try:
        data = json.loads(path.read_text())
        data["theta_best"] = Theta.from_dict(data["theta_best"])
    except FileNotFoundError:
        raise ValueError(f"--class-best {directory}: no tune.json there; expected the output "
                         "directory of `python -m mpcrl_lite tune`") from None
    except (OSError, ValueError, KeyError, TypeError) as err:
        raise ValueError(f"--class-best {directory}: tune.json is not a tune result ({err})") \
            from None
    return data


def regret_split(J_learned_per_day: Any, J_class_per_day: Any, J_star_per_day: Any) -> dict:
    r"""The regret split in two, day by day on the same draws:

    .. math:: \underbrace{J_{learned} - J^\star}_{regret} =
              \underbrace{(J_{learned} - J_{class})}_{learner} +
              \underbrace{(J_{class} - J^\star)}_{class}

    Each part is the mean over the days of the paired per-day differences with its 95 %
    Student-t interval (:func:`mpcrl_lite._util.stats.mean_ci`; ``J_star_per_day`` may be one
    number, then the class part's interval is that of ``J_class``). ``J_learned_per_day`` may
    be None (only the class part).
    """
    J_class = np.asarray(J_class_per_day, dtype=float)
    J_star = np.broadcast_to(np.asarray(J_star_per_day, dtype=float), J_class.shape)
    out = {"class": mean_ci(J_class - J_star).as_dict()}
    if J_learned_per_day is not None:
        J_learned = np.asarray(J_learned_per_day, dtype=float)
        out["learner"] = mean_ci(J_learned - J_class).as_dict()
        out["regret"] = mean_ci(J_learned - J_star).as_dict()
    return out


def run_baselines_cli(
    system: SystemConfig,
    mpc_config: MPCConfig,
    learning: LearningConfig,
    history_dir: str | Path | None,
    out_dir: str | Path,
    prices: Prices | None = None,
    force: bool = False,
    causal: bool = True,
    class_best: str | Path | None = None,
) -> dict[str, Any]:
    """The ``baselines`` command: evaluate and write ``out_dir/baselines.json``.

    The scenario has ``learning.days_per_month`` days and seed ``learning.seed``. With
    ``history_dir`` (a ``learn`` output directory) its final theta is evaluated as
    ``"learned"``; its system must have the same ``n`` (a different configuration otherwise
    only triggers a warning, since evaluating a theta elsewhere can be deliberate).

    With ``causal`` (the default) every policy is judged against J* (:func:`causal_reference`:
    the stored table, the DP, or the Lagrangian bound), under ``"causal"`` with ``J_star``,
    ``source``, and per policy the regret and the gap closed. With ``class_best`` (a ``tune``
    output directory) its ``theta_best`` is evaluated as ``"class_best"`` on the same draws,
    and ``"causal"`` gets ``"split"``: the regret of the learned policy split into the
    learner's part ``J_learned - J_class`` and the class's part ``J_class - J*``, each with a
    95 % interval over the days (:func:`regret_split`); ``"class_best"`` records the tune
    result (its directory, forecast, ``J_best`` and ``J_heldout``).

    ``prices`` (e.g. another month of a Nord Pool export) must have that many days.
    ``out_dir`` is checked before any work: a file, a directory that cannot be written, or
    one that holds ``baselines.json`` already (unless ``force``) is a ``ValueError``
    (:class:`~mpcrl_lite.learning.outdir.RunDirError`). ``baselines.json`` is strict JSON (NaN as
    null), written atomically.

    Returns
    -------
    dict
        As :func:`evaluate_baselines`, plus ``"history"`` (the directory or None).
    """
    thetas: dict[str, Theta] = {}
    if history_dir is not None:
        history = History.load(history_dir)
        if history.system.n != system.n:
            raise ValueError(
                f"history in {history_dir} has n={history.system.n}; expected n={system.n} "
                "(pass --n to match)"
            )
        if history.system != system:
            learned, here = history.system.to_dict(), system.to_dict()
            changed = "; ".join(f"{k}={learned[k]!r} there, {here[k]!r} here"
                                for k in here if learned[k] != here[k])
            warnings.warn(f"history in {history_dir} was learned on a different system "
                          f"({changed}); evaluating it on this one", UserWarning, stacklevel=2)
        if not history.theta_final:
            raise ValueError(f"history in {history_dir} has no final theta (no month finished)")
        thetas["learned"] = history.final_theta()
        if history.mpc.forecast != mpc_config.forecast:
            warnings.warn(f"history in {history_dir} was learned with forecast="
                          f"{history.mpc.forecast!r}; evaluating it with forecast="
                          f"{mpc_config.forecast!r} (pass --forecast to match)", UserWarning,
                          stacklevel=2)
    tuned = None
    if class_best is not None:
        tuned = load_class_best(class_best)
        if tuned["theta_best"].n != system.n:
            raise ValueError(f"--class-best {class_best}: its theta has n={tuned['theta_best'].n}"
                             f"; expected n={system.n}")
        if tuned.get("forecast", "paper") != mpc_config.forecast:
            warnings.warn(f"--class-best {class_best} was searched with forecast="
                          f"{tuned.get('forecast')!r}; evaluating it with forecast="
                          f"{mpc_config.forecast!r} (pass --forecast to match)", UserWarning,
                          stacklevel=2)
        tuned_N = tuned.get("system", {}).get("N", system.N)
        if tuned_N != system.N:
            warnings.warn(f"--class-best {class_best} was searched with the horizon N={tuned_N}"
                          f"; evaluating it with N={system.N} (pass --policy-class to match)",
                          UserWarning, stacklevel=2)
        thetas["class_best"] = tuned["theta_best"]
    if rundir.inspect(out_dir, others=[BASELINES_JSON]).others and not force:
        raise outdir.RunDirError(f"--out {out_dir} already holds {BASELINES_JSON}; pass --force "
                                 "to replace it or choose another --out")
    out = outdir.check_output_dir(out_dir)
    reference: CausalBound | float | bool = False
    source = None
    if causal:
        month = prices if prices is not None else Prices.month(system, learning.days_per_month)
        reference, source = causal_reference(system, month)
    result = evaluate_baselines(system, mpc_config, learning.days_per_month, learning.seed, thetas,
                                prices=prices, causal=reference)
    if "causal" in result:
        result["causal"]["source"] = source
    if tuned is not None:
        result["class_best"] = {
            "dir": str(class_best), "forecast": tuned.get("forecast"),
            "J_best": tuned.get("J_best"), "J_heldout": tuned.get("J_heldout"),
            "evals": tuned.get("evals"),
        }
        if "causal" in result:
            policies = result["policies"]
            star = result["causal"]["J_star_per_day"]
            result["causal"]["split"] = regret_split(
                policies["learned"]["J_per_day"] if "learned" in policies else None,
                policies["class_best"]["J_per_day"],
                result["causal"]["J_star"] if star is None else star)
    result["history"] = None if history_dir is None else str(history_dir)
    result["policy_class"] = policy_class_of(system, mpc_config or MPCConfig())
    durable.write_json(out / BASELINES_JSON, result)
    return result
