"""Telemetry CSV (spec §1): reading, every refusal, input/sensor checks, exact round trip."""

import math

import numpy as np
import pytest

from thermojax._errors import InputError
from thermojax.measurements._telemetry import (
    Telemetry,
    check_inputs,
    check_sensors,
    read_telemetry,
    write_telemetry,
)


def write(tmp_path, text, name="run.csv"):
    path = tmp_path / name
    path.write_text(text, encoding="utf-8")
    return path


GOOD = """\
# chamber run 3
#   operator: test

time_s,T_chamber,T_core,P_heater
0,25.0,24.9,0
1,25.5,,1.5
  # an indented comment
2,26.0,nan,1.5

3, 26.5 ,25.1,NaN
"""


def test_read_basic_file_with_comments_blanks_and_dropped_samples(tmp_path):
    path = write(tmp_path, GOOD)
    tel = read_telemetry(path)
    np.testing.assert_array_equal(tel.ts, [0.0, 1.0, 2.0, 3.0])
    assert list(tel.channels) == ["T_chamber", "T_core", "P_heater"]
    np.testing.assert_array_equal(tel.channels["T_chamber"], [25.0, 25.5, 26.0, 26.5])
    np.testing.assert_array_equal(tel.channels["T_core"], [24.9, np.nan, np.nan, 25.1])
    np.testing.assert_array_equal(tel.channels["P_heater"], [0.0, 1.5, 1.5, np.nan])
    np.testing.assert_array_equal(tel.lines, [5, 6, 8, 10])  # 1-based file lines, counted by hand
    assert tel.path == str(path)
    assert tel.dt == 1.0
    assert len(tel) == 4
    assert tel.column("time_s") is tel.ts
    assert tel.column("T_core") is tel.channels["T_core"]
    assert all(a.dtype == np.float64 for a in tel.channels.values())


def test_read_quoted_header_and_crlf_and_bom(tmp_path):
    path = tmp_path / "q.csv"
    path.write_bytes(b'\xef\xbb\xbf"time_s","T, outer"\r\n0,1\r\n0.5,"2"\r\n')
    tel = read_telemetry(path)
    assert list(tel.channels) == ["T, outer"]
    np.testing.assert_array_equal(tel.channels["T, outer"], [1.0, 2.0])
    assert tel.dt == 0.5


def test_jitter_under_one_percent_is_tolerated(tmp_path):
    ts = 10.0 * np.arange(50)
    ts[17] += 0.04  # 0.4 % of the 10 s period
    ts[30] -= 0.09  # 0.9 %
    path = write_telemetry(tmp_path / "j.csv", ts, {"T": np.ones(50)})
    tel = read_telemetry(path)
    assert tel.dt == 10.0  # the median step
    np.testing.assert_array_equal(tel.ts, ts)


def test_irregular_step_is_refused_naming_first_line(tmp_path):
    ts = 10.0 * np.arange(50)
    ts[20:] += 0.5  # a 5 % longer step into row 20
    ts[40:] += 30.0  # a gap later on
    path = write_telemetry(tmp_path / "g.csv", ts, {"T": np.ones(50)}, comments=["c"])
    # line 1 comment, line 2 header, row k on line k + 3: row 20 is line 23
    with pytest.raises(InputError, match=r"line 23.*irregular sampling.*[Rr]esample.*split"):
        read_telemetry(path)


# ---------------------------------------------------------------------------
# refusals


def test_missing_file(tmp_path):
    with pytest.raises(InputError, match="nope.csv.*no such file"):
        read_telemetry(tmp_path / "nope.csv")


@pytest.mark.parametrize("text", ["", "\n\n", "# only a comment\n   \n"])
def test_empty_file_or_no_header(tmp_path, text):
    with pytest.raises(InputError, match="no header"):
        read_telemetry(write(tmp_path, text))


def test_first_column_must_be_time_s(tmp_path):
    path = write(tmp_path, "# c\ntime,T\n0,1\n1,2\n")
    with pytest.raises(InputError, match=r"line 2, field 'time'.*expected 'time_s'") as info:
        read_telemetry(path)
    assert info.value.line == 2 and info.value.file == str(path)


def test_duplicate_column_names(tmp_path):
    path = write(tmp_path, "time_s,T,P,T\n0,1,2,3\n1,1,2,3\n")
    with pytest.raises(InputError, match=r"line 1, field 'T'.*twice.*columns 2 and 4"):
        read_telemetry(path)


def test_empty_column_name(tmp_path):
    path = write(tmp_path, "time_s,T,\n0,1,2\n1,1,2\n")
    with pytest.raises(InputError, match=r"line 1.*column 3 .*no name"):
        read_telemetry(path)


@pytest.mark.parametrize("row, cells", [("2,3", 2), ("2,3,4,5", 4), ("2,3,4,", 4)])
def test_wrong_number_of_cells(tmp_path, row, cells):
    path = write(tmp_path, f"time_s,T,P\n0,1,2\n1,1,2\n\n{row}\n3,1,2\n")
    with pytest.raises(InputError, match=rf"line 5: the row has {cells} cells.*3 columns"):
        read_telemetry(path)


def test_wrong_number_of_cells_with_quotes(tmp_path):
    path = write(tmp_path, 'time_s,T\n0,"1"\n1,"1,5",7\n')
    with pytest.raises(InputError, match=r"line 3: the row has 3 cells"):
        read_telemetry(path)


def test_unclosed_quote(tmp_path):
    path = write(tmp_path, 'time_s,T\n0,"1\n1,2\n')
    with pytest.raises(InputError, match=r"line 2.*quote"):
        read_telemetry(path)


@pytest.mark.parametrize("cell", ["abc", "1.2.3", "12 C", "0x10"])
def test_non_numeric_cell_names_line_and_column(tmp_path, cell):
    path = write(tmp_path, f"time_s,T,P\n0,1,2\n# c\n1,1,{cell}\n2,1,2\n")
    with pytest.raises(InputError, match=rf"line 4, field 'P': cell '{cell}'.*not a number") \
            as info:
        read_telemetry(path)
    assert (info.value.line, info.value.field) == (4, "P")


def test_blank_cell_with_spaces_is_a_dropped_sample(tmp_path):
    tel = read_telemetry(write(tmp_path, "time_s,T\n0,  \n1,2\n"))
    np.testing.assert_array_equal(tel.channels["T"], [np.nan, 2.0])


@pytest.mark.parametrize("cell", ["", "nan", "inf", "-inf"])
def test_time_empty_or_non_finite(tmp_path, cell):
    path = write(tmp_path, f"time_s,T\n0,1\n1,1\n{cell},1\n3,1\n")
    with pytest.raises(InputError, match=r"line 4, field 'time_s'.*empty or not finite"):
        read_telemetry(path)


@pytest.mark.parametrize("bad", ["2", "1.5"])
def test_time_not_strictly_increasing_names_first_offending_line(tmp_path, bad):
    path = write(tmp_path, f"time_s,T\n0,1\n1,1\n2,1\n{bad},1\n1,1\n")
    with pytest.raises(InputError, match=r"line 5, field 'time_s'.*strictly increasing"):
        read_telemetry(path)


def test_no_data_rows(tmp_path):
    path = write(tmp_path, "# c\ntime_s,T\n# nothing\n")
    with pytest.raises(InputError, match=r"line 2.*no data rows"):
        read_telemetry(path)


def test_single_data_row(tmp_path):
    with pytest.raises(InputError, match=r"line 2.*single data row"):
        read_telemetry(write(tmp_path, "time_s,T\n0,1\n"))


def test_directory_is_refused(tmp_path):
    with pytest.raises(InputError, match="directory"):
        read_telemetry(tmp_path)


# ---------------------------------------------------------------------------
# input and sensor checks


CHECKS = """\
time_s,T_chamber,P,T_a,T_b,T_c
0,25,1,20,,1
1,25,1,20,,1
2,25,,nan,,inf
3,25,1,20,,1
"""


def test_check_inputs(tmp_path):
    tel = read_telemetry(write(tmp_path, "# comment\n" + CHECKS))
    check_inputs(tel, ["T_chamber"])  # clean column: no error
    with pytest.raises(InputError, match=r"line 5, field 'P': input column 'P' is empty"):
        check_inputs(tel, ["T_chamber", "P"])
    with pytest.raises(InputError, match=r"line 5, field 'T_c'.*not finite"):
        check_inputs(tel, ["T_c"])
    with pytest.raises(InputError, match=r"no column 'T_x'.*T_chamber, P, T_a, T_b, T_c"):
        check_inputs(tel, ["T_x"])


def test_check_sensors(tmp_path):
    tel = read_telemetry(write(tmp_path, CHECKS))
    check_sensors(tel, ["T_chamber", "T_a"])  # a dropped sample is fine
    with pytest.raises(InputError, match=r"field 'T_b'.*no readings"):
        check_sensors(tel, ["T_b"])
    with pytest.raises(InputError, match=r"line 4, field 'T_c'.*infinite"):
        check_sensors(tel, ["T_c"])
    with pytest.raises(InputError, match=r"no column 'T_z'.*available columns"):
        check_sensors(tel, ["T_a", "T_z"])


def test_in_memory_telemetry_names_data_rows():
    tel = Telemetry(ts=np.arange(3.0), channels={"u": [1.0, np.nan, 2.0]})
    assert tel.path is None
    np.testing.assert_array_equal(tel.lines, [1, 2, 3])
    with pytest.raises(InputError, match=r"^field 'u'.*data row 2"):
        check_inputs(tel, ["u"])
    with pytest.raises(InputError, match="shape"):
        Telemetry(ts=np.arange(3.0), channels={"u": [1.0, 2.0]})


# ---------------------------------------------------------------------------
# writing


def test_round_trip_is_bit_exact(tmp_path):
    rng = np.random.default_rng(0)
    n = 500
    ts = np.arange(n) * 0.1  # 0.1 is not representable: every digit must survive
    specials = np.array([0.0, -0.0, 5e-324, 2.2250738585072014e-308, 1.7976931348623157e308,
                         -1.7976931348623157e308, 1 / 3, math.pi, np.inf, -np.inf, 1e-300,
                         123456789.123456789])
    a = rng.standard_normal(n) * 10.0 ** rng.integers(-30, 30, n)
    a[: specials.size] = specials
    b = rng.uniform(-40, 85, n)
    b[rng.random(n) < 0.2] = np.nan  # dropped samples
    path = write_telemetry(tmp_path / "rt.csv", ts, {"a": a, "b": b},
                           comments=["first", "multi\nline", ""])
    tel = read_telemetry(path)
    assert tel.ts.view(np.uint64).tolist() == ts.view(np.uint64).tolist()
    assert tel.channels["a"].view(np.uint64).tolist() == a.view(np.uint64).tolist()
    nan_b = np.isnan(b)
    np.testing.assert_array_equal(np.isnan(tel.channels["b"]), nan_b)
    assert tel.channels["b"][~nan_b].view(np.uint64).tolist() == b[~nan_b].view(np.uint64).tolist()
    text = path.read_text().splitlines()
    assert text[:5] == ["# first", "# multi", "# line", "#", "time_s,a,b"]
    np.testing.assert_array_equal(tel.lines, np.arange(n) + 6)


def test_written_cells_format(tmp_path):
    path = write_telemetry(tmp_path / "f.csv", [0.0, 1.0], {"T": [0.1, np.nan]})
    assert path.read_text() == "time_s,T\n0,0.10000000000000001\n1,\n"


@pytest.mark.parametrize("name", ["a,b", 'a"b', " a", "", "time_s", "a\nb"])
def test_write_refuses_bad_column_names(tmp_path, name):
    with pytest.raises(InputError, match="time_s|column name"):
        write_telemetry(tmp_path / "x.csv", [0.0, 1.0], {name: [1.0, 2.0]})


def test_write_refuses_mismatched_shapes(tmp_path):
    with pytest.raises(InputError, match=r"column 'T' has shape \(3,\), expected \(2,\)"):
        write_telemetry(tmp_path / "x.csv", [0.0, 1.0], {"T": [1.0, 2.0, 3.0]})
    with pytest.raises(InputError, match="one-dimensional"):
        write_telemetry(tmp_path / "x.csv", [[0.0, 1.0]], {})


def test_reads_a_four_hour_run(tmp_path):
    """A four-hour run reads back bit for bit (its reading time is measured by
    benchmarks/wallclock.py, not asserted here: a shared CI machine's clock says nothing
    about the code)."""
    n = 14_400  # 4 h at 1 Hz, time plus 5 channels
    rng = np.random.default_rng(1)
    channels = {f"c{i}": rng.standard_normal(n) for i in range(5)}
    channels["c2"][::13] = np.nan
    path = write_telemetry(tmp_path / "big.csv", np.arange(n, dtype=np.float64), channels)
    tel = read_telemetry(path)
    assert len(tel) == n
    np.testing.assert_array_equal(tel.ts, np.arange(n, dtype=np.float64))
    for name, values in channels.items():
        np.testing.assert_array_equal(tel.channels[name], values)


def test_quote_spanning_lines_is_refused(tmp_path):
    path = write(tmp_path, 'time_s,T\n0,"1\n1",2\n2,3\n')
    with pytest.raises(InputError, match=r"line 2: a quoted cell is not closed"):
        read_telemetry(path)


def test_readers_do_not_import_jax():
    # NumPy-only modules: no import of jax (or anything from it) at any level
    import ast
    from pathlib import Path

    import thermojax

    root = Path(thermojax.__file__).parent
    for name in ("measurements/_telemetry.py", "measurements/_profiles.py"):
        tree = ast.parse((root / name).read_text())
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                modules = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom):
                modules = [node.module or ""]
            else:
                continue
            assert not any(m.split(".")[0] in ("jax", "jaxlib", "equinox") for m in modules), name
