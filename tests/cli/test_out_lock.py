"""One process at a time per output directory: the lock of
:func:`mpcrl_lite.learning.outdir.lock_output_dir`, taken by ``learn``, ``study``, ``sweep``,
``report`` and ``tune`` (and the library functions they call).

Two processes on one ``--out``: exactly one runs, the other is refused in one line naming
the holder's PID, and the directory holds the winner's run, verified. The lock of a killed
process is taken over.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from mpcrl_lite.cli.main import main
from mpcrl_lite.learning import outdir
from mpcrl_lite.learning.history import History

ROOT = Path(__file__).resolve().parents[2]


def python(*argv: str, cwd: Path) -> subprocess.Popen:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    return subprocess.Popen([sys.executable, "-m", "mpcrl_lite", *argv], cwd=cwd, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def learn_argv(out: Path, seed: int, months: int = 3) -> list[str]:
    return ["learn", "--months", str(months), "--days", "4", "--out", str(out), "--quiet",
            "--no-figures", "--seed", str(seed)]


def test_two_learn_processes_on_one_out_one_runs_one_is_refused(tmp_path):
    out = tmp_path / "run"
    procs = {seed: python(*learn_argv(out, seed), cwd=tmp_path) for seed in (0, 1)}
    results = {seed: (p.wait(timeout=600), *p.communicate()) for seed, p in procs.items()}
    codes = sorted(code for code, _, _ in results.values())
    assert codes == [0, 2], results
    winner = next(seed for seed, r in results.items() if r[0] == 0)
    loser = 1 - winner
    err = results[loser][2].strip().splitlines()
    assert len(err) == 1 and err[0].startswith("mpcrl_lite learn: error: "), err
    # refused by the lock (naming the winner) or, had it come after the winner, by the run
    assert (f"is in use by another process (PID {procs[winner].pid}, learn)" in err[0]
            or "already holds a run" in err[0]), err
    history = History.load(out)  # verified against the manifest
    assert history.months == 3 and history.learning.seed == winner
    assert not (out / outdir.LOCK).exists()


@pytest.mark.parametrize("command", ["learn", "sweep", "study", "report", "tune"])
def test_a_held_lock_refuses_every_command_naming_the_pid(command, tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    grid = tmp_path / "grid.yaml"
    grid.write_text("base: {learning: {months: 1, days_per_month: 1}}\n"
                    "grid: {learning.seed: [0]}\n")
    argv = {
        "learn": learn_argv(out, 0, months=1),
        "sweep": ["sweep", "--grid", str(grid), "--out", str(out), "--workers", "0", "--quiet"],
        "study": ["study", "--seeds", "1", "--months", "1", "--days", "1", "--workers", "0",
                  "--target", "best_seen", "--out", str(out), "--quiet"],
        "report": ["report", "--notebooks", "01_battery_dynamics", "--profile", "ci",
                   "--out", str(out)],
        "tune": ["tune", "--evals", "4", "--draws", "1", "--heldout-draws", "2", "--days", "1",
                 "--out", str(out), "--quiet"],
    }[command]
    with outdir.lock_output_dir(out, "test"):
        proc = python(*argv, cwd=tmp_path)
        code, (_, err) = proc.wait(timeout=300), proc.communicate()
        assert sorted(p.name for p in out.iterdir()) == [outdir.LOCK]
    lines = err.strip().splitlines()
    assert code == 2 and len(lines) == 1, err
    assert f"is in use by another process (PID {os.getpid()}, test)" in lines[0], lines
    assert list(out.iterdir()) == []  # the lock file goes with its holder


def test_the_lock_of_a_killed_process_is_taken_over(tmp_path, capsys):
    out = tmp_path / "run"
    out.mkdir()
    pid = os.fork()
    if pid == 0:  # the child takes the lock and dies without releasing it
        with outdir.lock_output_dir(out, "learn"):
            os.kill(os.getpid(), signal.SIGKILL)
    os.waitpid(pid, 0)
    assert (out / outdir.LOCK).read_text().split()[0] == str(pid)  # left behind
    status = main(["learn", "--months", "1", "--days", "1", "--out", str(out), "--quiet",
                   "--no-figures"])
    assert status == 0, capsys.readouterr().err
    assert History.load(out).months == 1 and not (out / outdir.LOCK).exists()


def test_the_lock_is_reentrant_in_its_process_and_exclusive_across(tmp_path):
    out = tmp_path / "d"
    out.mkdir()
    probe = ("import sys; from mpcrl_lite.learning import outdir\n"
             "try:\n    with outdir.lock_output_dir(sys.argv[1], 'probe'): print('got it')\n"
             "except outdir.RunDirLocked as err: print(err)\n")
    env = {**os.environ, "PYTHONPATH": str(ROOT)}

    def other() -> str:
        return subprocess.run([sys.executable, "-c", probe, str(out)], env=env, text=True,
                              capture_output=True, check=True).stdout.strip()

    with outdir.lock_output_dir(out, "outer"):
        with outdir.lock_output_dir(out / ".", "inner"):  # the same directory, re-entered
            assert (out / outdir.LOCK).read_text().split() == [str(os.getpid()), "outer"]
        assert f"in use by another process (PID {os.getpid()}, outer)" in other()
    assert other() == "got it"
    assert list(out.iterdir()) == []
