"""Starting the learning from a stored theta: ``LearningConfig.theta0``, ``--theta0 SOURCE`` on
``learn`` and ``study``, and :func:`mpcrl_lite.cli.inputs.read_theta`."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from conftest import run_cli

from mpcrl_lite.cli.inputs import read_theta
from mpcrl_lite.config import LearningConfig, SystemConfig
from mpcrl_lite.learning.experiment import Experiment
from mpcrl_lite.learning.history import History
from mpcrl_lite.theta import Theta

ROOT = Path(__file__).resolve().parents[2]
BEST = ROOT / "data" / "class_best_paper"
SYSTEM = SystemConfig()


def _best() -> Theta:
    return Theta.from_dict(json.loads((BEST / "tune.json").read_text())["theta_best"])


# -- the sources ----------------------------------------------------------------------------
def test_a_tune_result_gives_its_best_theta_as_a_directory_or_a_file():
    for source in (BEST, BEST / "tune.json"):
        theta, what = read_theta(source, SYSTEM.n)
        np.testing.assert_array_equal(theta.to_vector(), _best().to_vector())
        assert "best theta of the search" in what and str(source) in what


def test_a_json_of_parts_and_a_summary_theta_final_are_read(tmp_path):
    theta = Theta.nominal(SYSTEM).replace(T1=np.array([1.0, 2.0, 3.0]))
    plain = tmp_path / "theta.json"
    plain.write_text(json.dumps(theta.to_dict()))
    summary = tmp_path / "summary.json"
    summary.write_text(json.dumps({"months": 3, "theta_final": theta.to_dict()}))
    for source in (plain, summary):
        got, _ = read_theta(source, SYSTEM.n)
        np.testing.assert_array_equal(got.to_vector(), theta.to_vector())


@pytest.mark.parametrize("content, match", [
    ("not json", "not a readable JSON file"),
    ("[1, 2, 3]", "a JSON list"),
    ('{"alpha": [0.1, 0.1, 0.1]}', "lacks parts"),
])
def test_bad_files_are_refused_with_the_source_and_what_was_expected(tmp_path, content, match):
    path = tmp_path / "bad.json"
    path.write_text(content)
    with pytest.raises(ValueError, match=match) as err:
        read_theta(path, SYSTEM.n)
    assert str(path) in str(err.value) and "expected a tune directory" in str(err.value)


def test_another_n_a_missing_path_and_non_finite_entries_are_refused(tmp_path):
    with pytest.raises(ValueError, match="a theta for n=3 batteries; expected n=4"):
        read_theta(BEST, 4)
    with pytest.raises(ValueError, match="no such file or directory"):
        read_theta(tmp_path / "nothing", SYSTEM.n)
    parts = Theta.nominal(SYSTEM).to_dict()
    parts["T2"] = [float("nan")] * 3
    path = tmp_path / "nan.json"
    path.write_text(json.dumps(parts))
    with pytest.raises(ValueError, match="T2.*expected finite numbers"):
        read_theta(path, SYSTEM.n)
    empty = tmp_path / "empty_dir"
    empty.mkdir()
    with pytest.raises(ValueError, match="neither tune.json nor a readable run"):
        read_theta(empty, SYSTEM.n)


# -- the config and the learner ---------------------------------------------------------------
def test_the_config_keeps_the_start_and_writes_it_only_when_set():
    start = tuple(float(x) for x in _best().to_vector())
    learning = LearningConfig(theta0=list(start))
    assert learning.theta0 == start
    assert LearningConfig.from_dict(learning.to_dict()) == learning
    assert "theta0" not in LearningConfig().to_dict()
    with pytest.raises(ValueError, match="not all finite"):
        LearningConfig(theta0=[math.inf] * 30)
    with pytest.raises(ValueError, match="sequence of numbers"):
        LearningConfig(theta0="nominal")


def test_the_learner_starts_at_the_configured_theta_and_checks_its_length():
    start = _best()
    exp = Experiment(learning=LearningConfig(days_per_month=2, eval_every=0,
                                             theta0=tuple(start.to_vector())))
    np.testing.assert_array_equal(exp.theta.to_vector(), start.to_vector())
    history = exp.run(months=1, progress=False)
    np.testing.assert_array_equal(history.theta[0], start.to_vector())
    with pytest.raises(ValueError, match="has 20 entries; expected 10 n = 30"):
        Experiment(learning=LearningConfig(days_per_month=2, theta0=(0.1,) * 20))
    with pytest.raises(ValueError, match="differs from learning.theta0"):
        Experiment(learning=LearningConfig(days_per_month=2, theta0=tuple(start.to_vector())),
                   theta0=Theta.nominal(SYSTEM))


# -- the commands -----------------------------------------------------------------------------
def test_learn_starts_from_the_source_records_it_and_a_resume_keeps_it(tmp_path, capsys):
    out = tmp_path / "run"
    common = ["learn", "--days", "2", "--out", str(out), "--no-figures", "--eval-draws", "1"]
    status, _, err = run_cli([*common, "--months", "1", "--theta0", str(BEST)], capsys)
    assert status == 0, err
    assert f"starting from the best theta of the search in {BEST}" in err
    history = History.load(out)
    np.testing.assert_array_equal(history.theta[0], _best().to_vector())
    summary = json.loads((out / "summary.json").read_text())
    assert summary["theta0"] == _best().to_dict()
    # another start with --resume is refused before any month runs
    status, _, err = run_cli([*common, "--months", "2", "--resume", "--theta0",
                              str(ROOT / "data" / "class_best_day_end")], capsys)
    assert status == 2 and "started from another theta" in err
    assert History.load(out).months == 1
    # without the flag (or with the same source) the run goes on from where it was
    status, _, err = run_cli([*common, "--months", "2", "--resume"], capsys)
    assert status == 0, err
    resumed = History.load(out)
    assert resumed.months == 2 and resumed.learning.theta0 == history.learning.theta0
    # the run directory itself is a source: its last theta
    theta, what = read_theta(out, SYSTEM.n)
    np.testing.assert_array_equal(theta.to_vector(), resumed.final_theta().to_vector())
    assert "last theta of the run" in what


def test_learn_refuses_a_bad_source_before_any_work(tmp_path, capsys):
    out = tmp_path / "run"
    status, _, err = run_cli(["learn", "--months", "1", "--days", "2", "--out", str(out),
                              "--theta0", str(tmp_path / "missing.json")], capsys)
    assert status == 2 and "--theta0" in err and "no such file" in err
    assert not out.exists() or not any(out.iterdir())


def test_study_starts_every_run_there_and_keeps_the_nominal_for_the_gap(tmp_path, capsys):
    common = ["study", "--seeds", "2", "--months", "1", "--days", "2", "--eval-draws", "1",
              "--target", "best_seen", "--quiet", "--workers", "1"]
    status, _, err = run_cli([*common, "--out", str(tmp_path / "nominal")], capsys)
    assert status == 0, err
    status, _, err = run_cli([*common, "--out", str(tmp_path / "best"), "--theta0",
                              str(BEST / "tune.json")], capsys)
    assert status == 0, err
    nominal = pd.read_csv(tmp_path / "nominal" / "study.csv")
    started = pd.read_csv(tmp_path / "best" / "study.csv")
    # the nominal MPC's J on the same draws stays the reference of the gap ...
    np.testing.assert_allclose(started["J_eval_nominal"], nominal["J_eval_nominal"], rtol=1e-12)
    # ... and month 0 evaluates the start, the class's best, in J_eval_start
    assert (started["J_eval_start"] < started["J_eval_nominal"]).all()
    for seed in started["seed"]:
        history = History.load(tmp_path / "best" / "runs" / f"seed={seed}")
        np.testing.assert_array_equal(history.theta[0], _best().to_vector())
        assert started.loc[started["seed"] == seed, "J_eval_start"].item() == history.J_eval[0]
    summary = json.loads((tmp_path / "best" / "study.json").read_text())
    assert summary["theta0"] == [float(x) for x in _best().to_vector()]
    assert "J_eval_start" not in nominal.columns


def test_a_failed_nominal_evaluation_keeps_the_studys_summary(tmp_path, capsys, monkeypatch):
    """The nominal theta is evaluated after every run; a failure there is recorded, not
    raised (the runs' results stay)."""
    from mpcrl_lite.studies import study

    def fail(run, theta):
        raise RuntimeError("solver exploded")

    monkeypatch.setattr(study, "class_on_run_draws", fail)
    out = tmp_path / "best"
    status, _, err = run_cli(["study", "--seeds", "1", "--months", "1", "--days", "2",
                              "--eval-draws", "1", "--target", "best_seen", "--quiet",
                              "--workers", "1", "--out", str(out), "--theta0", str(BEST)],
                             capsys)
    assert status == 0, err
    summary = json.loads((out / "study.json").read_text())
    assert summary["J_nominal_error"] == "RuntimeError: solver exploded"
    table = pd.read_csv(out / "study.csv")
    assert table["J_eval_nominal"].isna().all() and table["J_eval_start"].notna().all()
