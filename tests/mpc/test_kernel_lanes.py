"""Four problems at once (:func:`~mpcrl_lite.mpc.backends.kernel_core.solve_lanes`) give, problem
by problem, the bits of solving each alone (``solve_each``): converged, stopped at the
iteration limit, not finite, broken down, a hard grid limit, with and without the polishing
step, in the paper's copy of the kernels and in the generic ones."""

from __future__ import annotations

import numpy as np
import pytest
from mpc_problems import mixed_problems

from mpcrl_lite.config import MPCConfig, SystemConfig
from mpcrl_lite.mpc.backends import kernel_core, kernel_sizes
from mpcrl_lite.mpc.backends.kernel import KernelSolver
from mpcrl_lite.mpc.formulation import MPC
from mpcrl_lite.theta import Theta

FIELDS = ("x", "lam", "mu", "cost", "iters", "status", "action")


def _solve(entry, solver: KernelSolver, P: np.ndarray, x0: np.ndarray | None,
           lo: int = 0, hi: int | None = None) -> dict[str, np.ndarray]:
    """One call of the kernel ``entry`` on the rows ``lo:hi`` of ``P``; its outputs."""
    m, days = solver.mpc, P.shape[0]
    hi = days if hi is None else hi
    out = {"x": np.full((days, m.nx), -7.0), "lam": np.full((days, m.neq), -7.0),
           "mu": np.full((days, m.nin), -7.0), "cost": np.full(days, -7.0),
           "iters": np.full(days, -7, np.int64), "status": np.full(days, -7, np.int64),
           "action": np.full((days, solver.n), -7.0)}
    warm = x0 is not None
    x0 = np.ascontiguousarray(x0) if warm else np.zeros((1, m.nx))
    args = (np.ascontiguousarray(P), x0, warm, solver._opts(), solver._ubar, solver._stagew,
            solver.n, solver.N)
    outs = tuple(out[f] for f in FIELDS)
    if entry.__name__ == "solve_lanes":
        entry(*args, *outs, lo, hi)
    else:
        entry(*args, solver._method, *outs, lo, hi)
    return out


def _assert_same(a: dict, b: dict) -> None:
    for field in FIELDS:
        np.testing.assert_array_equal(a[field], b[field], err_msg=field)


def _solver(mpc: MPC, specialise: bool, **config) -> KernelSolver:
    solver = KernelSolver(mpc, MPCConfig(**config), method="stage")
    solver.specialise = specialise
    solver._ready()
    return solver


@pytest.mark.parametrize("specialise", [True, False])
def test_four_at_once_equal_one_at_a_time_bit_for_bit(specialise):
    mpc = MPC(SystemConfig())
    solver = _solver(mpc, specialise)
    K = solver._kernels
    assert (K is kernel_core) == (not specialise)
    P = mixed_problems(mpc, 23, seed=11)  # five groups of four and a last three
    cold_each = _solve(K.solve_each, solver, P, None)
    cold = _solve(K.solve_lanes, solver, P, None)
    _assert_same(cold, cold_each)
    assert (cold["status"] == kernel_core.CONVERGED).sum() >= 20
    # the iterations differ within groups: the lanes stop one by one
    assert any(len(set(cold["iters"][g:g + 4].tolist())) > 1 for g in range(0, 20, 4))
    x0 = mpc.shift(cold["x"])
    _assert_same(_solve(K.solve_lanes, solver, P, x0), _solve(K.solve_each, solver, P, x0))
    # solve_rows: groups of four, the rest one at a time; any split of the rows
    whole = _solve(K.solve_rows, solver, P, x0)
    parts = _solve(K.solve_rows, solver, P, x0, 0, 6)
    tail = _solve(K.solve_rows, solver, P, x0, 6, 23)
    for field in FIELDS:
        parts[field][6:] = tail[field][6:]
    _assert_same(whole, parts)
    _assert_same(whole, _solve(K.solve_each, solver, P, x0))


def test_the_lanes_stop_each_for_its_own_reason():
    """A group holding a converged problem, one at the iteration limit, one not finite and
    one that breaks down: each lane ends as it would alone, and the others are not
    disturbed."""
    mpc = MPC(SystemConfig())
    solver = _solver(mpc, True, max_iter=8)
    K = solver._kernels
    P = mixed_problems(mpc, 8, seed=3)
    P[1, mpc.n] = np.nan  # a price: not finite
    theta = Theta.nominal(mpc.system).to_dict()
    theta["phi1"] = -np.array(theta["phi1"]) * 400.0  # a concave soc cost
    P[2] = mpc.parameters(np.full(mpc.n, 0.5), P[2, mpc.n: mpc.n + mpc.N],
                          P[2, mpc.n + mpc.N: mpc.n + 2 * mpc.N], Theta.from_dict(theta))
    each = _solve(K.solve_each, solver, P, None)
    _assert_same(_solve(K.solve_lanes, solver, P, None), each)
    status = set(each["status"].tolist())
    assert {kernel_core.CONVERGED, kernel_core.NON_FINITE}.issubset(status)
    assert status & {kernel_core.BREAKDOWN, kernel_core.MAX_ITER}
    short = _solver(mpc, True, max_iter=2)
    each = _solve(K.solve_each, short, P, None)
    assert (each["status"] == kernel_core.MAX_ITER).sum() >= 4
    _assert_same(_solve(K.solve_lanes, short, P, None), each)


@pytest.mark.parametrize("P_bar", [0.3, 1.0])  # the grid limit binding hard, or mildly
@pytest.mark.parametrize("polish", [True, False])
def test_four_at_once_with_a_hard_grid_limit_and_without_polish(P_bar, polish):
    mpc = MPC(SystemConfig(P_bar=P_bar))
    solver = _solver(mpc, True, polish=polish)
    K = solver._kernels
    P = mixed_problems(mpc, 12, seed=7)
    each = _solve(K.solve_each, solver, P, None)
    _assert_same(_solve(K.solve_lanes, solver, P, None), each)
    assert (each["status"] == kernel_core.CONVERGED).all()


@pytest.mark.parametrize("n, N", [(2, 5), (4, 12), (1, 3)])
def test_four_at_once_in_the_generic_kernels_at_other_sizes(n, N):
    mpc = MPC(SystemConfig(n=n, N=N, P_bar=0.5 * n))
    assert (n, N) not in kernel_sizes.SPECIALISED_SIZES
    assert kernel_core.choose_method(n, N) == kernel_core.STAGE
    solver = _solver(mpc, True)
    P = mixed_problems(mpc, 10, seed=n + N)
    each = _solve(kernel_core.solve_each, solver, P, None)
    _assert_same(_solve(kernel_core.solve_lanes, solver, P, None), each)
    _assert_same(_solve(kernel_core.solve_rows, solver, P, None), each)


def _sensitivities(solver: KernelSolver, solution, lanes: bool):
    solver.lanes = lanes
    try:
        return solver.sensitivity(solution)
    finally:
        solver.lanes = True


def _assert_same_sensitivities(a, b) -> None:
    for field in ("grad", "ok", "cond", "grad_soc0"):
        np.testing.assert_array_equal(getattr(a, field), getattr(b, field), err_msg=field)
    assert a.reason == b.reason


@pytest.mark.parametrize("P_bar", [0.3, 1.5])  # a hard grid limit: refinement differs by lane
@pytest.mark.parametrize("specialise", [True, False])
def test_sensitivities_four_at_once_equal_one_at_a_time(P_bar, specialise):
    mpc = MPC(SystemConfig(P_bar=P_bar))
    solver = _solver(mpc, specialise)
    P = mixed_problems(mpc, 23, seed=13)
    solver.lanes = False
    solution = solver._solve_parameters(P, None)
    solver.lanes = True
    lanes = _sensitivities(solver, solution, True)
    each = _sensitivities(solver, solution, False)
    _assert_same_sensitivities(lanes, each)
    assert lanes.ok.sum() >= 18


def test_sensitivities_of_rows_that_fail_each_in_their_own_way():
    """A group with a row the solver did not solve, one not strictly interior and one whose
    point is not finite beside good rows: each row gets the verdict it gets alone."""
    mpc = MPC(SystemConfig())
    solver = _solver(mpc, True)
    P = mixed_problems(mpc, 8, seed=17)
    solution = solver._solve_parameters(P, None)
    solution.success[1] = False
    solution.mu[2, 5] = 0.0  # not strictly interior
    solution.x[5, 7] = np.nan
    lanes = _sensitivities(solver, solution, True)
    each = _sensitivities(solver, solution, False)
    _assert_same_sensitivities(lanes, each)
    assert "solver failed" in each.reason[1] and "interior" in each.reason[2]
    assert not each.ok[5] and each.ok[[0, 3, 4, 6, 7]].all()
