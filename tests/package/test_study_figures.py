"""The study figures README.md and notebook 09 quote are those of the stored study summaries
(benchmarks/studies/*/study.json): median and IQR of the final J_eval, worst seed, seeds
converged, median regret and the learner's part of it, each rounded as quoted."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import pytest
from bench_readme import bench_row

from mpcrl_lite.theta import Theta

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


def _summary(name: str) -> dict[str, Any]:
    """The ``study.json`` of the stored study ``name``."""
    return json.loads((STUDIES / name / "study.json").read_text())


def _config(name: str) -> dict[str, Any]:
    """The stored run configuration (``config_seed*.json``) of the stored study ``name``."""
    return json.loads(next((STUDIES / name).glob("config_seed*.json")).read_text())


def _row(label: str) -> str:
    rows = [line for line in README.splitlines() if line.startswith(f"| {label} |")] or [
        line for line in README.splitlines() if line.startswith(f"| {label}")]
    assert len(rows) == 1, f"README has {len(rows)} rows starting with {label!r}"
    return rows[0]


def _cells(label: str) -> list[str]:
    """The cells of README's table row ``label``."""
    return [cell.strip() for cell in _row(label).strip("|").split("|")]


def _seed_span(study: dict) -> str:
    """``first-last`` of the seeds a study's class split covers."""
    seeds = sorted(int(s) for s in study["class_split"]["learner_gap"])
    return f"{seeds[0]}-{seeds[-1]}"


def _median_iqr(study: dict) -> str:
    """The median final J_eval with its IQR, as README writes it."""
    low, high = study["J_eval_final_iqr"]
    return f"{study['J_eval_final_median']:.1f} ({low:.1f} to {high:.1f})"


def _gap_cell(split: dict, key: str) -> str:
    """A learner gap (``key``: ``learner_gap`` or ``learner_gap_paired``) as README writes it:
    median (IQR), worst."""
    low, high = split[f"{key}_iqr"]
    return (f"{split[f'{key}_median']:.1f} ({low:.1f} to {high:.1f}), "
            f"worst {split[f'{key}_worst']['value']:.1f}")


@pytest.mark.parametrize("name", sorted(ROWS))
def test_readme_quotes_the_stored_study(name):
    study = _summary(name)
    split = study["class_split"]
    cells = _cells(ROWS[name])
    assert cells[1] == _seed_span(study)
    assert cells[2] == _median_iqr(study)
    assert cells[3] == f"{study['worst_seed']['J_eval_final']:.1f}"
    assert cells[4] == f"{len(study['converged_seeds'])} / {study['done']}"
    assert cells[5] == f"{study['regret_median']:.1f}"
    assert cells[6] == _gap_cell(split, "learner_gap")
    assert cells[7] == _gap_cell(split, "learner_gap_paired")
    share = max(study["late_regression_share"].values()) \
        if isinstance(study["late_regression_share"], dict) else study["late_regression_share"]
    assert cells[8] == f"{100 * share:.2f} % of the gap"


def _gap(name: str, key: str = "learner_gap_median") -> float:
    return _summary(name)["class_split"][key]


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


@pytest.mark.parametrize(("name", "label"), [
    ("rest_of_day_pathwise_6000", "The rest of the day"),
    ("day_end_pathwise_6000", "The day-end forecast"),
    ("rest_of_day_pathwise_11000", "The rest of the day"),
    ("day_end_pathwise_11000", "The day-end forecast"),
])
def test_the_labelled_classes_on_more_fresh_seeds_are_the_stored_ones(name, label):
    """README's paragraphs on the labelled classes judged on the seeds 6000-6019 and
    11000-11019: medians, IQRs, the learner gaps, the late loss and the least share of the
    gap any seed closed."""
    text = " ".join(README.split())
    study, table = _study(name)
    split = study["class_split"]
    seeds = sorted(int(s) for s in split["learner_gap"])
    start = int(name.rsplit("_", 1)[1])
    assert (seeds[0], seeds[-1], len(seeds)) == (start, start + 19, 20)
    low, high = study["J_eval_final_iqr"]
    held, pair = split["learner_gap_iqr"], split["learner_gap_paired_iqr"]
    late = study["largest_late_regression"]
    share = study["late_regression_share"][str(late["seed"])]
    gap = study["J_nominal"] - study["J_target"]
    closed = min((study["J_nominal"] - float(j)) / gap for j in table["J_eval_final"])
    assert (f"{label}: median final J {study['J_eval_final_median']:.1f} ({low:.1f} to "
            f"{high:.1f}), median regret {study['regret_median']:.1f}; learner gap "
            f"{split['learner_gap_median']:.1f} (IQR {held[0]:.1f} to {held[1]:.1f}), paired "
            f"{split['learner_gap_paired_median']:.1f} ({pair[0]:.1f} to {pair[1]:.1f}); the "
            f"largest late loss {100 * share:.1f} % of the gap") in text
    assert f"closed at least {100 * closed:.1f} %" in text
    assert closed >= 0.95  # the target: every seed closes 95 % of the gap


def _fresh_split(name: str, start: int) -> tuple[dict, dict, list, list]:
    """A stored study of the 20 seeds from ``start``: its summary, its class split and the
    IQRs of the held-out and the paired learner gaps."""
    study = _summary(name)
    split = study["class_split"]
    seeds = sorted(int(s) for s in split["learner_gap"])
    assert (seeds[0], seeds[-1], len(seeds)) == (start, start + 19, 20)
    return study, split, split["learner_gap_iqr"], split["learner_gap_paired_iqr"]


def test_the_paired_gap_and_the_second_fresh_judgement_are_the_stored_ones():
    """The paragraph after README's results table: the class's best on both sets of draws and
    the paper class on the seeds 6000-6019 and 11000-11019."""
    text = " ".join(README.split())
    first = _summary("paper_pathwise_5000")
    split = first["class_split"]
    assert f"held-out draws it has J = {split['J_class']:.1f}" in text
    assert f"it has {split['J_class_eval']['mean']:.1f}." in text
    assert split["J_class_eval"]["draws"] == 10 and first["eval_draws"] == 10
    study, second, held, pair = _fresh_split("paper_pathwise_6000", 6000)
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
    # the third set of seeds
    study, third, held, pair = _fresh_split("paper_pathwise_11000", 11000)
    assert (f"learner gap median {third['learner_gap_median']:.1f} (IQR {held[0]:.1f} to "
            f"{held[1]:.1f}), paired {third['learner_gap_paired_median']:.1f} ({pair[0]:.1f} "
            f"to {pair[1]:.1f}); all {round(20 * study['fraction_converged'])} seeds close 90 % "
            "of the gap") in text
    worst, worst_paired = third["learner_gap_worst"], third["learner_gap_paired_worst"]
    late = study["largest_late_regression"]
    assert worst["seed"] == worst_paired["seed"] == late["seed"]
    share = study["late_regression_share"][str(late["seed"])]
    assert (f"the worst seed, {worst['seed']}, has a gap of {worst['value']:.1f}, or "
            f"{worst_paired['value']:.1f} paired, and lost {late['value']:.1f} NOK/day after its "
            f"best evaluation ({100 * share:.1f} % of the gap)") in text


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
    row = bench_row(label)
    split = _summary(PAIRED_ROWS[label])["class_split"]
    held = f"{split['learner_gap_median']:.1f} ({split['learner_gap_worst']['value']:.1f})"
    paired = (f"{split['learner_gap_paired_median']:.1f} "
              f"({split['learner_gap_paired_worst']['value']:.1f})")
    assert row == f"| {label} | {held} | {paired} |"


#: the studies of months never used to choose anything (October and December 2020, NO3, from
#: Nord Pool's export): folder -> the folder of the class's best theta found on that month
UNSEEN = {"oct2020_paper_pathwise_7000": "oct2020_class_best_paper",
          "oct2020_day_end_pathwise_7000": "oct2020_class_best_day_end",
          "oct2020_rest_of_day_pathwise_7000": "oct2020_class_best_rest_of_day",
          "oct2020_paper_critic_7000": "oct2020_class_best_paper",
          "oct2020_paper_critic_reset_7000": "oct2020_class_best_paper",
          "oct2020_day_end_pathwise_300m_7000": "oct2020_class_best_day_end",
          "dec2020_paper_pathwise_8000": "dec2020_class_best_paper",
          "dec2020_day_end_pathwise_8000": "dec2020_class_best_day_end",
          "dec2020_rest_of_day_pathwise_8000": "dec2020_class_best_rest_of_day",
          "oct2020_day_end_pathwise_scaled_7000": "oct2020_class_best_day_end",
          "oct2020_paper_pathwise_scaled_7000": "oct2020_class_best_paper",
          "oct2020_rest_of_day_pathwise_scaled_7000": "oct2020_class_best_rest_of_day",
          "oct2020_paper_critic_scaled_7000": "oct2020_class_best_paper",
          "oct2020_paper_critic_scaled_reset_7000": "oct2020_class_best_paper",
          "dec2020_paper_pathwise_scaled_8000": "dec2020_class_best_paper",
          "dec2020_day_end_pathwise_scaled_8000": "dec2020_class_best_day_end",
          "dec2020_rest_of_day_pathwise_scaled_8000": "dec2020_class_best_rest_of_day",
          "jul2020_rest_of_day_pathwise_9000": "jul2020_class_best_rest_of_day",
          "jul2020_day_end_pathwise_9000": "jul2020_class_best_day_end",
          "jul2020_paper_pathwise_9000": "jul2020_class_best_paper",
          "jul2020_paper_critic_9000": "jul2020_class_best_paper",
          "oct2020_paper_critic_months4_t1000_w5_7000": "oct2020_class_best_paper",
          "jul2020_paper_critic_months4_t1000_w5_9000": "jul2020_class_best_paper",
          "dec2020_paper_critic_8000": "dec2020_class_best_paper",
          "dec2020_paper_critic_months4_t1000_w5_8000": "dec2020_class_best_paper",
          "dec2020_paper_critic_reset_8000": "dec2020_class_best_paper",
          "sep2020_rest_of_day_pathwise_12000": "sep2020_class_best_rest_of_day",
          "sep2020_day_end_pathwise_12000": "sep2020_class_best_day_end",
          "sep2020_paper_pathwise_12000": "sep2020_class_best_paper",
          **{f"sep2020_{c}_pathwise_from_nov_12000": f"sep2020_class_best_{c}"
             for c in ("rest_of_day", "day_end", "paper")},
          "dec2020_day_end_pathwise_from_nov_8000": "dec2020_class_best_day_end",
          "dec2020_paper_pathwise_from_nov_8000": "dec2020_class_best_paper",
          "dec2020_paper_critic_from_nov_8000": "dec2020_class_best_paper",
          "oct2020_day_end_pathwise_from_nov_7000": "oct2020_class_best_day_end",
          "oct2020_paper_pathwise_from_nov_7000": "oct2020_class_best_paper"}
#: stored study -> the tune result its class split was made against
CLASS_BEST = {"paper_pathwise_5000": "data/class_best_paper",
              "paper_pathwise_6000": "data/class_best_paper",
              "paper_pathwise_11000": "data/class_best_paper",
              "paper_pathwise_14000": "data/class_best_paper",
              "paper_pathwise_terminal100_14000": "data/class_best_paper",
              "paper_critic_14000": "data/class_best_paper",
              "paper_critic_terminal3000_decay25_14000": "data/class_best_paper",
              "paper_critic_5000": "data/class_best_paper",
              "paper_critic_6000": "data/class_best_paper",
              "paper_critic_months4_5000": "data/class_best_paper",
              "paper_critic_months4_6000": "data/class_best_paper",
              "paper_critic_months4_t1000_w5_5000": "data/class_best_paper",
              "paper_critic_months4_t1000_w5_6000": "data/class_best_paper",
              "day_end_pathwise_5000": "data/class_best_day_end",
              "day_end_pathwise_6000": "data/class_best_day_end",
              "day_end_pathwise_11000": "data/class_best_day_end",
              "rest_of_day_pathwise_5000": "data/class_best_rest_of_day",
              "rest_of_day_pathwise_6000": "data/class_best_rest_of_day",
              "rest_of_day_pathwise_11000": "data/class_best_rest_of_day",
              "rest_of_day_pathwise_scale100_5000": "data/class_best_rest_of_day",
              "rest_of_day_critic_4000": "data/class_best_rest_of_day",
              "rest_of_day_critic_5000": "data/class_best_rest_of_day",
              "rest_of_day_critic_months4_4000": "data/class_best_rest_of_day",
              "rest_of_day_critic_months4_5000": "data/class_best_rest_of_day",
              **{name: f"benchmarks/studies/{best}" for name, best in UNSEEN.items()}}
#: where the October 2020 studies read their prices: Nord Pool's export, which its terms keep
#: out of the project (``../shared/data/README.md``)
NORD_POOL_2020 = ROOT.parent / "shared" / "data" / "nordpool" / "elspot-prices_2020_hourly_nok.csv"


def test_every_stored_study_has_a_class_best():
    assert {p.name for p in STUDIES.iterdir() if (p / "study.json").exists()} == set(CLASS_BEST)


@pytest.mark.parametrize("name", sorted(CLASS_BEST))
def test_the_stored_paired_gaps_are_the_final_j_evals_less_the_class_best(name):
    """The paired gaps are each seed's stored final J_eval minus ``J_class_eval``'s mean, and
    that mean is the mean of its per-draw values."""
    study, table = _study(name)
    split = study["class_split"]
    assert split["source"] == CLASS_BEST[name]
    assert (ROOT / split["source"] / "tune.json").exists()
    stored = split["J_class_eval"]
    assert stored["mean"] == pytest.approx(sum(stored["J"]) / len(stored["J"]), rel=1e-12)
    gaps = {str(int(s)): float(j) - stored["mean"]
            for s, j in zip(table["seed"], table["J_eval_final"], strict=True)}
    assert split["learner_gap_paired"] == pytest.approx(gaps, rel=1e-12)


def _draws_key(name: str) -> str:
    """What a study's ``J_class_eval`` depends on: the class's best theta and the runs'
    system, MPC, month and evaluation draws (not the learner's settings or seeds)."""
    config = _config(name)
    learning = config["learning"]
    return json.dumps([_summary(name)["class_split"]["source"],
                       config["system"], config["mpc"], config.get("prices", {}),
                       {k: learning.get(k) for k in ("eval_seed", "eval_draws", "days_per_month")}],
                      sort_keys=True)


#: one study for each distinct key: its J_class_eval is run again; the others share it
_KEYS = {name: _draws_key(name) for name in sorted(CLASS_BEST)}
REPRESENTATIVE = {key: name for name, key in reversed(list(_KEYS.items()))}


@pytest.mark.parametrize("name", sorted(set(REPRESENTATIVE.values())))
def test_the_stored_class_best_on_the_run_draws_is_what_their_files_give(name):
    """``J_class_eval`` is the class's best theta on the draws of the study's runs, run again
    here from the stored run config, to the rounding of another machine. The studies of 2020's
    other months need Nord Pool's export beside the checkout, as the price-file tests do."""
    from mpcrl_lite.bounds.baselines import load_class_best
    from mpcrl_lite.studies.study import class_on_run_draws
    from mpcrl_lite.studies.sweep.grid import SweepRun

    split = _summary(name)["class_split"]
    tuned = load_class_best(ROOT / split["source"])
    config = _config(name)
    if config.get("prices", {}).get("file"):
        assert config["prices"]["file"] == "../shared/data/nordpool/" + NORD_POOL_2020.name
        if not NORD_POOL_2020.exists():
            pytest.skip(f"needs {NORD_POOL_2020} (Nord Pool's export; not in the project)")
        config["prices"]["file"] = str(NORD_POOL_2020)
    again = class_on_run_draws(SweepRun.from_config(config), tuned["theta_best"])
    stored = split["J_class_eval"]
    assert (again["draws"], again["seed"]) == (stored["draws"], stored["seed"])
    assert again["J"] == pytest.approx(stored["J"], rel=1e-8)


@pytest.mark.parametrize("name", sorted(n for n, key in _KEYS.items() if REPRESENTATIVE[key] != n))
def test_studies_on_the_same_draws_share_their_class_best_figure(name):
    """A study whose class's best ran on the same draws as another's (same class, system,
    MPC, month and draws; only the learner differs) has the same ``J_class_eval``."""
    other = REPRESENTATIVE[_KEYS[name]]
    mine = _summary(name)["class_split"]
    theirs = _summary(other)["class_split"]
    assert mine["J_class_eval"]["J"] == pytest.approx(theirs["J_class_eval"]["J"], rel=1e-12)


#: README's table of the months never used to choose anything: row label -> stored study
UNSEEN_ROWS = {
    "October 2020: the rest of the day, pathwise": "oct2020_rest_of_day_pathwise_scaled_7000",
    "October 2020: the day-end forecast, pathwise": "oct2020_day_end_pathwise_scaled_7000",
    "October 2020: the paper's MPC, pathwise": "oct2020_paper_pathwise_scaled_7000",
    "October 2020: the paper's MPC, critic (default)": "oct2020_paper_critic_scaled_7000",
    "October 2020: the paper's MPC, critic, momentum reset at bounds":
        "oct2020_paper_critic_scaled_reset_7000",
    "December 2020: the rest of the day, pathwise": "dec2020_rest_of_day_pathwise_scaled_8000",
    "December 2020: the day-end forecast, pathwise": "dec2020_day_end_pathwise_scaled_8000",
    "December 2020: the paper's MPC, pathwise": "dec2020_paper_pathwise_scaled_8000",
    "October 2020: the rest of the day, pathwise, shipped month's scales":
        "oct2020_rest_of_day_pathwise_7000",
    "October 2020: the day-end forecast, pathwise, shipped month's scales":
        "oct2020_day_end_pathwise_7000",
    "October 2020: the paper's MPC, pathwise, shipped month's scales":
        "oct2020_paper_pathwise_7000",
    "October 2020: the paper's MPC, critic, shipped month's scales": "oct2020_paper_critic_7000",
    "October 2020: the paper's MPC, critic, shipped month's scales, momentum reset at bounds":
        "oct2020_paper_critic_reset_7000",
    "July 2020: the rest of the day, pathwise": "jul2020_rest_of_day_pathwise_9000",
    "July 2020: the day-end forecast, pathwise": "jul2020_day_end_pathwise_9000",
    "July 2020: the paper's MPC, pathwise": "jul2020_paper_pathwise_9000",
    "July 2020: the paper's MPC, critic (default)": "jul2020_paper_critic_9000",
    "September 2020: the rest of the day, pathwise": "sep2020_rest_of_day_pathwise_12000",
    "September 2020: the day-end forecast, pathwise": "sep2020_day_end_pathwise_12000",
    "September 2020: the paper's MPC, pathwise": "sep2020_paper_pathwise_12000",
    "September 2020: the rest of the day, pathwise, from November's class best":
        "sep2020_rest_of_day_pathwise_from_nov_12000",
    "September 2020: the day-end forecast, pathwise, from November's class best":
        "sep2020_day_end_pathwise_from_nov_12000",
    "September 2020: the paper's MPC, pathwise, from November's class best":
        "sep2020_paper_pathwise_from_nov_12000",
    "October 2020: the day-end forecast, pathwise, from November's class best":
        "oct2020_day_end_pathwise_from_nov_7000",
    "October 2020: the paper's MPC, pathwise, from November's class best":
        "oct2020_paper_pathwise_from_nov_7000",
    "December 2020: the day-end forecast, pathwise, from November's class best":
        "dec2020_day_end_pathwise_from_nov_8000",
    "December 2020: the paper's MPC, pathwise, from November's class best":
        "dec2020_paper_pathwise_from_nov_8000",
    "December 2020: the paper's MPC, critic (default), from November's class best":
        "dec2020_paper_critic_from_nov_8000",
    "December 2020: the rest of the day, pathwise, shipped month's scales":
        "dec2020_rest_of_day_pathwise_8000",
    "December 2020: the day-end forecast, pathwise, shipped month's scales":
        "dec2020_day_end_pathwise_8000",
    "December 2020: the paper's MPC, pathwise, shipped month's scales":
        "dec2020_paper_pathwise_8000",
}


@pytest.mark.parametrize("label", sorted(UNSEEN_ROWS))
def test_readme_quotes_the_studies_of_unseen_months(label):
    study, table = _study(UNSEEN_ROWS[label])
    split = study["class_split"]
    cells = _cells(label)
    assert cells[1] == _seed_span(study)
    assert cells[2] == f"{study['J_star']:.1f}"
    assert cells[3] == _median_iqr(study)
    assert cells[4] == f"{study['worst_seed']['J_eval_final']:.1f}"
    assert cells[5] == f"{int((table['gap_closed'] >= 0.95).sum())} / {study['done']}"
    assert cells[6] == f"{study['regret_median']:.1f}"
    assert cells[7] == f"{split['J_class']:.1f} / {split['J_class_eval']['mean']:.1f}"
    assert cells[8] == _gap_cell(split, "learner_gap_paired")


def _study(name: str) -> tuple[dict, Any]:
    """A stored study's summary and its table (a pandas DataFrame)."""
    import pandas as pd

    return _summary(name), pd.read_csv(STUDIES / name / "study.csv")


#: the pathwise studies of October and December 2020 with the month's step scales (the
#: default for a price file), and of July 2020 (run with that default)
OCT_DEC_PATHWISE = ("oct2020_rest_of_day_pathwise_scaled_7000",
                    "oct2020_day_end_pathwise_scaled_7000", "oct2020_paper_pathwise_scaled_7000",
                    "dec2020_rest_of_day_pathwise_scaled_8000",
                    "dec2020_day_end_pathwise_scaled_8000", "dec2020_paper_pathwise_scaled_8000")
JULY_PATHWISE = ("jul2020_rest_of_day_pathwise_9000", "jul2020_day_end_pathwise_9000",
                 "jul2020_paper_pathwise_9000")
SEPTEMBER_PATHWISE = ("sep2020_rest_of_day_pathwise_12000", "sep2020_day_end_pathwise_12000",
                      "sep2020_paper_pathwise_12000")


def _closed_and_late(studies: dict) -> tuple[int, str]:
    """The least share of the gap any run of ``studies`` (name -> (summary, table)) closes, in
    whole per cent rounded down, and the largest late loss, in per cent rounded up to 0.1, as
    README quotes them."""
    import math

    closed = min(float(table["gap_closed"].min()) for _, table in studies.values())
    late = max(max(v for v in study["late_regression_share"].values() if v is not None)
               for study, _ in studies.values())
    return math.floor(100 * closed), f"{math.ceil(1000 * late) / 10:.1f}"


def test_the_prose_on_unseen_months_is_the_stored_studies():
    """The paragraphs after README's tables of the October and December studies."""
    text = " ".join(README.split())
    pathwise = list(OCT_DEC_PATHWISE)
    studies = {name: _study(name) for name in pathwise}
    closed, late = _closed_and_late(studies)
    assert f"pathwise run closes at least {closed} % of the gap" in text
    assert f"none loses more than {late} % of it" in text
    kind = [study["class_split"]["J_class"] - study["class_split"]["J_class_eval"]["mean"]
            for study, _ in studies.values()]
    assert min(kind) > 0
    assert f"scores {min(kind):.0f} to {max(kind):.0f} NOK/day better on them" in text

    def regret(name: str) -> str:
        return f"{studies[name][0]['regret_median']:.1f}"

    def gap(name: str) -> float:
        return studies[name][0]["class_split"]["learner_gap_paired_median"]

    oct_, dec = [n for n in pathwise if "oct" in n], [n for n in pathwise if "dec" in n]
    assert (f"(regret {regret(oct_[0])} and {regret(oct_[1])} against {regret(oct_[2])} for the "
            f"paper's class in October, {regret(dec[0])} and {regret(dec[1])} against "
            f"{regret(dec[2])} in December)") in text
    best = [studies[n] for n in (oct_[0], dec[0])]
    assert all(s["regret_median"] <= 30 and (t["gap_closed"] >= 0.95).all() for s, t in best)
    assert all(gap(n) <= 10 for n in (oct_[0], dec[0]))
    assert (f"(regret {regret(oct_[0])} and {regret(dec[0])}, paired learner gap "
            f"{gap(oct_[0]):.1f} and {gap(dec[0]):.1f}, all 20 seeds close 95 % of the gap)"
            ) in text
    within = sum(gap(n) <= 10 for n in pathwise)
    over = sorted((n for n in pathwise if gap(n) > 10), key=gap)
    assert (within, over) == (4, ["dec2020_paper_pathwise_scaled_8000",
                                  "dec2020_day_end_pathwise_scaled_8000"])
    assert (f"10 NOK/day or less in four of the six class-months; it is {gap(over[0]):.1f} in the "
            f"paper's class and {gap(over[1]):.1f} in the day-end class in December") in text
    long, _ = _study("oct2020_day_end_pathwise_300m_7000")
    short, _ = _study("oct2020_day_end_pathwise_7000")
    assert (long["months"], long["done"], long["seeds"]) == (300, 6, list(range(7000, 7006)))
    assert (f"6 of its seeds run for 300 months end at a median of "
            f"{long['J_eval_final_median']:.1f}, against {short['J_eval_final_median']:.1f} for "
            "all 20 at month 100") in text
    # each class-month with the shipped month's scales, then with its own
    pairs = {"the rest-of-day gap from {} to {}": "oct2020_rest_of_day_pathwise",
             "the day-end gap from {} to {}": "oct2020_day_end_pathwise",
             "December day-end gap from {} to {}": "dec2020_day_end_pathwise",
             "the paper's class moves from {} to {} in October": "oct2020_paper_pathwise",
             "and from {} to {} in December": "dec2020_paper_pathwise"}
    for words, stem in pairs.items():
        seed = 7000 if stem.startswith("oct") else 8000
        before = _summary(f"{stem}_{seed}")["class_split"]["learner_gap_paired_median"]
        after = _summary(f"{stem}_scaled_{seed}")["class_split"]["learner_gap_paired_median"]
        assert words.format(f"{round(before, 1) + 0.0:.1f}", f"{after:.1f}") in text
    before = _summary("dec2020_rest_of_day_pathwise_8000")["class_split"]
    assert (f"December's rest of the day stays at {gap(dec[0]):.1f} "
            f"({before['learner_gap_paired_median']:.1f})") in text
    for name in ("oct2020_day_end_pathwise_scaled_7000", "oct2020_paper_pathwise_scaled_7000"):
        note = _summary(name)["note"]
        assert "2.3241971425734347" in note and "bit for bit" in note
        assert _config(name)["learning"]["scale_to_prices"] is True
    for name in pathwise[:1] + pathwise[3:]:  # made with the option itself
        assert _config(name)["learning"]["scale_to_prices"] is True and "note" not in _summary(name)
    for name in ("oct2020_rest_of_day_pathwise_7000", "dec2020_paper_pathwise_8000"):
        assert "scale_to_prices" not in _config(name)["learning"]  # before the option: False


def test_the_prose_on_july_is_the_stored_studies():
    """The paragraph on the third month, July 2020, run with today's defaults."""
    text = " ".join(README.split())
    pathwise = list(JULY_PATHWISE)
    studies = {name: _study(name) for name in pathwise}
    best, table = studies[pathwise[0]]
    gap = {name: study["class_split"]["learner_gap_paired_median"]
           for name, (study, _) in studies.items()}
    assert best["regret_median"] <= 30 and (table["gap_closed"] >= 0.95).all()
    assert (f"(regret {best['regret_median']:.1f}, paired learner gap {gap[pathwise[0]]:.1f}, "
            "all 20 seeds close 95 % of the gap)") in text
    assert (f"the paired gap is {gap[pathwise[1]]:.1f} in the day-end class and "
            f"{gap[pathwise[2]]:.1f} in the paper's") in text
    within = sum(_summary(n)["class_split"]["learner_gap_paired_median"] <= 10
                 for n in OCT_DEC_PATHWISE + JULY_PATHWISE)
    assert within == 7
    assert "10 NOK/day or less in seven of the nine class-months of the three months" in text
    closed, late = _closed_and_late(studies)
    assert (f"Every pathwise run closes at least {closed} % of the gap and "
            f"none loses more than {late} % of it") in text
    critic, critic_table = _study("jul2020_paper_critic_9000")
    assert critic["no_improvement_seeds"] == [] and critic["done"] == 20
    assert (critic_table["J_eval_final"] < critic_table["J_eval_nominal"]).all()
    split = critic["class_split"]
    assert (f"{split['learner_gap_paired_median']:.1f} NOK/day short of its class's best (worst "
            f"{split['learner_gap_paired_worst']['value']:.1f})") in text
    for name in [*pathwise, "jul2020_paper_critic_9000"]:
        config = _config(name)
        assert config["prices"]["month"] == "2020-07"
        assert config["learning"]["scale_to_prices"] is None  # the default: on for a file


def test_the_unseen_months_price_figures_are_those_of_the_export():
    """The mean buying prices and price levels README quotes for October, December and July
    2020 (NO3), read from Nord Pool's export as the studies read it."""
    if not NORD_POOL_2020.exists():
        pytest.skip(f"needs {NORD_POOL_2020} (Nord Pool's export; not in the project)")
    from mpcrl_lite.cli import inputs
    from mpcrl_lite.config import SystemConfig
    from mpcrl_lite.learning.dpg import price_level

    text = " ".join(README.split())
    month = {m: inputs.month_prices(NORD_POOL_2020, "NO3", m, SystemConfig(), None)
             for m in ("2020-10", "2020-12", "2020-07")}
    mean = {m: float(p.buy.mean()) for m, p in month.items()}
    level = {m: price_level(p) for m, p in month.items()}
    assert (f"mean prices {mean['2020-10']:.0f} and {mean['2020-12']:.0f} NOK/MWh "
            "against 56") in text
    assert (f"({level['2020-10']:.2f} and {level['2020-12']:.2f} here, {level['2020-07']:.2f} "
            "in July") in text
    assert (f"mean buying price {mean['2020-07']:.1f} NOK/MWh (price level "
            f"{level['2020-07']:.2f},") in text


def test_the_critic_on_october_is_the_stored_studies():
    """The seeds that never leave the nominal theta, and what the momentum reset changes, with
    the shipped month's step scales and with the month's own."""
    text = " ".join(README.split())
    default, plain = _study("oct2020_paper_critic_7000")
    reset, fixed = _study("oct2020_paper_critic_reset_7000")
    scaled, own = _study("oct2020_paper_critic_scaled_7000")
    both, own_reset = _study("oct2020_paper_critic_scaled_reset_7000")

    def stuck(table) -> set[int]:
        return set(table.loc[table["best_month"] == 0, "seed"])

    assert (f"gains most in its median ({scaled['J_eval_final_median']:.1f} against "
            f"{default['J_eval_final_median']:.1f})") in text
    assert (f"in October {len(stuck(own))} of the 20 seeds never leave the nominal theta "
            f"({len(stuck(plain))} with the shipped month's scales, J_eval "
            f"+{plain.loc[plain['best_month'] == 0, 'J_eval_final'].min():.0f} to "
            f"+{plain.loc[plain['best_month'] == 0, 'J_eval_final'].max():.0f} after 100 months)"
            ) in text
    freed = stuck(plain) - stuck(fixed)
    assert (f"With the shipped month's scales that option freed {len(freed)} of the "
            f"{len(stuck(plain))} (median {reset['J_eval_final_median']:.1f})") in text
    assert not stuck(own) - stuck(own_reset)
    assert (f"with the month's own it frees none and the median is "
            f"{both['J_eval_final_median']:.1f}") in text
    assert _config("oct2020_paper_critic_reset_7000")["learning"]["reset_momentum_at_bounds"]
    learning = _config("oct2020_paper_critic_scaled_reset_7000")["learning"]
    assert learning["reset_momentum_at_bounds"] and learning["scale_to_prices"]


def test_the_seeds_that_never_leave_the_start_are_those_the_stored_study_gives():
    """``study``'s ``no_improvement_seeds`` of the stored October critic study (summarized
    again from its table: the field is newer than the study), as benchmarks/README.md and
    README name them."""
    from mpcrl_lite.studies.study import summarize

    summary, table = _study("oct2020_paper_critic_scaled_7000")
    _, again = summarize(table, J_star=summary["J_star"])
    still = again["no_improvement_seeds"]
    assert still == [7000, 7007, 7017]
    finals = table.set_index("seed")["J_eval_final"]
    nominal = table["J_eval_nominal"].iloc[0]
    bench = " ".join((ROOT / "benchmarks" / "README.md").read_text().split())
    assert (f"seeds {still[0]}, {still[1]} and {still[2]} at a final J_eval of "
            f"{finals[still[0]]:.1f}, {finals[still[1]]:.1f} and {finals[still[2]]:.1f} "
            f"NOK/day against the nominal MPC's {nominal:.1f}") in bench
    assert f"(the October study above: {still[0]}, {still[1]}, {still[2]})" in bench
    text = " ".join(README.split())
    assert f"with the paper's critic on October 2020, {len(still)} of 20 seeds never left" in text


#: benchmarks/README.md's table of the months never used: row label -> stored study
BENCH_UNSEEN_ROWS = {
    "October, paper, pathwise": "oct2020_paper_pathwise_7000",
    "October, day-end, pathwise": "oct2020_day_end_pathwise_7000",
    "October, rest of the day, pathwise": "oct2020_rest_of_day_pathwise_7000",
    "October, paper, critic (default)": "oct2020_paper_critic_7000",
    "October, paper, critic, `--reset-momentum-at-bounds`": "oct2020_paper_critic_reset_7000",
    "December, paper, pathwise": "dec2020_paper_pathwise_8000",
    "December, day-end, pathwise": "dec2020_day_end_pathwise_8000",
    "December, rest of the day, pathwise": "dec2020_rest_of_day_pathwise_8000",
    "October, rest of the day, pathwise, month's scales": "oct2020_rest_of_day_pathwise_scaled_7000",
    "October, day-end, pathwise, month's scales": "oct2020_day_end_pathwise_scaled_7000",
    "October, paper, pathwise, month's scales": "oct2020_paper_pathwise_scaled_7000",
    "October, paper, critic (default), month's scales": "oct2020_paper_critic_scaled_7000",
    "October, paper, critic, month's scales, `--reset-momentum-at-bounds`":
        "oct2020_paper_critic_scaled_reset_7000",
    "December, paper, pathwise, month's scales": "dec2020_paper_pathwise_scaled_8000",
    "December, day-end, pathwise, month's scales": "dec2020_day_end_pathwise_scaled_8000",
    "December, rest of the day, pathwise, month's scales":
        "dec2020_rest_of_day_pathwise_scaled_8000",
}


@pytest.mark.parametrize("label", sorted(BENCH_UNSEEN_ROWS))
def test_the_benchmarks_table_of_unseen_months_is_the_stored_one(label):
    row = bench_row(label)
    study, _ = _study(BENCH_UNSEEN_ROWS[label])
    split = study["class_split"]
    low, high = study["J_eval_final_iqr"]
    plow, phigh = split["learner_gap_paired_iqr"]
    assert row == (
        f"| {label} | {study['J_star']:.1f} | {study['J_eval_final_median']:.1f} ({low:.1f} to "
        f"{high:.1f}) | {split['J_class']:.1f} / {split['J_class_eval']['mean']:.1f} | "
        f"{split['learner_gap_paired_median']:.1f} ({plow:.1f} to {phigh:.1f}), "
        f"{split['learner_gap_paired_worst']['value']:.1f} | {study['regret_median']:.1f} |")


def test_the_benchmarks_prose_on_unseen_months_is_the_stored_one():
    text = " ".join((ROOT / "benchmarks" / "README.md").read_text().split())
    first = [name for name in BENCH_UNSEEN_ROWS.values()
             if "pathwise" in name and "scaled" not in name]  # the shipped month's scales
    held = [_study(name)[0]["class_split"]["learner_gap_median"] for name in first]
    assert f"The held-out figures say otherwise ({min(held):.1f} to {max(held):.1f})" in text
    spread = [json.loads((ROOT / _study(name)[0]["class_split"]["source"] / "tune.json")
                         .read_text())["J_heldout"]["std"] for name in first]
    assert 80 <= min(spread) and max(spread) <= 115
    assert "their standard deviation over draws is 80-115 NOK/day here" in text
    shipped = [_gap(name, "learner_gap_paired_median") for name in
               ("paper_pathwise_5000", "day_end_pathwise_5000", "rest_of_day_pathwise_5000")]
    assert f"On the shipped month it is {min(shipped):.1f} to {max(shipped):.1f}" in text
    labelled = [name for name in first if "paper" not in name]
    closed = min(float(_study(name)[1]["gap_closed"].min()) for name in labelled)
    assert f"(the labelled classes at least {int(100 * closed)} %)" in text
    # each class-month: the paired gap and the median final J, before -> with the month's scales
    fell = improved = 0
    for name in first:
        plain = _study(name)[0]
        scaled = _study(name.replace("_7000", "_scaled_7000").replace("_8000", "_scaled_8000"))[0]
        before = plain["class_split"]["learner_gap_paired_median"]
        after = scaled["class_split"]["learner_gap_paired_median"]
        j0, j1 = plain["J_eval_final_median"], scaled["J_eval_final_median"]
        fell += after < before
        improved += round(j1, 1) < round(j0, 1)
        gaps = f"{round(before, 1) + 0.0:.1f} -> {after:.1f}"
        js = f"{j0:.1f} -> {j1:.1f}" if round(j0, 1) != round(j1, 1) else f"{j0:.1f} both"
        assert gaps in text and js in text, (name, gaps, js)
    assert (fell, improved) == (4, 4)
    assert ("the pathwise learner's paired gap fell in four of the six class-months and its "
            "median final J improved in four") in text
    critic, scaled = (_study(n)[0] for n in ("oct2020_paper_critic_7000",
                                              "oct2020_paper_critic_scaled_7000"))
    assert (f"The critic's median: {critic['J_eval_final_median']:.1f} -> "
            f"{scaled['J_eval_final_median']:.1f}") in text
    both = _study("oct2020_paper_critic_scaled_reset_7000")[0]
    assert (f"median {both['J_eval_final_median']:.1f} against "
            f"{scaled['J_eval_final_median']:.1f}") in text


def test_notebook_09_quotes_the_paired_gaps_of_unseen_months():
    gaps = [_study(name)[0]["class_split"]["learner_gap_paired_median"]
            for name in OCT_DEC_PATHWISE + JULY_PATHWISE + SEPTEMBER_PATHWISE]
    notebook = " ".join(NOTEBOOK_09.split())
    assert len(gaps) == 12 and sum(g <= 10 for g in gaps) == 8
    assert ("On four months on which nothing was chosen, October, December, July and September "
            "2020") in notebook
    assert (f"pathwise gaps are between {round(min(gaps)) + 0:d} and {round(max(gaps)):d} "
            "NOK/day over the classes, 10 or less in eight of the twelve") in notebook
    assert min(gaps) > -0.5 and max(gaps) > 10
    started = [_summary(FROM_NOVEMBER[c][1])["class_split"]["learner_gap_paired_median"]
               for c in ("day_end", "paper", "rest_of_day")]
    assert ("started at November's class best instead of the nominal $\\theta$ "
            "(`learn --theta0`), the paired gaps of the three classes are "
            f"{started[0]:.1f}, {started[1]:.1f} and {started[2]:.1f} NOK/day") in notebook


def test_the_segments_are_of_the_stored_studies_and_quoted():
    """``segments_2020.jsonl`` (``tools/theta_segment.py``): each segment ends at the class's
    best theta on the runs' draws, which the study scored too, and the rises are quoted."""
    segments = [json.loads(line) for line in
                (STUDIES / "segments_2020.jsonl").read_text().splitlines()]
    assert len(segments) == 33
    rises: dict[str, list[float]] = {}
    for seg in segments:
        study, _ = _study(seg["study"])
        assert seg["J_end"] == pytest.approx(study["class_split"]["J_class_eval"]["mean"],
                                             rel=1e-9)
        assert seg["rise"] == pytest.approx(max(seg["J"]) - max(seg["J_start"], seg["J_end"]))
        assert seg["run_seed"] in study["seeds"] and len(seg["t"]) == 11
        rises.setdefault(seg["study"], []).append(seg["rise"])
    bench = (ROOT / "benchmarks" / "README.md").read_text()
    labels = {"oct2020_paper_pathwise_7000": "October, paper, pathwise",
              "oct2020_day_end_pathwise_7000": "October, day-end, pathwise",
              "oct2020_rest_of_day_pathwise_7000": "October, rest of the day, pathwise",
              "dec2020_paper_pathwise_8000": "December, paper, pathwise",
              "dec2020_day_end_pathwise_8000": "December, day-end, pathwise",
              "dec2020_rest_of_day_pathwise_8000": "December, rest of the day, pathwise"}
    for name, label in labels.items():
        assert (f"| {label} (segment) | {min(rises[name]):.1f} to {max(rises[name]):.1f} |"
                in bench)
    # the labelled classes whose learner gap is large: both in October, day-end in December
    basins = [r for name in ("oct2020_day_end_pathwise_7000", "oct2020_rest_of_day_pathwise_7000",
                             "dec2020_day_end_pathwise_8000") for r in rises[name]]
    text = " ".join(README.split())
    assert (f"J rises by {math.floor(min(basins)):d} to {round(max(basins)):d} NOK/day in "
            "the labelled classes where the gap was large") in text
    near = rises["dec2020_rest_of_day_pathwise_8000"]
    assert f"In the rest-of-day class in December it rises by {math.ceil(max(near))} at most" in text
    assert max(rises["dec2020_paper_pathwise_8000"]) == 0.0
    bench_text = " ".join(bench.split())
    assert f"rises by {math.floor(min(basins)):d} NOK/day or more half-way" in bench_text
    assert f"it rises by {math.ceil(max(near))} at most" in bench_text
    scaled = rises["dec2020_day_end_pathwise_scaled_8000"]
    assert len(scaled) == 3
    assert (f"| December, day-end, pathwise, month's scales (segment; seeds 8000-8002) | "
            f"{min(scaled):.1f} to {max(scaled):.1f} |") in bench
    assert (f"where the ridge on the way to the best is now {math.floor(min(scaled))} to "
            f"{round(max(scaled))} NOK/day high (3 seeds)") in text
    october = rises["oct2020_paper_pathwise_7000"]
    assert f"a ridge of {round(min(october))} to {round(max(october))} NOK/day" in bench_text


#: benchmarks/README.md's table of the Q-learner with and without the step limit
Q_LIMIT = {("7000-7009", "none"): ("unlimited_7000", 7000, 7009),
           ("7010-7029", "none"): ("unlimited_7010", 7010, 7029),
           ("7000-7009", "5"): ("limited_7000", 7000, 7009),
           ("7010-7029", "5"): ("limited_7000", 7010, 7029)}


def _q_limit_runs(name: str, low: int, high: int):
    """The final J_eval per seed and the month each run collapsed in (or None)."""
    import pandas as pd

    folder = STUDIES / "q_step_limit" / name
    table = pd.read_csv(folder / "study.csv").set_index("seed").loc[low:high]
    collapse = json.loads((folder / "collapse.json").read_text())["first_month"]
    config = json.loads(next(folder.glob("config_seed*.json")).read_text())["learning"]
    return table["J_eval_final"], [collapse[str(s)] for s in table.index], config


@pytest.mark.parametrize("key", sorted(Q_LIMIT))
def test_the_q_step_limit_table_is_the_stored_studies(key):
    seeds, limit = key
    final, collapsed, config = _q_limit_runs(*Q_LIMIT[key])
    assert config["learner"] == "q" and config.get("step_limit", 0.0) == (
        0.0 if limit == "none" else float(limit))
    n = len(final)
    assert bench_row(seeds + " | " + limit) == (
        f"| {seeds} | {limit} | {sum(c is not None for c in collapsed)} of {n} | "
        f"{int((final <= -150).sum())} of {n} | {int((final > 266.3).sum())} of {n} | "
        f"{final.median():.1f} |")


def test_readme_quotes_the_q_step_limit_studies():
    text = " ".join(README.split())
    without = [_q_limit_runs(*Q_LIMIT[(s, "none")]) for s in ("7000-7009", "7010-7029")]
    limited = [_q_limit_runs(*Q_LIMIT[(s, "5")]) for s in ("7000-7009", "7010-7029")]

    def count(runs, test) -> int:
        return sum(int(test(final, collapsed)) for final, collapsed, _ in runs)

    ran_away = count(without, lambda f, c: sum(m is not None for m in c))
    good = count(limited, lambda f, c: (f <= -150).sum())
    good_without = count(without, lambda f, c: (f <= -150).sum())
    worse = count(limited, lambda f, c: (f > 266.3).sum())
    worse_without = count(without, lambda f, c: (f > 266.3).sum())
    worst = max(float(f.max()) for f, _, _ in limited)
    assert count(limited, lambda f, c: sum(m is not None for m in c)) == 0
    assert (f"{ran_away} of 30 fresh Q-learning runs (seeds 7000-7029, 100 months) ran away"
            in text)
    assert (f"with `--step-limit 5` none did, and {good} of 30 ended at -150 NOK/day or better, "
            f"against {good_without} without; but {worse} ended worse than idling (up to "
            f"+{worst:.0f}, against {worse_without} without)") in text


def test_the_prose_on_the_fourth_month_is_the_stored_studies():
    """README's paragraph on September 2020: the best labelled class's targets, the learner
    gaps of the other two, the count of class-months within 10 NOK/day over the four months
    and the least share of the gap a September run closed."""
    import math

    text = " ".join(README.split())
    studies = {name: _study(name) for name in SEPTEMBER_PATHWISE}
    rest, table = studies["sep2020_rest_of_day_pathwise_12000"]
    closed = float(table["gap_closed"].min())
    late = max(v for v in rest["late_regression_share"].values() if v is not None)
    assert closed >= 0.95 and late <= 0.05 and rest["regret_median"] <= 30.0
    assert (f"median regret {rest['regret_median']:.1f}, every seed closes at least "
            f"{math.floor(1000 * closed) / 10:.1f} % of the gap, none loses more than "
            f"{math.ceil(1000 * late) / 10:.1f} % of it after its best evaluation, paired learner "
            f"gap {rest['class_split']['learner_gap_paired_median']:.1f}") in text
    day_end = studies["sep2020_day_end_pathwise_12000"][0]["class_split"]
    paper = studies["sep2020_paper_pathwise_12000"][0]["class_split"]
    assert (f"{day_end['learner_gap_paired_median']:.1f} paired "
            f"({day_end['learner_gap_median']:.1f} held out) in the day-end class and "
            f"{paper['learner_gap_paired_median']:.1f} paired ({paper['learner_gap_median']:.1f} "
            "held out) in the paper's") in text
    months = (*OCT_DEC_PATHWISE, *JULY_PATHWISE, *SEPTEMBER_PATHWISE)
    within = sum(_gap(name, "learner_gap_paired_median") <= 10.0 for name in months)
    words = {8: "eight", 9: "nine", 10: "ten", 11: "eleven", 12: "twelve"}
    assert (f"the paired gap is 10 NOK/day or less in {words[within]} of the "
            f"{words[len(months)]} class-months") in text
    least = min(float(t["gap_closed"].min()) for _, t in studies.values())
    assert (f"Every pathwise run of September closes at least {math.floor(100 * least)} % of "
            "the gap") in text


#: September 2020 from the nominal start and from November's class best, per class
FROM_NOVEMBER = {c: (f"sep2020_{c}_pathwise_12000", f"sep2020_{c}_pathwise_from_nov_12000")
                 for c in ("day_end", "paper", "rest_of_day")}


def _from_november(name: str, nominal_name: str, c: str, month: str) -> dict[str, Any]:
    """A study started at November's class best of class ``c`` on ``month``, against the same
    study from the nominal start: checks that it started there (summary and run config), that
    the start was searched on the shipped month, that it ran the nominal study's learner and
    month, and that its gap still counts from the same nominal J; returns its paired gap
    (``gap``), the nominal start's (``nominal_gap``), the seeds it ended lower on (``better``),
    its start's J less the class's best on the runs' draws (``ahead``), its ``summary`` and
    ``table``."""
    summary, table = _study(name)
    nominal = _summary(nominal_name)
    tune = json.loads((ROOT / f"data/class_best_{c}/tune.json").read_text())
    start = [float(x) for x in Theta.from_dict(tune["theta_best"]).to_vector()]
    config, nominal_config = _config(name), _config(nominal_name)
    assert summary["theta0"] == config["learning"]["theta0"] == start
    assert config["prices"]["month"] == month
    # the start was not chosen on the month: the search behind it ran on the shipped month
    assert "November 2020" in tune["prices"] and month not in tune["prices"]
    assert config["learning"].get("gradient", "critic") == \
        nominal_config["learning"].get("gradient", "critic")
    # the gap still counts from the nominal MPC: the same J_nominal as the nominal start's
    assert summary["J_nominal"] == pytest.approx(nominal["J_nominal"], rel=1e-12)
    starts = table["J_eval_start"].unique()
    assert len(starts) == 1  # every seed starts at the same theta on the same draws
    mine, theirs = (s["class_split"]["learner_gap_paired"] for s in (summary, nominal))
    return {"gap": summary["class_split"]["learner_gap_paired_median"],
            "nominal_gap": nominal["class_split"]["learner_gap_paired_median"],
            "better": sum(mine[k] < theirs[k] for k in mine),
            "ahead": starts[0] - summary["class_split"]["J_class_eval"]["mean"],
            "summary": summary, "table": table}


def test_the_november_start_on_september_is_the_stored_studies():
    """README's paragraph "Starting from another month's best": every figure from the stored
    summaries, and the runs did start at November's class best."""
    text = " ".join(README.split())
    runs = {c: _from_november(name, nominal_name, c, "2020-09")
            for c, (nominal_name, name) in FROM_NOVEMBER.items()}
    assert max(r["gap"] for r in runs.values()) <= 10  # "within 10 NOK/day ... in all three"
    de, pa, rd = runs["day_end"], runs["paper"], runs["rest_of_day"]
    assert (f"paired learner gap {de['gap']:.1f} in the day-end class ({de['nominal_gap']:.1f} "
            f"from the nominal start, lower on {de['better']} of 20 seeds), {pa['gap']:.1f} in "
            f"the paper's ({pa['nominal_gap']:.1f}, lower on {pa['better']} of 20) and "
            f"{rd['gap']:.1f} in the rest of the day ({rd['nominal_gap']:.1f})") in text
    assert (f"The day-end regret falls from "
            f"{_summary(FROM_NOVEMBER['day_end'][0])['regret_median']:.1f} to "
            f"{de['summary']['regret_median']:.1f}") in text
    assert (f"November's best already starts {pa['ahead']:.1f} NOK/day above September's on "
            f"the runs' draws, and {pa['summary']['no_improvement_count']} of the 20 runs end "
            "no better than that start") in text
    closed, late = _closed_and_late({c: (r["summary"], r["table"]) for c, r in runs.items()})
    assert f"Every run closes at least {closed} % of the gap from the nominal theta to J*" in text
    assert f"none loses more than {late} % of it after its best evaluation" in text
    worst = rd["summary"]["class_split"]["learner_gap_paired_worst"]
    assert rd["summary"]["largest_late_regression"]["seed"] == worst["seed"]
    assert (f"(rest of the day, seed {worst['seed']}: its final evaluation is "
            f"{worst['value']:.1f} above the class's best)") in text


#: December 2020 from November's class best: stored study -> (the nominal start's, class)
DECEMBER_FROM_NOVEMBER = {
    "dec2020_day_end_pathwise_from_nov_8000": ("dec2020_day_end_pathwise_scaled_8000", "day_end"),
    "dec2020_paper_pathwise_from_nov_8000": ("dec2020_paper_pathwise_scaled_8000", "paper"),
    "dec2020_paper_critic_from_nov_8000": ("dec2020_paper_critic_8000", "paper"),
}


def test_the_november_start_on_december_is_the_stored_studies():
    text = " ".join(README.split())
    de, pa, critic = (_from_november(name, nominal_name, c, "2020-12")
                      for name, (nominal_name, c) in DECEMBER_FROM_NOVEMBER.items())
    assert (f"paired learner gap {de['gap']:.1f} in the day-end class ({de['nominal_gap']:.1f} "
            f"from the nominal start, lower on {de['better']} of 20 seeds) and {pa['gap']:.1f} "
            f"in the paper's ({pa['nominal_gap']:.1f}, lower on {pa['better']} of 20)") in text
    # the four class-months that missed from the nominal start, and the other eight
    nominal_gaps = {name: _summary(name)["class_split"]["learner_gap_paired_median"]
                    for name in OCT_DEC_PATHWISE + JULY_PATHWISE + SEPTEMBER_PATHWISE}
    missed = sorted(name for name, gap in nominal_gaps.items() if gap > 10)
    assert missed == ["dec2020_day_end_pathwise_scaled_8000", "dec2020_paper_pathwise_scaled_8000",
                      "sep2020_day_end_pathwise_12000", "sep2020_paper_pathwise_12000"]
    again = [de["gap"], pa["gap"]] + [
        _summary(FROM_NOVEMBER[c][1])["class_split"]["learner_gap_paired_median"]
        for c in ("day_end", "paper")]
    assert max(again) <= 10
    assert ("So the four class-months that missed 10 NOK/day from the nominal start are all "
            "within it from November's; the other eight were within it from the nominal start") \
        in text
    # the critic leaves its good start on every seed, but never falls back to the nominal level
    summary, table = critic["summary"], critic["table"]
    assert summary["no_improvement_count"] == 20
    assert (table["J_eval_final"] < table["J_eval_nominal"]).all()
    assert _summary("dec2020_paper_critic_8000")["class_split"]["learner_gap_paired_median"] > 1000
    assert (f"from November's best, {critic['ahead']:.1f} NOK/day above December's on the "
            "runs' draws, every one of its 20 runs ends worse than it began (median paired gap "
            f"{critic['gap']:.1f}), though none ends at the nominal MPC's level") in text


def test_the_november_start_on_october_is_the_stored_studies():
    """README's two October rows run again from November's class best, where the nominal start
    was within 10 NOK/day already."""
    text = " ".join(README.split())
    de, pa = (_from_november(f"oct2020_{c}_pathwise_from_nov_7000",
                             f"oct2020_{c}_pathwise_scaled_7000", c, "2020-10")
              for c in ("day_end", "paper"))
    assert de["nominal_gap"] <= 10 and pa["nominal_gap"] <= 10  # within it already
    assert (f"October's day-end and paper classes from November's start end at "
            f"{de['gap']:.1f} ({de['nominal_gap']:.1f} from the nominal start, lower on "
            f"{de['better']} of 20 seeds) and {pa['gap']:.1f} ({pa['nominal_gap']:.1f}, lower "
            f"on {pa['better']} of 20)") in text
    assert pa["ahead"] < 0  # November's best scores better than October's own class best there
    assert (f"November's best already scores {-pa['ahead']:.1f} NOK/day better than October's "
            f"own class best on the runs' draws, and {pa['summary']['no_improvement_count']} of "
            "the 20 paper-class runs end no better than that start") in text
