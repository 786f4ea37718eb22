"""Bidding-zone names: one table of the names each source uses for the same area.

Nord Pool's old exports name the Norwegian zones by city (``Tr.heim`` and ``Molde`` are both
NO3), its data portal and Energi Data Service by code (``NO3``, ``DK2``), ENTSO-E by its
bidding-zone label (``BZN|NO3``). :data:`AREAS` maps each code to its other names (the city
names are those of Nord Pool's yearly exports; the zone a city belongs to is Nord Pool's and
Statnett's published split of Norway into NO1 (Oslo), NO2 (Kristiansand), NO3 (Trondheim,
Molde), NO4 (Tromsø) and NO5 (Bergen)). :func:`canonical` reads any of them (case, spaces and
dots aside, with or without ``BZN|``) as the code.
"""

from __future__ import annotations

import re

__all__ = ["AREAS", "canonical", "find_column"]

#: Area code -> other names, in the order preferred when a file has several columns of one
#: area (``Tr.heim`` before ``Molde``).
AREAS: dict[str, tuple[str, ...]] = {
    "SYS": ("System",),
    "NO1": ("Oslo",),
    "NO2": ("Kr.sand", "Kristiansand"),
    "NO3": ("Tr.heim", "Trondheim", "Molde"),
    "NO4": ("Tromsø", "Tromso"),
    "NO5": ("Bergen",),
    "SE1": ("Luleå", "Lulea"),
    "SE2": ("Sundsvall",),
    "SE3": ("Stockholm",),
    "SE4": ("Malmö", "Malmo"),
    "DK1": ("West Denmark",),
    "DK2": ("East Denmark",),
    "FI": ("Finland",),
    "EE": ("Estonia",),
    "LV": ("Latvia",),
    "LT": ("Lithuania",),
    "DE-LU": ("DE", "Germany"),
    "NL": ("Netherlands",),
    "BE": ("Belgium",),
    "FR": ("France",),
    "AT": ("Austria",),
    "PL": ("Poland",),
}


def _key(name: str) -> str:
    text = re.sub(r"^\s*BZN\s*\|\s*", "", str(name), flags=re.IGNORECASE)
    return re.sub(r"[\s.]", "", text).casefold()


_LOOKUP: dict[str, str] = {}
for _code, _names in AREAS.items():
    for _name in (_code, *_names):
        _LOOKUP[_key(_name)] = _code


def canonical(name: str) -> str:
    """The area code of ``name`` (``'Tr.heim'``, ``'molde'``, ``'BZN|NO3'`` -> ``'NO3'``);
    a name outside :data:`AREAS` is returned without its ``BZN|`` prefix, unchanged otherwise."""
    key = _key(name)
    if key in _LOOKUP:
        return _LOOKUP[key]
    return re.sub(r"^\s*BZN\s*\|\s*", "", str(name), flags=re.IGNORECASE).strip()


def find_column(area: str, columns: list[str], where: str) -> str:
    """The column of ``columns`` holding ``area`` (any name of it); an exact name wins, then
    the preferred alias. One-line error listing the areas found when there is none."""
    if area in columns:
        return area
    code = canonical(area)
    found = [c for c in columns if canonical(c) == code]
    if not found:
        listed = ", ".join(dict.fromkeys(f"{c} ({canonical(c)})" if canonical(c) != c else c
                                         for c in columns))
        raise ValueError(f"area {area!r} is not in {where} (read as {code}); expected one of: "
                         f"{listed}")
    order = [_key(n) for n in (code, *AREAS.get(code, ()))]
    found.sort(key=lambda c: order.index(_key(c)) if _key(c) in order else len(order))
    return found[0]
