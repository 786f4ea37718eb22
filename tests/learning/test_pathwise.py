"""The pathwise policy gradient (mpcrl_lite.learning.pathwise): the exact derivative of J on the
same noise (finite differences in theta, through the low-level controller's clipping too), the
same gradient as the replayed days of rollout_policy_gradient, the learner option
LearningConfig.gradient = 'pathwise' and its refusals."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
from conftest import run_cli

from mpcrl_lite.bounds.baselines import load_class_best
from mpcrl_lite.config import LearningConfig, MPCConfig, SystemConfig
from mpcrl_lite.learning.experiment import Experiment
from mpcrl_lite.learning.history import History
from mpcrl_lite.learning.pathwise import PathwiseRecorder, pathwise_policy_gradient
from mpcrl_lite.learning.rollout_gradient import rollout_policy_gradient
from mpcrl_lite.mpc.backends.registry import make_solver
from mpcrl_lite.mpc.formulation import MPC
from mpcrl_lite.sim.closed_loop import MPCPolicy, run_month, simulate
from mpcrl_lite.system.battery import sample_noise
from mpcrl_lite.system.prices import Prices
from mpcrl_lite.theta import Theta

ROOT = Path(__file__).resolve().parents[2]
SYSTEM = SystemConfig()
DAYS = 3
H = SYSTEM.hours_per_day
N_THETA = Theta.nominal(SYSTEM).to_vector().size


@pytest.fixture(scope="module")
def setup():
    prices = Prices.month(SYSTEM, DAYS)
    solver = make_solver(MPC(SYSTEM), MPCConfig(), Theta.nominal(SYSTEM))
    noise = sample_noise(np.random.default_rng(5), (H, DAYS, SYSTEM.n), SYSTEM)
    return prices, solver, noise


def _J(solver, prices, noise, theta, system=SYSTEM, soc0=None):
    record = simulate(MPCPolicy(solver, theta, prices), prices.buy[:, :H], prices.sell[:, :H],
                      system, noise=noise, soc0=soc0)
    return record.J()


def _fd_errors(solver, prices, noise, theta, grad, system=SYSTEM, soc0=None, trials=4):
    """Errors of grad's directional derivatives against central differences of J along
    random directions, relative to ``|grad| . |step|``. The steps are small enough that no
    kink of the cost (soc penalty, buy against sell, the low-level controller) is crossed:
    at 1e-5 one direction of the nominal case crosses one and is off by 1.6 %, at 1e-6 all
    agree to about 1e-7."""
    v0 = theta.to_vector()
    rng = np.random.default_rng(3)
    scale = np.abs(grad) / np.abs(grad).max()
    errors = []
    for _ in range(trials):
        step = 1e-6 * rng.standard_normal(v0.size) * scale
        fd = (_J(solver, prices, noise, Theta.from_vector(v0 + step, system.n), system, soc0)
              - _J(solver, prices, noise, Theta.from_vector(v0 - step, system.n), system,
                   soc0)) / 2.0
        errors.append(abs(fd - grad @ step) / (np.abs(grad) @ np.abs(step)))
    return errors


@pytest.mark.parametrize("which", ["nominal", "class_best"])
def test_it_is_the_derivative_of_J_on_the_same_noise(setup, which):
    """Along random directions the central difference of J(theta) on the same noise equals
    the pathwise gradient's directional derivative, to the solver's precision (not a few per
    cent as for replays over a finite nudge: the derivative is exact)."""
    prices, solver, noise = setup
    theta = (Theta.nominal(SYSTEM) if which == "nominal"
             else load_class_best(ROOT / "data" / "class_best_paper")["theta_best"])
    result = pathwise_policy_gradient(theta, solver, prices, SYSTEM, noise)
    assert result.ok.all() and result.grad.shape == (N_THETA,)
    assert np.isfinite(result.grad).all() and np.abs(result.grad).max() > 0
    np.testing.assert_allclose(result.per_day.mean(axis=0), result.grad)
    errors = _fd_errors(solver, prices, noise, theta, result.grad)
    assert max(errors) < 1e-5, errors


def test_it_agrees_with_the_replayed_days(setup):
    """Two independent computations of the same gradient: the replays of
    rollout_policy_gradient with a small nudge and the forward derivative."""
    prices, solver, noise = setup
    theta = load_class_best(ROOT / "data" / "class_best_paper")["theta_best"]
    pathwise = pathwise_policy_gradient(theta, solver, prices, SYSTEM, noise)
    replayed = rollout_policy_gradient(theta, solver, prices, SYSTEM, noise, eps=1e-4)
    assert replayed.ok.all()
    np.testing.assert_allclose(pathwise.grad, replayed.grad,
                               atol=1e-3 * np.abs(replayed.grad).max())


def test_the_state_sensitivity_from_the_adjoint_is_the_central_difference(setup):
    """The kernel forms d pi / d soc from its sensitivity's adjoint; a back-end that does not
    (the numpy batch solver) gets it by central differences: the same gradient, and the
    recorder's central differences on the kernel's solutions too."""
    prices, solver, noise = setup
    theta = load_class_best(ROOT / "data" / "class_best_paper")["theta_best"]
    exact = pathwise_policy_gradient(theta, solver, prices, SYSTEM, noise)
    batch = make_solver(MPC(SYSTEM), MPCConfig(backend="batch"), theta)
    assert batch.sensitivity(batch.solve_batch(np.full((1, 3), 0.5), prices.buy[:1, :12],
                                               prices.sell[:1, :12], theta)).grad_soc0 is None
    measured = pathwise_policy_gradient(theta, batch, prices, SYSTEM, noise)
    assert exact.ok.all() and measured.ok.all()
    scale = np.abs(exact.grad).max()
    np.testing.assert_allclose(measured.grad, exact.grad, atol=1e-6 * scale)

    class Counted:  # the kernel, counting the problems solved; optionally without grad_soc0
        def __init__(self, inner, state_sensitivity):
            self.inner, self.mpc, self.name = inner, inner.mpc, inner.name
            self.state_sensitivity, self.rows = state_sensitivity, 0

        def solve_batch(self, soc0, *args, **kwargs):
            self.rows += len(soc0)
            return self.inner.solve_batch(soc0, *args, **kwargs)

        def sensitivity(self, sol):
            sens = self.inner.sensitivity(sol)
            return sens if self.state_sensitivity else dataclasses.replace(sens, grad_soc0=None)

    adjoint, differences = Counted(solver, True), Counted(solver, False)
    again = pathwise_policy_gradient(theta, adjoint, prices, SYSTEM, noise)
    differenced = pathwise_policy_gradient(theta, differences, prices, SYSTEM, noise)
    np.testing.assert_array_equal(again.grad, exact.grad)
    assert adjoint.rows == H * DAYS  # the policy's own problems only
    assert differences.rows == H * DAYS * (1 + 2 * SYSTEM.n)  # and 2 n shifted copies
    assert not np.array_equal(differenced.grad, exact.grad)  # two computations...
    np.testing.assert_allclose(differenced.grad, exact.grad, atol=1e-6 * scale)  # ...that agree


def test_stacked_draws_are_the_draws_alone(setup):
    """K draws of the month stacked as evaluate_mpc stacks them: the days of each draw are
    those of the draw alone, and the gradient is the mean over all."""
    prices, solver, noise = setup
    theta = Theta.nominal(SYSTEM)
    other = sample_noise(np.random.default_rng(6), (H, DAYS, SYSTEM.n), SYSTEM)
    both = pathwise_policy_gradient(theta, solver, prices, SYSTEM,
                                    np.concatenate([noise, other], axis=1))
    alone = [pathwise_policy_gradient(theta, solver, prices, SYSTEM, z) for z in (noise, other)]
    np.testing.assert_allclose(both.per_day, np.concatenate([a.per_day for a in alone]),
                               rtol=1e-9, atol=1e-9 * np.abs(both.per_day).max())
    np.testing.assert_allclose(both.grad, (alone[0].grad + alone[1].grad) / 2, rtol=1e-9,
                               atol=1e-9 * np.abs(both.grad).max())


def test_the_low_level_controllers_clipping_is_differentiated():
    """With large noise and a start near empty the low-level controller clips many hours (the
    applied power is then the bound's, not the MPC's); the derivative still equals finite
    differences of J."""
    system = SystemConfig(noise_var=0.5)
    prices = Prices.month(system, DAYS)
    solver = make_solver(MPC(system), MPCConfig(), Theta.nominal(system))
    noise = sample_noise(np.random.default_rng(11), (H, DAYS, system.n), system)
    theta = Theta.nominal(system)
    record = simulate(MPCPolicy(solver, theta, prices), prices.buy[:, :H], prices.sell[:, :H],
                      system, noise=noise, soc0=0.05)
    clipped = np.count_nonzero(record.correction)
    assert clipped >= 10, clipped  # the case under test occurs
    result = pathwise_policy_gradient(theta, solver, prices, system, noise, soc0=0.05)
    assert result.ok.all()
    errors = _fd_errors(solver, prices, noise, theta, result.grad, system, soc0=0.05)
    assert max(errors) < 1e-5, errors


def test_batteries_that_differ():
    """A mixed site (each battery its own alpha, noise and penalty weight, one parameter set
    each): the derivative still equals finite differences of J."""
    system = SystemConfig(alpha=(1 / 24, 1 / 12, 1 / 12), noise_var=(1.0, 0.5, 0.5),
                          p=(800.0, 1000.0, 1200.0))
    prices = Prices.month(system, DAYS)
    theta = Theta.nominal(system)
    solver = make_solver(MPC(system), MPCConfig(), theta)
    noise = sample_noise(np.random.default_rng(9), (H, DAYS, system.n), system)
    result = pathwise_policy_gradient(theta, solver, prices, system, noise)
    assert result.ok.all()
    errors = _fd_errors(solver, prices, noise, theta, result.grad, system)
    assert max(errors) < 1e-5, errors


def test_bad_input_is_refused(setup):
    prices, solver, noise = setup
    theta = Theta.nominal(SYSTEM)
    with pytest.raises(ValueError, match="expected a Theta with n=3"):
        pathwise_policy_gradient(Theta.nominal(SystemConfig(n=2)), solver, prices, SYSTEM, noise)
    with pytest.raises(ValueError, match="noise has shape"):
        pathwise_policy_gradient(theta, solver, prices, SYSTEM, noise[:, :, :2])
    with pytest.raises(ValueError, match="K >= 1 draws"):
        pathwise_policy_gradient(theta, solver, prices, SYSTEM, noise[:, :2])
    with pytest.raises(ValueError, match="soc_step"):
        PathwiseRecorder(solver, SYSTEM, soc_step=0.0)
    with pytest.raises(ValueError, match="expected a SystemConfig"):
        PathwiseRecorder(solver, "system")
    with pytest.raises(ValueError, match="no hour recorded"):
        PathwiseRecorder(solver, SYSTEM).result()
    # the derivative is the deterministic policy's: an explored loop is refused
    with pytest.raises(ValueError, match="without exploration"):
        run_month(theta, solver, prices, SYSTEM, np.random.default_rng(0), exploration_std=0.2,
                  on_hour=[PathwiseRecorder(solver, SYSTEM)])
    with pytest.raises(ValueError, match="no sensitivity"):
        run_month(theta, solver, prices, SYSTEM, np.random.default_rng(0), sensitivities=False,
                  on_hour=[PathwiseRecorder(solver, SYSTEM)])


# -- the learner option -------------------------------------------------------------------
def test_the_learner_follows_the_pathwise_gradient_of_its_month():
    """A month of the 'pathwise' learner is the deterministic policy's (no exploration),
    and its gradient is pathwise_policy_gradient at the month's theta on the month's noise."""
    learning = LearningConfig(gradient="pathwise", days_per_month=DAYS, months=2, eval_every=0)
    exp = Experiment(SYSTEM, MPCConfig(), learning)
    assert exp.month_options()["exploration_std"] == 0.0
    theta = exp.begin_month()
    record = run_month(theta, exp.solver, exp.prices, SYSTEM, exp.rng, **exp.month_options())
    np.testing.assert_array_equal(record.a, record.policy)
    grad, skipped, info = exp.learning_step(record)
    expected = pathwise_policy_gradient(theta, exp.solver, exp.prices, SYSTEM, record.noise)
    np.testing.assert_array_equal(grad, expected.grad)
    assert skipped == 0 and info["days_used"] == DAYS
    before = exp.theta.to_vector()
    exp.end_month(record, theta, 0.0)
    assert not np.array_equal(exp.theta.to_vector(), before)


def test_a_month_run_by_the_learner_solves_each_problem_once_and_learns_the_same():
    """``run_one_month`` records the pathwise gradient while the month runs: one solver call
    an hour instead of two, and the same record, gradient and theta, bit for bit, as the
    month simulated first and differentiated after (the route of runs in lockstep)."""
    learning = LearningConfig(gradient="pathwise", days_per_month=DAYS, months=2, eval_every=0)
    one, two = Experiment(SYSTEM, MPCConfig(), learning), Experiment(SYSTEM, MPCConfig(), learning)
    calls = []
    solve = one.solver.solve_batch
    one.solver.solve_batch = lambda *a, **k: calls.append(1) or solve(*a, **k)
    for month in range(2):
        del calls[:]
        rec_one = one.run_one_month()
        assert len(calls) == H, month  # the month's hours, no second pass
        theta = two.begin_month()
        rec_two = run_month(theta, two.solver, two.prices, SYSTEM, two.rng,
                            **two.month_options())
        two.end_month(rec_two, theta, 0.0)
        for field in ("soc", "a", "policy", "stage_cost", "noise", "solver_ok", "sens_ok"):
            np.testing.assert_array_equal(getattr(rec_one, field), getattr(rec_two, field))
        assert rec_one.grad_pi is None and not rec_one.sens_ok.any()
        np.testing.assert_array_equal(one.theta.to_vector(), two.theta.to_vector())
        np.testing.assert_array_equal(one.history.grad_norm, two.history.grad_norm)
    assert one._pathwise is None  # used once, not kept


def test_the_gradient_option_is_validated_and_stored_as_before():
    assert LearningConfig().gradient == "critic"
    assert "gradient" not in LearningConfig().to_dict()  # files of critic runs unchanged
    config = LearningConfig(gradient="pathwise")
    assert LearningConfig.from_dict(config.to_dict()) == config
    assert LearningConfig.from_dict(LearningConfig().to_dict()).gradient == "critic"
    with pytest.raises(ValueError, match="gradient='sarsa'"):
        LearningConfig(gradient="sarsa")
    for bad in ({"learner": "q"}, {"optimizer": "natural"}, {"max_policy_change": 0.1}):
        with pytest.raises(ValueError, match="gradient='pathwise' with"):
            LearningConfig(gradient="pathwise", **bad)
    from mpcrl_lite.decentralized.learner import DecentralizedExperiment
    with pytest.raises(ValueError, match="decentralized learners use their critics"):
        DecentralizedExperiment(SYSTEM, MPCConfig(), LearningConfig(gradient="pathwise"))


def test_learn_gradient_on_the_command_line(tmp_path, capsys):
    """learn --gradient pathwise runs and records it; a resume keeps it and refuses another
    one in one line, leaving the run as it was; --decentralized refuses it."""

    out = tmp_path / "run"
    common = ["learn", "--days", "3", "--out", str(out), "--no-figures", "--eval-draws", "1"]
    status, _, err = run_cli([*common, "--months", "2", "--gradient", "pathwise"], capsys)
    assert status == 0, err
    assert History.load(out).learning.gradient == "pathwise"
    before = (out / "history.npz").read_bytes()
    status, _, err = run_cli([*common, "--months", "3", "--resume", "--gradient", "critic"],
                             capsys)
    assert status == 2 and "learns with 'pathwise'" in err and len(err.strip().splitlines()) == 1
    assert (out / "history.npz").read_bytes() == before
    status, _, err = run_cli([*common, "--months", "3", "--resume"], capsys)
    assert status == 0, err
    resumed = History.load(out)
    assert resumed.months == 3 and resumed.learning.gradient == "pathwise"
    status, _, err = run_cli(["learn", "--months", "1", "--out", str(tmp_path / "d"),
                              "--decentralized", "--gradient", "pathwise"], capsys)
    assert status == 2 and "--decentralized" in err


def test_the_terminal_scale_follows_the_gradient_unless_given():
    from mpcrl_lite.config import PATHWISE_TERMINAL_SCALE, TERMINAL_SCALE
    from mpcrl_lite.learning.dpg import DPGUpdater

    assert LearningConfig().terminal_scale == TERMINAL_SCALE == 100.0
    assert LearningConfig(gradient="pathwise").terminal_scale == PATHWISE_TERMINAL_SCALE
    assert LearningConfig().replace(gradient="pathwise").terminal_scale == PATHWISE_TERMINAL_SCALE
    given = LearningConfig(terminal_scale=500.0)
    assert given.replace(gradient="pathwise").terminal_scale == 500.0
    assert "terminal_scale" not in LearningConfig().to_dict()
    assert LearningConfig.from_dict(given.to_dict()) == given
    # a pathwise config with the critic's scale is written without the field (the value of
    # configs from before it) and must read back with 100, not with the pathwise default
    slow = LearningConfig(gradient="pathwise", terminal_scale=TERMINAL_SCALE)
    assert "terminal_scale" not in slow.to_dict()
    assert LearningConfig.from_dict(slow.to_dict()).terminal_scale == TERMINAL_SCALE
    assert LearningConfig.from_dict(slow.to_dict()) == slow
    wide = LearningConfig(gradient="pathwise")
    assert wide.to_dict()["terminal_scale"] == PATHWISE_TERMINAL_SCALE
    assert LearningConfig.from_dict(wide.to_dict()) == wide
    with pytest.raises(ValueError, match="terminal_scale"):
        LearningConfig(terminal_scale=0.0)
    # Adam's scale of the terminal weights, and of nothing else
    n = SYSTEM.n
    default = DPGUpdater.from_configs(LearningConfig(), SYSTEM).scale
    wide = DPGUpdater.from_configs(LearningConfig(gradient="pathwise"), SYSTEM).scale
    terminal = np.concatenate([np.arange(n * 10)[Theta.index(n, p)] for p in ("T1", "T2", "T3")])
    np.testing.assert_array_equal(default[terminal], 100.0)
    np.testing.assert_array_equal(wide[terminal], 3000.0)
    rest = np.setdiff1d(np.arange(default.size), terminal)
    np.testing.assert_array_equal(default[rest], wide[rest])


def test_a_resume_keeps_the_terminal_scale(tmp_path, capsys):
    out = tmp_path / "run"
    common = ["learn", "--days", "3", "--out", str(out), "--no-figures", "--eval-draws", "1"]
    status, _, err = run_cli([*common, "--months", "1", "--terminal-scale", "250"], capsys)
    assert status == 0, err
    status, _, err = run_cli([*common, "--months", "2", "--resume", "--terminal-scale", "300"],
                             capsys)
    assert status == 2 and "learns with 250.0" in err
    status, _, err = run_cli([*common, "--months", "2", "--resume"], capsys)
    assert status == 0, err
    assert History.load(out).learning.terminal_scale == 250.0
