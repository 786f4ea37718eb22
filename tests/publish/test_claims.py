"""The prose's claims (notebooks/claims.yaml): well formed, in their notebooks, checked."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

from mpcrl_lite.publish.claims import Claim, check_claims, load_claims, lookup, missing_texts

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
import nbref


def test_every_claim_names_a_notebook_and_is_in_its_text():
    claims = load_claims()
    assert claims, "notebooks/claims.yaml has no claims"
    stems = set(nbref.stems())
    for stem, entries in claims.items():
        assert stem in stems, f"claims.yaml: unknown notebook {stem}"
        assert not missing_texts(nbref.read_notebook(stem), entries), stem
        for claim in entries:
            assert claim.summary_of in stems, claim.describe()


def test_lookup_follows_dicts_and_list_indices():
    summary = {"a": {"b": [1.5, 2.5]}, "c": True}
    assert lookup(summary, "a.b.1") == 2.5 and lookup(summary, "c") is True
    with pytest.raises(KeyError, match="no 'x'"):
        lookup(summary, "a.x")


def test_check_claims_per_profile_tolerance_and_source():
    claims = {
        "05_x": [Claim("05_x", "about 5.2e7", "grad", 5.2e7, rtol=0.01, source="04_y"),
                 Claim("05_x", "tau 0.1", "tau", 0.1, profiles=("full", "ci")),
                 Claim("05_x", "five", "n", 5, profiles=("ci",))],
    }
    summaries = {"05_x": {"tau": 0.1, "n": 4}, "04_y": {"grad": 5.24e7}}
    full = check_claims(summaries, "full", claims)
    assert full["checked"] == 2 and full["failed"] == []
    ci = check_claims(summaries, "ci", claims)
    assert ci["checked"] == 2 and len(ci["failed"]) == 1 and "gives 4" in ci["failed"][0]
    summaries["04_y"]["grad"] = 5.3e7
    assert len(check_claims(summaries, "full", claims)["failed"]) == 1
    alone = check_claims({"05_x": summaries["05_x"]}, "full", claims)
    assert alone["checked"] == 1 and len(alone["unchecked"]) == 1


def test_malformed_claims_are_named(tmp_path):
    path = tmp_path / "claims.yaml"
    path.write_text("01_a:\n  - text: x\n    value: 1\n")
    with pytest.raises(ValueError, match="claim 1.*missing \\['variable'\\]"):
        load_claims(path)
    path.write_text("01_a:\n  - {text: x, variable: v, value: 1, profiles: [fast]}\n")
    with pytest.raises(ValueError, match="profiles \\['fast'\\]"):
        load_claims(path)
