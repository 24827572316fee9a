"""The sensor-noise estimator against known noise: on signals with strong low-frequency content
(triangles, nested loops, a resonant transient), and on the foreign-stage sweeps whose noise the
data README states (an independent simulator)."""

from __future__ import annotations

import numpy as np
import pytest

from afmctl.files import sweepfile as sw
from afmctl.fit import noise
from afmctl.planning import sweepdesign as sd
from tests.harness.paths import SHARED_DATA

FOREIGN = SHARED_DATA / "foreign-stage"


def _triangle_um(freq_hz: float, rate_hz: float, cycles: float, range_um: float) -> np.ndarray:
    return range_um / 150.0 * sd.voltage_triangle(freq_hz, 150.0, cycles, rate_hz)


def _ringing_um(rate_hz: float) -> np.ndarray:
    """A 60 um step response of a lightly damped 150 Hz mode, repeated (an AFM stage's corners);
    150 Hz at 10 kHz is the estimator's stated limit f dt = 0.015."""
    t = np.arange(int(0.05 * rate_hz)) / rate_hz
    w, z = 2 * np.pi * 150.0, 0.1
    step = 60 * (1 - np.exp(-z * w * t) * np.cos(w * np.sqrt(1 - z * z) * t))
    return np.concatenate([step, 60 - step] * 4)


@pytest.mark.parametrize(("name", "signal"), [
    ("27.9 Hz triangle, 75 um, 10 kHz", _triangle_um(27.9, 1e4, 10, 75.0)),
    ("0.279 Hz triangle, 75 um, 1 kHz", _triangle_um(0.279, 1e3, 1, 75.0)),
    ("nested loops, 90 um, 2 kHz", 0.6 * sd.nested_loops(0.5, 150.0, 4, 2e3)),
    ("5 Hz sine, 120 um, 5 kHz", 60 * np.sin(2 * np.pi * 5 * np.arange(20000) / 5e3)),
])
@pytest.mark.parametrize("sigma_um", [0.005, 0.02, 0.1])
def test_known_white_noise_on_strong_low_frequency_signals(name: str, signal: np.ndarray,
                                                           sigma_um: float) -> None:
    rng = np.random.default_rng(int(sigma_um * 1e4))
    est = noise.sensor_noise_um(signal + sigma_um * rng.standard_normal(signal.size))
    assert est == pytest.approx(sigma_um, rel=0.08), name


@pytest.mark.parametrize("sigma_um", [0.02, 0.1])
def test_known_white_noise_on_a_resonant_transient(sigma_um: float) -> None:
    """At the stated limit (f dt = 0.015) the mode's own third differences bias the estimate by
    about 0.0008 um in quadrature: negligible at 0.02 um of noise, 13 % at 0.005 um."""
    y = _ringing_um(1e4)
    est = noise.sensor_noise_um(y + sigma_um * np.random.default_rng(7).standard_normal(y.size))
    assert est == pytest.approx(sigma_um, rel=0.08)


def test_the_signal_alone_is_not_taken_for_noise() -> None:
    assert noise.sensor_noise_um(_triangle_um(27.9, 1e4, 10, 75.0)) < 1e-3
    assert noise.sensor_noise_um(_ringing_um(1e4)) < 3e-3


def test_plain_standard_deviation_would_be_wrong() -> None:
    """What the estimator is for: the record's own scatter is the signal's, 1000x the noise."""
    y = _triangle_um(5.58, 5e3, 5, 75.0) + 0.02 * np.random.default_rng(3).standard_normal(4481)
    assert np.std(np.diff(y)) > 5 * noise.sensor_noise_um(y)


def test_too_short_or_bad_order() -> None:
    with pytest.raises(ValueError):
        noise.sensor_noise_um(np.zeros(4))
    with pytest.raises(ValueError):
        noise.sensor_noise_um(np.zeros(100), order=0)


@pytest.mark.parametrize(("folder", "sigma_um"), [("unipolar", 0.0202), ("semi-bipolar", 0.0208)])
def test_foreign_stage_sweeps(folder: str, sigma_um: float) -> None:
    files = sorted((FOREIGN / folder).glob("sweep_*.csv"))
    if not files:
        pytest.skip(f"foreign-stage data not found at {FOREIGN}")
    for f in files:
        est = noise.sensor_noise_um(sw.read(f).displacement_um)
        assert est == pytest.approx(sigma_um, rel=0.1), f.name
