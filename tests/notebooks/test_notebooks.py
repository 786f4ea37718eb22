"""The teaching notebooks: structure of the committed files, parameters, and execution.

Static tests (fast, no kernel) check the committed notebooks: kernelspec, exactly one
``parameters`` cell of typed literals, the ``check_parameters`` cell after it, one ``summary``
cell, exercises with ``solution`` cells that a student version can drop, no outputs.

Execution tests (marked ``notebook``) run every notebook once with papermill and the CI profile
(``notebooks/ci_parameters.yaml``) in a temporary directory, then compare the outputs with
``tests/notebook_refs/`` nbval-style (see ``tests/nbref.py``; regenerate the references with
``tools/update_notebook_refs.py`` after an intended change of results).
"""

from __future__ import annotations

import ast
import json
import math
import sys
from pathlib import Path

import nbformat
import nbref
import papermill
import pytest

from mpcrl_lite.publish.claims import check_claims, load_claims
from mpcrl_lite.publish.launch import (
    NOTEBOOK_FOLDER,
    STUDENT_FOLDER,
    binder_url,
    launch_badges,
    student_launch_line,
)
from mpcrl_lite.publish.report import (
    check_parameters,
    execute_notebook,
    notebook_parameters,
    read_summary,
)

STEMS = nbref.stems()

TOOLS = nbref.ROOT / "tools"
README = nbref.NOTEBOOK_DIR / "README.md"


def test_the_notebooks_exist():
    assert [s[:2] for s in STEMS] == ["01", "02", "03", "04", "05", "06", "07", "08", "09"], STEMS


# -- static structure ----------------------------------------------------------------------
def _tags(cell) -> list[str]:
    return list(cell.get("metadata", {}).get("tags", []))


def _code(nb) -> list:
    return [c for c in nb.cells if c.cell_type == "code"]


@pytest.mark.parametrize("stem", STEMS)
def test_committed_notebook_is_clean(stem):
    nb = nbref.read_notebook(stem)
    nbformat.validate(nb)
    assert nb.metadata["kernelspec"]["name"] == "python3"
    for cell in _code(nb):
        assert cell.outputs == [], f"{stem}: cell {cell.id} has outputs (commit notebooks clean)"
        assert cell.execution_count is None, f"{stem}: cell {cell.id} has an execution count"
    ids = [c.id for c in nb.cells]
    assert len(ids) == len(set(ids)), f"{stem}: duplicate cell ids"


@pytest.mark.parametrize("stem", STEMS)
def test_notebook_layout(stem):
    nb = nbref.read_notebook(stem)
    first = nb.cells[0]
    assert first.cell_type == "markdown" and first.source.startswith("# "), "title first"
    assert "Goal" in first.source and "you can" in first.source, "goal and objectives first"
    code = _code(nb)
    # the first code cell installs the package where it is missing (Colab; see test_site.py)
    assert "install" in _tags(code[0]), f"{stem}: the first code cell must be the install cell"
    code = code[1:]
    tagged = [c for c in nb.cells if "parameters" in _tags(c)]
    assert len(tagged) == 1, f"{stem}: expected exactly one 'parameters' cell"
    assert code[0] is tagged[0], f"{stem}: the parameters cell must follow the install cell"
    check = code[1].source
    assert f'check_parameters(globals(), "{stem}.ipynb")' in check, (
        f"{stem}: the cell after the parameters must call check_parameters with the file name")
    assert check.index("check_parameters(globals()") < check.index("%matplotlib inline"), (
        "check_parameters must run before anything else is imported")
    # figures are shown as drawn, not cropped to their content (which draws them twice), so
    # every figure must lay itself out inside its canvas (tests/figures check the package's)
    assert check.index("%matplotlib inline") < check.index(
        '%config InlineBackend.print_figure_kwargs = {"bbox_inches": None}'), (
        f"{stem}: the check cell must show figures uncropped after %matplotlib inline")
    for cell in code:
        if "plt.subplots(" in cell.source:
            assert 'layout="constrained"' in cell.source or "tight_layout()" in cell.source, (
                f"{stem}: cell {cell.id} draws a figure without a layout; shown uncropped, "
                "its labels could fall off the canvas")
    summary = [c for c in nb.cells if "summary" in _tags(c)]
    assert len(summary) == 1 and "show_summary(" in summary[0].source
    assert code[-1] is summary[0], f"{stem}: the summary cell comes last"
    text = "\n".join(c.source for c in nb.cells if c.cell_type == "markdown")
    for heading in ("## Exercises", "## Summary", "Interactive", "Check"):
        assert heading in text, f"{stem}: no '{heading}' section"
    assert any("mpcrl_lite.classroom.widgets" in c.source for c in code), f"{stem}: no widget"


@pytest.mark.parametrize("stem", STEMS)
def test_parameters_cell_holds_typed_documented_literals(stem):
    nb = nbref.read_notebook(stem)
    (cell,) = [c for c in nb.cells if "parameters" in _tags(c)]
    tree = ast.parse(cell.source)
    lines = cell.source.splitlines()
    for node in tree.body:
        assert isinstance(node, ast.AnnAssign), (
            f"{stem}: '{ast.unparse(node)}' is not NAME: type = literal")
        name = node.target.id
        assert name.isupper(), f"{stem}: parameter {name} is not UPPER_CASE"
        assert isinstance(node.value, ast.Constant), f"{stem}: {name} is not a literal"
        assert ast.unparse(node.annotation) in ("int", "float", "str", "bool"), name
        assert "#" in lines[node.lineno - 1], f"{stem}: {name} has no comment"


@pytest.mark.parametrize("stem", STEMS)
def test_no_class_definitions_and_upper_case_only_for_parameters(stem):
    nb = nbref.read_notebook(stem)
    parameters = set(notebook_parameters(nbref.notebook_path(stem)))
    for cell in [c for c in _code(nb) if "parameters" not in _tags(c)]:
        source = "\n".join(l for l in cell.source.splitlines() if not l.startswith("%"))
        for node in ast.walk(ast.parse(source)):
            assert not isinstance(node, ast.ClassDef), f"{stem}: class defined in cell {cell.id}"
            if isinstance(node, ast.Name) and isinstance(node.ctx, ast.Store):
                # Upper-case globals would be taken for unknown parameters when a notebook is
                # re-run in a live kernel (check_parameters inspects globals()).
                assert not (node.id.isupper() and node.id not in parameters), (
                    f"{stem}: cell {cell.id} assigns the upper-case name {node.id}")


def _python(source: str) -> str:
    """A cell's source without its IPython line magics (``%matplotlib inline``, ``%config``)."""
    return "\n".join("" if line.lstrip().startswith("%") else line
                     for line in source.splitlines())


def _assigned(source: str) -> set[str]:
    names = set()
    for node in ast.walk(ast.parse(_python(source))):
        if isinstance(node, ast.Name) and isinstance(node.ctx, ast.Store):
            names.add(node.id)
        elif isinstance(node, (ast.FunctionDef, ast.Import, ast.ImportFrom)):
            if isinstance(node, ast.FunctionDef):
                names.add(node.name)
            else:
                names.update((a.asname or a.name).split(".")[0] for a in node.names)
    return names


def _used(source: str) -> set[str]:
    return {n.id for n in ast.walk(ast.parse(_python(source)))
            if isinstance(n, ast.Name) and isinstance(n.ctx, ast.Load)}


@pytest.mark.parametrize("stem", STEMS)
def test_exercises_have_solutions_that_a_student_version_can_drop(stem):
    nb = nbref.read_notebook(stem)
    solutions = [c for c in nb.cells if "solution" in _tags(c)]
    assert 2 <= len(solutions) <= 3, f"{stem}: expected 2-3 solution cells"
    for cell in solutions:
        before = nb.cells[nb.cells.index(cell) - 1]
        assert before.cell_type == "markdown" and "Exercise" in before.source, (
            f"{stem}: solution cell {cell.id} must follow its exercise text")
    # nothing after a solution may depend on what only the solution defines
    defined_outside = set()
    for cell in _code(nb):
        if "solution" in _tags(cell):
            continue
        defined_outside |= _assigned(cell.source)
    only_in_solutions = set()
    for cell in _code(nb):
        if "solution" in _tags(cell):
            only_in_solutions |= _assigned(cell.source) - defined_outside
        else:
            leaked = _used(cell.source) & only_in_solutions
            assert not leaked, f"{stem}: cell {cell.id} uses {leaked} from a solution cell"


def test_make_student_version(tmp_path):
    sys.path.insert(0, str(TOOLS))
    try:
        import make_student_version
    finally:
        sys.path.remove(str(TOOLS))
    written = make_student_version.main(["--out", str(tmp_path)])
    assert sorted(p.name for p in written) == sorted(f"{s}.ipynb" for s in STEMS)
    for path in written:
        nb = nbformat.read(path, as_version=4)
        nbformat.validate(nb)
        assert not any("solution" in _tags(c) for c in nb.cells)
        original = nbref.read_notebook(path.stem)
        solutions = [c for c in original.cells if "solution" in _tags(c)]
        for cell in solutions:
            assert cell.source not in [c.source for c in nb.cells]
        placeholders = [c for c in nb.cells if "exercise" in _tags(c)]
        assert len(placeholders) == len(solutions)
        assert len(nb.cells) == len(original.cells)
        # the student copy opens the student copy: Binder at student/, never notebooks/
        first = nb.cells[0].source
        assert binder_url(path.stem, folder=STUDENT_FOLDER) in first
        assert f"/{NOTEBOOK_FOLDER}/{path.stem}.ipynb" not in first
        assert first.replace(student_launch_line(path.stem), "") == \
            original.cells[0].source.replace(launch_badges(path.stem), "")


# -- parameters ----------------------------------------------------------------------------
def _readme_parameters() -> dict[str, set[str]]:
    """Parameter names per notebook from the table in notebooks/README.md."""
    table: dict[str, set[str]] = {}
    for line in README.read_text().splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) >= 2 and cells[0].startswith("`0") and cells[0].endswith("`"):
            names = {n.strip("` ") for n in cells[1].split(",") if n.strip()}
            table[cells[0].strip("`")] = names
    return table


@pytest.mark.parametrize("stem", STEMS)
def test_inspect_notebook_lists_the_documented_parameters(stem):
    info = papermill.inspect_notebook(str(nbref.notebook_path(stem)))
    assert info, f"{stem}: papermill finds no parameters"
    for name, spec in info.items():
        assert spec["inferred_type_name"] in ("int", "float", "str", "bool"), (name, spec)
        assert spec["help"], f"{stem}: {name} has no help comment"
    documented = _readme_parameters()
    assert stem in documented, f"notebooks/README.md lists no parameters for {stem}"
    assert set(info) == documented[stem], f"{stem}: README table differs from the notebook"


@pytest.mark.parametrize("stem", STEMS)
def test_ci_profile_names_only_parameters_of_the_right_type(stem):
    profile = nbref.ci_parameters()
    assert set(profile) <= set(STEMS), f"unknown notebooks in the CI profile: {set(profile)}"
    allowed = notebook_parameters(nbref.notebook_path(stem))
    values = profile.get(stem, {})
    assert set(values) <= set(allowed)
    # the same check that guards a papermill run: unknown names and wrong types are errors
    namespace = {**{k: ast.literal_eval(v["default"]) for k, v in allowed.items()}, **values}
    assert check_parameters(namespace, f"{stem}.ipynb") == namespace


def test_unknown_parameter_is_rejected_before_running(tmp_path):
    stem = STEMS[0]
    with pytest.raises(ValueError, match="unknown parameter"):
        execute_notebook(nbref.notebook_path(stem), tmp_path / "out.ipynb", {"NOT_A_PARAMETER": 1})
    assert not (tmp_path / "out.ipynb").exists()


def test_check_parameters_rejects_unknown_and_mistyped_names():
    stem = STEMS[0]
    with pytest.raises(ValueError, match="unknown parameter"):
        check_parameters({"NOT_A_PARAMETER": 1}, f"{stem}.ipynb")
    name, spec = next(iter(notebook_parameters(nbref.notebook_path(stem)).items()))
    if spec["type"] in ("int", "float"):
        with pytest.raises(ValueError, match="has type str"):
            check_parameters({name: "1.0"}, f"{stem}.ipynb")


@pytest.mark.notebook
def test_papermill_with_an_unknown_parameter_fails_in_the_notebook(tmp_path, monkeypatch):
    """papermill itself only warns about an unknown name; the notebook's check cell fails."""
    monkeypatch.setenv("MPLBACKEND", "Agg")
    stem = STEMS[0]
    parameters = {**nbref.ci_parameters().get(stem, {}), "NOT_A_PARAMETER": 1}
    with pytest.raises(papermill.PapermillExecutionError) as info:
        papermill.execute_notebook(str(nbref.notebook_path(stem)), str(tmp_path / "out.ipynb"),
                                   parameters=parameters, kernel_name="python3",
                                   cwd=str(tmp_path), progress_bar=False)
    assert "NOT_A_PARAMETER" in str(info.value)
    nb = nbformat.read(tmp_path / "out.ipynb", as_version=4)
    failed = [c for c in nb.cells
              if any(o.get("output_type") == "error" for o in c.get("outputs", []))]
    assert len(failed) == 1 and "check_parameters" in failed[0].source


# -- execution -----------------------------------------------------------------------------
@pytest.fixture(scope="session")
def executed(tmp_path_factory):
    """Execute each notebook at most once per session (CI profile), on demand."""
    cache: dict[str, object] = {}

    def run(stem: str):
        if stem not in cache:
            workdir = tmp_path_factory.mktemp(stem)
            try:
                cache[stem] = nbref.execute_ci(stem, workdir)
            except Exception as err:  # keep the failure for every test of this notebook
                cache[stem] = err
        result = cache[stem]
        if isinstance(result, Exception):
            pytest.fail(f"{stem} failed to execute: {result}")
        return result

    return run


@pytest.mark.notebook
@pytest.mark.parametrize("stem", STEMS)
def test_notebook_matches_reference_outputs(stem, executed):
    nb = executed(stem)
    reference = nbref.load_reference(stem)
    assert reference["parameters"] == nbref.ci_parameters().get(stem, {}), (
        f"{stem}: the reference was made with other CI parameters; run "
        "tools/update_notebook_refs.py")
    problems = nbref.compare(reference, nb)
    assert not problems, (
        f"{stem}: outputs differ from tests/notebook_refs/{stem}.json (if intended, run "
        "tools/update_notebook_refs.py):\n" + "\n".join(map(str, problems[:10])))


@pytest.mark.notebook
@pytest.mark.parametrize("stem", sorted(load_claims()))
def test_prose_claims_hold_for_the_ci_profile(stem, executed):
    """The claims of notebooks/claims.yaml that hold in the ci profile (defaults of the
    package, run sizes) are true of the ci run; ``make report`` checks the full profile's."""
    claims = {stem: load_claims()[stem]}
    wanted = [c for c in claims[stem] if "ci" in c.profiles]
    summaries = {name: read_summary(executed(name)) for name in
                 {stem, *(c.summary_of for c in wanted)}}
    result = check_claims(summaries, "ci", claims)
    assert result["checked"] == len(wanted) and not result["unchecked"]
    assert not result["failed"], "\n".join(result["failed"])


@pytest.mark.parametrize("stem", STEMS)
def test_every_code_cell_is_in_the_reference(stem):
    nb = nbref.read_notebook(stem)
    reference = nbref.load_reference(stem)
    by_id = {c["id"]: c for c in reference["cells"]}
    for cell in _code(nb):
        assert cell.id in by_id, (
            f"{stem}: cell {cell.id} is not in the reference; run tools/update_notebook_refs.py")
        assert by_id[cell.id]["source_sha1"] == nbref.source_hash(cell.source), (
            f"{stem}: cell {cell.id} changed since the reference was made; run "
            "tools/update_notebook_refs.py")
        ignored = any(t in _tags(cell) for t in nbref.IGNORE_TAGS)
        assert by_id[cell.id]["ignore_output"] == ignored
    assert len(reference["cells"]) == len(_code(nb)), f"{stem}: the reference has extra cells"


@pytest.mark.notebook
@pytest.mark.parametrize("stem", STEMS)
def test_ipopt_is_silent_and_no_warnings_leak(stem, executed):
    nb = executed(stem)
    for cell in nb.cells:
        for out in cell.get("outputs", []):
            texts = [out.get("text", "")] + [v for v in out.get("data", {}).values()
                                             if isinstance(v, str)]
            for text in texts:
                for marker in nbref.IPOPT_MARKERS:
                    assert marker not in text, f"{stem}: '{marker}' in the output of {cell.id}"
            if out.get("name") == "stderr":
                for word in ("ConfigWarning", "RuntimeWarning", "mpcrl_lite"):
                    assert word not in out["text"], f"{stem}: {out['text'][:300]}"


@pytest.mark.notebook
@pytest.mark.parametrize("stem", STEMS)
def test_summary_is_shown_with_finite_numbers(stem, executed):
    summary = read_summary(executed(stem))
    assert summary, f"{stem}: no summary"

    def numbers(value):
        if isinstance(value, bool):
            return
        if isinstance(value, (int, float)):
            yield value
        elif isinstance(value, dict):
            for v in value.values():
                yield from numbers(v)
        elif isinstance(value, list):
            for v in value:
                yield from numbers(v)

    assert all(math.isfinite(x) for x in numbers(summary)), json.dumps(summary)[:500]


def test_reference_files_exist_for_every_notebook_and_only_for_them():
    refs = sorted(p.stem for p in nbref.REF_DIR.glob("*.json"))
    assert refs == STEMS


def test_comparison_tolerates_round_off_and_catches_changes():
    assert nbref.compare_text("J = 1833.91 NOK", "J = 1833.9135 NOK") is None
    assert nbref.compare_text("hours: 57", "hours: 58") is not None
    assert nbref.compare_text("J = 1833.9", "J = 1900.0") is not None
    assert nbref.compare_text("agent 1 sells", "agent 1 buys") is not None
    assert nbref.round_floats("J = 1833.9135046460824, n = 3") == "J = 1833.91, n = 3"


def test_notebooks_readme_exists_and_names_every_notebook():
    text = README.read_text()
    for stem in STEMS:
        assert f"{stem}" in text
    assert Path(nbref.ROOT / "notebooks" / "ci_parameters.yaml").exists()
