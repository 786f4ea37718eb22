"""The package's shape: data flows one way, so the import graph has no cycle and no module
imports from a layer above its own.

Imports are read from the source (every ``from . import`` / ``from .x import`` /
``import mpcrl_lite.x``, also those inside functions), so a lazy import that only hides a cycle
is caught too. A new module must be placed in :data:`LAYERS` before this test passes: its
place in the data flow is a decision, not an accident.
"""

from __future__ import annotations

import ast
import graphlib
from pathlib import Path

import pytest

import mpcrl_lite

PACKAGE = Path(mpcrl_lite.__file__).parent

#: The layers of the data flow, lowest first (see the README's layout diagram). A module may
#: import modules of its own layer or of lower layers.
LAYERS: list[set[str]] = [
    # foundation: configuration, parameter structure, plain helpers
    {"config", "theta", "json_values", "resources", "references", "batch_linalg",
     "causal_kernels"},
    # the true system and its prices
    {"prices", "model", "day_end"},
    # the one MPC formulation
    {"mpc"},
    # solution and sensitivity types, below every back-end
    {"solution"},
    # the back-ends and the KKT sensitivity
    {"sensitivity", "batch_kkt", "batch_adjoint", "batch_solver", "ipopt_solver", "_kernel",
     "kernel_solver", "local_qp", "_explore_kernel", "_coord_kernel"},
    # the back-end registry
    {"solvers"},
    # the one closed loop and its record
    {"record", "exploration", "closed_loop"},
    # learning algorithms and results as data
    {"lstd", "update_rules", "dpg", "rundir", "history"},
    # what learners, coordination and bounds share
    {"learner", "coordination", "causal_grid", "causal_dual", "causal", "causal_table"},
    # learners, baselines and evaluation
    {"experiment", "decentralized", "baselines", "evaluation", "transfer"},
    # figures
    {"plot_style", "paper_figures", "plots"},
    # classroom and reports
    {"explore", "controls", "widgets", "alt_text", "html_export", "report", "launch", "site"},
    # orchestration: studies, sweeps and the command line
    {"sweep_grid", "sweep_store", "sweep_table", "sweep_run", "sweep_schedule", "sweep",
     "study", "lockstep", "cli", "cli_inputs", "__main__", "__init__"},
]
RANK = {module: rank for rank, layer in enumerate(LAYERS) for module in layer}


def _modules() -> dict[str, Path]:
    return {path.stem: path for path in PACKAGE.glob("*.py")}


def _imports(path: Path, modules: set[str]) -> dict[str, int]:
    """Package modules imported by ``path``, with the line of the first import."""
    found: dict[str, int] = {}
    for node in ast.walk(ast.parse(path.read_text())):
        names: list[str] = []
        if isinstance(node, ast.ImportFrom) and node.level:
            names = ([node.module.split(".")[0]] if node.module
                     else [alias.name for alias in node.names])
        elif isinstance(node, ast.ImportFrom) and node.module and node.module.startswith(
                "mpcrl_lite"):
            parts = node.module.split(".")
            names = [parts[1]] if len(parts) > 1 else [alias.name for alias in node.names]
        elif isinstance(node, ast.Import):
            names = [alias.name.split(".")[1] for alias in node.names
                     if alias.name.startswith("mpcrl_lite.")]
        for name in names:
            if name in modules and name != path.stem:
                found.setdefault(name, node.lineno)
    return found


GRAPH = {name: _imports(path, set(_modules())) for name, path in _modules().items()}


def test_every_module_has_a_place_in_the_data_flow():
    unplaced = sorted(set(GRAPH) - set(RANK))
    assert not unplaced, f"place these modules in LAYERS: {unplaced}"


def test_the_import_graph_has_no_cycle():
    try:
        list(graphlib.TopologicalSorter({m: set(d) for m, d in GRAPH.items()}).static_order())
    except graphlib.CycleError as err:
        pytest.fail(f"import cycle: {' -> '.join(err.args[1])}")


@pytest.mark.parametrize("module", sorted(GRAPH))
def test_no_module_imports_from_a_layer_above(module):
    if module not in RANK:
        pytest.fail(f"{module} has no place in LAYERS")
    upward = {name: line for name, line in GRAPH[module].items()
              if RANK.get(name, len(LAYERS)) > RANK[module]}
    assert not upward, f"{module} imports from higher layers: {upward} (name: line)"


def test_the_check_sees_imports_inside_functions(tmp_path):
    """The reader counts an import hidden in a function body (a lazy import is no way out)."""
    source = tmp_path / "probe.py"
    source.write_text("def f():\n    from .cli import main\n    return main\n")
    assert _imports(source, {"cli", "probe"}) == {"cli": 2}
