"""The front door, ``import afmctl``: its names (httpx's exported-members test), their docs, the
API reference that lists them, and the tutorial that uses them (executed here, so it cannot rot)."""

from __future__ import annotations

import doctest
import re
from types import ModuleType

import pytest

import afmctl
from tests.harness.paths import REPO

INCLUDED_PRIVATE = ["__version__"]


def test_all_is_every_public_name_sorted() -> None:
    """httpx's test: ``__all__`` is the module's public names, sorted (the rooms, subpackages
    that Python sets as attributes once imported, are not names of the front door)."""
    for name in afmctl.__all__:
        getattr(afmctl, name)
    public = [name for name, value in vars(afmctl).items()
              if (not name.startswith("_") or name in INCLUDED_PRIVATE)
              and not isinstance(value, ModuleType)]
    assert afmctl.__all__ == sorted(public, key=str.casefold)


@pytest.mark.parametrize("name", [n for n in afmctl.__all__ if n != "__version__"])
def test_every_name_resolves_and_is_documented(name: str) -> None:
    obj = getattr(afmctl, name)
    doc = (obj.__doc__ or "").strip()
    assert len(doc) > 20, f"afmctl.{name} has no docstring"


def test_an_unknown_name_is_an_attribute_error() -> None:
    with pytest.raises(AttributeError, match="no attribute 'trianglee'"):
        afmctl.trianglee  # noqa: B018


def test_the_api_reference_lists_exactly_the_front_door() -> None:
    text = (REPO / "docs" / "reference" / "api.md").read_text()
    rows = [line for line in text.splitlines() if line.startswith("| `")]
    listed = {n for row in rows for n in re.findall(r"`(\w+)(?:\(|`)", row.split("|")[1])}
    assert listed == set(afmctl.__all__)


@pytest.mark.slow
def test_the_python_tutorial_runs_as_written() -> None:
    """docs/tutorials/python-api.md on the emulated stage (about half a minute)."""
    result = doctest.testfile(str(REPO / "docs" / "tutorials" / "python-api.md"),
                              module_relative=False, optionflags=doctest.ELLIPSIS)
    assert result.attempted > 10 and result.failed == 0
