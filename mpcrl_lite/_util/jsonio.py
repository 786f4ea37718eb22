"""Strict JSON from results that hold numpy values: the one JSON encoding of the package.

A learning step's diagnostics, a checkpoint, a sweep's files and a notebook's summary all mix
Python and numpy values: :func:`dumps` writes them as strict JSON (numpy arrays as lists,
numpy scalars as numbers, paths as strings, every NaN or infinity as ``null`` -- ``NaN`` is
not JSON and other readers reject it), :func:`plain` gives what reading that back gives.
Files are written atomically by :func:`mpcrl_lite.learning.durable.write_json` (fsync, rename).
"""

from __future__ import annotations

import json
import math
import os
from typing import Any

import numpy as np

__all__ = ["dumps", "dumps_by_key", "json_default", "plain", "to_json_types"]


def json_default(value: Any) -> Any:
    """``value`` as a JSON type, for ``json.dumps(..., default=json_default)``.

    Raises
    ------
    TypeError
        For anything but a numpy array or scalar (as :func:`json.dumps` itself would).
    """
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, os.PathLike):
        return os.fspath(value)
    raise TypeError(f"cannot store {type(value).__name__} in JSON")


def to_json_types(value: Any) -> Any:
    """``value`` with numpy values as Python ones and every non-finite float as ``None``."""
    if isinstance(value, np.ndarray):
        value = value.tolist()
    elif isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: to_json_types(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [to_json_types(v) for v in value]
    return value


def dumps(data: Any, indent: int | None = 1, **options: Any) -> bytes:
    """Strict JSON (UTF-8) of ``data``: numpy values as plain numbers, NaN and infinities
    as ``null``; ``options`` go to :func:`json.dumps` (e.g. ``sort_keys``, ``separators``)."""
    try:  # the same text at once where every number is finite (most of the time)
        text = json.dumps(data, indent=indent, allow_nan=False, default=json_default,
                          **options)
    except ValueError:  # a NaN or an infinity: each one made null first
        text = json.dumps(to_json_types(data), indent=indent, allow_nan=False,
                          default=json_default, **options)
    return text.encode("utf-8")


def dumps_by_key(data: dict[str, Any]) -> bytes:
    """:func:`dumps` of an object with one line per top-level key, each value on its line
    as compact JSON (e.g. ``history.json``: a series per line). ``json`` indents only with
    its Python encoder, which took 12 ms for a 100-month History; this is its C encoder's
    speed, and the same JSON."""
    lines = [b'%s: %s' % (dumps(key, indent=None), dumps(value, indent=None))
             for key, value in data.items()]
    return b"{\n " + b",\n ".join(lines) + b"\n}" if lines else b"{}"


def plain(data: Any, keep_nonfinite: bool = False) -> Any:
    """``data`` made of JSON types only (plain lists, dicts, numbers, strings, None), as it
    reads back from :func:`dumps`: NaN and infinities become ``None``, unless
    ``keep_nonfinite`` (a notebook's displayed summary keeps them as ``NaN``/``Infinity``).

    Raises
    ------
    TypeError
        For a value JSON cannot hold (e.g. a set), naming its type.
    """
    if keep_nonfinite:
        return json.loads(json.dumps(data, default=json_default))
    return json.loads(dumps(data, indent=None))
