"""The course as a static site: one folder that works from the file system, with no server.

``python -m mpcrl_lite.publish.site --out site [--profile classroom] [--report reports]`` (or ``make
site``) writes::

    site/index.html            the tour: every notebook with what it teaches and its run time,
                               the paper's figures, the parameter study, the key numbers
    site/notebooks/NN_*.html   each executed notebook as an offline page (html_export)
    site/notebooks/NN_*.ipynb  the executed notebooks, to download
    site/notebooks/mathjax/    the local MathJax the pages use
    site/figures/*.png         the paper's figures, as drawn by notebook 05
    site/study/<sweep>/        the parameter study's results table (notebook 07)
    site/summary.json          every notebook's key numbers, parameters and run time

Every link is relative and nothing is loaded from the network, so the folder can be opened
with a browser from disk, zipped and mailed, or published as it is on any static host
(GitHub Pages, GitLab Pages, a university web space).

The notebooks are executed with a parameter profile (default ``classroom``, a few minutes
for all eight), or taken from an existing report directory (``--report reports`` after ``make
report``, which reuses its executed notebooks and parameter study).
"""

from __future__ import annotations

import argparse
import base64
import datetime as _dt
import functools
import html
import json
import re
import shutil
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from .._util.references import PAPER
from .._util.version import __version__
from .html_export import MATHJAX_DIRNAME, mathjax_tags, remote_resources, write_html
from .launch import binder_url, colab_url
from .report import PROFILES, notebook_parameters, notebook_paths, run_report

__all__ = [
    "PAPER_FIGURES_NOTEBOOK",
    "NotebookEntry",
    "build_site",
    "collect_study",
    "extract_paper_figures",
    "main",
    "notebook_entry",
    "render_index",
]

#: The notebook whose figures are the paper's (cells calling ``figN_...`` of ``plots``).
PAPER_FIGURES_NOTEBOOK = "05_three_agent_learning"
_FIGURE_CALL = re.compile(r"\b(fig\d+_[a-z_]+)\s*\(")
_STUDY_NOTEBOOK = "07_parameter_study"
_STUDY_FOLDER = "sweep_runs"


@dataclass(frozen=True)
class NotebookEntry:
    """One notebook on the index page: its title (plain text), its goal (markdown, with TeX
    typeset on the page by the local MathJax) and its run time."""

    stem: str
    title: str
    goal: str
    seconds: float | None


def notebook_entry(nb, stem: str, seconds: float | None = None) -> NotebookEntry:
    """Title and goal of a notebook, read from its first (title) cell."""
    first = next((c for c in nb.cells if c.cell_type == "markdown"), None)
    source = first.source if first is not None else ""
    title = next((line[2:].strip() for line in source.splitlines() if line.startswith("# ")),
                 stem)
    goal = ""
    for paragraph in re.split(r"\n\s*\n", source):
        if paragraph.lstrip().startswith("**Goal.**"):
            goal = paragraph.replace("**Goal.**", "", 1).strip()
            break
    return NotebookEntry(stem, title, goal, seconds)


def _markdown(text: str) -> str:
    """Markdown to HTML as in the notebook pages (TeX is left for MathJax)."""
    from nbconvert.filters.markdown_mistune import markdown2html_mistune

    return markdown2html_mistune(text)


def extract_paper_figures(nb, folder: str | Path) -> list[dict[str, str]]:
    """Save the PNG of every cell of the executed notebook ``nb`` that draws a paper figure
    (calls ``figN_name(...)``) as ``folder/figN_name.png``.

    Returns ``[{'file', 'name', 'alt'}]`` in the notebook's order; ``alt`` is the figure's
    description from its title (:mod:`mpcrl_lite.publish.alt_text`), or its function name.
    """
    folder = Path(folder)
    found: list[dict[str, str]] = []
    for cell in nb.cells:
        if cell.cell_type != "code" or "solution" in cell.get("metadata", {}).get("tags", []):
            continue
        calls = _FIGURE_CALL.findall(cell.source)
        pictures = [o for o in cell.get("outputs", []) if "image/png" in o.get("data", {})]
        if not calls or not pictures:
            continue
        name = calls[0]
        if any(f["name"] == name for f in found):
            continue
        output = pictures[-1]
        folder.mkdir(parents=True, exist_ok=True)
        target = folder / f"{name}.png"
        target.write_bytes(base64.b64decode(output["data"]["image/png"]))
        alt = output.get("metadata", {}).get("image/png", {}).get("alt") or name
        found.append({"file": target.name, "name": name, "alt": alt})
    return found


def collect_study(report: str | Path, folder: str | Path,
                  study: dict[str, Any] | None = None) -> list[dict[str, Any]]:
    """Copy the results tables of the parameter study (``report/sweep_runs/*/results.csv``,
    except the notebook's ``*check*`` sweeps) into ``folder/<sweep>/``; returns one dict per
    sweep with its name, files and table (a :class:`pandas.DataFrame`).

    With ``study`` (the results of notebook 07's summary: ``months``, ``days``, ``P_bars``,
    ``noise_vars``, ``seeds``) only the study the notebook ran is kept: its sweep folder
    (``months=M,days=D``) and, of its table, the finished runs of its own grid. Rows added to
    the same folder by an exercise (another seed) or left ``pending`` by it are not the
    study's results and are dropped, from the page and from the copied table.
    """
    import pandas as pd

    studies = []
    for results in sorted(Path(report).glob(f"{_STUDY_FOLDER}/*/results.csv")):
        if "check" in results.parent.name:  # the notebook's consistency checks, not the study
            continue
        table = pd.read_csv(results)
        if study is not None:
            if results.parent.name != f"months={study['months']},days={study['days']}":
                continue
            table = _study_rows(table, study)
        target = Path(folder) / results.parent.name
        target.mkdir(parents=True, exist_ok=True)
        table.to_csv(target / "results.csv", index=False)
        files = ["results.csv"]
        if study is None and (results.parent / "sweep.json").is_file():
            shutil.copy2(results.parent / "sweep.json", target / "sweep.json")
            files.append("sweep.json")
        studies.append({"name": results.parent.name, "files": files, "table": table})
    return studies


def _study_rows(table, study: dict[str, Any]):
    """The finished runs of the study's grid: its grid limits, noise variances and seeds."""
    import numpy as np

    keep = table["status"].eq("done") if "status" in table else np.ones(len(table), bool)
    for column, values in (("P_bar", study.get("P_bars")), ("noise_var", study.get("noise_vars"))):
        if values is not None and column in table:
            keep &= np.isclose(table[column].to_numpy(float)[:, None],
                               np.asarray(values, float)[None, :]).any(axis=1)
    if study.get("seeds") is not None and "seed" in table:
        keep &= table["seed"] < int(study["seeds"])
    return table[keep].reset_index(drop=True)


_STYLE = """
body { font-family: system-ui, -apple-system, "Segoe UI", Roboto, sans-serif; margin: 0 auto;
       max-width: 62rem; padding: 1rem 1.5rem 3rem; line-height: 1.5; color: #1b1b1b; }
table { border-collapse: collapse; margin: 0.5rem 0 1rem; }
th, td { border-bottom: 1px solid #ccc; padding: 0.35rem 0.6rem; text-align: left;
         vertical-align: top; }
th { background: #f2f2f2; }
td p { margin: 0; }
td.num { text-align: right; font-variant-numeric: tabular-nums; white-space: nowrap; }
figure { display: inline-block; margin: 0.5rem 1rem 1rem 0; max-width: 29rem; }
figure img { max-width: 100%; border: 1px solid #ddd; }
figcaption { font-size: 0.9rem; color: #444; }
code { background: #f4f4f4; padding: 0 0.2rem; }
a { color: #0b5cad; text-decoration: underline; }
.small { font-size: 0.9rem; color: #444; }
"""


def _e(value: Any) -> str:
    return html.escape(str(value))


def render_index(entries: list[NotebookEntry], summary: dict[str, Any],
                 figures: list[dict[str, str]], studies: list[dict[str, Any]],
                 mathjax_url: str = f"notebooks/{MATHJAX_DIRNAME}/MathJax.js") -> str:
    """The index page (HTML) of the site; TeX in the goals is typeset by the local MathJax
    at ``mathjax_url``."""
    profile = summary.get("profile", "?")
    paper = PAPER
    rows = []
    for i, entry in enumerate(entries, 1):
        seconds = "" if entry.seconds is None else f"{entry.seconds:.0f} s"
        rows.append(
            f'<tr><td class="num">{i}</td><td><a href="notebooks/{_e(entry.stem)}.html">'
            f"{_e(entry.title)}</a><br><span class=\"small\"><code>{_e(entry.stem)}</code></span>"
            f"</td><td>{_markdown(entry.goal)}</td><td class=\"num\">{seconds}</td>"
            f'<td><a href="notebooks/{_e(entry.stem)}.ipynb" download>executed .ipynb</a><br>'
            f'<a href="{_e(colab_url(entry.stem))}">Colab</a> · '
            f'<a href="{_e(binder_url(entry.stem))}">Binder</a></td></tr>')
    parts = [
        "<!DOCTYPE html>", '<html lang="en">', "<head>", '<meta charset="utf-8">',
        '<meta name="viewport" content="width=device-width, initial-scale=1">',
        "<title>mpcrl_lite: MPC-based reinforcement learning for battery storage</title>",
        f"<style>{_STYLE}</style>", mathjax_tags(mathjax_url), "</head>", "<body>", "<main>",
        "<h1>MPC-based reinforcement learning for a multi-agent battery storage system</h1>",
        "<p>Eight teaching notebooks that rebuild, step by step, the paper</p>",
        (f"<blockquote>{_e(', '.join(paper['authors']))}, “{_e(paper['title'])}”, "
        f"<em>{_e(paper['venue'])}</em>, {paper['year']}. "
        f'DOI <a href="{_e(paper["url"])}">{_e(paper["doi"])}</a>; '
        f'preprint <a href="{_e(paper["preprint_url"])}">{_e(paper["preprint"])}</a>.'
        "</blockquote>"),
        (f'<p class="small">Executed with the <strong>{_e(profile)}</strong> parameter profile by '
        f"mpcrl_lite {_e(__version__)} on {_dt.date.today().isoformat()}. Every page works "
        "offline; the interactive explorers appear as pictures of their first state (open a "
        "notebook in Jupyter, Colab or Binder to move their controls).</p>"),
        '<h2 id="tour">The notebook tour</h2>',
        ("<table><thead><tr><th>#</th><th>notebook</th><th>goal</th><th>run time</th>"
        "<th>open</th></tr></thead><tbody>"), *rows, "</tbody></table>",
        '<h2 id="figures">The paper\'s figures</h2>',
    ]
    if figures:
        parts.append(f'<p>Drawn by <a href="notebooks/{PAPER_FIGURES_NOTEBOOK}.html">notebook '
                     f"05</a> from its learning run ({_e(profile)} profile).</p>")
        for fig in figures:
            # the thumbnail opens the full-size picture
            parts.append(f'<figure><a href="figures/{_e(fig["file"])}">'
                         f'<img src="figures/{_e(fig["file"])}" alt="{_e(fig["alt"])}"></a>'
                         f"<figcaption><code>{_e(fig['name'])}</code>: {_e(fig['alt'])} "
                         f'(<a href="figures/{_e(fig["file"])}">full size</a>)'
                         "</figcaption></figure>")
    else:
        parts.append(f"<p>Not in this build (notebook <code>{PAPER_FIGURES_NOTEBOOK}</code> was "
                     "not executed).</p>")
    parts.append('<h2 id="study">The parameter study</h2>')
    if studies:
        for study in studies:
            table = study["table"]
            columns = [c for c in ("P_bar", "noise_var", "seed", "months", "J_first", "J_last",
                                   "hours_soc_below_0_1_last", "max_P_mpc", "status")
                       if c in table.columns]
            links = " · ".join(f'<a href="study/{_e(study["name"])}/{_e(f)}">{_e(f)}</a>'
                               for f in study["files"])
            parts.append(f"<h3><code>{_e(study['name'])}</code></h3><p>{links}</p>")
            parts.append(table[columns].to_html(index=False, float_format=lambda x: f"{x:.1f}",
                                                border=0))
            parts.append(f'<p class="small">{_e(_study_note(study["name"], profile))}</p>')
    else:
        parts.append(f"<p>Not in this build (notebook <code>{_STUDY_NOTEBOOK}</code> was not "
                     "executed).</p>")
    parts.append('<h2 id="numbers">Key numbers</h2>')
    parts.append('<p>Every notebook\'s summary, parameters and run time: '
                 '<a href="summary.json">summary.json</a>.</p><table><thead><tr>'
                 "<th>notebook</th><th>parameters</th><th>results</th></tr></thead><tbody>")
    for stem, info in summary.get("notebooks", {}).items():
        results = ", ".join(f"{k} = {_short(v)}" for k, v in info.get("results", {}).items()
                            if not isinstance(v, (list, dict)))
        params = ", ".join(f"{k} = {v}" for k, v in info.get("parameters", {}).items())
        parts.append(f"<tr><td><code>{_e(stem)}</code></td><td>{_e(params or 'defaults')}</td>"
                     f"<td class=\"small\">{_e(results)}</td></tr>")
    parts += ["</tbody></table>", "</main>", "</body>", "</html>", ""]
    return "\n".join(parts)


def _study_note(name: str, profile: str, full_run: tuple[int, int] | None = None) -> str:
    """How to read a study table: its run size, the spread between seeds, and, for runs
    shorter than the notebook's defaults ``full_run`` (months, days; read from the notebook
    when not given), what so short a run can show."""
    sizes = dict(part.split("=", 1) for part in name.split(",") if "=" in part)
    months, days = sizes.get("months", "?"), sizes.get("days", "?")
    note = (f"One row per run of the study ({profile} profile): each run learned {months} "
            f"months of {days} days from theta0 and was evaluated on the same 10 noise draws. "
            "The rows of one grid limit differ only by their seed: a difference between grid "
            "limits means something where it is large against that spread (the notebook adds "
            "each run's 95 % interval over the draws and its regret against J*).")
    full_months, full_days = full_run or _study_defaults()
    try:
        short = int(months) < full_months or int(days) < full_days
    except ValueError:  # a folder not named months=M,days=D: its size is unknown
        short = True
    if short:
        note += (" A run this short shows where learning stands after so few months, not what "
                 "a grid limit or a noise level is worth: a run that has not settled yet can "
                 "cost far more than the nominal MPC. The notebook's defaults "
                 f"({full_months} months of {full_days} days) and benchmarks/README.md give "
                 "the comparison over longer runs.")
    return note


@functools.cache
def _study_defaults() -> tuple[int, int]:
    """The run size (months, days) of the study notebook's defaults."""
    parameters = notebook_parameters(f"{_STUDY_NOTEBOOK}.ipynb")
    return int(parameters["MONTHS"]["default"]), int(parameters["DAYS"]["default"])


def _short(value: Any) -> str:
    if isinstance(value, float):
        return f"{value:.4g}"
    return str(value)


def build_site(out: str | Path, profile: str = "classroom", report: str | Path | None = None,
               notebooks: list[str] | None = None) -> Path:
    """Build the site into ``out`` (see the module docstring) and return ``out/index.html``.

    With ``report`` naming a directory that holds a finished report (``summary.json``), its
    executed notebooks are used; otherwise the notebooks are executed with ``profile`` into
    ``report`` (or a temporary directory). Only the named ``notebooks`` (stems) are included,
    default all.
    """
    if profile not in PROFILES:
        raise ValueError(f"profile={profile!r}: expected one of {list(PROFILES)}")
    stems = [p.stem for p in notebook_paths(notebooks)]
    out = Path(out)
    with tempfile.TemporaryDirectory(prefix="mpcrl-site-") as scratch:
        source = Path(report) if report is not None else Path(scratch)
        if not (source / "summary.json").is_file():
            run_report(source, profile=profile, notebooks=stems)
        summary = json.loads((source / "summary.json").read_text())
        missing = [s for s in stems if not (source / f"{s}.ipynb").is_file()]
        if missing:
            raise FileNotFoundError(f"{source}: no executed notebooks {missing}; run the "
                                    "report for them or leave out report=")
        return _write_site(out, source, stems, summary)


def _write_site(out: Path, source: Path, stems: list[str], summary: dict[str, Any]) -> Path:
    import nbformat

    if out.exists():
        shutil.rmtree(out)
    pages = out / "notebooks"
    pages.mkdir(parents=True)
    entries = []
    executed = {}
    for stem in stems:
        nb = nbformat.read(source / f"{stem}.ipynb", as_version=4)
        executed[stem] = nb
        shutil.copy2(source / f"{stem}.ipynb", pages / f"{stem}.ipynb")
        write_html(nb, pages / f"{stem}.html")
        seconds = summary.get("notebooks", {}).get(stem, {}).get("seconds")
        entries.append(notebook_entry(nb, stem, seconds))
    kept = {**summary, "notebooks": {s: v for s, v in summary.get("notebooks", {}).items()
                                     if s in stems}}
    (out / "summary.json").write_text(json.dumps(kept, indent=1))
    figures = (extract_paper_figures(executed[PAPER_FIGURES_NOTEBOOK], out / "figures")
               if PAPER_FIGURES_NOTEBOOK in executed else [])
    study = summary.get("notebooks", {}).get(_STUDY_NOTEBOOK, {}).get("results") or None
    studies = (collect_study(source, out / "study", study) if _STUDY_NOTEBOOK in executed
               else [])
    index = out / "index.html"
    page = render_index(entries, kept, figures, studies)
    remote = remote_resources(page)
    if remote:
        raise RuntimeError(f"index.html would load {remote[:5]} from the network")
    index.write_text(page, encoding="utf-8")
    # GitHub Pages: serve the folder as it is (no Jekyll processing).
    (out / ".nojekyll").write_text("")
    return index


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m mpcrl_lite.publish.site",
        description="Build the course's static site (a folder that works without a server).")
    parser.add_argument("--out", type=Path, default=Path("site"), help="site folder (replaced)")
    parser.add_argument("--profile", choices=PROFILES, default="classroom",
                        help="parameters for executing the notebooks (default: classroom)")
    parser.add_argument("--report", type=Path, default=None,
                        help="report directory: reuse its executed notebooks if it holds a "
                             "finished report, else execute into it")
    parser.add_argument("--notebooks", nargs="*", default=None, help="notebook stems (default: "
                                                                     "all)")
    args = parser.parse_args(argv)
    try:
        index = build_site(args.out, profile=args.profile, report=args.report,
                           notebooks=args.notebooks)
    except (ValueError, FileNotFoundError, ModuleNotFoundError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    print(json.dumps({"site": str(args.out), "index": str(index)}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
