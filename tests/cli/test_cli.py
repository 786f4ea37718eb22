"""The command line: contracts of `simulate` and `learn`, one-line errors."""

from __future__ import annotations

import argparse
import json
import subprocess
import sys

import pytest

from mpcrl_lite.cli.main import build_parser, main
from mpcrl_lite.config import BACKENDS, OPTIMIZERS, LearningConfig, MPCConfig, SystemConfig
from mpcrl_lite.learning.history import History
from mpcrl_lite.learning.rundir import CHECKPOINT
from mpcrl_lite.publish.report import PROFILES


def test_simulate_writes_summary_and_figure(tmp_path, capsys):
    out = tmp_path / "nominal"
    assert main(["simulate", "--days", "2", "--out", str(out), "--seed", "3", "--quiet"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    for key in ("J", "J_per_agent", "max_P_mpc", "max_P_applied", "hours_soc_below_0_1",
                "hours_soc_above_0_9", "solver_failures"):
        assert key in summary
    assert summary["max_P_mpc"] <= 1.5 + 1e-9
    assert summary["solver_failures"] == 0
    assert len(summary["J_per_agent"]) == 3
    assert summary["J"] == pytest.approx(sum(summary["J_per_agent"]))
    assert (out / "day0.png").stat().st_size > 0
    assert (out / "trajectories.npz").exists()
    printed = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert printed["J"] == summary["J"]


def test_simulate_options_change_the_system(tmp_path):
    out = tmp_path / "tight"
    assert main(["simulate", "--days", "1", "--out", str(out), "--p-bar", "0.8",
                 "--noise-var", "0.1"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["P_bar"] == 0.8 and summary["noise_var"] == 0.1
    assert summary["max_P_mpc"] <= 0.8 + 1e-9


def test_learn_writes_history_summary_and_figures(tmp_path):
    out = tmp_path / "run"
    args = ["learn", "--months", "2", "--days", "2", "--out", str(out), "--quiet"]
    assert main(args) == 0
    summary = json.loads((out / "summary.json").read_text())
    for key in ("J", "J_per_agent", "grad_norm", "theta_final", "hours_soc_below_0_1",
                "max_P_mpc", "skipped_steps"):
        assert key in summary
    assert len(summary["J"]) == 2 and len(summary["grad_norm"]) == 2
    assert set(summary["theta_final"]) >= {"alpha", "delta", "T2"}
    assert (out / "history.json").exists() and (out / "history.npz").exists()
    assert len(list(out.glob("fig*.png"))) == 7
    # a second call without --resume refuses to overwrite; with --resume it extends the run
    before = (out / "history.json").read_bytes()
    assert main(args) == 2
    assert (out / "history.json").read_bytes() == before
    assert main(["learn", "--months", "3", "--days", "2", "--out", str(out), "--quiet",
                 "--resume", "--no-figures"]) == 0
    assert len(json.loads((out / "summary.json").read_text())["J"]) == 3


@pytest.mark.parametrize("extra, names_pathwise",
                         [([], True), (["--learner", "q", "--hessian", "none"], False)])
def test_learn_warns_when_the_run_ends_no_better_than_it_started(extra, names_pathwise,
                                                                  tmp_path, capsys):
    # a zero step keeps the starting theta: its last evaluation equals the first, on the
    # same draws, and the command says so in one line (the run is kept, exit code 0); the
    # pathwise gradient is named only where it could replace the run's critic
    out = tmp_path / "still"
    assert main(["learn", "--months", "2", "--days", "2", "--out", str(out), "--quiet",
                 "--no-figures", "--eval-draws", "1", "--step-size", "0", *extra]) == 0
    err = capsys.readouterr().err
    warnings = [line for line in err.splitlines() if "learned nothing usable" in line]
    assert len(warnings) == 1, err
    summary = json.loads((out / "summary.json").read_text())
    verdict = summary["improvement"]
    assert verdict["improved_on_start"] is False and verdict["change"] == 0.0
    assert f"{verdict['J_eval_start']:.1f}" in warnings[0]
    assert ("--gradient pathwise" in warnings[0]) is names_pathwise
    assert "another --seed" in warnings[0]


def test_learn_records_the_step_rule_and_a_resume_keeps_it(tmp_path, capsys):
    out = tmp_path / "rule"
    common = ["learn", "--days", "2", "--out", str(out), "--quiet", "--no-figures",
              "--eval-draws", "1"]
    assert main([*common, "--months", "2", "--step-warmup", "3", "--step-decay", "5",
                 "--average-months", "2"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    history = json.loads((out / "history.json").read_text())  # the run's own record
    stored = history["learning"]
    assert (stored["step_warmup"], stored["step_decay"], stored["average_months"]) == (3, 5, 2)
    assert summary["months"] == 2
    info = history["update_info"]
    # update t: 0.02 * min(1, t / 3) / (1 + (t - 1) / 5)
    assert [i["step_size"] for i in info] == pytest.approx([0.02 / 3, 0.02 * 2 / 3 / 1.2])
    # a resume keeps the rule without the flags, and refuses another one in one line
    assert main([*common, "--months", "3", "--resume"]) == 0
    info = json.loads((out / "history.json").read_text())["update_info"]
    assert info[-1]["step_size"] == pytest.approx(0.02 / 1.4)
    capsys.readouterr()
    assert main([*common, "--months", "4", "--resume", "--step-decay", "9"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--step-decay 9 with --resume" in err[0] and "5" in err[0], err


@pytest.mark.parametrize(
    "argv, message",
    [
        (["simulate", "--days", "0", "--out", "x"], "--days: 0 must be >= 1"),
        (["simulate", "--days", "2", "--out", "x", "--p-bar", "-1"], "P_bar=-1.0"),
        (["simulate", "--days", "2", "--out", "x", "--noise-var", "abc"], "'abc' is not a number"),
        (["simulate", "--days", "2", "--out", "x", "--noise-var", "-0.5"], "noise_var=-0.5"),
        (["learn", "--months", "1", "--out", "x", "--step-size", "-1"], "step_size=-1.0"),
        (["learn", "--out", "x"], "--months"),
        (["learn", "--months", "1", "--out", ""], "--out '': expected a directory path"),
        (["learn", "--months", "1", "--out", "x", "--resume", "--force"],
         "--resume and --force exclude each other"),
        (["learn", "--months", "1", "--out", "x/afile"], "is an existing file; expected a directory"),
    ],
)
def test_bad_arguments_give_one_line(argv, message, tmp_path):
    argv = [a.replace("x", str(tmp_path / "x"), 1) if a.startswith("x") else a for a in argv]
    (tmp_path / "x").mkdir()
    (tmp_path / "x" / "afile").write_text("mine")
    proc = subprocess.run([sys.executable, "-m", "mpcrl_lite", *argv],
                          capture_output=True, text=True, timeout=120, check=False)
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1, proc.stderr
    assert message in lines[0]
    assert "Traceback" not in proc.stderr
    assert sorted(p.name for p in (tmp_path / "x").iterdir()) == ["afile"]  # nothing written


def _options(command: str) -> dict[str, argparse.Action]:
    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return {a.dest: a for a in sub.choices[command]._actions}


def test_choices_and_shown_defaults_come_from_the_package():
    for command in ("simulate", "learn", "baselines"):
        assert tuple(_options(command)["backend"].choices) == BACKENDS
    assert tuple(_options("learn")["optimizer"].choices) == OPTIMIZERS
    assert tuple(_options("report")["profile"].choices) == PROFILES
    learn = _options("learn")
    system, mpc, learning = SystemConfig(), MPCConfig(), LearningConfig()
    assert f"default {system.P_bar:g}" in learn["p_bar"].help
    assert f"default {system.noise_var:g}" in learn["noise_var"].help
    assert f"default {system.n}" in learn["n"].help
    assert f"default {mpc.tau:g}" in learn["tau"].help
    assert f"default {learning.days_per_month}" in learn["days"].help
    assert f"default {learning.optimizer}" in learn["optimizer"].help
    assert learn["seed"].default == learning.seed


def test_decentralized_help_says_how_the_grid_limit_is_shared():
    text = _options("learn")["decentralized"].help
    assert "dual decomposition" not in text  # the coordination is not plain dual decomposition
    assert "grid prices" in text and "Newton" in text


def test_learn_refuses_a_directory_holding_a_checkpoint(tmp_path, capsys):
    (tmp_path / CHECKPOINT).write_text("{}")
    assert main(["learn", "--months", "1", "--out", str(tmp_path), "--quiet"]) == 2
    assert "already holds a run (checkpoint.json); pass --resume" in capsys.readouterr().err


@pytest.mark.parametrize("flag, expected", [([], None), (["--eval-here"], False)])
def test_learn_eval_here_keeps_the_evaluations_in_the_process(flag, expected, tmp_path,
                                                               monkeypatch):
    from mpcrl_lite.learning.experiment import Experiment

    seen = []
    real_run = Experiment.run

    def spy(self, *args, **kwargs):
        seen.append(self.eval_worker)
        return real_run(self, *args, **kwargs)

    monkeypatch.setattr(Experiment, "run", spy)
    argv = ["learn", "--months", "1", "--days", "1", "--out", str(tmp_path / "run"), "--quiet",
            "--no-figures", *flag]
    assert main(argv) == 0
    assert seen == [expected]


def test_the_command_ends_its_process_with_everything_written(tmp_path):
    """``python -m mpcrl_lite`` ends at once once its command returns (cli.main.end_process):
    the run is committed, the summary written, the output flushed and the status kept."""
    out = tmp_path / "run"
    proc = subprocess.run([sys.executable, "-m", "mpcrl_lite", "learn", "--months", "2",
                           "--days", "2", "--eval-draws", "1", "--no-figures", "--quiet",
                           "--out", str(out)],
                          capture_output=True, text=True, timeout=300, check=False)
    assert proc.returncode == 0, proc.stderr
    assert json.loads(proc.stdout.strip().splitlines()[-1])["months"] == 2
    assert History.load(out).months == 2
    assert json.loads((out / "summary.json").read_text())["months"] == 2
    assert not (out / ".run").exists()  # the last commit published and tidied


def test_the_process_ends_with_idle_thread_pools_alive():
    """A command that used the kernels' helper threads (``run_blocks``: the decentralized
    learner's coordination rounds, a forked worker's solves) leaves an idle thread pool; the
    process still ends at once, with its exit handlers run (``learn --decentralized`` waited
    for ever on the pool's worker)."""
    code = """
import atexit, sys, threading
from mpcrl_lite._util.threads import run_blocks
from mpcrl_lite.cli.main import end_process
done = []
run_blocks(lambda lo, hi: done.append((lo, hi)), (), 8, 2, 2)
assert sorted(done) == [(0, 2), (2, 4), (4, 6), (6, 8)], done
assert any(t.name.startswith("mpcrl_lite-kernel") for t in threading.enumerate())
finished = threading.Thread(target=lambda: done.append("joined"))  # a thread that is no daemon
finished.start()
atexit.register(lambda: print("exit handlers ran", len(done)))
end_process(3)
"""
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          timeout=60, check=False)
    assert proc.returncode == 3, proc.stderr
    assert proc.stdout.strip() == "exit handlers ran 5"
