"""The learning loop: closed-loop invariants, determinism, checkpoint/resume, History I/O."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy import stats

from mpcrl_lite import LearningConfig, MPCConfig, SystemConfig, Theta
from mpcrl_lite.learning.experiment import Experiment
from mpcrl_lite.learning.history import History
from mpcrl_lite.mpc.backends.registry import make_solver
from mpcrl_lite.mpc.formulation import MPC
from mpcrl_lite.sim.closed_loop import draw_J, evaluate_mpc, run_month
from mpcrl_lite.system.prices import Prices

SMALL = SystemConfig(N=6)


def small_experiment(months: int = 3, **learning) -> Experiment:
    cfg = LearningConfig(days_per_month=3, months=months, seed=7, **learning)
    return Experiment(system=SMALL, learning=cfg)


def test_run_month_invariants():
    system = SystemConfig(P_bar=1.0)
    mpc = MPC(system)
    solver = make_solver(mpc, MPCConfig(), Theta.nominal(system))
    prices = Prices.month(system, 4)
    rec = run_month(Theta.nominal(system), solver, prices, system,
                    np.random.default_rng(0), exploration_std=0.1)
    assert rec.soc.shape == (25, 4, 3)
    assert np.all((rec.soc >= 0) & (rec.soc <= 1))
    assert np.all(rec.soc[0] == system.soc0)
    assert rec.solver_ok.all()
    # the MPC's plan never exceeds the grid limit; the commanded (explored) action neither
    assert np.max(rec.planned_power) <= system.P_bar + 1e-9
    a = rec.a
    assert np.all(np.clip(a, 0, None).sum(axis=2) <= system.P_bar + 1e-9)
    assert np.all(np.clip(-a, 0, None).sum(axis=2) <= system.P_bar + 1e-9)
    # stage cost is the sum of the agents' costs, and J is its discounted daily mean
    np.testing.assert_allclose(rec.agent_cost.sum(axis=2), rec.stage_cost)
    disc = system.gamma ** np.arange(24)
    assert rec.J() == pytest.approx(float((disc[:, None] * rec.stage_cost).sum(axis=0).mean()))
    # sensitivities were computed and are finite
    assert rec.grad_pi.shape == (24, 4, 30, 3)
    assert np.all(np.isfinite(rec.grad_pi))
    assert rec.sens_ok.mean() > 0.9


def test_prices_follow_the_hour():
    system = SMALL
    mpc = MPC(system)
    solver = make_solver(mpc, MPCConfig(), Theta.nominal(system))
    prices = Prices.month(system, 2)
    rec = run_month(Theta.nominal(system), solver, prices, system, np.random.default_rng(1),
                    sensitivities=False)
    np.testing.assert_allclose(rec.buy, prices.buy.T)


def test_same_seed_same_history():
    h1 = small_experiment().run(progress=False)
    h2 = small_experiment().run(progress=False)
    assert h1.J == h2.J
    assert h1.theta == h2.theta
    assert h1.theta_final == h2.theta_final
    h3 = Experiment(system=SMALL, learning=LearningConfig(days_per_month=3, months=3, seed=8)).run(progress=False)
    assert h3.J != h1.J


def test_month_loop_uses_one_blas_thread_and_any_outer_limit_gives_the_same_run():
    from threadpoolctl import threadpool_info, threadpool_limits

    from mpcrl_lite.learning.learner import BLAS_THREADS

    seen: list[int] = []
    # the libraries loaded before the run (numpy's BLAS, which the months' LSTD uses); the run
    # may load more (numba's OpenMP and, through numba, scipy's BLAS)
    before = {pool["filepath"]: pool["num_threads"] for pool in threadpool_info()}

    def record_threads(month, history, learner):
        seen.extend(pool["num_threads"] for pool in threadpool_info()
                    if pool["filepath"] in before)

    exp = small_experiment(months=2)
    exp.callbacks.append(record_threads)
    h1 = exp.run(progress=False)
    # the limit holds inside the month loop only
    after = {pool["filepath"]: pool["num_threads"] for pool in threadpool_info()}
    assert {path: after[path] for path in before} == before
    assert seen and set(seen) == {BLAS_THREADS}
    # a process (or a Dask worker) that already limits its threads learns the same numbers
    with threadpool_limits(limits=1):
        h2 = small_experiment(months=2).run(progress=False)
    assert h1.J == h2.J
    assert h1.theta_final == h2.theta_final


@pytest.mark.parametrize("kind", ["dpg", "q", "decentralized"])
def test_a_month_on_its_own_uses_one_blas_thread_and_learns_what_run_learns(kind):
    # run_one_month called on its own (a notebook, a benchmark) limits BLAS as run does: the
    # same numbers as the month loop, with OpenBLAS's spinning threads kept off the kernel's
    from threadpoolctl import threadpool_info, threadpool_limits

    from mpcrl_lite.decentralized.learner import DecentralizedExperiment
    from mpcrl_lite.learning.learner import BLAS_THREADS
    from mpcrl_lite.learning.q_experiment import QLearningExperiment

    def make():
        learning = LearningConfig(days_per_month=3, months=2, seed=7, eval_every=0)
        if kind == "q":
            return QLearningExperiment(system=SMALL, learning=learning)
        if kind == "decentralized":
            return DecentralizedExperiment(SMALL, learning=learning)
        return Experiment(system=SMALL, learning=learning)

    seen: list[int] = []
    exp = make()
    update = exp.learning_step

    def watched(*args, **kwargs):
        seen.extend(pool["num_threads"] for pool in threadpool_info()
                    if pool["user_api"] == "blas")
        return update(*args, **kwargs)

    exp.learning_step = watched
    with threadpool_limits(limits=2, user_api="blas"):
        # the BLAS libraries loaded now (numpy's); a month may load more (scipy's, by numba)
        outside = {pool["filepath"] for pool in threadpool_info() if pool["user_api"] == "blas"}
        for _ in range(2):
            exp.run_one_month()
        # the caller's limit is back after each month
        assert {pool["num_threads"] for pool in threadpool_info()
                if pool["filepath"] in outside} == {2}
    assert seen and set(seen) == {BLAS_THREADS}
    ran = make().run(progress=False)
    assert exp.history.J == ran.J
    assert exp.history.theta == ran.theta


def test_a_learning_step_on_its_own_uses_one_blas_thread(monkeypatch):
    # notebook 04 takes the month's update in the open: Experiment.learning_step limits BLAS
    from threadpoolctl import threadpool_info, threadpool_limits

    import mpcrl_lite.learning.experiment as experiment_module

    exp = small_experiment(months=1)
    record = run_month(exp.theta, exp.solver, exp.prices, exp.system, np.random.default_rng(0),
                       exploration_std=0.2, sensitivities=True)
    seen: list[int] = []
    fit = experiment_module.lstd_policy_gradient

    def watched(*args, **kwargs):
        seen.extend(pool["num_threads"] for pool in threadpool_info()
                    if pool["user_api"] == "blas")
        return fit(*args, **kwargs)

    monkeypatch.setattr(experiment_module, "lstd_policy_gradient", watched)
    with threadpool_limits(limits=2, user_api="blas"):
        grad, _, _ = exp.learning_step(record)
    assert seen and set(seen) == {1}
    assert np.all(np.isfinite(grad))


def test_resume_reproduces_uninterrupted_run(tmp_path):
    full = small_experiment(months=4).run(progress=False)
    # interrupted after two months, then resumed by a fresh process-like object
    small_experiment(months=4).run(months=2, out=tmp_path, progress=False)
    saved = json.loads((tmp_path / "checkpoint.json").read_text())
    assert saved["months_done"] == 2
    resumed = small_experiment(months=4).run(out=tmp_path, resume=True, progress=False)
    assert resumed.months == 4
    np.testing.assert_array_equal(resumed.J, full.J)
    np.testing.assert_array_equal(resumed.theta_final, full.theta_final)
    np.testing.assert_array_equal(resumed.last_month.soc, full.last_month.soc)
    np.testing.assert_array_equal(resumed.first_month.soc, full.first_month.soc)


def test_resume_refuses_a_different_config(tmp_path):
    small_experiment(months=2).run(months=1, out=tmp_path, progress=False)
    other = Experiment(system=SMALL.replace(P_bar=1.2), learning=LearningConfig(days_per_month=3, months=2, seed=7))
    with pytest.raises(ValueError, match="different system config"):
        other.run(out=tmp_path, resume=True, progress=False)


def test_history_roundtrip(tmp_path):
    h = small_experiment(months=2).run(progress=False)
    h.save(tmp_path)
    assert not any(p.suffix == ".pkl" for p in tmp_path.iterdir())
    back = History.load(tmp_path)
    assert back.J == h.J
    assert back.J_per_agent == h.J_per_agent
    assert back.theta == h.theta
    assert back.system == h.system and back.learning == h.learning
    np.testing.assert_array_equal(back.last_month.policy, h.last_month.policy)
    assert back.summary() == h.summary()
    summary = h.summary()
    for key in ("J", "J_per_agent", "grad_norm", "theta_final", "hours_soc_below_0_1",
                "max_P_mpc", "skipped_steps"):
        assert key in summary
    assert set(summary["theta_final"]) == {"alpha", "delta", "b", "s", "phi1", "phi2", "phi3",
                                           "T1", "T2", "T3"}


def test_history_save_is_one_commit_and_never_detaches_a_checkpoint(tmp_path):
    h = small_experiment(months=1).run(out=tmp_path / "run", progress=False)
    with pytest.raises(ValueError, match="holds a learning run"):
        h.save(tmp_path / "run")
    h.save(tmp_path / "copy")
    manifest = json.loads((tmp_path / "copy" / "manifest.json").read_text())
    assert manifest["kind"] == "history" and manifest["months_done"] == 1
    assert sorted(manifest["files"]) == ["history.json", "history.npz"]
    assert History.load(tmp_path / "copy").J == h.J
    # a run directory is not replaced by accident, only with force=True
    with pytest.raises(ValueError, match="already holds a run"):
        small_experiment(months=1).run(out=tmp_path / "run", progress=False)
    again = small_experiment(months=1).run(out=tmp_path / "run", force=True, progress=False)
    assert again.J == h.J


def test_history_load_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="history.json"):
        History.load(tmp_path)
    (tmp_path / "history.json").write_text(json.dumps({"format": "something else"}))
    with pytest.raises(ValueError, match="format"):
        History.load(tmp_path)


def test_constants_never_move_and_alpha_stays_positive():
    h = small_experiment(months=3).run(progress=False)
    theta = np.vstack([h.theta_array(), np.asarray(h.theta_final)[None]])
    n = SMALL.n
    for part in ("phi3", "T3"):
        assert np.all(theta[:, Theta.index(n, part)] == 0)
    assert np.all(theta[:, Theta.index(n, "alpha")] > 0)
    assert np.all(theta[:, Theta.index(n, "phi1")] >= 0)


def test_experiment_rejects_bad_input():
    with pytest.raises(ValueError, match="months"):
        small_experiment().run(months=0, progress=False)
    with pytest.raises(ValueError, match="resume"):
        small_experiment().run(resume=True, progress=False)
    with pytest.raises(ValueError, match="theta0 has n=2"):
        Experiment(system=SMALL, theta0=Theta.nominal(SystemConfig(n=2)),
                   learning=LearningConfig(days_per_month=3))


def test_a_month_larger_than_the_memory_is_refused_before_anything_is_built(monkeypatch):
    from mpcrl_lite._util import budget
    from mpcrl_lite.learning.q_experiment import QLearningExperiment
    from mpcrl_lite.system.prices import Prices

    built = []
    monkeypatch.setattr(Prices, "month", classmethod(lambda cls, *a: built.append(a)))
    huge = LearningConfig(days_per_month=10**9)
    for make in (Experiment, QLearningExperiment):
        with pytest.raises(ValueError, match=r"days_per_month=1000000000, n=3, eval_draws=10: "
                                             r"needs about .* GiB of memory"):
            make(learning=huge)
    assert not built  # the shipped month was never repeated to that many days
    # the paper's month fits easily, and nothing is refused where the memory is unknown
    assert budget.check_memory("x", budget.learning_estimate(3, 30, 1, 10, 5)).memory < 2**30
    monkeypatch.setattr(budget, "available_memory", lambda: None)
    assert budget.check_memory("x", budget.Budget(1e30, 0.0)).memory == 1e30


def test_the_available_memory_is_linuxs_figure_read_without_psutil():
    import subprocess
    import sys

    import psutil

    from mpcrl_lite._util import budget

    ours, theirs = budget.available_memory(), psutil.virtual_memory().available
    assert ours is not None and abs(ours - theirs) <= 0.05 * theirs  # moments apart
    code = ("import sys; from mpcrl_lite._util import budget; budget.available_memory(); "
            "print('psutil' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


# -- critic features --------------------------------------------------------------------------
def test_value_baseline_features():
    from mpcrl_lite.learning.lstd import value_baseline_features, value_features

    soc = np.random.default_rng(0).uniform(size=(25, 4, 3))
    paper = value_baseline_features(soc, "paper")
    np.testing.assert_array_equal(paper, value_features(soc))
    hourly = value_baseline_features(soc, "paper+hour")
    assert hourly.shape == (25, 4, 6 + 24)
    np.testing.assert_array_equal(hourly[..., :6], paper[..., :6])
    # one indicator per hour of the day; the end of the day (row 24) has none
    np.testing.assert_array_equal(hourly[:24, 2, 6:], np.eye(24))
    assert np.all(hourly[24, :, 6:] == 0)
    # the indicators alone: a table over the hours of the day
    np.testing.assert_array_equal(value_baseline_features(soc, "hour"), hourly[..., 6:])
    with pytest.raises(ValueError, match="kind='cubic'"):
        value_baseline_features(soc, "cubic")
    with pytest.raises(ValueError, match="expected \\(H \\+ 1, D, n\\)"):
        value_baseline_features(soc[0], "paper")
    with pytest.raises(ValueError, match="value_features='x'"):
        LearningConfig(value_features="x")


def test_learning_step_uses_the_configured_features():
    from mpcrl_lite.learning.dpg import policy_gradient
    from mpcrl_lite.learning.lstd import compatible_features, lstd_q, value_features

    exp = small_experiment(value_features="paper")
    rec = run_month(exp.theta, exp.solver, exp.prices, exp.system, np.random.default_rng(3),
                    exploration_std=0.2)
    grad, _, _ = exp.learning_step(rec)
    use = rec.sens_ok & rec.solver_ok
    H = exp.system.hours_per_day
    done = np.broadcast_to((np.arange(H) == H - 1)[:, None], use.shape)
    psi = compatible_features(rec.grad_pi, rec.a, rec.policy)
    fit = lstd_q(value_features(rec.soc[:-1])[use], psi[use], rec.stage_cost[use],
                 value_features(rec.soc[1:])[use], exp.system.gamma, done=done[use],
                 ridge=exp.learning.ridge)
    np.testing.assert_allclose(grad, policy_gradient(rec.grad_pi[use], fit.w), rtol=1e-12)
    hourly = small_experiment(value_features="paper+hour")
    grad_h, _, _ = hourly.learning_step(rec)
    assert np.all(np.isfinite(grad_h)) and not np.allclose(grad_h, grad)
    # the hour indicators alone (a table over the hours) are a baseline too
    grad_t, _, info = small_experiment(value_features="hour").learning_step(rec)
    assert np.all(np.isfinite(grad_t)) and info["samples"] == int(use.sum())


# -- evaluation on fixed noise ----------------------------------------------------------------
def test_evaluation_series_and_schedule():
    exp = small_experiment(months=4, eval_every=2)
    h = exp.run(progress=False)
    assert h.eval_month == [0, 2, 3]  # every 2 months and the last month
    for key in History.EVAL_SERIES:
        assert len(getattr(h, key)) == 3, key
    # J_eval[j] is the mean over the K fixed draws of J of that month's theta: repeatable
    K = exp.learning.eval_draws
    assert K == 10  # the default
    theta0 = Theta.from_vector(np.asarray(h.theta[0]), SMALL.n)
    again = exp.evaluate(theta0)
    assert again.days == K * 3
    per_draw = draw_J(again, K)
    assert per_draw.mean() == h.J_eval[0]
    assert again.J() == pytest.approx(h.J_eval[0], rel=1e-12)
    assert exp.evaluate(theta0).J() == again.J()
    # the 95 % interval over the draws: mean -+ t(0.975, K-1) sd / sqrt(K)
    half = stats.t.ppf(0.975, K - 1) * per_draw.std(ddof=1) / np.sqrt(K)
    assert h.J_eval_ci_low[0] == pytest.approx(h.J_eval[0] - half, rel=1e-12)
    assert h.J_eval_ci_high[0] == pytest.approx(h.J_eval[0] + half, rel=1e-12)
    assert np.all(again.a == again.policy)  # no exploration
    assert again.grad_pi is None
    np.testing.assert_allclose(h.J_eval_per_agent[0], again.J_per_agent())
    assert h.eval_hours_soc_below_0_1[0] == again.summary()["hours_soc_below_0_1"] / K
    assert max(h.eval_max_P_mpc) <= SMALL.P_bar + 1e-9
    assert all(0.0 <= b <= 1.0 for b in h.eval_bound_share)
    # the evaluation never touches the learning run
    quiet = small_experiment(months=4, eval_every=0).run(progress=False)
    assert quiet.J == h.J and quiet.theta_final == h.theta_final
    assert quiet.J_eval == [] and quiet.eval_month == []
    # a different evaluation seed gives a different draw
    other = small_experiment(months=1, eval_seed=5).run(progress=False)
    assert other.J_eval[0] != h.J_eval[0]
    with pytest.raises(ValueError, match="eval_every=-1"):
        LearningConfig(eval_every=-1)


def test_evaluation_draws_are_independent_nested_and_leave_learning_alone():
    one = small_experiment(months=2, eval_every=1, eval_draws=1).run(progress=False)
    three = small_experiment(months=2, eval_every=1, eval_draws=3)
    h3 = three.run(progress=False)
    # learning (J, theta) does not depend on the evaluation
    assert one.J == h3.J and one.theta == h3.theta and one.theta_final == h3.theta_final
    # one draw: no interval; draw 0 of three is that draw (same noise, same J)
    assert all(np.isnan(one.J_eval_ci_low)) and all(np.isnan(one.J_eval_ci_high))
    theta0 = Theta.from_vector(np.asarray(h3.theta[0]), SMALL.n)
    rec = three.evaluate(theta0)
    J3 = draw_J(rec, 3)
    assert J3[0] == pytest.approx(one.J_eval[0], rel=1e-9)
    single = evaluate_mpc(theta0, three.solver, three.prices, SMALL, three.learning.eval_seed)
    np.testing.assert_array_equal(rec.noise[:, :3], single.noise)
    # the draws differ from each other (independent noise), the prices repeat
    assert not np.allclose(rec.noise[:, :3], rec.noise[:, 3:6])
    np.testing.assert_array_equal(rec.buy[:, :3], rec.buy[:, 6:9])
    assert len(set(np.round(J3, 6))) == 3
    assert h3.J_eval_ci_low[0] < h3.J_eval[0] < h3.J_eval_ci_high[0]
    with pytest.raises(ValueError, match="eval_draws=0"):
        LearningConfig(eval_draws=0)
    with pytest.raises(ValueError, match="draws=2"):
        draw_J(single, 2)


def test_hours_above_P_bar_per_month():
    h = small_experiment(months=2, eval_every=0).run(progress=False)
    for m, rec in ((0, h.first_month), (1, h.last_month)):
        above = np.count_nonzero(rec.grid_power > SMALL.P_bar + 1e-9)
        assert h.hours_above_P_bar[m] == above
        assert h.max_P_applied[m] == rec.grid_power.max()
        assert (above > 0) == (h.max_P_applied[m] > SMALL.P_bar + 1e-9)
    assert h.summary()["hours_above_P_bar"] == h.hours_above_P_bar


def test_resume_reproduces_the_evaluation_series(tmp_path):
    # evaluate every month, so that the month the run stopped in is evaluated too
    full = small_experiment(months=3, eval_every=1).run(progress=False)
    small_experiment(months=3, eval_every=1).run(months=1, out=tmp_path, progress=False)
    resumed = small_experiment(months=3, eval_every=1).run(out=tmp_path, resume=True,
                                                           progress=False)
    assert resumed.eval_month == full.eval_month == [0, 1, 2]
    assert resumed.J_eval == full.J_eval
    assert resumed.J_eval_per_agent == full.J_eval_per_agent
    assert resumed.J_eval_ci_low == full.J_eval_ci_low
    assert resumed.J_eval_ci_high == full.J_eval_ci_high


def test_history_roundtrip_keeps_the_evaluation_and_reads_older_files(tmp_path):
    h = small_experiment(months=2).run(progress=False)
    h.save(tmp_path)
    back = History.load(tmp_path)
    for key in History.EVAL_SERIES:
        assert getattr(back, key) == getattr(h, key), key
    assert back.summary()["J_eval"] == h.J_eval
    # a history written before the evaluation series (and the manifest) existed still loads
    (tmp_path / "manifest.json").unlink()
    meta = json.loads((tmp_path / "history.json").read_text())
    for key in History.EVAL_SERIES + History.EVAL_CI_SERIES:
        del meta[key]
    (tmp_path / "history.json").write_text(json.dumps(meta))
    old = History.load(tmp_path)
    assert old.J == h.J and old.J_eval == [] and old.eval_month == []



def test_history_from_before_the_interval_loads_as_one_draw(tmp_path):
    h = small_experiment(months=2, eval_every=1, eval_draws=2).run(progress=False)
    h.save(tmp_path)
    (tmp_path / "manifest.json").unlink()
    meta = json.loads((tmp_path / "history.json").read_text())
    for key in History.LATER_SERIES:
        del meta[key]
    del meta["learning"]["eval_draws"]
    (tmp_path / "history.json").write_text(json.dumps(meta))
    old = History.load(tmp_path)
    assert old.learning.eval_draws == 1  # what runs were evaluated on before
    assert old.J_eval == h.J_eval and len(old.J_eval_ci_low) == 2
    assert all(np.isnan(old.J_eval_ci_low + old.J_eval_ci_high + old.hours_above_P_bar))
    assert len(old.hours_above_P_bar) == old.months


def test_bound_share_by_hand():
    system = SystemConfig(P_bar=1.5)
    rec = small_experiment(months=1).evaluate()
    # hand-made actions: (hours=1, days=1, n=3) rows
    cases = {
        (1.0, -1.0, 0.0): 1.0,      # at U_bar, at -U_bar, idle
        (0.5, 0.5, 0.5): 1.0,       # buying together at the grid limit 1.5
        (0.5, 0.5, 0.2): 0.0,       # interior, total 1.2 < P_bar
        (-0.97, 0.3, 0.03): 2 / 3,  # within 0.05 of -U_bar and of 0; 0.3 is interior
    }
    for actions, share in cases.items():
        a = np.array(actions, dtype=float).reshape(1, 1, 3)
        rec.policy, rec.solver_ok, rec.system = a, np.ones((1, 1), bool), system
        assert rec.bound_share() == pytest.approx(share), actions
    assert rec.bound_share(tol=0.0) == pytest.approx(0.0)
    with pytest.raises(ValueError, match="tol"):
        rec.bound_share(tol=-1.0)


def test_batch_and_ipopt_back_ends_give_the_same_history():
    """The fast back-end solves the same barrier problem: a short learning run agrees with the
    IPOPT reference (policy to ~1e-9, so J and theta agree far inside the tolerance)."""
    learning = LearningConfig(days_per_month=2, months=2, seed=3, eval_every=1)
    runs = {
        backend: Experiment(system=SMALL, mpc_config=MPCConfig(backend=backend),
                            learning=learning).run(progress=False)
        for backend in ("ipopt", "batch")
    }
    ref, fast = runs["ipopt"], runs["batch"]
    assert ref.backend == "ipopt" and fast.backend == "batch"
    np.testing.assert_allclose(fast.J, ref.J, rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(fast.J_eval, ref.J_eval, rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(fast.theta_final, ref.theta_final, rtol=1e-5, atol=1e-8)
    assert fast.solver_failures == ref.solver_failures == [0, 0]
    assert fast.skipped_steps == ref.skipped_steps


# -- the day-end forecast as an option of MPCConfig -----------------------------------------
def test_forecast_option_changes_only_the_forecast():
    """``MPCConfig(forecast='until_midnight')``: the MPC's windows are zero after midnight,
    everything else (the true cost, the random draws, the hours whose windows end before
    midnight) is the paper's."""
    from mpcrl_lite.system.battery import agent_costs
    from mpcrl_lite.system.forecast import DayEndPrices

    learning = LearningConfig(days_per_month=3, months=1, seed=7, eval_every=0)
    paper = Experiment(system=SMALL, learning=learning)
    late = Experiment(system=SMALL, mpc_config=MPCConfig(forecast="until_midnight"),
                      learning=learning)
    assert paper.mpc_config.forecast == "paper" and not isinstance(paper.prices, DayEndPrices)
    assert isinstance(late.prices, DayEndPrices)
    np.testing.assert_array_equal(late.prices.buy, paper.prices.buy)  # what is charged
    np.testing.assert_array_equal(late.prices.sell, paper.prices.sell)
    N = SMALL.N
    for hour in (0, 17, 18, 20, 23):
        buy, sell = late.prices.window(hour, N)
        ref_buy, ref_sell = paper.prices.window(hour, N)
        today = hour + np.arange(N) < 24
        np.testing.assert_array_equal(buy[:, today], ref_buy[:, today])
        np.testing.assert_array_equal(sell[:, today], ref_sell[:, today])
        assert np.all(buy[:, ~today] == 0.0) and np.all(sell[:, ~today] == 0.0)
    a = paper.run_one_month()
    b = late.run_one_month()
    early = 24 - N  # windows of hours 0 .. 17 end before midnight: the same MPC, same actions
    np.testing.assert_allclose(b.a[:early], a.a[:early], rtol=0, atol=1e-9)
    np.testing.assert_array_equal(b.noise, a.noise)  # the same draws
    assert np.abs(b.a[early:] - a.a[early:]).max() > 1e-3  # the late hours plan otherwise
    # the true cost is charged at the real prices, hour by hour
    real_buy, real_sell = paper.prices.buy, paper.prices.sell
    for k in range(24):
        cost = agent_costs(b.soc[k], b.b[k], b.s[k], real_buy[:, k], real_sell[:, k], SMALL)
        np.testing.assert_allclose(b.agent_cost[k], cost, rtol=1e-12, atol=1e-9)


def test_forecast_round_trips_through_history_and_checkpoint(tmp_path):
    from mpcrl_lite.system.forecast import until_midnight

    learning = LearningConfig(days_per_month=3, months=2, seed=7, eval_every=0)
    late = MPCConfig(forecast="until_midnight")
    Experiment(system=SMALL, mpc_config=late, learning=learning).run(months=1, out=tmp_path,
                                                                     progress=False)
    assert History.load(tmp_path).mpc.forecast == "until_midnight"
    saved = json.loads((tmp_path / "checkpoint.json").read_text())
    assert saved["mpc"]["forecast"] == "until_midnight"
    # a resume with the paper's forecast is refused in one line naming the field
    with pytest.raises(ValueError, match="mpc.forecast='until_midnight' in the run, 'paper' "
                                         "now") as err:
        Experiment(system=SMALL, learning=learning).run(out=tmp_path, resume=True,
                                                        progress=False)
    assert len(str(err.value).splitlines()) == 1
    # prices given as until_midnight(...) are the same option, recorded as such
    prices = until_midnight(Prices.month(SMALL, 3))
    again = Experiment(system=SMALL, learning=learning, prices=prices)
    assert again.mpc_config.forecast == "until_midnight"
    history = again.run(out=tmp_path, resume=True, progress=False)
    assert history.months == 2 and history.mpc.forecast == "until_midnight"


def test_a_run_from_before_the_forecast_option_resumes_with_the_paper_forecast(tmp_path):
    """Checkpoints and manifests written before ``MPCConfig.forecast`` (and the price
    fingerprint) existed resume unchanged."""
    from mpcrl_lite._util import jsonio
    from mpcrl_lite.learning import rundir

    small_experiment(months=2).run(months=1, out=tmp_path, progress=False)
    state = json.loads((tmp_path / "checkpoint.json").read_text())
    history = json.loads((tmp_path / "history.json").read_text())
    for data in (state, history):
        del data["mpc"]["forecast"]
    del state["prices"]
    files = {"checkpoint.json": jsonio.dumps(state), "history.json": jsonio.dumps(history),
             "history.npz": (tmp_path / "history.npz").read_bytes()}
    configs = {key: state[key] for key in ("system", "mpc", "learning")}
    configs["learning"] = {k: v for k, v in configs["learning"].items() if k != "months"}
    rundir.commit(tmp_path, files, kind="centralized", months_done=1,
                  configs_hash=rundir.config_sha256(configs))
    resumed = small_experiment(months=2).run(out=tmp_path, resume=True, progress=False)
    assert resumed.months == 2 and resumed.mpc.forecast == "paper"


def test_resume_refuses_other_prices_in_one_line(tmp_path):
    learning = LearningConfig(days_per_month=3, months=2, seed=7, eval_every=0)
    Experiment(system=SMALL, learning=learning).run(months=1, out=tmp_path, progress=False)
    saved = json.loads((tmp_path / "checkpoint.json").read_text())["prices"]
    assert saved["shape"] == [3, 24] and len(saved["sha256"]) == 64
    shipped = Prices.month(SMALL, 3)
    other = Prices(shipped.buy[::-1], source="other month")
    with pytest.raises(ValueError, match="other prices") as err:
        Experiment(system=SMALL, learning=learning, prices=other).run(
            out=tmp_path, resume=True, progress=False)
    message = str(err.value)
    assert len(message.splitlines()) == 1
    assert "'other month'" in message and repr(shipped.source) in message
    assert saved["sha256"][:12] in message
    # the same prices resume
    assert Experiment(system=SMALL, learning=learning, prices=Prices.month(SMALL, 3)).run(
        out=tmp_path, resume=True, progress=False).months == 2
