"""Shared fixtures: the shipped emulated profile and its true model, emulated sweeps recorded by the
emulated device's own physics (true parameters hidden from fits), a slew-safe test waveform, and
servers on 127.0.0.1 / ptys that start and stop cleanly."""

from __future__ import annotations

import dataclasses as dc
import logging
from collections.abc import Callable, Iterator
from typing import TYPE_CHECKING

import numpy as np
import pytest

from afmctl.drivers.device import plant
from afmctl.files import sweepfile as sw
from afmctl.files.profile import Profile
from afmctl.fit import identify as idf
from afmctl.model.transducer import Transducer
from afmctl.planning import sweepdesign as sd
from tests.harness.emulated import NOISE_UM, PROFILE, SAMPLE_RATE_HZ, SENSOR_ZERO_UM, TRANSPORTS, stage_on  # noqa: F401

if TYPE_CHECKING:
    pass



def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption("--device", action="store", default=None, metavar="PROFILE",
                     help="run the tests marked `device` against the real stage of this profile")
    parser.addoption("--guide", action="store_true", default=False,
                     help="run the tests marked `guide`: the calibration guide end to end on a "
                          "fresh clone (several minutes; kept out of CI's 20-minute budget)")
    parser.addoption("--heavy", action="store_true", default=False,
                     help="run the tests marked `heavy`: full-size cases a benchmark or other "
                          "tests also cover, a minute or more each (kept out of CI's 20-minute "
                          "budget)")


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    opt_in = {"device": (config.getoption("--device") is not None,
                         "needs real hardware: pytest --device PROFILE"),
              "guide": (config.getoption("--guide"),
                        "the guide end to end takes minutes: pytest --guide"),
              "heavy": (config.getoption("--heavy"),
                        "a full-size case a benchmark or other tests also cover, a minute or more: "
                        "pytest --heavy")}
    for item in items:
        for marker, (wanted, reason) in opt_in.items():
            if not wanted and item.get_closest_marker(marker) is not None:
                item.add_marker(pytest.mark.skip(reason=reason))


@pytest.fixture(autouse=True)
def _quiet_pymodbus() -> None:
    logging.getLogger("pymodbus").setLevel(logging.CRITICAL)


@pytest.fixture(scope="session")
def profile() -> Profile:
    return PROFILE


@pytest.fixture(scope="session")
def nominal(profile: Profile) -> Transducer:
    """The emulated stage's true model (the nominal AFM stage)."""
    assert profile.emulator is not None
    return profile.emulator.model


@pytest.fixture(scope="session")
def true_model(nominal: Transducer) -> Transducer:
    """The truth as a sweep sees it: the nominal stage with the sensor zero added."""
    return dc.replace(nominal, rod=dc.replace(nominal.rod, offset_um=SENSOR_ZERO_UM))


@pytest.fixture(scope="session")
def emulate() -> Callable[..., sw.Sweep]:
    """``emulate(voltage, frequency_hz, seed, meta=True)``: a sweep recorded by the emulated device
    (its physics and seeded sensor noise), with the sensor zero shifted by SENSOR_ZERO_UM."""
    assert PROFILE.emulator is not None
    cfg = PROFILE.emulator

    def make(voltage_v: np.ndarray, frequency_hz: float, seed: int,
             meta: bool = True) -> sw.Sweep:
        u, _ = plant.expected_readback(dc.replace(cfg, seed=seed), SAMPLE_RATE_HZ, voltage_v)
        md = {"frequency_hz": f"{frequency_hz:g}", "layer_thickness_um": "100.0",
              "profile": "emulated"} if meta else {}
        return sw.from_arrays(voltage_v, u + SENSOR_ZERO_UM, SAMPLE_RATE_HZ, md,
                              f"triangle_{frequency_hz:g}hz")

    return make


@pytest.fixture(scope="session")
def standard_sweeps(emulate: Callable[..., sw.Sweep]) -> list[sw.Sweep]:
    return [emulate(v, f, seed) for seed, (_, f, v) in
            enumerate(sd.standard_set(150.0, SAMPLE_RATE_HZ)[:3])]


@pytest.fixture(scope="session")
def standard_fit(standard_sweeps: list[sw.Sweep]) -> idf.FitResult:
    return idf.fit(standard_sweeps)


@pytest.fixture(scope="session")
def waveform() -> np.ndarray:
    """20,000 samples (2 s at 10 kHz) with a decaying envelope, so hysteresis minor loops show."""
    n = 20_000
    return 100.0 * np.sin(2 * np.pi * 5.0 * np.arange(n) / 10_000.0) * np.linspace(1.0, 0.3, n)


@pytest.fixture
def device(profile: Profile) -> Iterator[object]:
    from afmctl.drivers.device.emulated import EmulatedDevice
    with EmulatedDevice(profile) as dev:
        yield dev
