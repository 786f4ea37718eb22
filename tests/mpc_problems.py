"""Parameter rows of MPC problems for the kernel tests that compare two ways of solving the same
problems (``tests/mpc/test_kernel_sizes.py``, ``tests/mpc/test_kernel_lanes.py``)."""

from __future__ import annotations

import numpy as np

from mpcrl_lite.mpc.formulation import MPC
from mpcrl_lite.theta import Theta


def mixed_problems(mpc: MPC, days: int, seed: int) -> np.ndarray:
    """``days`` parameter rows: states outside [0.1, 0.9] too, random prices and a different
    theta per row (every fourth the nominal one)."""
    rng = np.random.default_rng(seed)
    nominal = Theta.nominal(mpc.system).to_vector()
    rows = []
    for d in range(days):
        theta = nominal + (0.0 if d % 4 == 0 else
                           rng.normal(0.0, 0.3, nominal.size) * np.abs(nominal).clip(0.1))
        buy = rng.uniform(5.0, 130.0, mpc.N)
        rows.append(mpc.parameters(rng.uniform(-0.05, 1.05, mpc.n), buy, 0.5 * buy,
                                   Theta.from_vector(theta, mpc.n)))
    return np.array(rows)
