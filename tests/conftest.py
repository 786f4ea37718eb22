"""Shared fixtures: the paper's system, its MPC, the reference solver and a month of prices."""

from __future__ import annotations

import numpy as np
import pytest

from mpcrl_lite.config import MPCConfig, SystemConfig
from mpcrl_lite.mpc import MPC
from mpcrl_lite.solvers import IpoptSolver


@pytest.fixture(scope="session")
def system() -> SystemConfig:
    """The paper's Table I (n = 3, N = 12)."""
    return SystemConfig()


@pytest.fixture(scope="session")
def mpc(system: SystemConfig) -> MPC:
    """The symbolic MPC of ``system`` (built once)."""
    return MPC(system)


@pytest.fixture(scope="session")
def ipopt(mpc: MPC) -> IpoptSolver:
    """The reference back-end at the default barrier parameter."""
    return IpoptSolver(mpc, MPCConfig(backend="ipopt"))


@pytest.fixture(scope="session")
def month_prices() -> np.ndarray:
    """Buying prices (NOK/MWh) of 30 days x 24 hours, roughly 20..120.

    A smooth daily curve (cheap night, morning bump, evening peak) scaled by a weekly
    rhythm and shifted by a slow monthly drift, so that every day differs a little.
    """
    h = np.arange(24)
    daily = (
        55.0
        - 25.0 * np.cos(2 * np.pi * (h - 3) / 24)
        + 25.0 * np.exp(-0.5 * ((h - 18) / 2.0) ** 2)
        + 12.0 * np.exp(-0.5 * ((h - 8) / 1.5) ** 2)
    )
    d = np.arange(30)[:, None]
    prices = daily[None, :] * (1 + 0.12 * np.sin(2 * np.pi * d / 7 + 0.5))
    prices = prices + 6.0 * np.sin(2 * np.pi * d / 30)
    prices.setflags(write=False)
    return prices
