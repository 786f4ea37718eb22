"""The summary a notebook shows (mpcrl_lite.report.show_summary): JSON with rounded floats."""

from __future__ import annotations

import json
import math

import IPython.display
import numpy as np

from mpcrl_lite.report import SUMMARY_DIGITS, SUMMARY_MIME, show_summary


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
