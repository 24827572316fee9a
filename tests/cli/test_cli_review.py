"""Rough hands found in review: output paths under a file, sweeps over a uselessly narrow range."""

from __future__ import annotations

from pathlib import Path

from click.testing import CliRunner

from afmctl.cli import main


def _err(res) -> str:  # noqa: ANN001 (click Result)
    return res.stderr.strip().splitlines()[-1]


def test_output_file_under_a_file_names_the_file(tmp_path: Path) -> None:
    """`-o afile/m.toml` where afile is a file: the line says afile is a file (it exists)."""
    (tmp_path / "afile").write_text("x\n")
    sweep = tmp_path / "s.csv"
    sweep.write_text("time_s,voltage_V,displacement_um\n0,0,0\n0.1,1,1\n0.2,0,0\n")
    out = tmp_path / "afile" / "m.toml"
    res = CliRunner().invoke(main, ["identify", str(sweep), "-o", str(out)])
    assert res.exit_code == 2
    assert _err(res) == f"afmctl: error: -o {out}: {tmp_path / 'afile'} is a file, not a folder"


def test_sweep_refuses_a_uselessly_narrow_range_before_touching_the_stage(tmp_path: Path) -> None:
    """`--v-range 0 1e-6` once recorded four sweeps of noise; now exit 2, nothing written."""
    out = tmp_path / "s"
    res = CliRunner().invoke(main, ["sweep", "--out", str(out), "--v-range", "0", "1e-6"])
    assert res.exit_code == 2
    assert _err(res) == ("afmctl: error: --v-range 0 1e-06 V: too narrow to identify a model; "
                         "at least 1% of the profile's span (300 V)")
    assert not out.exists()
