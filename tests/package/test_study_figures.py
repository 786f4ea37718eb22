"""The study figures README.md and notebook 09 quote are those of the stored study summaries
(benchmarks/studies/*/study.json): median and IQR of the final J_eval, worst seed, seeds
converged, median regret and the learner's part of it, each rounded as quoted."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

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


def _summary(name: str) -> dict[str, Any]:
    """The ``study.json`` of the stored study ``name``."""
    return json.loads((STUDIES / name / "study.json").read_text())


def _config(name: str) -> dict[str, Any]:
    """The stored run configuration (``config_seed*.json``) of the stored study ``name``."""
    return json.loads(next((STUDIES / name).glob("config_seed*.json")).read_text())


def _row(label: str) -> str:
    rows = [line for line in README.splitlines() if line.startswith(f"| {label}")]
    assert len(rows) == 1, f"README has {len(rows)} rows starting with {label!r}"
    return rows[0]


@pytest.mark.parametrize("name", sorted(ROWS))
def test_readme_quotes_the_stored_study(name):
    study = _summary(name)
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


def test_the_paired_gap_and_the_second_fresh_judgement_are_the_stored_ones():
    """The paragraph after README's results table: the class's best on both sets of draws and
    the paper class on the seeds 6000-6019."""
    text = " ".join(README.split())
    first = _summary("paper_pathwise_5000")
    split = first["class_split"]
    assert f"held-out draws it has J = {split['J_class']:.1f}" in text
    assert f"it has {split['J_class_eval']['mean']:.1f}." in text
    assert split["J_class_eval"]["draws"] == 10 and first["eval_draws"] == 10
    study = _summary("paper_pathwise_6000")
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


def _bench_row(label: str) -> str:
    """The one row of a table in benchmarks/README.md whose first cell is ``label``."""
    text = (ROOT / "benchmarks" / "README.md").read_text()
    rows = [line for line in text.splitlines() if line.startswith(f"| {label} |")]
    assert len(rows) == 1, f"benchmarks/README.md has {len(rows)} rows {label!r}"
    return rows[0]


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
    row = _bench_row(label)
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
          "oct2020_paper_pathwise_scaled_7000": "oct2020_class_best_paper"}
#: stored study -> the tune result its class split was made against
CLASS_BEST = {"paper_pathwise_5000": "data/class_best_paper",
              "paper_pathwise_6000": "data/class_best_paper",
              "paper_critic_5000": "data/class_best_paper",
              "day_end_pathwise_5000": "data/class_best_day_end",
              "rest_of_day_pathwise_5000": "data/class_best_rest_of_day",
              "rest_of_day_pathwise_scale100_5000": "data/class_best_rest_of_day",
              "rest_of_day_critic_4000": "data/class_best_rest_of_day",
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
    "October 2020: the rest of the day, pathwise": "oct2020_rest_of_day_pathwise_7000",
    "October 2020: the day-end forecast, pathwise": "oct2020_day_end_pathwise_7000",
    "October 2020: the paper's MPC, pathwise": "oct2020_paper_pathwise_7000",
    "October 2020: the paper's MPC, critic (default)": "oct2020_paper_critic_7000",
    "October 2020: the paper's MPC, critic, momentum reset at bounds":
        "oct2020_paper_critic_reset_7000",
    "December 2020: the rest of the day, pathwise": "dec2020_rest_of_day_pathwise_8000",
    "December 2020: the day-end forecast, pathwise": "dec2020_day_end_pathwise_8000",
    "December 2020: the paper's MPC, pathwise": "dec2020_paper_pathwise_8000",
}


@pytest.mark.parametrize("label", sorted(UNSEEN_ROWS))
def test_readme_quotes_the_studies_of_unseen_months(label):
    study, table = _study(UNSEEN_ROWS[label])
    split = study["class_split"]
    cells = [cell.strip() for cell in _row(label).strip("|").split("|")]
    seeds = sorted(int(s) for s in split["learner_gap"])
    assert cells[1] == f"{seeds[0]}-{seeds[-1]}"
    assert cells[2] == f"{study['J_star']:.1f}"
    low, high = study["J_eval_final_iqr"]
    assert cells[3] == f"{study['J_eval_final_median']:.1f} ({low:.1f} to {high:.1f})"
    assert cells[4] == f"{study['worst_seed']['J_eval_final']:.1f}"
    assert cells[5] == f"{int((table['gap_closed'] >= 0.95).sum())} / {study['done']}"
    assert cells[6] == f"{study['regret_median']:.1f}"
    assert cells[7] == f"{split['J_class']:.1f} / {split['J_class_eval']['mean']:.1f}"
    low, high = split["learner_gap_paired_iqr"]
    assert cells[8] == (f"{split['learner_gap_paired_median']:.1f} ({low:.1f} to {high:.1f}), "
                        f"worst {split['learner_gap_paired_worst']['value']:.1f}")


def _study(name: str) -> tuple[dict, Any]:
    """A stored study's summary and its table (a pandas DataFrame)."""
    import pandas as pd

    return _summary(name), pd.read_csv(STUDIES / name / "study.csv")


def test_the_prose_on_unseen_months_is_the_stored_studies():
    """The paragraph after README's table of the October and December studies."""
    import math

    text = " ".join(README.split())
    pathwise = ["oct2020_rest_of_day_pathwise_7000", "oct2020_day_end_pathwise_7000",
                "oct2020_paper_pathwise_7000", "dec2020_rest_of_day_pathwise_8000",
                "dec2020_day_end_pathwise_8000", "dec2020_paper_pathwise_8000"]
    studies = [_study(name) for name in pathwise]
    closed = min(float(table["gap_closed"].min()) for _, table in studies)
    late = max(max(study["late_regression_share"].values()) for study, _ in studies)
    assert f"pathwise run closes at least {math.floor(100 * closed)} % of the gap" in text
    assert f"none loses more than {math.ceil(1000 * late) / 10:.1f} % of it" in text
    kind = [study["class_split"]["J_class"] - study["class_split"]["J_class_eval"]["mean"]
            for study, _ in studies]
    assert min(kind) > 0
    assert f"scores {min(kind):.0f} to {max(kind):.0f} NOK/day better on them" in text
    long, _ = _study("oct2020_day_end_pathwise_300m_7000")
    short, _ = _study("oct2020_day_end_pathwise_7000")
    assert (long["months"], long["done"], long["seeds"]) == (300, 6, list(range(7000, 7006)))
    assert (f"6 of its seeds run for 300 months end at a median of "
            f"{long['J_eval_final_median']:.1f}, against {short['J_eval_final_median']:.1f} for "
            "all 20 at month 100") in text
    scaled_words = {"oct2020_day_end_pathwise_scaled_7000": "narrow the October day-end gap to {:.1f}",
                    "oct2020_paper_pathwise_scaled_7000": "widen the paper class's to {:.1f}"}
    for name, words in scaled_words.items():
        study, _ = _study(name)
        assert "2.3241971425734347" in study["note"]
        assert words.format(study["class_split"]["learner_gap_paired_median"]) in text


def test_the_critic_on_october_is_the_stored_studies():
    """The seeds that never leave the nominal theta, and what the momentum reset changes."""
    text = " ".join(README.split())
    default, plain = _study("oct2020_paper_critic_7000")
    reset, fixed = _study("oct2020_paper_critic_reset_7000")
    stuck = plain[plain["best_month"] == 0]
    assert (f"{len(stuck)} of the 20 seeds never leave the nominal theta (J_eval "
            f"+{stuck['J_eval_final'].min():.0f} to +{stuck['J_eval_final'].max():.0f} after 100 "
            "months)") in text
    freed = set(stuck["seed"]) - set(fixed.loc[fixed["best_month"] == 0, "seed"])
    better = int((fixed.set_index("seed")["J_eval_final"]
                  < plain.set_index("seed")["J_eval_final"]).sum())
    assert (f"With that option {len(freed)} of the {len(stuck)} learn, the median is "
            f"{reset['J_eval_final_median']:.1f} instead of {default['J_eval_final_median']:.1f} "
            f"and {better} of the 20 seeds end better") in text
    config = _config("oct2020_paper_critic_reset_7000")
    assert config["learning"]["reset_momentum_at_bounds"] is True


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
}


@pytest.mark.parametrize("label", sorted(BENCH_UNSEEN_ROWS))
def test_the_benchmarks_table_of_unseen_months_is_the_stored_one(label):
    row = _bench_row(label)
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
    pathwise = [name for name in BENCH_UNSEEN_ROWS.values() if "pathwise" in name]
    held = [_study(name)[0]["class_split"]["learner_gap_median"] for name in pathwise]
    assert f"The held-out figures say otherwise ({min(held):.1f} to {max(held):.1f})" in text
    spread = [json.loads((ROOT / _study(name)[0]["class_split"]["source"] / "tune.json")
                         .read_text())["J_heldout"]["std"] for name in pathwise]
    assert 80 <= min(spread) and max(spread) <= 115
    assert "their standard deviation over draws is 80-115 NOK/day here" in text
    shipped = [_gap(name, "learner_gap_paired_median") for name in
               ("paper_pathwise_5000", "day_end_pathwise_5000", "rest_of_day_pathwise_5000")]
    assert f"On the shipped month it is {min(shipped):.1f} to {max(shipped):.1f}" in text
    labelled = [name for name in pathwise if "paper" not in name]
    closed = min(float(_study(name)[1]["gap_closed"].min()) for name in labelled)
    assert f"(the labelled classes at least {int(100 * closed)} %)" in text
    scaled_words = {
        "oct2020_day_end_pathwise_scaled_7000": "day-end {} (IQR {} to {}), paired gap {} instead of {}",
        "oct2020_paper_pathwise_scaled_7000": "paper {} ({} to {}), paired gap {} instead of {}",
    }
    for name, words in scaled_words.items():
        scaled = _study(name)[0]
        plain = _study(name.replace("_scaled", ""))[0]
        low, high = scaled["J_eval_final_iqr"]
        assert words.format(*(f"{round(v, 1) + 0.0:.1f}" for v in (  # no "-0.0"
            scaled["J_eval_final_median"], low, high,
            scaled["class_split"]["learner_gap_paired_median"],
            plain["class_split"]["learner_gap_paired_median"]))) in text


def test_notebook_09_quotes_the_paired_gaps_of_unseen_months():
    gaps = [_study(name)[0]["class_split"]["learner_gap_paired_median"]
            for name in BENCH_UNSEEN_ROWS.values() if "pathwise" in name]
    notebook = " ".join(NOTEBOOK_09.split())
    assert (f"pathwise gaps are between {round(min(gaps)) + 0:d} and {round(max(gaps)):d} "
            "NOK/day over the classes") in notebook
    assert min(gaps) > -0.5 and max(gaps) > 10


def test_the_segments_are_of_the_stored_studies_and_quoted():
    """``segments_2020.jsonl`` (``tools/theta_segment.py``): each segment ends at the class's
    best theta on the runs' draws, which the study scored too, and the rises are quoted."""
    segments = [json.loads(line) for line in
                (STUDIES / "segments_2020.jsonl").read_text().splitlines()]
    assert len(segments) == 30
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
            "the labelled classes where the gap is large") in text
    near = rises["dec2020_rest_of_day_pathwise_8000"]
    assert f"In the rest-of-day class in December it rises by {math.ceil(max(near))} at most" in text
    assert max(rises["dec2020_paper_pathwise_8000"]) == 0.0
    bench_text = " ".join(bench.split())
    assert f"rises by {math.floor(min(basins)):d} NOK/day or more half-way" in bench_text
    assert f"it rises by {math.ceil(max(near))} at most" in bench_text
    october = rises["oct2020_paper_pathwise_7000"]
    assert f"a ridge of {round(min(october))} to {round(max(october))} NOK/day" in bench_text
