"""The regret split in ``study --class-best``: each seed's learner gap against a tune result
of the study's class, the class gap against J*, and a tune result of another class refused
before any run."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest

from mpcrl_lite._util import jsonio
from mpcrl_lite.config import SystemConfig
from mpcrl_lite.studies.study import class_split, run_study
from mpcrl_lite.theta import Theta

HELD = {"mean": -260.0, "ci_low": -267.0, "ci_high": -253.0, "draws": 30}


def tune_dir(path, forecast="paper", system=None):
    path.mkdir(parents=True, exist_ok=True)
    system = system or SystemConfig()
    path.joinpath("tune.json").write_bytes(jsonio.dumps({
        "theta_best": Theta.nominal(system).to_dict(), "J_heldout": HELD, "J_best": -270.0,
        "forecast": forecast, "system": system.to_dict(), "evals": 10}))
    return path


def test_class_split_on_synthetic_seeds():
    table = pd.DataFrame({"seed": [0, 1, 2, 3], "status": ["done", "done", "failed", "done"],
                          "J_eval_final": [-210.0, -250.0, np.nan, -200.0]})
    split = class_split(table, {"J_heldout": HELD}, -401.5)
    assert split["learner_gap"] == {"0": 50.0, "1": 10.0, "3": 60.0}
    assert split["learner_gap_median"] == 50.0
    assert split["learner_gap_worst"] == {"seed": 3, "value": 60.0}
    assert split["class_gap"] == {"mean": 141.5, "ci_low": 134.5, "ci_high": 148.5}
    assert split["J_class_ci"] == [-267.0, -253.0]
    assert "class_gap" not in class_split(table, {"J_heldout": HELD}, None)


def test_tiny_study_with_class_best(tmp_path):
    base = {"learning.days_per_month": 2, "learning.eval_draws": 2, "learning.eval_every": 1}
    summary = run_study(2, 1, tmp_path / "s", base=base, workers=0, progress=False,
                        J_star=-400.0, class_best=tune_dir(tmp_path / "t"))
    split = summary["class_split"]
    saved = json.loads((tmp_path / "s" / "study.json").read_text())
    assert saved["class_split"] == json.loads(json.dumps(split))
    for seed, regret in summary["regret"].items():
        assert split["learner_gap"][seed] + split["class_gap"]["mean"] == pytest.approx(regret)
    with pytest.raises(ValueError, match="searched for another class"):
        run_study(2, 1, tmp_path / "s2", base=base, workers=0, progress=False, J_star=-400.0,
                  class_best=tune_dir(tmp_path / "u", forecast="until_midnight"))
    assert not (tmp_path / "s2" / "runs").exists()
