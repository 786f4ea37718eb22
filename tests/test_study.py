"""The multi-seed study: files, keys, values read back from the runs, convergence rule."""

from __future__ import annotations

import json
import math

import numpy as np
import pandas as pd
import pytest

from mpcrl_lite.cli import main
from mpcrl_lite.history import History
from mpcrl_lite.study import SEED_COLUMNS, gap_closed, run_study, summarize


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
    assert s["worst_seed"] == {"seed": 2, "J_eval_final": 300.0}
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
    summary = run_study(2, 2, out, seed_start=3, base=base, workers=0, progress=False)
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
    again = run_study(2, 2, out, seed_start=3, base=base, workers=0, progress=False)
    assert json.loads(json.dumps(again)) == saved


def test_study_command_checks_its_arguments(tmp_path, capsys):
    assert main(["study", "--seeds", "1", "--months", "1", "--out", str(tmp_path / "s"),
                 "--threshold", "2", "--workers", "0", "--quiet"]) == 2
    assert "threshold=2" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["study", "--seeds", "0", "--months", "1", "--out", str(tmp_path / "s")])
    assert not (tmp_path / "s").exists()
