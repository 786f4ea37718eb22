"""Figures drawn from data only (a History, a Record, a Prices): no solving here.

- :mod:`~mpcrl_lite.figures.style`: conventions and small drawing helpers;
- :mod:`~mpcrl_lite.figures.describe`: a figure in words (its alt text);
- :mod:`~mpcrl_lite.figures.plots`: one day in closed loop and the explorers' figures;
- :mod:`~mpcrl_lite.figures.paper`: the paper's Figs. 1-7;
- :mod:`~mpcrl_lite.figures.comparison`: notebook 06: policies against the bounds, two learners.

May import: :mod:`mpcrl_lite.bounds` and below.
"""
