"""The stop without the polishing step (``MPCConfig.polish = False``) of the kernel and batch
interior points: a solve stops as soon as its scaled KKT residual reaches ``tol``, in fewer
Newton iterations than the polished solve, by the same path in both back-ends; the
polished default reaches the rounding level. IPOPT, asked for by name, refuses it."""

from __future__ import annotations

import numpy as np
import pytest

from mpcrl_lite.config import MPCConfig, SystemConfig
from mpcrl_lite.mpc.backends.batch import BatchSolver
from mpcrl_lite.mpc.backends.ipopt import IpoptSolver
from mpcrl_lite.mpc.backends.kernel import KernelSolver
from mpcrl_lite.mpc.formulation import MPC
from mpcrl_lite.system.prices import Prices
from mpcrl_lite.theta import Theta

DAYS = 10


@pytest.fixture(scope="module")
def mpc() -> MPC:
    return MPC(SystemConfig())


@pytest.fixture(scope="module")
def hour(mpc):
    """A warm-started hour of ``DAYS`` problems: the previous hour's plans shifted, the states
    moved by their actions and some noise."""
    prices = Prices.month(mpc.system, DAYS)
    theta = Theta.nominal(mpc.system)
    rng = np.random.default_rng(11)
    soc = rng.uniform(0.15, 0.85, (DAYS, mpc.n))
    first = KernelSolver(mpc).solve_batch(soc, *prices.window(5, mpc.N), theta)
    soc_next = np.clip(soc + mpc.system.alpha * first.action
                       + rng.normal(0, 0.02, soc.shape), 0.0, 1.0)
    return theta, soc_next, prices.window(6, mpc.N), mpc.shift(first.x)


@pytest.mark.parametrize("tol", [1e-6, 1e-8])
def test_without_polishing_a_solve_stops_at_the_tolerance(mpc, hour, tol):
    theta, soc, (buy, sell), x0 = hour
    residual = BatchSolver(mpc).residual  # the scaled KKT residual of any solution
    loose = {}
    for cls in (KernelSolver, BatchSolver):
        exact = cls(mpc).solve_batch(soc, buy, sell, theta, x0=x0)
        loose[cls] = cls(mpc, MPCConfig(polish=False, tol=tol)).solve_batch(
            soc, buy, sell, theta, x0=x0)
        b = loose[cls]
        assert exact.success.all() and b.success.all()
        assert np.all(b.iterations <= exact.iterations)
        assert b.iterations.sum() < exact.iterations.sum()
        assert np.all(residual(b) <= tol)
        assert np.all(residual(exact) <= 1e-12)
        np.testing.assert_allclose(b.action, exact.action, rtol=0, atol=1e3 * tol)
    k, b = loose[KernelSolver], loose[BatchSolver]
    np.testing.assert_array_equal(k.iterations, b.iterations)
    np.testing.assert_allclose(k.x, b.x, rtol=0, atol=1e-10)


def test_the_formulation_check_does_not_depend_on_the_tolerance(mpc, hour):
    """The kernel's check of its QP data against CasADi solves exactly whatever the config."""
    theta, soc, (buy, sell), _ = hour
    solver = KernelSolver(mpc, MPCConfig(polish=False, tol=1e-4))
    assert solver.solve_batch(soc, buy, sell, theta).success.all()


def test_ipopt_by_name_refuses_and_the_flag_is_checked(mpc):
    with pytest.raises(ValueError, match="polish=False: the IPOPT back-end"):
        IpoptSolver(mpc, MPCConfig(backend="ipopt", polish=False))
    with pytest.raises(ValueError, match="polish"):
        MPCConfig(polish="no")
