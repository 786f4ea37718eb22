"""The classroom explorers: what they compute, their accessible controls, the widgets.

- :mod:`~mpcrl_lite.classroom.explorers`: the computations behind each explorer;
- :mod:`~mpcrl_lite.classroom.controls`: labelled, keyboard-friendly controls;
- :mod:`~mpcrl_lite.classroom.widgets`: the explorers as ipywidgets.

May import: :mod:`mpcrl_lite.figures` and below.
"""
