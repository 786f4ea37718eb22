"""What the commands share: the parser class with one-line errors, argument types, the
option groups several commands take, the configs built from the options and the checks made
before any work (through :mod:`mpcrl_lite.cli.inputs`).
"""

from __future__ import annotations

import argparse
import sys
import warnings
from pathlib import Path
from typing import Any

import numpy as np

from ..config import (
    BACKENDS,
    EUR_NOK_RATE,
    FORECASTS,
    PAPER_TAU,
    POLICY_CLASSES,
    PRICE_UNIT,
    LearningConfig,
    MPCConfig,
    SystemConfig,
    check_grid_bound,
)
from ..learning import durable
from ..system.price_files.currency import CURRENCIES
from ..system.price_files.detect import FORMATS


class Parser(argparse.ArgumentParser):
    """argparse with one-line errors, and negative numbers that argparse would take for
    options (``--p-bar -inf``, ``--tau -1e-5``) read as the option's value, so that the
    value's own check refuses them by value."""

    def error(self, message: str) -> None:  # type: ignore[override]
        self.exit(2, f"{self.prog}: error: {message}\n")

    def parse_known_args(self, args=None, namespace=None):  # type: ignore[override]
        args = list(sys.argv[1:] if args is None else args)
        return super().parse_known_args(_join_negative_numbers(args), namespace)


def _is_negative_number(text: str) -> bool:
    if not text.startswith("-") or text.startswith("--"):
        return False
    try:
        float(text)
    except ValueError:
        return False
    return True


def _join_negative_numbers(args: list[str]) -> list[str]:
    """``['--p-bar', '-inf']`` -> ``['--p-bar=-inf']`` (argparse reads ``-inf``, ``-1e5``
    and ``-nan`` as options, not as negative numbers)."""
    joined: list[str] = []
    for text in args:
        last = joined[-1] if joined else ""
        if _is_negative_number(text) and last.startswith("--") and "=" not in last:
            joined[-1] = f"{last}={text}"
        else:
            joined.append(text)
    return joined


class UsageError(Exception):
    """A bad value found after parsing (reported in one line, exit 2)."""


def int_at_least(low: int):
    """argparse type: an integer >= ``low``."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not an integer") from None
        if value < low:
            raise argparse.ArgumentTypeError(f"{value} must be >= {low}")
        return value

    return parse


positive_int = int_at_least(1)
nonneg_int = int_at_least(0)


def finite_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not np.isfinite(value):
        raise argparse.ArgumentTypeError(f"{text!r} is not a finite number")
    return value


def out_dir(text: str) -> Path:
    """argparse type of ``--out``: a path, not the empty string (``Path('')`` would be the
    current directory)."""
    if text == "":
        raise argparse.ArgumentTypeError(
            "'': expected a directory path (an empty path would write into the current "
            "directory; pass '.' to mean it)")
    return Path(text)


# Defaults shown in --help are read from the configs, never copied.
SYSTEM, MPC_DEFAULTS, LEARNING = SystemConfig(), MPCConfig(), LearningConfig()


def add_update_options(p: argparse.ArgumentParser, kept: str = "") -> None:
    """How each update moves theta, shared by ``learn`` and ``study`` (``LearningConfig``'s
    fields of the same names; ``kept`` ends each help, e.g. what a resume does with them):
    ``--scale-to-prices`` / ``--no-scale-to-prices``, ``--step-limit``, and how the step
    changes over the months, ``--step-warmup``, ``--step-decay``, ``--average-months``."""
    scale = p.add_mutually_exclusive_group()
    scale.add_argument("--scale-to-prices", action="store_const", const=True, default=None,
                       help="Adam's scales of the cost parts follow the month's price level "
                            "(its mean buying price over the shipped month's; "
                            "LearningConfig.scale_to_prices); the default with --prices, so "
                            "this flag matters for the shipped month with another price scale"
                            f"{kept}")
    scale.add_argument("--no-scale-to-prices", dest="scale_to_prices", action="store_const",
                       const=False,
                       help="keep the shipped month's scales (times the price scale) with "
                            f"--prices too, as runs did before the option{kept}")
    p.add_argument("--step-limit", type=finite_float, default=None,
                   help="the largest move of a theta entry per update, in units of its typical "
                        "magnitude (LearningConfig.step_limit; default 0: no limit; 5 keeps "
                        f"--learner q from running away{kept})")
    p.add_argument("--step-warmup", type=nonneg_int, default=None, metavar="MONTHS",
                   help="months of a linear warm-up of the step size (default "
                        f"{LEARNING.step_warmup}: none; LearningConfig.step_warmup{kept})")
    p.add_argument("--step-decay", type=nonneg_int, default=None, metavar="MONTHS",
                   help="months after which a harmonic decay has halved the step size "
                        f"(default {LEARNING.step_decay}: a constant step; "
                        f"LearningConfig.step_decay{kept})")
    p.add_argument("--average-months", type=nonneg_int, default=None, metavar="MONTHS",
                   help="use an exponential average of the raw iterates over about this many "
                        f"months (default {LEARNING.average_months}: the iterates themselves; "
                        f"LearningConfig.average_months{kept})")


def add_critic_months(p: argparse.ArgumentParser, kept: str = "") -> None:
    """``--critic-months K`` (``LearningConfig.critic_months``), shared by ``learn`` and
    ``study``."""
    p.add_argument("--critic-months", type=int_at_least(1), default=None, metavar="K",
                   help="fit the critic of each update on the samples of the last K months "
                        f"(default {LEARNING.critic_months}: the month alone, the paper's rule; "
                        "4 lowered the paper class's learner gap on fresh seeds; "
                        f"LearningConfig.critic_months{kept})")


def add_theta0(p: argparse.ArgumentParser, kept: str = "") -> None:
    """``--theta0 SOURCE`` (``LearningConfig.theta0``), shared by ``learn`` and ``study``."""
    p.add_argument("--theta0", default=None, metavar="SOURCE",
                   help="start the learning from this theta instead of the nominal one: a "
                        "tune directory or its tune.json (the best theta found), a learn run "
                        "directory (its last theta) or a JSON file of theta's parts "
                        f"(LearningConfig.theta0{kept})")


def start_theta(args: argparse.Namespace, n: int) -> tuple[tuple[float, ...], str] | None:
    """The start of ``--theta0 SOURCE`` for ``n`` batteries (None without it), checked before
    any work: its entries (``LearningConfig.theta0``) and what it is, for the command's line
    on stderr; the one place ``learn`` and ``study`` read the option."""
    if args.theta0 is None:
        return None
    from .inputs import read_theta

    try:
        theta, what = read_theta(args.theta0, n)
    except ValueError as err:
        raise UsageError(str(err)) from None
    return tuple(float(x) for x in theta.to_vector()), what


def add_system_file(p: argparse.ArgumentParser) -> None:
    """``--system FILE.yaml``: the fields of SystemConfig from a YAML file."""
    p.add_argument("--system", type=Path, default=None, metavar="FILE.yaml",
                   help="the battery system from a YAML file of SystemConfig fields (e.g. "
                        "examples/mixed_site.yaml); --n, --p-bar and --noise-var override it")


def system_file(args: argparse.Namespace) -> dict[str, Any]:
    """The fields of ``--system`` (empty without it), checked before any work."""
    from . import inputs as cli_inputs

    path = getattr(args, "system", None)
    if path is None:
        return {}
    try:
        return cli_inputs.read_system_file(path)
    except ValueError as err:
        raise UsageError(str(err)) from None


def add_system_args(p: argparse.ArgumentParser) -> None:
    add_system_file(p)
    p.add_argument("--seed", type=nonneg_int, default=LEARNING.seed,
                   help=f"random seed (default {LEARNING.seed})")
    p.add_argument("--p-bar", type=finite_float, default=None,
                   help=f"grid peak bound P_bar (default {SYSTEM.P_bar:g})")
    p.add_argument("--noise-var", type=finite_float, default=None,
                   help=f"variance of the production-demand noise (default {SYSTEM.noise_var:g})")
    p.add_argument("--n", type=positive_int, default=None,
                   help=f"number of batteries (default {SYSTEM.n})")
    p.add_argument("--tau", type=finite_float, default=None,
                   help=f"MPC barrier parameter in NOK (default {MPC_DEFAULTS.tau:g}; "
                        f"{PAPER_TAU:g} is the nearly exact MPC)")
    p.add_argument("--backend", choices=BACKENDS, default=None,
                   help=f"MPC solver back-end (default {MPC_DEFAULTS.backend})")
    add_forecast(p)
    add_policy_class(p)
    p.add_argument("--quiet", action="store_true", help="no progress bar")


def add_forecast(p: argparse.ArgumentParser, help_text: str | None = None) -> None:
    p.add_argument("--forecast", choices=FORECASTS, default=None,
                   help=help_text or (
                       f"the MPC's price forecast (default {MPC_DEFAULTS.forecast}: the paper's, "
                       "reading on into the next day; until_midnight is an extension beyond "
                       "the paper whose forecast stops at midnight)"))


def add_policy_class(p: argparse.ArgumentParser, help_text: str | None = None) -> None:
    names = ", ".join(f"{c.name}: {c.about}" for c in POLICY_CLASSES.values())
    p.add_argument("--policy-class", choices=tuple(POLICY_CLASSES), default=None,
                   help=help_text or (
                       "the MPC's policy class, its horizon and forecast (default paper; "
                       f"{names})"))


def policy_class_fields(args: argparse.Namespace, system: dict[str, Any],
                        mpc: dict[str, Any]) -> None:
    """Put the horizon (``system['N']``) and the forecast (``mpc['forecast']``) of
    ``--policy-class`` into the fields, refusing a ``--forecast`` or a ``--system`` file's
    ``N`` that says otherwise (one line)."""
    name = getattr(args, "policy_class", None)
    if name is None:
        return
    cls = POLICY_CLASSES[name]
    if mpc.get("forecast", cls.forecast) != cls.forecast:
        raise UsageError(f"--forecast {mpc['forecast']} with --policy-class {name}: the class "
                         f"has forecast {cls.forecast}; give one of the two")
    if system.get("N", cls.N) != cls.N:
        raise UsageError(f"N={system['N']} of --system with --policy-class {name}: the class "
                         f"has N={cls.N}; give one of the two")
    system["N"], mpc["forecast"] = cls.N, cls.forecast


def add_price_args(p: argparse.ArgumentParser) -> None:
    """``--prices FILE --area AREA --month YYYY-MM [--currency] [--eur-rate] [--price-format]``:
    the one set of price options (read by :func:`month_prices`)."""
    p.add_argument("--prices", type=Path, default=None, metavar="FILE",
                   help="day-ahead prices from a file of Nord Pool (data portal or old export), "
                        "ENTSO-E or Energi Data Service, the format read from its header "
                        "(default: the shipped November 2020 month)")
    p.add_argument("--area", default=None,
                   help="bidding zone of --prices by any of its names (NO3 = Tr.heim = Molde = "
                        "BZN|NO3, DK2, ...; default Tr.heim for Nord Pool's old export)")
    p.add_argument("--month", default=None, metavar="YYYY-MM",
                   help="month of --prices to use (every hour of every day must have a price)")
    p.add_argument("--currency", choices=CURRENCIES, default=None,
                   help="currency of the model's prices (default NOK, the unit of the "
                        "penalties: a EUR file is converted at --eur-rate)")
    p.add_argument("--eur-rate", type=finite_float, default=None, metavar="NOK_PER_EUR",
                   help=f"NOK per EUR for a EUR file (default {EUR_NOK_RATE:g}: the ECB "
                        "reference rate, November 2025 average)")
    p.add_argument("--price-format", choices=FORMATS[:-1], default=None,
                   help="force the format of --prices instead of reading it from the header")


def add_force(p: argparse.ArgumentParser) -> None:
    p.add_argument("--force", action="store_true",
                   help="replace the results found in --out (they are refused otherwise)")


# -- configs from arguments ----------------------------------------------------------------
def configs(args: argparse.Namespace, **learning: Any):
    """The three configs of the options: the fields of ``--system`` (if given), then the
    flags ``--p-bar``, ``--noise-var`` and ``--n`` over them, ``--tau``, ``--backend``,
    ``--forecast``, ``--policy-class`` (:func:`policy_class_fields`), ``--seed`` and the
    ``learning`` fields given (None: the default)."""
    system = system_file(args)
    if args.p_bar is not None:
        system["P_bar"] = args.p_bar
    if args.noise_var is not None:
        system["noise_var"] = args.noise_var
    if args.n is not None:
        system["n"] = args.n
    mpc = {}
    if args.tau is not None:
        mpc["tau"] = args.tau
    if args.backend is not None:
        mpc["backend"] = args.backend
    if args.forecast is not None:
        mpc["forecast"] = args.forecast
    policy_class_fields(args, system, mpc)
    learning = {k: v for k, v in learning.items() if v is not None}
    try:
        with warnings.catch_warnings(record=True) as caught:  # a refusal is the one line
            warnings.simplefilter("always")
            system_config = check_grid_bound(SystemConfig(**system))
        for warning in caught:
            warnings.warn_explicit(warning.message, warning.category, warning.filename,
                                   warning.lineno)
        configs = (
            system_config,
            MPCConfig(**mpc),
            LearningConfig(seed=args.seed, **learning),
        )
    except ValueError as err:
        raise UsageError(str(err)) from None
    return configs


def write_json(path: Path, data: dict[str, Any]) -> None:
    """Strict JSON (NaN as null), written atomically."""
    try:
        durable.write_json(path, data)
    except OSError as err:
        raise UsageError(str(err)) from None


def write_bytes(path: Path, data: bytes) -> None:
    try:
        durable.write_atomic(path, data)
    except OSError as err:
        raise UsageError(str(err)) from None


def month_prices(args: argparse.Namespace, system: SystemConfig, days: int | None):
    """The month of ``--prices/--area/--month`` (None without ``--prices``), checked; the one
    place every command reads its price options."""
    from . import inputs as cli_inputs

    given = [f for f, v in (("--area", getattr(args, "area", None)),
                            ("--month", getattr(args, "month", None)),
                            ("--currency", getattr(args, "currency", None)),
                            ("--eur-rate", getattr(args, "eur_rate", None)),
                            ("--price-format", getattr(args, "price_format", None)))
             if v is not None]
    if getattr(args, "prices", None) is None:
        if given:
            raise UsageError(f"{' and '.join(given)} given without --prices; expected "
                             "--prices FILE with them")
        return None
    if args.month is None:
        raise UsageError(f"--prices {args.prices} given without --month; expected --month "
                         "YYYY-MM (the month of the file to use)")
    if args.eur_rate is not None and args.eur_rate <= 0:
        raise UsageError(f"--eur-rate {args.eur_rate:g}: expected a positive number of NOK "
                         "per EUR")
    currency = args.currency or "NOK"
    if currency != "NOK":
        raise UsageError(f"--currency {currency}: the model's penalties are in NOK "
                         f"({PRICE_UNIT}); expected NOK (a EUR file is converted at --eur-rate)")
    try:
        return cli_inputs.month_prices(args.prices, args.area, args.month, system, days,
                                       currency=currency, eur_rate=args.eur_rate,
                                       fmt=args.price_format)
    except ValueError as err:
        raise UsageError(str(err)) from None


def price_base(args: argparse.Namespace) -> dict[str, Any]:
    """The price options as sweep base-config keys (``prices.file``, ``prices.area``, ...),
    for the commands that run through a sweep (``study``); empty without ``--prices``."""
    keys = {"file": "prices", "area": "area", "month": "month", "currency": "currency",
            "eur_rate": "eur_rate", "format": "price_format"}
    if getattr(args, "prices", None) is None:
        return {}
    return {f"prices.{k}": (str(Path(getattr(args, a)).resolve()) if k == "file" else getattr(args, a))
            for k, a in keys.items() if getattr(args, a, None) is not None}


def budget(what: str, n: int, days: int, runs: int = 1, sensitivities: bool = False,
            horizon: int = SystemConfig().N) -> None:
    from . import inputs as cli_inputs

    try:
        cli_inputs.check_budget(what, n, days, runs, sensitivities, horizon)
    except ValueError as err:
        raise UsageError(str(err)) from None


def learning_budget(what: str, system: SystemConfig, learning: Any) -> None:
    """:func:`budget` of a learning run with its evaluations (``learning``: its
    ``LearningConfig``): the estimate the library checks before it builds anything
    (:func:`mpcrl_lite.learning.learner.resolve_setup`), refused here in one line."""
    from .._util.budget import check_estimate, learning_estimate

    try:
        check_estimate(what, learning_estimate(
            system.n, learning.days_per_month, learning.months, learning.eval_draws,
            learning.eval_every, system.N))
    except ValueError as err:
        raise UsageError(str(err)) from None


def prepare_out(args: argparse.Namespace, outputs: tuple[str, ...]) -> Path:
    """--out checked (writable, no finished results unless --force) before any work."""
    from . import inputs as cli_inputs

    try:
        return cli_inputs.prepare_out(args.out, outputs, force=args.force)
    except ValueError as err:
        raise UsageError(str(err)) from None
