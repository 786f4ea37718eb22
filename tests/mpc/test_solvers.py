"""Tests of the solver layer around the back-ends: the solution types (mpcrl_lite.mpc.solution),
the back-end registry and :func:`make_solver` (mpcrl_lite.mpc.backends.registry), the old import paths of
moved names, and the import structure (solution types below the back-ends, back-ends never
importing each other, nothing imported inside functions)."""

from __future__ import annotations

import dataclasses
import logging

import numpy as np
import pytest
from conftest import assert_imports_within

import mpcrl_lite.mpc.backends.registry as solvers_module
from mpcrl_lite.config import BACKENDS, MPCConfig
from mpcrl_lite.mpc.backends.ipopt import IpoptSolver
from mpcrl_lite.mpc.backends.kernel import KernelSolver
from mpcrl_lite.mpc.backends.registry import make_solver
from mpcrl_lite.mpc.solution import FALLBACK, BatchSolution
from mpcrl_lite.theta import Theta


# -- solution types ---------------------------------------------------------------------------
def test_failure_summary_counts_the_statuses(ipopt, system):
    buy = np.full(system.N, 50.0)
    good = ipopt.solve(np.full(system.n, 0.5), buy, 0.5 * buy, Theta.nominal(system))
    assert good.success
    bad = [dataclasses.replace(good, success=False, status=status)
           for status in ("max_iter_reached", "non_finite", "max_iter_reached")]
    batch = BatchSolution.stack([good, *bad], 0.0, "test")
    assert batch.failures == 3
    summary = batch.failure_summary()
    assert summary.startswith("test back-end: 3 of 4 MPC problems failed")
    assert "(max_iter_reached: 2, non_finite: 1)" in summary
    assert BatchSolution.stack([good, good], 0.0, "test").failure_summary() == ""
    assert "b = s = 0" in FALLBACK


# -- the back-end registry and the import structure -------------------------------------------
def test_registry_holds_every_configured_backend():
    assert set(solvers_module.REGISTRY) == set(BACKENDS) - {solvers_module.AUTO}


@pytest.mark.parametrize("name", sorted(solvers_module.REGISTRY))
def test_make_solver_builds_the_named_backend(mpc, name):
    solver = make_solver(mpc, MPCConfig(backend=name))
    assert isinstance(solver, solvers_module.REGISTRY[name])
    assert solver.name == name and solver.mpc is mpc and solver.config.backend == name


def test_make_solver_auto_chooses_by_convexity(mpc, system, caplog):
    theta0 = Theta.nominal(system)
    concave = theta0.replace(phi1=np.full(system.n, -1.0))
    with caplog.at_level(logging.INFO, logger="mpcrl_lite.mpc.backends.registry"):
        assert isinstance(make_solver(mpc, MPCConfig(backend="auto"), theta0), KernelSolver)
        assert isinstance(make_solver(mpc, MPCConfig(backend="auto"), concave), IpoptSolver)
        assert make_solver(mpc, MPCConfig(backend="auto")).name == "kernel"  # no theta
    assert [r.getMessage() for r in caplog.records] == [
        "MPC back-end 'auto' chose 'kernel'", "MPC back-end 'auto' chose 'ipopt'",
        "MPC back-end 'auto' chose 'kernel'"]


def test_make_solver_rejects_an_unregistered_backend(mpc, monkeypatch):
    monkeypatch.delitem(solvers_module.REGISTRY, "batch")
    with pytest.raises(ValueError, match=r"'batch' is not available; expected one of "
                                         r"\('auto', 'ipopt', 'kernel'\)"):
        make_solver(mpc, MPCConfig(backend="batch"))


#: What each module of the solver layer may import from the package: the solution types sit
#: below every back-end, back-ends never import each other, only the factory imports them.
SOLVER_LAYER = {
    "mpc.formulation": {"config", "theta"},
    "mpc.solution": {"config", "mpc.formulation", "theta"},
    "mpc.sensitivity": {"config", "mpc.formulation", "mpc.solution", "theta"},
    "mpc.backends.batch_linalg": set(),
    "mpc.backends.batch_kkt": {"mpc.backends.batch_linalg", "config", "mpc.formulation",
                               "mpc.solution", "theta"},
    "mpc.backends.batch_adjoint": {"mpc.backends.batch_kkt", "mpc.backends.batch_linalg",
                                   "config", "mpc.solution", "theta"},
    "mpc.backends.batch": {"mpc.backends.batch_adjoint", "mpc.backends.batch_kkt",
                           "mpc.backends.batch_linalg", "config", "mpc.formulation",
                           "mpc.solution", "theta"},
    "mpc.backends.ipopt": {"config", "mpc.formulation", "mpc.sensitivity", "mpc.solution",
                           "theta"},
    "mpc.backends.kernel_core": {"_util", "_util.jit"},
    "mpc.backends.kernel": {"mpc.backends.kernel_core", "config", "mpc.formulation",
                            "mpc.solution", "theta", "_util.lazy"},
    "mpc.backends.registry": {"mpc.backends.batch", "config", "mpc.backends.ipopt",
                              "mpc.backends.kernel", "mpc.formulation", "mpc.solution", "theta"},
}


@pytest.mark.parametrize("module", sorted(SOLVER_LAYER))
def test_solver_layer_imports_only_downwards(module):
    assert_imports_within(module, SOLVER_LAYER[module])
