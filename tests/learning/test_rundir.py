"""The run directory format: one commit point, verified reads, strict JSON, output checks."""

from __future__ import annotations

import errno
import hashlib
import json
import os
import shutil
import tempfile
from pathlib import Path

import numpy as np
import pytest

from mpcrl_lite._util import jsonio
from mpcrl_lite.learning import durable, outdir, rundir
from mpcrl_lite.learning.durable import RunWriteError
from mpcrl_lite.learning.outdir import RunDirError, RunDirMissing

FILES = {"history.json": b'{"a": 1}', "history.npz": b"\x00binary\xff", "checkpoint.json": b"{}"}


def commit(directory: Path, files=FILES, months: int = 1) -> dict:
    return rundir.commit(directory, files, kind="centralized", months_done=months,
                         configs_hash="0" * 64)


def test_commit_writes_visible_files_and_one_manifest(tmp_path):
    manifest = commit(tmp_path)
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([*FILES, "manifest.json"])
    for name, data in FILES.items():
        assert (tmp_path / name).read_bytes() == data
        entry = manifest["files"][name]
        assert entry["sha256"] == hashlib.sha256(data).hexdigest()
        assert entry["size"] == len(data)
    on_disk = json.loads((tmp_path / "manifest.json").read_text())
    assert on_disk == manifest
    assert set(on_disk) == {"format", "kind", "months_done", "config_sha256", "files"}
    assert on_disk["format"] == rundir.FORMAT and on_disk["months_done"] == 1
    run = rundir.read(tmp_path, list(FILES))
    assert run.files == FILES and run.kind == "centralized" and run.months_done == 1
    # the next commit replaces everything; nothing of the first is left
    new = {k: v + b" " for k, v in FILES.items()}
    commit(tmp_path, new, months=2)
    assert rundir.read(tmp_path, list(FILES)).files == new
    assert not (tmp_path / rundir.STAGING).exists()


def test_a_changed_file_is_refused_in_one_line(tmp_path):
    commit(tmp_path)
    (tmp_path / "history.json").write_bytes(b'{"a": 2}')
    with pytest.raises(RunDirError, match=r"history.json does not match its sha256") as err:
        rundir.read(tmp_path, list(FILES))
    assert "\n" not in str(err.value) and "--force" in str(err.value)
    (tmp_path / "history.npz").unlink()
    with pytest.raises(RunDirError, match=r"history.npz is missing"):
        rundir.read(tmp_path, ["history.npz"])


def test_commit_interrupted_after_the_manifest_reads_the_staged_files(tmp_path, monkeypatch):
    commit(tmp_path)
    new = {k: v + b"!" for k, v in FILES.items()}

    def no_publish(*args, **kwargs):  # the process dies right after the commit
        return None

    monkeypatch.setattr(rundir, "_publish", no_publish)
    commit(tmp_path, new, months=2)
    monkeypatch.undo()
    # the visible names still hold month 1, the manifest names month 2: the staged files win
    assert (tmp_path / "history.json").read_bytes() == FILES["history.json"]
    run = rundir.read(tmp_path, list(FILES))
    assert run.files == new and run.months_done == 2
    assert (tmp_path / "history.json").read_bytes() == FILES["history.json"]  # read-only
    rundir.read(tmp_path, list(FILES), repair=True)
    assert (tmp_path / "history.json").read_bytes() == new["history.json"]
    assert not (tmp_path / rundir.STAGING).exists()


@pytest.mark.parametrize("failing", ["fsync", "replace", "link"])
def test_a_full_disk_at_any_write_keeps_a_whole_commit(tmp_path, monkeypatch, failing):
    """ENOSPC at the i-th call: before the commit the write fails and month 1 stays; after
    it month 2 is committed (the visible names are fixed by the next reader or writer)."""
    real = getattr(os, failing)
    new = {k: v + b"?" for k, v in FILES.items()}
    outcomes = set()
    for i in range(1, 12):
        directory = tmp_path / str(i)
        commit(directory)
        calls = []

        def full(*args, _i=i, _calls=calls):
            _calls.append(args)
            if len(_calls) == _i:
                raise OSError(errno.ENOSPC, "No space left on device")
            return real(*args)

        monkeypatch.setattr(os, failing, full)
        try:
            commit(directory, new, months=2)
            outcome = "committed"
        except RunWriteError as err:
            assert "No space left on device" in str(err)
            assert "previous commit is kept" in str(err)
            outcome = "kept"
        monkeypatch.undo()
        run = rundir.read(directory, list(FILES), repair=True)
        assert run.files == (new if outcome == "committed" else FILES), (failing, i)
        assert run.months_done == (2 if outcome == "committed" else 1)
        assert not (directory / rundir.STAGING).exists()
        assert sorted(p.name for p in directory.iterdir()) == sorted([*FILES, "manifest.json"])
        outcomes.add(outcome)
    assert outcomes == ({"committed"} if failing == "link" else {"kept", "committed"})


@pytest.mark.parametrize(
    "content, message",
    [
        (b"{not json", "cannot be read"),
        (b"[1, 2]", "holds a list"),
        (json.dumps({"format": "other/1"}).encode(), "format 'other/1'"),
    ],
)
def test_a_damaged_manifest_is_refused(tmp_path, content, message):
    commit(tmp_path)
    (tmp_path / "manifest.json").write_bytes(content)
    with pytest.raises(RunDirError, match=message) as err:
        rundir.read(tmp_path, list(FILES))
    assert "\n" not in str(err.value)


def test_manifest_fields_are_checked(tmp_path):
    manifest = commit(tmp_path)
    for key, value, message in [
        ("months_done", -1, "months_done -1"),
        ("kind", "mine", "kind 'mine'"),
        ("files", {"history.json": {"sha256": "x"}}, "malformed"),
        ("files", {"history.json": {**manifest["files"]["history.json"],
                                    "staged": "../../etc/passwd"}}, "malformed"),
    ]:
        (tmp_path / "manifest.json").write_text(json.dumps({**manifest, key: value}))
        with pytest.raises(RunDirError, match=message):
            rundir.read(tmp_path, ["history.json"])


def test_legacy_directories_are_read_as_they_are(tmp_path):
    with pytest.raises(RunDirMissing, match="history.json not found"):
        rundir.read(tmp_path, ["history.json"])
    with pytest.raises(FileNotFoundError):
        rundir.read(tmp_path / "nowhere", ["history.json"])
    (tmp_path / "history.json").write_text("{}")
    run = rundir.read(tmp_path, ["history.json", "history.npz"], optional=["history.npz"])
    assert run.legacy and run.kind is None and run.files == {"history.json": b"{}"}
    with pytest.raises(RunDirError, match="history.npz is missing next to"):
        rundir.read(tmp_path, ["history.json", "history.npz"])


def test_clear_removes_the_manifest_and_the_run(tmp_path):
    commit(tmp_path)
    (tmp_path / "summary.json").write_text("{}")
    (tmp_path / "mine.txt").write_text("kept")
    rundir.clear(tmp_path, others=["summary.json"])
    assert sorted(p.name for p in tmp_path.iterdir()) == ["mine.txt"]
    assert not rundir.inspect(tmp_path).holds_run


def test_dumps_writes_strict_json():
    data = {"x": float("nan"), "y": [np.float64(np.inf), -np.inf, 1.5], "z": np.arange(2),
            "w": np.int64(3)}
    text = jsonio.dumps(data).decode()

    def no_constants(name):
        raise AssertionError(f"{name} is not JSON")

    assert json.loads(text, parse_constant=no_constants) == {
        "x": None, "y": [None, None, 1.5], "z": [0, 1], "w": 3}
    assert jsonio.plain({"a": (1, np.float32(0.5))}) == {"a": [1, 0.5]}
    with pytest.raises(TypeError, match="cannot store object"):
        jsonio.dumps({"a": object()})


def test_config_hash_ignores_key_order():
    a = rundir.config_sha256({"system": {"n": 3, "P_bar": 1.5}, "mpc": {"tau": 0.1}})
    b = rundir.config_sha256({"mpc": {"tau": 0.1}, "system": {"P_bar": 1.5, "n": 3}})
    c = rundir.config_sha256({"mpc": {"tau": 0.2}, "system": {"P_bar": 1.5, "n": 3}})
    assert a == b != c and len(a) == 64


def test_write_atomic_replaces_whole_files(tmp_path):
    target = tmp_path / "summary.json"
    durable.write_atomic(target, b"one")
    durable.write_atomic(target, b"two")
    assert target.read_bytes() == b"two"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["summary.json"]


def test_check_output_dir(tmp_path):
    with pytest.raises(RunDirError, match=r"--out '': expected a directory path"):
        outdir.check_output_dir("")
    afile = tmp_path / "afile"
    afile.write_text("x")
    with pytest.raises(RunDirError, match="is an existing file; expected a directory"):
        outdir.check_output_dir(afile)
    with pytest.raises(RunDirError, match="cannot write there"):
        outdir.check_output_dir(afile / "below")
    made = outdir.check_output_dir(tmp_path / "a" / "b")
    assert made.is_dir() and list(made.iterdir()) == []


def test_check_output_dir_refuses_a_read_only_directory():
    """In a child process without privileges (root may write anywhere: the child becomes
    'nobody' when started as root)."""
    base = Path(tempfile.mkdtemp())  # pytest's tmp_path is closed to other users
    base.chmod(0o755)
    locked = base / "locked"
    locked.mkdir()
    locked.chmod(0o555)
    read, write = os.pipe()
    pid = os.fork()
    if pid == 0:  # the child: report the message through the pipe, never return to pytest
        code = 0
        try:
            os.close(read)
            if os.geteuid() == 0:
                os.setgid(65534)
                os.setuid(65534)
            outdir.check_output_dir(locked / "run")
        except RunDirError as err:
            os.write(write, str(err).encode())
            code = 3
        except BaseException:
            code = 4
        os._exit(code)
    os.close(write)
    with os.fdopen(read) as pipe:
        message = pipe.read()
    _, status = os.waitpid(pid, 0)
    locked.chmod(0o755)
    left = list(locked.iterdir())
    shutil.rmtree(base)
    assert os.WEXITSTATUS(status) == 3, message
    assert "cannot write there (Permission denied); expected a writable directory" in message
    assert left == []


# -- outputs written by other writers (figures, notebooks) ----------------------------------
def test_atomic_output_replaces_whole_or_not_at_all(tmp_path):
    path = tmp_path / "fig.png"
    path.write_bytes(b"old figure")
    with pytest.raises(RuntimeError, match="killed"), durable.atomic_output(path) as tmp:
        assert tmp.parent == tmp_path and tmp.suffix == ".png" and tmp != path
        tmp.write_bytes(b"half a fig")
        raise RuntimeError("killed half-way")
    assert path.read_bytes() == b"old figure"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["fig.png"]  # nothing partial left
    with durable.atomic_output(path) as tmp:
        tmp.write_bytes(b"new figure")
        assert path.read_bytes() == b"old figure"  # until the block ends
    assert path.read_bytes() == b"new figure"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["fig.png"]
    # a writer that wrote nothing: the old file stays, the error is a RunWriteError
    with pytest.raises(RunWriteError, match="could not write"), durable.atomic_output(path):
        pass
    assert path.read_bytes() == b"new figure"
    # failed=: what the writer left is kept aside for inspection
    kept = tmp_path / "nb.failed.ipynb"
    with pytest.raises(RuntimeError), durable.atomic_output(tmp_path / "nb.ipynb",
                                                           failed=kept) as tmp:
        tmp.write_text("executed up to the failing cell")
        raise RuntimeError("a cell failed")
    assert not (tmp_path / "nb.ipynb").exists()
    assert (tmp_path / "nb.failed.ipynb").read_text() == "executed up to the failing cell"


def test_a_figure_that_fails_half_way_leaves_the_old_one(tmp_path, monkeypatch):
    """save_paper_figures (``learn``'s figures): a write killed half-way leaves the figure of
    the previous call, never a truncated file."""
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib.figure import Figure

    from mpcrl_lite.figures.paper import PAPER_FIGURES, save_paper_figures
    from mpcrl_lite.learning.history import History

    history = History.load(Path(__file__).resolve().parents[1] / "fixtures" / "run_v0_centralized")
    save_paper_figures(history, tmp_path)
    before = {name: (tmp_path / name).read_bytes() for name in PAPER_FIGURES}
    assert all(data.startswith(b"\x89PNG") for data in before.values())
    real = Figure.savefig
    calls = []

    def dying(self, fname, *args, **kwargs):
        calls.append(fname)
        if len(calls) == 2:  # the second figure: half of it written, then the process dies
            real(self, fname, *args, **kwargs)
            data = Path(fname).read_bytes()
            Path(fname).write_bytes(data[: len(data) // 2])
            raise KeyboardInterrupt
        return real(self, fname, *args, **kwargs)

    monkeypatch.setattr(Figure, "savefig", dying)
    with pytest.raises(KeyboardInterrupt):
        save_paper_figures(history, tmp_path)
    assert Path(calls[1]).name != PAPER_FIGURES[1]  # written aside, not in place
    for name in PAPER_FIGURES:
        assert (tmp_path / name).read_bytes().startswith(b"\x89PNG")
    assert (tmp_path / PAPER_FIGURES[1]).read_bytes() == before[PAPER_FIGURES[1]]
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(PAPER_FIGURES)


def test_a_report_notebook_that_fails_is_not_left_as_the_result(tmp_path, monkeypatch):
    """run_report writes each executed notebook aside and renames it when papermill is done;
    a failing notebook leaves ``<name>.failed.ipynb`` and no ``<name>.ipynb``."""
    from mpcrl_lite.publish import report

    def failing(path, output, parameters=None, cwd=None, timeout=3600):
        Path(output).write_text('{"cells": [')  # papermill saves after every cell
        raise RuntimeError("cell 3 raised")

    monkeypatch.setattr(report, "execute_notebook", failing)
    monkeypatch.setattr(report, "copy_mathjax", lambda out: out)
    name = report.notebook_paths(None)[0]
    with pytest.raises(RuntimeError, match="cell 3"):
        report.run_report(tmp_path / "r", profile="ci", notebooks=[name.stem])
    names = sorted(p.name for p in (tmp_path / "r").iterdir())
    assert names == [f"{name.stem}.failed.ipynb"]


# -- months appended without a manifest ------------------------------------------------------
def journal_commit(directory: Path, months: int = 1) -> dict:
    return rundir.commit(directory, FILES, kind="centralized", months_done=months,
                         configs_hash="0" * 64, journal=True)


def test_appended_months_count_line_by_line(tmp_path):
    manifest = journal_commit(tmp_path)
    entry = manifest["files"][rundir.JOURNAL]
    assert manifest["format"] == rundir.FORMAT_APPEND and entry["size"] == 0
    assert rundir.read(tmp_path, ["history.json"]).months_done == 1
    sizes = [rundir.append_month(tmp_path, b'{"m": %d}' % m, months_done=m) for m in (2, 3, 4)]
    assert sizes == sorted(sizes) and sizes[-1] == (tmp_path / rundir.JOURNAL).stat().st_size
    # the manifest is the first month's; the lines commit the others
    assert json.loads((tmp_path / "manifest.json").read_text()) == manifest
    run = rundir.read(tmp_path, ["history.json", rundir.JOURNAL])
    assert run.months_done == 4 and run.manifest["months_done"] == 1
    assert run.files[rundir.JOURNAL] == b'{"m": 2}\n{"m": 3}\n{"m": 4}\n'
    # asked for other files only, the months are still the lines'
    assert rundir.read(tmp_path, ["history.json"]).months_done == 4
    assert rundir.JOURNAL not in rundir.read(tmp_path, ["history.json"]).files
    # each line carries its own sha256 and the one of the line before it
    lines = (tmp_path / rundir.JOURNAL).read_bytes().splitlines()
    heads = [json.loads(line) for line in lines]
    assert [h["months_done"] for h in heads] == [2, 3, 4]
    assert heads[0]["previous"] == hashlib.sha256(b"").hexdigest()
    assert [h["previous"] for h in heads[1:]] == [h["sha256"] for h in heads[:-1]]
    assert {h["token"] for h in heads} == {entry["token"]}


def test_append_month_refuses_what_does_not_follow(tmp_path):
    with pytest.raises(ValueError, match="journal=True"):
        rundir.append_month(tmp_path, b"{}", months_done=2)
    commit(tmp_path)  # a commit without a journal
    with pytest.raises(ValueError, match="journal=True"):
        rundir.append_month(tmp_path, b"{}", months_done=2)
    journal_commit(tmp_path, months=3)
    for bad in (3, 5, True):
        with pytest.raises(ValueError, match="expected 4"):
            rundir.append_month(tmp_path, b"{}", months_done=bad)
    with pytest.raises(ValueError, match="newline"):
        rundir.append_month(tmp_path, b"{}\n{}", months_done=4)
    assert not (tmp_path / rundir.JOURNAL).exists()  # nothing written by a refused call
    rundir.append_month(tmp_path, b"{}", months_done=4)
    rundir.clear(tmp_path)
    with pytest.raises(ValueError, match="journal=True"):
        rundir.append_month(tmp_path, b"{}", months_done=5)


def test_lines_of_an_earlier_commit_are_ignored_then_cut(tmp_path):
    journal_commit(tmp_path)
    for m in (2, 3):
        rundir.append_month(tmp_path, b'{"old": %d}' % m, months_done=m)
    journal_commit(tmp_path, months=3)  # a new token: the old lines are not this commit's
    run = rundir.read(tmp_path, [rundir.JOURNAL])
    assert run.months_done == 3 and run.files[rundir.JOURNAL] == b""
    rundir.append_month(tmp_path, b'{"new": 4}', months_done=4)
    assert b"old" not in (tmp_path / rundir.JOURNAL).read_bytes()
    assert rundir.read(tmp_path, [rundir.JOURNAL]).files[rundir.JOURNAL] == b'{"new": 4}\n'
    commit(tmp_path, months=4)  # whole files without a journal: it goes
    assert not (tmp_path / rundir.JOURNAL).exists()
    assert rundir.read(tmp_path, ["history.json"]).months_done == 4


@pytest.mark.parametrize("every", [0.0, 3600.0])
def test_appended_months_are_fsynced_at_most_every_few_seconds(tmp_path, monkeypatch, every):
    monkeypatch.setattr(rundir, "SYNC_EVERY_S", every)
    journal_commit(tmp_path)
    synced = []
    real = os.fsync
    monkeypatch.setattr(os, "fsync", lambda fd: (synced.append(fd), real(fd))[1])
    for m in (2, 3, 4):
        rundir.append_month(tmp_path, b"{}", months_done=m)
    # every append then the file and its directory; or none within the hour
    assert len(synced) == (6 if every == 0.0 else 0)


def test_a_full_disk_during_an_append_keeps_the_months_before(tmp_path, monkeypatch):
    journal_commit(tmp_path)
    rundir.append_month(tmp_path, b'{"m": 2}', months_done=2)
    write = "pwritev" if hasattr(os, "pwritev") else "pwrite"  # what an append calls
    pwrite = os.pwrite

    def full(fd, data, offset):
        first = data[0] if write == "pwritev" else data  # its buffers, or its bytes
        pwrite(fd, bytes(first)[:5], offset)  # part of the line reached the disk
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(os, write, full)
    with pytest.raises(RunWriteError, match="month 3 .* months before it are kept"):
        rundir.append_month(tmp_path, b'{"m": 3}', months_done=3)
    monkeypatch.undo()
    run = rundir.read(tmp_path, [rundir.JOURNAL])
    assert run.months_done == 2 and run.files[rundir.JOURNAL] == b'{"m": 2}\n'
    rundir.append_month(tmp_path, b'{"m": 3}', months_done=3)  # the torn bytes are cut
    assert rundir.read(tmp_path, [rundir.JOURNAL]).months_done == 3


def test_a_month_appended_in_the_background_reads_as_one_appended_at_once(tmp_path):
    """append_month_soon: the same journal bytes as append_month, its payload written from
    several buffers without joining them; a reader (and appended_size) waits for it."""
    payload = [np.arange(5.0), np.array([True, False]), memoryview(b"tail")]
    joined = b"".join(bytes(memoryview(p).cast("B")) for p in payload)
    at_once, soon = tmp_path / "at_once", tmp_path / "soon"
    for directory in (at_once, soon):
        directory.mkdir()
        journal_commit(directory)
    for m in (2, 3):
        rundir.append_month(at_once, b'{"m": %d}' % m, months_done=m, payload=payload)
        pending = rundir.append_month_soon(soon, b'{"m": %d}' % m, months_done=m,
                                           payload=payload)
        assert rundir.appended_size(soon) == rundir.appended_size(at_once)
        assert pending.done() and pending.result() == rundir.appended_size(soon)
    # the same lines but for the token (a random one per journal) and the sha256s
    assert (soon / rundir.JOURNAL).stat().st_size == (at_once / rundir.JOURNAL).stat().st_size
    assert rundir.read(at_once, [rundir.JOURNAL]).payload == joined
    run = rundir.read(soon, [rundir.JOURNAL])
    assert run.months_done == 3 and run.payload == joined


def test_a_month_appended_in_the_background_is_checked_before_it_returns(tmp_path):
    journal_commit(tmp_path)
    with pytest.raises(ValueError, match="months_done=3: expected 2"):
        rundir.append_month_soon(tmp_path, b'{"m": 3}', months_done=3)
    with pytest.raises(ValueError, match="no commit of this process lists a journal"):
        rundir.append_month_soon(tmp_path / "elsewhere", b"{}", months_done=2)


def test_a_failed_append_in_the_background_raises_from_its_result(tmp_path, monkeypatch):
    journal_commit(tmp_path)
    write = "pwritev" if hasattr(os, "pwritev") else "pwrite"

    def full(*args):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(os, write, full)
    pending = rundir.append_month_soon(tmp_path, b'{"m": 2}', months_done=2)
    with pytest.raises(RunWriteError, match="month 2 .* months before it are kept"):
        pending.result()
    monkeypatch.undo()
    assert rundir.read(tmp_path, [rundir.JOURNAL]).months_done == 1
    rundir.append_month(tmp_path, b'{"m": 2}', months_done=2)
    assert rundir.read(tmp_path, [rundir.JOURNAL]).months_done == 2


@pytest.mark.skipif(not hasattr(os, "fork"), reason="fork is POSIX")
def test_a_forked_child_writes_in_the_background_on_a_writer_of_its_own(tmp_path):
    """The parent's writer thread does not exist in a forked child: the child starts its
    own (else its first background write would wait for ever)."""
    (tmp_path / "parent").mkdir()
    journal_commit(tmp_path / "parent")
    rundir.append_month_soon(tmp_path / "parent", b'{"m": 2}', months_done=2).result()
    child_dir = tmp_path / "child"
    child_dir.mkdir()
    pid = os.fork()
    if pid == 0:  # the child: exit status 0 only if its background append completes
        code = 1
        try:
            journal_commit(child_dir)
            pending = rundir.append_month_soon(child_dir, b'{"m": 2}', months_done=2)
            pending.wait()
            code = 0 if pending.result() > 0 else 1
        finally:
            os._exit(code)
    _, status = os.waitpid(pid, 0)
    assert os.WIFEXITED(status) and os.WEXITSTATUS(status) == 0
    assert rundir.read(child_dir, [rundir.JOURNAL]).months_done == 2


def test_append_file_writes_buffers_in_order_and_trims_only_when_asked(tmp_path):
    path = tmp_path / "f"
    durable.append_file(path, 0, [b"ab", memoryview(np.array([1.5])), b"", b"cd"])
    assert path.read_bytes() == b"ab" + np.array([1.5]).tobytes() + b"cd"
    size = path.stat().st_size
    durable.append_file(path, 2, b"XY")  # cut at 2 first
    assert path.read_bytes() == b"abXY"
    durable.append_file(path, 4, b"ZZ", trim=False)
    durable.append_file(path, 2, b"--", trim=False)  # overwrites, keeps what follows
    assert path.read_bytes() == b"ab--ZZ" and size > 6
