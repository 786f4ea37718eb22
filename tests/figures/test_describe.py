"""A figure in words: mathtext turned into Unicode, and the description of a figure (title,
panels, series, data ranges) that the explorers and the notebooks use as alt text."""

from __future__ import annotations

import unicodedata

import pytest
from matplotlib.figure import Figure

from mpcrl_lite.figures.describe import describe_figure, plain_text


@pytest.mark.parametrize(("tex", "plain"), [
    (r"$\bar P$ = 1.5 MW", "P̄ = 1.5 MW"),
    (r"$\pm\bar U$", "±Ū"),
    (r"$\bar{\phi}_b$", "φ̄_b"),
    (r"$\theta_s^1$ ($\mathrm{NOK}$)", "θ_s^1 (NOK)"),
    (r"policy  $\pi^i(s)$", "policy π^i(s)"),
    ("P_bar [MW]", "P_bar [MW]"),
])
def test_plain_text_turns_mathtext_into_unicode(tex, plain):
    assert plain_text(tex) == unicodedata.normalize("NFC", plain)


def test_describe_figure_names_title_panels_series_and_data_range():
    fig = Figure()
    a, b = fig.subplots(1, 2)
    fig.suptitle("Closed loop: $J$ = 12.5 NOK/day")
    a.plot([0, 1, 2], [3.0, -1.0, 7.25], label=r"$\bar P$")
    a.plot([0, 1, 2], [0.5, 0.5, 0.5], label="applied")
    a.legend()
    a.set(xlabel="hour", ylabel="power (MW)")
    b.set_title("prices")
    b.scatter([0, 1], [10.0, 20.0])
    text = describe_figure(fig)
    assert text == unicodedata.normalize("NFC", "Figure: Closed loop: J = 12.5 NOK/day. Panels: power (MW) against hour "
                    "(series P̄, applied; values from -1 to 7.25); prices (values from 10 to 20).")
    assert "values" not in describe_figure(fig, ranges=False)
