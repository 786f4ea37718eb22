"""The command line's checks before any work: another month of prices (--prices/--area/
--month), the evaluate command, --out and --force, the size of the work; and a fuzz test:
any argument list ends with exit 0, or exit 2 and exactly one line on stderr."""

from __future__ import annotations

import calendar
import json
import os
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st

from mpcrl_lite._util.stats import mean_ci
from mpcrl_lite.bounds import baselines
from mpcrl_lite.cli import inputs as cli_inputs
from mpcrl_lite.cli.main import main
from mpcrl_lite.config import SystemConfig
from mpcrl_lite.decentralized import learner as decentralized
from mpcrl_lite.learning import experiment
from mpcrl_lite.learning.dpg import REFERENCE_PRICE, price_level
from mpcrl_lite.learning.history import History
from mpcrl_lite.mpc.backends import registry as solvers
from mpcrl_lite.mpc.formulation import MPC
from mpcrl_lite.publish import report
from mpcrl_lite.sim.closed_loop import evaluate_mpc
from mpcrl_lite.studies import study as study_module
from mpcrl_lite.studies import transfer
from mpcrl_lite.studies import tune as tune_module
from mpcrl_lite.studies.sweep import api as sweep_api
from mpcrl_lite.theta import Theta

FIXTURES = Path(__file__).resolve().parents[1] / "fixtures"
RUN = FIXTURES / "run_v0_centralized"
REAL_EXPORT = Path(os.environ.get(
    "MPCRL_LITE_NORDPOOL_EXPORT",
    Path(__file__).resolve().parents[3] / "shared/data/nordpool/elspot-prices_2020_hourly_nok.csv",
))


def price(day: int, hour: int) -> float:
    """The invented Tr.heim price of :func:`write_export` (NOK/MWh)."""
    return 200.5 + 7 * day + 3 * hour


def write_export(path: Path, year: int, month: int, skip: tuple[int, int] | None = None) -> Path:
    """A Nord Pool "Elspot Prices" export of one month without clock change (title lines, a
    byte-order mark, decimal commas, CRLF), areas Oslo and Tr.heim; the cell of Tr.heim at
    ``skip = (day, hour)`` (1-based day) is left empty."""
    days = calendar.monthrange(year, month)[1]
    lines = ["Elspot Prices in NOK/MWh;;;", "Data was last updated 01-01-2030;;;",
             ";Hours;Oslo;Tr.heim"]
    for d in range(1, days + 1):
        for h in range(24):
            cell = "" if skip == (d, h) else f"{price(d, h):.2f}".replace(".", ",")
            lines.append(f"{d:02d}.{month:02d}.{year};{h:02d} - {(h + 1) % 24:02d};1,0;{cell}")
    path.write_bytes(("\ufeff" + "\r\n".join(lines) + "\r\n").encode("utf-8"))
    return path


@pytest.fixture
def export(tmp_path) -> Path:
    return write_export(tmp_path / "elspot.csv", 2021, 2)  # February 2021: no clock change


def run_cli(args: list[str], capsys) -> tuple[int, list[str]]:
    code = main([str(a) for a in args])
    return code, capsys.readouterr().err.strip().splitlines()


# -- prices of another month ------------------------------------------------------------------
def test_month_prices_reads_the_whole_month(export):
    prices = cli_inputs.month_prices(export, "Tr.heim", "2021-02", SystemConfig())
    assert prices.buy.shape == (28, 24)
    expected = np.array([[price(d, h) for h in range(24)] for d in range(1, 29)])
    np.testing.assert_allclose(prices.buy, expected)
    assert prices.sell_ratio == SystemConfig().sell_ratio
    first = cli_inputs.month_prices(export, "Tr.heim", "2021-02", SystemConfig(), days=3)
    np.testing.assert_array_equal(first.buy, expected[:3])
    scaled = cli_inputs.month_prices(export, "Tr.heim", "2021-02", SystemConfig(price_scale=2.0))
    np.testing.assert_allclose(scaled.buy, 2 * expected)


@pytest.mark.parametrize("area, month, days, match", [
    ("Tr.heim", "2021-2", None, "YYYY-MM"),
    ("Tr.heim", "2021-13", None, "YYYY-MM"),
    ("Bergen", "2021-02", None, (r"--area 'Bergen' is not in .* \(read as NO5\); expected one of: "
                                    r"Oslo \(NO1\), "
                                    r"Tr.heim \(NO3\)")),
    ("Tr.heim", "2021-03", None, "no prices from 2021-03-01"),
    ("Tr.heim", "2021-02", 29, "--days 29: 2021-02 has 28 days"),
])
def test_month_prices_refuses_what_is_not_there(export, area, month, days, match):
    with pytest.raises(ValueError, match=match) as info:
        cli_inputs.month_prices(export, area, month, SystemConfig(), days)
    assert "\n" not in str(info.value)


def test_a_file_that_is_not_an_export_is_refused(tmp_path):
    path = tmp_path / "prices.csv"
    path.write_text("time,price\n2021-02-01T00:00,30.25\n")
    with pytest.raises(ValueError, match="is not a price file this package reads") as info:
        cli_inputs.month_prices(path, "Tr.heim", "2021-02", SystemConfig())
    assert "\n" not in str(info.value)


def test_a_month_with_a_missing_hour_is_refused(tmp_path):
    path = write_export(tmp_path / "gap.csv", 2021, 2, skip=(17, 5))
    with pytest.raises(ValueError, match=r"1 hour\(s\) missing .* 2021-02-17 05:00"):
        cli_inputs.month_prices(path, "Tr.heim", "2021-02", SystemConfig())


def test_simulate_on_another_month(export, tmp_path, capsys):
    out = tmp_path / "sim"
    code, err = run_cli(["simulate", "--prices", export, "--area", "Tr.heim", "--month",
                         "2021-02", "--days", "2", "--out", out, "--quiet"], capsys)
    assert code == 0, err
    summary = json.loads((out / "summary.json").read_text())
    assert summary["days"] == 2 and "2021-02-01" in summary["prices"]
    # the same closed loop as the library on these prices
    system = SystemConfig()
    prices = cli_inputs.month_prices(export, "Tr.heim", "2021-02", system, days=2)
    theta = Theta.nominal(system)
    record = evaluate_mpc(theta, solvers.make_solver(MPC(system), None, theta), prices, system,
                          seed=0)
    assert summary["J"] == pytest.approx(record.J(), rel=1e-9)


@pytest.mark.parametrize("extra, match", [
    (["--area", "Tr.heim"], "--area given without --prices"),
    (["--month", "2021-02"], "--month given without --prices"),
    (["--prices", "{export}"], "without --month"),
    (["--prices", "{missing}", "--month", "2021-02"], "no such file"),
    (["--prices", "{export}", "--month", "2021-02", "--area", "SE9"], "'SE9' is not in"),
])
@pytest.mark.parametrize("command", ["simulate", "learn", "baselines"])
def test_bad_prices_arguments_are_one_line_before_any_work(command, extra, match, export,
                                                          tmp_path, capsys):
    out = tmp_path / "out"
    extra = [e.format(export=export, missing=tmp_path / "nope.csv") for e in extra]
    sizes = {"simulate": ["--days", "1"], "learn": ["--months", "1"], "baselines": []}[command]
    code, err = run_cli([command, *sizes, "--out", out, *extra], capsys)
    assert code == 2 and len(err) == 1 and match in err[0], err
    assert not out.exists()


# -- evaluate ---------------------------------------------------------------------------------
def test_evaluate_pairs_the_learned_and_nominal_mpc(export, tmp_path, capsys):
    out = tmp_path / "eval"
    args = ["evaluate", "--history", RUN, "--prices", export, "--month", "2021-02", "--days",
            "2", "--draws", "3", "--seed", "5", "--out", out]
    code, err = run_cli(args, capsys)
    assert code == 0, err
    summary = json.loads((out / "summary.json").read_text())
    history = History.load(RUN)
    assert summary["seeds"] == [5, 6, 7]
    system = history.system
    prices = cli_inputs.month_prices(export, "Tr.heim", "2021-02", system, days=2)
    for name, theta in (("nominal", Theta.nominal(system)), ("learned", history.final_theta())):
        solver = solvers.make_solver(MPC(system), history.mpc, theta)
        expected = [evaluate_mpc(theta, solver, prices, system, s).J() for s in (5, 6, 7)]
        np.testing.assert_allclose(summary["policies"][name]["J"], expected, rtol=1e-9)
        stats = summary["policies"][name]["J_stats"]
        assert stats["mean"] == pytest.approx(np.mean(expected))
        assert stats["ci_low"] < stats["mean"] < stats["ci_high"]
    diff = summary["difference"]["learned - nominal"]
    paired = np.subtract(summary["policies"]["learned"]["J"], summary["policies"]["nominal"]["J"])
    assert diff["mean"] == pytest.approx(paired.mean())
    # finished results are kept unless --force
    before = (out / "summary.json").read_bytes()
    code, err = run_cli(args, capsys)
    assert code == 2 and len(err) == 1 and "--force" in err[0]
    assert (out / "summary.json").read_bytes() == before
    code, err = run_cli([*args[:-2], "--draws", "1", "--out", out, "--force"], capsys)
    assert code == 0, err
    assert json.loads((out / "summary.json").read_text())["draws"] == 1


def test_mean_ci_is_the_t_interval():
    stats = mean_ci([1.0, 2.0, 3.0, 6.0]).as_dict()
    half = 3.182446305284263 * np.std([1, 2, 3, 6], ddof=1) / 2  # t_{0.975, 3}
    assert stats["ci_high"] - stats["mean"] == pytest.approx(half)
    assert mean_ci([4.0]).as_dict()["ci_low"] is None


@pytest.mark.skipif(not REAL_EXPORT.is_file(), reason="the Nord Pool export is not present")
def test_evaluate_on_a_month_of_the_real_export(tmp_path, capsys):
    code, err = run_cli(["evaluate", "--history", RUN, "--prices", REAL_EXPORT, "--month",
                         "2020-03", "--days", "1", "--draws", "2", "--out", tmp_path / "e"],
                        capsys)
    assert code == 0, err
    summary = json.loads((tmp_path / "e" / "summary.json").read_text())
    assert "2020-03-01" in summary["prices"]


def test_evaluate_refuses_a_missing_run(tmp_path, capsys):
    code, err = run_cli(["evaluate", "--history", tmp_path / "none", "--out", tmp_path / "e"],
                        capsys)
    assert code == 2 and len(err) == 1 and "--history" in err[0]
    assert not (tmp_path / "e").exists()


# -- --out ------------------------------------------------------------------------------------
COMMANDS = {
    "simulate": ["simulate", "--days", "1"],
    "baselines": ["baselines", "--days", "1"],
    "evaluate": ["evaluate", "--history", str(RUN), "--days", "1", "--draws", "1"],
    "report": ["report", "--notebooks", "01_battery_dynamics"],
}


@pytest.fixture
def no_work(monkeypatch):
    """Every command's work replaced by an error: a test passes only if it stops before."""

    def work(*_args, **_kwargs):
        raise AssertionError("the work started")

    for module, name in ((solvers, "make_solver"), (baselines, "evaluate_baselines"),
                         (transfer, "make_solver"), (report, "execute_notebook"),
                         (experiment, "make_solver")):
        monkeypatch.setattr(module, name, work)


@pytest.mark.parametrize("command", sorted(COMMANDS))
def test_out_naming_a_file_is_one_line(command, tmp_path, capsys, no_work):
    target = tmp_path / "file.txt"
    target.write_text("keep")
    code, err = run_cli([*COMMANDS[command], "--out", target], capsys)
    assert code == 2 and len(err) == 1 and "is an existing file" in err[0], err
    assert target.read_text() == "keep"


def _lock(directory: Path) -> bool:
    """Make ``directory`` unwritable: read-only, or immutable where we are root (root writes
    into read-only directories); False where neither is possible."""
    if os.geteuid() != 0:
        directory.chmod(0o555)
        return True
    chattr = shutil.which("chattr")
    if chattr is None:
        return False
    return subprocess.run([chattr, "+i", str(directory)], check=False,
                          capture_output=True).returncode == 0


def _unlock(directory: Path) -> None:
    if os.geteuid() == 0:
        subprocess.run(["chattr", "-i", str(directory)], check=False, capture_output=True)
    directory.chmod(0o755)


@pytest.mark.parametrize("command", sorted(COMMANDS))
def test_read_only_or_immutable_out_is_one_line(command, tmp_path, capsys, no_work):
    locked = tmp_path / "locked"
    locked.mkdir()
    if not _lock(locked):
        pytest.skip("cannot make a directory unwritable here (root without chattr)")
    try:
        code, err = run_cli([*COMMANDS[command], "--out", locked / "sub"], capsys)
        assert code == 2 and len(err) == 1 and "cannot write there" in err[0], err
        code, err = run_cli([*COMMANDS[command], "--out", locked], capsys)
        assert code == 2 and len(err) == 1 and "cannot write there" in err[0], err
        assert list(locked.iterdir()) == []
    finally:
        _unlock(locked)


@pytest.mark.parametrize("command, output", [("simulate", "summary.json"),
                                             ("baselines", "baselines.json"),
                                             ("evaluate", "summary.json"),
                                             ("report", "summary.json")])
def test_finished_results_are_kept_without_force(command, output, tmp_path, capsys, no_work):
    out = tmp_path / "done"
    out.mkdir()
    (out / output).write_text("{}")
    code, err = run_cli([*COMMANDS[command], "--out", out], capsys)
    assert code == 2 and len(err) == 1 and "--force" in err[0] and output in err[0], err
    assert (out / output).read_text() == "{}"
    with pytest.raises(AssertionError, match="the work started"):
        main([*COMMANDS[command], "--out", str(out), "--force"])


def test_report_with_an_unknown_notebook_creates_nothing(tmp_path, capsys):
    out = tmp_path / "report"
    code, err = run_cli(["report", "--notebooks", "99_nothing", "--out", out], capsys)
    assert code == 2 and len(err) == 1 and "99_nothing" in err[0]
    assert not out.exists()


def test_baselines_json_is_strict(tmp_path, capsys):
    out = tmp_path / "b"
    code, err = run_cli(["baselines", "--days", "1", "--out", out, "--quiet"], capsys)
    assert code == 0, err

    def refuse(constant):
        raise ValueError(f"{constant} is not JSON")

    data = json.loads((out / "baselines.json").read_text(), parse_constant=refuse)
    assert set(data["policies"]) >= {"clairvoyant", "nominal", "rule_based"}
    assert not list(out.glob(".*.tmp"))


# -- size of the work -------------------------------------------------------------------------
@pytest.mark.parametrize("command", ["simulate", "tune"])
def test_too_much_memory_is_refused_before_allocating(command, tmp_path, capsys):
    # tune used to repeat the shipped month to that many days before checking (179 GiB)
    code, err = run_cli([command, "--days", "1000000000", "--out", tmp_path / "s"], capsys)
    assert code == 2 and len(err) == 1
    assert "--days 1000000000" in err[0] and "GiB available" in err[0]
    assert not (tmp_path / "s").exists()


def test_too_long_a_run_is_refused(tmp_path, capsys, monkeypatch):
    code, err = run_cli(["simulate", "--days", "2", "--n", "100000", "--out", tmp_path / "s"],
                        capsys)
    assert code == 2 and len(err) == 1 and "--n 100000" in err[0] and "time limit" in err[0]
    # the limit is the documented one, and the environment variable moves it
    monkeypatch.setenv(cli_inputs.TIME_LIMIT_ENV, "1e-6")
    code, err = run_cli(["simulate", "--days", "1", "--out", tmp_path / "s"], capsys)
    assert code == 2 and len(err) == 1 and "time limit" in err[0]
    monkeypatch.setenv(cli_inputs.TIME_LIMIT_ENV, "soon")
    code, err = run_cli(["simulate", "--days", "1", "--out", tmp_path / "s"], capsys)
    assert code == 2 and len(err) == 1 and "MPCRL_LITE_TIME_LIMIT_S='soon'" in err[0]


def test_estimate_grows_with_the_work():
    small, days, agents = (cli_inputs.estimate(3, 30), cli_inputs.estimate(3, 60),
                           cli_inputs.estimate(6, 30))
    assert days.memory > small.memory and days.seconds > small.seconds
    assert agents.memory > small.memory and agents.seconds > small.seconds
    assert cli_inputs.estimate(3, 30, sensitivities=True).seconds > small.seconds


# -- fuzz -------------------------------------------------------------------------------------
class WorkStarted(Exception):
    """Raised by the stubbed work: every check before it passed."""


def _stub(*_args, **_kwargs):
    raise WorkStarted


def _stub_init(self, *_args, **_kwargs):
    raise WorkStarted


_GOOD = st.sampled_from(["1", "2", "3"])
_NUMBERS = st.one_of(_GOOD, st.sampled_from(["0", "-1", "3.5", "nan", "inf", "1e9", "1000000000",
                                             "abc", "", "100000", "-inf", "1e308", "1e-320",
                                             "-1e5", "1e300"]))
_MONTHS = st.sampled_from(["2021-02", "2021-02", "2021-03", "2021-2", "1999-13", "x"])
_AREAS = st.sampled_from(["Tr.heim", "Oslo", "Bergen", "", "tr.heim"])
_OUTS = st.sampled_from(["FRESH", "FRESH", "FRESH", "FILE", "DONE", ""])
_FLAGS = {
    "--days": _NUMBERS, "--n": _NUMBERS, "--seed": _NUMBERS, "--p-bar": _NUMBERS,
    "--noise-var": _NUMBERS, "--tau": _NUMBERS, "--months": _NUMBERS, "--draws": _NUMBERS,
    "--month": _MONTHS, "--area": _AREAS, "--prices": st.sampled_from(["EXPORT", "MISSING"]),
    "--out": _OUTS, "--history": st.sampled_from(["RUN", "MISSING"]),
    "--backend": st.sampled_from(["batch", "x"]), "--profile": st.sampled_from(["ci", "nope"]),
    "--notebooks": st.sampled_from(["01_battery_dynamics", "99_none"]),
    "--force": st.none(), "--resume": st.none(), "--quiet": st.none(), "--bogus": st.none(),
    "--adopt": st.none(), "--step-size": _NUMBERS, "--seeds": _NUMBERS, "--lockstep": _NUMBERS,
    "--workers": st.sampled_from(["0", "0", "1", "-1", "x"]),
    "--scheduler": st.sampled_from(["garbage", "tcp://127.0.0.1:1", "serial", ""]),
    "--grid": st.sampled_from(["GRID", "GRID", "DUPGRID", "MISSING", "FILE"]),
    "--system": st.sampled_from(["SYSTEM", "SYSTEM", "DUPSYSTEM", "BADSYSTEM", "MISSING"]),
    "--evals": _NUMBERS, "--heldout-draws": _NUMBERS, "--popsize": _NUMBERS,
}
# What each command needs, drawn first (mostly valid) so that the cases reach the work too.
_REQUIRED = {
    "simulate": ("--days", "--out"), "learn": ("--months", "--days", "--out"),
    "baselines": ("--days", "--out"), "evaluate": ("--history", "--draws", "--days", "--out"),
    "report": ("--notebooks", "--profile", "--out"),
    "sweep": ("--grid", "--workers", "--out"),
    "study": ("--seeds", "--months", "--days", "--workers", "--out"),
    "tune": ("--evals", "--draws", "--days", "--out"),
}
_COMMANDS = sorted(_REQUIRED)


@st.composite
def argument_lists(draw, command: str) -> list[str]:
    """The command's required flags, then up to 6 flags of any command, each with a value
    that is valid or not."""
    args = [command]
    if draw(st.booleans()):  # half the cases: a month of the export as well
        args += ["--prices", "EXPORT", "--month", draw(_MONTHS)]
    flags = [*_REQUIRED[command], *draw(st.lists(st.sampled_from(sorted(_FLAGS)), max_size=6))]
    for flag in flags:
        args.append(flag)
        value = draw(_FLAGS[flag])
        if value is not None:
            args.append(value)
    return args


@pytest.fixture
def stubbed(monkeypatch):
    for module, name in ((solvers, "make_solver"), (baselines, "evaluate_baselines"),
                         (transfer, "make_solver"), (report, "execute_notebook"),
                         (experiment, "make_solver")):
        monkeypatch.setattr(module, name, _stub)
    monkeypatch.setattr(decentralized.DecentralizedExperiment, "__init__", _stub_init)
    # sweeps and studies: the runs, the causal target and the scheduler's answer
    for name in ("run_serial", "run_dask"):
        monkeypatch.setattr(sweep_api, name, _stub)
    monkeypatch.setattr(study_module, "_study_target", _stub)
    monkeypatch.setattr(tune_module, "tune", _stub)

    def no_scheduler(address, *_args):
        raise sweep_api.SchedulerError(f"no Dask scheduler answered at {address}")

    monkeypatch.setattr(sweep_api, "check_scheduler", no_scheduler)


@pytest.mark.parametrize("command", _COMMANDS)
@settings(max_examples=25, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
@given(data=st.data())
def test_fuzz_any_arguments_end_in_one_line_or_work(command, data, tmp_path, capsys, stubbed):
    base = tmp_path / f"case{len(list(tmp_path.iterdir()))}"
    base.mkdir()
    export = write_export(base / "elspot.csv", 2021, 2)
    (base / "file").write_text("x")
    (base / "done").mkdir()
    (base / "done" / "summary.json").write_text("{}")
    (base / "done" / "baselines.json").write_text("{}")
    (base / "grid.yaml").write_text("base: {learning: {months: 1, days_per_month: 1}}\n"
                                    "grid: {learning.seed: [0, 1]}\n")
    (base / "dup.yaml").write_text("grid:\n  learning.seed: [0]\n  learning.seed: [1]\n")
    (base / "system.yaml").write_text("P_bar: 1.2\nU_bar: [1.0, 1.0, 0.5]\n")
    (base / "dupsystem.yaml").write_text("P_bar: 1.2\nP_bar: 1.0\n")
    (base / "badsystem.yaml").write_text("noise_var: 1.0e+308\n")
    where = {"EXPORT": export, "MISSING": base / "missing", "FRESH": base / "fresh",
             "FILE": base / "file", "DONE": base / "done", "RUN": base / "run",
             "GRID": base / "grid.yaml", "DUPGRID": base / "dup.yaml",
             "SYSTEM": base / "system.yaml", "DUPSYSTEM": base / "dupsystem.yaml",
             "BADSYSTEM": base / "badsystem.yaml"}
    shutil.copytree(RUN, base / "run")
    args = [str(where.get(a, a)) for a in data.draw(argument_lists(command))]
    capsys.readouterr()
    try:
        code = main(args)
    except SystemExit as exit_:  # argparse
        code = exit_.code
    except WorkStarted:
        code = None
    err = capsys.readouterr().err.strip().splitlines()
    outcome = {None: "work started", 0: "exit 0", 2: "exit 2"}.get(code, f"exit {code}")
    event(outcome)
    assert code in (None, 0, 2), (args, code, err)
    if code == 2:
        assert len(err) == 1 and "error:" in err[0], (args, err)
        assert not (base / "fresh").exists(), args  # nothing created by a refused command
    assert (base / "file").read_text() == "x"
    # --force may replace the results in DONE (its summary.json is then gone): only without
    # it must they be untouched
    assert "--force" in args or (base / "done" / "summary.json").read_text() == "{}"
    assert not any("Traceback" in line for line in err)


def test_learn_on_another_month(export, tmp_path, capsys):
    out = tmp_path / "run"
    code, err = run_cli(["learn", "--months", "1", "--days", "2", "--prices", export, "--month",
                         "2021-02", "--out", out, "--no-figures", "--quiet"], capsys)
    assert code == 0, err
    history = History.load(out)
    system = SystemConfig()
    prices = cli_inputs.month_prices(export, "Tr.heim", "2021-02", system, days=2)
    expected = experiment.Experiment(
        system, None, history.learning, prices=prices).run(months=1, progress=False)
    assert history.J == pytest.approx(expected.J, rel=1e-9)
    # on a price file Adam's cost scales follow its price level (recorded as resolved) ...
    assert history.learning.scale_to_prices is True
    level = price_level(prices)
    assert level == pytest.approx(np.mean([[price(d, h) for h in range(24)] for d in (1, 2)])
                                  / REFERENCE_PRICE, rel=1e-12)
    auto = experiment.Experiment(system, None, experiment.LearningConfig(days_per_month=2),
                                 prices=prices)
    assert auto.learning.scale_to_prices is True
    np.testing.assert_allclose(auto.updater.scale[Theta.index(3, "b")], 10.0 * level,
                               rtol=1e-15)
    # ... unless told not to; a resume cannot change it
    code, err = run_cli(["learn", "--months", "2", "--days", "2", "--prices", export, "--month",
                         "2021-02", "--out", out, "--no-figures", "--quiet", "--resume",
                         "--no-scale-to-prices"], capsys)
    assert code == 2 and len(err) == 1 and "--no-scale-to-prices with --resume" in err[0], err
    plain = tmp_path / "plain"
    code, err = run_cli(["learn", "--months", "1", "--days", "2", "--prices", export, "--month",
                         "2021-02", "--out", plain, "--no-figures", "--quiet",
                         "--no-scale-to-prices"], capsys)
    assert code == 0, err
    assert History.load(plain).learning.scale_to_prices is False
    # the first month runs on the nominal theta either way; the step differs by the level
    unscaled = History.load(plain)
    assert unscaled.J[0] == history.J[0]
    first = np.array(history.theta_final) - np.array(history.theta[0])
    second = np.array(unscaled.theta_final) - np.array(unscaled.theta[0])
    b = Theta.index(3, "b")
    assert np.all(second[b] != 0)
    np.testing.assert_allclose(first[b], level * second[b], rtol=1e-9)


def test_baselines_json_writes_nan_as_null(tmp_path, monkeypatch):
    def fake(*_args, **_kwargs):
        return {"policies": {"nominal": {"J": float("nan"), "J_per_day": [1.0, float("inf")]}},
                "gap_closed": {"rule_based": float("nan")}}

    monkeypatch.setattr(baselines, "evaluate_baselines", fake)
    baselines.run_baselines_cli(SystemConfig(), None, experiment.LearningConfig(), None,
                                tmp_path / "b")
    text = (tmp_path / "b" / "baselines.json").read_text()
    assert "NaN" not in text and "Infinity" not in text
    data = json.loads(text)
    assert data["policies"]["nominal"] == {"J": None, "J_per_day": [1.0, None]}
    assert data["gap_closed"]["rule_based"] is None


_SMALL = {"--days": st.sampled_from(["1", "2", "0", "x"]), "--n": st.sampled_from(["1", "2", "0"]),
          "--seed": st.sampled_from(["0", "7", "-3"]), "--draws": st.sampled_from(["1", "2", "0"]),
          "--p-bar": st.sampled_from(["1.0", "1.5", "nan"]), "--month": _MONTHS,
          "--force": st.none()}


@pytest.mark.parametrize("command", ["simulate", "evaluate"])
@settings(max_examples=6, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
@given(data=st.data())
def test_fuzz_small_real_runs_end_in_exit_0_or_one_line(command, data, tmp_path, capsys):
    base = tmp_path / f"case{len(list(tmp_path.iterdir()))}"
    base.mkdir()
    export = write_export(base / "elspot.csv", 2021, 2)
    args = [command, "--out", str(base / "out"), "--quiet"]
    args += ["--days", "1"] if command == "simulate" else ["--history", str(RUN), "--days", "1"]
    if data.draw(st.booleans()):
        args += ["--prices", str(export), "--month", "2021-02"]
    allowed = sorted(k for k in _SMALL if command == "evaluate" or k != "--draws")
    for flag in data.draw(st.lists(st.sampled_from(allowed), max_size=3)):
        value = data.draw(_SMALL[flag])
        args += [flag] if value is None else [flag, value]
    capsys.readouterr()
    try:
        code = main(args)
    except SystemExit as exit_:
        code = exit_.code
    err = capsys.readouterr().err.strip().splitlines()
    event(f"exit {code}")
    assert code in (0, 2), (args, err)
    if code == 2:
        assert len(err) == 1 and "error:" in err[0], (args, err)
        assert not (base / "out").exists()
    else:
        json.loads((base / "out" / "summary.json").read_text())
        assert not list((base / "out").glob(".*.tmp"))


# -- the MPC's forecast (--forecast) and the run's prices on --resume ---------------------------
def test_learn_with_the_day_end_forecast_records_and_keeps_it(tmp_path, capsys):
    out = tmp_path / "run"
    base = ["learn", "--days", "2", "--out", out, "--no-figures", "--quiet"]
    code, err = run_cli([*base, "--months", "1", "--forecast", "until_midnight"], capsys)
    assert code == 0, err
    assert json.loads((out / "summary.json").read_text())["forecast"] == "until_midnight"
    assert History.load(out).mpc.forecast == "until_midnight"
    # the paper's forecast on resume is another policy class: refused in one line
    code, err = run_cli([*base, "--months", "2", "--resume", "--forecast", "paper"], capsys)
    assert code == 2 and len(err) == 1
    assert "mpc.forecast='until_midnight' in the run, 'paper' now" in err[0]
    # without --forecast a resume keeps the run's
    code, err = run_cli([*base, "--months", "2", "--resume"], capsys)
    assert code == 0, err
    assert History.load(out).months == 2


def test_simulate_and_evaluate_honour_the_forecast(tmp_path, capsys):
    runs = {}
    for forecast in ("paper", "until_midnight"):
        out = tmp_path / forecast
        code, err = run_cli(["simulate", "--days", "1", "--out", out, "--seed", "3", "--quiet",
                             "--forecast", forecast], capsys)
        assert code == 0, err
        runs[forecast] = json.loads((out / "summary.json").read_text())
        assert runs[forecast]["mpc"]["forecast"] == forecast
    assert runs["paper"]["J"] != pytest.approx(runs["until_midnight"]["J"], rel=1e-6)
    # evaluate: the run's own forecast by default, --forecast overrides it
    found = {}
    for extra in ([], ["--forecast", "until_midnight"]):
        out = tmp_path / f"eval{len(extra)}"
        code, err = run_cli(["evaluate", "--history", RUN, "--days", "1", "--draws", "1",
                             "--out", out, *extra], capsys)
        assert code == 0, err
        found[len(extra)] = json.loads((out / "summary.json").read_text())
    assert found[0]["mpc"]["forecast"] == History.load(RUN).mpc.forecast == "paper"
    assert found[2]["mpc"]["forecast"] == "until_midnight"
    assert found[0]["policies"]["nominal"]["J"] != pytest.approx(
        found[2]["policies"]["nominal"]["J"], rel=1e-6)


@pytest.mark.parametrize("command", ["learn", "simulate", "baselines", "evaluate", "study"])
def test_a_bad_forecast_is_one_line(command, tmp_path):
    proc = subprocess.run(
        [os.sys.executable, "-m", "mpcrl_lite", command, "--forecast", "midnight", "--out",
         str(tmp_path / "x")], capture_output=True, text=True, timeout=120, check=False)
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "--forecast" in lines[0] and "'midnight'" in lines[0], proc.stderr
    assert "until_midnight" in lines[0]
    assert not (tmp_path / "x").exists()


def test_learn_resume_with_other_prices_is_refused_in_one_line(export, tmp_path, capsys):
    out = tmp_path / "run"
    base = ["learn", "--days", "2", "--prices", export, "--month", "2021-02", "--out", out,
            "--no-figures", "--quiet"]
    code, err = run_cli([*base, "--months", "1"], capsys)
    assert code == 0, err
    before = (out / "checkpoint.json").read_bytes()
    for other in ([*base, "--area", "Oslo"],  # another column of the same export
                  ["learn", "--days", "2", "--out", out, "--no-figures", "--quiet"]):  # shipped
        code, err = run_cli([*other, "--months", "2", "--resume"], capsys)
        assert code == 2 and len(err) == 1, err
        assert "other prices" in err[0] and "Tr.heim" in err[0], err[0]
        assert (out / "checkpoint.json").read_bytes() == before
    code, err = run_cli([*base, "--months", "2", "--resume"], capsys)
    assert code == 0, err


def test_learn_on_a_price_file_keeps_its_evaluation_draws(export, tmp_path, capsys):
    """``--eval-draws`` holds with ``--prices`` (the month's days re-make the configs)."""
    out = tmp_path / "run"
    code, err = run_cli(["learn", "--prices", export, "--area", "Tr.heim", "--month", "2021-02",
                         "--days", "2", "--months", "1", "--eval-draws", "2", "--no-figures",
                         "--out", out, "--quiet"], capsys)
    assert code == 0, err
    history = json.loads((out / "history.json").read_text())
    assert history["learning"]["eval_draws"] == 2
    assert history["learning"]["days_per_month"] == 2


def test_learn_refuses_an_evaluation_batch_beyond_the_memory_in_one_line(monkeypatch, tmp_path,
                                                                         capsys):
    """A month that fits but whose evaluation batch (``eval_draws`` months at once) does not:
    refused before any work, in one line, as the library would refuse it."""
    from mpcrl_lite._util import budget

    days = 20_000
    month = budget.learning_estimate(3, days, 1).memory  # a learning month alone
    batch = budget.learning_estimate(3, days, 1, eval_draws=10, eval_every=5).memory
    assert batch > 2 * month
    monkeypatch.setattr(budget, "available_memory", lambda: 1.5 * month)
    code, err = run_cli(["learn", "--months", "1", "--days", str(days), "--out",
                         tmp_path / "run"], capsys)
    assert code == 2 and len(err) == 1, err
    assert "--eval-draws 10" in err[0] and "GiB of memory" in err[0]
    assert not (tmp_path / "run").exists()
