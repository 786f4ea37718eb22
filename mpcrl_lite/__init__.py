"""mpcrl_lite: MPC-based reinforcement learning for a multi-agent battery storage system.

``import mpcrl_lite as ml`` gives the names a user needs; each is loaded on first use, so the
import itself stays light (no CasADi, numba, pandas, scipy or matplotlib until asked for).

Configuration and parameters
    ``SystemConfig``, ``MPCConfig``, ``LearningConfig``: every number and choice (Table I and
    the open ones); ``Theta``: the MPC parameters, named parts per battery.
The system (:mod:`mpcrl_lite.system`)
    ``Prices``: a month of buying and selling prices; ``load_prices``: day-ahead prices from the files
    of Nord Pool, ENTSO-E or Energi Data Service; ``load_nordpool_csv``: Nord Pool's old
    export; ``until_midnight``: the forecast that stops at midnight (an extension);
    ``step``: one hour of the true batteries (paper eq. 1).
The MPC (:mod:`mpcrl_lite.mpc`)
    ``MPC``: the paper's MPC (eq. 9) in CasADi; ``make_solver``: a solver back-end for it;
    ``policy_sensitivity``: d pi / d theta from the KKT conditions (eq. 20).
The closed loop (:mod:`mpcrl_lite.sim`)
    ``simulate``: the one closed loop; ``MPCPolicy``: the MPC as a policy; ``run_month``: a
    month in closed loop; ``evaluate_mpc``: a theta on common noise draws; ``Record``: the
    record of a simulated period; ``BatteryEnv``: the system as a Gymnasium environment
    (``gymnasium.make("mpcrl_lite/Batteries-v0")``), ``MPCAgent``: the MPC as its policy.
Learning (:mod:`mpcrl_lite.learning`, :mod:`mpcrl_lite.decentralized`)
    ``Experiment``: the centralized learner (LSTD critic, DPG actor); ``History``: a run's
    results; ``lstd_q``: the compatible critic's fit; ``policy_gradient``: the DPG estimate
    (eq. 13); ``DecentralizedExperiment``: one learner per battery.
Bounds and studies (:mod:`mpcrl_lite.bounds`, :mod:`mpcrl_lite.studies`)
    ``evaluate_baselines``: the clairvoyant bound, nominal MPC and price rule on one scenario;
    ``causal_optimum``: the best causal policy J* by dynamic programming;
    ``lagrangian_bound``: a lower bound on J* for any number of batteries; ``run_study``:
    one learning run over many seeds; ``run_sweep``: a grid of runs.
Figures (:mod:`mpcrl_lite.figures`)
    ``plot_day``: one day in closed loop; ``save_paper_figures``: the paper's Figs. 1-7.

The subpackages follow the data flow, one way (``tests/package/test_architecture.py`` holds the
layers)::

    config, theta -> system -> mpc -> sim -> learning -> decentralized, bounds
        -> figures -> classroom -> publish -> studies -> cli
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from ._util import gym_registration as _gym_registration
from ._util.lazy import lazy_names as _lazy_names
from ._util.version import __version__

# gymnasium.make("mpcrl_lite/Batteries-v0") from now on, Gymnasium itself not imported here
_gym_registration.install()

#: Where each public name lives (module below ``mpcrl_lite``); loaded on first access.
_HOMES: dict[str, str] = {
    "SystemConfig": "config",
    "MPCConfig": "config",
    "LearningConfig": "config",
    "Theta": "theta",
    "Prices": "system.prices",
    "load_nordpool_csv": "system.price_files.nordpool_elspot",
    "load_prices": "system.price_files.load",
    "until_midnight": "system.forecast",
    "step": "system.battery",
    "MPC": "mpc.formulation",
    "make_solver": "mpc.backends.registry",
    "policy_sensitivity": "mpc.sensitivity",
    "simulate": "sim.closed_loop",
    "MPCPolicy": "sim.closed_loop",
    "run_month": "sim.closed_loop",
    "evaluate_mpc": "sim.closed_loop",
    "Record": "sim.record",
    "BatteryEnv": "sim.env",
    "MPCAgent": "sim.env",
    "Experiment": "learning.experiment",
    "History": "learning.history",
    "lstd_q": "learning.lstd",
    "policy_gradient": "learning.dpg",
    "DecentralizedExperiment": "decentralized.learner",
    "evaluate_baselines": "bounds.baselines",
    "causal_optimum": "bounds.causal.dp",
    "lagrangian_bound": "bounds.causal.dual",
    "run_study": "studies.study",
    "run_sweep": "studies.sweep.api",
    "plot_day": "figures.plots",
    "save_paper_figures": "figures.paper",
}

__all__ = [
    "MPC",
    "BatteryEnv",
    "DecentralizedExperiment",
    "Experiment",
    "History",
    "LearningConfig",
    "MPCAgent",
    "MPCConfig",
    "MPCPolicy",
    "Prices",
    "Record",
    "SystemConfig",
    "Theta",
    "__version__",
    "causal_optimum",
    "evaluate_baselines",
    "evaluate_mpc",
    "lagrangian_bound",
    "load_nordpool_csv",
    "load_prices",
    "lstd_q",
    "make_solver",
    "plot_day",
    "policy_gradient",
    "policy_sensitivity",
    "run_month",
    "run_study",
    "run_sweep",
    "save_paper_figures",
    "simulate",
    "step",
    "until_midnight",
]


__getattr__ = _lazy_names(__name__, {name: f"{__name__}.{home}" for name, home in _HOMES.items()})


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_HOMES))


if TYPE_CHECKING:  # the same names for type checkers and editors
    from .bounds.baselines import evaluate_baselines
    from .bounds.causal.dp import causal_optimum
    from .bounds.causal.dual import lagrangian_bound
    from .config import LearningConfig, MPCConfig, SystemConfig
    from .decentralized.learner import DecentralizedExperiment
    from .figures.paper import save_paper_figures
    from .figures.plots import plot_day
    from .learning.dpg import policy_gradient
    from .learning.experiment import Experiment
    from .learning.history import History
    from .learning.lstd import lstd_q
    from .mpc.backends.registry import make_solver
    from .mpc.formulation import MPC
    from .mpc.sensitivity import policy_sensitivity
    from .sim.closed_loop import MPCPolicy, evaluate_mpc, run_month, simulate
    from .sim.env import BatteryEnv, MPCAgent
    from .sim.record import Record
    from .studies.study import run_study
    from .studies.sweep.api import run_sweep
    from .system.battery import step
    from .system.forecast import until_midnight
    from .system.price_files.load import load_prices
    from .system.price_files.nordpool_elspot import load_nordpool_csv
    from .system.prices import Prices
    from .theta import Theta
