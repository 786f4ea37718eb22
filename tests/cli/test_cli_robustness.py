"""The command line against a careless or unlucky user: an empty ``--out``, negative numbers
argparse would take for options, a full disk once the run is committed, numbers the model
cannot mean; each ends in one line (exit 2) with nothing lost."""

from __future__ import annotations

import errno
from pathlib import Path

import pytest

from mpcrl_lite.cli.main import main
from mpcrl_lite.figures import paper
from mpcrl_lite.learning.history import History

RUN = Path(__file__).resolve().parents[1] / "fixtures" / "run_v0_centralized"


def run_cli(argv: list[str], capsys) -> tuple[int, list[str]]:
    capsys.readouterr()
    try:
        code = main([str(a) for a in argv])
    except SystemExit as exit_:  # argparse
        code = exit_.code
    return code, capsys.readouterr().err.strip().splitlines()


COMMANDS = {
    "simulate": ["simulate", "--days", "1"],
    "learn": ["learn", "--months", "1", "--days", "1", "--no-figures"],
    "baselines": ["baselines", "--days", "1"],
    "evaluate": ["evaluate", "--history", RUN, "--days", "1", "--draws", "1"],
    "sweep": ["sweep", "--grid", "grid.yaml", "--workers", "0"],
    "study": ["study", "--seeds", "1", "--months", "1", "--days", "1", "--workers", "0"],
    "report": ["report", "--notebooks", "01_battery_dynamics", "--profile", "ci"],
    "tune": ["tune", "--evals", "4", "--draws", "1", "--days", "1"],
}


@pytest.mark.parametrize("command", sorted(COMMANDS))
def test_an_empty_out_is_refused_by_every_command(command, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "grid.yaml").write_text("grid: {learning.seed: [0]}\n")
    code, err = run_cli([*COMMANDS[command], "--out", "", "--quiet"][
        : None if command != "report" else -1], capsys)
    assert code == 2 and len(err) == 1, err
    assert "'': expected a directory path" in err[0] and err[0].startswith(
        f"mpcrl_lite {command}: error: "), err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["grid.yaml"]


@pytest.mark.parametrize("flag, value, message", [
    ("--p-bar", "-inf", "argument --p-bar: '-inf' is not a finite number"),
    ("--p-bar", "-1e5", "P_bar=-100000.0: expected"),
    ("--tau", "-1e-5", "tau=-1e-05: expected"),
    ("--noise-var", "-nan", "argument --noise-var: '-nan' is not a finite number"),
])
def test_negative_numbers_are_refused_by_value(flag, value, message, tmp_path, capsys):
    code, err = run_cli(["simulate", "--days", "1", "--out", tmp_path / "s", flag, value],
                        capsys)
    assert code == 2 and len(err) == 1 and message in err[0], err
    assert "expected one argument" not in err[0]
    assert not (tmp_path / "s").exists()


def test_a_full_disk_while_the_figures_are_written_is_one_line(tmp_path, capsys, monkeypatch):
    real = paper.save_paper_figures

    def full_disk(*_args, **_kwargs):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(paper, "save_paper_figures", full_disk)
    out = tmp_path / "run"
    argv = ["learn", "--months", "1", "--days", "1", "--out", out, "--quiet"]
    code, err = run_cli(argv, capsys)
    assert code == 2 and len(err) == 1, err
    assert "the run is committed in" in err[0] and "No space left on device" in err[0]
    assert "--resume" in err[0]
    assert History.load(out).months == 1  # committed, verified
    monkeypatch.setattr(paper, "save_paper_figures", real)
    code, err = run_cli([*argv, "--resume"], capsys)  # the space is back: the figures too
    assert code == 0, err
    assert all((out / name).exists() for name in paper.PAPER_FIGURES)
    assert History.load(out).months == 1


def test_a_system_file_with_a_key_written_twice_is_refused(tmp_path, capsys):
    system = tmp_path / "site.yaml"
    system.write_text("P_bar: 1.2\nnoise_var: 0.2\nP_bar: 1.0\n")
    code, err = run_cli(["simulate", "--days", "1", "--system", system, "--out", tmp_path / "s"],
                        capsys)
    assert code == 2 and len(err) == 1, err
    assert "key 'P_bar' is written twice (first at line 1)" in err[0]
    assert not (tmp_path / "s").exists()
