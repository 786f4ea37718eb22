"""The stored J* table (data/causal_j_star.csv): it is what the causal DP gives, it is used only
where it applies, and a bound read from it measures policies like a solved one."""

from __future__ import annotations

import json
import warnings

import numpy as np
import pytest

from mpcrl_lite.bounds.baselines import evaluate_baselines
from mpcrl_lite.bounds.causal.dp import causal_optimum
from mpcrl_lite.bounds.causal.table import (
    SITES_CSV,
    causal_bound,
    provenance,
    site_key,
    stored_bound,
)
from mpcrl_lite.config import ConfigWarning, MPCConfig, SystemConfig
from mpcrl_lite.system.prices import Prices

#: The systems notebooks 06 and 07 read from the table (07's default grid).
STORED = [(p, v) for p in (1.0, 1.5, 2.0) for v in (0.2, 0.5)]


def _one_day(system: SystemConfig, day: int) -> Prices:
    month = Prices.default(system)
    return Prices(month.buy[[day]], sell_ratio=month.sell_ratio, unit=month.unit, source="test")


@pytest.mark.parametrize(("P_bar", "noise_var"), STORED)
def test_table_covers_the_notebooks_systems_and_matches_its_provenance(P_bar, noise_var):
    system = SystemConfig(P_bar=P_bar, noise_var=noise_var)
    bound = stored_bound(system)
    assert bound is not None and bound.J_star_per_day.shape == (30,)
    assert np.all(np.isfinite(bound.J_star_per_day))
    run = [r for r in provenance()["runs"] if (r["P_bar"], r["noise_var"]) == (P_bar, noise_var)]
    assert len(run) == 1 and np.isclose(run[0]["J_star"], bound.J_star, rtol=1e-12)
    # the first days of the month (what a notebook with DAYS < 30 learns on) are covered
    days = Prices.month(system, 2)
    assert np.array_equal(bound.J_star_for(days), bound.J_star_per_day[:2])


@pytest.mark.parametrize(("P_bar", "noise_var", "day"), [(1.5, 0.5, 0), (2.0, 0.2, 17)])
def test_stored_values_are_what_the_dp_gives(P_bar, noise_var, day):
    system = SystemConfig(P_bar=P_bar, noise_var=noise_var)
    solved = causal_optimum(system, _one_day(system, day), keep_values=False)
    stored = stored_bound(system).J_star_per_day[day]
    assert solved.J_star_per_day[0] == pytest.approx(stored, rel=1e-10, abs=1e-9)


def test_systems_and_prices_outside_the_table_are_solved():
    with warnings.catch_warnings():  # one battery never reaches the grid limit: it warns
        warnings.simplefilter("ignore", ConfigWarning)
        other = SystemConfig(n=1)  # differs in more than P_bar and noise_var
    assert stored_bound(other) is None
    one_day = _one_day(other, 3)
    bound = causal_bound(other, one_day)
    assert bound.info["source"] == "solved"
    assert bound.J_star_for(one_day)[0] == pytest.approx(
        causal_optimum(other, one_day).J_star_per_day[0], rel=1e-12)
    system = SystemConfig()
    shifted = Prices(Prices.default(system).buy[:1] + 1.0, sell_ratio=system.sell_ratio)
    assert stored_bound(system, shifted) is None  # prices of a day the table does not hold
    assert stored_bound(system, _one_day(system, 5)) is not None
    assert stored_bound(system, grid=61) is None  # another discretisation


def test_a_stored_bound_measures_policies_without_a_dp_policy_row():
    system = SystemConfig()
    days = Prices.month(system, 1)
    bound = causal_bound(system, days)
    assert bound.values is None and bound.info["source"].endswith("causal_j_star.csv")
    result = evaluate_baselines(system, MPCConfig(), 1, 10_000, causal=bound)
    causal = result["causal"]
    assert "causal_dp" not in result["policies"]
    assert causal["J_star"] == pytest.approx(bound.J_star_per_day[0])
    for name, policy in result["policies"].items():
        assert causal["regret"][name] == pytest.approx(policy["J"] - causal["J_star"])
    # the nominal MPC is far from the best causal policy; the gap is measured from it
    assert causal["regret"]["nominal"] > 0 and causal["gap_closed"]["nominal"] == 0.0
    with pytest.raises(ValueError, match="value tables"):
        bound.policy(days)


# -- the notebooks' sites (data/causal_j_star_sites.csv) -----------------------------------
#: Notebook 06's mixed site (section 4, default P_BAR).
MIXED = SystemConfig(alpha=(1 / 24, 1 / 12, 1 / 12), noise_var=(1.0, 0.5, 0.5), P_bar=1.5)


def test_the_sites_table_covers_notebook_06s_mixed_site():
    bound = stored_bound(MIXED)
    assert bound is not None and bound.info["source"] == f"data/{SITES_CSV}"
    assert bound.J_star_per_day.shape == (30,) and np.all(np.isfinite(bound.J_star_per_day))
    [run] = [r for r in provenance(SITES_CSV)["runs"] if r["key"] == site_key(MIXED)]
    assert np.isclose(run["J_star"], bound.J_star, rtol=1e-12)
    # the notebook's call: the first DAYS days, read rather than solved
    days = Prices.month(MIXED, 30)
    assert causal_bound(MIXED, days).info["source"] == f"data/{SITES_CSV}"
    # the same site with another horizon N of the MPC is the same true system
    assert stored_bound(MIXED.replace(N=6)) is not None
    # one field different: not stored
    assert stored_bound(MIXED.replace(P_bar=1.0)) is None


def test_a_stored_site_day_is_what_the_dp_gives():
    day = 11
    solved = causal_optimum(MIXED, _one_day(MIXED, day), keep_values=False)
    stored = stored_bound(MIXED).J_star_per_day[day]
    assert solved.J_star_per_day[0] == pytest.approx(stored, rel=1e-10, abs=1e-9)


def test_site_keys_name_the_fields_that_differ():
    assert site_key(SystemConfig()) == "{}"
    assert site_key(SystemConfig(N=6)) == "{}"  # the MPC's horizon is not the site's
    key = json.loads(site_key(MIXED))
    assert key == {"alpha": [1 / 24, 1 / 12, 1 / 12], "noise_var": [1.0, 0.5, 0.5]}
