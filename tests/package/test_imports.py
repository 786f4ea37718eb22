"""Importing the package pays only for what it uses: the heavy libraries (statistics, data
frames, plotting, the distributed scheduler, the widgets, the compiler) load where they are
used, never with the package, its public names or the learner's module."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
#: Libraries that no import of the package, its face or the learner may bring in.
HEAVY = ("scipy.stats", "pandas", "matplotlib", "dask", "ipywidgets")


def loaded_after(code: str) -> list[str]:
    """The modules of :data:`HEAVY` (and numba, scipy.linalg) in ``sys.modules`` after
    running ``code`` in a fresh interpreter."""
    probe = (f"{code}\nimport json, sys\n"
             "print(json.dumps(sorted(m for m in sys.modules if m.split('.')[0] in "
             "('scipy', 'pandas', 'matplotlib', 'dask', 'ipywidgets', 'numba'))))")
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True,
                         cwd=ROOT, env={"PYTHONPATH": str(ROOT), "PATH": "/usr/bin:/bin"},
                         check=True, timeout=300).stdout
    return json.loads(out.strip().splitlines()[-1])


def heavy(modules: list[str]) -> list[str]:
    return [m for m in modules if any(m == h or m.startswith(h + ".") for h in HEAVY)]


@pytest.mark.parametrize("code", [
    "import mpcrl_lite",
    "import mpcrl_lite.learning.experiment",
    "from mpcrl_lite import Experiment, History, LearningConfig, MPCConfig, SystemConfig, Theta",
    "import mpcrl_lite.mpc.backends.registry",
    # what `learn --no-figures` imports: the figures' names, not matplotlib
    "import mpcrl_lite.figures.paper\nimport mpcrl_lite.cli.commands.learn",
])
def test_importing_loads_no_heavy_library(code):
    modules = loaded_after(code)
    assert heavy(modules) == []
    assert not any(m == "numba" or m.startswith("numba.") for m in modules)  # first use only


def test_the_probe_sees_a_heavy_import():
    """The check above can fail: importing pandas shows in it."""
    assert "pandas" in heavy(loaded_after("import mpcrl_lite\nimport pandas"))


def test_a_solver_loads_numba_at_its_first_solve_only():
    """Building a KernelSolver (as Experiment() does) loads no compiler; its first solve
    loads the kernels, checks them against the formulation and gives the usual solution."""
    modules = loaded_after(
        "import sys\n"
        "import numpy as np\n"
        "from mpcrl_lite import SystemConfig, Theta\n"
        "from mpcrl_lite.mpc.backends.kernel import KernelSolver\n"
        "from mpcrl_lite.mpc.formulation import MPC\n"
        "system = SystemConfig(N=4)\n"
        "solver = KernelSolver(MPC(system))\n"
        "assert 'numba' not in sys.modules and not solver._checked\n"
        "buy = np.linspace(20.0, 80.0, 4)\n"
        "sol = solver.solve(np.full(3, 0.5), buy, 0.9 * buy, Theta.nominal(system))\n"
        "assert sol.success and solver._checked and 'numba' in sys.modules")
    assert "numba" in modules and heavy(modules) == []


def test_an_experiment_is_built_without_casadi_or_the_compiler():
    """``Experiment()`` (the default kernel back-end, the shipped prices) loads neither
    CasADi nor numba nor pandas: the MPC's symbolic problem is built at its first use and
    the default price profile is read without a data-frame library."""
    probe = ("import sys\nfrom mpcrl_lite import Experiment\nexperiment = Experiment()\n"
             "print('casadi' in sys.modules)")
    modules = loaded_after(probe)
    assert heavy(modules) == [] and "numba" not in modules
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True,
                         cwd=ROOT, env={"PYTHONPATH": str(ROOT), "PATH": "/usr/bin:/bin"},
                         check=True, timeout=300).stdout
    assert out.strip().splitlines()[-1] == "False"


def test_the_symbolic_problem_is_built_at_its_first_use():
    """The MPC builds its CasADi problem at the first read of one of its names, once, and
    it is the problem of an MPC whose functions were read at once: same numbers."""
    import numpy as np

    from mpcrl_lite import SystemConfig
    from mpcrl_lite.mpc.formulation import MPC

    system = SystemConfig(N=4)
    mpc = MPC(system)
    assert "fgh" not in vars(mpc) and mpc.nx > 0
    fgh = mpc.fgh
    assert "fgh" in vars(mpc) and mpc.fgh is fgh and mpc._x.shape[0] == mpc.nx
    other = MPC(system)
    x = np.linspace(0.0, 1.0, mpc.nx)
    p = np.linspace(0.5, 1.5, mpc.np)
    for a, b in zip(fgh(x, p), other.fgh(x, p)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    with pytest.raises(AttributeError, match="no attribute 'not_a_name'"):
        mpc.not_a_name  # noqa: B018


def test_a_learner_loads_only_the_back_end_and_readers_it_uses():
    """The default learner needs the compiled back-end only: the numpy interior point, the
    IPOPT wrapper and the price-file readers load at their first lookup, and are then the
    same classes and functions as their modules'."""
    probe = ("import json, sys\nfrom mpcrl_lite import Experiment\nExperiment()\n"
             "print(json.dumps(sorted(m for m in sys.modules if m.startswith('mpcrl_lite'))))")
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True,
                         cwd=ROOT, env={"PYTHONPATH": str(ROOT), "PATH": "/usr/bin:/bin"},
                         check=True, timeout=300).stdout
    loaded = json.loads(out.strip().splitlines()[-1])
    assert "mpcrl_lite.mpc.backends.kernel" in loaded
    for lazy in ("mpcrl_lite.mpc.backends.batch", "mpcrl_lite.mpc.backends.ipopt",
                 "mpcrl_lite.system.price_files.load"):
        assert lazy not in loaded
    from mpcrl_lite.mpc.backends import batch, ipopt, registry
    from mpcrl_lite.system import prices
    from mpcrl_lite.system.price_files import load, nordpool_elspot

    assert registry.REGISTRY["batch"] is batch.BatchSolver is registry.BatchSolver
    assert registry.REGISTRY["ipopt"] is ipopt.IpoptSolver is registry.IpoptSolver
    assert prices.load_prices is load.load_prices
    assert prices.load_nordpool_csv is nordpool_elspot.load_nordpool_csv
    with pytest.raises(AttributeError, match="no attribute 'NoSolver'"):
        registry.NoSolver  # noqa: B018
