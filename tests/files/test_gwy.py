"""scan.gwy: written with gwyfile, read back with gwyfile.load, and checked by Gwyddion itself
where it is installed (``gwyddion --check``; the test says when it is skipped)."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import gwyfile
import numpy as np
import pytest

from afmctl.files import gwy


def images() -> dict[str, np.ndarray]:
    rng = np.random.default_rng(3)
    a = rng.normal(size=(4, 6))
    b = a.copy()
    b[2, 3] = np.nan
    return {"frame 0 inverse: x trace": a, "y": b}


def test_round_trip_through_gwyfile(tmp_path: Path) -> None:
    path = gwy.write(tmp_path / "scan.gwy", images(), (12.0, 8.0), (1.0, -2.0), {"lines": 4})
    obj = gwyfile.load(str(path))
    field = obj["/0/data"]
    assert field.xreal == pytest.approx(12e-6) and field.yreal == pytest.approx(8e-6)
    assert field.xoff == pytest.approx(1e-6) and field.yoff == pytest.approx(-2e-6)
    assert field["si_unit_xy"].unitstr == "m" and field["si_unit_z"].unitstr == "m"
    assert obj["/0/data/title"] == "frame 0 inverse: x trace" and obj["/1/data/title"] == "y"
    assert field.data == pytest.approx(images()["frame 0 inverse: x trace"] * 1e-6)
    back = gwy.read(path)
    assert list(back) == list(images())
    assert np.isnan(back["y"][2, 3]) and np.isfinite(back["y"]).sum() == 23
    assert obj["/1/mask"].data[2, 3] == 1.0


def test_gwyddion_checks_it_clean(tmp_path: Path) -> None:
    exe = shutil.which("gwyddion")
    if exe is None:
        pytest.skip("Gwyddion is not installed here: `gwyddion --check` not run "
                    "(gwyfile's round trip is tested above)")
    path = gwy.write(tmp_path / "scan.gwy", images(), (12.0, 8.0))
    res = subprocess.run([exe, "--check", str(path)], capture_output=True, text=True,
                         timeout=120)
    assert res.returncode == 0 and res.stdout.strip() == "", res.stdout + res.stderr
    ident = subprocess.run([exe, "--identify", str(path)], capture_output=True, text=True,
                           timeout=120)
    assert "Gwyddion native" in ident.stdout


def test_not_a_gwyddion_file_is_a_format_error(tmp_path: Path) -> None:
    bad = tmp_path / "bad.gwy"
    bad.write_text("hello")
    with pytest.raises(gwy.FileFormatError):
        gwy.read(bad)
