"""Two-axis sweep files: columns per axis, lab spellings, per-axis metadata, refusals."""

from pathlib import Path

import numpy as np
import pytest

from afmctl.errors import SweepFormatError
from afmctl.files import sweepfile as sw
from afmctl.files import xysweepfile as xs

GOOD = ("# layer_thickness_x_um: 100\n# layer_thickness_y_um: 80\n# profile: emulated-xy\n"
        "time_s,voltage_x_V,voltage_y_V,displacement_x_um,displacement_y_um\n"
        "0.0,0.0,60.0,0.1,5.0\n0.001,1.0,60.0,0.2,5.01\n0.002,2.0,60.0,0.3,5.02\n")


def test_parse_reads_both_axes_and_maps_per_axis_metadata() -> None:
    s = xs.parse(GOOD)
    np.testing.assert_allclose(s.voltage_v, [[0, 60], [1, 60], [2, 60]])
    np.testing.assert_allclose(s.displacement_um[:, 1], [5.0, 5.01, 5.02])
    assert s.moving == ("x",)
    x, y = s.axis("x"), s.axis("y")
    assert (x.thickness_um, y.thickness_um) == (100.0, 80.0)
    assert x.meta["profile"] == "emulated-xy" and "layer_thickness_y_um" not in x.meta
    np.testing.assert_allclose(y.voltage_v, [60, 60, 60])
    assert y.dt == pytest.approx(0.001)


def test_lab_spellings_units_and_decimal_commas() -> None:
    text = ("Time (ms);X voltage (mV);Voltage Y [V];displacement x nm;Y_position_um\n"
            "0;0;1,5;100;2,0\n1;500;1,5;200;2,5\n2;1000;1,5;300;3,0\n")
    s = xs.parse(text)
    np.testing.assert_allclose(s.time_s, [0, 0.001, 0.002], atol=1e-12)
    np.testing.assert_allclose(s.voltage_v[:, 0], [0, 0.5, 1.0])
    np.testing.assert_allclose(s.voltage_v[:, 1], [1.5, 1.5, 1.5])
    np.testing.assert_allclose(s.displacement_um, [[0.1, 2.0], [0.2, 2.5], [0.3, 3.0]])


def test_round_trip(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    v, d = rng.uniform(0, 150, (50, 2)), rng.normal(0, 10, (50, 2))
    s = xs.from_arrays(v, d, 5000.0, {"frequency_hz": "5.58"}, "a")
    xs.write(s, tmp_path / "a.csv")
    back = xs.read(tmp_path / "a.csv")
    np.testing.assert_allclose(back.voltage_v, v, atol=1e-6)
    np.testing.assert_allclose(back.displacement_um, d, atol=1e-6)
    assert back.meta == {"frequency_hz": "5.58"} and back.dt == pytest.approx(2e-4)
    assert back.moving == ("x", "y")


@pytest.mark.parametrize("text, words", [
    ("time_s,voltage_x_V,displacement_x_um,displacement_y_um\n0,0,0,0\n0.1,1,1,1\n",
     "missing column voltage_y_V"),
    ("time_s,voltage_x_V,voltage_y_V,displacement_x_um,displacement_y_um\n0,0,0,0,0\n"
     "0.1,1,nan,1,1\n", "non-finite"),
    ("# layer_thickness_y_um: -3\ntime_s,voltage_x_V,voltage_y_V,displacement_x_um,"
     "displacement_y_um\n0,0,0,0,0\n0.1,1,0,1,1\n", "layer_thickness_y_um"),
    ("time_s,voltage_x_V,voltage_y_V,displacement_x_um,displacement_y_um\n0,0,0,0,0\n"
     "0.1,1,0,1,1\n0.1,2,0,1,1\n", "not strictly increasing"),
])
def test_malformed_is_one_line(text: str, words: str) -> None:
    with pytest.raises(SweepFormatError) as e:
        xs.parse(text, "f.csv")
    assert words in str(e.value) and "\n" not in str(e.value) and "f.csv" in str(e.value)


def test_one_axis_reader_names_a_two_axis_file_and_sets_are_not_mixed(tmp_path: Path) -> None:
    (tmp_path / "xy.csv").write_text(GOOD)
    (tmp_path / "one.csv").write_text("time_s,voltage_V,displacement_um\n0,0,0\n0.1,1,1\n")
    with pytest.raises(SweepFormatError, match="a two-axis sweep file"):
        sw.read(tmp_path / "xy.csv")
    assert xs.read_set([tmp_path / "one.csv"]) is None
    with pytest.raises(SweepFormatError, match="one-axis sweep file in a set of two-axis"):
        xs.read_set([tmp_path / "xy.csv", tmp_path / "one.csv"])
    (tmp_path / "cut.csv").write_text(GOOD + "# end: interrupted (lost link)\n")
    with pytest.raises(SweepFormatError, match="interrupted"):
        xs.read(tmp_path / "cut.csv")
