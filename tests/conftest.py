"""Shared fixtures: the shipped emulated profile and its true model, a slew-safe test waveform, and
servers on 127.0.0.1 / ptys that start and stop cleanly."""

from __future__ import annotations

import logging
from collections.abc import Iterator

import numpy as np
import pytest

from afmctl.profile import Profile, default_profile
from afmctl.transducer import Transducer


@pytest.fixture(autouse=True)
def _quiet_pymodbus() -> None:
    logging.getLogger("pymodbus").setLevel(logging.CRITICAL)


@pytest.fixture(scope="session")
def profile() -> Profile:
    return default_profile()


@pytest.fixture(scope="session")
def nominal(profile: Profile) -> Transducer:
    """The emulated stage's true model (the nominal AFM stage)."""
    assert profile.emulator is not None
    return profile.emulator.model


@pytest.fixture(scope="session")
def waveform() -> np.ndarray:
    """20,000 samples (2 s at 10 kHz) with a decaying envelope, so hysteresis minor loops show."""
    n = 20_000
    return 100.0 * np.sin(2 * np.pi * 5.0 * np.arange(n) / 10_000.0) * np.linspace(1.0, 0.3, n)


@pytest.fixture
def device(profile: Profile) -> Iterator[object]:
    from drivers.servers import EmulatedDevice
    with EmulatedDevice(profile) as dev:
        yield dev
