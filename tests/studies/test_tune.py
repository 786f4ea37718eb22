"""The best theta of a class (mpcrl_lite.studies.tune and ``python -m mpcrl_lite tune``): the
search finds a known optimum (a bound included), the held-out figure uses no train draw, a
resumed search is the uninterrupted one, a mismatching resume is refused in one line, and the
real closed loop gives what a direct evaluation gives, whatever the number of workers."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest

import mpcrl_lite.studies.tune as tune_module
from mpcrl_lite.cli.main import main
from mpcrl_lite.config import LearningConfig, MPCConfig, SystemConfig
from mpcrl_lite.sim.candidates import candidate_noise, evaluate_candidates
from mpcrl_lite.studies.tune import (
    SCALES,
    SEARCH_PARTS,
    SEARCH_TOL,
    SEARCH_TOL_MAX,
    Space,
    TuneSettings,
    tune,
)
from mpcrl_lite.system.prices import Prices
from mpcrl_lite.theta import Theta

SMALL = SystemConfig(N=6)
#: the optimum of the synthetic objective, T1 at its bound 0
TARGET = {"alpha": 0.1, "delta": 0.004, "b": 1.0, "s": -1.5, "phi1": 5.0, "phi2": -3.0,
          "T1": 0.0, "T2": 2.0}


class Quadratic:
    """Stands in for the closed loop: J = sum over the searched parts of
    ((part - TARGET) / scale)^2 (T1 pulled below 0, where it may not go) plus a per-draw
    offset; records every (seed, draws) it is asked for."""

    def __init__(self) -> None:
        self.calls: list[tuple[int, tuple[int, ...]]] = []
        self.configs: list[MPCConfig] = []

    def __call__(self, thetas, system, mpc_config, prices, seed, draws, solver=None):
        self.calls.append((seed, tuple(draws)))
        self.configs.append(mpc_config)
        vectors = np.atleast_2d(thetas)
        out = []
        for v in vectors:
            th = Theta.from_vector(v, system.n)
            f = 0.0
            for name in SEARCH_PARTS:
                goal = -1.0 if name == "T1" else TARGET[name]
                f += float(np.mean(((getattr(th, name) - goal) / SCALES[name]) ** 2))
            out.append([f + 0.01 * d for d in draws])
        return np.asarray(out)


@pytest.fixture
def quadratic(monkeypatch) -> Quadratic:
    fake = Quadratic()
    monkeypatch.setattr(tune_module, "evaluate_candidates", fake)
    return fake


def small_prices(days: int = 2) -> Prices:
    return Prices.month(SMALL, days)


def test_space_maps_coordinates_to_theta():
    theta0 = Theta.nominal(SMALL)
    tied, untied = Space(theta0), Space(theta0, tied=False)
    assert tied.dim == len(SEARCH_PARTS) and untied.dim == len(SEARCH_PARTS) * SMALL.n
    z = np.arange(1.0, tied.dim + 1)
    th = tied.theta(z)
    for i, name in enumerate(SEARCH_PARTS):
        np.testing.assert_allclose(getattr(th, name), getattr(theta0, name) + SCALES[name] * z[i])
    assert tied.theta(-z).phi1.min() == 0.0 and tied.theta(-z).T1.min() == 0.0  # clipped
    assert th.phi3.tolist() == theta0.phi3.tolist() and th.T3.tolist() == theta0.T3.tolist()
    zu = np.arange(untied.dim, dtype=float)
    assert untied.theta(zu).b.tolist() == (SCALES["b"] * zu[2 * SMALL.n:3 * SMALL.n]).tolist()
    assert untied.lower[SEARCH_PARTS.index("phi1") * SMALL.n] == 0.0


def test_search_finds_a_known_optimum(quadratic, tmp_path):
    result = tune(tmp_path, TuneSettings(evals=1500, draws=2, heldout_draws=3), system=SMALL,
                  prices=small_prices(), progress=False, figure=False)
    best = result["theta_best"]
    for name, goal in TARGET.items():
        np.testing.assert_allclose(best[name], goal, atol=2e-3 * SCALES[name], err_msg=name)
    # J_best: the quadratic's floor at the optimum (T1 held at 0, one scale from its goal),
    # plus the mean offset of the train draws 0 and 1
    assert result["J_best"] == pytest.approx((1.0 / SCALES["T1"]) ** 2 + 0.005, abs=1e-4)
    assert result["evals"] >= 1500 and result["evals"] % result["popsize"] == 0


def test_heldout_uses_no_train_draw(quadratic, tmp_path):
    s = TuneSettings(evals=30, draws=3, heldout_draws=4, seed=5)
    result = tune(tmp_path, s, system=SMALL, prices=small_prices(), progress=False,
                  figure=False)
    # the search, then the judgement on held-out draws, then theta_best's train mean solved
    # as the judgement is
    *search, final, best = quadratic.calls
    assert {call for call in search} == {(5, (0, 1, 2))}
    eval_seed = LearningConfig().eval_seed
    assert final == (eval_seed, (0, 1, 2, 3)) and best == (5, (0, 1, 2))
    assert result["train"] == {"seed": 5, "draws": [0, 1, 2]}
    assert result["heldout"] == {"seed": eval_seed, "draws": [0, 1, 2, 3]}
    # the noise of the held-out draws is none of the train draws' noise
    train = candidate_noise(SMALL, 2, 5, 3).reshape(SMALL.hours_per_day, 3, -1)
    held = candidate_noise(SMALL, 2, eval_seed, 4).reshape(SMALL.hours_per_day, 4, -1)
    for i in range(3):
        for j in range(4):
            assert not np.array_equal(train[:, i], held[:, j])
    with pytest.raises(ValueError, match="held-out draws' seed"):
        TuneSettings(seed=eval_seed)


def test_resume_continues_exactly_and_refuses_other_settings(quadratic, tmp_path):
    whole = tune(tmp_path / "whole", TuneSettings(evals=60, draws=2, heldout_draws=2),
                 system=SMALL, prices=small_prices(), progress=False, figure=False)
    part = tmp_path / "part"
    tune(part, TuneSettings(evals=30, draws=2, heldout_draws=2), system=SMALL,
         prices=small_prices(), progress=False, figure=False)
    np.random.seed(123)  # whatever happens to numpy's global generator in between
    resumed = tune(part, TuneSettings(evals=60, draws=2, heldout_draws=2), system=SMALL,
                   prices=small_prices(), progress=False, figure=False, resume=True)
    assert resumed["log"] == whole["log"]
    assert resumed["theta_best"] == whole["theta_best"] and resumed["evals"] == whole["evals"]
    with pytest.raises(ValueError, match=r"^cannot resume the search in .*: settings\.draws is "
                                         r"2 in the saved search, 3 now"):
        tune(part, TuneSettings(evals=90, draws=3, heldout_draws=2), system=SMALL,
             prices=small_prices(), progress=False, figure=False, resume=True)
    with pytest.raises(ValueError, match=r"mpc\.forecast is 'paper' in the saved search"):
        tune(part, TuneSettings(evals=90, draws=2, heldout_draws=2), system=SMALL,
             mpc_config=MPCConfig(forecast="until_midnight"), prices=small_prices(),
             progress=False, figure=False, resume=True)


def test_real_closed_loop_and_workers(tmp_path):
    settings = TuneSettings(evals=12, draws=1, heldout_draws=2, popsize=6)
    one = tune(tmp_path / "one", settings, system=SMALL, prices=small_prices(),
               progress=False)
    two = tune(tmp_path / "two", settings, system=SMALL, prices=small_prices(),
               progress=False, workers=2)
    assert one["log"] == two["log"] and one["theta_best"] == two["theta_best"]
    assert one["J_heldout"] == two["J_heldout"]
    best = Theta.from_dict(one["theta_best"])
    eval_seed = LearningConfig().eval_seed
    J = evaluate_candidates([best, Theta.nominal(SMALL)], SMALL, None, small_prices(),
                            eval_seed, 2)
    assert one["J_heldout"]["mean"] == pytest.approx(J[0].mean(), rel=1e-12)
    assert one["J_nominal_heldout"]["mean"] == pytest.approx(J[1].mean(), rel=1e-12)
    train = evaluate_candidates([best], SMALL, None, small_prices(), 0, 1)
    assert one["J_best"] == pytest.approx(train[0].mean(), rel=1e-12)
    # the search's own figure: its solves stop at search_tol (SEARCH_TOL), which moves a J by
    # well under 1e-3 of it (0.13 NOK/day of about 270 on the paper's system, 0.2 of 365 here)
    assert one["J_best_search"] == min(r["J_min"] for r in one["log"])
    assert one["J_best_search"] == pytest.approx(one["J_best"], rel=1e-3)
    assert one["J_best_search"] != one["J_best"]  # the search's figure is not the exact one
    assert one["search_mpc"]["polish"] is False and one["search_mpc"]["tol"] == SEARCH_TOL
    assert one["mpc"]["polish"] is True and one["mpc"]["tol"] == MPCConfig().tol
    assert (tmp_path / "one" / "tune.png").stat().st_size > 0
    saved = json.loads((tmp_path / "one" / "tune.json").read_text())
    for key in ("J_best", "J_heldout", "theta_best", "evals"):
        assert key in saved
    assert set(saved["J_heldout"]) >= {"mean", "ci_low", "ci_high", "draws"}


def test_the_search_solves_loosely_and_the_judgement_exactly(quadratic, tmp_path):
    given = MPCConfig(tau=0.05)
    tune(tmp_path / "fast", TuneSettings(evals=20, draws=2, heldout_draws=2), system=SMALL,
         mpc_config=given, prices=small_prices(), progress=False, figure=False)
    *search, held, best = quadratic.configs
    assert held == given and best == given
    assert {c for c in search} == {given.replace(polish=False, tol=SEARCH_TOL)}
    quadratic.configs.clear()
    exact = tune(tmp_path / "exact", TuneSettings(evals=20, draws=2, heldout_draws=2,
                                                  search_tol=None),
                 system=SMALL, mpc_config=given, prices=small_prices(), progress=False,
                 figure=False)
    assert set(quadratic.configs) == {given} and len(quadratic.calls) > 0
    assert exact["J_best"] == exact["J_best_search"]
    for bad in (0.0, 2 * SEARCH_TOL_MAX, float("nan")):
        with pytest.raises(ValueError, match="search_tol"):
            TuneSettings(search_tol=bad)
    assert TuneSettings(search_tol=SEARCH_TOL_MAX).search_config(given).tol == SEARCH_TOL_MAX


def test_cli_tune(tmp_path, capsys):
    out = tmp_path / "t"
    common = ["tune", "--out", str(out), "--draws", "1", "--heldout-draws", "2", "--days", "1",
              "--quiet", "--popsize", "4"]
    assert main([*common, "--evals", "4"]) == 0
    printed = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert printed["evals"] == 4
    saved = json.loads((out / "tune.json").read_text())
    assert saved["settings"]["tied"] is True and saved["forecast"] == "paper"
    assert saved["settings"]["search_tol"] == SEARCH_TOL
    exact = tmp_path / "exact"
    assert main(["tune", "--out", str(exact), "--draws", "1", "--heldout-draws", "2", "--days",
                 "1", "--quiet", "--popsize", "4", "--evals", "4", "--exact-search"]) == 0
    capsys.readouterr()
    assert json.loads((exact / "tune.json").read_text())["settings"]["search_tol"] is None
    assert main([*common, "--evals", "4", "--search-tol", "0.5"]) == 2
    assert "search_tol=0.5" in capsys.readouterr().err
    assert main([*common, "--evals", "8"]) == 2
    assert "already holds results" in capsys.readouterr().err
    assert main([*common, "--evals", "8", "--resume"]) == 0
    assert json.loads((out / "tune.json").read_text())["evals"] == 8
    assert main([*common, "--evals", "12", "--resume", "--untied"]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1
    assert "settings.tied is True in the saved search, False now" in err
    assert main([*common, "--resume", "--force"]) == 2
    assert "exclude each other" in capsys.readouterr().err


def test_a_search_killed_outright_leaves_no_worker_behind(tmp_path):
    """``tune --workers 2`` killed with SIGKILL: its forked workers end with it."""
    import sys

    from conftest import assert_workers_die_with

    assert_workers_die_with([sys.executable, "-m", "mpcrl_lite", "tune", "--out",
                             str(tmp_path / "best"), "--evals", "400", "--draws", "2",
                             "--heldout-draws", "2", "--days", "2", "--workers", "2",
                             "--quiet"], workers=2)


def test_the_readme_quotes_the_search_tolerance():
    readme = (Path(__file__).resolve().parents[2] / "README.md").read_text()
    quoted = re.search(r"`--search-tol` \(default ([0-9.e+-]+)\)", readme)
    assert quoted is not None and float(quoted.group(1)) == SEARCH_TOL
    assert TuneSettings().search_tol == SEARCH_TOL
