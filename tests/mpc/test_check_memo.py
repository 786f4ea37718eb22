"""The kernels' formulation check, remembered once it has passed (mpcrl_lite.mpc.backends.check_memo):
a second solver with the same inputs skips it, any input that differs checks again, a failed
check leaves nothing behind, and the switches turn the memory off."""

from __future__ import annotations

import json

import numpy as np
import pytest

from mpcrl_lite.config import MPCConfig, SystemConfig
from mpcrl_lite.mpc.backends import check_memo
from mpcrl_lite.mpc.backends.kernel import KernelSolver
from mpcrl_lite.mpc.formulation import MPC
from mpcrl_lite.theta import Theta


@pytest.fixture
def memo_dir(tmp_path, monkeypatch):
    """The remembered checks in a folder of the test's own."""
    folder = tmp_path / "checked"
    monkeypatch.setattr(check_memo, "_path", lambda name: folder / f"{name}.json")
    monkeypatch.delenv(check_memo.ENV, raising=False)
    return folder


@pytest.fixture
def checks(monkeypatch):
    """How many times KernelSolver._check_formulation ran."""
    count = [0]
    real = KernelSolver._check_formulation

    def counted(self, *args, **kwargs):
        count[0] += 1
        return real(self, *args, **kwargs)

    monkeypatch.setattr(KernelSolver, "_check_formulation", counted)
    return count


def _solve(solver: KernelSolver) -> None:
    system = solver.mpc.system
    sol = solver.solve(np.full(system.n, 0.5), np.full(system.N, 80.0),
                       np.full(system.N, 40.0), Theta.nominal(system))
    assert sol.success


def test_a_passed_check_is_remembered_and_skipped_by_the_next_solver(memo_dir, checks):
    system = SystemConfig()
    first = KernelSolver(MPC(system), MPCConfig())
    _solve(first)
    assert checks[0] == 1
    files = list(memo_dir.glob("*.json"))
    assert len(files) == 1
    residuals = json.loads(files[0].read_text())
    assert set(residuals) == {"dual residual", "primal residual", "complementarity", "cost"}
    assert all(0.0 <= v < 1e-6 for v in residuals.values())
    second = KernelSolver(MPC(system), MPCConfig())
    _solve(second)  # the same solves, without the check
    assert checks[0] == 1
    # the solver's results do not depend on whether it checked
    p = np.random.default_rng(3).uniform(0.2, 0.8, (6, system.n))
    theta = Theta.nominal(system)
    a = first.solve_batch(p, np.full((6, system.N), 70.0), np.full((6, system.N), 35.0), theta)
    b = second.solve_batch(p, np.full((6, system.N), 70.0), np.full((6, system.N), 35.0), theta)
    assert np.array_equal(a.x, b.x) and np.array_equal(a.action, b.action)


@pytest.mark.parametrize("change", ["system", "tau", "opts", "kernels", "source"])
def test_any_input_of_the_check_that_differs_checks_again(memo_dir, checks, monkeypatch, change):
    _solve(KernelSolver(MPC(SystemConfig()), MPCConfig()))
    assert checks[0] == 1
    system, config = SystemConfig(), MPCConfig()
    if change == "system":
        system = SystemConfig(P_bar=1.2)
    elif change == "tau":
        config = MPCConfig(tau=2e-3)
    elif change == "opts":  # a start setting of the solver class, read into the options
        monkeypatch.setattr(KernelSolver, "u0_fraction", KernelSolver.u0_fraction * 0.9)
    elif change == "kernels":  # the generic kernels instead of the paper's sized copy
        monkeypatch.setattr(KernelSolver, "specialise", False)
    else:  # a source the check depends on, as another version of the package
        monkeypatch.setattr(check_memo, "_source_digest",
                            {str(p): "another version" for p in check_memo._SOURCES})
    _solve(KernelSolver(MPC(system), config))
    assert checks[0] == 2
    assert len(list(memo_dir.glob("*.json"))) == 2


def test_code_the_key_cannot_see_is_checked_every_time(memo_dir, checks):
    class Mine(KernelSolver):
        pass

    for _ in range(2):
        _solve(Mine(MPC(SystemConfig()), MPCConfig()))
    assert checks[0] == 2
    mpc = MPC(SystemConfig())
    original = mpc.qp_function  # the formulation's own CasADi Function: still remembered
    assert check_memo.applies(mpc)
    mpc.qp_function = lambda p: original(p)  # replaced on the instance
    assert not check_memo.applies(mpc)
    for _ in range(2):
        _solve(KernelSolver(mpc, MPCConfig()))
    assert checks[0] == 4
    assert not memo_dir.exists()


def test_the_switches_check_every_solver_and_write_nothing(memo_dir, checks, monkeypatch):
    monkeypatch.setattr(KernelSolver, "remember_check", False)
    for _ in range(2):
        _solve(KernelSolver(MPC(SystemConfig()), MPCConfig()))
    assert checks[0] == 2
    monkeypatch.setattr(KernelSolver, "remember_check", True)
    monkeypatch.setenv(check_memo.ENV, "1")
    for _ in range(2):
        _solve(KernelSolver(MPC(SystemConfig()), MPCConfig()))
    assert checks[0] == 4
    assert not memo_dir.exists()


def test_a_failed_check_is_not_remembered(memo_dir, monkeypatch):
    from mpcrl_lite.mpc.backends.kernel import KernelInputError

    real = KernelSolver._opts
    monkeypatch.setattr(KernelSolver, "_opts", lambda self, max_iter=None: real(
        self, max_iter=1 if max_iter == 500 else max_iter))  # the check's solve cannot converge
    for _ in range(2):  # raised each time: nothing was remembered
        with pytest.raises(KernelInputError, match="cannot solve the MPC"):
            _solve(KernelSolver(MPC(SystemConfig(P_bar=1.3)), MPCConfig(tau=2e-3)))
    assert not memo_dir.exists() or not list(memo_dir.glob("*.json"))


def test_a_folder_that_cannot_be_written_only_means_checking_each_time(tmp_path, monkeypatch,
                                                                       checks):
    blocked = tmp_path / "a file"  # where the folder would be: no folder can be made there
    blocked.write_text("")
    monkeypatch.setattr(check_memo, "_path", lambda name: blocked / "checked" / f"{name}.json")
    monkeypatch.delenv(check_memo.ENV, raising=False)
    for _ in range(2):
        _solve(KernelSolver(MPC(SystemConfig()), MPCConfig()))
    assert checks[0] == 2
