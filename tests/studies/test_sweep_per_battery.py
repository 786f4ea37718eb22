"""Sweep keys with per-battery values: a list is one value per battery, a scalar one for all."""

from __future__ import annotations

import pytest

from mpcrl_lite.studies.sweep.grid import GridError, load_grid


def test_a_grid_over_per_battery_values():
    sweep = load_grid({"base": {"learning.months": 1, "system.soc0": [0.5, 0.6, 0.7]},
                       "grid": {"system.alpha": [[0.04, 0.08, 0.08], 0.08]}})
    assert sweep.run_ids == ["alpha=0.04_0.08_0.08", "alpha=0.08"]
    mixed, same = sweep.runs
    assert mixed.system.alpha == (0.04, 0.08, 0.08) and same.system.alpha == 0.08
    assert mixed.system.soc0 == (0.5, 0.6, 0.7)
    assert mixed.configs()["system"]["alpha"] == [0.04, 0.08, 0.08]


def test_a_wrong_length_is_refused_naming_the_field():
    with pytest.raises((GridError, ValueError), match=r"alpha=\(0.04, 0.08\): expected a scalar"):
        load_grid({"grid": {"system.alpha": [[0.04, 0.08]]}})
