"""The notebooks' parameters: their defaults follow the package, and papermill names are exact.

Each notebook's ``parameters`` cell restates some package defaults (``P_BAR: float = 1.5``
for ``SystemConfig().P_bar``). They must agree, or the notebook must be listed in
:data:`DELIBERATE` with the value it uses and why. A name given to papermill that is not
exactly a parameter (``-p months 5``, ``-p P_Bar 1.0``) is an error naming the closest one.
"""

from __future__ import annotations

import ast
import json
import subprocess
import sys

import nbref
import papermill
import pytest

from mpcrl_lite.config import (
    PAPER_EXPLORATION_STD,
    PAPER_TAU,
    LearningConfig,
    MPCConfig,
    SystemConfig,
)
from mpcrl_lite.publish.report import check_parameters, execute_notebook, notebook_parameters

STEMS = nbref.stems()

#: Parameter name -> the config field whose default it restates.
FOLLOWS = {
    "P_BAR": (SystemConfig, "P_bar"),
    "NOISE_VAR": (SystemConfig, "noise_var"),
    "SOC0": (SystemConfig, "soc0"),
    "TAU": (MPCConfig, "tau"),
    "BACKEND": (MPCConfig, "backend"),
    "MONTHS": (LearningConfig, "months"),
    "DAYS": (LearningConfig, "days_per_month"),
    "SEED": (LearningConfig, "seed"),
    "EVAL_SEED": (LearningConfig, "eval_seed"),
    "EXPLORATION_STD": (LearningConfig, "exploration_std"),
    "EVAL_DRAWS": (LearningConfig, "eval_draws"),
    "EVAL_EVERY": (LearningConfig, "eval_every"),
    "HESSIAN": (LearningConfig, "hessian"),
}

#: Parameters of a notebook's own, with no package default to follow.
OWN = {
    "01_battery_dynamics": {"BUY_BELOW", "SELL_ABOVE", "SOC_MIN", "SOC_MAX", "NOISE_SAMPLES",
                            "PRICE_FILE", "PRICE_AREA", "PRICE_MONTH"},
    "02_mpc_policy": {"SMALL_P_BAR", "HOUR", "CURVE_POINTS"},
    "04_deterministic_policy_gradient": {"HOUR", "FD_STEP"},
    "06_baselines_and_decentralized_learning": {"LEARNER_MONTHS", "N_LARGE", "CAUSAL_POLICY",
                                                "MIXED_MONTHS"},
    "07_parameter_study": {"P_BARS", "NOISE_VARS", "SEEDS", "WORKERS"},
    "08_q_learning_vs_policy_gradient": {"SEEDS", "THRESHOLD"},
    "09_why_the_learner_stops_short": {"ROLLOUT_DRAWS", "ROLLOUT_SEED", "EPS_SLOPE", "EPS_WIDE",
                                       "CRITIC_MONTHS"},
}

#: (notebook, parameter) -> (the value it uses instead of the package default, why).
DELIBERATE = {
    ("02_mpc_policy", "TAU"): (PAPER_TAU, (
        "teaches the MPC itself, its bang-bang plans included: the nearly exact MPC "
        "(MPCConfig.paper()); the learning default 0.1 comes with the policy gradient in 04")),
    ("02_mpc_policy", "DAYS"): (5, "a few days of closed loop to look at, not a learning month"),
    ("03_lstd_value_functions", "TAU"): (
        PAPER_TAU, "fits the critic to the nearly exact nominal MPC of notebook 02"),
    ("03_lstd_value_functions", "EXPLORATION_STD"): (PAPER_EXPLORATION_STD, (
        "studies the critic under the paper's 'small random exploration' "
        "(LearningConfig.paper()); the learning default is larger to make its fit less noisy")),
    ("04_deterministic_policy_gradient", "EVAL_SEED"): (1, (
        "one evaluation draw shared by the parameters compared in this notebook; any seed "
        "other than SEED serves")),
    ("07_parameter_study", "MONTHS"): (30, (
        "a grid of 3 x 2 x 3 = 18 learning runs: 30 months each keeps the default study "
        "affordable; the full 100-month run is notebook 05's")),
    ("08_q_learning_vs_policy_gradient", "MONTHS"): (40, (
        "two learners x 3 seeds: 40 months each keeps the notebook at about two minutes and "
        "shows both the fast start of Q-learning and its late drift")),
}


def _defaults(stem: str) -> dict:
    return {name: ast.literal_eval(spec["default"])
            for name, spec in notebook_parameters(nbref.notebook_path(stem)).items()}


@pytest.mark.parametrize("stem", STEMS)
def test_parameter_defaults_are_the_package_defaults(stem):
    for name, value in _defaults(stem).items():
        if (stem, name) in DELIBERATE:
            expected, why = DELIBERATE[(stem, name)]
            assert value == expected, f"{stem}: {name} = {value!r}, listed as {expected!r} ({why})"
        elif name in FOLLOWS:
            config, field = FOLLOWS[name]
            default = getattr(config(), field)
            assert value == default and type(value) is type(default), (
                f"{stem}: {name} = {value!r} but {config.__name__}().{field} = {default!r}; "
                "make them equal, or list the difference in DELIBERATE with the reason")
        else:
            assert name in OWN.get(stem, set()), (
                f"{stem}: {name} is neither a config field's default (FOLLOWS) nor listed as "
                "the notebook's own (OWN)")


def test_deliberate_differences_are_real_and_current():
    for (stem, name), (value, why) in DELIBERATE.items():
        assert why
        config, field = FOLLOWS[name]
        assert value != getattr(config(), field), f"{stem}: {name} no longer differs; drop it"
        assert name in _defaults(stem), f"{stem} has no parameter {name}"


def test_the_parameter_study_grid_contains_the_defaults():
    values = _defaults("07_parameter_study")
    assert SystemConfig().P_bar in [float(v) for v in values["P_BARS"].split(",")]
    assert SystemConfig().noise_var in [float(v) for v in values["NOISE_VARS"].split(",")]


# -- names given to papermill must be exact ---------------------------------------------------
STEM = "05_three_agent_learning"


def _kernel_namespace(injected: dict) -> dict:
    """globals() of a kernel after the parameters cell and papermill's injected cell."""
    cell = "# Parameters\n" + "".join(f"{k} = {v!r}\n" for k, v in injected.items())
    defaults = _defaults(STEM)
    parameters_cell = "\n".join(f"{k} = {v!r}" for k, v in defaults.items())
    return {"In": ["", parameters_cell, cell], "Out": {}, **defaults, **injected}


@pytest.mark.parametrize("name, closest", [("months", "MONTHS"), ("P_Bar", "P_BAR"),
                                           ("Days", "DAYS"), ("TAUU", "TAU")])
def test_a_name_that_is_not_exactly_a_parameter_names_the_closest_one(name, closest):
    namespace = _kernel_namespace({name: 5})
    with pytest.raises(ValueError, match=rf"unknown parameter\(s\) \['{name}'\]; did you mean "
                                         rf"'{closest}' for '{name}'\? Names must match exactly"):
        check_parameters(namespace, f"{STEM}.ipynb")


def test_exact_injected_names_pass_and_are_returned():
    namespace = _kernel_namespace({"MONTHS": 2, "DAYS": 2})
    values = check_parameters(namespace, f"{STEM}.ipynb")
    assert values["MONTHS"] == 2 and values["DAYS"] == 2 and values["P_BAR"] == 1.5


def test_later_lower_case_variables_are_not_taken_for_parameters():
    """Only names papermill injected (and UPPER_CASE globals) are checked, so re-running the
    check cell in a live kernel after later cells defined ``system``, ``months``... is fine."""
    namespace = {**_kernel_namespace({}), "months": [1, 2], "system": SystemConfig()}
    assert check_parameters(namespace, f"{STEM}.ipynb")["MONTHS"] == 100


def test_execute_notebook_names_the_closest_parameter_before_running(tmp_path):
    with pytest.raises(ValueError, match="did you mean 'MONTHS' for 'months'"):
        execute_notebook(nbref.notebook_path(STEM), tmp_path / "out.ipynb", {"months": 5})
    assert not (tmp_path / "out.ipynb").exists()


@pytest.mark.notebook
def test_papermill_with_a_lower_case_name_fails_in_the_check_cell(tmp_path, monkeypatch):
    """``papermill 05_....ipynb out.ipynb -p months 5`` ran 100 months, silently."""
    monkeypatch.setenv("MPLBACKEND", "Agg")
    with pytest.raises(papermill.PapermillExecutionError) as info:
        papermill.execute_notebook(str(nbref.notebook_path(STEM)), str(tmp_path / "out.ipynb"),
                                   parameters={"months": 1, "DAYS": 1}, kernel_name="python3",
                                   cwd=str(tmp_path), progress_bar=False)
    assert "did you mean 'MONTHS' for 'months'" in str(info.value)


# -- reading the parameters cell without papermill ----------------------------------------
def _papermill_view(path) -> dict:
    return {name: {"default": spec["default"], "type": spec["inferred_type_name"],
                   "help": spec["help"]}
            for name, spec in papermill.inspect_notebook(str(path)).items()}


@pytest.mark.parametrize("stem", STEMS)
def test_the_parameters_read_in_the_kernel_are_papermills(stem):
    """``notebook_parameters`` reads plain cells itself (no papermill import in the kernel);
    the answer is papermill's, names in the same order."""
    ours = notebook_parameters(nbref.notebook_path(stem))
    theirs = _papermill_view(nbref.notebook_path(stem))
    assert ours == theirs
    assert list(ours) == list(theirs)


def _notebook_with(tmp_path, source: str):
    cell = {"cell_type": "code", "execution_count": None, "id": "p", "outputs": [],
            "metadata": {"tags": ["parameters"]}, "source": source}
    nb = {"cells": [cell], "metadata": {"kernelspec": {"name": "python3",
                                                      "language": "python"}},
          "nbformat": 4, "nbformat_minor": 5}
    path = tmp_path / "nb.ipynb"
    path.write_text(json.dumps(nb))
    return path


@pytest.mark.parametrize("source", [
    'A: int = 3  # three\nB = "x=y"  # a string with an equals sign\nC: float = 1e-4\n',
    'A = 1\nD = {\n    "k": 2,  # inner\n}  # a dict over lines\n',
    'A = 1  # type: int\n',
    'A = 1\nprint(A)\n',
    'A = (\n',
    '',
])
def test_cells_it_cannot_read_plainly_go_to_papermill_with_the_same_answer(tmp_path, source):
    path = _notebook_with(tmp_path, source)
    assert notebook_parameters(path) == _papermill_view(path)


def test_a_plain_cell_is_read_without_papermill(tmp_path):
    from mpcrl_lite.publish import report

    assert report._plain_parameters('A: int = 3  # three\nB = 1.5\n') == {
        "A": {"default": "3", "type": "int", "help": "three"},
        "B": {"default": "1.5", "type": "None", "help": ""},
    }
    for odd in ('D = {\n  "k": 2,\n}\n', 'A = 1  # type: int\n', 'print(1)\n', 'A = (\n',
                'B = "x=y"\n'):
        assert report._plain_parameters(odd) is None, odd


def test_the_check_cell_does_not_import_papermill():
    code = ("import sys\n"
            "from mpcrl_lite.publish.report import check_parameters\n"
            f"check_parameters({{'MONTHS': 2}}, '{STEM}.ipynb')\n"
            "print(sorted(m for m in ('papermill', 'nbformat', 'jsonschema') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True)
    assert out.stdout.strip() == "[]", out.stdout + out.stderr
