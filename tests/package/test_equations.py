"""The paper in the code: one table of the paper's numbered equations
(:data:`mpcrl_lite._util.references.EQUATIONS`), checked against the paper's LaTeX source,
and every citation in the package's docstrings and the notebooks' prose checked against it.

The numbering is re-derived from the LaTeX as LaTeX numbers it: every ``equation`` and every
line of an ``align`` without ``\\nonumber`` takes the next number (a label on an unnumbered
line names the next number); a ``subequations`` group
takes one number and its lines the letters a, b, c, ...
"""

from __future__ import annotations

import importlib
import inspect
import json
import re
from pathlib import Path

import pytest
from conftest import package_modules

from mpcrl_lite._util.references import EQUATIONS, cited_equations, equation

ROOT = Path(__file__).resolve().parents[2]
PAPER_TEX = ROOT.parent / "shared" / "paper" / "multi-agent-battery-mpc-rl.tex"
NUMBERS = {eq.number for eq in EQUATIONS}


def numbered_equations(tex: str) -> list[tuple[str, list[str]]]:
    """``(number, labels)`` of every numbered equation of a LaTeX document, in order."""
    body = re.sub(r"(?<!\\)%.*", "", tex[tex.index("\\begin{document}"):])
    found: list[tuple[str, list[str]]] = []
    n = 0
    for m in re.finditer(r"\\begin\{(subequations|equation|align)\}(.*?)\\end\{\1\}", body, re.DOTALL):
        env, content = m.group(1), m.group(2)
        if env == "subequations":
            n += 1
            group = re.match(r"\s*\\label\{([^}]*)\}", content)
            inner = re.search(r"\\begin\{align\}(.*?)\\end\{align\}", content, re.DOTALL).group(1)
            rows = [r for r in re.split(r"\\\\", inner) if "\\nonumber" not in r]
            for letter, row in zip("abcdefghij", rows):
                found.append((f"{n}{letter}", re.findall(r"\\label\{([^}]*)\}", row)))
            found.append((str(n), [group.group(1)] if group else []))
            continue
        pending: list[str] = []  # a label on an unnumbered line names the next number
        for row in re.split(r"\\\\", content) if env == "align" else [content]:
            pending += re.findall(r"\\label\{([^}]*)\}", row)
            if "\\nonumber" in row or "\\notag" in row:
                continue
            n += 1
            found.append((str(n), pending))
            pending = []
    return found


@pytest.mark.skipif(not PAPER_TEX.is_file(), reason=f"the paper's source is not at {PAPER_TEX}")
def test_the_table_follows_the_papers_numbering_and_labels():
    derived = numbered_equations(PAPER_TEX.read_text())
    assert sorted(number for number, _ in derived) == sorted(NUMBERS)
    labels = {number: labels for number, labels in derived}
    for eq in EQUATIONS:
        assert labels[eq.number] == ([eq.label] if eq.label else []), eq.number


def test_the_numbering_reader_on_a_small_document():
    tex = ("\\begin{document}\\begin{align}a\\label{eq:a}\\end{align}"
           "\\begin{align}b\\nonumber\\\\ c\\end{align}"
           "\\begin{subequations}\\label{eq:g}\\begin{align}d\\label{eq:d}\\\\ e\\nonumber\\\\ f"
           "\\end{align}\\end{subequations}\\begin{equation}g\\end{equation}")
    assert numbered_equations(tex) == [("1", ["eq:a"]), ("2", []), ("3a", ["eq:d"]),
                                       ("3b", []), ("3", ["eq:g"]), ("4", [])]


def _resolve(where: str) -> object:
    parts = where.split(".")
    for cut in range(len(parts), 0, -1):
        try:
            obj = importlib.import_module("mpcrl_lite." + ".".join(parts[:cut]))
        except ModuleNotFoundError:
            continue
        for name in parts[cut:]:
            obj = getattr(obj, name)
        return obj
    raise AssertionError(f"{where} names nothing in the package")


@pytest.mark.parametrize("eq", EQUATIONS, ids=[eq.number for eq in EQUATIONS])
def test_each_equation_lives_in_a_public_object_whose_docstring_cites_it(eq):
    obj = _resolve(eq.where)
    assert not any(part.startswith("_") for part in eq.where.split(".")), eq.where
    doc = inspect.getdoc(obj) or ""
    cited = set(cited_equations(doc))
    # a part (9f) may be cited through its group (eq. 9) or the group through its parts
    group = re.match(r"\d+", eq.number).group(0)
    assert eq.number in cited or (group in cited and eq.number != group) or any(
        c.startswith(group) for c in cited), f"{eq.where}'s docstring does not cite eq. {eq.number}"


def _citations_in_package() -> list[tuple[str, str]]:
    return [(f"mpcrl_lite/{path.relative_to(ROOT / 'mpcrl_lite')}", number)
            for path in package_modules().values()
            for number in cited_equations(path.read_text())]


def _citations_in_notebooks() -> list[tuple[str, str]]:
    found = []
    for path in sorted((ROOT / "notebooks").glob("[0-9][0-9]_*.ipynb")):
        for cell in json.loads(path.read_text())["cells"]:
            if cell["cell_type"] == "markdown":
                found += [(path.name, n) for n in cited_equations("".join(cell["source"]))]
    return found


def test_every_citation_in_the_package_and_the_notebooks_names_an_equation_of_the_table():
    citations = _citations_in_package() + _citations_in_notebooks()
    assert len(citations) > 40  # the reader finds them (docstrings and notebooks cite many)
    unknown = [(where, n) for where, n in citations if n not in NUMBERS]
    assert not unknown, f"citations of equations the paper does not have: {unknown}"


@pytest.mark.parametrize(("topic", "number"), [
    ("sensitivity", "20"), ("policy gradient", "13"), ("compatible", "15"),
])
def test_citations_next_to_a_topic_give_its_number(topic, number):
    """Where a docstring or notebook names the sensitivity, the policy gradient or the
    compatible critic and cites a number in the same sentence, it is that topic's number
    (eq. 21 for the sensitivity was a past mistake)."""
    wrong = []
    texts = [p.read_text() for p in package_modules().values()]
    for path in (ROOT / "notebooks").glob("[0-9][0-9]_*.ipynb"):
        texts += ["".join(c["source"]) for c in json.loads(path.read_text())["cells"]
                  if c["cell_type"] == "markdown"]
    for text in texts:
        for sentence in re.split(r"(?<=[.;])\s+(?=[A-Z])|\n\n", text):
            cited = cited_equations(sentence)
            if len(cited) == 1 and topic in sentence.lower() and cited[0] in ("11", "12", "21"):
                wrong.append((cited[0], sentence.strip()[:100]))
    assert not wrong, f"{topic} cited as another equation than {number}: {wrong}"


def test_citation_reader():
    assert cited_equations("paper eqs. 9c-9d and eq. 14; Eq. (6), eqs. 15-17, eqs. 10, 11") == [
        "9c", "9d", "14", "6", "15", "16", "17", "10", "11"]
    assert cited_equations("eqs. 23a-23c") == ["23a", "23b", "23c"]
    assert equation("9f").label == "eq:MPC:ppeak1"
    with pytest.raises(ValueError, match="number='25': the paper has no such"):
        equation("25")
