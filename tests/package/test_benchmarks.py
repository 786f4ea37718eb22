"""The benchmarks stay runnable: each imports against today's package and its tiny
measurement function runs (their figures are judged in ``make bench``, never here)."""

from __future__ import annotations

import importlib
import sys
from pathlib import Path

import numpy as np
import pytest

from mpcrl_lite import SystemConfig
from mpcrl_lite.mpc.backends.batch import BatchSolver
from mpcrl_lite.mpc.backends.kernel import KernelSolver
from mpcrl_lite.mpc.formulation import MPC
from mpcrl_lite.system.prices import Prices

BENCHMARKS = Path(__file__).resolve().parents[2] / "benchmarks"
MODULES = sorted(p.stem for p in BENCHMARKS.glob("bench_*.py"))


@pytest.fixture(scope="module", autouse=True)
def _on_path():
    sys.path.insert(0, str(BENCHMARKS))
    yield
    sys.path.remove(str(BENCHMARKS))


@pytest.mark.parametrize("name", [*MODULES, "run_all"])
def test_every_benchmark_imports(name):
    module = importlib.import_module(name)
    assert callable(getattr(module, "main", None)) or callable(getattr(module, "run", None))


def test_kernel_benchmark_times_the_same_closed_loop_for_both_back_ends():
    bench_kernel = importlib.import_module("bench_kernel")
    system = SystemConfig(N=6)
    prices = Prices.month(system, 4)
    mpc = MPC(system)
    k = bench_kernel.closed_loop(KernelSolver(mpc), system, prices, hours=3, seed=1)
    b = bench_kernel.closed_loop(BatchSolver(mpc), system, prices, hours=3, seed=1)
    assert k["ok"] and b["ok"] and k["cpu"] > 0 and b["cpu"] > 0
    assert k["action"].shape == (3, 4, 3)
    np.testing.assert_allclose(k["action"], b["action"], atol=1e-9)
    np.testing.assert_array_equal(k["iters"], b["iters"])
