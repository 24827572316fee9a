"""The readings' frame (afmctl.model.frame): a steady drift read from the recordings' offsets,
held past what they span, and nothing read into a scatter."""

from __future__ import annotations

import numpy as np
import pytest

from afmctl.model import frame as fr


def line(times: list[float], offset: float, rate: float, wobble: float = 0.0
         ) -> list[fr.Observation]:
    rng = np.random.default_rng(3)
    return [fr.Observation(t, offset + rate * t + wobble * rng.standard_normal()) for t in times]


def test_a_steady_drift_is_followed_to_the_run() -> None:
    """Six recordings on a line 0.02 + 0.012 t (um) with 1 nm of scatter: at 40 s the frame
    is the line's value, moving at its slope."""
    obs = line([2.0, 9.0, 11.0, 20.0, 24.0, 31.0], 0.02, 0.012, 0.001)
    f = fr.estimate(obs, 40.0)
    assert f.um_per_s == pytest.approx(0.012, rel=0.02)
    assert f.offset_um == pytest.approx(0.02 + 0.012 * 40.0, abs=0.005)
    assert f.basis.startswith("drift +1") and f.basis.endswith("over 6 recordings (29 s)")
    np.testing.assert_allclose(f.along(10, 3, 0.5),
                               f.offset_um + f.um_per_s * np.array([5.0, 5.5, 6.0]))


def test_a_drift_is_held_beyond_the_span_it_was_seen_over() -> None:
    """Seen over 29 s, the line is followed to 29 s after the last recording and held there."""
    obs = line([2.0, 9.0, 11.0, 20.0, 24.0, 31.0], 0.0, 0.01)
    far = fr.estimate(obs, 500.0)
    assert far.um_per_s == 0.0
    assert far.offset_um == pytest.approx(0.01 * 60.0, rel=1e-9)


@pytest.mark.parametrize("obs", [
    line([1.0, 2.0, 3.0], 0.0, 0.05),  # too few for a rate
    line([1.0, 2.0, 3.0, 4.0, 5.0], 0.1, 0.0, 0.02),  # a scatter, no slope
])
def test_no_rate_without_a_steady_line(obs: list[fr.Observation]) -> None:
    """Fewer than four recordings, or a scatter with no steady slope: the last one's offset,
    not moving."""
    f = fr.estimate(obs, 100.0)
    assert f.um_per_s == 0.0
    assert f.offset_um == obs[-1].offset_um
    assert f.basis == f"offset of the last of {len(obs)} recordings"


def test_nothing_seen_is_the_models_own_zero() -> None:
    assert fr.estimate([], 5.0) == fr.Frame()


def test_an_observation_is_the_second_half_of_a_recording() -> None:
    """The first half (a start the model may have got wrong) is left out, and missing samples."""
    t = np.arange(10.0)
    readings = np.where(t < 5, 3.0, 1.0)
    readings[7] = np.nan
    ob = fr.observe(t, readings, np.zeros(10))
    assert ob == fr.Observation(float(np.mean([5.0, 6.0, 8.0, 9.0])), 1.0)
    assert fr.observe(t, np.full(10, np.nan), np.zeros(10)) is None


def test_a_reading_at_the_held_output_sets_the_level_not_the_slope() -> None:
    """Six sweeps over a minute at a steady offset (a stage that creeps but does not drift), then
    a reading 200 s on, 0.18 um off (what the model misses at rest): the frame anchored on the
    reading is at its offset and does not move, where the straight line through all seven would
    have taken the single far point for a drift and followed it."""
    sweeps = line([0.0, 10.0, 20.0, 30.0, 40.0, 50.0], 0.0, 0.0, 0.004)
    read = fr.Observation(250.0, -0.18)
    f = fr.anchored(sweeps, read, 250.5)
    assert f.offset_um == -0.18 and f.um_per_s == 0.0
    assert f.basis == "read at the held output 0.5 s before"
    assert fr.estimate([*sweeps, read], 250.5).um_per_s < -5e-4  # the line's false drift


def test_a_reading_moves_on_at_a_drift_the_observations_before_it_show() -> None:
    """A steady drift of 2 nm/s over six recordings: the reading sets the level, the drift
    carries it to the run's start."""
    obs = line([0.0, 10.0, 20.0, 30.0, 40.0, 50.0], 0.1, 0.002, 0.0005)
    f = fr.anchored(obs, fr.Observation(300.0, 0.75), 302.0)
    assert f.um_per_s == pytest.approx(0.002, rel=0.05)
    assert f.offset_um == pytest.approx(0.75 + 2 * f.um_per_s)
    assert f.basis.startswith("read at the held output 2.0 s before, drift +") \
        and f.basis.endswith(" nm/s over 6 recordings")


def test_a_long_reading_tells_its_own_drift_rate_where_the_line_lags() -> None:
    """Recordings over two minutes of a drift that has risen from 5 to 15 nm/s (the line through
    them: about 9 nm/s), then a 1 s reading at the held output, 20 nm of noise at 10 kHz: the
    reading's own line gives the rate now (within 1 nm/s) and its value at its end, and the
    frame carries them to the run's start; a stage that does not drift reads no rate (0, said),
    not the recordings' line."""
    rng = np.random.default_rng(7)
    times = np.linspace(0.0, 120.0, 8)
    drift = 0.005 * times + 0.5 * (0.010 / 120.0) * times**2  # um: 5 -> 15 nm/s
    obs = [fr.Observation(float(t), float(y)) for t, y in zip(times, drift, strict=True)]
    assert fr.estimate(obs, 121.0).um_per_s < 0.0105  # the line lags the rate now (15 nm/s)
    t = 125.0 + np.arange(10_000) * 1e-4
    now = 0.005 * t + 0.5 * (0.010 / 120.0) * t**2
    read = fr.read_line(t, now + 0.02 * rng.standard_normal(t.size), np.zeros(t.size))
    assert read is not None and read.at_s == pytest.approx(t[-1])
    rate_now = 0.005 + (0.010 / 120.0) * t[-1]
    assert read.um_per_s == pytest.approx(rate_now, abs=1e-3)
    assert read.offset_um == pytest.approx(now[-1], abs=2e-3)
    f = fr.anchored(obs, read, t[-1] + 2.0)
    assert f.um_per_s == read.um_per_s and f.offset_um == pytest.approx(now[-1] + 2 * rate_now,
                                                                        abs=4e-3)
    assert f.basis.endswith("nm/s over the reading")
    still = fr.read_line(t, 0.3 + 0.02 * rng.standard_normal(t.size), np.zeros(t.size))
    assert still is not None and still.um_per_s == 0.0
    held = fr.anchored(obs, still, t[-1] + 2.0)
    assert held.um_per_s == 0.0 and held.offset_um == pytest.approx(0.3, abs=2e-3)
    assert held.basis.endswith(", no drift told over the reading")
