"""One table of the notebooks' run times, from the last report, shared by the documents.

``make report`` writes ``reports/summary.json`` with each notebook's wall-clock seconds for
the profile it ran. :func:`record` keeps the latest seconds per profile and notebook in
``notebooks/run_times.json``; :func:`table` writes them as one Markdown table, and
:func:`rewrite` puts that table between the markers

.. code-block:: markdown

    <!-- run-times:begin -->
    ...
    <!-- run-times:end -->

of README.md, notebooks/README.md and notebooks/TEACHING.md (:data:`DOCUMENTS`), so the three
say the same. ``tools/update_run_times.py`` does both; a test checks that the blocks agree
with the file.
"""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any

from .._util.resources import package_folder

__all__ = ["BEGIN", "DOCUMENTS", "END", "RUN_TIMES", "block", "load", "record", "rewrite",
           "table"]

NOTEBOOK_DIR = package_folder("notebooks")
#: The latest run time per profile and notebook (seconds), with where each came from.
RUN_TIMES = NOTEBOOK_DIR / "run_times.json"
#: The documents that show the table (relative to the repository's root).
DOCUMENTS = ("README.md", "notebooks/README.md", "notebooks/TEACHING.md")
BEGIN = "<!-- run-times:begin -->"
END = "<!-- run-times:end -->"
_PROFILE_ORDER = ("full", "classroom", "ci")


def load(path: str | Path = RUN_TIMES) -> dict[str, Any]:
    """``{'profiles': {profile: {'source': str, 'seconds': {stem: s}}}}``."""
    data = json.loads(Path(path).read_text(encoding="utf-8"))
    if not isinstance(data.get("profiles"), dict):
        raise TypeError(f"{path}: expected {{'profiles': {{profile: ...}}}}")
    return data


def record(summary: dict[str, Any], source: str, data: dict[str, Any] | None = None
           ) -> dict[str, Any]:
    """``data`` with the seconds of a report's ``summary`` (its ``profile`` and
    ``notebooks[stem]['seconds']``) replacing the older ones of that profile.

    A report of every notebook the profile has times for becomes the profile's ``source``; a
    report of some of them keeps it and records ``source`` for those notebooks alone
    (``notebook_sources``), so that the table never credits the other notebooks' times to
    it."""
    data = {"profiles": {}} if data is None else json.loads(json.dumps(data))
    profile = summary.get("profile")
    notebooks = summary.get("notebooks")
    if profile not in _PROFILE_ORDER or not isinstance(notebooks, dict) or not notebooks:
        raise ValueError(f"summary: expected a report's summary.json (profile one of "
                         f"{list(_PROFILE_ORDER)}, notebooks with seconds), got profile "
                         f"{profile!r}")
    entry = data["profiles"].setdefault(profile, {"source": source, "seconds": {}})
    if set(notebooks) >= set(entry["seconds"]):
        entry["source"] = source
        entry.pop("notebook_sources", None)
    else:
        alone = entry.setdefault("notebook_sources", {})
        alone.update(dict.fromkeys(notebooks, source))
        entry["notebook_sources"] = dict(sorted(alone.items()))
    for stem, info in notebooks.items():
        entry["seconds"][stem] = float(info["seconds"])
    entry["seconds"] = dict(sorted(entry["seconds"].items()))
    return data


def _shown(seconds: float | None) -> str:
    if seconds is None:
        return "–"
    if seconds < 60:
        return f"{seconds:.0f} s"
    return f"{seconds / 60:.1f} min"


def table(data: dict[str, Any]) -> str:
    """The Markdown table: one row per notebook, one column per profile, then the sources."""
    profiles = [p for p in _PROFILE_ORDER if p in data["profiles"]]
    stems = sorted({s for p in profiles for s in data["profiles"][p]["seconds"]})
    lines = ["| notebook | " + " | ".join(f"{p} profile" for p in profiles) + " |",
             "|---|" + "---:|" * len(profiles)]
    for stem in stems:
        cells = [_shown(data["profiles"][p]["seconds"].get(stem)) for p in profiles]
        lines.append(f"| `{stem}` | " + " | ".join(cells) + " |")
    totals = [sum(data["profiles"][p]["seconds"].values()) for p in profiles]
    lines.append("| all | " + " | ".join(_shown(t) for t in totals) + " |")
    lines.append("")
    sources: dict[str, list[str]] = {}
    for p in profiles:
        entry = data["profiles"][p]
        text = "; ".join([entry["source"]] + [
            f"{stem} alone: {source}" for stem, source in entry.get("notebook_sources", {}).items()])
        sources.setdefault(text, []).append(p)
    said = "; ".join(f"{', '.join(ps)}: {source}" for source, ps in sources.items())
    lines.append("Wall-clock time of each notebook in the last report of each profile "
                 "(`make report`, `REPORT_PROFILE=classroom|ci`), kernel start included ("
                 + said + "). Written by `tools/update_run_times.py` from the report's "
                 "`summary.json`.")
    return "\n".join(lines)


def block(data: dict[str, Any]) -> str:
    """The table between its markers."""
    return f"{BEGIN}\n{table(data)}\n{END}"


_BLOCK = re.compile(re.escape(BEGIN) + r".*?" + re.escape(END), re.DOTALL)


def rewrite(text: str, data: dict[str, Any], name: str = "document") -> str:
    """``text`` with its marked block replaced by :func:`block`; a ``ValueError`` if it has
    not exactly one."""
    found = len(_BLOCK.findall(text))
    if found != 1:
        raise ValueError(f"{name}: expected one block between {BEGIN} and {END}, found {found}")
    return _BLOCK.sub(lambda _m: block(data), text)
