"""Tests of mpcrl_lite.sim.compiled_month: the month in one compiled call gives the Python
loop's record to the last bit, for every kind of month it takes, and leaves the others to the
Python loop."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from mpcrl_lite.config import LearningConfig, MPCConfig, SystemConfig
from mpcrl_lite.learning.experiment import Experiment
from mpcrl_lite.mpc.backends.registry import make_solver
from mpcrl_lite.mpc.formulation import MPC
from mpcrl_lite.sim import compiled_month
from mpcrl_lite.sim.closed_loop import RunBlocks, evaluate_mpc, run_month
from mpcrl_lite.sim.record import RECORD_ARRAYS
from mpcrl_lite.system.prices import Prices
from mpcrl_lite.theta import Theta

SYSTEM = SystemConfig()
EXPLORATION = LearningConfig().exploration_std


@pytest.fixture(scope="module")
def solver():
    return make_solver(MPC(SYSTEM), MPCConfig(backend="kernel"))


def _months(monkeypatch, make):
    """``make()`` through the Python loop, then compiled (and checks it was)."""
    calls = []
    real = compiled_month.run

    def spy(*args, **kwargs):
        calls.append(1)
        return real(*args, **kwargs)

    monkeypatch.setattr(compiled_month, "run", spy)
    monkeypatch.setattr(compiled_month, "ENABLED", False)
    reference = make()
    assert not calls
    monkeypatch.setattr(compiled_month, "ENABLED", True)
    compiled = make()
    assert calls, "the month did not run compiled"
    return reference, compiled


def _same(reference, compiled):
    for key in RECORD_ARRAYS:
        want, got = getattr(reference, key), getattr(compiled, key)
        assert got.shape == want.shape and got.dtype == want.dtype, key
        assert got.tobytes() == want.tobytes(), key
    if reference.grad_pi is None:
        assert compiled.grad_pi is None
    else:
        assert compiled.grad_pi.tobytes() == reference.grad_pi.tobytes()


@pytest.mark.parametrize("threads", [1, 2])
@pytest.mark.parametrize("bounds", ["symmetric", "radial"])
def test_a_learning_month_is_the_python_loops_to_the_last_bit(monkeypatch, solver, threads,
                                                               bounds):
    monkeypatch.setattr(solver, "threads", threads)
    prices = Prices.month(SYSTEM, 30)
    theta = Theta.nominal(SYSTEM)
    reference, compiled = _months(monkeypatch, lambda: run_month(
        theta, solver, prices, SYSTEM, np.random.default_rng(5), exploration_std=EXPLORATION,
        sensitivities=True, exploration_bounds=bounds))
    _same(reference, compiled)
    assert reference.sens_ok.mean() > 0.9  # the month computed its sensitivities


def test_a_month_without_exploration_or_sensitivities(monkeypatch, solver):
    prices = Prices.month(SYSTEM, 9)  # a last group of four that is not full
    reference, compiled = _months(monkeypatch, lambda: run_month(
        Theta.nominal(SYSTEM), solver, prices, SYSTEM, np.random.default_rng(1),
        sensitivities=False, soc0=np.linspace(0.0, 1.0, 9 * SYSTEM.n).reshape(9, SYSTEM.n)))
    _same(reference, compiled)
    assert compiled.grad_pi is None and not compiled.sens_ok.any()


def test_an_evaluation_on_several_draws(monkeypatch, solver):
    prices = Prices.month(SYSTEM, 6)
    theta = Theta.nominal(SYSTEM).replace(b=np.full(SYSTEM.n, 0.2))
    reference, compiled = _months(monkeypatch, lambda: evaluate_mpc(
        theta, solver, prices, SYSTEM, seed=4, draws=3))
    _same(reference, compiled)


def test_runs_in_lockstep_each_with_its_theta(monkeypatch, solver):
    prices = Prices.month(SYSTEM, 5)
    thetas = [Theta.nominal(SYSTEM), Theta.nominal(SYSTEM).replace(b=np.full(SYSTEM.n, 0.5))]

    def month():
        rngs = RunBlocks([np.random.default_rng(s) for s in (7, 8)], [SYSTEM, SYSTEM])
        return run_month(thetas, solver, prices, SYSTEM, rngs, exploration_std=EXPLORATION,
                         sensitivities=True)

    reference, compiled = _months(monkeypatch, month)
    _same(reference, compiled)
    # the two runs differ: each row got its own theta
    assert not np.array_equal(compiled.policy[:, :5], compiled.policy[:, 5:])


@pytest.mark.parametrize("system", [
    SystemConfig(n=2, N=5),  # the generic kernels
    SystemConfig(P_bar=0.4),  # the grid limit binds in most hours
    SystemConfig(alpha=(1 / 24, 1 / 12, 1 / 12), noise_mean=(0.1, 0.0, -0.05),
                 noise_var=(1.0, 0.5, 0.5), U_bar=(1.0, 0.6, 0.8), p=(800.0, 1000.0, 1200.0),
                 P_bar=1.2),  # per-battery parameters
])
def test_other_systems(monkeypatch, system):
    solver = make_solver(MPC(system), MPCConfig(backend="kernel"))
    prices = Prices.month(system, 10)
    reference, compiled = _months(monkeypatch, lambda: run_month(
        Theta.nominal(system), solver, prices, system, np.random.default_rng(3),
        exploration_std=EXPLORATION, sensitivities=True))
    _same(reference, compiled)


def test_failed_solves_act_idle_and_are_logged_as_by_the_python_loop(monkeypatch, caplog):
    solver = make_solver(MPC(SYSTEM), MPCConfig(backend="kernel", max_iter=6))
    prices = Prices.month(SYSTEM, 8)
    logs = []

    def month():
        caplog.clear()
        with caplog.at_level(logging.WARNING, logger="mpcrl_lite.mpc.backends.kernel"):
            record = run_month(Theta.nominal(SYSTEM), solver, prices, SYSTEM,
                               np.random.default_rng(2), exploration_std=EXPLORATION,
                               sensitivities=True)
        logs.append([r.getMessage() for r in caplog.records])
        return record

    reference, compiled = _months(monkeypatch, month)
    _same(reference, compiled)
    assert not reference.solver_ok.all() and reference.solver_ok.any()
    assert logs[0] == logs[1] and logs[0]
    assert np.all(compiled.policy[~compiled.solver_ok] == 0.0)  # the fallback: idle


def test_a_learning_run_is_the_same_run(monkeypatch):
    histories = []
    for enabled in (False, True):
        monkeypatch.setattr(compiled_month, "ENABLED", enabled)
        exp = Experiment(learning=LearningConfig(days_per_month=8, eval_draws=2, eval_every=1,
                                                 seed=21))
        histories.append(exp.run(3, progress=False))
    want, got = histories
    for key in ("J", "theta", "theta_final", "J_eval", "grad_norm", "max_P_mpc",
                "hours_soc_below_0_1", "solver_failures", "skipped_steps"):
        assert getattr(got, key) == getattr(want, key), key


@pytest.mark.parametrize("bounds, margin", [("project", 0.0), ("symmetric", 0.1)])
def test_months_it_does_not_cover_run_the_python_loop(monkeypatch, solver, bounds, margin):
    calls = []
    monkeypatch.setattr(compiled_month, "run", lambda *a, **k: calls.append(1))
    record = run_month(Theta.nominal(SYSTEM), solver, Prices.month(SYSTEM, 4), SYSTEM,
                       np.random.default_rng(0), exploration_std=EXPLORATION,
                       sensitivities=True, exploration_bounds=bounds,
                       exploration_margin=margin)
    assert not calls and record.solver_ok.all()
    hooks = []
    run_month(Theta.nominal(SYSTEM), solver, Prices.month(SYSTEM, 4), SYSTEM,
              np.random.default_rng(0), on_hour=[hooks.append])
    assert not calls and len(hooks) == SYSTEM.hours_per_day
    assert not compiled_month.eligible(None, 3, None, 0.0)
    assert not compiled_month.eligible({}, compiled_month.MAX_BATTERIES + 1, None, 0.0)


def test_bad_input_gets_the_python_loops_error(monkeypatch, solver):
    monkeypatch.setattr(compiled_month, "ENABLED", True)
    with pytest.raises(ValueError, match="soc0"):
        run_month(Theta.nominal(SYSTEM), solver, Prices.month(SYSTEM, 4), SYSTEM,
                  np.random.default_rng(0), soc0=1.5)
    with pytest.raises(ValueError, match="Theta"):
        run_month([Theta.nominal(SystemConfig(n=2))], solver, Prices.month(SYSTEM, 4), SYSTEM,
                  np.random.default_rng(0))


def test_each_kernel_module_gets_its_own_copy():
    from mpcrl_lite.mpc.backends import kernel_core, kernel_sizes

    generic = compiled_month.source(kernel_core)
    sized = compiled_month.source(kernel_sizes.kernels(3, 12))
    assert "from mpcrl_lite.mpc.backends.kernel_core import" in generic
    assert "from mpcrl_lite.mpc.backends.kernel_core_n3_N12 import" in sized
    assert compiled_month.module(kernel_core) is not compiled_month.module(
        kernel_sizes.kernels(3, 12))


class _Steps:
    """A replayable hook keeping every step it is given (copies)."""

    replayable = True

    def __init__(self) -> None:
        self.steps = []

    def __call__(self, step) -> None:
        d, r = step.decision, step.result
        sol = d.solution
        self.steps.append([step.hour, step.soc.copy(), step.a.copy(), step.noise.copy(),
                           step.buy.copy(), step.sell.copy(), d.action.copy(),
                           d.solver_ok.copy(), d.planned_power.copy(), d.sens_ok.copy(),
                           d.grad.copy(), sol.x.copy(), sol.lam.copy(), sol.mu.copy(),
                           sol.p.copy(), sol.cost.copy(), sol.success.copy(), sol.status,
                           sol.iterations.copy(), r.soc_next.copy(), r.b.copy(), r.s.copy(),
                           r.correction.copy(), r.agent_cost.copy(), r.stage_cost.copy(),
                           r.grid_power.copy()])


def test_replayable_hooks_get_the_python_loops_steps(monkeypatch, solver):
    prices = Prices.month(SYSTEM, 6)
    hooks = []

    def month():
        hooks.append(_Steps())
        return run_month(Theta.nominal(SYSTEM), solver, prices, SYSTEM,
                         np.random.default_rng(9), exploration_std=EXPLORATION,
                         sensitivities=True, on_hour=[hooks[-1]])

    reference, compiled = _months(monkeypatch, month)
    _same(reference, compiled)
    want, got = hooks
    assert len(want.steps) == len(got.steps) == SYSTEM.hours_per_day
    for w, g in zip(want.steps, got.steps, strict=True):
        for a, b in zip(w, g, strict=True):
            if isinstance(a, np.ndarray):
                assert a.dtype == b.dtype and a.tobytes() == b.tobytes()
            else:
                assert a == b


@pytest.mark.parametrize("hessian", ["approx", "full"])
def test_a_q_learning_run_is_the_same_run(monkeypatch, hessian):
    from mpcrl_lite.learning.q_experiment import QLearningExperiment

    histories = []
    for enabled in (False, True):
        monkeypatch.setattr(compiled_month, "ENABLED", enabled)
        exp = QLearningExperiment(learning=LearningConfig(days_per_month=6, eval_draws=1,
                                                          hessian=hessian, seed=5))
        histories.append(exp.run(2, progress=False))
    want, got = histories
    for key in ("J", "theta", "theta_final", "J_eval", "grad_norm", "solver_failures"):
        assert getattr(got, key) == getattr(want, key), key


def test_every_kind_of_month_calls_one_compiled_version(monkeypatch, solver):
    """Read-only, strided or per-battery inputs must not make numba compile the month again
    (a type of its own each): make setup's compiled month serves them all."""
    from mpcrl_lite.mpc.backends import kernel_sizes
    from mpcrl_lite.system.forecast import until_midnight

    monkeypatch.setattr(compiled_month, "ENABLED", True)
    monkeypatch.setattr(solver, "threads", 2)
    prices = Prices.month(SYSTEM, 16)  # two threads' blocks: the parallel entry
    theta = Theta.nominal(SYSTEM)
    run_month(theta, solver, prices, SYSTEM, np.random.default_rng(0),
              exploration_std=EXPLORATION, sensitivities=True)  # read-only prices
    run_month(theta, solver, until_midnight(prices), SYSTEM, np.random.default_rng(0))
    evaluate_mpc(theta, solver, prices, SYSTEM, seed=1, draws=2)  # tiled, writable prices
    run_month([theta, theta], solver, prices, SYSTEM,
              RunBlocks([np.random.default_rng(s) for s in (1, 2)], [SYSTEM, SYSTEM]))
    mixed = SystemConfig(alpha=(1 / 24, 1 / 12, 1 / 12), U_bar=(1.0, 0.6, 0.8),
                         p=(800.0, 1000.0, 1200.0))
    run_month(Theta.nominal(mixed), make_solver(MPC(mixed), MPCConfig(backend="kernel")),
              Prices.month(mixed, 16), mixed, np.random.default_rng(0))
    month = compiled_month.module(kernel_sizes.kernels(SYSTEM.n, SYSTEM.N))
    assert len(month.month_parallel.signatures) == 1


def _same_draws(hourly, at_once, shape, system, std) -> np.ndarray:
    """Assert that :func:`_month_draws` from ``at_once`` gives the Python loop's hour-by-hour
    draws from ``hourly`` (the exploration, then the noise, every hour) to the last bit;
    returns the noise."""
    from mpcrl_lite.sim.closed_loop import _draw_noise, _month_draws

    H, D, n = shape
    e, noise = ([] if std else None), []
    for _ in range(H):
        if std:
            e.append(std * hourly.standard_normal((D, n)))
        noise.append(_draw_noise(hourly, (D, n), system))
    e_all, noise_all = _month_draws(at_once, shape, system, std)
    np.testing.assert_array_equal(noise_all, np.array(noise))
    if std:
        np.testing.assert_array_equal(e_all, np.array(e))
    else:
        assert e_all is None
    return noise_all


@pytest.mark.parametrize("system", [SYSTEM, SystemConfig(noise_mean=(0.1, 0.0, -0.05),
                                                         noise_var=(1.0, 0.5, 0.25))])
@pytest.mark.parametrize("std", [None, 0.3])
def test_a_months_draws_at_once_are_the_hours_draws(system, std):
    """The compiled month draws its exploration and noise in one call of the generator: the
    numbers of the Python loop's hour-by-hour draws to the last bit, and the generator left
    where the loop leaves it."""
    hourly, at_once = np.random.default_rng(11), np.random.default_rng(11)
    _same_draws(hourly, at_once, (24, 7, system.n), system, std)
    assert hourly.standard_normal() == at_once.standard_normal()


@pytest.mark.parametrize("std", [None, 0.3])
def test_a_months_draws_at_once_for_runs_in_lockstep(std):
    """Runs in lockstep with systems of their own: each block of days gets its run's draws,
    the numbers of the Python loop's hour-by-hour draws through :class:`RunBlocks`."""
    systems = [SYSTEM, SystemConfig(noise_mean=0.2, noise_var=0.25)]

    def blocks():
        return RunBlocks([np.random.default_rng(s) for s in (5, 6)], systems)

    hourly, at_once = blocks(), blocks()
    noise = _same_draws(hourly, at_once, (24, 6, SYSTEM.n), SYSTEM, std)
    assert not np.array_equal(noise[:, :3], noise[:, 3:])
    for a, b in zip(hourly.rngs, at_once.rngs, strict=True):
        assert a.standard_normal() == b.standard_normal()
