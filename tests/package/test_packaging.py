"""The package installs anywhere: a wheel carries the repository's data/ and notebooks/ (the one
copy, mapped into the package at build time), finds them through importlib.resources from any
working directory, and runs a notebook in a fresh virtual environment outside the checkout.
The first code cell of every notebook installs the package only where it is missing.
"""

from __future__ import annotations

import importlib.util
import json
import os
import shutil
import subprocess
import sys
import sysconfig
import zipfile
from pathlib import Path

import nbformat
import nbref
import pytest

from mpcrl_lite._util import resources
from mpcrl_lite.publish.launch import INSTALL_TAG, install_requirement

ROOT = nbref.ROOT
STEMS = nbref.stems()
# What the build reads: pyproject.toml maps data/ and notebooks/ into the package.
BUILD_INPUTS = ("pyproject.toml", "README.md", "mpcrl_lite", "data", "notebooks")


def _clean_env(**extra: str) -> dict[str, str]:
    """The environment of a process that must not see the checkout through PYTHONPATH."""
    env = {k: v for k, v in os.environ.items()
           if k not in ("PYTHONPATH", "PYTHONHOME", "JUPYTER_PATH", "VIRTUAL_ENV")}
    env.update(MPLBACKEND="Agg", PYTHONNOUSERSITE="1", **extra)
    return env


def _copy_build_inputs(folder: Path) -> Path:
    """Copy what the build reads into ``folder`` (the checkout then gets no build/ or
    egg-info folders)."""
    folder.mkdir(parents=True, exist_ok=True)
    for name in BUILD_INPUTS:
        path = ROOT / name
        if path.is_dir():
            shutil.copytree(path, folder / name,
                            ignore=shutil.ignore_patterns("__pycache__", ".ipynb_checkpoints"))
        else:
            shutil.copy2(path, folder / name)
    return folder


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> Path:
    """The wheel, built from a copy of the build inputs the way `pip wheel . --no-deps` does."""
    src = _copy_build_inputs(tmp_path_factory.mktemp("src"))
    dist = tmp_path_factory.mktemp("dist")
    build = subprocess.run(
        [sys.executable, "-m", "pip", "wheel", str(src), "-w", str(dist), "--no-deps", "-q",
         "--disable-pip-version-check"],
        capture_output=True, text=True, env=_clean_env(), timeout=300)
    assert build.returncode == 0, f"pip wheel failed:\n{build.stdout[-2000:]}{build.stderr[-3000:]}"
    (found,) = dist.glob("mpcrl_lite-*.whl")
    return found


def _shipped_files() -> dict[str, Path]:
    """Files of data/ and notebooks/ that the wheel must carry, by their name in the wheel."""
    files = {f"mpcrl_lite/data/{p.name}": p for p in (ROOT / "data").iterdir()
             if p.suffix in (".csv", ".md")}
    # the stored results of the search for a class's best theta (notebook 08, --class-best)
    files |= {f"mpcrl_lite/data/{p.parent.name}/{p.name}": p
              for p in (ROOT / "data").glob("class_best_*/*.json")}
    files |= {f"mpcrl_lite/notebooks/{p.name}": p
              for p in (ROOT / "notebooks").glob("[0-9][0-9]_*.ipynb")}
    files |= {f"mpcrl_lite/notebooks/{p.name}": p
              for p in (ROOT / "notebooks").glob("*_parameters.yaml")}
    return files


def test_wheel_carries_data_and_notebooks_identical_to_the_repository(wheel):
    expected = _shipped_files()
    assert "mpcrl_lite/data/no3_nov2020_daily.csv" in expected
    assert "mpcrl_lite/notebooks/classroom_parameters.yaml" in expected
    with zipfile.ZipFile(wheel) as archive:
        names = set(archive.namelist())
        for name, path in expected.items():
            assert name in names, f"{wheel.name} lacks {name}"
            assert archive.read(name) == path.read_bytes(), f"{name} differs from {path}"
        shipped = {n for n in names if n.startswith(("mpcrl_lite/data/", "mpcrl_lite/notebooks/"))}
    # nothing else from those folders (no checkpoints, no teachers' notes)
    assert shipped == set(expected), sorted(shipped - set(expected))


def test_unpacked_wheel_finds_its_data_from_any_directory(wheel, tmp_path):
    site = tmp_path / "site-packages"
    with zipfile.ZipFile(wheel) as archive:
        archive.extractall(site)
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    code = """
import json, mpcrl_lite
from mpcrl_lite.system import prices
from mpcrl_lite.publish import report
p = prices.Prices.default()
print(json.dumps({
    "package": mpcrl_lite.__file__, "data": str(prices.DATA_DIR),
    "notebooks": str(report.NOTEBOOK_DIR), "shape": list(p.buy.shape),
    "mean": float(p.buy.mean()),
    "stems": [q.stem for q in report.notebook_paths()],
    "parameters": sorted(report.notebook_parameters("01_battery_dynamics.ipynb")),
    "classroom": sorted(report.profile_parameters("classroom")),
}))
"""
    run = subprocess.run([sys.executable, "-c", code], cwd=elsewhere, capture_output=True,
                         text=True, env=_clean_env(PYTHONPATH=str(site)), timeout=120)
    assert run.returncode == 0, run.stderr[-3000:]
    info = json.loads(run.stdout.strip().splitlines()[-1])
    for key in ("package", "data", "notebooks"):
        assert Path(info[key]).resolve().is_relative_to(site.resolve()), (key, info[key])
    assert info["shape"] == [30, 24]
    assert info["mean"] == pytest.approx(56.35, abs=0.01)  # data/README.md
    assert info["stems"] == STEMS
    assert "DAYS" in info["parameters"]
    assert info["classroom"] == _classroom_stems()


def _classroom_stems() -> list[str]:
    import yaml

    return sorted(yaml.safe_load((ROOT / "notebooks" / "classroom_parameters.yaml").read_text()))


def test_a_checkout_reads_the_top_level_folders():
    # This test session imports the package from the checkout (or an editable install of it):
    # no copy inside the package, so the repository's folders are the ones read.
    import mpcrl_lite
    from mpcrl_lite.publish.report import NOTEBOOK_DIR
    from mpcrl_lite.system.prices import DATA_DIR

    checkout = Path(mpcrl_lite.__file__).resolve().parent.parent
    assert not (checkout / "mpcrl_lite" / "data").exists()
    assert DATA_DIR == checkout / "data" and NOTEBOOK_DIR == checkout / "notebooks"
    candidates = resources.candidate_folders("data")
    assert candidates[0] == checkout / "mpcrl_lite" / "data"  # an installed wheel's place first
    assert candidates[-1] == checkout / "data"


def test_unknown_shipped_folder_is_an_error():
    with pytest.raises(ValueError,
                       match=r"name='figures': expected one of \['data', 'notebooks'\]"):
        resources.package_folder("figures")


# -- the install cell ---------------------------------------------------------------------------
def _install_cell(stem: str):
    nb = nbref.read_notebook(stem)
    (cell,) = [c for c in nb.cells if INSTALL_TAG in c.get("metadata", {}).get("tags", [])]
    return cell


@pytest.mark.parametrize("stem", STEMS)
def test_install_cell_does_nothing_where_the_package_is_importable(stem, monkeypatch):
    calls = []
    monkeypatch.setattr(subprocess, "run", lambda *args, **kwargs: calls.append(args))
    exec(compile(_install_cell(stem).source, f"{stem}-install", "exec"), {})
    assert calls == []


@pytest.mark.parametrize("stem", [STEMS[0], STEMS[-1]])
def test_install_cell_installs_the_package_where_it_is_missing(stem, monkeypatch):
    calls = []
    real_find_spec = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *args: (
        None if name == "mpcrl_lite" else real_find_spec(name, *args)))
    monkeypatch.setattr(subprocess, "run", lambda *args, **kwargs: calls.append((args, kwargs)))
    exec(compile(_install_cell(stem).source, f"{stem}-install", "exec"), {})
    ((args, kwargs),) = calls
    assert args[0] == [sys.executable, "-m", "pip", "install", "--quiet",
                       install_requirement(stem)]
    assert kwargs == {"check": True}
    assert install_requirement(stem).startswith("mpcrl_lite[classroom")
    assert ("sweep" in install_requirement(stem)) == stem.startswith("07")


# -- a fresh virtual environment ----------------------------------------------------------------
@pytest.mark.notebook
def test_wheel_in_a_fresh_venv_outside_the_checkout_runs_notebook_01(wheel, tmp_path):
    """pip installs the wheel into a new virtual environment; notebook 01 (CI profile) runs
    there with the kernel of that environment, from a folder outside the checkout."""
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True,
                   timeout=120)
    python = venv / "bin" / "python"
    install = subprocess.run(
        [sys.executable, "-m", "pip", "--python", str(python), "install", "--no-deps",
         "--no-index", "-q", "--disable-pip-version-check", str(wheel)],
        capture_output=True, text=True, env=_clean_env(), timeout=300)
    assert install.returncode == 0, install.stderr[-3000:]
    # The dependencies (numpy, casadi, papermill, ...) come from this test's environment:
    # a path file adds its site-packages *after* the venv's own, where the wheel sits.
    purelib = Path(subprocess.run(
        [str(python), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
        capture_output=True, text=True, check=True, env=_clean_env()).stdout.strip())
    deps = {sysconfig.get_paths()["purelib"], sysconfig.get_paths()["platlib"]}
    (purelib / "zz_test_dependencies.pth").write_text("\n".join(sorted(deps)) + "\n")
    installed_before = sorted(p.name for p in purelib.iterdir())

    work = tmp_path / "work"
    work.mkdir()
    code = f"""
import json, sys
import mpcrl_lite
from jupyter_client.kernelspec import KernelSpecManager
from mpcrl_lite.publish.report import execute_notebook, profile_parameters
nb = execute_notebook({str(nbref.notebook_path(STEMS[0]))!r}, "out.ipynb",
                      profile_parameters("ci")[{STEMS[0]!r}], cwd=".")
print(json.dumps({{"package": mpcrl_lite.__file__,
                   "kernel": KernelSpecManager().get_kernel_spec("python3").argv[0],
                   "python": sys.executable}}))
"""
    run = subprocess.run([str(python), "-c", code], cwd=work, capture_output=True, text=True,
                         env=_clean_env(JUPYTER_DATA_DIR=str(tmp_path / "jupyter-data")),
                         timeout=600)
    assert run.returncode == 0, run.stdout[-2000:] + run.stderr[-4000:]
    info = json.loads(run.stdout.strip().splitlines()[-1])
    assert Path(info["package"]).resolve().is_relative_to(venv.resolve()), info
    assert Path(info["kernel"]).parent == python.parent or info["kernel"] == info["python"], info
    assert "without encryption" not in run.stderr  # local kernels talk over IPC sockets
    nb = nbformat.read(work / "out.ipynb", as_version=4)
    errors = [o for c in nb.cells for o in c.get("outputs", []) if o.output_type == "error"]
    assert not errors, errors[0].get("evalue")
    install_cell = next(c for c in nb.cells if INSTALL_TAG in c.metadata.get("tags", []))
    assert install_cell.outputs == []  # the package was importable: nothing installed
    assert sorted(p.name for p in purelib.iterdir()) == installed_before
    assert nbref.read_notebook(STEMS[0]).cells[-1].id == nb.cells[-1].id


def test_editable_install_reads_the_repository_folders(tmp_path):
    """`pip install -e .` (what `make setup` does) maps the package to the source tree; the
    data and notebooks are then read from the top-level folders, still from any directory."""
    src = _copy_build_inputs(tmp_path / "src")
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True,
                   timeout=120)
    python = venv / "bin" / "python"
    install = subprocess.run(
        [sys.executable, "-m", "pip", "--python", str(python), "install", "--no-deps", "-q",
         "--disable-pip-version-check", "-e", str(src)],
        capture_output=True, text=True, env=_clean_env(), timeout=300)
    assert install.returncode == 0, install.stderr[-3000:]
    purelib = Path(subprocess.run(
        [str(python), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
        capture_output=True, text=True, check=True, env=_clean_env()).stdout.strip())
    deps = {sysconfig.get_paths()["purelib"], sysconfig.get_paths()["platlib"]}
    (purelib / "zz_test_dependencies.pth").write_text("\n".join(sorted(deps)) + "\n")
    code = ("import json, mpcrl_lite\nfrom mpcrl_lite.system import prices\nfrom mpcrl_lite.publish import report\n"
            "print(json.dumps([mpcrl_lite.__file__, str(prices.DATA_DIR), "
            "str(report.NOTEBOOK_DIR), prices.Prices.default().buy.shape[0]]))")
    run = subprocess.run([str(python), "-c", code], cwd=tmp_path, capture_output=True,
                         text=True, env=_clean_env(), timeout=120)
    assert run.returncode == 0, run.stderr[-3000:]
    package, data, notebooks, days = json.loads(run.stdout.strip().splitlines()[-1])
    assert Path(package).resolve() == (src / "mpcrl_lite" / "__init__.py").resolve()
    assert Path(data).resolve() == (src / "data").resolve()
    assert Path(notebooks).resolve() == (src / "notebooks").resolve()
    assert days == 30
