"""The regret split in two in ``baselines``: J* by default (the stored table), per policy the
regret and the gap closed, and with a class's best theta (a ``tune`` result) the learner's and
the class's parts, which add up to the regret day by day."""

from __future__ import annotations

import json

import numpy as np
import pytest

from mpcrl_lite._util.stats import mean_ci
from mpcrl_lite.bounds.baselines import (
    causal_reference,
    evaluate_baselines,
    load_class_best,
    regret_split,
    run_baselines_cli,
)
from mpcrl_lite.bounds.causal.table import causal_bound
from mpcrl_lite.cli.main import main
from mpcrl_lite.config import LearningConfig, MPCConfig, SystemConfig
from mpcrl_lite.learning.history import History
from mpcrl_lite.system.prices import Prices
from mpcrl_lite.theta import Theta

SYSTEM = SystemConfig()
DAYS = 2


def test_regret_split_adds_up_day_by_day():
    rng = np.random.default_rng(0)
    learned, best = rng.normal(-200, 20, 10), rng.normal(-260, 20, 10)
    star = rng.normal(-400, 5, 10)
    split = regret_split(learned, best, star)
    assert split["learner"]["mean"] + split["class"]["mean"] == pytest.approx(
        split["regret"]["mean"], rel=1e-12)
    assert split["learner"] == mean_ci(learned - best).as_dict()
    assert split["class"] == mean_ci(best - star).as_dict()
    one = regret_split(None, best, -401.5)
    assert set(one) == {"class"} and one["class"]["mean"] == pytest.approx(best.mean() + 401.5)


def tune_result(directory, theta: Theta, forecast: str = "paper") -> None:
    directory.mkdir(parents=True, exist_ok=True)
    (directory / "tune.json").write_text(json.dumps({
        "theta_best": theta.to_dict(), "forecast": forecast, "J_best": -1.0, "evals": 10,
        "J_heldout": {"mean": -2.0, "ci_low": -3.0, "ci_high": -1.0, "draws": 2}}))


@pytest.fixture(scope="module")
def learned(tmp_path_factory):
    """A History whose final theta differs from the nominal one."""
    path = tmp_path_factory.mktemp("run")
    learning = LearningConfig(days_per_month=DAYS, seed=2)
    history = History(SYSTEM, MPCConfig(), learning)
    nominal = Theta.nominal(SYSTEM)
    history.theta_final = nominal.replace(b=np.full(SYSTEM.n, -2.0), T1=np.full(SYSTEM.n, 5.0),
                                          T2=np.full(SYSTEM.n, -5.0)).to_vector().tolist()
    history.save(path)
    return path, learning


def test_baselines_judge_against_the_stored_j_star_and_split_the_regret(learned, tmp_path):
    run, learning = learned
    tune_result(tmp_path / "tune", Theta.nominal(SYSTEM))  # the "class's best": theta0
    result = run_baselines_cli(SYSTEM, MPCConfig(), learning, run, tmp_path / "out",
                               class_best=tmp_path / "tune")
    saved = json.loads((tmp_path / "out" / "baselines.json").read_text())
    causal = saved["causal"]
    prices = Prices.month(SYSTEM, DAYS)
    star = causal_bound(SYSTEM, prices).J_star_for(prices)
    assert causal["source"] == "stored table data/causal_j_star.csv"
    assert causal["J_star"] == pytest.approx(float(star.mean()), rel=1e-12)
    J = {k: v["J"] for k, v in saved["policies"].items()}
    for name in ("nominal", "learned", "class_best", "rule_based"):
        assert causal["regret"][name] == pytest.approx(J[name] - causal["J_star"], rel=1e-12)
    assert causal["gap_closed"]["learned"] == pytest.approx(
        (J["nominal"] - J["learned"]) / (J["nominal"] - causal["J_star"]), rel=1e-12)
    # theta0 as the class's best: the same policy as the nominal MPC, on the same draws
    assert J["class_best"] == J["nominal"]
    split = causal["split"]
    per_day = {k: np.asarray(v["J_per_day"]) for k, v in saved["policies"].items()}
    assert split["learner"]["mean"] == pytest.approx(
        float(np.mean(per_day["learned"] - per_day["class_best"])), rel=1e-12)
    assert split["class"]["mean"] == pytest.approx(
        float(np.mean(per_day["class_best"] - star)), rel=1e-12)
    assert split["learner"]["mean"] + split["class"]["mean"] == pytest.approx(
        causal["regret"]["learned"], rel=1e-9)
    assert saved["class_best"]["J_heldout"]["mean"] == -2.0
    assert result["causal"]["J_star"] == causal["J_star"]


def test_no_causal_and_a_given_j_star(learned, tmp_path):
    run, learning = learned
    result = run_baselines_cli(SYSTEM, MPCConfig(), learning, run, tmp_path / "a",
                               causal=False)
    assert "causal" not in result
    given = evaluate_baselines(SYSTEM, MPCConfig(), days=DAYS, seed=2, causal=-400.0)
    assert given["causal"]["J_star"] == -400.0 and given["causal"]["grid"] is None
    J = given["policies"]["nominal"]["J"]
    assert given["causal"]["regret"]["nominal"] == pytest.approx(J + 400.0)
    with pytest.raises(ValueError, match="finite J"):
        evaluate_baselines(SYSTEM, MPCConfig(), days=DAYS, seed=2, causal=float("nan"))


def test_causal_reference_falls_back_to_the_lagrangian_bound():
    system = SystemConfig(n=4)
    bound, source = causal_reference(system, Prices.month(system, 1))
    assert isinstance(bound, float) and source == "Lagrangian lower bound"


def test_class_best_errors(learned, tmp_path):
    with pytest.raises(ValueError, match="no tune.json there"):
        load_class_best(tmp_path)
    (tmp_path / "tune.json").write_text("{}")
    with pytest.raises(ValueError, match="not a tune result"):
        load_class_best(tmp_path)
    run, learning = learned
    tune_result(tmp_path / "two", Theta.nominal(SystemConfig(n=2)))
    with pytest.raises(ValueError, match="has n=2; expected n=3"):
        run_baselines_cli(SYSTEM, MPCConfig(), learning, run, tmp_path / "o",
                          class_best=tmp_path / "two")


def test_cli_baselines_prints_j_star_and_the_split(learned, tmp_path, capsys):
    run, _ = learned
    tune_result(tmp_path / "tune", Theta.nominal(SYSTEM))
    code = main(["baselines", "--out", str(tmp_path / "b"), "--days", str(DAYS), "--seed", "2",
                 "--history", str(run), "--class-best", str(tmp_path / "tune"), "--quiet"])
    assert code == 0
    printed = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert set(printed["split"]) == {"learner", "class", "regret"}
    saved = json.loads((tmp_path / "b" / "baselines.json").read_text())
    assert printed["J_star"] == saved["causal"]["J_star"]
    assert printed["split"]["learner"] == saved["causal"]["split"]["learner"]["mean"]
    code = main(["baselines", "--out", str(tmp_path / "c"), "--days", "1", "--no-causal",
                 "--quiet"])
    assert code == 0
    assert "J_star" not in json.loads(capsys.readouterr().out.strip().splitlines()[-1])


def test_cli_evaluate_splits_the_regret(learned, tmp_path, capsys):
    run, _ = learned
    tune_result(tmp_path / "tune", Theta.nominal(SYSTEM))
    code = main(["evaluate", "--history", str(run), "--out", str(tmp_path / "e"), "--draws", "2",
                 "--days", str(DAYS), "--class-best", str(tmp_path / "tune"), "--quiet"])
    assert code == 0
    saved = json.loads((tmp_path / "e" / "summary.json").read_text())
    J = {k: np.asarray(v["J"]) for k, v in saved["policies"].items()}
    np.testing.assert_array_equal(J["class_best"], J["nominal"])  # theta0, same draws
    causal = saved["causal"]
    prices = Prices.month(SYSTEM, DAYS)
    assert causal["J_star"] == pytest.approx(
        float(causal_bound(SYSTEM, prices).J_star_for(prices).mean()), rel=1e-12)
    split = causal["split"]
    assert split["learner"] == mean_ci(J["learned"] - J["class_best"]).as_dict()
    assert split["class"]["mean"] == pytest.approx(J["class_best"].mean() - causal["J_star"])
    printed = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert printed["split"]["regret"] == pytest.approx(J["learned"].mean() - causal["J_star"])
    tune_result(tmp_path / "other", Theta.nominal(SYSTEM), forecast="until_midnight")
    code = main(["evaluate", "--history", str(run), "--out", str(tmp_path / "f"), "--draws", "2",
                 "--class-best", str(tmp_path / "other"), "--quiet"])
    assert code == 2 and "expected the run's class" in capsys.readouterr().err
