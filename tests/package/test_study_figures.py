"""The study figures README.md and notebook 09 quote are those of the stored study summaries
(benchmarks/studies/*/study.json): median and IQR of the final J_eval, worst seed, seeds
converged, median regret and the learner's part of it, each rounded as quoted."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
README = (ROOT / "README.md").read_text()
NOTEBOOK_09 = " ".join(
    "".join(cell["source"]) for cell in json.loads(
        (ROOT / "notebooks" / "09_why_the_learner_stops_short.ipynb").read_text())["cells"]
    if cell["cell_type"] == "markdown").replace("\n", " ")
STUDIES = ROOT / "benchmarks" / "studies"
#: stored study -> the words that pick its row of README's results table
ROWS = {"paper_pathwise_5000": "the paper's MPC, pathwise gradient",
        "day_end_pathwise_5000": "the day-end forecast, pathwise gradient",
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
    low, high = split["learner_gap_paired_iqr"]
    assert cells[7] == (f"{split['learner_gap_paired_median']:.1f} ({low:.1f} to {high:.1f}), "
                        f"worst {split['learner_gap_paired_worst']['value']:.1f}")
    share = max(study["late_regression_share"].values()) \
        if isinstance(study["late_regression_share"], dict) else study["late_regression_share"]
    assert cells[8] == f"{100 * share:.2f} % of the gap"


def _gap(name: str, key: str = "learner_gap_median") -> float:
    return json.loads((STUDIES / name / "study.json").read_text())["class_split"][key]


def test_the_learner_gaps_quoted_in_prose_are_the_stored_ones():
    """The sentences that compare the critic's learner with the pathwise one."""
    paper, rest = _gap("paper_pathwise_5000"), _gap("rest_of_day_pathwise_5000")
    critic_paper, critic_rest = _gap("paper_critic_5000"), _gap("rest_of_day_critic_4000")
    text = " ".join(README.split())
    assert f"the rest-of-day learner ends {-rest:.1f} NOK/day *below*" in text
    assert f"(the critic: {critic_rest:.1f} above, on the seeds 4000-4009)" in text
    assert f"paper class's learner {paper:.1f} above its class's best" in text
    assert f"(the critic on the same seeds: {critic_paper:.1f})" in text
    notebook = " ".join(NOTEBOOK_09.split())
    assert f"a median {paper:.0f} NOK/day above the paper class's" in notebook
    assert f"and {-rest:.0f} NOK/day *below* the rest-of-day class's" in notebook
    assert f"stays {critic_paper:.0f} above (paper, the same seeds) and {critic_rest:.0f} " \
           "above (rest of the day, seeds 4000-4009)" in notebook
    paired_paper = _gap("paper_pathwise_5000", "learner_gap_paired_median")
    paired_rest = _gap("rest_of_day_pathwise_5000", "learner_gap_paired_median")
    assert paired_paper > 0 > paired_rest
    assert f"the pathwise gaps are {paired_paper:.0f} above and {-paired_rest:.0f} below" \
        in notebook


def test_the_paired_gap_and_the_second_fresh_judgement_are_the_stored_ones():
    """The paragraph after README's results table: the class's best on both sets of draws and
    the paper class on the seeds 6000-6019."""
    text = " ".join(README.split())
    first = json.loads((STUDIES / "paper_pathwise_5000" / "study.json").read_text())
    split = first["class_split"]
    assert f"held-out draws it has J = {split['J_class']:.1f}" in text
    assert f"it has {split['J_class_eval']['mean']:.1f}." in text
    assert split["J_class_eval"]["draws"] == 10 and first["eval_draws"] == 10
    study = json.loads((STUDIES / "paper_pathwise_6000" / "study.json").read_text())
    second = study["class_split"]
    seeds = sorted(int(s) for s in second["learner_gap"])
    assert (seeds[0], seeds[-1], len(seeds)) == (6000, 6019, 20)
    held, pair = second["learner_gap_iqr"], second["learner_gap_paired_iqr"]
    assert (f"Learner gap: median {second['learner_gap_median']:.1f} (IQR {held[0]:.1f} to "
            f"{held[1]:.1f}); paired: {second['learner_gap_paired_median']:.1f} ({pair[0]:.1f} "
            f"to {pair[1]:.1f})") in text
    worst, worst_paired = second["learner_gap_worst"], second["learner_gap_paired_worst"]
    assert worst["seed"] == worst_paired["seed"] == study["worst_seed"]["seed"]
    assert (f"The worst seed is {worst['seed']}, with a gap of {worst['value']:.1f}, or "
            f"{worst_paired['value']:.1f} paired.") in text
    late = study["largest_late_regression"]
    share = study["late_regression_share"][str(late["seed"])]
    assert f"It lost {late['value']:.1f} NOK/day after its best evaluation, which is " \
           f"{100 * share:.1f} % of the gap." in text


#: benchmarks/README.md's table of the paired learner gaps: row label -> stored study
PAIRED_ROWS = {
    "paper, pathwise, 5000-5019": "paper_pathwise_5000",
    "day-end, pathwise, 5000-5019": "day_end_pathwise_5000",
    "rest of the day, pathwise, 5000-5019": "rest_of_day_pathwise_5000",
    "rest of the day, pathwise, scale 100, 5000-5019": "rest_of_day_pathwise_scale100_5000",
    "paper, critic (default), 5000-5019": "paper_critic_5000",
    "rest of the day, critic, 4000-4009": "rest_of_day_critic_4000",
}


@pytest.mark.parametrize("label", sorted(PAIRED_ROWS))
def test_the_benchmarks_table_of_paired_gaps_is_the_stored_one(label):
    text = (ROOT / "benchmarks" / "README.md").read_text()
    rows = [line for line in text.splitlines() if line.startswith(f"| {label} |")]
    assert len(rows) == 1, rows
    split = json.loads((STUDIES / PAIRED_ROWS[label] / "study.json").read_text())["class_split"]
    held = f"{split['learner_gap_median']:.1f} ({split['learner_gap_worst']['value']:.1f})"
    paired = (f"{split['learner_gap_paired_median']:.1f} "
              f"({split['learner_gap_paired_worst']['value']:.1f})")
    assert rows[0] == f"| {label} | {held} | {paired} |"


#: stored study -> the tune result its class split was made against
CLASS_BEST = {"paper_pathwise_5000": "paper", "paper_pathwise_6000": "paper",
              "paper_critic_5000": "paper", "day_end_pathwise_5000": "day_end",
              "rest_of_day_pathwise_5000": "rest_of_day",
              "rest_of_day_pathwise_scale100_5000": "rest_of_day",
              "rest_of_day_critic_4000": "rest_of_day"}


def test_every_stored_study_has_a_class_best():
    assert {p.name for p in STUDIES.iterdir() if (p / "study.json").exists()} == set(CLASS_BEST)


@pytest.mark.parametrize("name", sorted(CLASS_BEST))
def test_the_stored_paired_figures_are_what_their_files_give(name):
    """``J_class_eval`` is the class's best theta on the draws of the study's runs (run again
    here from the stored run config, to the rounding of another machine) and the paired gaps
    are the stored final J_evals minus it."""
    import pandas as pd

    from mpcrl_lite.bounds.baselines import load_class_best
    from mpcrl_lite.studies.study import class_on_run_draws
    from mpcrl_lite.studies.sweep.grid import SweepRun

    folder = STUDIES / name
    split = json.loads((folder / "study.json").read_text())["class_split"]
    assert split["source"] == f"data/class_best_{CLASS_BEST[name]}"
    tuned = load_class_best(ROOT / split["source"])
    config = json.loads(next(folder.glob("config_seed*.json")).read_text())
    again = class_on_run_draws(SweepRun.from_config(config), tuned["theta_best"])
    stored = split["J_class_eval"]
    assert (again["draws"], again["seed"]) == (stored["draws"], stored["seed"])
    assert again["J"] == pytest.approx(stored["J"], rel=1e-8)
    table = pd.read_csv(folder / "study.csv")
    gaps = {str(int(s)): float(j) - stored["mean"]
            for s, j in zip(table["seed"], table["J_eval_final"], strict=True)}
    assert split["learner_gap_paired"] == pytest.approx(gaps, rel=1e-12)
