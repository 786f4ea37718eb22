"""What a sweep (and a study) refuses before it starts, and how it ends when the machine
fails it: duplicate grid keys, contradictory or malformed scheduler options, work beyond the
machine, an empty ``out``, a full disk while the table is written, no Dask worker alive;
and ``--quiet`` keeping Dask's INFO lines off the terminal."""

from __future__ import annotations

import errno
import logging
import time

import pandas as pd
import pytest

from mpcrl_lite.publish.report import run_report
from mpcrl_lite.studies.study import run_study
from mpcrl_lite.studies.sweep import api, schedule
from mpcrl_lite.studies.sweep.api import GridError, SchedulerError, run_sweep

TINY = {"base": {"learning": {"months": 1, "days_per_month": 1, "eval_every": 0},
                 "system": {"N": 4}},
        "grid": {"learning.seed": [0]}}


@pytest.mark.parametrize("text, key", [
    ("grid:\n  learning.seed: [0]\n  system.P_bar: [1.0]\n  learning.seed: [1]\n",
     "learning.seed"),
    ("base:\n  learning: {months: 1, months: 2}\ngrid:\n  learning.seed: [0]\n", "months"),
    ("base: {}\ngrid: {learning.seed: [0]}\nbase: {}\n", "base"),
])
def test_a_key_written_twice_is_refused(text, key, tmp_path):
    grid = tmp_path / "grid.yaml"
    grid.write_text(text)
    with pytest.raises(GridError, match=rf"key '{key}' is written twice \(first at line \d\)"):
        run_sweep(grid, tmp_path / "out", scheduler="serial", progress=False)
    assert not (tmp_path / "out").exists()


def test_yaml_merge_keys_are_not_duplicates(tmp_path):
    grid = tmp_path / "grid.yaml"
    grid.write_text("base:\n  learning:\n    <<: {months: 1, days_per_month: 1}\n"
                    "    days_per_month: 2\ngrid:\n  learning.seed: [0]\n")
    sweep = api.load_grid(grid)
    assert sweep.runs[0].learning.days_per_month == 2


@pytest.mark.parametrize("scheduler, workers, match", [
    ("garbage", 0, "workers=0 and scheduler='garbage' contradict each other"),
    ("tcp://127.0.0.1:8786", 2, "contradict each other"),
    ("garbage", None, "scheduler address 'garbage' is not an address"),
    ("tcp://", None, "is not an address"),
    ("host:port", None, "is not an address"),
])
def test_scheduler_options_are_checked(scheduler, workers, match, tmp_path):
    with pytest.raises(GridError, match=match):
        run_sweep(TINY, tmp_path / "out", scheduler=scheduler, workers=workers, progress=False)
    assert not (tmp_path / "out").exists()


def test_work_beyond_the_machine_is_refused_before_anything(tmp_path):
    huge = {"base": {"learning.days_per_month": 1},
            "grid": {"learning.months": [2, 1_000_000_000]}}
    with pytest.raises(GridError, match=r"the sweep's 2 run\(s\) \(the largest: run "
                                        r"'learning.months=1000000000'.*time limit"):
        run_sweep(huge, tmp_path / "out", scheduler="serial", progress=False)
    t0 = time.perf_counter()
    with pytest.raises(ValueError, match=r"seeds=1000000000, months=1 .*time limit"):
        run_study(1_000_000_000, 1, tmp_path / "study", workers=0, target="best_seen")
    assert time.perf_counter() - t0 < 30  # refused before building a billion seeds
    with pytest.raises(ValueError, match=r"seeds=1, months=1000000000 .*time limit"):
        run_study(1, 1_000_000_000, tmp_path / "study", workers=0, target="best_seen")
    assert not (tmp_path / "out").exists() and not (tmp_path / "study").exists()


def test_an_empty_out_is_refused(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    for call in (lambda: run_sweep(TINY, "", scheduler="serial", progress=False),
                 lambda: run_study(1, 1, "", workers=0, target="best_seen"),
                 lambda: run_report("", profile="ci", notebooks=["01_battery_dynamics"])):
        with pytest.raises(ValueError, match="'': expected a directory path"):
            call()
    assert list(tmp_path.iterdir()) == []


def test_a_full_disk_while_the_table_is_written_leaves_no_temporary_file(tmp_path,
                                                                           monkeypatch):
    def full(self, path, *args, **kwargs):
        with open(path, "wb") as f:  # a part written, then the disk is full
            f.write(b"PAR1")
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(pd.DataFrame, "to_parquet", full)
    out = tmp_path / "out"
    with pytest.raises(GridError, match="cannot be written: .*No space left on device"):
        run_sweep(TINY, out, scheduler="serial", progress=False)
    assert not (out / "results.tmp.parquet").exists()
    assert not (out / "results.csv.tmp").exists()


def test_no_worker_alive_ends_the_sweep_in_one_line(tmp_path, monkeypatch):
    from distributed import LocalCluster

    monkeypatch.setenv(schedule.NO_WORKER_TIMEOUT_ENV, "2")
    out = tmp_path / "out"
    with LocalCluster(n_workers=0, host="127.0.0.1", dashboard_address=None) as cluster:
        t0 = time.perf_counter()
        with pytest.raises(SchedulerError, match=r"no Dask worker alive at tcp://.* for 2 s "
                                                 r"with 1 task\(s\) left"):
            run_sweep(TINY, out, scheduler=cluster.scheduler_address, progress=False)
        assert time.perf_counter() - t0 < 60
    table = pd.read_csv(out / "results.csv")
    assert list(table["status"]) == ["pending"]  # the table is kept, the run to do again


def test_quiet_keeps_dasks_info_lines_off(tmp_path, caplog):
    caplog.set_level(logging.INFO)
    table = run_sweep(TINY, tmp_path / "out", workers=1, progress=False)
    assert list(table["status"]) == ["done"]
    chatter = [r for r in caplog.records
               if r.name.startswith("distributed") and r.levelno < logging.ERROR]
    assert chatter == [], [r.getMessage() for r in chatter[:3]]
