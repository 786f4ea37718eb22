"""The configs and the shared validators: one clear error per bad input, plain types stored."""

from __future__ import annotations

import dataclasses
import json
import math
import warnings
from decimal import Decimal
from fractions import Fraction

import numpy as np
import pytest
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st

from mpcrl_lite.config import (
    BACKENDS,
    HOURS_PER_DAY,
    OPTIMIZERS,
    VALUE_FEATURES,
    ConfigWarning,
    CoordinationConfig,
    InputTypeError,
    LearningConfig,
    MPCConfig,
    SystemConfig,
    check_bool,
    check_choice,
    check_grid_bound,
    check_instance,
    check_int,
    check_real,
)

CONFIGS = (SystemConfig, MPCConfig, LearningConfig, CoordinationConfig)

# (config, field, a bad value, what the message must say is expected)
BAD = [
    (SystemConfig, "n", 0, "an integer >= 1"),
    (SystemConfig, "n", 2.0, "an integer >= 1, got float"),
    (SystemConfig, "alpha", 0.0, "a value in (0, inf)"),
    (SystemConfig, "noise_mean", math.nan, "a finite value in (-inf, inf)"),
    (SystemConfig, "noise_var", -0.1, "a value in [0, inf)"),
    (SystemConfig, "U_bar", 0, "a value in (0, inf)"),
    (SystemConfig, "P_bar", -1.0, "a value in (0, inf)"),
    (SystemConfig, "omega", (20.0,), "a pair (above, below) of weights >= 0, got 1 value(s)"),
    (SystemConfig, "omega", (20.0, -1.0), "a value in [0, inf)"),
    (SystemConfig, "omega_f", [20.0, 20.0], "a pair (above, below) of weights >= 0, got list"),
    (SystemConfig, "p", -1.0, "a value in [0, inf)"),
    (SystemConfig, "soc_low", 1.5, "a value in [0, 1]"),
    (SystemConfig, "soc_high", 0.05, "a value in [0.1, 1]"),
    (SystemConfig, "gamma", 0.0, "a value in (0, 1]"),
    (SystemConfig, "N", 0, "an integer >= 1"),
    (SystemConfig, "hours_per_day", 48, "an integer in [1, 24]"),
    (SystemConfig, "sample_time_h", 0.0, "a value in (0, inf)"),
    (SystemConfig, "sell_ratio", -0.5, "a value in [0, inf)"),
    (SystemConfig, "price_scale", math.inf, "a finite value in [0, inf)"),
    (SystemConfig, "soc0", 1.2, "a value in [0, 1]"),
    (MPCConfig, "tau", 0.0, "a value in (0, 1]"),
    (MPCConfig, "backend", "fast", "one of 'auto', 'ipopt', 'batch', 'kernel'"),
    (MPCConfig, "tol", 2.0, "a value in (0, 1]"),
    (MPCConfig, "max_iter", 0, "an integer >= 1"),
    (MPCConfig, "warm_start", 1, "True or False"),
    (MPCConfig, "polish", "no", "True or False"),
    (MPCConfig, "kkt_cond_max", 1.0, "a value in (1, inf)"),
    (MPCConfig, "forecast", "midnight", "one of 'paper', 'until_midnight'"),
    (LearningConfig, "step_size", -1.0, "a value in [0, inf)"),
    (LearningConfig, "months", "12", "an integer >= 1, got str"),
    (LearningConfig, "days_per_month", 0, "an integer >= 1"),
    (LearningConfig, "eval_draws", 0, "an integer >= 1"),
    (LearningConfig, "learner", "td", "one of 'dpg', 'q'"),
    (LearningConfig, "hessian", "exact", "one of 'none', 'approx', 'full'"),
    (LearningConfig, "newton_step", 0.0, "a value in (0, inf)"),
    (LearningConfig, "gradient", "exact", "one of 'critic', 'pathwise'"),
    (LearningConfig, "terminal_scale", -100.0, "a value in (0, inf)"),
    (LearningConfig, "reset_momentum_at_bounds", 1, "True or False"),
    (LearningConfig, "scale_to_prices", "yes", "True or False"),
    (LearningConfig, "step_limit", -1.0, "a value in [0, inf)"),
    (LearningConfig, "exploration_std", -0.1, "a value in [0, inf)"),
    (LearningConfig, "ridge", -1e-6, "a value in [0, inf)"),
    (LearningConfig, "value_features", "quadratic",
     "one of 'paper', 'paper+hour', 'hour', 'hour*paper'"),
    (LearningConfig, "exploration_bounds", "clip", "one of 'symmetric', 'radial', 'project'"),
    (LearningConfig, "exploration_margin", -0.1, "a value in [0, inf)"),
    (LearningConfig, "learn_constants", "yes", "True or False"),
    (LearningConfig, "optimizer", "rmsprop", "one of 'sgd', 'adam', 'natural'"),
    (LearningConfig, "grad_clip", 0.0, "a value in (0, inf)"),
    (LearningConfig, "tie_agents", 1, "True or False"),
    (LearningConfig, "natural_damping", -1.0, "a value in [0, inf)"),
    (LearningConfig, "step_warmup", -1, "an integer >= 0"),
    (LearningConfig, "step_decay", 2.5, "an integer >= 0, got float"),
    (LearningConfig, "max_policy_change", 0.0, "a value in (0, inf)"),
    (LearningConfig, "average_months", -2, "an integer >= 0"),
    (LearningConfig, "critic_months", 0, "an integer >= 1"),
    (LearningConfig, "critic_months", 25, "a value in [1, 24]"),
    (LearningConfig, "theta0", (0.1, float("nan")), "None or a theta's 10 n finite entries"),
    (LearningConfig, "theta0", "nominal", "None or a sequence of numbers"),
    (LearningConfig, "keep_well_posed", None, "True or False"),
    (LearningConfig, "alpha_min", 0.0, "a value in (0, inf)"),
    (LearningConfig, "seed", -1, "an integer >= 0"),
    (LearningConfig, "eval_every", -1, "an integer >= 0"),
    (LearningConfig, "eval_seed", 1.5, "an integer >= 0, got float"),
    (CoordinationConfig, "tol", 0.1, "a value in (0, 0.01]"),
    (CoordinationConfig, "max_iter", 0, "an integer >= 1"),
    (CoordinationConfig, "local_grid_factor", 5.0, "a value in [10, inf)"),
]


@pytest.mark.parametrize(
    "config, field, value, expected", BAD,
    ids=[f"{c.__name__}.{f}={v!r}" for c, f, v, _ in BAD],
)
def test_a_bad_value_names_the_field_the_value_and_the_range(config, field, value, expected):
    with pytest.raises(ValueError) as err:
        config(**{field: value})
    message = str(err.value)
    assert message.startswith(f"{field}="), message
    assert f"expected {expected}" in message, message
    assert len(message.splitlines()) == 1


def test_every_field_of_every_config_has_a_bad_value_above():
    for config in CONFIGS:
        covered = {f for c, f, _, _ in BAD if c is config}
        assert covered == {f.name for f in dataclasses.fields(config)}, config.__name__


# -- the issues of "every bad input gets one clear line" -----------------------------------
def test_numpy_scalars_are_stored_as_plain_python_numbers():
    system = SystemConfig(n=np.int64(3), P_bar=np.float32(1.5), omega=(np.float32(20), 20))
    learning = LearningConfig(seed=np.int64(0), months=np.int32(5), step_size=np.float16(0.5))
    mpc = MPCConfig(tau=np.float32(0.5), max_iter=np.uint8(50))
    coordination = CoordinationConfig(max_iter=np.int16(7))
    assert type(system.n) is int and type(system.P_bar) is float
    assert all(type(w) is float for w in system.omega)
    assert type(learning.seed) is int and type(learning.months) is int
    assert type(learning.step_size) is float and type(mpc.tau) is float
    assert type(mpc.max_iter) is int and type(coordination.max_iter) is int
    for config in (system, learning, mpc, coordination):
        text = json.dumps(config.to_dict())  # failed before: np.int64 is not JSON serialisable
        assert type(config).from_dict(json.loads(text)) == config
    # the values are the ones given
    assert system.P_bar == 1.5 and system == SystemConfig()
    assert learning == LearningConfig(months=5, step_size=0.5)


def test_python_ints_in_float_fields_are_stored_as_floats():
    system = SystemConfig(P_bar=2, soc0=1)
    assert type(system.P_bar) is float and type(system.soc0) is float
    assert system == SystemConfig(P_bar=2.0, soc0=1.0)


@pytest.mark.parametrize("field, choices", [("optimizer", OPTIMIZERS),
                                            ("value_features", VALUE_FEATURES)])
def test_an_array_in_a_choice_field_is_a_clear_error(field, choices):
    value = np.array(choices)
    with pytest.raises(ValueError, match=rf"^{field}=array\(.*expected one of .*got ndarray$"):
        LearningConfig(**{field: value})
    with pytest.raises(ValueError, match=r"^backend=.*expected one of 'auto'"):
        MPCConfig(backend=np.array(BACKENDS))


def test_hours_per_day_beyond_the_price_day_fails_at_construction():
    with pytest.raises(ValueError, match=r"^hours_per_day=48: expected an integer in \[1, 24\] "
                                         r"\(a day of the price data has 24 clock hours\)$"):
        SystemConfig(hours_per_day=48)
    assert SystemConfig(hours_per_day=HOURS_PER_DAY).hours_per_day == 24
    assert SystemConfig(hours_per_day=5).hours_per_day == 5


def test_huge_integers_are_refused_without_overflow():
    with pytest.raises(ValueError, match=r"^P_bar=.*expected a finite value in \(0, inf\)"):
        SystemConfig(P_bar=10**400)
    assert SystemConfig(n=10**400).n == 10**400  # n * U_bar overflowed in the grid check
    with pytest.warns(ConfigWarning, match=r"P_bar=1.5 >= n\*U_bar=1: the grid peak limit"):
        SystemConfig(n=1)


def test_coordination_config_lives_with_the_other_configs():
    from mpcrl_lite.config import CoordinationConfig as FromDecentralized

    assert FromDecentralized is CoordinationConfig
    config = CoordinationConfig(tol=1e-9, max_iter=np.int64(10))
    assert CoordinationConfig.from_dict(json.loads(json.dumps(config.to_dict()))) == config
    with pytest.raises(ValueError, match=r"unknown field\(s\) \['tolerance'\]"):
        CoordinationConfig.from_dict({"tolerance": 1e-9})
    assert config.replace(max_iter=3).max_iter == 3


# -- the shared validators -----------------------------------------------------------------
def test_check_real():
    assert check_real("x", 2) == 2.0 and type(check_real("x", 2)) is float
    assert check_real("x", Fraction(1, 4), 0.0, 1.0) == 0.25
    assert check_real("x", np.float32(0.5), 0.5, 1.0) == 0.5  # closed bounds
    with pytest.raises(ValueError, match=r"^x=0.5: expected a value in \(0.5, 1\)$"):
        check_real("x", 0.5, 0.5, 1.0, low_open=True, high_open=True)
    with pytest.raises(ValueError, match=r"^x=1.0: expected a value in \[0, 1\)$"):
        check_real("x", 1.0, 0.0, 1.0, high_open=True)
    for value in (True, "1.0", None, 1j, Decimal("1.0"), np.array([1.0]), [1.0]):
        with pytest.raises(InputTypeError, match=r"^x=.*: expected a real number in"):
            check_real("x", value)
    with pytest.raises(ValueError, match="finite"):
        check_real("x", -math.inf)
    with pytest.raises(ValueError, match="finite"):
        check_real("x", Fraction(10**400, 3))


def test_check_int():
    assert check_int("k", np.int64(3), 1) == 3 and type(check_int("k", np.int64(3), 1)) is int
    assert check_int("k", 24, 1, 24) == 24
    with pytest.raises(ValueError, match=r"^k=25: expected an integer in \[1, 24\] \(why\)$"):
        check_int("k", 25, 1, 24, note="why")
    with pytest.raises(ValueError, match=r"^k=5: expected an integer <= 4$"):
        check_int("k", 5, high=4)
    for value in (True, 3.0, "3", np.array(3), None):
        with pytest.raises(InputTypeError, match=r"^k=.*: expected an integer, got"):
            check_int("k", value)


def test_check_choice_bool_and_instance():
    assert check_choice("c", np.str_("adam"), OPTIMIZERS) == "adam"
    assert type(check_choice("c", np.str_("adam"), OPTIMIZERS)) is str
    with pytest.raises(ValueError, match=r"^c='Adam': expected one of 'sgd', 'adam', 'natural'$"):
        check_choice("c", "Adam", OPTIMIZERS)
    with pytest.raises(InputTypeError, match="got list"):
        check_choice("c", ["adam"], OPTIMIZERS)
    assert check_bool("b", False) is False
    for value in (0, 1, np.bool_(True), "True", None):
        with pytest.raises(InputTypeError, match=r"^b=.*: expected True or False"):
            check_bool("b", value)
    system = SystemConfig()
    assert check_instance("system", system, SystemConfig) is system
    with pytest.raises(InputTypeError, match=r"^system: expected a SystemConfig or MPCConfig, "
                                             r"got dict$"):
        check_instance("system", {}, (SystemConfig, MPCConfig))


def test_input_type_error_is_both_a_type_and_a_value_error():
    with pytest.raises(TypeError):
        check_int("k", "3")
    with pytest.raises(ValueError):
        check_int("k", "3")


def test_long_bad_values_are_shortened_in_messages():
    with pytest.raises(ValueError) as err:
        check_real("x", "y" * 10_000)
    assert len(str(err.value)) < 200


# -- fuzz: any value of any type either makes a valid config or one clear error --------------
_ANY = st.one_of(
    st.integers(min_value=-(10**400), max_value=10**400),
    st.integers(min_value=-3, max_value=40),
    st.floats(allow_nan=True, allow_infinity=True),
    st.floats(min_value=0.0, max_value=2.0),
    st.booleans(),
    st.none(),
    st.text(max_size=20),
    st.sampled_from(BACKENDS + OPTIMIZERS + VALUE_FEATURES),
    st.fractions(max_denominator=10**6),
    st.decimals(allow_nan=True),
    st.complex_numbers(max_magnitude=10.0),
    st.integers(-5, 50).map(np.int64),
    st.floats(0.0, 2.0, width=32).map(np.float32),
    st.booleans().map(np.bool_),
    st.lists(st.floats(0.0, 30.0), max_size=3).map(np.array),
    st.lists(st.floats(0.0, 30.0), max_size=3),
    st.tuples(st.floats(0.0, 30.0), st.floats(0.0, 30.0)),
    st.tuples(st.integers(-2, 30)),
    st.dictionaries(st.text(max_size=3), st.integers(), max_size=2),
    st.just(object()),
)


def _near_default(field: dataclasses.Field):
    """Values of the default's own type around it: mostly valid, sometimes just outside."""
    default = field.default
    if isinstance(default, bool):
        return st.booleans()
    if isinstance(default, int):
        return st.integers(default - 3, default + 3)
    if isinstance(default, float):
        return st.floats(-0.2, 1.5).map(lambda f: default * f if default else f)
    if isinstance(default, str):
        return st.sampled_from(BACKENDS + OPTIMIZERS + VALUE_FEATURES)
    if isinstance(default, tuple):
        return st.tuples(*[st.floats(-1.0, 2.0 * d) for d in default])
    return st.none() | st.floats(-1.0, 2.0)  # grad_clip: None or a number


def _plain(value):
    """Only plain Python values, as a config stores them."""
    if isinstance(value, tuple):
        return all(_plain(v) for v in value)
    return value is None or type(value) in (int, float, bool, str)


@pytest.mark.parametrize("config", CONFIGS, ids=lambda c: c.__name__)
@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(data=st.data())
def test_fuzz_a_config_is_valid_or_one_clear_error(config, data):
    fields = {f.name: f for f in dataclasses.fields(config)}
    names = list(fields)
    chosen = data.draw(st.lists(st.sampled_from(names), min_size=1, max_size=4, unique=True))
    kwargs = {}
    for n in chosen:  # three in four values near the default, the others of any type
        any_type = data.draw(st.integers(0, 3), label="any type") == 0
        kwargs[n] = data.draw(_ANY if any_type else _near_default(fields[n]), label=n)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ConfigWarning)
        try:
            made = config(**kwargs)
        except (ValueError, TypeError) as err:
            message = str(err)
            # the field, or one battery's entry of a per-battery field (alpha[1]=...)
            assert any(message.startswith((f"{n}=", f"{n}:", f"{n}[")) for n in names), message
            assert len(message.splitlines()) == 1, message
            event(f"refused: {type(err).__name__}")
            return
        event("valid")
        # valid: stored as plain values, JSON round trip gives the same config
        assert all(_plain(getattr(made, n)) for n in names), made
        again = config.from_dict(json.loads(json.dumps(made.to_dict())))
    assert again == made


# -- numbers the model cannot mean (config.RANGES) ------------------------------------------------
@pytest.mark.parametrize("make, message", [
    (lambda: SystemConfig(P_bar=1e308), r"P_bar=1e\+308: expected a value in \[1e-06, 1e\+12\]"),
    (lambda: check_grid_bound(SystemConfig(P_bar=31.0)),
     r"P_bar=31.0: expected a value in \(0, 30\]"),
    (lambda: check_grid_bound(SystemConfig(n=1, P_bar=10.5)),
     r"P_bar=10.5: expected a value in \(0, 10\]"),
    (lambda: SystemConfig(noise_var=1e308), r"noise_var=1e\+308: expected a value in \[0, 100\]"),
    (lambda: SystemConfig(noise_mean=-1e3), r"noise_mean=-1000.0: expected a value in \[-100, 100"),
    (lambda: SystemConfig(U_bar=1e9), r"U_bar=1000000000.0: expected a value in \[1e-06, 1000\]"),
    (lambda: SystemConfig(alpha=1e-300), r"alpha=1e-300: expected a value in \[1e-06, 10\]"),
    (lambda: SystemConfig(omega=(20.0, 1e300)), r"omega=\(20.0, 1e\+300\) \(entry 1e\+300\)"),
    (lambda: SystemConfig(N=1000), r"N=1000: expected a value in \[1, 168\]"),
    (lambda: SystemConfig(price_scale=1e6), r"price_scale=1000000.0: expected"),
    (lambda: MPCConfig(tau=1e-320), r"tau=1e-320: expected a value in \[1e-12, 1\]"),
    (lambda: MPCConfig(tol=1e-300), r"tol=1e-300: expected a value in \[1e-14, 1\]"),
    (lambda: MPCConfig(max_iter=10**9), r"max_iter=1000000000: expected"),
    (lambda: LearningConfig(step_size=1e300), r"step_size=1e\+300: expected a value in \[0, 1\]"),
    (lambda: LearningConfig(exploration_std=1e3), r"exploration_std=1000.0: expected"),
    (lambda: LearningConfig(max_policy_change=1e9), r"max_policy_change=1000000000.0: expect"),
])
def test_numbers_the_model_cannot_mean_are_refused_in_one_line(make, message):

    with pytest.raises(ValueError, match=message) as err:
        make()
    assert "\n" not in str(err.value) and "config.RANGES" in str(err.value)


def test_the_ranges_hold_the_defaults_and_the_papers_settings():
    from mpcrl_lite.config import PAPER_STEP_SIZE, PAPER_TAU, RANGES, check_ranges

    for section, config in (("system", SystemConfig()), ("mpc", MPCConfig.paper()),
                            ("learning", LearningConfig.paper())):
        check_ranges(section, config)
        assert set(RANGES[section]) <= {f.name for f in dataclasses.fields(config)}
    assert RANGES["mpc"]["tau"][0] <= PAPER_TAU and PAPER_STEP_SIZE <= 1.0
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ConfigWarning)
        check_grid_bound(SystemConfig(P_bar=30.0))  # 10 * n * U_bar: still accepted


def test_the_ranges_apply_to_every_entry_of_a_per_battery_value():
    from mpcrl_lite.config import check_ranges

    class PerBattery:  # a field given per battery, as an array
        noise_var = np.array([0.5, 0.5, 101.0])

    with pytest.raises(ValueError, match=r"noise_var=.* \(entry 101.0\): expected a value in "
                                         r"\[0, 100\]"):
        check_ranges("system", PerBattery())
    PerBattery.noise_var = np.array([0.5, 0.2, 100.0])
    check_ranges("system", PerBattery())


def test_an_integer_beyond_every_float_is_refused_by_its_range():
    """10**400 cannot become a float (OverflowError in numpy): still one clear line."""
    with pytest.raises(ValueError, match=r"^N=1000.*: expected a value in \[1, 168\]"):
        SystemConfig(N=10**400)
    with pytest.raises(ValueError, match=r"^P_bar=-1000.*: expected a finite value"):
        SystemConfig(P_bar=-(10**400))


def test_prices_the_model_cannot_mean_are_refused():
    from mpcrl_lite.config import PRICE_LIMIT
    from mpcrl_lite.system.prices import Prices

    buy = np.full((2, 24), 300.0)
    buy[1, 5] = 1e308
    with pytest.raises(ValueError, match=r"buy: price 1e\+308 at day 1, hour 5: expected "
                                         r"prices within \+-100000 per MWh"):
        Prices(buy)
    buy[1, 5] = -PRICE_LIMIT  # the limit itself, and negative prices, are prices
    Prices(buy)
    with pytest.raises(ValueError, match="within"):
        Prices(np.full((1, 24), 2e4)).scaled(10.0)


def test_a_bad_battery_entry_is_named_by_its_index():
    with pytest.raises(ValueError, match=r"^alpha\[0\]=0\.0") as err:
        SystemConfig(alpha=(0.0, 1 / 12, 1 / 12))
    assert len(str(err.value).splitlines()) == 1
