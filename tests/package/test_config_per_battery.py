"""Per-battery fields of SystemConfig: a scalar or one value per battery, checked element-wise."""

from __future__ import annotations

import pytest

from mpcrl_lite.config import PER_BATTERY, SystemConfig

MIXED = {"alpha": (1 / 24, 1 / 12, 1 / 12), "noise_var": (1.0, 0.5, 0.5)}


def test_scalars_stay_floats_and_lists_become_tuples_of_floats():
    system = SystemConfig(alpha=[1 / 24, 1 / 12, 1 / 12], U_bar=(2, 1, 1), P_bar=2.0, soc0=0.5)
    assert system.alpha == (1 / 24, 1 / 12, 1 / 12)
    assert system.U_bar == (2.0, 1.0, 1.0) and all(type(u) is float for u in system.U_bar)
    assert system.soc0 == 0.5 and system.battery("soc0") == (0.5, 0.5, 0.5)
    assert SystemConfig().alpha == 1 / 12  # the default is untouched
    assert SystemConfig.from_dict(system.to_dict()) == system
    assert system.to_dict()["U_bar"] == [2.0, 1.0, 1.0]


@pytest.mark.parametrize("field, value, message", [
    ("alpha", (0.1, 0.1), "alpha=(0.1, 0.1): expected a scalar or one value per battery"),
    ("alpha", (0.1, -0.1, 0.1), "alpha[1]=-0.1: expected a value in (0, inf)"),
    ("soc0", (0.5, 0.5, 1.5), "soc0[2]=1.5: expected a value in [0, 1]"),
    ("noise_var", (0.5, "a", 0.5), "noise_var[1]='a'"),
    ("U_bar", (1.0, 0.0, 1.0), "U_bar[1]=0.0: expected a value in (0, inf)"),
    ("p", (1000.0, 1000.0, -1.0), "p[2]=-1.0: expected a value in [0, inf)"),
])
def test_bad_values_name_the_field_and_the_battery(field, value, message):
    with pytest.raises(ValueError) as info:
        SystemConfig(**{field: value})
    assert message in str(info.value) and "\n" not in str(info.value)


def test_groups_of_identical_batteries():
    assert SystemConfig().battery_groups() == (0, 0, 0) and SystemConfig().identical
    mixed = SystemConfig(**MIXED)
    assert mixed.battery_groups() == (0, 1, 1) and not mixed.identical
    assert SystemConfig(n=4, soc0=(0.5, 0.6, 0.5, 0.7)).battery_groups() == (0, 1, 0, 2)
    assert SystemConfig(alpha=(0.1, 0.1, 0.1)).identical  # equal values are one group
    assert set(PER_BATTERY) == {"alpha", "noise_mean", "noise_var", "U_bar", "p", "soc0"}


def test_noise_std_and_the_grid_warning_follow_the_batteries():
    system = SystemConfig(noise_var=(1.0, 0.25, 0.25))
    assert system.noise_std == (1.0, 0.5, 0.5)
    with pytest.warns(UserWarning, match="n\\*U_bar=2.5"):
        SystemConfig(U_bar=(0.5, 1.0, 1.0), P_bar=2.5)
