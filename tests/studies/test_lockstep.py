"""Runs in lockstep: each run's History, theta, optimizer and generator are those of the run
alone, bit for bit; runs resume across both ways of running; one failing run fails alone."""

from __future__ import annotations

import io
import json

import numpy as np
import pytest

from mpcrl_lite import LearningConfig, SystemConfig
from mpcrl_lite.learning import rundir
from mpcrl_lite.learning.experiment import Experiment
from mpcrl_lite.learning.history import History
from mpcrl_lite.sim.closed_loop import MPCPolicy, RunBlocks, run_month, simulate
from mpcrl_lite.studies import lockstep
from mpcrl_lite.studies.lockstep import group_key, run_lockstep, split_record
from mpcrl_lite.system.battery import sample_noise
from mpcrl_lite.system.prices import Prices
from mpcrl_lite.theta import Theta

TIMINGS = ("wall_time_s",)


def make_runs(months: int = 3) -> list[Experiment]:
    """Three runs: two seeds and two noise variances at one grid limit, a third run at
    another grid limit (a second group), evaluated every other month."""
    def one(seed: int, noise_var: float, P_bar: float) -> Experiment:
        system = SystemConfig(N=6, noise_var=noise_var, P_bar=P_bar)
        learning = LearningConfig(days_per_month=3, months=months, seed=seed, eval_every=2,
                                  eval_draws=2)
        return Experiment(system=system, learning=learning)
    return [one(1, 0.5, 2.0), one(2, 0.3, 2.0), one(3, 0.5, 1.8)]


def comparable(exp: Experiment) -> dict:
    """Everything a run leaves, timings aside: history.json, the arrays of history.npz,
    theta, the optimizer and the generator."""
    files = exp.history.to_files()
    meta = json.loads(files["history.json"])
    for key in TIMINGS:
        assert len(meta.pop(key)) == exp.history.months
    for info in meta["update_info"]:
        info.pop("eval_time_s", None)
    with np.load(io.BytesIO(files["history.npz"])) as npz:
        arrays = {k: npz[k] for k in npz.files}
    state = exp.checkpoint_state()
    return {"meta": meta, "arrays": arrays, "state": json.loads(json.dumps(state))}


def assert_same(a: dict, b: dict) -> None:
    assert a["meta"] == b["meta"]
    assert a["state"] == b["state"]
    assert a["arrays"].keys() == b["arrays"].keys()
    for k in a["arrays"]:
        np.testing.assert_array_equal(a["arrays"][k], b["arrays"][k], err_msg=k)


def test_groups_follow_the_formulation_not_the_seed_or_noise():
    runs = make_runs()
    keys = [group_key(r) for r in runs]
    assert keys[0] == keys[1] != keys[2]
    assert group_key(Experiment(system=SystemConfig(N=6), mpc_config=runs[0].mpc_config.replace(
        backend="batch"))) is None


def test_run_blocks_draw_each_block_from_its_own_generator():
    systems = [SystemConfig(noise_var=0.5), SystemConfig(noise_var=0.2, noise_mean=0.1)]
    blocks = RunBlocks([np.random.default_rng(1), np.random.default_rng(2)], systems)
    e = blocks.standard_normal((4, 3))
    d = blocks.noise((4, 3))
    for r, (seed, system) in enumerate(zip((1, 2), systems, strict=True)):
        alone = np.random.default_rng(seed)
        np.testing.assert_array_equal(e[2 * r:2 * r + 2], alone.standard_normal((2, 3)))
        np.testing.assert_array_equal(d[2 * r:2 * r + 2], sample_noise(alone, (2, 3), system))
    with pytest.raises(ValueError, match="2 blocks"):
        blocks.standard_normal((3, 3))
    with pytest.raises(ValueError, match="generators"):
        RunBlocks([np.random.default_rng(1)], systems)
    with pytest.raises(ValueError, match="rngs\\[0\\]"):
        RunBlocks([1, 2], systems)


def test_a_stacked_month_is_each_run_month_alone():
    system = SystemConfig(N=6)
    exp = Experiment(system=system, learning=LearningConfig(days_per_month=3))
    thetas = [Theta.nominal(system), Theta.nominal(system).replace(b=np.full(3, 0.3))]
    systems = [system, system.replace(noise_var=0.1)]
    stacked = run_month(thetas, exp.solver, exp.prices, system,
                        RunBlocks([np.random.default_rng(5), np.random.default_rng(6)], systems),
                        exploration_std=0.2)
    assert stacked.days == 6 and stacked.grad_pi.shape[1] == 6
    for part, theta, sys_r, seed in zip(split_record(stacked, systems), thetas, systems, (5, 6),
                                        strict=True):
        alone = run_month(theta, exp.solver, exp.prices, sys_r, np.random.default_rng(seed),
                          exploration_std=0.2)
        for name, value in alone.fields().items():
            if isinstance(value, np.ndarray):
                np.testing.assert_array_equal(getattr(part, name), value, err_msg=name)
        np.testing.assert_array_equal(part.grad_pi, alone.grad_pi)
        assert part.system == sys_r
    with pytest.raises(ValueError, match="equal days"):
        split_record(stacked, systems * 2)


def test_mpc_policy_checks_its_thetas():
    exp = Experiment(system=SystemConfig(N=6), learning=LearningConfig(days_per_month=3))
    with pytest.raises(ValueError, match="sequence"):
        MPCPolicy(exp.solver, [], exp.prices)
    policy = MPCPolicy(exp.solver, [exp.theta, exp.theta], exp.prices)
    prices = Prices(np.tile(exp.prices.buy, (2, 1))[:5])
    with pytest.raises(ValueError, match="5 rows for 2 thetas"):
        simulate(MPCPolicy(exp.solver, [exp.theta, exp.theta], prices), prices.buy, prices.sell,
                 exp.system, rng=np.random.default_rng(0))
    assert policy.theta == [exp.theta, exp.theta]


def test_lockstep_runs_are_the_runs_alone_and_resume_both_ways(tmp_path, monkeypatch):
    alone = [run.run(progress=False) and comparable(run) for run in make_runs(4)]
    stacked: list[int] = []

    def counting(theta, *args, **kwargs):
        stacked.append(len(theta))
        return run_month(theta, *args, **kwargs)

    monkeypatch.setattr(lockstep, "run_month", counting)
    # two months in lockstep, then one run resumed alone and the others in lockstep again
    outs = [tmp_path / f"run{i}" for i in range(3)]
    first = make_runs(4)
    results = run_lockstep(first, months=2, outs=outs)
    assert all(h.months == 2 for h in results)
    assert (outs[0] / "checkpoint.json").exists()
    solo = make_runs(4)[0]
    solo.run(out=outs[0], resume=True, progress=False)
    rest = make_runs(4)
    results = run_lockstep(rest[1:], outs=outs[1:], resume=True)
    assert [h.months for h in results] == [4, 4]
    # the two runs at one grid limit shared their loop (twice), the third ran in a group
    # of its own; after the resume, runs 1 and 2 are in different groups
    assert stacked == [2, 2]
    for got, want in zip([solo, *rest[1:]], alone, strict=True):
        assert_same(comparable(got), want)
    # and a run begun alone continues in lockstep
    again = make_runs(4)
    again[2].run(months=1, out=tmp_path / "x2", progress=False)
    run_lockstep(again, outs=[tmp_path / "x0", tmp_path / "x1", tmp_path / "x2"], resume=True)
    assert stacked == [2] * 6
    for got, want in zip(again, alone, strict=True):
        assert_same(comparable(got), want)


def test_pathwise_runs_in_lockstep_record_their_gradients_in_the_shared_loop(monkeypatch):
    """Pathwise runs in lockstep record their gradients in the group's one loop (a solver
    call an hour for the group, no second pass per run) and learn what they learn alone,
    bit for bit."""
    def runs() -> list[Experiment]:
        system = SystemConfig(N=6)
        return [Experiment(system=system, learning=LearningConfig(
            gradient="pathwise", days_per_month=3, months=2, seed=seed, eval_every=0))
            for seed in (1, 2)]

    alone = [run.run(progress=False) and comparable(run) for run in runs()]
    together = runs()
    calls: list[int] = []
    solve = together[0].solver.solve_batch
    together[0].solver.solve_batch = lambda *a, **k: calls.append(1) or solve(*a, **k)
    results = run_lockstep(together)
    assert [h.months for h in results] == [2, 2]
    assert len(calls) == 2 * together[0].system.hours_per_day  # two months, one call an hour
    for got, want in zip(together, alone, strict=True):
        assert_same(comparable(got), want)


class BrokenGenerator(np.random.Generator):
    """A generator that fails when asked for the exploration (a fault inside a group's loop)."""

    def standard_normal(self, *args, **kwargs):
        raise RuntimeError("broken generator")


def test_one_failing_run_does_not_stop_the_others(tmp_path):
    alone = [run.run(progress=False) and comparable(run) for run in make_runs(3)]
    runs = make_runs(3)
    # run 1 fails inside its group's loop, after run 0 has drawn from its generator: the
    # group is stepped alone (run 0's generator restored) and only run 1 fails
    runs[1].rng = BrokenGenerator(np.random.PCG64(2))

    def crash(month, history, learner):
        if month == 1:
            raise RuntimeError("boom")

    runs[2].callbacks.append(crash)
    failed = []
    results = run_lockstep(runs, outs=[tmp_path / str(i) for i in range(3)],
                           on_failure=lambda i, err: failed.append(i))
    assert sorted(failed) == [1, 2]
    assert isinstance(results[1], RuntimeError) and "broken" in str(results[1])
    assert runs[1].history.months == 0
    assert isinstance(results[2], RuntimeError) and runs[2].history.months == 2
    assert results[0].months == 3
    assert_same(comparable(runs[0]), alone[0])
    # the run that failed after its checkpoint keeps its last good month
    assert rundir.read(tmp_path / "2", ["checkpoint.json"]).months_done == 2
    assert History.load(tmp_path / "2").J == runs[2].history.J


def test_lockstep_rejects_bad_input(tmp_path):
    runs = make_runs(1)
    with pytest.raises(ValueError, match="run directories"):
        run_lockstep(runs, outs=[tmp_path])
    with pytest.raises(ValueError, match="months=0"):
        run_lockstep(runs, months=0)
    results = run_lockstep(runs[:1], outs=[tmp_path], resume=True, force=True)
    assert isinstance(results[0], ValueError) and "exclude" in str(results[0])


# -- the sweep runs its chunks in lockstep -------------------------------------------------
SWEEP_GRID = {
    "base": {"learning": {"months": 2, "days_per_month": 2, "eval_draws": 2},
             "system": {"N": 4}},
    "grid": {"system.P_bar": [1.0, 1.5], "system.noise_var": [0.5, 0.3],
             "learning.seed": [0, 1]},
}


def test_sweep_in_lockstep_is_the_sweep_run_by_run(tmp_path, monkeypatch):
    from mpcrl_lite.learning.history import History
    from mpcrl_lite.studies.sweep.api import GridError, run_sweep

    stacked: list[int] = []

    def counting(theta, *args, **kwargs):
        stacked.append(len(theta))
        return run_month(theta, *args, **kwargs)

    monkeypatch.setattr(lockstep, "run_month", counting)
    together = run_sweep(SWEEP_GRID, tmp_path / "a", scheduler="serial", progress=False)
    # one chunk of all 8 runs: two groups (the grid limits) of 4 runs, for 2 months
    assert stacked == [4, 4, 4, 4]
    one = run_sweep(SWEEP_GRID, tmp_path / "b", scheduler="serial", progress=False, lockstep=1)
    assert stacked == [4, 4, 4, 4]
    three = run_sweep(SWEEP_GRID, tmp_path / "c", scheduler="serial", progress=False,
                      lockstep=3)
    # chunks of 3 + 3 + 2 runs in grid order (P_bar outermost): 3 | 1 alone + 2 | 2
    assert sorted(stacked[4:]) == [2, 2, 2, 2, 3, 3]
    assert (together["status"] == "done").all() and (one["status"] == "done").all()
    for run_id in together["run_id"]:
        files = [History.load(tmp_path / d / "runs" / run_id).to_files()["history.json"]
                 for d in "abc"]
        metas = [json.loads(f) for f in files]
        for meta in metas:
            meta.pop("wall_time_s")
            for info in meta["update_info"]:
                info.pop("eval_time_s", None)
        assert metas[0] == metas[1] == metas[2]
    for col in ("J_first", "J_last", "months"):
        assert together[col].tolist() == one[col].tolist() == three[col].tolist()
    with pytest.raises(GridError, match="lockstep=0"):
        run_sweep(SWEEP_GRID, tmp_path / "d", scheduler="serial", lockstep=0)
    assert not (tmp_path / "d").exists()


def test_cli_lockstep_flags(tmp_path, monkeypatch, capsys):
    from mpcrl_lite.cli import main as cli

    parser = cli.build_parser()
    args = parser.parse_args(["sweep", "--grid", "g.yaml", "--out", "o", "--lockstep", "3"])
    assert args.lockstep == 3
    args = parser.parse_args(["study", "--seeds", "2", "--months", "1", "--out", "o"])
    assert args.lockstep is None
    with pytest.raises(SystemExit):
        parser.parse_args(["study", "--seeds", "2", "--months", "1", "--out", "o",
                           "--lockstep", "0"])
    assert "--lockstep" in capsys.readouterr().err
    seen = {}

    def fake_study(*args, **kwargs):
        seen.update(kwargs)
        raise ValueError("stop here")

    monkeypatch.setattr("mpcrl_lite.studies.study.run_study", fake_study)
    assert cli.main(["study", "--seeds", "2", "--months", "1", "--out", str(tmp_path),
                     "--lockstep", "2", "--quiet"]) == 2
    assert seen["lockstep"] == 2


def test_parameters_take_one_theta_per_problem():
    from mpcrl_lite.mpc.formulation import MPC

    system = SystemConfig(N=6)
    mpc = MPC(system)
    rng = np.random.default_rng(0)
    soc, buy, sell = rng.uniform(size=(4, 3)), rng.uniform(size=(4, 6)), rng.uniform(size=(4, 6))
    thetas = [Theta.nominal(system), Theta.nominal(system).replace(b=np.full(3, 0.2))]
    rows = np.repeat(np.stack([t.to_vector() for t in thetas]), 2, axis=0)
    P = mpc.parameters(soc, buy, sell, rows)
    for r, theta in enumerate(thetas):
        block = slice(2 * r, 2 * r + 2)
        np.testing.assert_array_equal(P[block], mpc.parameters(soc[block], buy[block],
                                                               sell[block], theta))
    with pytest.raises(ValueError, match=r"theta has shape \(3, 30\).*\(4, 30\)"):
        mpc.parameters(soc, buy, sell, rows[:3])
