"""Baselines and bounds of a mixed site: the clairvoyant LP, the price rule, the Lagrangian
bound group by group, the causal DP's refusal beyond three batteries that differ; identical
batteries as tuples change nothing."""

from __future__ import annotations

import numpy as np
import pytest

from mpcrl_lite.bounds.baselines import evaluate_baselines
from mpcrl_lite.bounds.causal.dp import causal_optimum
from mpcrl_lite.bounds.causal.dual import battery_groups, lagrangian_bound
from mpcrl_lite.config import SystemConfig
from mpcrl_lite.system.prices import Prices

MIXED = SystemConfig(alpha=(1 / 24, 1 / 12, 1 / 12), noise_var=(1.0, 0.5, 0.5))


def test_the_clairvoyant_bound_stays_below_every_policy_on_a_mixed_site():
    result = evaluate_baselines(MIXED, days=3, seed=1)
    J = {name: p["J"] for name, p in result["policies"].items()}
    assert set(J) >= {"clairvoyant", "nominal", "rule_based"}
    assert all(np.isfinite(v) for v in J.values())
    assert J["clairvoyant"] <= min(J["nominal"], J["rule_based"])


def test_identical_batteries_as_tuples_give_the_same_baselines():
    same = SystemConfig(alpha=(1 / 12,) * 3, soc0=(0.6,) * 3, p=(1000.0,) * 3)
    a = evaluate_baselines(SystemConfig(), days=2, seed=0)["policies"]
    b = evaluate_baselines(same, days=2, seed=0)["policies"]
    for name in a:
        assert a[name]["J"] == b[name]["J"], name


def test_the_lagrangian_bound_relaxes_group_by_group():
    prices = Prices.month(MIXED, 1)
    groups = battery_groups(MIXED)
    assert [g.n for g in groups] == [1, 2]
    assert groups[0].alpha == 1 / 24 and groups[1].noise_var == 0.5
    mixed = lagrangian_bound(MIXED, prices, max_iter=0)
    parts = [lagrangian_bound(g, prices, max_iter=0).J_relaxed for g in groups]
    # without multipliers the batteries decouple: the site is the sum of its groups
    assert mixed.J_relaxed == pytest.approx(sum(parts), rel=1e-12)
    best = lagrangian_bound(MIXED, prices, max_iter=50)
    assert best.J_bound >= mixed.J_relaxed - 1e-9  # the maximised dual only gains
    # identical batteries: the same bound whether written as scalars or as tuples
    one = lagrangian_bound(SystemConfig(), prices, max_iter=0).J_relaxed
    assert lagrangian_bound(SystemConfig(alpha=(1 / 12,) * 3), prices,
                            max_iter=0).J_relaxed == one


def test_the_causal_dp_refuses_four_batteries_that_differ_in_one_line():
    four = SystemConfig(n=4, alpha=(1 / 24, 1 / 12, 1 / 12, 1 / 12))
    with pytest.raises(ValueError) as info:
        causal_optimum(four, Prices.month(four, 1))
    text = str(info.value)
    assert "\n" not in text and "alpha=[" in text and "lagrangian_bound" in text
