"""Text alternatives for the figures of the notebooks, derived from their titles.

A screen reader, a page that fails to load its images and a search all need words for a
figure. The words are already there: every figure of the package has a title (``suptitle``,
with its key numbers) or titled panels, legends and data.
:func:`~mpcrl_lite.figures.describe.describe_figure` turns them into a paragraph (title,
panels, series, data ranges), and the IPython extension
in this module attaches that sentence to every figure a notebook displays, as the ``alt``
metadata of its image output (``{"image/png": {"alt": ...}}``), which the HTML export writes into
the ``alt`` attribute of the picture (:mod:`mpcrl_lite.publish.html_export`).

The report runner loads the extension into each notebook's kernel
(``--IPKernelApp.extensions=mpcrl_lite.publish.alt_text``); by hand: ``%load_ext mpcrl_lite.publish.alt_text``.
"""

from __future__ import annotations

from typing import Any

from matplotlib.figure import Figure

from ..figures.describe import describe_figure

__all__ = ["IMAGE_MIMES", "load_ipython_extension"]  # describe_figure: figures.describe

#: Image outputs that get an ``alt`` entry in their metadata.
IMAGE_MIMES = ("image/png", "image/jpeg", "image/svg+xml")


def _with_alt(format_function):
    """Wrap IPython's ``DisplayFormatter.format`` so that figures carry their description."""

    def format_with_alt(obj: Any, include=None, exclude=None):
        data, metadata = format_function(obj, include=include, exclude=exclude)
        if isinstance(obj, Figure):
            text = describe_figure(obj)
            for mime in IMAGE_MIMES:
                if mime in data:
                    entry = dict(metadata.get(mime, {}))
                    entry.setdefault("alt", text)
                    metadata[mime] = entry
        return data, metadata

    format_with_alt.__wrapped__ = format_function
    return format_with_alt


def load_ipython_extension(ipython) -> None:
    """Attach :func:`describe_figure` to every figure this kernel displays.

    The inline backend re-registers its image formatters when ``%matplotlib inline`` runs, so
    the hook wraps the display formatter's ``format`` method, which every display and every
    cell result passes through, rather than one formatter.
    """
    formatter = ipython.display_formatter
    if not hasattr(formatter.format, "__wrapped__"):
        formatter.format = _with_alt(formatter.format)


def unload_ipython_extension(ipython) -> None:
    formatter = ipython.display_formatter
    wrapped = getattr(formatter.format, "__wrapped__", None)
    if wrapped is not None:
        formatter.format = wrapped
