"""The copy of the kernels compiled for the paper's sizes (:mod:`mpcrl_lite.mpc.backends.
kernel_sizes`) gives the generic kernels' results bit for bit, and is used where it applies."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
from mpc_problems import mixed_problems

from mpcrl_lite.config import MPCConfig, SystemConfig
from mpcrl_lite.mpc.backends import kernel_core, kernel_sizes
from mpcrl_lite.mpc.backends.kernel import KernelSolver
from mpcrl_lite.mpc.formulation import MPC
from mpcrl_lite.theta import Theta


@pytest.fixture(scope="module")
def mpc() -> MPC:
    return MPC(SystemConfig())

@pytest.mark.parametrize("N", [12, 11])  # the paper's MPC, the Q-learner's tail
@pytest.mark.parametrize("method", ["stage", "agent"])
def test_specialised_kernels_equal_the_generic_ones_bit_for_bit(method, N):
    mpc = MPC(SystemConfig(N=N))
    assert (mpc.n, mpc.N) in kernel_sizes.SPECIALISED_SIZES
    P = mixed_problems(mpc, 23, seed=5)
    results = []
    for specialise in (True, False):
        solver = KernelSolver(mpc, MPCConfig(), method=method)
        solver.specialise = specialise
        sol = solver._solve_parameters(P, None)
        warm = solver._solve_parameters(P, mpc.shift(sol.x))
        short = KernelSolver(mpc, MPCConfig(max_iter=2), method=method)
        short.specialise = specialise
        failed = short._solve_parameters(P, None)
        sens = solver.sensitivity(warm)
        used = solver._kernels
        results.append((sol, warm, failed, sens))
        assert (used is kernel_core) == (not specialise)
        if specialise:
            assert used.FIXED_N == mpc.n and used.FIXED_HORIZON == mpc.N
    (a, aw, af, asens), (b, bw, bf, bsens) = results
    assert a.success.all() and not af.success.all()
    for x, y in ((a, b), (aw, bw), (af, bf)):
        for field in ("x", "lam", "mu", "cost", "action", "iterations"):
            np.testing.assert_array_equal(getattr(x, field), getattr(y, field))
        assert x.status == y.status
    for field in ("grad", "cond", "ok"):
        np.testing.assert_array_equal(getattr(asens, field), getattr(bsens, field))


def test_the_q_learners_tail_runs_on_its_copy():
    from mpcrl_lite.mpc.q_kernel import FixedActionKernel

    tail = FixedActionKernel(MPC(SystemConfig())).tail
    assert (tail._kernels.FIXED_N, tail._kernels.FIXED_HORIZON) == (3, 11)


def test_other_sizes_use_the_generic_kernels():
    assert kernel_sizes.kernels(2, 12) is kernel_core
    assert kernel_sizes.kernels(3, 12, specialise=False) is kernel_core
    small = KernelSolver(MPC(SystemConfig(n=2, P_bar=1.0)))
    small.solve(np.array([0.5, 0.5]), np.linspace(10, 50, 12), np.linspace(5, 25, 12),
                Theta.nominal(small.mpc.system))
    assert small._kernels is kernel_core


def test_the_copy_is_written_once_and_differs_only_in_the_sizes():
    module = kernel_sizes.kernels(3, 12)
    path = module.__file__
    stamp = os.stat(path).st_mtime_ns
    generic = Path(kernel_core.__file__).read_text(encoding="utf-8").splitlines()
    copy = Path(path).read_text(encoding="utf-8").splitlines()
    assert copy[0].startswith("# Generated from kernel_core.py")
    changed = [(g, c) for g, c in zip(generic, copy[1:]) if g != c]
    assert changed == [("FIXED_N = 0", "FIXED_N = 3"), ("FIXED_HORIZON = 0", "FIXED_HORIZON = 12")]
    assert len(copy) == len(generic) + 1
    # loading again (another process would) leaves the file, and numba's cache of it, alone
    kernel_sizes._load(3, 12)
    assert os.stat(path).st_mtime_ns == stamp


def test_a_copy_is_written_whole_with_the_given_time_and_never_rewritten(tmp_path):
    """A missing copy appears with the modification time of ``kernel_core.py`` (processes
    writing it at once leave the same file); one already there, written by an earlier
    checkout or run at another time, is left as it is, so numba's cache of it stays valid."""
    path = tmp_path / "kernel_core_n3_N12_0123456789ab.py"
    kernel_sizes._write(path, "first\n", 1_000_000_000.0)
    assert path.read_text(encoding="utf-8") == "first\n"
    assert os.stat(path).st_mtime == 1_000_000_000.0
    kernel_sizes._write(path, "first\n", 2_000_000_000.0)
    assert os.stat(path).st_mtime == 1_000_000_000.0
    assert [p.name for p in tmp_path.iterdir()] == [path.name]  # no temporary file left


def test_a_generated_module_keeps_its_bytecode_where_python_would_not_write_it(tmp_path,
                                                                              monkeypatch):
    """Imported with bytecode writing off (PYTHONDONTWRITEBYTECODE), a generated module's
    bytecode is written beside it once and used by the next import; a folder where it cannot
    be written only means compiling on import."""
    import importlib.util
    import py_compile
    import sys

    monkeypatch.setattr(sys, "dont_write_bytecode", True)
    path = tmp_path / "generated_probe_0123.py"
    kernel_sizes._write(path, "VALUE = 41 + 1\n", 1_000_000_000.0)
    cached = Path(importlib.util.cache_from_source(str(path)))
    module = kernel_sizes.import_generated(path, "mpcrl_lite_probe_generated", "mpcrl_lite")
    try:
        assert module.VALUE == 42 and cached.is_file()
        # bytecode of another text of the same size and time in its place: an import that
        # reads the bytecode sees that text's value, one that compiles the source 42
        other = tmp_path / "other" / path.name
        other.parent.mkdir()
        kernel_sizes._write(other, "VALUE = 40 + 7\n", 1_000_000_000.0)
        py_compile.compile(str(other), cfile=str(cached), doraise=True)
        stamp = cached.stat().st_mtime_ns
        again = kernel_sizes.import_generated(path, "mpcrl_lite_probe_generated", "mpcrl_lite")
        assert again.VALUE == 47
        assert cached.stat().st_mtime_ns == stamp  # not written again
    finally:
        sys.modules.pop("mpcrl_lite_probe_generated", None)
    blocked = tmp_path / "a file"
    blocked.write_text("")
    kernel_sizes._write_bytecode(path, str(blocked / "__pycache__" / "x.pyc"))  # no error


def test_bad_sizes():
    with pytest.raises(ValueError, match="n=0, N=12"):
        kernel_sizes.source(0, 12)


def test_the_copies_go_to_the_first_writable_cache_folder(tmp_path, monkeypatch):
    numba_dir, home_cache = tmp_path / "numba", tmp_path / "xdg"
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(numba_dir))
    monkeypatch.setenv("XDG_CACHE_HOME", str(home_cache))
    assert kernel_sizes._folder() == numba_dir / "mpcrl_lite-kernels"
    monkeypatch.delenv("NUMBA_CACHE_DIR")
    assert kernel_sizes._folder() == home_cache / "mpcrl_lite-kernels"
    # a folder that cannot be written is passed over (here: the user's cache)
    real_access = os.access
    monkeypatch.setattr(kernel_sizes.os, "access", lambda p, mode: (
        False if str(p).startswith(str(home_cache)) else real_access(p, mode)))
    folder = kernel_sizes._folder()
    assert folder.parent == Path(kernel_sizes.tempfile.gettempdir())
    # the package's own folders never hold a copy
    assert Path(kernel_sizes.kernels(3, 12).__file__).parent != Path(kernel_core.__file__).parent


def test_a_large_call_goes_to_numbas_threads_in_one_compiled_call(mpc, monkeypatch):
    """With two threads, a call of 16 problems or more is one call of the ``*_parallel``
    entry (a block per thread); smaller calls stay on the calling thread."""
    solver = KernelSolver(mpc)
    solver.threads = 2
    P = mixed_problems(mpc, 17, seed=2)
    # the kernels loaded: each entry where the solver first calls it
    solver.sensitivity(solver._solve_parameters(P, None))
    solver.sensitivity(solver._solve_parameters(P[:1], None))
    module = solver._kernels
    calls = []
    for name in ("solve_rows", "solve_rows_parallel", "sensitivity_rows",
                 "sensitivity_rows_parallel"):
        real = getattr(module, name)
        monkeypatch.setattr(module, name, lambda *a, _real=real, _name=name: (
            calls.append((_name, a[-3:] if _name.endswith("parallel") else a[-2:])), _real(*a))[1])
    sol = solver._solve_parameters(P, None)
    solver.sensitivity(sol)
    solver._solve_parameters(P[:15], None)
    # blocks of whole groups of four: ceil(17 / 2) = 9 rounded up to 12
    assert calls == [("solve_rows_parallel", (0, 17, 12)), ("sensitivity_rows_parallel", (0, 17, 12)),
                     ("solve_rows", (0, 15))]


def test_prune_removes_other_versions_copies_and_their_compiled_code(tmp_path, monkeypatch):
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path))
    folder = kernel_sizes._folder()
    current = kernel_sizes._stem(3, 12)
    cache = folder / "__pycache__"
    cache.mkdir()
    keep = [folder / f"{current}.py", cache / f"{current}.solve_rows-878.py311.nbi",
            cache / f"{current}.solve_rows-878.py311.1.nbc", folder / "unrelated.txt"]
    old = [folder / "kernel_core_n3_N12_000000000000.py",
           cache / "kernel_core_n3_N12_000000000000.solve_rows-870.py311.nbi",
           cache / "kernel_core_n3_N12_000000000000.solve_rows-870.py311.1.nbc",
           folder / "kernel_core_n4_N6_111111111111.py"]  # sizes no longer specialised
    for path in keep + old:
        path.write_text("x")
    removed = kernel_sizes.prune()
    assert sorted(removed) == sorted(old)
    assert all(p.exists() for p in keep) and not any(p.exists() for p in old)
    assert kernel_sizes.prune() == []  # nothing left to remove
