"""What the command line checks before any work: prices from a price file, a theta to start
from, the size of the work against the machine, and the output directory.

Every check raises a ``ValueError`` whose message is one line naming the bad value and what
was expected; :mod:`mpcrl_lite.cli.main` prints it and exits with status 2.

Resource limits
---------------
:func:`check_budget` and :func:`estimate` (from :mod:`mpcrl_lite._util.budget`, importable
from here) refuse work beyond the machine's memory or the time limit.
"""

from __future__ import annotations

import json
import os
import re
import warnings
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
from ..config import PRICE_UNIT, SystemConfig
from ..learning.history import History
from ..learning.outdir import RunDirError, check_output_dir
from ..learning.rundir import inspect
from ..studies.sweep.grid import load_yaml
from ..system.price_files.load import load_prices
from ..system.price_files.month import parse_month
from ..system.price_files.series import PriceFileWarning
from ..system.prices import Prices
from ..theta import Theta

# check_budget, estimate, Budget, available_memory and TIME_LIMIT_S/_ENV live in
# mpcrl_lite._util.budget and stay importable from here.
__all__ = [
    "month_prices",
    "prepare_out",
    "read_system_file",
    "read_theta",
    "refuse_finished",
]

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
# -- a theta to start from --------------------------------------------------------------
def read_theta(source: str | os.PathLike, n: int) -> tuple[Theta, str]:
    """The theta of ``source`` for ``n`` batteries, and what it is (for messages).

    ``source`` is one of: a ``tune`` result (its directory or its ``tune.json``:
    ``theta_best``); a run directory of ``learn`` (the theta after its last update); a JSON
    file of a theta's parts (``{"alpha": [...], ..., "T3": [...]}``, as
    :meth:`~mpcrl_lite.theta.Theta.to_dict` writes and ``summary.json``'s ``theta_final``
    holds), or any JSON object with such a dict under ``theta_best`` or ``theta_final``.
    Anything else, a theta for another ``n`` or one with entries that are not finite is a
    ``ValueError`` naming the source and what was expected.
    """
    path = Path(source)
    expected = ("expected a tune directory or tune.json, a learn run directory, or a JSON "
                "file of theta's parts")
    if not path.exists():
        raise ValueError(f"--theta0 {source}: no such file or directory; {expected}")
    if path.is_dir():
        if (path / "tune.json").is_file():
            theta, what = _theta_of_json(path / "tune.json", source, expected)
        else:
            try:
                history = History.load(path)
            except Exception as err:  # noqa: BLE001 (any unreadable run is the same error)
                raise ValueError(_one_line(f"--theta0 {source}: a directory with neither "
                                           f"tune.json nor a readable run ({err}); "
                                           f"{expected}")) from None
            if not history.theta_final:
                raise ValueError(f"--theta0 {source}: the run has no months; {expected}")
            theta, what = history.final_theta(), f"the last theta of the run in {source}"
    else:
        theta, what = _theta_of_json(path, source, expected)
    if theta.n != n:
        raise ValueError(f"--theta0 {source}: a theta for n={theta.n} batteries; expected "
                         f"n={n}")
    return theta, what


def _theta_of_json(path: Path, source: str | os.PathLike, expected: str) -> tuple[Theta, str]:
    try:
        data = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
        raise ValueError(_one_line(f"--theta0 {source}: not a readable JSON file ({err}); "
                                   f"{expected}")) from None
    if not isinstance(data, dict):
        raise ValueError(f"--theta0 {source}: a JSON {type(data).__name__}; {expected}")  # noqa: TRY004
    for key, what in (("theta_best", "the best theta of the search in"),
                      ("theta_final", "the last theta of")):
        if isinstance(data.get(key), dict):
            data, label = data[key], f"{what} {source}"
            break
    else:
        label = f"the theta in {source}"
    try:
        return Theta.from_dict(data), label
    except (ValueError, TypeError) as err:
        raise ValueError(_one_line(f"--theta0 {source}: {err}; {expected}")) from None


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
        (:class:`~mpcrl_lite.learning.outdir.RunDirError`) one line with the remedy.
    """
    refuse_finished(path, outputs, force, flag)
    return check_output_dir(path, flag)
