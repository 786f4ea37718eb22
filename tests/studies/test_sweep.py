"""Parameter sweeps: grid validation, Dask vs serial, failures, reruns, reports, summaries,
and the one-line errors for everything that can be wrong before a sweep starts (grid file,
output directory, scheduler address, damaged files of an earlier sweep).

The learning runs are tiny (2 months of 2 days, horizon N = 4, IPOPT) so the whole file stays
around a minute; one local Dask cluster of 2 worker processes is started for the sweep, and
one small cluster with a single worker for the scheduler-address route.
"""

from __future__ import annotations

import json
import logging
import os
import re
import shutil
import socket
import time
from pathlib import Path

import nbformat
import numpy as np
import pandas as pd
import pytest
import yaml
from conftest import assert_imports_within
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import mpcrl_lite.studies.sweep.api as sweep_module
from mpcrl_lite.cli.main import main
from mpcrl_lite.learning.history import History
from mpcrl_lite.learning.rundir import RECOVER
from mpcrl_lite.studies.sweep import grid as sweep_grid
from mpcrl_lite.studies.sweep import run as sweep_run
from mpcrl_lite.studies.sweep import schedule as sweep_schedule
from mpcrl_lite.studies.sweep import store as sweep_store
from mpcrl_lite.studies.sweep import table as sweep_table
from mpcrl_lite.studies.sweep.api import (
    FAIL_ENV,
    NOTEBOOK_PARAMETERS,
    DamagedFileError,
    GridError,
    MissingFileError,
    SchedulerError,
    Sweep,
    check_scheduler,
    load_grid,
    load_results,
    run_sweep,
    run_sweep_cli,
    summarize,
)

ROOT = Path(__file__).resolve().parents[2]

# the reference back-end keeps these tests independent of the batch solver's own tests
GRID = {
    "base": {
        "learning": {"months": 2, "days_per_month": 2},
        "system": {"N": 4},
        "mpc": {"backend": "ipopt"},
    },
    "grid": {
        "system.P_bar": [1.0, 1.5],
        "system.noise_var": [0.5],
        "learning.seed": [0, 1],
    },
}
IDS = [
    "P_bar=1.0,noise_var=0.5,seed=0",
    "P_bar=1.0,noise_var=0.5,seed=1",
    "P_bar=1.5,noise_var=0.5,seed=0",
    "P_bar=1.5,noise_var=0.5,seed=1",
]
FAILING = IDS[3]


def J_series(out: Path, run_id: str) -> list[float]:
    return History.load(out / "runs" / run_id).J


@pytest.fixture(scope="module")
def serial(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, pd.DataFrame]:
    """The 4 runs, one after another in this process."""
    out = tmp_path_factory.mktemp("serial")
    return out, run_sweep(GRID, out, scheduler="serial", progress=False)


@pytest.fixture(scope="module")
def distributed(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, pd.DataFrame]:
    """The same runs on a local cluster of 2 processes, with FAILING crashing after month 1."""
    out = tmp_path_factory.mktemp("dask")
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv(FAIL_ENV, FAILING)  # inherited by the worker processes
        table = run_sweep(GRID, out, workers=2, progress=False)
    return out, table


# -- the grid ------------------------------------------------------------------------------
def test_grid_ids_order_and_configs() -> None:
    sweep = load_grid(GRID)
    assert sweep.run_ids == IDS
    run = sweep.runs[2]
    assert run.values == {"system.P_bar": 1.5, "system.noise_var": 0.5, "learning.seed": 0}
    assert (run.system.P_bar, run.system.N, run.learning.seed, run.learning.months) == (
        1.5, 4, 0, 2)
    assert sweep.columns == {
        "system.P_bar": "P_bar", "system.noise_var": "noise_var", "learning.seed": "seed"}
    # ids do not depend on the order of the keys (only the row order does)
    reordered = load_grid({"base": GRID["base"], "grid": dict(reversed(GRID["grid"].items()))})
    assert sorted(reordered.run_ids) == sorted(IDS)
    assert reordered.run_ids[1] == "P_bar=1.5,noise_var=0.5,seed=0"


def test_grid_from_yaml_with_dotted_base_and_tuples(tmp_path: Path) -> None:
    path = tmp_path / "grid.yaml"
    path.write_text(
        "base:\n  learning.months: 3\n"
        "grid:\n  system.omega: [[20.0, 20.0], [5.0, 30.0]]\n  learning.months_x: []\n"
    )
    with pytest.raises(GridError, match="'learning.months_x'.*no field 'months_x'"):
        load_grid(path)
    path.write_text(
        "base:\n  learning.months: 3\ngrid:\n  system.omega: [[20.0, 20.0], [5.0, 30.0]]\n")
    sweep = load_grid(path)
    assert sweep.run_ids == ["omega=20.0_20.0", "omega=5.0_30.0"]
    assert sweep.runs[1].system.omega == (5.0, 30.0)
    assert sweep.runs[1].learning.months == 3


def test_grid_column_that_would_shadow_a_result_keeps_its_section() -> None:
    sweep = load_grid({"grid": {"learning.months": [1, 2]}})
    assert sweep.columns == {"learning.months": "learning.months"}
    assert sweep.run_ids == ["learning.months=1", "learning.months=2"]


@pytest.mark.parametrize(
    ("grid", "message"),
    [
        ({"grid": {"sytem.P_bar": [1.0]}}, r"'sytem.P_bar'.*unknown section 'sytem'"),
        ({"grid": {"system.P_barr": [1.0]}},
         r"'system.P_barr'.*SystemConfig has no field 'P_barr'"),
        ({"grid": {"P_bar": [1.0]}}, r"'P_bar'.*expected 'section.field'"),
        ({"grid": {"system.P_bar": []}}, r"'system.P_bar': empty list"),
        ({"grid": {"system.P_bar": 1.0}}, r"'system.P_bar': expected a list"),
        ({"grid": {"system.P_bar": [1.0, 1.0]}}, r"value 1.0 is listed twice"),
        ({"grid": {}}, r"'grid' must be a non-empty mapping"),
        ({"grid": {"system.P_bar": [1.0]}, "extra": 1}, r"unknown top-level key\(s\) \['extra'\]"),
        ({"grid": {"system.P_bar": [1.0, -1.0]}},
         r"grid point P_bar=-1.0 \(system\): P_bar=-1.0: expected a value in \(0, inf\)"),
        ({"grid": {"learning.seed": [0, 1.5]}},
         r"grid point seed=1.5 \(learning\): seed=1.5: expected an integer"),
        ({"grid": {"mpc.tau": ["1e-4"]}}, r"tau='1e-4'.*YAML read '1e-4' as text"),
        ({"grid": {"mpc.backend": ["ipopt", "fast"]}}, r"backend='fast': expected one of"),
        ({"base": {"learning": {"months": 0}}, "grid": {"learning.seed": [0]}},
         r"^base \(learning\): months=0"),
        ({"base": {"physics": {"g": 9.81}}, "grid": {"learning.seed": [0]}},
         r"base key 'physics': unknown section"),
        ({"base": {"system.P_bar": 1.0}, "grid": {"system.P_bar": [1.0]}}, r"also set in base"),
    ],
)
def test_grid_validation_errors(grid: dict, message: str) -> None:
    with pytest.raises(GridError, match=message):
        load_grid(grid)


def test_invalid_grid_starts_nothing(tmp_path: Path) -> None:
    bad = {"grid": {"system.P_bar": [1.0, 0.0]}}
    with pytest.raises(ValueError, match="P_bar=0.0"):
        run_sweep(bad, tmp_path / "out", scheduler="serial", progress=False)
    assert not (tmp_path / "out").exists()
    with pytest.raises(FileNotFoundError):
        load_grid(tmp_path / "missing.yaml")
    with pytest.raises(GridError, match="unknown run id"):
        run_sweep(GRID, tmp_path / "out", scheduler="serial", progress=False, only=["nope"])


def test_example_grid_has_twelve_runs() -> None:
    sweep = load_grid(ROOT / "examples" / "sweep_grid.yaml")
    assert len(sweep.runs) == 12
    assert len(set(sweep.run_ids)) == 12


# -- execution -----------------------------------------------------------------------------
def test_serial_table(serial: tuple[Path, pd.DataFrame]) -> None:
    out, table = serial
    assert list(table["run_id"]) == IDS
    assert (table["status"] == "done").all() and not table["cached"].any()
    for column in ("P_bar", "noise_var", "seed", "months", "J_first", "J_last", "J_1_first",
                   "J_3_last", "hours_soc_below_0_1_first", "hours_soc_below_0_1_last",
                   "max_P_mpc", "skipped_steps", "wall_time_s"):
        assert column in table.columns, column
    assert (table["months"] == 2).all()
    assert (table["max_P_mpc"] <= table["P_bar"] + 1e-6).all()
    for run_id in IDS:
        assert (out / "runs" / run_id / "done.json").exists()
        assert J_series(out, run_id)[-1] == table.set_index("run_id").loc[run_id, "J_last"]
    on_disk = load_results(out)
    pd.testing.assert_series_equal(on_disk["J_last"], table["J_last"])
    csv = pd.read_csv(out / "results.csv")
    assert list(csv["run_id"]) == IDS


def test_dask_matches_serial(serial, distributed) -> None:
    (out_s, _), (out_d, table) = serial, distributed
    done = table[table["status"] == "done"]
    assert list(done["run_id"]) == IDS[:3]
    for run_id in IDS[:3]:
        assert J_series(out_d, run_id) == J_series(out_s, run_id)  # bit for bit
        a = History.load(out_d / "runs" / run_id).J_per_agent
        b = History.load(out_s / "runs" / run_id).J_per_agent
        np.testing.assert_array_equal(a, b)


def test_failed_run_is_reported_and_the_others_finish(distributed) -> None:
    out, table = distributed
    row = table.set_index("run_id").loc[FAILING]
    assert row["status"] == "failed"
    assert row["error"].startswith("InjectedFailure: run " + FAILING)
    assert row["months"] == 1  # the month before the crash was checkpointed
    error = json.loads((out / "runs" / FAILING / "error.json").read_text())
    assert error["type"] == "InjectedFailure"
    assert "Traceback" in error["traceback"] and "InjectedFailure" in error["traceback"]
    assert not (out / "runs" / FAILING / "done.json").exists()
    assert table.attrs["failed"] == 1
    csv = pd.read_csv(out / "results.csv", keep_default_na=False)
    assert list(csv["status"]) == ["done", "done", "done", "failed"]


def test_rerun_resumes_failed_and_skips_finished(serial, distributed, tmp_path: Path) -> None:
    out = tmp_path / "again"
    shutil.copytree(distributed[0], out)
    markers = {i: (out / "runs" / i / "done.json").stat().st_mtime_ns for i in IDS[:3]}
    first_month_time = History.load(out / "runs" / FAILING).wall_time_s[0]

    table = run_sweep(GRID, out, scheduler="serial", progress=False, only=[FAILING])
    assert table.attrs["executed"] == 1
    assert (table["status"] == "done").all()
    assert list(table["cached"]) == [True, True, True, False]
    assert table.set_index("run_id").loc[FAILING, "error"] == ""
    assert not (out / "runs" / FAILING / "error.json").exists()
    for run_id, mtime in markers.items():
        assert (out / "runs" / run_id / "done.json").stat().st_mtime_ns == mtime
    # resumed from its checkpoint (month 1 kept) and identical to an uninterrupted run
    resumed = History.load(out / "runs" / FAILING)
    assert resumed.wall_time_s[0] == first_month_time
    for run_id in IDS:
        assert J_series(out, run_id) == J_series(serial[0], run_id)

    table = run_sweep(GRID, out, scheduler="serial", progress=False)
    assert table.attrs["executed"] == 0 and table["cached"].all()


def test_rerun_with_other_settings_is_refused(serial, tmp_path: Path) -> None:
    out = tmp_path / "changed"
    shutil.copytree(serial[0], out)
    changed = {**GRID, "base": {**GRID["base"], "mpc": {"backend": "ipopt", "tau": 1e-3}}}
    # the stored runs use the default tau (0.1)
    message = r"holds a run with mpc\.tau=0\.1, but this sweep sets 0\.001"
    with pytest.raises(GridError, match=message):
        run_sweep(changed, out, scheduler="serial", progress=False)


def test_cli_reruns_only_what_is_missing(serial, tmp_path: Path, capsys) -> None:
    out = tmp_path / "cli"
    shutil.copytree(serial[0], out)
    grid = tmp_path / "grid.yaml"
    grid.write_text(yaml.safe_dump(GRID))  # sorted keys: same runs, other row order
    args = ["sweep", "--grid", str(grid), "--out", str(out), "--scheduler", "serial"]
    assert main([*args, "--quiet"]) == 0
    assert json.loads(capsys.readouterr().out)["runs"] == 4
    assert load_results(out)["cached"].all()
    table = run_sweep_cli(grid, out, scheduler="serial", progress=False)
    assert table.attrs["executed"] == 0

    grid.write_text("grid:\n  system.P_bar: []\n")
    assert main(args) == 2
    assert "grid key 'system.P_bar': empty list" in capsys.readouterr().err


def test_summarize(serial) -> None:
    _, table = serial
    summary = summarize(table, by=["P_bar", "noise_var"])
    assert list(summary["P_bar"]) == [1.0, 1.5]
    assert list(summary["runs"]) == [2, 2]
    for p_bar, group in table.groupby("P_bar"):
        row = summary[summary["P_bar"] == p_bar].iloc[0]
        assert row["J_last_mean"] == pytest.approx(group["J_last"].mean())
        assert row["J_last_std"] == pytest.approx(group["J_last"].std())
        assert row["J_2_last_mean"] == pytest.approx(group["J_2_last"].mean())
    with pytest.raises(ValueError, match="not in the table"):
        summarize(table, by=["tau"])


# -- the papermill route -------------------------------------------------------------------
@pytest.fixture
def tiny_notebook(tmp_path: Path) -> Path:
    """A notebook with notebook 05's parameter names that records what it was given."""
    nb = nbformat.v4.new_notebook()
    params = nbformat.v4.new_code_cell(
        "MONTHS = 100  # learning steps\nDAYS = 30  # days per month\nP_BAR = 1.5  # grid limit\n"
        "NOISE_VAR = 0.5  # noise variance\nSEED = 0  # random seed"
    )
    params.metadata["tags"] = ["parameters"]
    nb.cells = [params, nbformat.v4.new_code_cell(
        "import json\n"
        "print(json.dumps({'P_BAR': P_BAR, 'SEED': SEED, 'MONTHS': MONTHS, 'DAYS': DAYS}))"
    )]
    nb.metadata["kernelspec"] = {
        "name": "python3", "display_name": "Python 3", "language": "python"}
    path = tmp_path / "tiny.ipynb"
    nbformat.write(nb, path)
    return path


def test_notebook_route(tiny_notebook: Path, tmp_path: Path) -> None:
    grid = {"base": {"learning": {"months": 1, "days_per_month": 1}},  # notebook-mapped only
            "grid": {"system.P_bar": [1.0, 1.5], "learning.seed": [3]}}
    out = tmp_path / "out"
    table = run_sweep(grid, out, scheduler="serial", progress=False, notebooks=True,
                      notebook=tiny_notebook)
    assert (table["status"] == "done").all()
    assert (table["notebook_error"] == "").all()
    for run_id, p_bar in (("P_bar=1.0,seed=3", 1.0), ("P_bar=1.5,seed=3", 1.5)):
        path = out / "reports" / f"{run_id}.ipynb"
        assert table.set_index("run_id").loc[run_id, "notebook"] == f"reports/{run_id}.ipynb"
        executed = nbformat.read(path, as_version=4)
        text = executed.cells[-1].outputs[0]["text"]
        assert json.loads(text) == {"P_BAR": p_bar, "SEED": 3, "MONTHS": 1, "DAYS": 1}
    # unmapped overrides and parameters the notebook lacks fail before anything runs
    with pytest.raises(GridError, match=r"base key 'system.N' has no notebook parameter"):
        run_sweep({**grid, "base": {"system": {"N": 4}}}, tmp_path / "o2", scheduler="serial",
                  notebooks=True, notebook=tiny_notebook)
    with pytest.raises(ValueError, match=r"unknown parameter\(s\) \['TAU'\]"):
        run_sweep({**grid, "base": {"mpc": {"tau": 1e-3}}}, tmp_path / "o3", scheduler="serial",
                  notebooks=True, notebook=tiny_notebook,
                  notebook_parameters={**NOTEBOOK_PARAMETERS, "mpc.tau": "TAU"})
    assert not (tmp_path / "o2").exists() and not (tmp_path / "o3").exists()


# -- the module layout ---------------------------------------------------------------------
#: What each sweep module may import from the package, read from the source (an import hidden
#: in a function counts too): grid -> store -> table -> run -> schedule -> sweep.
SWEEP_LAYER = {
    "studies.sweep.grid": {"config", "system.prices"},  # prices: a run's price file month
    # rundir: LEGACY_VALUES of older configs; durable, outdir: atomic files, the out check
    "studies.sweep.store": {"learning.durable", "learning.outdir", "learning.rundir",
                            "studies.sweep.grid"},
    "studies.sweep.table": {"learning.history", "studies.sweep.grid", "studies.sweep.store"},
    "studies.sweep.run": {"learning.experiment", "learning.q_experiment", "studies.lockstep",
                          "publish.report", "studies.sweep.grid", "studies.sweep.store", "studies.sweep.table"},
    "studies.sweep.schedule": {"_util.progress", "studies.sweep.grid", "studies.sweep.run",
                               "studies.sweep.store", "studies.sweep.table"},
    # outdir: the lock of out; budget: the size of the work
    "studies.sweep.api": {"_util.budget", "learning.outdir", "publish.report",
                          "studies.sweep.grid", "studies.sweep.run",
                          "studies.sweep.schedule", "studies.sweep.store", "studies.sweep.table"},
}


@pytest.mark.parametrize("module", sorted(SWEEP_LAYER))
def test_sweep_modules_import_only_downwards(module: str) -> None:
    assert_imports_within(module, SWEEP_LAYER[module])


def test_public_names_stay_importable_from_sweep() -> None:
    before_the_split = [
        "SECTIONS", "NOTEBOOK", "NOTEBOOK_PARAMETERS", "FAIL_ENV", "GridError", "InjectedFailure",
        "SweepRun", "Sweep", "load_grid", "run_sweep", "run_sweep_cli", "load_results",
        "summarize",
    ]
    assert set(before_the_split) <= set(sweep_module.__all__)
    for name in sweep_module.__all__:
        assert hasattr(sweep_module, name), name
    assert sweep_module.load_grid is sweep_grid.load_grid
    assert sweep_module.summarize is sweep_table.summarize
    assert sweep_module.FAIL_ENV is sweep_run.FAIL_ENV
    assert issubclass(sweep_store.DamagedFileError, GridError)
    assert issubclass(sweep_schedule.SchedulerError, GridError)
    assert issubclass(sweep_schedule.DaskMissingError, ImportError)


def test_grid_columns_never_shadow_result_columns() -> None:
    assert set(sweep_table.COLUMNS) <= sweep_grid._RESERVED


# -- grid files: every problem is one GridError line naming the file -----------------------
@pytest.mark.parametrize(
    ("content", "message"),
    [
        (None, r"grid file \S+ is a directory; expected a YAML file$"),
        ("grid:\n  system.P_bar: [1.0\n  learning.seed: [0]\n",
         (r"grid file \S+: not valid YAML: line 3, column 16: expected ',' or ']', but got ':' "
          r"\(while parsing a flow sequence started at line 2, column 17\)$")),
        ("grid:\n  system.P_bar: [1.0]\n    learning.seed: [0]\n",
         (r"not valid YAML: line 3, column 5: expected <block end>, but found '<block mapping "
          r"start>' \(while parsing a block mapping started at line 2, column 3\)$")),
        ("grid: {learning.seed: [0]}\n\x00\n",
         r"not valid YAML: character #x0000 at position 27: special characters are not allowed"),
        (b"\xff\xfegrid:", r"grid file \S+ is not UTF-8 text \(byte 0xff at position 0\)$"),
        ("grid:\n  learning.seed: &x [*x]\n", r"a value contains itself"),
        ("- 1\n- 2\n", r"grid file \S+: a sweep is a mapping with keys 'base' and 'grid'; got li"),
        ("", r"got NoneType$"),
        ("grid:\n  learning.seed: [2001-13-45]\n", r"not valid YAML: month must be in 1\.\.12$"),
        ("[" * 3000, r"not valid YAML: nested too deeply$"),
        # too large for a float: rejected by the config or by the conversion, in one line
        ("grid:\n  system.P_bar: [1" + "0" * 400 + "]\n",
         r"^grid point P_bar=10+~\w+ \(system\): (int too large to convert to float|P_bar=)"),
    ],
)
def test_grid_file_errors_are_one_line(tmp_path: Path, content, message: str) -> None:
    path = tmp_path / "grid.yaml"
    if content is None:
        path.mkdir()
    elif isinstance(content, bytes):
        path.write_bytes(content)
    else:
        path.write_text(content)
    with pytest.raises(GridError, match=message) as info:
        load_grid(path)
    assert len(str(info.value).splitlines()) == 1
    if "grid point" not in message:
        assert str(path) in str(info.value)


def test_missing_grid_file_is_a_grid_error_and_a_file_not_found(tmp_path: Path) -> None:
    path = tmp_path / "nope.yaml"
    with pytest.raises(MissingFileError, match=r"^grid file \S+nope\.yaml not found$") as info:
        load_grid(path)
    assert isinstance(info.value, FileNotFoundError) and isinstance(info.value, GridError)


def test_unreadable_grid_file(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    path = tmp_path / "grid.yaml"
    path.write_text(yaml.safe_dump(GRID))
    path.chmod(0)
    if os.access(path, os.R_OK):  # root reads it anyway: fail the read as it fails for a user
        def denied(self: Path) -> bytes:
            raise PermissionError(13, "Permission denied", str(self))

        monkeypatch.setattr(Path, "read_bytes", denied)
    with pytest.raises(GridError, match=r"^grid file \S+ cannot be read: Permission denied$"):
        load_grid(path)


# -- hypothesis: any document is a Sweep or one GridError line, never another exception ------
_TEXT = st.text(st.characters(codec="utf-8"), max_size=8)
_KEYS = st.sampled_from([
    "system.P_bar", "system.noise_var", "system.n", "system.N", "system.omega", "mpc.tau",
    "mpc.backend", "learning.seed", "learning.months", "system.P_barr", "sytem.P_bar", "P_bar",
    "a.b.c", "", "base", "grid",
]) | _TEXT | st.integers() | st.none() | st.booleans() | st.floats()
_SCALARS = (
    st.none() | st.booleans() | st.integers() | st.floats() | _TEXT
    | st.sampled_from([0, 1, 2, 0.5, 1.0, 1.5, 20.0, "1e-4", "ipopt", "batch", 10**400])
)
_VALUES = st.recursive(
    _SCALARS,
    lambda inner: st.lists(inner, max_size=3) | st.dictionaries(_KEYS, inner, max_size=3),
    max_leaves=8,
)
_SECTION_KEYS = st.sampled_from(["system", "mpc", "learning", "physics"]) | _KEYS
_BASE = st.none() | _VALUES | st.dictionaries(
    _SECTION_KEYS,
    st.dictionaries(st.sampled_from(["N", "P_bar", "seed", "months", "tau", "x"]) | _TEXT,
                    _VALUES, max_size=3) | _VALUES,
    max_size=3,
)
_AXES = st.dictionaries(_KEYS, st.lists(_VALUES, max_size=3) | _VALUES, max_size=3)
#: Grids close to valid ones, so the fuzz also reaches run ids and the configs' validation.
_NEAR_AXES = st.dictionaries(
    st.sampled_from(["system.P_bar", "system.noise_var", "system.omega", "mpc.tau",
                     "mpc.backend", "learning.seed", "learning.months", "system.N"]),
    st.lists(_SCALARS | st.lists(st.floats(0, 50), min_size=2, max_size=2), min_size=1,
             max_size=3),
    min_size=1, max_size=3,
)
#: Grids that are valid by construction (seeds, grid limits), so the fuzz reaches the runs.
_VALID_AXES = st.fixed_dictionaries(
    {"learning.seed": st.lists(st.integers(0, 10**6), min_size=1, max_size=3, unique=True)},
    optional={"system.P_bar": st.lists(st.sampled_from([1.0, 1.5, 2.0]), min_size=1,
                                       max_size=3, unique=True)},
)
_DOCUMENTS = (
    st.fixed_dictionaries({"grid": _VALID_AXES})
    | st.fixed_dictionaries({"grid": _NEAR_AXES}, optional={"base": _BASE})
    | st.fixed_dictionaries({"grid": _AXES}, optional={"base": _BASE, "extra": _VALUES})
    | st.dictionaries(_KEYS, _VALUES, max_size=3)
    | _VALUES
)
_NOISE = st.text(":-[]{},#&*!|>'\"%@`?\n\t .0123456789abeglmnrsty_\x00\x85\u2028", max_size=30)


@st.composite
def _yaml_texts(draw: st.DrawFn) -> bytes:
    """YAML written from a random document, then (usually) damaged by a random splice."""
    text = yaml.safe_dump(draw(_DOCUMENTS), allow_unicode=True, sort_keys=False)
    if draw(st.booleans()):
        i = draw(st.integers(0, len(text)))
        j = draw(st.integers(i, min(len(text), i + 10)))
        text = text[:i] + draw(_NOISE) + text[j:]
    raw = text.encode("utf-8")
    if draw(st.integers(0, 9)) == 0:  # sometimes not UTF-8 at all
        raw = raw[: draw(st.integers(0, len(raw)))] + b"\xc3\x28"
    return raw


def _sweep_or_one_line_error(load) -> None:
    try:
        result = load()
    except GridError as err:
        text = str(err)
        assert text.strip() and len(text.splitlines()) == 1, repr(text)
    else:
        assert isinstance(result, Sweep) and len(result.runs) >= 1


@pytest.mark.filterwarnings("ignore::mpcrl_lite.config.ConfigWarning")
@settings(max_examples=200, deadline=None)
@given(document=_DOCUMENTS)
def test_fuzz_load_grid_documents(document) -> None:
    _sweep_or_one_line_error(lambda: load_grid(document))


@pytest.fixture(scope="module")
def scratch(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("fuzz")


@pytest.mark.filterwarnings("ignore::mpcrl_lite.config.ConfigWarning")
@settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(raw=_yaml_texts() | st.binary(max_size=40))
def test_fuzz_load_grid_files(raw: bytes, scratch: Path) -> None:
    path = scratch / "grid.yaml"
    path.write_bytes(raw)
    _sweep_or_one_line_error(lambda: load_grid(path))


@pytest.mark.filterwarnings("ignore::mpcrl_lite.config.ConfigWarning")
def test_fuzz_documents_include_valid_sweeps() -> None:
    """The fuzz above is not all rejected at the door: its documents include valid sweeps
    (a fixed draw of the same strategy, so this count does not vary between runs)."""
    valid: list[bool] = []

    @settings(max_examples=300, deadline=None, database=None, derandomize=True)
    @given(document=_DOCUMENTS)
    def classify(document) -> None:
        try:
            valid.append(isinstance(load_grid(document), Sweep))
        except GridError:
            valid.append(False)

    classify()
    assert any(valid) and not all(valid)


# -- the output directory and the scheduler: checked before anything is written ------------
def _files(root: Path) -> list[Path]:
    return sorted(root.rglob("*"))


@pytest.mark.parametrize(
    ("case", "message"),
    [
        ("grid is a directory", r"grid file \S+ is a directory; expected a YAML file"),
        ("grid is missing", r"grid file \S+missing\.yaml not found"),
        ("grid is not YAML", r"grid file \S+: not valid YAML: line 3, column 16: "),
        ("out is a file", r"--out \S+taken: is an existing file; expected a directory"),
        ("out is under a file",
         r"--out \S+taken/out: \S+taken is an existing file, so it cannot be created"),
    ],
)
def test_cli_errors_before_the_start_are_one_line(
    case: str, message: str, tmp_path: Path, capfd: pytest.CaptureFixture
) -> None:
    grid, out = tmp_path / "grid.yaml", tmp_path / "out"
    grid.write_text(yaml.safe_dump(GRID))
    (tmp_path / "taken").write_text("a file")
    if case == "grid is a directory":
        grid = tmp_path
    elif case == "grid is missing":
        grid = tmp_path / "missing.yaml"
    elif case == "grid is not YAML":
        grid.write_text("grid:\n  system.P_bar: [1.0\n  learning.seed: [0]\n")
    elif case == "out is a file":
        out = tmp_path / "taken"
    else:
        out = tmp_path / "taken" / "out"
    before = _files(tmp_path)
    code = main(["sweep", "--grid", str(grid), "--out", str(out), "--workers", "0", "--quiet"])
    err = capfd.readouterr().err
    assert code == 2
    assert len(err.splitlines()) == 1, err
    assert re.match(r"mpcrl_lite sweep: error: " + message, err), err
    assert _files(tmp_path) == before


def test_read_only_output_directory_is_refused_before_any_work(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    out = tmp_path / "read_only"
    out.mkdir()
    out.chmod(0o555)
    if os.access(out, os.W_OK):  # root writes anyway: answer as the system does for a user
        access = os.access
        monkeypatch.setattr(
            os, "access", lambda path, mode, **kw: False if Path(path) == out
            else access(path, mode, **kw))
    with pytest.raises(GridError, match=r"^--out \S+read_only: cannot write there \(\S+"
                                        r"read_only is not writable\); expected a writable"):
        run_sweep(GRID, out, scheduler="serial", progress=False)
    with pytest.raises(GridError, match=r"^--out \S+read_only/new: cannot write there \(\S+"
                                        r"read_only is not writable\); expected a writable"):
        run_sweep(GRID, out / "new", scheduler="serial", progress=False)
    assert list(out.iterdir()) == []


def test_values_yaml_cannot_save_are_refused_before_anything_is_written(tmp_path: Path) -> None:
    grid = {**GRID, "grid": {"system.P_bar": [np.float64(1.0)]}}  # valid for the config
    with pytest.raises(GridError, match=r"^the sweep cannot be saved as grid\.yaml \(cannot "
                                        r"represent an object \S*1\.0\)?\); give"):
        run_sweep(grid, tmp_path / "out", scheduler="serial", progress=False)
    assert not (tmp_path / "out").exists()


def test_unreachable_scheduler_is_reported_before_anything_is_written(tmp_path: Path) -> None:
    out = tmp_path / "out"
    t0 = time.perf_counter()
    with pytest.raises(SchedulerError, match=(
        r"^no Dask scheduler answered at tcp://127\.0\.0\.1:1 within 1 s; expected the address "
        r"of a running Dask scheduler, e\.g\. tcp://HOST:8786$"
    )):
        run_sweep(GRID, out, scheduler="tcp://127.0.0.1:1", connect_timeout=1, progress=False)
    assert time.perf_counter() - t0 < 10  # not Dask's 30 s
    assert not out.exists()


def test_cli_unreachable_scheduler_is_one_line(tmp_path: Path, capfd) -> None:
    grid, out = tmp_path / "grid.yaml", tmp_path / "out"
    grid.write_text(yaml.safe_dump(GRID))
    code = main(["sweep", "--grid", str(grid), "--out", str(out), "--scheduler",
                 "tcp://127.0.0.1:1", "--quiet"])
    err = capfd.readouterr().err
    assert code == 2
    assert err.splitlines() == [(
        "mpcrl_lite sweep: error: no Dask scheduler answered at tcp://127.0.0.1:1 within "
        f"{sweep_schedule.CONNECT_TIMEOUT:g} s; expected the address of a running Dask "
        "scheduler, e.g. tcp://HOST:8786"
    )]
    assert not out.exists()


def test_check_scheduler_rejects_what_is_not_a_scheduler() -> None:
    with socket.socket() as listener:  # accepts connections and never answers
        listener.bind(("127.0.0.1", 0))
        listener.listen()
        address = f"tcp://127.0.0.1:{listener.getsockname()[1]}"
        with pytest.raises(SchedulerError, match=rf"^no Dask scheduler answered at {address} "
                                                 r"within 0\.5 s; expected"):
            check_scheduler(address, timeout=0.5)
    with pytest.raises(SchedulerError, match=r"^scheduler address 'host' is malformed \("):
        check_scheduler("host")
    with pytest.raises(GridError, match=r"^connect_timeout=0: expected a number of seconds > 0"):
        check_scheduler("tcp://127.0.0.1:1", timeout=0)


def test_sweep_on_a_scheduler_address(serial: tuple[Path, pd.DataFrame], tmp_path: Path) -> None:
    """The address route: the check accepts a scheduler, refuses its worker, and a run
    executed there equals the serial one bit for bit."""
    from distributed import Client, LocalCluster

    out = tmp_path / "remote"
    shutil.copytree(serial[0], out)
    shutil.rmtree(out / "runs" / IDS[1])
    with LocalCluster(n_workers=1, threads_per_worker=1, processes=True, host="127.0.0.1",
                      dashboard_address="127.0.0.1:0", silence_logs=logging.CRITICAL) as cluster:
        with Client(cluster) as client:
            client.wait_for_workers(1)
            worker = next(iter(client.scheduler_info()["workers"]))
        check_scheduler(cluster.scheduler_address, timeout=5)
        with pytest.raises(SchedulerError, match=r"is not a Dask scheduler \(it answered as "
                                                 r"'Worker'\)"):
            check_scheduler(worker, timeout=5)
        table = run_sweep(GRID, out, scheduler=cluster.scheduler_address, progress=False)
    assert table.attrs["executed"] == 1 and (table["status"] == "done").all()
    assert table.attrs["scheduler"] == cluster.scheduler_address
    assert J_series(out, IDS[1]) == J_series(serial[0], IDS[1])


# -- damaged files of an earlier sweep are named -------------------------------------------
def test_damaged_config_json_is_named_before_anything_runs(serial, tmp_path: Path) -> None:
    out = tmp_path / "damaged_config"
    shutil.copytree(serial[0], out)
    (out / "runs" / IDS[0] / "config.json").write_text('{"system": ')
    before = (out / "results.csv").stat().st_mtime_ns
    with pytest.raises(DamagedFileError, match=(
        rf"^\S+/runs/{re.escape(IDS[0])}/config\.json is not valid JSON \(line 1, column 12: "
        r"Expecting value\); delete that run directory \(or the file\) to run it again$"
    )):
        run_sweep(GRID, out, scheduler="serial", progress=False)
    assert (out / "results.csv").stat().st_mtime_ns == before


def test_damaged_run_files_are_named_in_the_table(serial, tmp_path: Path) -> None:
    out = tmp_path / "damaged"
    shutil.copytree(serial[0], out)
    runs = out / "runs"
    (runs / IDS[0] / "done.json").write_text("")
    (runs / IDS[1] / "done.json").unlink()
    (runs / IDS[1] / "error.json").write_text('{"type": ')
    (runs / IDS[2] / "history.json").write_text("[")
    (runs / IDS[3] / "done.json").unlink()
    (runs / IDS[3] / "checkpoint.json").write_text("{}}")

    # only IDS[3] is executed: its resume meets the damaged checkpoint, recorded in error.json
    table = run_sweep(GRID, out, scheduler="serial", progress=False, only=[IDS[3]])
    rows = table.set_index("run_id")
    expected = {
        IDS[0]: ("failed", "done.json is not valid JSON (line 1, column 1: Expecting value)"),
        IDS[1]: ("failed", "error.json is not valid JSON (line 1, column 10: Expecting value)"),
        IDS[2]: ("done", ("history.json does not match its sha256 in manifest.json (damaged "
                          f"or changed after the run wrote it); {RECOVER}")),
        IDS[3]: ("failed", "checkpoint.json is not valid JSON (line 1, column 3: Extra data)"),
    }
    for run_id, (status, message) in expected.items():
        assert rows.loc[run_id, "status"] == status, run_id
        assert rows.loc[run_id, "error"].startswith("DamagedFileError: "), rows.loc[run_id, "error"]
        assert rows.loc[run_id, "error"].endswith(f"/runs/{run_id}/{message}")
    assert json.loads((runs / IDS[3] / "error.json").read_text())["type"] == "DamagedFileError"

    # a damaged done.json does not stop the run from being finished again
    table = run_sweep(GRID, out, scheduler="serial", progress=False, only=[IDS[0]])
    assert table.set_index("run_id").loc[IDS[0], "status"] == "done"
    assert J_series(out, IDS[0]) == J_series(serial[0], IDS[0])


def test_a_run_reads_back_from_its_stored_config():
    """``SweepRun.from_config`` of what ``config.json`` holds gives the same configurations,
    and the month of a price file (``file_month``) is read with the run's days; the shipped
    month is None (each learner builds it)."""
    from mpcrl_lite.studies.sweep.grid import SweepRun, load_grid
    from mpcrl_lite.system.prices import Prices

    run = load_grid({"base": {"learning.days_per_month": 3}, "grid": {"learning.seed": [4]}}).runs[0]
    again = SweepRun.from_config({"run_id": run.run_id, **run.configs()})
    assert again.run_id == run.run_id and again.configs() == run.configs()
    assert (again.system, again.mpc, again.learning) == (run.system, run.mpc, run.learning)
    assert run.file_month() is None
    path = Path(__file__).resolve().parents[2] / "data" / \
        "example_prices_nordpool_portal_NO3_2025-11.csv"
    on_file = load_grid({"base": {"learning.days_per_month": 3, "prices.file": str(path),
                                  "prices.month": "2025-11", "prices.area": "NO3"},
                         "grid": {"learning.seed": [4]}}).runs[0]
    month = on_file.file_month()
    expected = Prices.from_file(on_file.prices, on_file.system, 3)
    assert month.days == 3 and np.array_equal(month.buy, expected.buy)
    assert not np.array_equal(month.buy, Prices.month(run.system, 3).buy)
    stored = SweepRun.from_config({"run_id": on_file.run_id, **on_file.configs()})
    assert stored.prices == on_file.prices
    assert np.array_equal(stored.file_month().buy, month.buy)
