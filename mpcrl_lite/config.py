"""Every number of the experiment, and every choice the paper leaves open, in one place.

Three frozen dataclasses:

* :class:`SystemConfig` -- the battery system and the MPC's fixed structure (the paper's
  Table I).
* :class:`MPCConfig` -- how the MPC is solved (barrier parameter, back-end, tolerances).
* :class:`LearningConfig` -- the LSTD / DPG learning loop (step size, months, exploration,
  safeguards).

All three validate themselves at construction and raise a :class:`ValueError` that names the
field, the value given and the range allowed, before any work starts.

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
  problem and its KKT sensitivity is exact (``MPCConfig.tau``).
* **Initial theta.** The paper does not list it. We start from the nominal model:
  ``theta_alpha = alpha``, ``theta_delta = alpha * noise_mean``, all cost corrections zero.
"""

from __future__ import annotations

import math
import numbers
import warnings
from dataclasses import asdict, dataclass, fields, replace
from typing import Any

__all__ = [
    "SystemConfig",
    "MPCConfig",
    "LearningConfig",
    "ConfigWarning",
    "PRICE_UNIT",
]

#: Unit of every price in the project (see the module docstring for why).
PRICE_UNIT = "NOK/MWh"


class ConfigWarning(UserWarning):
    """A setting that is legal but probably not what the user meant."""


def _check_finite(name: str, value: Any) -> None:
    values = value if isinstance(value, tuple) else (value,)
    for v in values:
        if isinstance(v, bool) or not isinstance(v, numbers.Real):
            raise ValueError(f"{name}={value!r}: expected a real number")
        if not math.isfinite(float(v)):
            raise ValueError(f"{name}={value!r}: expected a finite number")


def _check_range(
    name: str,
    value: float,
    low: float | None = None,
    high: float | None = None,
    low_open: bool = False,
    high_open: bool = False,
) -> None:
    _check_finite(name, value)
    bad = (
        (low is not None and (value <= low if low_open else value < low))
        or (high is not None and (value >= high if high_open else value > high))
    )
    if bad:
        lo = "-inf" if low is None else f"{low:g}"
        hi = "inf" if high is None else f"{high:g}"
        left = "(" if (low_open or low is None) else "["
        right = ")" if (high_open or high is None) else "]"
        raise ValueError(f"{name}={value!r}: expected a value in {left}{lo}, {hi}{right}")


def _check_int(name: str, value: Any, low: int) -> None:
    if isinstance(value, bool) or not isinstance(value, numbers.Integral):
        raise ValueError(f"{name}={value!r}: expected an integer >= {low}")
    if value < low:
        raise ValueError(f"{name}={value!r}: expected an integer >= {low}")


def _check_choice(name: str, value: Any, choices: tuple[str, ...]) -> None:
    if value not in choices:
        raise ValueError(f"{name}={value!r}: expected one of {', '.join(map(repr, choices))}")


class _Config:
    """Shared helpers: ``replace`` with validation, and plain-dict round trips."""

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

    Prices are in :data:`PRICE_UNIT` (NOK/MWh); powers ``b``, ``s`` and ``Delta`` are in MW
    averaged over one hour, so one unit of power for one hour is one MWh.
    """

    n: int = 3
    """Number of batteries (agents)."""
    alpha: float = 1.0 / 12.0
    """True battery size factor in ``soc+ = soc + alpha (Delta + b - s)``; must be > 0."""
    noise_mean: float = 0.0
    """Mean of the production-demand noise ``Delta``."""
    noise_var: float = 0.5
    """Variance of ``Delta`` (Table I's ``N(0, 0.5)``; the std is ``sqrt(noise_var)``)."""
    U_bar: float = 1.0
    """Bound on each battery's buying and selling power, ``0 <= b, s <= U_bar``."""
    P_bar: float = 1.5
    """Grid peak bound: ``sum_i b_i <= P_bar`` and ``sum_i s_i <= P_bar``."""
    omega: tuple[float, float] = (20.0, 20.0)
    """MPC stage slack weights on (soc above 0.9, soc below 0.1)."""
    omega_f: tuple[float, float] = (20.0, 20.0)
    """MPC terminal slack weights."""
    p: float = 1000.0
    """True-cost penalty per unit of soc outside [soc_low, soc_high]."""
    soc_low: float = 0.1
    """Lower edge of the safe soc band (penalised below)."""
    soc_high: float = 0.9
    """Upper edge of the safe soc band (penalised above)."""
    gamma: float = 0.99
    """Discount factor, in (0, 1]."""
    N: int = 12
    """MPC horizon in hours (prices are known about 12 hours ahead)."""
    hours_per_day: int = 24
    """Length of one episode; soc restarts at ``soc0`` every day."""
    sample_time_h: float = 1.0
    """Sampling time in hours (informational: the dynamics are written per sample)."""
    sell_ratio: float = 0.5
    """Selling price = ``sell_ratio`` x buying price (the paper uses 0.5)."""
    price_scale: float = 1.0
    """Multiplier on the price series (1.0 keeps NOK/MWh; a classroom knob)."""
    soc0: float = 0.6
    """soc of every battery at the start of each day (text: 0.6; Table I says 0.5)."""

    def __post_init__(self) -> None:
        _check_int("n", self.n, 1)
        _check_range("alpha", self.alpha, 0.0, low_open=True)
        _check_range("noise_mean", self.noise_mean)
        _check_range("noise_var", self.noise_var, 0.0)
        _check_range("U_bar", self.U_bar, 0.0, low_open=True)
        _check_range("P_bar", self.P_bar, 0.0, low_open=True)
        for name in ("omega", "omega_f"):
            value = getattr(self, name)
            if not isinstance(value, tuple) or len(value) != 2:
                raise ValueError(f"{name}={value!r}: expected a pair (above, below) of weights >= 0")
            for v in value:
                _check_range(name, v, 0.0)
        _check_range("p", self.p, 0.0)
        _check_range("soc_low", self.soc_low, 0.0, 1.0)
        _check_range("soc_high", self.soc_high, self.soc_low, 1.0)
        _check_range("gamma", self.gamma, 0.0, 1.0, low_open=True)
        _check_int("N", self.N, 1)
        _check_int("hours_per_day", self.hours_per_day, 1)
        _check_range("sample_time_h", self.sample_time_h, 0.0, low_open=True)
        _check_range("sell_ratio", self.sell_ratio, 0.0)
        _check_range("price_scale", self.price_scale, 0.0)
        _check_range("soc0", self.soc0, 0.0, 1.0)
        if self.P_bar >= self.n * self.U_bar:
            warnings.warn(
                f"P_bar={self.P_bar:g} >= n*U_bar={self.n * self.U_bar:g}: "
                "the grid peak limit can never bind",
                ConfigWarning,
                stacklevel=3,
            )

    @property
    def noise_std(self) -> float:
        """Standard deviation of ``Delta``."""
        return math.sqrt(self.noise_var)


#: Solver back-ends known to :mod:`mpcrl_lite.solvers`.
BACKENDS = ("auto", "ipopt", "batch")


@dataclass(frozen=True)
class MPCConfig(_Config):
    """How the MPC is solved.

    The MPC is solved as the barrier problem ``min f - tau * sum(log(-h))`` subject to its
    equality constraints, with ``tau`` fixed: its solution is unique and smooth in the
    parameters, and for ``tau -> 0`` it tends to the exact (nearly bang-bang) MPC solution.
    """

    tau: float = 1e-4
    """Fixed interior-point barrier parameter; sensitivities are exact for this problem."""
    backend: str = "auto"
    """'ipopt' (reference, IPOPT through nlpsol), 'batch' (numpy interior point over all days
    at once) or 'auto' (batch when the MPC is convex, else ipopt; the choice is logged)."""
    tol: float = 1e-10
    """Tolerance on the barrier problem's KKT residual."""
    max_iter: int = 200
    """Iteration limit of one solve."""
    warm_start: bool = True
    """Start each solve from the previous hour's solution (shifted)."""
    kkt_cond_max: float = 1e12
    """KKT matrices with a larger condition estimate are reported as ill-conditioned."""

    def __post_init__(self) -> None:
        _check_range("tau", self.tau, 0.0, 1.0, low_open=True)
        _check_choice("backend", self.backend, BACKENDS)
        _check_range("tol", self.tol, 0.0, 1.0, low_open=True)
        _check_int("max_iter", self.max_iter, 1)
        if not isinstance(self.warm_start, bool):
            raise ValueError(f"warm_start={self.warm_start!r}: expected True or False")
        _check_range("kkt_cond_max", self.kkt_cond_max, 1.0, low_open=True)


#: Names of the DPG update rules in :mod:`mpcrl_lite.dpg`.
OPTIMIZERS = ("sgd", "adam")


@dataclass(frozen=True)
class LearningConfig(_Config):
    """The LSTD / DPG learning loop (paper Section III and its simulation section)."""

    step_size: float = 5e-8
    """DPG step size (the paper's alpha = 5e-8)."""
    months: int = 100
    """Number of learning steps; one update per month."""
    days_per_month: int = 30
    """Days simulated in parallel each month; their average approximates expectations."""
    exploration_std: float = 0.05
    """Std of the Gaussian noise added to the MPC action (projected onto the input bounds
    and the grid limit)."""
    ridge: float = 1e-6
    """Ridge (Tikhonov) term of the LSTD normal equations, relative to their scale."""
    learn_constants: bool = False
    """Also update phi3 and T3 (their policy gradient is always zero)."""
    optimizer: str = "sgd"
    """'sgd' (the paper's plain gradient step) or 'adam'."""
    grad_clip: float | None = None
    """If set, rescale each update so that ||step|| <= grad_clip."""
    keep_well_posed: bool = True
    """Project theta after each update: theta_alpha >= alpha_min and phi1, T1 >= 0 (the MPC
    then stays a convex QP with a unique solution)."""
    alpha_min: float = 1e-3
    """Smallest theta_alpha allowed by the projection."""
    seed: int = 0
    """Seed of every random draw (noise, exploration)."""

    def __post_init__(self) -> None:
        _check_range("step_size", self.step_size, 0.0)
        _check_int("months", self.months, 1)
        _check_int("days_per_month", self.days_per_month, 1)
        _check_range("exploration_std", self.exploration_std, 0.0)
        _check_range("ridge", self.ridge, 0.0)
        if not isinstance(self.learn_constants, bool):
            raise ValueError(f"learn_constants={self.learn_constants!r}: expected True or False")
        _check_choice("optimizer", self.optimizer, OPTIMIZERS)
        if self.grad_clip is not None:
            _check_range("grad_clip", self.grad_clip, 0.0, low_open=True)
        if not isinstance(self.keep_well_posed, bool):
            raise ValueError(f"keep_well_posed={self.keep_well_posed!r}: expected True or False")
        _check_range("alpha_min", self.alpha_min, 0.0, low_open=True)
        _check_int("seed", self.seed, 0)
