"""What the command line checks before any work: prices from a Nord Pool export, the size of
the work against the machine, and the output directory.

Every check raises a ``ValueError`` whose message is one line naming the bad value and what
was expected; :mod:`mpcrl_lite.cli.main` prints it and exits with status 2.

Resource limits
---------------
:func:`check_budget` and :func:`estimate` (from :mod:`mpcrl_lite._util.budget`, importable
from here) refuse work beyond the machine's memory or the time limit.
"""

from __future__ import annotations

import calendar
import os
import re
from collections.abc import Iterable
from pathlib import Path

import yaml

from .._util.budget import (  # noqa: F401 (importable from here)
    TIME_LIMIT_ENV,
    TIME_LIMIT_S,
    Budget,
    available_memory,
    check_budget,
    estimate,
)
from ..config import SystemConfig
from ..learning.rundir import RunDirError, check_output_dir, inspect
from ..studies.sweep.grid import load_yaml
from ..system.prices import Prices, load_nordpool_csv, nordpool_areas

# check_budget, estimate, Budget, available_memory and TIME_LIMIT_S/_ENV live in
# mpcrl_lite._util.budget and stay importable from here.
__all__ = [
    "month_prices",
    "prepare_out",
    "read_system_file",
    "refuse_finished",
]

_MONTH = re.compile(r"^(\d{4})-(\d{2})$")


def _one_line(text: str) -> str:
    return " ".join(str(text).split())


# -- prices -------------------------------------------------------------------------------
def month_prices(path: str | os.PathLike, area: str, month: str, system: SystemConfig,
                 days: int | None = None) -> Prices:
    """The prices of one calendar ``month`` (``'YYYY-MM'``) of ``area`` in a Nord Pool
    export, as the buying price matrix for ``system`` (its ``sell_ratio``, scaled by its
    ``price_scale`` like :meth:`Prices.default`).

    Parameters
    ----------
    path, area
        The export and the area column (see :func:`~mpcrl_lite.system.prices.load_nordpool_csv`).
    month
        ``'YYYY-MM'``; every hour of every day of the month must have a price.
    system
        Supplies ``sell_ratio`` and ``price_scale``.
    days
        The first ``days`` days of the month only (default all of them).

    Returns
    -------
    Prices
        Shape ``(days, 24)``; clock-change days mapped onto 24 hours as
        :func:`~mpcrl_lite.system.prices.daily_matrix` describes.

    Raises
    ------
    ValueError
        One line naming the file, area, month or hour that is wrong.
    """
    found = _MONTH.match(str(month))
    if not found or not 1 <= int(found.group(2)) <= 12:
        raise ValueError(f"--month {month!r}: expected a calendar month as YYYY-MM, e.g. 2020-11")
    year, number = int(found.group(1)), int(found.group(2))
    length = calendar.monthrange(year, number)[1]
    if days is not None and days > length:
        raise ValueError(f"--days {days}: {month} has {length} days; expected at most {length}")
    if not Path(path).is_file():
        raise ValueError(f"--prices {path}: no such file; expected a Nord Pool price export (CSV)")
    try:
        areas = nordpool_areas(path)
    except (OSError, ValueError, TypeError) as err:
        raise ValueError(_one_line(f"--prices {path}: {err}")) from None
    if area not in areas:
        raise ValueError(f"--area {area!r} is not in {path}; expected one of {areas}")
    try:
        series = load_nordpool_csv(path, area)
        prices = Prices.from_series(series, f"{month}-01", length, sell_ratio=system.sell_ratio)
    except (OSError, ValueError, TypeError) as err:
        raise ValueError(_one_line(f"--prices {path} --area {area} --month {month}: {err}")) \
            from None
    prices = prices.scaled(system.price_scale) if system.price_scale != 1.0 else prices
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
        data = load_yaml(text)  # a key written twice is refused
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
