"""Every number of the experiment, and every choice the paper leaves open, in one place.

Four frozen dataclasses:

* :class:`SystemConfig` -- the battery system and the MPC's fixed structure (the paper's
  Table I).
* :class:`MPCConfig` -- how the MPC is solved (barrier parameter, back-end, tolerances).
* :class:`LearningConfig` -- the LSTD / DPG learning loop (step size, months, exploration,
  safeguards).
* :class:`CoordinationConfig` -- how the decentralized MPCs are coordinated on the grid limit
  (:mod:`mpcrl_lite.decentralized.learner`).

All of them validate themselves at construction and raise a :class:`ValueError` that names
the field, the value given and the range allowed, before any work starts. Numeric fields are
stored as plain Python ``int``/``float`` whatever was given (numpy scalars included), so a
config always serialises to JSON.

The validators behind them are the package's shared ones (:mod:`mpcrl_lite._util.validate`,
still importable from here): :func:`check_real`,
:func:`check_int`, :func:`check_choice`, :func:`check_bool` and :func:`check_instance`. Every
module checks its arguments with them, so every bad input reads the same way:
``"P_bar=-1.0: expected a value in (0, inf)"``.

Choices the paper leaves open (each is a field below, with the reason in its comment):

* **Start of day soc.** Table I says 0.5, the text says "the states start from 0.6 at the
  beginning of the day". We follow the text (``soc0 = 0.6``); the table value is one
  argument away.
* **Noise.** ``Delta ~ N(0, 0.5)``: the paper calls its second argument the variance, so the
  standard deviation is ``sqrt(0.5)``. Each agent draws independently.
* **Price unit.** The paper gives none. We use the Nord Pool unit NOK/MWh, with one unit of
  ``b`` or ``s`` meaning one MWh over the one-hour sampling time. With this scale the MPC's
  slack weight 20 and the penalty 1000 interact as the paper describes: the untrained MPC lets
  soc fall below 0.1 to earn money, and learning pushes it back up.
* **After midnight.** Every day starts again at ``soc0`` and lasts 24 hours. The MPC's
  12-hour horizon at a late hour reads on into the next day's prices; the month is repeated,
  so day 30 is followed by day 1.
* **24 or 30 parameters.** theta has 10 entries per agent (30 for n = 3), but the constants
  ``phi3`` and ``T3`` shift the MPC's cost without changing its solution, so the policy
  gradient with respect to them is zero. By default only the other 24 are learned
  (``LearningConfig.learn_constants = False``), which matches the paper's "24 parameters".
* **Barrier parameter.** The economic MPC is nearly bang-bang; solved exactly, its policy is
  not unique and its derivative is zero almost everywhere. We keep an interior-point barrier
  parameter ``tau > 0`` fixed, so the policy is the unique, smooth solution of the barrier
  problem and its KKT sensitivity is exact (``MPCConfig.tau``). Its value is a trade-off,
  measured on the paper's system: at ``tau = 1e-4`` batteries that sell together at the grid
  limit are split by the barrier alone, ``d pi / d theta`` reaches ~1e5 and the policy
  gradient is dominated by that tie-breaking (learning fails); at ``tau = 1`` the policy is
  smooth rather than bang-bang (4 % of the actions at theta0 within 0.05 of a constraint).
  The default ``tau = 0.1`` (in NOK, the unit of the cost) keeps 81 % of the actions at
  theta0 within 0.05 of a constraint, and the parameters learned with it give the same J when
  the MPC is then solved nearly exactly (``tau = 1e-4``, 85 % of the actions at a
  constraint).
* **Initial theta.** The paper does not list it. We start from the nominal model:
  ``theta_alpha = alpha``, ``theta_delta = alpha * noise_mean``, all cost corrections zero.
* **Exploration.** The paper adds "small random exploration" without a size. We use a
  Gaussian of std 0.2 MW (``LearningConfig.exploration_std``): the noise of the critic's
  estimate of the action gradient scales like ``1 / std``. With 0.1 or 0.05, one month of 30
  days is not enough: single batteries drift the wrong way and stay in the penalised zone
  (0 of 2 seeds learned with 0.1; with 0.1 and 60 days per month, 2 of 2 did). The paper does
  not say how the explored action respects the input bounds and the grid limit. Projecting
  ``pi + e`` onto them moves the mean of ``a - pi`` inwards wherever ``pi`` is near a bound
  (+0.04 MW in the first month), while the compatible critic assumes a zero mean: the state
  part of the cost then leaks into its weights. By default the exploration is an odd function
  of the Gaussian draw, hence zero-mean (``exploration_bounds='symmetric'``,
  :func:`mpcrl_lite.sim.exploration.bounded_exploration`): it slides along the grid faces and is
  shrunk just enough that ``pi + e`` and ``pi - e`` are both feasible; the grid limit is
  nearly active in 84 % of the hours, and there it keeps about half of the exploration where a
  radial shrink keeps 2-12 %. Recentring it away from the bounds (``exploration_margin``)
  changed nothing measurable once the batteries are tied (20 seeds, paired difference
  -1 +- 3 NOK/day), so it is off.
* **Critic features.** The paper's value baseline ``V(s) = Phi(s)' v`` uses
  ``Phi = [soc_i^2, soc_i, 1]``. A day is a 24-hour episode with time-varying prices, so the
  expected cost to go depends on the hour as much as on soc, which these features cannot
  represent; the LSTD fit of the compatible critic is then too noisy to learn from (0 of 2
  seeds with the other defaults). One indicator per hour instead of the constant
  (``'paper+hour'``, 2n + 24 features) fixes the variance; but at the LSTD fixed point the
  critic's action gradient also contains ``gamma alpha dV/dsoc`` at the next state, and the
  value of a unit of charge changes through the day (nothing is left of it at midnight). The
  paper's features once per hour (``'hour*paper'``, 24 (2n + 1) features) give every hour its
  own soc slope. The value of a unit of charge also depends on the day's prices, and so does
  the policy's sensitivity: a baseline whose slope is the same on every day of a month biases
  the critic's gradient towards the days' common part (an omitted variable). By default the
  baseline adds the soc times the highest and the mean buy price of the hours left in the day
  (``LearningConfig.value_features = 'hour*paper+price'``, 2n more features): on 20 fresh
  learning seeds it ended 8 NOK/day lower in the median, 29 in the worst seed, in the paper's
  class (6 and 105 with the rest-of-day MPC; ``benchmarks/README.md``). The price terms are
  fitted across the month's days: below :data:`PRICE_FEATURES_MIN_DAYS` (25) days a month the
  default falls back to ``'hour*paper'``, with which short months learn more reliably.
  ``'paper'`` keeps the paper's 2n + 1.
* **The gradient's source.** The critic's estimate, not the update, is most of what keeps the
  learner from its class's best theta: with the exact derivative of the simulated month's cost
  (``LearningConfig.gradient = 'pathwise'``, an extension that needs the model and the month's
  noise, never the default) the same Adam update, with a wider scale of the terminal weights
  (:data:`PATHWISE_TERMINAL_SCALE`), ends 9 NOK/day above the paper class's best theta found
  by search and 2 below the rest-of-day class's (medians over 20 fresh seeds), against 41 and
  27 above with the critic (20 and 10 fresh seeds; ``benchmarks/README.md``). The default
  stays the paper's model-free critic.
* **Shared parameters.** The three batteries are identical and play the same part in the
  cost, so the best causal policy treats them alike. Learning one parameter set per battery
  (the paper's 24 parameters) lets the first, noisiest months push a single battery into a
  corner (selling at its bound all day, its soc below 0.1) where its policy no longer
  responds to its parameters, and it stays there: 3 of 20 seeds with the earlier defaults.
  By default the gradient is averaged over the batteries (``LearningConfig.tie_agents``), so
  they keep one value per part (8 free parameters).
* **Update rule.** The paper's plain step ``theta -= 5e-8 grad J`` cannot serve parameters of
  such different units: the first gradient has a norm of ~1e8, almost all of it in
  theta_alpha, so one step throws theta_alpha to several units while the cost weights do not
  move. By default the step is Adam with a typical magnitude per part
  (:data:`mpcrl_lite.learning.dpg.DEFAULT_SCALE`), moving each entry by about 2 % of its magnitude per
  month at most (``optimizer='adam'``, ``step_size=0.02``; with 0.05 single batteries were
  pushed into the penalised zone for tens of months). The paper's rule is
  ``optimizer='sgd'``, ``step_size=PAPER_STEP_SIZE``. The natural gradient in the metric of
  the actions (``optimizer='natural'``: the critic's ``w`` itself, no per-part scales) was
  measured too: it learns, more slowly, and fails on some seeds (``benchmarks/README.md``).
* **Evaluation.** J of a learning month is noisy (+-200 from month to month: every month
  draws new noise and exploration). Each month the parameters in use are also evaluated on a
  fixed set of ``LearningConfig.eval_draws`` noise draws without exploration
  (``eval_every``, ``eval_seed``); that series (``History.J_eval``, the mean over the draws,
  with a 95 % confidence interval) shows the learning trend of the paper's Fig. 2.

With these defaults the 100-month run (30 days, n = 3) takes 7-10 s with the compiled
kernel back-end on a two-core machine when evaluated on one draw (about 40 s with the numpy
batch back-end; the default ten evaluation draws cost 1.6-2.1x the CPU time). On two sets of
20 learning seeds never used to choose these settings (200-219 and 500-519), evaluated on 10
noise draws of the month, the final J has a median of -217 and -219 NOK/day (worst -167 and
-125); every seed learns, 13-14 of 20 close 90 % of the gap between the nominal MPC (+1576)
and the best causal policy (J* = -401.5), and the median regret is 180-185 NOK/day. The rest
is mostly the policy class: the MPC's forecast reads on into the next day, whose prices do
not count. With a forecast that stops at midnight (``MPCConfig(forecast='until_midnight')``,
:mod:`mpcrl_lite.system.forecast`: an extension beyond the paper's class, never a default) the same
learner reaches medians of -314 and -311, every seed closes 90 % of the gap and the median
regret is 87-88. With the earlier defaults (projected exploration, one parameter set per
battery, ``'paper+hour'``) the median was -180 and 3 of the 20 seeds never learned
(J ~ 1250).

:meth:`LearningConfig.paper` and :meth:`MPCConfig.paper` give the paper's literal settings
(where it states them) for comparison.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import asdict, dataclass, fields, replace
from typing import Any

import numpy as np

# the shared validators, also importable from here (their home is mpcrl_lite._util.validate)
from ._util.validate import (
    InputTypeError,
    check_bool,
    check_choice,
    check_instance,
    check_int,
    check_real,
    show,
)

__all__ = [
    "BACKENDS",
    "EARLIER_BEHAVIOUR",
    "EUR_NOK_RATE",
    "EXPLORATION_BOUNDS",
    "FORECASTS",
    "GRADIENTS",
    "HESSIANS",
    "HOURS_PER_DAY",
    "LEARNERS",
    "OPTIMIZERS",
    "PAPER_EXPLORATION_STD",
    "PAPER_STEP_SIZE",
    "PAPER_TAU",
    "PATHWISE_TERMINAL_SCALE",
    "PER_BATTERY",
    "POLICY_CLASSES",
    "PRICE_FEATURES_MIN_DAYS",
    "PRICE_LIMIT",
    "PRICE_UNIT",
    "Q_STEP_LIMIT",
    "RANGES",
    "TERMINAL_SCALE",
    "VALUE_FEATURES",
    "VALUE_FEATURE_SETS",
    "ConfigWarning",
    "CoordinationConfig",
    "LearningConfig",
    "MPCConfig",
    "PolicyClass",
    "PriceFileConfig",
    "SystemConfig",
    "check_grid_bound",
    "check_ranges",
    "policy_class_configs",
    "policy_class_of",
]

#: Unit of every price in the project (see the module docstring for why).
PRICE_UNIT = "NOK/MWh"

#: NOK per EUR used to convert a price file in EUR/MWh to :data:`PRICE_UNIT` when no rate is
#: given (``--eur-rate``, ``load_prices(..., eur_rate=)``): the European Central Bank's euro
#: reference rate for the Norwegian krone, monthly average of November 2025 (11.7402; ECB
#: statistical data warehouse, series EXR.M.NOK.EUR.SP00.A). The monthly averages of 2025
#: ranged from about 11.5 to 11.9, so a run on another month should pass its own rate; the
#: rate used is recorded in the run's History and summary.json.
EUR_NOK_RATE = 11.7402

#: Clock hours in one day of price data; an episode (``SystemConfig.hours_per_day``) lasts at
#: most this long, since the price matrices (:class:`mpcrl_lite.system.prices.Prices`) are indexed by
#: day and clock hour.
HOURS_PER_DAY = 24


#: Prices (buying and selling, after ``price_scale``) must lie within +-PRICE_LIMIT per MWh:
#: the highest day-ahead prices ever cleared are a few thousand EUR/MWh (some 1e4 NOK/MWh),
#: so a larger number is a unit or typing mistake, and the MPC's cost is not solvable in
#: floating point far beyond it (``Prices`` refuses it).
PRICE_LIMIT = 1e5

#: Where each number of the configurations means something to the model, as
#: ``{section: {field: (low, high, why)}}`` (closed intervals). Every configuration refuses a
#: value outside in one line naming the value and the interval, element-wise for a field given
#: per battery (:func:`check_ranges`); a number inside may still be a poor choice, one outside
#: is a mistake (an overflow, a denormal, a unit off by powers of ten). ``P_bar`` has in
#: addition ``P_bar <= 10 * n * U_bar`` (ten times what all batteries together can draw: a
#: larger bound only means no bound; :func:`check_grid_bound`, where a user's system enters),
#: and the prices :data:`PRICE_LIMIT`.
RANGES: dict[str, dict[str, tuple[float, float, str]]] = {
    "system": {
        "alpha": (1e-6, 10.0, "soc moves by alpha * U_bar per hour at most"),
        "noise_mean": (-100.0, 100.0, "MW, a production-demand imbalance"),
        "noise_var": (0.0, 100.0, "MW^2; a std of 10 MW swamps any battery of the model"),
        "U_bar": (1e-6, 1e3, "MW per battery"),
        "P_bar": (1e-6, 1e12, "MW; for a user's system at most 10 * n * U_bar, see above"),
        "omega": (0.0, 1e6, "cost per unit of soc slack"),
        "omega_f": (0.0, 1e6, "cost per unit of terminal soc slack"),
        "p": (0.0, 1e6, "cost per unit of soc outside the band"),
        "N": (1, 168, "hours of horizon; a week at most"),
        "sample_time_h": (1e-3, 24.0, "hours"),
        "sell_ratio": (0.0, 10.0, "selling / buying price"),
        "price_scale": (0.0, 100.0, "multiplier on the price series"),
    },
    "mpc": {
        "tau": (1e-12, 1.0, "NOK; below 1e-12 the barrier is lost in rounding"),
        "tol": (1e-14, 1.0, "below 1e-14 the KKT residual is rounding noise"),
        "max_iter": (1, 10_000, "interior-point iterations of one solve"),
        "kkt_cond_max": (1.0, 1e20, "condition estimate"),
    },
    "learning": {
        "step_size": (0.0, 1.0, ("adam: relative move per update (1 = its whole magnitude); "
                                 "natural: RMS action change in MW; sgd: the gradient's "
                                 "multiplier (the paper's 5e-8)")),
        "exploration_std": (0.0, 10.0, "MW"),
        "exploration_margin": (0.0, 10.0, "MW"),
        "ridge": (0.0, 1.0, "relative Tikhonov term"),
        "natural_damping": (0.0, 1e3, "relative damping"),
        "max_policy_change": (0.0, 10.0, "MW"),
        "grad_clip": (0.0, 1e12, "norm of one update"),
        "alpha_min": (1e-9, 1.0, "smallest theta_alpha"),
        "critic_months": (1, 24, "months of samples in one critic fit"),
    },
}


def check_ranges(section: str, config: Any) -> None:
    """Refuse a field of ``config`` outside its :data:`RANGES` interval (``ValueError``, one
    line naming the field, the value and the interval), element by element where a field
    holds one value per battery (or a pair, like ``omega``). ``None`` (an optional field not
    set) passes."""
    for name, (low, high, why) in RANGES[section].items():
        value = getattr(config, name, None)
        if value is None:
            continue
        try:
            values = np.asarray(value, dtype=float).ravel()
        except OverflowError:  # an integer beyond any float (10**400): out of every range
            raise ValueError(f"{name}={show(value)}: expected a value in [{low:g}, {high:g}] "
                             f"({why}; config.RANGES)") from None
        bad = values[~((values >= low) & (values <= high))]
        if bad.size:
            shown = f"{name}={value!r}" if values.size == 1 else \
                f"{name}={show(value)} (entry {float(bad[0])!r})"
            raise ValueError(f"{shown}: expected a value in [{low:g}, {high:g}] ({why}; "
                             "config.RANGES)")


def check_grid_bound(system: SystemConfig) -> SystemConfig:
    """``system``, or a ``ValueError`` (one line) if ``P_bar > 10 * n * U_bar``: ten times what
    all batteries can draw together, a bound that means no bound (a typing or unit mistake).
    Checked where a user's system enters (the command line, sweep grids, every learner and
    :func:`~mpcrl_lite.mpc.backends.registry.make_solver` callers through
    :func:`mpcrl_lite.learning.learner.resolve_setup`), not by :class:`SystemConfig` itself: the
    per-battery MPCs of :mod:`mpcrl_lite.decentralized` make their grid row inert with a
    far larger bound on purpose."""
    U_bar = np.asarray(system.U_bar, dtype=float)  # one value, or one per battery
    reach = float(np.sum(U_bar)) if U_bar.ndim else float(system.n) * float(U_bar)
    top = np.max(np.asarray(system.P_bar, dtype=float))
    if top > 10 * reach:
        raise ValueError(
            f"P_bar={system.P_bar!r}: expected a value in (0, {10 * reach:g}] (10 * n * U_bar: "
            "ten times what all batteries can draw together; a larger bound means no bound; "
            "config.RANGES)")
    return system


class ConfigWarning(UserWarning):
    """A setting that is legal but probably not what the user meant."""


class _Config:
    """Shared helpers: ``replace`` with validation, and plain-dict round trips."""

    def _set(self, name: str, value: Any) -> None:
        """Store the validated, normalised ``value`` of a field (the dataclass is frozen)."""
        object.__setattr__(self, name, value)

    def replace(self, **changes: Any):
        """A copy with ``changes`` applied (validated like a new instance)."""
        unknown = set(changes) - {f.name for f in fields(self)}  # type: ignore[arg-type]
        if unknown:
            raise ValueError(
                f"unknown field(s) {sorted(unknown)} for {type(self).__name__}; "
                f"expected some of {[f.name for f in fields(self)]}"  # type: ignore[arg-type]
            )
        return replace(self, **changes)  # type: ignore[type-var]

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON-friendly dict (tuples become lists)."""
        return {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(self).items()}  # type: ignore[call-overload]

    @classmethod
    def from_dict(cls, data: dict[str, Any]):
        """Inverse of :meth:`to_dict`; unknown keys are an error, not silently dropped."""
        names = {f.name: f for f in fields(cls)}  # type: ignore[arg-type]
        unknown = set(data) - set(names)
        if unknown:
            raise ValueError(f"unknown field(s) {sorted(unknown)} for {cls.__name__}")
        kwargs = {k: tuple(v) if isinstance(v, list) else v for k, v in data.items()}
        return cls(**kwargs)


@dataclass(frozen=True)
class SystemConfig(_Config):
    """The battery system and the MPC's structure; defaults are the paper's Table I.

    **Per battery.** ``alpha``, ``U_bar``, ``soc0``, ``noise_mean``, ``noise_var`` and ``p``
    (:data:`PER_BATTERY`) take a scalar, the same for every battery (stored as a float), or
    one value per battery (a sequence of length ``n``, stored as a tuple; each value checked
    with the battery's index in the message, ``"alpha[1]=-0.1: expected ..."``): a site that
    mixes battery sizes. :meth:`battery` gives any of them as ``n`` values,
    :meth:`battery_groups` the groups of identical batteries.

    A grid bound at or above the batteries' total, ``P_bar >= n * U_bar``, can never bind
    (paper eq. 8 asks for less): it is legal and warns (:class:`ConfigWarning`).

    Prices are in :data:`PRICE_UNIT` (NOK/MWh); powers ``b``, ``s`` and ``Delta`` are in MW
    averaged over one hour, so one unit of power for one hour is one MWh.
    """

    n: int = 3
    """Number of batteries (agents)."""
    alpha: float | tuple[float, ...] = 1.0 / 12.0
    """True battery size factor in ``soc+ = soc + alpha (Delta + b - s)``; must be > 0
    (per battery: a scalar for all, or one value each, see the class docstring)."""
    noise_mean: float | tuple[float, ...] = 0.0
    """Mean of the production-demand noise ``Delta`` (per battery)."""
    noise_var: float | tuple[float, ...] = 0.5
    """Variance of ``Delta`` (Table I's ``N(0, 0.5)``; the std is ``sqrt(noise_var)``; per
    battery)."""
    U_bar: float | tuple[float, ...] = 1.0
    """Bound on each battery's buying and selling power, ``0 <= b, s <= U_bar`` (per
    battery)."""
    P_bar: float = 1.5
    """Grid peak bound: ``sum_i b_i <= P_bar`` and ``sum_i s_i <= P_bar``."""
    omega: tuple[float, float] = (20.0, 20.0)
    """MPC stage slack weights on (soc above 0.9, soc below 0.1)."""
    omega_f: tuple[float, float] = (20.0, 20.0)
    """MPC terminal slack weights."""
    p: float | tuple[float, ...] = 1000.0
    """True-cost penalty per unit of soc outside [soc_low, soc_high] (per battery)."""
    soc_low: float = 0.1
    """Lower edge of the safe soc band (penalised below)."""
    soc_high: float = 0.9
    """Upper edge of the safe soc band (penalised above)."""
    gamma: float = 0.99
    """Discount factor, in (0, 1]."""
    N: int = 12
    """MPC horizon in hours (prices are known about 12 hours ahead)."""
    hours_per_day: int = HOURS_PER_DAY
    """Length of one episode in hours, at most :data:`HOURS_PER_DAY` (the price data has 24
    clock hours a day); soc restarts at ``soc0`` every day."""
    sample_time_h: float = 1.0
    """Sampling time in hours (informational: the dynamics are written per sample)."""
    sell_ratio: float = 0.5
    """Selling price = ``sell_ratio`` x buying price (the paper uses 0.5). For a negative
    buying price (common in 2025, never in the paper's month) ``sell_ratio`` x price would be
    *above* the buying price, so that a battery could earn by buying and selling at once; the
    spread is kept instead: ``phi_s = phi_b - (1 - sell_ratio) |phi_b|``, i.e.
    ``(2 - sell_ratio) phi_b`` for ``phi_b < 0`` (``mpcrl_lite.system.prices.sell_prices``)."""
    price_scale: float = 1.0
    """Multiplier on the price series (1.0 keeps NOK/MWh; a classroom knob)."""
    soc0: float | tuple[float, ...] = 0.6
    """soc at the start of each day (text: 0.6; Table I says 0.5; per battery)."""

    def __post_init__(self) -> None:
        set_ = self._set
        set_("n", check_int("n", self.n, 1))
        set_("alpha", self._battery_values("alpha", 0.0, low_open=True))
        set_("noise_mean", self._battery_values("noise_mean"))
        set_("noise_var", self._battery_values("noise_var", 0.0))
        set_("U_bar", self._battery_values("U_bar", 0.0, low_open=True))
        set_("P_bar", check_real("P_bar", self.P_bar, 0.0, low_open=True))
        for name in ("omega", "omega_f"):
            value = getattr(self, name)
            expected = f"{name}={show(value)}: expected a pair (above, below) of weights >= 0"
            if not isinstance(value, tuple):
                raise InputTypeError(f"{expected}, got {type(value).__name__}")
            if len(value) != 2:
                raise ValueError(f"{expected}, got {len(value)} value(s)")
            set_(name, tuple(check_real(name, v, 0.0) for v in value))
        set_("p", self._battery_values("p", 0.0))
        set_("soc_low", check_real("soc_low", self.soc_low, 0.0, 1.0))
        set_("soc_high", check_real("soc_high", self.soc_high, self.soc_low, 1.0))
        set_("gamma", check_real("gamma", self.gamma, 0.0, 1.0, low_open=True))
        set_("N", check_int("N", self.N, 1))
        set_("hours_per_day", check_int(
            "hours_per_day", self.hours_per_day, 1, HOURS_PER_DAY,
            note=f"a day of the price data has {HOURS_PER_DAY} clock hours",
        ))
        set_("sample_time_h", check_real("sample_time_h", self.sample_time_h, 0.0, low_open=True))
        set_("sell_ratio", check_real("sell_ratio", self.sell_ratio, 0.0))
        set_("price_scale", check_real("price_scale", self.price_scale, 0.0))
        set_("soc0", self._battery_values("soc0", 0.0, 1.0))
        check_ranges("system", self)
        try:  # the most all batteries can buy (or sell) at once
            reach = (self.n * self.U_bar if isinstance(self.U_bar, float)
                     else math.fsum(self.U_bar))
        except OverflowError:  # an n beyond the float range
            reach = math.inf
        if self.P_bar >= reach:
            warnings.warn(
                f"P_bar={self.P_bar:g} >= n*U_bar={reach:g}: "
                "the grid peak limit can never bind",
                ConfigWarning,
                stacklevel=3,
            )

    def _battery_values(self, name: str, low: float | None = None, high: float | None = None,
                        *, low_open: bool = False) -> float | tuple[float, ...]:
        """A per-battery field validated: a scalar (every battery) as a float, or one value
        per battery as a tuple of floats, each in the range (errors name the battery)."""
        value = getattr(self, name)
        if isinstance(value, (str, bytes)) or not hasattr(value, "__len__"):
            return check_real(name, value, low, high, low_open=low_open)
        values = tuple(value)
        if len(values) != self.n:
            raise ValueError(f"{name}={show(value)}: expected a scalar or one value per battery "
                             f"(n={self.n}), got {len(values)} value(s)")
        return tuple(check_real(f"{name}[{i}]", v, low, high, low_open=low_open)
                     for i, v in enumerate(values))

    def battery(self, name: str) -> tuple[float, ...]:
        """The per-battery field ``name`` (one of :data:`PER_BATTERY`) as ``n`` values."""
        check_choice("name", name, PER_BATTERY)
        value = getattr(self, name)
        return value if isinstance(value, tuple) else (value,) * self.n

    def common(self, name: str, where: str) -> float:
        """The one value of the per-battery field ``name`` that ``where`` needs the same for
        every battery, else a one-line ``ValueError`` naming the field, the values and
        ``where``."""
        values = self.battery(name)
        if len(set(values)) > 1:
            raise ValueError(f"{name}={list(values)}: {where} expects one value for every "
                             "battery")
        return values[0]

    def battery_groups(self) -> tuple[int, ...]:
        """The group of every battery: batteries with equal values of every field of
        :data:`PER_BATTERY` share a group, numbered from 0 in order of first appearance
        (``(0, 0, 0)`` for identical batteries, ``(0, 1, 1)`` for one large and two equal
        small ones)."""
        keys = list(zip(*(self.battery(name) for name in PER_BATTERY), strict=True))
        first = {key: i for i, key in reversed(list(enumerate(keys)))}
        labels = {i: g for g, i in enumerate(sorted(set(first.values())))}
        return tuple(labels[first[key]] for key in keys)

    @property
    def identical(self) -> bool:
        """Every battery has the same parameters (every field of :data:`PER_BATTERY`)."""
        return all(not isinstance(getattr(self, name), tuple)
                   or len(set(getattr(self, name))) <= 1 for name in PER_BATTERY)

    @property
    def noise_std(self) -> float | tuple[float, ...]:
        """Standard deviation of ``Delta`` (per battery when ``noise_var`` is)."""
        if isinstance(self.noise_var, tuple):
            return tuple(math.sqrt(v) for v in self.noise_var)
        return math.sqrt(self.noise_var)


#: The fields of :class:`SystemConfig` that take one value per battery (or one for all).
PER_BATTERY = ("alpha", "noise_mean", "noise_var", "U_bar", "p", "soc0")


#: Solver back-ends known to :mod:`mpcrl_lite.mpc.backends.registry`.
BACKENDS = ("auto", "ipopt", "batch", "kernel")

#: What the MPC's price forecast covers (:attr:`MPCConfig.forecast`): ``'paper'``, the paper's
#: 12-hour window that reads on into the next day, and ``'until_midnight'``, an extension beyond
#: the paper whose forecast stops at the end of the day (:mod:`mpcrl_lite.system.forecast`).
FORECASTS = ("paper", "until_midnight")

#: A nearly exact barrier parameter: the policy is then practically the exact MPC's (the
#: paper does not give the barrier value of its interior-point solver).
PAPER_TAU = 1e-4
#: The paper's DPG step size (Table I's alpha = 5e-8), for ``optimizer='sgd'``.
PAPER_STEP_SIZE = 5e-8
#: A "small random exploration" in the paper's words (it gives no value): 0.05 MW.
PAPER_EXPLORATION_STD = 0.05


@dataclass(frozen=True)
class MPCConfig(_Config):
    """How the MPC is solved.

    The MPC is solved as the barrier problem ``min f - tau * sum(log(-h))`` subject to its
    equality constraints, with ``tau`` fixed: its solution is unique and smooth in the
    parameters, and for ``tau -> 0`` it tends to the exact (nearly bang-bang) MPC solution.
    """

    tau: float = 0.1
    """Fixed interior-point barrier parameter (in cost units, NOK); sensitivities are exact
    for this barrier problem. 0.1 keeps the policy near bang-bang and its sensitivities usable
    for learning (see the module docstring); :data:`PAPER_TAU` = 1e-4 is the nearly exact
    MPC."""
    backend: str = "auto"
    """'ipopt' (reference, IPOPT through nlpsol), 'batch' (numpy interior point over all days
    at once), 'kernel' (the same iteration compiled with numba) or 'auto' (kernel when the MPC
    is convex, else ipopt; the choice is logged)."""
    tol: float = 1e-10
    """Tolerance on the barrier problem's KKT residual."""
    max_iter: int = 200
    """Iteration limit of one solve."""
    warm_start: bool = True
    """Start each solve from the previous hour's solution (shifted)."""
    polish: bool = True
    """After the KKT residual reaches ``tol``, take one more Newton step (quadratic
    convergence: the solution to rounding, where the KKT sensitivities are exact). Without
    it a solve stops at ``tol``: about one iteration fewer, for evaluations that use the
    action only (``tune``'s search, :attr:`~mpcrl_lite.studies.tune.TuneSettings.search_tol`).
    The kernel and batch back-ends; the IPOPT back-end, which has its own stopping rule,
    refuses ``False`` when asked for by name."""
    kkt_cond_max: float = 1e12
    """KKT matrices with a larger condition estimate are reported as ill-conditioned."""
    forecast: str = "paper"
    """What the MPC's price forecast covers (:data:`FORECASTS`). ``'paper'`` (the default)
    is the paper's policy class: the ``N``-hour window reads on into the next day's prices.
    ``'until_midnight'`` is an **extension beyond the paper**, never a default: the forecast
    prices of the hours after the day's midnight are zero, since nothing after midnight
    counts in the day's cost (:mod:`mpcrl_lite.system.forecast`); the MPC, theta and the true cost
    are unchanged. Every learner, evaluation and baseline that builds the MPC from this
    config applies it (:func:`mpcrl_lite.system.forecast.forecast_prices`)."""

    def __post_init__(self) -> None:
        set_ = self._set
        set_("tau", check_real("tau", self.tau, 0.0, 1.0, low_open=True))
        set_("backend", check_choice("backend", self.backend, BACKENDS))
        set_("tol", check_real("tol", self.tol, 0.0, 1.0, low_open=True))
        set_("max_iter", check_int("max_iter", self.max_iter, 1))
        set_("warm_start", check_bool("warm_start", self.warm_start))
        set_("polish", check_bool("polish", self.polish))
        set_("kkt_cond_max", check_real("kkt_cond_max", self.kkt_cond_max, 1.0, low_open=True))
        set_("forecast", check_choice("forecast", self.forecast, FORECASTS))
        check_ranges("mpc", self)

    @classmethod
    def paper(cls, **changes: Any) -> MPCConfig:
        """The nearly exact MPC, ``tau = PAPER_TAU = 1e-4`` (the paper does not give a
        barrier value); ``changes`` override any field."""
        return cls(**{"tau": PAPER_TAU, **changes})


@dataclass(frozen=True)
class PolicyClass:
    """A named policy class of the centralized MPC: its horizon and its price forecast.

    The MPC's formulation and its parameters theta are the same in every class; a class sets
    only the two fields that say what the MPC plans over, :attr:`SystemConfig.N` (the hours of
    the horizon) and :attr:`MPCConfig.forecast` (the prices it sees). ``--policy-class NAME`` on
    the command line (``learn``, ``study``, ``tune``, ``baselines``, ``evaluate``, ``simulate``)
    sets both (:func:`policy_class_configs`); :func:`policy_class_of` names the class of a pair
    of configs, as recorded in a run's ``summary.json``. :data:`POLICY_CLASSES` lists them.
    """

    name: str
    """The name ``--policy-class`` takes."""
    N: int
    """The MPC's horizon in hours (:attr:`SystemConfig.N`)."""
    forecast: str
    """The MPC's price forecast (:attr:`MPCConfig.forecast`, one of :data:`FORECASTS`)."""
    extension: bool
    """True for a class beyond the paper's (never a default)."""
    about: str
    """What the class is, in one sentence."""


#: The policy classes by name (:class:`PolicyClass`). ``'paper'`` is the paper's MPC (eq. 9:
#: a 12-hour window that reads on into the next day), the default; the others are
#: **extensions beyond the paper**, labelled as such wherever they are reported:
#:
#: * ``'day_end'`` -- the paper's 12-hour MPC whose forecast prices are zero after the day's
#:   midnight (``MPCConfig(forecast='until_midnight')``, :mod:`mpcrl_lite.system.forecast`):
#:   the MPC knows that nothing after midnight counts in the day's cost.
#: * ``'rest_of_day'`` -- the same forecast with a 24-hour horizon: at hour ``h`` the MPC plans
#:   the whole rest of the day (``24 - h`` priced stages, then free stages after midnight), so
#:   that already at 00:00 it sees the evening's peak that the 12-hour window misses
#:   (measured in ``benchmarks/README.md``, "A policy class closer to J*").
POLICY_CLASSES: dict[str, PolicyClass] = {
    "paper": PolicyClass("paper", 12, "paper", False,
                         "the paper's MPC: a 12-hour forecast reading on into the next day"),
    "day_end": PolicyClass("day_end", 12, "until_midnight", True,
                           "extension: the 12-hour MPC with zero prices after midnight"),
    "rest_of_day": PolicyClass("rest_of_day", 24, "until_midnight", True,
                               "extension: a 24-hour MPC with zero prices after midnight, so "
                               "it plans the whole rest of the day"),
}


def policy_class_configs(name: str, system: SystemConfig | None = None,
                         mpc: MPCConfig | None = None) -> tuple[SystemConfig, MPCConfig]:
    """``system`` and ``mpc`` (default the defaults) with the horizon and the forecast of the
    policy class ``name`` (a key of :data:`POLICY_CLASSES`); every other field is kept."""
    name = check_choice("policy_class", name, tuple(POLICY_CLASSES))
    cls = POLICY_CLASSES[name]
    system = SystemConfig() if system is None else check_instance("system", system, SystemConfig)
    mpc = MPCConfig() if mpc is None else check_instance("mpc", mpc, MPCConfig)
    return system.replace(N=cls.N), mpc.replace(forecast=cls.forecast)


def policy_class_of(system: SystemConfig, mpc: MPCConfig) -> str | None:
    """The name of the policy class of ``system.N`` and ``mpc.forecast``
    (:data:`POLICY_CLASSES`), or None for a horizon and forecast no class names."""
    for cls in POLICY_CLASSES.values():
        if system.N == cls.N and mpc.forecast == cls.forecast:
            return cls.name
    return None


#: Names of the DPG update rules (:data:`mpcrl_lite.learning.update_rules.UPDATE_RULES`).
OPTIMIZERS = ("sgd", "adam", "natural")
#: The learners of the centralized MPC (:attr:`LearningConfig.learner`): ``'dpg'``, the
#: paper's deterministic policy gradient with the LSTD compatible critic, and ``'q'``, LSTD
#: Q-learning with the MPC itself as the action-value function (:mod:`mpcrl_lite.learning.qlearning`).
LEARNERS = ("dpg", "q")
#: Where the policy gradient of ``learner='dpg'`` comes from (:attr:`LearningConfig.gradient`):
#: ``'critic'``, the paper's compatible critic fitted by LSTD from explored actions, or
#: ``'pathwise'``, the exact derivative of the simulated month's cost on its noise
#: (:mod:`mpcrl_lite.learning.pathwise`; an extension that needs the model).
GRADIENTS = ("critic", "pathwise")
#: Adam's typical magnitude of the terminal weights T1, T2, T3 with the critic's gradient
#: (:attr:`LearningConfig.terminal_scale`; that of ``mpcrl_lite.learning.dpg.DEFAULT_SCALE``).
TERMINAL_SCALE = 100.0
#: The same with ``gradient='pathwise'``: chosen on the seeds 4000-4002 of the paper's class
#: (learner gap 8, 6, 5 NOK/day against 28-31 with 100), checked on 4000-4009 of the
#: rest-of-day class (median gap -2.3 against 1.0 with 100) and judged on 5000-5019 in both
#: (``benchmarks/README.md``).
PATHWISE_TERMINAL_SCALE = 3000.0
#: The ``LearningConfig.step_limit`` to use with the Q-learner (``--learner q --step-limit 5``):
#: no entry of theta moves by more than 5 of its typical magnitudes in one Newton step. On the
#: shipped month (fresh seeds 7000-7009, 100 months, without a limit) the 4 runs that learned
#: never stepped farther than 3.4 of them, while each of the 6 that collapsed (every MPC
#: failing, J_eval stuck at +266) ran away with steps of 10 to 10^10 of them first
#: (``benchmarks/README.md``).
Q_STEP_LIMIT = 5.0
#: The curvature of a Q-learning update (:attr:`LearningConfig.hessian`): ``'none'`` (a
#: first-order step with ``optimizer``), ``'approx'`` (Gauss-Newton) or ``'full'``.
HESSIANS = ("none", "approx", "full")
#: Feature sets of the critic's value baseline by name, with a short description
#: (built by :func:`mpcrl_lite.learning.lstd.value_features`).
VALUE_FEATURE_SETS: dict[str, str] = {
    "paper": "the paper's [soc_i^2, soc_i, 1]",
    "paper+hour": "soc_i^2, soc_i and one indicator per hour",
    "hour": "one indicator per hour of the day",
    "hour*paper": "the paper's [soc_i^2, soc_i, 1] for each hour of the day",
    "hour*paper+price": ("those, and soc_i times the highest and the mean buy price of the "
                         "hours left in the day"),
}
#: Their names, the values ``LearningConfig.value_features`` takes.
VALUE_FEATURES = tuple(VALUE_FEATURE_SETS)
#: Days per month from which ``LearningConfig(value_features=None)`` (the default) takes the
#: price terms (``'hour*paper+price'``); below, ``'hour*paper'``.
PRICE_FEATURES_MIN_DAYS = 25
#: How the exploration respects the input bounds and the grid limit
#: (:class:`mpcrl_lite.sim.exploration.GaussianExploration`).
EXPLORATION_BOUNDS = ("symmetric", "radial", "project")
#: What runs did before a field of :class:`LearningConfig` existed: a saved config without
#: the field reads back with this value (:meth:`LearningConfig.from_dict`), so a resumed run
#: goes on as it started. ``terminal_scale`` is also what :meth:`LearningConfig.to_dict`
#: leaves out (at 100, whatever the gradient), so a pathwise run with the critic's scale reads
#: back as it ran, not with the pathwise default.
EARLIER_BEHAVIOUR: dict[str, Any] = {
    "eval_draws": 1,
    "exploration_bounds": "project",
    "scale_to_prices": False,
    "terminal_scale": TERMINAL_SCALE,
    "tie_agents": False,
    "value_features": "hour*paper",
}


@dataclass(frozen=True)
class LearningConfig(_Config):
    """The LSTD / DPG learning loop (paper Section III and its simulation section).

    The defaults are the settings that make the paper's claims reproduce (see the module
    docstring); :meth:`paper` gives the paper's literal rule for comparison.
    """

    step_size: float = 0.02
    """DPG step size. With ``optimizer='adam'`` (default) a relative move per update: each
    learnable entry moves by at most about ``step_size`` times its typical magnitude
    (:data:`mpcrl_lite.learning.dpg.DEFAULT_SCALE`). With ``'sgd'`` the multiplier of the gradient (the
    paper's alpha = 5e-8, :data:`PAPER_STEP_SIZE`)."""
    months: int = 100
    """Number of learning steps; one update per month."""
    days_per_month: int = 30
    """Days simulated in parallel each month; their average approximates expectations."""
    exploration_std: float = 0.2
    """Std of the Gaussian noise added to the MPC action (kept within the input bounds and
    the grid limit as ``exploration_bounds`` says). The paper gives no value; with 0.05 or
    0.1 the critic's action gradient is too noisy to learn from a month (its noise scales
    like 1 / std)."""
    exploration_bounds: str = "symmetric"
    """How the explored action respects the input bounds and the grid limit
    (:func:`mpcrl_lite.sim.exploration.bounded_exploration`). ``'symmetric'`` slides the
    exploration along the grid faces it could reach, clips each entry to the distance of the
    policy's action to its nearer bound and shrinks the vector until both ``pi + e`` and
    ``pi - e`` are feasible: the map is odd in ``e``, so the applied exploration keeps a zero
    mean, which the compatible critic assumes. ``'project'`` (the closest feasible action to
    ``pi + e``, the behaviour before this option) shifts the mean inwards near a bound
    (+0.04 MW in the first month at std 0.2) and biases the critic; ``'radial'`` shrinks the
    whole vector (zero mean too, but little is left where the grid limit is active)."""
    exploration_margin: float = 0.0
    """In MW: the exploration is centred on the policy's action pulled this far away from
    the input bounds and the grid limits (:func:`mpcrl_lite.sim.exploration.exploration_center`),
    and the critic's compatible features use that centre. A battery whose action sits at a
    bound then still explores both ways with zero mean. 0 (the default) centres on the
    action itself; 0.2 made no measurable difference with tied batteries. Needs
    ``exploration_bounds`` other than ``'project'``; a record simulated with a margin must be
    learned from with the same margin (:meth:`mpcrl_lite.learning.experiment.Experiment.learning_step`
    reads it from this config)."""
    ridge: float = 1e-6
    """Ridge (Tikhonov) term of the LSTD normal equations, relative to their scale."""
    value_features: str | None = None
    """Features of the critic's value baseline: ``'paper'`` is the paper's
    ``[soc_i^2, soc_i, 1]``; ``'paper+hour'`` replaces the constant by one indicator per hour
    of the day (the cost to go of a 24-hour day depends on the hour); ``'hour'`` keeps only
    the indicators; ``'hour*paper'`` is the paper's features once per hour, so that the soc
    slope of the value, which enters the critic's action gradient, may change through the
    day; ``'hour*paper+price'`` adds the soc times the highest and the mean buy price of the
    hours left in the day, so that the slope also follows the day's prices
    (:mod:`mpcrl_lite.learning.lstd`; a run resumed keeps the features it started with).
    ``None`` (the default) is resolved when the config is made: ``'hour*paper+price'`` for
    months of at least :data:`PRICE_FEATURES_MIN_DAYS` days, else ``'hour*paper'``: the price
    terms are fitted across the month's days, and with fewer days they made learning fail
    (10 days a month: 5 of 6 seeds still above J = +1000 after 40 months, against 2 of 6 with
    ``'hour*paper'``; 20 days: 1 of 6 against none; 25 and 28 days: none, and lower medians
    than ``'hour*paper'``). ``replace`` of a config made with ``None`` resolves it again."""
    learn_constants: bool = False
    """Also update phi3 and T3 (their policy gradient is always zero)."""
    optimizer: str = "adam"
    """'adam' (per-part scaled Adam, the default), 'sgd' (the paper's plain gradient step) or
    'natural' (the natural gradient in the metric of the actions, normalised so that
    ``step_size`` is the RMS change of the action in MW; :mod:`mpcrl_lite.learning.update_rules`)."""
    grad_clip: float | None = None
    """If set, rescale each update so that ||step|| <= grad_clip."""
    tie_agents: bool = True
    """Learn one value of each part of theta for all *identical* batteries: the gradient is
    averaged over the agents of each group of identical batteries
    (:meth:`SystemConfig.battery_groups`: equal values of every per-battery field) before the
    update, so batteries that start alike stay alike. The batteries of the default
    :class:`SystemConfig` are identical, and so is the role of each in the cost, so the best
    causal policy treats them alike; tying them triples the data behind each parameter and
    rules out one battery drifting alone into a corner where its policy no longer responds
    (see the module docstring). On a mixed site only equal batteries are tied: with one large
    and two small batteries the large one learns its own parameters and the two small ones
    share theirs; batteries that all differ learn each their own. False learns every
    battery's own (the paper's 24 parameters; :meth:`paper`)."""
    natural_damping: float = 1e-3
    """``optimizer='natural'`` only: relative damping ``lambda`` of the metric,
    ``(F + lambda diag F)^-1 g`` (:func:`mpcrl_lite.learning.update_rules.natural_direction`)."""
    step_warmup: int = 0
    """Months of a linear warm-up of the step size, ``step_size * min(1, t / step_warmup)``
    at update ``t``: the first gradients are the noisiest relative to what they teach, and
    Adam's first directions are close to their signs whatever their noise; 0 starts at the
    full step size."""
    step_decay: int = 0
    """Months ``T`` of a harmonic decay of the step size, ``step_size / (1 + (t - 1) / T)``
    at update ``t`` (it has halved after ``T`` updates); 0 keeps it constant."""
    max_policy_change: float | None = None
    """If set, a trust region on the change of the policy: each update is shrunk so that the
    RMS change of the action it causes to first order, ``sqrt(step' F step)`` with
    ``F = mean(grad_pi grad_pi')`` of the month, is at most this many MW."""
    average_months: int = 0
    """If > 0, the parameters in use are an exponential average of the optimizer's raw
    iterates over about this many months (the running mean for the first ones): primal
    (Polyak) averaging, which damps the month-to-month noise of theta. 0 uses the raw
    iterates (the paper)."""
    keep_well_posed: bool = True
    """Project theta after each update: theta_alpha >= alpha_min and phi1, T1 >= 0 (the MPC
    then stays a convex QP with a unique solution)."""
    alpha_min: float = 1e-3
    """Smallest theta_alpha allowed by the projection."""
    seed: int = 0
    """Seed of every random draw of the learning months (noise, exploration)."""
    eval_every: int = 5
    """Evaluate the parameters in use every ``eval_every`` months (and in the last month):
    ``eval_draws`` months on fixed noise draws, without exploration and sensitivities
    (recorded as ``History.J_eval``). 0 turns the evaluation off. An evaluation of one draw
    costs about as much as a learning month, of ``eval_draws`` draws about that many times
    as much (one batched closed loop); 1 gives the smoothest learning curve."""
    eval_seed: int = 20201101
    """Seed of the fixed evaluation noise (independent of ``seed``, so every run and every
    month is evaluated on the same draws)."""
    eval_draws: int = 10
    """Independent noise draws of every evaluation, each a month of ``days_per_month`` days
    (common random numbers: the same draws, derived from ``eval_seed``, for every month and
    every policy; draw 0 is the single draw of runs made before this field existed).
    ``History.J_eval`` is the mean of the draws' J and ``J_eval_ci_low``/``_high`` its 95 %
    confidence interval over the draws. Files without the field were written with 1."""

    learner: str = "dpg"
    """Which learner updates theta (:data:`LEARNERS`): ``'dpg'``, the paper's deterministic
    policy gradient with the LSTD compatible critic, or ``'q'``, LSTD Q-learning with the
    MPC as the action-value function (the TD errors of the month's transitions fitted by the
    MPC's own Q; :mod:`mpcrl_lite.learning.qlearning`). The Q learner also learns the level
    of Q (``T3``, one value shared by the batteries; ``phi3`` stays), whatever
    ``learn_constants`` says, and does not support
    ``optimizer='natural'`` or ``max_policy_change`` (both need the policy's sensitivity)."""
    hessian: str = "approx"
    """``learner='q'`` only (:data:`HESSIANS`): ``'none'`` is a first-order step with
    ``optimizer`` on the TD gradient; ``'approx'`` (the default) and ``'full'`` are Newton
    steps ``theta - step_size H^-1 g`` with the Gauss-Newton ``H = mean(dQ dQ')`` or the full
    Hessian of the TD loss ``mean(dQ dQ' - delta d2Q)``, made positive definite by adding a
    multiple of the identity (Nocedal & Wright, Algorithm 3.3), of the length
    ``newton_step`` (``step_size`` is the first-order step's). A ``to_dict`` of a DPG
    config leaves the Q-learning fields out (files of DPG runs read as before they existed)."""
    newton_step: float = 0.3
    """``learner='q'`` with ``hessian`` other than ``'none'``: the fraction of the
    (regularised) Newton step taken per month. Measured on the paper's system over 20 months
    (seed 0): 0.1 learns steadily but slowly, 0.3 reaches the DPG's level of J_eval, 1.0
    (the full step) throws theta where the MPC no longer solves; the ``'full'`` Hessian is
    less stable than Gauss-Newton at the same step."""
    step_limit: float = 0.0
    """The largest move of any learnable entry of theta in one update, in units of its
    typical magnitude (Adam's scale: :data:`mpcrl_lite.learning.dpg.DEFAULT_SCALE`,
    ``terminal_scale``, times the price level of ``scale_to_prices``); a longer step is
    shortened, its direction kept, and the update's info says so (``step_limited``). 0 (the
    default) sets no limit. Adam moves an entry by about ``step_size`` of its scale, so the
    limit matters for the Q-learner's Newton steps, which run away on some seeds without it:
    use :data:`Q_STEP_LIMIT` (5) there. It is not the Q-learner's default because notebook 08
    shows what happens without it. ``to_dict`` leaves out 0 (files read as before the
    field)."""
    gradient: str = "critic"
    """``learner='dpg'`` only (:data:`GRADIENTS`): ``'critic'`` (the default, the paper's
    method) estimates the policy gradient with the compatible critic fitted by LSTD from the
    month's explored actions. ``'pathwise'`` is an **extension beyond the paper** that needs
    what a real battery does not have, the model's derivatives and the month's noise: the
    month is simulated without exploration and the gradient is the exact derivative of its
    discounted cost in theta, carried through the closed loop
    (:mod:`mpcrl_lite.learning.pathwise`). Its learner does what the paper's would do with an
    exact critic, so the two split the learner's part of the regret into the critic's error
    and what the step rule leaves. It does not support ``optimizer='natural'`` or
    ``max_policy_change`` (both use the critic's sensitivities of the explored month). A
    ``to_dict`` with ``'critic'`` leaves the field out (files read as before it existed)."""
    terminal_scale: float | None = None
    """Adam's typical magnitude of the terminal cost weights ``T1, T2, T3`` (NOK per unit of
    soc or soc^2, times ``SystemConfig.price_scale``; :data:`mpcrl_lite.learning.dpg.DEFAULT_SCALE`
    has the other parts). ``None`` (the default) is resolved when the config is made:
    :data:`TERMINAL_SCALE` (100) with ``gradient='critic'``, :data:`PATHWISE_TERMINAL_SCALE`
    (3000) with ``'pathwise'``. With the exact gradient the paper's class learns a terminal
    weight of about 1000 (its best theta found by search: 477), which Adam's pace at 100 does
    not reach in 100 months; with the critic's noisy estimate a wider scale gained nothing on
    fresh seeds (``benchmarks/README.md``). ``replace`` of a config made with ``None``
    resolves it again; ``to_dict`` leaves out the value 100 (files read as before)."""
    reset_momentum_at_bounds: bool = False
    """With ``keep_well_posed``: where the projection holds an entry at its bound (phi1, T1 at
    0, theta_alpha at ``alpha_min``), the update rule's first moment of that entry is set to
    zero, so that Adam's momentum does not keep pushing it into the bound after the gradient
    has turned. It frees seed 4007 of the default learner, which stayed at J_eval +1788 for
    100 months with both curvature weights held at 0 (with the reset: -213); on 20 other
    fresh seeds (5000-5019) it changed the final J_eval by -2.3 +- 2.2 NOK/day (paired, s.e.),
    better on 12 of 20, so it stays off by default and the results keep their History
    (``benchmarks/README.md``). On a month nothing was chosen on (October 2020, NO3) with the
    shipped month's step scales the collapse struck 5 of 20 seeds of the default learner and
    the reset freed 3 of them (median final J_eval -608.8 against -535.4); with the month's
    own step scales (``scale_to_prices``, the default for a price file) it struck 3 and the
    reset did not help (5 stuck, median -589.0 against -610.8). ``to_dict`` leaves out
    ``False``."""
    scale_to_prices: bool | None = None
    """Adam's typical magnitudes of the cost parts (:data:`mpcrl_lite.learning.dpg.DEFAULT_SCALE`
    and ``terminal_scale``) are set for the shipped month's price level (mean buying price
    :data:`mpcrl_lite.learning.dpg.REFERENCE_PRICE`, 56.3 NOK/MWh). With True they are
    multiplied by the level of the learning month's own prices instead (their mean buying
    price over that one; :func:`mpcrl_lite.learning.dpg.price_level`), so that a price
    correction or a soc weight moves by the same fraction of its natural size whatever the
    month's prices (``SystemConfig.price_scale`` is then part of that level); with False
    they are multiplied by ``SystemConfig.price_scale`` only. ``None`` (the default) is True
    for prices read from a file (``--prices``) and False for the shipped month, whose level is
    the reference, and for price arrays given directly; every learner resolves it when it is
    built and records the result. Measured on two months nothing was chosen on (October and
    December 2020, NO3, price levels 2.32 and 2.68, 20 new seeds each): the pathwise learner's
    paired gap to its class's best fell in four of six class-months (October's rest-of-day
    class from 13.1 to 3.8 NOK/day, its regret from 33.1 to 23.9) and the critic's median
    final J_eval improved from -535.4 to -610.8 (``benchmarks/README.md``). ``to_dict``
    leaves out ``False`` (files read as before the field: :data:`EARLIER_BEHAVIOUR`)."""
    critic_months: int = 1
    """``gradient='critic'`` of the centralized DPG learner only: the compatible critic of each
    update is fitted by LSTD on the samples of the last ``critic_months`` months together
    (the month just run and the ones before it, each sample with the policy, sensitivity and
    exploration of its own month), and the gradient is averaged over the same samples. 1 (the
    default, the paper's rule) fits each month on its own 720 samples. Measured on the paper's
    class (``benchmarks/README.md``): 4 months lowered the learner's gap to its class's best
    on 20 seeds nothing was chosen on (5000-5019: median final J_eval -233.6 against -224.7,
    worst -195.7 against -151.9, better on 14 of 20), and 8 months raised it (the older
    months' samples were taken by a policy the updates have moved away from). In the
    rest-of-day class (5000-5019) 4 months lowered the median gap from 15.1 to 10.7 but not
    the worst seeds, one of which lost 9.4 % of the nominal -> J* gap late. A run keeps the
    earlier months' samples in its checkpoint (``critic.npz``), so a resumed run learns as an
    uninterrupted one. ``to_dict`` leaves out 1 (files read as before the field)."""
    theta0: tuple[float, ...] | None = None
    """Where the learning starts: ``None`` (the default) is the nominal model's theta
    (:meth:`mpcrl_lite.theta.Theta.nominal`, the paper's start); otherwise a theta's entries in
    the order of :meth:`~mpcrl_lite.theta.Theta.to_vector` (``10 n`` finite numbers), e.g. a
    class's best found by ``tune`` on another month or the end of an earlier run (``learn/study
    --theta0 SOURCE``, :func:`mpcrl_lite.cli.inputs.read_theta`). Started at November's
    class's best, the pathwise learner on September 2020 ended a median -0.1 (day end) and
    1.8 (paper) NOK/day from September's own class best on the same draws, where from the
    nominal start it ended 11.3 and 13.5 above (README, "Months never used to choose
    anything"). The length is checked against ``SystemConfig.n`` when a learner is built;
    ``to_dict`` leaves out ``None`` (files read as before the field)."""

    def __post_init__(self) -> None:
        set_ = self._set
        if self.theta0 is not None:
            try:
                start = tuple(float(x) for x in self.theta0)
            except (TypeError, ValueError):
                raise ValueError(f"theta0={self.theta0!r}: expected None or a sequence of "
                                 "numbers (a theta's entries, Theta.to_vector)") from None
            if not start or not all(math.isfinite(x) for x in start):
                raise ValueError(f"theta0={self.theta0!r}: expected None or a theta's 10 n "
                                 f"finite entries (Theta.to_vector); {len(start)} entries, "
                                 "not all finite")
            set_("theta0", start)
        set_("step_size", check_real("step_size", self.step_size, 0.0))
        set_("months", check_int("months", self.months, 1))
        set_("days_per_month", check_int("days_per_month", self.days_per_month, 1))
        set_("exploration_std", check_real("exploration_std", self.exploration_std, 0.0))
        set_("exploration_bounds",
             check_choice("exploration_bounds", self.exploration_bounds, EXPLORATION_BOUNDS))
        set_("exploration_margin", check_real("exploration_margin", self.exploration_margin,
                                              0.0))
        if self.exploration_margin and self.exploration_bounds == "project":
            raise ValueError(
                f"exploration_margin={self.exploration_margin!r} with exploration_bounds="
                "'project': the margin centres a zero-mean exploration; expected 0 or "
                "exploration_bounds='symmetric' or 'radial'"
            )
        set_("ridge", check_real("ridge", self.ridge, 0.0))
        auto = self.value_features is None
        if auto:
            set_("value_features", "hour*paper+price"
                 if self.days_per_month >= PRICE_FEATURES_MIN_DAYS else "hour*paper")
        object.__setattr__(self, "_auto_value_features", auto)
        set_("value_features", check_choice("value_features", self.value_features, VALUE_FEATURES))
        set_("learn_constants", check_bool("learn_constants", self.learn_constants))
        set_("optimizer", check_choice("optimizer", self.optimizer, OPTIMIZERS))
        if self.grad_clip is not None:
            set_("grad_clip", check_real("grad_clip", self.grad_clip, 0.0, low_open=True))
        set_("tie_agents", check_bool("tie_agents", self.tie_agents))
        set_("natural_damping", check_real("natural_damping", self.natural_damping, 0.0))
        set_("step_warmup", check_int("step_warmup", self.step_warmup, 0))
        set_("step_decay", check_int("step_decay", self.step_decay, 0))
        if self.max_policy_change is not None:
            set_("max_policy_change", check_real("max_policy_change", self.max_policy_change,
                                                 0.0, low_open=True))
        set_("average_months", check_int("average_months", self.average_months, 0))
        set_("keep_well_posed", check_bool("keep_well_posed", self.keep_well_posed))
        set_("alpha_min", check_real("alpha_min", self.alpha_min, 0.0, low_open=True))
        set_("seed", check_int("seed", self.seed, 0))
        set_("eval_every", check_int("eval_every", self.eval_every, 0))
        set_("eval_seed", check_int("eval_seed", self.eval_seed, 0))
        set_("eval_draws", check_int("eval_draws", self.eval_draws, 1))
        set_("learner", check_choice("learner", self.learner, LEARNERS))
        set_("hessian", check_choice("hessian", self.hessian, HESSIANS))
        set_("newton_step", check_real("newton_step", self.newton_step, 0.0, low_open=True))
        set_("step_limit", check_real("step_limit", self.step_limit, 0.0))
        set_("reset_momentum_at_bounds", check_bool("reset_momentum_at_bounds",
                                                    self.reset_momentum_at_bounds))
        if self.scale_to_prices is not None:
            set_("scale_to_prices", check_bool("scale_to_prices", self.scale_to_prices))
        set_("gradient", check_choice("gradient", self.gradient, GRADIENTS))
        auto_scale = self.terminal_scale is None
        if auto_scale:
            set_("terminal_scale", PATHWISE_TERMINAL_SCALE if self.gradient == "pathwise"
                 else TERMINAL_SCALE)
        object.__setattr__(self, "_auto_terminal_scale", auto_scale)
        set_("terminal_scale", check_real("terminal_scale", self.terminal_scale, 0.0,
                                          low_open=True))
        if self.gradient == "pathwise" and (self.learner != "dpg" or self.optimizer == "natural"
                                            or self.max_policy_change):
            raise ValueError(
                f"gradient='pathwise' with learner={self.learner!r}, optimizer="
                f"{self.optimizer!r}, max_policy_change={self.max_policy_change!r}: the "
                "pathwise gradient is the policy gradient's and has no metric of explored "
                "actions; expected learner 'dpg', optimizer 'adam' or 'sgd' and no "
                "max_policy_change")
        set_("critic_months", check_int("critic_months", self.critic_months, 1))
        if self.critic_months > 1 and (self.learner != "dpg" or self.gradient != "critic"):
            raise ValueError(
                f"critic_months={self.critic_months!r} with learner={self.learner!r}, "
                f"gradient={self.gradient!r}: only the compatible critic is fitted on months of "
                "samples; expected critic_months=1 or learner 'dpg' with gradient 'critic'")
        if self.learner == "q" and (self.optimizer == "natural" or self.max_policy_change):
            raise ValueError(
                f"learner='q' with optimizer={self.optimizer!r}, max_policy_change="
                f"{self.max_policy_change!r}: both need the policy sensitivity, which "
                "Q-learning does not compute; expected optimizer 'adam' or 'sgd' and no "
                "max_policy_change")
        check_ranges("learning", self)

    def to_dict(self) -> dict[str, Any]:
        """As for every config; a DPG config (``learner='dpg'``, the Q-learning fields at
        their defaults) leaves out ``learner``, ``hessian`` and ``newton_step``, so its files
        are those of before the fields."""
        out = super().to_dict()
        if self.gradient == "critic":
            out.pop("gradient")
        if self.terminal_scale == TERMINAL_SCALE:
            out.pop("terminal_scale")
        if not self.reset_momentum_at_bounds:
            out.pop("reset_momentum_at_bounds")
        if self.scale_to_prices is False:
            out.pop("scale_to_prices")
        if self.step_limit == 0.0:
            out.pop("step_limit")
        if self.critic_months == 1:
            out.pop("critic_months")
        if self.theta0 is None:
            out.pop("theta0")
        if self.learner == "dpg" and self.hessian == "approx" and self.newton_step == 0.3:
            for key in ("learner", "hessian", "newton_step"):
                out.pop(key)
        return out

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> LearningConfig:
        """Inverse of :meth:`to_dict`. A dict written before a field existed reads back with
        what its run did (:data:`EARLIER_BEHAVIOUR`): one evaluation draw, the projected
        exploration, one parameter set per battery, the per-hour value features and the
        shipped month's step scales."""
        if isinstance(data, dict):
            data = {**{k: v for k, v in EARLIER_BEHAVIOUR.items() if k not in data}, **data}
        return super().from_dict(data)

    def replace(self, **changes: Any) -> LearningConfig:
        """A copy with ``changes`` applied (validated like a new instance); where this config's
        ``value_features`` was chosen by its days (``None``), the copy chooses again."""
        if getattr(self, "_auto_value_features", False) and "value_features" not in changes:
            changes = {**changes, "value_features": None}
        if getattr(self, "_auto_terminal_scale", False) and "terminal_scale" not in changes:
            changes = {**changes, "terminal_scale": None}
        return super().replace(**changes)

    @classmethod
    def paper(cls, **changes: Any) -> LearningConfig:
        """The paper's literal learning rule: plain gradient steps of 5e-8 (Table I), the
        paper's value features, a small exploration (0.05 MW, kept zero-mean at the bounds
        as the compatible critic assumes; the paper does not say how) and the 24 parameters
        of its three batteries learned separately. ``changes`` override any field."""
        base = {
            "optimizer": "sgd",
            "step_size": PAPER_STEP_SIZE,
            "exploration_std": PAPER_EXPLORATION_STD,
            "value_features": "paper",
            "tie_agents": False,
            "exploration_margin": 0.0,
        }
        return cls(**{**base, **changes})


@dataclass(frozen=True)
class CoordinationConfig(_Config):
    """How the decentralized MPCs are coordinated on the grid limit.

    Used by :class:`mpcrl_lite.decentralized.coordination.CoordinatedMPC`: per-stage grid prices found with
    a decomposed Newton method (see that module's docstring).
    """

    tol: float = 1e-11
    """Stop when every KKT residual is at most ``tol * (1 + max |q|)`` (``q``: local linear
    costs, i.e. prices and slack weights)."""
    max_iter: int = 60
    """Coordination rounds per hour before the fallback (local IPOPT + projection)."""
    local_grid_factor: float = 1e4
    """The local MPC is the paper's MPC with ``n = 1`` and its grid row ``b <= P_loc`` made
    inert by ``P_loc = local_grid_factor * max(U_bar, P_bar)``; that row's barrier moves the
    solution by ~1e-10 (the real limit is priced, not constrained per battery)."""

    def __post_init__(self) -> None:
        set_ = self._set
        set_("tol", check_real("tol", self.tol, 0.0, 1e-2, low_open=True))
        set_("max_iter", check_int("max_iter", self.max_iter, 1))
        set_("local_grid_factor", check_real("local_grid_factor", self.local_grid_factor, 10.0))


@dataclass(frozen=True)
class PriceFileConfig(_Config):
    """A month of prices from a file, for runs set up by configuration (the sweep's and the
    study's ``prices`` section; the commands' ``--prices/--area/--month/--currency/--eur-rate/
    --price-format``). ``file=''`` (the default) is the shipped month.

    Read by :meth:`mpcrl_lite.system.prices.Prices.from_file` through
    :func:`mpcrl_lite.system.price_files.load.load_prices`.
    """

    file: str = ""
    """The price file (any format ``load_prices`` reads); empty: the shipped month."""
    area: str = ""
    """Its bidding zone by any of its names (``'NO3'``, ``'Tr.heim'``, ``'BZN|NO3'``); empty:
    the format's default (Tr.heim for Nord Pool's old export)."""
    month: str = ""
    """The month to use, ``'YYYY-MM'`` (required with ``file``)."""
    currency: str = "NOK"
    """The model's currency: NOK (:data:`PRICE_UNIT`, a EUR file converted at ``eur_rate``)."""
    eur_rate: float = EUR_NOK_RATE
    """NOK per EUR for a EUR file (default :data:`EUR_NOK_RATE`, its source stated there)."""
    format: str = ""
    """A format to force (``mpcrl_lite.system.price_files.detect.FORMATS``); empty: from the
    file's header."""

    def __post_init__(self) -> None:
        set_ = self._set
        for name in ("file", "area", "month", "currency", "format"):
            value = getattr(self, name)
            if not isinstance(value, str):
                raise TypeError(f"{name}={value!r}: expected a string")
        if self.currency != "NOK":
            raise ValueError(f"currency={self.currency!r}: expected 'NOK' (the penalties are in "
                             f"{PRICE_UNIT}; a EUR file is converted at eur_rate)")
        set_("eur_rate", check_real("eur_rate", self.eur_rate, 0.0, low_open=True))
        if self.file and not self.month:
            raise ValueError(f"month='': expected 'YYYY-MM' with file={self.file!r}")
