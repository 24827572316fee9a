"""Shared fixtures: the nominal emulated stage model shipped in profiles/."""

from __future__ import annotations

from pathlib import Path

import pytest

from afmctl import modelfile
from afmctl.transducer import Transducer

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="session")
def nominal() -> Transducer:
    return modelfile.read(ROOT / "profiles" / "nominal-model.toml")
