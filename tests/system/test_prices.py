"""Tests of mpcrl_lite.system.prices: the shipped month, the Nord Pool reader, and price windows."""

from __future__ import annotations

import datetime as dt
import os
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st

from mpcrl_lite.config import PRICE_UNIT, SystemConfig
from mpcrl_lite.system.prices import (
    DATA_DIR,
    Prices,
    daily_matrix,
    load_default_profile,
    load_nordpool_csv,
    nordpool_areas,
)

FIXTURES = Path(__file__).resolve().parents[1] / "fixtures"
SPRING = FIXTURES / "elspot_spring_dst_2021.csv"  # 27..29.03.2021, clock change on the 28th
AUTUMN = FIXTURES / "elspot_autumn_dst_2021.csv"  # 30.10..01.11.2021, clock change on the 31st
NOT_EXPORT = FIXTURES / "not_an_export.csv"
# The real export is read in place (never copied into the project): from
# MPCRL_LITE_NORDPOOL_EXPORT if set, else next to the checkout; its tests skip without it.
REAL_EXPORT = Path(os.environ.get(
    "MPCRL_LITE_NORDPOOL_EXPORT",
    Path(__file__).resolve().parents[3] / "shared/data/nordpool/elspot-prices_2020_hourly_nok.csv",
))


def trheim(day: int, hour: int) -> float:
    """The invented Tr.heim price of the fixtures (see tests/fixtures/make_nordpool_fixtures.py)."""
    return 30.25 + 10 * day + hour


LOCAL = "Europe/Oslo"


def oslo_time(text: str, offset: str) -> pd.Timestamp:
    return pd.Timestamp(f"{text}{offset}").tz_convert("Europe/Oslo")


# ----------------------------------------------------------------------------------------------
# The shipped default month
# ----------------------------------------------------------------------------------------------


def test_data_dir_is_found_through_the_package(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert DATA_DIR.is_absolute()
    assert (DATA_DIR / "no3_nov2020_daily.csv").is_file()
    assert load_default_profile().shape == (30, 24)


def test_default_profile_matches_the_data_readme():
    profile = load_default_profile()
    assert profile.shape == (30, 24)
    assert np.isfinite(profile).all()
    assert profile.mean() == pytest.approx(56.35, abs=0.01)
    assert profile.min() == pytest.approx(6.44, abs=0.01)
    assert profile.max() == pytest.approx(123.18, abs=0.01)


def test_default_profile_is_the_reconstruction_formula():
    shape = pd.read_csv(DATA_DIR / "no3_nov2020_intraday_shape.csv")["shape"].to_numpy()
    daily = pd.read_csv(DATA_DIR / "no3_nov2020_daily.csv")
    assert daily["date"].iloc[0] == "2020-11-01" and daily["date"].iloc[-1] == "2020-11-30"
    # Day 0 by hand: 62.995 + 19.162 * shape[h]; hour 3 is the night minimum of the shape.
    profile = load_default_profile()
    np.testing.assert_allclose(profile[0], 62.995 + 19.162 * shape)
    assert profile[0, 3] == pytest.approx(62.995 + 19.162 * -1.3850)
    np.testing.assert_allclose(
        profile,
        daily["daily_mean"].to_numpy()[:, None] + daily["daily_std"].to_numpy()[:, None] * shape,
    )


def test_default_profile_returns_a_fresh_copy():
    a = load_default_profile()
    a[:] = 0.0
    assert load_default_profile().mean() == pytest.approx(56.35, abs=0.01)


# ----------------------------------------------------------------------------------------------
# Prices
# ----------------------------------------------------------------------------------------------


def ramp_prices(days: int = 3, sell_ratio: float = 0.5) -> Prices:
    """buy[d, h] = 100 d + h, so every value tells its day and hour."""
    buy = 100.0 * np.arange(days)[:, None] + np.arange(24)[None, :]
    return Prices(buy, sell_ratio=sell_ratio, source="ramp")


def test_default_prices():
    prices = Prices.default()
    assert prices.days == 30
    assert prices.unit == PRICE_UNIT == "NOK/MWh"
    assert prices.sell_ratio == 0.5
    np.testing.assert_allclose(prices.buy, load_default_profile())
    np.testing.assert_allclose(prices.sell, 0.5 * prices.buy)
    assert "NO3" in prices.source and "2020" in prices.source
    assert "Prices(days=30" in repr(prices)


def test_default_prices_follow_the_system_config():
    system = SystemConfig(price_scale=0.01, sell_ratio=0.8)
    prices = Prices.default(system)
    np.testing.assert_allclose(prices.buy, 0.01 * load_default_profile())
    np.testing.assert_allclose(prices.sell, 0.8 * 0.01 * load_default_profile())
    assert prices.sell_ratio == 0.8


def test_buy_is_a_read_only_copy():
    raw = np.ones((2, 24))
    prices = Prices(raw)
    raw[:] = 5.0
    assert (prices.buy == 1.0).all()
    with pytest.raises(ValueError):
        prices.buy[0, 0] = 3.0
    with pytest.raises(AttributeError):
        prices.sell_ratio = 0.7  # frozen


def test_window_within_one_day():
    prices = ramp_prices()
    buy, sell = prices.window(hour=5, N=4)
    assert buy.shape == sell.shape == (3, 4)
    np.testing.assert_array_equal(buy[1], [105, 106, 107, 108])
    np.testing.assert_allclose(sell, 0.5 * buy)


def test_window_crosses_midnight_into_the_next_day():
    buy, _ = ramp_prices().window(hour=22, N=4)
    np.testing.assert_array_equal(buy[0], [22, 23, 100, 101])
    np.testing.assert_array_equal(buy[1], [122, 123, 200, 201])


def test_window_after_the_last_day_wraps_to_the_first():
    buy, _ = ramp_prices().window(hour=20, N=12)
    np.testing.assert_array_equal(buy[2], [220, 221, 222, 223, 0, 1, 2, 3, 4, 5, 6, 7])


def test_window_longer_than_a_day():
    buy, _ = ramp_prices().window(hour=23, N=50)
    assert buy.shape == (3, 50)
    # Day 1 at 23:00: 123, then all of day 2 (200..223), then day 0 again (0..24 hours on).
    expected = [123] + [200 + h for h in range(24)] + [h for h in range(24)] + [100]
    np.testing.assert_array_equal(buy[1], expected)
    # A horizon of whole months comes back to the same price.
    long, _ = ramp_prices().window(hour=0, N=3 * 24 + 1)
    np.testing.assert_array_equal(long[:, -1], long[:, 0])


def test_window_matches_a_flattened_cyclic_series():
    prices = Prices.default()
    flat = np.tile(prices.buy.reshape(-1), 3)
    for hour in (0, 7, 23):
        for N in (1, 12, 30):
            buy, sell = prices.window(hour, N)
            for d in (0, 13, 29):
                start = 24 * d + hour
                np.testing.assert_allclose(buy[d], flat[start : start + N])
                np.testing.assert_allclose(sell[d], 0.5 * flat[start : start + N])


@pytest.mark.parametrize(
    ("hour", "N"), [(-1, 12), (24, 12), (3.0, 12), (True, 12), (0, 0), (0, 2.5)]
)
def test_window_rejects_bad_arguments(hour, N):
    with pytest.raises(ValueError, match="hour|N"):
        ramp_prices().window(hour, N)


def test_window_accepts_numpy_integers():
    buy, _ = ramp_prices().window(np.int64(22), np.int32(3))
    np.testing.assert_array_equal(buy[0], [22, 23, 100])


def test_take_makes_a_smaller_cyclic_month():
    small = ramp_prices(days=5).take(2)
    assert small.days == 2
    assert small.sell_ratio == 0.5 and small.unit == PRICE_UNIT
    buy, _ = small.window(hour=23, N=2)
    # The last day of the smaller month is followed by its own day 0 (not by day 2).
    np.testing.assert_array_equal(buy[1], [123, 0])
    assert Prices.default().take(30).days == 30
    with pytest.raises(ValueError, match="at most 5"):
        ramp_prices(days=5).take(6)
    with pytest.raises(ValueError, match="days"):
        ramp_prices(days=5).take(0)


def test_scaled():
    prices = ramp_prices(sell_ratio=0.25)
    double = prices.scaled(2.0)
    np.testing.assert_allclose(double.buy, 2.0 * prices.buy)
    np.testing.assert_allclose(double.sell, 0.5 * prices.buy)
    assert "x2" in double.source
    with pytest.raises(ValueError, match="factor"):
        prices.scaled(-1.0)
    with pytest.raises(ValueError, match="factor"):
        prices.scaled(float("nan"))


def test_to_frame_is_tidy():
    frame = ramp_prices(days=2).to_frame()
    assert list(frame.columns) == ["day", "hour", "buy", "sell"]
    assert len(frame) == 48
    row = frame[(frame["day"] == 1) & (frame["hour"] == 5)].iloc[0]
    assert row["buy"] == 105 and row["sell"] == 52.5
    assert frame.attrs["unit"] == PRICE_UNIT


@pytest.mark.parametrize(
    ("buy", "match"),
    [
        (np.ones(24), r"shape \(days, 24\)"),
        (np.ones((2, 23)), r"shape \(days, 24\)"),
        (np.ones((0, 24)), "at least 1 day"),
        (np.full((2, 24), np.nan), "finite"),
        (np.array([[np.inf] * 24]), "finite"),
        ([["a"] * 24], "real numbers"),
    ],
)
def test_prices_validation(buy, match):
    with pytest.raises(ValueError, match=match):
        Prices(buy)


def test_prices_validation_of_ratio_and_labels():
    with pytest.raises(ValueError, match="sell_ratio"):
        Prices(np.ones((1, 24)), sell_ratio=-0.5)
    with pytest.raises(ValueError, match="sell_ratio"):
        Prices(np.ones((1, 24)), sell_ratio=float("inf"))
    with pytest.raises(ValueError, match="unit"):
        Prices(np.ones((1, 24)), unit=None)


# ----------------------------------------------------------------------------------------------
# Nord Pool reader on hand-written fixtures
# ----------------------------------------------------------------------------------------------


def test_fixtures_have_the_export_layout():
    raw = SPRING.read_bytes()
    assert raw.startswith(b"\xef\xbb\xbf")
    assert b"\r\n" in raw and b"\n" not in raw.replace(b"\r\n", b"")
    text = raw.decode("utf-8-sig")
    assert text.splitlines()[2].startswith(";Hours;")
    assert "28.03.2021;02 - 03;;;;" in text
    assert AUTUMN.read_bytes().decode("utf-8-sig").count("31.10.2021;02 - 03;") == 2


def test_areas_listed_once_in_file_order():
    assert nordpool_areas(SPRING) == ["SYS", "Oslo", "Molde", "Tr.heim", "Tromsø", "EE", "LV"]


def check_hourly_index(series: pd.Series) -> None:
    assert isinstance(series.index, pd.DatetimeIndex)
    assert str(series.index.tz) == "Europe/Oslo"
    utc = series.index.tz_convert("UTC")
    assert utc.is_monotonic_increasing and utc.is_unique
    # One real hour between consecutive values, also across the clock change.
    assert (np.diff(utc.asi8) > 0).all()
    assert set(utc.to_series().diff().dropna()) == {pd.Timedelta(hours=1)}


def test_spring_clock_change_day_has_23_hours():
    series = load_nordpool_csv(SPRING)
    assert series.name == "Tr.heim"
    assert series.dtype == np.float64
    check_hourly_index(series)
    counts = series.groupby(series.index.date).size()
    assert counts.to_dict() == {dt.date(2021, 3, 27): 24, dt.date(2021, 3, 28): 23,
                                dt.date(2021, 3, 29): 24}
    assert len(series) == 71
    # 01:00 (+01:00) is followed directly by 03:00 (+02:00), one hour later.
    assert series[oslo_time("2021-03-28 01:00", "+01:00")] == pytest.approx(trheim(1, 1))
    assert series[oslo_time("2021-03-28 03:00", "+02:00")] == pytest.approx(trheim(1, 3))
    # Values are never shifted: every stamp carries the price written on its own row.
    local = series.index
    expected = [trheim((d.day - 27), h) for d, h in zip(local.date, local.hour)]
    np.testing.assert_allclose(series.to_numpy(), expected)


def test_autumn_clock_change_day_has_25_hours():
    series = load_nordpool_csv(AUTUMN)
    check_hourly_index(series)
    counts = series.groupby(series.index.date).size()
    assert counts[dt.date(2021, 10, 31)] == 25
    assert counts[dt.date(2021, 10, 30)] == 24 and counts[dt.date(2021, 11, 1)] == 24
    # The first 02 - 03 row is summer time, the second winter time.
    summer = oslo_time("2021-10-31 02:00", "+02:00")
    winter = oslo_time("2021-10-31 02:00", "+01:00")
    assert winter - summer == pd.Timedelta(hours=1)
    assert series[summer] == pytest.approx(61.5)
    assert series[winter] == pytest.approx(48.25)
    assert series[oslo_time("2021-10-31 01:00", "+02:00")] == pytest.approx(trheim(1, 1))
    assert series[oslo_time("2021-10-31 03:00", "+01:00")] == pytest.approx(trheim(1, 3))


def test_negative_prices_and_non_ascii_area_names():
    sys_price = load_nordpool_csv(SPRING, area="SYS")
    assert sys_price.iloc[0] == pytest.approx(trheim(0, 0) - 40.0)
    assert (sys_price < 0).any()
    tromso = load_nordpool_csv(SPRING, area="Tromsø")
    assert (tromso == 12.5).all()


def test_molde_equals_trondheim_in_the_fixture():
    pd.testing.assert_series_equal(
        load_nordpool_csv(AUTUMN, area="Molde"), load_nordpool_csv(AUTUMN, area="Tr.heim"),
        check_names=False,
    )


def test_repeated_area_names_use_the_column_holding_data():
    ee = load_nordpool_csv(SPRING, area="EE")  # second EE column on day 1, first on days 2, 3
    assert len(ee) == 71
    np.testing.assert_allclose(ee.to_numpy(), 100.0 + ee.index.hour)
    lv = load_nordpool_csv(SPRING, area="LV")  # the second LV column is always empty
    np.testing.assert_allclose(lv.to_numpy(), 200.0 + lv.index.hour)


def test_repeated_area_with_conflicting_values_is_an_error(tmp_path):
    text = SPRING.read_bytes().decode("utf-8-sig")
    text = text.replace("27.03.2021;00 - 01;-9,75;35,25;30,25;30,25;12,5;;100;",
                        "27.03.2021;00 - 01;-9,75;35,25;30,25;30,25;12,5;99;100;")
    bad = tmp_path / "conflict.csv"
    bad.write_bytes(b"\xef\xbb\xbf" + text.encode("utf-8"))
    with pytest.raises(ValueError, match="'EE'.*different prices"):
        load_nordpool_csv(bad, area="EE")


def test_empty_cell_is_a_missing_hour():
    oslo = load_nordpool_csv(SPRING, area="Oslo")
    assert len(oslo) == 70
    assert oslo_time("2021-03-29 10:00", "+02:00") not in oslo.index
    with pytest.raises(ValueError, match=r"missing.*2021-03-29 10:00"):
        daily_matrix(oslo, "2021-03-29", 1)


def test_plain_lf_file_without_bom_is_read_the_same(tmp_path):
    text = SPRING.read_bytes().decode("utf-8-sig").replace("\r\n", "\n")
    plain = tmp_path / "plain.csv"
    plain.write_text(text, encoding="utf-8", newline="\n")
    pd.testing.assert_series_equal(load_nordpool_csv(plain), load_nordpool_csv(SPRING))


def test_not_an_export():
    with pytest.raises(ValueError, match=r"not_an_export\.csv is not a Nord Pool price export"):
        load_nordpool_csv(NOT_EXPORT)


def test_binary_and_missing_files(tmp_path):
    binary = tmp_path / "prices.xlsx"
    binary.write_bytes(b"PK\x03\x04\xff\xfe\x00\x01" * 20)
    with pytest.raises(ValueError, match="not a Nord Pool price export"):
        load_nordpool_csv(binary)
    with pytest.raises(FileNotFoundError):
        load_nordpool_csv(tmp_path / "nowhere.csv")


def test_unknown_area_lists_the_available_ones():
    with pytest.raises(ValueError, match="unknown area 'NO3'") as err:
        load_nordpool_csv(SPRING, area="NO3")
    assert "SYS, Oslo, Molde, Tr.heim, Tromsø, EE, LV" in str(err.value)


def test_unreadable_cells_are_reported(tmp_path):
    text = SPRING.read_bytes().decode("utf-8-sig")
    bad = tmp_path / "bad_price.csv"
    bad.write_text(text.replace(";30,25;30,25;", ";30,25;n/a;", 1), encoding="utf-8")
    with pytest.raises(ValueError, match=r"27\.03\.2021 00 - 01.*'n/a'"):
        load_nordpool_csv(bad)
    bad_date = tmp_path / "bad_date.csv"
    bad_date.write_text(text.replace("27.03.2021;05 - 06", "2021-03-27;05 - 06"), encoding="utf-8")
    with pytest.raises(ValueError, match="DD.MM.YYYY"):
        load_nordpool_csv(bad_date)


def test_price_in_the_skipped_spring_hour_is_an_error(tmp_path):
    text = SPRING.read_bytes().decode("utf-8-sig")
    bad = tmp_path / "spring_value.csv"
    bad.write_text(
        text.replace("28.03.2021;02 - 03;;;;;", "28.03.2021;02 - 03;1;2;3;4;"), encoding="utf-8"
    )
    with pytest.raises(ValueError, match="does not exist"):
        load_nordpool_csv(bad)


def write_export(path: Path, lines: list[str], bom: bool = True, newline: str = "\r\n") -> Path:
    """An export made of ``lines`` (title, header and data lines, as strings)."""
    path.write_bytes((b"\xef\xbb\xbf" if bom else b"") + newline.join(lines).encode("utf-8"))
    return path


SMALL_HEADER = ";Hours;SYS;Oslo;Tr.heim;Bergen"


def test_a_row_with_a_cell_too_many_or_too_few_is_an_error_naming_the_line(tmp_path):
    rows = ["04.01.2021;00 - 01;10,0;20,0;555,55;40,0",
            "04.01.2021;01 - 02;11,0;999,99;21,0;555,55;41,0",  # one cell too many
            "04.01.2021;02 - 03;12,0;22,0;42,0"]  # one cell too few
    good = write_export(tmp_path / "good.csv", ["Elspot Prices", SMALL_HEADER, rows[0]])
    assert load_nordpool_csv(good).tolist() == [555.55]
    too_many = write_export(tmp_path / "too_many.csv", ["Elspot Prices", SMALL_HEADER, *rows[:2]])
    with pytest.raises(ValueError, match=r"too_many\.csv: line 4 has 7 ';'-separated cells, the "
                                         r"header \(line 2\) has 6"):
        load_nordpool_csv(too_many)  # was read as Tr.heim = 21.0, shifted by one column
    too_few = write_export(tmp_path / "too_few.csv", [SMALL_HEADER, rows[0], rows[2]])
    with pytest.raises(ValueError, match=r"too_few\.csv: line 3 has 5 .* has 6"):
        load_nordpool_csv(too_few, area="Bergen")  # was read as Bergen = NaN, Tr.heim = 42


def test_trailing_separators_count_as_cells(tmp_path):
    lines = [SMALL_HEADER + ";", "04.01.2021;00 - 01;1;2;3;4;", "04.01.2021;01 - 02;1;2;5;;",
             ";;;;;;", ""]  # padding lines of separators and blank lines are not data
    assert load_nordpool_csv(write_export(tmp_path / "ok.csv", lines)).tolist() == [3.0, 5.0]
    # Under a header with a trailing ';', a row without one lacks a cell: it cannot be told
    # from a row with a cell missing in the middle ("1;5;4;" would read Tr.heim = 4).
    lines[2] = "04.01.2021;01 - 02;1;2;5;4"
    with pytest.raises(ValueError, match="line 3 has 6 ';'-separated cells, the header"):
        load_nordpool_csv(write_export(tmp_path / "short.csv", lines))
    lines[2] = "04.01.2021;01 - 02;1;2;5;4;;"
    with pytest.raises(ValueError, match="line 3 has 8"):
        load_nordpool_csv(write_export(tmp_path / "long.csv", lines))


@pytest.mark.parametrize("cell", ["inf", "-Infinity", "1e999", "-1e999", "nan"])
def test_non_finite_prices_are_refused_naming_the_line(tmp_path, cell):
    lines = [SMALL_HEADER, "04.01.2021;00 - 01;1;2;3;4", f"04.01.2021;01 - 02;1;2;{cell};4"]
    path = write_export(tmp_path / "infinite.csv", lines)
    with pytest.raises(ValueError, match=rf"infinite\.csv: area 'Tr.heim', line 3 "
                                         rf"\(04\.01\.2021 01 - 02\).*'{cell}'"):
        load_nordpool_csv(path)
    assert load_nordpool_csv(path, area="Oslo").tolist() == [2.0, 2.0]  # other areas are fine


def test_bytes_that_are_not_utf8_name_the_line(tmp_path):
    path = tmp_path / "latin1.csv"
    path.write_bytes(f"{SMALL_HEADER}\r\n04.01.2021;00 - 01;1;2;3;4\r\n".encode()
                     + "04.01.2021;01 - 02;1;2;3;Troms\u00f8".encode("latin-1"))
    with pytest.raises(ValueError, match=r"latin1\.csv is not a Nord Pool .*; line 3 is not UTF-8"):
        load_nordpool_csv(path)


def test_errors_name_the_line_of_bad_dates_and_hours(tmp_path):
    lines = [SMALL_HEADER, "04.01.2021;00 - 01;1;2;3;4", "2021-01-04;01 - 02;1;2;3;4"]
    with pytest.raises(ValueError, match=r"line 3: cannot read date '2021-01-04'"):
        load_nordpool_csv(write_export(tmp_path / "date.csv", lines))
    lines[2] = "04.01.2021;1-3;1;2;3;4"
    with pytest.raises(ValueError, match=r"line 3: cannot read hour '1-3'"):
        load_nordpool_csv(write_export(tmp_path / "hour.csv", lines))


# -- fuzz: a malformed export gives a clear error or the prices as written, never shifted ------
_AREAS = ["SYS", "Oslo", "Molde", "Tr.heim", "Bergen", "EE"]
_NOT_A_PRICE = ["inf", "-Infinity", "1e999", "nan", "n/a", "1,2,3", "--5", "12 ,5 x"]
_MUTATIONS = ["drop_cell", "add_cell", "not_a_price", "empty_price", "delete_line",
              "duplicate_line", "swap_lines", "blank_line", "separator_line", "truncate",
              "bad_bytes", "bad_date", "bad_hour", "noise"]


def _price_text(code: int, style: int) -> str:
    """``code + 0.5`` with a decimal comma, with or without a thousands separator."""
    whole = f"{code:,}".replace(",", [" ", ".", ""][style])
    return f"{whole},5"


@st.composite
def malformed_exports(draw):
    """An export of ordinary days (no clock change) whose Tr.heim price on line ``r`` of the
    data encodes its column and row: ``1000 * column + r + 0.5``; then a few mutations."""
    areas = draw(st.permutations(_AREAS))[: draw(st.integers(2, len(_AREAS)))]
    if "Tr.heim" not in areas:
        areas = [*areas, "Tr.heim"]
    if areas[-1] == "Tr.heim":  # a cut inside the last cell would keep the cell count
        areas = [*areas, "Tromsø"]
    trailing = draw(st.booleans())
    style = draw(st.integers(0, 2))
    days = draw(st.integers(1, 3))
    lines = [f"Elspot Prices in NOK/MWh{';' * (len(areas) + 1)}"] * draw(st.integers(0, 2))
    lines.append(";Hours;" + ";".join(areas) + (";" if trailing else ""))
    for r in range(24 * days):
        d, h = divmod(r, 24)
        prices = [_price_text(1000 * c + r, style) for c in range(2, len(areas) + 2)]
        cells = [f"{4 + d:02d}.01.2021", f"{h:02d} - {(h + 1) % 24:02d}", *prices]
        lines.append(";".join(cells) + (";" if trailing else ""))
    header = len(lines) - 24 * days - 1
    mutations = draw(st.lists(st.sampled_from(_MUTATIONS), max_size=3))
    if sum(m in ("drop_cell", "add_cell") for m in mutations) > 1:
        # Two opposite edits of one line keep its cell count with shifted values: no reader
        # can see that, so the fuzz makes at most one such edit.
        mutations = [m for m in mutations if m not in ("drop_cell", "add_cell")][:2] + ["add_cell"]
    if "truncate" in mutations and "add_cell" in mutations:
        # A cut that takes the last cell off the line with the added cell is the same pair of
        # opposite edits (its cell count kept, its values shifted: seen with the cut after
        # "4 0" of a line ";;2 000,5;3 000,5;4 000,5;5 000,5" with the empty cell added).
        mutations = [m for m in mutations if m != "add_cell"]
    area_col = 2 + areas.index("Tr.heim")
    cut = bad_byte = None
    for m in mutations:
        event(f"mutation {m}")
        i = draw(st.integers(min(header + 1, len(lines) - 1), len(lines) - 1))  # a data line
        cells = lines[i].split(";")
        if m == "drop_cell":
            del cells[draw(st.integers(0, len(cells) - 1))]
        elif m == "add_cell":
            extra = draw(st.text("0123456789,.- x", max_size=6))
            cells.insert(draw(st.integers(0, len(cells))), extra)
        elif m == "not_a_price" and area_col < len(cells):
            garbage = st.sampled_from(_NOT_A_PRICE) | st.text(max_size=8).map("x".__add__)
            cells[area_col] = draw(garbage)
        elif m == "empty_price" and area_col < len(cells):
            cells[area_col] = ""
        elif m == "bad_date":
            cells[0] = draw(st.sampled_from(["31.02.2021", "2021-01-04", "", "04.13.2021", "x"]))
        elif m == "bad_hour" and len(cells) > 1:
            cells[1] = draw(st.sampled_from(["24 - 01", "1-3", "", "03 - 05", "x"]))
        elif m == "noise":  # a random line anywhere, e.g. in place of the header
            i = draw(st.integers(0, len(lines) - 1))
            cells = [draw(st.text(max_size=30))]
        lines[i] = ";".join(cells)
        if m == "delete_line":
            del lines[draw(st.integers(0, len(lines) - 1))]
        elif m == "duplicate_line":
            j = draw(st.integers(0, len(lines) - 1))
            lines.insert(j, lines[j])
        elif m == "swap_lines":
            j, k = draw(st.integers(0, len(lines) - 1)), draw(st.integers(0, len(lines) - 1))
            lines[j], lines[k] = lines[k], lines[j]
        elif m == "blank_line":
            lines.insert(draw(st.integers(0, len(lines))), "")
        elif m == "separator_line":
            lines.insert(draw(st.integers(0, len(lines))), ";" * draw(st.integers(1, 12)))
        elif m == "truncate":
            cut = draw(st.floats(0.0, 1.0))
        elif m == "bad_bytes":
            bad_byte = draw(st.floats(0.0, 1.0))
    newline = draw(st.sampled_from(["\r\n", "\n"]))
    text = newline.join(lines)
    if cut is not None:
        text = text[: int(cut * len(text))]
    raw = (b"\xef\xbb\xbf" if draw(st.booleans()) else b"") + text.encode("utf-8")
    if bad_byte is not None:
        at = int(bad_byte * len(raw))
        raw = raw[:at] + b"\xff" + raw[at:]
    return raw, area_col, days, bool(mutations)


@settings(max_examples=250, deadline=None,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
@given(export=malformed_exports())
def test_fuzz_nordpool_loader_gives_a_clear_error_or_the_prices_as_written(export,
                                                                           tmp_path_factory):
    raw, area_col, days, mutated = export
    path = tmp_path_factory.getbasetemp() / "fuzzed_export.csv"
    path.write_bytes(raw)
    try:
        series = load_nordpool_csv(path)
    except ValueError as err:
        assert str(path) in str(err), err
        assert mutated, f"an unmodified export was refused: {err}"
        event("clear error")
        return
    event("loaded")
    assert series.name == "Tr.heim" and series.dtype == np.float64
    assert str(series.index.tz) == "Europe/Oslo" and series.index.is_monotonic_increasing
    codes = np.round(series.to_numpy() - 0.5).astype(int)
    column, row = np.divmod(codes, 1000)
    # every value is the one written in the Tr.heim column of the row of its own hour
    assert (column == area_col).all(), "prices read from another area's column"
    stamps = (pd.Timestamp("2021-01-04") + pd.to_timedelta(row, unit="h")).tz_localize(LOCAL)
    assert (stamps == series.index).all(), "prices moved to another hour"
    if not mutated:
        assert len(series) == 24 * days


# ----------------------------------------------------------------------------------------------
# daily_matrix and Prices.from_series
# ----------------------------------------------------------------------------------------------


def test_daily_matrix_on_ordinary_days():
    series = load_nordpool_csv(SPRING)
    matrix = daily_matrix(series, "2021-03-29", 1)
    assert matrix.shape == (1, 24)
    np.testing.assert_allclose(matrix[0], [trheim(2, h) for h in range(24)])
    same = daily_matrix(series, dt.date(2021, 3, 29), 1)
    np.testing.assert_array_equal(same, matrix)


def test_daily_matrix_spring_day_repeats_the_hour_before_the_gap():
    matrix = daily_matrix(load_nordpool_csv(SPRING), "2021-03-27", 3)
    assert matrix.shape == (3, 24)
    expected = np.array([[trheim(d, h) for h in range(24)] for d in range(3)])
    expected[1, 2] = trheim(1, 1)
    np.testing.assert_allclose(matrix, expected)


def test_daily_matrix_autumn_day_averages_the_repeated_hour():
    matrix = daily_matrix(load_nordpool_csv(AUTUMN), "2021-10-30", 3)
    expected = np.array([[trheim(d, h) for h in range(24)] for d in range(3)])
    expected[1, 2] = (61.5 + 48.25) / 2
    np.testing.assert_allclose(matrix, expected)


def test_daily_matrix_errors():
    series = load_nordpool_csv(SPRING)
    with pytest.raises(ValueError, match=r"no prices from 2022-01-01 to 2022-01-02"):
        daily_matrix(series, "2022-01-01", 2)
    with pytest.raises(ValueError, match=r"missing from 2021-03-29 to 2021-03-30"):
        daily_matrix(series, "2021-03-29", 2)
    with pytest.raises(ValueError, match="days"):
        daily_matrix(series, "2021-03-27", 0)
    with pytest.raises(ValueError, match="time-zone-aware"):
        daily_matrix(series.tz_localize(None), "2021-03-27", 1)
    with pytest.raises(ValueError, match="not a time of day"):
        daily_matrix(series, "2021-03-27 05:00", 1)


def test_from_series():
    prices = Prices.from_series(load_nordpool_csv(AUTUMN), "2021-10-30", 3, sell_ratio=0.4)
    assert prices.days == 3 and prices.sell_ratio == 0.4
    assert "Tr.heim" in prices.source and "2021-10-30" in prices.source
    buy, sell = prices.window(hour=23, N=2)
    np.testing.assert_allclose(buy[2], [trheim(2, 23), trheim(0, 0)])
    np.testing.assert_allclose(sell, 0.4 * buy)


# ----------------------------------------------------------------------------------------------
# The real Nord Pool export (read in place; never copied into the project)
# ----------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def real_trheim() -> pd.Series:
    if not REAL_EXPORT.is_file():
        pytest.skip(
            f"real Nord Pool export not found at {REAL_EXPORT} (it is not shipped with the "
            "project because of Nord Pool's terms; see data/README.md)"
        )
    return load_nordpool_csv(REAL_EXPORT, area="Tr.heim")


def test_real_export_november_2020(real_trheim):
    check_hourly_index(real_trheim)
    november = real_trheim[
        (real_trheim.index >= pd.Timestamp("2020-11-01", tz="Europe/Oslo"))
        & (real_trheim.index < pd.Timestamp("2020-12-01", tz="Europe/Oslo"))
    ]
    assert len(november) == 720
    assert november.mean() == pytest.approx(56.35, abs=0.01)
    assert november.min() == pytest.approx(2.89) and november.max() == pytest.approx(128.62)


def test_real_export_clock_change_days(real_trheim):
    counts = real_trheim.groupby(real_trheim.index.date).size()
    assert counts[dt.date(2020, 3, 29)] == 23
    assert counts[dt.date(2020, 10, 25)] == 25
    assert (counts.drop([dt.date(2020, 3, 29), dt.date(2020, 10, 25)]) == 24).all()
    assert len(real_trheim) == 366 * 24  # 2020 is a leap year; the two changes cancel


def test_real_export_molde_equals_trondheim_in_november(real_trheim):
    molde = load_nordpool_csv(REAL_EXPORT, area="Molde")
    nov = slice("2020-11-01", "2020-11-30")
    pd.testing.assert_series_equal(molde.loc[nov], real_trheim.loc[nov], check_names=False)


def test_real_export_matches_the_shipped_profile(real_trheim):
    matrix = daily_matrix(real_trheim, "2020-11-01", 30)
    assert matrix.shape == (30, 24)
    assert matrix.mean() == pytest.approx(56.35, abs=0.01)
    corr = np.corrcoef(matrix.ravel(), load_default_profile().ravel())[0, 1]
    assert corr > 0.97
    prices = Prices.from_series(real_trheim, "2020-11-01", 30)
    assert prices.buy.min() == pytest.approx(2.89)


def test_prices_pickle_with_their_origin():
    """Worker processes started with ``spawn`` (the evaluation worker; ``tune --workers`` where
    spawn is the default) receive prices pickled."""
    import pickle

    prices = Prices(np.full((2, 24), 30.0), origin={"file": "x.csv", "days": 2})
    assert prices.origin  # a read-only mapping, which pickle refuses as such
    back = pickle.loads(pickle.dumps(prices))
    assert type(back) is Prices
    np.testing.assert_array_equal(back.buy, prices.buy)
    assert (back.sell_ratio, back.unit, back.source) == (prices.sell_ratio, prices.unit,
                                                         prices.source)
    assert dict(back.origin) == dict(prices.origin)
    with pytest.raises(TypeError):
        back.origin["days"] = 1  # read-only again


def test_a_window_is_made_once_and_handed_out_read_only():
    prices = ramp_prices()
    buy, sell = prices.window(hour=21, N=6)
    again = prices.window(hour=21, N=6)
    assert again[0] is buy and again[1] is sell
    with pytest.raises(ValueError):
        buy[0, 0] = 1.0
    # the same numbers as a month made anew (whose cache is empty)
    fresh = Prices(prices.buy.copy()).window(hour=21, N=6)
    np.testing.assert_array_equal(buy, fresh[0])
    np.testing.assert_array_equal(sell, fresh[1])
