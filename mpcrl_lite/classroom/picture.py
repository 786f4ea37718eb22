r"""A picture for the explorers: a PNG shown as an ``<img>`` with an ``alt`` text.

:class:`ipywidgets.Image` draws an ``<img>`` without ``alt`` (a screen reader announces
"image" or the file name; axe reports *image-alt*), and setting its ``tooltip`` in JupyterLab
puts the text on the element without naming the image. :class:`Picture` is a small
:mod:`anywidget` view that keeps the same attributes as the ipywidgets image it replaces
(``value`` as PNG bytes, ``format``, ``width``, ``layout``) and writes ``alt`` (and ``title``,
the same words on hover) on the ``<img>`` itself.
"""

from __future__ import annotations

import anywidget
import traitlets

__all__ = ["Picture"]

#: The view: one <img>, its source a blob URL of the bytes, its alt text the model's.
_ESM = """
function render({ model, el }) {
  const img = document.createElement("img");
  img.className = "mpcrl-picture";
  el.append(img);
  let url = null;
  const sync = () => {
    const data = model.get("value");
    if (url) URL.revokeObjectURL(url);
    url = data && data.byteLength ? URL.createObjectURL(
        new Blob([data], { type: `image/${model.get("format")}` })) : null;
    if (url) img.src = url; else img.removeAttribute("src");
    img.alt = model.get("alt");
    if (model.get("alt")) img.title = model.get("alt"); else img.removeAttribute("title");
    if (model.get("width")) img.width = Number(model.get("width"));
  };
  model.on("change", sync);
  sync();
  return () => { model.off("change", sync); if (url) URL.revokeObjectURL(url); };
}
export default { render };
"""

_CSS = """
.mpcrl-picture { display: block; max-width: 100%; height: auto; }
"""


class Picture(anywidget.AnyWidget):
    """An image with an alternative text.

    Attributes (synchronized with the view)
    ----------------------------------------
    value : bytes
        The encoded image (PNG by default).
    format : str, default ``"png"``
        Its format (the ``image/<format>`` MIME type).
    width : str
        Width in CSS pixels (as the ``width`` attribute of ``<img>``); the image is never
        shown wider than its container and keeps its aspect ratio.
    alt : str
        What the picture shows, in words (also its hover text).
    """

    _esm = _ESM
    _css = _CSS
    value = traitlets.Bytes(b"").tag(sync=True)
    format = traitlets.Unicode("png").tag(sync=True)
    width = traitlets.Unicode("").tag(sync=True)
    alt = traitlets.Unicode("").tag(sync=True)
