"""A critic fitted on several months (``LearningConfig.critic_months``): what each fit sees,
the resume, the checkpoint file, the command line and the refusals."""

from __future__ import annotations

import json

import numpy as np
import pytest
from threadpoolctl import threadpool_limits

from mpcrl_lite import LearningConfig, SystemConfig
from mpcrl_lite._util.threads import BLAS_THREADS
from mpcrl_lite.cli.main import main
from mpcrl_lite.decentralized.learner import DecentralizedExperiment
from mpcrl_lite.learning import experiment as experiment_module
from mpcrl_lite.learning import rundir
from mpcrl_lite.learning.critic_samples import CriticSamples
from mpcrl_lite.learning.experiment import Experiment
from mpcrl_lite.learning.outdir import RunDirError
from mpcrl_lite.learning.step import lstd_policy_gradient
from mpcrl_lite.sim.exploration import exploration_center

SMALL = SystemConfig(N=6)


def experiment(critic_months: int, months: int = 4) -> Experiment:
    learning = LearningConfig(days_per_month=3, months=months, seed=11, eval_every=0,
                              critic_months=critic_months)
    return Experiment(system=SMALL, learning=learning)


def test_each_fit_sees_the_last_k_months_oldest_first(monkeypatch):
    exp = experiment(3)
    months, fits = [], []
    real_run_month, real_fit = experiment_module.run_month, experiment_module.lstd_policy_gradient

    def run_month(*args, **kwargs):
        record = real_run_month(*args, **kwargs)
        center = exploration_center(record.policy, exp.system, exp.learning.exploration_margin)
        # copies: the learner drops grad_pi from the record once it has learned from it
        months.append({"soc": record.soc.copy(), "a": record.a.copy(), "center": center,
                       "grad_pi": record.grad_pi.copy(), "cost": record.stage_cost.copy(),
                       "use": record.sens_ok & record.solver_ok, "buy": record.buy.copy()})
        return record

    def fit(*args, **kwargs):
        grad, info = real_fit(*args, **kwargs)
        fits.append((args, grad))
        return grad, info

    monkeypatch.setattr(experiment_module, "run_month", run_month)
    monkeypatch.setattr(experiment_module, "lstd_policy_gradient", fit)
    history = exp.run(progress=False)
    assert [info["critic_months"] for info in history.update_info] == [1, 2, 3, 3]
    names = ("soc", "a", "center", "grad_pi", "cost", "use")
    for i, (args, grad) in enumerate(fits):
        window = months[max(0, i - 2): i + 1]
        joined = {k: np.concatenate([m[k] for m in window], axis=1) for k in (*names, "buy")}
        for k, value in zip(names, args[:6], strict=True):
            np.testing.assert_array_equal(value, joined[k], err_msg=f"fit {i}: {k}")
        np.testing.assert_array_equal(args[8], joined["buy"])
        assert args[0].shape[1] == 3 * len(window)  # days of every month of the window
        # the update's gradient is the fit of those samples, nothing else (under the
        # learner's BLAS limit: the LSTD system is ill-conditioned enough for the thread
        # count to show in the last digits)
        with threadpool_limits(BLAS_THREADS):
            by_hand, _ = lstd_policy_gradient(*(joined[k] for k in names), exp.learning,
                                              exp.system.gamma, joined["buy"])
        np.testing.assert_array_equal(grad, by_hand)


def test_one_month_is_the_paper_rule_and_more_months_change_the_run():
    one = experiment(1, months=3).run(progress=False)
    assert "critic_months" not in one.update_info[0]
    assert "critic_months" not in one.learning.to_dict()
    two = experiment(2, months=3).run(progress=False)
    # the first update sees one month either way, the second one two months with K = 2
    assert one.grad_norm[0] == two.grad_norm[0]
    assert one.grad_norm[1] != two.grad_norm[1]


def test_a_resumed_run_fits_what_the_uninterrupted_one_did(tmp_path):
    full = experiment(3, months=4).run(progress=False)
    experiment(3, months=4).run(months=2, out=tmp_path, progress=False)
    kept = CriticSamples.from_npz(
        rundir.read(tmp_path, [rundir.CRITIC]).files[rundir.CRITIC], "critic.npz", SMALL.n, 2)
    assert len(kept) == 2 and kept[0].soc.shape == (25, 3, 3)
    resumed = experiment(3, months=4).run(out=tmp_path, resume=True, progress=False)
    assert resumed.grad_norm == full.grad_norm and resumed.theta == full.theta
    np.testing.assert_array_equal(resumed.theta_final, full.theta_final)
    assert [i["critic_months"] for i in resumed.update_info] == [1, 2, 3, 3]


def test_a_run_of_one_month_writes_no_critic_file(tmp_path):
    experiment(1, months=1).run(out=tmp_path, progress=False)
    assert not (tmp_path / rundir.CRITIC).exists()
    assert rundir.CRITIC not in json.loads((tmp_path / rundir.MANIFEST).read_text())["files"]


def month(days: int = 2, n: int = 3, n_theta: int = 5, seed: int = 0) -> CriticSamples:
    rng = np.random.default_rng(seed)
    return CriticSamples(soc=rng.random((25, days, n)), a=rng.random((24, days, n)),
                         center=rng.random((24, days, n)),
                         grad_pi=rng.random((24, days, n_theta, n)), cost=rng.random((24, days)),
                         use=rng.random((24, days)) > 0.1, buy=rng.random((24, days)))


def test_the_months_round_trip_through_the_file():
    months = [month(seed=1), month(seed=2)]
    back = CriticSamples.from_npz(CriticSamples.to_npz(months), "f", 3, 3)
    for got, want in zip(back, months, strict=True):
        for name in ("soc", "a", "center", "grad_pi", "cost", "use", "buy"):
            np.testing.assert_array_equal(getattr(got, name), getattr(want, name))
    assert CriticSamples.from_npz(CriticSamples.to_npz([]), "f", 3, 3) == []
    joined = CriticSamples.join(months)
    assert joined.soc.shape == (25, 4, 3) and joined.grad_pi.shape == (24, 4, 5, 3)
    no_buy = CriticSamples(**{**vars(months[0]), "buy": None})
    assert CriticSamples.join([no_buy, months[1]]).buy is None


@pytest.mark.parametrize("data, n, limit, match", [
    (b"not a zip", 3, 3, "not a readable .npz"),
    (CriticSamples.to_npz([month(), month(), month()]), 3, 2,
     "'months' is 3, expected an integer in \\[0, 2\\]"),
    (CriticSamples.to_npz([month(n=2)]), 3, 3, "month 0: soc has shape \\(25, 2, 2\\)"),
    (CriticSamples.to_npz([month(), month(n_theta=4)]), 3, 3, "month 1 has grad_pi"),
    (CriticSamples.to_npz([CriticSamples(**{**vars(month()), "use": np.ones((24, 2))})]), 3, 3,
     "month 0: use has dtype float64, expected bool"),
    (CriticSamples.to_npz([CriticSamples(**{**vars(month()), "cost": np.ones((24, 3))})]), 3, 3,
     "month 0: cost has shape \\(24, 3\\), expected \\(24, 2\\)"),
])
def test_a_bad_critic_file_is_refused_naming_it(data, n, limit, match):
    with pytest.raises(RunDirError, match=f"DIR/critic.npz: {match}"):
        CriticSamples.from_npz(data, "DIR/critic.npz", n, limit)


def test_a_run_of_several_months_without_its_critic_file_is_refused(tmp_path):
    exp = experiment(2)
    with pytest.raises(RunDirError, match="critic.npz is missing: a run with critic_months=2"):
        exp.restore_extra_files({}, tmp_path)


@pytest.mark.parametrize("changes, match", [
    ({"critic_months": 0}, "critic_months=0: expected an integer >= 1"),
    ({"critic_months": 25}, "critic_months=25: expected a value in \\[1, 24\\]"),
    ({"critic_months": 2, "gradient": "pathwise"}, "only the compatible critic"),
    ({"critic_months": 2, "learner": "q"}, "only the compatible critic"),
])
def test_bad_settings_are_refused(changes, match):
    with pytest.raises(ValueError, match=match):
        LearningConfig(**changes)


def test_the_decentralized_learner_refuses_it():
    with pytest.raises(ValueError, match="critic_months=2: each decentralized learner"):
        DecentralizedExperiment(learning=LearningConfig(days_per_month=1, critic_months=2))


def test_learn_records_it_and_a_resume_keeps_it(tmp_path, capsys):
    out = tmp_path / "run"
    common = ["learn", "--days", "2", "--out", str(out), "--quiet", "--no-figures",
              "--eval-draws", "1"]
    assert main([*common, "--months", "2", "--critic-months", "3"]) == 0
    history = json.loads((out / "history.json").read_text())
    assert history["learning"]["critic_months"] == 3
    assert [i["critic_months"] for i in history["update_info"]] == [1, 2]
    assert main([*common, "--months", "3", "--resume"]) == 0
    info = json.loads((out / "history.json").read_text())["update_info"]
    assert info[-1]["critic_months"] == 3
    capsys.readouterr()
    assert main([*common, "--months", "4", "--resume", "--critic-months", "2"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--critic-months 2 with --resume" in err[0] and "3" in err[0], err
    assert main(["learn", "--months", "1", "--out", str(tmp_path / "d"), "--decentralized",
                 "--critic-months", "2"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--critic-months 2 with --decentralized" in err[0], err


def test_study_gives_it_to_every_run(tmp_path):
    out = tmp_path / "study"
    assert main(["study", "--seeds", "2", "--months", "2", "--days", "2", "--eval-draws", "1",
                 "--critic-months", "2", "--workers", "0", "--out", str(out), "--quiet",
                 "--j-star", "-100"]) == 0
    for seed in (0, 1):
        config = json.loads((out / "runs" / f"seed={seed}" / "config.json").read_text())
        assert config["learning"]["critic_months"] == 2
        history = json.loads((out / "runs" / f"seed={seed}" / "history.json").read_text())
        assert [i["critic_months"] for i in history["update_info"]] == [1, 2]
