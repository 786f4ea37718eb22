"""LSTD Q-learning with the MPC as Q (:mod:`mpcrl_lite.learning.qlearning`,
:mod:`mpcrl_lite.learning.q_experiment`): TD errors, the TD gradient and Hessians, the
regularised Newton step, the learner's runs, resume and the ``learn --learner q`` command."""

from __future__ import annotations

import json

import numpy as np
import pytest
from conftest import run_cli

from mpcrl_lite.config import LearningConfig, SystemConfig
from mpcrl_lite.learning import rundir
from mpcrl_lite.learning.experiment import Experiment
from mpcrl_lite.learning.history import History
from mpcrl_lite.learning.outdir import RunDirError
from mpcrl_lite.learning.q_experiment import QLearningExperiment
from mpcrl_lite.learning.qlearning import (
    QLearningUpdater,
    regularised_solve,
    td_errors,
    td_gradient,
)
from mpcrl_lite.theta import Theta

SMALL = SystemConfig(N=6)


def test_td_errors_bootstrap_inside_the_day_only():
    cost = np.array([[1.0, 2.0], [3.0, 4.0], [5.0, 6.0]])
    q = np.array([[0.5, 0.5], [1.0, 1.0], [2.0, 2.0]])
    v = np.array([[10.0, 20.0], [30.0, 40.0], [50.0, 60.0]])
    delta = td_errors(cost, q, v, 0.9)
    expected = np.array([[1 + 0.9 * 30 - 0.5, 2 + 0.9 * 40 - 0.5],
                         [3 + 0.9 * 50 - 1.0, 4 + 0.9 * 60 - 1.0],
                         [5 - 2.0, 6 - 2.0]])
    np.testing.assert_allclose(delta, expected)
    v_after = np.vstack([v, [[7.0, 8.0]]])
    last = td_errors(cost, q, v_after, 0.9, bootstrap_last=True)
    np.testing.assert_allclose(last[-1], [5 + 0.9 * 7 - 2, 6 + 0.9 * 8 - 2])
    with pytest.raises(ValueError, match="H \\+ 1"):
        td_errors(cost, q, v, 0.9, bootstrap_last=True)


def test_td_gradient_is_the_semi_gradient_of_the_squared_td_loss():
    """For a Q linear-quadratic in theta, g and the full Hessian are the derivatives of
    0.5 mean (target - Q(theta))^2 with the target held fixed; 'approx' drops d2Q."""
    rng = np.random.default_rng(0)
    S, k = 7, 3
    A = rng.normal(size=(S, k))
    B = rng.normal(size=(S, k, k))
    B = B + B.transpose(0, 2, 1)
    target = rng.normal(size=S)
    theta = rng.normal(size=k)

    def q(t):
        return A @ t + 0.5 * np.einsum("i,sij,j->s", t, B, t)

    def loss(t):
        return 0.5 * np.mean((target - q(t)) ** 2)

    delta = target - q(theta)
    dq = A + np.einsum("sij,j->si", B, theta)
    g, H = td_gradient(delta, dq, B, "full")
    eps = 1e-6
    g_fd = np.array([(loss(theta + eps * e) - loss(theta - eps * e)) / (2 * eps)
                     for e in np.eye(k)])
    np.testing.assert_allclose(g, g_fd, rtol=1e-6)
    def grad(t):  # the gradient of the loss by the formula, checked above
        return td_gradient(target - q(t), A + np.einsum("sij,j->si", B, t), B, "full")[0]

    H_fd = np.array([(grad(theta + eps * e) - grad(theta - eps * e)) / (2 * eps)
                     for e in np.eye(k)])
    np.testing.assert_allclose(H, H_fd, rtol=1e-6, atol=1e-8)
    g2, Ha = td_gradient(delta, dq, None, "approx")
    np.testing.assert_array_equal(g2, g)
    np.testing.assert_allclose(Ha, dq.T @ dq / S)
    assert td_gradient(delta, dq, None, "none")[1] is None
    with pytest.raises(ValueError, match="d2q"):
        td_gradient(delta, dq, None, "full")


def test_regularised_solve_shifts_only_what_is_not_positive_definite():
    rng = np.random.default_rng(1)
    M = rng.normal(size=(4, 4))
    pd = M @ M.T + np.eye(4)
    g = rng.normal(size=4)
    x, t = regularised_solve(pd, g)
    assert t == 0.0
    np.testing.assert_allclose(pd @ x, g)
    indefinite = pd - 3.0 * np.eye(4) * np.linalg.eigvalsh(pd).max()
    x, t = regularised_solve(indefinite, g)
    assert t > 0 and np.linalg.eigvalsh(indefinite + t * np.eye(4)).min() > 0
    np.testing.assert_allclose((indefinite + t * np.eye(4)) @ x, g)
    # the smallest shift of the doubling sequence: half of it fails
    assert np.linalg.eigvalsh(indefinite + 0.5 * t * np.eye(4)).min() <= 0


def test_regularised_solve_grows_the_shift_by_its_factor():
    """growth=1.05 (mpcrl's schedule) finds a smaller shift than doubling, still the first of
    its own sequence that factorises; a factor <= 1 is refused."""
    rng = np.random.default_rng(2)
    M = rng.normal(size=(5, 5))
    indefinite = M @ M.T - 4.0 * np.eye(5)
    g = rng.normal(size=5)
    _, t2 = regularised_solve(indefinite, g)
    x, t = regularised_solve(indefinite, g, growth=1.05, max_tries=5000)
    lam = np.linalg.eigvalsh(indefinite).min()
    assert -lam < t <= t2 and t <= 1.05 * -lam + 1e-3
    np.testing.assert_allclose((indefinite + t * np.eye(5)) @ x, g)
    assert np.linalg.eigvalsh(indefinite + (t / 1.05) * np.eye(5)).min() <= 0
    with pytest.raises(ValueError, match="growth=1.0: expected a factor > 1"):
        regularised_solve(indefinite, g, growth=1.0)


def test_tied_newton_step_solves_in_the_shared_parameters(system):
    n = system.n
    config = LearningConfig(learner="q", hessian="approx", newton_step=0.5,
                            keep_well_posed=False)
    upd = QLearningUpdater(config, system)
    rng = np.random.default_rng(2)
    J = rng.normal(size=(50, 10 * n))
    H = J.T @ J / 50 + np.eye(10 * n)
    g = rng.normal(size=10 * n)
    theta = Theta.nominal(system)
    new = upd.step(theta, g, H)
    B = np.kron(np.eye(10), np.ones((n, 1)))  # one column per part, ones on its agents
    B = np.delete(B, 6, axis=1)  # phi3 is not learned (T3 is the level of Q)
    d = B @ np.linalg.solve(B.T @ H @ B, B.T @ g)
    np.testing.assert_allclose(new.to_vector(), theta.to_vector() - 0.5 * d, rtol=1e-10)
    assert upd.last_info["newton_shift"] == 0.0
    untied = QLearningUpdater(config.replace(tie_agents=False), system)
    assert untied._basis.shape == (10 * n, 8 * n + 1)  # the level T3 is shared
    # the projection of the policy gradient's updater keeps the MPC a convex QP
    safe = QLearningUpdater(config.replace(keep_well_posed=True), system)
    moved = safe.step(theta, 1e6 * np.abs(g), H)
    assert moved.is_convex() and np.all(moved.alpha >= config.alpha_min)


def test_config_refuses_what_q_learning_cannot_do():
    with pytest.raises(ValueError, match="sensitivity"):
        LearningConfig(learner="q", optimizer="natural")
    with pytest.raises(ValueError, match="learner"):
        LearningConfig(learner="td")
    assert "learner" not in LearningConfig().to_dict()  # DPG files are unchanged
    q = LearningConfig(learner="q", hessian="full")
    assert LearningConfig.from_dict(q.to_dict()) == q


@pytest.fixture(scope="module")
def q_learning():
    return LearningConfig(learner="q", months=3, days_per_month=2, eval_every=2, eval_draws=2,
                          step_size=0.1)


@pytest.mark.parametrize("hessian", ["approx", "full", "none"])
def test_q_learning_runs_and_learns_from_every_sample(q_learning, hessian):
    exp = QLearningExperiment(SMALL, learning=q_learning.replace(hessian=hessian, months=2))
    history = exp.run(progress=False)
    assert history.months == 2 and exp.value.backend == "kernel"
    info = history.update_info[0]
    assert info["samples"] == 48 and info["q_failures"] == 0 and history.skipped_steps == [0, 0]
    assert np.isfinite(info["td_rms"]) and history.grad_norm[0] > 0
    assert history.theta[1] != history.theta[0]
    assert history.learning.learner == "q"


def test_q_learning_on_ipopt_equals_the_kernel(q_learning):
    """The reference back-end's run and the compiled one give the same first update."""
    from mpcrl_lite.config import MPCConfig

    runs = [QLearningExperiment(SMALL, MPCConfig(backend=b), q_learning.replace(months=1,
                                                                                eval_every=0))
            for b in ("ipopt", "kernel")]
    grads = [np.asarray(r.run(progress=False).theta_final) for r in runs]
    assert runs[0].value.backend == "ipopt"
    np.testing.assert_allclose(grads[0], grads[1], rtol=1e-6)


def test_resume_equals_the_run_alone_and_a_mismatch_is_refused(q_learning, tmp_path):
    whole = QLearningExperiment(SMALL, learning=q_learning)
    whole.run(out=tmp_path / "whole", progress=False)
    part = QLearningExperiment(SMALL, learning=q_learning)
    part.run(months=1, out=tmp_path / "part", progress=False)
    resumed = QLearningExperiment(SMALL, learning=q_learning)
    resumed.run(out=tmp_path / "part", resume=True, progress=False)
    got, want = History.load(tmp_path / "part"), History.load(tmp_path / "whole")
    assert got.theta == want.theta and got.J_eval == want.J_eval and got.J == want.J
    checkpoints = [json.loads(rundir.read(d, ["checkpoint.json"]).files["checkpoint.json"])
                   for d in (tmp_path / "part", tmp_path / "whole")]
    assert checkpoints[0] == checkpoints[1]
    with pytest.raises(RunDirError, match="q-learning run"):
        Experiment(SMALL, learning=q_learning.replace(learner="dpg")).run(
            out=tmp_path / "whole", resume=True, progress=False)
    with pytest.raises(RunDirError, match="hessian"):
        QLearningExperiment(SMALL, learning=q_learning.replace(hessian="full")).run(
            out=tmp_path / "whole", resume=True, progress=False)


def test_learn_command_runs_resumes_and_refuses_mismatches(tmp_path, capsys):
    base = ["learn", "--days", "1", "--n", "2", "--quiet", "--no-figures"]
    out = str(tmp_path / "q")
    status, stdout, _ = run_cli([*base, "--months", "1", "--learner", "q", "--out", out], capsys)
    assert status == 0 and json.loads(stdout)["months"] == 1
    status, _, _ = run_cli([*base, "--months", "2", "--out", out, "--resume"], capsys)
    assert status == 0 and History.load(out).learning.learner == "q"
    status, _, err = run_cli([*base, "--months", "3", "--learner", "dpg", "--out", out,
                           "--resume"], capsys)
    assert status == 2 and len(err.strip().splitlines()) == 1 and "q-learning run" in err
    status, _, err = run_cli([*base, "--months", "1", "--hessian", "full", "--out",
                           str(tmp_path / "d")], capsys)
    assert status == 2 and "--learner q" in err
    status, _, err = run_cli([*base, "--months", "1", "--learner", "q", "--decentralized",
                           "--out", str(tmp_path / "e")], capsys)
    assert status == 2 and "decentralized" in err
