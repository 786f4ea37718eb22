"""One run-time table, from the last report, in the three documents that show it."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from mpcrl_lite.publish import run_times

ROOT = Path(__file__).resolve().parents[2]


def test_documents_show_the_table_of_run_times_json():
    data = run_times.load()
    expected = run_times.block(data)
    for name in run_times.DOCUMENTS:
        text = (ROOT / name).read_text(encoding="utf-8")
        assert text.count(run_times.BEGIN) == 1, name
        assert expected in text, f"{name}: run tools/update_run_times.py"


def test_tool_check_agrees():
    result = subprocess.run([sys.executable, str(ROOT / "tools" / "update_run_times.py"),
                             "--check"], capture_output=True, text=True)
    assert result.returncode == 0, result.stdout + result.stderr


def test_a_report_summary_replaces_its_profile_only():
    data = {"profiles": {"full": {"source": "old", "seconds": {"01_a": 10.0, "02_b": 20.0}},
                         "ci": {"source": "old ci", "seconds": {"01_a": 3.0}}}}
    summary = {"profile": "full", "notebooks": {"02_b": {"seconds": 31.4, "results": {}}}}
    new = run_times.record(summary, "report of 2026-12-02", data)
    # a report of one notebook: the profile keeps its source, the notebook gets its own
    assert new["profiles"]["full"] == {"source": "old",
                                       "notebook_sources": {"02_b": "report of 2026-12-02"},
                                       "seconds": {"01_a": 10.0, "02_b": 31.4}}
    assert "full: old; 02_b alone: report of 2026-12-02; ci: old ci" in run_times.table(new)
    assert new["profiles"]["ci"] == data["profiles"]["ci"]
    assert data["profiles"]["full"]["seconds"]["02_b"] == 20.0  # a copy
    table = run_times.table(new)
    assert "| `02_b` | 31 s | 3 s |" not in table  # 02_b has no ci time
    assert "| `02_b` | 31 s | – |" in table and "| all | 41 s | 3 s |" in table
    # a report of every notebook of the profile becomes its source, and the notes go
    whole = {"profile": "full", "notebooks": {"01_a": {"seconds": 9.0}, "02_b": {"seconds": 30.0}}}
    assert run_times.record(whole, "report of 2026-12-03", new)["profiles"]["full"] == {
        "source": "report of 2026-12-03", "seconds": {"01_a": 9.0, "02_b": 30.0}}
    with pytest.raises(ValueError, match="profile"):
        run_times.record({"profile": "fast", "notebooks": {}}, "x", data)


def test_rewrite_replaces_exactly_one_block():
    data = {"profiles": {"ci": {"source": "s", "seconds": {"01_a": 61.0}}}}
    text = f"before\n{run_times.BEGIN}\nold\n{run_times.END}\nafter\n"
    new = run_times.rewrite(text, data)
    assert new.startswith("before\n") and new.endswith("\nafter\n")
    assert "| `01_a` | 1.0 min |" in new and "old" not in new
    assert run_times.rewrite(new, data) == new
    with pytest.raises(ValueError, match="found 0"):
        run_times.rewrite("no block", data, "doc.md")
