"""Shared fixtures: emulated sweeps from the nominal "true" stage (parameters hidden from fits)."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pytest

from afmctl import hysteresis as hy
from afmctl import identify as idf
from afmctl import rod as rd
from afmctl import sweeps as sw
from afmctl.transducer import Transducer

SAMPLE_RATE_HZ = 10_000.0
NOISE_UM = 0.03
SENSOR_ZERO_UM = 2.0


@pytest.fixture(scope="session")
def true_model() -> Transducer:
    """The nominal emulated stage (same values as the project's nominal model file)."""
    pol = hy.Polarization(eta=1.2, p_r=0.3, coercive=hy.Lognormal(1.0, 0.4),
                          interaction=hy.Normal(0.3))
    rod = rd.Rod(m=0.05, c=39.27, k=123370.0, a1=3.8, a2=0.5, offset_um=SENSOR_ZERO_UM)
    return Transducer(pol, rod, 100.0)


@pytest.fixture(scope="session")
def emulate(true_model: Transducer) -> Callable[..., sw.Sweep]:
    """``emulate(voltage, frequency_hz, seed, meta=True)``: a noisy sweep of the true stage."""

    def make(voltage_v: np.ndarray, frequency_hz: float, seed: int,
             meta: bool = True) -> sw.Sweep:
        rng = np.random.default_rng(seed)
        u = idf.predict(true_model, voltage_v, 1.0 / SAMPLE_RATE_HZ)
        u = u + NOISE_UM * rng.standard_normal(u.size)
        md = {"frequency_hz": f"{frequency_hz:g}", "layer_thickness_um": "100.0",
              "profile": "emulated"} if meta else {}
        return sw.from_arrays(voltage_v, u, SAMPLE_RATE_HZ, md, f"triangle_{frequency_hz:g}hz")

    return make


@pytest.fixture(scope="session")
def standard_sweeps(emulate: Callable[..., sw.Sweep]) -> list[sw.Sweep]:
    return [emulate(v, f, seed) for seed, (_, f, v) in
            enumerate(sw.standard_set(150.0, SAMPLE_RATE_HZ)[:3])]


@pytest.fixture(scope="session")
def standard_fit(standard_sweeps: list[sw.Sweep]) -> idf.FitResult:
    return idf.fit(standard_sweeps)
