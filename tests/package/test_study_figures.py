"""The study figures README.md quotes are those of the stored study summaries
(benchmarks/studies/*/study.json): median and IQR of the final J_eval, worst seed, seeds
converged, median regret and the learner's part of it, each rounded as quoted."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
README = (ROOT / "README.md").read_text()
STUDIES = ROOT / "benchmarks" / "studies"
#: stored study -> the words that pick its row of README's results table
ROWS = {"paper_pathwise_5000": "the paper's MPC, pathwise gradient",
        "rest_of_day_pathwise_5000": "the rest of the day, pathwise gradient"}


def _row(label: str) -> str:
    rows = [line for line in README.splitlines() if line.startswith(f"| {label}")]
    assert len(rows) == 1, f"README has {len(rows)} rows starting with {label!r}"
    return rows[0]


@pytest.mark.parametrize("name", sorted(ROWS))
def test_readme_quotes_the_stored_study(name):
    study = json.loads((STUDIES / name / "study.json").read_text())
    split = study["class_split"]
    cells = [cell.strip() for cell in _row(ROWS[name]).strip("|").split("|")]
    low, high = study["J_eval_final_iqr"]
    seeds = sorted(int(s) for s in split["learner_gap"])
    assert cells[1] == f"{seeds[0]}-{seeds[-1]}"
    assert cells[2] == f"{study['J_eval_final_median']:.1f} ({low:.1f} to {high:.1f})"
    assert cells[3] == f"{study['worst_seed']['J_eval_final']:.1f}"
    assert cells[4] == f"{len(study['converged_seeds'])} / {study['done']}"
    assert cells[5] == f"{study['regret_median']:.1f}"
    gap_low, gap_high = split["learner_gap_iqr"]
    assert cells[6] == (f"{split['learner_gap_median']:.1f} ({gap_low:.1f} to {gap_high:.1f}), "
                        f"worst {split['learner_gap_worst']['value']:.1f}")
    share = max(study["late_regression_share"].values()) \
        if isinstance(study["late_regression_share"], dict) else study["late_regression_share"]
    assert cells[7] == f"{100 * share:.2f} % of the gap"
