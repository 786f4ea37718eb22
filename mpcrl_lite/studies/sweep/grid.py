"""Sweep descriptions: read a grid (YAML file or mapping), validate it, build every run.

A sweep is ``{'base': {...}, 'grid': {'section.field': [values]}}`` (the format is described in
:mod:`mpcrl_lite.studies.sweep.api`). :func:`load_grid` builds the three configurations of *every* grid
point before anything runs, so a bad value is reported at once, in one line naming the key or
the grid point, the value and what was expected. Everything a user can get wrong here raises a
:class:`GridError` (a ``ValueError``), including a grid file that is missing, a directory,
unreadable or not valid YAML.
"""

from __future__ import annotations

import hashlib
import itertools
import os
import re
from collections.abc import Mapping
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

import yaml

from ...config import LearningConfig, MPCConfig, PriceFileConfig, SystemConfig, check_grid_bound
from ...system.prices import Prices

__all__ = [
    "SECTIONS",
    "GridError",
    "MissingFileError",
    "Sweep",
    "SweepRun",
    "load_grid",
    "load_yaml",
    "one_line",
]

#: Grid sections and the configuration class each one sets.
SECTIONS: dict[str, type] = {"system": SystemConfig, "mpc": MPCConfig, "learning": LearningConfig,
                             "prices": PriceFileConfig}

_ID_MAX = 100
#: Result columns a grid column must not shadow (the grid key keeps its section then).
_RESERVED = frozenset({
    "run_id", "status", "error", "cached", "months_requested", "months", "J_first", "J_last",
    "hours_soc_below_0_1_first", "hours_soc_below_0_1_last", "max_P_mpc", "skipped_steps",
    "solver_failures", "wall_time_s", "task_time_s", "backend", "run_dir", "notebook",
    "notebook_error",
})
_ID_UNSAFE = re.compile(r"[^A-Za-z0-9._+=,-]")
_BREAK = re.compile(r"\s*[\n\r\v\f\x1c-\x1e\x85\u2028\u2029]+\s*")


class GridError(ValueError):
    """A sweep that cannot be run, found before any run starts; the message is one line."""


class MissingFileError(GridError, FileNotFoundError):
    """A file the sweep needs (the grid, the report notebook) does not exist."""


def one_line(text: Any) -> str:
    """``str(text)`` on one line: each line break, with the blanks around it, becomes a space."""
    return _BREAK.sub(" ", str(text)).strip()


# -- the grid ------------------------------------------------------------------------------
@dataclass(frozen=True)
class SweepRun:
    """One grid point: its id, the values that define it and its three configurations.

    Attributes
    ----------
    run_id : directory name and row key, built from the grid values
    values : ``{'section.field': value}`` of the grid keys, in grid order
    overrides : base overrides and grid values together (every field the sweep sets)
    system, mpc, learning : the validated configurations
    """

    run_id: str
    values: dict[str, Any]
    overrides: dict[str, Any]
    system: SystemConfig
    mpc: MPCConfig
    learning: LearningConfig
    prices: PriceFileConfig = field(default_factory=PriceFileConfig)

    def configs(self) -> dict[str, dict[str, Any]]:
        """The configurations as plain dicts (as stored in ``config.json``); ``prices`` only
        for a run on a price file (runs on the shipped month store what they did before)."""
        return {
            "system": self.system.to_dict(),
            "mpc": self.mpc.to_dict(),
            "learning": self.learning.to_dict(),
            **({"prices": self.prices.to_dict()} if self.prices.file else {}),
        }

    @classmethod
    def from_config(cls, data: Mapping[str, Any]) -> SweepRun:
        """The run of a stored ``config.json`` (``run_id`` and :meth:`configs`); its grid
        values and overrides are not stored there and read as empty."""
        return cls(str(data.get("run_id", "")), {}, {},
                   SystemConfig.from_dict(data["system"]), MPCConfig.from_dict(data["mpc"]),
                   LearningConfig.from_dict(data["learning"]),
                   PriceFileConfig.from_dict(data.get("prices", {})))

    def file_month(self) -> Prices | None:
        """The month of the run's price file, or None for the shipped month (which every
        learner, given None, builds itself)."""
        if not self.prices.file:
            return None
        return Prices.from_file(self.prices, self.system, self.learning.days_per_month)


@dataclass(frozen=True)
class Sweep:
    """A validated sweep: base overrides, grid and the resulting runs (grid order).

    Attributes
    ----------
    base : ``{'section.field': value}`` applied to every run
    grid : ``{'section.field': [values]}``
    columns : ``{'section.field': column}``; the column is the field name unless two
        sections share it
    runs : every grid point
    """

    base: dict[str, Any]
    grid: dict[str, list[Any]]
    columns: dict[str, str]
    runs: tuple[SweepRun, ...]

    @property
    def run_ids(self) -> list[str]:
        """The ids of all runs, in grid order."""
        return [r.run_id for r in self.runs]

    def to_dict(self) -> dict[str, Any]:
        """The sweep in the YAML format (dotted keys; tuples as lists)."""
        def plain(v: Any) -> Any:
            return list(v) if isinstance(v, tuple) else v

        return {
            "base": {k: plain(v) for k, v in self.base.items()},
            "grid": {k: [plain(v) for v in vs] for k, vs in self.grid.items()},
        }


# -- reading a grid file -------------------------------------------------------------------
def _yaml_problem(err: yaml.YAMLError) -> str:
    """One line for a YAML error: where (1-based line and column), what, and in what."""

    def at(mark: Any) -> str:
        return f"line {mark.line + 1}, column {mark.column + 1}"

    if isinstance(err, yaml.MarkedYAMLError) and err.problem_mark is not None:
        text = f"{at(err.problem_mark)}: {err.problem}"
        if err.context:
            started = f" started at {at(err.context_mark)}" if err.context_mark is not None else ""
            text += f" ({err.context}{started})"
        return one_line(text)
    if isinstance(err, yaml.reader.ReaderError):
        return one_line(f"character #x{err.character:04x} at position {err.position}: {err.reason}")
    return one_line(err)


class _UniqueKeyLoader(yaml.SafeLoader):
    """YAML's safe loader, refusing a key written twice in one mapping: YAML keeps the last
    one silently, and a grid that names ``learning.seed`` twice never means that."""

    def construct_mapping(self, node, deep=False):  # type: ignore[override]
        if isinstance(node, yaml.MappingNode):
            seen: dict[Any, Any] = {}
            for key_node, _ in node.value:
                if key_node.tag == "tag:yaml.org,2002:merge":
                    continue
                key = self.construct_object(key_node, deep=True)
                try:
                    first = seen.setdefault(key, key_node)
                except TypeError:  # an unhashable key: the constructor reports it
                    continue
                if first is not key_node:
                    raise yaml.constructor.ConstructorError(
                        None, None, f"key {key!r} is written twice (first at line "
                        f"{first.start_mark.line + 1}); expected each key once",
                        key_node.start_mark)
        return super().construct_mapping(node, deep=deep)


def load_yaml(text: str) -> Any:
    """``yaml.safe_load`` that refuses a key written twice in one mapping (a
    ``yaml.YAMLError`` naming the key and both lines): for grids and system files, where a
    repeated key is a mistake YAML would hide by keeping the last one."""
    return yaml.load(text, Loader=_UniqueKeyLoader)  # a SafeLoader


def _refers_to_itself(value: Any, path: tuple[int, ...] = ()) -> bool:
    # a YAML alias inside its own anchor ('a: &x [*x]') makes a list that contains itself
    if isinstance(value, (list, tuple, dict)):
        if id(value) in path:
            return True
        items = value.items() if isinstance(value, dict) else enumerate(value)
        return any(_refers_to_itself(v, (*path, id(value))) for _, v in items)
    return False


def _read_grid_file(path: Path) -> Any:
    """The YAML document in ``path``; every way to fail is one :class:`GridError` line."""
    name = str(path)
    # a name with a line break or another unprintable character is quoted, so that the
    # message stays one line
    where = f"grid file {name if name.isprintable() else repr(name)}"
    try:
        raw = path.read_bytes()
    except FileNotFoundError:
        raise MissingFileError(f"{where} not found") from None
    except IsADirectoryError:
        raise GridError(f"{where} is a directory; expected a YAML file") from None
    except OSError as err:
        raise GridError(f"{where} cannot be read: {err.strerror or one_line(err)}") from None
    except ValueError as err:  # e.g. a NUL character in the path
        raise GridError(f"{where}: not a usable path ({one_line(err)})") from None
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as err:
        raise GridError(
            f"{where} is not UTF-8 text (byte {raw[err.start]:#04x} at position {err.start})"
        ) from None
    try:
        data = load_yaml(text)
    except yaml.YAMLError as err:
        raise GridError(f"{where}: not valid YAML: {_yaml_problem(err)}") from None
    except RecursionError:
        raise GridError(f"{where}: not valid YAML: nested too deeply") from None
    except ValueError as err:  # a value YAML takes for a date but is none, e.g. 2001-13-45
        raise GridError(f"{where}: not valid YAML: {one_line(err)}") from None
    if _refers_to_itself(data):
        raise GridError(f"{where}: a value contains itself (a YAML alias inside its own anchor)")
    if not isinstance(data, Mapping):
        raise GridError(
            f"{where}: a sweep is a mapping with keys 'base' and 'grid'; "
            f"got {type(data).__name__}"
        )
    return data


# -- validation ----------------------------------------------------------------------------
def _split_key(key: Any, where: str) -> tuple[str, str]:
    if not isinstance(key, str) or key.count(".") != 1:
        raise GridError(
            f"{where} key {key!r}: expected 'section.field' with section one of {list(SECTIONS)}"
        )
    section, name = key.split(".")
    if section not in SECTIONS:
        raise GridError(
            f"{where} key {key!r}: unknown section {section!r}; expected one of {list(SECTIONS)}"
        )
    allowed = [f.name for f in fields(SECTIONS[section])]
    if name not in allowed:
        raise GridError(
            f"{where} key {key!r}: {SECTIONS[section].__name__} has no field {name!r}; "
            f"expected one of {allowed}"
        )
    return section, name


def _as_value(value: Any) -> Any:
    # YAML lists stand for the configs' tuples (omega, omega_f)
    return tuple(value) if isinstance(value, list) else value


def _parse_base(base: Any) -> dict[str, Any]:
    if base is None:
        return {}
    if not isinstance(base, Mapping):
        raise GridError(f"base: expected a mapping of section -> {{field: value}}, got {base!r}")
    flat: dict[str, Any] = {}
    for key, value in base.items():
        if key in SECTIONS:
            if value is None:
                continue
            if not isinstance(value, Mapping):
                raise GridError(f"base.{key}: expected a mapping of field -> value, got {value!r}")
            items = [(f"{key}.{name}", v) for name, v in value.items()]
        elif isinstance(value, Mapping):
            raise GridError(f"base key {key!r}: unknown section; expected one of {list(SECTIONS)}")
        else:
            items = [(key, value)]
        for dotted, v in items:
            _split_key(dotted, "base")
            if dotted in flat:
                raise GridError(f"base key {dotted!r} is given twice")
            flat[dotted] = _as_value(v)
    return flat


def _format_value(value: Any) -> str:
    if isinstance(value, (tuple, list)):
        return "_".join(_format_value(v) for v in value)
    if isinstance(value, float):
        return repr(value)
    return str(value)


def _run_id(values: Mapping[str, Any], columns: Mapping[str, str]) -> str:
    # sorted by column, so reordering the keys of a grid file keeps every run's directory
    pairs = sorted((columns[k], _format_value(v)) for k, v in values.items())
    text = ",".join(f"{name}={value}" for name, value in pairs)
    safe = _ID_UNSAFE.sub("_", text)
    if len(safe) > _ID_MAX:
        digest = hashlib.sha1(text.encode()).hexdigest()[:10]
        safe = f"{safe[: _ID_MAX - 12]}~{digest}"
    return safe


def _yaml_hint(value: Any) -> str:
    if isinstance(value, str):
        try:
            float(value)
        except ValueError:
            return ""
        return f" (YAML read {value!r} as text; write numbers like 1.0e-4 with a dot)"
    return ""


def load_grid(grid: Mapping[str, Any] | str | os.PathLike) -> Sweep:
    """Read and validate a sweep description; build every run's configurations.

    Parameters
    ----------
    grid
        A mapping with keys ``base`` (optional) and ``grid``, or the path of a YAML file
        holding one (see :mod:`mpcrl_lite.studies.sweep.api`).

    Returns
    -------
    Sweep

    Raises
    ------
    GridError
        (a ``ValueError``, message in one line) naming the bad key, value or grid point:
        unknown section or field, a key that is not a non-empty list, a key both in ``base``
        and ``grid``, a value rejected by the configuration's validation, two grid points
        with the same id; or naming the grid file: a directory, unreadable, not UTF-8, not
        valid YAML (with line and column), not a mapping.
    MissingFileError
        (a :class:`GridError` and a ``FileNotFoundError``) if ``grid`` is a path that does not
        exist.
    """
    if isinstance(grid, (str, os.PathLike)):
        data = _read_grid_file(Path(grid))
    else:
        data = grid
    if not isinstance(data, Mapping):
        raise GridError(
            f"a sweep is a mapping with keys 'base' and 'grid'; got {type(data).__name__}"
        )
    if _refers_to_itself(dict(data)):
        raise GridError("a value of the sweep contains itself")
    unknown = sorted(set(data) - {"base", "grid"}, key=repr)
    if unknown:
        raise GridError(
            f"unknown top-level key(s) {unknown}; expected 'base' (optional) and 'grid'"
        )
    base = _parse_base(data.get("base"))
    raw = data.get("grid")
    if not isinstance(raw, Mapping) or not raw:
        raise GridError("'grid' must be a non-empty mapping of 'section.field' -> [values]")

    axes: dict[str, list[Any]] = {}
    for key, values in raw.items():
        _split_key(key, "grid")
        if key in base:
            raise GridError(f"grid key {key!r} is also set in base; keep one of them")
        if not isinstance(values, list):
            raise GridError(f"grid key {key!r}: expected a list of values, got {values!r}")
        if not values:
            raise GridError(f"grid key {key!r}: empty list of values")
        values = [_as_value(v) for v in values]
        for i, v in enumerate(values):
            if v in values[:i]:
                raise GridError(f"grid key {key!r}: value {v!r} is listed twice")
        axes[key] = values

    # a column is named by its field unless that is ambiguous or taken by the results
    names = [k.split(".")[1] for k in axes]
    columns = {
        k: name if names.count(name) == 1 and name not in _RESERVED else k
        for k, name in zip(axes, names)
    }

    runs: list[SweepRun] = []
    seen: dict[str, dict[str, Any]] = {}
    for combo in itertools.product(*axes.values()):
        values = dict(zip(axes, combo))
        run_id = _run_id(values, columns)
        if run_id in seen:
            raise GridError(f"grid points {seen[run_id]} and {values} get the same id {run_id!r}")
        seen[run_id] = values
        overrides = {**base, **values}
        configs = {}
        for section, cls in SECTIONS.items():
            prefix = section + "."
            kwargs = {k[len(prefix):]: v for k, v in overrides.items() if k.startswith(prefix)}
            try:
                configs[section] = cls(**kwargs)
                if section == "system":
                    check_grid_bound(configs[section])
            # ArithmeticError: an integer too large for a float (YAML reads any length)
            except (ValueError, TypeError, ArithmeticError) as err:
                hints = "".join(_yaml_hint(v) for v in kwargs.values())
                # the config's message starts with 'field=value': blame base or the grid point
                field = re.match(r"(\w+)=", str(err))
                key = f"{section}.{field.group(1)}" if field else ""
                where = "base" if key in base else f"grid point {run_id}"
                raise GridError(one_line(f"{where} ({section}): {err}{hints}")) from None
        runs.append(SweepRun(run_id, values, overrides, configs["system"], configs["mpc"],
                             configs["learning"], configs["prices"]))
    return Sweep(base=base, grid=axes, columns=columns, runs=tuple(runs))
