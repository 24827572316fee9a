from pathlib import Path

import numpy as np
import pytest

from afmctl.errors import FileFormatError
from afmctl.files import sweepfile as sw
from afmctl.planning import sweepdesign as sd

GOOD = "# frequency_hz: 5.58\n# layer_thickness_um: 100\ntime_s,voltage_V,displacement_um\n" \
       "0.0,0.0,0.1\n0.001,1.0,0.2\n0.002,2.0,0.3\n"

MALFORMED = {
    "missing_column": "time_s,voltage_V\n0,0\n0.001,1\n",
    "nan": "time_s,voltage_V,displacement_um\n0,0,0\n0.001,nan,1\n0.002,1,1\n",
    "non_increasing_time": "time_s,voltage_V,displacement_um\n0,0,0\n0.001,1,1\n0.001,2,1\n",
    "empty": "",
    "comments_only": "# frequency_hz: 1\n",
    "header_only": "time_s,voltage_V,displacement_um\n",
    "not_a_number": "time_s,voltage_V,displacement_um\n0,0,0\n0.001,abc,1\n",
    "non_uniform": "time_s,voltage_V,displacement_um\n0,0,0\n0.001,1,1\n0.003,1,1\n",
}


def test_parse_reads_columns_and_metadata() -> None:
    s = sw.parse(GOOD)
    assert s.thickness_um == 100.0 and s.frequency_hz == 5.58
    np.testing.assert_allclose(s.voltage_v, [0, 1, 2])
    assert s.dt == pytest.approx(0.001)


def test_foreign_file_without_metadata_and_extra_columns_loads() -> None:
    s = sw.parse("displacement_um,time_s,note,voltage_V\n0.5,0,1,10\n0.6,0.5,2,20\n")
    assert s.thickness_um is None and s.meta == {}
    np.testing.assert_allclose(s.voltage_v, [10, 20])
    np.testing.assert_allclose(s.displacement_um, [0.5, 0.6])


def test_bom_crlf_and_quoted_header_load(tmp_path: Path) -> None:
    p = tmp_path / "excel.csv"
    p.write_bytes(b'\xef\xbb\xbf"time_s","voltage_V","displacement_um"\r\n0,1,2\r\n0.5,3,4\r\n')
    s = sw.read(p)
    np.testing.assert_allclose(s.voltage_v, [1, 3])


def test_round_trip(tmp_path: Path) -> None:
    s = sw.from_arrays(sd.voltage_triangle(5.0, 10.0, 1, 1000.0), np.linspace(0, 1, 201), 1000.0,
                       {"frequency_hz": "5"})
    sw.write(s, tmp_path / "a.csv")
    back = sw.read(tmp_path / "a.csv")
    np.testing.assert_allclose(back.voltage_v, s.voltage_v, atol=1e-6)
    np.testing.assert_allclose(back.time_s, s.time_s, atol=1e-7)
    assert back.meta == {"frequency_hz": "5"}


@pytest.mark.parametrize("case", sorted(MALFORMED))
def test_malformed_text_raises_one_line(case: str, tmp_path: Path) -> None:
    p = tmp_path / f"{case}.csv"
    p.write_text(MALFORMED[case])
    with pytest.raises(sw.SweepFormatError) as info:
        sw.read(p)
    assert str(p) in str(info.value) and "\n" not in str(info.value)
    assert isinstance(info.value, FileFormatError)


def test_binary_and_missing_files_raise(tmp_path: Path) -> None:
    p = tmp_path / "b.csv"
    p.write_bytes(b"\x89PNG\x00\x01\xff")
    with pytest.raises(sw.SweepFormatError, match="not a text file"):
        sw.read(p)
    with pytest.raises(sw.SweepFormatError, match="no such file"):
        sw.read(tmp_path / "absent.csv")


def test_memory_index_is_the_first_full_excursion() -> None:
    v = sd.voltage_triangle(1.0, 2.0, 2, 8.0)  # 0 1 2 1 0 -1 -2 -1 0 1 2 ...
    s = sw.from_arrays(v, np.zeros(v.size), 8.0)
    assert s.memory_index == 6  # both extremes reached: +2 at sample 2, -2 at sample 6
    assert not s.mask(None)[:6].any() and s.mask(None)[6:].all()
    assert s.mask((0.5, 1.0)).sum() == 2  # the window and the memory both apply
    v[-3] -= 1e-6  # a later peak larger in its last digits does not move it
    assert sw.from_arrays(v, np.zeros(v.size), 8.0).memory_index == 6
    ramp = sw.from_arrays(np.arange(10.0), np.zeros(10), 8.0)  # one-sided: the top counts
    assert ramp.memory_index == 9


@pytest.mark.parametrize(("name", "column", "scale"), [
    ("time_s", "time_s", 1.0), ("time_ms", "time_s", 1e-3), ("Time (s)", "time_s", 1.0),
    ("t [us]", "time_s", 1e-6), ("Voltage (V)", "voltage_V", 1.0), ("voltage_mV", "voltage_V", 1e-3),
    ("displacement_nm", "displacement_um", 1e-3), ("Position (\u00b5m)", "displacement_um", 1.0),
    ("displacement_mm", "displacement_um", 1e3), ("disp", "displacement_um", None),
    ("voltage_um", "voltage_V", None), ("time_s", "voltage_V", None),
])
def test_column_units(name: str, column: str, scale: float | None) -> None:
    assert sw.column_scale(name, column) == scale


def test_units_are_converted() -> None:
    s = sw.parse("Time (ms);Voltage (V);displacement_nm\n0;1,5;1000\n0,1;2,5;2000\n")
    np.testing.assert_allclose(s.time_s, [0, 1e-4])
    np.testing.assert_allclose(s.voltage_v, [1.5, 2.5])
    np.testing.assert_allclose(s.displacement_um, [1.0, 2.0])


def test_jitter_within_a_tenth_of_a_period_is_put_on_the_grid() -> None:
    t = np.arange(1000) * 1e-4 + np.tile([0.0, 9e-6], 500)
    rows = "".join(f"{a:.8f},1,2\n" for a in t)
    s = sw.parse("time_s,voltage_V,displacement_um\n" + rows)
    assert np.abs(np.diff(s.time_s) - s.dt).max() < 1e-12
    t[700] += 2e-5  # 20 % of a period off at data row 701
    bad = "time_s,voltage_V,displacement_um\n" + "".join(f"{a:.8f},1,2\n" for a in t)
    with pytest.raises(sw.SweepFormatError, match=r"data row 701 is 1\.[0-9]+e-05 s off the 0\.0001 s grid"):
        sw.parse(bad, "x.csv")


def test_sample_rate_metadata_stands_for_a_time_column() -> None:
    s = sw.parse("# sample_rate_hz: 2000\nvoltage_V,displacement_um\n1,2\n3,4\n5,6\n")
    np.testing.assert_allclose(s.time_s, [0, 5e-4, 1e-3])


def test_measured_files_are_recognised(tmp_path: Path) -> None:
    cases = {"sweep.csv": GOOD, "lab.csv": "Time (ms);Voltage (V);displacement_nm\n0;1;2\n",
             "run.csv": "# afmctl-run: 1\nseq,time_s\n", "model.toml": "format = 1\n",
             "wave.csv": "time_s,desired_um\n0,1\n",
             "tracked.csv": "time_s,desired_um,voltage_V_inverse,displacement_um_inverse\n"}
    kinds = {}
    for name, text in cases.items():
        (tmp_path / name).write_text(text)
        kinds[name] = sw.measured_kind(tmp_path / name)
    assert kinds == {"sweep.csv": "a sweep file", "lab.csv": "a sweep file",
                     "run.csv": "an afmctl run file", "model.toml": "", "wave.csv": "",
                     "tracked.csv": "measured displacements"}


def test_an_interrupted_sweep_reads_but_is_refused_for_fitting(tmp_path: Path) -> None:
    """afmctl sweep's partial file (kept on Ctrl-C) is a valid sweep, but identify and diagnose
    (read_complete) refuse it, naming --resume; a complete file passes both."""
    done, partial = tmp_path / "a.csv", tmp_path / "a.incomplete.csv"
    done.write_text(GOOD)
    partial.write_text(GOOD + "# end: interrupted (KeyboardInterrupt)\n")
    np.testing.assert_array_equal(sw.read(partial).voltage_v, sw.read_complete(done).voltage_v)
    with pytest.raises(FileFormatError, match="interrupted sweep.*--resume"):
        sw.read_complete(partial)
