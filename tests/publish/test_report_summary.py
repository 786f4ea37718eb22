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


def test_the_kernels_own_log_stays_off_stderr(tmp_path, capfd):
    """The kernel manager interrupts a kernel before shutting it down; a kernel caught in a
    handler then logs ``[IPKernelApp] ERROR | KeyboardInterrupt caught in kernel`` on the
    report's stderr. That log (here written by a cell, deterministically) is silenced."""
    import nbformat

    from mpcrl_lite.publish.report import execute_notebook

    nb = nbformat.v4.new_notebook()
    nb.cells = [nbformat.v4.new_code_cell(
        "from ipykernel.kernelapp import IPKernelApp\n"
        "IPKernelApp.instance().log.error('KeyboardInterrupt caught in kernel')\n"
        "print('ran')")]
    path = tmp_path / "logs.ipynb"
    nbformat.write(nb, path)
    capfd.readouterr()
    done = execute_notebook(path, tmp_path / "out.ipynb", cwd=tmp_path)
    assert done.cells[0].outputs[0]["text"].strip() == "ran"
    assert "KeyboardInterrupt caught in kernel" not in capfd.readouterr().err


def test_a_child_that_ignores_sigterm_does_not_hold_the_finished_kernel(tmp_path):
    """At exit ipykernel signals the children of its process group and waits for them; the
    resource tracker beside a spawned worker ignores the signals. The report's kernel manager
    (``KERNEL_SHUTDOWN_WAIT_S``) then ends the finished kernel after half of its wait instead
    of jupyter_client's 2.5 s. The child here ignores SIGTERM as the tracker does and ends once
    its parent, the kernel, is gone."""
    from datetime import datetime

    import nbformat

    from mpcrl_lite.publish.report import KERNEL_SHUTDOWN_WAIT_S, execute_notebook

    assert KERNEL_SHUTDOWN_WAIT_S / 2 < 2.5  # below jupyter_client's default (5 s) / 2
    child = ("import os, signal, time\n"
             "signal.signal(signal.SIGTERM, signal.SIG_IGN)\n"
             "parent = os.getppid()\n"
             "while os.getppid() == parent:\n"
             "    time.sleep(0.05)\n")
    nb = nbformat.v4.new_notebook()
    nb.cells = [nbformat.v4.new_code_cell(
        f"import subprocess, sys\nkid = subprocess.Popen([sys.executable, '-c', {child!r}])\n"
        "print(kid.poll())")]
    path = tmp_path / "child.ipynb"
    nbformat.write(nb, path)
    done = execute_notebook(path, tmp_path / "out.ipynb", cwd=tmp_path)
    assert done.cells[0].outputs[0]["text"].strip() == "None"  # the child was alive
    stamp = lambda s: datetime.fromisoformat(s.rstrip("Z"))
    tail = (stamp(done.metadata.papermill.end_time)
            - stamp(done.cells[0].metadata.papermill.end_time)).total_seconds()
    # jupyter_client's default would keep the kernel at least 2.5 s here
    assert tail < 2.0, tail
