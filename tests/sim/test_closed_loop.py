"""The one closed loop (mpcrl_lite.sim.closed_loop) and its record (mpcrl_lite.sim.record)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from mpcrl_lite.config import SystemConfig
from mpcrl_lite.mpc.formulation import MPC
from mpcrl_lite.sim.closed_loop import Decision, MPCPolicy, SensitivityRecorder, rollout, simulate
from mpcrl_lite.sim.exploration import GaussianExploration, Projection
from mpcrl_lite.sim.record import RECORD_ARRAYS, MonthRecord, Record, Trajectory
from mpcrl_lite.system.battery import discounted_return, project_action, sample_noise
from mpcrl_lite.system.prices import Prices
from mpcrl_lite.theta import Theta

SYSTEM = SystemConfig()


def _prices(days: int, hours: int = 24) -> tuple[np.ndarray, np.ndarray]:
    buy = 50.0 + 40.0 * np.sin(np.arange(days * hours).reshape(days, hours) / 3.0)
    return buy, 0.5 * buy


def _rule(hour: int, soc: np.ndarray) -> np.ndarray:
    """Charge when low, discharge when high, harder in the evening."""
    return np.where(soc < 0.5, 0.6, -0.6) * (1.0 + (hour >= 18))


# -- rollouts of plain policies ---------------------------------------------------------------
def _two_hour_system():
    return SystemConfig(
        n=2, alpha=0.1, noise_mean=0.2, noise_var=0.0, U_bar=1.0, P_bar=1.5,
        p=1000.0, gamma=0.9, hours_per_day=2,
    )


def test_rollout_reproduces_hand_computed_two_hour_day():
    system = _two_hour_system()
    plan = {0: [1.0, -1.0], 1: [-0.5, -1.0]}  # the rule: a fixed schedule per hour
    calls = []

    def policy(hour, soc):
        calls.append((hour, soc.copy()))
        return np.array([plan[hour]])

    buy = np.array([[100.0, 200.0]])
    sell = np.array([[50.0, 100.0]])
    traj = rollout(policy, buy, sell, system, np.random.default_rng(0), soc0=[0.95, 0.15])

    assert isinstance(traj, Trajectory)
    assert (traj.hours, traj.days, traj.n) == (2, 1, 2)
    # hour 0: agent 1 raw 0.95 + 0.1 (0.2 + 1) = 1.07 -> buys only 0.3, soc 1;
    #         agent 2 raw 0.15 + 0.1 (0.2 - 1) = 0.07, untouched
    # hour 1: agent 1 raw 1 + 0.1 (0.2 - 0.5) = 0.97, untouched;
    #         agent 2 raw 0.07 + 0.1 (0.2 - 1) = -0.01 -> sells only 0.9, soc 0
    np.testing.assert_allclose(
        traj.soc[:, 0, :], [[0.95, 0.15], [1.0, 0.07], [0.97, 0.0]], atol=1e-12
    )
    np.testing.assert_allclose(traj.a[:, 0, :], [[1.0, -1.0], [-0.5, -1.0]])
    np.testing.assert_allclose(traj.b[:, 0, :], [[0.3, 0.0], [0.0, 0.0]], atol=1e-12)
    np.testing.assert_allclose(traj.s[:, 0, :], [[0.0, 1.0], [0.5, 0.9]], atol=1e-12)
    np.testing.assert_allclose(traj.correction[:, 0, :], [[-0.7, 0.0], [0.0, 0.1]], atol=1e-12)
    np.testing.assert_allclose(traj.noise, 0.2)
    # costs: hour 0: 100*0.3 + 50 (soc 0.95) and -50*1; hour 1: -100*0.5 + 100 (soc 1.0)
    # and -100*0.9 + 30 (soc 0.07)
    np.testing.assert_allclose(
        traj.agent_cost[:, 0, :], [[80.0, -50.0], [50.0, -60.0]], atol=1e-9
    )
    np.testing.assert_allclose(traj.stage_cost[:, 0], [30.0, -10.0], atol=1e-9)
    np.testing.assert_allclose(traj.grid_power[:, 0], [1.0, 1.4], atol=1e-12)
    assert traj.J() == pytest.approx(30.0 + 0.9 * -10.0)
    np.testing.assert_allclose(traj.J_per_agent(), [80 + 0.9 * 50, -50 + 0.9 * -60])
    assert traj.hours_soc_below() == 1  # 0.07 at hour 1 (the final 0.0 is not counted)
    assert traj.hours_soc_above() == 2  # 0.95 and 1.0
    assert traj.hours_soc_below(0.2) == 2
    assert traj.hours_soc_above(0.99) == 1
    assert [h for h, _ in calls] == [0, 1]
    np.testing.assert_allclose(calls[1][1], [[1.0, 0.07]], atol=1e-12)


def test_rollout_noise_is_drawn_hour_by_hour_and_reproducible():
    system = SystemConfig(hours_per_day=5)
    days = 4
    buy = np.full((days, 5), 100.0)
    sell = 0.5 * buy

    def policy(hour, soc):
        return np.where(soc < 0.5, 0.5, -0.5)

    t1 = rollout(policy, buy, sell, system, np.random.default_rng(7))
    t2 = rollout(policy, buy, sell, system, np.random.default_rng(7))
    np.testing.assert_array_equal(t1.soc, t2.soc)
    expected = np.random.default_rng(7).normal(0.0, np.sqrt(0.5), size=(5, days, 3))
    np.testing.assert_array_equal(t1.noise, expected)
    np.testing.assert_allclose(t1.soc[0], 0.6)
    assert np.all((t1.soc >= 0) & (t1.soc <= 1))
    # the trajectory's arrays are consistent with one another
    np.testing.assert_allclose(t1.stage_cost, t1.agent_cost.sum(-1))
    np.testing.assert_allclose(t1.b - t1.s, t1.a + t1.correction, atol=1e-12)
    np.testing.assert_allclose(
        t1.soc[1:], t1.soc[:-1] + system.alpha * (t1.noise + t1.b - t1.s), atol=1e-12
    )
    np.testing.assert_allclose(
        t1.J(), discounted_return(t1.stage_cost, system.gamma).mean()
    )
    np.testing.assert_allclose(t1.J_per_agent().sum(), t1.J())


def test_rollout_soc0_broadcasts():
    system = _two_hour_system()
    buy = np.ones((3, 2))
    zero = lambda hour, soc: np.zeros_like(soc)
    for soc0 in (0.3, [0.3, 0.4], np.full((3, 2), 0.3)):
        traj = rollout(zero, buy, buy, system, np.random.default_rng(0), soc0=soc0)
        assert traj.soc.shape == (3, 3, 2)
    traj = rollout(zero, buy, buy, system.replace(soc0=0.5), np.random.default_rng(0))
    np.testing.assert_array_equal(traj.soc[0], 0.5)


def test_rollout_bad_inputs():
    system = _two_hour_system()
    rng = np.random.default_rng(0)
    ok = lambda hour, soc: np.zeros_like(soc)
    buy = np.ones((3, 2))
    with pytest.raises(ValueError, match=r"buy has shape \(3, 5\).*\(days, 2\)"):
        rollout(ok, np.ones((3, 5)), np.ones((3, 5)), system, rng)
    with pytest.raises(ValueError, match=r"sell has shape \(2, 2\)"):
        rollout(ok, buy, np.ones((2, 2)), system, rng)
    with pytest.raises(ValueError, match=r"soc0 has shape \(4,\)"):
        rollout(ok, buy, buy, system, rng, soc0=np.zeros(4))
    with pytest.raises(ValueError, match=r"soc0\[0, 1\]=.*1\.2"):
        rollout(ok, buy, buy, system, rng, soc0=[0.5, 1.2])
    with pytest.raises(ValueError, match=r"at hour 0: policy output has shape \(3, 3\)"):
        rollout(lambda h, soc: np.zeros((3, 3)), buy, buy, system, rng)
    nan_at_1 = lambda h, soc: np.full_like(soc, np.nan if h == 1 else 0.0)
    with pytest.raises(ValueError, match=r"at hour 1: policy output\[0, 0\]=.*nan"):
        rollout(nan_at_1, buy, buy, system, rng)
    with pytest.raises(ValueError, match=r"at hour 0: policy output has shape \(1, 2\).*\(3, 2\)"):
        rollout(lambda h, soc: np.zeros((1, 2)), buy, buy, system, rng)
    with pytest.raises(ValueError, match=r"policy=3"):
        rollout(3, buy, buy, system, rng)
    with pytest.raises(ValueError, match=r"rng=0"):
        rollout(ok, buy, buy, system, 0)


# -- the loop's contract ----------------------------------------------------------------------
def test_noise_array_gives_the_same_record_as_the_generator():
    """Common random numbers: the noise drawn at once is the noise drawn hour by hour."""
    buy, sell = _prices(3)
    drawn = simulate(_rule, buy, sell, SYSTEM, rng=np.random.default_rng(5))
    noise = sample_noise(np.random.default_rng(5), (24, 3, SYSTEM.n), SYSTEM)
    given = simulate(_rule, buy, sell, SYSTEM, noise=noise)
    for key in RECORD_ARRAYS:
        np.testing.assert_array_equal(getattr(given, key), getattr(drawn, key), err_msg=key)


def test_exploration_is_drawn_before_the_noise_every_hour():
    days, std = 4, 0.3
    buy, sell = _prices(days)
    record = simulate(_rule, buy, sell, SYSTEM, rng=np.random.default_rng(9),
                      explore=GaussianExploration(std, SYSTEM, "project"))
    replay = np.random.default_rng(9)
    for k in range(24):
        e = replay.standard_normal((days, SYSTEM.n))
        np.testing.assert_array_equal(record.noise[k], sample_noise(replay, (days, SYSTEM.n),
                                                                     SYSTEM))
        pi = _rule(k, record.soc[k])
        np.testing.assert_array_equal(record.policy[k], pi)
        np.testing.assert_array_equal(record.a[k], project_action(pi + std * e, SYSTEM))
    # the commanded actions respect the bounds and the grid limit
    assert np.all(np.abs(record.a) <= SYSTEM.U_bar + 1e-12)
    assert np.all(np.maximum(record.a, 0).sum(-1) <= SYSTEM.P_bar + 1e-12)


def test_hooks_see_every_hour_and_the_finished_record():
    buy, sell = _prices(2)
    seen, ends = [], []
    record = simulate(_rule, buy, sell, SYSTEM, rng=np.random.default_rng(0),
                      explore=Projection(SYSTEM), on_hour=[seen.append], on_day_end=[ends.append])
    assert [s.hour for s in seen] == list(range(24))
    assert ends == [record]
    for k, s in enumerate(seen):
        np.testing.assert_array_equal(s.soc, record.soc[k])
        np.testing.assert_array_equal(s.result.soc_next, record.soc[k + 1])
        np.testing.assert_array_equal(s.a, record.a[k])
        np.testing.assert_array_equal(s.noise, record.noise[k])
        np.testing.assert_array_equal(s.buy, buy[:, k])
        np.testing.assert_array_equal(s.sell, sell[:, k])


def test_plain_policy_record_and_its_figures():
    buy, sell = _prices(3)
    record = simulate(_rule, buy, sell, SYSTEM, rng=np.random.default_rng(1), hours=10)
    assert isinstance(record, Record) and Trajectory is Record
    assert (record.hours, record.days, record.n) == (10, 3, SYSTEM.n)
    assert record.soc.shape == (11, 3, SYSTEM.n)
    # a plain policy: no solver, no sensitivity, its plan is its own command
    assert record.solver_ok.all() and not record.sens_ok.any()
    np.testing.assert_array_equal(record.a, record.policy)
    planned = np.maximum(np.maximum(record.a, 0).sum(-1), np.maximum(-record.a, 0).sum(-1))
    np.testing.assert_allclose(record.planned_power, planned)
    np.testing.assert_array_equal(record.buy, buy[:, :10].T)
    # the costs add up and J is their discounted daily mean
    np.testing.assert_allclose(record.stage_cost, record.agent_cost.sum(-1))
    per_day = discounted_return(record.stage_cost, SYSTEM.gamma)
    np.testing.assert_array_equal(record.J_per_day(), per_day)
    assert record.J() == pytest.approx(per_day.mean())
    summary = record.summary()
    assert summary["J"] == record.J() and summary["solver_failures"] == 0
    assert summary["max_P_mpc"] == pytest.approx(planned.max())


def test_decision_fields_are_recorded():
    buy, sell = _prices(2)
    ok = np.array([True, False])

    def policy(hour, soc):
        return Decision(np.zeros_like(soc), solver_ok=ok, planned_power=np.full(2, 0.7),
                        sens_ok=~ok, grad=np.full((2, 5, SYSTEM.n), float(hour)))

    grads = SensitivityRecorder()
    record = simulate(policy, buy, sell, SYSTEM, rng=np.random.default_rng(0), on_hour=[grads])
    np.testing.assert_array_equal(record.solver_ok, np.broadcast_to(ok, (24, 2)))
    np.testing.assert_array_equal(record.sens_ok, np.broadcast_to(~ok, (24, 2)))
    assert np.all(record.planned_power == 0.7)
    assert grads.grad_pi.shape == (24, 2, 5, SYSTEM.n)
    np.testing.assert_array_equal(grads.grad_pi[:, 0, 0, 0], np.arange(24))
    assert record.summary()["solver_failures"] == 24
    with pytest.raises(ValueError, match="at hour 0: the policy returned no sensitivity"):
        simulate(_rule, buy, sell, SYSTEM, rng=np.random.default_rng(0),
                 on_hour=[SensitivityRecorder()])


def test_simulate_bad_inputs():
    buy, sell = _prices(2)
    rng = np.random.default_rng(0)
    with pytest.raises(ValueError, match="rng=None"):
        simulate(_rule, buy, sell, SYSTEM)
    with pytest.raises(ValueError, match=r"noise has shape \(24, 2, 2\)"):
        simulate(_rule, buy, sell, SYSTEM, noise=np.zeros((24, 2, 2)))
    with pytest.raises(ValueError, match="noise: expected finite"):
        simulate(_rule, buy, sell, SYSTEM, noise=np.full((24, 2, 3), np.nan))
    for hours in (0, 25, 2.0):
        with pytest.raises(ValueError, match=f"hours={hours!r}"):
            simulate(_rule, buy, sell, SYSTEM, rng=rng, hours=hours)
    with pytest.raises(ValueError, match="system="):
        simulate(_rule, buy, sell, "system", rng=rng)
    with pytest.raises(ValueError, match="std=-0.1"):
        GaussianExploration(-0.1, SYSTEM)
    with pytest.raises(ValueError, match="exploration needs rng"):
        simulate(_rule, buy, sell, SYSTEM, noise=np.zeros((24, 2, 3)),
                 explore=GaussianExploration(0.1, SYSTEM))


# -- the MPC as a policy ----------------------------------------------------------------------
class _ScriptedSolver:
    """A back-end stand-in: records the warm starts it gets; day 1 fails at hour 2."""

    def __init__(self, mpc: MPC) -> None:
        self.mpc, self.calls = mpc, []

    def solve_batch(self, soc, buy, sell, theta, x0=None):
        days = soc.shape[0]
        hour = len(self.calls)
        self.calls.append(None if x0 is None else x0.copy())
        x = np.full((days, self.mpc.nx), 0.01 * (hour + 1))
        success = np.ones(days, bool)
        if hour == 2:
            success[1] = False
        return SimpleNamespace(x=x, success=success, action=np.zeros((days, self.mpc.n)))


def test_mpc_policy_warm_starts_from_the_shifted_solution_and_restarts_per_run():
    system = SystemConfig(N=4)
    mpc = MPC(system)
    solver = _ScriptedSolver(mpc)
    prices = Prices.month(system, 2)
    policy = MPCPolicy(solver, Theta.nominal(system), prices)
    H = system.hours_per_day
    simulate(policy, prices.buy[:, :H], prices.sell[:, :H], system,
             rng=np.random.default_rng(0), hours=5)
    assert solver.calls[0] is None
    np.testing.assert_array_equal(solver.calls[1], mpc.shift(np.full((2, mpc.nx), 0.01)))
    # day 1 failed at hour 2: its shifted guess is kept, day 0 moves on to the new solution
    np.testing.assert_array_equal(solver.calls[3][0], mpc.shift(np.full(mpc.nx, 0.03)))
    np.testing.assert_array_equal(solver.calls[3][1], mpc.shift(solver.calls[2][1]))
    assert policy.failures == 1
    simulate(policy, prices.buy[:, :H], prices.sell[:, :H], system,
             rng=np.random.default_rng(0), hours=1)
    assert solver.calls[5] is None  # a new run starts cold
    with pytest.raises(ValueError, match="theta="):
        MPCPolicy(solver, Theta.nominal(SystemConfig(n=2)), prices)


# -- the record -------------------------------------------------------------------------------
def test_record_arrays_round_trip_and_month_record_shares_them():
    buy, sell = _prices(2)
    record = simulate(_rule, buy, sell, SYSTEM, rng=np.random.default_rng(3))
    saved = record.arrays("first")
    assert set(saved) == {f"first_{k}" for k in RECORD_ARRAYS}
    back = MonthRecord.from_arrays(saved, "first", SYSTEM)
    assert isinstance(back, MonthRecord) and back.grad_pi is None
    for key in RECORD_ARRAYS:
        np.testing.assert_array_equal(getattr(back, key), getattr(record, key))
    month = MonthRecord.from_record(record, grad_pi=np.zeros(1))
    assert month.soc is record.soc and month.summary() == record.summary()
    with pytest.raises(ValueError, match="level="):
        record.hours_soc_below([0.1, 0.2])


# -- the hour's checks: once where the inputs are known to be good ---------------------------
def test_the_unchecked_step_is_the_checked_one_to_the_last_bit():
    from mpcrl_lite.system.battery import step, step_unchecked

    rng = np.random.default_rng(4)
    soc = rng.uniform(0.0, 1.0, (7, SYSTEM.n))
    a = rng.uniform(-2.0, 2.0, (7, SYSTEM.n))  # some beyond the low-level controller's edges
    noise = sample_noise(rng, (7, SYSTEM.n), SYSTEM)
    buy = rng.uniform(10.0, 90.0, 7)
    checked = step(soc, a, noise, buy, 0.5 * buy, SYSTEM)
    unchecked = step_unchecked(soc, a, noise, buy, 0.5 * buy, SYSTEM)
    for name in ("soc_next", "b", "s", "correction", "agent_cost", "stage_cost", "grid_power"):
        assert getattr(checked, name).tobytes() == getattr(unchecked, name).tobytes(), name


def test_the_exploration_hook_gives_bounded_exploration_to_the_last_bit():
    from mpcrl_lite.sim.exploration import bounded_exploration

    pi = project_action(np.random.default_rng(8).uniform(-1.5, 1.5, (40, SYSTEM.n)), SYSTEM)
    for bounds in ("symmetric", "radial", "project"):
        hook = GaussianExploration(0.4, SYSTEM, bounds)
        got = hook(3, pi, np.random.default_rng(2))
        e = 0.4 * np.random.default_rng(2).standard_normal(pi.shape)
        assert got.tobytes() == bounded_exploration(pi, e, SYSTEM, bounds).tobytes(), bounds
    # a bad action still gets bounded_exploration's error
    with pytest.raises(ValueError, match="non-finite"):
        GaussianExploration(0.4, SYSTEM)(3, np.full((2, SYSTEM.n), np.nan),
                                        np.random.default_rng(2))


def test_an_action_from_another_hook_is_still_checked():
    buy, sell = _prices(2)

    def broken(hour, pi, rng):
        return np.where(hour == 5, np.inf, pi)

    with pytest.raises(ValueError, match="expected finite values only"):
        simulate(_rule, buy, sell, SYSTEM, rng=np.random.default_rng(0), explore=broken)
