"""Two-axis model files (version 4): round trip, one-axis files still read, refusals."""

from pathlib import Path

import numpy as np
import pytest

from afmctl.errors import FileFormatError
from afmctl.files import modelfile as mf
from afmctl.files import xymodelfile as xm
from afmctl.fit import parametrization as pz
from afmctl.model.coupling import Coupling
from afmctl.model.xy import XYModel


def _model(scale: float):
    return pz.to_model(np.array([1.0, 0.4, 0.3, 0.36, 250.0, 0.25]) * scale,
                       np.array([10.0, 0.5, 0.0]), pz.Scales(), 100.0)


XY = XYModel({"x": _model(1.0), "y": _model(1.1)},
             {"yx": Coupling(0.012, 420.0, 0.03, 0.02, 0.05, 1.5, -1.6e-5, 53.0),
              "xy": Coupling(-0.008, 0.0, 0.05, 0.0, 0.0, -2.0)})


def test_round_trip_and_axis_extraction(tmp_path: Path) -> None:
    env = mf.Envelope(0.0, 150.0, 0.0, 1.5, (0.279, 5.58), (1e4, 1e4))
    fit = mf.FitRecord("identify", "every sweep within 2x its sensor noise", False, ("a.csv",),
                       (1.01,))
    xm.write(XY, tmp_path / "m.toml", "a header", {"x": env, "y": None}, None,
             {"x": fit, "y": fit}, {"yx": [1e-4, 0.01, 0.1, 1e-3, 1e-3]})
    back = xm.read(tmp_path / "m.toml")
    assert back.coupling == XY.coupling
    for a in ("x", "y"):
        assert mf.to_dict(back.axis(a)) == mf.to_dict(XY.axis(a))
    model, e, f = xm.read_axis(tmp_path / "m.toml", "x")
    assert e == env and f == fit and mf.to_dict(model) == mf.to_dict(XY.axis("x"))
    assert xm.read_axis(tmp_path / "m.toml", "y")[1] is None
    with pytest.raises(FileFormatError, match="name the axis"):
        mf.read(tmp_path / "m.toml")  # the one-axis reader names what the file is


def test_a_file_without_the_arc_reads_as_no_arc(tmp_path: Path) -> None:
    """Files written before the arc's keys existed read with none."""
    xm.write(XY, tmp_path / "m.toml")
    text = (tmp_path / "m.toml").read_text()
    assert "quadratic_um_per_um2 = -1.6e-05" in text
    lines = [ln for ln in text.splitlines()
             if not ln.startswith(("quadratic_um_per_um2", "centre_um"))]
    (tmp_path / "old.toml").write_text("\n".join(lines) + "\n")
    back = xm.read(tmp_path / "old.toml").coupling["yx"]
    assert (back.quadratic, back.centre_um) == (0.0, 0.0)
    assert back.static == 0.012 and back.reference_um == 1.5


def test_one_axis_file_still_reads_as_any_axis_but_not_as_two(tmp_path: Path) -> None:
    mf.write(_model(1.0), tmp_path / "one.toml")
    model, _, _ = xm.read_axis(tmp_path / "one.toml", "y")
    assert mf.to_dict(model) == mf.to_dict(_model(1.0))
    with pytest.raises(FileFormatError, match="a one-axis model file"):
        xm.read(tmp_path / "one.toml")


@pytest.mark.parametrize("edit, words", [
    (("mode_Hz = 420.0", "mode_Hz = -1.0"), "mode_Hz"),
    (('names = ["x", "y"]', 'names = ["x", "z"]'), "names"),
    (("static_um_per_um = 0.012", "static_um_per_mm = 0.012"), "static_um_per_"),
    (("[coupling.xy]", "[coupling.zz]"), "coupling"),
])
def test_malformed_is_one_line(tmp_path: Path, edit: tuple[str, str], words: str) -> None:
    xm.write(XY, tmp_path / "m.toml")
    text = (tmp_path / "m.toml").read_text()
    assert edit[0] in text
    (tmp_path / "m.toml").write_text(text.replace(edit[0], edit[1]))
    with pytest.raises(FileFormatError) as e:
        xm.read(tmp_path / "m.toml")
    assert words in str(e.value) and "\n" not in str(e.value)
