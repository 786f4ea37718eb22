"""The progress bars of the long loops (mpcrl_lite._util.progress): a hidden bar imports no tqdm
and takes the calls the loops make; a shown bar is the terminal's tqdm outside a notebook."""

from __future__ import annotations

import io
import subprocess
import sys

from mpcrl_lite._util.progress import progress_bar

_HIDDEN = """
import sys
from mpcrl_lite._util.progress import progress_bar
with progress_bar(total=3, desc="learning", unit="month", disable=True) as bar:
    for _ in range(3):
        bar.set_postfix({"J": "1.0"}, refresh=False)
        bar.update(1)
bar.close()
assert not any(name == "tqdm" or name.startswith("tqdm.") for name in sys.modules), \\
    sorted(name for name in sys.modules if name.startswith("tqdm"))
print("ok")
"""

_SHOWN = """
import io, sys
from mpcrl_lite._util.progress import progress_bar
import tqdm.std
out = io.StringIO()
bar = progress_bar(total=2, desc="learning", unit="month", file=out)
assert type(bar) is tqdm.std.tqdm, type(bar)
assert "asyncio" not in sys.modules
bar.update(2)
bar.close()
assert "2/2" in out.getvalue(), out.getvalue()
print("ok")
"""


def _run(code: str) -> str:
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          timeout=120)
    assert proc.returncode == 0, proc.stderr
    return proc.stdout.strip()


def test_a_hidden_bar_imports_no_tqdm_and_takes_the_loops_calls():
    assert _run(_HIDDEN) == "ok"


def test_a_shown_bar_outside_a_notebook_is_the_terminals_tqdm():
    assert _run(_SHOWN) == "ok"


def test_a_shown_bar_counts_the_months():
    out = io.StringIO()
    with progress_bar(total=4, initial=1, desc="learning", unit="month", file=out) as bar:
        bar.update(3)
    assert "4/4" in out.getvalue() and "learning" in out.getvalue()
