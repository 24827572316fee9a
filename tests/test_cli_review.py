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
