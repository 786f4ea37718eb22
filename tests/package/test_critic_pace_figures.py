"""The figures of "The critic's learner gap: its pace and its estimate" (``benchmarks/README.md``)
and README's sentences on it are those of the stored studies and runs
(``benchmarks/studies/``): the critic started at its class's best, the exact gradient at the
critic's pace on the fresh seeds 14000-14019, and the screen of wider paces on 13000-13009."""

from __future__ import annotations

import importlib.util
import json
import statistics
from pathlib import Path

import pytest
from bench_readme import BENCH_README, bench_row

ROOT = Path(__file__).resolve().parents[2]
STUDIES = ROOT / "benchmarks" / "studies"
SCREEN = STUDIES / "critic_pace_screen_13000"
FROM_BEST = STUDIES / "from_class_best_13010"
README = " ".join((ROOT / "README.md").read_text().split())
BENCH = " ".join(BENCH_README.read_text().split())

#: the table of the 20 fresh seeds: row label -> stored study
FRESH_ROWS = {
    "critic (the default)": "paper_critic_14000",
    "pathwise, terminal scale 100 (the critic's)": "paper_pathwise_terminal100_14000",
    "pathwise, terminal scale 3000 (its default)": "paper_pathwise_14000",
    "critic, terminal scale 3000, step decay 25": "paper_critic_terminal3000_decay25_14000",
}
#: what each of those studies ran: (gradient, Adam's terminal scale, step decay)
FRESH_OPTIONS = {
    "critic (the default)": ("critic", 100.0, 0),
    "pathwise, terminal scale 100 (the critic's)": ("pathwise", 100.0, 0),
    "pathwise, terminal scale 3000 (its default)": ("pathwise", 3000.0, 0),
    "critic, terminal scale 3000, step decay 25": ("critic", 3000.0, 25),
}
#: the screen's table: row label -> folder of SCREEN
SCREEN_ROWS = {
    "critic, defaults": "default",
    "pathwise, `--terminal-scale 100`": "pathwise_terminal100",
    "critic, `--terminal-scale 3000`": "terminal3000",
    "... `--step-decay 10`": "terminal3000_decay10",
    "... `--step-decay 25`": "terminal3000_decay25",
    "... `--step-decay 50`": "terminal3000_decay50",
    "... `--step-decay 25 --critic-months 4`": "terminal3000_decay25_months4",
    "... `--step-decay 25 --step-size 0.04`": "step0.04_terminal3000_decay25",
}
#: the options each screen folder's runs were made with (their stored run config says so)
SCREEN_OPTIONS = {
    "default": {"gradient": "critic", "terminal_scale": 100.0, "step_decay": 0},
    "pathwise_terminal100": {"gradient": "pathwise", "terminal_scale": 100.0},
    "terminal3000": {"terminal_scale": 3000.0, "step_decay": 0},
    "terminal3000_decay10": {"terminal_scale": 3000.0, "step_decay": 10},
    "terminal3000_decay25": {"terminal_scale": 3000.0, "step_decay": 25, "critic_months": 1},
    "terminal3000_decay50": {"terminal_scale": 3000.0, "step_decay": 50},
    "terminal3000_decay25_months4": {"terminal_scale": 3000.0, "step_decay": 25,
                                     "critic_months": 4},
    "step0.04_terminal3000_decay25": {"terminal_scale": 3000.0, "step_decay": 25,
                                      "step_size": 0.04},
}


def _summary(folder: Path) -> dict:
    return json.loads((folder / "study.json").read_text())


def _paired(study: dict) -> str:
    split = study["class_split"]
    low, high = split["learner_gap_paired_iqr"]
    return (f"{split['learner_gap_paired_median']:.1f} ({low:.1f} to {high:.1f}), "
            f"{split['learner_gap_paired_worst']['value']:.1f}")


def _final(study: dict) -> str:
    low, high = study["J_eval_final_iqr"]
    return f"{study['J_eval_final_median']:.1f} ({low:.1f} to {high:.1f})"


def _never_improved(study: dict) -> str:
    seeds = study["no_improvement_seeds"]
    return f"{len(seeds)} ({', '.join(str(s) for s in seeds)})" if seeds else "0"


@pytest.mark.parametrize("label", list(FRESH_ROWS))
def test_the_fresh_seed_rows_are_the_stored_studies(label):
    study = _summary(STUDIES / FRESH_ROWS[label])
    seeds = sorted(int(s) for s in study["class_split"]["learner_gap"])
    assert seeds == list(range(14000, 14020))
    assert study["class_split"]["source"] == "data/class_best_paper"
    from mpcrl_lite.config import LearningConfig

    stored = json.loads((STUDIES / FRESH_ROWS[label] / "config_seed14000.json").read_text())
    learning = LearningConfig.from_dict(stored["learning"])
    assert (learning.gradient, learning.terminal_scale, learning.step_decay) == FRESH_OPTIONS[label]
    assert bench_row(label) == (f"| {label} | {_final(study)} | {_paired(study)} | "
                                f"{_never_improved(study)} |")


@pytest.mark.parametrize("label", list(SCREEN_ROWS))
def test_the_screen_rows_are_the_stored_studies(label):
    folder = SCREEN / SCREEN_ROWS[label]
    study = _summary(folder)
    assert sorted(int(s) for s in study["class_split"]["learner_gap"]) == list(
        range(13000, 13010))
    assert bench_row(label) == f"| {label} | {_final(study)} | {_paired(study)} |"


@pytest.mark.parametrize("name", list(SCREEN_OPTIONS))
def test_the_screen_folders_ran_the_options_they_are_named_for(name):
    """Read back as a run reads its config (a pathwise run at the critic's scale 100 stores
    no ``terminal_scale`` and must read back with 100)."""
    from mpcrl_lite.config import LearningConfig

    stored = json.loads((SCREEN / name / "config_seed13000.json").read_text())["learning"]
    learning = LearningConfig.from_dict(stored)
    for key, value in SCREEN_OPTIONS[name].items():
        assert getattr(learning, key) == value, (name, key)


def _from_best(gradient: str) -> tuple[list[dict], dict]:
    lines = [json.loads(line) for line in
             (FROM_BEST / f"{gradient}.jsonl").read_text().splitlines()]
    return lines[:-1], lines[-1]


@pytest.mark.parametrize("gradient", ["critic", "pathwise"])
def test_the_from_best_rows_are_the_stored_runs(gradient):
    """The summary line is recomputed from the runs, and the table quotes it."""
    runs, summary = _from_best(gradient)
    assert summary["summary"] and summary["gradient"] == gradient
    assert [r["seed"] for r in runs] == summary["seeds"] == list(range(13010, 13016))
    class_best = json.loads((ROOT / "data/class_best_paper/tune.json").read_text())
    assert summary["tune"] == "data/class_best_paper/tune.json"
    late = []
    for run in runs:
        assert run["gradient"] == gradient and run["eval_month"][0] == 0
        assert run["J_eval"][0] == summary["J_start"]  # every run starts at the same theta
        late.append(statistics.median(j for m, j in zip(run["eval_month"], run["J_eval"],
                                                        strict=True) if m >= 55))
    assert late == summary["late_median_per_seed"]
    assert statistics.median(late) == summary["late_median"]
    finals = [r["J_eval"][-1] for r in runs]
    assert (statistics.median(finals), max(finals)) == (summary["final_median"],
                                                        summary["final_worst"])
    # the start is the class's best theta, judged on the evaluation draws as README quotes it
    assert f"{summary['J_start']:.1f} NOK/day on the evaluation draws" in BENCH
    assert class_best["theta_best"]["T1"][0] > 400  # far from theta0's 0, as the text says
    label = f"{gradient}, from the class's best"
    assert bench_row(label) == (
        f"| {label} | {summary['late_median']:.1f} ({min(late):.1f} to {max(late):.1f}) | "
        f"{summary['final_median']:.1f}, {summary['final_worst']:.1f} | "
        f"{summary['late_worst']:.1f} |")


def test_the_critic_stays_about_ten_above_the_class_best():
    _, critic = _from_best("critic")
    _, pathwise = _from_best("pathwise")
    above = critic["late_median"] - critic["J_start"]
    assert 9.5 <= above < 10.5  # "about 10"
    assert pathwise["late_median"] - pathwise["J_start"] < 3  # "within 3"
    default = _summary(STUDIES / "paper_critic_14000")
    assert f"where from theta0 it ends near {default['J_eval_final_median']:.0f}" in BENCH


def test_the_split_of_the_critics_gap_is_the_stored_one():
    """README's and benchmarks/README's pace / estimate split on 14000-14019."""
    critic, slow, exact = (_summary(STUDIES / FRESH_ROWS[label])["class_split"]
                           for label in list(FRESH_ROWS)[:3])
    c, s, e = (split["learner_gap_paired_median"] for split in (critic, slow, exact))
    diffs = [critic["learner_gap_paired"][k] - slow["learner_gap_paired"][k]
             for k in critic["learner_gap_paired"]]
    worse = sum(d > 0 for d in diffs)
    assert (round(s - e), round(c - s)) == (22, 9)
    assert (f"the critic's paired gap of {c:.1f} splits into about {round(s - e)} of pace (the "
            f"exact gradient at the critic's scale: {s:.1f}") in README
    assert f"at its own: {e:.1f}) and about {round(c - s)} of the estimate" in README
    assert (f"the critic ends a median {statistics.median(diffs):.1f} above the exact gradient "
            f"at the same pace, on {worse} of the 20 seeds") in README
    assert (f"per seed the critic ends a median {statistics.median(diffs):.1f} above the exact "
            f"gradient at the same pace, worse on {worse} of 20") in BENCH
    assert f"So the critic's {c:.0f} NOK/day are about {round(s - e)} of pace" in BENCH
    notebook = json.loads((ROOT / "notebooks/09_why_the_learner_stops_short.ipynb").read_text())
    prose = " ".join(" ".join("".join(cell["source"]) for cell in notebook["cells"]
                              if cell["cell_type"] == "markdown").split())
    assert (f"the exact gradient, too, ends some {round(s)} NOK/day above the paper class's best "
            "(paired, 20 fresh seeds)") in prose
    assert "left four runs of 20 where they started" in prose


def test_the_wider_pace_on_fresh_seeds_is_the_stored_one():
    wide = _summary(STUDIES / "paper_critic_terminal3000_decay25_14000")
    default = _summary(STUDIES / "paper_critic_14000")
    screen = _summary(SCREEN / "terminal3000_decay25")
    screen_default = _summary(SCREEN / "default")
    assert (f"{wide['class_split']['learner_gap_paired_median']:.1f} against the default's "
            f"{default['class_split']['learner_gap_paired_median']:.1f} in the median") in BENCH
    assert len(wide["no_improvement_seeds"]) == 4 and len(default["no_improvement_seeds"]) == 1
    assert "four runs ended no better than they started (against one with the defaults)" in BENCH
    assert ("with it and a decaying step, 4 of those 20 runs never improved on their start, "
            "against 1 with the defaults") in README
    gain = (screen_default["class_split"]["learner_gap_paired_median"]
            - screen["class_split"]["learner_gap_paired_median"])
    assert round(gain) == 14 and "The screen's 14 NOK/day were mostly the draw" in BENCH


def test_the_fourth_fresh_set_of_the_pathwise_learner():
    study = _summary(STUDIES / "paper_pathwise_14000")
    split = study["class_split"]
    low, high = split["learner_gap_iqr"]
    plow, phigh = split["learner_gap_paired_iqr"]
    worst, worst_paired = split["learner_gap_worst"], split["learner_gap_paired_worst"]
    late = study["largest_late_regression"]
    assert worst["seed"] == worst_paired["seed"] == late["seed"]
    share = study["late_regression_share"][str(late["seed"])]
    assert split["learner_gap_median"] <= 10  # the target, on seeds nobody chose
    assert (f"learner gap median {split['learner_gap_median']:.1f} (IQR {low:.1f} to "
            f"{high:.1f}), paired {split['learner_gap_paired_median']:.1f} ({plow:.1f} to "
            f"{phigh:.1f}); all {round(20 * study['fraction_converged'])} seeds close 90 % of "
            f"the gap; the worst seed, {worst['seed']}, has a gap of {worst['value']:.1f}, or "
            f"{worst_paired['value']:.1f} paired, and lost {late['value']:.1f} NOK/day after its "
            f"best evaluation ({100 * share:.1f} % of the gap)") in README
    assert (f"held-out learner gap median {split['learner_gap_median']:.1f} (IQR {low:.1f} to "
            f"{high:.1f}), worst {worst['value']:.1f} (seed {worst['seed']})") in BENCH


def test_the_from_best_script_summarises_as_the_table_reads():
    """benchmarks/from_class_best.py's summary on a small made-up case."""
    spec = importlib.util.spec_from_file_location(
        "from_class_best", ROOT / "benchmarks" / "from_class_best.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    rows = [{"seed": 1, "gradient": "critic", "eval_month": [0, 5, 9], "J_eval": [-10, -8, -6]},
            {"seed": 2, "gradient": "critic", "eval_month": [0, 5, 9], "J_eval": [-10, -2, -4]}]
    out = module.summary(rows, late=5, months=10)
    assert out["late_median_per_seed"] == [-7, -3]  # months 5 and 9 of each
    assert (out["late_median"], out["late_worst"]) == (-5, -2)
    assert (out["final_median"], out["final_worst"]) == (-5, -4)
    assert module.seed_range("3-5") == [3, 4, 5] and module.seed_range("7,9") == [7, 9]
