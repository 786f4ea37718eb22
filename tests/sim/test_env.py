"""The Gymnasium environment: the API contract, the closed loop's costs, seeding, registration."""

from __future__ import annotations

import subprocess
import sys
import textwrap

import gymnasium
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

from mpcrl_lite.config import MPCConfig, SystemConfig
from mpcrl_lite.mpc.backends.registry import make_solver
from mpcrl_lite.mpc.formulation import MPC
from mpcrl_lite.sim.closed_loop import run_month, simulate
from mpcrl_lite.sim.env import ENV_ID, BatteryEnv, MPCAgent, make_day_vector_env
from mpcrl_lite.sim.exploration import Projection
from mpcrl_lite.system.battery import discounted_return
from mpcrl_lite.system.prices import Prices
from mpcrl_lite.theta import Theta


def _episode(env, policy, seed=None, options=None):
    obs, _ = env.reset(seed=seed, options=options)
    rewards, infos, done = [], [], False
    while not done:
        obs, reward, done, truncated, info = env.step(policy(obs))
        assert not truncated
        rewards.append(reward)
        infos.append(info)
    return np.array(rewards), infos


def test_check_env_passes():
    check_env(BatteryEnv(prices=Prices.month(None, 3)), skip_render_check=True)
    check_env(BatteryEnv(SystemConfig(n=2, P_bar=0.8), prices=Prices.month(None, 2), day=1),
              skip_render_check=True)


def test_spaces_have_the_systems_bounds():
    system = SystemConfig(n=2, U_bar=0.7, P_bar=1.0, N=5)
    env = BatteryEnv(system, prices=Prices.month(system, 4))
    assert env.action_space.shape == (2,)
    np.testing.assert_array_equal(env.action_space.high, [0.7, 0.7])
    np.testing.assert_array_equal(env.action_space.low, [-0.7, -0.7])
    space = env.observation_space
    assert space["soc"].shape == (2,) and space["buy"].shape == (5,)
    assert space["hour"].high[0] == system.hours_per_day - 1
    prices = Prices.month(system, 4)
    assert space["buy"].low[0] == pytest.approx(prices.sell.min())
    assert space["buy"].high[0] == pytest.approx(prices.buy.max())


def test_the_mpc_through_the_environment_gives_the_closed_loops_costs():
    system, config = SystemConfig(), MPCConfig()
    prices = Prices.month(system, 3)
    theta = Theta.nominal(system)
    solver = make_solver(MPC(system), config, theta)
    record = run_month(theta, solver, prices, system, np.random.default_rng(5),
                       sensitivities=False)
    env = BatteryEnv(system, config, prices)
    for d in range(prices.days):
        agent = MPCAgent(env, theta, make_solver(MPC(system), config, theta))
        rewards, infos = _episode(env, agent, options={"day": d, "noise": record.noise[:, d]})
        np.testing.assert_allclose(-rewards, record.stage_cost[:, d], rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose([i["agent_cost"] for i in infos], record.agent_cost[:, d],
                                   rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose([i["grid_power"] for i in infos], record.grid_power[:, d],
                                   rtol=1e-9, atol=1e-9)
        assert not any(i["grid_limited"] for i in infos)  # the MPC's command is feasible
        J = discounted_return(-rewards, system.gamma)
        assert J == pytest.approx(record.J_per_day()[d], rel=1e-9)


def test_the_grid_limit_is_applied_as_the_closed_loop_does_and_reported():
    system = SystemConfig(n=3, P_bar=1.5)
    prices = Prices.month(system, 1)
    greedy = np.array([1.0, 1.0, 0.8])  # buys 2.8 > P_bar every hour
    record = simulate(lambda k, soc: np.tile(greedy, (1, 1)), prices.buy, prices.sell, system,
                      rng=np.random.default_rng(2), explore=Projection(system))
    env = BatteryEnv(system, prices=prices, day=0)
    rewards, infos = _episode(env, lambda obs: greedy, options={"noise": record.noise[:, 0]})
    np.testing.assert_allclose(-rewards, record.stage_cost[:, 0], rtol=1e-12, atol=1e-9)
    assert infos[0]["grid_limited"]
    assert infos[0]["planned_grid_power"] == pytest.approx(2.8)
    assert sum(infos[0]["applied_action"]) == pytest.approx(system.P_bar)
    # the low-level controller may exchange more than P_bar when it keeps soc in [0, 1]
    np.testing.assert_allclose([i["grid_power"] for i in infos], record.grid_power[:, 0],
                               rtol=1e-12)


def test_seeding_follows_reset_seed():
    system = SystemConfig()
    prices = Prices.month(system, 5)
    env = BatteryEnv(system, prices=prices)
    idle = np.zeros(system.n)
    first, infos1 = _episode(env, lambda obs: idle, seed=11)
    again, infos2 = _episode(env, lambda obs: idle, seed=11)
    np.testing.assert_array_equal(first, again)
    assert infos1[0]["day"] == infos2[0]["day"]
    other, _ = _episode(env, lambda obs: idle, seed=12)
    assert not np.array_equal(first, other)
    # unseeded resets continue the generator: a new day of noise, not a replay
    cont, _ = _episode(env, lambda obs: idle)
    assert not np.array_equal(cont, again)
    # with a fixed day the noise is what simulate draws from default_rng(seed) for one day
    fixed = BatteryEnv(system, prices=prices, day=2)
    _, infos = _episode(fixed, lambda obs: idle, seed=7)
    record = simulate(lambda k, soc: np.zeros_like(soc), prices.buy[2:3], prices.sell[2:3],
                      system, rng=np.random.default_rng(7))
    np.testing.assert_array_equal([i["noise"] for i in infos], record.noise[:, 0])


def test_the_vector_form_plays_one_day_per_environment():
    system = SystemConfig(n=2, P_bar=1.2)
    prices = Prices.month(system, 3)
    envs = make_day_vector_env(system=system, prices=prices)
    assert envs.num_envs == 3
    obs, _ = envs.reset(seed=3)
    assert obs["soc"].shape == (3, 2)
    np.testing.assert_allclose(obs["buy"][:, 0], prices.buy[:, 0])
    total = np.zeros(3)
    for _ in range(system.hours_per_day):
        obs, reward, terminated, _, _ = envs.step(np.zeros((3, 2)))
        total += reward
    assert terminated.all()
    # environment i is day i seeded 3 + i
    for i in range(3):
        rewards, _ = _episode(BatteryEnv(system, prices=prices, day=i), lambda o: np.zeros(2),
                              seed=3 + i)
        assert total[i] == pytest.approx(rewards.sum(), rel=1e-12)
    envs.close()
    vec = gymnasium.make_vec(ENV_ID, num_envs=2, vectorization_mode="vector_entry_point",
                             system=system, prices=prices)
    assert vec.num_envs == 2
    vec.close()


def test_make_passes_the_configs_as_keyword_arguments():
    system = SystemConfig(n=2, P_bar=1.0)
    env = gymnasium.make(ENV_ID, system=system, prices=Prices.month(system, 2), day=1)
    assert env.unwrapped.system == system and env.unwrapped.fixed_day == 1
    obs, _ = env.reset(seed=0)
    assert obs["soc"].shape == (2,)
    env.close()


def test_bad_input_is_refused():
    env = BatteryEnv(prices=Prices.month(None, 2))
    with pytest.raises(ValueError, match="day=5"):
        BatteryEnv(prices=Prices.month(None, 2), day=5)
    with pytest.raises(ValueError, match="options"):
        env.reset(options={"days": 1})
    with pytest.raises(ValueError, match=r"options\['noise'\]"):
        env.reset(options={"noise": np.zeros((3, 3))})
    env.reset(seed=0)
    with pytest.raises(ValueError, match="expected 3 finite net powers"):
        env.step([0.0, 0.0])


def _run(code: str) -> str:
    proc = subprocess.run([sys.executable, "-c", textwrap.dedent(code)], capture_output=True,
                          text=True, timeout=300, check=True)
    return proc.stdout.strip()


def test_importing_the_package_registers_without_importing_gymnasium():
    out = _run("""
        import sys
        import mpcrl_lite
        print('gymnasium' in sys.modules, 'mpcrl_lite.sim.env' in sys.modules)
        import gymnasium
        print(gymnasium.spec('mpcrl_lite/Batteries-v0').entry_point)
        env = gymnasium.make('mpcrl_lite/Batteries-v0')
        print(type(env.unwrapped).__name__)
    """)
    assert out.splitlines() == ["False False", "mpcrl_lite.sim.env:BatteryEnv", "BatteryEnv"]


def test_registration_when_gymnasium_came_first():
    out = _run("""
        import gymnasium
        import mpcrl_lite
        print('mpcrl_lite/Batteries-v0' in gymnasium.registry)
    """)
    assert out == "True"


def test_a_mixed_site_through_the_environment():
    system = SystemConfig(alpha=(1 / 24, 1 / 12, 1 / 12), U_bar=(2.0, 1.0, 1.0), P_bar=2.0,
                          soc0=(0.5, 0.6, 0.6), noise_var=(1.0, 0.5, 0.5))
    prices = Prices.month(system, 2)
    env = BatteryEnv(system, MPCConfig(backend="ipopt"), prices)
    check_env(env, skip_render_check=True)
    np.testing.assert_array_equal(env.action_space.high, [2.0, 1.0, 1.0])
    obs, _ = env.reset(seed=0, options={"day": 1})
    np.testing.assert_array_equal(obs["soc"], [0.5, 0.6, 0.6])
    theta = Theta.nominal(system)
    record = run_month(theta, make_solver(MPC(system), MPCConfig(backend="ipopt"), theta),
                       prices, system, np.random.default_rng(1), sensitivities=False)
    rewards, _ = _episode(env, MPCAgent(env, theta), options={"day": 1,
                                                              "noise": record.noise[:, 1]})
    np.testing.assert_allclose(-rewards, record.stage_cost[:, 1], rtol=1e-7, atol=1e-7)
