"""Runs never lose or corrupt data: kills at every write, full disks, damaged and foreign
run directories, and the one-line refusals of ``learn`` and ``baselines --history``.

The kill tests run ``learn`` in a child process (forked from this one, so that the imports
are paid once) with ``MPCRL_LITE_KILL_AFTER_WRITE=i`` / ``MPCRL_LITE_KILL_MID_WRITE=i``
(:mod:`mpcrl_lite.learning.rundir`): the child kills itself with SIGKILL after (or half-way through)
its ``i``-th write to the run directory, for every ``i`` of an uninterrupted run; a few more
runs are real ``python -m mpcrl_lite learn`` processes killed at random times. After each kill
``learn --resume`` must either finish with results identical to the uninterrupted run (the
History up to timings, the checkpoint exactly) or refuse in one line; it must never do
anything else.
"""

from __future__ import annotations

import errno
import io
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import learn_in_child

from mpcrl_lite import LearningConfig, MPCConfig, SystemConfig, Theta
from mpcrl_lite._util import jsonio
from mpcrl_lite.cli.main import main
from mpcrl_lite.decentralized.learner import DecentralizedExperiment
from mpcrl_lite.learning import durable, rundir
from mpcrl_lite.learning.durable import RunWriteError
from mpcrl_lite.learning.experiment import Experiment
from mpcrl_lite.learning.history import History
from mpcrl_lite.learning.outdir import RunDirError
from mpcrl_lite.sim.record import RECORD_ARRAYS

FIXTURES = Path(__file__).resolve().parents[1] / "fixtures"
LEGACY = {"": FIXTURES / "run_v0_centralized", "--decentralized": FIXTURES / "run_v0_decentralized"}
LEARNERS = ["", "--decentralized"]
SMALL = SystemConfig(N=6)


def learn_args(out: Path | str, months: int, learner: str = "", *extra: str) -> list[str]:
    args = ["learn", "--months", str(months), "--days", "1", "--out", str(out), "--quiet",
            "--no-figures", *extra]
    return args + ([learner] if learner else [])


def cli(argv: list[str], capsys) -> tuple[int, str, str]:
    """Run the command line in this process; returns (status, stdout, stderr)."""
    capsys.readouterr()
    status = main(argv)
    out, err = capsys.readouterr()
    return status, out, err


def one_line(err: str) -> str:
    """The error line of a failed command (warnings of the run may precede it)."""
    lines = err.strip().splitlines()
    assert lines and "Traceback" not in err, err
    last = lines[-1]
    assert last.startswith("mpcrl_lite ") and ": error: " in last, err
    return last


def comparable(history: History) -> str:
    """Everything a History holds except timings, as exact JSON (floats by repr)."""
    data = {k: getattr(history, k) for k in History.SERIES + History.EVAL_SERIES
            if k != "wall_time_s"}
    data["update_info"] = [_drop_times(info) for info in history.update_info]
    data["theta_final"], data["backend"] = history.theta_final, history.backend
    return json.dumps(jsonio.plain(data), sort_keys=True)


def _drop_times(value):
    if isinstance(value, dict):
        return {k: _drop_times(v) for k, v in value.items() if not k.endswith("time_s")}
    if isinstance(value, list):
        return [_drop_times(v) for v in value]
    return value


def assert_same_run(directory: Path, reference: Path) -> None:
    """The run in ``directory`` equals the one in ``reference`` (checkpoint exactly)."""
    got, want = History.load(directory), History.load(reference)
    assert comparable(got) == comparable(want)
    for month in ("first_month", "last_month"):
        for key in RECORD_ARRAYS:
            np.testing.assert_array_equal(getattr(getattr(got, month), key),
                                          getattr(getattr(want, month), key))
    checkpoint = [json.loads(rundir.read(d, ["checkpoint.json"]).files["checkpoint.json"])
                  for d in (directory, reference)]
    assert checkpoint[0] == checkpoint[1]


def copy_run(source: Path, target: Path) -> Path:
    shutil.copytree(source, target)
    return target


# -- kills at every write ---------------------------------------------------------------------


def resume_and_judge(out: Path, reference: Path, argv: list[str], capsys) -> str:
    """``learn --resume``: 'identical' or 'refused' (one line, nothing changed)."""
    before = {p.name: p.read_bytes() for p in out.iterdir() if p.is_file()} if out.exists() else {}
    status, _, err = cli(argv + ["--resume"], capsys)
    if status == 2:
        one_line(err)
        after = {p.name: p.read_bytes() for p in out.iterdir() if p.is_file()}
        assert after == before
        return "refused"
    assert status == 0, err
    assert_same_run(out, reference)
    assert (out / "summary.json").exists()
    return "identical"


@pytest.mark.parametrize("learner, stride", [
    ("", 1),
    ("--decentralized", 3),  # the same writes with another learner state: every third
    # a critic fitted on two months: its earlier month in a fourth file of every commit
    ("--critic-months=2", 3),
    pytest.param("--decentralized", 1, marks=pytest.mark.slow),
])
def test_a_kill_at_any_write_resumes_identically(learner, stride, tmp_path, capsys,
                                                 monkeypatch):
    reference = tmp_path / "reference"
    file_writes: list[int] = []
    real_write = durable.write_file

    def spy(path, data):
        file_writes.append(durable._writes + 1)
        return real_write(path, data)

    monkeypatch.setattr(durable, "write_file", spy)
    start = durable._writes
    assert cli(learn_args(reference, 2, learner), capsys)[0] == 0
    writes = durable._writes - start
    file_writes = [i - start for i in file_writes]
    monkeypatch.undo()
    # 2 commits (staging, 3 files (4 with critic.npz), manifest, visible names, clean-up)
    # + summary.json
    files = 4 if "critic" in learner else 3
    assert writes >= 2 * (files + 7) + 2 and len(file_writes) == 2 * (files + 1) + 1
    points = [(durable.KILL_AFTER_WRITE_ENV, i) for i in range(1, writes + 1)]
    points += [(durable.KILL_MID_WRITE_ENV, i) for i in file_writes]
    points = points[::stride]
    outcomes: dict[str, list] = {"identical": [], "refused": []}
    for hook, i in points:
        out = tmp_path / f"{hook[-10:]}-{i}"
        argv = learn_args(out, 2, learner)
        status = learn_in_child(argv, {hook: str(i)})
        assert os.WIFSIGNALED(status) and os.WTERMSIG(status) == signal.SIGKILL, (hook, i)
        outcomes[resume_and_judge(out, reference, argv, capsys)].append((hook, i))
        shutil.rmtree(out)
    print(f"\n{learner or 'centralized'}: {len(points)} kill points, "
          f"{len(outcomes['identical'])} resumed identically, {len(outcomes['refused'])} refused")
    # the format promises more than the test requires: no kill ever needs a refusal
    assert outcomes["refused"] == []


def started(out: Path, proc: subprocess.Popen) -> float:
    """Wait until ``learn`` has checked and created ``out`` (its imports are done)."""
    t0 = time.perf_counter()
    while not out.exists() and proc.poll() is None:
        time.sleep(0.005)
    return time.perf_counter() - t0


@pytest.mark.parametrize("learner", LEARNERS)
def test_real_kills_at_random_times(learner, tmp_path, capsys):
    """``python -m mpcrl_lite learn`` killed at random times after its start-up."""
    env = {**os.environ, "PYTHONPATH": str(Path(rundir.__file__).parents[2]),
           "MPLBACKEND": "Agg"}
    command = [sys.executable, "-m", "mpcrl_lite"]
    reference = tmp_path / "reference"
    proc = subprocess.Popen(command + learn_args(reference, 3, learner), env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    started(reference, proc)
    t0 = time.perf_counter()
    assert proc.wait(timeout=300) == 0
    duration = time.perf_counter() - t0  # from the start of the work to its end
    rng = np.random.default_rng(1)
    outcomes: list[str] = []
    k = 0
    while sum("killed" in o for o in outcomes) < 3 and k < 10:  # the load varies: try again
        when = rng.uniform(0.0, 0.8) * duration
        k += 1
        out = tmp_path / f"kill{k}"
        argv = learn_args(out, 3, learner)
        proc = subprocess.Popen(command + argv, env=env, stdout=subprocess.DEVNULL,
                                stderr=subprocess.DEVNULL)
        started(out, proc)
        try:
            proc.wait(timeout=when)
            outcomes.append("finished before the kill")
        except subprocess.TimeoutExpired:
            proc.send_signal(signal.SIGKILL)
            proc.wait()
            months = rundir.read(out, ["history.json"]).months_done if (
                out / "manifest.json").exists() else 0
            outcomes.append(f"killed after {months} months: "
                            + resume_and_judge(out, reference, argv, capsys))
    print(f"\n{learner or 'centralized'} random kills: {outcomes}")
    assert all("refused" not in o for o in outcomes)
    assert sum("killed" in o for o in outcomes) == 3


# -- full disk ---------------------------------------------------------------------------------
@pytest.mark.parametrize("failing", ["replace", "fsync"])
def test_a_full_disk_during_a_month_keeps_the_previous_month(tmp_path, failing, monkeypatch):
    """ENOSPC at the i-th rename (or fsync) while month 2 is written, for every i: the run
    stops with an OSError and resumes to the uninterrupted results."""
    learning = LearningConfig(days_per_month=2, months=3, seed=7)

    def experiment() -> Experiment:
        return Experiment(system=SMALL, learning=learning)

    reference = tmp_path / "reference"
    experiment().run(out=reference, progress=False)
    one_month = tmp_path / "one"
    experiment().run(months=1, out=one_month, progress=False)
    real = getattr(os, failing)
    committed = kept = 0
    for i in range(1, 30):
        out = copy_run(one_month, tmp_path / f"full{i}")
        calls = []

        def full(*args, _calls=calls, _i=i):
            _calls.append(args)
            if len(_calls) == _i:
                raise OSError(errno.ENOSPC, "No space left on device")
            return real(*args)

        exp = experiment()
        monkeypatch.setattr(os, failing, full)
        try:
            exp.run(months=2, out=out, resume=True, progress=False)
            committed += 1
        except RunWriteError as err:
            assert "No space left on device" in str(err)
            kept += 1
        monkeypatch.undo()
        experiment().run(out=out, resume=True, progress=False)
        assert_same_run(out, reference)
        shutil.rmtree(out)
        if len(calls) < i:  # the failure was never reached: every later i is the same
            break
    assert kept >= 1 and committed >= 1


# -- defect 1: files a month apart, impossible checkpoints ------------------------------------
def legacy_copy(tmp_path: Path, learner: str = "", name: str = "legacy") -> Path:
    return copy_run(LEGACY[learner], tmp_path / name)


def edit_json(path: Path, change) -> None:
    data = json.loads(path.read_text())
    data = change(data)
    path.write_text(json.dumps(data))


def test_history_and_checkpoint_a_month_apart_are_refused(tmp_path, capsys):
    """The state an interrupted write of the previous version left: history.json has two
    months, checkpoint.json one."""
    later = legacy_copy(tmp_path, name="later")
    assert cli(learn_args(later, 2, "", "--resume", "--adopt"), capsys)[0] == 0
    apart = legacy_copy(tmp_path, name="apart")
    for name in ("history.json", "history.npz"):
        shutil.copy(later / name, apart / name)
    status, _, err = cli(learn_args(apart, 3, "", "--resume", "--adopt"), capsys)
    assert status == 2
    assert "records months_done=1 but history.json 2 months" in one_line(err)
    assert History.load(apart).months == 2  # untouched


def recommit(directory: Path, change_checkpoint=None, change_history=None) -> None:
    """Rewrite a committed run with valid checksums but changed contents (what a bug or a
    foreign writer could commit)."""
    run = rundir.read(directory, ["history.json", "history.npz", "checkpoint.json"])
    files = dict(run.files)
    if change_checkpoint:
        files["checkpoint.json"] = jsonio.dumps(change_checkpoint(json.loads(files["checkpoint.json"])))
    if change_history:
        files["history.json"] = jsonio.dumps(change_history(json.loads(files["history.json"])))
    manifest = run.manifest
    rundir.commit(directory, files, kind=manifest["kind"], months_done=manifest["months_done"],
                  configs_hash=manifest["config_sha256"])


def _set(key, value):
    def change(data):
        data[key] = value
        return data
    return change


def _drop(key):
    def change(data):
        del data[key]
        return data
    return change


def _shorten(key):
    def change(data):
        data[key] = data[key][:-1]
        return data
    return change


@pytest.mark.parametrize(
    "where, change, message",
    [
        ("checkpoint", _set("months_done", 99), "months_done=99 but history.json 1 months"),
        ("checkpoint", _set("format", "mpcrl_lite.DecentralizedCheckpoint/1"),
         "holds a decentralized run"),
        ("checkpoint", _set("format", "something/2"), "format 'something/2'"),
        ("history", _shorten("J"), "series 'J' has 0 entries, expected 1"),
        ("history", _shorten("theta"), "series 'theta' has 0 entries, expected 1"),
        ("checkpoint", _set("theta", [0.0] * 29), "'theta' is not a list of 30 finite numbers"),
    ],
)
@pytest.mark.parametrize("layout", ["legacy", "committed"])
def test_inconsistent_runs_are_refused(tmp_path, capsys, where, change, message, layout):
    out = legacy_copy(tmp_path)
    if layout == "committed":  # resume once to the new format (still one month)
        assert cli(learn_args(out, 1, "", "--resume", "--adopt"), capsys)[0] == 0
        recommit(out, **{f"change_{where}": change})
    else:
        edit_json(out / f"{where}.json", change)
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    status, _, err = cli(learn_args(out, 2, "", "--resume", "--adopt"), capsys)
    assert status == 2
    assert message in one_line(err)
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before


def test_a_longer_history_in_the_manifest_is_refused(tmp_path, capsys):
    out = legacy_copy(tmp_path)
    assert cli(learn_args(out, 1, "", "--resume", "--adopt"), capsys)[0] == 0
    run = rundir.read(out, ["history.json", "history.npz", "checkpoint.json"])
    rundir.commit(out, run.files, kind="centralized", months_done=5,
                  configs_hash=run.manifest["config_sha256"])
    status, _, err = cli(learn_args(out, 2, "", "--resume", "--adopt"), capsys)
    assert status == 2 and "manifest.json 5" in one_line(err)
    with pytest.raises(RunDirError, match="records 5 months but history.json 1"):
        History.load(out)


# -- defect 2: results are never replaced without --force --------------------------------------
def test_a_history_without_checkpoint_is_never_replaced(tmp_path, capsys):
    for layout in ("saved", "legacy"):
        out = tmp_path / layout
        if layout == "saved":
            History.load(LEGACY[""]).save(out)
        else:
            legacy_copy(tmp_path, name=layout)
            (out / "checkpoint.json").unlink()
        before = {p.name: p.read_bytes() for p in out.iterdir()}
        status, _, err = cli(learn_args(out, 2), capsys)
        assert status == 2 and "already holds a run" in one_line(err)
        status, _, err = cli(learn_args(out, 2, "", "--resume", "--adopt"), capsys)
        assert status == 2
        assert "holds a History without checkpoint.json: it cannot be resumed" in one_line(err)
        assert {p.name: p.read_bytes() for p in out.iterdir()} == before
        assert cli(learn_args(out, 1, "", "--force"), capsys)[0] == 0
        assert History.load(out).months == 1 and (out / "checkpoint.json").exists()


def test_an_empty_out_never_writes_into_the_current_directory(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "summary.json").write_text('{"mine": 1}')
    status, _, err = cli(learn_args("", 1), capsys)
    assert status == 2 and "--out '': expected a directory path" in one_line(err)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["summary.json"]
    # '.' is a directory like any other: its summary.json is not replaced without --force
    status, _, err = cli(learn_args(".", 1), capsys)
    assert status == 2 and "already holds results (summary.json)" in one_line(err)
    status, _, err = cli(learn_args(".", 1, "", "--resume"), capsys)
    assert status == 2 and "nothing to resume" in one_line(err)
    assert (tmp_path / "summary.json").read_text() == '{"mine": 1}'


def test_force_replaces_and_resume_extends(tmp_path, capsys):
    out = tmp_path / "run"
    assert cli(learn_args(out, 1), capsys)[0] == 0
    status, _, err = cli(learn_args(out, 1, "", "--force", "--resume"), capsys)
    assert status == 2 and "exclude each other" in one_line(err)
    reference = tmp_path / "reference"
    assert cli(learn_args(reference, 2, "", "--step-size", "0.05"), capsys)[0] == 0
    status, _, err = cli(learn_args(out, 2, "", "--step-size", "0.05", "--resume"), capsys)
    assert status == 2 and "learning.step_size=" in one_line(err)
    assert cli(learn_args(out, 2, "", "--step-size", "0.05", "--force"), capsys)[0] == 0
    assert_same_run(out, reference)
    # resume with an empty directory starts a run and says so
    fresh = tmp_path / "fresh"
    status, _, err = cli(learn_args(fresh, 1, "", "--resume"), capsys)
    assert status == 0 and "starting a new one" in err


# -- defect 3: a missing npz ------------------------------------------------------------------
@pytest.mark.parametrize("layout", ["legacy", "committed"])
def test_a_missing_npz_is_refused(tmp_path, capsys, layout):
    out = legacy_copy(tmp_path)
    if layout == "committed":
        assert cli(learn_args(out, 1, "", "--resume", "--adopt"), capsys)[0] == 0
    (out / "history.npz").unlink()
    status, _, err = cli(learn_args(out, 2, "", "--resume", "--adopt"), capsys)
    assert status == 2 and "history.npz is missing" in one_line(err)
    with pytest.raises(RunDirError, match="history.npz is missing"):
        History.load(out)
    assert not (out / "history.npz").exists()


# -- defect 8: damaged files --------------------------------------------------------------------
def _truncate(path: Path) -> None:
    path.write_bytes(path.read_bytes()[:200])


DAMAGES = {
    "no rng": ("checkpoint.json", lambda p: edit_json(p, _drop("rng")), "lacks 'rng'"),
    "no theta": ("checkpoint.json", lambda p: edit_json(p, _drop("theta")), "lacks 'theta'"),
    "no system": ("checkpoint.json", lambda p: edit_json(p, _drop("system")), "lacks 'system'"),
    "bad rng": ("checkpoint.json", lambda p: edit_json(p, _set("rng", {"bit_generator": "MT"})),
                "'rng' is not a PCG64 state"),
    "bad updater": ("checkpoint.json", lambda p: edit_json(p, _set("updater", [1])),
                    "bad 'updater'"),
    "checkpoint a list": ("checkpoint.json", lambda p: p.write_text("[1, 2]"), "holds a list"),
    "checkpoint not JSON": ("checkpoint.json", lambda p: p.write_text("{"), "is not valid JSON"),
    "history deleted": ("history.json", lambda p: p.unlink(), "history.json is missing"),
    "no series": ("history.json", lambda p: edit_json(p, _drop("grad_norm")),
                  "lacks 'grad_norm'"),
    "history a list": ("history.json", lambda p: p.write_text("[]"), "holds a list"),
    "npz truncated": ("history.npz", _truncate, "history.npz cannot be read"),
}
HISTORY_DAMAGES = [k for k, v in DAMAGES.items() if v[0] != "checkpoint.json"]


@pytest.mark.parametrize("damage", list(DAMAGES))
def test_damaged_runs_are_refused_in_one_line(tmp_path, capsys, damage):
    name, apply, message = DAMAGES[damage]
    legacy = legacy_copy(tmp_path, name="legacy")
    committed = legacy_copy(tmp_path, name="committed")
    assert cli(learn_args(committed, 1, "", "--resume", "--adopt"), capsys)[0] == 0
    for out in (legacy, committed):
        apply(out / name)
        before = {p.name: p.read_bytes() for p in out.iterdir()}
        status, _, err = cli(learn_args(out, 2, "", "--resume", "--adopt"), capsys)
        assert status == 2
        line = one_line(err)
        # a legacy directory is checked field by field, a committed one by its checksums
        expected = message if out is legacy else (
            f"{name} is missing" if damage == "history deleted" else f"{name} does not match")
        assert expected in line and "--force" in line
        assert {p.name: p.read_bytes() for p in out.iterdir()} == before


@pytest.mark.parametrize("damage", HISTORY_DAMAGES)
def test_baselines_refuse_a_damaged_history_in_one_line(tmp_path, capsys, damage):
    name, apply, message = DAMAGES[damage]
    legacy = legacy_copy(tmp_path)
    apply(legacy / name)
    status, _, err = cli(["baselines", "--out", str(tmp_path / "b"), "--days", "1",
                          "--history", str(legacy)], capsys)
    assert status == 2
    assert (message if damage != "history deleted" else "history.json not found") in one_line(err)
    assert not (tmp_path / "b").exists()


def test_baselines_read_runs_of_both_formats(tmp_path, capsys):
    committed = legacy_copy(tmp_path, name="committed")
    assert cli(learn_args(committed, 1, "", "--resume", "--adopt"), capsys)[0] == 0
    results = []
    for run in (LEGACY[""], committed):
        out = tmp_path / f"b-{run.name}"
        status, _, err = cli(["baselines", "--out", str(out), "--days", "1",
                              "--history", str(run)], capsys)
        assert status == 0, err
        learned = json.loads((out / "baselines.json").read_text())["policies"]["learned"]
        results.append({k: v for k, v in learned.items() if "time" not in k})
    assert results[0] == results[1]


def test_the_wrong_learner_is_named(tmp_path, capsys):
    for learner, other, name in (("--decentralized", "", "decentralized"),
                                 ("", "--decentralized", "centralized")):
        out = legacy_copy(tmp_path, learner, name=f"{name}")
        for layout in ("legacy", "committed"):
            if layout == "committed":
                assert cli(learn_args(out, 1, learner, "--resume", "--adopt"), capsys)[0] == 0
            status, _, err = cli(learn_args(out, 2, other, "--resume", "--adopt"), capsys)
            assert status == 2 and f"holds a {name} run" in one_line(err)


# -- runs of the previous version ----------------------------------------------------------------
def test_a_run_without_manifest_is_resumed_only_when_adopted(tmp_path, capsys, caplog):
    """A committed run whose manifest was deleted and whose theta was changed by 1e-4
    (relative): nothing can verify it, so --resume refuses it; --adopt resumes it as it is,
    with a warning."""
    out = legacy_copy(tmp_path)
    assert cli(learn_args(out, 1, "", "--resume", "--adopt"), capsys)[0] == 0
    (out / "manifest.json").unlink()
    edit_json(out / "checkpoint.json",
              lambda d: {**d, "theta": [t * (1 + 1e-4) for t in d["theta"]]})
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    status, _, err = cli(learn_args(out, 2, "", "--resume"), capsys)
    assert status == 2 and "without manifest.json" in one_line(err)
    assert "--adopt" in one_line(err) and "--force" in one_line(err)
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before
    status, _, err = cli(learn_args(out, 2, "", "--adopt"), capsys)
    assert status == 2 and "--adopt without --resume" in one_line(err)
    caplog.clear()
    assert cli(learn_args(out, 2, "", "--resume", "--adopt"), capsys)[0] == 0
    assert "adopting" in caplog.text and "resumed unverified" in caplog.text
    assert (out / "manifest.json").exists() and History.load(out).months == 2


@pytest.mark.parametrize("learner", LEARNERS)
def test_runs_of_the_previous_version_load_and_resume(tmp_path, capsys, learner):
    old = History.load(LEGACY[learner])
    assert old.months == 1 and old.first_month is not None
    out = legacy_copy(tmp_path, learner)
    assert cli(learn_args(out, 2, learner, "--resume", "--adopt"), capsys)[0] == 0
    reference = tmp_path / "reference"
    # the previous version evaluated on one noise draw, explored with a projection and learned
    # one parameter set per battery; the resumed run keeps all that (LearningConfig.from_dict)
    resumed = History.load(out)
    assert resumed.learning.eval_draws == 1 and not resumed.learning.tie_agents
    assert resumed.learning.exploration_bounds == "project"
    learner_class = DecentralizedExperiment if learner else Experiment
    learner_class(resumed.system, resumed.mpc, resumed.learning.replace(months=2)).run(
        months=2, out=reference, progress=False)
    # The previous version's 'auto' back-end was the numpy interior point (centralized) and
    # the numpy coordination rounds (decentralized); today's are compiled, which agree with
    # them to rounding (tests/mpc/test_kernel.py, tests/decentralized/test_decentralized_kernel.py), not bit for
    # bit: the resumed run equals a fresh one to the tolerance of those tests (1e-8).
    assert_close_run(out, reference, rtol=1e-8)
    assert (out / "manifest.json").exists()


def assert_close_run(directory: Path, reference: Path, rtol: float) -> None:
    """Every number of the two runs agrees to ``rtol`` (relative to each series' largest)."""
    got, want = History.load(directory), History.load(reference)
    for key in History.SERIES + History.EVAL_SERIES:
        if key in ("wall_time_s", "update_info"):
            continue
        a = np.asarray(getattr(got, key), dtype=float)
        b = np.asarray(getattr(want, key), dtype=float)
        scale = max(1.0, float(np.nanmax(np.abs(b), initial=0.0)))
        np.testing.assert_allclose(a, b, rtol=0, atol=rtol * scale, equal_nan=True,
                                   err_msg=key)
    np.testing.assert_allclose(got.theta_final, want.theta_final, rtol=0, atol=rtol)
    for month in ("first_month", "last_month"):
        for key in RECORD_ARRAYS:
            a = np.asarray(getattr(getattr(got, month), key), dtype=float)
            b = np.asarray(getattr(getattr(want, month), key), dtype=float)
            np.testing.assert_allclose(a, b, rtol=0, atol=rtol * max(1.0, np.abs(b).max()),
                                       err_msg=f"{month}.{key}")


# -- defect 12: failed solves, NaN and overflow -------------------------------------------------
def strict_json(path: Path):
    def refuse(name):
        raise AssertionError(f"{path.name} holds {name}: not JSON")
    return json.loads(path.read_text(), parse_constant=refuse)


def test_all_solves_failing_writes_valid_json_and_exits_2(tmp_path, capsys, monkeypatch):
    import mpcrl_lite.cli.args as cli_module

    real = cli_module.configs

    def failing(args, **learning):  # one interior-point iteration: every solve fails
        system, mpc, learn = real(args, **learning)
        return system, mpc.replace(max_iter=1), learn

    monkeypatch.setattr(cli_module, "configs", failing)
    out = tmp_path / "run"
    status, stdout, err = cli(learn_args(out, 1), capsys)
    assert status == 2
    assert "100 % of the MPC solves failed" in one_line(err)
    assert "MAX_FAILED_SOLVE_SHARE" in one_line(err)
    meta = strict_json(out / "history.json")
    assert meta["solver_failures"] == [24] and meta["eval_bound_share"] == [None]
    strict_json(out / "summary.json")
    json.loads(stdout.strip().splitlines()[-1])
    history = History.load(out)  # the results are kept
    assert np.isnan(history.eval_bound_share[0]) and history.failed_solve_share() == 1.0


# the optimizer's own diagnostics overflow with gradients of 1e200 (they are stored as null)
@pytest.mark.filterwarnings("ignore:overflow encountered:RuntimeWarning")
def test_grad_norm_does_not_overflow(tmp_path):
    history = History(SMALL, MPCConfig(), LearningConfig(days_per_month=1))
    record = Experiment(system=SMALL, learning=LearningConfig(days_per_month=1)).evaluate()
    grad = np.full(30, 1e200)
    grad[3] = -3e200
    history.append(record, Theta.nominal(SMALL), grad, 0, 0.0, {})
    assert history.grad_norm[0] == pytest.approx(1e200 * np.sqrt(29 + 9), rel=1e-14)
    small = np.arange(30.0)
    history.append(record, Theta.nominal(SMALL), small, 0, 0.0, {})
    assert history.grad_norm[1] == np.linalg.norm(small)  # unchanged where it was finite
    # an absurd noise is refused (config.RANGES); the largest one accepted runs with every
    # figure finite or null and the file strict JSON
    with pytest.raises(ValueError, match=r"noise_var=1e\+300: expected a value in \[0, 100\]"):
        SMALL.replace(noise_var=1e300)
    learning = LearningConfig(days_per_month=1, months=1)
    run = Experiment(system=SMALL.replace(noise_var=100.0), learning=learning)
    run.run(out=tmp_path, progress=False)
    assert np.isfinite(run.history.grad_norm[0])
    strict_json(tmp_path / "history.json")


# -- defect 13: short messages, bad --out ---------------------------------------------------------
def test_config_mismatch_names_only_the_differing_fields(tmp_path):
    learning = LearningConfig(days_per_month=1, months=2, seed=7)
    Experiment(system=SMALL, learning=learning).run(months=1, out=tmp_path, progress=False)
    other = Experiment(system=SMALL.replace(P_bar=1.2), learning=learning.replace(seed=8))
    with pytest.raises(RunDirError) as err:
        other.run(out=tmp_path, resume=True, progress=False)
    message = str(err.value)
    assert "different system and learning config" in message
    assert "system.P_bar=1.5 in the run, 1.2 now" in message
    assert "learning.seed=7 in the run, 8 now" in message
    assert "SystemConfig(" not in message and len(message) < 300 and "\n" not in message


def test_out_naming_a_file_is_refused_before_any_work(tmp_path, capsys):
    afile = tmp_path / "afile"
    afile.write_text("mine")
    t0 = time.perf_counter()
    status, _, err = cli(learn_args(afile, 1), capsys)
    assert status == 2 and "is an existing file; expected a directory" in one_line(err)
    assert time.perf_counter() - t0 < 5  # refused before building the MPC
    assert afile.read_text() == "mine"


def test_out_in_a_read_only_directory_is_refused_in_one_line():
    """``learn`` in a child process without privileges ('nobody' when run as root)."""
    import tempfile

    base = Path(tempfile.mkdtemp())
    base.chmod(0o755)
    locked = base / "locked"
    locked.mkdir()
    locked.chmod(0o555)
    read, write = os.pipe()
    pid = os.fork()
    if pid == 0:
        code = 70
        try:
            os.close(read)
            os.dup2(write, 2)
            sys.stderr = io.TextIOWrapper(os.fdopen(2, "wb", closefd=False), write_through=True)
            if os.geteuid() == 0:
                os.setgid(65534)
                os.setuid(65534)
            code = main(learn_args(locked / "run", 1))
        finally:
            sys.stderr.flush()
            os._exit(code)
    os.close(write)
    with os.fdopen(read) as pipe:
        err = pipe.read()
    _, status = os.waitpid(pid, 0)
    locked.chmod(0o755)
    left = list(locked.iterdir())
    shutil.rmtree(base)
    assert os.WEXITSTATUS(status) == 2, err
    assert "cannot write there (Permission denied)" in one_line(err)
    assert left == []


def test_decentralized_learner_api_refuses_the_same(tmp_path):
    """The API of both learners: no overwrite without force, resume verified."""
    learning = LearningConfig(days_per_month=1, months=1, seed=1)
    DecentralizedExperiment(SMALL, MPCConfig(), learning).run(out=tmp_path, progress=False)
    with pytest.raises(RunDirError, match="already holds a run"):
        DecentralizedExperiment(SMALL, MPCConfig(), learning).run(out=tmp_path, progress=False)
    with pytest.raises(RunDirError, match="holds a decentralized run"):
        Experiment(SMALL, MPCConfig(), learning).run(out=tmp_path, resume=True, progress=False)
    (tmp_path / "checkpoint.json").write_text("{}")
    with pytest.raises(RunDirError, match="checkpoint.json does not match its sha256"):
        DecentralizedExperiment(SMALL, MPCConfig(), learning).run(out=tmp_path, resume=True,
                                                                   progress=False)


def test_baselines_name_only_the_differing_system_fields(tmp_path):
    from mpcrl_lite.bounds.baselines import run_baselines_cli

    system = SystemConfig(P_bar=1.2)
    learning = LearningConfig(days_per_month=1)
    with pytest.warns(UserWarning, match="P_bar=1.5 there, 1.2 here") as caught:
        run_baselines_cli(system, MPCConfig(), learning, LEGACY[""], tmp_path / "b")
    message = str(caught[0].message)
    assert "SystemConfig(" not in message and len(message) < 200
