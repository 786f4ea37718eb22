"""What the command line checks before any work: prices from a price file, the size of
the work against the machine, and the output directory.

Every check raises a ``ValueError`` whose message is one line naming the bad value and what
was expected; :mod:`mpcrl_lite.cli.main` prints it and exits with status 2.

Resource limits
---------------
Before a command allocates anything, :func:`check_budget` estimates its peak memory and its
run time from the problem size and refuses

* memory above what the machine has available (``psutil.virtual_memory().available`` when
  psutil is installed, else ``os.sysconf`` of the available physical pages), and
* an estimated run time above :data:`TIME_LIMIT_S` seconds (4 hours; the environment
  variable ``MPCRL_LITE_TIME_LIMIT_S`` sets another limit, e.g. for a long cluster run).

The estimates are deliberately low (measured on a laptop core and rounded down for time, up
only where memory grows with the data), so a refusal means the work surely does not fit;
work near the limits is left to run.
"""

from __future__ import annotations

import os
import re
import warnings
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

import yaml

from ..config import PRICE_UNIT, SystemConfig
from ..learning.rundir import RunDirError, check_output_dir, inspect
from ..system.price_files.load import load_prices
from ..system.price_files.month import parse_month
from ..system.price_files.series import PriceFileWarning
from ..system.prices import Prices

try:  # optional: a better figure of the available memory
    import psutil
except ImportError:  # pragma: no cover (psutil is present in the project's environments)
    psutil = None

__all__ = [
    "TIME_LIMIT_ENV",
    "TIME_LIMIT_S",
    "Budget",
    "available_memory",
    "check_budget",
    "estimate",
    "month_prices",
    "prepare_out",
    "read_system_file",
    "refuse_finished",
]

#: Default limit of the estimated run time of one command, in seconds.
TIME_LIMIT_S = 4 * 3600.0
TIME_LIMIT_ENV = "MPCRL_LITE_TIME_LIMIT_S"

# Measured (simulate, N = 12, tau default): about 23 KiB of arrays per battery-day, 125 KiB of
# set-up per battery, 3 ms per battery-day of closed loop, and a set-up that grows with n**2
# (about 2e-5 s * n**2: 170 s at n = 3000). The time constants are rounded down.
_BYTES_PER_AGENT_DAY = 32 * 1024
_BYTES_PER_AGENT = 128 * 1024
_SECONDS_PER_AGENT_DAY = 1e-3
_SETUP_SECONDS_PER_AGENT2 = 1e-5

_MONTH = re.compile(r"^(\d{4})-(\d{2})$")


def _one_line(text: str) -> str:
    return " ".join(str(text).split())


# -- prices -------------------------------------------------------------------------------
def month_prices(path: str | os.PathLike, area: str | None, month: str, system: SystemConfig,
                 days: int | None = None, currency: str = "NOK", eur_rate: float | None = None,
                 fmt: str | None = None) -> Prices:
    """The prices of one calendar ``month`` (``'YYYY-MM'``) of ``area`` in a price file of
    any format :func:`~mpcrl_lite.system.price_files.load.load_prices` reads, as the buying
    price matrix for ``system`` (its ``sell_ratio``, scaled by its ``price_scale`` like
    :meth:`Prices.default`).

    Parameters
    ----------
    path, area
        The file and the area (any name of :mod:`~mpcrl_lite.system.price_files.areas`;
        None: the format's default, see ``load_prices``).
    month
        ``'YYYY-MM'``; every hour of every day of the month must have a price.
    system
        Supplies ``sell_ratio`` and ``price_scale``.
    days
        The first ``days`` days of the month only (default all of them).
    currency, eur_rate, fmt
        The currency of the model (NOK: a EUR file is converted at ``eur_rate``, default
        :data:`~mpcrl_lite.config.EUR_NOK_RATE`), and a format to force.

    Returns
    -------
    Prices
        Shape ``(days, 24)``; clock-change days mapped onto 24 hours as
        :func:`~mpcrl_lite.system.prices.daily_matrix` describes; ``origin`` records the file.

    Raises
    ------
    ValueError
        One line naming the file, area, month or hour that is wrong.
    """
    try:
        length = parse_month(month)[1]
    except ValueError:
        raise ValueError(f"--month {month!r}: expected a calendar month as YYYY-MM, e.g. "
                         "2025-11") from None
    if days is not None and days > length:
        raise ValueError(f"--days {days}: {month} has {length} days; expected at most {length}")
    if not Path(path).is_file():
        raise ValueError(f"--prices {path}: no such file; expected a price file (CSV, see "
                         "README 'Prices from your own files')")
    try:
        with warnings.catch_warnings():  # hours without a price: refused below if in the month
            warnings.simplefilter("ignore", PriceFileWarning)
            series = load_prices(path, area, currency=currency, format=fmt, eur_rate=eur_rate)
    except (OSError, ValueError, TypeError) as err:
        text = str(err)
        if text.startswith("area "):
            raise ValueError(_one_line(f"--{text}")) from None
        text = text.removeprefix(f"{path}: ")
        raise ValueError(_one_line(f"--prices {path}: {text}")) from None
    try:
        if series.attrs.get("unit") != PRICE_UNIT:
            raise ValueError(f"prices in {series.attrs.get('unit')}; expected {PRICE_UNIT} "
                             "(--currency NOK)")
        prices = Prices.from_month(series, month, system)
    except (OSError, ValueError, TypeError) as err:
        raise ValueError(_one_line(f"--prices {path} --area {area} --month {month}: {err}")) \
            from None
    return prices.take(days) if days is not None and days < length else prices


# -- a system file ------------------------------------------------------------------------
def _yaml_where(err: yaml.YAMLError) -> str:
    mark = getattr(err, "problem_mark", None)
    problem = getattr(err, "problem", None)
    if mark is not None and problem:
        return f"line {mark.line + 1}, column {mark.column + 1}: {problem}"
    return _one_line(str(err))


def read_system_file(path: str | os.PathLike) -> dict:
    """The fields of a :class:`~mpcrl_lite.config.SystemConfig` written in the YAML file
    ``path`` (a mapping ``field: value``; YAML lists stand for tuples: ``omega``, and one value
    per battery where a field takes them), checked by building the config from them alone.

    Returns
    -------
    dict
        The fields as given (lists as tuples), for the command's flags to override.

    Raises
    ------
    ValueError
        One line naming the file and what is wrong: missing, not YAML, not a mapping, an
        unknown field, a value of the wrong type or out of range.
    """
    where = f"--system {os.fspath(path)}"
    try:
        text = Path(path).read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ValueError(f"{where}: no such file; expected a YAML file of SystemConfig fields") \
            from None
    except (OSError, UnicodeDecodeError) as err:
        raise ValueError(_one_line(f"{where}: cannot be read ({err})")) from None
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as err:
        raise ValueError(_one_line(f"{where}: not valid YAML: {_yaml_where(err)}")) from None
    except (RecursionError, ValueError) as err:
        raise ValueError(_one_line(f"{where}: not valid YAML: {err}")) from None
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise ValueError(  # noqa: TRY004
            f"{where}: expected a mapping of SystemConfig fields (field: value), "
            f"got {type(data).__name__}")
    bad_keys = [k for k in data if not isinstance(k, str)]
    if bad_keys:
        raise ValueError(f"{where}: field {bad_keys[0]!r} is not a name; expected SystemConfig "
                         "field names")
    fields = {k: tuple(v) if isinstance(v, list) else v for k, v in data.items()}
    try:
        import warnings

        with warnings.catch_warnings():  # a warning is for the final config, not the file
            warnings.simplefilter("ignore")
            SystemConfig.from_dict(fields)
    except (ValueError, TypeError) as err:
        raise ValueError(_one_line(f"{where}: {err}")) from None
    return fields


# -- resources ----------------------------------------------------------------------------
def available_memory() -> int | None:
    """Bytes of memory available to a new allocation now, or None where it is not known."""
    if psutil is not None:
        return int(psutil.virtual_memory().available)
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):  # pragma: no cover (not POSIX)
        return None


@dataclass(frozen=True)
class Budget:
    """Estimated peak memory (bytes) and run time (seconds) of a command."""

    memory: float
    seconds: float


def estimate(n: int, days: int, runs: int = 1, sensitivities: bool = False,
             horizon: int = SystemConfig().N) -> Budget:
    """Lower estimates of the peak memory and run time of ``runs`` closed-loop months of
    ``days`` days with ``n`` batteries (``sensitivities``: a learning month, twice the cost)."""
    scale = max(1.0, (horizon / 12) ** 2)
    factor = 2.0 if sensitivities else 1.0
    memory = factor * scale * float(n) * float(days) * _BYTES_PER_AGENT_DAY \
        + float(n) * _BYTES_PER_AGENT
    seconds = factor * float(runs) * float(n) * float(days) * _SECONDS_PER_AGENT_DAY \
        + _SETUP_SECONDS_PER_AGENT2 * float(n) ** 2
    return Budget(memory, seconds)


def _time_limit() -> float:
    text = os.environ.get(TIME_LIMIT_ENV)
    if not text:
        return TIME_LIMIT_S
    try:
        value = float(text)
    except ValueError:
        raise ValueError(f"{TIME_LIMIT_ENV}={text!r}: expected a number of seconds") from None
    if not value > 0:
        raise ValueError(f"{TIME_LIMIT_ENV}={text!r}: expected a positive number of seconds")
    return value


def check_budget(what: str, n: int, days: int, runs: int = 1, sensitivities: bool = False,
                 horizon: int = SystemConfig().N) -> Budget:
    """:func:`estimate`, refused (``ValueError``, one line) above the available memory or the
    time limit. ``what`` names the values in the message, e.g. ``'--days 1000000000 --n 3'``."""
    budget = estimate(n, days, runs, sensitivities, horizon)
    memory = available_memory()
    if memory is not None and budget.memory > memory:
        raise ValueError(
            f"{what}: needs about {budget.memory / 2**30:.3g} GiB of memory; expected at most "
            f"the {memory / 2**30:.3g} GiB available (use fewer days or batteries)")
    limit = _time_limit()
    if budget.seconds > limit:
        raise ValueError(
            f"{what}: would run for about {budget.seconds / 3600:.3g} hours or more; expected "
            f"at most the time limit of {limit / 3600:.3g} hours (set {TIME_LIMIT_ENV} to "
            "raise it)")
    return budget


# -- output directory ---------------------------------------------------------------------
def refuse_finished(path: str | os.PathLike, outputs: Iterable[str], force: bool = False,
                    flag: str = "--out") -> None:
    """A ``RunDirError`` (one line) when the directory ``path`` holds one of ``outputs`` and
    not ``force``; nothing is created."""
    directory = Path(os.fspath(path))
    found = inspect(directory, others=outputs).others if directory.is_dir() else []
    if found and not force:
        raise RunDirError(
            f"{flag} {os.fspath(path)} already holds results ({', '.join(found)}); pass --force "
            "to replace them or choose another --out")


def prepare_out(path: str | os.PathLike, outputs: Iterable[str], force: bool = False,
                flag: str = "--out") -> Path:
    """The output directory, created and checked writable (:func:`~mpcrl_lite.learning.rundir.
    check_output_dir`), refused when it already holds one of ``outputs`` unless ``force``
    (:func:`refuse_finished`).

    Raises
    ------
    ValueError
        (:class:`~mpcrl_lite.learning.rundir.RunDirError`) one line with the remedy.
    """
    refuse_finished(path, outputs, force, flag)
    return check_output_dir(path, flag)
