"""What the notebooks' prose claims, checked against what they compute.

A sentence such as "the gradient's norm is 5.2·10⁷" is true for one run: the notebook's
defaults (the *full* profile) or a smaller profile. ``notebooks/claims.yaml`` lists such
sentences per notebook, each with the summary entry that holds the number and a tolerance::

    04_deterministic_policy_gradient:
      - text: "the gradient's norm is $5.2\\cdot10^7$"   # exactly as in the notebook
        variable: paper_step.grad_norm                    # path in the notebook's summary
        value: 5.2e7
        rtol: 0.01                                         # or atol; default exact
        profiles: [full]                                   # where the number holds

``variable`` is a dotted path into the dict shown by the notebook's summary cell
(:func:`mpcrl_lite.publish.report.show_summary`); a number in the path indexes a list. A claim
may read another notebook's summary (``source: 04_deterministic_policy_gradient``), e.g. when
notebook 05 repeats a result of notebook 04. ``profiles`` defaults to ``[full]``; a default
of the package, true whatever the profile, says ``[full, classroom, ci]``.

The notebook tests check the claims of the *ci* profile (``tests/notebooks/``) and that every
claim's text is in its notebook; ``make report`` (:func:`mpcrl_lite.publish.report.run_report`)
checks those of the profile it runs and fails on a false one.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from .._util.resources import package_folder

__all__ = ["CLAIMS", "Claim", "check_claims", "load_claims", "lookup", "missing_texts"]

#: The claims of every notebook.
CLAIMS = package_folder("notebooks") / "claims.yaml"
_PROFILES = ("full", "ci", "classroom")


@dataclass(frozen=True)
class Claim:
    """One sentence of a notebook and the number behind it (see the module docstring)."""

    notebook: str
    text: str
    variable: str
    value: Any
    rtol: float = 0.0
    atol: float = 0.0
    profiles: tuple[str, ...] = ("full",)
    source: str = ""
    extra: dict = field(default_factory=dict, compare=False)

    @property
    def summary_of(self) -> str:
        """The notebook whose summary holds ``variable``."""
        return self.source or self.notebook

    def holds(self, actual: Any) -> bool:
        """``actual`` equals ``value`` within the tolerance (exactly for bools and strings)."""
        if isinstance(self.value, (bool, str)) or isinstance(actual, (bool, str)):
            return actual == self.value
        try:
            x, v = float(actual), float(self.value)
        except (TypeError, ValueError):
            return False
        return math.isfinite(x) and abs(x - v) <= self.atol + self.rtol * abs(v)

    def describe(self) -> str:
        tol = (f" +- {self.atol:g}" if self.atol else "") + (
            f" (rel. {self.rtol:g})" if self.rtol else "")
        return f"{self.notebook}: {self.text!r}: {self.summary_of}:{self.variable} = {self.value!r}{tol}"


def load_claims(path: str | Path = CLAIMS) -> dict[str, list[Claim]]:
    """The claims per notebook stem; a malformed entry is a ``ValueError`` naming it."""
    import yaml

    path = Path(path)
    data = yaml.safe_load(path.read_text(encoding="utf-8")) or {}
    if not isinstance(data, dict):
        raise TypeError(f"{path}: expected a mapping of notebook -> list of claims")
    claims: dict[str, list[Claim]] = {}
    for stem, entries in data.items():
        if not isinstance(entries, list):
            raise TypeError(f"{path}: {stem}: expected a list of claims, got {entries!r}")
        for k, entry in enumerate(entries):
            where = f"{path.name}: {stem}, claim {k + 1}"
            if not isinstance(entry, dict):
                raise TypeError(f"{where}: expected a mapping, got {entry!r}")
            unknown = set(entry) - {"text", "variable", "value", "rtol", "atol", "profiles",
                                    "source", "note"}
            missing = {"text", "variable", "value"} - set(entry)
            if unknown or missing:
                raise ValueError(f"{where}: unknown keys {sorted(unknown)}, missing "
                                 f"{sorted(missing)}; expected text, variable, value and "
                                 "optionally rtol, atol, profiles, source, note")
            profiles = tuple(entry.get("profiles", ["full"]))
            bad = [p for p in profiles if p not in _PROFILES]
            if bad:
                raise ValueError(f"{where}: profiles {bad}: expected some of {list(_PROFILES)}")
            value = entry["value"]
            if isinstance(value, str):  # YAML 1.1 reads 5.2e7 (no dot, no sign) as a string
                try:
                    value = float(value)
                except ValueError:
                    pass
            claims.setdefault(str(stem), []).append(Claim(
                notebook=str(stem), text=str(entry["text"]), variable=str(entry["variable"]),
                value=value, rtol=float(entry.get("rtol", 0.0)),
                atol=float(entry.get("atol", 0.0)), profiles=profiles,
                source=str(entry.get("source", "")), extra={"note": entry.get("note", "")}))
    return claims


def lookup(summary: dict[str, Any], variable: str) -> Any:
    """``summary['a']['b'][0]`` for ``'a.b.0'``; a ``KeyError`` naming the missing step."""
    value: Any = summary
    for step in variable.split("."):
        if isinstance(value, list) and step.lstrip("-").isdigit():
            value = value[int(step)]
        elif isinstance(value, dict) and step in value:
            value = value[step]
        else:
            raise KeyError(f"{variable}: no {step!r} in the summary")
    return value


def missing_texts(notebook: Any, claims: list[Claim]) -> list[str]:
    """The claims' texts that the notebook (nbformat node) does not contain."""
    sources = "\n".join(cell.source for cell in notebook.cells)
    return [c.text for c in claims if c.text not in sources]


def check_claims(
    summaries: dict[str, dict[str, Any]], profile: str,
    claims: dict[str, list[Claim]] | None = None,
) -> dict[str, Any]:
    """Check every claim of ``profile`` whose notebook and source summary are in
    ``summaries`` (``{stem: summary}``).

    Returns ``{'profile', 'checked', 'failed': [message, ...], 'unchecked': [...]}``:
    ``unchecked`` are the claims of a notebook that ran whose source notebook did not.
    """
    claims = load_claims() if claims is None else claims
    checked, failed, unchecked = 0, [], []
    for stem, entries in claims.items():
        if stem not in summaries:
            continue
        for claim in entries:
            if profile not in claim.profiles:
                continue
            if claim.summary_of not in summaries:
                unchecked.append(claim.describe())
                continue
            checked += 1
            try:
                actual = lookup(summaries[claim.summary_of], claim.variable)
            except (KeyError, IndexError) as err:
                failed.append(f"{claim.describe()}: {err}")
                continue
            if not claim.holds(actual):
                failed.append(f"{claim.describe()}: the run gives {actual!r}")
    return {"profile": profile, "checked": checked, "failed": failed, "unchecked": unchecked}
