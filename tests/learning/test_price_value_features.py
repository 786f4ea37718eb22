"""The critic's value baseline with the day's prices ('hour*paper+price'): the learning step
fits exactly the LSTD problem it describes, the command line takes it and a resumed run keeps
it, and the classroom's value fit accepts it."""

from __future__ import annotations

import json

import numpy as np
import pytest
from conftest import run_cli
from threadpoolctl import threadpool_limits

from mpcrl_lite.classroom.explorers import value_fit
from mpcrl_lite.cli.main import main
from mpcrl_lite.config import LearningConfig, MPCConfig, SystemConfig
from mpcrl_lite.learning.dpg import policy_gradient
from mpcrl_lite.learning.experiment import Experiment
from mpcrl_lite.learning.history import History
from mpcrl_lite.learning.learner import BLAS_THREADS
from mpcrl_lite.learning.lstd import (
    compatible_features,
    lstd_q,
    prices_left,
    value_baseline_features,
)
from mpcrl_lite.mpc.backends.registry import make_solver
from mpcrl_lite.mpc.formulation import MPC
from mpcrl_lite.sim.closed_loop import run_month
from mpcrl_lite.system.prices import Prices
from mpcrl_lite.theta import Theta

SMALL = SystemConfig(N=6)
PRICE = "hour*paper+price"


@pytest.fixture(scope="module")
def record():
    system = SMALL
    solver = make_solver(MPC(system), MPCConfig(), Theta.nominal(system))
    return run_month(Theta.nominal(system), solver, Prices.month(system, 6), system,
                     np.random.default_rng(5), exploration_std=0.2)


def test_the_learning_step_fits_the_price_features(record):
    """Experiment.learning_step with the price features is the LSTD fit of paper eq. 17 with
    Phi = [hour*paper, soc * highest price left, soc * mean price left], assembled by hand here;
    and the day's prices change the gradient (it differs from 'hour*paper')."""
    learning = LearningConfig(value_features=PRICE, days_per_month=6)
    exp = Experiment(SMALL, learning=learning)
    grad, skipped, _ = exp.learning_step(record)
    use = record.sens_ok & record.solver_ok
    H = record.stage_cost.shape[0]
    per_hour = value_baseline_features(record.soc, "hour*paper")
    left = prices_left(record.buy)
    phi = np.concatenate([per_hour, record.soc * left[..., :1], record.soc * left[..., 1:]], -1)
    psi = compatible_features(record.grad_pi, record.a, record.policy)
    done = np.broadcast_to((np.arange(H) == H - 1)[:, None], use.shape)
    # with one BLAS thread, as every learning step (its LSTD system is ill-conditioned enough
    # that another thread count moves the gradient by ~5e-7 of itself)
    with threadpool_limits(limits=BLAS_THREADS):
        fit = lstd_q(phi[:-1][use], psi[use], record.stage_cost[use], phi[1:][use],
                     SMALL.gamma, done=done[use], ridge=learning.ridge)
    np.testing.assert_allclose(grad, policy_gradient(record.grad_pi[use], fit.w), rtol=1e-9,
                               atol=1e-12 * np.abs(grad).max())
    assert skipped == int(use.size - use.sum())
    plain, _, _ = Experiment(SMALL, learning=learning.replace(value_features="hour*paper")
                             ).learning_step(record)
    assert np.linalg.norm(plain - grad) > 1e-3 * np.linalg.norm(grad)


def test_the_classroom_value_fit_takes_the_price_features(record):
    out = value_fit(record, PRICE)
    assert out["fit"].v.shape == (24 * (2 * SMALL.n + 1) + 2 * SMALL.n,)
    assert np.isfinite(out["rmse"]) and out["r2"] <= 1.0


def test_learn_takes_the_option_and_a_resumed_run_keeps_it(tmp_path, capsys):
    base = ["learn", "--days", "2", "--n", "2", "--quiet", "--no-figures"]
    out = str(tmp_path / "run")
    status, stdout, _ = run_cli([*base, "--months", "1", "--value-features", PRICE, "--out", out],
                             capsys)
    assert status == 0 and json.loads(stdout)["months"] == 1
    assert History.load(out).learning.value_features == PRICE
    status, _, _ = run_cli([*base, "--months", "2", "--out", out, "--resume"], capsys)
    assert status == 0 and History.load(out).learning.value_features == PRICE
    status, _, err = run_cli([*base, "--months", "3", "--value-features", "hour*paper",
                           "--out", out, "--resume"], capsys)
    assert status == 2 and len(err.strip().splitlines()) == 1
    assert "--value-features hour*paper" in err and PRICE in err
    with pytest.raises(SystemExit) as exit_:  # argparse's own refusal of a bad choice
        main([*base, "--months", "1", "--value-features", "cubic", "--out",
              str(tmp_path / "bad")])
    assert exit_.value.code == 2 and "invalid choice: 'cubic'" in capsys.readouterr().err


def test_the_default_takes_the_price_terms_from_25_days_a_month():
    """value_features=None (the default) is 'hour*paper+price' for months of at least
    PRICE_FEATURES_MIN_DAYS days and 'hour*paper' below; replace chooses again, an explicit
    choice stays, and a saved config reads back as it ran."""
    from mpcrl_lite.config import PRICE_FEATURES_MIN_DAYS

    assert PRICE_FEATURES_MIN_DAYS == 25
    assert LearningConfig().value_features == PRICE  # 30 days
    assert LearningConfig(days_per_month=25).value_features == PRICE
    assert LearningConfig(days_per_month=24).value_features == "hour*paper"
    assert LearningConfig().replace(days_per_month=10).value_features == "hour*paper"
    assert LearningConfig(days_per_month=10).replace(days_per_month=31).value_features == PRICE
    chosen = LearningConfig(value_features="hour*paper")
    assert chosen.replace(days_per_month=30).value_features == "hour*paper"
    assert LearningConfig(value_features=PRICE, days_per_month=3).value_features == PRICE
    saved = LearningConfig(days_per_month=10).to_dict()
    assert saved["value_features"] == "hour*paper"
    assert LearningConfig.from_dict(saved).replace(days_per_month=30).value_features == \
        "hour*paper"
    with pytest.raises(ValueError, match="value_features='cubic'"):
        LearningConfig(value_features="cubic")
