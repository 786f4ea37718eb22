"""Monthly commits in O(1): the months between a run's first and last commit are lines
appended to the journal ``history.jsonl`` (each with its own sha256, chained to the one
before), and ``history.json``, ``history.npz``, ``checkpoint.json`` and the manifest are kept;
every directory a run leaves on the way reads back as the History of that month, a kill at
any write of the journal resumes to the uninterrupted run, a changed journal is refused and
an interrupted append is ignored."""

from __future__ import annotations

import json
import os
import shutil
import signal
from pathlib import Path

import numpy as np
import pytest
from conftest import learn_in_child

from mpcrl_lite import LearningConfig, MPCConfig, SystemConfig
from mpcrl_lite._util import jsonio
from mpcrl_lite.cli.main import main
from mpcrl_lite.decentralized.learner import DecentralizedExperiment
from mpcrl_lite.learning import durable, outdir, rundir
from mpcrl_lite.learning.experiment import Experiment
from mpcrl_lite.learning.history import History
from mpcrl_lite.learning.outdir import RunDirError
from mpcrl_lite.sim.record import RECORD_ARRAYS
from mpcrl_lite.studies.lockstep import run_lockstep

SMALL = SystemConfig(N=6)


def plain_history(history: History) -> str:
    """Everything a History holds, timings included, as exact JSON (floats by repr)."""
    data = {k: getattr(history, k) for k in History.STORED_SERIES}
    data["theta_final"], data["backend"] = history.theta_final, history.backend
    data["configs"] = history.configs()
    return json.dumps(jsonio.plain(data), sort_keys=True)


def assert_same_history(got: History, want: History) -> None:
    assert plain_history(got) == plain_history(want)
    for month in ("first_month", "last_month"):
        for key in RECORD_ARRAYS:
            np.testing.assert_array_equal(getattr(getattr(got, month), key),
                                          getattr(getattr(want, month), key))


def journal_lines(data: bytes) -> list[bytes]:
    """The appended months of a journal: each line with the payload after it."""
    lines, start = [], 0
    while start < len(data):
        end = data.index(b"\n", start)
        size = json.loads(data[start:end + 1])["payload"]
        lines.append(data[start:end + 1 + size])
        start = end + 1 + size
    return lines


def snapshots(tmp_path: Path, out: Path, seen: list):
    """A callback that copies ``out`` after every month and keeps the History then."""
    def snapshot(month, history, learner):
        copy = shutil.copytree(out, tmp_path / f"month{month + 1}")
        seen.append((copy, History.from_files(history.to_files())))
    return snapshot


@pytest.mark.parametrize("learner", [Experiment, DecentralizedExperiment])
def test_every_monthly_directory_reads_back_as_that_month(learner, tmp_path):
    out, seen = tmp_path / "run", []
    learning = LearningConfig(days_per_month=1, months=5, seed=3, eval_every=2)
    run = learner(SMALL, MPCConfig(), learning, callbacks=[snapshots(tmp_path, out, seen)])
    run.run(out=out, progress=False)
    manifests = set()
    for months, (copy, history) in enumerate(seen, start=1):
        manifest = json.loads((copy / "manifest.json").read_text())
        last = months == 5  # the first and the last commit write the whole History
        assert (rundir.JOURNAL in manifest["files"]) is not last
        assert manifest["format"] == (rundir.FORMAT if last else rundir.FORMAT_APPEND)
        assert rundir.read(copy, ["history.json"]).months_done == months
        if not last:  # the first month's manifest and files, kept as they were
            manifests.add((copy / "manifest.json").read_bytes())
            assert manifest["months_done"] == 1
            assert manifest["files"][rundir.JOURNAL]["size"] == 0
            lines = journal_lines((copy / rundir.JOURNAL).read_bytes()) if months > 1 else []
            assert len(lines) == months - 1
            assert json.loads((copy / "history.json").read_text())["J"] == history.J[:1]
        assert_same_history(History.load(copy), history)
    assert len(manifests) == 1
    assert_same_history(History.load(out), run.history)
    assert sorted(p.name for p in out.iterdir()) == sorted(
        ["manifest.json", "history.json", "history.npz", "checkpoint.json"])


def test_the_bytes_written_per_month_do_not_grow(tmp_path):
    """What a month commits (its journal line, the npz, the checkpoint) is the same size in
    month 3 and month 9: the cost of a commit does not grow with the months done."""
    out, seen = tmp_path / "run", []
    learning = LearningConfig(days_per_month=1, months=10, seed=1, eval_every=1)
    Experiment(SMALL, MPCConfig(), learning, callbacks=[snapshots(tmp_path, out, seen)]).run(
        out=out, progress=False)
    lines = journal_lines((seen[8][0] / rundir.JOURNAL).read_bytes())
    sizes = [len(line) for line in lines]
    assert len(sizes) == 8 and max(sizes) < 1.1 * min(sizes)
    for name in ("history.npz", "checkpoint.json"):  # kept from the first month
        assert (seen[2][0] / name).read_bytes() == (seen[8][0] / name).read_bytes()


def learn_args(out: Path, months: int, *extra: str) -> list[str]:
    return ["learn", "--months", str(months), "--days", "1", "--out", str(out), "--quiet",
            "--no-figures", *extra]




def test_a_kill_at_any_write_of_a_journaled_run_resumes_identically(tmp_path, capsys,
                                                                      monkeypatch):
    """A 4-month run (two months appended): killed after (or half-way through) each of its
    writes, then resumed: the results equal the uninterrupted run's, and every directory a
    kill leaves reads as a History of the months its manifest and journal record."""
    reference = tmp_path / "reference"
    appends: list[int] = []
    real = durable.append_file

    def spy(path, offset, data, **options):
        appends.append(durable._writes + 1)
        return real(path, offset, data, **options)

    monkeypatch.setattr(durable, "append_file", spy)
    start = durable._writes
    assert main(learn_args(reference, 4)) == 0
    writes = durable._writes - start
    appends = [i - start for i in appends]
    monkeypatch.undo()
    assert len(appends) == 2
    want = History.load(reference)
    checkpoint = json.loads((reference / "checkpoint.json").read_text())
    points = [(durable.KILL_AFTER_WRITE_ENV, i) for i in range(1, writes + 1)]
    points += [(durable.KILL_MID_WRITE_ENV, i) for i in appends]
    for hook, i in points:
        out = tmp_path / f"{hook[-10:]}-{i}"
        status = learn_in_child(learn_args(out, 4), {hook: str(i)})
        assert os.WIFSIGNALED(status) and os.WTERMSIG(status) == signal.SIGKILL, (hook, i)
        if (out / "manifest.json").exists():
            months = History.load(out).months
            assert months == rundir.read(out, ["history.json"]).months_done
            assert want.J[:months] == History.load(out).J
            if hook == durable.KILL_MID_WRITE_ENV:  # the half-written month is not one
                assert months == appends.index(i) + 1, (hook, i)
        capsys.readouterr()
        assert main(learn_args(out, 4, "--resume")) == 0, (hook, i, capsys.readouterr().err)
        got = History.load(out)
        for key in History.STORED_SERIES:
            if key not in ("wall_time_s", "update_info"):
                assert getattr(got, key) == getattr(want, key), (hook, i, key)
        assert got.theta_final == want.theta_final
        assert json.loads((out / "checkpoint.json").read_text()) == checkpoint, (hook, i)
        assert not (out / rundir.JOURNAL).exists()
        shutil.rmtree(out)


def journaled_run(tmp_path: Path) -> Path:
    """A directory as a run leaves it after its third month (of five): a journal of two."""
    out, seen = tmp_path / "run", []
    learning = LearningConfig(days_per_month=1, months=5, seed=2)
    Experiment(SMALL, MPCConfig(), learning, callbacks=[snapshots(tmp_path, out, seen)]).run(
        out=out, progress=False)
    return seen[2][0]


def seen_month(tmp_path: Path, month: int) -> Path:
    """The copy :func:`journaled_run` kept of the directory after ``month`` (from 0)."""
    return tmp_path / f"month{month + 1}"


@pytest.mark.parametrize("tail", ["start", "half", "cut"])
def test_an_interrupted_append_is_ignored_and_cut(tmp_path, tail):
    """What a kill (or a power cut) during an append leaves: the start of a line, half of
    one, or the last line without its end; the run reads as the months before it."""
    run = journaled_run(tmp_path)
    want = History.load(run)
    path = run / rundir.JOURNAL
    lines = journal_lines(path.read_bytes())
    if tail == "cut":
        path.write_bytes(b"".join(lines[:-1]) + lines[-1][:-2])
        want = History.load(seen_month(tmp_path, 1))
    else:
        with open(path, "ab") as f:
            f.write(lines[-1][:20] if tail == "start" else lines[-1][: len(lines[-1]) // 2])
    assert_same_history(History.load(run), want)
    learning = LearningConfig(days_per_month=1, months=5, seed=2)
    exp = Experiment(SMALL, MPCConfig(), learning)
    exp.run(months=4, out=run, resume=True, progress=False)
    reference = Experiment(SMALL, MPCConfig(), learning)
    reference.run(months=4, progress=False)
    assert exp.history.J == reference.history.J
    assert History.load(run).J == reference.history.J


@pytest.mark.parametrize("change", ["byte", "shorter", "dropped"])
def test_a_changed_journal_is_refused(tmp_path, capsys, change):
    """A committed line changed, cut or left out before another one: refused (only the last
    line can be an interrupted write)."""
    run = journaled_run(tmp_path)
    path = run / rundir.JOURNAL
    data = path.read_bytes()
    first, second = journal_lines(data)
    path.write_bytes({"byte": data.replace(b'"months": 2', b'"months": 7'),
                      "shorter": first[:-10] + b"\n" + second,
                      "dropped": second}[change])
    before = {p.name: p.read_bytes() for p in run.iterdir() if p.name != outdir.LOCK}
    message = "history.jsonl does not match its sha256"
    with pytest.raises(RunDirError, match=message):
        History.load(run)
    status = main(learn_args(run, 5, "--resume"))
    assert status == 2 and message in capsys.readouterr().err
    # nothing of the run touched (the command's lock file is not part of the run)
    assert {p.name: p.read_bytes() for p in run.iterdir() if p.name != outdir.LOCK} == before


def test_a_stale_journal_next_to_a_whole_history_is_ignored_and_removed(tmp_path):
    """A kill after a whole commit, before the old journal was removed."""
    run = journaled_run(tmp_path)
    stale = (run / rundir.JOURNAL).read_bytes()
    done = tmp_path / "done"
    shutil.copytree(tmp_path / "run", done)  # the finished run (no journal)
    (done / rundir.JOURNAL).write_bytes(stale)
    want = History.load(tmp_path / "run")
    assert_same_history(History.load(done), want)
    rundir.read(done, ["history.json"], repair=True)
    assert not (done / rundir.JOURNAL).exists()


def test_lockstep_writes_the_files_of_the_runs_alone(tmp_path):
    def runs(callbacks):
        return [Experiment(SystemConfig(N=6, noise_var=v), MPCConfig(),
                           LearningConfig(days_per_month=2, months=4, seed=s),
                           callbacks=[c])
                for (s, v), c in zip([(1, 0.5), (2, 0.3)], callbacks, strict=True)]

    seen: list[list] = [[], []]
    alone = runs([snapshots(tmp_path / f"alone{i}", tmp_path / f"a{i}", seen[i])
                  for i in range(2)])
    for i, run in enumerate(alone):
        run.run(out=tmp_path / f"a{i}", progress=False)
    stacked_seen: list[list] = [[], []]
    stacked = runs([snapshots(tmp_path / f"stacked{i}", tmp_path / f"s{i}", stacked_seen[i])
                    for i in range(2)])
    run_lockstep(stacked, outs=[tmp_path / "s0", tmp_path / "s1"])
    for i in range(2):
        for (a, _), (s, _) in zip(seen[i], stacked_seen[i], strict=True):
            got, want = History.load(s), History.load(a)
            assert got.J == want.J and got.theta_final == want.theta_final
            def files(d):  # the run's files (a process's lock file is not part of the run)
                return sorted(p.name for p in d.iterdir() if p.name != outdir.LOCK)

            assert files(s) == files(a)
            manifest = [json.loads((d / "manifest.json").read_text()) for d in (s, a)]
            assert manifest[0]["format"] == manifest[1]["format"]
            assert sorted(manifest[0]["files"]) == sorted(manifest[1]["files"])


# an appended month's write: one pwritev of its buffers where the system has it
_APPEND_WRITE = "pwritev" if hasattr(os, "pwritev") else "pwrite"


@pytest.mark.parametrize("failing", ["fsync", _APPEND_WRITE])
def test_a_failed_commit_stops_the_run_and_keeps_the_months_before(tmp_path, monkeypatch,
                                                                   failing):
    """A full disk during a commit: a month's whole files or appended line (``pwritev``),
    written while the next month computes, raise by the next month's checkpoint, the last
    month's at once; an OSError, the months committed before it intact, and the run resumes
    to the uninterrupted results."""
    import errno

    learning = LearningConfig(days_per_month=1, months=4, seed=5)
    reference = Experiment(SMALL, MPCConfig(), learning)
    reference.run(out=tmp_path / "reference", progress=False)
    real = getattr(os, failing)
    lags = set()
    for i in ((1, 3, 6, 9, 14) if failing == "fsync" else (1, 2)):
        out = tmp_path / f"full{i}"
        calls = []

        def full(*args, _calls=calls, _i=i):
            _calls.append(args)
            if len(_calls) == _i:
                raise OSError(errno.ENOSPC, "No space left on device")
            return real(*args)

        monkeypatch.setattr(os, failing, full)
        exp = Experiment(SMALL, MPCConfig(), learning)
        try:
            exp.run(out=out, progress=False)
        except durable.RunWriteError as err:
            assert "No space left on device" in str(err)
            committed = rundir.read(out, ["history.json"]).months_done if (
                out / "manifest.json").exists() else 0
            lag = exp.history.months - committed
            # every month's commit but the last is written while the next month computes,
            # and its error raised by that month's checkpoint
            assert lag in (1, 2), (i, lag, committed)
            lags.add(lag)
        monkeypatch.undo()
        resumed = Experiment(SMALL, MPCConfig(), learning)
        resumed.run(out=out, resume=True, progress=False)
        assert_same_history_but_timings(History.load(out), reference.history)
    assert lags == ({1, 2} if failing == "fsync" else {2})


def assert_same_history_but_timings(got: History, want: History) -> None:
    for key in History.STORED_SERIES:
        if key not in ("wall_time_s", "update_info"):
            assert getattr(got, key) == getattr(want, key), key
    assert got.theta_final == want.theta_final
    for month in ("first_month", "last_month"):
        for key in RECORD_ARRAYS:
            np.testing.assert_array_equal(getattr(getattr(got, month), key),
                                          getattr(getattr(want, month), key))


def test_the_run_directory_appends_and_keeps(tmp_path):
    """rundir.commit with keep/append: the kept entry stays as it was, the journal is the
    concatenation of the appends, bytes after its committed size are not part of it, and a
    whole commit drops the journal."""
    base = {"history.json": b'{"a": 1}', "history.npz": b"npz", "checkpoint.json": b"{}"}
    options = {"kind": "centralized", "configs_hash": "0" * 64}
    first = rundir.commit(tmp_path, base, months_done=1, **options)
    manifest = first
    for month, line in ((2, b"one\n"), (3, b"two\n")):
        manifest = rundir.commit(tmp_path, {"checkpoint.json": b"{%d}" % month},
                                 months_done=month, previous=manifest, keep=["history.json"],
                                 append={rundir.JOURNAL: line}, **options)
    assert manifest["format"] == rundir.FORMAT_APPEND
    assert manifest["files"]["history.json"] == first["files"]["history.json"]
    assert "history.npz" not in manifest["files"]
    run = rundir.read(tmp_path, ["history.json", rundir.JOURNAL, "checkpoint.json"])
    assert run.files == {"history.json": b'{"a": 1}', rundir.JOURNAL: b"one\ntwo\n",
                         "checkpoint.json": b"{3}"}
    with open(tmp_path / rundir.JOURNAL, "ab") as f:
        f.write(b"thr")  # an append that never reached its commit
    assert rundir.read(tmp_path, [rundir.JOURNAL]).files[rundir.JOURNAL] == b"one\ntwo\n"
    again = rundir.commit(tmp_path, {"checkpoint.json": b"{4}"}, months_done=4,
                          previous=manifest, keep=["history.json"],
                          append={rundir.JOURNAL: b"four\n"}, **options)
    assert (tmp_path / rundir.JOURNAL).read_bytes() == b"one\ntwo\nfour\n"
    with pytest.raises(ValueError, match="keep"):
        rundir.commit(tmp_path, {}, months_done=5, previous=again, keep=["history.npz"],
                      **options)
    rundir.commit(tmp_path, base, months_done=5, **options)
    assert not (tmp_path / rundir.JOURNAL).exists()
    assert json.loads((tmp_path / "manifest.json").read_text())["format"] == rundir.FORMAT


def test_a_critic_of_several_months_commits_its_months_through_the_manifest(tmp_path):
    """A learner with files of its own (the critic's earlier months, ``critic.npz``) commits
    every month through the manifest, its journal line with the arrays inline; each month's
    directory reads back as that month and resumes to the uninterrupted results."""
    out, seen = tmp_path / "run", []
    learning = LearningConfig(days_per_month=2, months=5, seed=3, critic_months=2)
    run = Experiment(SMALL, MPCConfig(), learning, callbacks=[snapshots(tmp_path, out, seen)])
    run.run(out=out, progress=False)
    for months, (copy, history) in enumerate(seen, start=1):
        manifest = json.loads((copy / "manifest.json").read_text())
        assert manifest["months_done"] == months and rundir.CRITIC in manifest["files"]
        journal = manifest["files"].get(rundir.JOURNAL)
        assert (journal is not None) is (months not in (1, 5))
        if journal is not None:  # through the manifest: no token, lines of plain JSON
            assert "token" not in journal
            lines = (copy / rundir.JOURNAL).read_bytes().splitlines()
            assert len(lines) == months - 1
            assert "data" in json.loads(lines[-1])["last_month"]["soc"]
        assert_same_history(History.load(copy), history)
    middle = seen[2][0]
    resumed = Experiment(SMALL, MPCConfig(), learning)
    resumed.run(out=middle, resume=True, progress=False)
    assert_same_history_but_timings(History.load(middle), run.history)


def test_a_long_journal_is_folded_into_the_whole_files(tmp_path, monkeypatch):
    """Past JOURNAL_LIMIT bytes the next month writes the whole files with a new, empty
    journal: months then alternate here (a limit of one byte), and every directory still
    reads back as its month."""
    from mpcrl_lite.learning import checkpoint

    monkeypatch.setattr(checkpoint, "JOURNAL_LIMIT", 1)
    out, seen = tmp_path / "run", []
    learning = LearningConfig(days_per_month=1, months=6, seed=4)
    run = Experiment(SMALL, MPCConfig(), learning, callbacks=[snapshots(tmp_path, out, seen)])
    run.run(out=out, progress=False)
    tokens = []
    for months, (copy, history) in enumerate(seen, start=1):
        manifest = json.loads((copy / "manifest.json").read_text())
        # whole files at months 1, 3, 5 (and the last), a line appended at 2 and 4
        assert manifest["months_done"] == (months if months % 2 or months == 6 else months - 1)
        if months < 6:
            tokens.append(manifest["files"][rundir.JOURNAL]["token"])
        assert_same_history(History.load(copy), history)
    assert len(set(tokens)) == 3
    reference = Experiment(SMALL, MPCConfig(), learning)
    reference.run(progress=False)
    assert_same_history_but_timings(History.load(out), reference.history)


@pytest.mark.parametrize("shape", [(1,), (4,), (720, 3), (24, 30, 10, 3)])
def test_a_journal_line_writes_shapes_as_json_does(shape):
    from mpcrl_lite.learning import history as history_module

    class Month:
        pass

    month = Month()
    for name in history_module.RECORD_ARRAYS:
        setattr(month, name, np.zeros(shape))
    arrays, _ = history_module._month_arrays(month, inline=False)
    for entry in json.loads(arrays).values():
        assert entry["shape"] == list(shape)
    assert (b'"shape":%s,' % json.dumps(list(shape)).encode()) in arrays


@pytest.mark.parametrize("learner", [Experiment, DecentralizedExperiment])
def test_a_months_line_is_written_beside_the_next_months_update(learner, tmp_path,
                                                                monkeypatch):
    """Without callbacks a month's journal line goes to the writer thread once the next
    month has been simulated (its update then leaves a core idle), and the run's directory
    ends as the History of the run, the same as a run committed month by month."""
    handed = []
    real = rundir.append_month_soon

    def spy(directory, record, *, months_done, payload=()):
        handed.append((months_done, run.history.months))
        return real(directory, record, months_done=months_done, payload=payload)

    monkeypatch.setattr(rundir, "append_month_soon", spy)
    learning = LearningConfig(days_per_month=1, months=4, seed=3, eval_every=2)
    run = learner(SMALL, MPCConfig(), learning)
    run.run(out=tmp_path / "beside", progress=False)
    # months 2 and 3 appended (1 and 4 are whole commits), each while the next month's
    # update ran: that month simulated, not yet recorded
    assert handed == [(2, 2), (3, 3)]
    monkeypatch.undo()
    at_once = learner(SMALL, MPCConfig(), learning, callbacks=[lambda *args: None])
    at_once.run(out=tmp_path / "at_once", progress=False)
    for directory in ("beside", "at_once"):
        got = History.load(tmp_path / directory)
        assert got.J == run.history.J and got.theta == run.history.theta
    assert_same_history(History.load(tmp_path / "beside"), run.history)
