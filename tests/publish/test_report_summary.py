"""The summary a notebook shows (mpcrl_lite.publish.report.show_summary): JSON with rounded floats,
made of JSON types by mpcrl_lite._util.jsonio."""

from __future__ import annotations

import json
import math

import IPython.display
import numpy as np
import pytest

from mpcrl_lite._util.jsonio import plain
from mpcrl_lite.publish.report import SUMMARY_DIGITS, SUMMARY_MIME, show_summary


def test_show_summary_rounds_floats_to_significant_digits(monkeypatch):
    shown = []
    monkeypatch.setattr(IPython.display, "display", lambda data, raw: shown.append(data))
    show_summary({
        "J": 1833.9135046460824,
        "tiny": np.float64(1.234567890123e-7),
        "per_agent": np.array([0.1 + 0.2, -2276.961234567]),
        "nested": {"se": 157.41612345, "count": 12, "ok": True, "name": "batch"},
        "nan": float("nan"),
    })
    (data,) = shown
    summary = data[SUMMARY_MIME]
    assert SUMMARY_DIGITS == 6
    assert summary["J"] == 1833.91 and summary["tiny"] == 1.23457e-07
    assert summary["per_agent"] == [0.3, -2276.96]
    assert summary["nested"] == {"se": 157.416, "count": 12, "ok": True, "name": "batch"}
    assert isinstance(summary["nested"]["count"], int) and summary["nested"]["ok"] is True
    assert math.isnan(summary["nan"])
    # the text shows the same rounded numbers: no 16-digit floats
    text = data["text/plain"]
    assert json.loads(text.replace("NaN", "null"))["J"] == 1833.91
    assert "1833.9135" not in text and "0.30000000000000004" not in text


def test_plain_turns_numpy_values_into_json_types():
    value = {"a": np.arange(3), "x": np.float32(0.5), "k": np.int64(7), "ok": np.bool_(True),
             "list": [np.float64(1.5), {"m": np.ones((2, 1))}], "s": "text"}
    plain_value = plain(value, keep_nonfinite=True)
    assert plain(value) == plain_value  # nothing non-finite here: both forms agree
    assert plain_value == {"a": [0, 1, 2], "x": 0.5, "k": 7, "ok": True,
                     "list": [1.5, {"m": [[1.0], [1.0]]}], "s": "text"}
    assert type(plain_value["k"]) is int and type(plain_value["ok"]) is bool
    assert type(plain_value["x"]) is float
    # the input is not changed
    assert isinstance(value["a"], np.ndarray)


def test_values_json_cannot_hold_are_refused_by_name():
    with pytest.raises(TypeError, match="cannot store set in JSON"):
        plain({"bad": {1, 2}})
    with pytest.raises(TypeError, match="cannot store set in JSON"):
        show_summary({"bad": {1, 2}})


def test_plain_turns_nonfinite_into_none_unless_kept():
    value = {"x": float("nan"), "y": [np.inf, 1.0]}
    assert plain(value) == {"x": None, "y": [None, 1.0]}
    kept = plain(value, keep_nonfinite=True)
    assert np.isnan(kept["x"]) and kept["y"] == [np.inf, 1.0]
