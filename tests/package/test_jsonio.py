"""The package's one JSON encoding: numpy values as plain numbers, every NaN or infinity as
null, and the same text whether or not a value needed converting."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from mpcrl_lite._util import jsonio


def slow(data, **options) -> bytes:
    """What dumps gives by converting everything first."""
    return json.dumps(jsonio.to_json_types(data), allow_nan=False,
                      default=jsonio.json_default, **options).encode()


def values(rng: np.random.Generator, depth: int = 0):
    """A random nest of what results hold: Python and numpy numbers, arrays, tuples,
    dicts, strings, paths, None and booleans (finite numbers only)."""
    kinds = ["float", "npfloat", "npint", "int", "str", "none", "bool", "npbool", "path",
             "f32"]
    if depth < 3:
        kinds += ["list", "tuple", "dict", "array"]
    kind = kinds[rng.integers(len(kinds))]
    number = float(rng.standard_normal() * 10.0 ** rng.integers(-5, 6))
    if kind in ("list", "tuple"):
        items = [values(rng, depth + 1) for _ in range(rng.integers(0, 4))]
        return items if kind == "list" else tuple(items)
    if kind == "dict":
        return {f"k{i}": values(rng, depth + 1) for i in range(rng.integers(0, 4))}
    return {"float": number, "npfloat": np.float64(number), "npint": np.int64(rng.integers(99)),
            "int": int(rng.integers(99)), "str": "a\"b\u00e9", "none": None, "bool": True,
            "npbool": np.bool_(False), "path": Path("/tmp/x"), "f32": np.float32(number),
            "array": rng.standard_normal((2, 3))}[kind]


@pytest.mark.parametrize("options", [{"indent": None}, {"indent": 1},
                                     {"indent": None, "sort_keys": True}])
def test_dumps_is_the_converted_text_for_any_finite_nest(options):
    rng = np.random.default_rng(7)
    for _ in range(300):
        data = {"x": values(rng)}
        assert jsonio.dumps(data, **options) == slow(data, **options)


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf, np.float64("nan"),
                                 np.array([1.0, np.inf]), np.float32("nan")])
def test_every_non_finite_number_is_null(bad):
    data = {"a": [1.5, bad, {"b": (bad, 2)}], "c": np.arange(3)}
    text = jsonio.dumps(data, indent=None)
    assert b"NaN" not in text and b"Infinity" not in text
    assert text == slow(data, indent=None)
    assert json.loads(text)["a"][2]["b"][1] == 2
    assert jsonio.plain(data) == json.loads(text)


def test_what_json_cannot_hold_is_named():
    with pytest.raises(TypeError, match="set"):
        jsonio.dumps({"a": {1, 2}})


def test_dumps_by_key_is_the_same_json_a_key_per_line():
    rng = np.random.default_rng(3)
    data = {"format": "x", "J": [1.5, math.nan, np.float64(2.0)], "theta": rng.standard_normal(
        (4, 3)), "nested": {"a": (1, np.int64(2))}, "empty": []}
    text = jsonio.dumps_by_key(data)
    assert json.loads(text) == json.loads(jsonio.dumps(data))
    lines = text.split(b"\n")
    assert lines[0] == b"{" and lines[-1] == b"}" and len(lines) == len(data) + 2
    assert [json.loads(b"{" + line.rstrip(b",") + b"}") for line in lines[1:-1]] == [
        {k: v} for k, v in json.loads(text).items()]
    assert jsonio.dumps_by_key({}) == b"{}" and json.loads(jsonio.dumps_by_key({})) == {}
