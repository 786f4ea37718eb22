"""Notebook tests under pytest-xdist: every test that needs a notebook's execution (the
session fixture ``executed`` of test_notebooks.py, one execution per notebook and worker) is
put in the group of its notebook, so that ``--dist loadgroup`` (``make test``) runs each
notebook once, on one worker, instead of once on every worker that draws one of its tests."""

from __future__ import annotations

import pytest


def pytest_collection_modifyitems(config, items):
    for item in items:
        if "executed" not in getattr(item, "fixturenames", ()):
            continue
        callspec = getattr(item, "callspec", None)
        stem = callspec.params.get("stem") if callspec is not None else None
        if stem is not None:
            item.add_marker(pytest.mark.xdist_group(name=f"notebook-{stem}"))
