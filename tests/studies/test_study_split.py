"""The regret split in ``study --class-best``: each seed's learner gap against a tune result
of the study's class (on its held-out draws, and paired on the runs' own evaluation draws),
the class gap against J*, and a tune result of another class refused before any run."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest

from mpcrl_lite._util import jsonio
from mpcrl_lite.config import LearningConfig, SystemConfig
from mpcrl_lite.studies.study import class_split, run_study
from mpcrl_lite.theta import Theta

HELD = {"mean": -260.0, "ci_low": -267.0, "ci_high": -253.0, "draws": 30}


def tune_dir(path, forecast="paper", system=None):
    path.mkdir(parents=True, exist_ok=True)
    system = system or SystemConfig()
    path.joinpath("tune.json").write_bytes(jsonio.dumps({
        "theta_best": Theta.nominal(system).to_dict(), "J_heldout": HELD, "J_best": -270.0,
        "forecast": forecast, "system": system.to_dict(), "evals": 10}))
    return path


def test_class_split_on_synthetic_seeds():
    table = pd.DataFrame({"seed": [0, 1, 2, 3], "status": ["done", "done", "failed", "done"],
                          "J_eval_final": [-210.0, -250.0, np.nan, -200.0]})
    split = class_split(table, {"J_heldout": HELD}, -401.5)
    assert split["learner_gap"] == {"0": 50.0, "1": 10.0, "3": 60.0}
    assert split["learner_gap_median"] == 50.0
    assert split["learner_gap_worst"] == {"seed": 3, "value": 60.0}
    assert split["class_gap"] == {"mean": 141.5, "ci_low": 134.5, "ci_high": 148.5}
    assert split["J_class_ci"] == [-267.0, -253.0]
    assert "class_gap" not in class_split(table, {"J_heldout": HELD}, None)
    assert "learner_gap_paired" not in split and "J_class_eval" not in split


def test_the_paired_gap_is_against_the_class_on_the_runs_draws():
    table = pd.DataFrame({"seed": [0, 1, 2], "status": ["done", "done", "done"],
                          "J_eval_final": [-210.0, -250.0, -200.0]})
    runs = {"mean": -255.0, "ci_low": -262.0, "ci_high": -248.0, "draws": 10, "seed": 7,
            "J": [-255.0] * 10}
    split = class_split(table, {"J_heldout": HELD}, -401.5, runs)
    assert split["J_class_eval"] == runs
    assert split["learner_gap_paired"] == {"0": 45.0, "1": 5.0, "2": 55.0}
    assert split["learner_gap_paired_median"] == 45.0
    assert split["learner_gap_paired_iqr"] == [25.0, 50.0]
    assert split["learner_gap_paired_worst"] == {"seed": 2, "value": 55.0}
    # the held-out figures are unchanged beside it
    assert split["learner_gap"] == {"0": 50.0, "1": 10.0, "2": 60.0}
    assert split["class_gap"]["mean"] == 141.5


def test_tiny_study_with_class_best(tmp_path):
    base = {"learning.days_per_month": 2, "learning.eval_draws": 2, "learning.eval_every": 1}
    summary = run_study(2, 2, tmp_path / "s", base=base, workers=0, progress=False,
                        J_star=-400.0, class_best=tune_dir(tmp_path / "t"))
    split = summary["class_split"]
    saved = json.loads((tmp_path / "s" / "study.json").read_text())
    assert saved["class_split"] == json.loads(json.dumps(split))
    for seed, regret in summary["regret"].items():
        assert split["learner_gap"][seed] + split["class_gap"]["mean"] == pytest.approx(regret)
    # the class's best theta (here the nominal one) ran on the runs' own draws: the runs'
    # evaluation of month 0, the nominal theta, is the same number
    on_runs = split["J_class_eval"]
    assert on_runs["draws"] == 2 and on_runs["seed"] == LearningConfig().eval_seed
    assert len(on_runs["J"]) == 2 and on_runs["mean"] == pytest.approx(np.mean(on_runs["J"]))
    table = pd.read_csv(tmp_path / "s" / "study.csv")
    for _, row in table.iterrows():
        assert row["J_eval_nominal"] == pytest.approx(on_runs["mean"], rel=1e-12)
        assert split["learner_gap_paired"][str(row["seed"])] == pytest.approx(
            row["J_eval_final"] - on_runs["mean"], rel=1e-12)
    with pytest.raises(ValueError, match="searched for another class"):
        run_study(2, 1, tmp_path / "s2", base=base, workers=0, progress=False, J_star=-400.0,
                  class_best=tune_dir(tmp_path / "u", forecast="until_midnight"))
    assert not (tmp_path / "s2" / "runs").exists()


def test_no_paired_gap_without_evaluations(tmp_path):
    base = {"learning.days_per_month": 2, "learning.eval_every": 0}
    summary = run_study(1, 1, tmp_path / "s", base=base, workers=0, progress=False,
                        J_star=-400.0, target="causal", class_best=tune_dir(tmp_path / "t"))
    assert "J_class_eval" not in summary["class_split"]


def test_the_command_prints_the_paired_gap(tmp_path, capsys):
    from mpcrl_lite.cli.main import main

    assert main(["study", "--seeds", "1", "--months", "2", "--days", "2", "--eval-draws", "2",
                 "--workers", "0", "--j-star", "-400", "--quiet", "--out", str(tmp_path / "s"),
                 "--class-best", str(tune_dir(tmp_path / "t"))]) == 0
    printed = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    saved = json.loads((tmp_path / "s" / "study.json").read_text())["class_split"]
    assert printed["J_class_eval"] == saved["J_class_eval"]["mean"]
    assert printed["learner_gap_paired_median"] == saved["learner_gap_paired_median"]
    assert printed["learner_gap_median"] == saved["learner_gap_median"]


def test_a_failed_paired_evaluation_keeps_the_summary(tmp_path, monkeypatch, caplog):
    from mpcrl_lite.studies import study

    def broken(run, theta):
        raise RuntimeError("no memory left")

    monkeypatch.setattr(study, "class_on_run_draws", broken)
    base = {"learning.days_per_month": 2, "learning.eval_draws": 2, "learning.eval_every": 1}
    summary = run_study(1, 1, tmp_path / "s", base=base, workers=0, progress=False,
                        J_star=-400.0, class_best=tune_dir(tmp_path / "t"))
    split = summary["class_split"]
    assert split["J_class_eval_error"] == "RuntimeError: no memory left"
    assert "learner_gap_paired" not in split and split["learner_gap"]
    saved = json.loads((tmp_path / "s" / "study.json").read_text())
    assert saved["class_split"]["J_class_eval_error"] == split["J_class_eval_error"]
    assert "paired learner gap is left out" in caplog.text


def test_the_segment_between_two_thetas_on_the_run_draws(tmp_path):
    from mpcrl_lite.studies.study import class_on_run_draws, segment_on_run_draws
    from mpcrl_lite.studies.sweep.grid import SweepRun

    base = {"learning.days_per_month": 2, "learning.eval_draws": 2, "learning.eval_every": 1}
    run_study(1, 1, tmp_path / "s", base=base, workers=0, progress=False, J_star=-400.0)
    config = json.loads(next((tmp_path / "s" / "runs").glob("*/config.json")).read_text())
    run = SweepRun.from_config(config)
    start = Theta.nominal(SystemConfig())
    end = start.replace(T1=[40.0] * 3, b=[5.0] * 3, phi2=[-3.0] * 3)
    seg = segment_on_run_draws(run, start, end, points=5)
    assert seg["t"] == [0.0, 0.25, 0.5, 0.75, 1.0]
    assert (seg["draws"], seg["seed"]) == (2, LearningConfig().eval_seed)
    # each point is the theta there on the same draws as the runs' evaluations
    assert seg["J_start"] == pytest.approx(class_on_run_draws(run, start)["mean"], rel=1e-12)
    assert seg["J_end"] == pytest.approx(class_on_run_draws(run, end)["mean"], rel=1e-12)
    middle = Theta.from_vector(0.5 * (start.to_vector() + end.to_vector()), 3)
    assert seg["J"][2] == pytest.approx(class_on_run_draws(run, middle)["mean"], rel=1e-12)
    assert seg["rise"] == pytest.approx(max(seg["J"]) - max(seg["J"][0], seg["J"][-1]))
    assert seg["rise"] >= 0.0 and len(set(seg["J"])) == 5
    with pytest.raises(ValueError, match="points=1"):
        segment_on_run_draws(run, start, end, points=1)
    with pytest.raises(ValueError, match="points=102"):
        segment_on_run_draws(run, start, end, points=102)
    with pytest.raises(ValueError, match="end has n=2"):
        segment_on_run_draws(run, start, Theta.nominal(SystemConfig(n=2)))
    with pytest.raises(TypeError, match="start"):
        segment_on_run_draws(run, start.to_vector(), end)


def test_the_segment_tool_scores_each_run_against_the_class_best(tmp_path, capsys):
    """``tools/theta_segment.py``: one JSON line per finished run, from its final theta (t = 0)
    to the class's best (t = 1), on the run's own draws."""
    import importlib.util
    from pathlib import Path

    from mpcrl_lite.learning.history import History
    from mpcrl_lite.studies.study import class_on_run_draws
    from mpcrl_lite.studies.sweep.grid import SweepRun

    path = Path(__file__).resolve().parents[2] / "tools" / "theta_segment.py"
    spec = importlib.util.spec_from_file_location("theta_segment", path)
    tool = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(tool)
    base = {"learning.days_per_month": 2, "learning.eval_draws": 2, "learning.eval_every": 1}
    run_study(2, 1, tmp_path / "s", base=base, workers=0, progress=False, J_star=-400.0)
    best = tune_dir(tmp_path / "t")
    assert tool.main([str(tmp_path / "s"), str(best), "--seeds", "1", "--points", "3"]) == 0
    lines = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    assert [line["run_seed"] for line in lines] == [1]
    folder = next(p.parent for p in (tmp_path / "s" / "runs").glob("*/config.json")
                  if SweepRun.from_config(json.loads(p.read_text())).learning.seed == 1)
    run = SweepRun.from_config(json.loads((folder / "config.json").read_text()))
    final = History.load(folder).final_theta()
    assert lines[0]["t"] == [0.0, 0.5, 1.0]
    assert lines[0]["J_start"] == pytest.approx(class_on_run_draws(run, final)["mean"], rel=1e-12)
    nominal = Theta.nominal(SystemConfig())
    assert lines[0]["J_end"] == pytest.approx(class_on_run_draws(run, nominal)["mean"], rel=1e-12)
    with pytest.raises(SystemExit):
        tool.main([str(tmp_path / "empty"), str(best)])
