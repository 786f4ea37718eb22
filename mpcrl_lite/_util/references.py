"""The works the course cites, in one place (notebooks, site, reports).

* :data:`PAPER` -- the paper the package reproduces. Equation numbers written "eq. N" or
  "paper eq. N" in the notebooks and the package's docstrings refer to it: its equations are
  numbered 1 to 24 in the order of its LaTeX source (every numbered line of an ``align``; the
  MPC is eq. 9 with parts 9a-9g, the value functions 14a-14b, the parametrisation 23a-23c).
  :data:`EQUATIONS` lists each with what it is and where the package implements it;
  :func:`cited_equations` reads the citations of a text (tests check every docstring and
  notebook against the table, and the table against the paper's source).
* :data:`DPG` -- the deterministic policy gradient theorem and compatible critics that the
  paper's learning step builds on.

Sources: the DOI of :data:`PAPER` is the IEEE Xplore record of the CCTA 2021 proceedings
(document 9659202); the preprint is arXiv:2106.03541. :data:`DPG` appeared in the Proceedings
of Machine Learning Research, volume 32 (no DOI).
"""

from __future__ import annotations

import re
from typing import Any, NamedTuple

__all__ = [
    "DPG",
    "EQUATIONS",
    "PAPER",
    "Equation",
    "citation_markdown",
    "citation_text",
    "cited_equations",
    "equation",
]

PAPER: dict[str, Any] = {
    "key": "kordabad2021multiagent",
    "authors": ["Arash Bahari Kordabad", "Wenqi Cai", "Sébastien Gros"],
    "title": "Multi-agent Battery Storage Management using MPC-based Reinforcement Learning",
    "venue": "2021 IEEE Conference on Control Technology and Applications (CCTA)",
    "year": 2021,
    "doi": "10.1109/CCTA48906.2021.9659202",
    "url": "https://doi.org/10.1109/CCTA48906.2021.9659202",
    "preprint": "arXiv:2106.03541",
    "preprint_url": "https://arxiv.org/abs/2106.03541",
}

DPG: dict[str, Any] = {
    "key": "silver2014deterministic",
    "authors": ["David Silver", "Guy Lever", "Nicolas Heess", "Thomas Degris", "Daan Wierstra",
                "Martin Riedmiller"],
    "title": "Deterministic Policy Gradient Algorithms",
    "venue": "Proceedings of the 31st International Conference on Machine Learning (ICML), "
             "PMLR 32, pp. 387-395",
    "year": 2014,
    "doi": None,
    "url": "https://proceedings.mlr.press/v32/silver14.html",
    "preprint": None,
    "preprint_url": None,
}


def _authors(names: list[str]) -> str:
    return names[0] if len(names) == 1 else ", ".join(names[:-1]) + " and " + names[-1]


def citation_text(ref: dict[str, Any]) -> str:
    """Plain text: authors, "title", venue, year, DOI (or address)."""
    where = f"doi:{ref['doi']}" if ref["doi"] else ref["url"]
    return (f"{_authors(ref['authors'])}, \"{ref['title']}\", {ref['venue']}, {ref['year']}, "
            f"{where}.")


def citation_markdown(ref: dict[str, Any]) -> str:
    """Markdown: as :func:`citation_text`, title in italics, DOI and preprint as links."""
    link = (f"doi:[{ref['doi']}]({ref['url']})" if ref["doi"] else f"<{ref['url']}>")
    preprint = (f" (preprint [{ref['preprint']}]({ref['preprint_url']}))"
                if ref["preprint"] else "")
    return (f"{_authors(ref['authors'])}, *{ref['title']}*, {ref['venue']}, {ref['year']}, "
            f"{link}{preprint}.")


class Equation(NamedTuple):
    """One numbered equation of :data:`PAPER`."""

    number: str  #: as printed: ``"9"``, ``"9f"``, ``"14a"``
    label: str | None  #: its ``\\label`` in the paper's LaTeX source, if it has one
    what: str  #: what it is, in a few words
    where: str  #: the package object that implements it (dotted path below ``mpcrl_lite``)


#: The paper's numbered equations in their order, each with the object that implements it;
#: that object's docstring cites the number. Derived from the paper's LaTeX source (the test
#: ``tests/package/test_equations.py`` re-derives the numbering from it).
EQUATIONS: tuple[Equation, ...] = (
    Equation("1", "eq:Dyna0", "battery dynamics with production-demand noise",
             "system.battery.step"),
    Equation("2", "eq:L", "economic stage cost of one battery", "system.battery.agent_costs"),
    Equation("3", None, "stage cost with the soc penalties, summed over batteries",
             "system.battery.agent_costs"),
    Equation("4", "eq:J", "closed-loop performance J", "system.battery.discounted_return"),
    Equation("5", "eq:J_i", "closed-loop performance J^i of one battery",
             "system.battery.discounted_return"),
    Equation("6", None, "grid power P_k", "system.battery.grid_power"),
    Equation("7", "eq:ppeak", "grid peak bound P_k <= P_bar", "mpc.formulation.MPC.build_problem"),
    Equation("8", None, "P_bar below the sum of the batteries' bounds", "config.SystemConfig"),
    Equation("9", "eq:MPC", "the parametrised centralized MPC", "mpc.formulation.MPC"),
    Equation("9a", "eq:MPC:cost", "MPC cost", "mpc.formulation.MPC.build_problem"),
    Equation("9b", "eq:MPC:dynamics", "MPC model", "mpc.formulation.MPC.build_problem"),
    Equation("9c", "eq:MPC:state:cons1", "relaxed stage soc band",
             "mpc.formulation.MPC.build_problem"),
    Equation("9d", "eq:MPC:state:cons2", "relaxed terminal soc band",
             "mpc.formulation.MPC.build_problem"),
    Equation("9e", "eq:MPC:input:cons", "input bounds", "mpc.formulation.MPC.build_problem"),
    Equation("9f", "eq:MPC:ppeak1", "grid peak limits of the plan",
             "mpc.formulation.MPC.build_problem"),
    Equation("9g", "eq:MPC:equality", "initial state", "mpc.formulation.MPC.build_problem"),
    Equation("10", None, "policy of one battery: first planned net power",
             "mpc.formulation.MPC.policy_selector"),
    Equation("11", "eq:pi", "the centralized policy", "mpc.formulation.MPC.policy_selector"),
    Equation("12", None, "gradient step on theta", "learning.update_rules.GradientDescent"),
    Equation("13", "eq:dj", "deterministic policy gradient", "learning.dpg.policy_gradient"),
    Equation("14a", "eq:Q", "action-value function", "learning.lstd.lstd_q"),
    Equation("14b", "eq:V", "value function", "learning.lstd.lstd_v"),
    Equation("14", None, "the value functions of a policy", "learning.lstd.lstd_q"),
    Equation("15", "eq:Q_w", "compatible action-value approximation",
             "learning.lstd.compatible_features"),
    Equation("16", "eq:V_v", "linear value baseline", "learning.lstd.value_baseline_features"),
    Equation("17", "eq:error", "least-squares fit of the critic", "learning.lstd.lstd_q"),
    Equation("18", None, "KKT conditions of the MPC", "mpc.formulation.KKT"),
    Equation("19", None, "Lagrange function of the MPC", "mpc.formulation.KKT"),
    Equation("20", "eq:sensetivity", "policy sensitivity from the KKT conditions",
             "mpc.sensitivity.PolicySensitivity"),
    Equation("21", None, "the first input u_0", "mpc.formulation.MPC.policy_selector"),
    Equation("22", None, "the paper's state features", "learning.lstd.value_features"),
    Equation("23", "eq:approx", "parametrised costs of the MPC", "mpc.formulation.MPC.build_problem"),
    Equation("23a", "eq:L:theta", "parametrised economic cost", "mpc.formulation.MPC.build_problem"),
    Equation("23b", "eq:phi:theta", "parametrised stage cost", "mpc.formulation.MPC.build_problem"),
    Equation("23c", "eq:T:theta", "parametrised terminal cost",
             "mpc.formulation.MPC.build_problem"),
    Equation("24", None, "the learned parameters theta", "theta.Theta"),
)

_BY_NUMBER = {eq.number: eq for eq in EQUATIONS}


def equation(number: str | int) -> Equation:
    """The entry of :data:`EQUATIONS` for ``number`` (``9``, ``"9f"``)."""
    try:
        return _BY_NUMBER[str(number)]
    except KeyError:
        raise ValueError(f"number={number!r}: the paper has no such numbered equation "
                         f"(expected one of {', '.join(_BY_NUMBER)})") from None


_ONE = r"\(?\d+[a-g]?\)?"
_CITATION = re.compile(rf"\b[Ee]qs?\.\s*({_ONE}(?:\s*(?:-|–|,|and|&)\s*{_ONE})*)")


def _expand(first: str, last: str) -> list[str]:
    """``9c``-``9d`` -> 9c, 9d; ``15``-``17`` -> 15, 16, 17; ``23a``-``23c`` -> a, b, c."""
    a, b = re.fullmatch(r"(\d+)([a-g]?)", first), re.fullmatch(r"(\d+)([a-g]?)", last)
    if a is None or b is None:
        return [first, last]
    if a[2] and b[2] and a[1] == b[1]:
        return [a[1] + chr(c) for c in range(ord(a[2]), ord(b[2]) + 1)]
    if not a[2] and not b[2] and int(a[1]) <= int(b[1]):
        return [str(k) for k in range(int(a[1]), int(b[1]) + 1)]
    return [first, last]


def cited_equations(text: str) -> list[str]:
    """Every equation number that ``text`` cites as ``eq. N``, ``eqs. A-B``, ``eqs. A, B``,
    ``eqs. A and B`` or ``Eq. (N)``, in order (ranges expanded)."""
    found: list[str] = []
    for match in _CITATION.finditer(text):
        parts = re.split(r"\s*(-|–|,|and|&)\s*", match[1])
        numbers = [x.strip("()") for x in parts[::2]]
        seps = parts[1::2]
        out = [numbers[0]]
        for sep, number in zip(seps, numbers[1:]):
            if sep in "-–":
                out[-1:] = _expand(out[-1], number)
            else:
                out.append(number)
        found += out
    return found
