"""The works the course cites, in one place (notebooks, site, reports).

* :data:`PAPER` -- the paper the package reproduces. Equation numbers written "paper eq. N" in
  the notebooks refer to it (its equations are numbered 1 to 24; the MPC is eq. 9, with parts
  9a-9g).
* :data:`DPG` -- the deterministic policy gradient theorem and compatible critics that the
  paper's learning step builds on.

Sources: the DOI of :data:`PAPER` is the IEEE Xplore record of the CCTA 2021 proceedings
(document 9659202); the preprint is arXiv:2106.03541. :data:`DPG` appeared in the Proceedings
of Machine Learning Research, volume 32 (no DOI).
"""

from __future__ import annotations

from typing import Any

__all__ = ["DPG", "PAPER", "citation_markdown", "citation_text"]

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
