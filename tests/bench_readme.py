"""The tables of ``benchmarks/README.md`` as the tests that check them read them.

Used by ``tests/package/test_study_figures.py`` and
``tests/package/test_critic_months_figures.py``.
"""

from __future__ import annotations

from pathlib import Path

BENCH_README = Path(__file__).resolve().parents[1] / "benchmarks" / "README.md"


def bench_row(label: str) -> str:
    """The one row of a table in benchmarks/README.md whose first cell is ``label``."""
    rows = [line for line in BENCH_README.read_text().splitlines()
            if line.startswith(f"| {label} |")]
    assert len(rows) == 1, f"benchmarks/README.md has {len(rows)} rows {label!r}"
    return rows[0]
