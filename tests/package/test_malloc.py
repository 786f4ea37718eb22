"""Tests of mpcrl_lite._util.malloc: the allocator's thresholds, set once, and the way out."""

from __future__ import annotations

import ctypes
import subprocess
import sys

import pytest

from mpcrl_lite._util import malloc

GLIBC = sys.platform.startswith("linux") and hasattr(ctypes.CDLL(None), "mallopt")


def _in_fresh_process(code: str, env: dict[str, str] | None = None) -> str:
    import os

    return subprocess.run([sys.executable, "-c", code], check=True, capture_output=True,
                          text=True, env={**os.environ, **(env or {})}).stdout.strip()


@pytest.mark.skipif(not GLIBC, reason="mallopt is glibc's")
def test_thresholds_are_set_once_per_process():
    out = _in_fresh_process(
        "from mpcrl_lite._util import malloc; "
        "print(malloc.keep_freed_memory(), malloc.keep_freed_memory(), malloc._applied)")
    assert out == "True True True"


def test_the_environment_variable_leaves_the_allocator_alone():
    out = _in_fresh_process(
        "from mpcrl_lite._util import malloc; print(malloc.keep_freed_memory())",
        env={malloc.ENV: "0"})
    assert out == "False"


@pytest.mark.skipif(not GLIBC, reason="mallopt is glibc's")
def test_arrays_computed_after_the_change_are_the_same():
    """The thresholds change where memory comes from, never a result: the same computation
    before and after, in one fresh process, gives the same bits."""
    code = (
        "import numpy as np; from mpcrl_lite._util import malloc\n"
        "def work():\n"
        "    rng = np.random.default_rng(3); z = rng.standard_normal((720, 204))\n"
        "    zs = z / np.sqrt(np.mean(z**2, axis=0)); m = zs.T @ (zs - 0.5 * zs)\n"
        "    return np.linalg.lstsq(m, zs.T @ z[:, 0], rcond=None)[0].tobytes().hex()\n"
        "a = work(); assert malloc.keep_freed_memory(); b = work(); print(a == b)")
    assert _in_fresh_process(code) == "True"


def test_the_learning_loop_and_the_commands_set_it():
    """Where the long loops start, the thresholds are set (the run's own process)."""
    code = ("from mpcrl_lite._util import malloc\n"
            "from mpcrl_lite.config import LearningConfig\n"
            "from mpcrl_lite.learning.experiment import Experiment\n"
            "assert malloc._applied is None\n"
            "Experiment(learning=LearningConfig(days_per_month=2, eval_every=0)).run(1, "
            "progress=False)\n"
            "print(malloc._applied)")
    assert _in_fresh_process(code) == str(GLIBC)
