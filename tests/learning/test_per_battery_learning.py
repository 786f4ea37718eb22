"""Learning on a mixed site: tying within groups of identical batteries, each battery's own
step scale, the run's files with per-battery fields, the decentralized learner."""

from __future__ import annotations

import json

import numpy as np

from mpcrl_lite.cli.main import main
from mpcrl_lite.config import LearningConfig, MPCConfig, SystemConfig
from mpcrl_lite.decentralized.learner import DecentralizedExperiment
from mpcrl_lite.learning.dpg import DPGUpdater
from mpcrl_lite.learning.experiment import Experiment
from mpcrl_lite.learning.history import History
from mpcrl_lite.theta import PARTS, Theta

MIXED = SystemConfig(alpha=(1 / 24, 1 / 12, 1 / 12), noise_var=(1.0, 0.5, 0.5))


def test_tie_agents_ties_only_identical_batteries():
    up = DPGUpdater.from_configs(LearningConfig(), MIXED)
    assert up.groups == (0, 1, 1)
    g = np.random.default_rng(0).normal(size=10 * 3)
    tied = up.effective_gradient(g).reshape(len(PARTS), 3)
    raw = np.where(up.mask, g, 0.0).reshape(len(PARTS), 3)
    np.testing.assert_array_equal(tied[:, 0], raw[:, 0])  # the large battery on its own
    np.testing.assert_allclose(tied[:, 1], raw[:, 1:].mean(axis=1), rtol=1e-15)
    np.testing.assert_array_equal(tied[:, 1], tied[:, 2])
    # identical batteries: one group, the mean over all of them as before
    same = DPGUpdater.from_configs(LearningConfig(), SystemConfig())
    assert same.groups is None
    tied = same.effective_gradient(g).reshape(len(PARTS), 3)
    np.testing.assert_array_equal(tied, np.broadcast_to(
        np.where(same.mask, g, 0.0).reshape(len(PARTS), 3).mean(axis=1, keepdims=True),
        (len(PARTS), 3)))


def test_each_battery_scales_its_own_model_parts():
    up = DPGUpdater.from_configs(LearningConfig(), MIXED)
    np.testing.assert_array_equal(up.scale[Theta.index(3, "alpha")], MIXED.alpha)
    np.testing.assert_array_equal(up.scale[Theta.index(3, "delta")], MIXED.alpha)
    base = DPGUpdater.from_configs(LearningConfig(), SystemConfig())
    np.testing.assert_array_equal(base.scale[Theta.index(3, "alpha")], [1 / 12] * 3)


def test_a_mixed_site_learns_with_the_small_batteries_tied(tmp_path):
    exp = Experiment(MIXED, MPCConfig(), LearningConfig(months=2, days_per_month=3,
                                                        eval_draws=1))
    history = exp.run()
    theta = history.final_theta()
    np.testing.assert_array_equal(theta.alpha[1], theta.alpha[2])
    assert theta.alpha[0] != theta.alpha[1]
    history.save(tmp_path)
    loaded = History.load(tmp_path)
    assert loaded.system == MIXED
    assert json.loads((tmp_path / "history.json").read_text())["system"]["alpha"] == \
        list(MIXED.alpha)


def test_the_decentralized_learner_runs_a_mixed_site():
    exp = DecentralizedExperiment(MIXED, MPCConfig(), LearningConfig(months=1, days_per_month=2,
                                                                     eval_draws=1))
    history = exp.run()
    assert np.isfinite(history.J).all()
    assert [u.system_alpha for u in exp.updaters] == list(MIXED.alpha)


def test_learn_with_a_system_file_resumes(tmp_path):
    path = tmp_path / "mixed.yaml"
    path.write_text("alpha: [0.041666666666666664, 0.08333333333333333, 0.08333333333333333]\n"
                    "noise_var: [1.0, 0.5, 0.5]\n")
    out = tmp_path / "run"
    base = ["learn", "--system", str(path), "--days", "2", "--eval-draws", "1", "--out",
            str(out), "--quiet", "--no-figures"]
    assert main([*base, "--months", "1"]) == 0
    assert main([*base, "--months", "2", "--resume"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert len(summary["J"]) == 2 and len(summary["J_per_agent"][0]) == 3
