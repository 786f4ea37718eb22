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
    "mpc.formulation": {"config", "theta", "_util.lazy"},
    "mpc.solution": {"config", "mpc.formulation", "theta"},
    "mpc.sensitivity": {"config", "mpc.formulation", "mpc.solution", "theta",
                        "_util.lazy"},
    "mpc.backends.batch_linalg": set(),
    "mpc.backends.batch_kkt": {"mpc.backends.batch_linalg", "config", "mpc.formulation",
                               "mpc.solution", "theta", "_util.lazy"},
    "mpc.backends.batch_adjoint": {"mpc.backends.batch_kkt", "mpc.backends.batch_linalg",
                                   "config", "mpc.solution", "theta"},
    "mpc.backends.batch": {"mpc.backends.batch_adjoint", "mpc.backends.batch_kkt",
                           "mpc.backends.batch_linalg", "config", "mpc.formulation",
                           "mpc.solution", "theta"},
    "mpc.backends.ipopt": {"config", "mpc.formulation", "mpc.sensitivity", "mpc.solution",
                           "theta", "_util.lazy"},
    "mpc.backends.kernel_core": {"_util", "_util.jit", "_util.vec4"},
    "mpc.backends.kernel_sizes": set(),  # imports kernel_core (or its copy) by name
    "mpc.backends.check_memo": {"mpc.backends.kernel_sizes", "mpc.formulation"},
    "mpc.backends.kernel": {"mpc.backends.check_memo", "mpc.backends.kernel_core",
                            "mpc.backends.kernel_sizes", "config", "mpc.formulation",
                            "mpc.solution", "theta", "_util.lazy", "_util.threads",
                            "_util.validate"},  # ModelInputError
    "mpc.backends.registry": {"mpc.backends.batch", "config", "mpc.backends.ipopt",
                              "mpc.backends.kernel", "mpc.formulation", "mpc.solution", "theta",
                              "_util.lazy"},
}


@pytest.mark.parametrize("module", sorted(SOLVER_LAYER))
def test_solver_layer_imports_only_downwards(module):
    assert_imports_within(module, SOLVER_LAYER[module])


# -- inputs a back-end cannot solve -----------------------------------------------------------------
@pytest.fixture
def kernel_out_of_reach(monkeypatch):
    """A kernel that cannot solve the MPC at tau < 1e-11 (one iteration allowed there), as
    a kernel beyond its reach on accepted input; the default input solves as usual."""
    real = KernelSolver._opts

    def opts(self, max_iter=None):
        return real(self, max_iter=1 if self.config.tau < 1e-11 else max_iter)

    monkeypatch.setattr(KernelSolver, "_opts", opts)


def test_a_kernel_that_cannot_solve_accepted_input_names_the_input(kernel_out_of_reach):
    from mpcrl_lite.config import SystemConfig
    from mpcrl_lite.mpc.backends.kernel import KernelInputError
    from mpcrl_lite.mpc.formulation import MPC

    mpc = MPC(SystemConfig())
    system = mpc.system
    for config in (MPCConfig(tau=1e-12, backend="kernel"), MPCConfig(tau=1e-12)):  # in RANGES
        solver = make_solver(mpc, config)
        with pytest.raises(KernelInputError, match=r"cannot solve the MPC of this system and "
                                                   r"config \(max_iter_reached; tau=1e-12") as err:
            solver.solve(0.6 * np.ones(system.n), 300.0 * np.ones(system.N),
                         150.0 * np.ones(system.N), Theta.nominal(system))
        assert "formulation" not in str(err.value) and "'ipopt'" in str(err.value)


def test_the_kernels_input_error_names_each_batterys_input_bound(kernel_out_of_reach):
    from mpcrl_lite.config import SystemConfig
    from mpcrl_lite.mpc.backends.kernel import KernelInputError
    from mpcrl_lite.mpc.formulation import MPC

    system = SystemConfig(U_bar=(1.0, 0.6, 0.3), P_bar=1.2)
    solver = make_solver(MPC(system), MPCConfig(tau=1e-12))
    assert solver.name == "kernel"
    with pytest.raises(KernelInputError, match=r"tau=1e-12, .*U_bar=\(1.0, 0.6, 0.3\)"):
        solver.solve(0.6 * np.ones(system.n), 300.0 * np.ones(system.N),
                     150.0 * np.ones(system.N), Theta.nominal(system))
    # at the default tau the same site solves
    sol = make_solver(MPC(system)).solve(0.6 * np.ones(system.n), 300.0 * np.ones(system.N),
                                         150.0 * np.ones(system.N), Theta.nominal(system))
    assert sol.success


def test_the_cli_reports_it_in_one_line(tmp_path, capsys, kernel_out_of_reach):
    from mpcrl_lite.cli.main import main

    capsys.readouterr()
    assert main(["simulate", "--days", "1", "--tau", "1e-12", "--backend", "kernel",
                 "--out", str(tmp_path / "s")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "mpcrl_lite simulate: error: the compiled MPC kernel" in err[0]
    assert not (tmp_path / "s").exists()  # no empty --out left behind


@pytest.mark.parametrize("backend", ["kernel", "batch"])
def test_an_explicit_convex_only_back_end_with_a_non_convex_theta_uses_ipopt(backend, mpc,
                                                                            caplog):
    theta = Theta.nominal(mpc.system)
    theta = theta.replace(phi1=-0.5 * np.ones(mpc.n))
    assert not theta.is_convex()
    caplog.set_level(logging.WARNING)
    solver = make_solver(mpc, MPCConfig(backend=backend), theta)
    assert isinstance(solver, IpoptSolver)
    assert "theta is not convex" in caplog.text and f"the '{backend}' back-end" in caplog.text
    convex = make_solver(mpc, MPCConfig(backend=backend), Theta.nominal(mpc.system))
    assert convex.name == backend
