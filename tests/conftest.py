"""Shared fixtures and helpers: the paper's system, its MPC, the reference solver, a month of
prices, price windows and random thetas.

The helpers are plain functions (``from conftest import window, random_theta``) because some
tests build their cases from them at import time.
"""

from __future__ import annotations

import ast
import os
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from mpcrl_lite.config import MPCConfig, SystemConfig
from mpcrl_lite.mpc.backends.ipopt import IpoptSolver
from mpcrl_lite.mpc.formulation import MPC
from mpcrl_lite.theta import Theta

# The test workers run two at a time on two cores: numba's OpenMP threads (the kernel's calls
# of 16 problems or more) then sleep soon after a call instead of spinning against the other
# worker. Results do not depend on it (each problem is solved alone); the suite's wall time
# does (tests/learning + tests/sim on 2 workers: 85 s against 98 s). A single process, as a
# user runs one, keeps the default spin, which starts its next call sooner (benchmarks/README).
os.environ.setdefault("GOMP_SPINCOUNT", "10000")

# -- helpers ----------------------------------------------------------------------------------
PACKAGE = Path(__file__).resolve().parents[1] / "mpcrl_lite"


def package_modules() -> dict[str, Path]:
    """Every module of the package by dotted name below ``mpcrl_lite`` (``'mpc.formulation'``;
    a subpackage's ``__init__`` by the subpackage's name, the package's own as ``'__init__'``)."""
    found = {}
    for path in sorted(PACKAGE.rglob("*.py")):
        parts = list(path.relative_to(PACKAGE).with_suffix("").parts)
        if parts[-1] == "__init__" and len(parts) > 1:
            parts = parts[:-1]
        found[".".join(parts)] = path
    return found


def package_imports(module: str, modules: dict[str, Path] | None = None,
                    top_level_only: bool = False) -> dict[str, int]:
    """Package modules imported by ``module`` (dotted, as :func:`package_modules` names them),
    with the line of the first import; read from the source (ast), so an import inside a
    function counts too, unless ``top_level_only``. ``from pkg import name`` counts as an
    import of the module ``pkg.name`` where that is a module, else of ``pkg``; a module
    imported on first use (``name = lazy_module("mpcrl_lite.pkg.mod")``,
    :mod:`mpcrl_lite._util.lazy`) counts as an import of ``pkg.mod``."""
    modules = package_modules() if modules is None else modules
    path = modules[module]
    if path.name == "__init__.py":
        here = [] if module == "__init__" else module.split(".")
    else:
        here = module.split(".")[:-1]
    tree = ast.parse(path.read_text())
    nodes = tree.body if top_level_only else list(ast.walk(tree))
    found: dict[str, int] = {}

    def add(target: list[str], line: int) -> None:
        name = ".".join(target) or "__init__"
        if name in modules and name != module:
            found.setdefault(name, line)

    for node in nodes:
        if isinstance(node, ast.ImportFrom):
            if node.level:
                base = here[: len(here) - node.level + 1]
            elif node.module and (node.module == "mpcrl_lite" or node.module.startswith("mpcrl_lite.")):
                base = []
            else:
                continue
            mod = (node.module or "").split(".") if node.module else []
            if not node.level:
                mod = mod[1:]
            target = base + mod
            for alias in node.names:
                if ".".join(target + [alias.name]) in modules:
                    add(target + [alias.name], node.lineno)
                else:
                    add(target, node.lineno)
        elif isinstance(node, ast.Import):
            for alias in node.names:
                if alias.name.startswith("mpcrl_lite."):
                    add(alias.name.split(".")[1:], node.lineno)
        elif isinstance(node, ast.Assign) and isinstance(node.value, ast.Call):
            # name = lazy_module("mpcrl_lite.x.y"): an import made on first use
            call = node.value
            if getattr(call.func, "id", None) == "lazy_module" and call.args \
                    and isinstance(call.args[0], ast.Constant) \
                    and str(call.args[0].value).startswith("mpcrl_lite."):
                add(str(call.args[0].value).split(".")[1:], node.lineno)
    return found


def assert_imports_within(module: str, allowed: set[str]) -> None:
    """Every package import of ``mpcrl_lite.<module>`` (dotted) is at the top level of the
    file and names a module of ``allowed``; read from the source (ast), so an import hidden
    in a function counts too."""
    everywhere = package_imports(module)
    top = package_imports(module, top_level_only=True)
    inside = sorted(set(everywhere) - set(top))
    assert not inside, f"{module}: import inside a function: {inside}"
    outside = {name: line for name, line in everywhere.items() if name not in allowed}
    assert not outside, f"{module} imports {outside} (name: line)"


def window(prices: np.ndarray, day: int, hour: int, N: int) -> np.ndarray:
    """The N buying prices from (day, hour) on, running past midnight (the month repeats)."""
    flat = np.asarray(prices).ravel()
    return flat[(day * prices.shape[1] + hour + np.arange(N)) % flat.size]


def convex_theta(rng: np.random.Generator, n: int, quadratic: bool = False) -> Theta:
    """A convex theta (phi1, T1 >= 0) away from theta0; ``quadratic`` gives strong soc
    targets (phi1, T1 up to 1500), otherwise mild cost corrections."""
    if quadratic:
        target = rng.uniform(0.3, 0.7, (2, n))
        phi1, T1 = rng.uniform(0.0, 1500.0, (2, n))
        phi2, T2 = -2.0 * phi1 * target[0], -2.0 * T1 * target[1]
    else:
        phi1, T1 = rng.uniform(0.0, 20.0, n), rng.uniform(0.0, 50.0, n)
        phi2, T2 = rng.uniform(-20.0, 20.0, n), rng.uniform(-50.0, 50.0, n)
    return Theta(
        alpha=rng.uniform(0.05, 0.12, n), delta=rng.uniform(-0.005, 0.005, n),
        b=rng.uniform(-5.0, 5.0, n), s=rng.uniform(-5.0, 5.0, n),
        phi1=phi1, phi2=phi2, phi3=rng.uniform(-5.0, 5.0, n),
        T1=T1, T2=T2, T3=rng.uniform(-5.0, 5.0, n),
    )


def random_theta(
    rng: np.random.Generator, n: int, curvature: tuple[float, float] = (0.0, 1500.0)
) -> Theta:
    """A theta far from theta0 for which the MPC stays a convex QP: quadratic stage and
    terminal costs (``phi1, T1`` drawn from ``curvature``, so >= 0 for the default) pulling soc
    towards random targets in [0.3, 0.7]; larger curvature gives interior, non-bang-bang
    actions."""
    target = rng.uniform(0.3, 0.7, (2, n))
    phi1 = rng.uniform(*curvature, n)
    T1 = rng.uniform(*curvature, n)
    return Theta(
        alpha=rng.uniform(0.06, 0.11, n),
        delta=rng.uniform(-0.01, 0.01, n),
        b=rng.uniform(-5.0, 5.0, n),
        s=rng.uniform(-5.0, 5.0, n),
        phi1=phi1,
        phi2=-2.0 * phi1 * target[0],
        phi3=rng.uniform(-10.0, 10.0, n),
        T1=T1,
        T2=-2.0 * T1 * target[1],
        T3=rng.uniform(-10.0, 10.0, n),
    )


# -- fixtures ---------------------------------------------------------------------------------


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


@pytest.fixture(scope="session")
def mpc_of() -> Callable[..., MPC]:
    """``mpc_of(**system)``: the MPC of ``SystemConfig(**system)``, built once per session
    (building one takes ~20 ms, an IPOPT solver on it more)."""
    cache: dict[tuple, MPC] = {}

    def build(**system) -> MPC:
        key = tuple(sorted(system.items()))
        if key not in cache:
            cache[key] = MPC(SystemConfig(**system))
        return cache[key]

    return build


@pytest.fixture(scope="session")
def ipopt_at(mpc: MPC) -> Callable[..., IpoptSolver]:
    """``ipopt_at(tau, on=None)``: the reference back-end at barrier parameter ``tau`` (on
    the MPC ``on``, the paper's by default), built once per session."""
    cache: dict[tuple[int, float], tuple[MPC, IpoptSolver]] = {}

    def build(tau: float, on: MPC | None = None) -> IpoptSolver:
        target = mpc if on is None else on
        key = (id(target), tau)  # the cache holds target, so its id is not reused
        if key not in cache:
            cache[key] = (target, IpoptSolver(target, MPCConfig(tau=tau, backend="ipopt")))
        return cache[key][1]

    return build


# -- a command in a forked child (kill tests) ----------------------------------------------------
def assert_workers_die_with(argv: list[str], workers: int = 1, match: str = "") -> None:
    """Start ``argv``, wait until it has ``workers`` child processes (whose command lines
    contain ``match``), kill it with SIGKILL and check that those children end too."""
    import signal
    import subprocess
    import time

    import psutil

    proc = subprocess.Popen(argv, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        parent = psutil.Process(proc.pid)
        deadline = time.monotonic() + 120
        found: list = []
        while len(found) < workers and time.monotonic() < deadline and proc.poll() is None:
            found = [p for p in parent.children() if match in " ".join(p.cmdline())]
            time.sleep(0.1)
        assert len(found) == workers, f"{len(found)} worker processes started, not {workers}"
        proc.send_signal(signal.SIGKILL)
        proc.wait()
        _, alive = psutil.wait_procs(found, timeout=20)
        assert alive == [], f"worker processes outlived the process that made them: {alive}"
    finally:
        if proc.poll() is None:
            proc.kill()


def learn_in_child(argv: list[str], env: dict[str, str]) -> int:
    """Run ``python -m mpcrl_lite`` with ``argv`` (e.g. ``learn ...``) in a forked child with
    ``env`` set and its output silenced; returns the wait status (the kill tests read the
    signal that ended it)."""
    import os

    from mpcrl_lite.cli.main import main
    from mpcrl_lite.learning import durable

    pid = os.fork()
    if pid == 0:
        code = 70
        try:
            devnull = os.open(os.devnull, os.O_WRONLY)
            os.dup2(devnull, 1)
            os.dup2(devnull, 2)
            os.environ.update(env)
            durable._writes = 0
            code = main(argv)
        finally:
            os._exit(code)
    _, status = os.waitpid(pid, 0)
    return status


def run_cli(argv: list[str], capsys) -> tuple[int, str, str]:
    """``python -m mpcrl_lite ARGV`` in this process: its exit status, stdout and stderr."""
    from mpcrl_lite.cli.main import main

    capsys.readouterr()
    status = main(argv)
    return status, *capsys.readouterr()


def assert_drawn_inside(fig, slack: float = 0.01) -> None:
    """Everything ``fig`` draws lies on its canvas (``slack`` inches of rounding allowed).

    The notebooks show figures as drawn, without cropping them to their content
    (``InlineBackend.print_figure_kwargs``): a label or legend outside the canvas would be cut
    off there, where cropping would have kept it."""
    fig.draw_without_rendering()
    box = fig.get_tightbbox(fig.canvas.get_renderer())
    width, height = fig.get_size_inches()
    assert (box.x0 >= -slack and box.y0 >= -slack and box.x1 <= width + slack
            and box.y1 <= height + slack), (
        f"{fig.get_suptitle() or fig.axes[0].get_title()!r}: drawn over "
        f"[{box.x0:.3f}, {box.x1:.3f}] x [{box.y0:.3f}, {box.y1:.3f}] inches, "
        f"expected within its canvas {width:g} x {height:g}")
