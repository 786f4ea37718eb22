r"""The reference library: the same MPC and learning loop written with ``mpcrl`` 1.4.1.

The paper's MPC (eq. 9 with eq. 14, n = 3 batteries, N = 12, Table I values, theta0 nominal)
is built with ``csnlp.Nlp`` and ``csnlp.wrappers.Mpc`` and handed to ``mpcrl.LstdDpgAgent``;
a gymnasium environment wraps :func:`mpcrl_lite.system.battery.step` and steps one day hour by hour,
exactly like :func:`mpcrl_lite.learning.experiment.run_month` does for each of its days.

Mapping onto mpcrl, and where it cannot be the very same problem
-------------------------------------------------------------------
* **Variables and constraints.** ``soc`` is an Mpc state (multiple shooting: csnlp adds
  ``soc[:, 0]`` as a variable tied to the parameter ``soc_0``, n variables and n equalities
  more than :mod:`mpcrl_lite.mpc.formulation`, which substitutes it). ``b`` and ``s`` are Mpc actions
  with the bounds ``[0, U_bar]`` as variable bounds, the slacks ``sigma_hi, sigma_lo`` plain
  variables with ``lb = 0`` (stages 1..N, like ours), the dynamics, the two grid rows per stage
  and the soft soc band general constraints. Cost: eq. 9a with eq. 14, the same discounting
  as :class:`mpcrl_lite.mpc.formulation.MPC` (the constant ``phi(soc_0)`` term is kept, on ``soc[:, 0]``).
* **Actions.** mpcrl's policy is the stack of the Mpc's first actions, ``(b_0, s_0)`` (2n
  numbers); the environment applies ``a = b - s``, projected onto the input bounds and the
  grid limit like ours (:func:`mpcrl_lite.system.battery.project_action`). The sensitivity mpcrl
  computes is therefore ``d(b_0, s_0)/d theta`` (ours: ``d(b_0 - s_0)/d theta``) -- the
  same linear solve with twice the right-hand sides.
* **Exploration.** mpcrl's ``GreedyExploration(mode="additive")`` adds Gaussian noise to
  each of ``b_0`` and ``s_0`` and clips to the action space ``[0, U_bar]``; its strength is
  ``exploration_std / sqrt(2)`` so that the net power sees the same standard deviation.
* **theta.** All 10 parts per agent are learnable parameters (30 for n = 3); bounds mirror
  ``LearningConfig.keep_well_posed`` (``theta_alpha >= alpha_min``, ``phi1, T1 >= 0``).
* **Prices.** mpcrl has no first-class time-varying parameter: the 12-hour price windows are
  fixed parameters ``buy`` and ``sell`` that the agent rewrites in its ``fixed_parameters``
  dict at the start of each episode and after every environment step (two callbacks).
* **Learning.** One episode = one day (24 steps); ``update_strategy = 30`` episodes and an
  experience replay of 30 rollouts give one DPG update per 30-day month, like ours. The
  state features are the paper's (``soc^2, soc, 1``); LSTD and the gradient are mpcrl's.
  The optimizer follows ``LearningConfig.optimizer`` (mpcrl's ``GradientDescent`` or
  ``Adam`` with ``LearningConfig.step_size``). Every number (``tau``, exploration, step
  size, bounds) comes from the package's default configs, so the two sides stay the same
  problem when those defaults change.
* **Solver.** IPOPT with the reference options of :mod:`mpcrl_lite.mpc.backends.registry`
  (``mu_target = tau``, no scaling, no bound relaxation, ``kappa_d = 0``, constant
  derivatives, silent), warm started from the last successful solution (mpcrl's default;
  ours shifts the previous plan). mpcrl computes the KKT sensitivities itself (CasADi
  ``csparse``) at the end of each episode, for all 24 hours at once. There is no Newton
  polishing of IPOPT's point (our IPOPT back-end has it); sensitivities agree with ours to
  IPOPT's tolerance (``check`` in the output).

Measured
--------
* ``ms_per_step``: median over the measured days of (wall time of the day's episode,
  i.e. 24 solves + environment steps + the end-of-episode sensitivities and bookkeeping)
  / 24, plus one DPG update (timed separately) / 720, after one warm-up day.
* ``cold_start_s`` (``--cold``, run in a fresh interpreter): from before ``import mpcrl``
  to the first solved MPC (agent built, which also builds the sensitivity function);
  ``first_day_s``: to the end of the first learned day, which includes numba's
  compilation of mpcrl's kernels. Numba's on-disk cache is pointed at an empty folder so
  the first-run cost is what is measured.

Run ``python benchmarks/bench_mpcrl.py [--days 2] [--cold]``; prints one JSON line.
"""

from __future__ import annotations

import argparse
import itertools
import json
import math
import os
import sys
import time

T_IMPORT = time.perf_counter()  # cold start: measured from here in a fresh interpreter

__all__ = ["available", "build", "cold_start", "cold_start_subprocess", "main", "measure"]


def available() -> bool:
    """True when mpcrl (and therefore csnlp and gymnasium) can be imported."""
    import importlib.util

    try:
        return all(importlib.util.find_spec(m) is not None
                   for m in ("mpcrl", "csnlp", "gymnasium"))
    except (ImportError, ValueError):  # e.g. a module blocked with sys.modules[name] = None
        return False


def _ipopt_options(tau: float, tol: float, max_iter: int) -> dict:
    # the reference options of mpcrl_lite.mpc.backends.registry (kept literal here on purpose: the
    # benchmark must describe exactly what mpcrl is given)
    return {
        "print_time": False,
        "ipopt": {
            "mu_target": tau,
            "nlp_scaling_method": "none",
            "bound_relax_factor": 0.0,
            "kappa_d": 0.0,
            "hessian_constant": "yes",
            "jac_c_constant": "yes",
            "jac_d_constant": "yes",
            "tol": max(tol, 1e-12),
            "acceptable_tol": 1e-7,
            "max_iter": max_iter,
            "print_level": 0,
            "sb": "yes",
        },
    }


def build_mpc(system, mpc_config, box_as_constraints: bool = True):
    """The paper's MPC as a ``csnlp.wrappers.Mpc`` (SX, multiple shooting).

    ``box_as_constraints`` puts ``0 <= b, s <= U_bar`` in the general constraints instead of
    the variable bounds: csnlp rebuilds the bound multipliers from IPOPT's net ``lam_x``
    (``lam_lbx = max(-lam_x, 0)``, ``lam_ubx = max(lam_x, 0)``), which drops the smaller of
    the two multipliers of a two-sided bound. For the barrier problem both are nonzero
    (``tau / slack``), so with the bounds in ``lbx/ubx`` mpcrl's sensitivity is not the exact
    derivative of the barrier solution (relative error 0.2-0.8 at the check point,
    depending on tau); as general constraints every row keeps its own multiplier and the
    sensitivity matches ours.
    """
    import casadi as cs
    from csnlp import Nlp
    from csnlp.wrappers import Mpc

    from mpcrl_lite.theta import PARTS

    n, N = system.n, system.N
    nlp = Nlp[cs.SX](sym_type="SX", name="battery")
    mpc = Mpc(nlp, prediction_horizon=N, shooting="multi")
    soc, _ = mpc.state("soc", n)  # (n, N+1); soc[:, 0] == soc_0 is added by csnlp
    if box_as_constraints:
        b, _ = mpc.action("b", n)  # (n, N)
        s, _ = mpc.action("s", n)
    else:
        b, _ = mpc.action("b", n, lb=0.0, ub=system.U_bar)
        s, _ = mpc.action("s", n, lb=0.0, ub=system.U_bar)
    shi, _, _ = mpc.variable("sigma_hi", (n, N), lb=0.0)  # slacks of stages 1..N
    slo, _, _ = mpc.variable("sigma_lo", (n, N), lb=0.0)
    buy = mpc.parameter("buy", (N, 1))
    sell = mpc.parameter("sell", (N, 1))
    th = {name: mpc.parameter(f"theta_{name}", (n, 1)) for name in PARTS}

    rep = lambda v: cs.repmat(v, 1, N)
    mpc.constraint("dynamics", soc[:, 1:], "==",
                   soc[:, :-1] + rep(th["alpha"]) * (b - s) + rep(th["delta"]))
    if box_as_constraints:
        for name, u in (("b", b), ("s", s)):
            mpc.constraint(f"{name}_min", u, ">=", 0.0)
            mpc.constraint(f"{name}_max", u, "<=", system.U_bar)
    mpc.constraint("grid_buy", cs.sum1(b), "<=", system.P_bar)
    mpc.constraint("grid_sell", cs.sum1(s), "<=", system.P_bar)
    mpc.constraint("soc_high", soc[:, 1:] - system.soc_high, "<=", shi)
    mpc.constraint("soc_low", system.soc_low - soc[:, 1:], "<=", slo)

    def phi(x):
        return cs.sum1(th["phi1"] * x**2 + th["phi2"] * x + th["phi3"])

    gamma = system.gamma
    (w_hi, w_lo), (wf_hi, wf_lo) = system.omega, system.omega_f
    cost = phi(soc[:, 0])  # constant (soc_0 is fixed): kept as in eq. 9a
    for j in range(N):
        cost += gamma**j * cs.sum1((buy[j] + th["b"]) * b[:, j] - (sell[j] + th["s"]) * s[:, j])
        if j + 1 < N:
            cost += gamma ** (j + 1) * (
                phi(soc[:, j + 1]) + w_hi * cs.sum1(shi[:, j]) + w_lo * cs.sum1(slo[:, j])
            )
    last = soc[:, N]
    cost += cs.sum1(th["T1"] * last**2 + th["T2"] * last + th["T3"])
    cost += wf_hi * cs.sum1(shi[:, N - 1]) + wf_lo * cs.sum1(slo[:, N - 1])
    mpc.minimize(cost)
    mpc.init_solver(_ipopt_options(mpc_config.tau, mpc_config.tol, mpc_config.max_iter), "ipopt")
    return mpc


def _make_env_class():
    import gymnasium as gym
    import numpy as np

    from mpcrl_lite.system.battery import project_action, sample_noise, step

    class BatteryDayEnv(gym.Env):
        """One day of the true battery system (``mpcrl_lite.system.battery``), hour by hour.

        Observation: soc (n,). Action: ``(b, s)`` (2n,), applied as ``a = b - s`` after
        the projection onto the input bounds and the grid limit. Cost (not reward): the
        stage cost ``L~``. Each reset starts the next day of the month at ``soc0``.
        """

        def __init__(self, system, prices, seed: int = 0) -> None:
            super().__init__()
            self.system, self.prices = system, prices
            n, N, H = system.n, system.N, system.hours_per_day
            self.observation_space = gym.spaces.Box(0.0, 1.0, (n,), np.float64)
            self.action_space = gym.spaces.Box(0.0, system.U_bar, (2 * n,), np.float64)
            windows = [prices.window(k, N) for k in range(H)]
            self._buy = np.stack([w[0] for w in windows])  # (H, days, N)
            self._sell = np.stack([w[1] for w in windows])
            self._rng = np.random.default_rng(seed)
            self.day, self.hour, self._next_day = 0, 0, 0
            self.soc = np.full(n, system.soc0)

        def reset(self, *, seed=None, options=None):
            super().reset(seed=seed)
            self.day = self._next_day % self.prices.days
            self._next_day += 1
            self.hour = 0
            self.soc = np.full(self.system.n, self.system.soc0)
            return self.soc.copy(), {}

        def price_window(self):
            """Buy and sell windows the MPC sees now, each (N, 1)."""
            k = min(self.hour, self.system.hours_per_day - 1)
            return self._buy[k, self.day][:, None], self._sell[k, self.day][:, None]

        def step(self, action):
            n, sysc = self.system.n, self.system
            u = np.asarray(action, dtype=float).reshape(2 * n)
            a = project_action((u[:n] - u[n:])[None], sysc)
            noise = sample_noise(self._rng, (1, n), sysc)
            k = self.hour
            res = step(self.soc[None], a, noise, self._buy[k, self.day, 0],
                       self._sell[k, self.day, 0], sysc)
            self.soc = res.soc_next[0]
            self.hour += 1
            truncated = self.hour >= sysc.hours_per_day
            return self.soc.copy(), float(res.stage_cost[0]), False, truncated, {}

    return BatteryDayEnv


def build(system=None, mpc_config=None, learning=None, prices=None, seed: int = 0,
          box_as_constraints: bool = True):
    """``(agent, env)``: an ``mpcrl.LstdDpgAgent`` on the paper's MPC and the day env."""
    import casadi as cs
    import numpy as np
    from mpcrl import LearnableParameter, LearnableParametersDict, LstdDpgAgent
    from mpcrl import exploration as E
    from mpcrl.optim import Adam, GradientDescent

    from mpcrl_lite.config import LearningConfig, MPCConfig, SystemConfig
    from mpcrl_lite.system.prices import Prices
    from mpcrl_lite.theta import PARTS, Theta

    system = system or SystemConfig()
    mpc_config = mpc_config or MPCConfig(backend="ipopt")
    learning = learning or LearningConfig()
    prices = prices or Prices.month(system, learning.days_per_month)
    n = system.n
    mpc = build_mpc(system, mpc_config, box_as_constraints)

    theta0 = Theta.nominal(system)
    lower = {"alpha": learning.alpha_min, "phi1": 0.0, "T1": 0.0}
    learnable = LearnableParametersDict(
        LearnableParameter(f"theta_{name}", n, getattr(theta0, name),
                           lb=lower.get(name, -np.inf) if learning.keep_well_posed else -np.inf)
        for name in PARTS
    )
    soc = cs.SX.sym("soc", n)
    features = cs.Function("Phi", [soc], [cs.vertcat(soc**2, soc, 1)])

    class PricedLstdDpgAgent(LstdDpgAgent):
        """LstdDpgAgent whose price windows follow the environment's clock, with timers."""

        def _set_prices(self, env) -> None:
            buy, sell = env.unwrapped.price_window()
            self.fixed_parameters["buy"] = buy
            self.fixed_parameters["sell"] = sell

        def on_episode_start(self, env, episode, state) -> None:
            self._set_prices(env)
            super().on_episode_start(env, episode, state)
            self.step_stamps = [time.perf_counter()]
            self.episode_t0 = self.step_stamps[0]
            self.episode_c0 = time.process_time()

        def on_env_step(self, env, episode, timestep) -> None:
            super().on_env_step(env, episode, timestep)
            self._set_prices(env)
            self.step_stamps.append(time.perf_counter())

        def on_episode_end(self, env, episode, rewards) -> None:
            super().on_episode_end(env, episode, rewards)
            self.episode_times.append(time.perf_counter() - self.episode_t0)
            self.episode_cpu.append(time.process_time() - self.episode_c0)
            steps = self.step_stamps
            self.step_times.extend(b - a for a, b in itertools.pairwise(steps))
            self.consolidation_times.append(time.perf_counter() - steps[-1])

    # the same rule as LearningConfig.optimizer ('sgd' or 'adam'; ours scales Adam's step per
    # entry, mpcrl's does not); bound_consistency clips theta into its bounds after each step
    # like our projection (without it a step that mpcrl's QP leaves a hair outside a bound
    # raises)
    Optimizer = Adam if getattr(learning, "optimizer", "sgd") == "adam" else GradientDescent
    optimizer = Optimizer(learning_rate=learning.step_size, bound_consistency=True)
    Env = _make_env_class()
    env = Env(system, prices, seed=seed)
    buy0, sell0 = env.price_window()
    agent = PricedLstdDpgAgent(
        mpc=mpc,
        update_strategy=learning.days_per_month,
        discount_factor=system.gamma,
        optimizer=optimizer,
        learnable_parameters=learnable,
        fixed_parameters={"buy": buy0, "sell": sell0},
        exploration=E.GreedyExploration(learning.exploration_std / math.sqrt(2), mode="additive",
                                        seed=seed),
        experience=learning.days_per_month,
        state_features=features,
        ridge_regression_regularization=learning.ridge,
        record_policy_performance=False,
        name="battery_dpg",
    )
    agent.episode_times, agent.step_times, agent.consolidation_times = [], [], []
    agent.episode_cpu = []
    return agent, env


def consistency_check(agent, env, system, mpc_config) -> dict:
    """Policy and sensitivity of mpcrl's MPC vs mpcrl_lite's at one state (relative
    differences), so the comparison is known to be between equal problems."""
    import numpy as np

    from mpcrl_lite.mpc.backends.ipopt import IpoptSolver
    from mpcrl_lite.mpc.formulation import MPC
    from mpcrl_lite.theta import PARTS, Theta

    env.reset()
    soc = np.array([0.6, 0.3, 0.8])[: system.n] if system.n <= 3 else np.full(system.n, 0.5)
    agent._set_prices(env)
    agent._last_solution = None
    _, sol = agent.state_value(soc, deterministic=True)
    n = system.n
    b0 = np.asarray(sol.vals["b"][:, 0]).ravel()
    s0 = np.asarray(sol.vals["s"][:, 0]).ravel()
    vals = np.asarray(sol.x_and_lam_and_p.elements())[None]
    sens = agent._sensitivity(vals, 1)[0]  # (n_theta, 2n): d(b0, s0)/d theta
    grad_mpcrl = sens[:, :n] - sens[:, n:]
    # the reference back-end (IPOPT + Newton polish + KKT sensitivity), checked against
    # finite differences in the package's tests
    solver = IpoptSolver(MPC(system), mpc_config.replace(backend="ipopt"))
    buy, sell = env.price_window()
    theta = Theta.from_vector(
        np.concatenate([agent.learnable_parameters[f"theta_{p}"].value for p in PARTS]), n)
    mine = solver.solve(soc, buy.ravel(), sell.ravel(), theta)
    grad_mine = solver.sensitivity(mine).grad[0]
    scale = np.abs(grad_mine).max()
    return {
        "policy_max_abs_diff": float(np.abs((b0 - s0) - mine.action).max()),
        "sensitivity_max_rel_diff": float(np.abs(grad_mpcrl - grad_mine).max() / scale),
    }


def measure(days: int = 2, warmup_days: int = 1, seed: int = 0,
            box_as_constraints: bool = True) -> dict:
    """Warm per-step timing of mpcrl's learning loop (see the module docstring)."""
    import numpy as np

    from mpcrl_lite.config import LearningConfig, MPCConfig, SystemConfig

    system, mpc_config, learning = SystemConfig(), MPCConfig(backend="ipopt"), LearningConfig()
    kw = {"seed": seed, "box_as_constraints": box_as_constraints}
    agent, env = build(system, mpc_config, learning, **kw)
    check = consistency_check(agent, env, system, mpc_config)
    agent, env = build(system, mpc_config, learning, **kw)
    H = system.hours_per_day
    agent.train(env, episodes=warmup_days + days, seed=seed, raises=False)
    day_ms = [1e3 * t / H for t in agent.episode_times[warmup_days:]]
    day_cpu_ms = [1e3 * t / H for t in agent.episode_cpu[warmup_days:]]
    step_ms = [1e3 * t for t in agent.step_times[warmup_days * H:]]
    consolidation_ms = [1e3 * t for t in agent.consolidation_times[warmup_days:]]
    # a DPG update on the rollouts in memory (the agent does one per 30-day month); the
    # first call compiles mpcrl's numba kernels, so the second one is the steady cost
    update_ms, update_cpu = [], []
    for _ in range(2):
        t0, c0 = time.perf_counter(), time.process_time()
        try:
            msg = agent.update()
        except (ValueError, RuntimeError) as err:  # timed all the same; reported below
            msg = f"update raised: {err}"
        update_ms.append(1e3 * (time.perf_counter() - t0))
        update_cpu.append(1e3 * (time.process_time() - c0))
    first_update_ms, update_ms = update_ms
    per_month = learning.days_per_month * H
    ms = float(np.median(day_ms)) + update_ms / per_month
    return {
        "mpcrl_version": __import__("mpcrl").__version__,
        "csnlp_version": __import__("csnlp").__version__,
        "ms_per_step": ms,
        "cpu_ms_per_step": float(np.median(day_cpu_ms)) + update_cpu[1] / per_month,
        "ms_per_step_days": day_ms,
        "median_step_ms_solve_env": float(np.median(step_ms)),
        "sensitivity_ms_per_day": float(np.median(consolidation_ms)),
        "update_ms": update_ms,
        "first_update_ms": first_update_ms,
        "box_as_constraints": box_as_constraints,
        "update_status": msg,
        "days_measured": days,
        "warmup_days": warmup_days,
        "check": check,
    }


def cold_start(seed: int = 0) -> dict:
    """Launch -> first solved MPC -> first learned day, in THIS (fresh) interpreter.

    Times count from ``BENCH_T0`` (the parent's ``time.time()`` just before the launch) when
    set, else from this module's first line.
    """
    t_launch = float(os.environ.get("BENCH_T0", time.time() - (time.perf_counter() - T_IMPORT)))
    import mpcrl  # noqa: F401  (part of the cold start)

    from mpcrl_lite.config import LearningConfig, MPCConfig, SystemConfig

    system, learning = SystemConfig(), LearningConfig()
    agent, env = build(system, MPCConfig(backend="ipopt"), learning, seed=seed)
    state, _ = env.reset()
    agent.on_episode_start(env, 0, state)
    _, sol = agent.state_value(state, deterministic=False)
    t_first = time.time() - t_launch
    cpu_first = time.process_time()
    agent, env = build(system, MPCConfig(backend="ipopt"), learning, seed=seed)
    t_build = time.perf_counter()
    agent.train(env, episodes=1, seed=seed, raises=False)
    t_day = time.perf_counter()
    return {
        "cold_start_s": t_first,
        "cpu_s": cpu_first,
        "first_day_cpu_s": time.process_time(),
        "first_solve_ok": bool(sol.success),
        "first_day_s": t_first + (t_day - t_build),
        "first_day_train_s": t_day - t_build,
    }


def cold_start_subprocess(fresh_numba_cache: bool = True, python: str | None = None) -> dict:
    """:func:`cold_start` in a fresh interpreter; with ``fresh_numba_cache`` numba's cache
    points at an empty folder, so mpcrl's kernels are compiled as on a first run."""
    import tempfile

    from _common import python_env, run_json

    env = python_env()
    with tempfile.TemporaryDirectory(prefix="bench_mpcrl_numba_") as cache:
        if fresh_numba_cache:
            env["NUMBA_CACHE_DIR"] = cache
        env["BENCH_T0"] = repr(time.time())
        code = "import sys, bench_mpcrl; sys.exit(bench_mpcrl.main(['--cold']))"
        out = run_json(code, env=env, timeout=900, python=python)
    out["fresh_numba_cache"] = fresh_numba_cache
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--days", type=int, default=2, help="measured days (after 1 warm-up day)")
    parser.add_argument("--warmup-days", type=int, default=1)
    parser.add_argument("--bounds-in-lbx", action="store_true",
                        help="keep 0 <= b, s <= U as variable bounds (inexact sensitivity, "
                             "see build_mpc)")
    parser.add_argument("--cold", action="store_true",
                        help="measure the cold start instead (run in a fresh interpreter)")
    args = parser.parse_args(argv)
    if not available():
        print(json.dumps({"skipped": "mpcrl is not importable; "
                          "pip install -r benchmarks/requirements.txt"}))
        return 0
    import warnings

    warnings.filterwarnings("ignore")
    if args.cold:
        out = cold_start()
    else:
        out = measure(args.days, args.warmup_days, box_as_constraints=not args.bounds_in_lbx)
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
