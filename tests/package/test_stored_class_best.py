"""The stored best thetas of the policy classes (``data/class_best_*/tune.json``) and the
figures the READMEs quote from them: every quoted number is the file's, rounded."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

from mpcrl_lite.bounds.baselines import load_class_best
from mpcrl_lite.config import POLICY_CLASSES, MPCConfig, SystemConfig, policy_class_of

ROOT = Path(__file__).resolve().parents[2]
DATA_README = (ROOT / "data" / "README.md").read_text()
README = (ROOT / "README.md").read_text()
STORED = {"paper": ROOT / "data" / "class_best_paper",
          "day_end": ROOT / "data" / "class_best_day_end",
          "rest_of_day": ROOT / "data" / "class_best_rest_of_day"}


def one(value: float) -> str:
    return f"{value:.1f}"


@pytest.mark.parametrize("name", sorted(STORED))
def test_a_stored_result_is_of_its_class_and_loads(name):
    result = json.loads((STORED[name] / "tune.json").read_text())
    system, mpc = SystemConfig.from_dict(result["system"]), MPCConfig.from_dict(result["mpc"])
    assert policy_class_of(system, mpc) == name
    assert (system.N, mpc.forecast) == (POLICY_CLASSES[name].N, POLICY_CLASSES[name].forecast)
    assert result["evals"] == 2500 and result["J_heldout"]["draws"] == 30
    assert load_class_best(STORED[name])["theta_best"].n == system.n


@pytest.mark.parametrize("name", sorted(STORED))
def test_the_data_readme_quotes_the_stored_figures(name):
    result = json.loads((STORED[name] / "tune.json").read_text())
    held = result["J_heldout"]
    section = DATA_README[DATA_README.index(f"`{STORED[name].name}/tune.json`"):]
    section = section[:section.index("\n## ")]
    assert f"J_best\n{one(result['J_best'])}" in section or \
        f"J_best {one(result['J_best'])}" in section
    assert (f"{one(held['mean'])} [{one(held['ci_low'])}, {one(held['ci_high'])}]"
            in section)
    assert f"+{one(result['J_nominal_heldout']['mean'])}" in section


def test_the_readme_quotes_the_rest_of_day_class():
    result = json.loads((STORED["rest_of_day"] / "tune.json").read_text())
    held = result["J_heldout"]
    quoted = re.search(r"holds\s+(-\d+\.\d) \[(-\d+\.\d), (-\d+\.\d)\]", README)
    assert quoted is not None
    assert quoted.groups() == (one(held["mean"]), one(held["ci_low"]), one(held["ci_high"]))
