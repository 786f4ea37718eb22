"""The multi-seed study: files, keys, values read back from the runs, convergence rule."""

from __future__ import annotations

import json
import math

import numpy as np
import pandas as pd
import pytest

from mpcrl_lite.bounds.causal.dp import causal_optimum
from mpcrl_lite.cli.commands.study import STUDY_TARGETS
from mpcrl_lite.cli.main import main
from mpcrl_lite.config import SystemConfig
from mpcrl_lite.learning.history import History
from mpcrl_lite.studies import study
from mpcrl_lite.studies.study import (
    LATE_COLLAPSE,
    SEED_COLUMNS,
    TARGETS,
    causal_target,
    gap_closed,
    run_study,
    summarize,
)
from mpcrl_lite.system.prices import Prices


def test_gap_closed_is_the_share_of_the_gap():
    assert gap_closed(1000.0, 1000.0, 0.0) == 0.0
    assert gap_closed(100.0, 1000.0, 0.0) == pytest.approx(0.9)
    assert gap_closed(-50.0, 1000.0, -100.0) == pytest.approx(1050 / 1100)
    assert gap_closed(1200.0, 1000.0, 0.0) == pytest.approx(-0.2)  # worse than nominal
    assert math.isnan(gap_closed(5.0, 1.0, 1.0))  # no gap
    assert math.isnan(gap_closed(float("nan"), 1.0, 0.0))


def synthetic(rows):
    return pd.DataFrame(rows)


def test_convergence_on_synthetic_seeds():
    # nominal 1000 for all, best reached -100 (seed 2, month 40)
    table = synthetic([
        {"seed": 0, "status": "done", "J_eval_nominal": 1000.0, "J_eval_final": 10.0,
         "J_eval_best": 0.0, "late_regression": 10.0},       # closes 990/1100 = 0.9 -> yes
        {"seed": 1, "status": "done", "J_eval_nominal": 1000.0, "J_eval_final": 20.0,
         "J_eval_best": 20.0, "late_regression": 0.0},       # 980/1100 < 0.9 -> no
        {"seed": 2, "status": "done", "J_eval_nominal": 1000.0, "J_eval_final": 300.0,
         "J_eval_best": -100.0, "late_regression": 400.0},   # regressed late -> no
        {"seed": 3, "status": "failed", "J_eval_nominal": np.nan, "J_eval_final": np.nan,
         "J_eval_best": np.nan, "late_regression": np.nan},
    ])
    out, s = summarize(table, threshold=0.9)
    assert s["target"] == "best_J_eval_reached" and s["J_target"] == -100.0
    assert s["J_nominal"] == 1000.0
    np.testing.assert_allclose(out["gap_closed"][:3], [990 / 1100, 980 / 1100, 700 / 1100])
    assert list(out["converged"]) == [True, False, False, False]
    assert s["fraction_converged"] == pytest.approx(1 / 3)  # of the 3 finished seeds
    assert s["converged_seeds"] == [0] and s["failed_seeds"] == [3] and s["done"] == 3
    assert s["J_eval_final_median"] == 20.0
    assert s["J_eval_final_iqr"] == [15.0, 160.0]
    assert s["worst_seed"] == {"seed": 2, "J_eval_final": 300.0, "regret": 400.0}
    assert s["largest_late_regression"] == {"seed": 2, "value": 400.0}
    assert s["late_regression"] == {"0": 10.0, "1": 0.0, "2": 400.0}
    # a given J* replaces the best reached; a looser threshold admits seed 1
    out, s = summarize(table, J_star=-1000.0, threshold=0.5)
    assert s["target"] == "J_star" and s["J_target"] == -1000.0
    np.testing.assert_allclose(out["gap_closed"][:3], [990 / 2000, 980 / 2000, 700 / 2000])
    assert s["converged_seeds"] == []
    _, s = summarize(table, J_star=-1000.0, threshold=0.49)
    assert s["converged_seeds"] == [0, 1]
    for bad in (0.0, 1.5, True, "0.9"):
        with pytest.raises(ValueError, match="threshold="):
            summarize(table, threshold=bad)
    with pytest.raises(ValueError, match="J_star="):
        summarize(table, J_star=float("nan"))


def test_tiny_study_matches_the_runs(tmp_path):
    out = tmp_path / "study"
    base = {"learning.days_per_month": 2, "learning.eval_draws": 3, "learning.eval_every": 1}
    summary = run_study(2, 2, out, seed_start=3, base=base, workers=0, progress=False,
                        target="best_seen")
    table = pd.read_csv(out / "study.csv")
    assert tuple(table.columns) == SEED_COLUMNS
    assert list(table["seed"]) == [3, 4] and list(table["status"]) == ["done", "done"]
    saved = json.loads((out / "study.json").read_text())
    for key in ("seeds", "done", "definition", "threshold", "J_nominal", "J_target",
                "fraction_converged", "converged_seeds", "J_eval_final_median",
                "J_eval_final_iqr", "worst_seed", "late_regression",
                "largest_late_regression", "eval_draws", "months"):
        assert key in saved, key
    assert saved["seeds"] == [3, 4] and saved["eval_draws"] == 3 and saved["months"] == 2
    assert saved == json.loads(json.dumps(summary))
    finals, bests = [], []
    for _, row in table.iterrows():
        history = History.load(out / "runs" / row["run_id"])
        assert history.learning.seed == row["seed"] and history.months == 2
        assert history.eval_month == [0, 1]
        assert row["J_eval_nominal"] == pytest.approx(history.J_eval[0])
        assert row["J_eval_final"] == pytest.approx(history.J_eval[-1])
        assert row["J_eval_final_ci_low"] == pytest.approx(history.J_eval_ci_low[-1])
        assert row["J_eval_best"] == pytest.approx(min(history.J_eval))
        assert row["late_regression"] == pytest.approx(history.J_eval[-1] - min(history.J_eval))
        assert row["max_P_applied"] == pytest.approx(max(history.max_P_applied))
        finals.append(history.J_eval[-1])
        bests.append(min(history.J_eval))
    # month 0 is the nominal theta on the same draws: the same J_eval for every seed
    assert table["J_eval_nominal"].nunique() == 1
    assert saved["J_target"] == pytest.approx(min(bests))
    assert saved["J_eval_final_median"] == pytest.approx(np.median(finals))
    worst = int(np.argmax(finals))
    assert saved["worst_seed"]["seed"] == [3, 4][worst]
    curves = pd.read_csv(out / "study_curves.csv")
    assert len(curves) == 4 and set(curves["seed"]) == {3, 4}
    assert (out / "study_curves.png").read_bytes().startswith(b"\x89PNG")
    # run again: every seed is finished, nothing is recomputed, same summary
    again = run_study(2, 2, out, seed_start=3, base=base, workers=0, progress=False,
                      target="best_seen")
    assert json.loads(json.dumps(again)) == saved


def test_study_command_checks_its_arguments(tmp_path, capsys):
    assert main(["study", "--seeds", "1", "--months", "1", "--out", str(tmp_path / "s"),
                 "--threshold", "2", "--workers", "0", "--quiet"]) == 2
    assert "threshold=2" in capsys.readouterr().err
    assert main(["study", "--seeds", "1", "--months", "1", "--out", str(tmp_path / "s"),
                 "--step-size", "-1", "--workers", "0", "--quiet"]) == 2
    assert "step_size=-1.0: expected a value in [0, inf)" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["study", "--seeds", "0", "--months", "1", "--out", str(tmp_path / "s")])
    assert not (tmp_path / "s").exists()


def test_regret_and_late_collapse_on_synthetic_seeds():
    # nominal 1000, J* = -100: the gap is 1100, 5 % of it is 55
    table = synthetic([
        {"seed": 0, "status": "done", "J_eval_nominal": 1000.0, "J_eval_final": -50.0,
         "J_eval_best": -60.0, "late_regression": 10.0},     # 10 / 1100 < 5 %
        {"seed": 1, "status": "done", "J_eval_nominal": 1000.0, "J_eval_final": 40.0,
         "J_eval_best": -40.0, "late_regression": 80.0},     # 80 / 1100 > 5 %: collapsed
        {"seed": 2, "status": "done", "J_eval_nominal": 1000.0, "J_eval_final": 0.0,
         "J_eval_best": -55.0, "late_regression": 55.0},     # exactly 5 %: allowed
        {"seed": 3, "status": "failed"},
    ])
    out, s = summarize(table, J_star=-100.0, J_star_method="causal_dp", J_star_note="a note")
    np.testing.assert_allclose(out["regret"][:3], [50.0, 140.0, 100.0])
    assert math.isnan(out["regret"][3])
    np.testing.assert_allclose(out["late_regression_share"][:3], [10 / 1100, 80 / 1100, 0.05])
    assert list(out["late_collapse"]) == [False, True, False, False]
    assert s["J_star"] == -100.0 and s["J_star_method"] == "causal_dp"
    assert s["J_star_note"] == "a note" and "(causal_dp)" in s["definition"]
    assert s["regret"] == {"0": 50.0, "1": 140.0, "2": 100.0}
    assert s["regret_median"] == 100.0 and s["regret_iqr"] == [75.0, 120.0]
    assert s["worst_seed"] == {"seed": 1, "J_eval_final": 40.0, "regret": 140.0}
    assert s["late_collapse_limit"] == LATE_COLLAPSE == 0.05
    assert s["late_collapse_seeds"] == [1] and s["late_collapse_count"] == 1
    assert s["no_late_collapse"] is False
    _, s = summarize(table[table["seed"] != 1], J_star=-100.0)
    assert s["late_collapse_count"] == 0 and s["no_late_collapse"] is True
    # seeds that end no better than they started (two of five here) are named
    stuck = synthetic([
        {"seed": 5, "status": "done", "J_eval_nominal": 1000.0, "J_eval_final": 1000.0,
         "J_eval_best": 990.0, "late_regression": 10.0},     # back where it began
        {"seed": 6, "status": "done", "J_eval_nominal": 1000.0, "J_eval_final": 1200.0,
         "J_eval_best": 1000.0, "late_regression": 200.0},   # worse than its start
        {"seed": 7, "status": "done", "J_eval_nominal": 1000.0, "J_eval_final": 999.9,
         "J_eval_best": 999.9, "late_regression": 0.0},      # a little better
    ])
    _, s_stuck = summarize(pd.concat([table, stuck], ignore_index=True), J_star=-100.0)
    assert s_stuck["no_improvement_seeds"] == [5, 6] and s_stuck["no_improvement_count"] == 2
    assert s["no_improvement_seeds"] == [] and s["no_improvement_count"] == 0
    # without a J*: judged against the best reached, J_star null
    _, s = summarize(table)
    assert s["J_star"] is None and s["J_star_method"] is None and s["J_target"] == -60.0


def test_causal_target_chooses_the_method_the_system_allows():
    one = SystemConfig(n=1, P_bar=0.8)
    prices = Prices.month(one, 2)
    found = causal_target(one, prices)
    assert found["method"] == "causal_dp"
    assert found["J_star"] == pytest.approx(causal_optimum(one, prices,
                                                           keep_values=False).J_star)
    # a soc grid the DP cannot use for this alpha: no causal J*, said in words
    odd = SystemConfig(n=1, P_bar=0.8, alpha=0.1)
    found = causal_target(odd, Prices.month(odd, 1))
    assert found["J_star"] is None and found["method"] is None
    assert "best J_eval" in found["note"]
    assert STUDY_TARGETS == TARGETS


def test_the_paper_system_reads_its_j_star_from_the_stored_table():
    """The default system's month is in data/causal_j_star.csv: no DP is solved, and the
    figure is the table's (itself checked against a fresh solve in test_causal_table)."""
    from mpcrl_lite.bounds.causal.table import TABLE_CSV, stored_bound

    system = SystemConfig()
    prices = Prices.month(system, 30)
    target = study.causal_target(system, prices)
    assert target["source"].endswith(TABLE_CSV) and target["method"] == "causal_dp"
    assert target["J_star"] == pytest.approx(stored_bound(system, prices).J_star_for(prices).mean())
    assert -402.0 < target["J_star"] < -398.0  # -399.3 on the 41-point grid


def test_study_judges_against_the_causal_optimum_by_default(tmp_path, monkeypatch):
    out = tmp_path / "study"
    base = {"learning.days_per_month": 2, "learning.eval_draws": 2, "learning.eval_every": 1,
            "system.n": 1, "system.P_bar": 0.8, "mpc.forecast": "until_midnight"}
    summary = run_study(2, 2, out, seed_start=5, base=base, workers=0, progress=False)
    system = SystemConfig(n=1, P_bar=0.8)
    J_star = causal_optimum(system, Prices.month(system, 2), keep_values=False).J_star
    saved = json.loads((out / "study.json").read_text())
    assert saved == json.loads(json.dumps(summary))
    assert saved["target"] == "J_star" and saved["J_star_method"] == "causal_dp"
    assert saved["J_target"] == pytest.approx(J_star) and saved["J_star"] == pytest.approx(J_star)
    assert "41 soc nodes" in saved["J_star_note"]
    table = pd.read_csv(out / "study.csv")
    assert tuple(table.columns) == SEED_COLUMNS
    gap = saved["J_nominal"] - J_star
    for _, row in table.iterrows():
        history = History.load(out / "runs" / row["run_id"])
        assert history.mpc.forecast == "until_midnight"  # the base reaches every run
        assert row["regret"] == pytest.approx(history.J_eval[-1] - J_star)
        share = (history.J_eval[-1] - min(history.J_eval)) / gap
        assert row["late_regression_share"] == pytest.approx(share)
        assert row["late_collapse"] == (share > LATE_COLLAPSE)
        assert saved["regret"][str(row["seed"])] == pytest.approx(row["regret"])
    assert saved["regret_median"] == pytest.approx(table["regret"].median())
    assert saved["late_collapse_count"] == int(table["late_collapse"].sum())
    # run again: J* is read back from study_j_star.json, not solved again
    assert (out / study.J_STAR_FILE).exists()

    def refuse(*args, **kwargs):
        raise AssertionError("the DP was solved again")

    monkeypatch.setattr(study, "causal_bound", refuse)
    again = run_study(2, 2, out, seed_start=5, base=base, workers=0, progress=False)
    assert json.loads(json.dumps(again)) == saved
    with pytest.raises(ValueError, match="target='best'"):
        run_study(2, 2, out, seed_start=5, base=base, workers=0, progress=False, target="best")


def test_study_command_passes_forecast_and_target(tmp_path, capsys):
    out = tmp_path / "s"
    assert main(["study", "--seeds", "1", "--months", "1", "--days", "1", "--out", str(out),
                 "--forecast", "until_midnight", "--target", "best_seen", "--workers", "0",
                 "--quiet"]) == 0
    printed = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert printed["J_star_method"] is None and "regret_median" in printed
    config = json.loads(next((out / "runs").glob("*/config.json")).read_text())
    assert config["mpc"]["forecast"] == "until_midnight"


def test_a_sweep_run_written_before_the_forecast_option_is_still_its_own(tmp_path):
    """config.json of a run from before MPCConfig.forecast reads as the paper's forecast; a
    run of the other forecast is refused in one line."""
    from mpcrl_lite.studies.sweep.grid import load_grid
    from mpcrl_lite.studies.sweep.store import check_run_dirs, run_dir

    sweep = load_grid({"grid": {"learning.seed": [1]}})
    directory = run_dir(tmp_path, sweep.runs[0])
    directory.mkdir(parents=True)
    configs = sweep.runs[0].configs()
    del configs["mpc"]["forecast"]
    (directory / "config.json").write_text(json.dumps(configs))
    check_run_dirs(sweep, tmp_path)  # no error
    configs["mpc"]["forecast"] = "until_midnight"
    (directory / "config.json").write_text(json.dumps(configs))
    with pytest.raises(ValueError, match="mpc.forecast='until_midnight'") as err:
        check_run_dirs(sweep, tmp_path)
    assert len(str(err.value).splitlines()) == 1


def _evaluated(J_eval, months=(0, 5, 9)):
    from mpcrl_lite.config import LearningConfig, MPCConfig

    history = History(SystemConfig(), MPCConfig(), LearningConfig())
    history.eval_month, history.J_eval = list(months), list(J_eval)
    return history


def test_updates_to_close_is_the_first_evaluated_month_past_the_share():
    from mpcrl_lite.studies.study import updates_to_close

    run = _evaluated([1000.0, 150.0, 50.0])  # gap 1000 -> 0: closes 0, 0.85, 0.95
    assert updates_to_close(run, 1000.0, 0.0, 0.9) == 9
    assert updates_to_close(run, 1000.0, 0.0, 0.8) == 5
    assert updates_to_close(run, 1000.0, 0.0) == 9  # default: THRESHOLD
    assert updates_to_close(run, 1000.0, -1000.0, 0.9) is None  # never within the run
    assert updates_to_close(_evaluated([-10.0, 50.0, 60.0]), 1000.0, 0.0, 0.9) == 0
    with pytest.raises(ValueError, match="share=1.5"):
        updates_to_close(run, 1000.0, 0.0, 1.5)


def test_seed_band_is_the_mean_and_t_interval_over_the_seeds():
    from mpcrl_lite._util.stats import mean_ci
    from mpcrl_lite.studies.study import seed_band

    runs = [_evaluated([1000.0, 100.0, 0.0]), _evaluated([1000.0, 300.0, -40.0]),
            _evaluated([1000.0, 200.0, -80.0])]
    band = seed_band(runs)
    assert band["seeds"] == 3 and list(band["month"]) == [0, 5, 9]
    np.testing.assert_allclose(band["mean"], [1000.0, 200.0, -40.0])
    ci = mean_ci([100.0, 300.0, 200.0])
    assert (band["ci_low"][1], band["ci_high"][1]) == pytest.approx((ci.ci_low, ci.ci_high))
    assert band["ci_low"][1] < 200.0 < band["ci_high"][1]
    assert band["J_eval"].shape == (3, 3)
    alone = seed_band(runs[:1])
    assert np.isnan(alone["ci_low"]).all() and list(alone["mean"]) == [1000.0, 100.0, 0.0]
    with pytest.raises(ValueError, match="different months"):
        seed_band([runs[0], _evaluated([1.0, 2.0], months=(0, 4))])
    with pytest.raises(ValueError, match="histories is empty"):
        seed_band([])


def test_study_command_passes_the_learning_options_to_every_run(tmp_path):
    """--scale-to-prices, --reset-momentum-at-bounds and --step-limit reach every run's
    LearningConfig (its stored config), and each run learns with them."""
    out = tmp_path / "s"
    assert main(["study", "--seeds", "1", "--months", "1", "--days", "2", "--eval-draws", "1",
                 "--out", str(out), "--workers", "0", "--quiet", "--scale-to-prices",
                 "--reset-momentum-at-bounds", "--step-limit", "3"]) == 0
    stored = json.loads((out / "runs" / "seed=0" / "config.json").read_text())["learning"]
    assert stored["scale_to_prices"] is True and stored["reset_momentum_at_bounds"] is True
    assert stored["step_limit"] == 3.0
    history = History.load(out / "runs" / "seed=0")
    assert history.learning.scale_to_prices and history.learning.reset_momentum_at_bounds
    assert history.learning.step_limit == 3.0 and "step_limited" in history.update_info[0]


def test_study_command_passes_the_step_rule_to_every_run(tmp_path):
    """--step-size, --optimizer, --exploration-std, --step-warmup, --step-decay and
    --average-months reach every run's stored LearningConfig, and the first update's step
    is the warmed-up, decayed one."""
    out = tmp_path / "s"
    assert main(["study", "--seeds", "1", "--months", "1", "--days", "2", "--eval-draws", "1",
                 "--out", str(out), "--workers", "0", "--quiet", "--step-size", "0.03",
                 "--optimizer", "adam", "--exploration-std", "0.1", "--step-warmup", "4",
                 "--step-decay", "7", "--average-months", "3"]) == 0
    stored = json.loads((out / "runs" / "seed=0" / "config.json").read_text())["learning"]
    assert (stored["step_size"], stored["optimizer"], stored["exploration_std"]) == (
        0.03, "adam", 0.1)
    assert (stored["step_warmup"], stored["step_decay"], stored["average_months"]) == (4, 7, 3)
    history = History.load(out / "runs" / "seed=0")
    # update 1: 0.03 * min(1, 1/4) / (1 + 0/7)
    assert history.update_info[0]["step"] == 1
    assert history.update_info[0]["step_size"] == pytest.approx(0.03 / 4)
    assert history.learning.step_warmup == 4 and history.learning.average_months == 3
