"""JSON from results that hold numpy values: arrays become lists, numpy scalars numbers.

A learning step's diagnostics, a checkpoint and a notebook's summary all mix Python and numpy
values; :func:`json_default` is the one ``default=`` hook of :func:`json.dumps` for them, and
:func:`plain_json` gives a copy made of JSON types only (what reading the file back gives).
"""

from __future__ import annotations

import json
from typing import Any

import numpy as np

__all__ = ["json_default", "plain_json"]


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
    raise TypeError(f"cannot store {type(value).__name__} in JSON")


def plain_json(value: Any) -> Any:
    """A copy of ``value`` (dicts, lists, numbers, strings, numpy values) made of JSON types
    only, as written and read back."""
    return json.loads(json.dumps(value, default=json_default))
