"""Packaging contracts: import isolation and the console entry point."""

from __future__ import annotations

import subprocess
import sys

from click.testing import CliRunner

from afmctl.cli import main


def test_import_afmctl_does_not_touch_device_libraries() -> None:
    code = ("import sys, afmctl, afmctl.cli, afmctl.model.hysteresis, afmctl.model.inverse, "
            "afmctl.files.modelfile;"
            "bad = [m for m in ('serial', 'pymodbus') if m in sys.modules]; print(bad)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"


def test_help() -> None:
    res = CliRunner().invoke(main, ["--help"])
    assert res.exit_code == 0 and "Usage" in res.output
