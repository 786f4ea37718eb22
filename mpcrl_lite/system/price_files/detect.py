"""Which source wrote a price file, read from its header.

Each format is recognised by the header line it alone writes (the first of the first
:data:`HEADER_SEARCH_LINES` non-empty lines that matches one):

====================  ============================================================
``nordpool_elspot``   ``;Hours;SYS;...`` (Nord Pool's old yearly export)
``nordpool_portal``   ``Delivery Start (...);Delivery End (...);XX Price (CUR)``
``entsoe``            ``"MTU (...)","Area",...,"Day-ahead Price (EUR/MWh)"``
``entsoe_legacy``     ``"MTU (...)","Day-ahead Price [EUR/MWh]","Currency","BZN|.."``
``energidataservice`` ``HourUTC;HourDK;PriceArea;...`` or ``TimeUTC;TimeDK;PriceArea;...``
====================  ============================================================
"""

from __future__ import annotations

__all__ = ["FORMATS", "HEADER_SEARCH_LINES", "detect_format"]

#: The file formats :func:`detect_format` tells apart (and ``format=`` may name), plus
#: ``pandas`` for a Series.
FORMATS = ("nordpool_elspot", "nordpool_portal", "entsoe", "entsoe_legacy",
           "energidataservice", "pandas")

#: How many non-empty lines are searched for a header.
HEADER_SEARCH_LINES = 20


def _cells(line: str) -> list[str]:
    sep = ";" if line.count(";") >= line.count(",") else ","
    return [c.strip().strip('"').strip() for c in line.split(sep)]


def _which(line: str) -> str | None:
    cells = _cells(line)
    if len(cells) >= 3 and cells[0] == "" and cells[1].lower() == "hours":
        return "nordpool_elspot"
    if len(cells) >= 3 and cells[0].startswith("Delivery Start") \
            and cells[1].startswith("Delivery End") and "Price (" in cells[2]:
        return "nordpool_portal"
    if len(cells) >= 2 and cells[0].startswith("MTU ("):
        if "Area" in cells and any(c.startswith("Day-ahead Price (") for c in cells):
            return "entsoe"
        if cells[1].startswith("Day-ahead Price ["):
            return "entsoe_legacy"
    if len(cells) >= 3 and cells[:3] in (["HourUTC", "HourDK", "PriceArea"],
                                         ["TimeUTC", "TimeDK", "PriceArea"]):
        return "energidataservice"
    return None


def detect_format(text: str, where: str = "file") -> tuple[str, int]:
    """The format of a price file's ``text`` and the index of its header line.

    Raises
    ------
    ValueError
        One line naming the formats expected when no header matches.
    """
    if not isinstance(text, str):
        raise TypeError(f"{where}: expected the file's text, got {type(text).__name__}")
    seen = 0
    for i, line in enumerate(text.split("\n")):
        if not line.strip():
            continue
        found = _which(line)
        if found:
            return found, i
        seen += 1
        if seen >= HEADER_SEARCH_LINES:
            break
    raise ValueError(f"{where} is not a price file this package reads; expected the header of one "
                     f"of {', '.join(FORMATS[:-1])} among the first {HEADER_SEARCH_LINES} lines "
                     "(see README 'Prices from your own files')")
