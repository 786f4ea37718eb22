"""Parameter sweeps: grid validation, Dask vs serial, failures, reruns, reports, summaries.

The learning runs are tiny (2 months of 2 days, horizon N = 4, IPOPT) so the whole file stays
well under a minute; one local Dask cluster of 2 worker processes is started once.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import nbformat
import numpy as np
import pandas as pd
import pytest
import yaml

from mpcrl_lite.history import History
from mpcrl_lite.sweep import (
    FAIL_ENV,
    GridError,
    NOTEBOOK_PARAMETERS,
    load_grid,
    load_results,
    run_sweep,
    run_sweep_cli,
    summarize,
)

ROOT = Path(__file__).resolve().parent.parent

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
    from mpcrl_lite.cli import main

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
