"""Price files of every source format, written by us with invented prices (never real rows).

Each writer takes local days ``[first, last)`` in Europe/Oslo, a period length (15 or 60
minutes) and writes the file the source would write; the price of a period is
:func:`price` of its UTC start, so a test knows every value. The hourly mean of four quarters
of :func:`price` is :func:`hourly_price`.
"""

from __future__ import annotations

from pathlib import Path

import pandas as pd

TZ = "Europe/Oslo"


def price(t: pd.Timestamp, area: str = "NO3") -> float:
    """Invented price of the period starting at ``t``: a number that names the hour (UTC
    hours since 2020) plus its quarter, negative on some hours, different per area."""
    t = t.tz_convert("UTC")
    hours = int((t - pd.Timestamp("2020-01-01", tz="UTC")) / pd.Timedelta(hours=1))
    base = (hours % 97) - 20.5  # negative for some hours
    offset = {"NO3": 0.0, "NO1": 1000.0, "DK2": 0.5, "DK1": 3000.0, "NO4": 4000.0}[area]
    return round(base + offset + 0.25 * (t.minute // 15), 2)


def hourly_price(t: pd.Timestamp, area: str = "NO3", minutes: int = 60) -> float:
    """The hourly mean of :func:`price` for an hour starting at ``t``."""
    if minutes == 60:
        return price(t, area)
    return sum(price(t + pd.Timedelta(minutes=15 * q), area) for q in range(4)) / 4


def periods(first: str, last: str, minutes: int) -> pd.DatetimeIndex:
    """UTC starts of the periods of local days ``[first, last)``."""
    t0 = pd.Timestamp(first).tz_localize(TZ)
    t1 = pd.Timestamp(last).tz_localize(TZ)
    return pd.date_range(t0, t1, freq=f"{minutes}min", inclusive="left").tz_convert("UTC")


def _write(path: Path, lines: list[str], bom: bool = False, crlf: bool = False) -> Path:
    text = ("\r\n" if crlf else "\n").join(lines) + ("\r\n" if crlf else "\n")
    path.write_bytes((b"\xef\xbb\xbf" if bom else b"") + text.encode("utf-8"))
    return path


def _changes(t: pd.Timestamp) -> bool:
    """Whether ``t`` (local) lies on a clock-change day between 01:00 and 04:00."""
    day = t.normalize()
    length = (day + pd.Timedelta(days=1)).tz_localize(None).tz_localize(TZ) - day
    return length != pd.Timedelta(days=1) and 1 <= t.hour < 4


def nordpool_portal(path, first, last, minutes=60, currency="NOK", areas=("NO3", "NO4"),
                    **kw) -> Path:
    lines = ["Delivery Start (CET);Delivery End (CET);"
             + ";".join(f"{a} Price ({currency})" for a in areas)]
    for t in periods(first, last, minutes):
        s = t.tz_convert(TZ)
        e = (t + pd.Timedelta(minutes=minutes)).tz_convert(TZ)
        cells = [f"{price(t, a):.2f}" for a in areas]
        lines.append(f"{s:%d.%m.%Y %H:%M:%S};{e:%d.%m.%Y %H:%M:%S};" + ";".join(cells))
    return _write(Path(path), lines, **kw)


def entsoe(path, first, last, minutes=15, areas=("NO3", "NO1"), utc=False, **kw) -> Path:
    mtu = "MTU (UTC)" if utc else "MTU (CET/CEST)"
    lines = [(f'"{mtu}","Area","Sequence","Day-ahead Price (EUR/MWh)",'
              '"Intraday Period (CET/CEST)","Intraday Price (EUR/MWh)"')]
    for a in areas:
        for t in periods(first, last, minutes):
            s = t if utc else t.tz_convert(TZ)
            e = (t + pd.Timedelta(minutes=minutes))
            e = e if utc else e.tz_convert(TZ)

            def stamp(x):
                text = f"{x:%d/%m/%Y %H:%M:%S}"
                if not utc and _changes(x):
                    text += " (CEST)" if x.utcoffset() == pd.Timedelta(hours=2) else " (CET)"
                return text

            lines.append(f'"{stamp(s)} - {stamp(e)}","BZN|{a}","Without Sequence",'
                         f'"{price(t, a):.2f}","",""')
    return _write(Path(path), lines, **kw)


def entsoe_legacy(path, first, last, area="NO3", future_from=None, **kw) -> Path:
    lines = [f'"MTU (CET/CEST)","Day-ahead Price [EUR/MWh]","Currency","BZN|{area}"']
    for t in periods(first, last, 60):
        s = t.tz_convert(TZ)
        e = (t + pd.Timedelta(hours=1)).tz_convert(TZ)
        value = f"{price(t, area):.2f}"
        if future_from is not None and s >= pd.Timestamp(future_from).tz_localize(TZ):
            value = "-"
        if s.hour == 1 and e.hour == 3:  # spring: the hour that does not exist, present, empty
            lines.append(f'"{s:%d.%m.%Y} 01:00 - {s:%d.%m.%Y} 02:00","{value}","EUR"')
            lines.append(f'"{s:%d.%m.%Y} 02:00 - {s:%d.%m.%Y} 03:00","","EUR"')
            continue
        lines.append(f'"{s:%d.%m.%Y %H:%M} - {e:%d.%m.%Y %H:%M}","{value}","EUR"')
    return _write(Path(path), lines, **kw)


def energidataservice(path, first, last, minutes=60, areas=("DK2", "DK1"), **kw) -> Path:
    if minutes == 60:
        lines = ["HourUTC;HourDK;PriceArea;SpotPriceDKK;SpotPriceEUR"]
    else:
        lines = ["TimeUTC;TimeDK;PriceArea;DayAheadPriceEUR;DayAheadPriceDKK"]
    rows = []
    for t in periods(first, last, minutes):
        for a in areas:
            eur = f"{price(t, a):.2f}".replace(".", ",")
            dkk = f"{price(t, a) * 7.46:.2f}".replace(".", ",")
            local = f"{t.tz_convert(TZ):%Y-%m-%d %H:%M}"
            cells = [f"{t:%Y-%m-%d %H:%M}", local, a] + ([dkk, eur] if minutes == 60
                                                         else [eur, dkk])
            rows.append(";".join(cells))
    return _write(Path(path), lines + rows[::-1], **kw)  # newest first


def nordpool_elspot(path, first, last, areas=("Molde", "Tr.heim", "Oslo"), **kw) -> Path:
    """The old yearly export: title, note, ``;Hours;...`` header, decimal comma."""
    lines = ["Elspot Prices in NOK/MWh", "Data was last updated 01.01.2030", ";Hours;"
             + ";".join(areas)]
    code = {"Molde": "NO3", "Tr.heim": "NO3", "Oslo": "NO1"}
    for t in periods(first, last, 60):
        s = t.tz_convert(TZ)
        e = (s.hour + 1) % 24
        cells = [f"{price(t, code[a]):.2f}".replace(".", ",") for a in areas]
        if s.hour == 1 and (t + pd.Timedelta(hours=1)).tz_convert(TZ).hour == 3:
            lines.append(f"{s:%d.%m.%Y};01 - 02;" + ";".join(cells))
            lines.append(f"{s:%d.%m.%Y};02 - 03;" + ";" * (len(areas) - 1))
            continue
        lines.append(f"{s:%d.%m.%Y};{s.hour:02d} - {e:02d};" + ";".join(cells))
    return _write(Path(path), lines, **kw)


WRITERS = {
    "nordpool_portal": nordpool_portal,
    "entsoe": entsoe,
    "entsoe_legacy": entsoe_legacy,
    "energidataservice": energidataservice,
    "nordpool_elspot": nordpool_elspot,
}
