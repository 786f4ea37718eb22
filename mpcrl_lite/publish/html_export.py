"""Executed notebooks as HTML pages that work offline, from the file system, with no server.

nbconvert's default page loads require.js, MathJax and the widget manager from CDNs: offline,
equations stay raw ``$$...$$`` and every explorer is an empty output. This module writes pages
that load nothing from the network:

* **Equations**: MathJax 2 from a local copy (the files of the ``jupyter-server-mathjax``
  package, copied once into ``mathjax/`` next to the pages; :func:`copy_mathjax`).
* **Explorers** (ipywidgets): a widget needs a running kernel, so each explorer is replaced
  by a static picture of its state when the notebook ran -- the PNG it showed, read from the
  widget state that nbclient stores in the notebook -- with its control values and a note to
  open the notebook for the live version (:func:`static_widgets`).
* **Figures**: every picture carries an ``alt`` text: the description that
  :mod:`mpcrl_lite.publish.alt_text` derived from the figure's title while the notebook ran, or a
  generic one.
* **Launch badges** and other images from the web in markdown cells become plain links.
* **Reading**: the page is titled after the notebook (:func:`page_title`), its colours meet
  WCAG AA contrast (4.5:1) and links in running text are underlined; every font MathJax asks
  for is in the local copy.
* No require.js, no widget embedder, no mermaid loader; :func:`remote_resources` lists
  anything that would still reach the network and :func:`write_html` refuses to write such a
  page.
"""

from __future__ import annotations

import copy
import html
import os
import re
import shutil
from html.parser import HTMLParser
from importlib import resources
from pathlib import Path
from typing import Any

__all__ = [
    "MATHJAX_DIRNAME",
    "WIDGET_STATE_MIME",
    "WIDGET_VIEW_MIME",
    "copy_mathjax",
    "mathjax_source",
    "mathjax_tags",
    "page_title",
    "remote_resources",
    "static_widgets",
    "to_html",
    "unlink_remote_images",
    "write_html",
]

#: Folder (next to the pages) holding the local MathJax copy.
MATHJAX_DIRNAME = "mathjax"
WIDGET_VIEW_MIME = "application/vnd.jupyter.widget-view+json"
WIDGET_STATE_MIME = "application/vnd.jupyter.widget-state+json"

# Parts of MathJax 2 the pages use: TeX input, the HTML-CSS output with its STIX web fonts,
# English messages. The accessibility extensions and other languages are left out (~9 MB).
_MATHJAX_PARTS = ("MathJax.js", "LICENSE", "config", "extensions", "jax/input", "jax/element",
                  "jax/output/HTML-CSS", "fonts", "localization/en")
_MATHJAX_SKIP = ("a11y",)
_MATHJAX_CONFIG = "TeX-AMS-MML_HTMLorMML-full,Safe"

_TEMPLATE_NAME = "mpcrl_offline.html.j2"
# Extends nbconvert's "lab" page; every block that loads a script from the web is emptied or
# pointed at a local file, and pictures get their alt text.
_TEMPLATE = r"""
{%- extends 'index.html.j2' -%}
{%- block html_head_js_requirejs -%}{%- endblock html_head_js_requirejs -%}
{% block jupyter_widgets %}{% endblock jupyter_widgets %}
{%- block html_head_js_mermaidjs -%}{%- endblock html_head_js_mermaidjs -%}
{%- block html_head_js_mathjax -%}
{{ resources.mpcrl_mathjax }}
{%- endblock html_head_js_mathjax -%}
{%- block html_head_css -%}
<style type="text/css">{{ resources.mpcrl_css }}</style>
{%- endblock html_head_css -%}
{% block data_png scoped %}
<div class="jp-RenderedImage jp-OutputArea-output {{ extra_class }}">
<img src="data:image/png;base64,{{ output.data['image/png'] | escape_html }}"
{%- set alt = (output | get_metadata('alt', 'image/png')) or resources.mpcrl_default_alt %}
alt="{{ alt | escape_html }}"
{%- set width=output | get_metadata('width', 'image/png') -%}
{%- if width is not none %} width={{ width | escape_html }}{%- endif %}
{%- set height=output | get_metadata('height', 'image/png') -%}
{%- if height is not none %} height={{ height | escape_html }}{%- endif %}
>
</div>
{%- endblock data_png %}
{% block data_jpg scoped %}
<div class="jp-RenderedImage jp-OutputArea-output {{ extra_class }}">
<img src="data:image/jpeg;base64,{{ output.data['image/jpeg'] | escape_html }}"
{%- set alt = (output | get_metadata('alt', 'image/jpeg')) or resources.mpcrl_default_alt %}
alt="{{ alt | escape_html }}">
</div>
{%- endblock data_jpg %}
"""

_DEFAULT_ALT = "Figure without a title (see the code cell above for what it plots)."

#: Colours of the light theme that fall below WCAG AA (4.5:1) on the code cells' background
#: (#f5f5f5) or on white, replaced by darker tones of the same hue (each at least 5:1 on
#: #f5f5f5), the cell prompts at full opacity, and links in running text underlined (WCAG
#: 1.4.1: not told apart by colour alone).
_ACCESSIBLE_CSS = """
:root {
  --jp-mirror-editor-atom-color: #3c3cc4;
  --jp-mirror-editor-bracket-color: #66663d;
  --jp-mirror-editor-comment-color: #2f6464;
  --jp-mirror-editor-error-color: #c00000;
  --jp-mirror-editor-hr-color: #666666;
  --jp-mirror-editor-meta-color: #8a1ccf;
  --jp-mirror-editor-operator-color: #8a1ccf;
  --jp-mirror-editor-number-color: #006600;
  --jp-mirror-editor-quote-color: #006b00;
  --jp-mirror-editor-variable-3-color: #00664a;
  --jp-cell-inprompt-font-color: #1f5f99;
  --jp-cell-outprompt-font-color: #a3432a;
  --jp-cell-prompt-not-active-font-color: #616161;
  --jp-cell-prompt-not-active-opacity: 1;
}
.jp-InputPrompt, .jp-OutputPrompt { opacity: 1; }
.jp-InputPrompt { color: #1f5f99; }
.jp-OutputPrompt { color: #a3432a; }
.jp-RenderedHTMLCommon a, .jp-RenderedHTMLCommon a:link, .jp-RenderedHTMLCommon a:visited,
.mpcrl-static-widget a, .mpcrl-static-widget a:link, .mpcrl-static-widget a:visited {
  text-decoration: underline;
}
"""


# MathJax 2 set up as in JupyterLab: $...$ and $$...$$, AMS numbering, STIX web fonts.
_MATHJAX_SETUP = r"""<script type="text/x-mathjax-config">
MathJax.Hub.Config({
  tex2jax: {
    inlineMath: [["$", "$"], ["\\(", "\\)"]],
    displayMath: [["$$", "$$"], ["\\[", "\\]"]],
    processEscapes: true,
    processEnvironments: true
  },
  TeX: {equationNumbers: {autoNumber: "AMS", useLabelIds: true}},
  "HTML-CSS": {availableFonts: [], imageFont: null, preferredFont: null, webFont: "STIX-Web",
               linebreaks: {automatic: true}},
  displayAlign: "center",
  messageStyle: "none"
});
</script>"""


def mathjax_tags(url: str = f"{MATHJAX_DIRNAME}/MathJax.js") -> str:
    """The ``<script>`` tags that typeset a page's TeX with the local MathJax at ``url``
    (relative to the page; see :func:`copy_mathjax`)."""
    return f'{_MATHJAX_SETUP}\n<script src="{url}?config={_MATHJAX_CONFIG}"></script>'


# -- MathJax -----------------------------------------------------------------------------------
def mathjax_source() -> Path:
    """The MathJax 2 files shipped by the ``jupyter-server-mathjax`` package."""
    try:
        root = resources.files("jupyter_server_mathjax") / "static"
    except ModuleNotFoundError:
        raise ModuleNotFoundError(
            "offline HTML pages need the MathJax files of the package jupyter-server-mathjax; "
            "install it (python -m pip install jupyter-server-mathjax, or the notebooks extra "
            "of mpcrl_lite; it is in environment-requirements.txt)") from None
    root = Path(str(root))
    if not (root / "MathJax.js").is_file():
        raise FileNotFoundError(f"{root / 'MathJax.js'} not found: jupyter-server-mathjax is "
                                "installed without its MathJax files; reinstall it")
    return root


def copy_mathjax(folder: str | Path) -> Path:
    """Copy the parts of MathJax the pages use into ``folder/mathjax`` (once) and return it."""
    target = Path(folder) / MATHJAX_DIRNAME
    source = mathjax_source()
    ignore = shutil.ignore_patterns(*_MATHJAX_SKIP)
    for part in () if (target / "MathJax.js").is_file() else _MATHJAX_PARTS:
        src = source / part
        if src.is_dir():
            shutil.copytree(src, target / part, ignore=ignore, dirs_exist_ok=True)
        elif src.is_file():
            (target / part).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(src, target / part)
    for missing, stand_in in _FONT_STAND_INS.items():
        if not (target / missing).is_file() and (source / stand_in).is_file():
            (target / missing).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(source / stand_in, target / missing)
    return target


#: Fonts that MathJax asks for but jupyter-server-mathjax does not ship, and the shipped font
#: that stands in. The MathML that MathJax hides in the page for screen readers styles
#: double-struck (``\mathbb E``), script, calligraphic (``\mathcal N``) and fraktur letters
#: with the TeX fonts ``MathJax_AMS``, ``MathJax_Script``, ..., which the package leaves out;
#: the STIX faces of the same alphabets stand in. Browsers read the font format from the
#: file's content, not its name.
_STIX = "fonts/HTML-CSS/STIX-Web/woff/STIXMathJax_"
_FONT_STAND_INS = {
    f"fonts/HTML-CSS/TeX/otf/MathJax_{tex}.otf": f"{_STIX}{stix}.woff"
    for tex, stix in (("AMS-Regular", "DoubleStruck-Regular"),
                      ("Script-Regular", "Script-Regular"),
                      ("Caligraphic-Regular", "Script-Regular"),
                      ("Caligraphic-Bold", "Script-BoldItalic"),
                      ("Fraktur-Regular", "Fraktur-Regular"),
                      ("Fraktur-Bold", "Fraktur-Bold"))
}


# -- widgets -----------------------------------------------------------------------------------
def _widget_models(nb) -> dict[str, dict[str, Any]]:
    state = nb.get("metadata", {}).get("widgets", {}).get(WIDGET_STATE_MIME, {})
    return dict(state.get("state", {}))


def _walk(model_id: str, models: dict[str, dict[str, Any]], seen: set[str] | None = None):
    """The widget ``model_id`` and all its descendants, depth first (children in order)."""
    seen = set() if seen is None else seen
    if model_id in seen or model_id not in models:
        return
    seen.add(model_id)
    model = models[model_id]
    yield model
    for child in model.get("state", {}).get("children", []) or []:
        if isinstance(child, str) and child.startswith("IPY_MODEL_"):
            yield from _walk(child[len("IPY_MODEL_"):], models, seen)


def _explorer_name(plain_text: str) -> str:
    """'DayExplorer(children=...' -> 'Day explorer'."""
    name = re.match(r"\s*([A-Za-z_][A-Za-z0-9_]*)", plain_text or "")
    if not name:
        return "Interactive explorer"
    words = re.sub(r"(?<=[a-z0-9])(?=[A-Z])", " ", name.group(1)).split()
    return " ".join([words[0]] + [w.lower() if not w.isupper() else w for w in words[1:]])


def _png_of(model: dict[str, Any]) -> str | None:
    for buffer in model.get("buffers", []) or []:
        if buffer.get("path") == ["value"] and buffer.get("encoding", "base64") == "base64":
            return buffer.get("data")
    return None


def _static_widget_output(view: dict[str, Any], plain: str, models: dict) -> dict[str, Any]:
    """A display_data output standing in for one widget view."""
    name = _explorer_name(plain)
    parts = list(_walk(view.get("model_id", ""), models))
    controls, labels, images = [], [], []
    for model in parts:
        kind, state = model.get("model_name", ""), model.get("state", {})
        if kind == "ImageModel" or (kind == "AnyModel" and "alt" in state):
            # an ipywidgets Image, or the explorers' picture (classroom.picture.Picture)
            data = _png_of(model)
            if data and state.get("format", "png") == "png":
                images.append((data, state.get("alt") or state.get("tooltip")
                               or state.get("description") or ""))
        elif kind in ("HTMLModel", "HTMLMathModel", "LabelModel"):
            if state.get("value"):
                labels.append(state["value"] if kind != "LabelModel"
                              else html.escape(str(state["value"])))
        elif state.get("description") and "value" in state:
            value = state["value"]
            if isinstance(value, list):
                value = " to ".join(str(v) for v in value)
            controls.append(f"{state['description']} = {value}")
    setting = "; ".join(controls)
    note = (f"{name}: a static picture of this interactive explorer as it was drawn when the "
            "notebook ran" + (f" ({setting})" if setting else "") + ". Open the notebook in "
            "Jupyter, Colab or Binder to move its controls.")
    if not parts:
        note = (f"{name}: an interactive explorer. Its controls work only in a live notebook "
                "(Jupyter, Colab or Binder); this page has no picture of it.")
    body = ['<figure class="mpcrl-static-widget">']
    for data, own_alt in images:
        alt = own_alt or f"{name} as drawn when the notebook ran" + (
            f": {setting}" if setting else "")
        body.append(f'<img src="data:image/png;base64,{data}" alt="{html.escape(alt)}">')
    for label in labels:
        body.append(f"<div>{label}</div>")
    body.append(f"<figcaption><em>{html.escape(note)}</em></figcaption></figure>")
    return {"output_type": "display_data", "metadata": {},
            "data": {"text/html": "\n".join(body), "text/plain": note}}


def static_widgets(nb):
    """A copy of the executed notebook ``nb`` whose widget outputs are static pictures.

    Each output showing a widget view becomes an HTML figure: the PNG of every image the
    widget contained when the notebook ran (the explorers draw their figure into a
    :class:`~mpcrl_lite.classroom.picture.Picture`, whose alt text the picture keeps), the values of its controls, its text labels and a note that the
    controls need a live notebook. The stored widget state is dropped from the copy.
    """
    out = copy.deepcopy(nb)
    models = _widget_models(out)
    for cell in out.get("cells", []):
        for i, output in enumerate(cell.get("outputs", []) or []):
            data = output.get("data", {})
            if WIDGET_VIEW_MIME in data:
                plain = data.get("text/plain", "")
                plain = "".join(plain) if isinstance(plain, list) else plain
                replacement = _static_widget_output(data[WIDGET_VIEW_MIME], plain, models)
                if output.get("output_type") == "execute_result":
                    replacement = {**replacement, "output_type": "execute_result",
                                   "execution_count": output.get("execution_count")}
                cell["outputs"][i] = replacement
    out.get("metadata", {}).pop("widgets", None)
    return out


# -- markdown ----------------------------------------------------------------------------------
_LINKED_IMAGE = re.compile(r"\[!\[([^\]]*)\]\((https?://[^)\s]+)\)\]\(([^)\s]+)\)")
_REMOTE_IMAGE = re.compile(r"!\[([^\]]*)\]\((https?://[^)\s]+)\)")


def unlink_remote_images(nb):
    """A copy of ``nb`` whose markdown images from the web (launch badges) are text links:
    ``[![Open in Colab](https://...svg)](url)`` becomes ``[Open in Colab](url)``."""
    out = copy.deepcopy(nb)
    for cell in out.get("cells", []):
        if cell.get("cell_type") != "markdown":
            continue
        source = cell["source"] if isinstance(cell["source"], str) else "".join(cell["source"])
        source = _LINKED_IMAGE.sub(lambda m: f"[{m.group(1) or 'link'}]({m.group(3)})", source)
        source = _REMOTE_IMAGE.sub(lambda m: f"[{m.group(1) or 'image'}]({m.group(2)})", source)
        cell["source"] = source
    return out


# -- the page ----------------------------------------------------------------------------------
def to_html(nb, mathjax_url: str = f"{MATHJAX_DIRNAME}/MathJax.js") -> str:
    """The offline HTML page of the executed notebook ``nb`` (nbformat node).

    ``mathjax_url`` is where the page finds ``MathJax.js``, relative to the page (see
    :func:`copy_mathjax`).
    """
    import nbformat
    from jinja2 import DictLoader
    from nbconvert import HTMLExporter

    exporter = HTMLExporter(template_name="lab", template_file=_TEMPLATE_NAME,
                            extra_loaders=[DictLoader({_TEMPLATE_NAME: _TEMPLATE})])
    page = unlink_remote_images(static_widgets(nb))
    page.setdefault("metadata", {})["title"] = page_title(page)
    body, _ = exporter.from_notebook_node(
        nbformat.from_dict(page), resources={"mpcrl_default_alt": _DEFAULT_ALT,
                                             "mpcrl_mathjax": mathjax_tags(mathjax_url),
                                             "mpcrl_css": _ACCESSIBLE_CSS})
    return body


def page_title(nb, suffix: str = "mpcrl_lite") -> str:
    """The page's ``<title>``: the notebook's own title (its first ``# `` heading, as plain
    text: markdown and TeX marks dropped), then ``suffix``; a notebook's ``metadata.title``
    wins."""
    title = (nb.get("metadata") or {}).get("title")
    if not title:
        for cell in nb.get("cells", []):
            if cell.get("cell_type") != "markdown":
                continue
            source = cell.get("source", "")
            source = "".join(source) if isinstance(source, list) else source
            heading = next((line[2:] for line in source.splitlines() if line.startswith("# ")),
                           None)
            if heading:
                title = re.sub(r"[`*_$\\]", "", re.sub(r"\[([^\]]*)\]\([^)]*\)", r"\1",
                                                        heading)).strip()
                break
    title = title or "Notebook"
    return f"{title} · {suffix}" if suffix and suffix not in title else title


def write_html(nb, path: str | Path, assets: str | Path | None = None) -> Path:
    """Write the offline page of ``nb`` to ``path``, with MathJax copied into ``assets``
    (default: the page's folder). Raises ``RuntimeError`` if the page would still load
    anything from the network."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    assets = path.parent if assets is None else Path(assets)
    mathjax = copy_mathjax(assets)
    relative = Path(_relpath(mathjax / "MathJax.js", path.parent)).as_posix()
    page = to_html(nb, mathjax_url=relative)
    remote = remote_resources(page)
    if remote:
        raise RuntimeError(f"{path.name}: the page would load {remote[:5]} from the network")
    path.write_text(page, encoding="utf-8")
    return path


def _relpath(target: Path, start: Path) -> str:
    return os.path.relpath(target.resolve(), start.resolve())


# -- checking a page ---------------------------------------------------------------------------
_REMOTE = re.compile(r"^\s*(https?:)?//", re.IGNORECASE)
_URL_IN_CODE = re.compile(r"""(?:https?:)?//[A-Za-z0-9.-]+\.[A-Za-z]{2,}[^\s'"()<>]*""")
_CSS_URL = re.compile(r"""(?:url\(\s*['"]?|@import\s+['"])((?:https?:)?//[^'")\s]+)""",
                      re.IGNORECASE)


class _ResourceScanner(HTMLParser):
    def __init__(self):
        super().__init__(convert_charrefs=True)
        self.remote: list[str] = []
        self._in: str | None = None

    def handle_starttag(self, tag, attrs):
        attrs = dict(attrs)
        if tag in ("script", "img", "iframe", "audio", "video", "source", "embed"):
            src = attrs.get("src") or ""
            if _REMOTE.match(src):
                self.remote.append(src)
        if tag == "link" and "stylesheet" in (attrs.get("rel") or "").lower():
            href = attrs.get("href") or ""
            if _REMOTE.match(href):
                self.remote.append(href)
        if tag == "link" and (attrs.get("rel") or "").lower() in ("preload", "modulepreload"):
            href = attrs.get("href") or ""
            if _REMOTE.match(href):
                self.remote.append(href)
        if tag in ("script", "style"):
            self._in = tag
        style = attrs.get("style") or ""
        self.remote.extend(_CSS_URL.findall(style))

    def handle_endtag(self, tag):
        if tag == self._in:
            self._in = None

    def handle_data(self, data):
        if self._in == "style":
            self.remote.extend(_CSS_URL.findall(data))
        elif self._in == "script":
            # code that fetches or imports from the web (the widget embedder, mermaid)
            for url in _URL_IN_CODE.findall(data):
                if "www.w3.org" not in url:  # XML namespace names, never loaded
                    self.remote.append(url)


def remote_resources(page: str) -> list[str]:
    """Every URL in the HTML ``page`` that a browser would load from the network: scripts,
    stylesheets, images and frames with remote sources, ``url(...)``/``@import`` in styles,
    and web addresses inside inline scripts. Links (``<a href>``) are not loads."""
    scanner = _ResourceScanner()
    scanner.feed(page)
    scanner.close()
    return scanner.remote
