"""Packaging contracts: one import root, every subpackage in the wheel, import isolation, the
console entry point."""

from __future__ import annotations

import subprocess
import sys
import tomllib
import zipfile
from pathlib import Path

import pytest
from click.testing import CliRunner

from afmctl.cli import main
from tests.harness.paths import REPO

SETUPTOOLS = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]


def _folders_with_init() -> set[str]:
    """Every package on disk, by the import name it installs under (``drivers/`` as
    ``afmctl.drivers``, ``profiles/`` as ``afmctl.profiles``)."""
    names = set()
    for name, folder in [("afmctl", "afmctl"), *SETUPTOOLS["package-dir"].items()]:
        root = REPO / folder
        for init in root.rglob("__init__.py"):
            rel = init.parent.relative_to(root).parts
            names.add(".".join((name, *rel)))
    return names


def test_the_package_list_holds_every_folder_with_an_init() -> None:
    """A subpackage missing from pyproject's list works in an editable install but is absent
    from the wheel."""
    assert set(SETUPTOOLS["packages"]) == _folders_with_init()


@pytest.mark.slow
def test_the_wheel_holds_every_subpackage_and_no_top_level_drivers(tmp_path: Path) -> None:
    subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w", str(tmp_path),
                    str(REPO)], check=True, capture_output=True)
    wheel, = tmp_path.glob("afmctl-*.whl")
    names = zipfile.ZipFile(wheel).namelist()
    tops = {n.split("/")[0] for n in names if not n.split("/")[0].endswith(".dist-info")}
    assert tops == {"afmctl"}
    for package in SETUPTOOLS["packages"]:
        assert package.replace(".", "/") + "/__init__.py" in names, package
    assert {"afmctl/profiles/emulated.toml", "afmctl/profiles/lab-serial.toml"} <= set(names)
    assert not any(n.startswith("afmctl/tests/") or n.startswith("afmctl/benchmarks/")
                   for n in names)


def test_outside_the_checkout_drivers_is_not_a_top_level_name(tmp_path: Path) -> None:
    code = ("import importlib.util, sys, afmctl.drivers, afmctl.profiles\n"
            "print(importlib.util.find_spec('drivers') is None, 'drivers' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                         cwd=tmp_path)
    assert out.stdout.split() == ["True", "False"]


def _loaded(imports: str, watched: tuple[str, ...]) -> list[str]:
    code = (f"import sys, {imports}; "
            f"print([m for m in {watched!r} if m in sys.modules])")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    return eval(out.stdout)  # a printed list of names


def test_import_afmctl_is_cheap_and_the_science_touches_no_device_library() -> None:
    heavy = ("numpy", "scipy", "numba", "matplotlib", "serial", "pymodbus", "click")
    assert _loaded("afmctl", heavy) == []
    assert _loaded("afmctl.cli, afmctl.model.hysteresis, afmctl.model.inverse, "
                   "afmctl.files.modelfile, afmctl.fit.identify", ("serial", "pymodbus",
                                                                   "matplotlib")) == []


def test_the_figures_leave_the_callers_matplotlib_backend_alone() -> None:
    code = ("import matplotlib; matplotlib.use('svg'); import afmctl.plots, afmctl.cli.track, "
            "afmctl.cli.play; print(matplotlib.get_backend())")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "svg"


def test_help_and_version() -> None:
    res = CliRunner().invoke(main, ["--help"])
    assert res.exit_code == 0 and "Usage" in res.output and "--debug" in res.output
    res = CliRunner().invoke(main, ["--version"])
    import afmctl
    assert res.exit_code == 0 and afmctl.__version__ in res.output
