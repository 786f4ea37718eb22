"""The package's shape: data flows one way, so the import graph has no cycle, no subpackage
imports from a layer above its own, and inside a subpackage no module imports from a module
placed above it.

Imports are read from the source (every ``from . import`` / ``from ..x import`` /
``import mpcrl_lite.x``, also those inside functions), so a lazy import that only hides a cycle
is caught too. A new module or subpackage must be placed in :data:`LAYERS` (and in its
subpackage's :data:`SUBLAYERS`) before this test passes: its place in the data flow is a
decision, not an accident. An entry that names nothing fails too, so the tables cannot drift
from the folders.
"""

from __future__ import annotations

import ast
import graphlib
import re
from pathlib import Path

import pytest
from conftest import package_imports, package_modules

#: The layers of the data flow, lowest first (the README's layout diagram): top-level modules
#: and subpackages of ``mpcrl_lite``. A module may import from its own layer or lower ones.
LAYERS: list[set[str]] = [
    {"_util"},  # plain helpers: jit set-up, four-lane vectors, JSON, statistics, validators, files,
    #           references, the allocator's thresholds
    {"config", "theta"},  # every number and choice; the parameter vector
    {"system"},  # prices, the true batteries, forecasts
    {"mpc"},  # the one formulation, its solutions and sensitivity, the back-ends
    {"sim"},  # the one closed loop and its record
    {"learning"},  # critic, actor, update rules, month loop, run files, history
    {"decentralized", "bounds"},  # per-battery learners; baselines and the causal optimum
    {"figures"},
    {"classroom"},
    {"publish"},  # reports, HTML, site
    {"studies"},  # seeds, lockstep, sweeps (a sweep may run a report notebook per run)
    {"cli", "__init__", "__main__"},
]

#: Inside a subpackage, its modules lowest first: a module imports only from a lower entry of
#: its own subpackage (never from its own entry: modules side by side are independent).
SUBLAYERS: dict[str, list[set[str]]] = {
    "_util": [{"budget", "gym_registration", "jit", "jsonio", "lazy", "malloc", "progress",
               "resources", "references", "stats", "threads", "validate", "vec4", "version",
               "workers"}],
    "system": [{"price_files", "battery"}, {"prices"}, {"forecast"}],
    "system.price_files": [{"areas", "series"},
                           {"currency", "detect", "energidataservice", "entsoe", "entsoe_legacy",
                            "month", "nordpool_elspot", "nordpool_portal", "pandas_series"},
                           {"load"}],
    "mpc": [{"formulation", "q_stage_kernel"}, {"solution"}, {"sensitivity"}, {"backends"},
            {"q_kernel"}, {"value"}],
    "mpc.backends": [{"batch_linalg", "kernel_core", "kernel_sizes"}, {"batch_kkt", "check_memo"},
                     {"batch_adjoint"},
                     {"batch", "ipopt", "kernel"}, {"registry"}],
    "sim": [{"record", "exploration_kernel"}, {"exploration", "month_kernel"}, {"compiled_month"},
            {"closed_loop"}, {"candidates", "env"}],
    "learning": [{"lstd", "update_rules", "durable", "rollout_gradient", "pathwise",
                  "eval_worker"}, {"outdir"}, {"rundir"}, {"dpg", "history", "critic_samples"},
                 {"step", "checkpoint", "qlearning"}, {"learner"}, {"experiment"},
                 {"q_experiment"}],
    "decentralized": [{"local_qp", "coordination_kernel"}, {"coordination"}, {"learner"}],
    "bounds": [{"causal", "scenario"}, {"rule", "clairvoyant"}, {"baselines"}],
    "bounds.causal": [{"kernels"}, {"grid"}, {"mixed"}, {"dp", "dual"}, {"table"}],
    "figures": [{"style", "describe"}, {"paper", "comparison"}, {"plots"}],
    "classroom": [{"controls", "explorers", "picture"}, {"widgets"}],
    "publish": [{"alt_text", "claims", "html_export", "launch", "run_times"}, {"report"}, {"site"}],
    "studies": [{"transfer", "lockstep", "tune"}, {"sweep"}, {"study"}],
    "studies.sweep": [{"grid"}, {"store"}, {"table"}, {"run"}, {"schedule"}, {"api"}],
    "cli": [{"inputs"}, {"args"}, {"commands"}, {"main"}, {"warm"}],
    "cli.commands": [{"baselines", "evaluate", "learn", "report", "simulate", "study", "sweep",
                      "tune"}],
}

MODULES = package_modules()
GRAPH = {name: package_imports(name, MODULES) for name in MODULES}
RANK = {unit: rank for rank, layer in enumerate(LAYERS) for unit in layer}


def _unit(module: str) -> str:
    """The top-level module or subpackage ``module`` belongs to."""
    return module.split(".")[0]


def _place(module: str, package: str) -> str | None:
    """The entry of ``package``'s SUBLAYERS that holds ``module`` (a module or subpackage
    directly below ``package``), or None if ``module`` is not inside ``package``."""
    if not module.startswith(package + "."):
        return None
    return module[len(package) + 1:].split(".")[0]


def test_every_module_has_a_place_in_the_data_flow():
    unplaced = sorted({_unit(m) for m in MODULES} - set(RANK))
    assert not unplaced, f"place these in LAYERS: {unplaced}"
    for package, layers in SUBLAYERS.items():
        placed = {name for layer in layers for name in layer}
        present = {_place(m, package) for m in MODULES} - {None}
        assert not present - placed, f"place these in SUBLAYERS[{package!r}]: {present - placed}"


def test_every_layer_entry_names_a_module():
    units = {_unit(m) for m in MODULES}
    assert not set(RANK) - units, f"LAYERS names nothing: {sorted(set(RANK) - units)}"
    for package, layers in SUBLAYERS.items():
        assert package in MODULES, f"SUBLAYERS names no subpackage {package!r}"
        present = {_place(m, package) for m in MODULES} - {None}
        named = {name for layer in layers for name in layer}
        assert not named - present, f"SUBLAYERS[{package!r}] names nothing: {named - present}"
    packages = {m for m, path in MODULES.items() if path.name == "__init__.py" and m != "__init__"}
    assert packages <= set(SUBLAYERS), f"subpackages without SUBLAYERS: {packages - set(SUBLAYERS)}"


def test_the_import_graph_has_no_cycle():
    try:
        list(graphlib.TopologicalSorter({m: set(d) for m, d in GRAPH.items()}).static_order())
    except graphlib.CycleError as err:
        pytest.fail(f"import cycle: {' -> '.join(err.args[1])}")


@pytest.mark.parametrize("module", sorted(MODULES))
def test_no_module_imports_from_a_layer_above(module):
    upward = {name: line for name, line in GRAPH[module].items()
              if RANK[_unit(name)] > RANK[_unit(module)]}
    assert not upward, f"{module} imports from higher layers: {upward} (name: line)"


@pytest.mark.parametrize("module", sorted(MODULES))
def test_inside_a_subpackage_modules_import_only_lower_ones(module):
    for package, layers in SUBLAYERS.items():
        mine = _place(module, package)
        if mine is None:
            continue
        rank = {name: r for r, layer in enumerate(layers) for name in layer}
        for name, line in GRAPH[module].items():
            theirs = _place(name, package)
            if theirs is None or theirs == mine:
                continue
            assert rank[theirs] < rank[mine], (
                f"{module} imports {name} (line {line}): in {package}, {theirs!r} is not "
                f"below {mine!r}")


def test_a_subpackage_init_imports_only_its_own_modules():
    """``__init__`` files hold a docstring (and at most re-export their own modules), so that
    importing one module of a subpackage loads nothing else."""
    for package in SUBLAYERS:
        outside = [name for name in GRAPH[package] if not name.startswith(package + ".")]
        assert not outside, f"{package}/__init__.py imports {outside}"


#: Modules whose ``__all__`` gathers names from other modules on purpose: the package's face
#: and the sweep's public API.
FACES = {"__init__", "studies.sweep.api"}


def _defined(module: str) -> set[str]:
    names: set[str] = set()
    for node in ast.parse(MODULES[module].read_text()).body:
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            names.add(node.name)
        elif isinstance(node, (ast.Assign, ast.AnnAssign)):
            targets = node.targets if isinstance(node, ast.Assign) else [node.target]
            names |= {n.id for t in targets for n in ast.walk(t) if isinstance(n, ast.Name)}
    return names


@pytest.mark.parametrize("module", sorted(set(MODULES) - FACES))
def test_every_public_name_has_one_home(module):
    """A module's ``__all__`` lists only what it defines: each name is imported from the one
    module that holds it (no re-exports that keep two paths to one object)."""
    for node in ast.parse(MODULES[module].read_text()).body:
        if isinstance(node, ast.Assign) and getattr(node.targets[0], "id", "") == "__all__":
            foreign = sorted(set(ast.literal_eval(node.value)) - _defined(module))
            assert not foreign, f"{module}.__all__ lists names defined elsewhere: {foreign}"


def test_the_check_sees_imports_inside_functions(tmp_path):
    """The reader counts an import hidden in a function body (a lazy import is no way out)."""
    probe = tmp_path / "probe.py"
    probe.write_text("def f():\n    from .cli import main\n    return main\n")
    modules = {"probe": probe, "cli": tmp_path / "cli.py"}
    assert package_imports("probe", modules) == {"cli": 2}
    assert package_imports("probe", modules, top_level_only=True) == {}


def test_the_readme_lists_every_module():
    """The README's module table (written by ``tools/update_module_table.py``) has one row
    per module and subpackage, and no row for anything that does not exist."""
    readme = (Path(__file__).resolve().parents[2] / "README.md").read_text()
    start = readme.index("| module | what it holds |")
    table = readme[start:readme.index("\n\n", start)]
    rows = set(re.findall(r"^\| `([\w.]+)` \|", table, re.MULTILINE))
    expected = {"mpcrl_lite" if m == "__init__" else m for m in MODULES} - {"__main__"}
    assert rows == expected, (f"missing from the README's table: {sorted(expected - rows)}; "
                              f"not in the package: {sorted(rows - expected)}")


#: Test folders that are not a subpackage: the package as a whole, and the notebooks.
TEST_FOLDERS_BEYOND_THE_PACKAGE = {"package", "notebooks"}


def test_the_tests_mirror_the_package_layout():
    """Every test module sits in ``tests/<subpackage>/`` (or ``tests/package/`` for the package
    as a whole, ``tests/notebooks/`` for the notebooks); none is left at the top, and every
    folder names a unit of LAYERS."""
    tests = Path(__file__).resolve().parents[1]
    assert not sorted(p.name for p in tests.glob("test_*.py")), "test modules left in tests/"
    folders = {p.parent.name for p in tests.glob("*/test_*.py")}
    units = {unit for layer in LAYERS for unit in layer}
    assert folders - units - TEST_FOLDERS_BEYOND_THE_PACKAGE == set()
    names = [p.name for p in tests.rglob("test_*.py")]
    assert len(names) == len(set(names)), "two test modules share a name"
