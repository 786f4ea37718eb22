"""Tests of mpcrl_lite.system.price_files: every source format to the same hourly series.

The files are written by tests/price_fixtures.py with invented prices (a number that names its
hour), so every value read back is known; the real Nord Pool export is read in place when it
is present (never copied into the project).
"""

from __future__ import annotations

import json
import os
import warnings
from pathlib import Path

import numpy as np
import pandas as pd
import price_fixtures as F
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import mpcrl_lite
from mpcrl_lite.bounds.causal.dp import causal_optimum
from mpcrl_lite.bounds.clairvoyant import clairvoyant
from mpcrl_lite.bounds.rule import RuleBasedPolicy
from mpcrl_lite.bounds.scenario import evaluate_policy, make_scenario
from mpcrl_lite.cli.main import main
from mpcrl_lite.config import EUR_NOK_RATE, PRICE_UNIT, SystemConfig
from mpcrl_lite.system.price_files.areas import canonical, find_column
from mpcrl_lite.system.price_files.detect import FORMATS, detect_format
from mpcrl_lite.system.price_files.load import load_prices
from mpcrl_lite.system.price_files.series import PriceFileWarning
from mpcrl_lite.system.prices import Prices, load_nordpool_csv, sell_prices

# the real export, read in place (as in test_prices.py)
REAL_EXPORT = Path(os.environ.get(
    "MPCRL_LITE_NORDPOOL_EXPORT",
    Path(__file__).resolve().parents[3] / "shared/data/nordpool/elspot-prices_2020_hourly_nok.csv",
))
SPRING, AUTUMN = ("2025-03-29", "2025-04-01"), ("2025-10-25", "2025-10-28")

#: (writer, writer options, area asked for): every format, hourly and quarter-hourly.
CASES = {
    "portal_hourly": ("nordpool_portal", {"minutes": 60}, "Tr.heim"),
    "portal_quarters": ("nordpool_portal", {"minutes": 15}, "NO3"),
    "entsoe_quarters": ("entsoe", {"minutes": 15}, "NO3"),
    "entsoe_hourly": ("entsoe", {"minutes": 60}, "BZN|NO3"),
    "entsoe_utc": ("entsoe", {"minutes": 15, "utc": True}, "Molde"),
    "entsoe_legacy": ("entsoe_legacy", {}, None),
    "eds_hourly": ("energidataservice", {"minutes": 60}, "DK2"),
    "eds_quarters": ("energidataservice", {"minutes": 15}, "DK2"),
    "elspot": ("nordpool_elspot", {}, "NO3"),
}


def write(tmp_path, case, days, **more):
    fmt, options, area = CASES[case]
    path = F.WRITERS[fmt](tmp_path / f"{case}.csv", *days, **{**options, **more})
    return path, fmt, area


def expected(series):
    minutes = series.attrs["resolution_min"]
    return np.array([F.hourly_price(t, series.attrs["area"], minutes) for t in series.index])


# -- every format: values, DST lengths, the recorded origin ----------------------------------
@pytest.mark.parametrize("case", list(CASES))
@pytest.mark.parametrize("days, lengths", [(SPRING, [24, 23, 24]), (AUTUMN, [24, 25, 24])])
def test_each_format_loads_the_right_hourly_values_and_dst_lengths(tmp_path, case, days,
                                                                   lengths):
    path, fmt, area = write(tmp_path, case, days)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # nothing missing, nothing reported
        series = load_prices(path, area)
    assert series.attrs["format"] == fmt
    assert detect_format(path.read_bytes().decode("utf-8-sig"))[0] == fmt
    assert series.groupby(series.index.date).size().tolist() == lengths
    assert str(series.index.tz) == "Europe/Oslo" and series.index.is_monotonic_increasing
    steps = series.index.to_series().diff().dropna()
    assert (steps == pd.Timedelta(hours=1)).all()  # one entry per real hour
    np.testing.assert_allclose(series.to_numpy(), expected(series), rtol=0, atol=1e-9)
    assert series.attrs["unit"] == f"{series.attrs['currency']}/MWh"
    assert series.attrs["area"] in ("NO3", "DK2") and series.name == series.attrs["area"]
    assert (series < 0).any()  # the invented prices go negative


def test_quarter_hours_become_hourly_means_and_equal_quarters_stay_exact(tmp_path):
    path = F.entsoe(tmp_path / "q.csv", "2025-11-03", "2025-11-04", 15, areas=("NO3",))
    series = load_prices(path, "NO3")
    assert len(series) == 24 and series.attrs["resolution_min"] == 15
    t = series.index[5]
    quarters = [F.price(t + pd.Timedelta(minutes=15 * q)) for q in range(4)]
    assert series.iloc[5] == pytest.approx(np.mean(quarters), abs=1e-12)
    # an hourly price repeated four times (ENTSO-E before October 2025) is kept bit for bit
    lines = path.read_text().splitlines()
    value = "0.1"
    same = [lines[0]] + [
        ",".join(row.split(",")[:3] + [f'"{value}"', '""', '""']) for row in lines[1:5]]
    (tmp_path / "same.csv").write_text("\n".join(same) + "\n")
    assert load_prices(tmp_path / "same.csv", "NO3").tolist() == [0.1]


def test_bom_crlf_and_decimal_comma_are_read(tmp_path):
    plain = F.nordpool_portal(tmp_path / "a.csv", *AUTUMN, 60)
    dressed = F.nordpool_portal(tmp_path / "b.csv", *AUTUMN, 60, bom=True, crlf=True)
    comma = tmp_path / "c.csv"
    comma.write_text(plain.read_text().replace(".", ",").replace(
        "Delivery", "Delivery").replace(",20", ".20"))  # dates keep their dots
    lines = plain.read_text().splitlines()
    comma.write_text("\n".join([lines[0]] + [
        ";".join(r.split(";")[:2] + [c.replace(".", ",") for c in r.split(";")[2:]])
        for r in lines[1:]]) + "\n")
    a, b, c = (load_prices(p, "NO3") for p in (plain, dressed, comma))
    pd.testing.assert_series_equal(a, b)
    pd.testing.assert_series_equal(a, c)


# -- missing, doubled, empty periods --------------------------------------------------------
def test_a_missing_row_is_reported_never_filled_and_its_month_refused(tmp_path):
    path = F.nordpool_portal(tmp_path / "p.csv", "2025-11-01", "2025-12-01", 60)
    lines = path.read_text().splitlines()
    gone = lines.pop(1 + 24 * 4 + 5)  # 05.11.2025 05:00
    assert gone.startswith("05.11.2025 05:00")
    path.write_text("\n".join(lines) + "\n")
    with pytest.warns(PriceFileWarning, match=r"1 hour\(s\) without a price, the first "
                                              r"2025-11-05 05:00:00\+01:00"):
        series = load_prices(path, "NO3")
    assert np.isnan(series["2025-11-05 05:00"]).all() and series.isna().sum() == 1
    assert series.attrs["missing"] == ["2025-11-05 05:00:00+01:00"]
    with pytest.raises(ValueError, match=r"1 hour\(s\) missing from 2025-11: the first "
                                         r"2025-11-05 05:00:00\+01:00"):
        Prices.from_month(series, "2025-11")


def test_empty_and_dash_cells_are_missing_and_a_future_tail_is_trimmed(tmp_path):
    path = F.entsoe_legacy(tmp_path / "l.csv", "2025-11-01", "2025-11-04",
                           future_from="2025-11-03")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        series = load_prices(path)
    assert len(series) == 48 and series.attrs["trimmed"] == 24  # the "-" hours after the last
    text = path.read_text().replace('"-"', '"1.5"', 24)
    lines = text.splitlines()
    lines[10] = lines[10].replace(lines[10].split(",")[1], '"-"')
    path.write_text("\n".join(lines) + "\n")
    with pytest.warns(PriceFileWarning, match=r"line 11"):
        assert load_prices(path).isna().sum() == 1


def test_a_doubled_row_is_an_error_naming_both_rows(tmp_path):
    path = F.nordpool_portal(tmp_path / "d.csv", "2025-11-01", "2025-11-02", 60)
    lines = path.read_text().splitlines()
    path.write_text("\n".join(lines[:5] + [lines[4]] + lines[5:]) + "\n")
    with pytest.raises(ValueError, match=r"line 6 \(01\.11\.2025 03:00:00\) repeats the period "
                                         r"of line 5") as info:
        load_prices(path, "NO3")
    assert "\n" not in str(info.value)


@pytest.mark.parametrize("bad, match", [
    ("abc", r"line 3 \(01\.11\.2025 01:00:00\): cannot read price 'abc'"),
    ("inf", "cannot read price 'inf'"),
])
def test_a_bad_price_is_named_with_its_row(tmp_path, bad, match):
    path = F.nordpool_portal(tmp_path / "b.csv", "2025-11-01", "2025-11-02", 60)
    lines = path.read_text().splitlines()
    cells = lines[2].split(";")
    lines[2] = ";".join(cells[:2] + [bad] + cells[3:])
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(ValueError, match=match):
        load_prices(path, "NO3")


def test_a_price_in_the_spring_hour_that_does_not_exist_is_an_error(tmp_path):
    path = F.entsoe_legacy(tmp_path / "s.csv", *SPRING)
    path.write_text(path.read_text().replace('"30.03.2025 02:00 - 30.03.2025 03:00",""',
                                             '"30.03.2025 02:00 - 30.03.2025 03:00","7.0"'))
    with pytest.raises(ValueError, match="does not exist in Europe/Oslo"):
        load_prices(path)


# -- areas, currency, formats ---------------------------------------------------------------
def test_area_aliases_name_one_zone():
    assert {canonical(n) for n in ("NO3", "Tr.heim", "molde", "BZN|NO3", " Trondheim ")} \
        == {"NO3"}
    assert canonical("BZN|DK2") == "DK2" and canonical("Kr.sand") == "NO2"
    assert find_column("NO3", ["Oslo", "Molde", "Tr.heim"], "f") == "Tr.heim"
    assert find_column("Molde", ["Oslo", "Molde", "Tr.heim"], "f") == "Molde"  # exact name
    with pytest.raises(ValueError, match=r"area 'Bergen' is not in f \(read as NO5\); expected "
                                         r"one of: Oslo \(NO1\)"):
        find_column("Bergen", ["Oslo"], "f")


def test_areas_of_a_multi_area_file_are_told_apart(tmp_path):
    path = F.entsoe(tmp_path / "e.csv", *AUTUMN, 60, areas=("NO3", "NO1"))
    no1 = load_prices(path, "Oslo")
    assert no1.attrs["area"] == "NO1" and no1.min() > 900  # the NO1 prices are +1000
    with pytest.raises(ValueError, match="area 'SE3' is not in"):
        load_prices(path, "SE3")
    with pytest.raises(ValueError, match="expected area="):
        load_prices(path)


def test_eur_is_converted_to_nok_at_the_stated_rate(tmp_path):
    path = F.entsoe(tmp_path / "e.csv", *AUTUMN, 60, areas=("NO3",))
    eur = load_prices(path, "NO3")
    nok = load_prices(path, "NO3", currency="NOK")
    np.testing.assert_array_equal(nok.to_numpy(), eur.to_numpy() * EUR_NOK_RATE)
    assert nok.attrs["eur_rate"] == EUR_NOK_RATE and nok.attrs["unit"] == PRICE_UNIT
    own = load_prices(path, "NO3", currency="NOK", eur_rate=11.0)
    np.testing.assert_array_equal(own.to_numpy(), eur.to_numpy() * 11.0)
    with pytest.raises(ValueError, match="eur_rate=-1"):
        load_prices(path, "NO3", currency="NOK", eur_rate=-1)
    with pytest.raises(ValueError, match="currency='SEK'"):
        load_prices(path, "NO3", currency="SEK")
    # a month of NOK prices records where they come from
    month = F.entsoe(tmp_path / "m.csv", "2025-11-01", "2025-12-01", 60, areas=("NO3",))
    prices = Prices.from_month(load_prices(month, "NO3", currency="NOK"), "2025-11")
    assert prices.days == 30 and prices.unit == PRICE_UNIT
    assert prices.origin["eur_rate"] == EUR_NOK_RATE and prices.origin["file_currency"] == "EUR"
    with pytest.raises(ValueError, match="prices in EUR/MWh; expected NOK/MWh"):
        Prices.from_month(load_prices(month, "NO3"), "2025-11")


def test_format_can_be_forced_and_unknown_files_are_refused(tmp_path):
    path = F.energidataservice(tmp_path / "x.csv", *AUTUMN, 60)
    forced = load_prices(path, "DK2", format="energidataservice")
    pd.testing.assert_series_equal(forced, load_prices(path, "DK2"))
    with pytest.raises(ValueError, match="format='csv'"):
        load_prices(path, "DK2", format="csv")
    other = tmp_path / "o.csv"
    other.write_text("time,price\n2025-11-01T00:00,30.25\n")
    with pytest.raises(ValueError, match="not a price file this package reads"):
        load_prices(other, "NO3")


def test_a_pandas_series_as_entsoe_py_returns_it():
    index = pd.date_range("2025-10-26", "2025-10-27", freq="15min", inclusive="left",
                          tz="Europe/Brussels")
    raw = pd.Series([F.price(t) for t in index], index=index)
    series = mpcrl_lite.load_prices(raw, "NO3")
    assert len(series) == 25 and series.attrs["currency"] == "EUR"
    np.testing.assert_allclose(series.to_numpy(), expected(series), atol=1e-9)
    with pytest.raises(ValueError, match="time-zone-aware"):
        load_prices(raw.tz_localize(None), "NO3")


# -- the detector, fuzzed --------------------------------------------------------------------
HEADERS = {
    "nordpool_elspot": ";Hours;SYS;Tr.heim",
    "nordpool_portal": "Delivery Start (CET);Delivery End (CET);NO3 Price (NOK)",
    "entsoe": '"MTU (CET/CEST)","Area","Sequence","Day-ahead Price (EUR/MWh)"',
    "entsoe_legacy": '"MTU (CET/CEST)","Day-ahead Price [EUR/MWh]","Currency","BZN|FI"',
    "energidataservice": "HourUTC;HourDK;PriceArea;SpotPriceDKK;SpotPriceEUR",
}
noise = st.text(st.characters(blacklist_categories=("Cs",), blacklist_characters="\n\r"),
                max_size=60).filter(lambda line: not any(h in line for h in ("Hours", "MTU",
                                                                              "Delivery",
                                                                              "UTC;")))


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.lists(noise, max_size=8), st.sampled_from(sorted(HEADERS)), st.booleans())
def test_the_detector_finds_each_header_after_any_preamble(preamble, fmt, crlf):
    text = "\n".join([*preamble, HEADERS[fmt], "01.01.2025;1"])
    found, line = detect_format(text)
    assert found == fmt and text.split("\n")[line] == HEADERS[fmt]


@settings(max_examples=150, deadline=None)
@given(st.lists(noise, max_size=25))
def test_the_detector_refuses_text_without_a_header_in_one_line(lines):
    with pytest.raises(ValueError, match="not a price file") as info:
        detect_format("\n".join(lines))
    assert "\n" not in str(info.value)
    assert set(FORMATS) >= set(HEADERS)


# -- negative prices in the baselines and bounds ---------------------------------------------
def negative_month(days: int = 2) -> Prices:
    buy = Prices.default().buy[:days] - 60.0  # about half the hours below zero
    assert (buy < 0).mean() > 0.3
    return Prices(buy)


def test_sell_never_pays_more_than_buy():
    buy = np.array([-10.0, -0.0, 0.0, 3.0, 50.0])
    sell = sell_prices(buy, 0.5)
    np.testing.assert_array_equal(sell, [-15.0, 0.0, 0.0, 1.5, 25.0])
    assert (sell <= buy).all()
    prices = negative_month()
    assert (prices.sell <= prices.buy).all()
    buy_w, sell_w = prices.window(20, 12)
    assert (sell_w <= buy_w).all()
    # the paper's month: bit for bit the paper's r * buy
    default = Prices.default()
    np.testing.assert_array_equal(default.sell, 0.5 * default.buy)


def test_rule_baseline_dp_and_clairvoyant_lp_on_negative_prices():
    system = SystemConfig()
    prices = negative_month()
    scenario = make_scenario(system, 2, 0, prices=prices)
    rule = evaluate_policy(RuleBasedPolicy(prices, system), scenario)
    bound = clairvoyant(scenario)
    assert np.isfinite(rule.J) and np.isfinite(bound.J)
    assert np.all(bound.J_per_day <= rule.J_per_day + 1e-6 * np.abs(rule.J_per_day))
    # the rule buys in the negative hours (below the day's median)
    policy = RuleBasedPolicy(prices, system, soc_guard=False)
    hour = int(np.argmin(prices.buy[0]))
    assert (policy(hour, np.full((2, system.n), 0.5))[0] > 0).all()
    dp = causal_optimum(system, prices, grid=13, action_step=0.5)
    assert np.isfinite(dp.J_star_per_day).all()
    assert np.all(bound.J_per_day <= dp.J_star_per_day + 1e-6 * np.abs(dp.J_star_per_day) + 1)


# -- the real Nord Pool export, read in place --------------------------------------------------
@pytest.mark.skipif(not REAL_EXPORT.is_file(), reason=f"real export not found at {REAL_EXPORT}")
def test_the_real_old_export_loads_through_load_prices():
    series = load_prices(REAL_EXPORT, "NO3")
    old = load_nordpool_csv(REAL_EXPORT, "Tr.heim")
    np.testing.assert_array_equal(series.dropna().to_numpy(), old.to_numpy())
    assert series.attrs["format"] == "nordpool_elspot" and series.attrs["currency"] == "NOK"
    november = Prices.from_month(series, "2020-11")
    assert november.days == 30 and november.origin["column"] == "Tr.heim"
    days = series.groupby(series.index.date).size()
    assert days[pd.Timestamp("2020-03-29").date()] == 23
    assert days[pd.Timestamp("2020-10-25").date()] == 25


# -- the command line, one small run per format ------------------------------------------------
@pytest.mark.parametrize("case", ["portal_quarters", "entsoe_quarters", "entsoe_legacy",
                                  "eds_quarters", "elspot"])
def test_learn_on_a_month_of_each_format(tmp_path, case, capsys):
    path, fmt, area = write(tmp_path, case, ("2025-11-01", "2025-12-01"))
    area = area or "NO3"
    out = tmp_path / "run"
    code = main(["learn", "--prices", str(path), "--area", area, "--month", "2025-11",
                 "--months", "1", "--days", "2", "--no-figures", "--quiet", "--out", str(out)])
    assert code == 0, capsys.readouterr().err
    summary = json.loads((out / "summary.json").read_text())
    origin = summary["prices_origin"]
    assert origin["format"] == fmt and origin["month"] == "2025-11" and origin["days"] == 2
    assert origin["unit"] == PRICE_UNIT
    if origin["file_currency"] == "EUR":
        assert origin["eur_rate"] == EUR_NOK_RATE
    history = json.loads((out / "history.json").read_text())
    assert history["prices_origin"] == origin


def test_cli_price_options_are_checked(tmp_path, capsys):
    path, _, _ = write(tmp_path, "entsoe_quarters", ("2025-11-01", "2025-12-01"))
    cases = [
        (["--area", "NO3"], "--area given without --prices"),
        (["--prices", str(path), "--area", "NO3", "--month", "2025-10"], "no prices from"),
        (["--prices", str(path), "--month", "2025-11"], "expected area="),
        (["--prices", str(path), "--area", "NO3", "--month", "2025-11", "--eur-rate", "0"],
         "--eur-rate 0"),
        (["--prices", str(path), "--area", "NO3", "--month", "2025-11", "--price-format",
          "nordpool_portal"], "Nord Pool portal header"),
    ]
    for extra, match in cases:
        code = main(["simulate", "--days", "1", "--out", str(tmp_path / "o"), "--quiet", *extra])
        err = capsys.readouterr().err.strip()
        assert code == 2 and match in err and len(err.splitlines()) == 1, err


def test_study_runs_on_a_price_file_through_the_sweep_base(tmp_path, capsys):
    path, _, _ = write(tmp_path, "portal_quarters", ("2025-11-01", "2025-12-01"))
    out = tmp_path / "study"
    code = main(["study", "--seeds", "1", "--months", "1", "--days", "2", "--prices", str(path),
                 "--area", "NO3", "--month", "2025-11", "--target", "best_seen", "--workers",
                 "0", "--quiet", "--out", str(out)])
    assert code == 0, capsys.readouterr().err
    config = json.loads(next(out.rglob("config.json")).read_text())
    assert config["prices"]["file"] == str(path.resolve())
    assert config["prices"]["month"] == "2025-11" and config["learning"]["days_per_month"] == 2
    history = json.loads(next(out.rglob("history.json")).read_text())
    assert history["prices_origin"]["format"] == "nordpool_portal"


def test_baselines_record_the_origin_of_file_prices(tmp_path, capsys):
    path, _, _ = write(tmp_path, "eds_hourly", ("2025-11-01", "2025-12-01"))
    out = tmp_path / "bl"
    code = main(["baselines", "--prices", str(path), "--area", "DK2", "--month", "2025-11",
                 "--days", "1", "--eur-rate", "11.5", "--quiet", "--out", str(out)])
    assert code == 0, capsys.readouterr().err
    origin = json.loads((out / "baselines.json").read_text())["scenario"]["prices_origin"]
    assert origin["format"] == "energidataservice" and origin["area"] == "DK2"
    assert origin["eur_rate"] == 11.5 and origin["days"] == 1


def test_a_preamble_before_the_header_keeps_the_line_numbers_and_times_without_seconds(tmp_path):
    path = F.nordpool_portal(tmp_path / "p.csv", "2025-11-01", "2025-11-02", 60)
    lines = path.read_text().splitlines()
    short = [lines[0]] + [r.replace(":00:00;", ":00;").replace(":00:00", ":00") for r in lines[1:]]
    cells = short[3].split(";")
    short[3] = ";".join(cells[:2] + ["x"] + cells[3:])
    path.write_text("\n".join(["Day-ahead prices, exported 2025-11-02", "", *short]) + "\n")
    with pytest.raises(ValueError, match=r"line 6 \(01\.11\.2025 02:00\): cannot read price 'x'"):
        load_prices(path, "NO3")
    short[3] = ";".join(cells)
    path.write_text("\n".join(short) + "\n")
    np.testing.assert_allclose(load_prices(path, "NO3").to_numpy(),
                               [F.price(t) for t in F.periods("2025-11-01", "2025-11-02", 60)])
