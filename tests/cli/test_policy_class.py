"""Named policy classes (``config.POLICY_CLASSES``, ``--policy-class``): the horizon and the
forecast they set, recorded in every output, kept on resume and refused when they change."""

from __future__ import annotations

import json

import numpy as np
import pytest

from mpcrl_lite.bounds.causal import table as causal_table
from mpcrl_lite.cli.main import main
from mpcrl_lite.config import (
    POLICY_CLASSES,
    MPCConfig,
    SystemConfig,
    policy_class_configs,
    policy_class_of,
)
from mpcrl_lite.learning.history import History


def run_cli(args, capsys):
    code = main([str(a) for a in args])
    return code, capsys.readouterr().err.strip().splitlines()


@pytest.mark.parametrize("name", sorted(POLICY_CLASSES))
def test_a_class_sets_its_horizon_and_forecast_and_is_named_back(name):
    cls = POLICY_CLASSES[name]
    base = SystemConfig(P_bar=1.5)
    system, mpc = policy_class_configs(name, base, MPCConfig(tau=0.2))
    assert (system.N, mpc.forecast) == (cls.N, cls.forecast)
    assert system.P_bar == 1.5 and mpc.tau == 0.2  # every other field kept
    assert policy_class_of(system, mpc) == name
    assert cls.extension == (name != "paper")


def test_the_default_configs_are_the_papers_class_and_others_name_none():
    assert policy_class_of(SystemConfig(), MPCConfig()) == "paper"
    assert policy_class_of(SystemConfig(N=6), MPCConfig()) is None
    with pytest.raises(ValueError, match="'rest_of_the_day'"):
        policy_class_configs("rest_of_the_day")


def test_the_stored_j_star_does_not_depend_on_the_mpcs_horizon():
    """J* is a property of the true system: the MPC's horizon N does not change it."""
    default = causal_table.stored_bound(SystemConfig())
    longer = causal_table.stored_bound(SystemConfig(N=24))
    assert default is not None and longer is not None
    assert longer.J_star == default.J_star
    assert causal_table.stored_bound(SystemConfig(alpha=0.2)) is None  # the system counts


def test_learn_records_the_class_keeps_it_on_resume_and_refuses_another(tmp_path, capsys):
    out = tmp_path / "run"
    base = ["learn", "--days", "1", "--out", out, "--no-figures", "--quiet"]
    code, err = run_cli([*base, "--months", "1", "--policy-class", "rest_of_day"], capsys)
    assert code == 0, err
    assert json.loads((out / "summary.json").read_text())["policy_class"] == "rest_of_day"
    history = History.load(out)
    assert (history.system.N, history.mpc.forecast) == (24, "until_midnight")
    assert history.policy_class == "rest_of_day"
    before = (out / "checkpoint.json").read_bytes()
    for other in (["--policy-class", "paper"], ["--policy-class", "day_end"]):
        code, err = run_cli([*base, "--months", "2", "--resume", *other], capsys)
        assert code == 2 and len(err) == 1, err
        assert (out / "checkpoint.json").read_bytes() == before
    code, err = run_cli([*base, "--months", "2", "--resume"], capsys)  # the run's own class
    assert code == 0, err
    assert History.load(out).months == 2 and History.load(out).system.N == 24


def test_a_class_and_a_contradicting_forecast_are_one_line(tmp_path, capsys):
    out = tmp_path / "x"
    code, err = run_cli(["learn", "--months", "1", "--days", "1", "--out", out, "--quiet",
                         "--policy-class", "day_end", "--forecast", "paper"], capsys)
    assert code == 2 and len(err) == 1
    assert "--policy-class day_end" in err[0] and "until_midnight" in err[0]
    assert not out.exists()


def test_a_bad_class_name_is_one_line(tmp_path, capsys):
    with pytest.raises(SystemExit) as exit_:
        main(["learn", "--policy-class", "midnight", "--out", str(tmp_path / "y")])
    assert exit_.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert "'midnight'" in err[-1] and "rest_of_day" in err[-1]


def test_simulate_with_a_class_plans_over_its_horizon(tmp_path, capsys):
    runs = {}
    for name in ("day_end", "rest_of_day"):
        out = tmp_path / name
        code, err = run_cli(["simulate", "--days", "1", "--seed", "3", "--quiet", "--out", out,
                             "--policy-class", name], capsys)
        assert code == 0, err
        runs[name] = json.loads((out / "summary.json").read_text())
        assert runs[name]["system"]["N"] == POLICY_CLASSES[name].N
        assert runs[name]["mpc"]["forecast"] == "until_midnight"
    assert not np.isclose(runs["day_end"]["J"], runs["rest_of_day"]["J"], rtol=1e-9)


def test_tune_records_the_class(tmp_path, capsys):
    out = tmp_path / "tune"
    code, err = run_cli(["tune", "--out", out, "--evals", "4", "--popsize", "2", "--draws", "1",
                         "--heldout-draws", "2", "--days", "1", "--quiet",
                         "--policy-class", "rest_of_day"], capsys)
    assert code == 0, err
    result = json.loads((out / "tune.json").read_text())
    assert result["policy_class"] == "rest_of_day"
    assert result["system"]["N"] == 24 and result["forecast"] == "until_midnight"


def test_evaluate_judges_a_run_in_another_class_and_refuses_a_contradiction(tmp_path, capsys):
    run = tmp_path / "run"
    code, err = run_cli(["learn", "--months", "1", "--days", "1", "--out", run, "--no-figures",
                         "--quiet"], capsys)
    assert code == 0, err
    out = tmp_path / "eval"
    code, err = run_cli(["evaluate", "--history", run, "--days", "1", "--draws", "1", "--out",
                         out, "--policy-class", "rest_of_day"], capsys)
    assert code == 0, err
    summary = json.loads((out / "summary.json").read_text())
    assert summary["policy_class"] == "rest_of_day"
    assert summary["system"]["N"] == 24 and summary["mpc"]["forecast"] == "until_midnight"
    code, err = run_cli(["evaluate", "--history", run, "--days", "1", "--draws", "1", "--out",
                         tmp_path / "bad", "--policy-class", "day_end", "--forecast", "paper"],
                        capsys)
    assert code == 2 and len(err) == 1 and "--policy-class day_end" in err[0]
