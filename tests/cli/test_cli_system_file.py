"""``--system FILE.yaml``: the system of a YAML file, the flags over it, one-line refusals."""

from __future__ import annotations

import argparse
import json

import pytest

from mpcrl_lite.cli import args as cli_args
from mpcrl_lite.cli.args import UsageError
from mpcrl_lite.cli.main import build_parser, main
from mpcrl_lite.config import SystemConfig


def _parse(argv: list[str]) -> argparse.Namespace:
    return build_parser().parse_args(argv)


def test_the_file_sets_the_system_and_the_flags_override_it(tmp_path):
    path = tmp_path / "site.yaml"
    path.write_text("n: 2\nP_bar: 1.2\nnoise_var: 0.3\nsoc0: 0.5\nomega: [10, 30]\n")
    system, _, _ = cli_args.configs(_parse(["simulate", "--days", "1", "--out", "o",
                                            "--system", str(path)]))
    assert system == SystemConfig(n=2, P_bar=1.2, noise_var=0.3, soc0=0.5, omega=(10.0, 30.0))
    system, _, _ = cli_args.configs(_parse(["learn", "--months", "1", "--out", "o",
                                            "--system", str(path), "--p-bar", "0.7",
                                            "--n", "3", "--noise-var", "0.1"]))
    assert system == SystemConfig(n=3, P_bar=0.7, noise_var=0.1, soc0=0.5, omega=(10.0, 30.0))
    empty = tmp_path / "empty.yaml"
    empty.write_text("# nothing set\n")
    system, _, _ = cli_args.configs(_parse(["baselines", "--out", "o", "--system", str(empty)]))
    assert system == SystemConfig()


@pytest.mark.parametrize("text, message", [
    ("n: 2\nbattery_size: 3\n", "unknown field(s) ['battery_size']"),
    ("P_bar: big\n", "P_bar='big'"),
    ("P_bar: -1\n", "P_bar=-1: expected a value in (0, inf)"),
    ("n: [2\n", "not valid YAML: line 2, column 1"),
    ("- n: 2\n", "expected a mapping of SystemConfig fields"),
    ("omega: [1, 2, 3]\n", "omega=(1, 2, 3)"),
])
def test_a_malformed_file_is_refused_in_one_line(tmp_path, text, message):
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    with pytest.raises(UsageError) as info:
        cli_args.configs(_parse(["simulate", "--days", "1", "--out", "o", "--system", str(path)]))
    text = str(info.value)
    assert "\n" not in text and text.startswith(f"--system {path}: ")
    assert message in text


def test_a_missing_file_is_refused_before_any_work(tmp_path, capsys):
    out = tmp_path / "out"
    assert main(["simulate", "--days", "1", "--out", str(out),
                 "--system", str(tmp_path / "none.yaml")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "none.yaml: no such file" in err[0]
    assert not out.exists()


def test_simulate_runs_the_system_of_the_file(tmp_path):
    path = tmp_path / "site.yaml"
    path.write_text("n: 2\nP_bar: 0.8\n")
    out = tmp_path / "sim"
    assert main(["simulate", "--days", "1", "--out", str(out), "--system", str(path),
                 "--quiet"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["system"]["n"] == 2 and summary["P_bar"] == 0.8
    assert len(summary["J_per_agent"]) == 2


def test_every_system_command_takes_the_option():
    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    for command in ("simulate", "learn", "baselines", "study"):
        assert "system" in {a.dest for a in sub.choices[command]._actions}, command


def test_study_passes_the_file_as_the_sweeps_base(tmp_path, monkeypatch):
    from mpcrl_lite.studies import study

    path = tmp_path / "site.yaml"
    path.write_text("n: 2\nomega: [5, 5]\n")
    seen = {}

    def fake(seeds, months, out, **kwargs):
        seen.update(kwargs["base"])
        raise ValueError("stop here")

    monkeypatch.setattr(study, "run_study", fake)
    assert main(["study", "--seeds", "1", "--months", "1", "--out", str(tmp_path / "s"),
                 "--system", str(path)]) == 2
    assert seen == {"system.n": 2, "system.omega": (5, 5)}


def test_every_backend_runs_a_per_battery_input_bound_and_agrees(tmp_path, capsys):
    path = tmp_path / "u.yaml"
    path.write_text("U_bar: [2, 1, 0.5]\nP_bar: 2.0\n")
    J = {}
    for backend in ("ipopt", "kernel", "batch"):
        out = tmp_path / backend
        assert main(["simulate", "--days", "1", "--backend", backend, "--out", str(out),
                     "--system", str(path), "--quiet"]) == 0, capsys.readouterr().err
        summary = json.loads((out / "summary.json").read_text())
        assert summary["solver_failures"] == 0
        J[backend] = summary["J"]
    assert J["kernel"] == pytest.approx(J["ipopt"], rel=1e-8, abs=1e-8)
    assert J["batch"] == pytest.approx(J["ipopt"], rel=1e-8, abs=1e-8)


def test_auto_chooses_the_kernel_for_per_battery_input_bounds():
    from mpcrl_lite.mpc.backends.registry import make_solver
    from mpcrl_lite.mpc.formulation import MPC

    assert make_solver(MPC(SystemConfig(U_bar=(2.0, 1.0, 1.0), P_bar=2.0))).name == "kernel"
    assert make_solver(MPC(SystemConfig())).name == "kernel"


def test_the_decentralized_learner_takes_a_per_battery_input_bound(tmp_path, capsys):
    path = tmp_path / "u.yaml"
    path.write_text("U_bar: [2, 1, 0.5]\nP_bar: 2.0\n")
    out = tmp_path / "out"
    assert main(["learn", "--decentralized", "--months", "1", "--days", "1", "--out", str(out),
                 "--system", str(path), "--quiet", "--no-figures"]) == 0
    assert "U_bar" not in capsys.readouterr().err
    summary = json.loads((out / "summary.json").read_text())
    assert summary["months"] == 1 and max(summary["max_P_mpc"]) < 2.0
