"""Offline pages and the static site: no resource from the network, an alt text on every
picture, explorers as static pictures, local MathJax that really typesets (checked in a
headless Chromium where one is installed), relative links that resolve, and the launch cells
and Binder files that open the notebooks elsewhere.
"""

from __future__ import annotations

import base64
import io
import json
import re
import shutil
import subprocess
from html.parser import HTMLParser
from pathlib import Path

import matplotlib
import nbformat
import nbref
import pytest
from matplotlib.figure import Figure

from mpcrl_lite._util.references import DPG, PAPER
from mpcrl_lite.publish import site as site_module
from mpcrl_lite.publish.alt_text import _with_alt, describe_figure
from mpcrl_lite.publish.html_export import (
    WIDGET_STATE_MIME,
    WIDGET_VIEW_MIME,
    copy_mathjax,
    page_title,
    remote_resources,
    static_widgets,
    to_html,
    unlink_remote_images,
)
from mpcrl_lite.publish.launch import (
    apply_launch_cells,
    binder_url,
    colab_url,
    launch_badges,
)

matplotlib.use("Agg")

ROOT = nbref.ROOT
STEMS = nbref.stems()
CHROMIUM = next((shutil.which(n) for n in ("chromium", "chromium-browser", "google-chrome")
                 if shutil.which(n)), None)
needs_chromium = pytest.mark.skipif(
    CHROMIUM is None, reason="no Chromium on this machine (Debian: apt-get install chromium); "
    "the offline pages are then checked by parsing only")


# -- pieces --------------------------------------------------------------------------------------
def test_remote_resources_finds_scripts_styles_images_and_fetches_but_not_links():
    page = """<html><head>
    <script src="https://cdn.example.org/require.js"></script>
    <script src="mathjax/MathJax.js"></script>
    <link rel="stylesheet" href="//fonts.example.org/a.css">
    <link rel="stylesheet" href="style.css">
    <style>@import "https://example.org/b.css"; .x { background: url(local.png) }</style>
    <script>var s = document.createElement('script'); s.src = 'https://unpkg.com/x.js';</script>
    <script>var ns = "http://www.w3.org/2000/svg";</script>
    </head><body>
    <img src="https://example.org/badge.svg" alt="b"><img src="data:image/png;base64,AA" alt="a">
    <a href="https://doi.org/10.1/x">paper</a>
    <div style="background-image: url('https://example.org/bg.png')"></div>
    </body></html>"""
    assert remote_resources(page) == [
        "https://cdn.example.org/require.js", "//fonts.example.org/a.css",
        "https://example.org/b.css", "https://unpkg.com/x.js",
        "https://example.org/badge.svg", "https://example.org/bg.png"]


def test_describe_figure_uses_title_then_panels_then_labels_and_is_never_empty():
    fig = Figure()
    a, b = fig.subplots(1, 2)
    fig.suptitle("Learning curve $J$")
    a.set_title("closed loop")
    b.set(xlabel="month", ylabel="gradient norm")
    assert describe_figure(fig) == ("Figure: Learning curve J. Panels: closed loop, "
                                    "gradient norm against month.")
    empty = Figure()
    empty.subplots(1, 3)
    assert describe_figure(empty) == "Figure with 3 untitled panels."


def test_alt_text_hook_adds_the_description_to_figure_outputs_only():
    fig = Figure()
    fig.subplots().set_title("prices")

    def fmt(obj, include=None, exclude=None):
        return {"image/png": "AAAA", "text/plain": repr(obj)}, {"image/png": {"width": 400}}

    _data, metadata = _with_alt(fmt)(fig)
    assert metadata["image/png"] == {"width": 400, "alt": "Figure: prices."}
    assert _with_alt(fmt)("not a figure")[1] == {"image/png": {"width": 400}}


def _png() -> str:
    fig = Figure(figsize=(1, 1))
    fig.subplots().plot([0, 1])
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png")
    return base64.b64encode(buffer.getvalue()).decode()


def _widget_notebook() -> nbformat.NotebookNode:
    """An executed notebook with one explorer: a VBox holding a slider and an image."""
    nb = nbformat.v4.new_notebook()
    cell = nbformat.v4.new_code_cell("day_explorer()")
    cell.outputs = [nbformat.v4.new_output(
        "execute_result", execution_count=1,
        data={WIDGET_VIEW_MIME: {"model_id": "box", "version_major": 2, "version_minor": 0},
              "text/plain": "DayExplorer(children=(...))"})]
    nb.cells = [nbformat.v4.new_markdown_cell(
        "# T\n\n[![Open in Colab](https://x.org/badge.svg)](https://colab.example/nb)\n\n"
        "![chart](https://x.org/chart.png) and $$a^2$$"), cell]
    nb.metadata["widgets"] = {WIDGET_STATE_MIME: {"version_major": 2, "version_minor": 0,
                                                  "state": {
        "box": {"model_name": "VBoxModel",
                "state": {"children": ["IPY_MODEL_slider", "IPY_MODEL_image", "IPY_MODEL_text"]}},
        "slider": {"model_name": "FloatSliderModel",
                   "state": {"description": "P_bar", "value": 1.5}},
        "text": {"model_name": "HTMLModel", "state": {"value": "J = 12.5 NOK", "description": ""}},
        "image": {"model_name": "ImageModel", "state": {"format": "png"},
                  "buffers": [{"path": ["value"], "encoding": "base64", "data": _png()}]},
    }}}
    return nb


def test_static_widgets_replace_explorers_by_their_picture_and_settings():
    nb = _widget_notebook()
    out = static_widgets(nb)
    assert "widgets" not in out.metadata and "widgets" in nb.metadata  # a copy
    (output,) = out.cells[1].outputs
    assert WIDGET_VIEW_MIME not in output["data"]
    page = output["data"]["text/html"]
    assert page.count("<img ") == 1 and "data:image/png;base64," in page
    assert 'alt="Day explorer as drawn when the notebook ran: P_bar = 1.5"' in page
    assert "J = 12.5 NOK" in page and "Open the notebook" in output["data"]["text/plain"]


def test_static_widgets_keep_the_explorer_picture_alt_text():
    """The explorers draw into a classroom.picture.Picture (an anywidget with ``alt``): its
    picture and its own alt text reach the page."""
    nb = _widget_notebook()
    state = nb.metadata["widgets"][WIDGET_STATE_MIME]["state"]
    state["image"] = {"model_name": "AnyModel",
                      "state": {"format": "png", "alt": "Figure: MPC, day 1: J = 12.5 NOK/day."},
                      "buffers": state["image"]["buffers"]}
    page = static_widgets(nb).cells[1].outputs[0]["data"]["text/html"]
    assert page.count("<img ") == 1 and 'alt="Figure: MPC, day 1: J = 12.5 NOK/day."' in page


def test_pages_are_titled_after_their_notebook_and_meet_contrast():
    nb = _widget_notebook()
    nb.cells[0].source = "# 02 · The *MPC* policy, [$\\tau$](x.md)\n\ntext"
    assert page_title(nb) == "02 · The MPC policy, tau · mpcrl_lite"
    page = to_html(nb)
    assert "<title>02 · The MPC policy, tau · mpcrl_lite</title>" in page
    # the light theme's comment (#408080) and number (#080) colours fall below 4.5:1 on the
    # code background; the page replaces them and underlines links in running text
    assert "--jp-mirror-editor-comment-color: #2f6464" in page
    assert "--jp-mirror-editor-number-color: #006600" in page
    assert "--jp-cell-prompt-not-active-opacity: 1" in page
    assert "text-decoration: underline" in page
    untitled = nbformat.v4.new_notebook()
    assert page_title(untitled) == "Notebook · mpcrl_lite"


def test_the_offline_mathjax_has_every_font_it_asks_for(tmp_path):
    """The MathML hidden for screen readers asks for the TeX fonts MathJax_AMS, _Script,
    _Caligraphic and _Fraktur, which jupyter-server-mathjax does not ship: STIX faces stand in."""
    folder = copy_mathjax(tmp_path)
    config = (folder / "config" / "TeX-AMS-MML_HTMLorMML-full.js").read_text()
    asked = set(re.findall(r"MathJax_[A-Za-z]+-[A-Za-z]+\.otf", config))
    assert "MathJax_AMS-Regular.otf" in asked
    for name in asked:
        font = folder / "fonts" / "HTML-CSS" / "TeX" / "otf" / name
        assert font.is_file() and font.read_bytes()[:4] == b"wOFF", name
    (folder / "fonts" / "HTML-CSS" / "TeX" / "otf" / "MathJax_AMS-Regular.otf").unlink()
    copy_mathjax(tmp_path)  # an older copy gets the missing fonts too
    assert (folder / "fonts" / "HTML-CSS" / "TeX" / "otf" / "MathJax_AMS-Regular.otf").is_file()


def test_unlink_remote_images_turns_badges_into_links():
    source = unlink_remote_images(_widget_notebook()).cells[0].source
    assert "[Open in Colab](https://colab.example/nb)" in source
    assert "[chart](https://x.org/chart.png)" in source and "![" not in source


def test_page_of_a_notebook_with_widgets_loads_nothing_remote():
    page = to_html(_widget_notebook())
    assert remote_resources(page) == []
    assert '<script src="mathjax/MathJax.js?config=' in page
    assert "require.js" not in page and "embed-amd" not in page


# -- launch cells and Binder ---------------------------------------------------------------------
@pytest.mark.parametrize("stem", STEMS)
def test_launch_cells_are_up_to_date(stem):
    nb = nbref.read_notebook(stem)
    assert apply_launch_cells(nb, stem) == nb, (
        f"{stem}: run tools/update_launch_cells.py")
    first = nb.cells[0].source
    assert launch_badges(stem) in first and PAPER["doi"] in first


def test_readme_has_launch_links_for_every_notebook():
    readme = (ROOT / "README.md").read_text()
    for stem in STEMS:
        assert colab_url(stem) in readme and binder_url(stem) in readme, stem


def test_dpg_reference_is_given_where_silver_et_al_is_cited():
    for stem in STEMS:
        nb = nbref.read_notebook(stem)
        for cell in nb.cells:
            if cell.cell_type == "markdown" and "Silver et al." in cell.source:
                assert DPG["title"] in cell.source and "ICML" in cell.source, (stem, cell.id)


def test_binder_environment_is_the_project_environment():
    binder = ROOT / "binder"
    assert (binder / "requirements.txt").read_text().count("-r ../environment-requirements.txt")
    assert (binder / "runtime.txt").read_text().strip().startswith("python-3.11")
    post = (binder / "postBuild").read_text()
    assert "pip install --no-deps" in post and " -e " not in post
    assert (binder / "postBuild").stat().st_mode & 0o111, "postBuild must be executable"
    assert (ROOT / "environment-requirements.txt").is_file()


# -- the static site -----------------------------------------------------------------------------
@pytest.fixture(scope="module")
def built_site(tmp_path_factory):
    """The site of notebook 01, executed with the CI profile."""
    out = tmp_path_factory.mktemp("site")
    report = tmp_path_factory.mktemp("report")
    site_module.build_site(out, profile="ci", report=report, notebooks=[STEMS[0]])
    return out


class _Page(HTMLParser):
    def __init__(self):
        super().__init__(convert_charrefs=True)
        self.images: list[dict[str, str | None]] = []
        self.refs: list[str] = []

    def handle_starttag(self, tag, attrs):
        attrs = dict(attrs)
        if tag == "img":
            self.images.append(attrs)
        for key in ("href", "src"):
            value = attrs.get(key)
            if value and not re.match(r"^(https?:|data:|mailto:|#)", value):
                self.refs.append(value.split("#")[0].split("?")[0])


def _parse(path: Path) -> _Page:
    page = _Page()
    page.feed(path.read_text(encoding="utf-8"))
    return page


@pytest.mark.notebook
def test_site_pages_are_offline_described_and_linked(built_site):
    pages = sorted(built_site.rglob("*.html"))
    assert {p.relative_to(built_site).as_posix() for p in pages} == {
        "index.html", f"notebooks/{STEMS[0]}.html"}
    for path in pages:
        text = path.read_text(encoding="utf-8")
        assert remote_resources(text) == [], path
        parsed = _parse(path)
        for image in parsed.images:
            assert (image.get("alt") or "").strip(), f"{path.name}: an image without alt text"
        for ref in parsed.refs:
            assert ref and (path.parent / ref).exists(), f"{path.name}: broken link {ref}"
    page = (built_site / "notebooks" / f"{STEMS[0]}.html").read_text(encoding="utf-8")
    assert WIDGET_VIEW_MIME not in page and "mpcrl-static-widget" in page
    assert "No description has been provided" not in page
    assert "without encryption" not in page
    alts = [image.get("alt") or "" for image in
            _parse(built_site / "notebooks" / f"{STEMS[0]}.html").images]
    assert any(alt.startswith("Figure: buying price φ_b (NOK/MWh) against hour") and "series day 1"
               in alt and "values from" in alt for alt in alts), \
        f"figures carry their panels, series and data range as alt text: {alts}"
    summary = json.loads((built_site / "summary.json").read_text())
    assert list(summary["notebooks"]) == [STEMS[0]] and summary["profile"] == "ci"
    index = (built_site / "index.html").read_text(encoding="utf-8")
    assert PAPER["doi"] in index and f'href="notebooks/{STEMS[0]}.html"' in index
    assert (built_site / "notebooks" / "mathjax" / "MathJax.js").is_file()


def test_paper_figures_and_study_tables_are_collected(tmp_path):
    nb = nbformat.v4.new_notebook()
    cell = nbformat.v4.new_code_cell("fig = fig2_performance(history)")
    cell.outputs = [nbformat.v4.new_output(
        "display_data", data={"image/png": _png(), "text/plain": "<Figure>"},
        metadata={"image/png": {"alt": "Figure: J per month."}})]
    solution = nbformat.v4.new_code_cell("fig = fig3_gradient_norm(history)")
    solution.metadata["tags"] = ["solution"]
    solution.outputs = list(cell.outputs)
    nb.cells = [cell, solution]
    figures = site_module.extract_paper_figures(nb, tmp_path / "figures")
    assert figures == [{"file": "fig2_performance.png", "name": "fig2_performance",
                        "alt": "Figure: J per month."}]
    assert (tmp_path / "figures" / "fig2_performance.png").read_bytes().startswith(b"\x89PNG")

    sweep = tmp_path / "report" / "sweep_runs" / "months=2,days=2"
    (sweep / "runs").mkdir(parents=True)
    (sweep / "results.csv").write_text("P_bar,seed,J_last\n1.0,0,12.5\n2.0,0,14.0\n")
    (sweep / "sweep.json").write_text("{}")
    studies = site_module.collect_study(tmp_path / "report", tmp_path / "study")
    assert [s["name"] for s in studies] == ["months=2,days=2"]
    assert studies[0]["table"]["J_last"].tolist() == [12.5, 14.0]
    assert sorted(p.name for p in (tmp_path / "study" / "months=2,days=2").iterdir()) == [
        "results.csv", "sweep.json"]  # the run folders stay behind
    entry = site_module.NotebookEntry("05_x", "05 · Learning", "Run it.", 12.0)
    page = site_module.render_index([entry], {"profile": "ci", "notebooks": {}}, figures,
                                    studies)
    assert remote_resources(page) == []
    assert 'src="figures/fig2_performance.png" alt="Figure: J per month."' in page
    assert "study/months=2,days=2/results.csv" in page and "14.0" in page


class _Thumbnails(HTMLParser):
    """Every <img> of a page with the href of the <a> it sits in (None outside a link)."""

    def __init__(self):
        super().__init__(convert_charrefs=True)
        self.links: list[str | None] = []
        self.images: list[tuple[str | None, str | None]] = []

    def handle_starttag(self, tag, attrs):
        attrs = dict(attrs)
        if tag == "a":
            self.links.append(attrs.get("href"))
        elif tag == "img":
            self.images.append((attrs.get("src"), self.links[-1] if self.links else None))

    def handle_endtag(self, tag):
        if tag == "a" and self.links:
            self.links.pop()


def test_every_figure_thumbnail_links_to_its_full_image():
    figures = [{"file": "fig2_performance.png", "name": "fig2_performance", "alt": "J."},
               {"file": "fig7_theta.png", "name": "fig7_theta", "alt": "theta."}]
    page = site_module.render_index([], {"profile": "ci", "notebooks": {}}, figures, [])
    parsed = _Thumbnails()
    parsed.feed(page)
    assert [src for src, _ in parsed.images] == ["figures/fig2_performance.png",
                                                 "figures/fig7_theta.png"]
    for src, href in parsed.images:
        assert href == src, f"thumbnail {src} is not a link to itself (inside {href!r})"


def test_the_site_study_is_the_notebook_own_run(tmp_path):
    """Rows an exercise added to the study's folder (another seed, a pending run) and other
    sweeps' folders are not the study: only the finished runs of its own grid are shown."""
    sweep = tmp_path / "report" / "sweep_runs" / "months=2,days=2"
    sweep.mkdir(parents=True)
    (sweep / "results.csv").write_text(
        "P_bar,noise_var,seed,status,J_last\n"
        "1.0,0.5,0,done,12.5\n1.0,0.5,1,done,13.0\n2.0,0.5,0,done,14.0\n2.0,0.5,1,done,15.0\n"
        "1.0,0.5,2,done,99.0\n2.0,0.5,2,pending,\n")
    other = tmp_path / "report" / "sweep_runs" / "months=9,days=9"
    other.mkdir(parents=True)
    (other / "results.csv").write_text("P_bar,noise_var,seed,status,J_last\n1.0,0.5,0,done,1\n")
    study = {"months": 2, "days": 2, "P_bars": [1.0, 2.0], "noise_vars": [0.5], "seeds": 2}
    studies = site_module.collect_study(tmp_path / "report", tmp_path / "study", study)
    assert [s["name"] for s in studies] == ["months=2,days=2"]
    table = studies[0]["table"]
    assert table["J_last"].tolist() == [12.5, 13.0, 14.0, 15.0]
    assert (table["status"] == "done").all() and table["seed"].max() == 1
    copied = (tmp_path / "study" / "months=2,days=2" / "results.csv").read_text()
    assert "99.0" not in copied and "pending" not in copied


def test_the_study_note_warns_of_short_runs_only_when_the_runs_are_short():
    """The classroom profile runs the notebook's default run size (30 months of 30 days) on a
    smaller grid: its table must not be introduced as a run too short to judge a grid limit,
    while the test profile's 2 months of 2 days must be."""
    import pandas as pd

    table = pd.DataFrame({"P_bar": [1.5, 2.0], "seed": [0, 0], "J_last": [-150.0, -226.0]})

    def note(name: str) -> str:
        page = site_module.render_index([], {"profile": "classroom", "notebooks": {}}, [],
                                        [{"name": name, "files": [], "table": table}])
        (text,) = re.findall(r'<p class="small">(One row per run.*?)</p>', page, re.DOTALL)
        return text

    defaults = nbref.read_notebook("07_parameter_study")
    assert "MONTHS: int = 30" in defaults.cells[2].source
    assert "DAYS: int = 30" in defaults.cells[2].source
    full = note("months=30,days=30")
    assert "learned 30 months of 30 days" in full and "differ only by their seed" in full
    assert "A run this short" not in full
    short = note("months=2,days=2")
    assert "A run this short" in short and "(30 months of 30 days)" in short
    assert "A run this short" in note("months=12,days=30")


def test_the_classroom_study_runs_the_notebook_run_size():
    """The site shows the classroom profile's study: its runs are as long as the notebook's
    defaults (shorter runs end before the learning shows what a grid limit is worth: 12 months
    of 12 days left P_bar = 2.0 near the nominal MPC's soc penalties), on a smaller grid."""
    from mpcrl_lite.publish.report import notebook_parameters, profile_parameters

    classroom = profile_parameters("classroom")["07_parameter_study"]
    defaults = {k: v["default"] for k, v in notebook_parameters("07_parameter_study.ipynb").items()}
    assert classroom["MONTHS"] >= int(defaults["MONTHS"]) == 30
    assert classroom["DAYS"] >= int(defaults["DAYS"]) == 30
    assert "A run this short" not in site_module._study_note(
        f"months={classroom['MONTHS']},days={classroom['DAYS']}", "classroom")
    # the paper's grid limit is on the grid: the day-end comparison runs at the paper's system
    assert 1.5 in [float(p) for p in classroom["P_BARS"].split(",")]


def test_site_command_rejects_a_bad_profile(capsys):
    with pytest.raises(SystemExit) as info:
        site_module.main(["--out", "unused", "--profile", "huge"])
    assert info.value.code == 2
    assert "invalid choice: 'huge'" in capsys.readouterr().err


def _dump_dom(url: str) -> str:
    """The page after its scripts ran, in headless Chromium with every network request sent
    to a dead proxy: a page that needed the network would stay untypeset."""
    run = subprocess.run(
        [CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu", "--no-first-run",
         "--proxy-server=127.0.0.1:9", "--proxy-bypass-list=<-loopback>",
         "--virtual-time-budget=20000", "--dump-dom", url],
        capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr[-2000:]
    return run.stdout


@needs_chromium
@pytest.mark.notebook
def test_pages_render_offline_in_a_real_browser(built_site):
    nb = nbref.read_notebook(STEMS[0])
    display = sum(c.source.count("$$") // 2 for c in nb.cells if c.cell_type == "markdown")
    dom = _dump_dom((built_site / "notebooks" / f"{STEMS[0]}.html").resolve().as_uri())
    assert dom.count('class="MathJax_Display"') >= display > 0, "display equations typeset"
    assert dom.count('class="MathJax"') > display, "inline equations typeset"
    assert 'class="MathJax_Error"' not in dom and "Math Processing Error" not in dom
    text = re.sub(r"<script.*?</script>", "", dom, flags=re.DOTALL)
    assert "$$" not in text, "no raw TeX left on the page"
    # the two explorers of notebook 01 (the class also names the page's style rules)
    assert dom.count('<figure class="mpcrl-static-widget"') == 2
    index = _dump_dom((built_site / "index.html").resolve().as_uri())
    assert f'href="notebooks/{STEMS[0]}.html"' in index and "The notebook tour" in index
