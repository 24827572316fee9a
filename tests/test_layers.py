"""The house's layers (import-linter contracts in pyproject.toml) hold, and an upward import
breaks them.

import-linter reads the package from disk; ``drivers/`` and ``profiles/`` install as
``afmctl.drivers`` and ``afmctl.profiles`` (setuptools ``package-dir``), which the checkout's
editable install maps without a folder of that name under ``afmctl/``. The contracts are therefore
checked on a copy laid out as the wheel lays it out.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

from tests.harness.paths import REPO

LINT = Path(sys.executable).with_name("lint-imports")


def installed_layout(dest: Path) -> Path:
    """``dest`` holding ``afmctl/`` as the wheel holds it, and pyproject.toml; returns ``dest``."""
    package_dir = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"][
        "package-dir"]
    ignore = shutil.ignore_patterns("__pycache__", "*.pyc")
    shutil.copytree(REPO / "afmctl", dest / "afmctl", ignore=ignore)
    for name, folder in package_dir.items():
        shutil.copytree(REPO / folder, dest / Path(*name.split(".")), ignore=ignore)
    shutil.copy(REPO / "pyproject.toml", dest)
    return dest


def lint(where: Path) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "PYTHONPATH": str(where)}
    return subprocess.run([str(LINT), "--no-cache"], cwd=where, env=env, capture_output=True,
                          text=True)


pytestmark = pytest.mark.skipif(not LINT.exists(), reason="import-linter is not installed "
                                "(pip install -e '.[test]')")


def test_the_layer_contracts_hold(tmp_path: Path) -> None:
    res = lint(installed_layout(tmp_path))
    assert res.returncode == 0, res.stdout[-3000:]
    assert "Contracts: 4 kept, 0 broken." in res.stdout


@pytest.mark.parametrize(("module", "line", "contract"), [
    ("afmctl/model/upward.py", "from afmctl.fit import identify\n", "rooms are layered"),
    ("afmctl/files/upward.py", "import afmctl.drivers.stage\n", "rooms are layered"),
    ("afmctl/fit/upward.py", "import matplotlib.figure\n", "no device or plotting library"),
    ("afmctl/drivers/serial_link_extra.py", "import pymodbus\n", "every pymodbus call"),
], ids=["model-imports-fit", "files-imports-drivers", "fit-imports-matplotlib",
        "pymodbus-outside-its-modules"])
def test_an_upward_or_forbidden_import_breaks_a_contract(tmp_path: Path, module: str, line: str,
                                                         contract: str) -> None:
    where = installed_layout(tmp_path)
    (where / module).write_text(f'"""A deliberate violation."""\n\n{line}')
    res = lint(where)
    assert res.returncode != 0
    broken = res.stdout[res.stdout.index("Broken contracts"):]
    assert contract in broken and module.removesuffix(".py").replace("/", ".") in broken
